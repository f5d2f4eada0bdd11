"""Write the box tet meshes of the contact gallery scenes (byte for byte reproducible).

    python scripts/make_contact_meshes.py

* ``data/contact_block.mesh``: a 10 x 5 x 10 cm block, 4 x 2 x 4 cells of 6 Kuhn tets
  (75 vertices, 192 tets): the incline and stack scenes.
* ``data/contact_bar.mesh``: a 50 x 4 x 4 cm bar along x, 25 x 2 x 2 cells (234 vertices,
  600 tets): the twisted-bar self-contact scene.
* ``data/scenes/meshes/contact_strip_24x1x3.mesh``: a 30 x 1 x 6 cm strip along x, 24 x 1 x 3
  cells (200 vertices, 432 tets): the folded-strip self-contact scene (contact_fold).
* ``data/scenes/meshes/contact_pile_block.mesh``: a 12 x 8 x 12 cm block, 6 x 4 x 6 cells (245
  vertices, 864 tets), ``data/scenes/meshes/contact_pile_board.mesh``: a 36 x 2.5 x 36 cm
  board, 12 x 1 x 12 cells (338 vertices, 864 tets), and
  ``data/scenes/meshes/contact_pile_box.obj``: the open box (floor 40 x 40 cm at y = 0, four
  walls 45 cm high, 8 x 8 and 8 x 9 grids of 5 cm squares, two triangles each; 369 vertices,
  704 triangles, the corners shared): the pile (contact_pile).
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # this checkout's fem3d, not an installed one

import numpy as np  # noqa: E402

from fem3d.mesh.formats import write_surface_mesh, write_tet_mesh  # noqa: E402
from fem3d.mesh.tetmesh import TetMesh, box_tet_mesh  # noqa: E402


def box(n, size, origin=(0.0, 0.0, 0.0)):
    """Kuhn-subdivided box: 6 positively oriented tets per cell."""
    return box_tet_mesh(n, size, origin)


def grid(origin, u, v, nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """A parallelogram ``origin + s u + t v`` (s, t in [0, 1]) as ``nu x nv`` quads, two
    triangles each: ``(V, F)``."""
    i, j = np.meshgrid(np.arange(nu + 1), np.arange(nv + 1), indexing="ij")
    V = (np.asarray(origin, float) + i.reshape(-1, 1) * np.asarray(u, float) / nu
         + j.reshape(-1, 1) * np.asarray(v, float) / nv)
    k = (i[:-1, :-1] * (nv + 1) + j[:-1, :-1]).reshape(-1)
    F = np.concatenate([np.stack([k, k + nv + 1, k + nv + 2], 1),
                        np.stack([k, k + nv + 2, k + 1], 1)])
    return V, F


def open_box(half: float, height: float, n: int, nh: int) -> tuple[np.ndarray, np.ndarray]:
    """The surface of an open box: the floor ``[-half, half]^2`` at y = 0 (``n x n`` quads) and
    four walls up to ``height`` (``n x nh`` quads), vertices on shared edges merged."""
    a, h = half, height
    parts = [grid([-a, 0, -a], [2 * a, 0, 0], [0, 0, 2 * a], n, n)]
    for o, u in (([-a, 0, -a], [2 * a, 0, 0]), ([a, 0, -a], [0, 0, 2 * a]),
                 ([a, 0, a], [-2 * a, 0, 0]), ([-a, 0, a], [0, 0, -2 * a])):
        parts.append(grid(o, u, [0, h, 0], n, nh))
    V = np.concatenate([p[0] for p in parts])
    offsets = np.cumsum([0] + [len(p[0]) for p in parts])
    F = np.concatenate([p[1] + o for p, o in zip(parts, offsets, strict=False)])
    key = np.round(V / 1e-9).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    rank = np.argsort(np.argsort(first))  # keep the vertices in order of first appearance
    return V[np.sort(first)], rank[inv.reshape(-1)][F]


def main() -> None:
    for name, n, size, origin in (
        ("contact_block.mesh", (4, 2, 4), (0.1, 0.05, 0.1), (-0.05, 0.0, -0.05)),
        ("contact_bar.mesh", (25, 2, 2), (0.5, 0.04, 0.04), (-0.25, -0.02, -0.02)),
    ):
        X, T = box(n, size, origin)
        write_tet_mesh(ROOT / "data" / name, TetMesh(X=X, T=T))
        print(f"data/{name}: {len(X)} vertices, {len(T)} tets")
    for name, n, size, origin in (
        ("contact_strip_24x1x3.mesh", (24, 1, 3), (0.3, 0.01, 0.06), (-0.15, 0.0, -0.03)),
        ("contact_pile_block.mesh", (6, 4, 6), (0.12, 0.08, 0.12), (-0.06, 0.0, -0.06)),
        ("contact_pile_board.mesh", (12, 1, 12), (0.36, 0.025, 0.36), (-0.18, 0.0, -0.18)),
    ):
        X, T = box(n, size, origin)
        write_tet_mesh(ROOT / "data" / "scenes" / "meshes" / name, TetMesh(X=X, T=T))
        print(f"data/scenes/meshes/{name}: {len(X)} vertices, {len(T)} tets")
    V, F = open_box(0.2, 0.45, 8, 9)
    write_surface_mesh(ROOT / "data" / "scenes" / "meshes" / "contact_pile_box.obj", V, F)
    print(f"data/scenes/meshes/contact_pile_box.obj: {len(V)} vertices, {len(F)} triangles")


if __name__ == "__main__":
    main()
