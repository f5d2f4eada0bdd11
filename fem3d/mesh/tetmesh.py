"""The tet mesh itself: :class:`TetMesh`, its checks, boundary faces and orientation.

Orientation
-----------
Tetrahedra are returned positively oriented: ``det([X1-X0, X2-X0, X3-X0]) > 0``. Negatively
oriented rest tets are *re-oriented* (two vertices swapped) with a :class:`MeshWarning`
rather than rejected: the vertex order of a tet is a file-format convention (MEDIT, TetGen
and Gmsh do not agree on it), not a physical inversion, because a rest configuration cannot
be "inverted" relative to itself. Zero-volume tets, on the other hand, are an error: they
have no rest shape at all.

Every reader of :mod:`fem3d.mesh.formats` returns what :func:`validate_tet_mesh` /
:func:`validate_surface_mesh` accept, or raises :class:`fem3d.errors.InputError` naming the
file, the line and/or element and what is wrong.
"""

from __future__ import annotations

import itertools
import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from os import PathLike

import numpy as np

from fem3d.errors import InputError

__all__ = [
    "DEGENERATE_RTOL",
    "MeshWarning",
    "TET_FACES",
    "TetMesh",
    "boundary_face_index",
    "boundary_faces",
    "box_tet_mesh",
    "tet_signed_volumes",
    "validate_surface_mesh",
    "validate_tet_mesh",
]

PathArg = str | PathLike[str]

_stages = logging.getLogger("fem3d.stages")  # stage marks (fem3d run --profile)

#: A tet is degenerate when ``|6 V| <= DEGENERATE_RTOL * h**3`` with ``h`` its longest edge
#: (a regular tet has ``6 V = h**3 / sqrt(2)``). Scale-invariant, so the 165-unit bunny and
#: the 1-unit armadillo are judged alike. The shipped meshes' worst ratio is about 0.03.
DEGENERATE_RTOL = 1e-8

#: Local vertex indices of the 4 faces of a positively oriented tet, each ordered so its
#: right-hand normal points away from the tet's remaining (opposite) vertex.
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)


class MeshWarning(UserWarning):
    """A mesh was usable but something about it was fixed or looks suspicious."""


@dataclass(frozen=True, eq=False)
class TetMesh:
    """A validated linear tetrahedral mesh.

    Attributes
    ----------
    X : (n_vertices, 3) float64
        Rest positions (read-only array).
    T : (n_tets, 4) int64
        0-based vertex indices, positively oriented (read-only array).
    path : str or None
        The file the mesh was read from.
    """

    X: np.ndarray
    T: np.ndarray
    path: str | None = None

    def __post_init__(self) -> None:
        X = np.array(self.X, dtype=np.float64, order="C")
        T = np.array(self.T, dtype=np.int64, order="C")
        X.flags.writeable = False
        T.flags.writeable = False
        object.__setattr__(self, "X", X)
        object.__setattr__(self, "T", T)

    @property
    def n_vertices(self) -> int:
        """Number of vertices."""
        return int(self.X.shape[0])

    @property
    def n_tets(self) -> int:
        """Number of tetrahedra."""
        return int(self.T.shape[0])

    def volumes(self) -> np.ndarray:
        """Rest volumes, ``(n_tets,) float64``, all positive."""
        return tet_signed_volumes(self.X, self.T)

    def __repr__(self) -> str:
        return f"TetMesh({self.n_vertices} vertices, {self.n_tets} tets, path={self.path!r})"


# --------------------------------------------------------------------------------------
# geometry helpers
# --------------------------------------------------------------------------------------


def tet_signed_volumes(X: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Signed volumes of tetrahedra.

    Parameters
    ----------
    X : (n_vertices, 3) float64
    T : (n_tets, 4) int64

    Returns
    -------
    vol : (n_tets,) float64
        ``det([X1-X0, X2-X0, X3-X0]) / 6``.
    """
    e = X[T]
    a, b, c = e[:, 1] - e[:, 0], e[:, 2] - e[:, 0], e[:, 3] - e[:, 0]
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def _sorted_columns(A: np.ndarray | Sequence[np.ndarray]) -> list[np.ndarray]:
    """The columns of ``np.sort(A, axis=1)`` of an ``(k, 3)`` or ``(k, 4)`` array (or of its
    columns), by a sorting network of whole columns (a sort per row of 3 or 4 numbers is a
    call per row)."""
    cols = [A[:, k] for k in range(A.shape[1])] if isinstance(A, np.ndarray) else list(A)
    pairs = ((0, 1), (1, 2), (0, 1)) if len(cols) == 3 else \
        ((0, 1), (2, 3), (0, 2), (1, 3), (1, 2))
    for i, j in pairs:
        cols[i], cols[j] = np.minimum(cols[i], cols[j]), np.maximum(cols[i], cols[j])
    return cols


def _tet_faces(T: np.ndarray) -> np.ndarray:
    """``(4 m, 3)`` faces of tets ``T`` (``T[:, TET_FACES]`` with C-ordered rows)."""
    return T.take(TET_FACES.reshape(-1), axis=1).reshape(-1, 3)


def _tet_face_keys(T: np.ndarray) -> np.ndarray | None:
    """:func:`_face_keys` of :func:`_tet_faces` ``(T)`` without making the faces (None: too
    many vertices for one int64 key per face)."""
    m = T.shape[0]
    if m == 0:
        return np.zeros(0, dtype=np.int64)
    n = int(T.max()) + 1  # every vertex of a tet is on three of its faces
    if n >= 2_000_000:
        return None
    keys = np.empty((m, 4), dtype=np.int64)
    for k, face in enumerate(TET_FACES):
        s0, s1, s2 = _sorted_columns([T[:, v] for v in face])
        key = keys[:, k]
        np.multiply(s0, n, out=key)
        key += s1
        key *= n
        key += s2
    return keys.reshape(-1)


def _face_keys(faces: np.ndarray) -> np.ndarray:
    """Orientation-independent integer keys of triangles, ``(f,) int64`` (or ``(f, 3)``)."""
    if faces.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    n = int(faces.max()) + 1
    if n >= 2_000_000:  # n**3 >= 2**63: the sorted rows themselves
        return np.sort(faces, axis=1)
    s0, s1, s2 = _sorted_columns(faces)
    key = s0 * n
    key += s1
    key *= n
    key += s2
    return key


def boundary_face_index(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The boundary faces of a tet mesh as (tet, local face) pairs.

    A face is on the boundary when exactly one tet has it.

    Parameters
    ----------
    T : (n_tets, k >= 4) int64
        Elements; their first four nodes are the corners (positively oriented).

    Returns
    -------
    tet, face : (n_faces,) int64
        The element having each boundary face and the face's row of :data:`TET_FACES`, in
        the order of the elements (then of their faces).
    """
    T = np.asarray(T, dtype=np.int64)
    if T.ndim != 2 or T.shape[1] < 4:
        raise ValueError(f"T must be (n_tets, 4), got {T.shape}")
    T = T[:, :4]
    keys = _tet_face_keys(T)
    if keys is not None:  # keys of the faces only one tet has, then a lookup (no argsort)
        none = np.zeros(0, dtype=np.int64)
        if keys.size == 0:
            return none, none
        s = np.sort(keys)
        single = np.ones(s.size, dtype=bool)
        same = s[1:] == s[:-1]
        single[1:] &= ~same
        single[:-1] &= ~same
        once = s[single]
        if once.size == 0:
            return none, none
        pos = np.searchsorted(once, keys)
        np.minimum(pos, once.size - 1, out=pos)
        return np.divmod(np.flatnonzero(once[pos] == keys), 4)
    faces = _tet_faces(T)
    keys = _face_keys(faces)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return np.divmod(np.flatnonzero(counts[inverse.reshape(-1)] == 1), 4)


def boundary_faces(T: np.ndarray) -> np.ndarray:
    """Boundary triangles of a tet mesh, oriented outward.

    A face is on the boundary when exactly one tet has it. Its vertex order makes the
    right-hand normal point away from that tet's fourth (opposite) vertex, i.e. outward
    when ``T`` is positively oriented.

    Parameters
    ----------
    T : (n_tets, 4) int64
        Positively oriented tets.

    Returns
    -------
    F : (n_faces, 3) int64
        Boundary triangles, in the order of the tets they belong to.
    """
    T = np.asarray(T, dtype=np.int64)
    if T.ndim != 2 or T.shape[1] != 4:
        raise ValueError(f"T must be (n_tets, 4), got {T.shape}")
    tet, k = boundary_face_index(T)
    return np.ascontiguousarray(T[tet[:, None], TET_FACES[k]]).reshape(-1, 3)


# --------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------


def _where(lines: np.ndarray | None, i: int) -> int | None:
    return None if lines is None else int(lines[i])


def _more(k: int) -> str:
    return f" (and {k - 1} more)" if k > 1 else ""


def validate_tet_mesh(
    X: np.ndarray,
    T: np.ndarray,
    *,
    path: PathArg | None = None,
    vertex_lines: np.ndarray | None = None,
    tet_lines: np.ndarray | None = None,
    index_base: int = 0,
    rtol: float = DEGENERATE_RTOL,
) -> TetMesh:
    """Check a tet mesh and return it as a positively oriented :class:`TetMesh`.

    Raises :class:`InputError` for: no vertices, non-finite coordinates, no tets, indices out
    of range or negative, tets with repeated vertices, duplicate tets, faces shared by more
    than two tets, zero-volume tets. Warns (:class:`MeshWarning`) and fixes: negatively
    oriented tets (two vertices swapped) and vertices no tet uses (removed, the others
    renumbered; they would have no mass and make the system singular).

    Parameters
    ----------
    X : (n_vertices, 3) float
        Vertex positions.
    T : (n_tets, 4) int
        0-based vertex indices.
    path : str or PathLike, optional
        The file, for messages.
    vertex_lines, tet_lines : (n_vertices,) / (n_tets,) int, optional
        1-based line number of each vertex / tet in ``path``, for messages.
    index_base : int
        What the file's indices start at (``T + index_base`` is what the file says).
    rtol : float
        Degeneracy tolerance, see :data:`DEGENERATE_RTOL`.

    Returns
    -------
    TetMesh
    """
    X = np.asarray(X, dtype=np.float64)
    T = np.asarray(T)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InputError(f"vertices must be 3-D points, got an array of shape {X.shape}", path=path)
    n = X.shape[0]
    if n == 0:
        raise InputError("mesh has no vertices", path=path)
    bad = np.flatnonzero(~np.isfinite(X).all(axis=1))
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"vertex {i + index_base} has a non-finite coordinate {X[i].tolist()}{_more(bad.size)}",
            path=path, line=_where(vertex_lines, i), element=i,
        )
    if T.ndim != 2 or T.shape[1] != 4:
        raise InputError(f"tets must have 4 vertices, got an array of shape {T.shape}", path=path)
    m = T.shape[0]
    if m == 0:
        raise InputError("mesh has no tetrahedra", path=path)
    T = T.astype(np.int64, copy=True)

    where = {"path": path, "tet_lines": tet_lines, "index_base": index_base}
    _check_tet_indices(T, n, **where)
    det = _tet_determinants(X, T, rtol, **where)
    _check_face_sharing(T, **where)

    inverted = det < 0
    if inverted.any():
        k = int(inverted.sum())
        warnings.warn(
            f"{path or 'mesh'}: re-oriented {k} of {m} negatively oriented tets (swapped their "
            f"last two vertices; first: tet {int(np.argmax(inverted))})",
            MeshWarning, stacklevel=3,
        )
        T[inverted] = T[inverted][:, [0, 1, 3, 2]]

    used = np.zeros(n, dtype=bool)
    used[T.reshape(-1)] = True
    if not used.all():
        k = int((~used).sum())
        warnings.warn(
            f"{path or 'mesh'}: removed {k} vertices that no tet uses (first: vertex "
            f"{int(np.argmax(~used)) + index_base}); the others were renumbered",
            MeshWarning, stacklevel=3,
        )
        new_index = np.cumsum(used) - 1
        X = X[used]
        T = new_index[T]
    mesh = TetMesh(X=X, T=T, path=None if path is None else str(path))
    _stages.debug("validate mesh")
    return mesh


def _check_tet_indices(T: np.ndarray, n: int, *, path: PathArg | None,
                       tet_lines: np.ndarray | None, index_base: int) -> None:
    """Refuse tets with an index out of ``[0, n)``, a repeated vertex, or that repeat a tet."""
    m = T.shape[0]
    neg = np.flatnonzero((T < 0).any(axis=1))
    big = np.flatnonzero((T >= n).any(axis=1))
    if neg.size or big.size:
        j = int(min(neg[0] if neg.size else m, big[0] if big.size else m))
        v = T[j] + index_base
        what = (
            f"index out of range: tet {j} refers to vertex {v.tolist()}, valid indices are "
            f"{index_base}..{n - 1 + index_base}"
        )
        if (T[j] < 0).any() and index_base == 1 and (v == 0).any():
            what += " (this file format is 1-based)"
        raise InputError(what + _more(neg.size + big.size), path=path,
                         line=_where(tet_lines, j), element=j)

    s0, s1, s2, s3 = _sorted_columns(T)
    rep = np.flatnonzero((s0 == s1) | (s1 == s2) | (s2 == s3))
    if rep.size:
        j = int(rep[0])
        raise InputError(
            f"tet {j} has a repeated vertex {(T[j] + index_base).tolist()}{_more(rep.size)}",
            path=path, line=_where(tet_lines, j), element=j,
        )
    if _may_repeat_rows((s0, s1, s2, s3), n):
        _report_duplicate_tets(np.stack([s0, s1, s2, s3], axis=1), T, path=path,
                               tet_lines=tet_lines, index_base=index_base)


def _may_repeat_rows(S: tuple[np.ndarray, ...], n: int) -> bool:
    """Whether two rows of the sorted tets with columns ``S`` (indices in ``[0, n)``) may be
    equal: a sort of one int64 hash per row (equal rows have equal hashes; a collision costs
    the exact check only)."""
    s0, s1, s2, s3 = S
    if s0.size < 2:
        return False
    if n < 55_000:  # n**4 < 2**63: the key is the row itself
        h = ((s0 * n + s1) * n + s2) * n + s3
    else:  # integer arrays wrap around silently
        h = (s0 * n + s1) * np.int64(0x9E3779B97F4A7C15 - 2**64) + (s2 * n + s3)
    h.sort()
    return bool((h[1:] == h[:-1]).any())


def _report_duplicate_tets(S: np.ndarray, T: np.ndarray, *, path: PathArg | None,
                           tet_lines: np.ndarray | None, index_base: int) -> None:
    """Raise the message about the first repeated tet, if any row of ``S`` repeats."""
    _, first, counts = np.unique(S, axis=0, return_index=True, return_counts=True)
    if (counts > 1).any():
        dup_rows = np.flatnonzero((S == S[first[np.argmax(counts > 1)]]).all(axis=1))
        j = int(dup_rows[1])
        raise InputError(
            f"tet {j} duplicates tet {int(dup_rows[0])} (vertices {(T[j] + index_base).tolist()})",
            path=path, line=_where(tet_lines, j), element=j,
        )


def _tet_determinants(X: np.ndarray, T: np.ndarray, rtol: float, *, path: PathArg | None,
                      tet_lines: np.ndarray | None, index_base: int) -> np.ndarray:
    """Refuse degenerate tets, and tets whose volume double precision cannot work with.

    Returns
    -------
    det : (n_tets,) float64
        ``6 V`` of each tet scaled to its largest edge-vector component (its sign is the
        tet's orientation).
    """
    # the degeneracy test is scale-invariant: evaluate it on each tet translated to its
    # first vertex and divided by its largest edge-vector component (no overflow or
    # underflow for any finite coordinates); report sizes in the file's units
    m = T.shape[0]
    scale, h, det = np.empty(m), np.empty(m), np.empty(m)
    for a in range(0, m, _CHUNK):  # chunks of tets: temporaries stay in cache
        b = min(m, a + _CHUNK)
        scale[a:b], h[a:b], det[a:b] = _scaled_determinants(X, T[a:b])
    degen = np.flatnonzero(~(np.abs(det) > rtol * h**3))
    if degen.size:
        j = int(degen[0])
        with np.errstate(all="ignore"):
            vol_j = det[j] / 6 * scale[j] ** 3 if det[j] != 0 else 0.0
            h_j = h[j] * scale[j]
        raise InputError(
            f"tet {j} (vertices {(T[j] + index_base).tolist()}) is degenerate: volume "
            f"{vol_j:.3g} for longest edge {h_j:.3g}{_more(degen.size)}",
            path=path, line=_where(tet_lines, j), element=j,
        )
    with np.errstate(all="ignore"):
        vol = det / 6 * scale**3
    badsize = np.flatnonzero(~((np.abs(vol) > 1e-250) & (np.abs(vol) < 1e250)))
    if badsize.size:
        j = int(badsize[0])
        raise InputError(
            f"tet {j} (vertices {(T[j] + index_base).tolist()}) has volume {vol[j]:.3g}, "
            "which double precision cannot work with: rescale the mesh"
            f"{_more(badsize.size)}", path=path, line=_where(tet_lines, j), element=j,
        )
    return det


#: Tets per chunk of the element-wise checks.
_CHUNK = 1 << 15


def _scaled_determinants(X: np.ndarray, T: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(scale, h, det)`` of tets ``T``: the largest edge-vector component, the longest edge
    and ``6 V``, the last two of the tet divided by ``scale``."""
    with np.errstate(all="ignore"):
        e = X[T]
        rel = e[:, [1, 2, 3, 2, 3, 3]] - e[:, [0, 0, 0, 1, 1, 2]]
        scale = np.abs(rel).max(axis=(1, 2))
        edges = rel / np.where(scale > 0, scale, 1.0)[:, None, None]
        h = np.sqrt(np.einsum("mij,mij->mi", edges, edges).max(axis=1))
        det = np.einsum("ij,ij->i", edges[:, 0], np.cross(edges[:, 1], edges[:, 2]))
    return scale, h, det


def _check_face_sharing(T: np.ndarray, *, path: PathArg | None, tet_lines: np.ndarray | None,
                        index_base: int) -> None:
    """Refuse a face shared by more than two tets (overlapping / non-conforming mesh)."""
    keys = _tet_face_keys(T)
    if keys is not None:  # a sort says whether any key is there three times
        s = np.sort(keys)
        if not (s[2:] == s[:-2]).any():
            return
    faces = _tet_faces(T)
    keys = _face_keys(faces)
    fax = None if keys.ndim == 1 else 0
    _, finv, fcounts = np.unique(keys, axis=fax, return_inverse=True, return_counts=True)
    finv = finv.reshape(-1)
    over = np.flatnonzero(fcounts[finv] > 2)
    if over.size:
        sharing = np.flatnonzero(finv == finv[over[0]])
        j = int(sharing[-1] // 4)
        others = ", ".join(str(int(i // 4)) for i in sharing[:-1])
        raise InputError(
            f"tet {j} has face {(faces[sharing[-1]] + index_base).tolist()} that tets {others} "
            "already share (overlapping / non-conforming mesh)",
            path=path, line=_where(tet_lines, j), element=j,
        )


def validate_surface_mesh(
    V: np.ndarray,
    F: np.ndarray,
    *,
    path: PathArg | None = None,
    vertex_lines: np.ndarray | None = None,
    face_lines: np.ndarray | None = None,
    index_base: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Check a triangle (display) mesh.

    Raises :class:`InputError` for no vertices, non-finite coordinates, no faces and
    indices out of range; drops faces with a repeated vertex with a :class:`MeshWarning`.

    Parameters
    ----------
    V : (n_vertices, 3) float
    F : (n_faces, 3) int, 0-based
    path, vertex_lines, face_lines, index_base
        As for :func:`validate_tet_mesh`.

    Returns
    -------
    V : (n_vertices, 3) float64
    F : (n_faces, 3) int64
    """
    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.asarray(F)
    if V.ndim != 2 or V.shape[1] != 3:
        raise InputError(f"vertices must be 3-D points, got an array of shape {V.shape}", path=path)
    n = V.shape[0]
    if n == 0:
        raise InputError("display mesh has no vertices", path=path)
    bad = np.flatnonzero(~np.isfinite(V).all(axis=1))
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"vertex {i + index_base} has a non-finite coordinate {V[i].tolist()}{_more(bad.size)}",
            path=path, line=_where(vertex_lines, i), element=i,
        )
    if F.ndim != 2 or F.shape[1] != 3:
        raise InputError(f"faces must be triangles, got an array of shape {F.shape}", path=path)
    if F.shape[0] == 0:
        raise InputError("display mesh has no faces", path=path)
    F = np.ascontiguousarray(F, dtype=np.int64)
    out = np.flatnonzero(((F < 0) | (F >= n)).any(axis=1))
    if out.size:
        j = int(out[0])
        raise InputError(
            f"index out of range: face {j} refers to vertex {(F[j] + index_base).tolist()}, "
            f"valid indices are {index_base}..{n - 1 + index_base}{_more(out.size)}",
            path=path, line=_where(face_lines, j), element=j,
        )
    rep = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 0] == F[:, 2])
    if rep.any():
        warnings.warn(
            f"{path or 'display mesh'}: dropped {int(rep.sum())} faces with a repeated vertex "
            f"(first: face {int(np.argmax(rep))})",
            MeshWarning, stacklevel=3,
        )
        F = F[~rep]
        if F.shape[0] == 0:
            raise InputError("display mesh has no faces", path=path)
    return V, F


# --------------------------------------------------------------------------------------
# generated meshes
# --------------------------------------------------------------------------------------


def box_tet_mesh(
    cells: Sequence[int] = (2, 2, 2),
    size: Sequence[float] = (1.0, 1.0, 1.0),
    origin: Sequence[float] = (0.0, 0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """A box split into grid cells of 6 Kuhn (Freudenthal) tets each, all positively oriented.

    Every tet follows a monotone path from a cell's lowest corner to its highest, along the
    axes in the order of one permutation, so neighbouring cells share faces (conforming).

    Parameters
    ----------
    cells : (3,) int
        Cells along x, y, z.
    size : (3,) float
        Box extents.
    origin : (3,) float
        Lowest corner.

    Returns
    -------
    X : ((nx+1)(ny+1)(nz+1), 3) float64
        Grid vertices, z fastest (``meshgrid(..., indexing="ij")`` order).
    T : (6 nx ny nz, 4) int64
        Tets, cell after cell (x slowest), the six permutations of (0, 1, 2) in
        lexicographic order within a cell.
    """
    n = tuple(int(k) for k in cells)
    axes = [np.linspace(0.0, float(s), k + 1) for s, k in zip(size, n, strict=True)]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    X = X + np.asarray(origin, dtype=np.float64)
    shape = tuple(k + 1 for k in n)
    lowest = np.stack(np.meshgrid(*(np.arange(k) for k in n), indexing="ij"),
                      axis=-1).reshape(-1, 1, 1, 3)
    steps = np.zeros((6, 4, 3), dtype=np.int64)  # corner offsets along each permutation's path
    for p, perm in enumerate(itertools.permutations(range(3))):
        for i, axis in enumerate(perm):
            steps[p, i + 1:, axis] += 1
    corners = (lowest + steps).reshape(-1, 3)
    T = np.ravel_multi_index(tuple(corners.T), shape).reshape(-1, 4).astype(np.int64)
    e = X[T[:, 1:]] - X[T[:, :1]]
    neg = np.linalg.det(e) < 0
    T[neg, 2], T[neg, 3] = T[neg, 3].copy(), T[neg, 2].copy()
    return X, T
