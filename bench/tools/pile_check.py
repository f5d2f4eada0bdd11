"""The contact pile (``data/scenes/contact_pile.toml``) run to rest and checked frame by frame.

    python -m bench.tools.pile_check [--steps N] [--out DIR] [--set KEY=VALUE ...] [--rest 1e-6]
    python -m bench.tools.pile_check --check DIR [--set ...]   # a run already made (or still going)
    python -m bench.tools.pile_check --bodies 0,1,2,3,4,5,6,7,8 ...  # without its top layer

The scene runs as ``fem3d run`` runs it (:func:`fem3d.app.run.run_scene`, frames written every
step, one thread). Then every written frame is checked by a test of its own, built from the
frame file alone (not the solver's contact set or filter):

* no two surface triangles intersect, between bodies or within one (self-intersection): a
  fresh ``ipctk.CollisionMesh`` of the frame's triangles, all in one group, and
  ``ipctk.has_intersections``;
* every vertex is inside the open box (the mesh obstacle's bounding box: strictly inside its
  walls' ``x`` and ``z`` range and above its floor);
* the pile comes to rest: the first step from which the kinetic energy (``energy.csv``) stays
  below ``--rest`` (default 1e-6) times its peak, and that the run ends there.

``--check DIR`` checks the frames of a run made by ``fem3d run contact_pile --out DIR`` (or
this script's ``--out``), also a partial one: the kinetic energy is then ``1/2 v^T M v`` with
``v = (q_n - q_(n-1)) / dt`` from consecutive frames (backward Euler's own velocity, so the
same as ``energy.csv``'s), and the speed is read from the frames' file times.

Prints one line per figure and exits 1 when a check fails.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.tools.contact_check import StateChecks, rest_step  # noqa: F401 (rest_step: re-exported)

ROOT = Path(__file__).resolve().parents[2]
SCENE = ROOT / "data" / "scenes" / "contact_pile.toml"


@dataclass
class FrameReport:
    """What :func:`check_frames` found."""

    frames: int
    intersecting: list[int]
    outside: list[int]
    #: smallest distance of a vertex to the box (walls and floor) over the frames; > 0 inside
    min_clearance: float


def box_bounds(scene) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) corner of the scene's mesh obstacles (the box) at rest."""
    from fem3d.scene.build import obstacles_from_scene

    _planes, meshes = obstacles_from_scene(scene)
    V = np.concatenate([m.positions(0.0) for m in meshes])
    return V.min(axis=0), V.max(axis=0)


def check_frames(out: Path, lower: np.ndarray, upper: np.ndarray) -> FrameReport:
    """Check every ``frames/frame_*.vtu`` of a run in ``out`` (see the module) with
    :class:`bench.tools.contact_check.StateChecks` (the box's floor and walls at ``lower``,
    ``upper``; the box's own triangles are not in the frames)."""
    import meshio

    files = sorted((out / "frames").glob("frame_*.vtu"))
    if not files:
        raise FileNotFoundError(f"no frames in {out / 'frames'}")
    faces = np.asarray(meshio.read(files[0]).cells_dict["triangle"], dtype=np.int64)
    checks = StateChecks(faces, [], (lower, upper))
    for f in files:
        checks.add(np.asarray(meshio.read(f).points, dtype=np.float64), [])
    return FrameReport(checks.states, checks.intersecting, checks.outside_box,
                       checks.min_box_clearance)


def frame_kinetic(out: Path, scene) -> np.ndarray:
    """``1/2 v^T M v`` per frame, ``v`` from consecutive frames (0 for the first)."""
    import meshio

    from fem3d.simulation import Simulation

    M = Simulation(scene).model.mass
    dt = scene.simulation.dt
    files = sorted((out / "frames").glob("frame_*.vtu"))
    prev, ke = None, []
    for f in files:
        x = np.asarray(meshio.read(f).points, dtype=np.float64).reshape(-1)
        v = np.zeros_like(x) if prev is None else (x - prev) / dt
        ke.append(0.5 * float(v @ (M @ v)))
        prev = x
    return np.asarray(ke)


def check_run(out: Path, scene, rest: float) -> bool:
    """Print the checks of the run in ``out``; True when all pass."""
    from fem3d.io.energy import read_energy_csv

    dt = scene.simulation.dt
    if (out / "energy.csv").is_file():
        kinetic = np.asarray(read_energy_csv(out / "energy.csv")["kinetic"])
    else:
        kinetic = frame_kinetic(out, scene)
        files = sorted((out / "frames").glob("frame_*.vtu"))
        span = files[-1].stat().st_mtime - files[0].stat().st_mtime
        print(f"partial run: {len(files) - 1} steps written, {span:.0f} s wall between the "
              f"first and last frame ({(len(files) - 1) / max(span, 1e-9):.3f} steps/s); "
              "kinetic energy from the frames")
    k = rest_step(kinetic, rest)
    print(f"kinetic energy: peak {kinetic.max():.3e} J at step {int(kinetic.argmax())}, "
          f"last {kinetic[-1]:.3e} J ({kinetic[-1] / kinetic.max():.1e} of the peak); "
          + (f"below {rest:g} of the peak from step {k} (t = {k * dt:.2f} s) on"
             if k is not None else f"not below {rest:g} of the peak at the end"))
    lower, upper = box_bounds(scene)
    rep = check_frames(out, lower, upper)
    print(f"frames: {rep.frames} checked by a fresh ipctk mesh each: "
          f"{len(rep.intersecting)} intersect {rep.intersecting[:5]}, "
          f"{len(rep.outside)} have a vertex outside the box {rep.outside[:5]}; "
          f"closest vertex to the box {rep.min_clearance * 1e3:.3f} mm")
    return not rep.intersecting and not rep.outside and k is not None


def main(argv: list[str] | None = None) -> int:
    from fem3d.app.cli import parse_assignments
    from fem3d.app.run import run_scene
    from fem3d.scene import apply_overrides, load_scene

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=None, help="default: the scene's duration")
    ap.add_argument("--out", type=Path, default=None, help="default: a temporary folder")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--rest", type=float, default=1e-6)
    ap.add_argument("--bodies", default=None, metavar="I,J,...",
                    help="only these of the scene's bodies (e.g. 0,4: a block and its bunny)")
    ap.add_argument("--check", type=Path, default=None, metavar="DIR",
                    help="check the frames of a run in DIR instead of running")
    args = ap.parse_args(argv)
    overrides = dict(parse_assignments(args.set))
    if args.steps is not None:
        overrides["simulation.steps"] = args.steps
    scene = load_scene(str(SCENE))
    if args.bodies:
        every = scene.model_dump(mode="json")["bodies"]
        overrides["bodies"] = [every[int(i)] for i in args.bodies.split(",")]
    scene = apply_overrides(scene, overrides)
    if args.check is not None:
        ok = check_run(args.check, scene, args.rest)
        print("OK" if ok else "FAILED")
        return 0 if ok else 1
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp) / "pile"
        t0, c0 = time.perf_counter(), time.process_time()
        summary = run_scene(scene, out, preview=False, quiet=True)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        n = summary.steps
        print(f"pile: {len(scene.bodies)} bodies, {_tets(scene)} tets, dt {scene.simulation.dt}, "
              f"{n} steps ({summary.status}{': ' + summary.message if summary.message else ''})")
        print(f"speed: {n / summary.wall_seconds:.3f} steps/s wall ({summary.wall_seconds:.0f} s;"
              f" process CPU {cpu:.0f} s, whole run {wall:.0f} s wall), "
              f"{summary.newton_iterations / max(n, 1):.2f} Newton iterations/step")
        ok = check_run(out, scene, args.rest) and summary.status == "ok"
    print("OK" if ok else "FAILED")
    return 0 if ok else 1

def _tets(scene) -> str:
    from fem3d.simulation import Simulation

    return f"{Simulation(scene).model.n_tets:,}"


if __name__ == "__main__":
    sys.exit(main())
