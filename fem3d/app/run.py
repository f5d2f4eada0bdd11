"""The headless run loop: :func:`run_scene` (``fem3d run``), :func:`resume_run`
(``fem3d resume``) and the :class:`RunLoop` that steps a simulation and writes its outputs.

:func:`run_scene` is the same code path for Python callers (sweeps, the gallery): a scene
in, a :class:`RunSummary` out. It writes into its output folder:

* the display mesh per frame (``scene.output``: ``frames/*.vtu`` + ``frames.pvd``,
  ``frames/*.obj``, or one ``frames.usdc``); the VTU frames carry the von Mises stress, the
  Cauchy stress and the principal stretches as point data (vertex averages of the elements');
* with ``output.volume``, the volume mesh per frame (``volume/*.vtu`` + ``volume.pvd``: the
  element's own cells, per-element stress as cell data and its vertex averages);
* ``energy.csv`` (``t,kinetic,potential,total``) and ``energy.png``;
* ``reactions.csv`` - the force each pin exerts per step (:mod:`fem3d.io.reactions`);
* ``preview.gif`` - a shaded offscreen animation;
* ``checkpoint.npz`` - every N steps and at the end, and always on SIGINT / SIGTERM (see
  :mod:`fem3d.io.checkpoint`). It holds the whole scene.

SIGINT (Ctrl-C) or SIGTERM during the steps: the current step is finished (a second signal
abandons it; the state stays at the last finished step), a checkpoint is saved, energy.csv and
the frames are complete up to that step, one line says how to continue, exit status 130.

The argument parsing of ``fem3d run`` / ``fem3d resume`` is in :mod:`fem3d.app.cli`.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import os
import sys
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from fem3d.app.surfaces import record_tet_meshes
from fem3d.errors import InputError, ParameterError, SimulationError
from fem3d.io import rundir
from fem3d.io.checkpoint import (
    CHECKPOINT_NAME,
    RunCheckpoint,
    load_run_checkpoint,
    mesh_digest,
    restore_run_checkpoint,
    save_run_checkpoint,
)
from fem3d.io.energy import EnergyLog
from fem3d.io.framequeue import BackgroundWriter
from fem3d.io.frames import frame_format, make_frame_writer
from fem3d.io.frames.volume import VolumeVtuWriter
from fem3d.io.interrupts import EXIT_INTERRUPTED, Interrupts, interrupted_message
from fem3d.io.reactions import ReactionLog
from fem3d.kernels.dispatch import resolve_backend
from fem3d.physics.stress import element_fields, element_stress, vertex_fields
from fem3d.scene import Scene, apply_overrides
from fem3d.simulation import Simulation

__all__ = ["run_scene", "resume_run", "resume_inputs", "RunSummary", "RunLoop", "PREVIEW_FRAMES",
           "EXIT_INTERRUPTED"]

#: Frames kept in memory for the GIF preview (evenly spaced).
PREVIEW_FRAMES = 60

#: Stage marks (``fem3d run --profile``, :mod:`fem3d.app.profile`).
_stages = logging.getLogger("fem3d.stages")


def _check_writable(out: Path) -> None:
    """Refuse an output folder that cannot be created or written, before any setup (writes
    nothing)."""
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


class RunLoop:
    """Step ``sim`` up to ``scene.n_steps``, writing outputs (and checkpoints) to ``out``.

    Construction sets up the frame writer and the energy log (on a resume: restores the
    saved energy rows and frame list); :meth:`run` steps and writes.

    Parameters
    ----------
    scene : fem3d.scene.spec.Scene
    sim : fem3d.simulation.Simulation
    out : Path
        Output folder (exists and is claimed by the caller).
    settings : dict
        JSON-able options of the run, saved in its checkpoints (``checkpoint_every``,
        ``preview``, ...).
    quiet : bool
        No progress bar.
    debug : bool
        Print a traceback when the simulation fails.
    ckpt : fem3d.io.checkpoint.RunCheckpoint, optional
        The checkpoint a resume continues from.
    command : str
        ``"run"`` or ``"resume"`` (in the messages).
    """

    def __init__(
        self,
        scene,
        sim,
        out: Path,
        settings: dict[str, Any],
        *,
        quiet: bool,
        debug: bool,
        ckpt=None,
        command: str = "run",
    ) -> None:
        self.scene, self.sim, self.out, self.settings = scene, sim, out, settings
        self.quiet, self.debug, self.ckpt, self.command = quiet, debug, ckpt, command
        self.steps, self.frame_every = scene.n_steps, scene.output.every
        self.every = settings["checkpoint_every"]
        self.preview_on = bool(settings["preview"])
        self.digest = mesh_digest(sim.model.X, model_cells(sim.model))
        self.faces = sim.display_faces
        self.obstacles = sim.obstacle_meshes()
        # frames are written by a thread of their own (fem3d.io.framequeue)
        self.writer = BackgroundWriter(make_frame_writer(
            out, self.faces, scene.output.format, bodies=_display_bodies(scene, sim),
            dt=sim.dt, obstacles=self.obstacles))
        self.volume = (BackgroundWriter(VolumeVtuWriter(out, model_cells(sim.model),
                                                        model_cell_types(sim.model)))
                       if scene.output.volume else None)
        n_frames = self.steps // self.frame_every + 1
        self.preview_stride = max(1, math.ceil(n_frames / PREVIEW_FRAMES))
        self.preview: list[np.ndarray] = []
        self.preview_times: list[float] = []
        self.frame_count = 0
        self.reactions = ReactionLog(out / "reactions.csv", [k for k, _ in sim.pin_groups])
        if ckpt is not None:
            self.reactions.keep_until(ckpt.step)
        if ckpt is None:
            self.log = EnergyLog(out / "energy.csv")
        else:  # resume: the saved energy rows and frame list; frames after the checkpoint go
            self.log = EnergyLog.from_array(ckpt.energy, out / "energy.csv")
            self.writer.restore(ckpt.frames, ckpt.step)
            if self.volume is not None:
                self.volume.restore(ckpt.frames, ckpt.step)
            self.frame_count = ckpt.frame_count
            self.log.write()
            if self.preview_on:
                kept = list(self.writer.read_frames(self.preview_stride))
                self.preview = [V for _, V in kept]
                self.preview_times = [float(ckpt.frames[s][0]) if s in ckpt.frames else 0.0
                                      for s, _ in kept]
        # per-step statistics of this invocation
        self.step_seconds: list[float] = []
        self.iterations: list[int] = []
        self.max_disp = 0.0

    def record(self, step: int, t: float, kinetic: float, potential: float,
               total: float, pull: float = 0.0) -> None:
        """Log one step's energies and write its frame (every ``output.every`` steps).

        Raises
        ------
        SimulationError
            A non-finite energy (nothing written for this step).
        """
        if not all(math.isfinite(x) for x in (t, kinetic, potential, total)):
            raise SimulationError("non-finite energy (nothing written for this step)", step=step)
        if step % self.frame_every == 0:
            V = self.sim.skin_positions()
            vtu = self.scene.output.format == "vtu"
            volume = self.volume is not None
            stress = element_stress(self.sim.model, self.sim.q) if vtu or volume else None
            fields = self._stress_fields(stress) if vtu else None
            self.writer.write(step, t, V, fields)  # refuses non-finite coordinates
            if volume:
                self.volume.write(step, t, self.sim.q.reshape(-1, 3),
                                  vertex_fields(self.sim.model, self.sim.q, stress),
                                  cell_data=element_fields(stress))
            if self.frame_count % self.preview_stride == 0:
                self.preview.append(V)
                self.preview_times.append(float(t))
            self.frame_count += 1
        self.log.append(t, kinetic, potential, total, gravity=self.sim.gravity_energy(),
                        pull=pull)
        if self.reactions.pins:
            self.reactions.append(step, t, self.sim.reactions())

    def _stress_fields(self, stress) -> dict[str, np.ndarray]:
        """The frame's point data: von Mises stress, Cauchy stress (9 components) and principal
        stretches averaged at the vertices (:func:`fem3d.physics.stress.vertex_fields` of the
        elements' ``stress``), on the display mesh (through the skinning weights when it is a
        skin)."""
        fields = vertex_fields(self.sim.model, self.sim.q, stress)
        W = self.sim.skinning_matrix
        return fields if W is None else {k: np.asarray(W @ v) for k, v in fields.items()}

    def save_checkpoint(self) -> Path:
        """Write ``energy.csv``, flush the frames and save ``checkpoint.npz``; its path."""
        self.log.write()  # energy.csv and the checkpoint agree
        self.reactions.write()
        self.writer.flush()
        if self.volume is not None:
            self.volume.flush()
        return save_run_checkpoint(self.out / CHECKPOINT_NAME, RunCheckpoint(
            settings=self.settings, snapshot=self.sim.snapshot(), energy=self.log.as_array(),
            frames=dict(self.writer.frames), frame_count=self.frame_count,
            mesh_digest=self.digest,
        ))

    def run(self) -> RunSummary:
        """Step to the end (or a signal, or a failure) and write the outputs."""
        try:
            return self._run()
        finally:
            self.writer.abandon()  # the frame threads stop on every way out
            if self.volume is not None:
                self.volume.abandon()

    def _run(self) -> RunSummary:
        sim, out, command = self.sim, self.out, self.command
        if self.ckpt is None:
            e = sim.energies()
            self.record(0, sim.t, e["kinetic"], e["potential"], e["total"], e["pull"])
            _stages.debug("initial state and frame")
        start = sim.step_index
        scene = self.scene
        print(
            f"fem3d {command} {scene.name}: {sim.model.n_vertices} vertices, {sim.model.n_tets} "
            f"tets, {sim.constraints.fixed_vertices.size} fixed, integrator {sim.integrator}, "
            f"material {sim.model.material}, dt {sim.dt:g}, kernels {sim.model.kernel_backend}, "
            f"steps {start} -> {self.steps} -> {out}",
            file=sys.stderr,
        )
        status, message = "ok", ""
        t_start = time.perf_counter()
        bar = tqdm(total=self.steps, initial=start, unit="step",
                   disable=self.quiet or None, file=sys.stderr, dynamic_ncols=True)
        intr = Interrupts()
        try:
            with intr.installed():
                self._step_all(bar, intr)
        except SimulationError as exc:
            status, message = "failed", str(exc)
            bar.close()
            print(
                f"fem3d {command}: simulation failed: {exc}\n"
                f"  output up to the last good step ({sim.step_index}, t = {sim.t:.4g}) is in "
                f"{out}",
                file=sys.stderr,
            )
            if self.debug:
                traceback.print_exc()
        except BaseException:  # a frame that could not be written (disk full), ...
            bar.close()
            self.log.write()
            self.reactions.write()
            raise
        bar.close()
        self.log.write()
        self.reactions.write()
        if intr.signum is not None:  # stop before any slow output
            return self._interrupted(intr, t_start)
        self.writer.close()  # every frame on disk (or the writer's error)
        if self.volume is not None:
            self.volume.close()
        wall = time.perf_counter() - t_start
        self._write_outputs(status, wall)
        return self._summary(status, message, wall)

    def _step_all(self, bar, intr: Interrupts) -> None:
        """Step until ``scene.n_steps`` or a signal; a second signal abandons the step."""
        sim = self.sim
        X0 = sim.model.X
        first = True
        while sim.step_index < self.steps and intr.signum is None:
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
            if first:
                _stages.debug("first step")
                first = False
            self.step_seconds.append(info.seconds)
            self.iterations.append(info.newton_iterations)
            self.record(sim.step_index, info.t, info.kinetic, info.potential, info.total,
                        float(getattr(info, "pull", 0.0)))
            self.max_disp = max(self.max_disp, float(np.abs(sim.q - X0).max()))
            bar.update(1)
            bar.set_postfix_str(f"t={info.t:.2f} E={info.total:.3g}", refresh=False)
            if self.every and sim.step_index % self.every == 0:
                self.save_checkpoint()
            elif sim.step_index % 50 == 0:
                self.log.write()

    def _interrupted(self, intr: Interrupts, t_start: float) -> RunSummary:
        """Save a checkpoint and say how to continue (no slow outputs)."""
        sim, out = self.sim, self.out
        path = self.save_checkpoint()
        message = interrupted_message(intr.name, sim.step_index, sim.t, path, out)
        print(f"fem3d {self.command}: {message}", file=sys.stderr)
        return self._summary("interrupted", message, time.perf_counter() - t_start)

    def _write_outputs(self, status: str, wall: float) -> None:
        """The end of a run: a checkpoint (with ``checkpoint_every``), ``energy.png``,
        ``preview.gif`` and the timing line."""
        # matplotlib is imported when a run ends, not before its first step
        from fem3d.io.preview import plot_energy, render_preview

        sim, out, scene = self.sim, self.out, self.scene
        if status == "ok" and self.every:
            self.save_checkpoint()
        if self.step_seconds:
            print(
                f"fem3d {self.command}: {len(self.step_seconds)} steps in {wall:.2f} s; "
                f"{1e3 * float(np.mean(self.step_seconds)):.2f} ms/step "
                f"({float(np.mean(self.iterations)):.2f} Newton iterations/step); "
                f"{self.frame_count} frames in {out}",
                file=sys.stderr,
            )
        t0 = time.perf_counter()
        if len(self.log):
            plot_energy(self.log, out / "energy.png",
                               title=f"{scene.name} ({sim.integrator})")
        if self.preview_on and self.preview:
            cam = scene.output.preview
            render_preview(self.preview, self.faces, out / "preview.gif",
                           elev=cam.elev, azim=cam.azim, view_bounds=cam.bounds,
                           obstacles=self.obstacles, times=self.preview_times)
            print(f"fem3d {self.command}: wrote {out / 'preview.gif'} ({len(self.preview)} "
                  f"frames) and energy.png in {time.perf_counter() - t0:.1f} s",
                  file=sys.stderr)

    def _summary(self, status: str, message: str, wall: float) -> RunSummary:
        return _summary(self.sim, status, message, wall, self.iterations, self.max_disp,
                        self.log, self.out)


def model_cells(model):
    """The model's elements (:func:`mesh_digest`, volume frames): ``T``, or each element
    block's."""
    return [b.T for b in model.blocks] if model.is_mixed else model.T


def model_cell_types(model):
    """VTK's cell type of :func:`model_cells`: the element's, or each element block's."""
    return [b.element.vtk_type for b in model.blocks] if model.is_mixed else \
        model.element.vtk_type


def _display_bodies(scene, sim) -> list[tuple[str, slice, slice]]:
    """``(name, display vertex range, face range)`` of each body (USD prims)."""
    a = sim.assembled
    if a.skin_V is None and len(scene.bodies) > 1:
        # one boundary over the concatenated mesh: split its faces by body
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
    if checkpoint_every < 0:
        raise ParameterError(f"--checkpoint-every must be >= 0, got {checkpoint_every}")
    out = Path(out)
    _check_writable(out)
    _require_extras(scene)  # before anything is written
    inputs = _scene_inputs(scene)
    rundir.check_overwrite(out, inputs)  # before any expensive setup
    backend = _resolve_kernels(backend)
    sim = Simulation(scene, backend=backend, scripted=True)
    _stages.debug("simulation set-up")
    settings = {
        "scene": scene.to_dict(), "kernels": backend, "solver": sim.system.linear_backend,
        "checkpoint_every": int(checkpoint_every), "preview": bool(preview),
    }
    out.mkdir(parents=True, exist_ok=True)
    with rundir.claim(out, inputs=inputs):  # lock; refuse overwriting inputs; clean temps
        record_tet_meshes(scene, sim.assembled.mesh_paths, out)  # surface bodies' tets, kept
        loop = RunLoop(scene, sim, out, settings, quiet=quiet, debug=debug)
        _stages.debug("output set-up")
        return loop.run()


def _require_extras(scene) -> None:
    """Refuse, in one line naming the extra to install, a scene that needs a missing
    optional dependency (:mod:`fem3d.io.extras`). Surfaces (wildmeshing) are checked where
    they are tetrahedralized, the sparse solver where it is chosen: both before any output."""
    frame_format(scene.output.format).require()


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
    out, ckpt, scene, settings = resume_inputs(args)
    sim = Simulation(scene, backend=settings["kernels"], scripted=True)
    restore_run_checkpoint(sim, ckpt, mesh_digest(sim.model.X, model_cells(sim.model)),
                           sim.assembled.mesh_paths[0], out)
    ck = out / CHECKPOINT_NAME
    inputs = {**_scene_inputs(scene), "checkpoint": ck}
    with rundir.claim(out, inputs=inputs, allow=(ck,)):
        summary = RunLoop(scene, sim, out, settings, quiet=args.quiet,
                          debug=getattr(args, "debug", False), ckpt=ckpt,
                          command="resume").run()
    return summary.exit_status


def resume_inputs(args: argparse.Namespace) -> tuple[Path, RunCheckpoint, Scene, dict]:
    """What ``fem3d resume DIR`` continues (in one process or on MPI ranks): the output
    folder, its checkpoint, the scene (with ``--steps``) and the run's settings (with
    ``--checkpoint-every``, ``--no-preview``, the kernels resolved).

    Raises
    ------
    InputError
        No or a bad checkpoint, or a bad ``--steps`` / ``--checkpoint-every``.
    """
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
    _require_extras(scene)
    settings["kernels"] = _resolve_kernels(settings["kernels"])
    return out, ckpt, scene, settings

