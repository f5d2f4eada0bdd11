"""Intel MKL PARDISO through pypardiso, the ``"pardiso"`` solver.

Real SPD matrix type (``mtype=2``), METIS ordering: analysis phase 11 once per pattern,
numeric phase 22 per ``factorize``, solve phase 33, on the stored upper triangle.
"""

from __future__ import annotations

import functools
import os
from typing import ClassVar

import numpy as np

from fem3d.solve.linear.base import DirectSolver, NotPositiveDefinite

__all__ = ["PardisoSolver"]

_MKL_RT: str | None = None


def _pardiso_solver():
    """A new ``pypardiso.PyPardisoSolver`` (real SPD), finding libmkl_rt only once.

    pypardiso searches ``sys.prefix`` for ``mkl_rt`` on every construction (seconds); the path
    found the first time is handed to later ones through ``PYPARDISO_MKL_RT``.
    """
    global _MKL_RT
    import pypardiso  # optional back end (fem3d[bench]): imported when chosen

    if _MKL_RT is None or "PYPARDISO_MKL_RT" in os.environ:
        solver = pypardiso.PyPardisoSolver(mtype=2)
        _MKL_RT = solver.libmkl._name
        return solver
    os.environ["PYPARDISO_MKL_RT"] = _MKL_RT
    try:
        return pypardiso.PyPardisoSolver(mtype=2)
    finally:
        del os.environ["PYPARDISO_MKL_RT"]


class PardisoSolver(DirectSolver):
    """MKL PARDISO's sparse Cholesky (``"pardiso"``)."""

    name: ClassVar[str] = "pardiso"
    install_hint: ClassVar[str] = "pip install pypardiso"

    @classmethod
    @functools.cache
    def available(cls) -> bool:
        """Whether pypardiso imports and finds libmkl_rt."""
        try:
            _pardiso_solver()  # raises ImportError when mkl_rt is missing
        except (ImportError, OSError):
            return False
        return True

    def _analyse(self) -> None:
        from pypardiso.pardiso_wrapper import PyPardisoError  # optional back end

        self._pardiso_error = PyPardisoError
        self._release()  # a pattern analysed before
        solver = _pardiso_solver()  # holds the MKL handle (pt) and iparm
        iparm = solver.iparm
        iparm[:] = 0
        iparm[0] = 1  # iparm given here, not defaults
        iparm[1] = 2  # METIS nested dissection ordering
        iparm[9] = 8  # pivot perturbation 1e-8 (only used by the indefinite types)
        iparm[17] = -1  # report nnz(L) in iparm[17]
        iparm[34] = 1  # zero-based ia/ja: no index conversion per call
        upper = self._indices >= self._rows
        self._upper = np.flatnonzero(upper)
        counts = np.bincount(self._rows[upper], minlength=self.n)
        self._ia = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        self._ja = self._indices[upper].astype(np.int32)
        self._pardiso = solver
        self._a_upper = np.ones(len(self._ja))
        self._pardiso_call(11, np.zeros((self.n, 1)))

    def _pardiso_call(self, phase: int, b: np.ndarray) -> np.ndarray:
        """One MKL ``pardiso`` call on the stored upper triangle (real SPD, ``mtype = 2``)."""
        import ctypes  # the optional PARDISO back end's calls only

        s = self._pardiso
        i32 = ctypes.c_int32
        i32p = ctypes.POINTER(i32)
        f64p = ctypes.POINTER(ctypes.c_double)
        b = np.asfortranarray(b, dtype=np.float64)
        x = np.zeros_like(b)
        err = i32(0)
        s._mkl_pardiso(
            s.pt.ctypes.data_as(ctypes.POINTER(s._pt_type[0])),
            ctypes.byref(i32(1)), ctypes.byref(i32(1)), ctypes.byref(i32(2)),
            ctypes.byref(i32(phase)), ctypes.byref(i32(self.n)),
            self._a_upper.ctypes.data_as(f64p), self._ia.ctypes.data_as(i32p),
            self._ja.ctypes.data_as(i32p), s.perm.ctypes.data_as(i32p),
            ctypes.byref(i32(b.shape[1])), s.iparm.ctypes.data_as(i32p), ctypes.byref(i32(0)),
            b.ctypes.data_as(f64p), x.ctypes.data_as(f64p), ctypes.byref(err),
        )
        if err.value != 0:
            # -4: zero pivot (for mtype 2: the matrix is not positive definite)
            if phase == 22 and err.value == -4:
                raise NotPositiveDefinite("PARDISO error -4 (zero or negative pivot)",
                                          backend="pardiso")
            raise RuntimeError(f"PARDISO phase {phase} failed with error {err.value}")
        return x

    def _factor(self, data: np.ndarray) -> None:
        self._a_upper = np.ascontiguousarray(data[self._upper])
        self._pardiso_call(22, np.zeros((self.n, 1)))

    def _solve(self, b: np.ndarray) -> np.ndarray:
        x = self._pardiso_call(33, b.reshape(self.n, -1))
        return np.ascontiguousarray(x).reshape(b.shape)

    def _release(self) -> None:
        """Free PARDISO's internal memory of the analysed pattern (phase -1)."""
        if getattr(self, "_pardiso", None) is not None:
            self._pardiso_call(-1, np.zeros((self.n, 1)))
            self._pardiso = None

    def __del__(self) -> None:
        try:
            self._release()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass
