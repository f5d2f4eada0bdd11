"""``mpiexec -n N fem3d run scene.toml``: one simulation on N ranks.

Every rank reads the scene and builds the whole model (the pins, motions and reported
energies are the whole model's), partitions the tets (:mod:`fem3d.parallel.partition`) and
steps a :class:`~fem3d.simulation.Simulation` whose system is its
:class:`~fem3d.parallel.system.DistributedSystem`. Outputs in ``out``:

* ``frames/frame_NNNNN_R.vtu``: rank ``R``'s piece, the surface of its tets (a ``rank``
  field per point); ``frames/frame_NNNNN.pvtu`` gathers the pieces of a frame and
  ``frames.pvd`` lists the frames by time (ParaView opens it);
* ``energy.csv`` (rank 0), the columns of a one-process run;
* ``state.npz`` (rank 0): the last step's ``q``, ``v``, ``t``, ``step`` (whole model).

Contact, scripted pulls, the linearly-implicit, static and Newmark schemes, Newton's ``reuse`` and
``amg`` directions and OBJ/USD frames are refused in one line naming the key (what runs:
docs/parallel.md).
"""

from __future__ import annotations

import resource
import time
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from fem3d.io import extras
from fem3d.io.energy import EnergyLog
from fem3d.io.files import atomic_write
from fem3d.io.frames import RawVtu
from fem3d.mesh.tetmesh import boundary_faces
from fem3d.parallel.comm import launched_ranks, world
from fem3d.parallel.local import local_loads, local_model
from fem3d.parallel.partition import dof_layout, partition_tets
from fem3d.parallel.system import DistributedSystem
from fem3d.physics.constraints import Constraints
from fem3d.physics.model import Model
from fem3d.physics.terms.loads import Loads
from fem3d.simulation import Simulation
from fem3d.solve.linear.petsc import PetscSolver
from fem3d.solve.schemes.registry import SCHEMES, get_scheme

__all__ = ["check_distributable", "distributed_system",
           "run_distributed", "PieceWriter"]

#: The schemes a distributed run steps (their Newton sees only element-wise terms; Newmark's
#: initial acceleration solves with the mass matrix outside the linear-solver seam).


def check_distributable(scene: Any, ranks: int) -> None:
    """Refuse, in one line naming the key, what a distributed run cannot do.

    Raises
    ------
    InputError
        Contact, pulls, a scheme not marked ``distributed``, a Newton
        direction other than ``direct``, frames other than ``vtu``, ``output.volume``.
    """
    why = f"mpiexec -n {ranks} runs"
    if scene.contact.enabled:
        raise scene.error("contact.enabled", f"{why} have no contact (the IPC Toolkit is "
                          "serial): run contact scenes in one process (docs/parallel.md)")
    if scene.pulls:
        raise scene.error("pulls", f"{why} have no scripted pulls yet (their springs are not "
                          "element-wise): run without mpiexec, or --no-pull")
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


def distributed_system(comm: Any, petsc_options: str = ""):
    """A ``make_system`` for :class:`~fem3d.simulation.Simulation`: this rank's
    :class:`DistributedSystem` of the whole model (partitioned here)."""
    def make(model: Model, constraints: Constraints, loads: Loads) -> DistributedSystem:
        tet_rank = partition_tets(model.T, comm)
        tets = np.flatnonzero(tet_rank == comm.Get_rank())
        layout = dof_layout(model.T, tet_rank, constraints.free_dofs, comm)
        local = local_model(model, tets)
        system = DistributedSystem(local, constraints, layout,
                                   loads=local_loads(loads, local, tets),
                                   petsc_options=petsc_options)
        system.tet_rank = tet_rank
        return system
    return make


class PieceWriter:
    """One rank's frames: the surface of its tets as ``frame_NNNNN_R.vtu``; rank 0 also
    writes each frame's ``.pvtu`` and ``frames.pvd``.

    Parameters
    ----------
    out : Path
    T : (m, 4) int64
        The whole mesh.
    tet_rank : (m,) int64
    comm : mpi4py.MPI.Comm
    """

    def __init__(self, out: Path, T: np.ndarray, tet_rank: np.ndarray, comm: Any) -> None:
        self.rank, self.size = comm.Get_rank(), comm.Get_size()
        self.out = Path(out)
        self.frame_dir = self.out / "frames"
        faces = boundary_faces(T[tet_rank == self.rank])
        self.vertices, local = np.unique(faces, return_inverse=True)
        self._vtu = RawVtu(local.reshape(-1, 3))
        self._rank_field = np.full(self.vertices.size, self.rank, dtype=np.int32)
        self.frames: dict[int, tuple[float, str]] = {}

    def name(self, step: int, rank: int | None = None) -> str:
        return f"frame_{step:05d}" + ("" if rank is None else f"_{rank}") + \
            (".pvtu" if rank is None else ".vtu")

    def write(self, step: int, t: float, q: np.ndarray) -> None:
        """This rank's piece of frame ``step``; rank 0: the ``.pvtu`` and ``frames.pvd``."""
        self._vtu.write(self.frame_dir / self.name(step, self.rank), q[self.vertices],
                        {"rank": self._rank_field})
        if self.rank:
            return
        pieces = "\n".join(f"    <Piece Source={quoteattr(self.name(step, r))}/>"
                           for r in range(self.size))
        atomic_write(self.frame_dir / self.name(step), (
            '<?xml version="1.0"?>\n<VTKFile type="PUnstructuredGrid" version="1.0" '
            'byte_order="LittleEndian" header_type="UInt64">\n'
            '  <PUnstructuredGrid GhostLevel="0">\n'
            '    <PPointData><PDataArray type="Int32" Name="rank"/></PPointData>\n'
            '    <PPoints><PDataArray type="Float64" NumberOfComponents="3"/></PPoints>\n'
            f"{pieces}\n  </PUnstructuredGrid>\n</VTKFile>\n"))
        self.frames[step] = (t, f"frames/{self.name(step)}")
        rows = "\n".join(f'    <DataSet timestep="{tt!r}" group="" part="0" '
                         f"file={quoteattr(rel)}/>" for _, (tt, rel) in sorted(self.frames.items()))
        atomic_write(self.out / "frames.pvd", (
            '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1" '
            f'byte_order="LittleEndian">\n  <Collection>\n{rows}\n  </Collection>\n'
            "</VTKFile>\n"))


def run_distributed(scene: Any, out: Path, *, quiet: bool = True,
                    backend: str | None = None) -> int:
    """Run ``scene`` on the ranks of ``mpiexec`` into ``out`` (see the module docstring).

    Returns
    -------
    int
        The exit status (0; a failed step raises on every rank).

    Raises
    ------
    InputError
        What :func:`check_distributable` refuses, or the missing ``fem3d[mpi]`` extra; nothing
        is written.
    """
    ranks = launched_ranks()
    extras.require("mpi4py", f"mpiexec -n {ranks} fem3d run")
    extras.require("petsc4py", f"mpiexec -n {ranks} fem3d run")
    if not PetscSolver.available():  # installed but does not import (a PETSc it was not built for)
        raise extras.MissingExtra(f"mpiexec -n {ranks} fem3d run needs petsc4py and mpi4py, "
                                  f"which do not import here: {PetscSolver.install_hint}")
    check_distributable(scene, ranks)
    comm = world()
    rank = comm.Get_rank()
    t0 = time.perf_counter()
    sim = Simulation(scene, backend=backend,
                     make_system=distributed_system(comm, scene.simulation.petsc_options))
    setup = time.perf_counter() - t0
    out = Path(out)
    if rank == 0:
        (out / "frames").mkdir(parents=True, exist_ok=True)
    comm.Barrier()
    writer = PieceWriter(out, sim.model.T, sim.system.tet_rank, comm)
    log = EnergyLog(out / "energy.csv")
    every = scene.output.every

    def record() -> None:
        e = sim.energies()
        if rank == 0:
            log.append(sim.t, e["kinetic"], e["potential"], gravity=e["gravity"], pull=e["pull"])
        if sim.step_index % every == 0:
            writer.write(sim.step_index, sim.t, sim.q)

    record()
    iterations = 0
    t1 = time.perf_counter()
    for _ in range(scene.n_steps):
        info = sim.step()
        iterations += info.newton_iterations
        record()
    wall = time.perf_counter() - t1
    rss = comm.gather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, root=0)
    if rank == 0:
        log.write()
        np.savez(out / "state.npz", q=sim.q, v=sim.v, t=sim.t, step=sim.step_index)
        if not quiet:
            print(f"{scene.name}: {scene.n_steps} steps on {comm.Get_size()} ranks in "
                  f"{wall:.2f} s ({setup:.2f} s set-up), {iterations} Newton iterations, "
                  f"peak RSS per rank {', '.join(f'{m:.0f}' for m in rss)} MiB -> {out}")
    return 0
