"""``mpiexec -n N fem3d run scene.toml`` and ``mpiexec -n N fem3d resume DIR``: one
simulation on N ranks.

Rank 0 reads the scene's meshes, partitions the tets (:mod:`fem3d.parallel.partition`)
and sends every rank its part (:mod:`fem3d.scene.share`); each rank builds the model of its
tets over its own vertices and steps a :class:`~fem3d.simulation.Simulation` whose system
is its :class:`~fem3d.parallel.system.DistributedSystem` (energies, forces and reactions
summed over the ranks). Outputs in ``out``:

* ``frames/frame_NNNNN_R.vtu``: rank ``R``'s piece, the surface of its tets (a ``rank``
  field per point, and the stress fields of a one-process frame);
  ``frames/frame_NNNNN.pvtu`` gathers the pieces of a frame and ``frames.pvd`` lists the
  frames by time (ParaView opens it; :mod:`~fem3d.parallel.pieces`); a scene with a
  display mesh (a skin) has the one-process frames instead, ``frames/frame_NNNNN.vtu`` of
  the skinned display mesh (rank 0 gathers the positions and skins them);
* ``energy.csv`` and, with pins, ``reactions.csv`` (rank 0), the columns of a one-process
  run; ``energy.png`` (rank 0) at the end;
* ``checkpoint.npz`` (rank 0, with ``--checkpoint-every N``: every N steps and at the end):
  the one-process run checkpoint (:mod:`fem3d.io.checkpoint`) of the whole state, which
  every rank holds, and each tet's rank; ``fem3d resume DIR`` continues it on any number of
  ranks, one included (bit for bit on the rank count that wrote it: that partition is taken
  again, not made anew, so the PETSc numbering and every sum are the same), and
  ``mpiexec -n N fem3d resume`` continues a one-process run's;
* ``state.npz`` (rank 0): the last step's ``q``, ``v``, ``t``, ``step`` (whole model).

Surface and point loads and scripted pulls are each added once: a loaded face by the rank
of the tet it bounds, a point force or a pull spring by the rank that owns its vertex.
SIGINT, SIGTERM, SIGUSR1 or SIGUSR2 on any rank stops every rank at the same step's end,
with that step's checkpoint (:data:`SIGNALS`). Contact, Newton's ``reuse`` and ``amg``
directions and OBJ/USD frames are refused in one line naming the key (what runs:
docs/parallel.md).
"""

from __future__ import annotations

import resource
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from fem3d.errors import InputError, ParameterError, SimulationError
from fem3d.io import extras
from fem3d.io.checkpoint import (
    CHECKPOINT_NAME,
    RunCheckpoint,
    mesh_digest,
    restore_run_checkpoint,
    save_run_checkpoint,
)
from fem3d.io.energy import EnergyLog
from fem3d.io.interrupts import EXIT_INTERRUPTED, Interrupts, interrupted_message
from fem3d.io.reactions import ReactionLog
from fem3d.kernels.dispatch import resolve_backend
from fem3d.parallel.comm import launched_ranks, world
from fem3d.parallel.ghosts import Ghosts
from fem3d.parallel.partition import local_layout, partition_tets
from fem3d.parallel.pieces import PieceWriter
from fem3d.parallel.system import DistributedSystem
from fem3d.physics.constraints import Constraints
from fem3d.physics.model import Model
from fem3d.physics.springs import Pull
from fem3d.physics.stress import vertex_fields
from fem3d.physics.terms.loads import Loads
from fem3d.scene.build import refuse_mixed_elements
from fem3d.scene.local import LocalNumbering, split_tets
from fem3d.scene.share import SharePart, WholeScene
from fem3d.simulation import Simulation
from fem3d.solve.linear.petsc import DofLayout, PetscSolver
from fem3d.solve.schemes.registry import SCHEMES, get_scheme

#: The signals a distributed run stops at a step's end for, a checkpoint saved: what Open
#: MPI's ``mpiexec`` sends its ranks when it gets SIGINT or SIGTERM (SIGTERM, SIGKILL
#: ``odls_base_sigkill_timeout`` s later) and the SIGUSR1 / SIGUSR2 it forwards
#: (docs/parallel.md).
SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2)

__all__ = ["SIGNALS", "check_distributable", "RankShare", "distributed_simulation",
           "run_distributed", "DistributedLoop", "PieceWriter"]


def check_distributable(scene: Any, ranks: int) -> None:
    """Refuse, in one line naming the key, what a distributed run cannot do.

    Raises
    ------
    InputError
        Bodies of several elements, contact, a scheme not marked ``distributed`` (every
        built-in one is), a Newton direction other than ``direct``, frames other than
        ``vtu``, ``output.volume``.
    """
    why = f"mpiexec -n {ranks} runs"
    refuse_mixed_elements(scene, why)  # the rank's share is built for one element
    if scene.contact.enabled:
        raise scene.error("contact.enabled", f"{why} have no contact (the IPC Toolkit is "
                          "serial): run contact scenes in one process (docs/parallel.md)")
    sim = scene.simulation
    if not get_scheme(sim.integrator).distributed:
        names = ", ".join(n for n, s in SCHEMES.items() if s.distributed)
        raise scene.error("simulation.integrator", f"{why} step {names}, not "
                          f"{sim.integrator!r}")
    if sim.newton.solver != "direct":
        raise scene.error("simulation.newton.solver", f"{why} solve each Newton system "
                          f"with PETSc (\"direct\"), not {sim.newton.solver!r}")
    if scene.output.format != "vtu":
        raise scene.error("output.format", f"{why} write vtu pieces, not "
                          f"{scene.output.format!r}")
    if scene.output.volume:
        raise scene.error("output.volume", f"{why} write the surface's vtu pieces, not the "
                          "volume mesh: run without mpiexec for volume/*.vtu")


class RankShare:
    """One rank's share of a scene, made while the scene is built
    (:class:`~fem3d.simulation.Simulation`'s ``restrict_model`` and ``make_system``).

    It is :func:`~fem3d.scene.build.build`'s ``restrict``: :meth:`part` has rank 0 read the
    scene, partition the whole mesh's tets (:func:`partition_tets`) and send each rank its
    part (its tets over their vertices, :class:`~fem3d.scene.build.SharePart`), of which
    ``build`` makes the rank's model (no rank builds the whole model, and only rank 0 holds
    the whole mesh); :meth:`hold` finds which of the rank's vertices other ranks hold too
    (:class:`~fem3d.parallel.ghosts.Ghosts`) and numbers the free DOFs for PETSc
    (:func:`local_layout`); :meth:`summary` gives the model the whole model's
    ``E, nu, rho``. :meth:`make_system` makes the :class:`DistributedSystem` of the share.

    Parameters
    ----------
    comm : mpi4py.MPI.Comm
    petsc_options : str, optional
        The scene's ``simulation.petsc_options``.
    partition : (m,) int array, optional
        Each tet's rank, a resume's (the checkpoint's, written on as many ranks): taken
        when it fits the mesh and the ranks, else the tets are partitioned anew.

    Attributes
    ----------
    numbering : LocalNumbering
        The rank's tets and vertices (scene numbers), after :meth:`hold`.
    vertex_ghosts : Ghosts
        Its vertices, after :meth:`hold`.
    layout : DofLayout
        Its free DOFs, after :meth:`hold`.
    digest : str
        :func:`~fem3d.io.checkpoint.mesh_digest` of the whole mesh.
    partition : (m,) int32 or None
        Each tet's rank, after :meth:`part` (what the checkpoints write): rank 0's; None
        on the other ranks.
    n_vertices : int
        The scene's vertex count.
    skinned : bool
        Whether the scene shows a display mesh (a skin), after :meth:`part`.
    display : tuple of (sparse matrix, ndarray) or None
        Rank 0, a skinned scene: the skinning matrix ``W`` (display vertices from the whole
        mesh's) and the display triangles; None elsewhere.
    """

    def __init__(self, comm: Any, petsc_options: str = "",
                 partition: np.ndarray | None = None) -> None:
        self.comm, self.petsc_options = comm, petsc_options
        self.numbering: LocalNumbering | None = None
        self.vertex_ghosts: Ghosts | None = None
        self.layout: DofLayout | None = None
        self.digest = ""
        self.partition = partition
        self.n_vertices = 0
        self.skinned = False
        self.display: tuple[Any, np.ndarray] | None = None

    def part(self, read: Callable[[], WholeScene],
             cut: Callable[[WholeScene, np.ndarray, np.ndarray, int], SharePart]) -> SharePart:
        """Collective: this rank's part of the scene. Rank 0 alone reads it (``read``),
        partitions its tets (:func:`partition_tets`, or :attr:`partition` where it is one of
        this mesh on this many ranks: a resume's), cuts each rank's part (``cut``) and sends
        it; the other ranks never hold the whole mesh. An :class:`InputError` rank 0 meets
        (a bad mesh, a selection) is raised on every rank."""
        comm, size, rank = self.comm, self.comm.Get_size(), self.comm.Get_rank()
        failure, mine = "", None
        if rank == 0:
            sent = 0
            try:
                whole = read()
                X, T = whole.arrays.X, whole.arrays.T
                given = self.partition
                if (given is not None and given.shape == (T.shape[0],)
                        and np.array_equal(np.unique(given), np.arange(size))):
                    tet_rank = given.astype(np.int64)
                else:
                    tet_rank = partition_tets(T, size)
                self.partition = tet_rank.astype(np.int32)  # what the checkpoints write
                self.digest, self.n_vertices = mesh_digest(X, T), X.shape[0]
                W = whole.arrays.skinning_matrix()
                self.display = None if W is None else (W, whole.arrays.skin_F)
                parts, owner = split_tets(T, tet_rank, size)
                for r in range(1, size):  # one at a time: one part in memory beside the whole
                    comm.send(("part", cut(whole, parts[r], owner, r), self.digest,
                               self.n_vertices), dest=r)
                    sent = r
                mine = cut(whole, parts[0], owner, 0)
            except InputError as exc:
                failure = str(exc)
                for r in range(sent + 1, size):
                    comm.send(("failure", failure), dest=r)
        else:
            self.partition = None  # only rank 0 writes checkpoints
            message = comm.recv(source=0)
            if message[0] == "failure":
                failure = message[1]
            else:
                _, mine, self.digest, self.n_vertices = message
        self.agree(failure)
        self.skinned = bool(comm.bcast(self.display is not None, root=0))
        return mine

    def hold(self, numbering: LocalNumbering, constraints: Constraints) -> None:
        """Collective: this rank holds ``numbering``'s vertices, ``constraints`` (theirs)
        free DOFs: which other ranks hold them too (:attr:`vertex_ghosts`; a vertex's
        owner is the lowest rank holding it, as rank 0's cut said) and PETSc's numbering
        (:attr:`layout`)."""
        self.numbering = numbering
        self.vertex_ghosts = Ghosts.build(self.comm, numbering.vertices)
        free = constraints.free_dofs
        ids = 3 * numbering.vertices[free // 3] + free % 3  # increasing, as free is
        self.layout, _ = local_layout(self.comm, ids)

    def agree(self, failure: str) -> None:
        """Every rank raises the first rank's :class:`InputError` when any rank's ``failure``
        (its message, ``""`` for none) is not empty: a check of the rank's own elements
        fails on that rank alone, and one line (rank 0's) names it."""
        failures = [f for f in self.comm.allgather(failure) if f]
        if failures:
            raise InputError(failures[0])

    def summary(self, model: Model) -> Model:
        """``model`` (this rank's) with the whole model's summary ``E, nu, rho`` (the same
        on every rank: Newton's tolerance is made from them): the ranks' own when they all
        agree (one material), else their means weighted by the ranks' volumes."""
        rows = self.comm.allgather((model.E, model.nu, model.rho, model.total_volume))
        if all(r[:3] == rows[0][:3] for r in rows):
            return model
        total = sum(r[3] for r in rows)
        E, nu, rho = (sum(r[i] * r[3] for r in rows) / total for i in range(3))
        return replace(model, E=E, nu=nu, rho=rho)

    def make_system(self, model: Model, constraints: Constraints, loads: Loads
                    ) -> DistributedSystem:
        """The :class:`DistributedSystem` of the share's ``model`` and ``loads``."""
        return DistributedSystem(model, constraints, self.layout, self.vertex_ghosts,
                                 loads=loads, petsc_options=self.petsc_options)

    # -- the whole state: gathered on rank 0, and a whole state's share -------------------
    def gather(self, a: np.ndarray) -> np.ndarray | None:
        """Rank 0: the whole-mesh array ``(n, ...)`` of every rank's rows ``a`` (one per
        local vertex; each vertex from its owner); other ranks: None. Collective."""
        mine = self.vertex_ghosts.owned
        rows = self.comm.gather((self.numbering.vertices[mine], np.ascontiguousarray(a[mine])),
                                root=0)
        if rows is None:
            return None
        out = np.zeros((self.n_vertices, *a.shape[1:]), dtype=a.dtype)
        for ids, values in rows:
            out[ids] = values
        return out

    def take(self, whole: np.ndarray, key: str = "state") -> np.ndarray:
        """This rank's rows of a whole-mesh array ``(n, ...)``.

        Raises
        ------
        ParameterError
            ``whole`` is not one row per vertex of the mesh (``key`` names it).
        """
        whole = np.asarray(whole)
        if whole.ndim == 0 or whole.shape[0] != self.n_vertices:
            raise ParameterError(f"{key} has shape {whole.shape}, the mesh "
                                 f"{self.n_vertices} vertices")
        return whole[self.numbering.vertices]

    def whole_snapshot(self, snap: dict[str, Any]) -> dict[str, Any] | None:
        """Collective. Rank 0: the one-process :meth:`Simulation.snapshot
        <fem3d.simulation.Simulation.snapshot>` of the whole mesh made of every rank's
        ``snap`` (its vertices' rows from their owners; the pull's springs of every rank,
        with ``pull_attached``); other ranks: None."""
        whole = {k: v for k, v in snap.items() if not _per_vertex(k)}
        for key in sorted(k for k in snap if _per_vertex(k)):
            whole[key] = self.gather(np.asarray(snap[key]))
        verts = self.numbering.vertices[np.asarray(snap["pull_vertices"], dtype=np.int64)]
        rows = self.comm.gather((verts, np.asarray(snap["pull_targets"]).reshape(-1, 3),
                                 np.asarray(snap["pull_k"], dtype=np.float64)), root=0)
        attached = any(self.comm.allgather(bool(np.asarray(snap["pull_k"]).size
                                                and np.any(snap["pull_k"]))))
        if rows is None:
            return None
        ks = [k for _, _, k in rows]
        whole.update(pull_vertices=np.concatenate([v for v, _, _ in rows]),
                     pull_targets=np.concatenate([t for _, t, _ in rows]),
                     pull_k=ks[0] if all(k.ndim == 0 for k in ks) else np.concatenate(
                         [np.broadcast_to(k, v.shape) for v, _, k in rows]),
                     pull_attached=np.asarray(attached), pattern_keys=np.zeros(0, np.int64))
        return whole

    def local_snapshot(self, snap: dict[str, Any]) -> dict[str, Any]:
        """This rank's share of a whole (one-process) snapshot: its vertices' rows and the
        springs of the vertices it owns.

        Raises
        ------
        ParameterError
            An array that is not one row per vertex of the mesh.
        """
        out = {k: (self.take(v, k) if _per_vertex(k) else v) for k, v in snap.items()}
        verts = np.asarray(snap["pull_vertices"], dtype=np.int64).reshape(-1)
        if verts.size and (verts.min() < 0 or verts.max() >= self.n_vertices):
            raise ParameterError(f"pulled vertex out of range [0, {self.n_vertices})")
        k = np.asarray(snap["pull_k"], dtype=np.float64)
        targets = np.asarray(snap["pull_targets"], dtype=np.float64).reshape(-1, 3)
        mine = self.numbering.pull(Pull(verts, targets, k if k.ndim else float(k)),
                                   self.vertex_ghosts.owned)
        attached = snap.get("pull_attached", np.asarray(verts.size > 0))
        out.update(pull_vertices=mine.vertices, pull_targets=mine.targets,
                   pull_k=np.asarray(mine.k), pull_attached=np.asarray(bool(attached)))
        return out


def _per_vertex(key: str) -> bool:
    """Whether a snapshot's ``key`` holds one row per vertex (positions, velocities, a
    scheme's history)."""
    return key in ("q", "v") or key.startswith("history_")


class DistributedLoop:
    """Step a distributed ``sim`` up to ``scene.n_steps`` on every rank, writing the pieces,
    ``energy.csv`` and the checkpoints (rank 0) into ``out``.

    Parameters
    ----------
    scene : fem3d.scene.spec.Scene
    sim : Simulation
        This rank's (:func:`distributed_simulation`), at the checkpoint's state on a resume.
    out : Path
    settings : dict
        The checkpoint's ``settings`` (``scene``, ``kernels``, ``solver``,
        ``checkpoint_every``, ``preview``, ``ranks``).
    comm : mpi4py.MPI.Comm
    digest : str
        :func:`~fem3d.io.checkpoint.mesh_digest` of the whole mesh.
    ckpt : RunCheckpoint, optional
        The checkpoint a resume continues from (its energy rows and frames are kept).
    """

    def __init__(self, scene: Any, sim: Simulation, out: Path, settings: dict[str, Any],
                 comm: Any, share: RankShare, ckpt: RunCheckpoint | None = None) -> None:
        self.scene, self.sim, self.out, self.settings = scene, sim, Path(out), settings
        self.comm, self.rank, self.ckpt = comm, comm.Get_rank(), ckpt
        self.share, self.digest, self.partition = share, share.digest, share.partition
        self.every = int(settings["checkpoint_every"])
        if self.rank == 0:
            (self.out / "frames").mkdir(parents=True, exist_ok=True)
        comm.Barrier()
        self.writer = PieceWriter(self.out, sim.model.element.surface_triangles(sim.model.T),
                                  comm, None if share.display is None else share.display[1])
        #: reactions.csv (rank 0 writes it; every rank sums its share of the pins)
        self.reactions = ReactionLog(self.out / "reactions.csv", [k for k, _ in sim.pin_groups])
        if ckpt is None:
            self.log = EnergyLog(self.out / "energy.csv")
        else:
            self.log = EnergyLog.from_array(ckpt.energy, self.out / "energy.csv")
            if self.rank == 0:
                self.reactions.keep_until(ckpt.step)
            self.writer.restore(ckpt.frames, ckpt.step)
            comm.Barrier()  # later frames' files are gone before any rank writes
        self.iterations = 0
        #: caught while stepping (abandon=False: every rank finishes its step)
        self.interrupts = Interrupts(SIGNALS, abandon=False)
        #: the signal the ranks agreed on at a step's end (None: none)
        self.signum: int | None = None

    def record(self) -> None:
        """Log the state's energies (rank 0) and write its frame (every ``output.every``)."""
        sim = self.sim
        e = sim.energies()  # summed over the ranks (System.summed), the pull's whole
        forces = sim.reactions() if self.reactions.pins else None  # (collective)
        if self.rank == 0:
            self.log.append(sim.t, e["kinetic"], e["potential"], gravity=e["gravity"],
                            pull=e["pull"])
            if forces is not None:
                self.reactions.append(sim.step_index, sim.t, forces)
        if sim.step_index % self.scene.output.every == 0:
            # the one-process frames' stress fields, averaged over every rank's elements
            fields = vertex_fields(sim.model, sim.q,
                                   assemble=sim.system.vertex_ghosts.assemble)
            if self.share.skinned:
                self._write_display(fields)
            else:
                self.writer.write(sim.step_index, sim.t, sim.q, fields)

    def _write_display(self, fields: dict[str, np.ndarray]) -> None:
        """Collective. A skinned scene's frame, the one-process one: the positions and
        fields gathered on rank 0, which skins them (``W``) into the display mesh's
        ``.vtu`` (its rows come from any rank, so no rank alone could write a piece)."""
        sim, share = self.sim, self.share
        q = share.gather(sim.q)
        whole = {name: share.gather(values) for name, values in fields.items()}
        if self.rank == 0:
            W = share.display[0]
            self.writer.write_display(sim.step_index, sim.t, np.asarray(W @ q),
                                      {name: np.asarray(W @ v) for name, v in whole.items()})

    def _step(self) -> Any:
        """``sim.step()`` on every rank, its failure on any rank a failure on all (a step's
        closing checks see the local model: a rank may fail alone); :attr:`signum` the
        signal any rank was sent by the step's end, the same on every rank (one
        ``allgather`` for both: the ranks stop at the same step boundary)."""
        try:
            info, failure = self.sim.step(), ""
        except SimulationError as exc:
            info, failure = None, str(exc)
        rows = self.comm.allgather((failure, self.interrupts.signum))
        failures = [f for f, _ in rows if f]
        if failures:
            raise SimulationError(failures[0])
        self.signum = next((s for _, s in rows if s is not None), None)
        return info

    def save_checkpoint(self) -> None:
        """Collective. Rank 0: ``energy.csv`` and ``checkpoint.npz`` of the whole state
        (gathered from the ranks: :meth:`RankShare.whole_snapshot`), the one-process
        format."""
        snapshot = self.share.whole_snapshot(self.sim.snapshot())
        if self.rank:
            return
        self.write_logs()
        save_run_checkpoint(self.out / CHECKPOINT_NAME, RunCheckpoint(
            settings=self.settings, snapshot=snapshot, energy=self.log.as_array(),
            frames=dict(self.writer.frames), frame_count=len(self.writer.frames),
            mesh_digest=self.digest, partition=self.partition))

    def write_logs(self) -> None:
        """Rank 0: write ``energy.csv`` and ``reactions.csv``."""
        self.log.write()
        self.reactions.write()

    def run(self) -> float:
        """Step to ``scene.n_steps``, or to the end of the step in which a rank was sent
        one of :data:`SIGNALS` (:attr:`signum`; a checkpoint of that step is saved); the
        wall time of the steps."""
        sim = self.sim
        if self.ckpt is None:
            self.record()
        t1 = time.perf_counter()
        saved = -1
        with self.interrupts.installed():
            while sim.step_index < self.scene.n_steps and self.signum is None:
                info = self._step()
                self.iterations += info.newton_iterations
                self.record()
                if self.every and sim.step_index % self.every == 0:
                    self.save_checkpoint()
                    saved = sim.step_index
        wall = time.perf_counter() - t1
        if saved != sim.step_index and (self.signum is not None or
                                        (self.every and sim.step_index % self.every)):
            self.save_checkpoint()  # at the end, or at an interruption
        return wall


def run_distributed(scene: Any, out: Path, *, quiet: bool = True, backend: str | None = None,
                    checkpoint_every: int = 0, ckpt: RunCheckpoint | None = None,
                    settings: dict[str, Any] | None = None) -> int:
    """Run ``scene`` on the ranks of ``mpiexec`` into ``out`` (see the module docstring), or
    continue the run of checkpoint ``ckpt`` there (``fem3d resume``).

    Parameters
    ----------
    scene : fem3d.scene.spec.Scene
    out : Path
    quiet : bool
        No summary line.
    backend : {None, "numpy", "c"}
        Kernel back end (a resume: the checkpoint's, in ``settings``).
    checkpoint_every : int
        ``checkpoint.npz`` every this many steps and at the end (0: none).
    ckpt : RunCheckpoint, optional
        The checkpoint to continue (written by any number of ranks).
    settings : dict, optional
        With ``ckpt``: its settings as the resume amends them (``checkpoint_every``).

    Returns
    -------
    int
        The exit status: 0, or :data:`~fem3d.io.interrupts.EXIT_INTERRUPTED` when a rank
        was sent one of :data:`SIGNALS` (the checkpoint of the last step saved, one line
        from rank 0 saying how to continue); a failed step raises on every rank.

    Raises
    ------
    InputError
        What :func:`check_distributable` refuses, the missing ``fem3d[mpi]`` extra, or a
        checkpoint whose mesh or state does not fit; nothing is written.
    """
    ranks = launched_ranks()
    command = "fem3d run" if ckpt is None else "fem3d resume"
    extras.require("mpi4py", f"mpiexec -n {ranks} {command}")
    extras.require("petsc4py", f"mpiexec -n {ranks} {command}")
    if not PetscSolver.available():  # installed but does not import (a PETSc it was not built for)
        raise extras.MissingExtra(f"mpiexec -n {ranks} {command} needs petsc4py and mpi4py, "
                                  f"which do not import here: {PetscSolver.install_hint}")
    check_distributable(scene, ranks)
    if checkpoint_every < 0:
        raise ParameterError(f"--checkpoint-every must be >= 0, got {checkpoint_every}")
    comm = world()
    settings = dict(settings or {"checkpoint_every": int(checkpoint_every), "preview": False})
    kernels = settings.get("kernels", backend)
    try:
        kernels = resolve_backend(kernels)
    except (ImportError, ValueError) as exc:
        raise InputError(f"--kernels {kernels}: {exc}") from None
    settings.update(scene=scene.to_dict(), solver=PetscSolver.name, ranks=comm.Get_size(),
                    kernels=kernels)
    t0 = time.perf_counter()
    # a resume on as many ranks keeps the run's partition: the same sums in the same order
    same_ranks = ckpt is not None and ckpt.settings.get("ranks") == comm.Get_size()
    sim, share = distributed_simulation(scene, comm, settings["kernels"],
                                        ckpt.partition if same_ranks else None)
    if ckpt is not None:
        local = ckpt
        if ckpt.mesh_digest == share.digest:  # (else restore names the other mesh)
            try:  # this rank's share of the whole state (every rank reads the same file)
                local = replace(ckpt, snapshot=share.local_snapshot(ckpt.snapshot))
            except (ParameterError, KeyError) as exc:
                raise InputError(f"bad checkpoint state: {exc}",
                                 path=Path(out) / CHECKPOINT_NAME) from None
        restore_run_checkpoint(sim, local, share.digest, sim.assembled.mesh_paths[0], out)
    setup = time.perf_counter() - t0
    loop = DistributedLoop(scene, sim, Path(out), settings, comm, share, ckpt)
    setup_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    cpu = time.process_time()
    wall = loop.run()
    cpu = time.process_time() - cpu
    rss = comm.gather((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, setup_rss,
                       cpu), root=0)
    q, v = share.gather(sim.q), share.gather(sim.v)
    if comm.Get_rank() == 0:
        loop.write_logs()
        np.savez(Path(out) / "state.npz", q=q, v=v, t=sim.t, step=sim.step_index)
        if loop.signum is not None:  # the checkpoint of the last step is saved
            print(f"{command}: " + interrupted_message(
                Interrupts.name_of(loop.signum), sim.step_index, sim.t,
                Path(out) / CHECKPOINT_NAME, Path(out)), file=sys.stderr)
            return EXIT_INTERRUPTED
        # matplotlib is imported when a run ends (as in one process), on rank 0 alone
        from fem3d.io.preview import plot_energy

        plot_energy(loop.log, Path(out) / "energy.png",
                    title=f"{scene.name} ({scene.simulation.integrator})")
        if not quiet:
            steps = sim.step_index - (0 if ckpt is None else ckpt.step)
            print(f"{scene.name}: {steps} steps on {comm.Get_size()} ranks in "
                  f"{wall:.2f} s ({setup:.2f} s set-up), {loop.iterations} Newton iterations, "
                  f"peak RSS per rank {', '.join(f'{m:.0f}' for m, _, _ in rss)} MiB "
                  f"(after set-up {', '.join(f'{m:.0f}' for _, m, _ in rss)}), CPU of the "
                  f"steps per rank {', '.join(f'{c:.2f}' for _, _, c in rss)} s -> {out}")
    return 0 if loop.signum is None else EXIT_INTERRUPTED


def distributed_simulation(scene: Any, comm: Any, backend: str | None = None,
                           partition: np.ndarray | None = None
                           ) -> tuple[Simulation, RankShare]:
    """This rank's :class:`Simulation` of ``scene`` (:class:`RankShare`: its ``model`` the
    rank's local model, its system the rank's :class:`DistributedSystem`, its energies summed
    over the ranks by :meth:`DistributedSystem.summed`) and its share (the whole mesh's
    :func:`~fem3d.io.checkpoint.mesh_digest`, the partition: ``partition``, a resume's, when
    it fits the mesh and the ranks, else made anew)."""
    share = RankShare(comm, scene.simulation.petsc_options, partition)
    sim = Simulation(scene, backend=backend, scripted=True, restrict_model=share,
                     make_system=share.make_system)
    return sim, share
