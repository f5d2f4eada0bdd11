"""CHOLMOD Cholesky through scikit-sparse (``sksparse.cholmod``), the ``"cholmod"`` solver.

Supernodal, or simplicial ``LDL^T`` for small factors with short columns (the classic
scenes), where the supernodal code's dense-block overhead costs more than it saves
(:data:`SIMPLICIAL_MAX_FLOPS_PER_ENTRY`). Link it against an optimized BLAS (OpenBLAS): with
the reference BLAS the supernodal factorization is ~20x slower (:func:`loaded_blas`; a
warning says so).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import warnings
from collections.abc import Iterator
from typing import ClassVar

import numpy as np

from fem3d.solve.linear.base import DirectSolver, NotPositiveDefinite, SolverOptions

__all__ = ["CholmodSolver", "SIMPLICIAL_MAX_FLOPS_PER_ENTRY", "SIMPLICIAL_MAX_N", "loaded_blas"]

#: CHOLMOD runs simplicial (not supernodal) when the matrix has at most
#: :data:`SIMPLICIAL_MAX_N` rows and its factor costs fewer than this many flops per stored
#: entry (``sum c_j^2 / sum c_j`` over the column counts ``c_j`` of ``L``). Measured on this
#: project's 2-core machine with OpenBLAS (one thread, CPU time, best of 9): simplicial is
#: 1.2-1.6x faster on the armadillo (ratio 32), as fast or 1.7x faster on the bunny (66) and
#: as fast on a 300-DOF box (55); supernodal is 2.4x faster on a 540-DOF box (83), 3.0x on
#: the armadillo refined x8 (3,813 DOFs, 102), 2.4x on an 880-DOF box (118) and 7x on the
#: bunny refined x8 (266). The simplicial code slows down sharply once ``L`` leaves the cache.
#: CHOLMOD's own switch (40) sends the bunny to the supernodal code.
SIMPLICIAL_MAX_FLOPS_PER_ENTRY = 75.0
#: Above this size the pattern is not probed: the factorization is supernodal.
SIMPLICIAL_MAX_N = 5000

#: :attr:`SolverOptions.cholmod_mode`'s choices.
CHOLMOD_MODES = ("auto", "supernodal", "simplicial")


class CholmodSolver(DirectSolver):
    """CHOLMOD's Cholesky factorization (``"cholmod"``).

    Parameters
    ----------
    options : SolverOptions, optional
        ``cholmod_mode``: ``"auto"`` (default) probes small patterns and takes simplicial when
        their factor is cheap per entry (:data:`SIMPLICIAL_MAX_FLOPS_PER_ENTRY`), supernodal
        otherwise.

    Attributes
    ----------
    cholmod_mode : {"supernodal", "simplicial"} or None
        The factorization chosen for the analysed pattern (None before :meth:`analyse`).
    """

    name: ClassVar[str] = "cholmod"
    install_hint: ClassVar[str] = ("pip install 'fem3d[cholmod]' (after the SuiteSparse "
                                   "headers: sudo bash scripts/install_cholmod.sh)")

    def __init__(self, options: SolverOptions | None = None) -> None:
        super().__init__(options)
        mode = self.options.cholmod_mode
        if mode not in CHOLMOD_MODES:
            raise ValueError(f"cholmod_mode must be 'auto', 'supernodal' or 'simplicial', got "
                             f"{mode!r}")
        self.cholmod_mode: str | None = None

    @classmethod
    @functools.cache
    def available(cls) -> bool:
        """Whether scikit-sparse's CHOLMOD imports."""
        try:
            import sksparse.cholmod  # noqa: F401
        except (ImportError, OSError):
            return False
        return True

    def _analyse(self) -> None:
        from sksparse import cholmod  # optional (fem3d[cholmod]): imported when chosen

        _warn_reference_blas()
        self._cholmod = cholmod
        pattern = self._csc_view(np.ones(len(self._indices)))
        self.cholmod_mode = self.options.cholmod_mode
        if self.cholmod_mode == "auto":
            cheap = self.n <= SIMPLICIAL_MAX_N and \
                self._factor_cost_per_entry() < SIMPLICIAL_MAX_FLOPS_PER_ENTRY
            self.cholmod_mode = "simplicial" if cheap else "supernodal"
        with _serial_openmp_regions():
            self._chol = cholmod.analyze(pattern, mode=self.cholmod_mode)

    def _factor_cost_per_entry(self) -> float:
        """Flops per entry of ``L`` (``sum c_j^2 / sum c_j``) for this pattern, from one
        simplicial factorization of a diagonally dominant matrix on it (``L``'s structure does
        not depend on the values)."""
        data = np.full(len(self._indices), -1.0)
        data[self._diag_pos] = np.diff(self._indptr)  # row count > |off-diagonal sum|: SPD
        with _serial_openmp_regions():
            probe = self._cholmod.analyze(self._csc_view(data), mode="simplicial")
            probe.cholesky_inplace(self._csc_view(data))
        counts = np.diff(probe.L().indptr).astype(np.float64)
        return float((counts * counts).sum() / counts.sum())

    def _factor(self, data: np.ndarray) -> None:
        try:
            with _serial_openmp_regions():
                self._chol.cholesky_inplace(self._csc_view(data))
        except self._cholmod.CholmodNotPositiveDefiniteError as err:
            raise NotPositiveDefinite(str(err), backend="cholmod") from err
        if self.cholmod_mode == "simplicial":
            # simplicial CHOLMOD computes LDL^T, which exists for indefinite matrices too:
            # positive definite <=> every pivot of D is positive
            pivots = self._chol.D()
            if not np.all(pivots > 0.0):
                bad = int(np.count_nonzero(~(pivots > 0.0)))
                raise NotPositiveDefinite(
                    f"matrix not positive definite ({bad} non-positive pivots of LDL^T)",
                    backend="cholmod")

    def _solve(self, b: np.ndarray) -> np.ndarray:
        with _serial_openmp_regions():
            return self._chol.solve_A(b)


def _mapped_libraries() -> set[str]:
    """Paths of the shared libraries mapped into this process (Linux; else empty)."""
    try:
        with open("/proc/self/maps") as f:
            return {line.split()[-1] for line in f if "/" in line}
    except OSError:
        return set()


def loaded_blas() -> list[str]:
    """Paths of the BLAS/LAPACK shared libraries mapped into this process (Linux; else [])."""
    return sorted(p for p in _mapped_libraries()
                  if "blas" in os.path.basename(p) or "lapack" in p)


@functools.cache
def _openmp_runtimes() -> tuple[ctypes.CDLL, ...]:
    """The GNU OpenMP runtimes (``libgomp``) mapped into this process once CHOLMOD is loaded."""
    runtimes = []
    for path in sorted(p for p in _mapped_libraries() if "libgomp" in os.path.basename(p)):
        try:
            lib = ctypes.CDLL(path)
            lib.omp_get_max_active_levels.restype = ctypes.c_int
            lib.omp_set_max_active_levels.argtypes = [ctypes.c_int]
        except (OSError, AttributeError):
            continue
        runtimes.append(lib)
    return tuple(runtimes)


@contextlib.contextmanager
def _serial_openmp_regions() -> Iterator[None]:
    """Run the OpenMP parallel regions entered inside on one thread.

    CHOLMOD 3's supernodal code (Debian's ``libcholmod3``) opens a parallel region of a
    fixed 4 threads per supernode, whatever ``OMP_NUM_THREADS`` says; on a 2-core machine
    the threads wait for each other's cores at every supernode. Measured on the pile's 15k-DOF
    Newton matrix: 93 ms per factorization as shipped, 24 ms with those regions on one thread,
    the same bits (the loops in them are independent scatters; the BLAS keeps its own
    threads). A zero ``max-active-levels`` makes every region inactive: ``libgomp`` has no
    call that caps a ``num_threads`` clause (``OMP_THREAD_LIMIT`` is read once, at load).
    """
    runtimes = _openmp_runtimes()
    saved = [lib.omp_get_max_active_levels() for lib in runtimes]
    for lib in runtimes:
        lib.omp_set_max_active_levels(0)
    try:
        yield
    finally:
        for lib, levels in zip(runtimes, saved, strict=True):
            lib.omp_set_max_active_levels(levels)


@functools.cache
def _warn_reference_blas() -> None:
    """Warn once when CHOLMOD runs on Debian's reference BLAS (5-20x slower factorization)."""
    ref = [p for p in loaded_blas() if "/blas/libblas.so" in p]
    if ref:
        warnings.warn(
            f"CHOLMOD uses the reference BLAS ({ref[0]}): its supernodal factorization is "
            "5-20x slower than with OpenBLAS (apt-get install libopenblas0-pthread)",
            RuntimeWarning,
            stacklevel=4,
        )
