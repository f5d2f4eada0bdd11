"""Command line: ``fem3d run`` (headless main job), ``fem3d resume``, ``fem3d schema`` and the
sub-commands other modules register.

``fem3d run NAME|FILE.toml|MESH [--steps N] [--dt DT] [--integrator NAME]
[--material NAME] [--E E] [--nu NU] [--rho RHO] [--format NAME] [--frame-every K]
[--set KEY=VALUE ...] [--out DIR] [--kernels numpy|c] [--checkpoint-every N] [--profile]
[--debug]`` runs
a scene (:mod:`fem3d.scene.spec`: a name of ``data/scenes``, a scene file, or a one-body scene
around a mesh file) with its scripted pulls. Every flag but ``--out``, ``--kernels``,
``--checkpoint-every``, ``--no-preview`` and ``--quiet`` overrides one field of the scene
(:data:`RUN_FLAGS`; ``--set`` any field by its key path). ``--profile`` prints the time and
memory of each stage of the start (:mod:`fem3d.app.profile`). It writes into ``DIR``:

* ``frames/frame_00000.vtu`` ... and ``frames.pvd`` - the display mesh per frame (open
  ``frames.pvd`` in ParaView), ``frames/*.obj``, or one ``frames.usdc`` (``output.format``,
  :mod:`fem3d.io.frames`);
* ``energy.csv`` (``t,kinetic,potential,total``) and ``energy.png``;
* ``preview.gif`` - a shaded offscreen animation;
* ``checkpoint.npz`` - with ``--checkpoint-every N`` every N steps and at the end, and always
  on SIGINT / SIGTERM (see :mod:`fem3d.io.checkpoint`). It holds the whole scene.

``fem3d resume DIR [--steps N]`` continues a run from ``DIR/checkpoint.npz`` up to step ``N``
(default: the run's) with the saved scene, in the same folder: frames keep their numbering,
``energy.csv`` keeps the earlier rows, ``frames.pvd`` lists every frame. The result is bit
for bit the one of an uninterrupted run (same kernels and solver back end).

``fem3d schema`` prints the JSON Schema of scene files.

``fem3d fit FIT.toml --out DIR`` fits parameters to a run's frames (:mod:`fem3d.app.fit`).

SIGINT (Ctrl-C) or SIGTERM during the steps: the current step is finished (a second signal
abandons it; the state stays at the last finished step), a checkpoint is saved, energy.csv and
the frames are complete up to that step, one line says how to continue, exit status 130.

Exit status: 0 success; 1 the simulation failed (an explosion or inverted elements: the
message says at which step; every frame and energy up to the last good step is written, and
no output file ever holds a NaN); 2 bad input or parameters (one line on stderr naming the
file and key path, a traceback only with ``--debug``; nothing written); 130 interrupted.

The run loop itself is :mod:`fem3d.app.run` (:func:`~fem3d.app.run.run_scene` is the same code
path for Python callers, e.g. sweeps: a scene in, a :class:`~fem3d.app.run.RunSummary` out);
this module parses arguments and dispatches the sub-commands.

Adding a sub-command: append ``"module:function"`` to :data:`SUBCOMMANDS`; ``function``
receives the ``argparse`` sub-parser collection, adds its parser and sets ``func`` (a
callable ``args -> int``) with ``set_defaults``. Modules are imported when the parser is
built; one that fails to import (a missing optional dependency) is left out with a note in
``fem3d --help``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import sys
import tomllib
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from fem3d.app.profile import STAGES_LOGGER, profiled
from fem3d.app.run import resume_inputs, resume_run, run_scene
from fem3d.errors import InputError, ParameterError, SimulationError
from fem3d.io import rundir
from fem3d.io.files import atomic_write
from fem3d.io.frames import FRAME_FORMATS, frame_format_names
from fem3d.parallel.comm import abort, launched_rank, launched_ranks, leave_together, mpi_started
from fem3d.parallel.run import run_distributed
from fem3d.scene import apply_overrides, load_scene, material_names, scene_schema
from fem3d.solve.linear.registry import linear_solver_names
from fem3d.solve.schemes.registry import scheme_names

__all__ = ["main", "build_parser", "scene_from_args", "parse_assignments", "SUBCOMMANDS",
           "RUN_FLAGS"]

_stages = logging.getLogger(STAGES_LOGGER)  # stage marks (fem3d.app.profile)

#: Sub-command registrars, ``"module:function"``, in ``--help`` order.
SUBCOMMANDS: list[str] = [
    "fem3d.app.cli:add_run_subcommand",
    "fem3d.app.viewer.app:add_view_subcommand",
    "fem3d.app.cli:add_resume_subcommand",
    "fem3d.app.cli:add_schema_subcommand",
    "fem3d.app.surfaces:add_tetrahedralize_subcommand",
    "fem3d.app.sweep.cli:add_sweep_subcommand",
    "fem3d.app.fit.cli:add_fit_subcommand",
]

#: ``fem3d run`` flags that set one scene field: (flag, dest, key path; ``{body}`` = every body).
RUN_FLAGS: tuple[tuple[str, str, str], ...] = (
    ("--integrator", "integrator", "simulation.integrator"),
    ("--steps", "steps", "simulation.steps"),
    ("--duration", "duration", "simulation.duration"),
    ("--dt", "dt", "simulation.dt"),
    ("--newton-iterations", "newton_iterations", "simulation.newton.max_iterations"),
    ("--hessian", "hessian", "simulation.newton.hessian"),
    ("--newton-solver", "newton_solver", "simulation.newton.solver"),
    ("--linear-solver", "solver", "simulation.linear_solver"),
    ("--material", "material", "bodies[{body}].material.model"),
    ("--E", "E", "bodies[{body}].material.E"),
    ("--nu", "nu", "bodies[{body}].material.nu"),
    ("--rho", "rho", "bodies[{body}].material.density"),
    ("--skin", "skin", "bodies[0].skin"),
    ("--format", "format", "output.format"),
    ("--frame-every", "frame_every", "output.every"),
    ("--pick-radius", "pick_radius", "interaction.pick_radius"),
)


def _material_help() -> str:
    try:
        return ", ".join(material_names())
    except Exception:  # pragma: no cover - kernels missing
        return "see fem3d schema"


def add_run_subcommand(subparsers) -> argparse.ArgumentParser:
    """Register ``fem3d run``."""
    p = subparsers.add_parser(
        "run",
        help="run a scene headless and write frames, energies and a preview",
        description="Run a scene (a name of data/scenes, a .toml scene file, or a mesh file) "
        "with its scripted pulls and write the display mesh per frame (frames/*.vtu + "
        "frames.pvd, frames/*.obj, or frames.usdc), energy.csv, energy.png and preview.gif "
        "into --out. Flags override the scene's fields; --set KEY=VALUE any field. Ctrl-C "
        "saves a checkpoint (exit 130); continue with `fem3d resume DIR`.",
    )
    p.add_argument("scene", help="bunny | arma | other name in data/scenes | FILE.toml | a tet "
                   "mesh (.mesh, .node/.ele, .msh, ...) or closed surface (.obj, .stl, ...)")
    p.add_argument("--integrator", default=None, metavar="NAME",
                   help=f"{' | '.join(scheme_names())} (simulation.integrator; "
                   "docs/integrators.md)")
    p.add_argument("--steps", type=int, default=None,
                   help="number of time steps (simulation.steps; default the scene's, else 100)")
    p.add_argument("--duration", type=float, default=None,
                   help="simulated seconds instead of --steps (simulation.duration)")
    p.add_argument("--dt", type=float, default=None, help="time step (simulation.dt)")
    p.add_argument("--out", default=None, help="output folder (default out/<scene>)")
    p.add_argument("--kernels", choices=("numpy", "c"), default=None,
                   help="kernel back end (default: C if built, else NumPy)")
    p.add_argument("--frame-every", type=int, default=None, metavar="K",
                   help="write every K-th step (output.every)")
    p.add_argument("--checkpoint-every", type=int, default=0, metavar="N",
                   help="save DIR/checkpoint.npz every N steps and at the end (default 0: only "
                   "on SIGINT/SIGTERM)")
    p.add_argument("--format", choices=frame_format_names(), default=None,
                   help="frame format (output.format): " + "; ".join(
                       f"{f.name}: {f.summary}" for f in FRAME_FORMATS.values()))
    p.add_argument("--skin", default=None, help="display mesh of the first body (bodies[0].skin)")
    p.add_argument("--newton-iterations", type=int, default=None,
                   help="Newton iterations per backward-Euler step "
                   "(simulation.newton.max_iterations)")
    p.add_argument("--hessian", choices=("exact", "psd"), default=None,
                   help="Newton Hessian of backward Euler: exact or per-element PSD-projected "
                   "(simulation.newton.hessian)")
    p.add_argument("--newton-solver", choices=("direct", "reuse"), default=None,
                   help="Newton linear solves: refactorize each iteration, or keep a "
                   "factorization as the CG preconditioner (simulation.newton.solver)")
    p.add_argument("--linear-solver", "--solver", dest="solver", default=None,
                   help=f"linear solver: {', '.join(linear_solver_names())} "
                   "(simulation.linear_solver)")
    p.add_argument("--material", default=None, metavar="NAME",
                   help=f"material model of every body ({_material_help()})")
    p.add_argument("--E", type=float, default=None, help="Young's modulus of every body")
    p.add_argument("--nu", type=float, default=None, help="Poisson's ratio of every body")
    p.add_argument("--rho", type=float, default=None, help="density of every body")
    p.add_argument("--pick-radius", type=float, default=None, metavar="R",
                   help="viewer picking radius (interaction.pick_radius)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="set",
                   help="set any scene field, VALUE in TOML syntax: --set "
                   "bodies[0].material.E=1e5 --set 'simulation.gravity=[0,-9.81,0]'")
    p.add_argument("--no-preview", action="store_true", help="skip preview.gif")
    p.add_argument("--no-pull", action="store_true", help="no scripted pulls (pulls = [])")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--profile", action="store_true",
                   help="print the wall time, CPU time and memory of each stage of the start "
                   "(reading, validation, model, pattern, solver analysis, first step)")
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
        description="Continue a `fem3d run` from the checkpoint in its output folder (which "
        "holds the whole scene), writing into the same folder (bit for bit what an "
        "uninterrupted run gives).",
    )
    p.add_argument("dir", help="output folder of the run (holds checkpoint.npz)")
    p.add_argument("--steps", type=int, default=None,
                   help="total step count to reach (default: the run's)")
    p.add_argument("--checkpoint-every", type=int, default=None, metavar="N",
                   help="checkpoint interval (default: the run's)")
    p.add_argument("--no-preview", action="store_true", help="skip preview.gif")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks"
    )
    p.set_defaults(func=_resume_command)
    return p


def add_schema_subcommand(subparsers) -> argparse.ArgumentParser:
    """Register ``fem3d schema``."""
    p = subparsers.add_parser(
        "schema", help="print the JSON Schema of scene files",
        description="Print the JSON Schema of a scene file (for editors: completion and "
        "checking of data/scenes/*.toml).",
    )
    p.add_argument("--out", default=None, help="write it to this file instead of stdout")
    p.set_defaults(func=_schema_command)
    return p


def build_parser() -> argparse.ArgumentParser:
    """The ``fem3d`` parser with every registered sub-command."""
    parser = argparse.ArgumentParser(
        prog="fem3d",
        description="Linear tetrahedral FEM elastodynamics (SymPy-generated kernels).",
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


def _parse_value(text: str) -> Any:
    """A ``--set`` value: TOML syntax (``1e5``, ``"stvk"``, ``[0, -9.81, 0]``, ``{...}``), or
    the bare text as a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def parse_assignments(items: list[str], flag: str = "--set") -> list[tuple[str, Any]]:
    """``KEY=VALUE`` items (``--set``) as ``(key, value)`` scene overrides in their order,
    each value as :func:`_parse_value` reads it.

    Raises
    ------
    InputError
        ``FLAG 'item': expected KEY=VALUE, ...`` for an item without ``=`` or a key.
    """
    pairs = []
    for item in items:
        k, sep, v = item.partition("=")
        if not sep or not k.strip():
            raise InputError(f"{flag} {item!r}: expected KEY=VALUE, e.g. simulation.dt=0.005")
        pairs.append((k.strip(), _parse_value(v.strip())))
    return pairs


def scene_from_args(args: argparse.Namespace):
    """The scene of ``fem3d run`` arguments: loaded, then every flag applied as an override.

    Raises
    ------
    InputError
        ``FILE: key.path: ...`` from the scene, or ``--flag: key.path: ...`` from a flag.
    """
    scene = load_scene(args.scene)
    for flag, dest, key in RUN_FLAGS:
        value = getattr(args, dest, None)
        if value is None:
            continue
        if dest == "skin":
            value = str(Path(value).resolve())
        keys = ([key.format(body=i) for i in range(len(scene.bodies))] if "{body}" in key
                else [key])
        scene = apply_overrides(scene, {k: value for k in keys}, source=flag)
    for key, value in parse_assignments(args.set):
        scene = apply_overrides(scene, {key: value}, source="--set")
    if args.no_pull:
        scene = apply_overrides(scene, {"pulls": []}, source="--no-pull")
    return scene


def _run_command(args: argparse.Namespace) -> int:
    if args.steps is not None and args.steps < 0:
        raise ParameterError(f"--steps must be >= 0, got {args.steps}")
    if args.checkpoint_every < 0:
        raise ParameterError(f"--checkpoint-every must be >= 0, got {args.checkpoint_every}")
    if args.out:  # before reading the inputs: one of them may be an output of this run
        named = {"scene file" if str(args.scene).endswith(".toml") else "mesh": args.scene,
                 "skin": getattr(args, "skin", None)}
        rundir.check_overwrite(args.out, {k: v for k, v in named.items()
                                          if v is not None and Path(v).exists()})
    with profiled(getattr(args, "profile", False)):
        scene = scene_from_args(args)
        _stages.debug("scene file")
        out = Path(args.out) if args.out else Path("out") / scene.name
        if launched_ranks() > 1:  # mpiexec -n N fem3d run: one simulation on N ranks
            return run_distributed(scene, out, quiet=args.quiet, backend=args.kernels,
                                   checkpoint_every=args.checkpoint_every)
        summary = run_scene(scene, out, quiet=args.quiet,
                            checkpoint_every=args.checkpoint_every,
                            preview=not args.no_preview, backend=args.kernels,
                            debug=getattr(args, "debug", False))
    return summary.exit_status


def _resume_command(args: argparse.Namespace) -> int:
    if launched_ranks() > 1:  # mpiexec -n N fem3d resume: continued on N ranks
        out, ckpt, scene, settings = resume_inputs(args)
        return run_distributed(scene, out, quiet=args.quiet, ckpt=ckpt, settings=settings)
    return resume_run(args)


def _schema_command(args: argparse.Namespace) -> int:
    text = json.dumps(scene_schema(), indent=2) + "\n"
    if args.out:
        atomic_write(Path(args.out), text)
    else:
        sys.stdout.write(text)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``fem3d`` script; returns the exit status.

    ``InputError`` or ``OSError`` (e.g. an unwritable output folder) -> one line on stderr,
    status 2; ``SimulationError`` -> message, status 1. Under ``mpiexec``, once MPI has
    started, an ``OSError`` or an unexpected exception (which one rank may meet alone)
    stops every rank (``MPI_Abort``: status 2, or 1 with the traceback).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help(sys.stderr)
        return 2
    ranks = launched_ranks()
    # under mpiexec every rank meets the same error: rank 0 says it
    say = print if launched_rank() == 0 else (lambda *a, **k: None)
    status = _status_of(args, ranks, say)
    if status in (1, 2):
        leave_together()  # rank 0's line first: mpiexec ends every rank once one exits non-zero
    return status


def _status_of(args: argparse.Namespace, ranks: int, say: Callable[..., None]) -> int:
    """Run ``args``' command; its exit status, an error said in one line (by ``say``)."""
    try:
        if ranks > 1 and args.command not in ("run", "resume", "schema"):
            raise InputError(f"fem3d {args.command} runs in one process, not under mpiexec "
                             f"-n {ranks} (only fem3d run and resume are distributed: "
                             "docs/parallel.md)")
        with rundir.warnings_as_lines(f"fem3d {args.command}"):
            return int(args.func(args) or 0)
    except InputError as exc:
        if args.debug:
            traceback.print_exc()
        say(f"fem3d {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except SimulationError as exc:
        if args.debug:
            traceback.print_exc()
        say(f"fem3d {args.command}: simulation failed: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:  # e.g. an output folder that cannot be written
        if args.debug:
            traceback.print_exc()
        line = f"fem3d {args.command}: error: {exc}"
        if ranks > 1 and mpi_started():  # maybe this rank's alone: it says so, all stop
            print(line, file=sys.stderr)
            abort(2)
        say(line, file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"fem3d {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception:
        if ranks > 1 and mpi_started():  # a bug on one rank: the others would wait for it
            traceback.print_exc()
            abort(1)
        raise


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

