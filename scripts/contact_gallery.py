"""Render the contact gallery's previews: docs/gallery/contact_<scene>.gif (and a .png).

    python scripts/contact_gallery.py [SCENE ...]      # default: every data/scenes/contact_*
    python scripts/contact_gallery.py contact_pile --frames runs/pile   # from a run's frames

Each scene runs exactly as ``fem3d run`` steps it (``Simulation.step``); the picture holds every
body's display mesh and the obstacles as ``fem3d run``'s preview draws them
(:func:`fem3d.io.preview.render_preview`: a plane as a checkerboard, a mesh obstacle in
blue-grey at its current position, an open box cut away on the camera's side), with a camera
fixed to the whole clip.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # this checkout's fem3d, not an installed one


def simulate(name: str, frames_wanted: int = 60):
    """Step scene ``name`` as ``fem3d run`` does; every ``every``-th state's display mesh and
    time. Returns ``(sim, shots, times, every, seconds)``."""
    from fem3d.scene import DEFAULT_STEPS, load_scene
    from fem3d.simulation import Simulation

    scene = load_scene(name)
    sim = Simulation(scene, scripted=True)
    sc = scene.simulation
    steps = sc.steps or (round(sc.duration / sc.dt) if sc.duration else DEFAULT_STEPS)
    every = max(1, steps // frames_wanted)
    shots, times = [sim.skin_positions()], [sim.t]
    t0 = time.perf_counter()
    for k in range(steps):
        sim.step()
        if (k + 1) % every == 0 or k + 1 == steps:
            shots.append(sim.skin_positions())
            times.append(sim.t)
    return sim, shots, times, every, time.perf_counter() - t0


def from_frames(name: str, folder: Path, frames_wanted: int = 60):
    """The same from the frames a run wrote (``fem3d run NAME --out FOLDER``, a scene without
    a skin: the frames are the simulation surface), without stepping again."""
    import meshio

    from fem3d.scene import load_scene
    from fem3d.simulation import Simulation

    sim = Simulation(load_scene(name), scripted=True)
    files = sorted((folder / "frames").glob("frame_*.vtu"))
    every = max(1, (len(files) - 1) // frames_wanted)
    picked = list(range(0, len(files), every))
    if picked[-1] != len(files) - 1:
        picked.append(len(files) - 1)
    shots = [np.asarray(meshio.read(files[k]).points, dtype=np.float64) for k in picked]
    return sim, shots, [k * sim.dt for k in picked], every, float("nan")


def render(name: str, out_dir: Path, frames_wanted: int = 60, folder: Path | None = None) -> None:
    from fem3d.io.preview import render_preview

    sim, shots, times, every, seconds = (
        simulate(name, frames_wanted) if folder is None else from_frames(name, folder,
                                                                         frames_wanted))
    gif = out_dir / f"{name}.gif"
    out_dir.mkdir(parents=True, exist_ok=True)
    # the obstacles as `fem3d run`'s preview draws them: planes as checkerboards, mesh
    # obstacles in blue-grey (an open box cut away on the camera's side)
    render_preview(shots, sim.display_faces, gif, fps=min(50.0, 1.0 / (every * sim.dt)),
                   view_bounds="all", max_frames=frames_wanted + 1,
                   first_frame_png=out_dir / f"{name}.png", azim=30.0, elev=35.0,
                   obstacles=sim.obstacle_meshes(), times=times)
    steps = every * (len(shots) - 1)
    print(f"{name}: ~{steps} steps ({seconds:.1f} s), {len(shots)} frames -> {gif}", flush=True)


def main(argv: list[str]) -> None:
    folder = None
    if "--frames" in argv:  # --frames DIR: one scene, from the frames of a run in DIR
        i = argv.index("--frames")
        folder = Path(argv[i + 1])
        argv = argv[:i] + argv[i + 2:]
    names = argv or sorted(p.stem for p in (ROOT / "data" / "scenes").glob("contact_*.toml"))
    for name in names:
        render(name, ROOT / "docs" / "gallery", folder=folder)


if __name__ == "__main__":
    main(sys.argv[1:])
