"""Command line: ``fem3d run`` (headless main job) and the sub-commands other modules register.

``fem3d run bunny|arma|PATH [--integrator linear|implicit] [--steps N] [--dt DT] [--out DIR]
[--kernels numpy|c] [--frame-every K] [--debug]`` runs a scene with its scripted pull and
writes into ``DIR``:

* ``frames/frame_00000.vtu`` ... and ``frames.pvd`` - the skinned display mesh per frame
  (open ``frames.pvd`` in ParaView), or ``frames/*.obj`` with ``--format obj``;
* ``energy.csv`` (``t,kinetic,potential,total``) and ``energy.png``;
* ``preview.gif`` - a shaded offscreen animation.

Exit status: 0 success; 1 the simulation failed (an explosion: the message says at which step;
every frame and energy up to the last good step is written); 2 bad input (one line on stderr,
a traceback only with ``--debug``).

Adding a sub-command: append ``"module:function"`` to :data:`SUBCOMMANDS`; ``function``
receives the ``argparse`` sub-parser collection, adds its parser and sets ``func`` (a
callable ``args -> int``) with ``set_defaults``. Modules are imported when the parser is
built; one that fails to import (a missing optional dependency) is left out with a note in
``fem3d --help``.
"""

from __future__ import annotations

import argparse
import importlib
import math
import sys
import time
import traceback
from collections.abc import Sequence
from pathlib import Path

from fem3d.errors import InputError, SimulationError

__all__ = ["main", "build_parser", "run_scene", "SUBCOMMANDS"]

#: Sub-command registrars, ``"module:function"``, in ``--help`` order.
SUBCOMMANDS: list[str] = [
    "fem3d.cli:add_run_subcommand",
    "fem3d.viewer:add_view_subcommand",
    # "fem3d.resume:add_resume_subcommand",
]

#: Frames kept in memory for the GIF preview (evenly spaced).
PREVIEW_FRAMES = 60


def add_run_subcommand(subparsers) -> argparse.ArgumentParser:
    """Register ``fem3d run``."""
    p = subparsers.add_parser(
        "run",
        help="run a scene headless and write frames, energies and a preview",
        description="Run a scene with its scripted pull (attach for 0.3 s, release) and write "
        "the skinned display mesh per frame (frames/*.vtu + frames.pvd), energy.csv, "
        "energy.png and preview.gif into --out.",
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
    p.add_argument("--no-preview", action="store_true", help="skip preview.gif")
    p.add_argument("--no-pull", action="store_true", help="do not apply the scripted pull")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks"
    )
    p.set_defaults(func=_run_command)
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
    from fem3d.errors import ParameterError

    if args.steps < 0:
        raise ParameterError(f"--steps must be >= 0, got {args.steps}")
    if args.frame_every < 1:
        raise ParameterError(f"--frame-every must be >= 1, got {args.frame_every}")
    if args.newton_iterations < 1:
        raise ParameterError(f"--newton-iterations must be >= 1, got {args.newton_iterations}")
    if args.dt is not None and not (math.isfinite(args.dt) and args.dt > 0):
        raise ParameterError(f"--dt must be a finite number > 0, got {args.dt}")


def run_scene(args: argparse.Namespace) -> int:
    """Run ``fem3d run`` for parsed arguments; returns the exit status (0 or 1).

    Raises
    ------
    InputError
        Bad scene, mesh or parameter (the caller maps it to exit status 2).
    """
    import numpy as np
    from tqdm import tqdm

    from fem3d import output
    from fem3d.scenes import load_scene
    from fem3d.simulation import Simulation

    _check_args(args)
    try:
        from fem3d.kernels import resolve_backend

        backend = resolve_backend(args.kernels)
    except (ImportError, ValueError) as exc:
        raise InputError(f"--kernels {args.kernels}: {exc}") from None
    if args.out:  # fail on an unusable output folder before any expensive setup
        Path(args.out).mkdir(parents=True, exist_ok=True)
    scene = load_scene(args.scene, skin=args.skin, dt=args.dt)
    sim = Simulation(
        scene, args.integrator, backend, scripted=not args.no_pull,
        max_newton_iterations=args.newton_iterations, newton_hessian=args.hessian,
    )
    out = Path(args.out) if args.out else Path("out") / scene.name
    out.mkdir(parents=True, exist_ok=True)
    faces = sim.display_faces
    writer = output.FrameWriter(out, faces, args.format)
    log = output.EnergyLog(out / "energy.csv")
    n_frames = args.steps // args.frame_every + 1
    preview_stride = max(1, math.ceil(n_frames / PREVIEW_FRAMES))
    preview: list[np.ndarray] = []
    frame_count = 0

    def record(step: int, t: float, kinetic: float, potential: float, total: float) -> None:
        nonlocal frame_count
        log.append(t, kinetic, potential, total)
        if step % args.frame_every == 0:
            V = sim.skin_positions()
            writer.write(step, t, V)
            if frame_count % preview_stride == 0:
                preview.append(V)
            frame_count += 1

    e = sim.energies()
    record(0, sim.t, e["kinetic"], e["potential"], e["total"])
    print(
        f"fem3d run {scene.name}: {sim.model.n_vertices} vertices, {sim.model.n_tets} tets, "
        f"{sim.constraints.fixed_vertices.size} fixed, integrator {sim.integrator}, "
        f"dt {sim.dt:g}, kernels {sim.model.mat.backend}, {args.steps} steps -> {out}",
        file=sys.stderr,
    )
    status = 0
    step_seconds: list[float] = []
    iterations: list[int] = []
    t_start = time.perf_counter()
    bar = tqdm(total=args.steps, unit="step", disable=args.quiet or None, file=sys.stderr,
               dynamic_ncols=True)
    try:
        for _ in range(args.steps):
            info = sim.step()
            step_seconds.append(info.seconds)
            iterations.append(info.newton_iterations)
            record(sim.step_index, info.t, info.kinetic, info.potential, info.total)
            bar.update(1)
            bar.set_postfix_str(f"t={info.t:.2f} E={info.total:.3g}", refresh=False)
            if sim.step_index % 50 == 0:
                log.write()
    except SimulationError as exc:
        status = 1
        bar.close()
        print(
            f"fem3d run: simulation failed: {exc}\n"
            f"  output up to the last good step ({sim.step_index}, t = {sim.t:.4g}) is in {out}",
            file=sys.stderr,
        )
        if args.debug:
            traceback.print_exc()
    finally:
        bar.close()
        log.write()
    if len(log):
        output.plot_energy(log, out / "energy.png", title=f"{scene.name} ({sim.integrator})")
    if not args.no_preview and preview:
        output.render_preview(preview, faces, out / "preview.gif")
    if step_seconds:
        total = time.perf_counter() - t_start
        print(
            f"fem3d run: {len(step_seconds)} steps in {total:.2f} s; "
            f"{1e3 * float(np.mean(step_seconds)):.2f} ms/step "
            f"({float(np.mean(iterations)):.2f} Newton iterations/step); "
            f"{frame_count} frames in {out}",
            file=sys.stderr,
        )
    return status


def _run_command(args: argparse.Namespace) -> int:
    return run_scene(args)


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
