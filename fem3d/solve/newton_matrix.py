"""A reduced Newton matrix built from the terms' Hessian contributions.

:class:`NewtonMatrixBuilder` assembles ``P A P^T`` on a :class:`~fem3d.solve.system.System`'s
reduced pattern (or the pattern objective terms widened it to) in the order the terms come.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from fem3d.physics.assembly import add_element_hessians
from fem3d.physics.model import Model

if TYPE_CHECKING:
    from fem3d.solve.system import System

__all__ = ["NewtonMatrixBuilder"]


class NewtonMatrixBuilder:
    """A reduced Newton matrix ``P A P^T`` on :attr:`System.pattern_free`, built from the
    terms' contributions in the order they come.

    Each element-matrix entry goes straight to its reduced CSR slot (entries on fixed DOFs
    to a discarded sink slot), with ``position_scale`` folded into the element volumes, so
    no full ``3n x 3n`` matrix is built and reduced per Newton iteration. From
    :data:`~fem3d.solve.system.LEAN_ASSEMBLY_MIN_TETS` tets (no element-to-reduced-slot map)
    the contributions on the mesh's pattern accumulate on the full pattern and are gathered
    once: every kept entry gets the same contributions in the same order either way. Entries
    outside the mesh's pattern (contact pairs) widen the solver's pattern
    (:meth:`System.add_hessian`).

    Parameters
    ----------
    system : System
    position_scale : float
        ``h^2``: what position terms' Hessians are scaled by (the chain rule).
    psd : bool
        Terms add their PSD-projected Hessians.

    Attributes
    ----------
    kept : (nnz_free,) int
        The slot in ``model.pattern``'s data of every entry of :attr:`System.pattern_free`:
        a term whose values stay the same over a step gathers them once (``values[kept]``)
        and passes them as ``reduced`` to :meth:`add_pattern_values`.
    """

    def __init__(self, system: System, position_scale: float, psd: bool) -> None:
        self.system = system
        self.position_scale = position_scale
        self.psd = psd
        self.kept = system._kept
        nnz = system.pattern_free.nnz
        self._nnz = nnz
        self._data = np.empty(nnz + 1)  # the last slot is the sink of fixed-DOF entries
        self._data[nnz] = 0.0
        self._empty = True  # nothing added to _data yet
        self._lean = system._free_scatter is None
        self._full: np.ndarray | None = None  # lean: the full-pattern sum before the gather
        self._gathered = False
        self._matrix: sp.csr_matrix | None = None  # once entries outside the pattern came

    def _reduced(self) -> np.ndarray:
        """``_data`` with every contribution so far (gathers a lean full-pattern sum)."""
        if self._full is not None:
            # mode="clip": with mode="raise" (the default) NumPy buffers ``out`` (a copy of
            # the whole array; 0.75 s of a 1e6-tet Newton matrix instead of 0.04 s)
            np.take(self._full, self.system._kept, out=self._data[:self._nnz], mode="clip")
            self._full = None
            self._empty = False
        elif self._empty:
            self._data[:self._nnz] = 0.0
            self._empty = False
        self._gathered = True
        return self._data

    def _full_pattern(self) -> bool:
        """Whether mesh-pattern contributions still accumulate on the full pattern."""
        return self._lean and not self._gathered and self._matrix is None

    def add_pattern_values(self, values: np.ndarray, scale: float | None = None, *,
                           reduced: np.ndarray | None = None) -> None:
        """Add ``scale * values`` (``(model.nnz,)``, CSR data on ``model.pattern``; no scale:
        the values as they are; ``reduced``: ``values`` gathered to :attr:`System.pattern_free`
        already, e.g. ``mass_free.data``)."""
        if reduced is not None and scale is None and not self._full_pattern() and \
                self._matrix is None:
            self.add_reduced_values(reduced)
            return
        if self._matrix is not None:
            v = values if scale is None else scale * values
            self._matrix = self.system.add_hessian(self._matrix, self.system.model.csr(v))
        elif self._full_pattern():
            if self._full is None:
                self._full = np.array(values) if scale is None else scale * values
            else:
                self._full += values if scale is None else scale * values
        elif self._empty:
            kept = values[self.system._kept]
            self._data[:self._nnz] = kept if scale is None else scale * kept
            self._empty = False
        else:
            kept = values[self.system._kept]
            self._data[:self._nnz] += kept if scale is None else scale * kept

    def add_elements(self, model: Model, kernel: str, q: np.ndarray) -> None:
        """Add the element Hessians (``kernel``: ``"hessian"`` or ``"hessian_psd"``) at
        ``q``, scaled by :attr:`position_scale`."""
        system = self.system
        vol = system._volumes_times(self.position_scale)
        if self._matrix is not None:
            full = np.zeros(model.nnz)
            add_element_hessians(model, kernel, q, vol, model.scatter, full)
            self._matrix = system.add_hessian(self._matrix, model.csr(full))
        elif self._full_pattern():
            if self._full is None:
                self._full = np.zeros(model.nnz)
            add_element_hessians(model, kernel, q, vol, model.scatter, self._full)
        else:
            data = self._reduced() if self._empty or self._lean else self._data
            scatter = system._free_scatter
            if scatter is None:  # lean, after a gather: through a full-pattern buffer
                full = np.zeros(model.nnz)
                add_element_hessians(model, kernel, q, vol, model.scatter, full)
                data[:self._nnz] += full[system._kept]
            else:
                add_element_hessians(model, kernel, q, vol, scatter, data)

    def add_vertex_blocks(self, vertices: np.ndarray, blocks: np.ndarray,
                          scale: float) -> None:
        """Add ``scale * blocks`` (``(k, 3, 3)``) on the diagonal blocks of ``vertices``
        (repeats summed in order)."""
        if self._matrix is not None:
            d = 3 * np.asarray(vertices)[:, None] + np.arange(3)
            rows = np.broadcast_to(d[:, :, None], (d.shape[0], 3, 3)).reshape(-1)
            cols = np.broadcast_to(d[:, None, :], (d.shape[0], 3, 3)).reshape(-1)
            self.add_entries((rows, cols, blocks.reshape(-1)), scale)
            return
        data = self._reduced()
        np.add.at(data, self.system.vertex_block_slots(vertices), scale * blocks.reshape(-1))

    def add_reduced_values(self, values: np.ndarray) -> None:
        """Add ``values`` given on :attr:`System.pattern_free` itself."""
        if self._matrix is not None:
            A = self.system.on_solver_pattern(self._matrix)
            data = np.array(A.data)
            ext = self.system._ext
            if ext is None:
                data += values
            else:
                data[ext.base_pos] += values
            self._matrix = self.system._like(A, data)
            return
        if self._empty and not self._full_pattern():
            self._data[:self._nnz] = values
            self._empty = False
        else:
            self._reduced()[:self._nnz] += values

    def add_entries(self, H, scale: float) -> None:
        """Add ``scale * H`` given in full-DOF indices (``(3n, 3n)`` sparse matrix or ``(rows,
        cols, values)``; see :meth:`System.add_hessian`): may widen the solver's pattern."""
        self._matrix = self.system.add_hessian(self.matrix(), H, scale)

    def matrix(self) -> sp.csr_matrix:
        """The matrix so far, on :attr:`System.pattern_free` or the solver's pattern."""
        if self._matrix is not None:
            return self._matrix
        data = self._reduced()
        pf = self.system.pattern_free
        A = sp.csr_matrix((data[:self._nnz], pf.indices, pf.indptr), shape=pf.shape,
                          copy=False)
        A.has_canonical_format = True
        return A
