"""What the integrators reuse between steps for one model and constraint set.

:class:`System` holds the reduced sparsity (one symbolic analysis per run), the linear solvers
the registry gives it (:mod:`fem3d.solve.linear`), the model's loads as built by the scene
(:class:`~fem3d.physics.terms.loads.Loads`), and the extension of the solver's pattern by
terms whose Hessian entries fall outside the mesh's.
:class:`~fem3d.solve.newton_matrix.NewtonMatrixBuilder` is where the terms add their
Hessians into a reduced Newton matrix.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fem3d.errors import SimulationError
from fem3d.kernels.backend import c_extension
from fem3d.kernels.dispatch import spring_kernels
from fem3d.physics.constraints import Constraints
from fem3d.physics.model import Model
from fem3d.physics.springs import Pull
from fem3d.physics.terms.base import Term
from fem3d.physics.terms.elasticity import Elasticity
from fem3d.physics.terms.inertia import Inertia
from fem3d.physics.terms.loads import Loads
from fem3d.physics.terms.pull import PullSprings
from fem3d.solve.linear import (
    LINEAR_SOLVERS,
    DirectSolver,
    IterativeSolver,
    NotPositiveDefinite,
    SolverOptions,
    make_linear_solver,
    resolve_linear_solver,
)
from fem3d.solve.newton_matrix import NewtonMatrixBuilder
from fem3d.solve.reductions import WHOLE, Reductions

__all__ = ["System", "LEAN_ASSEMBLY_MIN_TETS", "SHIFT_LADDER_START", "SHIFT_LADDER_GROWTH"]

#: From this many tets :class:`System` keeps no element-to-reduced-slot map (4 bytes per
#: element-matrix entry) and assembles Newton matrices on the full pattern, then gathers.
LEAN_ASSEMBLY_MIN_TETS = 250_000

#: Shifts ``mu`` of an indefinite Newton matrix ``A + mu M``: ``1e-4, 1e-3, ...``.
SHIFT_LADDER_START = 1e-4
SHIFT_LADDER_GROWTH = 10.0

#: :meth:`System._locate`: how many answers are kept.
_LOCATE_CACHE_SIZE = 4

_stages = logging.getLogger("fem3d.stages")  # stage marks (fem3d run --profile)


class System:
    """What the integrators reuse between steps for one model and constraint set.

    Parameters
    ----------
    model : Model
    constraints : Constraints
        Fixed vertices.
    solver_backend : str, optional
        The linear solver's registry name or ``"auto"`` (default;
        :func:`fem3d.solve.linear.resolve_linear_solver`).
    loads : Loads, optional
        Gravity and Rayleigh damping (:func:`fem3d.scene.build.build_loads`); default none.
    cholmod_mode : {"auto", "simplicial", "supernodal"}, optional
        CHOLMOD's factorization (:attr:`fem3d.solve.linear.SolverOptions.cholmod_mode`).
    petsc_options : str, optional
        The ``"petsc"`` solver's options (:attr:`fem3d.solve.linear.SolverOptions.
        petsc_options`).

    Attributes
    ----------
    pattern_free : (n_free_dofs, n_free_dofs) scipy.sparse.csr_matrix
        Sparsity of the reduced system ``P A P^T`` (fixed for the whole run: one symbolic
        analysis).
    mass_free : (n_free_dofs, n_free_dofs) scipy.sparse.csr_matrix
        ``P M P^T``.

    Notes
    -----
    Newton matrices (:class:`NewtonMatrixBuilder`, :meth:`newton_matrix`) assemble
    ``P (M + dt^2 H) P^T`` directly on the reduced pattern:
    each element Hessian entry goes straight to its reduced CSR slot (entries on fixed DOFs
    to a discarded sink slot), with ``dt^2`` folded into the element volumes, so no full
    ``3n x 3n`` matrix is built and reduced per Newton iteration.
    """

    #: Whether :meth:`factorize` records the matrix it factorized in
    #: :attr:`factorized_data` (a copy of its values): what Newton's ``reuse`` direction and
    #: a checkpoint of a run that keeps its factorization need.
    records_factorized: bool = True

    #: How Newton reduces this system's vectors (:mod:`fem3d.solve.reductions`): one
    #: process's whole vectors here.
    reductions: Reductions = WHOLE

    #: Whether this is one MPI rank's share of a system: a pull may hold none of its springs
    #: here and still be attached (every rank keeps the same terms).
    is_share: bool = False

    def __init__(
        self,
        model: Model,
        constraints: Constraints,
        solver_backend: str = "auto",
        *,
        loads: Loads | None = None,
        cholmod_mode: str = "auto",
        petsc_options: str = "",
    ):
        if constraints.n_dofs != model.n_dofs:
            raise ValueError("constraints and model have different DOF counts")
        self.model = model
        #: The model's gravity and damping terms (:class:`Loads`).
        self.loads = loads if loads is not None else Loads()
        self.constraints = constraints
        self.free = constraints.free_dofs
        self.solver_backend = solver_backend
        #: CHOLMOD's factorization (:attr:`~fem3d.solve.linear.SolverOptions.cholmod_mode`;
        #: the other solvers ignore it)
        self.cholmod_mode = cholmod_mode
        #: PETSc options of the ``"petsc"`` solver (the others ignore them)
        self.petsc_options = petsc_options
        kept, self.pattern_free = _reduced_pattern(model.pattern, constraints)
        self.mass_free = self._reduced_mass(model, kept)
        self._kept = kept
        self._free_slot_map: np.ndarray | None = None
        # element entry -> reduced slot (4 bytes per element-matrix entry: 576 MB at 1e6 tets);
        # large meshes assemble on the full pattern and gather instead (the same sums)
        self._free_scatter = None
        if model.n_tets < LEAN_ASSEMBLY_MIN_TETS:
            self._free_scatter = self._free_slot[model.scatter]
            self._free_scatter.setflags(write=False)
        _stages.debug("system: reduced pattern")
        self._scaled_volumes: tuple[float, np.ndarray] | None = None
        self._pull_slots: tuple[np.ndarray, np.ndarray] | None = None
        #: The registry name of the linear solver (:mod:`fem3d.solve.linear.registry`:
        #: ``"auto"`` picks by size): ``"amg"`` (AMG-preconditioned CG for backward Euler's
        #: Newton systems) or a direct solver.
        self.linear_backend = resolve_linear_solver(solver_backend, constraints.n_free)
        iterative = LINEAR_SOLVERS[self.linear_backend].iterative
        self._solver: DirectSolver | None = None
        #: Symbolic analyses of the direct solver so far (one per pattern it factorized on).
        self.analyses = 0
        self._amg: IterativeSolver | None = None
        if not iterative:  # with an iterative solver a factorization is made only if needed
            self._solver = self._new_direct_solver(self.pattern_free)
        elif constraints.n_free:  # the AMG's aggregation: once per pattern, like an analysis
            self.amg.analyse(self.pattern_free, symmetric=True)
        _stages.debug(f"system: {self.linear_backend} analysis")
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
        # the last answers of _locate: (pattern keys, keys, positions, all inside)
        self._locate_cache: list[tuple[np.ndarray, np.ndarray, np.ndarray, bool]] = []
        # (pattern keys, their CSR indptr as int64, indices as int32) for _search
        self._csr_of: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._physics_cache()

    def with_model(self, model: Model) -> System:
        """Same constraints and solver (the pattern is shared), new material values."""
        new = object.__new__(System)
        new.__dict__.update(self.__dict__)
        new.model = model
        new.mass_free = self._reduced_mass(model, self._kept)
        new.loads = self.loads.with_model(model)
        new._physics_cache()
        return new

    @property
    def _free_slot(self) -> np.ndarray:
        """Reduced-data slot of every full-pattern entry (entries on fixed DOFs: the sink slot
        ``nnz_free``), ``(nnz,) int32``; made when first needed (pulls, small meshes)."""
        if self._free_slot_map is None:
            nnz_free = self._kept.size
            slot = np.full(self.model.nnz, nnz_free, dtype=np.int32)
            slot[self._kept] = np.arange(nnz_free, dtype=np.int32)
            slot.setflags(write=False)
            self._free_slot_map = slot
        return self._free_slot_map

    def _reduced_mass(self, model: Model, kept: np.ndarray) -> sp.csr_matrix:
        """``P M P^T`` on :attr:`pattern_free` (sharing its index arrays)."""
        pf = self.pattern_free
        M = sp.csr_matrix((model.mass.data[kept], pf.indices, pf.indptr), shape=pf.shape,
                          copy=False)
        M.has_sorted_indices = pf.has_sorted_indices
        return M

    # -- the model's own terms -------------------------------------------------------------
    def _physics_cache(self) -> None:
        """The current model's inertia and elasticity terms."""
        self._model_terms = (Inertia(self.model, self.mass_free), Elasticity(self.model))

    def model_terms(self) -> tuple[Term, Term]:
        """The model's inertia and elasticity terms."""
        return self._model_terms

    def summed(self, value: float | np.ndarray) -> float | np.ndarray:
        """``value`` (a number or an array) summed over the processes that share this system:
        itself in one process; over the ranks in a distributed run
        (:class:`~fem3d.parallel.system.DistributedSystem`, whose model is a rank's share of
        the tets), the same bits on every rank. What a scheme or the simulation computes
        from the model itself (energies, forces, a right-hand side) goes through it."""
        return value

    def total(self, parts: np.ndarray) -> np.ndarray:
        """A small array of per-process parts (a number per pin, say) summed over the
        processes that share this system: itself in one process."""
        return parts

    def pull_term(self, pull: Pull | None) -> PullSprings:
        """The objective's term of the pull springs ``pull`` (a distributed system: the
        springs of the vertices its rank owns, summed over the ranks)."""
        return PullSprings(self.model, pull, spring=self.spring)

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

    def vertex_block_positions(self, vertices: np.ndarray) -> np.ndarray:
        """Full-pattern ``data`` positions of the vertices' 3x3 diagonal blocks."""
        d = 3 * vertices[:, None] + np.arange(3)
        rows = np.broadcast_to(d[:, :, None], (d.shape[0], 3, 3))
        cols = np.broadcast_to(d[:, None, :], (d.shape[0], 3, 3))
        return self.data_positions(rows.reshape(-1), cols.reshape(-1))

    def vertex_block_slots(self, vertices: np.ndarray) -> np.ndarray:
        """Reduced-data slots of :meth:`vertex_block_positions` (the sink slot for fixed
        DOFs; cached for the last vertex set: a dragged pull keeps its vertices from step to
        step)."""
        cached = self._pull_slots
        if cached is None or not np.array_equal(cached[0], vertices):
            slots = self._free_slot[self.vertex_block_positions(vertices)]
            cached = (np.array(vertices), slots)
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
        damping: np.ndarray | None = None, stiffness: np.ndarray | None = None,
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
        stiffness : (model.nnz,) float64, optional
            The Hessian of further position terms on ``model.pattern`` (a follower
            pressure's), added as ``dt^2`` times it.

        Returns
        -------
        (n_free_dofs, n_free_dofs) scipy.sparse.csr_matrix
            A new matrix (its data is not reused by later calls); may hold non-finite values
            when ``q`` is out of range.
        """
        builder = NewtonMatrixBuilder(self, dt * dt, psd)
        builder.add_pattern_values(self.model.mass.data, reduced=self.mass_free.data)
        builder.add_elements(self.model, self.model.psd_hessian if psd else "hessian", q)
        if pull is not None and pull.vertices.size:
            q3 = np.asarray(q, dtype=np.float64).reshape(-1, 3)
            builder.add_vertex_blocks(pull.vertices, pull.hessian_blocks(self.spring, q3),
                                      dt * dt)
        if stiffness is not None:
            builder.add_pattern_values(stiffness, dt * dt)
        if damping is not None:  # + dt D (backward Euler's dissipation dt/2 v^T D v)
            builder.add_pattern_values(damping, dt)
        return builder.matrix()

    def factorize(self, A_free: sp.csr_matrix, *, shift_hint: float = 0.0,
                  shifts: bool = True) -> float:
        """Factorize an SPD reduced matrix; shift it when it is not positive definite.

        Strategy for an indefinite Newton Hessian: try ``A``; on
        :class:`NotPositiveDefinite` factorize ``A + mu M`` (``M`` the reduced consistent mass
        matrix, ``mu = 1e-4, 1e-3, ...``; :meth:`DirectSolver.factorize_shifted`), a
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
        if self.records_factorized:
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
        ext = self._ext
        pos, inside = self._locate(keys)
        if inside and ext is None:
            data = np.array(A.data)
            np.add.at(data, pos, vals)
            return self._like(A, data)
        if not inside:
            have = self._base_key_array() if ext is None else ext.keys
            missing = have[pos] != keys
            ext, moved = self._widen(keys[missing])
            # the keys found before move up with the pattern; the missing ones are searched
            pos = pos + moved[pos]
            pos[missing] = np.searchsorted(ext.keys, keys[missing])
            pos.setflags(write=False)
            self._locate_cache.insert(0, (ext.keys, np.array(keys), pos, True))
            del self._locate_cache[_LOCATE_CACHE_SIZE:]
        A = self.on_solver_pattern(A)
        data = np.array(A.data)
        np.add.at(data, pos, vals)
        return ext.csr(data)

    def pattern_covers(self, rows: np.ndarray, cols: np.ndarray) -> bool:
        """Whether the solver's current pattern holds every entry ``(rows, cols)`` (full-DOF
        indices; entries on fixed DOFs are ignored): adding them would not re-analyse."""
        new = self.constraints._new_index
        r = new[np.asarray(rows, dtype=np.int64)]
        c = new[np.asarray(cols, dtype=np.int64)]
        keep = (r >= 0) & (c >= 0)
        keys = r[keep] * self.constraints.n_free + c[keep]
        return keys.size == 0 or self._locate(keys)[1]

    def _locate(self, keys: np.ndarray) -> tuple[np.ndarray, bool]:
        """Positions of ``keys`` (``row * n_free + col``) in the solver's sorted pattern keys
        (clipped to the last one), and whether every key is there.

        The contact terms ask for the same keys several times (whether the pattern covers a
        barrier Hessian, then adding it; Newton iterates with the same contact set), so the
        last few answers are kept for the current pattern (each search of 3e4 keys in the
        pile's 5e5 takes a few milliseconds); keys that begin with a kept answer's (the
        barrier's entries asked about alone, then with the friction's) search only the rest.
        """
        have = self._base_key_array() if self._ext is None else self._ext.keys
        cache = self._locate_cache
        known = None  # a cached answer for the first keys (the barrier's, then friction's)
        for entry in cache:
            if entry[0] is not have or entry[1].size > keys.size:
                continue
            if entry[1].size == keys.size and np.array_equal(entry[1], keys):
                return entry[2], entry[3]
            if (known is None or entry[1].size > known[1].size) and \
                    np.array_equal(entry[1], keys[:entry[1].size]):
                known = entry
        start = 0 if known is None else known[1].size
        pos, inside = self._search(have, keys[start:])
        if known is not None:
            pos = np.concatenate([known[2], pos])
            inside = inside and known[3]
        pos.setflags(write=False)
        cache.insert(0, (have, np.array(keys), pos, inside))
        del cache[_LOCATE_CACHE_SIZE:]
        return pos, inside

    def _search(self, have: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, bool]:
        """``np.searchsorted(have, keys)`` clipped to the last key, and whether every key is
        in ``have`` (the keys of the base or the extended pattern). The C extension searches
        each key's row of the pattern's CSR arrays alone: 3-10x faster than NumPy's search
        of all the keys, the same positions."""
        ext = c_extension()
        if ext is None or have.size == 0:
            pos = np.searchsorted(have, keys)
            np.minimum(pos, max(have.size - 1, 0), out=pos)
            return pos, bool(have.size) and bool(np.array_equal(have[pos], keys))
        if self._csr_of is None or self._csr_of[0] is not have:
            pattern = self.pattern_free if self._ext is None else self._ext.pattern
            self._csr_of = (have, pattern.indptr.astype(np.int64),
                            pattern.indices.astype(np.int32, copy=False))
        pos = np.empty(keys.size, dtype=np.int64)
        inside = ext.csr_locate(self._csr_of[1], self._csr_of[2],
                                np.ascontiguousarray(keys, dtype=np.int64), pos)
        return pos, bool(inside)

    def _like(self, A: sp.csr_matrix, data: np.ndarray) -> sp.csr_matrix:
        B = sp.csr_matrix((data, A.indices, A.indptr), shape=A.shape, copy=False)
        # the solver's patterns hold sorted, unique columns: scipy need not scan for them
        B.has_canonical_format = True
        return B

    def _base_key_array(self) -> np.ndarray:
        if self._base_keys is None:
            pf = self.pattern_free
            r = np.repeat(np.arange(pf.shape[0], dtype=np.int64), np.diff(pf.indptr))
            self._base_keys = r * pf.shape[1] + pf.indices
        return self._base_keys

    def _extend(self, keys: np.ndarray) -> _ExtendedPattern:
        """Widen the solver's pattern by ``keys`` (and their transposes); new analysis."""
        old = self._base_key_array() if self._ext is None else self._ext.keys
        pos = np.minimum(np.searchsorted(old, keys), old.size - 1)
        return self._widen(keys[old[pos] != keys])[0]

    def _widen(self, missing: np.ndarray) -> tuple[_ExtendedPattern, np.ndarray]:
        """Widen the solver's pattern by the keys ``missing`` from it and their transposes
        (those are missing too: the pattern is structurally symmetric); new analysis.
        Returns the pattern and, for each old key's position, how far it moved up."""
        nf = self.constraints.n_free
        old = self._base_key_array() if self._ext is None else self._ext.keys
        r, c = np.divmod(missing, nf)
        # the (few) new keys inserted in order: the same array as ``np.union1d(old,
        # wanted)`` without sorting or searching the whole pattern again
        fresh = np.unique(np.concatenate([missing, c * nf + r]))
        before = np.searchsorted(old, fresh)
        union = np.insert(old, before, fresh)
        # each old key moves up by the fresh keys inserted at or before it: the base keys'
        # positions follow without searching the whole union (0.1 s at the pile's 6e5 keys)
        moved = np.cumsum(np.bincount(before, minlength=old.size))
        prev = np.arange(old.size) if self._ext is None else self._ext.base_pos
        rows, cols = np.divmod(union, nf)
        indptr = np.zeros(nf + 1, dtype=np.int64)
        np.cumsum(np.bincount(rows, minlength=nf), out=indptr[1:])
        pattern = sp.csr_matrix((np.zeros(union.size), cols.astype(np.int32), indptr),
                                shape=(nf, nf))
        pattern.has_sorted_indices = True
        ext = _ExtendedPattern(pattern=pattern, keys=union,
                               base_pos=prev + moved[prev])
        self._ext = ext
        # analysed when a factorization is next needed (several widenings between two
        # factorizations: one analysis, of the pattern they make together)
        self._solver = None
        self.factorized_data = None
        self.pattern_generation += 1
        return ext, moved

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

    def _new_direct_solver(self, pattern: sp.csr_matrix) -> DirectSolver:
        solver = make_linear_solver(self.solver_backend, self.direct_solver_options(),
                                    direct=True)
        assert isinstance(solver, DirectSolver)  # direct=True resolves to a direct solver
        # the reduced elastic pattern and its widenings (which add each key's transpose)
        solver.analyse(pattern, symmetric=True)
        self.analyses += 1
        if solver.name == "superlu" and pattern is self.pattern_free and \
                self.mass_free.shape[0]:
            # SuperLU orders on its first factorization and takes another code path (explicit
            # permutation, natural order) afterwards. Factorizing once here makes every step
            # take the same path, so a fresh System (a run resumed from a checkpoint) computes
            # bit for bit what a long-lived one does.
            solver.factorize(self.mass_free)
        return solver

    def solve_mass(self, rhs: np.ndarray) -> np.ndarray:
        """``M^-1 rhs`` with the mass matrix on the free DOFs (:attr:`mass_free`; Newmark's
        initial acceleration): SuperLU (a distributed system: PETSc over its ranks).

        Parameters
        ----------
        rhs : (n_free,) float64

        Returns
        -------
        (n_free,) float64
        """
        return spla.spsolve(self.mass_free.tocsc(), rhs)

    def direct_solver_options(self) -> SolverOptions:
        """What a direct solver is made with: CHOLMOD's mode, PETSc's options and the free
        vertices' rest positions (PETSc's GAMG: their rigid-body modes)."""
        return SolverOptions(cholmod_mode=self.cholmod_mode, petsc_options=self.petsc_options,
                             points=self.model.X[self.free[0::3] // 3])

    @property
    def solver(self) -> DirectSolver:
        """The sparse direct solver holding the last factorization (made on first use with
        an iterative solver: the linearly-implicit scheme factorizes)."""
        if self._solver is None:
            pat = self.pattern_free if self._ext is None else self._ext.pattern
            self._solver = self._new_direct_solver(pat)
        return self._solver

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve with the last factorization."""
        return np.asarray(self.solver.solve(b)).reshape(-1)

    def release_factorization(self) -> None:
        """The caller is done solving with the last :meth:`factorize` (Newton's direction
        is computed): the solver may let go of it (:meth:`DirectSolver.release`: PETSc's
        GAMG hierarchy is freed before the next matrix is assembled). A :meth:`solve`
        before the next :meth:`factorize` raises."""
        if self._solver is not None:
            self._solver.release()

    @property
    def amg(self) -> IterativeSolver:
        """The iterative solver (``"amg"``: AMG-preconditioned CG; near-nullspace: rigid-body
        modes of the free vertices at rest, so a hierarchy depends on its matrix alone)."""
        if self._amg is None:
            free_vertices = self.free[0::3] // 3
            options = SolverOptions(points=self.model.X[free_vertices])
            solver = make_linear_solver("amg", options)
            assert isinstance(solver, IterativeSolver)
            self._amg = solver
        return self._amg

    def amg_setup(self, A_free: sp.csr_matrix) -> None:
        """Build the AMG hierarchy from ``A_free`` (on the solver's pattern);
        :attr:`factorized_data` records the matrix (a checkpoint rebuilds the same one)."""
        A_free = self.on_solver_pattern(A_free)
        self.amg.factorize(A_free, pattern_key=self.pattern_generation)
        data = A_free.data.view()  # Newton matrices are new arrays: kept, not copied
        data.setflags(write=False)
        self.factorized_data = data

    @property
    def amg_current(self) -> bool:
        """A hierarchy exists for the solver's current pattern."""
        return self._amg is not None and self._amg.ready and \
            self._amg.pattern_key == self.pattern_generation


def _reduced_pattern(pattern: sp.csr_matrix, constraints: Constraints
                     ) -> tuple[np.ndarray, sp.csr_matrix]:
    """The entries of ``pattern`` on free rows and columns, and ``P pattern P^T``: what
    ``constraints.kept_entries`` / ``reduce_matrix`` give, in int32 where it fits, without
    keeping their cache (four ``nnz``-long arrays), the pattern's zeros never written.

    Returns
    -------
    kept : (nnz_free,) int32 or int64
        Positions in ``pattern.data`` of the reduced matrix's entries, in its order.
    pattern_free : (n_free, n_free) scipy.sparse.csr_matrix
    """
    N, nnz, nf = constraints.n_dofs, pattern.nnz, constraints.n_free
    index = np.int32 if max(nnz, N) < np.iinfo(np.int32).max else np.int64
    new = np.full(N, -1, dtype=index)
    new[constraints.free_dofs] = np.arange(nf, dtype=index)
    free = new >= 0
    row_length = np.diff(pattern.indptr)
    keep = np.repeat(free, row_length)
    keep &= free[pattern.indices]
    kept = np.arange(nnz, dtype=index)[keep]
    indices = new[pattern.indices[kept]]
    before = np.zeros(nnz + 1, dtype=index)  # kept entries before each position
    np.cumsum(keep, out=before[1:])
    del keep
    rows = constraints.free_dofs
    indptr = np.zeros(nf + 1, dtype=index)
    np.cumsum(before[pattern.indptr[rows + 1]] - before[pattern.indptr[rows]], out=indptr[1:])
    zeros = np.zeros(kept.size)
    zeros.setflags(write=False)
    R = sp.csr_matrix((zeros, indices, indptr), shape=(nf, nf), copy=False)
    # column relabelling is monotone, so sorted input stays sorted
    R.has_sorted_indices = bool(pattern.has_sorted_indices)
    kept.setflags(write=False)
    return kept, R


@dataclass(frozen=True, eq=False)
class _ExtendedPattern:
    """``pattern_free`` widened by objective terms' entries (``keys = row * n + col``)."""

    pattern: sp.csr_matrix
    keys: np.ndarray
    base_pos: np.ndarray

    def csr(self, data: np.ndarray) -> sp.csr_matrix:
        A = sp.csr_matrix((data, self.pattern.indices, self.pattern.indptr),
                          shape=self.pattern.shape, copy=False)
        A.has_canonical_format = True  # sorted unique keys
        return A
