"""Keyframed rigid motion (moving pins): interpolation, exact keyframes, validation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fem3d.errors import ParameterError
from fem3d.physics.motion import Keyframes


def points() -> np.ndarray:
    return np.random.default_rng(3).normal(size=(7, 3))


def test_keyframes_are_hit_exactly_and_held_outside_the_span():
    pivot = np.array([0.5, -1.0, 2.0])
    kf = Keyframes([0.0, 1.0, 2.5], [[0, 0, 0], [1, 2, 3], [-1, 0, 0.5]],
                   [[0, 0, 0], [10, 20, 30], [0, 90, 0]], pivot)
    x = points()
    np.testing.assert_array_equal(kf.apply(x, 0.0), x - pivot + pivot)
    for t, k in ((1.0, 1), (2.5, 2), (7.0, 2)):
        R = Rotation.from_euler("xyz", kf.rotations_deg[k], degrees=True)
        np.testing.assert_allclose(kf.apply(x, t), R.apply(x - pivot) + pivot
                                   + kf.translations[k], rtol=0, atol=1e-14)
    np.testing.assert_array_equal(kf.apply(x, -3.0), kf.apply(x, 0.0))


def test_linear_interpolation_is_rigid_with_constant_rates():
    kf = Keyframes([0.0, 2.0], [[0, 0, 0], [2, 0, 0]], [[0, 0, 0], [0, 0, 90]], [0, 0, 0])
    x = np.array([[1.0, 0.0, 0.0]])
    np.testing.assert_allclose(kf.apply(x, 1.0), [[1 + np.cos(np.pi / 4), np.sin(np.pi / 4),
                                                   0]], atol=1e-14)
    # distances are preserved at any time (a rigid motion)
    p = points()
    for t in (0.3, 1.1, 1.9):
        y = kf.apply(p, t)
        np.testing.assert_allclose(np.linalg.norm(y[1:] - y[0], axis=1),
                                   np.linalg.norm(p[1:] - p[0], axis=1), rtol=1e-12)


def test_smooth_interpolation_starts_and_ends_at_rest_on_the_same_path():
    lin = Keyframes([0.0, 1.0], [[0, 0, 0], [1, 0, 0]], [[0, 0, 0], [0, 0, 0]], [0, 0, 0])
    smooth = Keyframes([0.0, 1.0], [[0, 0, 0], [1, 0, 0]], [[0, 0, 0], [0, 0, 0]], [0, 0, 0],
                       interpolation="smooth")
    x = np.zeros((1, 3))
    h = 1e-6
    assert abs(smooth.apply(x, h)[0, 0]) < 1e-10  # zero start velocity (3 h^2)
    assert abs(smooth.apply(x, 1 - h)[0, 0] - 1) < 1e-10
    assert smooth.apply(x, 0.5)[0, 0] == pytest.approx(0.5)  # symmetric warp
    assert smooth.apply(x, 0.25)[0, 0] == pytest.approx(3 * 0.25**2 - 2 * 0.25**3)
    assert lin.apply(x, 0.25)[0, 0] == pytest.approx(0.25)


@pytest.mark.parametrize(("args", "message"), [
    (([0.0, 1.0, 1.0], [[0, 0, 0]] * 3, [[0, 0, 0]] * 3, [0, 0, 0]), "strictly increasing"),
    (([1.0, 0.0], [[0, 0, 0]] * 2, [[0, 0, 0]] * 2, [0, 0, 0]), "keyframe 1"),
    (([], [], [], [0, 0, 0]), "times"),
    (([0.0, 1.0], [[0, 0, 0]], [[0, 0, 0]] * 2, [0, 0, 0]), "translations"),
    (([0.0, 1.0], [[0, 0, 0]] * 2, [[0, 0]] * 2, [0, 0, 0]), "rotations_deg"),
    (([0.0, 1.0], [[0, 0, 0]] * 2, [[0, 0, 0]] * 2, [0, 0]), "pivot"),
    (([0.0, np.nan], [[0, 0, 0]] * 2, [[0, 0, 0]] * 2, [0, 0, 0]), "finite"),
])
def test_bad_keyframes_are_parameter_errors_naming_the_field(args, message):
    with pytest.raises(ParameterError, match=message):
        Keyframes(*args)


def test_unknown_interpolation_and_bad_points():
    with pytest.raises(ParameterError, match="interpolation"):
        Keyframes([0.0], [[0, 0, 0]], [[0, 0, 0]], [0, 0, 0], interpolation="cubic")
    kf = Keyframes([0.0], [[1, 0, 0]], [[0, 0, 0]], [0, 0, 0])
    np.testing.assert_array_equal(kf.apply(np.zeros((2, 3)), 5.0), [[1, 0, 0], [1, 0, 0]])
    with pytest.raises(ParameterError, match="shape"):
        kf.apply(np.zeros(3), 0.0)
