"""The obstacles of a contact scene: static planes and triangle meshes (static or kinematic).

Their vertices are not degrees of freedom; :mod:`.geometry` puts a mesh obstacle's vertices
after the bodies' surface in the collision mesh, :mod:`.planes` evaluates the planes' pairs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fem3d.errors import ParameterError

__all__ = ["PlaneObstacle", "MeshObstacle"]


@dataclass(frozen=True, eq=False)
class PlaneObstacle:
    """A static plane; the half-space ``(x - point) . normal < 0`` is solid.

    Attributes
    ----------
    point : (3,) float64
    normal : (3,) float64
        Unit normal (normalised on construction), pointing to the free side.
    name : str
    """

    point: np.ndarray
    normal: np.ndarray
    name: str = "plane"

    def __post_init__(self) -> None:
        p = np.asarray(self.point, dtype=np.float64).reshape(-1)
        n = np.asarray(self.normal, dtype=np.float64).reshape(-1)
        if p.shape != (3,) or n.shape != (3,) or not (np.isfinite(p).all() and
                                                       np.isfinite(n).all()):
            raise ParameterError(f"obstacle {self.name!r}: point and normal must be 3 finite "
                                 "numbers")
        norm = float(np.linalg.norm(n))
        if norm == 0.0:
            raise ParameterError(f"obstacle {self.name!r}: the normal is zero")
        object.__setattr__(self, "point", p)
        object.__setattr__(self, "normal", n / norm)

    def signed_distance(self, x: np.ndarray) -> np.ndarray:
        """``(x - point) . normal`` of points ``x (k, 3)``."""
        return (np.asarray(x).reshape(-1, 3) - self.point) @ self.normal


@dataclass(frozen=True, eq=False)
class MeshObstacle:
    """A triangle-mesh obstacle, static or kinematic (a prescribed motion).

    Attributes
    ----------
    vertices : (k, 3) float64
        Rest positions (the motion's reference).
    faces : (f, 3) int64
    motion : callable ``(rest (k, 3), t) -> (k, 3)``, optional
        Positions at time ``t`` (for example ``fem3d.physics.motion.Keyframes.apply``); None:
        static.
    name : str
    """

    vertices: np.ndarray
    faces: np.ndarray
    motion: Callable[[np.ndarray, float], np.ndarray] | None = None
    name: str = "obstacle"

    def __post_init__(self) -> None:
        V = np.ascontiguousarray(self.vertices, dtype=np.float64)
        F = np.ascontiguousarray(self.faces, dtype=np.int64)
        if V.ndim != 2 or V.shape[1] != 3 or not np.isfinite(V).all():
            raise ParameterError(f"obstacle {self.name!r}: vertices must be finite (k, 3)")
        if F.ndim != 2 or F.shape[1] != 3 or F.size == 0:
            raise ParameterError(f"obstacle {self.name!r}: faces must be (f, 3), f >= 1")
        if F.min() < 0 or F.max() >= V.shape[0]:
            raise ParameterError(f"obstacle {self.name!r}: a face index is out of range "
                                 f"[0, {V.shape[0]})")
        object.__setattr__(self, "vertices", V)
        object.__setattr__(self, "faces", F)

    def positions(self, t: float) -> np.ndarray:
        """Vertex positions at time ``t``, ``(k, 3)``."""
        if self.motion is None:
            return self.vertices
        x = np.asarray(self.motion(self.vertices, t), dtype=np.float64)
        if x.shape != self.vertices.shape:
            raise ValueError(f"obstacle {self.name!r}: motion returned shape {x.shape}")
        return x
