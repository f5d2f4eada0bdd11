"""Write the meshes of the load benchmarks (docs/loads.md) into data/scenes/meshes/.

    python scripts/make_load_meshes.py

* ``cook_<n>.mesh`` (n = 2, 4, 8, 16, 32, 64): Cook's membrane, the trapezoid (0, 0), (48, 44),
  (48, 60), (0, 44) extruded to thickness 1, ``n x n x 1`` cells of 6 tets (a bilinear map of
  the unit square).
* ``lame_eighth_<n>.mesh`` (n = 8, 16, 24) and ``lame_sphere_<n>.mesh`` (n = 8): the thick-walled
  sphere ``1 <= r <= 2``, one octant (``x, y, z >= 0``) and the whole sphere (the octant
  mirrored in the three coordinate planes, shared vertices merged). The octant is the cube
  shell ``[0, 1]^3 \\ [0, 1/2)^3`` (``n^3 - (n/2)^3`` cells of 6 tets) mapped radially:
  ``x = r(t) d / |d|`` with ``t = (|p|_inf - 1/2) / (1/2)``, ``r = 1 + t`` and the
  equal-angle direction ``d_i = tan(pi/4 p_i / |p|_inf)`` (the cube-sphere map: less
  distortion along the cube's edges).
* ``lame_eighth_<n>_p2.vtu`` (n = 4, 8) and ``lame_sphere_4_p2.vtu``: the same shell in
  quadratic (``tetra10``) tets, isoparametric: the cube shell's P2 nodes (corners and edge
  midpoints) mapped by the same map, so the edge nodes on ``r = 1`` and ``r = 2`` lie on the
  spheres and the elements there are curved (``element = "p2"``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fem3d.mesh.element import ELEMENTS
from fem3d.mesh.formats import write_tet_mesh
from fem3d.mesh.quadratic import lift_to_p2, write_element_mesh
from fem3d.mesh.tetmesh import TetMesh, box_tet_mesh

OUT = Path(__file__).resolve().parent.parent / "data" / "scenes" / "meshes"


def cook(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Cook's membrane with ``n x n x 1`` cells."""
    P, T = box_tet_mesh((n, n, 1))
    xi, eta, z = P.T
    x = 48.0 * xi
    y = (1.0 - eta) * 44.0 * xi + eta * (44.0 + 16.0 * xi)
    return np.column_stack([x, y, z]), T


def lame_eighth(n: int, a: float = 1.0, b: float = 2.0,
                quadratic: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The octant of the shell ``a <= r <= b`` (see the module docstring); ``quadratic``:
    10-node tets, every node mapped (isoparametric)."""
    P, T = box_tet_mesh((n, n, n))
    inner = n // 2
    corner = (np.round(P[T] * n).astype(np.int64)).max(axis=1)  # (m, 3): the cell's top
    keep = corner.max(axis=1) > inner  # cells outside [0, 1/2)^3
    T = T[keep]
    used = np.unique(T)
    index = np.full(P.shape[0], -1)
    index[used] = np.arange(used.size)
    P, T = P[used], index[T]
    if quadratic:
        P, T = lift_to_p2(P, T)
    m = np.abs(P).max(axis=1)
    t = (m - 0.5) / 0.5
    D = np.tan(np.pi / 4 * P / m[:, None])  # equal angles along each cube face
    X = (a + (b - a) * t)[:, None] * D / np.linalg.norm(D, axis=1)[:, None]
    return X, T


#: A reflected tet's nodes, reordered to keep it positively oriented (corners 0 and 1
#: swapped; a 10-node tet's edge nodes follow: 01, 02, 12, 13, 03, 23).
FLIP = {4: [1, 0, 2, 3], 10: [1, 0, 2, 3, 4, 6, 5, 8, 7, 9]}


def mirror(X: np.ndarray, T: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """``(X, T)`` and its mirror image in the plane ``x_axis = 0`` as one mesh."""
    on = np.flatnonzero(np.abs(X[:, axis]) < 1e-12)
    off = np.setdiff1d(np.arange(X.shape[0]), on)
    Xm = X[off].copy()
    Xm[:, axis] *= -1.0
    index = np.arange(X.shape[0])
    index[off] = X.shape[0] + np.arange(off.size)
    Tm = index[T][:, FLIP[T.shape[1]]]  # a reflection flips the orientation
    return np.vstack([X, Xm]), np.vstack([T, Tm])


def main() -> None:
    for n in (2, 4, 8, 16, 32, 64):
        write_tet_mesh(OUT / f"cook_{n}.mesh", TetMesh(*cook(n)))
    for n in (8, 16, 24):
        write_tet_mesh(OUT / f"lame_eighth_{n}.mesh", TetMesh(*lame_eighth(n)))
    X, T = lame_eighth(8)
    for axis in range(3):
        X, T = mirror(X, T, axis)
    write_tet_mesh(OUT / "lame_sphere_8.mesh", TetMesh(X, T))
    p2 = ELEMENTS["p2"]
    for n in (4, 8):
        write_element_mesh(OUT / f"lame_eighth_{n}_p2.vtu", *lame_eighth(n, quadratic=True), p2)
    X, T = lame_eighth(4, quadratic=True)
    for axis in range(3):
        X, T = mirror(X, T, axis)
    write_element_mesh(OUT / "lame_sphere_4_p2.vtu", X, T, p2)


if __name__ == "__main__":
    main()
