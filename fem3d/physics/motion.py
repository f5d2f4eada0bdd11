"""Keyframed rigid motion of pinned vertices (moving pins, moving obstacles).

A :class:`Keyframes` is a rigid motion over time: at each keyframe time a translation and a
rotation (XYZ Euler angles in degrees, about a pivot) of the rest positions. Between
keyframes the motion is interpolated, ``"linear"`` (piecewise linear in time) or
``"smooth"`` (the same path with a smoothstep ``3 s^2 - 2 s^3`` time warp in each interval,
so the velocity is zero at every keyframe and the start and end have no jerk from rest).
Translations are interpolated linearly, rotations by spherical linear interpolation (slerp,
``scipy.spatial.transform.Slerp``) between consecutive keyframes: constant angular velocity
along the shortest arc of each interval. Before the first keyframe the motion holds the first
keyframe's pose, after the last one the last's.

A point ``x`` (rest position) moves to ``R(t) (x - pivot) + pivot + translation(t)``.
The integrators take the result as ``fixed_positions`` (the pinned vertices' positions at
the end of a step).

Example
-------
>>> kf = Keyframes([0.0, 1.0], [[0, 0, 0], [0, 0, 0]], [[0, 0, 0], [0, 0, 90]],
...                pivot=[0, 0, 0])
>>> kf.apply(np.array([[1.0, 0.0, 0.0]]), 1.0).round(12)
array([[0., 1., 0.]])
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from fem3d.errors import ParameterError

__all__ = ["Keyframes", "INTERPOLATIONS"]

#: Interpolation names accepted by :class:`Keyframes`.
INTERPOLATIONS = ("linear", "smooth")


def _array(value, shape_tail: tuple[int, ...], name: str, count: int | None = None) -> np.ndarray:
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name} must be numbers ({exc})") from None
    if a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail or \
            (count is not None and a.shape[0] != count):
        want = ("k" if count is None else str(count),) + tuple(str(s) for s in shape_tail)
        raise ParameterError(f"{name} must have shape ({', '.join(want)}), got {a.shape}")
    if not np.isfinite(a).all():
        raise ParameterError(f"{name} must be finite")
    return a


class Keyframes:
    """A keyframed rigid motion.

    Parameters
    ----------
    times : (k,) float
        Keyframe times, strictly increasing (``k >= 1``).
    translations : (k, 3) float
        Translation at each keyframe.
    rotations_deg : (k, 3) float
        Rotation at each keyframe: extrinsic XYZ Euler angles in degrees (about the pivot).
    pivot : (3,) float
        Centre of the rotations.
    interpolation : {"linear", "smooth"}, optional
        See the module docstring.

    Raises
    ------
    ParameterError
        Shapes, non-finite values, times not strictly increasing, an unknown interpolation.
        The message names the field (``times``, ``translations``, ...) and, for times, the
        keyframe index: the scene loader prefixes it with the key path.
    """

    def __init__(self, times, translations, rotations_deg, pivot, interpolation: str = "linear"):
        t = _array(times, (), "times")
        if t.size == 0:
            raise ParameterError("times: at least one keyframe is needed")
        steps = np.diff(t)
        if (steps <= 0).any():
            i = int(np.flatnonzero(steps <= 0)[0]) + 1
            raise ParameterError(
                f"times must be strictly increasing: keyframe {i} has t = {t[i]:g} after "
                f"t = {t[i - 1]:g}")
        self.times = t
        self.translations = _array(translations, (3,), "translations", t.size)
        self.rotations_deg = _array(rotations_deg, (3,), "rotations_deg", t.size)
        if np.shape(pivot) != (3,):
            raise ParameterError(f"pivot must be 3 numbers, got shape {np.shape(pivot)}")
        self.pivot = _array([pivot], (3,), "pivot", 1)[0]
        if interpolation not in INTERPOLATIONS:
            raise ParameterError(f"interpolation must be one of {', '.join(INTERPOLATIONS)}, "
                                 f"got {interpolation!r}")
        self.interpolation = interpolation
        self._rotations = Rotation.from_euler("xyz", self.rotations_deg, degrees=True)
        self._slerp = Slerp(t, self._rotations) if t.size > 1 else None
        for a in (self.times, self.translations, self.rotations_deg, self.pivot):
            a.setflags(write=False)

    def _warped_time(self, t: float) -> float:
        """``t`` clamped to the keyframes' span and, for ``"smooth"``, time-warped."""
        times = self.times
        t = float(np.clip(t, times[0], times[-1]))
        if self.interpolation == "linear" or times.size == 1:
            return t
        i = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, times.size - 2))
        s = (t - times[i]) / (times[i + 1] - times[i])
        return float(times[i] + (times[i + 1] - times[i]) * s * s * (3.0 - 2.0 * s))

    def pose(self, t: float) -> tuple[Rotation, np.ndarray]:
        """Rotation and translation at time ``t``."""
        if not np.isfinite(t):
            raise ParameterError(f"time must be finite, got {t}")
        tw = self._warped_time(t)
        k = np.flatnonzero(self.times == tw)
        if k.size:  # exactly on a keyframe: its pose, not an interpolation of it
            return self._rotations[int(k[0])], self.translations[int(k[0])].copy()
        rot = self._slerp(tw)
        translation = np.array([np.interp(tw, self.times, self.translations[:, j])
                                for j in range(3)])
        return rot, translation

    def apply(self, points_rest, t: float) -> np.ndarray:
        """Positions of rest points at time ``t``.

        Parameters
        ----------
        points_rest : (k, 3) float64
        t : float

        Returns
        -------
        (k, 3) float64
            ``R(t) (x - pivot) + pivot + translation(t)``.
        """
        x = np.asarray(points_rest, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != 3:
            raise ParameterError(f"points must have shape (k, 3), got {x.shape}")
        rot, translation = self.pose(t)
        return rot.apply(x - self.pivot) + self.pivot + translation

    def __repr__(self) -> str:
        return (f"Keyframes({self.times.size} keyframes, t in [{self.times[0]:g}, "
                f"{self.times[-1]:g}], {self.interpolation})")
