"""Obstacles as triangle meshes for display and output: the preview GIF, the VTU/PVD and USD
frames.

- :class:`ObstacleMesh` - one obstacle's triangles, its static or moving vertices, and the
  plane it stands for (planes are drawn as a finite square sized to the scene).
- :func:`plane_square` - a square piece of a plane around a point, as a grid of quads.

This module knows no physics: the run loop makes the :class:`ObstacleMesh` list from the
contact model (``fem3d.simulation.Simulation.obstacle_meshes``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["ObstacleMesh", "plane_square", "plane_axes"]


def plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit ``(n, a, b)``: the normal and two in-plane axes, ``a x b = n``."""
    n = np.asarray(normal, dtype=np.float64).reshape(3)
    n = n / np.linalg.norm(n)
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return n, a, np.cross(n, a)


def plane_square(point: np.ndarray, normal: np.ndarray, center: np.ndarray, half: float,
                 cells: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A square piece of a plane, ``2 half`` wide, centred on ``center``'s projection onto
    the plane, as ``cells x cells`` quads (two triangles each, facing ``normal``).

    Parameters
    ----------
    point, normal : (3,) float
        The plane.
    center : (3,) float
    half : float
        Half the side length.
    cells : int
        Quads along a side (a grid: every other quad is a tile of a checkerboard).

    Returns
    -------
    vertices : ((cells + 1)^2, 3) float64
    faces : (2 cells^2, 3) int64
        Quad ``k`` (row-major, ``k = i cells + j``) is faces ``2k`` and ``2k + 1``.
    """
    n, a, b = plane_axes(normal)
    c = np.asarray(center, dtype=np.float64).reshape(3)
    c = c - ((c - np.asarray(point, dtype=np.float64).reshape(3)) @ n) * n
    cells = max(1, int(cells))
    s = np.linspace(-half, half, cells + 1)
    su, sv = np.meshgrid(s, s, indexing="ij")
    V = c + su.reshape(-1, 1) * a + sv.reshape(-1, 1) * b
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    v00 = (i * (cells + 1) + j).reshape(-1)
    v10, v01 = v00 + cells + 1, v00 + 1
    v11 = v10 + 1
    F = np.stack([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)], 1)
    return V, F.reshape(-1, 3).astype(np.int64)


@dataclass(frozen=True, eq=False)
class ObstacleMesh:
    """One obstacle as a triangle mesh.

    Attributes
    ----------
    name : str
        For file and prim names (``obstacles[0] (plane)``).
    vertices : (k, 3) float64
        Positions of a static obstacle, or the rest positions of a moving one.
    faces : (f, 3) int64
    motion : callable ``t -> (k, 3)``, optional
        Positions at time ``t`` (a keyframed mesh obstacle); None: static.
    plane : ((3,), (3,)) float64, optional
        ``(point, unit normal)`` when the obstacle is a plane (``vertices`` is then a square
        piece of it; the preview draws its own, sized to the view).
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    motion: Callable[[float], np.ndarray] | None = None
    plane: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def moving(self) -> bool:
        """Whether the obstacle moves (its positions depend on time)."""
        return self.motion is not None

    def positions(self, t: float) -> np.ndarray:
        """Vertex positions at time ``t``, ``(k, 3)`` float64."""
        if self.motion is None:
            return np.asarray(self.vertices, dtype=np.float64)
        return np.asarray(self.motion(float(t)), dtype=np.float64)
