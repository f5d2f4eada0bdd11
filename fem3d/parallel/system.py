"""The distributed system: a :class:`~fem3d.solve.system.System` on a rank's local model
whose terms sum over the ranks and whose linear solver is one distributed PETSc matrix.

A rank holds the vertices of its own tets (:class:`~fem3d.scene.local.LocalNumbering`): the
ones it owns and ghosts, vertices other ranks hold too. Its vectors (positions, velocities,
gradients, Newton directions) are that long. The integrators,
:class:`~fem3d.solve.objective.Objective` and :func:`~fem3d.solve.newton.newtons_method` run
unchanged on them: a term's gradient is summed over the ranks that hold each entry
(:class:`~fem3d.parallel.ghosts.Ghosts`, the same bits on every holder), and the dot
products, norms and checks Newton decides by are reduced over the entries each rank owns
(:class:`OwnedReductions`), so every rank takes the same decisions. What is distributed is
the work over the elements (energies, gradients, element Hessians: each rank its own tets),
the vectors, and the linear algebra (the Newton matrix's rows and the Krylov solve or
factorization: PETSc).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from fem3d.parallel.comm import sum_array, sum_scalar
from fem3d.parallel.ghosts import Ghosts
from fem3d.physics.constraints import Constraints
from fem3d.physics.model import Model
from fem3d.physics.springs import Pull
from fem3d.physics.terms.base import HessianSink, NewtonPolicy, StepMap, Term
from fem3d.physics.terms.loads import Loads
from fem3d.physics.terms.pull import PullSprings
from fem3d.solve.linear.base import DirectSolver
from fem3d.solve.linear.petsc import DofLayout, PetscSolver
from fem3d.solve.reductions import Reductions
from fem3d.solve.system import System

__all__ = ["DistributedSystem", "OwnedReductions", "ReducedLoads", "ReducedPullSprings",
           "ReducedTerm"]


class OwnedReductions(Reductions):
    """Newton's reductions of a rank's free-DOF vectors: over the entries it owns
    (``owned``), summed over the ranks in rank order; flags agreed by every rank.

    Parameters
    ----------
    comm : mpi4py.MPI.Comm
    owned : (n_free,) bool
        Which of the rank's free DOFs it owns.
    """

    def __init__(self, comm: Any, owned: np.ndarray) -> None:
        self.comm = comm
        self.owned = np.asarray(owned, dtype=bool)

    def dot(self, a: np.ndarray, b: np.ndarray) -> float:
        o = self.owned
        return sum_scalar(self.comm, float(a[o] @ b[o]))

    def all(self, flag: bool) -> bool:
        return all(self.comm.allgather(bool(flag)))

    def any(self, flag: bool) -> bool:
        return any(self.comm.allgather(bool(flag)))

    def _scaled_norm(self, g: np.ndarray) -> float:
        mine = g[self.owned]
        s = max(self.comm.allgather(float(np.abs(mine).max()) if mine.size else 0.0))
        if not s > 0:
            return 0.0
        scaled = mine / s
        return s * math.sqrt(sum_scalar(self.comm, float(scaled @ scaled)))

    def extent(self, X: np.ndarray) -> np.ndarray:
        from mpi4py import MPI  # optional (fem3d[mpi]): a distributed run has it

        lo = np.ascontiguousarray(X.min(axis=0) if X.size else np.full(3, np.inf))
        hi = np.ascontiguousarray(X.max(axis=0) if X.size else np.full(3, -np.inf))
        self.comm.Allreduce(MPI.IN_PLACE, lo, op=MPI.MIN)
        self.comm.Allreduce(MPI.IN_PLACE, hi, op=MPI.MAX)
        return hi - lo


class ReducedTerm(Term):
    """A term of a rank's local model, its energy summed over the ranks and its gradient
    over the ranks holding each entry (:meth:`DistributedSystem.summed`).

    Its Hessian is the rank's part (its tets): the distributed PETSc matrix sums the ranks'
    parts. Only element-wise terms (inertia, elasticity, gravity, Rayleigh damping, the
    surface and point loads, the pull springs of the vertices a rank owns) are additive over
    the ranks like this.

    Parameters
    ----------
    term : Term
        The local model's term.
    system : DistributedSystem
        Its :meth:`~DistributedSystem.summed`.
    """

    def __init__(self, term: Term, system: DistributedSystem) -> None:
        self.term = term
        self.system = system
        self.name = term.name
        self.variable = term.variable
        self.inertial = term.inertial
        self.dissipative = term.dissipative
        self.requires_convergence = term.requires_convergence
        self.allows_lagged_matrix = term.allows_lagged_matrix
        self.newton_policy: NewtonPolicy = term.newton_policy
        # active on every rank when on any (a rank's damping coefficients may all be zero
        # where another's are not): every rank keeps the same terms, so makes the same sums
        self._here = bool(term.active)
        self._active = system.reductions.any(self._here)

    @property
    def active(self) -> bool:
        return self._active

    @property
    def energy_scale(self) -> float:  # type: ignore[override]
        return self.system.summed(float(self.term.energy_scale) if self._here else 0.0)

    def energy(self, u: np.ndarray) -> float:
        return self.system.summed(float(self.term.energy(u)) if self._here else 0.0)

    def gradient(self, u: np.ndarray) -> np.ndarray:
        return self._summed(self.term.gradient, u)

    def reaction_gradient(self, u: np.ndarray) -> np.ndarray:
        """The term's ``reaction_gradient`` (its gradient where it has none), summed."""
        return self._summed(getattr(self.term, "reaction_gradient", self.term.gradient), u)

    def _summed(self, gradient, u: np.ndarray) -> np.ndarray:
        """``gradient(u)`` of the rank's term (zeros where it is not here), summed."""
        local = gradient(u) if self._here else np.zeros(np.size(u))
        return self.system.summed(local)

    def add_hessian(self, u: np.ndarray, sink: HessianSink) -> None:
        if self._here:
            self.term.add_hessian(u, sink)

    def begin_step(self, step: StepMap) -> None:
        if self._here:
            self.term.begin_step(step)

    def with_model(self, model: Model) -> ReducedTerm:
        return ReducedTerm(self.term.with_model(model), self.system)

    # contact: not element-wise, refused by fem3d.parallel.run


class ReducedPullSprings(ReducedTerm, PullSprings):
    """The pull springs of a rank's share of a pull (the springs of the vertices it owns,
    :meth:`fem3d.scene.local.LocalNumbering.pull`, possibly none), summed over the ranks;
    active whenever a pull is attached, on every rank alike."""

    def __init__(self, springs: PullSprings, system: DistributedSystem) -> None:
        ReducedTerm.__init__(self, springs, system)
        self.model, self.spring, self.pull = springs.model, springs.spring, springs.pull
        self._here = self._active = True  # attached on every rank (none of its springs here)

    def with_model(self, model: Model) -> ReducedPullSprings:
        return ReducedPullSprings(self.term.with_model(model), self.system)


class ReducedLoads(Loads):
    """A rank's gravity, damping and share of the surface and point loads (:class:`Loads`
    of its local model) as :class:`ReducedTerm` s, gravity's potential summed over the
    ranks; :attr:`surface` and :attr:`gravity_force` stay the rank's parts (the
    linearly-implicit scheme sums what it makes of them)."""

    def __init__(self, loads: Loads, system: DistributedSystem) -> None:
        super().__init__(loads.gravity, loads.damping, loads.rayleigh_alpha,
                         loads.rayleigh_beta, loads.surface)
        object.__setattr__(self, "system", system)
        object.__setattr__(self, "local", loads)
        # made once: a scheme tells the loads' terms from others by identity (linear)
        object.__setattr__(self, "_terms", [ReducedTerm(t, system) for t in loads.terms()])

    def terms(self) -> list[Term]:
        return list(self._terms)

    def gravity_energy(self, q: np.ndarray) -> float:
        return self.system.summed(self.local.gravity_energy(q))

    def with_model(self, model: Model) -> ReducedLoads:
        return ReducedLoads(self.local.with_model(model), self.system)


class DistributedSystem(System):
    """:class:`System` of one rank: its local model over its own vertices, their
    constraints, terms summed over the ranks, and the ``"petsc"`` solver over the ranks'
    :class:`DofLayout`.

    Parameters
    ----------
    model : Model
        The rank's local model (its tets over its vertices).
    constraints : Constraints
        The constraints of its vertices.
    layout : DofLayout
        Its free DOFs in PETSc's numbering, with their :class:`Ghosts`.
    vertex_ghosts : Ghosts
        Its vertices, shared with other ranks or not.
    loads : Loads
        The local model's gravity, damping and share of the surface and point loads.
    petsc_options : str, optional
        The scene's ``simulation.petsc_options``.
    """

    #: Distributed runs refuse Newton's ``reuse`` direction and the ``amg`` backend, the
    #: only readers of :attr:`factorized_data`: no copy of the rank's Newton matrix (8 bytes
    #: per stored entry) stays alive through the next iteration's GAMG set-up.
    records_factorized = False

    is_share = True

    def __init__(self, model: Model, constraints: Constraints, layout: DofLayout,
                 vertex_ghosts: Ghosts, *, loads: Loads, petsc_options: str = "") -> None:
        self.layout = layout
        self.vertex_ghosts = vertex_ghosts
        owned = np.zeros(constraints.n_free, dtype=bool)
        owned[layout.owned] = True
        self.reductions = OwnedReductions(layout.comm, owned)
        super().__init__(model, constraints, PetscSolver.name,
                         loads=ReducedLoads(loads, self), petsc_options=petsc_options)

    def _physics_cache(self) -> None:
        super()._physics_cache()
        self._model_terms = tuple(ReducedTerm(t, self) for t in self._model_terms)

    def pull_term(self, pull: Pull | None) -> PullSprings:
        """The springs of ``pull`` (this rank's share of it), summed over the ranks."""
        springs = PullSprings(self.model, pull, spring=self.spring)
        return springs if pull is None else ReducedPullSprings(springs, self)

    def summed(self, value: float | np.ndarray) -> float | np.ndarray:
        """``value`` of this rank's tets summed over the ranks, the same bits on every rank
        (:func:`~fem3d.parallel.comm.sum_scalar`); a vector (over the rank's DOFs, or its
        free DOFs) entry by entry over the ranks that hold the entry (:meth:`Ghosts.
        assemble`)."""
        if np.ndim(value) == 0:
            return sum_scalar(self.layout.comm, float(value))
        value = np.asarray(value, dtype=np.float64)
        if value.size == self.model.n_dofs:
            return self.vertex_ghosts.assemble(value.reshape(-1, 3)).reshape(value.shape)
        if value.size == self.constraints.n_free:
            return self.layout.ghosts.assemble(value)
        raise ValueError(f"a vector of {value.size} entries is not over this rank's "
                         f"{self.model.n_dofs} DOFs or {self.constraints.n_free} free DOFs")

    def total(self, parts: np.ndarray) -> np.ndarray:
        """``parts`` summed over the ranks entry by entry, in rank order (the same bits on
        every rank)."""
        return sum_array(self.layout.comm, parts)

    def solve_mass(self, rhs: np.ndarray) -> np.ndarray:
        """``M^-1 rhs`` with the mass matrix summed over the ranks (each rank's
        :attr:`mass_free` is its tets' part): a :class:`PetscSolver` over the
        :class:`DofLayout` (MUMPS or CG + GAMG, as for the Newton systems); ``rhs`` and the
        result over this rank's free DOFs."""
        solver = PetscSolver(self.direct_solver_options(), layout=self.layout)
        solver.analyse(self.mass_free, symmetric=True)
        solver.factorize(self.mass_free)
        return solver.solve(rhs)

    def _new_direct_solver(self, pattern) -> DirectSolver:
        solver = PetscSolver(self.direct_solver_options(), layout=self.layout)
        solver.analyse(pattern, symmetric=True)
        self.analyses += 1
        return solver
