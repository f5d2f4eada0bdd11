"""Write the box tet meshes of the contact gallery scenes (byte for byte reproducible).

    python scripts/make_contact_meshes.py

* ``data/contact_block.mesh``: a 10 x 5 x 10 cm block, 4 x 2 x 4 cells of 6 Kuhn tets
  (75 vertices, 192 tets): the incline and stack scenes.
* ``data/contact_bar.mesh``: a 50 x 4 x 4 cm bar along x, 25 x 2 x 2 cells (234 vertices,
  600 tets): the twisted-bar self-contact scene.
"""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # this checkout's fem3d, not an installed one

from fem3d.mesh import TetMesh, write_tet_mesh  # noqa: E402


def box(n, size, origin=(0.0, 0.0, 0.0)):
    """Kuhn-subdivided box: 6 positively oriented tets per cell."""
    g = np.stack(np.meshgrid(*(np.linspace(0, s, k + 1) for s, k in zip(size, n, strict=True)),
                             indexing="ij"), axis=-1).reshape(-1, 3) + np.asarray(origin)
    idx = np.arange(g.shape[0]).reshape(tuple(k + 1 for k in n))
    tets = []
    for cell in itertools.product(*(range(k) for k in n)):
        for perm in itertools.permutations(range(3)):
            c = np.array(cell)
            path = [c.copy()]
            for a in perm:
                c = c.copy()
                c[a] += 1
                path.append(c)
            tets.append([idx[tuple(p)] for p in path])
    T = np.array(tets, dtype=np.int64)
    e = g[T[:, 1:]] - g[T[:, :1]]
    neg = np.linalg.det(e) < 0
    T[neg, 2], T[neg, 3] = T[neg, 3].copy(), T[neg, 2].copy()
    return g, T


def main() -> None:
    for name, n, size, origin in (
        ("contact_block.mesh", (4, 2, 4), (0.1, 0.05, 0.1), (-0.05, 0.0, -0.05)),
        ("contact_bar.mesh", (25, 2, 2), (0.5, 0.04, 0.04), (-0.25, -0.02, -0.02)),
    ):
        X, T = box(n, size, origin)
        write_tet_mesh(ROOT / "data" / name, TetMesh(X=X, T=T))
        print(f"data/{name}: {len(X)} vertices, {len(T)} tets")


if __name__ == "__main__":
    main()
