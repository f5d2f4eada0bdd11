"""The sparsity pattern of a mesh's ``3n x 3n`` matrices, its scatter map, and the
consistent mass matrix assembled on it (the parts of :func:`fem3d.physics.model.build_model`
that see every node pair of every element).

Elements have ``k`` nodes (the columns of ``T``: 4 for P1, 10 for P2); their element
matrices are ``d x d`` with ``d = 3 k``. Both are built without a global sort of the ``k^2 m``
node pairs and without an ``(m, d^2)`` temporary: at 1e6 P1 tets the pattern took 6 s and the
mass matrix 2.3 GB before.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

__all__ = ["block_pattern", "assemble_mass", "merge_patterns"]


def _vertex_pairs(T: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The node pairs of elements ``T`` (each ``(T[e, a], T[e, b])``, ``a, b`` in
    ``0..k-1``): their CSR pattern over nodes and the pair index of every ``(e, a, b)``.

    Grouping the ``k^2 m`` pairs by row is a counting sort (scipy's CSC -> CSR conversion of
    the element-node incidence) and sorting them within a row (about a hundred each) is cache
    local, where a global sort of ``k^2 m`` keys is neither.

    Returns
    -------
    block_ptr : (n + 1,) int64
    block_cols : (nnzb,) int32
        Sorted within each row, no duplicates.
    pair : (m, k, k) int32
        ``pair[e, a, b]``: the position in ``block_cols`` of ``(T[e, a], T[e, b])``.
    """
    m, k = T.shape
    if k * k * m > np.iinfo(np.int32).max or n > np.iinfo(np.int32).max:
        raise ValueError(f"{m} elements: more node pairs than int32 indexes")
    # incidence (node x element-node), rows in element order: a counting sort by node
    corner = sp.csr_matrix((np.arange(k * m, dtype=np.int32), T.reshape(-1).astype(np.int32),
                            np.arange(0, k * m + 1, k, dtype=np.int32)), shape=(m, n))
    by_vertex = corner.T.tocsr()  # (n, m): data = e * k + a, grouped by node T[e, a]
    ea = by_vertex.data
    # every (e, a) of row T[e, a] brings the k pairs (T[e, a], T[e, b]), b = 0..k-1
    cols = T.astype(np.int32, copy=False).reshape(-1)[
        (ea - ea % k)[:, None] + np.arange(k, dtype=np.int32)].reshape(-1)
    origin = (k * ea[:, None] + np.arange(k, dtype=np.int32)).reshape(-1)  # e k^2 + a k + b
    del ea, corner
    pairs = sp.csr_matrix((origin, cols, k * by_vertex.indptr.astype(np.int32)), shape=(n, n))
    del by_vertex, cols, origin
    pairs.has_sorted_indices = False
    pairs.sort_indices()  # within each row, (column, origin) sorted by column
    cols, origin, ptr = pairs.indices, pairs.data, pairs.indptr
    first = np.empty(cols.size, dtype=bool)
    first[:1] = True
    np.not_equal(cols[1:], cols[:-1], out=first[1:])
    first[ptr[:-1][ptr[:-1] < cols.size]] = True  # a new row starts a new pair
    count = np.empty(cols.size + 1, dtype=np.int32)  # count[k]: pairs among entries [0, k)
    count[0] = 0
    np.cumsum(first, out=count[1:])
    block_ptr = count[ptr].astype(np.int64)
    block_cols = cols[first]
    pair = np.empty(k * k * m, dtype=np.int32)
    pair[origin] = count[1:]
    pair -= 1
    return block_ptr, block_cols, pair.reshape(m, k, k)


#: P1 tets per chunk of the scatter map's expansion (fewer elements of more nodes).
_PATTERN_CHUNK = 1 << 14


def block_pattern(T: np.ndarray, n_vertices: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """CSR pattern of the ``3n x 3n`` element matrices of elements ``T`` and their scatter map.

    The pattern is found over node pairs (``k^2`` per element, :func:`_vertex_pairs`) and expanded
    to 3x3 blocks arithmetically: the entry ``(3 i + c, 3 j + d)`` of block ``p = (i, j)``
    sits at ``9 bp_i + 3 c deg_i + 3 (p - bp_i) + d`` (``bp_i`` the first block of vertex row
    ``i``, ``deg_i`` its block count), so no ``3n x 3n`` conversion is needed.

    Parameters
    ----------
    T : (m, k) int64
        Elements of ``k`` nodes.
    n_vertices : int
        Number of nodes ``n``; the matrices are ``N x N`` with ``N = 3 n`` (node-major
        DOFs, see :meth:`fem3d.mesh.element.Element.element_dofs`).

    Returns
    -------
    pattern : (N, N) scipy.sparse.csr_matrix
        Canonical (sorted, no duplicates), ``data`` all zeros: every ``(3 i + c, 3 j + d)`` with
        nodes ``i, j`` in a common element.
    scatter : (m * d^2,) int32
        ``scatter[e d^2 + d r + s]`` (``d = 3 k``) is the ``data`` position of the entry of
        element DOFs ``(r, s)`` of element ``e``, so ``np.bincount(scatter, blocks.ravel(),
        nnz)`` assembles ``(m, d, d)`` blocks. int32 halves the memory and the bandwidth of
        the fused C assembly, which reads it on every call.

    Raises
    ------
    ValueError
        More than ``2**31 - 1`` stored entries.
    """
    T = np.asarray(T, dtype=np.int64)
    m, k = T.shape
    n = int(n_vertices)
    block_ptr, block_cols, pair = _vertex_pairs(T, n)
    nnzb = block_cols.size
    if 9 * nnzb > np.iinfo(np.int32).max:
        raise ValueError(f"the sparsity pattern has {9 * nnzb} entries, more than int32 "
                         "indexes")
    deg = np.diff(block_ptr).astype(np.int32)
    bp = block_ptr[:-1].astype(np.int32)
    # scatter[e, a, c, b, d] = 6 bp_i + 3 p + 3 c deg_i + d with i = T[e, a], p = pair[e, a, b]
    Ti = T.astype(np.int32, copy=False)
    base = pair
    base *= 3
    base += (6 * bp[Ti])[:, :, None]
    stride = 3 * deg[Ti]  # (m, k): row length of node T[e, a]'s rows
    scatter = np.empty((m, k, 3, k, 3), dtype=np.int32)
    three = np.arange(3, dtype=np.int32)
    chunk = max(1, _PATTERN_CHUNK * 16 // (k * k))
    for a in range(0, m, chunk):  # one pass over scatter, temporaries in cache
        b = min(m, a + chunk)
        row = base[a:b, :, None, :] + (stride[a:b, :, None] * three)[:, :, :, None]
        np.add(row[..., None], three, out=scatter[a:b])
    del base, stride
    # CSR rows 3i, 3i + 1, 3i + 2 each hold 3 j + d over vertex i's blocks j
    indptr = np.empty(3 * n + 1, dtype=np.int32)
    indptr[0] = 0
    row_len = np.repeat(3 * deg, 3)
    np.cumsum(row_len, out=indptr[1:])
    cols3 = (3 * block_cols[:, None] + np.arange(3, dtype=np.int32)).reshape(-1)
    # entry q of CSR row 3 i + c reads cols3[3 bp_i + (q - indptr[3 i + c])]
    shift = np.repeat(3 * bp, 3) - indptr[:-1]
    src = np.arange(9 * nnzb, dtype=np.int32)
    src += np.repeat(shift, row_len)
    indices = cols3[src]
    del src, cols3
    pattern = sp.csr_matrix((np.zeros(indices.size), indices, indptr), shape=(3 * n, 3 * n))
    pattern.has_sorted_indices = True
    return pattern, scatter.reshape(-1)


def merge_patterns(patterns: list[sp.csr_matrix]) -> tuple[sp.csr_matrix, list[np.ndarray]]:
    """The union of canonical CSR patterns of one shape (element blocks of different
    elements on one mesh) and where each pattern's entries sit in it.

    Returns
    -------
    pattern : (N, N) scipy.sparse.csr_matrix
        Canonical, ``data`` zeros, int32 indices.
    positions : list of (nnz_i,) int32
        ``positions[i][j]``: the union's ``data`` position of entry ``j`` of ``patterns[i]``
        (so ``positions[i][scatter_i]`` is block ``i``'s scatter map into the union).
    """
    n_rows, n_cols = patterns[0].shape

    def keys(p: sp.csr_matrix) -> np.ndarray:
        rows = np.repeat(np.arange(n_rows, dtype=np.int64), np.diff(p.indptr))
        return rows * n_cols + p.indices

    union = np.unique(np.concatenate([keys(p) for p in patterns]))
    if union.size > np.iinfo(np.int32).max:
        raise ValueError(f"the sparsity pattern has {union.size} entries, more than int32 "
                         "indexes")
    indptr = np.zeros(n_rows + 1, dtype=np.int32)
    np.cumsum(np.bincount(union // n_cols, minlength=n_rows), out=indptr[1:])
    indices = (union % n_cols).astype(np.int32)
    pattern = sp.csr_matrix((np.zeros(union.size), indices, indptr), shape=(n_rows, n_cols))
    pattern.has_sorted_indices = True
    positions = [np.searchsorted(union, keys(p)).astype(np.int32) for p in patterns]
    return pattern, positions


#: Tets per chunk of the mass matrix's element blocks (10 MB of blocks a chunk).
_MASS_CHUNK = 1 << 13


def assemble_mass(element_mass: Callable[[int, int], np.ndarray], scatter: np.ndarray,
                  T: np.ndarray, indptr: np.ndarray) -> np.ndarray:
    """CSR ``data`` of the consistent mass matrix (the generated mass kernels) on the
    pattern of :func:`block_pattern` (``scatter``, ``indptr``): the sums of
    ``np.bincount(scatter, all_blocks)`` bit for bit, without its ``(m, d^2)`` float64
    blocks and ``(m d^2,)`` intp copy of ``scatter`` (2.3 GB at 1e6 P1 tets).

    The kernel's blocks are ``M_ab I_3`` (made a chunk of tets at a time, their structure
    checked), so the three entries ``(3 i + c, 3 j + c)`` of a vertex pair ``p = (i, j)`` are
    one sum over its elements: a bincount of the ``k^2 m`` pairs ``(T[e, a], T[e, b])`` in element
    order, the order every entry got its terms in before (the other entries got zeros).
    Blocks of any other structure are added entry by entry in element order
    (``np.add.at``).

    Parameters
    ----------
    element_mass : callable
        ``(a, b)`` -> the mass matrices ``(b - a, d, d)`` of elements ``a .. b - 1``
        (:meth:`fem3d.mesh.element.Element.mass_matrices`).
    scatter : (m * d^2,) int32
    T : (m, k) int64
    indptr : (3 n + 1,) int32
        The scatter map and row pointers of :func:`block_pattern` ``(T, n)``.

    Returns
    -------
    (nnz,) float64
    """
    nnz = int(indptr[-1])
    m, k = T.shape
    pair_mass = np.empty((m, k, k))
    identity = np.eye(3, dtype=bool)
    chunk = max(1, _MASS_CHUNK * 16 // (k * k))
    for a in range(0, m, chunk):
        b = min(m, a + chunk)
        B = element_mass(a, b).reshape(b - a, k, 3, k, 3)
        if not ((np.moveaxis(B, 3, 2)[:, :, :, ~identity] == 0).all()
                and (B[:, :, 1, :, 1] == B[:, :, 0, :, 0]).all()
                and (B[:, :, 2, :, 2] == B[:, :, 0, :, 0]).all()):
            return _assemble_entries(element_mass, m, scatter, nnz)
        pair_mass[a:b] = B[:, :, 0, :, 0]
    # entry (3 i, 3 j) of pair p in vertex row i sits at 6 bp_i + 3 p (block_pattern), and
    # indptr[3 i] = 9 bp_i; entry (3 i + c, 3 j + c) c (3 deg_i + 1) further
    n = (indptr.size - 1) // 3
    bp = (np.asarray(indptr[0:3 * n + 1:3]) // 9).astype(np.int64)
    deg = np.diff(bp)
    pair = scatter.reshape(m, k, 3, k, 3)[:, :, 0, :, 0] // 3
    pair -= (2 * bp[:-1][T]).astype(pair.dtype)[:, :, None]
    sums = np.bincount(pair.reshape(-1), weights=pair_mass.reshape(-1), minlength=int(bp[-1]))
    del pair, pair_mass
    row = np.repeat(np.arange(n), deg)
    first = 6 * bp[:-1][row] + 3 * np.arange(row.size)
    step = 3 * deg[row] + 1
    data = np.zeros(nnz)
    for c in range(3):
        data[first + c * step] = sums
    return data


def _assemble_entries(element_mass: Callable[[int, int], np.ndarray], m: int,
                      scatter: np.ndarray, nnz: int) -> np.ndarray:
    """:func:`assemble_mass` of blocks of any structure: their non-zero entries added in
    element order, a chunk of elements at a time."""
    data = np.zeros(nnz)
    d2 = scatter.size // m
    for a in range(0, m, _MASS_CHUNK):
        b = min(m, a + _MASS_CHUNK)
        w = element_mass(a, b).reshape(-1)
        nonzero = w != 0.0
        np.add.at(data, scatter[d2 * a:d2 * b][nonzero], w[nonzero])
    return data
