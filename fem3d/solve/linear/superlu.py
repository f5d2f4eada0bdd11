"""SuperLU through SciPy (``scipy.sparse.linalg.splu``), the ``"superlu"`` solver.

Diagonal pivoting (``SymmetricMode``): the first factorization computes the fill-reducing
ordering (``MMD_AT_PLUS_A``; SuperLU has no separate analysis), later ones run on the
symmetrically pre-permuted matrix with ``permc_spec="NATURAL"``. Needs only SciPy; several
times slower than CHOLMOD or PARDISO on large meshes (no supernodal BLAS-3 Cholesky, LU
stores both triangles).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fem3d.solve.linear.base import DirectSolver, NotPositiveDefinite

__all__ = ["SuperLUSolver"]


class SuperLUSolver(DirectSolver):
    """SciPy's SuperLU with diagonal pivoting, an ``LDL^T`` in effect (``"superlu"``)."""

    name: ClassVar[str] = "superlu"

    def _analyse(self) -> None:
        # SuperLU cannot order without factorizing: the first factorization orders (MMD on
        # A^T + A, pattern only) and records the permutation; later ones reuse it.
        self._perm = None
        self._lu_permuted = False

    def _set_superlu_ordering(self, perm_c: np.ndarray) -> None:
        # SuperLU moves column j to position perm_c[j]: the new order lists argsort(perm_c).
        perm = np.argsort(np.asarray(perm_c))
        self._perm = perm
        self._iperm = np.asarray(perm_c)
        # Position map: data of P A P^T (CSC, canonical) = data[self._pmap]
        nnz = len(self._indices)
        tagged = self._matrix(np.arange(1, nnz + 1, dtype=np.float64))
        PAPt = tagged[perm][:, perm].tocsc()
        PAPt.sort_indices()
        self._p_indptr, self._p_indices = PAPt.indptr, PAPt.indices
        self._pmap = PAPt.data.astype(np.int64) - 1

    def _factor(self, data: np.ndarray) -> None:
        first = self._perm is None
        if first:
            Ap = self._csc_view(data)  # symmetric: CSR arrays are the CSC arrays
        else:
            Ap = sp.csc_matrix(
                (data[self._pmap], self._p_indices, self._p_indptr), shape=(self.n, self.n)
            )
        try:
            lu = spla.splu(
                Ap,
                permc_spec="MMD_AT_PLUS_A" if first else "NATURAL",
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
        except RuntimeError as err:  # "Factor is exactly singular"
            raise NotPositiveDefinite(str(err), backend="superlu") from err
        if first:
            self._set_superlu_ordering(lu.perm_c)  # depends on the pattern only
        # With diagonal pivoting the pivots are the D of A = L D L^T: SPD <=> all > 0.
        d = lu.U.diagonal()
        if not np.array_equal(lu.perm_r, lu.perm_c) or not np.all(d > 0):
            raise NotPositiveDefinite(
                f"{int(np.sum(d <= 0))} non-positive pivot(s)", backend="superlu"
            )
        self._lu = lu
        self._lu_permuted = not first

    def _solve(self, b: np.ndarray) -> np.ndarray:
        if not self._lu_permuted:
            return self._lu.solve(b)
        return self._lu.solve(b[self._perm])[self._iperm]
