"""Time integrators: linearly-implicit Euler and backward (implicit) Euler with Newton's method.

Both work on the free DOFs ``q_free = P q`` (fixed vertices removed with the selection
matrix of :class:`fem3d.physics.constraints.Constraints`); fixed DOFs keep their rest position and a
zero velocity. A state is immutable (:class:`State`); an integrator is
``step(system, state, dt, pull) -> (State, StepStats)``, where :class:`System` caches what
does not change between steps (model, constraints, reduced sparsity, the sparse solver with
its symbolic analysis done once).

Notation: ``M`` mass matrix, ``V(q)`` strain energy, ``H = d2V/dq2``, ``K = -H`` the
stiffness of the assignment, ``f = -dV/dq``.

* :func:`linearly_implicit_euler`: ``(M - dt^2 K) v+ = M v + dt f(q)``, ``q+ = q + dt v+``.
* :func:`implicit_euler`: ``v+ = argmin_v 1/2 (v - v_t)^T M (v - v_t) + V(q_t + dt v)
  (+ V_pull(q_t + dt v))``, ``q+ = q_t + dt v+``, minimised by :func:`newtons_method`
  (Hessian ``M + dt^2 H``, backtracking line search).

A pull (:class:`Pull`) is a set of zero-rest-length springs ``1/2 k |x_i - target_i|^2``
(generated ``spring_kernels``). In backward Euler its energy is part of the minimised
objective (and its Hessian of Newton's); in the linearly-implicit scheme its force is in
``f`` and its stiffness in ``K`` (the whole force is linearised). The assignment's main
program linearises only the elastic force and adds the spring force explicitly; with the
scenes' spring stiffness (``k dt^2`` far above a vertex mass) that explicit term alone makes
the scheme explode on the first step of a scripted pull, on either mesh.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
import scipy.sparse as sp

from fem3d.errors import SimulationError
from fem3d.physics.assembly import (
    assemble_gradient,
    count_inverted,
    kinetic_energy,
    potential_energy,
)
from fem3d.physics.constraints import Constraints
from fem3d.physics.model import Model, validate_dt
from fem3d.physics.springs import Pull
from fem3d.solve.linear import (
    AMGPreconditioner,
    NotPositiveDefinite,
    PreconditionedCG,
    SparseSPDSolver,
    choose_backend,
    iterations_per_decade,
    rigid_body_modes,
)

__all__ = [
    "State",
    "Pull",
    "StepStats",
    "NewtonResult",
    "ObjectiveTerm",
    "System",
    "NotPositiveDefinite",
    "linearly_implicit_euler",
    "implicit_euler",
    "newtons_method",
    "INTEGRATORS",
]



# ---------------------------------------------------------------------------------------------
# state, pull springs, statistics


@dataclass(frozen=True, eq=False)
class State:
    """Positions and velocities at one instant.

    Attributes
    ----------
    q : (n, 3) float64
        Positions.
    v : (n, 3) float64
        Velocities.
    t : float
        Time.
    step : int
        Number of steps taken to get here.
    """

    q: np.ndarray
    v: np.ndarray
    t: float = 0.0
    step: int = 0

    @classmethod
    def at_rest(cls, model: Model) -> State:
        """Rest positions, zero velocity, ``t = 0``."""
        return cls(q=model.X.copy(), v=np.zeros_like(model.X), t=0.0, step=0)


@dataclass
class StepStats:
    """What one step did.

    Attributes
    ----------
    newton_iterations : int
        Newton iterations (1 for the linearly-implicit scheme: one linear solve).
    gradient_norms : list of float
        Norm of the objective's gradient at each Newton iterate (implicit Euler).
    line_search_halvings : int
        Total step halvings in the line searches.
    factorizations, cg_iterations : int
        Numeric factorizations and preconditioned-CG iterations of the step's linear solves.
    shifted_factorizations : int
        Factorizations that needed a diagonal shift (indefinite Hessian).
    psd_fallbacks : int
        Newton iterations whose exact Hessian no shift made positive definite (with
        ``"reuse"``: that was indefinite), solved with the PSD-projected Hessian instead.
    gradient_tolerance : float
        The ``||g||`` Newton aimed for (implicit Euler); a converged step can end above it
        only where the line search met the objective's round-off.
    converged : bool
        Newton stopped on its tolerance (or at round-off), not on the iteration cap.
    amg_setups : int
        AMG hierarchies built during the step (``"amg"`` back end).
    lagged_matrices : int
        Newton iterations that solved with the previous iterate's Newton matrix instead of
        assembling one (``"reuse"``).
    seconds : dict of str to float
        Wall time of the step's parts (implicit Euler): ``"matrix"`` (Newton-matrix
        assembly), ``"factorize"``, ``"cg"`` (CG iterations, preconditioner included),
        ``"amg_setup"``, ``"objective"`` (energies and gradients, line search included).
    """

    newton_iterations: int = 0
    gradient_norms: list[float] = field(default_factory=list)
    line_search_halvings: int = 0
    shifted_factorizations: int = 0
    converged: bool = True
    factorizations: int = 0
    cg_iterations: int = 0
    psd_fallbacks: int = 0
    gradient_tolerance: float = 0.0
    amg_setups: int = 0
    lagged_matrices: int = 0
    seconds: dict[str, float] = field(default_factory=dict)

    def add_seconds(self, part: str, seconds: float) -> None:
        """Accumulate wall time into :attr:`seconds`."""
        self.seconds[part] = self.seconds.get(part, 0.0) + seconds


@dataclass
class NewtonResult:
    """Result of :func:`newtons_method`.

    Attributes
    ----------
    x : (N,) float64
        Final iterate.
    iterations : int
        Newton steps taken.
    gradient_norms : list of float
        ``||g||`` at each iterate visited, including the last.
    converged : bool
        Stopped because ``||g|| <= tol`` or the line search stalled at round-off.
    line_search_halvings : int
        Total halvings.
    """

    x: np.ndarray
    iterations: int
    gradient_norms: list[float]
    converged: bool
    line_search_halvings: int


# ---------------------------------------------------------------------------------------------
# sparse SPD solves on the fixed reduced pattern

#: From this many tets :class:`System` keeps no element-to-reduced-slot map (4 bytes per
#: element-matrix entry) and assembles Newton matrices on the full pattern, then gathers.
LEAN_ASSEMBLY_MIN_TETS = 250_000

#: ``"amg"``: rebuild the hierarchy when a solve needs more CG iterations than this per decade
#: of residual reduction (a fresh hierarchy needs about 3-4 on the swinging box; a setup costs
#: about 15 iterations).
AMG_ITERATIONS_PER_DECADE = 8.0
#: ``"amg"``: the loosest forcing term (relative CG residual) of the inexact Newton.
FORCING_MAX = 0.1
#: ``"amg"``: an iteration solves with the previous iteration's Newton matrix (no assembly)
#: when that iteration cut ``|g|`` by a factor below this fraction of the forcing term: the
#: Hessian's change is then far below the residual CG is asked for.
AMG_MATRIX_REUSE_FACTOR = 0.1
#: ``"amg"``: energy increases below this fraction of the objective are round-off in the line
#: search (:func:`newtons_method`'s ``roundoff_rtol``).
AMG_ROUNDOFF_RTOL = 1e-10
#: With ``roundoff_rtol``: a failed full step with ``||g||`` under this many tolerances is
#: round-off (measured floors on the swinging box: 10-20 tolerances).
ROUNDOFF_GRADIENT_FACTOR = 1e3

#: ``"reuse"``: the loosest relative CG residual; a solve is never tighter than reaching the
#: gradient tolerance in its Newton iteration needs (``0.5 tol / |g|``), nor looser than this.
REUSE_FORCING_MAX = 0.1
#: ``"reuse"``: a Newton iteration solves with the previous iterate's Newton matrix (no
#: assembly) when the gradient that lagging is estimated to leave is below this fraction of
#: the tolerance (:func:`implicit_euler`).
REUSE_LAG_FRACTION = 0.1

#: Shifts ``mu`` of an indefinite Newton matrix ``A + mu M``: ``1e-4, 1e-3, ...``.
SHIFT_LADDER_START = 1e-4
SHIFT_LADDER_GROWTH = 10.0


class System:
    """What the integrators reuse between steps for one model and constraint set.

    Parameters
    ----------
    model : Model
    constraints : Constraints
        Fixed vertices.
    solver_backend : str, optional
        Passed to :class:`fem3d.solve.linear.SparseSPDSolver` (default ``"auto"``).

    Attributes
    ----------
    pattern_free : (n_free_dofs, n_free_dofs) scipy.sparse.csr_matrix
        Sparsity of the reduced system ``P A P^T`` (fixed for the whole run: one symbolic
        analysis).
    mass_free : (n_free_dofs, n_free_dofs) scipy.sparse.csr_matrix
        ``P M P^T``.

    Notes
    -----
    :meth:`newton_matrix` assembles ``P (M + dt^2 H) P^T`` directly on the reduced pattern:
    each element Hessian entry goes straight to its reduced CSR slot (entries on fixed DOFs
    to a discarded sink slot), with ``dt^2`` folded into the element volumes, so no full
    ``3n x 3n`` matrix is built and reduced per Newton iteration.
    """

    def __init__(
        self,
        model: Model,
        constraints: Constraints,
        solver_backend: str = "auto",
        *,
        gravity=None,
        rayleigh_alpha=0.0,
        rayleigh_beta=0.0,
    ):
        if constraints.n_dofs != model.n_dofs:
            raise ValueError("constraints and model have different DOF counts")
        self.model = model
        self.gravity, self.rayleigh_alpha, self.rayleigh_beta = _validate_physics(
            model, gravity, rayleigh_alpha, rayleigh_beta)
        self.constraints = constraints
        self.free = constraints.free_dofs
        self.solver_backend = solver_backend
        self.mass_free = constraints.reduce_matrix(model.mass)
        self.pattern_free = constraints.reduce_matrix(model.pattern)
        self.pattern_free.data.setflags(write=False)
        # reduced-data slot of every full-pattern entry; entries on fixed DOFs -> sink slot
        nnz_free = self.pattern_free.nnz
        kept = constraints.kept_entries(model.pattern)
        self._free_slot = np.full(model.nnz, nnz_free, dtype=np.int32)
        self._free_slot[kept] = np.arange(nnz_free, dtype=np.int32)
        self._kept = kept
        # element entry -> reduced slot (4 bytes per element-matrix entry: 576 MB at 1e6 tets);
        # large meshes assemble on the full pattern and gather instead (the same sums)
        self._free_scatter = None
        if model.n_tets < LEAN_ASSEMBLY_MIN_TETS:
            self._free_scatter = self._free_slot[model.scatter]
            self._free_scatter.setflags(write=False)
        self._free_slot.setflags(write=False)
        self._scaled_volumes: tuple[float, np.ndarray] | None = None
        self._pull_slots: tuple[np.ndarray, np.ndarray] | None = None
        #: ``"amg"`` (AMG-preconditioned CG for backward Euler's Newton systems) or the direct
        #: back end (:func:`fem3d.solve.linear.choose_backend`: ``"auto"`` picks by size).
        self.linear_backend = choose_backend(solver_backend, constraints.n_free)
        self._direct_backend = "auto" if self.linear_backend == "amg" else solver_backend
        self._solver: SparseSPDSolver | None = None
        self._amg: AMGPreconditioner | None = None
        if self.linear_backend != "amg":  # with AMG a factorization is made only if needed
            self._solver = self._new_direct_solver(self.pattern_free)
        elif constraints.n_free:  # the AMG's aggregation: once per pattern, like an analysis
            self.amg.analyze(self.pattern_free)
        from fem3d.kernels.dispatch import spring_kernels

        self.spring = spring_kernels(backend=model.backend)
        self._keys: np.ndarray | None = None
        self.factorized_data: np.ndarray | None = None
        #: Shifted attempts of :meth:`factorize` (``mu = 1e-4 ... 1e8``) before giving up.
        self.max_shift_tries = 13
        # objective terms' Hessian entries outside pattern_free widen the solver's pattern
        self._ext: _ExtendedPattern | None = None
        #: Incremented whenever objective terms widen the solver's pattern (preconditioners
        #: built on an older pattern are stale).
        self.pattern_generation = 0
        self._base_keys: np.ndarray | None = None
        self._physics_cache()

    def with_model(self, model: Model) -> System:
        """Same constraints and solver (the pattern is shared), new material values."""
        new = object.__new__(System)
        new.__dict__.update(self.__dict__)
        new.model = model
        new.mass_free = self.constraints.reduce_matrix(model.mass)
        new._physics_cache()
        return new

    # -- gravity and Rayleigh damping ---------------------------------------------------------
    def _physics_cache(self) -> None:
        """Gravity force and the mass part of the damping matrix for the current model."""
        model = self.model
        self.gravity_force: np.ndarray | None = None
        if self.gravity is not None:
            f = model.mass @ np.tile(self.gravity, model.n_vertices)
            f.setflags(write=False)
            self.gravity_force = f
        alpha = self.rayleigh_alpha
        self._alpha_mass: np.ndarray | None = None
        if np.ndim(alpha) == 0:
            if alpha > 0:
                self._alpha_mass = float(alpha) * model.mass.data
        elif np.any(alpha > 0):
            # S M S with S = diag(sqrt(alpha)) per DOF: symmetric positive semi-definite, and
            # alpha M on every body whose vertices share one alpha
            s = np.repeat(np.sqrt(alpha), 3)
            pat = model.pattern
            rows = np.repeat(np.arange(pat.shape[0]), np.diff(pat.indptr))
            self._alpha_mass = model.mass.data * s[rows] * s[pat.indices]
        beta = self.rayleigh_beta
        self._beta_vol: np.ndarray | None = None
        if np.ndim(beta) == 0:
            if beta > 0:
                self._beta_vol = model.vol * float(beta)
        elif np.any(beta > 0):
            self._beta_vol = model.vol * beta

    @property
    def has_damping(self) -> bool:
        """Whether ``D = alpha M + beta K`` is non-zero."""
        return self._alpha_mass is not None or self._beta_vol is not None

    def damping_data(self, q: np.ndarray) -> np.ndarray | None:
        """CSR ``data`` on ``model.pattern`` of the Rayleigh damping matrix at ``q``.

        ``D = alpha M + beta K_psd(q)``: ``K_psd`` is the elastic Hessian with each
        element's ``dP/dF`` projected to positive semi-definite (generated ``hessian_psd``),
        scaled per tet by ``beta``. The integrators evaluate it at the start of the step
        (``q_t``: constant during the step, so backward Euler's dissipation stays a quadratic
        ``dt/2 v^T D v``). The projection keeps ``D`` positive semi-definite where the exact
        ``K`` is indefinite (compressed tets), so damping never feeds energy in; at rest it
        is the exact stiffness (the classic Rayleigh ``beta K``).

        Returns
        -------
        (nnz,) float64 or None
            None without damping.
        """
        if not self.has_damping:
            return None
        data = np.zeros(self.model.nnz)
        if self._beta_vol is not None:
            _hessian_into(self.model, "hessian_psd", q, self._beta_vol, self.model.scatter, data)
        if self._alpha_mass is not None:
            data += self._alpha_mass
        return data

    def gravity_energy(self, q: np.ndarray) -> float:
        """Gravity's potential ``-f_g . (q - X)`` (zero at rest; ``f_g = M g``)."""
        if self.gravity_force is None:
            return 0.0
        dq = np.asarray(q, dtype=np.float64).reshape(-1) - self.model.X.reshape(-1)
        return -float(self.gravity_force @ dq)

    # -- helpers ------------------------------------------------------------------------------
    def data_positions(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Positions in ``model.pattern.data`` of entries ``(rows, cols)`` (must exist)."""
        pat = self.model.pattern
        if self._keys is None:
            r = np.repeat(np.arange(pat.shape[0], dtype=np.int64), np.diff(pat.indptr))
            self._keys = r * pat.shape[1] + pat.indices
        want = np.asarray(rows, np.int64) * pat.shape[1] + np.asarray(cols, np.int64)
        pos = np.searchsorted(self._keys, want)
        found = self._keys[np.minimum(pos, self._keys.size - 1)] == want
        if not np.all(found & (pos < self._keys.size)):
            raise ValueError("entry not in the sparsity pattern")
        return pos

    def _pull_positions(self, pull: Pull) -> np.ndarray:
        """Full-pattern ``data`` positions of the pulled vertices' 3x3 diagonal blocks."""
        d = 3 * pull.vertices[:, None] + np.arange(3)
        rows = np.broadcast_to(d[:, :, None], (d.shape[0], 3, 3))
        cols = np.broadcast_to(d[:, None, :], (d.shape[0], 3, 3))
        return self.data_positions(rows.reshape(-1), cols.reshape(-1))

    def _pull_free_slots(self, pull: Pull) -> np.ndarray:
        """Reduced-data slots of :meth:`_pull_positions` (cached for the last vertex set: a
        dragged pull keeps its vertices from step to step)."""
        cached = self._pull_slots
        if cached is None or not np.array_equal(cached[0], pull.vertices):
            slots = self._free_slot[self._pull_positions(pull)]
            cached = (np.array(pull.vertices), slots)
            self._pull_slots = cached
        return cached[1]

    def reduced(self, data: np.ndarray) -> sp.csr_matrix:
        """``P A P^T`` of the full-pattern matrix with ``data``."""
        return self.constraints.reduce_matrix(self.model.csr(data))

    def _volumes_times(self, scale: float) -> np.ndarray:
        """``model.vol * scale`` (cached for the last ``scale``: it is ``dt^2``, fixed)."""
        cached = self._scaled_volumes
        if cached is None or cached[0] != scale or cached[1].shape != self.model.vol.shape:
            cached = (scale, self.model.vol * scale)
            cached[1].setflags(write=False)
            self._scaled_volumes = cached
        return cached[1]

    def newton_matrix(
        self, q: np.ndarray, dt: float, pull: Pull | None = None, *, psd: bool = False,
        damping: np.ndarray | None = None,
    ) -> sp.csr_matrix:
        """``P (M + dt^2 (H(q) + H_pull(q)) + dt D) P^T`` on :attr:`pattern_free`, assembled
        directly.

        Parameters
        ----------
        q : (3n,) or (n, 3) float64
            Positions where the Hessian ``H = d2V/dq2`` is evaluated.
        dt : float
            Time step.
        pull : Pull, optional
            Pull springs whose Hessian is added (the target is not a DOF).
        psd : bool, optional
            Use the generated ``hessian_psd`` kernel (``dP/dF`` projected per element).
        damping : (model.nnz,) float64, optional
            The damping matrix ``D`` on ``model.pattern`` (:meth:`damping_data`), added as
            ``dt D``.

        Returns
        -------
        (n_free_dofs, n_free_dofs) scipy.sparse.csr_matrix
            A new matrix (its data is not reused by later calls); may hold non-finite values
            when ``q`` is out of range.
        """
        model = self.model
        nnz_free = self.pattern_free.nnz
        kernel = "hessian_psd" if psd else "hessian"
        vol = self._volumes_times(dt * dt)
        data = np.empty(nnz_free + 1)  # the last slot is the sink of fixed-DOF entries
        data[nnz_free] = 0.0
        if self._free_scatter is not None:
            data[:nnz_free] = self.mass_free.data
            _hessian_into(model, kernel, q, vol, self._free_scatter, data)
        else:  # each kept entry gets the same contributions in the same order
            full = np.array(model.mass.data)
            _hessian_into(model, kernel, q, vol, model.scatter, full)
            np.take(full, self._kept, out=data[:nnz_free])
            del full
        if pull is not None and pull.vertices.size:
            q3 = np.asarray(q, dtype=np.float64).reshape(-1, 3)
            slots = self._pull_free_slots(pull)
            np.add.at(data, slots, (dt * dt) * pull.hessian_blocks(self.spring, q3).reshape(-1))
        if damping is not None:  # + dt D (backward Euler's dissipation dt/2 v^T D v)
            data[:nnz_free] += dt * damping[self._kept]
        A = sp.csr_matrix((data[:nnz_free], self.pattern_free.indices, self.pattern_free.indptr),
                          shape=self.pattern_free.shape, copy=False)
        A.has_sorted_indices = True
        return A

    def factorize(self, A_free: sp.csr_matrix, *, shift_hint: float = 0.0,
                  shifts: bool = True) -> float:
        """Factorize an SPD reduced matrix; shift it when it is not positive definite.

        Strategy for an indefinite Newton Hessian: try ``A``; on
        :class:`NotPositiveDefinite` factorize ``A + mu M`` (``M`` the reduced consistent mass
        matrix, ``mu = 1e-4, 1e-3, ...``; :meth:`SparseSPDSolver.factorize_shifted`), a
        Levenberg-Marquardt shift toward the mass-scaled gradient-descent direction, which is
        always a descent direction.

        Parameters
        ----------
        A_free : (n_free_dofs, n_free_dofs) scipy.sparse.csr_matrix
        shift_hint : float, optional
            ``> 0``: ``A`` is expected to be indefinite; start the ladder at this ``mu``
            instead of trying ``A`` itself (each failed attempt is a whole factorization).
        shifts : bool, optional
            False: try ``A`` itself only (no ladder; raises when it is not positive
            definite).

        Returns
        -------
        float
            The shift ``mu`` used (0.0: ``A`` itself).

        Raises
        ------
        SimulationError
            No shift up to ``mu = 1e8`` (:attr:`max_shift_tries`) works (e.g. a non-finite
            matrix, or tets close to inversion).
        """
        mu0, tries = SHIFT_LADDER_START, self.max_shift_tries
        mu_max = mu0 * SHIFT_LADDER_GROWTH ** (tries - 1)
        if not shifts:
            tries, shift_hint = 0, 0.0
        elif 0 < shift_hint <= mu_max:  # the rungs of the ladder from the hint up
            tries = 1 + math.floor(math.log(mu_max / shift_hint, SHIFT_LADDER_GROWTH) + 1e-9)
            mu0 = shift_hint
        A_free = self.on_solver_pattern(A_free)
        mass = self.on_solver_pattern(self.mass_free)
        try:
            mu = self.solver.factorize_shifted(
                A_free, mass, mu0=mu0, growth=SHIFT_LADDER_GROWTH, max_tries=tries,
                try_unshifted=mu0 == SHIFT_LADDER_START and shift_hint <= 0,
            )
        except NotPositiveDefinite as exc:
            raise SimulationError(f"could not factorize the system matrix: {exc}") from exc
        # the matrix actually factorized: a checkpoint rebuilds exactly this factor
        self.factorized_data = A_free.data + mu * mass.data if mu else np.array(A_free.data)
        return mu

    # -- objective terms' Hessian entries -----------------------------------------------------
    def on_solver_pattern(self, A: sp.csr_matrix) -> sp.csr_matrix:
        """``A`` (on :attr:`pattern_free` or the solver's pattern) on the solver's pattern."""
        ext = self._ext
        if ext is None or A.nnz == ext.pattern.nnz:
            return A
        if A.nnz != self.pattern_free.nnz:
            raise ValueError("matrix is on neither the reduced nor the extended pattern")
        data = np.zeros(ext.pattern.nnz)
        data[ext.base_pos] = A.data
        return ext.csr(data)

    def add_hessian(self, A: sp.csr_matrix, H, scale: float = 1.0) -> sp.csr_matrix:
        """``A + scale P H P^T``: an objective term's Hessian added to a reduced matrix.

        Parameters
        ----------
        A : (n_free_dofs, n_free_dofs) scipy.sparse.csr_matrix
            On :attr:`pattern_free` or the solver's current (extended) pattern.
        H : None, (3n, 3n) scipy.sparse matrix, or (rows, cols, values)
            The term's Hessian in full-DOF indices (duplicates are summed; entries on fixed
            DOFs are dropped). A matrix on ``model.pattern`` itself is added directly.
        scale : float
            ``dt^2`` for a position-space term in backward Euler's velocity unknowns.

        Returns
        -------
        scipy.sparse.csr_matrix
            On :attr:`pattern_free` when every entry falls inside it; otherwise on an extended
            pattern (``pattern_free`` plus the term's entries, made structurally symmetric).
            A new extended pattern replaces the solver (one symbolic analysis) and drops the
            kept factorization; the pattern only grows, so a term whose entries come and go
            (contact pairs) re-analyses only when an entry appears that was never seen.
        """
        if H is None:
            return A
        pat = self.model.pattern
        if sp.issparse(H):
            H = sp.csr_matrix(H)
            if H.shape != pat.shape:
                raise ValueError(f"term Hessian has shape {H.shape}, expected {pat.shape}")
            if H.nnz == pat.nnz and np.array_equal(H.indptr, pat.indptr) and \
                    np.array_equal(H.indices, pat.indices):
                A = self.on_solver_pattern(A)
                data = np.array(A.data)
                if self._ext is None:
                    data += scale * H.data[self._kept]
                else:
                    data[self._ext.base_pos] += scale * H.data[self._kept]
                return self._like(A, data)
            H = H.tocoo()
            rows, cols, vals = H.row, H.col, H.data
        else:
            rows, cols, vals = H
        new = self.constraints._new_index
        rows = new[np.asarray(rows, dtype=np.int64)]
        cols = new[np.asarray(cols, dtype=np.int64)]
        vals = scale * np.asarray(vals, dtype=np.float64)
        keep = (rows >= 0) & (cols >= 0)
        if not keep.all():
            rows, cols, vals = rows[keep], cols[keep], vals[keep]
        if rows.size == 0:
            return A
        nf = self.constraints.n_free
        keys = rows * nf + cols
        if self._ext is None:
            base = self._base_key_array()
            pos = np.minimum(np.searchsorted(base, keys), base.size - 1)
            if np.array_equal(base[pos], keys):
                data = np.array(A.data)
                np.add.at(data, pos, vals)
                return self._like(A, data)
        ext = self._ext
        if ext is None or not np.array_equal(
                ext.keys[np.minimum(np.searchsorted(ext.keys, keys), ext.keys.size - 1)], keys):
            ext = self._extend(keys)
        A = self.on_solver_pattern(A)
        data = np.array(A.data)
        np.add.at(data, np.searchsorted(ext.keys, keys), vals)
        return ext.csr(data)

    def _like(self, A: sp.csr_matrix, data: np.ndarray) -> sp.csr_matrix:
        B = sp.csr_matrix((data, A.indices, A.indptr), shape=A.shape, copy=False)
        B.has_sorted_indices = True
        return B

    def _base_key_array(self) -> np.ndarray:
        if self._base_keys is None:
            pf = self.pattern_free
            r = np.repeat(np.arange(pf.shape[0], dtype=np.int64), np.diff(pf.indptr))
            self._base_keys = r * pf.shape[1] + pf.indices
        return self._base_keys

    def _extend(self, keys: np.ndarray) -> _ExtendedPattern:
        """Widen the solver's pattern by ``keys`` (and their transposes); new analysis."""
        nf = self.constraints.n_free
        old = self._base_key_array() if self._ext is None else self._ext.keys
        r, c = np.divmod(keys, nf)
        union = np.union1d(old, np.concatenate([keys, c * nf + r]))
        rows, cols = np.divmod(union, nf)
        indptr = np.zeros(nf + 1, dtype=np.int64)
        np.cumsum(np.bincount(rows, minlength=nf), out=indptr[1:])
        pattern = sp.csr_matrix((np.zeros(union.size), cols.astype(np.int32), indptr),
                                shape=(nf, nf))
        pattern.has_sorted_indices = True
        ext = _ExtendedPattern(pattern=pattern, keys=union,
                               base_pos=np.searchsorted(union, self._base_key_array()))
        self._ext = ext
        self._solver = None if self.linear_backend == "amg" else \
            self._new_direct_solver(pattern)
        self.factorized_data = None
        self.pattern_generation += 1
        return ext

    def pattern_keys(self) -> np.ndarray:
        """Keys (``row * n_free + col``) of the solver's pattern when objective terms have
        widened it, else empty: what a checkpoint needs to rebuild the same pattern (and so
        the same fill-reducing ordering, bit for bit)."""
        return np.zeros(0, np.int64) if self._ext is None else self._ext.keys

    def restore_pattern(self, keys: np.ndarray) -> None:
        """Widen the solver's pattern to the saved :meth:`pattern_keys` (no-op when empty or
        already equal)."""
        keys = np.asarray(keys, dtype=np.int64).reshape(-1)
        if keys.size == 0 or (self._ext is not None and np.array_equal(self._ext.keys, keys)):
            return
        self._extend(keys)

    def refactorize_saved(self, data: np.ndarray) -> None:
        """Factorize the reduced matrix whose ``data`` :attr:`factorized_data` recorded (a
        checkpoint's preconditioner): the same matrix gives the same factor, so a resumed
        run that reuses factorizations across steps stays bit for bit identical."""
        data = np.asarray(data, dtype=np.float64)
        pat = self.pattern_free if self._ext is None else self._ext.pattern
        if data.shape != (pat.nnz,):
            raise ValueError(f"saved factorization data has shape {data.shape}, the reduced "
                             f"pattern {pat.nnz} entries")
        A = sp.csr_matrix((data.copy(), pat.indices, pat.indptr), shape=pat.shape)
        if self.linear_backend == "amg":
            self.amg_setup(A)
        else:
            self.factorize(A)

    def _new_direct_solver(self, pattern: sp.csr_matrix) -> SparseSPDSolver:
        solver = SparseSPDSolver(pattern, backend=self._direct_backend)
        if solver.backend == "superlu" and pattern is self.pattern_free and \
                self.mass_free.shape[0]:
            # SuperLU orders on its first factorization and takes another code path (explicit
            # permutation, natural order) afterwards. Factorizing once here makes every step
            # take the same path, so a fresh System (a run resumed from a checkpoint) computes
            # bit for bit what a long-lived one does.
            solver.factorize(self.mass_free)
        return solver

    @property
    def solver(self) -> SparseSPDSolver:
        """The sparse direct solver holding the last factorization (made on first use with
        the ``"amg"`` back end: the linearly-implicit scheme factorizes)."""
        if self._solver is None:
            pat = self.pattern_free if self._ext is None else self._ext.pattern
            self._solver = self._new_direct_solver(pat)
        return self._solver

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve with the last factorization."""
        return np.asarray(self.solver.solve(b)).reshape(-1)

    @property
    def amg(self) -> AMGPreconditioner:
        """The AMG hierarchy holder (near-nullspace: rigid-body modes of the free vertices at
        rest, so a hierarchy depends on its matrix alone)."""
        if self._amg is None:
            free_vertices = self.free[0::3] // 3
            self._amg = AMGPreconditioner(rigid_body_modes(self.model.X[free_vertices]))
        return self._amg

    def amg_setup(self, A_free: sp.csr_matrix) -> None:
        """Build the AMG hierarchy from ``A_free`` (on the solver's pattern);
        :attr:`factorized_data` records the matrix (a checkpoint rebuilds the same one)."""
        A_free = self.on_solver_pattern(A_free)
        self.amg.setup(A_free, pattern_key=self.pattern_generation)
        data = A_free.data.view()  # Newton matrices are new arrays: kept, not copied
        data.setflags(write=False)
        self.factorized_data = data

    @property
    def amg_current(self) -> bool:
        """A hierarchy exists for the solver's current pattern."""
        return self._amg is not None and self._amg.ready and \
            self._amg.pattern_key == self.pattern_generation


# ---------------------------------------------------------------------------------------------
# helpers


@dataclass(frozen=True, eq=False)
class _ExtendedPattern:
    """``pattern_free`` widened by objective terms' entries (``keys = row * n + col``)."""

    pattern: sp.csr_matrix
    keys: np.ndarray
    base_pos: np.ndarray

    def csr(self, data: np.ndarray) -> sp.csr_matrix:
        A = sp.csr_matrix((data, self.pattern.indices, self.pattern.indptr),
                          shape=self.pattern.shape, copy=False)
        A.has_sorted_indices = True
        return A


@dataclass(eq=False)
class _LaggedMatrix:
    """A Newton matrix kept for the next iterates of one step (``"reuse"``).

    Assembled at an iterate with gradient norm ``g_at``; ``expected`` is the iterate a full
    step along the direction solved with it reaches. At the first iterate after it (norm
    ``g_next``) Newton's quadratic model gives ``C = g_next / g_at^2`` (the next gradient of
    a fresh Newton step, ``C |g|^2``) and the contraction of a step solved with this older
    matrix: the matrix is off by about the step taken since, so such a step leaves about
    ``rho |g| + C |g|^2`` with ``rho = 2 g_next / g_at``.
    """

    A: sp.csr_matrix
    g_at: float
    expected: np.ndarray
    g_next: float = 0.0

    def lag(self, x: np.ndarray, gn: float, target: float) -> bool:
        """Whether to solve at ``x`` (gradient norm ``gn``) with this matrix: the last step
        was full and a step solved with it is estimated to leave a gradient below
        ``target``. (Lagging further, over more steps, does not pay: far from the solution
        the estimates are too optimistic, and each extra Newton iteration costs about an
        assembly.)"""
        if not np.array_equal(x, self.expected):
            return False  # the line search shortened the step: the estimates do not hold
        if not self.g_next:
            self.g_next = gn
        if not 0.0 < self.g_next < self.g_at:
            return False
        c = self.g_next / (self.g_at * self.g_at)
        rho = 2.0 * self.g_next / self.g_at
        return rho * gn + c * gn * gn <= target


def _hessian_into(model: Model, kernel: str, q: np.ndarray, vol: np.ndarray,
                  scatter: np.ndarray, out: np.ndarray) -> None:
    """Add the element Hessians (``kernel``: ``"hessian"`` or ``"hessian_psd"``, element
    volumes ``vol``, i.e. any per-element scale folded in) into ``out[scatter]``."""
    if model.mat.has_assemble(kernel):
        getattr(model.mat, f"{kernel}_assemble")(
            q, model.T, model.dphi_dX, vol, model.params, scatter, out)
    else:
        x_e = np.take(np.asarray(q, dtype=np.float64).reshape(-1, 3), model.T, axis=0)
        H = getattr(model.mat, kernel)(x_e, model.dphi_dX, vol, model.params)
        out += np.bincount(scatter, weights=H.reshape(-1), minlength=out.size)


@dataclass
class _NewtonProgress:
    """The gradient norms one backward-Euler step's Newton directions see: the first sets the
    tolerance ``newtons_method`` aims for (``max(atol, rtol |g_0|)``), the last one the
    Eisenstat-Walker ratio of the next iteration."""

    atol: float
    rtol: float
    tol: float = 0.0
    previous: float = 0.0

    def observe(self, gn: float) -> float:
        """Record ``|g_k|``; returns ``|g_k-1|`` (0 at the first iteration)."""
        if not self.tol:
            self.tol = max(self.atol, self.rtol * gn)
        previous, self.previous = self.previous, gn
        return previous


def _eisenstat_walker(gn: float, gn_prev: float) -> float:
    """Eisenstat and Walker's choice 2 (``gamma = 0.9``, ``alpha = 2``): ``0.9 (|g_k| /
    |g_k-1|)^2``; 0 without a previous iteration."""
    return 0.9 * (gn / gn_prev) ** 2 if gn_prev > 0.0 else 0.0


def _forcing_term(gn: float, gn_prev: float, eta_prev: float, tol: float,
                  forcing_max: float) -> float:
    """The relative CG residual of an inexact Newton iteration (Eisenstat and Walker's choice
    2, ``gamma = 0.9``, ``alpha = 2``): ``eta = 0.9 (|g_k| / |g_k-1|)^2``, at most
    ``forcing_max`` (the first iteration's), not much below ``0.9 eta_k-1^2`` while that is
    above 0.1 (no sudden over-solving after one lucky step), and never tighter than reaching
    ``|g| <= tol`` from ``|g_k|`` needs (``0.5 tol / |g_k|``).

    Loose while Newton is far from the solution, tightening as fast as Newton converges:
    each decade of gradient costs about one decade of CG residual, so a too loose term costs
    Newton iterations (an assembly and line search each) and a too tight one CG iterations.
    On the 1e5-tet swinging box: 4 Newton iterations and 30 CG iterations, where the older
    ``min(0.1, sqrt(|g_k| / |g_0|))`` needed 6 and 30.
    """
    if gn <= 0.0:
        return forcing_max
    if gn_prev > 0.0:
        eta = _eisenstat_walker(gn, gn_prev)
        floor = 0.9 * eta_prev * eta_prev
        if floor > 0.1:
            eta = max(eta, floor)
        eta = min(forcing_max, eta)
    else:
        eta = forcing_max
    return min(forcing_max, max(eta, 0.5 * tol / gn))


def _validate_physics(model: Model, gravity, alpha, beta):
    """Checked gravity ``(3,)`` (or None), Rayleigh ``alpha`` (float or ``(n,)``) and
    ``beta`` (float or ``(m,)``); ParameterError names the bad one."""
    from fem3d.errors import ParameterError

    g = None
    if gravity is not None:
        g = np.array(gravity, dtype=np.float64).reshape(-1)
        if g.shape != (3,) or not np.isfinite(g).all():
            raise ParameterError(f"gravity must be 3 finite numbers, got {gravity!r}")
        if not g.any():
            g = None
        else:
            g.setflags(write=False)

    def coefficient(value, name: str, count: int, what: str):
        a = np.asarray(value, dtype=np.float64)
        if a.ndim == 0:
            v = float(a)
            if not math.isfinite(v) or v < 0:
                raise ParameterError(f"{name} must be a finite number >= 0, got {v}")
            return v
        if a.shape != (count,):
            raise ParameterError(f"{name} must be a number or one per {what} ({count},), got "
                                 f"shape {a.shape}")
        if not (np.isfinite(a).all() and (a >= 0).all()):
            bad = int(np.flatnonzero(~(np.isfinite(a) & (a >= 0)))[0])
            raise ParameterError(f"{name} of {what} {bad} must be finite and >= 0, got {a[bad]}")
        a = a.copy()
        a.setflags(write=False)
        return a

    return (g, coefficient(alpha, "rayleigh_alpha", model.n_vertices, "vertex"),
            coefficient(beta, "rayleigh_beta", model.n_tets, "tet"))


def _check_finite(q: np.ndarray, v: np.ndarray, step: int, what: str) -> None:
    if not (np.isfinite(q).all() and np.isfinite(v).all()):
        raise SimulationError(
            f"{what} exploded: the new state has non-finite positions or velocities "
            "(state left at the last good step)",
            step=step,
        )


def _gradient_norm(g: np.ndarray) -> float:
    """``||g||`` without overflow for finite ``g``; raises on a non-finite gradient."""
    if not np.isfinite(g).all():
        raise SimulationError(
            "Newton's method: the gradient is not finite (forces overflow: parameters or "
            "state out of range)"
        )
    s = float(np.abs(g).max()) if g.size else 0.0
    n = s * float(np.linalg.norm(g / s)) if s > 0 else 0.0
    if not math.isfinite(n):
        raise SimulationError("Newton's method: the gradient norm overflows")
    return n


@dataclass(frozen=True, eq=False)
class _Pins:
    """The fixed vertices over one step: end positions ``p`` and velocities ``v_c``."""

    p: np.ndarray  # (n_fixed, 3) positions at the end of the step
    q_base: np.ndarray  # (3n,) q_t with the fixed DOFs at p
    v_fixed: np.ndarray | None  # (3n,) v_c on fixed DOFs, 0 on free ones (None: static pins)
    v_t_fixed: np.ndarray | None  # (3n,) v_t on fixed DOFs, 0 on free ones


def _pins(system: System, state: State, dt: float, fixed_positions) -> _Pins:
    """Where the fixed vertices go this step (``fixed_positions`` None: they stay)."""
    c = system.constraints
    fv = c.fixed_vertices
    q_t = state.q.reshape(-1)
    fixed_dofs = (3 * fv[:, None] + np.arange(3)).reshape(-1)
    v_t_fixed = None
    if fixed_dofs.size and np.any(state.v.reshape(-1)[fixed_dofs]):
        v_t_fixed = np.zeros(c.n_dofs)
        v_t_fixed[fixed_dofs] = state.v.reshape(-1)[fixed_dofs]
    if fixed_positions is None:
        v_fixed = None if v_t_fixed is None else np.zeros(c.n_dofs)
        return _Pins(state.q[fv], q_t, v_fixed, v_t_fixed)
    from fem3d.errors import ParameterError

    p = np.array(fixed_positions, dtype=np.float64)
    if p.shape != (fv.size, 3):
        raise ParameterError(f"fixed_positions must have shape ({fv.size}, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise ParameterError("fixed_positions are not finite")
    q_base = q_t.copy()
    q_base[fixed_dofs] = p.reshape(-1)
    v_fixed = np.zeros(c.n_dofs)
    v_fixed[fixed_dofs] = (p.reshape(-1) - q_t[fixed_dofs]) / dt
    if v_t_fixed is None:
        v_t_fixed = np.zeros(c.n_dofs)
    return _Pins(p, q_base, v_fixed, v_t_fixed)


def _new_state(system: System, state: State, v_free: np.ndarray, dt: float) -> State:
    v = system.constraints.expand_zero(v_free).reshape(-1, 3)
    q = state.q + dt * v
    if system.constraints.fixed_vertices.size:  # fixed vertices stay exactly at rest
        fv = system.constraints.fixed_vertices
        q[fv] = system.constraints.x0.reshape(-1, 3)[fv]
    return State(q=q, v=v, t=state.t + dt, step=state.step + 1)


def _place_pins(system: System, new: State, pins: _Pins) -> State:
    """``new`` with the fixed vertices where ``pins`` puts them (exactly) and their velocity."""
    fv = system.constraints.fixed_vertices
    if fv.size == 0:
        return new
    q = np.array(new.q)
    q[fv] = pins.p
    v = new.v
    if pins.v_fixed is not None:
        v = np.array(v)
        v[fv] = pins.v_fixed.reshape(-1, 3)[fv]
    return State(q=q, v=v, t=new.t, step=new.step)


# ---------------------------------------------------------------------------------------------
# linearly-implicit Euler


def linearly_implicit_euler(
    system: System,
    state: State,
    dt: float,
    pull: Pull | None = None,
    *,
    energy_bound: float | None = None,
    linearize_pull: bool = True,
    fixed_positions: np.ndarray | None = None,
) -> tuple[State, StepStats]:
    """One linearly-implicit Euler step.

    Solves ``(M - dt^2 K(q_t) + dt D) v+ = M v_t + dt (f(q_t) + M g)`` on the free DOFs
    (``K = -H``, ``D`` the Rayleigh damping :meth:`System.damping_data` at ``q_t``, ``g``
    gravity) and sets ``q+ = q_t + dt v+``. The pull springs' force is part of ``f`` and their
    stiffness part of ``K``. Moving pins: the fixed DOFs' velocity ``v_c = (p - q_t) / dt``
    is known, so the free rows solve ``A_ff v_f = rhs_f - A_fc v_c``.

    Parameters
    ----------
    system : System
    state : State
        ``q, v`` of shape ``(n, 3)``.
    dt : float
        Time step (> 0).
    pull : Pull, optional
        Active pull springs.
    energy_bound : float, optional
        Runaway threshold: if the new total energy (kinetic + strain + pull) exceeds it, raise.
        :class:`fem3d.simulation.Simulation` passes 1000 x the energy put in so far.
    linearize_pull : bool, optional
        Include the pull springs' stiffness in the matrix (default True). False gives the
        assignment's variant (spring force explicit), which explodes for the scenes' pulls.
    fixed_positions : (n_fixed, 3) float64, optional
        Positions of the fixed vertices at the end of the step (moving pins; None: they stay
        where they are). The fixed vertices land on them exactly.

    Returns
    -------
    (State, StepStats)

    Raises
    ------
    SimulationError
        ``"... exploded ..."``: non-finite state, inverted tets (non-finite energy) or energy
        above ``energy_bound``. The input ``state`` is untouched.
    """
    dt = validate_dt(dt)
    model, c = system.model, system.constraints
    qf, vf = state.q.reshape(-1), state.v.reshape(-1)
    pins = _pins(system, state, dt, fixed_positions)
    f = -assemble_gradient(model, qf)
    if pull is not None:
        f -= pull.gradient(system.spring, state.q)
    if system.gravity_force is not None:
        f += system.gravity_force
    damping = system.damping_data(qf)
    A = system.newton_matrix(qf, dt, pull if linearize_pull else None, damping=damping)
    rhs = model.mass @ vf + dt * f
    if pins.v_fixed is not None:  # move A_fc v_c to the right-hand side
        vc = pins.v_fixed
        Avc = model.mass @ vc
        hdata = np.zeros(model.nnz)
        _hessian_into(model, "hessian", qf, system._volumes_times(dt * dt), model.scatter,
                      hdata)
        Avc += model.csr(hdata) @ vc
        if damping is not None:
            Avc += dt * (model.csr(damping) @ vc)
        rhs = rhs - Avc
    stats = StepStats(newton_iterations=1)
    if not (np.isfinite(A.data).all() and np.isfinite(rhs).all()):
        raise SimulationError(
            "linearly-implicit Euler exploded: non-finite forces or stiffness", step=state.step
        )
    try:
        stats.shifted_factorizations = int(system.factorize(A) > 0)
    except SimulationError as exc:
        raise SimulationError(
            f"linearly-implicit Euler exploded: {exc.reason}", step=state.step
        ) from exc
    v_free = system.solve(c.restrict(rhs))
    new = _place_pins(system, _new_state(system, state, v_free, dt), pins)
    _check_finite(new.q, new.v, state.step, "linearly-implicit Euler")
    total = kinetic_energy(model, new.v) + potential_energy(model, new.q)
    if pull is not None:
        total += pull.energy(system.spring, new.q)
    if system.gravity_force is not None:
        total += system.gravity_energy(new.q)
    if not math.isfinite(total):
        n_inv = count_inverted(model, new.q)
        raise SimulationError(
            f"linearly-implicit Euler exploded: the energy is not finite ({n_inv} of "
            f"{model.n_tets} tets inverted); try --integrator implicit or a smaller dt",
            step=state.step,
        )
    if energy_bound is not None and total > energy_bound:
        raise SimulationError(
            f"linearly-implicit Euler exploded: total energy {total:.3g} exceeds the runaway "
            f"bound {energy_bound:.3g}; try --integrator implicit or a smaller dt",
            step=state.step,
        )
    return new, stats


# ---------------------------------------------------------------------------------------------
# Newton's method


def newtons_method(
    x0: np.ndarray,
    energy: Callable[[np.ndarray], float],
    gradient: Callable[[np.ndarray], np.ndarray],
    newton_direction: Callable[[np.ndarray, np.ndarray], np.ndarray],
    *,
    max_iterations: int | None = 5,
    rtol: float = 1e-10,
    atol: float = 0.0,
    alpha: float = 1.0,
    p: float = 0.5,
    c: float = 1e-8,
    max_halvings: int = 30,
    decrement_rtol: float = 1e-14,
    energy_scale: float = 0.0,
    on_no_step: Callable[[np.ndarray, np.ndarray], None] | None = None,
    max_step: Callable[[np.ndarray, np.ndarray], float] | None = None,
    converged_step: Callable[[np.ndarray, np.ndarray], bool] | None = None,
    after_step: Callable[[np.ndarray], bool] | None = None,
    roundoff_rtol: float = 0.0,
    f0: float | None = None,
) -> NewtonResult:
    """Minimise ``energy`` by Newton's method with a backtracking (Armijo) line search.

    Parameters
    ----------
    x0 : (N,) float64
        Start; ``energy(x0)`` must be finite.
    energy : callable ``(N,) -> float``
        Objective; ``+inf`` marks an inadmissible point (e.g. an inverted tet).
    gradient : callable ``(N,) -> (N,)``
    newton_direction : callable ``(x, g) -> d``
        Solves ``H(x) d = -g`` with an SPD (possibly shifted) Hessian.
    max_iterations : int or None, optional
        Cap on Newton steps (default 5, the assignment's); None: no cap (stops at tolerance
        or round-off).
    rtol, atol : float, optional
        Stop when ``||g|| <= max(atol, rtol ||g(x0)||)``.
    alpha, p, c : float, optional
        Initial step, shrink factor and Armijo constant: accept ``x + a d`` when
        ``E(x + a d) <= E(x) + c a g.d``; otherwise ``a *= p``.
    max_halvings : int, optional
        Line-search trials before giving up.
    decrement_rtol : float, optional
        When the Newton decrement ``-g.d`` is below ``decrement_rtol (|E(x)| +
        energy_scale)`` the decrease left is at the objective's round-off, where Armijo tests
        are noise: the full step is then taken if it is admissible and reduces ``||g||``;
        otherwise Newton stops (converged at round-off).
    energy_scale : float, optional
        The magnitude of the objective's summands when it is a sum of terms that cancel (an
        elastic energy near rest sums element energies whose own round-off is relative to
        ``E vol``, not to their tiny total); default 0: ``|E(x)|`` alone sets the round-off.
    on_no_step : callable ``(x, d)``, optional
        Called when every trial point was inadmissible (``+inf``); expected to raise. When it
        is None or returns, Newton stops at the current ``x``.
    max_step : callable ``(x, d) -> float``, optional
        Largest admissible step fraction along ``d`` (e.g. continuous collision detection);
        the line search starts at ``min(alpha, max_step(x, d))`` and backtracks from there.
        A non-positive value stops Newton at ``x`` (not converged).
    converged_step : callable ``(x, d) -> bool``, optional
        A further stopping rule on the Newton direction (IPC's velocity-based tolerance),
        from the second iteration on (the first step is always taken): True stops Newton at
        ``x``, converged.
    after_step : callable ``(x) -> bool``, optional
        Called at every accepted iterate; True means the objective itself changed there
        (IPC's adaptive barrier stiffness), so its value is re-evaluated.
    roundoff_rtol : float, optional
        ``> 0``: when the full (clamped) step fails the Armijo test but raises the energy by
        at most ``roundoff_rtol |E|`` (round-off for an inexact Newton direction near the
        solution), accept it if it reduces ``||g||``; and when ``||g||`` is already within
        :data:`ROUNDOFF_GRADIENT_FACTOR` of the tolerance (where a step changes the energy by
        less than its round-off, which scales with its terms rather than with ``|E|``), accept
        it whenever it is finite and reduces ``||g||``, or else stop (converged at round-off)
        rather than halve through noise. 0 (default): plain backtracking.
    f0 : float, optional
        ``energy(x0)`` when the caller has it already (saves one evaluation).

    Returns
    -------
    NewtonResult
        A line search that finds only finite, non-decreasing trial points means round-off
        has been reached: Newton stops there and reports ``converged=True``.
    """
    x = np.array(x0, dtype=np.float64)
    fx = energy(x) if f0 is None else float(f0)
    g = gradient(x)
    gn = _gradient_norm(g)
    norms = [gn]
    tol = max(atol, rtol * gn)
    halvings = 0
    it = 0
    while max_iterations is None or it < max_iterations:
        if gn <= tol:
            return NewtonResult(x, it, norms, True, halvings)
        d = newton_direction(x, g)
        slope = float(g @ d)
        if not (slope < 0 and np.isfinite(d).all()):  # not a descent direction: fall back
            d = -g
            slope = -gn * gn
        if converged_step is not None and it > 0 and converged_step(x, d):
            return NewtonResult(x, it, norms, True, halvings)
        a0 = alpha
        if max_step is not None:
            a0 = min(alpha, float(max_step(x, d)))
            if not a0 > 0.0:
                return NewtonResult(x, it, norms, False, halvings)
        if -slope <= decrement_rtol * (abs(fx) + energy_scale):
            # The predicted decrease is below the objective's round-off, so Armijo tests are
            # noise: take the full step while it is admissible and shrinks the gradient.
            xt = x + d if a0 == 1.0 else x + a0 * d
            ft = energy(xt)
            gt = gradient(xt) if math.isfinite(ft) else None
            gtn = math.inf if gt is None or not np.isfinite(gt).all() else _gradient_norm(gt)
            if not gtn < gn:
                return NewtonResult(x, it, norms, True, halvings)
            x, fx, g, gn = xt, ft, gt, gtn
            norms.append(gn)
            it += 1
            continue
        a = a0
        accepted = False
        any_finite = False
        gt = None
        for _ in range(max_halvings):
            xt = x + a * d
            if not (xt != x).any():
                break  # the step vanished in x's round-off: accepting it would loop forever
            ft = energy(xt)
            if math.isfinite(ft):
                any_finite = True
                if ft <= fx + c * a * slope:
                    accepted = True
                    break
                if roundoff_rtol and a == a0:
                    # near the tolerance a Newton step changes the energy by less than its
                    # round-off, which scales with its terms (elastic, kinetic), not with |E|
                    end_game = gn <= ROUNDOFF_GRADIENT_FACTOR * tol
                    if end_game or ft <= fx + roundoff_rtol * abs(fx):
                        # the energy cannot tell the trial from x: judge by the gradient
                        gt = gradient(xt)
                        if np.isfinite(gt).all() and _gradient_norm(gt) < gn:
                            accepted = True
                            break
                        gt = None
                    if end_game:
                        # a full step that does not shrink the gradient there is the
                        # gradient's round-off: stop rather than halve through noise
                        return NewtonResult(x, it, norms, True, halvings)
            a *= p
            halvings += 1
        if not accepted:
            if not any_finite and on_no_step is not None:
                on_no_step(x, d)
            return NewtonResult(x, it, norms, any_finite, halvings)
        x, fx = xt, ft
        if after_step is not None and after_step(x):
            fx = energy(x)  # the objective changed at x (barrier stiffness)
            gt = None
        g = gradient(x) if gt is None else gt
        gn = _gradient_norm(g)
        norms.append(gn)
        it += 1
    return NewtonResult(x, it, norms, gn <= tol, halvings)


# ---------------------------------------------------------------------------------------------
# backward Euler


@runtime_checkable
class ObjectiveTerm(Protocol):
    """A term added to backward Euler's objective (contact barrier, friction, ...).

    Everything is in positions ``q`` (full ``(3n,)`` vertex-major vector, fixed DOFs
    included); :func:`implicit_euler` applies the chain rule to its velocity unknowns
    (``q = q_base + dt P^T v_free``: gradient ``dt P g``, Hessian ``dt^2 P H P^T``).

    Required: ``energy(q) -> float`` (``+inf`` marks an inadmissible point) and
    ``gradient(q) -> (3n,)``. Optional:

    ``hessian(q)``
        ``None``, a ``(3n, 3n)`` scipy.sparse matrix, or ``(rows, cols, values)`` triplets in
        full-DOF indices (duplicates summed); symmetric positive semi-definite is the term's
        job (e.g. a PSD-projected barrier Hessian). Entries outside the mesh's pattern widen
        the solver's pattern (:meth:`System.add_hessian`).
    ``max_step(q, dq) -> float``
        Largest admissible fraction of the position increment ``dq`` (continuous collision
        detection); clamps the line search before it backtracks.
    ``requires_convergence`` (attribute, bool)
        True: the step runs Newton to its tolerance instead of stopping at the iteration cap
        (``converged_max_iterations`` caps it).

    Per-step hooks (contact, :class:`fem3d.physics.contact.ContactTerm`):

    ``begin_step(q_t, v_t, q_base, t, dt, step=)``
        Called once before Newton (lag friction, place obstacles, check the pins' motion).
    ``initialize_stiffness(q, grad_rest, average_mass)``
        Called at Newton's start with the gradient of the rest of the objective in positions.
    ``after_iteration(q) -> bool``
        Called at every accepted iterate; True when the term's energy changed there.
    ``newton_converged(dq) -> bool``
        Stopping rule on the Newton step's position change ``dq``; Newton stops when every
        term that has it agrees (and at the gradient tolerance as before).

    With a ``max_step`` term the Newton start is ``v_t`` clamped by ``max_step`` from
    ``v = 0`` (a start that tunnelled through an obstacle would be finite but wrong).
    """

    def energy(self, q: np.ndarray) -> float: ...

    def gradient(self, q: np.ndarray) -> np.ndarray: ...


def implicit_euler(
    system: System,
    state: State,
    dt: float,
    pull: Pull | None = None,
    *,
    fixed_positions: np.ndarray | None = None,
    terms: Sequence[ObjectiveTerm] = (),
    max_iterations: int | None = 5,
    rtol: float = 1e-10,
    atol_factor: float = 1e-12,
    hessian: str = "exact",
    linear_solver: str = "direct",
    cg_rtol: float = 1e-6,
    cg_maxiter: int = 16,
    converged_max_iterations: int = 100,
    amg_maxiter: int = 200,
    amg_budget: float = AMG_ITERATIONS_PER_DECADE,
    forcing_max: float = FORCING_MAX,
) -> tuple[State, StepStats]:
    """One backward (implicit) Euler step as an energy minimisation.

    ``v+ = argmin_v E(v)`` over the free DOFs, ``q(v) = q_base + dt P^T v`` (``q_base``:
    ``q_t`` with the fixed DOFs at their end-of-step positions), with

    ``E(v) = 1/2 dv^T M dv + V(q) + V_pull(q) - dt f_g . v + dt/2 v^T D v + sum_i T_i(q)``

    (``dv = v - v_t`` over all DOFs, the fixed ones' velocity ``(p - q_t)/dt`` prescribed;
    ``f_g = M g`` gravity, as the potential ``-f_g . q`` relative to ``q_t``; ``D`` the
    Rayleigh damping at ``q_t``, :meth:`System.damping_data`; ``T_i`` the objective terms),
    minimised by :func:`newtons_method` with gradient ``M dv + dt (dV/dq + ...) - dt f_g +
    dt D v`` and Hessian ``M + dt^2 (H + H_pull + sum H_i) + dt D``. Its minimiser is the
    backward-Euler update ``M (v+ - v_t) = dt (f(q+) + f_g - D v+)``, and the line search sees
    this one energy.

    Indefinite Hessian (compressed Neo-Hookean tets): the factorization is tried as is and,
    when it is not positive definite, retried with a diagonal shift ``tau diag(M)`` of
    increasing ``tau`` (see :meth:`System.factorize`), which always gives a descent
    direction; if no shift of the ladder works (tets close to inversion), the iteration uses
    the PSD-projected Hessian (``hessian_psd``), which is always positive definite. Any trial
    point with an inverted tet (``det F <= 0``; unless ``model.allows_inversion``) or a
    non-finite energy counts as ``+inf`` in the line search, so accepted states never invert.

    Parameters
    ----------
    system : System
        Holds gravity and damping.
    state : State
    dt : float
    pull : Pull, optional
    fixed_positions : (n_fixed, 3) float64, optional
        Positions of the fixed vertices at the end of the step (moving pins); None: they
        stay where they are. The free DOFs see them in the elastic energy; the fixed
        vertices land on them exactly.
    terms : sequence of ObjectiveTerm, optional
        Further terms of the objective (see :class:`ObjectiveTerm`).
    max_iterations : int or None, optional
        Newton iterations per step (default 5; None: until converged).
    rtol : float, optional
        Relative gradient tolerance for stopping early.
    atol_factor : float, optional
        Absolute gradient tolerance as a fraction of the scale ``dt E L^2`` (``L`` the
        diagonal of the rest bounding box; ``E L^2`` a force): gradients below it are
        round-off.
    hessian : {"exact", "psd"}, optional
        ``"exact"`` (default): the true Hessian, quadratic convergence, shifted when
        indefinite. ``"psd"``: per-element ``dP/dF`` projected to positive semi-definite
        (generated ``hessian_psd`` kernel), always SPD, linear convergence near the solution.
    linear_solver : {"direct", "reuse", "amg"}, optional
        How the Newton systems are solved; a :class:`System` whose back end is ``"amg"``
        (``System(..., "amg")``, or ``"auto"`` above
        :data:`fem3d.solve.linear.AMG_AUTO_MIN_FREE_DOFS` free DOFs) always uses ``"amg"``.
        ``"amg"``: an inexact Newton: CG preconditioned by a smoothed-aggregation AMG
        V-cycle (:class:`fem3d.solve.linear.AMGPreconditioner`), solved to the forcing term
        ``eta_k = min(forcing_max, 0.9 (|g_k| / |g_k-1|)^2)`` (Eisenstat-Walker: loose early,
        tighter as Newton converges; never tighter than needed to reach the gradient
        tolerance, whose value is unchanged; :func:`_forcing_term`). The hierarchy is kept
        across iterations and steps and rebuilt when the last solve needed more than
        ``amg_budget`` CG iterations per decade of residual reduction or did not converge
        within ``amg_maxiter``, and when an objective term widened the pattern. An
        indefinite Newton matrix (CG meets negative curvature) is replaced by the
        PSD-projected one for the rest of the step (``psd_fallbacks``).
        ``"direct"`` (default): factorize ``M + dt^2 H`` at every Newton iteration.
        ``"reuse"``: solve by conjugate gradients preconditioned with the last factorization
        (:class:`fem3d.solve.linear.PreconditionedCG`), kept across iterations and steps, and
        refactorize when CG does not converge within ``cg_maxiter`` iterations, meets
        negative curvature or returns a non-descent direction, when the step's previous
        solve needed more than ``cg_maxiter / 2`` iterations (the preconditioner has aged),
        or when no factorization exists yet. An inexact Newton: it converges to the same
        gradient tolerance. Its CG solves stop at the forcing term
        ``max(cg_rtol, min(REUSE_FORCING_MAX, max(0.9 (|g_k| / |g_k-1|)^2, 0.5 tol /
        |g_k|)))``: tight where Newton converges fast, loose where it crawls (far from the
        solution) and never tighter than reaching the tolerance in this iteration needs.
        Without objective terms, an iteration right after a full step solves with the
        previous iterate's Newton matrix instead of assembling one when the step that
        lagging leaves is estimated below :data:`REUSE_LAG_FRACTION` of the tolerance
        (``lagged_matrices``). An iteration whose exact Hessian is indefinite (CG meets
        negative curvature, or its factorization fails) factorizes the PSD-projected Hessian
        instead of climbing the shift ladder (``psd_fallbacks``); after two such iterations in
        a row the rest of the step assembles the PSD-projected one directly. With ``"direct"``
        and ``"reuse"`` the line search judges round-off against the strain energy's scale
        ``E vol`` (``energy_scale`` of :func:`newtons_method`).
        :attr:`System.factorized_data` records the factorized matrix so that a checkpoint
        can rebuild the same preconditioner.
    cg_rtol : float, optional
        The tightest relative residual of the CG solves with ``"reuse"`` (see the forcing
        term above).
    cg_maxiter : int, optional
        CG iterations per solve before refactorizing (default 16: about the cost of one
        factorization on armadillo-class meshes of 1e3 to 1e5 tets, where a factorization
        costs 10 to 40 CG iterations; ``python -m bench.newton_step``).
    converged_max_iterations : int, optional
        The iteration cap when a term sets ``requires_convergence`` (default 100).
    amg_maxiter, amg_budget, forcing_max : optional
        ``"amg"``: CG iterations per solve, the rebuild threshold in iterations per decade
        (:data:`AMG_ITERATIONS_PER_DECADE`) and the loosest forcing term
        (:data:`FORCING_MAX`).

    Returns
    -------
    (State, StepStats)

    Raises
    ------
    SimulationError
        No acceptable Newton step (every line-search trial inverts tets; the message says
        how many at the full step), or a non-finite state.
    """
    dt = validate_dt(dt)
    if hessian not in ("exact", "psd"):
        raise ValueError(f"hessian must be 'exact' or 'psd', got {hessian!r}")
    psd = hessian == "psd"
    if linear_solver not in ("direct", "reuse", "amg"):
        raise ValueError(
            f"linear_solver must be 'direct', 'reuse' or 'amg', got {linear_solver!r}")
    use_amg = linear_solver == "amg" or system.linear_backend == "amg"
    if use_amg:
        linear_solver = "amg"
    terms = tuple(terms)
    if max_iterations is not None and any(
            getattr(t, "requires_convergence", False) for t in terms):
        max_iterations = max(max_iterations, converged_max_iterations)
    pcg = None
    lag_matrices = linear_solver == "reuse" and not terms
    if linear_solver == "reuse":
        pcg = PreconditionedCG(system.solver, rtol=cg_rtol, maxiter=cg_maxiter,
                               refactorize_on_stall=False)
    last_cg = [0]  # CG iterations of this step's last solve (0 after a factorization)
    # reuse: the last Newton matrix (lagging, see reuse_direction)
    last_newton: list = [None]
    # reuse: [the PSD-projected Hessian for the rest of the step, consecutive iterations
    # whose exact Hessian was indefinite]
    reuse_psd = [psd, 0]
    shift_hint = [0.0]  # where this step's next shift ladder starts (0: unshifted first)
    model, c, spring = system.model, system.constraints, system.spring
    check_inversion = not getattr(model, "allows_inversion", False)
    free = c.free_dofs
    q_t = state.q.reshape(-1)
    v_t = state.v.reshape(-1)
    mass_free = system.mass_free
    vt_free = v_t[free]
    stats = StepStats()
    L = float(np.linalg.norm(np.ptp(model.X, axis=0)))
    atol = atol_factor * dt * model.E * L * L
    progress = _NewtonProgress(atol, rtol)  # the gradient norms the directions see
    # The direct and "reuse" line searches judge round-off by the strain energy's scale: its
    # element terms cancel near rest to much less than their own size, about E vol each (by
    # |E| alone, the direct Newton on the dragged armadillo x8 stalled at 5x the tolerance
    # halving through energy noise). AMG has its own end game (roundoff_rtol).
    energy_scale = model.E * float(model.vol.sum()) if linear_solver != "amg" else 0.0
    pins = _pins(system, state, dt, fixed_positions)
    q_base = pins.q_base
    f_free = None if system.gravity_force is None else system.gravity_force[free]
    damping = system.damping_data(q_t)
    D = None if damping is None else model.csr(damping)
    hessian_terms = [t for t in terms if callable(getattr(t, "hessian", None))]
    step_terms = [t for t in terms if callable(getattr(t, "max_step", None))]

    def hooks(name: str) -> list:
        return [getattr(t, name) for t in terms if callable(getattr(t, name, None))]

    for begin in hooks("begin_step"):
        begin(q_t, v_t, q_base, state.t, dt, step=state.step)

    def positions(v_free: np.ndarray) -> np.ndarray:
        return q_base + dt * c.expand_zero(v_free)

    # moving pins (or pins that stopped): the fixed DOFs' velocity change is prescribed and
    # enters the kinetic term through the mass matrix's free-fixed coupling
    dv_fixed = None if pins.v_fixed is None else pins.v_fixed - pins.v_t_fixed

    def velocity(v_free: np.ndarray) -> np.ndarray:
        v = c.expand_zero(v_free)
        return v if pins.v_fixed is None else v + pins.v_fixed

    kinetic_cache: list = [None, None]  # [v_free, M (v_free - v_t)] of the last energy

    def energy(v_free: np.ndarray) -> float:
        q = positions(v_free)
        if check_inversion and count_inverted(model, q):
            return math.inf
        if dv_fixed is None:
            dv = v_free - vt_free
            m_dv = mass_free @ dv
            kinetic_cache[:] = [v_free, m_dv]  # the gradient at an accepted point reuses it
            e = 0.5 * float(dv @ m_dv) + potential_energy(model, q)
        else:
            dv = c.expand_zero(v_free - vt_free) + dv_fixed
            e = 0.5 * float(dv @ (model.mass @ dv)) + potential_energy(model, q)
        if pull is not None:
            e += pull.energy(spring, q.reshape(-1, 3))
        if f_free is not None:
            e -= dt * float(f_free @ v_free)
        if D is not None:
            v = velocity(v_free)
            e += 0.5 * dt * float(v @ (D @ v))
        for term in terms:
            e += float(term.energy(q))
        return e if math.isfinite(e) else math.inf

    def gradient(v_free: np.ndarray, with_terms: bool = True) -> np.ndarray:
        q = positions(v_free)
        gq = assemble_gradient(model, q)
        if pull is not None:
            gq += pull.gradient(spring, q.reshape(-1, 3))
        for term in terms if with_terms else ():
            gq += term.gradient(q)
        if dv_fixed is None:
            cached, m_dv = kinetic_cache
            if cached is not v_free:  # newtons_method never changes an iterate in place
                m_dv = mass_free @ (v_free - vt_free)
            g = m_dv + dt * gq[free]
        else:
            dv = c.expand_zero(v_free - vt_free) + dv_fixed
            g = (model.mass @ dv)[free] + dt * gq[free]
        if f_free is not None:
            g -= dt * f_free
        if D is not None:
            g += dt * (D @ velocity(v_free))[free]
        return g

    def matrix(q: np.ndarray, psd_matrix: bool) -> sp.csr_matrix:
        t0 = time.perf_counter()
        A = system.newton_matrix(q, dt, pull, psd=psd_matrix, damping=damping)
        for term in hessian_terms:
            A = system.add_hessian(A, term.hessian(q), dt * dt)
        stats.add_seconds("matrix", time.perf_counter() - t0)
        return A

    def timed(f, part):
        def call(x):
            t0 = time.perf_counter()
            try:
                return f(x)
            finally:
                stats.add_seconds(part, time.perf_counter() - t0)
        return call

    psd_now = [psd]  # AMG: switched to the PSD-projected Hessian for the rest of the step
    eta_prev = [forcing_max]  # the forcing term's memory
    last_per_decade = [0.0]
    kept: list = [None, False]  # the last Newton matrix solved with, and whether it is PSD

    def amg_direction(v_free: np.ndarray, g: np.ndarray) -> np.ndarray:
        q = positions(v_free)
        gn = float(np.linalg.norm(g))
        gn_prev = progress.observe(gn)
        tol = progress.tol
        ratio = gn / gn_prev if gn_prev else math.inf
        eta = _forcing_term(gn, gn_prev, eta_prev[0], tol, forcing_max)
        eta_prev[0] = eta
        # A chord step: when the last iteration cut |g| by `ratio`, the Hessian moved by about
        # that fraction along it, so the last matrix still solves to well within eta (the
        # final iteration of a converging step: one assembly saved)
        reuse = kept[1] == psd_now[0] and ratio <= AMG_MATRIX_REUSE_FACTOR * eta
        A_free, kept[0] = kept[0] if reuse else None, None
        if A_free is None:
            A_free = matrix(q, psd_now[0])
        if not np.isfinite(A_free.data).all():
            return np.full_like(g, np.nan)
        amg = system.amg
        for _attempt in range(3):
            fresh = False
            if not system.amg_current or last_per_decade[0] > amg_budget:
                t0 = time.perf_counter()
                system.amg_setup(A_free)
                stats.add_seconds("amg_setup", time.perf_counter() - t0)
                stats.amg_setups += 1
                fresh = True
            t0 = time.perf_counter()
            result = amg.solve(A_free, -g, rtol=eta, maxiter=amg_maxiter)
            stats.add_seconds("cg", time.perf_counter() - t0)
            stats.cg_iterations += result.iterations
            last_per_decade[0] = iterations_per_decade(result)
            if result.negative_curvature and not psd_now[0]:
                # indefinite exact Hessian: the PSD-projected one for the rest of the step
                psd_now[0] = True
                stats.psd_fallbacks += 1
                A_free = matrix(q, True)
                last_per_decade[0] = 0.0
                continue
            if result.converged or (fresh and result.iterations and not
                                    result.negative_curvature):
                # a fresh hierarchy's best effort is still a descent direction (CG from 0)
                kept[:] = [A_free, psd_now[0]]
                return result.x
            if fresh:  # negative curvature on the PSD matrix: only round-off can do that
                break
            last_per_decade[0] = math.inf  # rebuild on this matrix and try again
        return np.full_like(g, np.nan)  # newtons_method falls back to -g

    def factorized_direction(q: np.ndarray, g: np.ndarray, A_free: sp.csr_matrix,
                             psd_matrix: bool, ladder: bool):
        """``-A^{-1} g`` by a fresh factorization; with ``ladder`` an indefinite ``A`` is
        shifted up the ladder first, else replaced by the PSD-projected Hessian at once.
        Returns the direction and the matrix factorized when it was not shifted (else None).
        """
        t_factor = time.perf_counter()
        try:
            mu = system.factorize(A_free, shift_hint=shift_hint[0], shifts=ladder)
        except SimulationError:
            if psd_matrix:
                raise
            # no shift up to the ladder's end makes the exact Hessian positive definite (tets
            # close to inversion); the PSD-projected one always is
            if not ladder:
                indefinite()
            A_free = matrix(q, True)
            mu = system.factorize(A_free)
            stats.psd_fallbacks += 1
        # Levenberg-Marquardt memory: the next iteration starts one rung lower, back to the
        # exact Hessian once below the ladder (a failed attempt costs a whole factorization)
        lower = mu / SHIFT_LADDER_GROWTH
        shift_hint[0] = lower if lower >= SHIFT_LADDER_START * (1 - 1e-9) else 0.0
        stats.shifted_factorizations += int(mu > 0)
        stats.factorizations += 1
        last_cg[0] = 0
        d = -system.solve(g)
        stats.add_seconds("factorize", time.perf_counter() - t_factor)
        return d, (A_free if mu == 0.0 else None)

    def direction(v_free: np.ndarray, g: np.ndarray) -> np.ndarray:
        if use_amg:
            return amg_direction(v_free, g)
        if pcg is not None:
            return reuse_direction(v_free, g)
        q = positions(v_free)
        A_free = matrix(q, psd)
        if not np.isfinite(A_free.data).all():
            return np.full_like(g, np.nan)  # newtons_method falls back to -g
        return factorized_direction(q, g, A_free, psd, ladder=True)[0]

    def indefinite() -> None:
        """``"reuse"``: this iteration's exact Hessian is indefinite; after two iterations in
        a row, the rest of the step assembles the PSD-projected one directly."""
        reuse_psd[1] += 1
        if reuse_psd[1] >= 2:
            reuse_psd[0] = True

    def reuse_cg(A_free: sp.csr_matrix, g: np.ndarray, eta: float):
        """CG preconditioned by the kept factorization to the relative residual ``eta``:
        the direction (None when CG fails) and whether it met negative curvature."""
        t0 = time.perf_counter()
        pcg.solver = system.solver  # an objective term may have widened the pattern
        pcg.rtol = eta
        result = pcg.solve(A_free, -g)
        stats.add_seconds("cg", time.perf_counter() - t0)
        stats.cg_iterations += result.iterations
        last_cg[0] = result.iterations
        # CG can converge on an indefinite A to a direction that is not a descent one;
        # a factorization always gives one
        if result.converged and float(g @ result.x) < 0.0:
            return result.x, False
        return None, result.negative_curvature

    def reuse_direction(v_free: np.ndarray, g: np.ndarray) -> np.ndarray:
        q = positions(v_free)
        gn = float(np.linalg.norm(g))
        gn_prev = progress.observe(gn)
        # forcing term: never tighter than reaching the tolerance in this iteration needs, and
        # loose while Newton converges slowly (Eisenstat-Walker: the last iteration's gradient
        # ratio squared), where a tight solve buys nothing
        eta = cg_rtol
        if gn > 0.0:
            ew = _eisenstat_walker(gn, gn_prev)
            eta = max(cg_rtol, min(REUSE_FORCING_MAX, max(ew, 0.5 * progress.tol / gn)))
        # an aged preconditioner (the last solve needed over half the budget) is replaced now
        # rather than after another long CG run
        use_cg = system.factorized_data is not None and last_cg[0] <= cg_maxiter // 2
        lagged, last_newton[0] = last_newton[0], None
        if use_cg and lagged is not None and \
                lagged.lag(v_free, gn, REUSE_LAG_FRACTION * progress.tol):
            d, _ = reuse_cg(lagged.A, g, eta)
            if d is not None:
                stats.lagged_matrices += 1
                lagged.expected = v_free + d
                last_newton[0] = lagged
                return d
            use_cg = last_cg[0] <= cg_maxiter // 2
        psd_matrix = reuse_psd[0]
        A_free = matrix(q, psd_matrix)
        if not np.isfinite(A_free.data).all():
            return np.full_like(g, np.nan)  # newtons_method falls back to -g
        if use_cg:
            d, negative = reuse_cg(A_free, g, eta)
            if d is not None:
                if not psd_matrix:
                    reuse_psd[1] = 0
                if lag_matrices:
                    last_newton[0] = _LaggedMatrix(A_free, gn, v_free + d)
                return d
            if negative and not psd_matrix:
                # indefinite exact Hessian: the PSD-projected one for this iteration (a shift
                # ladder costs a factorization per rung, and large shifts make Newton crawl)
                indefinite()
                stats.psd_fallbacks += 1
                psd_matrix = True
                A_free = matrix(q, True)
        d, A_spd = factorized_direction(q, g, A_free, psd_matrix, ladder=False)
        if not psd_matrix and A_spd is A_free:
            reuse_psd[1] = 0
        if lag_matrices and A_spd is not None:
            last_newton[0] = _LaggedMatrix(A_spd, gn, v_free + d)
        return d

    def clamp(v_free: np.ndarray, d: np.ndarray) -> float:
        q = positions(v_free)
        dq = dt * c.expand_zero(d)
        return min([1.0] + [float(t.max_step(q, dq)) for t in step_terms])

    def no_step(v_free: np.ndarray, d: np.ndarray) -> None:
        n_inv = count_inverted(model, positions(v_free + d))
        raise SimulationError(
            f"backward Euler found no acceptable Newton step: the full step inverts {n_inv} "
            f"of {model.n_tets} tets and every shorter trial also inverts tets or is not "
            "finite (try a smaller dt or softer pull)",
            step=state.step,
        )

    # start from v_t; if that position is inadmissible, from v = 0 (q_t itself, admissible)
    x0 = vt_free.copy()
    if step_terms:  # the start must be reached without crossing anything (CCD from v = 0)
        x0 *= clamp(np.zeros_like(vt_free), vt_free)
    e0 = energy(x0)
    if not math.isfinite(e0):
        x0 = np.zeros_like(vt_free)
        e0 = energy(x0)
        if not math.isfinite(e0):
            raise SimulationError(
                f"the current state is inadmissible ({count_inverted(model, q_base)} inverted "
                "tets or a non-finite energy)", step=state.step,
            )
    init_stiffness = hooks("initialize_stiffness")
    if init_stiffness:
        grad_rest = c.expand_zero(gradient(x0, with_terms=False)) / dt
        average_mass = float(model.mass.sum()) / model.n_dofs
        for init in init_stiffness:
            init(positions(x0), grad_rest, average_mass)
    converged_hooks = hooks("newton_converged")
    after_hooks = hooks("after_iteration")

    def converged_step(v_free: np.ndarray, d: np.ndarray) -> bool:
        dq = dt * c.expand_zero(d)
        return all([ok(dq) for ok in converged_hooks])

    def after_step(v_free: np.ndarray) -> bool:
        q = positions(v_free)
        return any([after(q) for after in after_hooks])

    try:
        res = newtons_method(
            x0, timed(energy, "objective"), timed(gradient, "objective"), direction,
            max_iterations=max_iterations, rtol=rtol, atol=atol, on_no_step=no_step,
            max_step=clamp if step_terms else None,
            converged_step=converged_step if converged_hooks else None,
            after_step=after_step if after_hooks else None,
            roundoff_rtol=AMG_ROUNDOFF_RTOL if use_amg else 0.0,
            f0=None if init_stiffness else e0,  # the stiffness hooks change the objective
            energy_scale=energy_scale,
        )
    except SimulationError as exc:
        if exc.step is not None:
            raise
        raise SimulationError(f"backward Euler: {exc.reason}", step=state.step) from exc
    stats.newton_iterations = res.iterations
    stats.gradient_norms = res.gradient_norms
    stats.gradient_tolerance = max(atol, rtol * res.gradient_norms[0])
    stats.line_search_halvings = res.line_search_halvings
    stats.converged = res.converged
    new = _place_pins(system, _new_state(system, state, res.x, dt), pins)
    _check_finite(new.q, new.v, state.step, "backward Euler")
    return new, stats


#: Integrator names accepted by :class:`fem3d.simulation.Simulation` and the CLI.
INTEGRATORS: dict[str, Callable[..., tuple[State, StepStats]]] = {
    "linear": linearly_implicit_euler,
    "implicit": implicit_euler,
}
