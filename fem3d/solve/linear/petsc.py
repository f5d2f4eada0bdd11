"""PETSc's Krylov solvers and factorizations through petsc4py, the ``"petsc"`` solver.

One process (``[simulation] linear_solver = "petsc"``) or one rank's share of a distributed
run (:mod:`fem3d.parallel`): ``analyse`` preallocates a PETSc AIJ matrix of block size 3 from
the pattern's coordinates (``MatSetPreallocationCOO``: each rank gives the entries of its own
elements, rows of other ranks included; PETSc sums them where they belong), ``factorize``
sets the values (``MatSetValuesCOO``) and sets up the KSP (a MUMPS factorization or the GAMG
hierarchy), ``solve`` runs it. The right-hand side and the solution are the whole reduced
vector in one process, or on an MPI rank its local free vector (:class:`DofLayout` with its
:class:`~fem3d.parallel.ghosts.Ghosts`: its own tets' free DOFs; the pattern, the
right-hand side and the solution are local, the matrix global).

The KSP, by default:

* below :data:`GAMG_MIN_FREE_DOFS` free DOFs, where MUMPS is there: ``-ksp_type preonly
  -pc_type cholesky -pc_factor_mat_solver_type mumps`` (an ``LDL^T`` whose negative pivots,
  MUMPS' ``INFOG(12)``, make :class:`NotPositiveDefinite`: the shift ladder works as with
  CHOLMOD);
* above, or without MUMPS: ``-ksp_type cg -pc_type gamg`` with the rigid-body modes of the
  free vertices as GAMG's near-null space, to ``-ksp_rtol`` :data:`KSP_RTOL` (a solve that
  meets negative curvature returns NaN: Newton falls back to the gradient).

Any PETSc option overrides them: the scene's ``simulation.petsc_options``, then
``FEM3D_PETSC_OPTIONS`` (both a string such as ``"-ksp_type gmres -pc_type hypre"``), and
PETSc's own ``PETSC_OPTIONS`` (read at PETSc's start; ``-log_view`` prints PETSc's timings
when the process ends). The algorithms of the matrix products GAMG forms
(:data:`PRODUCT_OPTIONS`: ``-matptap_via allatonce`` lowers a distributed set-up's memory,
docs/parallel.md) are read from PETSc's global database, not the KSP's prefix: given in the
scene (or by default: ``-mat_product_clear 1`` with GAMG), they are put there while the
preconditioner sets up. :meth:`PetscSolver.release` (Newton's direction calls it once its
direction is solved) destroys a GAMG KSP before the next matrix is assembled.
"""

from __future__ import annotations

import contextlib
import functools
import os
import shlex
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from fem3d.solve.linear.base import DirectSolver, NotPositiveDefinite, SolveReport, SolverOptions

if TYPE_CHECKING:
    from fem3d.parallel.ghosts import Ghosts

__all__ = ["DofLayout", "ENV_OPTIONS", "GAMG_MIN_FREE_DOFS", "KSP_RTOL", "PRODUCT_OPTIONS",
           "PetscSolver", "petsc_module", "parse_options"]

#: The environment variable of PETSc options (``"-ksp_type cg -pc_type gamg -log_view"``).
ENV_OPTIONS = "FEM3D_PETSC_OPTIONS"
#: From this many free DOFs the default KSP is CG + GAMG (below: MUMPS' Cholesky where
#: present), like ``"auto"``'s switch to AMG-CG (:data:`~fem3d.solve.linear.amg_cg.
#: AMG_AUTO_MIN_FREE_DOFS`).
GAMG_MIN_FREE_DOFS = 10000
#: Prefixes of the options PETSc reads from its global database (no object's prefix) while
#: a preconditioner sets up: the algorithms of the matrix products GAMG forms
#: (``-matptap_via``, ``-matmatmult_via``, ...).
PRODUCT_OPTIONS = ("matptap_", "matmatmult_", "mattransposematmult_", "mat_product_")
#: The default relative residual of the Krylov solves (a direct solve's in effect: Newton's
#: gradient tolerance is ``1e-10`` relative).
KSP_RTOL = 1e-10


@functools.cache
def petsc_module() -> Any:
    """``petsc4py.PETSc``, initialised (an optional dependency: ``fem3d[mpi]``)."""
    import petsc4py  # optional (fem3d[mpi]): imported when the solver is chosen

    # FEM3D_PETSC_OPTIONS also goes to PETSc's own database (-log_view, -info, ...)
    petsc4py.init([sys.argv[0] if sys.argv else "fem3d",
                   *shlex.split(os.environ.get(ENV_OPTIONS, ""))])
    from petsc4py import PETSc
    return PETSc


def parse_options(text: str) -> dict[str, str]:
    """``"-ksp_type cg -pc_type gamg -log_view"`` as ``{"ksp_type": "cg", "pc_type": "gamg",
    "log_view": ""}``.

    Raises
    ------
    ValueError
        A word that is neither an option (``-name``) nor the value after one.
    """
    words = shlex.split(text)
    out: dict[str, str] = {}
    key = None
    for word in words:
        if word.startswith("-") and not _is_number(word):
            key = word.lstrip("-")
            if not key:
                raise ValueError(f"PETSc options {text!r}: a lone '-'")
            out[key] = ""
        elif key is not None and out[key] == "":
            out[key] = word
        else:
            raise ValueError(f"PETSc options {text!r}: {word!r} follows no option")
    return out


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


@dataclass(frozen=True, eq=False)
class DofLayout:
    """What one rank owns of the reduced (free-DOF) vector of a distributed run.

    The vector a rank hands to :class:`PetscSolver` (and gets back) is its local free vector
    (``ghosts``: the free DOFs of its own tets, owned and ghosts;
    :func:`fem3d.parallel.partition.local_layout`), or in one process, without ``ghosts``,
    the whole reduced vector.

    Attributes
    ----------
    comm : mpi4py.MPI.Comm
        The ranks that share the system.
    order : (n_free,) or (k,) int64
        PETSc's global row of each free DOF of the vector (fem3d's free numbering to
        PETSc's, where each rank's rows are consecutive); a ghost's is its owner's.
    owned : (n_owned,) int64
        The entries of the vector this rank owns, in PETSc's order (``order[owned]`` is
        ``start, start + 1, ...``).
    start : int
        PETSc's first row on this rank.
    counts : (n_ranks,) int64
        Rows per rank.
    n : int
        The global number of free DOFs (``counts.sum()``; the default, -1, sets it so).
    ghosts : Ghosts or None
        The local vector's entries other ranks hold too (None: whole vectors).
    """

    comm: Any
    order: np.ndarray
    owned: np.ndarray
    start: int
    counts: np.ndarray
    n: int = -1
    ghosts: Ghosts | None = None

    def __post_init__(self) -> None:
        if self.n < 0:
            object.__setattr__(self, "n", int(np.asarray(self.counts).sum()))


class PetscSolver(DirectSolver):
    """PETSc's KSP on a (distributed) AIJ matrix of block size 3 (``"petsc"``).

    Parameters
    ----------
    options : SolverOptions, optional
        ``points`` (the free vertices' rest positions: GAMG's rigid-body modes; with a
        layout's ghosts, the rank's local free vertices') and ``petsc_options`` (the
        scene's).
    layout : DofLayout, optional
        One rank's share of a distributed system (default: the whole system in this
        process); with its ``ghosts``, the pattern, right-hand sides and solutions are the
        rank's local free vectors (a ghost's right-hand side is not read; its solution is
        its owner's).
    """

    name: ClassVar[str] = "petsc"
    install_hint: ClassVar[str] = ("pip install 'fem3d[mpi]' (PETSc first: sudo bash "
                                   "scripts/install_petsc.sh)")

    def __init__(self, options: SolverOptions | None = None, *,
                 layout: DofLayout | None = None) -> None:
        super().__init__(options)
        if layout is not None and layout.ghosts is None and layout.comm.Get_size() > 1:
            raise ValueError("a layout over several ranks needs its ghosts "
                             "(fem3d.parallel.partition.local_layout)")
        self.layout = layout
        # a rank's pattern holds its own elements' entries: rows of other ranks' vertices
        # may be empty there (the summed matrix has its whole diagonal)
        self.partial = layout is not None and layout.comm.Get_size() > 1
        self.ksp_options = self._ksp_options()
        self._mat = self._ksp = None
        self._keeps_ksp = True
        self._iterations, self._residual, self._converged = 0, float("nan"), True

    @classmethod
    @functools.cache
    def available(cls) -> bool:
        """Whether petsc4py and mpi4py import."""
        try:
            import mpi4py  # noqa: F401
            import petsc4py  # noqa: F401
        except (ImportError, OSError):  # OSError: a shared library that does not load
            return False
        return True

    def _ksp_options(self) -> dict[str, str]:
        given = parse_options(getattr(self.options, "petsc_options", "") or "")
        given.update(parse_options(os.environ.get(ENV_OPTIONS, "")))
        return given

    @property
    def report(self) -> SolveReport:
        """The last analysis, factorization and solve (:class:`SolveReport`)."""
        return SolveReport(self.name, iterations=self._iterations, residual=self._residual,
                           converged=self._converged, shift=self.shift,
                           analyse_seconds=self.analyze_seconds,
                           factorize_seconds=self.factor_seconds,
                           solve_seconds=self.solve_seconds)

    # -- the three phases -------------------------------------------------------------------
    def _comm(self) -> Any:
        PETSc = petsc_module()
        if self.layout is None:
            return PETSc.COMM_SELF
        return PETSc.Comm(self.layout.comm)

    def _analyse(self) -> None:
        PETSc = petsc_module()
        n, layout = self._global_n, self.layout
        rank = 0 if layout is None else layout.comm.Get_rank()
        counts = np.array([n]) if layout is None else np.asarray(layout.counts)
        n_owned = int(counts[rank])
        bs = 3 if n % 3 == 0 and not (counts % 3).any() else 1
        local_rows, cols = self._rows, self._indices
        rows = local_rows
        if layout is not None:
            rows, cols = layout.order[local_rows], layout.order[cols]
        if layout is not None and layout.ghosts is not None:
            nnz = self._local_row_counts(local_rows, rows, cols, counts, rank)
        else:
            nnz = self._row_counts(rows, cols, counts, rank)
        del local_rows  # let go with self._rows below (a distributed pattern)
        A = PETSc.Mat().create(comm=self._comm())
        A.setSizes(((n_owned, n), (n_owned, n)), bsize=bs)
        A.setType(PETSc.Mat.Type.AIJ)
        A.setPreallocationNNZ(nnz)
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        # the entries in PETSc's row order, each row's columns sorted (MatSetValues by rows)
        by_row = np.lexsort((cols, rows))
        self._cols = cols[by_row].astype(PETSc.IntType)
        del cols
        rows = rows[by_row]
        first = np.r_[True, rows[1:] != rows[:-1]]
        self._row_of = rows[first].astype(PETSc.IntType)
        self._row_ptr = np.r_[np.flatnonzero(first), by_row.size].astype(PETSc.IntType)
        del rows, first
        if self.partial:
            # memory per rank: the permutation in 4 bytes an entry where it fits, and the
            # entries' rows (8 bytes each) let go; a rank's matrices all have its pattern
            if by_row.size <= np.iinfo(np.int32).max:
                by_row = by_row.astype(np.int32)
            self._rows = None
        self._by_row = by_row
        self._bs = bs
        self._mat = A
        self._ksp = None

    def _row_counts(self, rows: np.ndarray, cols: np.ndarray, counts: np.ndarray,
                    rank: int) -> tuple[np.ndarray, np.ndarray]:
        """Entries per owned row in the diagonal and off-diagonal blocks (PETSc's
        preallocation) of a whole pattern in one process: exact."""
        ends = np.cumsum(counts)
        starts = ends - counts
        owner = np.searchsorted(ends, rows, side="right")
        diagonal = (cols >= starts[owner]) & (cols < ends[owner])
        n = self.n
        d = np.bincount(rows[diagonal], minlength=n).astype(np.int64)
        o = np.bincount(rows[~diagonal], minlength=n).astype(np.int64)
        PETSc = petsc_module()
        lo, hi = int(starts[rank]), int(ends[rank])
        d = np.minimum(d[lo:hi], hi - lo)
        o = np.minimum(o[lo:hi], n - (hi - lo))
        return d.astype(PETSc.IntType), o.astype(PETSc.IntType)

    def _local_row_counts(self, local_rows: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                          counts: np.ndarray, rank: int) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_row_counts` of a local pattern (each entry's row as a local free index
        and as PETSc's, and PETSc's column): each rank counts its local rows' entries, the
        holders of a row sum them (``layout.ghosts.assemble``), its owner keeps them; an
        upper bound where ranks share entries. O(local) memory."""
        layout = self.layout
        ends = np.cumsum(counts)
        starts = ends - counts
        owner = np.searchsorted(ends, rows, side="right")
        diagonal = (cols >= starts[owner]) & (cols < ends[owner])
        k = layout.order.size
        both = np.stack([np.bincount(local_rows[diagonal], minlength=k),
                         np.bincount(local_rows[~diagonal], minlength=k)], axis=1)
        # counts as float64 sums: exact below 2**53
        both = layout.ghosts.assemble(both.astype(np.float64))[layout.owned].astype(np.int64)
        PETSc = petsc_module()
        n_owned = int(counts[rank])
        d = np.minimum(both[:, 0], n_owned)
        o = np.minimum(both[:, 1], layout.n - n_owned)
        return d.astype(PETSc.IntType), o.astype(PETSc.IntType)

    @property
    def _global_n(self) -> int:
        """The matrix's rows over all ranks (:attr:`n` is the local vector's length)."""
        if self.layout is None or self.layout.ghosts is None:
            return self.n
        return self.layout.n

    def _new_ksp(self) -> Any:
        """The KSP of :attr:`ksp_options` over the defaults (see the module docstring)."""
        PETSc = petsc_module()
        ksp = PETSc.KSP().create(comm=self._comm())
        prefix = f"fem3d_{id(self)}_"
        ksp.setOptionsPrefix(prefix)
        opts = PETSc.Options(prefix)
        for key, value in self._defaults().items():
            opts[key] = value
        for key, value in self.ksp_options.items():
            opts[key] = value
        ksp.setOperators(self._mat)
        if opts.getString("pc_type", "") == "gamg" and self.options.points is not None:
            self._mat.setNearNullSpace(self._rigid_body_modes())
        ksp.setFromOptions()
        for key in {**self._defaults(), **self.ksp_options}:
            del opts[key]  # the prefix is this solver's: nothing left behind
        return ksp

    @contextlib.contextmanager
    def _product_options(self):
        """:attr:`ksp_options`' :data:`PRODUCT_OPTIONS` in PETSc's global database while the
        preconditioner sets up (GAMG's products read them there, not under the KSP's
        prefix); what the database held before, after."""
        given = {k: v for k, v in {**self._defaults(), **self.ksp_options}.items()
                 if k.startswith(PRODUCT_OPTIONS)}
        if not given:
            yield
            return
        opts = petsc_module().Options()
        before = {k: opts.getString(k) if opts.hasName(k) else None for k in given}
        for key, value in given.items():
            opts[key] = value
        try:
            yield
        finally:
            for key, value in before.items():
                if value is None:
                    del opts[key]
                else:
                    opts[key] = value

    def _defaults(self) -> dict[str, str]:
        PETSc = petsc_module()
        mumps = PETSc.Sys.hasExternalPackage("mumps")
        if mumps and self._global_n < GAMG_MIN_FREE_DOFS:
            return {"ksp_type": "preonly", "pc_type": "cholesky",
                    "pc_factor_mat_solver_type": "mumps"}
        # mat_product_clear: each product GAMG forms frees its intermediate data (A P, the
        # rows of P other ranks own, P's transposed pieces) once its values are computed:
        # kept only for a numeric product repeated on new values, which never comes (a new
        # KSP per matrix); the same bits, less memory through the set-up and the solve
        return {"ksp_type": "cg", "pc_type": "gamg", "ksp_rtol": f"{KSP_RTOL:g}",
                "ksp_max_it": "1000", "mat_product_clear": "1"}

    def _rigid_body_modes(self) -> Any:
        """GAMG's near-null space: the six rigid-body modes of the owned vertices."""
        PETSc = petsc_module()
        xyz = np.asarray(self.options.points, dtype=np.float64).reshape(-1)
        if self.layout is not None:
            xyz = xyz[self.layout.owned]
        coords = PETSc.Vec().createWithArray(np.ascontiguousarray(xyz), bsize=self._bs,
                                             comm=self._comm())
        return PETSc.NullSpace().createRigidBody(coords)

    def _factor(self, data: np.ndarray) -> None:
        PETSc = petsc_module()
        A = self._mat
        if A.isAssembled():
            A.zeroEntries()  # the same nonzero structure: MUMPS' analysis is kept
        # this rank's entries; those of rows on other ranks travel at assembly, and the
        # ranks' parts of a row add up
        A.setValuesIJV(self._row_ptr, self._cols, np.ascontiguousarray(data[self._by_row]),
                       addv=PETSc.InsertMode.ADD_VALUES, rowmap=self._row_of)
        A.assemble()
        if self._ksp is not None and not self._keeps_ksp:
            self._ksp.destroy()
            self._ksp = None
        if self._ksp is None:
            self._ksp = self._new_ksp()
            self._keeps_ksp = self._ksp.getPC().getType() in _FACTORIZATIONS
        else:
            self._ksp.setOperators(self._mat)
        try:
            with self._product_options():
                self._ksp.setUp()
        except PETSc.Error as err:
            raise NotPositiveDefinite(f"PETSc could not set up the solver ({err})",
                                      backend=self.name) from None
        failed, negative = _mumps_outcome(self._ksp.getPC())
        if failed:
            raise NotPositiveDefinite(f"MUMPS' factorization failed (INFOG(1) = {failed})",
                                      backend=self.name)
        if negative:
            raise NotPositiveDefinite(f"matrix not positive definite ({negative} negative "
                                      "pivots of LDL^T)", backend=self.name)

    def _release(self) -> None:
        """A KSP made anew for each matrix (GAMG's: :data:`_FACTORIZATIONS`) is destroyed
        now rather than at the next :meth:`factorize`: its hierarchy (coarse matrices,
        prolongators, the Galerkin products' kept data) is not alive through the next Newton
        matrix's assembly. A kept one (MUMPS') stays: its analysis serves the next matrix."""
        if self._ksp is not None and not self._keeps_ksp:
            self._ksp.destroy()
            self._ksp = None

    def _solve(self, b: np.ndarray) -> np.ndarray:
        if b.ndim == 2:
            return np.stack([self._solve(b[:, j]) for j in range(b.shape[1])], axis=1)
        PETSc = petsc_module()
        layout = self.layout
        owned = b if layout is None else b[layout.owned]
        rhs = self._mat.createVecLeft()
        rhs.setArray(np.ascontiguousarray(owned, dtype=np.float64))
        x = self._mat.createVecRight()
        self._ksp.solve(rhs, x)
        reason = self._ksp.getConvergedReason()
        self._iterations = int(self._ksp.getIterationNumber())
        self._residual = float(self._ksp.getResidualNorm()) / (float(rhs.norm()) or 1.0)
        self._converged = reason > 0
        part = x.getArray(readonly=True).copy()
        x.destroy()
        rhs.destroy()
        if layout is not None and layout.ghosts is not None:
            local = np.zeros(self.n)
            local[layout.owned] = part
            part = layout.ghosts.complete(local)  # the ghosts: their owners' entries
        if reason < 0 and reason != PETSc.KSP.ConvergedReason.DIVERGED_MAX_IT:
            part[:] = np.nan  # indefinite or broken down: Newton falls back to -g
        return part


#: The preconditioners whose KSP is kept from one matrix to the next (a factorization keeps
#: its symbolic analysis, and its factor is a function of the matrix alone). Any other (GAMG)
#: carries state from one set-up to the next, so its KSP is made anew for each matrix: a
#: resumed run then computes bit for bit what an uninterrupted one does.
_FACTORIZATIONS = ("cholesky", "lu")


def _mumps_outcome(pc: Any) -> tuple[int, int]:
    """MUMPS' error code (``INFOG(1)`` when negative, else 0) and count of negative pivots
    (``INFOG(12)``) of the factorization of ``pc``; ``(0, 0)`` for another
    preconditioner. The same on every rank (MUMPS' global information)."""
    if pc.getType() not in ("cholesky", "lu") or pc.getFactorSolverType() != "mumps":
        return 0, 0
    F = pc.getFactorMatrix()
    status = int(F.getMumpsInfog(1))
    return min(status, 0), int(F.getMumpsInfog(12))
