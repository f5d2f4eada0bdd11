"""Stiffness damping's matrix with its eigendecompositions, kept for the backward pass.

``D(q) = alpha M + beta K_psd(q)``: ``K_psd`` is the elastic Hessian with ``A = dP/dF`` (9x9)
projected to positive semi-definite at each of the element's quadrature points (a linear
tet: one point, its volume the weight; a quadratic tet: its rule's points, ``w det J`` the
weights), ``K_psd,e = sum_q w_q B_q^T A_psd(F_q) B_q`` with ``B_q = dF_q/dx_e``
(:func:`quadrature_points`, :func:`strain_operators`; the material's per-``F`` kernels
:func:`point_kernels`, the same on every element). The backward pass needs, at each
step's start ``q_n``, both ``D(q_n)`` (in the transposed Newton matrix) and the eigenvectors
and eigenvalues of every projected ``A`` (the projection's derivative, Daleckii-Krein:
:func:`fem3d.diff.terms.psd_bilinear_vjp`). :func:`linearize_damping` computes both from one
eigendecomposition per indefinite element; :class:`RecordingDamping` is the forward step's
damping term in :mod:`fem3d.diff` runs: it builds ``D`` that way and, while recording (the
recomputation of a segment, the last segment of the first forward run), keeps each step's
:class:`DampingLinearization` for the backward step that reads it (at most ``k`` of them,
within a byte budget), so that a backward step neither assembles ``D`` nor decomposes an
element again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fem3d.kernels.backend import c_extension
from fem3d.kernels.dispatch import material_kernels
from fem3d.physics.terms.damping import RayleighDamping

__all__ = ["DampingLinearization", "linearize_damping", "projected_eigen", "psd_elements",
           "strain_operators", "quadrature_points", "point_kernels", "chunk_elements", "per_point",
           "RecordingDamping", "DEFAULT_CACHE_BYTES"]

#: Default byte budget of the kept linearizations (``trajectory_gradient(cache_bytes=...)``).
DEFAULT_CACHE_BYTES = 1 << 30


@dataclass
class DampingLinearization:
    """``D`` at ``q`` and the eigendecompositions of its projected element blocks.

    Attributes
    ----------
    q : (3n,) float64
        The positions (a copy; a kept linearization is used only at these exact positions).
    data : (nnz,) float64
        ``D = alpha M + beta K_psd(q)`` on ``model.pattern``.
    eig : list of (bad, values, V)
        Per material group (:func:`fem3d.diff.terms.element_groups`' order): the group-local
        indices ``(k,)`` of the quadrature points (element ``i``'s point ``j`` is
        ``i nq + j``; a linear tet's one point: the element's index) whose ``A`` has a
        negative eigenvalue (projected), its eigenvalues ``(k, 9)`` and eigenvectors
        ``(k, 9, 9)`` (columns); every other point's ``A`` is kept exactly.
    """

    q: np.ndarray
    data: np.ndarray
    eig: list

    @property
    def nbytes(self) -> int:
        """Bytes held."""
        return int(self.q.nbytes + self.data.nbytes +
                   sum(b.nbytes + w.nbytes + v.nbytes for b, w, v in self.eig))


def psd_elements(A: np.ndarray) -> np.ndarray:
    """Which symmetric ``A`` (``(m, n, n)``) an LDL^T without pivoting proves positive
    semi-definite (every pivot ``>= -tol``, no zero pivot with coupling; ``tol = 1e-12
    |A|_F``, as the C kernels' projection decides): ``(m,) bool``. The others need an
    eigendecomposition (one with no negative eigenvalue is kept too)."""
    m, n, _ = A.shape
    tol = 1e-12 * np.sqrt(np.einsum("eij,eij->e", A, A))
    S = np.array(A, dtype=np.float64)  # right-looking: the Schur complements in place
    ok = np.ones(m, dtype=bool)
    for k in range(n):
        dk, col = S[:, k, k], S[:, k + 1:, k]
        big = dk > tol
        ok &= (dk >= -tol) & ~((~big)[:, None] & (np.abs(col) > tol[:, None])).any(axis=1)
        lk = col / np.where(big, dk, 1.0)[:, None] * big[:, None]
        S[:, k + 1:, k + 1:] -= lk[:, :, None] * col[:, None, :]
    return ok


def projected_eigen(A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The blocks of ``A`` (``(m, n, n)`` symmetric) with a negative eigenvalue, and their
    eigendecompositions: ``(indices (k,), values (k, n), vectors (k, n, n))`` (columns).

    The C extension's ``psd_eigen`` (an LDL^T test per block, a tridiagonal QL
    decomposition where it fails) when built, else :func:`psd_elements` and LAPACK's
    ``eigh``; the others are positive semi-definite (kept exactly by the projection).
    """
    ext = c_extension()
    if ext is not None and hasattr(ext, "psd_eigen"):
        m, n, _ = A.shape
        values, V = np.empty((m, n)), np.empty((m, n, n))
        flags = np.empty(m, dtype=np.int32)
        ext.psd_eigen(np.ascontiguousarray(A), values, V, flags)
        bad = np.flatnonzero(flags == 1)
        return bad, values[bad], V[bad]
    bad = np.flatnonzero(~psd_elements(A))
    values, V = np.linalg.eigh(A[bad])
    neg = (values < 0.0).any(axis=1)  # a PSD A is kept exactly
    return bad[neg], values[neg], V[neg]


def strain_operators(Dm: np.ndarray) -> np.ndarray:
    """``B = dF/dx`` at each point, ``(p, 9, 3 n)``: ``F_cj = sum_v x_vc Dm_vj`` with ``F``
    row-major ``(c, j)`` and ``x`` ``(v, c)``; ``Dm``: ``(p, n, 3)`` shape-function
    gradients of the ``n`` nodes at ``p`` points (a linear tet: ``(m, 4, 3)``, ``B (m, 9, 12)``)."""
    m, n = Dm.shape[0], Dm.shape[1]
    B = np.zeros((m, 3, 3, n, 3))
    for c in range(3):
        B[:, c, :, :, c] = Dm.transpose(0, 2, 1)
    return B.reshape(m, 9, 3 * n)


def quadrature_points(model, els: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The element's quadrature points of elements ``els`` (None: all), flattened.

    Parameters
    ----------
    model : Model
        Its ``dphi_dX`` and ``vol`` (:meth:`fem3d.mesh.element.Element.rest_shape`: one
        point per linear tet, ``(m, 4, 3)`` and ``(m,)``; ``nq`` per quadratic tet,
        ``(m, nq, 10, 3)`` and ``(m, nq)``).
    els : (k,) int, optional

    Returns
    -------
    D : (k nq, n, 3) float64
        Shape-function gradients at each point (element ``i``'s point ``j``: row
        ``i nq + j``).
    w : (k, nq) float64
        The points' weights (``w det J``; a linear tet: its volume).
    """
    D = model.dphi_dX if els is None else model.dphi_dX[els]
    w = model.vol if els is None else model.vol[els]
    w = w.reshape(w.shape[0], -1)
    return D.reshape(-1, model.element.n_nodes, 3), w


def point_kernels(group):
    """The per-``F`` kernels of a material group (``d2psi_dF2``, ``d3psi_contract``): the
    material's own module, the same on every element (its element kernels evaluate them at
    each quadrature point)."""
    return material_kernels(group.material, group.kernels.backend)


def chunk_elements(model) -> int:
    """Elements per chunk of :func:`linearize_damping`: :data:`CHUNK` linear tets, and as
    many bytes of an element's points' blocks for another element (``CHUNK * 144 /
    (nq d^2)``, ``d`` its DOFs)."""
    nq = model.vol.reshape(model.vol.shape[0], -1).shape[1]
    return max(1, CHUNK * 144 // (nq * model.element.n_entries))


#: Elements per chunk of :func:`linearize_damping` (bounds its temporaries, about 5 kB a tet:
#: the element blocks, strain operators, slots and eigendecompositions of one chunk).
CHUNK = 1 << 16


def _add_blocks(data: np.ndarray, slots: np.ndarray, blocks: np.ndarray) -> None:
    """``data[slots] += blocks`` with repeated slots summed (one ``bincount`` over the range
    of slots the chunk touches)."""
    lo, hi = int(slots.min()), int(slots.max()) + 1
    data[lo:hi] += np.bincount(slots.reshape(-1) - lo, weights=blocks.reshape(-1),
                               minlength=hi - lo)


def per_point(a: np.ndarray, nq: int) -> np.ndarray:
    """Each element's row of ``a`` once per quadrature point (``a`` itself for one point)."""
    return a if nq == 1 else np.repeat(a, nq, axis=0)


def linearize_damping(term: RayleighDamping, groups: list[tuple], q: np.ndarray,
                      B: np.ndarray | None = None) -> DampingLinearization:
    """``D(q)`` of a Rayleigh damping term and its eigendecompositions (see
    :class:`DampingLinearization`): the same matrix as ``term.matrix_data(q)`` up to
    round-off (the projection by :func:`projected_eigen` instead of the C kernels' Jacobi
    rotations). Elements go by chunks of :func:`chunk_elements`.

    Parameters
    ----------
    term : RayleighDamping
        Its ``alpha M`` and ``beta w`` (active; per element, or per quadrature point).
    groups : list
        :func:`fem3d.diff.terms.element_groups` of its model.
    q : (3n,) or (n, 3) float64
    B : (m nq, 9, d) float64, optional
        :func:`strain_operators` at every quadrature point of the model (None: made per
        chunk).
    """
    model = term.model
    q = np.array(q, dtype=np.float64).reshape(-1)
    data = np.zeros(model.nnz)
    eig = []
    beta_w = term._beta_vol
    x = q.reshape(-1, 3)
    d, nq = model.element.n_dofs, model.vol.reshape(model.n_tets, -1).shape[1]
    scatter = model.scatter.reshape(-1, d * d)
    chunk = chunk_elements(model)
    for g, els, params, inputs in groups if beta_w is not None else ():
        kernels = point_kernels(g)
        parts = [(np.zeros(0, dtype=np.int64), np.zeros((0, 9)), np.zeros((0, 9, 9)))]
        for lo in range(0, els.size, chunk):
            cut = slice(lo, lo + chunk)
            e = els[cut]
            whole = e.size == model.n_tets  # every element, in order: no copies
            Dm, _ = quadrature_points(model, None if whole else e)
            Be = strain_operators(Dm) if B is None else B if whole else \
                B.reshape(model.n_tets, nq, 9, d)[e].reshape(-1, 9, d)
            F = np.einsum("evc,evj->ecj", per_point(x[model.T[e]], nq), Dm)
            A = kernels.d2psi_dF2(F, *(per_point(v[cut], nq) for v in inputs),
                                  per_point(params[cut], nq)).reshape(-1, 9, 9)
            bad, values, V = projected_eigen(A)
            A[bad] = (V * np.maximum(values, 0.0)[:, None, :]) @ V.transpose(0, 2, 1)
            H = Be.transpose(0, 2, 1) @ (A @ Be)
            H *= beta_w[e].reshape(-1)[:, None, None]
            if nq > 1:  # the element's blocks: the sum over its points
                H = H.reshape(e.size, nq, d, d).sum(axis=1)
            if whole:
                data += np.bincount(model.scatter, weights=H.reshape(-1), minlength=data.size)
            else:
                _add_blocks(data, scatter[e], H)
            parts.append((bad + lo * nq, values, V))
        eig.append(tuple(np.concatenate(p) for p in zip(*parts, strict=True)))
    if term._alpha_mass is not None:
        data += term._alpha_mass
    return DampingLinearization(q=q, data=data, eig=eig)


class RecordingDamping(RayleighDamping):
    """The forward step's Rayleigh damping in :mod:`fem3d.diff` runs: ``D`` from
    :func:`linearize_damping`; while :attr:`recording`, each step's linearization is kept by
    the step's number (:meth:`take`), up to ``cache_bytes`` in all.

    Parameters
    ----------
    term : RayleighDamping
        The system's damping term (its model and coefficients).
    groups : list
        :func:`fem3d.diff.terms.element_groups` of the model.
    cache_bytes : int
    """

    def __init__(self, term: RayleighDamping, groups: list[tuple],
                 cache_bytes: int = DEFAULT_CACHE_BYTES) -> None:
        super().__init__(term.model, term.alpha, term.beta)
        self.groups, self.cache_bytes = groups, int(cache_bytes)
        #: the strain operators at every quadrature point, kept for a model of one chunk
        #: (else made per chunk)
        self.B = strain_operators(quadrature_points(term.model)[0]) \
            if term.model.n_tets <= chunk_elements(term.model) else None
        self.recording = False
        self.kept: dict[int, DampingLinearization] = {}
        self.peak_bytes = 0

    @property
    def held_bytes(self) -> int:
        """Bytes of the linearizations kept now."""
        return sum(lin.nbytes for lin in self.kept.values())

    def begin_step(self, step) -> None:
        self._step = step
        lin = linearize_damping(self, self.groups, step.q_t, self.B)
        self._data = lin.data
        self._D = self.model.csr(lin.data)
        if self.recording and self.held_bytes + lin.nbytes <= self.cache_bytes:
            self.kept[int(step.step)] = lin
            self.peak_bytes = max(self.peak_bytes, self.held_bytes)

    def take(self, step: int, q: np.ndarray) -> DampingLinearization | None:
        """The linearization kept for ``step`` (removed) if it was made at ``q``, else None."""
        lin = self.kept.pop(int(step), None)
        if lin is None or not np.array_equal(lin.q, np.asarray(q).reshape(-1)):
            return None
        return lin

    def clear(self) -> None:
        """Drop every kept linearization."""
        self.kept.clear()
