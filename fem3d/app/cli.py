"""Command line: ``fem3d run`` (headless main job), ``fem3d resume``, ``fem3d schema`` and the
sub-commands other modules register.

``fem3d run NAME|FILE.toml|MESH [--steps N] [--dt DT] [--integrator linear|implicit]
[--material NAME] [--E E] [--nu NU] [--rho RHO] [--format vtu|obj|usd] [--frame-every K]
[--set KEY=VALUE ...] [--out DIR] [--kernels numpy|c] [--checkpoint-every N] [--debug]`` runs
a scene (:mod:`fem3d.scene.spec`: a name of ``data/scenes``, a scene file, or a one-body scene
around a mesh file) with its scripted pulls. Every flag but ``--out``, ``--kernels``,
``--checkpoint-every``, ``--no-preview`` and ``--quiet`` overrides one field of the scene
(:data:`RUN_FLAGS`; ``--set`` any field by its key path). It writes into ``DIR``:

* ``frames/frame_00000.vtu`` ... and ``frames.pvd`` - the display mesh per frame (open
  ``frames.pvd`` in ParaView), ``frames/*.obj``, or one ``frames.usdc`` (``output.format``);
* ``energy.csv`` (``t,kinetic,potential,total``) and ``energy.png``;
* ``preview.gif`` - a shaded offscreen animation;
* ``checkpoint.npz`` - with ``--checkpoint-every N`` every N steps and at the end, and always
  on SIGINT / SIGTERM (see :mod:`fem3d.io.checkpoint`). It holds the whole scene.

``fem3d resume DIR [--steps N]`` continues a run from ``DIR/checkpoint.npz`` up to step ``N``
(default: the run's) with the saved scene, in the same folder: frames keep their numbering,
``energy.csv`` keeps the earlier rows, ``frames.pvd`` lists every frame. The result is bit
for bit the one of an uninterrupted run (same kernels and solver back end).

``fem3d schema`` prints the JSON Schema of scene files.

SIGINT (Ctrl-C) or SIGTERM during the steps: the current step is finished (a second signal
abandons it; the state stays at the last finished step), a checkpoint is saved, energy.csv and
the frames are complete up to that step, one line says how to continue, exit status 130.

Exit status: 0 success; 1 the simulation failed (an explosion or inverted elements: the
message says at which step; every frame and energy up to the last good step is written, and
no output file ever holds a NaN); 2 bad input or parameters (one line on stderr naming the
file and key path, a traceback only with ``--debug``; nothing written); 130 interrupted.

:func:`run_scene` is the same code path for Python callers (sweeps): a scene in, a
:class:`RunSummary` out.

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

from fem3d.errors import InputError, ParameterError, SimulationError
from fem3d.io import rundir

__all__ = ["main", "build_parser", "run_scene", "resume_run", "scene_from_args", "RunSummary",
           "SUBCOMMANDS", "RUN_FLAGS"]

#: Sub-command registrars, ``"module:function"``, in ``--help`` order.
SUBCOMMANDS: list[str] = [
    "fem3d.app.cli:add_run_subcommand",
    "fem3d.app.viewer.viewer:add_view_subcommand",
    "fem3d.app.cli:add_resume_subcommand",
    "fem3d.app.cli:add_schema_subcommand",
    "fem3d.app.sweep.sweep:add_sweep_subcommand",
]

#: Frames kept in memory for the GIF preview (evenly spaced).
PREVIEW_FRAMES = 60

#: Exit status of an interrupted run (128 + SIGINT).
EXIT_INTERRUPTED = 130


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
        from fem3d.scene.spec import material_names

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
    p.add_argument("--integrator", choices=("linear", "implicit"), default=None,
                   help="linearly-implicit or backward Euler (simulation.integrator)")
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
    p.add_argument("--format", choices=("vtu", "obj", "usd"), default=None,
                   help="frame format (output.format)")
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
                   help="sparse solver back end: auto, cholmod, pardiso, superlu, amg "
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
    import tomllib

    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def scene_from_args(args: argparse.Namespace):
    """The scene of ``fem3d run`` arguments: loaded, then every flag applied as an override.

    Raises
    ------
    InputError
        ``FILE: key.path: ...`` from the scene, or ``--flag: key.path: ...`` from a flag.
    """
    from fem3d.scene.load import apply_overrides, load_scene

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
    for item in args.set:
        k, sep, v = item.partition("=")
        if not sep or not k.strip():
            raise InputError(f"--set {item!r}: expected KEY=VALUE, e.g. simulation.dt=0.005")
        scene = apply_overrides(scene, {k.strip(): _parse_value(v.strip())}, source="--set")
    if args.no_pull:
        scene = apply_overrides(scene, {"pulls": []}, source="--no-pull")
    return scene


def _check_writable(out: Path) -> None:
    """Refuse an output folder that cannot be created or written, before any setup (writes
    nothing)."""
    import os

    p = out
    while not p.exists():
        if p.parent == p:
            break
        p = p.parent
    if p.exists() and (not p.is_dir() or not os.access(p, os.W_OK | os.X_OK)):
        what = "not a folder" if not p.is_dir() else "not writable"
        raise InputError(f"output folder: {p} is {what}", path=out)


@dataclasses.dataclass(frozen=True)
class RunSummary:
    """What :func:`run_scene` did.

    Attributes
    ----------
    status : {"ok", "failed", "interrupted"}
    message : str
        Empty when ok; the failure or interruption otherwise.
    steps : int
        Index of the last good step.
    wall_seconds : float
        Wall time of the stepping loop.
    newton_iterations : int
        Total over the steps taken here.
    max_displacement : float
        Largest ``|q - X|`` of a simulation-mesh vertex over the steps taken here.
    kinetic, potential, total : float
        Energies of the last good state.
    max_total : float
        Largest total energy logged (over the whole run, resumed parts included).
    out : str
        Output folder.
    """

    status: str
    message: str
    steps: int
    wall_seconds: float
    newton_iterations: int
    max_displacement: float
    kinetic: float
    potential: float
    total: float
    max_total: float
    out: str = ""

    @property
    def exit_status(self) -> int:
        """0 ok, 1 failed, 130 interrupted."""
        return {"ok": 0, "failed": 1}.get(self.status, EXIT_INTERRUPTED)


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


def _drive(
    scene,
    sim,
    out: Path,
    settings: dict[str, Any],
    *,
    quiet: bool,
    debug: bool,
    ckpt=None,
    command: str = "run",
) -> RunSummary:
    """Step ``sim`` up to ``scene.n_steps``, writing outputs (and checkpoints) to ``out``."""
    import numpy as np
    from tqdm import tqdm

    from fem3d.io.checkpoint import CHECKPOINT_NAME, RunCheckpoint, mesh_digest, save_run_checkpoint
    from fem3d.io.energy import EnergyLog
    from fem3d.io.frames import make_frame_writer
    from fem3d.io.preview import plot_energy, render_preview

    steps, frame_every = scene.n_steps, scene.output.every
    every = settings["checkpoint_every"]
    preview_on = bool(settings["preview"])
    digest = mesh_digest(sim.model.X, sim.model.T)
    faces = sim.display_faces
    writer = make_frame_writer(out, faces, scene.output.format,
                               bodies=_display_bodies(scene, sim), dt=sim.dt)
    n_frames = steps // frame_every + 1
    preview_stride = max(1, math.ceil(n_frames / PREVIEW_FRAMES))
    preview: list[np.ndarray] = []
    frame_count = 0
    if ckpt is None:
        log = EnergyLog(out / "energy.csv")
    else:  # resume: the saved energy rows and frame list; frames after the checkpoint go
        log = EnergyLog.from_array(ckpt.energy, out / "energy.csv")
        writer.restore(ckpt.frames, ckpt.step)
        frame_count = ckpt.frame_count
        log.write()
        if preview_on:
            for i, (_, V) in enumerate(writer.read_frames()):
                if i % preview_stride == 0:
                    preview.append(V)

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
        writer.flush()
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
        f"material {sim.model.material}, dt {sim.dt:g}, kernels {sim.model.mat.backend}, "
        f"steps {start} -> {steps} -> {out}",
        file=sys.stderr,
    )
    status, message = "ok", ""
    step_seconds: list[float] = []
    iterations: list[int] = []
    max_disp = 0.0
    X0 = sim.model.X
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
                max_disp = max(max_disp, float(np.abs(sim.q - X0).max()))
                bar.update(1)
                bar.set_postfix_str(f"t={info.t:.2f} E={info.total:.3g}", refresh=False)
                if every and sim.step_index % every == 0:
                    save_checkpoint()
                elif sim.step_index % 50 == 0:
                    log.write()
            if intr.signum is not None:  # stop before any slow output
                bar.close()
                path = save_checkpoint()
                message = (f"interrupted by {intr.name} at step {sim.step_index} "
                           f"(t = {sim.t:.4g}); checkpoint {path}; continue with: "
                           f"fem3d resume {out}")
                print(f"fem3d {command}: {message}", file=sys.stderr)
                return _summary(sim, "interrupted", message, time.perf_counter() - t_start,
                                iterations, max_disp, log, out)
    except SimulationError as exc:
        status, message = "failed", str(exc)
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
        writer.flush()
    wall = time.perf_counter() - t_start
    if status == "ok" and every:
        save_checkpoint()
    if len(log):
        plot_energy(log, out / "energy.png", title=f"{scene.name} ({sim.integrator})")
    if preview_on and preview:
        cam = scene.output.preview
        render_preview(preview, faces, out / "preview.gif", elev=cam.elev,
                       azim=cam.azim, view_bounds=cam.bounds)
    if step_seconds:
        print(
            f"fem3d {command}: {len(step_seconds)} steps in {wall:.2f} s; "
            f"{1e3 * float(np.mean(step_seconds)):.2f} ms/step "
            f"({float(np.mean(iterations)):.2f} Newton iterations/step); "
            f"{frame_count} frames in {out}",
            file=sys.stderr,
        )
    return _summary(sim, status, message, wall, iterations, max_disp, log, out)


def _display_bodies(scene, sim) -> list[tuple[str, slice, slice]]:
    """``(name, display vertex range, face range)`` of each body (USD prims)."""
    a = sim.assembled
    if a.skin_V is None and len(scene.bodies) > 1:
        # one boundary over the concatenated mesh: split its faces by body
        import numpy as np

        F = sim.surface_faces
        out = []
        for b, (vs, _) in zip(scene.bodies, a.skin_bodies, strict=True):
            rows = np.flatnonzero((F[:, 0] >= vs.start) & (F[:, 0] < vs.stop))
            out.append((b.label, vs, slice(int(rows[0]), int(rows[-1]) + 1) if rows.size
                        else slice(0, 0)))
        return out
    if a.skin_V is None:
        return [(scene.bodies[0].label, slice(0, a.X.shape[0]),
                 slice(0, sim.surface_faces.shape[0]))]
    return [(b.label, vs, fs) for b, (vs, fs) in zip(scene.bodies, a.skin_bodies, strict=True)]


def _summary(sim, status, message, wall, iterations, max_disp, log, out) -> RunSummary:
    e = sim.energies()
    rows = log.as_array()
    return RunSummary(
        status=status, message=message, steps=int(sim.step_index), wall_seconds=float(wall),
        newton_iterations=int(sum(iterations)), max_displacement=float(max_disp),
        kinetic=float(e["kinetic"]), potential=float(e["potential"]), total=float(e["total"]),
        max_total=float(rows[:, 3].max()) if rows.size else float(e["total"]), out=str(out),
    )


def _resolve_kernels(name: str | None) -> str:
    try:
        from fem3d.kernels.backend import resolve_backend

        return resolve_backend(name)
    except (ImportError, ValueError) as exc:
        raise InputError(f"--kernels {name}: {exc}") from None


def run_scene(
    scene,
    out: Path,
    *,
    quiet: bool = True,
    checkpoint_every: int = 0,
    preview: bool = False,
    backend: str | None = None,
    debug: bool = False,
) -> RunSummary:
    """Run ``scene`` headless into ``out``: the code path of ``fem3d run``.

    Writes the frames (``scene.output``), ``energy.csv``, ``energy.png``, ``preview.gif``
    (``preview``) and ``checkpoint.npz`` (every ``checkpoint_every`` steps, at the end, and
    on SIGINT/SIGTERM).

    Parameters
    ----------
    scene : fem3d.scene.spec.Scene
    out : Path
        Output folder (created; nothing is written before the scene is set up).
    quiet : bool
        No progress bar.
    checkpoint_every : int
        0: checkpoints only on a signal.
    preview : bool
        Render ``preview.gif``.
    backend : {None, "numpy", "c"}
        Kernel back end.
    debug : bool
        Print a traceback when the simulation fails.

    Returns
    -------
    RunSummary

    Raises
    ------
    InputError
        A bad scene (``FILE: key.path: ...``) or output folder; nothing is written.
    """
    from fem3d.simulation import Simulation

    if checkpoint_every < 0:
        raise ParameterError(f"--checkpoint-every must be >= 0, got {checkpoint_every}")
    out = Path(out)
    _check_writable(out)
    inputs = _scene_inputs(scene)
    rundir.check_overwrite(out, inputs)  # before any expensive setup
    backend = _resolve_kernels(backend)
    sim = Simulation(scene, backend=backend, scripted=True)
    settings = {
        "scene": scene.to_dict(), "kernels": backend, "solver": sim.system.linear_backend,
        "checkpoint_every": int(checkpoint_every), "preview": bool(preview),
    }
    out.mkdir(parents=True, exist_ok=True)
    with rundir.claim(out, inputs=inputs):  # lock; refuse overwriting inputs; clean temps
        return _drive(scene, sim, out, settings, quiet=quiet, debug=debug)


def _scene_inputs(scene) -> dict[str, Any]:
    """Every file a run of ``scene`` reads, by role (for the overwrite check)."""
    inputs: dict[str, Any] = dict(scene.files())
    if scene.source:
        inputs["scene file"] = scene.source
    return inputs


def resume_run(args: argparse.Namespace) -> int:
    """Run ``fem3d resume DIR``: continue from ``DIR/checkpoint.npz``; returns the exit status.

    Raises
    ------
    InputError
        No or a bad checkpoint, a mesh changed since, or a bad ``--steps``.
    """
    from fem3d.io.checkpoint import CHECKPOINT_NAME, load_run_checkpoint, mesh_digest
    from fem3d.scene.load import apply_overrides
    from fem3d.scene.spec import Scene
    from fem3d.simulation import Simulation

    out = Path(args.dir)
    ckpt = load_run_checkpoint(out / CHECKPOINT_NAME)
    settings = dict(ckpt.settings)
    where = str(out / CHECKPOINT_NAME)
    if not isinstance(settings.get("scene"), dict):
        raise InputError("checkpoint holds no scene (made by an older fem3d)", path=where)
    scene = Scene.from_dict(settings["scene"], source=where)
    if scene.simulation.linear_solver == "auto":  # the back end the run actually used
        scene = apply_overrides(scene, {"simulation.linear_solver": settings["solver"]},
                                source=where)
    if args.steps is not None:
        if args.steps < ckpt.step:
            raise ParameterError(
                f"--steps {args.steps} is below the checkpoint's step {ckpt.step}"
            )
        scene = apply_overrides(scene, {"simulation.steps": int(args.steps)}, source="--steps")
        settings["scene"] = scene.to_dict()
    if args.checkpoint_every is not None:
        if args.checkpoint_every < 0:
            raise ParameterError(f"--checkpoint-every must be >= 0, got {args.checkpoint_every}")
        settings["checkpoint_every"] = int(args.checkpoint_every)
    if args.no_preview:
        settings["preview"] = False
    settings["kernels"] = _resolve_kernels(settings["kernels"])
    sim = Simulation(scene, backend=settings["kernels"], scripted=True)
    if mesh_digest(sim.model.X, sim.model.T) != ckpt.mesh_digest:
        raise InputError("the mesh differs from the one the checkpoint was made with",
                         path=sim.assembled.mesh_paths[0])
    try:
        sim.restore(ckpt.snapshot)
    except (ParameterError, KeyError) as exc:
        raise InputError(f"bad checkpoint state: {exc}", path=out / CHECKPOINT_NAME) from None
    ck = out / CHECKPOINT_NAME
    inputs = {**_scene_inputs(scene), "checkpoint": ck}
    with rundir.claim(out, inputs=inputs, allow=(ck,)):
        summary = _drive(scene, sim, out, settings, quiet=args.quiet,
                         debug=getattr(args, "debug", False), ckpt=ckpt, command="resume")
    return summary.exit_status


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
    scene = scene_from_args(args)
    out = Path(args.out) if args.out else Path("out") / scene.name
    summary = run_scene(scene, out, quiet=args.quiet, checkpoint_every=args.checkpoint_every,
                        preview=not args.no_preview, backend=args.kernels,
                        debug=getattr(args, "debug", False))
    return summary.exit_status


def _resume_command(args: argparse.Namespace) -> int:
    return resume_run(args)


def _schema_command(args: argparse.Namespace) -> int:
    import json

    from fem3d.io.files import atomic_write
    from fem3d.scene.spec import scene_schema

    text = json.dumps(scene_schema(), indent=2) + "\n"
    if args.out:
        atomic_write(Path(args.out), text)
    else:
        sys.stdout.write(text)
    return 0


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
