"""P1 and P2 at equal DOFs: the gallery picture and the figures of docs/elements.md.

    python scripts/p2_gallery.py              # docs/gallery/beam_p1_p2.gif (and .png)
    python scripts/p2_gallery.py --figures    # the tip deflections: the two scenes' runs,
                                              # their static answers, the converged one

The two scenes ``data/scenes/beam_p1.toml`` (linear tets, 20 x 2 x 2 cells) and
``beam_p2.toml`` (quadratic tets, 10 x 1 x 1 cells, beside it at z = 0.5) have the same 189
nodes (567 DOFs). A scene holds one element, so each runs on its own, exactly as ``fem3d
run`` steps it (``Simulation.step``); the picture draws both display meshes in one frame with
one camera (:func:`fem3d.io.preview.render_preview`). The tip deflection is the mean
``-dy`` of the nodes at ``x = 1``; the converged answer is the Richardson extrapolation of the
static solves of the same beam on P2 meshes of 10 x 1 x 1, 20 x 2 x 2 and 40 x 4 x 4 cells
(``--converged``: the finer two), with the order observed on the three.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # this checkout's fem3d, not an installed one

#: The pair, P1 first (the left beam of the picture).
SCENES = ("beam_p1", "beam_p2")


def tip_deflection(sim) -> float:
    """Mean downward displacement of the nodes at the free end (``x`` largest)."""
    X, q = sim.model.X, np.asarray(sim.q)
    tip = np.flatnonzero(np.isclose(X[:, 0], X[:, 0].max()))
    return float(-(q[tip, 1] - X[tip, 1]).mean())


def run(name: str, frames_wanted: int = 50):
    """Step scene ``name`` to its end as ``fem3d run`` does: ``(sim, shots, times, seconds)``
    with about ``frames_wanted`` display meshes."""
    from fem3d.scene import load_scene
    from fem3d.simulation import Simulation

    scene = load_scene(name)
    sim = Simulation(scene, scripted=True)
    every = max(1, scene.n_steps // frames_wanted)
    shots, times = [sim.skin_positions()], [sim.t]
    t0 = time.perf_counter()
    for k in range(scene.n_steps):
        sim.step()
        if (k + 1) % every == 0 or k + 1 == scene.n_steps:
            shots.append(sim.skin_positions())
            times.append(sim.t)
    return sim, shots, times, time.perf_counter() - t0


def static_tip(name: str, overrides: dict | None = None) -> tuple[float, int]:
    """The static tip deflection of scene ``name`` (one ``static`` step: the equilibrium
    under gravity) and its DOFs."""
    from fem3d.scene import load_scene
    from fem3d.simulation import Simulation

    scene = load_scene(name, {"simulation.integrator": "static", "simulation.steps": 1,
                              **(overrides or {})})
    sim = Simulation(scene)
    sim.step()
    return tip_deflection(sim), sim.model.n_dofs


def converged_tip(cells: list[tuple[int, int, int]]) -> list[tuple[str, int, float]]:
    """Static tip deflections of beam_p2 on finer P2 meshes ``cells``: ``(cells, DOFs,
    tip)`` each."""
    from fem3d.mesh.formats import write_tet_mesh
    from fem3d.mesh.tetmesh import TetMesh, box_tet_mesh

    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for c in cells:
            mesh = Path(tmp) / f"beam_{'x'.join(map(str, c))}.mesh"
            write_tet_mesh(mesh, TetMesh(*box_tet_mesh(c, (1.0, 0.1, 0.1))))
            tip, dofs = static_tip("beam_p2", {"bodies[0].mesh": str(mesh)})
            out.append(("x".join(map(str, c)), dofs, tip))
    return out


def render(out_dir: Path, frames_wanted: int = 50) -> None:
    """docs/gallery/beam_p1_p2.gif (and the last frame as .png): both beams, one camera."""
    from fem3d.io.preview import render_preview

    runs = [run(name, frames_wanted) for name in SCENES]
    n = len(runs[0][1])
    assert all(len(r[1]) == n for r in runs), "the two scenes have different frame counts"
    offset = runs[0][1][0].shape[0]
    faces = np.concatenate([runs[0][0].display_faces, runs[1][0].display_faces + offset])
    shots = [np.concatenate([runs[0][1][k], runs[1][1][k]]) for k in range(n)]
    sim = runs[0][0]
    out_dir.mkdir(parents=True, exist_ok=True)
    gif = out_dir / "beam_p1_p2.gif"
    dt = runs[0][2][1] - runs[0][2][0]
    render_preview(shots, faces, gif, fps=min(25.0, 1.0 / dt), view_bounds="all",
                   max_frames=n, elev=25.0, azim=15.0, times=runs[0][2])
    render_preview(shots[-1:], faces, out_dir / "_last.gif", view_bounds="all", max_frames=1,
                   elev=25.0, azim=15.0, first_frame_png=out_dir / "beam_p1_p2.png")
    (out_dir / "_last.gif").unlink()
    for name, (s, _, _, secs) in zip(SCENES, runs, strict=True):
        print(f"{name}: {s.model.n_tets} tets, {s.model.n_vertices} nodes, {s.model.n_dofs} "
              f"DOFs, tip at t = {s.t:g}: {tip_deflection(s):.5f} m ({secs:.1f} s)")
    print(f"wrote {gif.relative_to(ROOT)} and beam_p1_p2.png ({sim.t:g} s simulated)")


def figures(converged: list[tuple[int, int, int]]) -> None:
    """Print the tip deflections: the runs' last states, the static answers, the finer P2
    meshes' and their Richardson extrapolation (the order observed on the last three)."""
    rows = []
    for name in SCENES:
        sim, _, _, secs = run(name)
        tip, dofs = static_tip(name)
        rows.append((name, dofs, tip_deflection(sim), secs, tip))
    conv = [("10x1x1", rows[1][1], rows[1][4]), *converged_tip(converged)]
    a, b, c = (t for _, _, t in conv[-3:])
    order = float(np.log2((b - a) / (c - b)))
    ref = c + (c - b) / (2.0 ** order - 1.0)
    print("| | DOFs | tip at the run's end | static tip | static / converged |")
    print("| --- | --- | --- | --- | --- |")
    for name, dofs, end, secs, tip in rows:
        print(f"| {name} | {dofs} | {end:.4f} m ({secs:.1f} s) | {tip:.4f} m "
              f"| {tip / ref:.3f} |")
    for cells, dofs, tip in conv:
        print(f"| P2 {cells} | {dofs} | | {tip:.5f} m | {tip / ref:.4f} |")
    print(f"| converged (Richardson, observed order {order:.2f}) | | | {ref:.5f} m | 1 |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--figures", action="store_true", help="print the tip deflections")
    parser.add_argument("--converged", default="20x2x2,40x4x4",
                        help="P2 meshes of the converged answer (cells, comma-separated)")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "gallery")
    args = parser.parse_args(argv)
    if args.figures:
        figures([tuple(int(x) for x in c.split("x")) for c in args.converged.split(",")])
    else:
        render(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
