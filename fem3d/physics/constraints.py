"""Fixed-DOF (Dirichlet) constraints and vertex selection.

Fixed DOFs are removed from the unknowns with a selection matrix ``P`` of the free DOFs
(the assignment's formulation)::

    q_full = P.T @ q_free + x0        x0: the fixed positions on fixed DOFs, 0 on free ones
    K_free = P @ K @ P.T              f_free = P @ f

A pin fixes every DOF of its vertices (the assignment's) or some of them (``dofs = "z"``: a
roller, a symmetry plane). ``fixed_vertices`` are the vertices with at least one fixed DOF;
prescribed positions are given per fixed vertex, ``(n_fixed, 3)``, of which only the fixed
components are read (:attr:`Constraints.fixed_slots`).

DOF vectors are vertex-major (``q.reshape(-1)`` = ``[x0, y0, z0, x1, ...]``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from fem3d.errors import InputError, ParameterError

__all__ = [
    "Constraints",
    "free_rigid_modes",
    "fixed_point_constraints",
    "fixed_vertices_lowest_y",
    "pick_nearest_vertices",
]


def _fixed_index_array(n_vertices: int, fixed_indices: np.ndarray) -> np.ndarray:
    idx = np.asarray(fixed_indices)
    if idx.size == 0:
        return np.zeros(0, dtype=np.int64)
    if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
        raise ParameterError(f"fixed vertex indices must be a 1-D integer array, got {idx.dtype}")
    bad = (idx < 0) | (idx >= n_vertices)
    if bad.any():
        raise ParameterError(
            f"fixed vertex index {int(idx[bad][0])} out of range [0, {n_vertices})"
        )
    return np.unique(idx.astype(np.int64))


def fixed_point_constraints(n_vertices: int, fixed_indices: np.ndarray) -> sp.csr_matrix:
    """Selection matrix of the free DOFs.

    Parameters
    ----------
    n_vertices : int
        Number of vertices ``n``.
    fixed_indices : (n_fixed,) int
        Fixed vertices (duplicates allowed).

    Returns
    -------
    P : (3 (n - n_fixed), 3 n) scipy.sparse.csr_matrix
        One 1 per row, at the column of the free DOF, in increasing DOF order, so that
        ``P @ P.T`` is the identity and ``P.T @ q_free`` puts free values back in place
        (zeros on fixed DOFs; the caller adds the fixed positions ``x0``).
    """
    fixed = _fixed_index_array(n_vertices, fixed_indices)
    free_dofs = _free_dofs(n_vertices, fixed)
    nf = free_dofs.size
    return sp.csr_matrix(
        (np.ones(nf), free_dofs, np.arange(nf + 1, dtype=np.int64)), shape=(nf, 3 * n_vertices)
    )


def _free_dofs(n_vertices: int, fixed: np.ndarray) -> np.ndarray:
    free_vertex = np.ones(n_vertices, dtype=bool)
    free_vertex[fixed] = False
    return np.flatnonzero(np.repeat(free_vertex, 3)).astype(np.int64)


@dataclass(frozen=True, eq=False)
class Constraints:
    """Fixed DOFs held at given positions (every DOF of a pinned vertex, or some).

    Attributes
    ----------
    P : (n_free_dofs, 3 n) scipy.sparse.csr_matrix
        Selection matrix of the free DOFs (see :func:`fixed_point_constraints`).
    free_dofs : (n_free_dofs,) int64
        Indices of the free DOFs in the full vertex-major vector, increasing.
    fixed_vertices : (n_fixed,) int64
        Vertices with a fixed DOF, sorted, unique (:attr:`fixed_dofs`: which DOFs).
    x0 : (3 n,) float64
        Fixed positions on fixed DOFs, zeros on free DOFs.
    """

    P: sp.csr_matrix
    free_dofs: np.ndarray
    fixed_vertices: np.ndarray
    x0: np.ndarray
    _new_index: np.ndarray = field(repr=False)
    _cache: list = field(default_factory=list, repr=False)

    @classmethod
    def from_fixed_vertices(cls, X: np.ndarray, fixed_vertices: np.ndarray) -> Constraints:
        """Hold ``fixed_vertices`` at their positions in ``X`` (every DOF).

        Parameters
        ----------
        X : (n_vertices, 3) float64
            Positions the fixed vertices keep (usually the rest positions).
        fixed_vertices : (n_fixed,) int
            Vertex indices; duplicates are merged.
        """
        X = _positions(X)
        fixed = _fixed_index_array(X.shape[0], fixed_vertices)
        return cls.from_fixed_dofs(X, (3 * fixed[:, None] + np.arange(3)).reshape(-1))

    @classmethod
    def from_fixed_dofs(cls, X: np.ndarray, fixed_dofs: np.ndarray) -> Constraints:
        """Hold the DOFs ``fixed_dofs`` (``3 vertex + axis``) at their values in ``X``.

        Parameters
        ----------
        X : (n_vertices, 3) float64
        fixed_dofs : (k,) int
            DOF indices in ``[0, 3 n)``; duplicates are merged.
        """
        X = _positions(X)
        n = X.shape[0]
        dofs = _fixed_index_array(3 * n, fixed_dofs)
        fixed_dof = np.zeros(3 * n, dtype=bool)
        fixed_dof[dofs] = True
        free_dofs = np.flatnonzero(~fixed_dof).astype(np.int64)
        fixed = np.unique(dofs // 3)
        nf = free_dofs.size
        P = sp.csr_matrix(
            (np.ones(nf), free_dofs, np.arange(nf + 1, dtype=np.int64)), shape=(nf, 3 * n)
        )
        x0 = np.zeros(3 * n)
        x0[dofs] = X.reshape(-1)[dofs]
        new_index = np.full(3 * n, -1, dtype=np.int64)
        new_index[free_dofs] = np.arange(nf)
        for a in (free_dofs, fixed, x0, new_index):
            a.setflags(write=False)
        return cls(P=P, free_dofs=free_dofs, fixed_vertices=fixed, x0=x0, _new_index=new_index)

    @cached_property
    def fixed_dofs(self) -> np.ndarray:
        """``(k,) int64`` the fixed DOFs, increasing (``3 vertex + axis``)."""
        a = np.flatnonzero(self._new_index < 0).astype(np.int64)
        a.setflags(write=False)
        return a

    @cached_property
    def fixed_slots(self) -> np.ndarray:
        """``(k,) int64``: where each fixed DOF sits in a flattened ``(n_fixed, 3)`` array of
        the fixed vertices' positions (``p.reshape(-1)[fixed_slots]`` are the fixed DOFs'
        values; with every DOF of the fixed vertices fixed, ``arange(3 n_fixed)``)."""
        d = self.fixed_dofs
        a = 3 * np.searchsorted(self.fixed_vertices, d // 3) + d % 3
        a.setflags(write=False)
        return a

    @property
    def partial(self) -> bool:
        """Some fixed vertex has a free DOF (a roller or symmetry-plane support)."""
        return self.fixed_dofs.size != 3 * self.fixed_vertices.size

    @property
    def n_dofs(self) -> int:
        """Number of DOFs of the full system, ``3 n``."""
        return self.x0.size

    @property
    def n_free(self) -> int:
        """Number of free DOFs."""
        return self.free_dofs.size

    def expand(self, q_free: np.ndarray) -> np.ndarray:
        """Full DOF vector from the free one: ``P.T @ q_free + x0``.

        Parameters
        ----------
        q_free : (n_free_dofs,) float64

        Returns
        -------
        (3 n,) float64
            Vertex-major; ``.reshape(-1, 3)`` gives positions.
        """
        q_free = np.asarray(q_free, dtype=np.float64).reshape(-1)
        if q_free.size != self.n_free:
            raise ValueError(f"expected {self.n_free} free DOFs, got {q_free.size}")
        q = self.x0.copy()
        q[self.free_dofs] = q_free
        return q

    def expand_zero(self, v_free: np.ndarray) -> np.ndarray:
        """``P.T @ v_free`` (zeros on fixed DOFs), e.g. for velocities or increments."""
        v_free = np.asarray(v_free, dtype=np.float64).reshape(-1)
        if v_free.size != self.n_free:
            raise ValueError(f"expected {self.n_free} free DOFs, got {v_free.size}")
        v = np.zeros(self.n_dofs)
        v[self.free_dofs] = v_free
        return v

    def restrict(self, v_full: np.ndarray) -> np.ndarray:
        """Free part ``P @ v_full`` of a full vector.

        Parameters
        ----------
        v_full : (3 n,) or (n, 3) float64

        Returns
        -------
        (n_free_dofs,) float64
        """
        v_full = np.asarray(v_full).reshape(-1)
        if v_full.size != self.n_dofs:
            raise ValueError(f"expected {self.n_dofs} DOFs, got {v_full.size}")
        return v_full[self.free_dofs]

    def reduce_matrix(self, A: sp.spmatrix | sp.sparray) -> sp.csr_matrix:
        """``P @ A @ P.T``: the free rows and columns of a ``(3 n, 3 n)`` sparse matrix.

        The entry mask and the reduced sparsity are computed from ``A``'s pattern once and
        cached (the last 4 patterns): a matrix with the same ``indptr`` / ``indices`` as an
        earlier call (the usual case, a Hessian re-assembled on a fixed pattern, or the mass
        matrix) costs a pattern comparison and one gather of ``A.data``. Works on
        non-canonical CSR (unsorted or duplicate entries kept as is).

        Parameters
        ----------
        A : (3 n, 3 n) sparse matrix (CSR preferred; others are converted)

        Returns
        -------
        (n_free_dofs, n_free_dofs) scipy.sparse.csr_matrix
        """
        if getattr(A, "format", None) != "csr":
            A = sp.csr_matrix(A)
        N = self.n_dofs
        if A.shape != (N, N):
            raise ValueError(f"expected a ({N}, {N}) matrix, got {A.shape}")
        c = self._lookup_pattern(A)
        R = sp.csr_matrix(
            (A.data[c["keep"]], c["new_indices"].copy(), c["new_indptr"].copy()),
            shape=(self.n_free, self.n_free),
        )
        # column relabelling is monotone, so sorted input stays sorted
        R.has_sorted_indices = c["sorted"]
        return R

    def kept_entries(self, A: sp.csr_matrix) -> np.ndarray:
        """Positions in ``A.data`` of the entries :meth:`reduce_matrix` keeps, in the reduced
        matrix's ``data`` order (free rows and columns).

        Parameters
        ----------
        A : (3 n, 3 n) scipy.sparse.csr_matrix

        Returns
        -------
        (nnz_free,) int64
        """
        if getattr(A, "format", None) != "csr" or A.shape != (self.n_dofs, self.n_dofs):
            raise ValueError(f"expected a ({self.n_dofs}, {self.n_dofs}) CSR matrix")
        return self._lookup_pattern(A)["keep"]

    #: Sparsity patterns remembered by :meth:`reduce_matrix` (mass, Hessian, ...).
    _MAX_PATTERNS = 4

    def _lookup_pattern(self, A: sp.csr_matrix) -> dict:
        """Cached reduction maps of ``A``'s pattern, computed on a miss (O(nnz) either way)."""
        for i, c in enumerate(self._cache):
            if (
                c["indptr"].size == A.indptr.size
                and c["indices"].size == A.indices.size
                and np.array_equal(c["indptr"], A.indptr)
                and np.array_equal(c["indices"], A.indices)
            ):
                if i:
                    self._cache.insert(0, self._cache.pop(i))
                return c
        N, new = self.n_dofs, self._new_index
        row = np.repeat(np.arange(N), np.diff(A.indptr))
        new_col = new[A.indices]
        keep = (new[row] >= 0) & (new_col >= 0)
        counts = np.bincount(new[row[keep]], minlength=self.n_free)
        indptr = np.zeros(self.n_free + 1, dtype=np.int64)
        np.cumsum(counts, out=indptr[1:])
        c = {
            "indptr": A.indptr.copy(),
            "indices": A.indices.copy(),
            "keep": np.flatnonzero(keep),
            "new_indices": new_col[keep],
            "new_indptr": indptr,
            "sorted": bool(A.has_sorted_indices),
        }
        self._cache.insert(0, c)
        del self._cache[self._MAX_PATTERNS :]
        return c


def _positions(X: np.ndarray) -> np.ndarray:
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InputError(f"X must have shape (n, 3), got {X.shape}")
    return X


#: Names of the rigid modes :func:`free_rigid_modes` reports (translations, rotations).
_AXES = ("x", "y", "z")


def free_rigid_modes(X: np.ndarray, fixed_dofs: np.ndarray) -> list[str]:
    """The rigid motions of a body that its fixed DOFs leave free, in words.

    A rigid motion ``u = t + w x (X - c)`` (``c`` the vertex centroid) is held when some fixed
    DOF moves under it; the free ones are the null space of the rigid modes restricted to
    the fixed DOFs (6 columns: three translations, three rotations).

    Parameters
    ----------
    X : (n, 3) float64
        The body's rest positions.
    fixed_dofs : (k,) int
        The body's fixed DOFs, ``3 vertex + axis`` (vertex indices local to ``X``).

    Returns
    -------
    list of str
        One name per free mode (``"translation along x"``, ``"rotation about an axis along
        z"``; an oblique direction as a unit vector); empty when the body is held.
    """
    X = _positions(X)
    dofs = np.asarray(fixed_dofs, dtype=np.int64).reshape(-1)
    c = X.mean(axis=0)
    scale = float(np.linalg.norm(np.ptp(X, axis=0))) or 1.0
    R = np.zeros((3 * X.shape[0], 6))
    for a in range(3):
        R[a::3, a] = 1.0
        e = np.zeros(3)
        e[a] = 1.0
        R[:, 3 + a] = (np.cross(e, X - c) / scale).reshape(-1)
    Rf = R[dofs]
    if Rf.shape[0] == 0:
        return [f"{kind} {a}" for kind in ("translation along", "rotation about an axis along")
                for a in _AXES]
    _, sv, Vt = np.linalg.svd(Rf, full_matrices=True)
    rank = int(np.sum(sv > 1e-9 * sv[0])) if sv.size else 0
    N = Vt[rank:].T  # (6, k): the free modes
    if N.shape[1] == 0:
        return []
    # name the free modes that are a plain translation or rotation first, then the rest
    plain = [i for i in range(6) if np.linalg.norm(N @ N[i]) > 1.0 - 1e-9]
    rest = N.copy()
    rest[plain] = 0.0  # less their plain parts (each plain mode lies in the free space)
    U, s, _ = np.linalg.svd(rest, full_matrices=False)
    others = U[:, s > 1e-6].T
    return [_mode_name(np.eye(6)[i]) for i in plain] + [_mode_name(v) for v in others]


def _mode_name(v: np.ndarray) -> str:
    """A rigid mode ``(t, w)`` in words: a translation, or a rotation about an axis."""
    t, w = v[:3], v[3:]
    if np.linalg.norm(w) < 1e-6:
        return f"translation along {_direction(t)}"
    return f"rotation about an axis along {_direction(w)}"


def _direction(d: np.ndarray) -> str:
    d = d / np.linalg.norm(d)
    a = int(np.argmax(np.abs(d)))
    if abs(abs(d[a]) - 1.0) < 1e-6:
        return _AXES[a]
    return "(" + ", ".join(f"{x:.3g}" for x in d * np.sign(d[a])) + ")"


def fixed_vertices_lowest_y(X: np.ndarray, tol: float) -> np.ndarray:
    """Vertices whose ``y`` is within ``tol`` of the lowest ``y``.

    Parameters
    ----------
    X : (n_vertices, 3) float64
    tol : float
        Non-negative tolerance (same units as ``X``).

    Returns
    -------
    (n_fixed,) int64
        Sorted vertex indices, never empty.

    Raises
    ------
    ParameterError
        ``tol`` negative or not finite, or nothing selected (no vertex, non-finite ``y``).
    """
    tol = float(tol)
    if not np.isfinite(tol) or tol < 0:
        raise ParameterError(f"fixed-y tolerance must be a finite number >= 0, got {tol}")
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InputError(f"X must have shape (n, 3), got {X.shape}")
    y = X[:, 1]
    if y.size == 0 or not np.isfinite(y).all():
        raise ParameterError("no vertex to fix: the mesh is empty or has non-finite y")
    idx = np.flatnonzero(y <= y.min() + tol).astype(np.int64)
    if idx.size == 0:  # pragma: no cover - the minimum itself always qualifies
        raise ParameterError(f"no vertex within {tol} of the lowest y")
    return idx


def pick_nearest_vertices(
    X: np.ndarray,
    point: np.ndarray,
    radius: float,
    *,
    tree: cKDTree | None = None,
    nearest_if_empty: bool = False,
) -> np.ndarray:
    """Vertices within ``radius`` of ``point``.

    Parameters
    ----------
    X : (n_vertices, 3) float64
        Current positions (ignored when ``tree`` is given, except for ``nearest_if_empty``'s
        fallback, which uses the tree too).
    point : (3,) float64
    radius : float
        Non-negative; the ball is closed (distance ``<= radius``).
    tree : scipy.spatial.cKDTree, optional
        Prebuilt tree over ``X`` for repeated picks.
    nearest_if_empty : bool, optional
        When nothing is within ``radius``, return the single nearest vertex instead of an
        empty array.

    Returns
    -------
    (n_picked,) int64
        Sorted vertex indices (possibly empty).
    """
    radius = float(radius)
    if not np.isfinite(radius) or radius < 0:
        raise ParameterError(f"picking radius must be a finite number >= 0, got {radius}")
    p = np.asarray(point, dtype=np.float64).reshape(-1)
    if p.size != 3 or not np.isfinite(p).all():
        raise ParameterError(f"pick point must be 3 finite numbers, got {point!r}")
    if tree is not None:
        idx = np.asarray(tree.query_ball_point(p, radius), dtype=np.int64)
        idx.sort()
        if idx.size == 0 and nearest_if_empty and tree.n > 0:
            idx = np.array([int(tree.query(p)[1])], dtype=np.int64)
        return idx
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InputError(f"X must have shape (n, 3), got {X.shape}")
    d2 = ((X - p) ** 2).sum(axis=1)
    idx = np.flatnonzero(d2 <= radius * radius).astype(np.int64)
    if idx.size == 0 and nearest_if_empty and X.shape[0] > 0:
        idx = np.array([int(np.argmin(d2))], dtype=np.int64)
    return idx
