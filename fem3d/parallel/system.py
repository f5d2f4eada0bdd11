"""The distributed system: a :class:`~fem3d.solve.system.System` on a rank's local model
whose terms sum over the ranks and whose linear solver is one distributed PETSc matrix.

Every rank holds the whole reduced vector (velocities, gradient, Newton direction): the
integrators, :class:`~fem3d.solve.objective.Objective` and :func:`~fem3d.solve.newton.
newtons_method` run unchanged and, because every sum they see is the same bits on every
rank (:mod:`fem3d.parallel.comm`), take the same decisions on every rank. What is
distributed is the work over the elements (energies, gradients, element Hessians: each rank
its own tets) and the linear algebra (the Newton matrix's rows and the Krylov solve or
factorization: PETSc).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fem3d.parallel.comm import owned_vertices, sum_scalar, sum_vector
from fem3d.physics.constraints import Constraints
from fem3d.physics.model import Model
from fem3d.physics.springs import Pull
from fem3d.physics.terms.base import HessianSink, NewtonPolicy, StepMap, Term
from fem3d.physics.terms.loads import Loads
from fem3d.physics.terms.pull import PullSprings
from fem3d.solve.linear.base import DirectSolver
from fem3d.solve.linear.petsc import DofLayout, PetscSolver
from fem3d.solve.system import System

__all__ = ["DistributedSystem", "ReducedLoads", "ReducedPullSprings", "ReducedTerm"]


class ReducedTerm(Term):
    """A term of a rank's local model, its energy and gradient summed over the ranks.

    Its Hessian is the rank's part (its tets): the distributed PETSc matrix sums the ranks'
    parts. Only element-wise terms (inertia, elasticity, gravity, Rayleigh damping) are
    additive over the tets like this.

    Parameters
    ----------
    term : Term
        The local model's term.
    comm : mpi4py.MPI.Comm
    """

    def __init__(self, term: Term, comm: Any) -> None:
        self.term = term
        self.comm = comm
        self.name = term.name
        self.variable = term.variable
        self.inertial = term.inertial
        self.dissipative = term.dissipative
        self.requires_convergence = term.requires_convergence
        self.allows_lagged_matrix = term.allows_lagged_matrix
        self.newton_policy: NewtonPolicy = term.newton_policy

    @property
    def active(self) -> bool:
        return self.term.active

    @property
    def energy_scale(self) -> float:  # type: ignore[override]
        return sum_scalar(self.comm, self.term.energy_scale)

    def energy(self, u: np.ndarray) -> float:
        return sum_scalar(self.comm, float(self.term.energy(u)))

    def gradient(self, u: np.ndarray) -> np.ndarray:
        return sum_vector(self.comm, self.term.gradient(u))

    def add_hessian(self, u: np.ndarray, sink: HessianSink) -> None:
        self.term.add_hessian(u, sink)

    def begin_step(self, step: StepMap) -> None:
        self.term.begin_step(step)

    def with_model(self, model: Model) -> ReducedTerm:
        return ReducedTerm(self.term.with_model(model), self.comm)

    # contact: not element-wise, refused by fem3d.parallel.run; the pull springs:
    # ReducedPullSprings


class ReducedPullSprings(PullSprings):
    """The pull springs of the vertices this rank owns (:func:`~fem3d.parallel.comm.
    owned_vertices`), their energy and gradient summed over the ranks; the Hessian blocks
    are this rank's (the distributed matrix sums them). :attr:`pull` is this rank's share
    (no springs on a rank that owns no pulled vertex: the term stays active on every
    rank, so every rank makes the same sums).

    Parameters
    ----------
    model : Model
        The rank's local model.
    pull : Pull
        Every rank's springs (the simulation's whole pull).
    owned : (k,) bool
        Which of ``pull``'s springs this rank adds.
    comm : mpi4py.MPI.Comm
    spring : optional
        The generated spring kernels.
    """

    def __init__(self, model: Model, pull: Pull, owned: np.ndarray, comm: Any, *,
                 spring=None) -> None:
        k = pull.k if np.ndim(pull.k) == 0 else pull.k[owned]
        super().__init__(model, Pull(pull.vertices[owned], pull.targets[owned], k),
                         spring=spring)
        self.whole, self.owned, self.comm = pull, owned, comm

    def energy(self, q: np.ndarray) -> float:
        return sum_scalar(self.comm, super().energy(q))

    def gradient(self, q: np.ndarray) -> np.ndarray:
        return sum_vector(self.comm, super().gradient(q))

    def with_model(self, model: Model) -> ReducedPullSprings:
        return ReducedPullSprings(model, self.whole, self.owned, self.comm, spring=self.spring)


class ReducedLoads(Loads):
    """A rank's gravity, damping and share of the surface and point loads (:class:`Loads`
    of its local model) as :class:`ReducedTerm` s, gravity's potential summed over the
    ranks; :attr:`surface` and :attr:`gravity_force` stay the rank's parts (the
    linearly-implicit scheme sums what it makes of them)."""

    def __init__(self, loads: Loads, comm: Any) -> None:
        super().__init__(loads.gravity, loads.damping, loads.rayleigh_alpha,
                         loads.rayleigh_beta, loads.surface)
        object.__setattr__(self, "comm", comm)
        object.__setattr__(self, "local", loads)
        # made once: a scheme tells the loads' terms from others by identity (linear)
        object.__setattr__(self, "_terms", [ReducedTerm(t, comm) for t in loads.terms()])

    def terms(self) -> list[Term]:
        return list(self._terms)

    def gravity_energy(self, q: np.ndarray) -> float:
        return sum_scalar(self.comm, self.local.gravity_energy(q))

    def with_model(self, model: Model) -> ReducedLoads:
        return ReducedLoads(self.local.with_model(model), self.comm)


class DistributedSystem(System):
    """:class:`System` of one rank: its local model (:func:`~fem3d.parallel.local.
    local_model`), the whole constraint set, terms summed over the ranks, and the
    ``"petsc"`` solver over the ranks' :class:`DofLayout`.

    Parameters
    ----------
    model : Model
        The rank's local model.
    constraints : Constraints
        The whole model's (every rank the same).
    layout : DofLayout
    loads : Loads
        The local model's gravity and damping (:func:`~fem3d.parallel.local.local_loads`).
    petsc_options : str, optional
        The scene's ``simulation.petsc_options``.
    """

    #: Distributed runs refuse Newton's ``reuse`` direction and the ``amg`` backend, the
    #: only readers of :attr:`factorized_data`: no copy of the rank's Newton matrix (8 bytes
    #: per stored entry) stays alive through the next iteration's GAMG set-up.
    records_factorized = False

    def __init__(self, model: Model, constraints: Constraints, layout: DofLayout, *,
                 loads: Loads, petsc_options: str = "") -> None:
        self.layout = layout
        self._pull_owned: tuple[Pull, np.ndarray] | None = None  # the last pull's owners
        super().__init__(model, constraints, PetscSolver.name,
                         loads=ReducedLoads(loads, layout.comm), petsc_options=petsc_options)

    def _physics_cache(self) -> None:
        super()._physics_cache()
        comm = self.layout.comm
        self._model_terms = tuple(ReducedTerm(t, comm) for t in self._model_terms)

    def pull_term(self, pull: Pull | None) -> PullSprings:
        """:class:`ReducedPullSprings` of ``pull`` (the same on every rank: a collective
        call the first time a pull is seen)."""
        if pull is None:
            return PullSprings(self.model, None, spring=self.spring)
        if self._pull_owned is None or self._pull_owned[0] is not pull:
            owned = owned_vertices(self.layout.comm, pull.vertices, self.model.T)
            self._pull_owned = (pull, owned)
        return ReducedPullSprings(self.model, pull, self._pull_owned[1], self.layout.comm,
                                  spring=self.spring)

    def summed(self, value: float | np.ndarray) -> float | np.ndarray:
        """``value`` of this rank's tets summed over the ranks, the same bits on every rank
        (:func:`~fem3d.parallel.comm.sum_scalar`, :func:`~fem3d.parallel.comm.sum_vector`)."""
        if np.ndim(value) == 0:
            return sum_scalar(self.layout.comm, float(value))
        return sum_vector(self.layout.comm, value)

    def solve_mass(self, rhs: np.ndarray) -> np.ndarray:
        """``M^-1 rhs`` with the mass matrix summed over the ranks (each rank's
        :attr:`mass_free` is its tets' part): a :class:`PetscSolver` over the
        :class:`DofLayout` (MUMPS or CG + GAMG, as for the Newton systems); the whole
        ``(n_free,)`` result on every rank."""
        solver = PetscSolver(self.direct_solver_options(), layout=self.layout)
        solver.analyse(self.mass_free, symmetric=True)
        solver.factorize(self.mass_free)
        return solver.solve(rhs)

    def _new_direct_solver(self, pattern) -> DirectSolver:
        solver = PetscSolver(self.direct_solver_options(), layout=self.layout)
        solver.analyse(pattern, symmetric=True)
        self.analyses += 1
        return solver
