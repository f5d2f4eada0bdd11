"""Build the scene gallery: the box meshes its scene files use, and a preview of each scene.

Run:  python examples/make_gallery.py [--only NAME ...] [--meshes-only]

* ``data/scenes/meshes/*.mesh``: Kuhn-subdivided boxes (6 positive tets per cell) written once
  (:func:`box_mesh`), e.g. the cantilever's 1 x 0.1 x 0.1 beam of 40 x 4 x 4 cells.
* ``docs/gallery/<scene>.gif``: each gallery scene run headless through
  :func:`fem3d.app.run.run_scene` (the code path of ``fem3d run``) with its preview rendered by
  :func:`fem3d.io.preview.render_preview`; the printed line per scene is its
  :class:`~fem3d.app.run.RunSummary`.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # this checkout's fem3d, not an installed one
MESHES = ROOT / "data" / "scenes" / "meshes"
GALLERY = ROOT / "docs" / "gallery"

#: Gallery scenes (data/scenes/<name>.toml), in the order docs/scenes.md lists them.
SCENES = ["cantilever", "twist", "bunny_surface", "armadillo_surface", "jelly_neo_hookean",
          "jelly_stvk", "jelly_pair", "swing", "two_pulls"]

#: name -> (cells (nx, ny, nz), size (x, y, z))
BOXES = {
    "beam_40x4x4": ((40, 4, 4), (1.0, 0.1, 0.1)),
    "beam_20x2x2": ((20, 2, 2), (1.0, 0.1, 0.1)),  # beam_p1: as many nodes as beam_p2's P2
    "beam_10x1x1": ((10, 1, 1), (1.0, 0.1, 0.1)),
    "bar_16x4x4": ((16, 4, 4), (1.0, 0.25, 0.25)),
    "cube_6": ((6, 6, 6), (0.2, 0.2, 0.2)),
    "hanging_bar_3x12x3": ((3, 12, 3), (0.1, 0.6, 0.1)),
}


def box_mesh(cells, size) -> tuple[np.ndarray, np.ndarray]:
    """Kuhn-subdivided box ``[0, size]``: ``(nx+1)(ny+1)(nz+1)`` vertices, ``6 nx ny nz``
    positively oriented tets.

    Returns
    -------
    X : (n, 3) float64
    T : (m, 4) int64
    """
    from fem3d.mesh.tetmesh import box_tet_mesh

    return box_tet_mesh(cells, size)


def write_meshes() -> None:
    """The box meshes of the gallery (skipped when present)."""
    from fem3d.mesh.formats import write_tet_mesh
    from fem3d.mesh.tetmesh import TetMesh

    MESHES.mkdir(parents=True, exist_ok=True)
    for name, (cells, size) in BOXES.items():
        p = MESHES / f"{name}.mesh"
        if not p.is_file():
            X, T = box_mesh(cells, size)
            write_tet_mesh(p, TetMesh(X, T))
            print(f"wrote {p.relative_to(ROOT)}: {len(X)} vertices, {len(T)} tets")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", default=None, help="scene names")
    parser.add_argument("--meshes-only", action="store_true")
    args = parser.parse_args(argv)
    write_meshes()
    if args.meshes_only:
        return 0
    from fem3d.app.run import run_scene
    from fem3d.scene import load_scene

    GALLERY.mkdir(parents=True, exist_ok=True)
    status = 0
    for name in args.only or SCENES:
        t0 = time.perf_counter()
        scene = load_scene(name)
        with tempfile.TemporaryDirectory() as tmp:
            summary = run_scene(scene, Path(tmp) / name, preview=True)
            if (Path(tmp) / name / "preview.gif").is_file():
                shutil.copy(Path(tmp) / name / "preview.gif", GALLERY / f"{name}.gif")
        status |= summary.status != "ok"
        print(f"{name}: {summary.status} {summary.message} steps {summary.steps}, "
              f"max displacement {summary.max_displacement:.4g}, "
              f"{time.perf_counter() - t0:.1f} s", flush=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
