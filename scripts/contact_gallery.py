"""Render the contact gallery's previews: docs/gallery/contact_<scene>.gif (and a .png).

    python scripts/contact_gallery.py [SCENE ...]      # default: every data/scenes/contact_*
    python scripts/contact_gallery.py contact_pile --frames runs/pile   # from a run's frames

Each scene runs exactly as ``fem3d run`` steps it (``Simulation.step``); the picture holds every
body's display mesh and the obstacles (a plane drawn as a square patch under the bodies, mesh
obstacles at their current positions), with a camera fixed to the whole clip.
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


def plane_patch(point, normal, center, half):
    """A square of half-width ``half`` on the plane, centred under ``center``."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    # drawn a little below the plane: faces resting on it stay in front in the depth sort
    c = np.asarray(center, float) - ((np.asarray(center) - point) @ n + 0.01 * half) * n
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    # a 40 x 40 grid: small faces keep the painter's depth sort right around the bodies
    k = 40
    u = np.linspace(-half, half, k + 1)
    V = (c + u[:, None, None] * a + u[None, :, None] * b).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    v0 = (i * (k + 1) + j).reshape(-1)
    F = np.concatenate([np.stack([v0, v0 + k + 1, v0 + k + 2], 1),
                        np.stack([v0, v0 + k + 2, v0 + 1], 1)])
    return V, F


def simulate(name: str, frames_wanted: int = 60):
    """Step scene ``name`` as ``fem3d run`` does; every ``every``-th state's display mesh and
    obstacles. Returns ``(sim, shots, obstacle_shots, every, seconds)``."""
    from fem3d.scene import DEFAULT_STEPS, load_scene
    from fem3d.simulation import Simulation

    scene = load_scene(name)
    sim = Simulation(scene, scripted=True)
    sc = scene.simulation
    steps = sc.steps or (round(sc.duration / sc.dt) if sc.duration else DEFAULT_STEPS)
    every = max(1, steps // frames_wanted)
    shots = [sim.skin_positions()]
    obstacle_shots = [sim.obstacles()]
    t0 = time.perf_counter()
    for k in range(steps):
        sim.step()
        if (k + 1) % every == 0 or k + 1 == steps:
            shots.append(sim.skin_positions())
            obstacle_shots.append(sim.obstacles())
    return sim, shots, obstacle_shots, every, time.perf_counter() - t0


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
    obstacle_shots = [sim.obstacles(k * sim.dt) for k in picked]
    return sim, shots, obstacle_shots, every, float("nan")


def render(name: str, out_dir: Path, frames_wanted: int = 60, folder: Path | None = None) -> None:
    from fem3d.io.preview import render_preview

    sim, shots, obstacle_shots, every, seconds = (
        simulate(name, frames_wanted) if folder is None else from_frames(name, folder,
                                                                         frames_wanted))
    faces = sim.display_faces
    allpts = np.vstack(shots)
    lo, hi = allpts.min(axis=0), allpts.max(axis=0)
    center = 0.5 * (lo + hi)
    half = 0.75 * float(np.max(hi - lo))
    extra_V, extra_F = [], []
    nv = shots[0].shape[0]
    for p in sim.contact.contact.planes:
        V, F = plane_patch(p.point, p.normal, center, half)
        extra_V.append(V)
        extra_F.append(F + nv + sum(len(v) for v in extra_V[:-1]))
    frames, all_faces = [], None
    for pos, obs in zip(shots, obstacle_shots, strict=True):
        Vs = [pos] + extra_V + [o[1] for o in obs]
        frames.append(np.vstack(Vs))
        if all_faces is None:
            Fs = [faces] + extra_F
            off = nv + sum(len(v) for v in extra_V)
            for o in obs:
                Fs.append(o[2] + off)
                off += len(o[1])
            all_faces = np.vstack(Fs)
    out_dir.mkdir(parents=True, exist_ok=True)
    gif = out_dir / f"{name}.gif"
    render_preview(frames, all_faces, gif, fps=min(50.0, 1.0 / (every * sim.dt)),
                   view_bounds="all", max_frames=frames_wanted + 1,
                   first_frame_png=out_dir / f"{name}.png", azim=30.0,
                   # from higher up where a mesh obstacle (an open box) would hide the bodies
                   elev=65.0 if sim.contact.contact.meshes else 35.0)
    steps = every * (len(shots) - 1)
    print(f"{name}: ~{steps} steps ({seconds:.1f} s), {len(frames)} frames -> {gif}", flush=True)


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
