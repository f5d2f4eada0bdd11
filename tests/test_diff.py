"""Adjoint gradients of backward-Euler trajectories against central finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from test_assembly import box_mesh

from fem3d.diff import PositionLoss, simulate, trajectory_gradient
from fem3d.diff.adjoint import scene_with
from fem3d.errors import ParameterError
from fem3d.scene.load import scene_from_arrays

STEPS = 10
VALUES = {
    "bodies[0].material.E": 1e5,
    "bodies[0].material.nu": 0.3,
    "bodies[0].material.density": 1000.0,
    "bodies[0].damping.rayleigh_mass": 0.5,
    "bodies[0].damping.rayleigh_stiffness": 0.002,
    "bodies[0].velocity": np.array([0.3, 0.0, -0.2]),
    "simulation.gravity": np.array([0.0, -9.81, 0.0]),
}


def box_scene(beta: float):
    X, T = box_mesh(2, 2, 2)
    values = {**VALUES, "bodies[0].damping.rayleigh_stiffness": beta}
    return scene_with(scene_from_arrays(X, T, {
        "simulation.dt": 0.01, "bodies[0].pins": [{"select": {"lowest_y": {"tol": 0.0}}}],
        "pulls": []}),  # the mesh scene's default pull: not differentiated (refused)
        values), values


def total_loss(scene, loss) -> float:
    qs = simulate(scene, STEPS)
    return sum(loss.frame(n, qs[n])[0] for n in range(1, STEPS + 1))


# beta = 0: every derivative is exact; beta > 0: the damping's dependence on q_n and on E, nu
# is differenced per element (see fem3d.diff.adjoint).
@pytest.mark.parametrize("beta", [0.0, 0.002])
def test_adjoint_gradient_matches_central_differences(beta: float) -> None:
    scene, values = box_scene(beta)
    rng = np.random.default_rng(0)
    qs = simulate(scene, STEPS)
    loss = PositionLoss({n: qs[n] + 0.01 * rng.normal(size=qs[n].shape)
                         for n in range(1, STEPS + 1)})
    keys = [k for k in VALUES if beta > 0 or "stiffness" not in k]
    value, grads = trajectory_gradient(scene, loss, keys, checkpoint_every=3)
    assert value == pytest.approx(total_loss(scene, loss), rel=1e-12)
    for key in keys:
        v = np.atleast_1d(np.asarray(values[key], dtype=np.float64))
        fd = np.empty(v.size)
        for c in range(v.size):
            # the step: 1e-5 of the value (vectors: of their largest entry, at least 1e-5)
            h = 1e-5 * max(abs(v).max(), 1.0 if v.size > 1 else 0.0)
            plus, minus = v.copy(), v.copy()
            plus[c] += h
            minus[c] -= h
            as_value = (lambda a: a) if v.size > 1 else (lambda a: a[0])
            fd[c] = (total_loss(scene_with(scene, {key: as_value(plus)}), loss)
                     - total_loss(scene_with(scene, {key: as_value(minus)}), loss)) / (2 * h)
        g = np.atleast_1d(grads[key])
        error = np.abs(g - fd).max() / np.abs(fd).max()
        assert error < 1e-5, f"{key}: adjoint {g}, differences {fd}, relative error {error:.2e}"


def test_checkpointing_does_not_change_the_gradient() -> None:
    scene, _ = box_scene(0.0)
    qs = simulate(scene, STEPS)
    loss = PositionLoss({STEPS: qs[STEPS][[5, 7]] + 0.01}, vertices=[5, 7])
    keys = ["bodies[0].material.E", "bodies[0].velocity"]
    _, every = trajectory_gradient(scene, loss, keys, checkpoint_every=1)
    _, once = trajectory_gradient(scene, loss, keys, checkpoint_every=100)
    for key in keys:
        np.testing.assert_allclose(every[key], once[key], rtol=1e-12)


def test_unknown_parameter_is_refused() -> None:
    scene, _ = box_scene(0.0)
    with pytest.raises(ParameterError, match="bodies\\[0\\].pins"):
        trajectory_gradient(scene, PositionLoss({1: np.zeros((27, 3))}), ["bodies[0].pins"])


def test_scripted_pulls_are_refused_not_ignored() -> None:
    """A run applies the scene's scripted pulls; a gradient without them would be of another
    trajectory, so the adjoint refuses them by name."""
    from fem3d.scene import apply_overrides

    scene, _ = box_scene(0.0)
    pulled = apply_overrides(scene, {"pulls": [{"select": {"vertices": [26]},
                                                "target": [1.5, 1.5, 1.5],
                                                "duration": 0.05}]})
    with pytest.raises(ParameterError, match="scripted pulls"):
        trajectory_gradient(pulled, PositionLoss({1: np.zeros((27, 3))}),
                            ["bodies[0].material.E"])
