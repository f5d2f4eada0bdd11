"""Command line: ``fem3d run`` (headless main job), ``fem3d resume`` and the sub-commands other
modules register.

``fem3d run bunny|arma|PATH [--integrator linear|implicit] [--steps N] [--dt DT] [--out DIR]
[--kernels numpy|c] [--frame-every K] [--checkpoint-every N] [--E E] [--nu NU] [--rho RHO]
[--pick-radius R] [--pull-point X Y Z] [--fix-below Y] [--debug]`` runs a scene with its
scripted pull and writes into ``DIR``:

* ``frames/frame_00000.vtu`` ... and ``frames.pvd`` - the skinned display mesh per frame
  (open ``frames.pvd`` in ParaView), or ``frames/*.obj`` with ``--format obj``;
* ``energy.csv`` (``t,kinetic,potential,total``) and ``energy.png``;
* ``preview.gif`` - a shaded offscreen animation;
* ``checkpoint.npz`` - with ``--checkpoint-every N`` every N steps and at the end, and always
  on SIGINT / SIGTERM (see :mod:`fem3d.checkpoint`).

``fem3d resume DIR [--steps N]`` continues a run from ``DIR/checkpoint.npz`` up to step ``N``
(default: the original ``--steps``) with the saved settings, in the same folder: frames keep
their numbering, ``energy.csv`` keeps the earlier rows, ``frames.pvd`` lists every frame. The
result is bit for bit the one of an uninterrupted run (same kernels and solver back end).

SIGINT (Ctrl-C) or SIGTERM during the steps: the current step is finished (a second signal
abandons it; the state stays at the last finished step), a checkpoint is saved, energy.csv and
the frames are complete up to that step, one line says how to continue, exit status 130.

Exit status: 0 success; 1 the simulation failed (an explosion or inverted elements: the
message says at which step; every frame and energy up to the last good step is written, and
no output file ever holds a NaN); 2 bad input or parameters (one line on stderr, a traceback
only with ``--debug``); 130 interrupted.

Adding a sub-command: append ``"module:function"`` to :data:`SUBCOMMANDS`; ``function``
receives the ``argparse`` sub-parser collection, adds its parser and sets ``func`` (a
callable ``args -> int``) with ``set_defaults``. Modules are imported when the parser is
built; one that fails to import (a missing optional dependency) is left out with a note in
``fem3d --help``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib
import math
import signal
import sys
import threading
import time
import traceback
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from fem3d import rundir
from fem3d.errors import InputError, ParameterError, SimulationError

__all__ = ["main", "build_parser", "run_scene", "resume_run", "SUBCOMMANDS"]

#: Sub-command registrars, ``"module:function"``, in ``--help`` order.
SUBCOMMANDS: list[str] = [
    "fem3d.cli:add_run_subcommand",
    "fem3d.viewer:add_view_subcommand",
    "fem3d.cli:add_resume_subcommand",
]

#: Frames kept in memory for the GIF preview (evenly spaced).
PREVIEW_FRAMES = 60

#: Exit status of an interrupted run (128 + SIGINT).
EXIT_INTERRUPTED = 130


def add_run_subcommand(subparsers) -> argparse.ArgumentParser:
    """Register ``fem3d run``."""
    p = subparsers.add_parser(
        "run",
        help="run a scene headless and write frames, energies and a preview",
        description="Run a scene with its scripted pull (attach for 0.3 s, release) and write "
        "the skinned display mesh per frame (frames/*.vtu + frames.pvd), energy.csv, "
        "energy.png and preview.gif into --out. Ctrl-C saves a checkpoint (exit 130); "
        "continue with `fem3d resume DIR`.",
    )
    p.add_argument("scene", help="bunny | arma | path to a tet mesh (.mesh, .node/.ele, .msh, ...)")
    p.add_argument(
        "--integrator", choices=("linear", "implicit"), default=None,
        help="linearly-implicit or backward Euler (default: the scene's)",
    )
    p.add_argument("--steps", type=int, default=100, help="number of time steps (default 100)")
    p.add_argument("--dt", type=float, default=None, help="time step (default: the scene's, 0.01)")
    p.add_argument("--out", default=None, help="output folder (default out/<scene>)")
    p.add_argument(
        "--kernels", choices=("numpy", "c"), default=None,
        help="kernel back end (default: C if built, else NumPy)",
    )
    p.add_argument(
        "--frame-every", type=int, default=1, metavar="K", help="write every K-th step (default 1)"
    )
    p.add_argument(
        "--checkpoint-every", type=int, default=0, metavar="N",
        help="save DIR/checkpoint.npz every N steps and at the end (default 0: only on "
        "SIGINT/SIGTERM)",
    )
    p.add_argument(
        "--format", choices=("vtu", "obj"), default="vtu", help="frame format (default vtu)"
    )
    p.add_argument("--skin", default=None, help="display mesh for a mesh-file scene")
    p.add_argument(
        "--newton-iterations", type=int, default=5,
        help="Newton iterations per backward-Euler step (default 5)",
    )
    p.add_argument(
        "--hessian", choices=("exact", "psd"), default="exact",
        help="Newton Hessian of backward Euler: exact (default) or per-element PSD-projected",
    )
    p.add_argument(
        "--newton-solver", choices=("direct", "reuse"), default="direct",
        help="Newton linear solves: refactorize each iteration (default) or keep a "
             "factorization as the CG preconditioner across iterations and steps, "
             "refactorizing when CG needs more than 16 iterations",
    )
    p.add_argument("--E", type=float, default=None, help="Young's modulus (default: the scene's)")
    p.add_argument("--nu", type=float, default=None,
                   help="Poisson's ratio, -1 < nu < 0.5 (default: the scene's)")
    p.add_argument("--rho", type=float, default=None, help="density (default: the scene's)")
    p.add_argument("--pick-radius", type=float, default=None, metavar="R",
                   help="vertices within R of the pull point are pulled (default: the scene's)")
    p.add_argument("--pull-point", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="centre of the scripted pull's pick (default: the scene's vertex)")
    p.add_argument("--fix-below", type=float, default=None, metavar="Y",
                   help="fix the vertices with rest y <= Y (default: within the scene's "
                   "tolerance of the lowest y)")
    p.add_argument("--no-preview", action="store_true", help="skip preview.gif")
    p.add_argument("--no-pull", action="store_true", help="do not apply the scripted pull")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks"
    )
    p.set_defaults(func=_run_command)
    return p


def add_resume_subcommand(subparsers) -> argparse.ArgumentParser:
    """Register ``fem3d resume``."""
    p = subparsers.add_parser(
        "resume",
        help="continue a run from DIR/checkpoint.npz",
        description="Continue a `fem3d run` from the checkpoint in its output folder, with "
        "the same settings, writing into the same folder (bit for bit what an uninterrupted "
        "run gives).",
    )
    p.add_argument("dir", help="output folder of the run (holds checkpoint.npz)")
    p.add_argument("--steps", type=int, default=None,
                   help="total step count to reach (default: the run's --steps)")
    p.add_argument("--checkpoint-every", type=int, default=None, metavar="N",
                   help="checkpoint interval (default: the run's)")
    p.add_argument("--no-preview", action="store_true", help="skip preview.gif")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks"
    )
    p.set_defaults(func=_resume_command)
    return p


def build_parser() -> argparse.ArgumentParser:
    """The ``fem3d`` parser with every registered sub-command."""
    parser = argparse.ArgumentParser(
        prog="fem3d",
        description="Linear tetrahedral FEM elastodynamics (Neo-Hookean, SymPy-generated kernels).",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    missing = []
    for spec in SUBCOMMANDS:
        module, _, function = spec.partition(":")
        try:
            register = getattr(importlib.import_module(module), function)
        except (ImportError, AttributeError) as exc:
            missing.append(f"{spec} ({exc})")
            continue
        register(sub)
    if missing:
        parser.epilog = "unavailable sub-commands: " + "; ".join(missing)
    return parser



def _check_args(args: argparse.Namespace) -> None:
    if args.steps < 0:
        raise ParameterError(f"--steps must be >= 0, got {args.steps}")
    if args.frame_every < 1:
        raise ParameterError(f"--frame-every must be >= 1, got {args.frame_every}")
    if args.checkpoint_every < 0:
        raise ParameterError(f"--checkpoint-every must be >= 0, got {args.checkpoint_every}")
    if args.newton_iterations < 1:
        raise ParameterError(f"--newton-iterations must be >= 1, got {args.newton_iterations}")
    if args.dt is not None and not (math.isfinite(args.dt) and args.dt > 0):
        raise ParameterError(f"--dt must be a finite number > 0, got {args.dt}")
    if args.pull_point is not None and not all(math.isfinite(c) for c in args.pull_point):
        raise ParameterError(f"--pull-point must be 3 finite numbers, got {args.pull_point}")
    if args.fix_below is not None and not math.isfinite(args.fix_below):
        raise ParameterError(f"--fix-below must be a finite number, got {args.fix_below}")


def _settings_from_args(args: argparse.Namespace, backend: str) -> dict[str, Any]:
    """The run's settings before the scene is loaded (completed by :func:`_build`)."""
    from fem3d.scenes import SCENES

    scene = str(args.scene)
    if scene not in SCENES:  # a mesh path: absolute, so `fem3d resume` works from anywhere
        scene = str(Path(scene).resolve()) if Path(scene).exists() else scene
    skin = None if args.skin is None else str(Path(args.skin).resolve())
    return {
        "scene": scene, "skin": skin, "integrator": args.integrator, "steps": int(args.steps),
        "dt": args.dt, "kernels": backend, "solver": None, "frame_every": int(args.frame_every),
        "checkpoint_every": int(args.checkpoint_every), "format": args.format,
        "newton_iterations": int(args.newton_iterations), "hessian": args.hessian,
        "newton_solver": args.newton_solver, "E": args.E, "nu": args.nu, "rho": args.rho,
        "pick_radius": args.pick_radius,
        "pull_point": None if args.pull_point is None else [float(c) for c in args.pull_point],
        "fix_below": args.fix_below, "no_pull": bool(args.no_pull),
        "no_preview": bool(args.no_preview),
    }


def _build(settings: dict[str, Any]):
    """Scene and Simulation for ``settings``; fills in the resolved values (in place).

    After the first call every value is explicit, so a second call with the completed
    settings (``fem3d resume``) rebuilds exactly the same run.
    """
    import numpy as np

    from fem3d.scenes import PullScript, load_scene
    from fem3d.simulation import Simulation

    scene = load_scene(
        settings["scene"], skin=settings["skin"], dt=settings["dt"], E=settings["E"],
        nu=settings["nu"], rho=settings["rho"], pick_radius=settings["pick_radius"],
        spring_k=settings.get("spring_k"), fixed_tol=settings.get("fixed_tol"),
    )
    pull = settings.get("pull")
    if pull is not None:  # the saved script (resume)
        scene = scene.replace(pull=PullScript(
            vertex=int(pull["vertex"]), point=np.array(pull["point"], dtype=np.float64),
            offset=np.array(pull["offset"], dtype=np.float64), start=float(pull["start"]),
            duration=float(pull["duration"]),
        ))
    elif settings["pull_point"] is not None and scene.pull is not None:
        scene = scene.replace(pull=dataclasses.replace(
            scene.pull, point=np.array(settings["pull_point"], dtype=np.float64)))
    fixed = None
    if settings["fix_below"] is not None:
        fixed = np.flatnonzero(scene.X[:, 1] <= settings["fix_below"])
        if fixed.size == 0:
            raise ParameterError(
                f"--fix-below {settings['fix_below']:g} selects no vertex to fix (the lowest "
                f"rest y is {float(scene.X[:, 1].min()):.6g}); a run needs a fixed vertex"
            )
    sim = Simulation(
        scene, settings["integrator"], settings["kernels"], scripted=not settings["no_pull"],
        solver_backend=settings["solver"] or "auto",
        max_newton_iterations=settings["newton_iterations"], newton_hessian=settings["hessian"],
        newton_solver=settings.get("newton_solver", "direct"), fixed_vertices=fixed,
    )
    settings.update(
        integrator=sim.integrator, dt=sim.dt, E=scene.E, nu=scene.nu, rho=scene.rho,
        pick_radius=scene.pick_radius, spring_k=scene.spring_k, fixed_tol=scene.fixed_tol,
        solver=sim.system._solver.backend,
        pull=None if scene.pull is None else {
            "vertex": int(scene.pull.vertex), "point": [float(c) for c in scene.pull.point],
            "offset": [float(c) for c in scene.pull.offset], "start": float(scene.pull.start),
            "duration": float(scene.pull.duration),
        },
    )
    return scene, sim


class _Interrupts:
    """SIGINT / SIGTERM while stepping: remember the first, abandon the step on a second."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.in_step = False

    def __call__(self, signum: int, frame: Any) -> None:
        first = self.signum is None
        self.signum = signum
        if not first and self.in_step:
            raise KeyboardInterrupt

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum is not None else ""

    @contextlib.contextmanager
    def installed(self) -> Iterator[_Interrupts]:
        if threading.current_thread() is not threading.main_thread():
            yield self  # signals are delivered to the main thread only
            return
        old = {s: signal.signal(s, self) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield self
        finally:
            for s, h in old.items():
                signal.signal(s, h)


def _read_frame(path: Path):
    import meshio

    return meshio.read(path).points


def _drive(
    settings: dict[str, Any],
    scene,
    sim,
    out: Path,
    *,
    quiet: bool,
    debug: bool,
    ckpt=None,
    command: str = "run",
) -> int:
    """Step ``sim`` up to ``settings["steps"]``, writing outputs (and checkpoints) to ``out``."""
    import numpy as np
    from tqdm import tqdm

    from fem3d import output
    from fem3d.checkpoint import CHECKPOINT_NAME, RunCheckpoint, mesh_digest, save_run_checkpoint

    steps, frame_every = settings["steps"], settings["frame_every"]
    every = settings["checkpoint_every"]
    digest = mesh_digest(scene.X, scene.T)
    faces = sim.display_faces
    writer = output.FrameWriter(out, faces, settings["format"])
    n_frames = steps // frame_every + 1
    preview_stride = max(1, math.ceil(n_frames / PREVIEW_FRAMES))
    preview: list[np.ndarray] = []
    frame_count = 0
    if ckpt is None:
        log = output.EnergyLog(out / "energy.csv")
    else:  # resume: the saved energy rows and frame list; frames after the checkpoint go
        log = output.EnergyLog.from_array(ckpt.energy, out / "energy.csv")
        writer.frames = dict(ckpt.frames)
        frame_count = ckpt.frame_count
        for f in writer.frame_dir.glob(f"frame_*.{writer.fmt}"):
            with contextlib.suppress(ValueError):
                if int(f.stem.split("_")[-1]) > ckpt.step:
                    f.unlink()  # written after the checkpoint by the interrupted run
        log.write()
        if writer.pvd_path is not None:
            output.atomic_write(writer.pvd_path, writer.pvd_text())
        if not settings["no_preview"]:
            for i, s in enumerate(sorted(writer.frames)):
                if i % preview_stride == 0:
                    with contextlib.suppress(Exception):
                        preview.append(_read_frame(out / writer.frames[s][1]))

    def record(step: int, t: float, kinetic: float, potential: float, total: float) -> None:
        nonlocal frame_count
        if not all(math.isfinite(x) for x in (t, kinetic, potential, total)):
            raise SimulationError("non-finite energy (nothing written for this step)", step=step)
        if step % frame_every == 0:
            V = sim.skin_positions()
            writer.write(step, t, V)  # refuses non-finite coordinates
            if frame_count % preview_stride == 0:
                preview.append(V)
            frame_count += 1
        log.append(t, kinetic, potential, total)

    def save_checkpoint() -> Path:
        log.write()  # energy.csv and the checkpoint agree
        return save_run_checkpoint(out / CHECKPOINT_NAME, RunCheckpoint(
            settings=settings, snapshot=sim.snapshot(), energy=log.as_array(),
            frames=dict(writer.frames), frame_count=frame_count, mesh_digest=digest,
        ))

    if ckpt is None:
        e = sim.energies()
        record(0, sim.t, e["kinetic"], e["potential"], e["total"])
    start = sim.step_index
    print(
        f"fem3d {command} {scene.name}: {sim.model.n_vertices} vertices, {sim.model.n_tets} "
        f"tets, {sim.constraints.fixed_vertices.size} fixed, integrator {sim.integrator}, "
        f"dt {sim.dt:g}, kernels {sim.model.mat.backend}, steps {start} -> {steps} -> {out}",
        file=sys.stderr,
    )
    status = 0
    step_seconds: list[float] = []
    iterations: list[int] = []
    t_start = time.perf_counter()
    bar = tqdm(total=steps, initial=start, unit="step", disable=quiet or None, file=sys.stderr,
               dynamic_ncols=True)
    intr = _Interrupts()
    try:
        with intr.installed():
            while sim.step_index < steps and intr.signum is None:
                before = sim.snapshot()
                intr.in_step = True
                try:
                    info = sim.step()
                except KeyboardInterrupt:  # a second signal: abandon this step
                    intr.in_step = False
                    sim.restore(before)
                    break
                finally:
                    intr.in_step = False
                step_seconds.append(info.seconds)
                iterations.append(info.newton_iterations)
                record(sim.step_index, info.t, info.kinetic, info.potential, info.total)
                bar.update(1)
                bar.set_postfix_str(f"t={info.t:.2f} E={info.total:.3g}", refresh=False)
                if every and sim.step_index % every == 0:
                    save_checkpoint()
                elif sim.step_index % 50 == 0:
                    log.write()
            if intr.signum is not None:  # stop before any slow output
                bar.close()
                path = save_checkpoint()
                print(
                    f"fem3d {command}: interrupted by {intr.name} at step {sim.step_index} "
                    f"(t = {sim.t:.4g}); checkpoint {path}; continue with: "
                    f"fem3d resume {out}",
                    file=sys.stderr,
                )
                return EXIT_INTERRUPTED
    except SimulationError as exc:
        status = 1
        bar.close()
        print(
            f"fem3d {command}: simulation failed: {exc}\n"
            f"  output up to the last good step ({sim.step_index}, t = {sim.t:.4g}) is in {out}",
            file=sys.stderr,
        )
        if debug:
            traceback.print_exc()
    finally:
        bar.close()
        log.write()
    if status == 0 and every:
        save_checkpoint()
    if len(log):
        output.plot_energy(log, out / "energy.png", title=f"{scene.name} ({sim.integrator})")
    if not settings["no_preview"] and preview:
        output.render_preview(preview, faces, out / "preview.gif")
    if step_seconds:
        total = time.perf_counter() - t_start
        print(
            f"fem3d {command}: {len(step_seconds)} steps in {total:.2f} s; "
            f"{1e3 * float(np.mean(step_seconds)):.2f} ms/step "
            f"({float(np.mean(iterations)):.2f} Newton iterations/step); "
            f"{frame_count} frames in {out}",
            file=sys.stderr,
        )
    return status


def _resolve_kernels(name: str | None) -> str:
    try:
        from fem3d.kernels import resolve_backend

        return resolve_backend(name)
    except (ImportError, ValueError) as exc:
        raise InputError(f"--kernels {name}: {exc}") from None


def run_scene(args: argparse.Namespace) -> int:
    """Run ``fem3d run`` for parsed arguments; returns the exit status (0, 1 or 130).

    Raises
    ------
    InputError
        Bad scene, mesh or parameter (the caller maps it to exit status 2).
    """
    _check_args(args)
    backend = _resolve_kernels(args.kernels)
    if args.out:  # fail on an unusable output folder before any expensive setup
        Path(args.out).mkdir(parents=True, exist_ok=True)
    settings = _settings_from_args(args, backend)
    if args.out:  # before reading the inputs: one of them may be an output of this run
        rundir.check_overwrite(args.out, {"mesh": settings["scene"], "skin": settings["skin"]})
    scene, sim = _build(settings)
    out = Path(args.out) if args.out else Path("out") / scene.name
    inputs = {"mesh": scene.mesh_path, "skin": scene.skin_path}
    with rundir.claim(out, inputs=inputs):  # lock; refuse overwriting inputs; clean temps
        return _drive(settings, scene, sim, out, quiet=args.quiet,
                      debug=getattr(args, "debug", False))


def resume_run(args: argparse.Namespace) -> int:
    """Run ``fem3d resume DIR``: continue from ``DIR/checkpoint.npz``; returns the exit status.

    Raises
    ------
    InputError
        No or a bad checkpoint, a mesh changed since, or a bad ``--steps``.
    """
    from fem3d.checkpoint import CHECKPOINT_NAME, load_run_checkpoint, mesh_digest

    out = Path(args.dir)
    ckpt = load_run_checkpoint(out / CHECKPOINT_NAME)
    settings = dict(ckpt.settings)
    if args.steps is not None:
        if args.steps < ckpt.step:
            raise ParameterError(
                f"--steps {args.steps} is below the checkpoint's step {ckpt.step}"
            )
        settings["steps"] = int(args.steps)
    if args.checkpoint_every is not None:
        if args.checkpoint_every < 0:
            raise ParameterError(f"--checkpoint-every must be >= 0, got {args.checkpoint_every}")
        settings["checkpoint_every"] = int(args.checkpoint_every)
    if args.no_preview:
        settings["no_preview"] = True
    settings["kernels"] = _resolve_kernels(settings["kernels"])
    scene, sim = _build(settings)
    if mesh_digest(scene.X, scene.T) != ckpt.mesh_digest:
        raise InputError("the mesh differs from the one the checkpoint was made with",
                         path=settings["scene"])
    try:
        sim.restore(ckpt.snapshot)
    except ParameterError as exc:
        raise InputError(f"bad checkpoint state: {exc}", path=out / CHECKPOINT_NAME) from None
    ck = out / CHECKPOINT_NAME
    inputs = {"mesh": scene.mesh_path, "skin": scene.skin_path, "checkpoint": ck}
    with rundir.claim(out, inputs=inputs, allow=(ck,)):
        return _drive(settings, scene, sim, out, quiet=args.quiet,
                      debug=getattr(args, "debug", False), ckpt=ckpt, command="resume")


def _run_command(args: argparse.Namespace) -> int:
    return run_scene(args)


def _resume_command(args: argparse.Namespace) -> int:
    return resume_run(args)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``fem3d`` script; returns the exit status.

    ``InputError`` or ``OSError`` (e.g. an unwritable output folder) -> one line on stderr,
    status 2; ``SimulationError`` -> message, status 1.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        with rundir.warnings_as_lines(f"fem3d {args.command}"):
            return int(args.func(args) or 0)
    except InputError as exc:
        if args.debug:
            traceback.print_exc()
        print(f"fem3d {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except SimulationError as exc:
        if args.debug:
            traceback.print_exc()
        print(f"fem3d {args.command}: simulation failed: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:  # e.g. an output folder that cannot be written
        if args.debug:
            traceback.print_exc()
        print(f"fem3d {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"fem3d {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
