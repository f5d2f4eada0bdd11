"""Write the box tet meshes of the contact gallery scenes (byte for byte reproducible).

    python scripts/make_contact_meshes.py

* ``data/contact_block.mesh``: a 10 x 5 x 10 cm block, 4 x 2 x 4 cells of 6 Kuhn tets
  (75 vertices, 192 tets): the incline and stack scenes.
* ``data/contact_bar.mesh``: a 50 x 4 x 4 cm bar along x, 25 x 2 x 2 cells (234 vertices,
  600 tets): the twisted-bar self-contact scene.
* ``data/scenes/meshes/contact_strip_24x1x3.mesh``: a 30 x 1 x 6 cm strip along x, 24 x 1 x 3
  cells (200 vertices, 432 tets): the folded-strip self-contact scene (contact_fold).
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # this checkout's fem3d, not an installed one

from fem3d.mesh.formats import write_tet_mesh  # noqa: E402
from fem3d.mesh.tetmesh import TetMesh, box_tet_mesh  # noqa: E402


def box(n, size, origin=(0.0, 0.0, 0.0)):
    """Kuhn-subdivided box: 6 positively oriented tets per cell."""
    return box_tet_mesh(n, size, origin)


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
    ):
        X, T = box(n, size, origin)
        write_tet_mesh(ROOT / "data" / "scenes" / "meshes" / name, TetMesh(X=X, T=T))
        print(f"data/scenes/meshes/{name}: {len(X)} vertices, {len(T)} tets")


if __name__ == "__main__":
    main()
