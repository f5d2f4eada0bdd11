"""Skinning: carry a high-resolution display mesh along with the deforming tet mesh.

Each display ("skin") vertex is bound to one rest tetrahedron by its barycentric coordinates
there, so its deformed position is the element's shape functions at those coordinates applied
to the element's deformed nodes (P1: the same affine combination of the tet's corners):

    skin_positions = W @ q    W : (k_skin, n_nodes) sparse, one entry per element node a row,
                              rows sum to 1

The containing tet is found with a k-d tree over the tet centroids (K nearest candidates, K
grown for the vertices not yet placed), never by testing every tet against every vertex.
A skin vertex that lies in no tet (display meshes poke out of coarse simulation meshes) is
bound to the candidate tet that is nearest in the barycentric sense - the one whose most
negative coordinate is the least negative - and keeps its extrapolated coordinates, so it
still follows the tet's affine motion exactly.
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from fem3d.errors import InputError
from fem3d.mesh.element import ELEMENTS, Element
from fem3d.mesh.tetmesh import MeshWarning, PathArg, boundary_faces

__all__ = ["build_skinning_matrix", "barycentric_in_tets", "check_skin_inside",
           "check_skin_placement", "skin_outside_distance"]

#: Candidate counts tried in turn for the vertices not yet placed (capped at the tet count).
_CANDIDATE_ROUNDS = (8, 32, 128)
#: Vertices processed at once, to bound the (chunk, K, 4) temporaries.
_CHUNK = 65536


def _as_points(a: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{name} must have shape (n, 3), got {a.shape}")
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise InputError(f"{name} has a non-finite coordinate", element=int(np.argmax(bad)))
    return a


def barycentric_in_tets(p: np.ndarray, origin: np.ndarray, inv_edges: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of points with respect to tets (vectorized).

    Parameters
    ----------
    p : (..., 3) float64
        Points.
    origin : (..., 3) float64
        First corner ``X0`` of the tet paired with each point.
    inv_edges : (..., 3, 3) float64
        Inverse of the edge matrix ``[X1-X0, X2-X0, X3-X0]`` (edges as columns).

    Returns
    -------
    (..., 4) float64
        ``(1 - l1 - l2 - l3, l1, l2, l3)``; they sum to one exactly up to rounding.
    """
    lam = np.einsum("...ij,...j->...i", inv_edges, p - origin)
    return np.concatenate([1.0 - lam.sum(axis=-1, keepdims=True), lam], axis=-1)


def build_skinning_matrix(
    X: np.ndarray,
    T: np.ndarray,
    skin_V: np.ndarray,
    *,
    eps: float = 1e-9,
    element: Element = ELEMENTS["p1"],
) -> sp.csr_matrix:
    """Sparse matrix mapping simulation positions to skin (display) positions.

    Parameters
    ----------
    X : (n_vertices, 3) float64
        Rest positions of the simulation mesh's nodes.
    T : (n_tets, k) int
        Elements of ``element`` (corners first), 0-based (orientation does not matter here).
    skin_V : (n_skin, 3) float64
        Rest positions of the display mesh, in the same frame as ``X``.
    eps : float, optional
        Tolerance on barycentric coordinates: a vertex is inside a tet when all four are
        ``>= -eps``.
    element : Element, optional
        The element of ``T`` (default P1): its :meth:`~Element.shape_values` at the
        barycentric coordinates are the weights.

    Returns
    -------
    W : (n_skin, n_vertices) scipy.sparse.csr_matrix
        ``k`` stored entries per row (P1: the barycentric coordinates in the chosen tet), each
        row summing to 1, so that ``W @ q`` is ``(n_skin, 3)`` for ``q`` of shape
        ``(n_vertices, 3)``. Exact for every polynomial map of ``X`` of the element's order.

    Raises
    ------
    InputError
        Bad shapes, non-finite coordinates, out-of-range indices, or no tet with volume.

    Notes
    -----
    Cost: one k-d tree over the tet centroids and ``O(n_skin K)`` 3x3 mat-vecs with ``K`` 8
    (grown to 32 and 128 for the vertices not yet placed); the 26002-vertex armadillo skin on
    its 627-tet mesh builds in a few tens of milliseconds. Outside vertices are bound to the
    best of their last ``K`` candidates.
    """
    X = _as_points(X, "X")
    skin_V = _as_points(skin_V, "skin vertices")
    T = np.asarray(T)
    if T.ndim != 2 or T.shape[1] != element.n_nodes or T.shape[0] == 0:
        raise InputError(f"tets must have shape (m, {element.n_nodes}) with m > 0, got "
                         f"{T.shape}")
    if not np.issubdtype(T.dtype, np.integer):
        raise InputError(f"tet indices must be integers, got dtype {T.dtype}")
    T = T.astype(np.int64, copy=False)
    bad = ((T < 0) | (T >= X.shape[0])).any(axis=1)
    if bad.any():
        raise InputError(
            f"tet vertex index out of range [0, {X.shape[0]})", element=int(np.argmax(bad))
        )
    n, k = X.shape[0], skin_V.shape[0]
    if k == 0:
        return sp.csr_matrix((0, n))

    corners = X[element.corners(T)]  # (m, 4, 3)
    origin = corners[:, 0, :]
    edges = np.transpose(corners[:, 1:, :] - origin[:, None, :], (0, 2, 1))  # columns = edges
    det = np.linalg.det(edges)
    scale = np.abs(edges).max(axis=(1, 2))
    degenerate = ~(np.abs(det) > 1e-12 * scale**3)
    if degenerate.all():
        raise InputError("every tet of the simulation mesh has zero volume")
    safe_edges = edges.copy()
    safe_edges[degenerate] = np.eye(3)
    inv_edges = np.linalg.inv(safe_edges)
    live = np.flatnonzero(~degenerate)  # tets that may take skin vertices

    tree = cKDTree(corners[live].mean(axis=1))
    tet_of = np.full(k, -1, dtype=np.int64)
    bary = np.empty((k, 4))

    todo = np.arange(k)
    rounds = sorted({min(r, live.size) for r in _CANDIDATE_ROUNDS})
    for r_i, K in enumerate(rounds):
        last = r_i == len(rounds) - 1
        still = []
        for c0 in range(0, todo.size, _CHUNK):
            idx = todo[c0 : c0 + _CHUNK]
            _, cand = tree.query(skin_V[idx], k=K)
            cand = live[cand.reshape(idx.size, K)]  # (c, K) tet ids
            lam = barycentric_in_tets(
                skin_V[idx, None, :], origin[cand], inv_edges[cand]
            )  # (c, K, 4)
            worst = lam.min(axis=2)  # (c, K)
            inside = worst >= -eps
            found = inside.any(axis=1)
            # first inside candidate (nearest centroid first); otherwise best-extrapolating one
            pick = np.where(found, np.argmax(inside, axis=1), np.argmax(worst, axis=1))
            rows = np.arange(idx.size)
            take = found | last
            tet_of[idx[take]] = cand[rows[take], pick[take]]
            bary[idx[take]] = lam[rows[take], pick[take]]
            still.append(idx[~take])
        todo = np.concatenate(still) if still else todo[:0]
        if todo.size == 0:
            break

    cols = T[tet_of]  # (k, n_nodes)
    weights = element.shape_values(bary)
    nodes = element.n_nodes
    indptr = np.arange(0, nodes * k + 1, nodes, dtype=np.int64)
    W = sp.csr_matrix((weights.reshape(-1), cols.reshape(-1), indptr), shape=(k, n))
    W.sum_duplicates()  # only changes anything for tets with repeated vertices
    return W


# --------------------------------------------------------------------------------------
# skin vs simulation mesh
# --------------------------------------------------------------------------------------


def _point_triangle_distance(P: np.ndarray, A: np.ndarray, B: np.ndarray,
                             C: np.ndarray) -> np.ndarray:
    """Exact distances from points to triangles, all ``(k, 3)`` -> ``(k,)`` (Ericson 5.1.5)."""
    ab, ac, ap = B - A, C - A, P - A
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = P - B
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = P - C
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = vb / denom
        w = vc / denom
        Q = A + ab * v[:, None] + ac * w[:, None]  # interior
        # edge regions
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    edge_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    edge_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    edge_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    Q = np.where(edge_bc[:, None], B + (C - B) * t_bc[:, None], Q)
    Q = np.where(edge_ac[:, None], A + ac * t_ac[:, None], Q)
    Q = np.where(edge_ab[:, None], A + ab * t_ab[:, None], Q)
    Q = np.where(((d6 >= 0) & (d5 <= d6))[:, None], C, Q)
    Q = np.where(((d3 >= 0) & (d4 <= d3))[:, None], B, Q)
    Q = np.where(((d1 <= 0) & (d2 <= 0))[:, None], A, Q)
    Q = np.where(np.isfinite(Q).all(axis=1)[:, None], Q, A)  # degenerate triangle
    return np.linalg.norm(P - Q, axis=1)


def skin_outside_distance(skin_V: np.ndarray, X: np.ndarray,
                          T: np.ndarray | None = None, k: int = 16) -> np.ndarray:
    """How far each display vertex lies outside the simulation mesh.

    Parameters
    ----------
    skin_V : (n_skin, 3) float64
    X : (n_vertices, 3) float64
    T : (n_tets, k) int64, optional
        Elements (corners first; their corner tets are measured). Without them the distance
        is to the bounding box of ``X``.
    k : int
        Candidate tets / boundary faces looked at per vertex (nearest by centroid).

    Returns
    -------
    d : (n_skin,) float64
        0 for vertices inside (a tet of) the mesh, else the distance to its boundary
        (an upper bound when the true closest face is not among the ``k`` candidates).
    """
    P = np.asarray(skin_V, np.float64)
    X = np.asarray(X, np.float64)
    lo, hi = X.min(axis=0), X.max(axis=0)
    d_box = np.linalg.norm(np.maximum(0.0, np.maximum(lo - P, P - hi)), axis=1)
    if T is None:
        return d_box
    T = np.ascontiguousarray(np.asarray(T, np.int64)[:, :4])  # the corner tets
    d = d_box.copy()
    cand = np.flatnonzero(d_box == 0)
    if cand.size:
        E = X[T]
        D = np.stack([E[:, 1] - E[:, 0], E[:, 2] - E[:, 0], E[:, 3] - E[:, 0]], axis=-1)
        Dinv = np.linalg.inv(D)
        kk = min(k, T.shape[0])
        _, nearest = cKDTree(E.mean(axis=1)).query(P[cand], k=kk)
        nearest = nearest.reshape(len(cand), kk)
        rel = P[cand][:, None, :] - E[nearest, 0]
        lam = np.einsum("pkij,pkj->pki", Dinv[nearest], rel)
        lam_all = np.concatenate([1 - lam.sum(-1, keepdims=True), lam], axis=-1)
        inside = (lam_all.min(axis=-1) >= -1e-9).any(axis=1)
        d[cand[~inside]] = -1.0  # inside the box but in no tet: measure below
    todo = np.flatnonzero(d != 0)
    if todo.size:
        F = boundary_faces(T)
        kf = min(k, F.shape[0])
        _, nf = cKDTree(X[F].mean(axis=1)).query(P[todo], k=kf)
        tri = F[nf.reshape(-1)]
        Pr = np.repeat(P[todo], kf, axis=0)
        dist = _point_triangle_distance(Pr, X[tri[:, 0]], X[tri[:, 1]], X[tri[:, 2]])
        d[todo] = dist.reshape(len(todo), kf).min(axis=1)
    return d


def check_skin_inside(skin_V: np.ndarray, X: np.ndarray, tol: float = 0.05,
                      T: np.ndarray | None = None, *, name: str = "display mesh") -> np.ndarray:
    """Warn when display vertices lie well outside the simulation mesh.

    Skinning extrapolates vertices outside every tet from the nearest tet, which distorts
    them more the farther out they are.

    Parameters
    ----------
    skin_V : (n_skin, 3) float64
    X : (n_vertices, 3) float64
        Simulation rest positions.
    tol : float
        Allowed distance, as a fraction of the diagonal of ``X``'s bounding box.
    T : (n_tets, k) int64, optional
        Simulation elements (corners first): measure to the mesh itself, not just its
        bounding box.
    name : str
        What to call the display mesh in the warning.

    Returns
    -------
    d : (n_skin,) float64
        Distance of each display vertex outside the simulation mesh (0 inside).
    """
    X = np.asarray(X, np.float64)
    diag = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    d = skin_outside_distance(skin_V, X, T)
    far = d > tol * diag
    if far.any():
        what = "surface" if T is not None else "bounding box"
        warnings.warn(
            f"{name}: {int(far.sum())} of {len(d)} vertices lie farther than {tol:g} x the "
            f"simulation mesh's bounding-box diagonal ({tol * diag:.4g}) outside its {what} "
            f"(max {d.max():.4g} = {d.max() / diag:.3g} x diagonal)",
            MeshWarning, stacklevel=2,
        )
    return d


def check_skin_placement(
    skin_V: np.ndarray,
    X: np.ndarray,
    T: np.ndarray | None = None,
    *,
    path: PathArg | None = None,
    warn_tol: float = 0.05,
    refuse_tol: float = 0.5,
) -> np.ndarray:
    """Refuse a display mesh far outside the simulation mesh; warn when it sticks out.

    A display mesh half a bounding-box diagonal or more outside the simulation mesh is in
    another frame (other units, an offset): skinning would extrapolate it into nonsense.

    Parameters
    ----------
    skin_V, X, T : as :func:`check_skin_inside`
    path : the display mesh's file, named in the message
    warn_tol, refuse_tol : float
        Distances outside, as fractions of the simulation mesh's bounding-box diagonal.

    Returns
    -------
    d : (n_skin,) float64
        Distance of each display vertex outside the simulation mesh.

    Raises
    ------
    InputError
        Some display vertex lies more than ``refuse_tol`` diagonals outside.
    """
    X = np.asarray(X, np.float64)
    diag = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    d = skin_outside_distance(skin_V, X, T)
    far = d > refuse_tol * diag
    if far.any():
        raise InputError(
            f"display mesh lies far outside the simulation mesh: {int(far.sum())} of {len(d)} "
            f"vertices are more than {refuse_tol:g} x its bounding-box diagonal outside (max "
            f"{d.max() / diag:.3g} x); is it in the same frame (units, offset)?",
            path=path,
        )
    name = "display mesh" if path is None else f"display mesh {path}"
    return check_skin_inside(skin_V, X, warn_tol, T, name=name)
