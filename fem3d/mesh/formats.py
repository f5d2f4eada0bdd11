"""Mesh input/output and validation.

Readers
-------
``read_tet_mesh(path) -> TetMesh``
    MEDIT ``.mesh`` (ASCII, own parser, 1-based), TetGen ``.node``/``.ele`` (either file or
    the common stem; 0- or 1-based, detected from the ``.node`` file's first index), and
    every volume format meshio reads (Gmsh ``.msh``, ``.vtu``, ``.vtk``, ...).
``read_surface_mesh(path) -> (V, F)``
    Wavefront ``.obj`` (own fast parser), MEDIT ``.mesh`` and every surface format meshio
    reads; quads and polygons are split into triangles.

Every reader either returns a fully validated mesh or raises
:class:`fem3d.errors.InputError` naming the file, the line and/or element and what is wrong;
lower-level exceptions (``ValueError``, ``UnicodeDecodeError``, meshio's errors, ...) never
escape and no half-read mesh is ever returned.

Why own MEDIT and OBJ parsers: meshio's MEDIT reader stores the coordinates of a
``MeshVersionFormatted 1`` file in single precision (the shipped bunny files are version 1
but carry 16 significant digits), and its error messages carry no line numbers. meshio 5.3's
OBJ reader cannot read the shipped ``armadillo.obj`` at all (it has 51986 ``vn`` lines for
26002 vertices); the own OBJ parser reads it in about 0.2 s and handles ``f a/b/c`` forms,
polygons and negative (relative) indices.

Orientation
-----------
Tetrahedra are returned positively oriented: ``det([X1-X0, X2-X0, X3-X0]) > 0``. Negatively
oriented rest tets are *re-oriented* (two vertices swapped) with a :class:`MeshWarning`
rather than rejected: the vertex order of a tet is a file-format convention (MEDIT, TetGen
and Gmsh do not agree on it), not a physical inversion, because a rest configuration cannot
be "inverted" relative to itself. Zero-volume tets, on the other hand, are an error: they
have no rest shape at all.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import struct
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from fem3d.errors import InputError
from fem3d.io.files import check_input_file

__all__ = [
    "MeshWarning",
    "TetMesh",
    "boundary_faces",
    "box_tet_mesh",
    "check_skin_inside",
    "check_skin_placement",
    "read_surface_mesh",
    "read_tet_mesh",
    "skin_outside_distance",
    "tet_signed_volumes",
    "validate_surface_mesh",
    "validate_tet_mesh",
    "write_surface_mesh",
    "write_tet_mesh",
]

PathArg = str | PathLike[str]

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


def _face_keys(faces: np.ndarray) -> np.ndarray:
    """Orientation-independent integer keys of triangles, ``(f,) int64`` (or ``(f, 3)``)."""
    s = np.sort(faces, axis=1)
    n = int(s.max()) + 1 if s.size else 1
    if n < 2_000_000:  # n**3 < 2**63
        return (s[:, 0] * n + s[:, 1]) * n + s[:, 2]
    return s


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
    faces = T[:, TET_FACES].reshape(-1, 3)
    if faces.shape[0] == 0:
        return np.zeros((0, 3), dtype=np.int64)
    keys = _face_keys(faces)
    axis = None if keys.ndim == 1 else 0
    _, inverse, counts = np.unique(keys, axis=axis, return_inverse=True, return_counts=True)
    return np.ascontiguousarray(faces[counts[inverse.reshape(-1)] == 1])


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

    S = np.sort(T, axis=1)
    rep = np.flatnonzero((S[:, 1:] == S[:, :-1]).any(axis=1))
    if rep.size:
        j = int(rep[0])
        raise InputError(
            f"tet {j} has a repeated vertex {(T[j] + index_base).tolist()}{_more(rep.size)}",
            path=path, line=_where(tet_lines, j), element=j,
        )
    _, first, counts = np.unique(S, axis=0, return_index=True, return_counts=True)
    if (counts > 1).any():
        dup_rows = np.flatnonzero((S == S[first[np.argmax(counts > 1)]]).all(axis=1))
        j = int(dup_rows[1])
        raise InputError(
            f"tet {j} duplicates tet {int(dup_rows[0])} (vertices {(T[j] + index_base).tolist()})",
            path=path, line=_where(tet_lines, j), element=j,
        )

    # the degeneracy test is scale-invariant: evaluate it on each tet translated to its
    # first vertex and divided by its largest edge-vector component (no overflow or
    # underflow for any finite coordinates); report sizes in the file's units
    with np.errstate(all="ignore"):
        e = X[T]
        rel = e[:, [1, 2, 3, 2, 3, 3]] - e[:, [0, 0, 0, 1, 1, 2]]
        scale = np.abs(rel).max(axis=(1, 2))
        edges = rel / np.where(scale > 0, scale, 1.0)[:, None, None]
        h = np.sqrt(np.einsum("mij,mij->mi", edges, edges).max(axis=1))
        det = np.einsum("ij,ij->i", edges[:, 0], np.cross(edges[:, 1], edges[:, 2]))
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

    faces = T[:, TET_FACES].reshape(-1, 3)
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
    return TetMesh(X=X, T=T, path=None if path is None else str(path))


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
# text tokenizer shared by the MEDIT and TetGen readers
# --------------------------------------------------------------------------------------


class _Tokens:
    """Whitespace tokens of a text file with their 1-based line numbers."""

    def __init__(self, path: Path, comment: str = "#") -> None:
        self.path = path
        text = _read_text(path)
        lines = text.split("\n")
        if comment in text:
            lines = [ln.split(comment, 1)[0] for ln in lines]
        split = [ln.split() for ln in lines]
        counts = np.fromiter(map(len, split), dtype=np.int64, count=len(split))
        self.tok: list[str] = list(itertools.chain.from_iterable(split))
        self.line = np.repeat(np.arange(1, len(lines) + 1, dtype=np.int64), counts)
        self.n_lines = len(lines)
        self.pos = 0
        if not self.tok:
            raise InputError("empty file (no data)", path=path)

    def lineno(self, i: int | None = None) -> int:
        i = self.pos if i is None else i
        if i >= len(self.tok):
            return int(self.line[-1]) if len(self.tok) else 1
        return int(self.line[i])

    def at_end(self) -> bool:
        return self.pos >= len(self.tok)

    def peek(self) -> str:
        return self.tok[self.pos]

    def next(self, what: str) -> str:
        if self.pos >= len(self.tok):
            raise InputError(f"file ends early (truncated?): expected {what}",
                             path=self.path, line=self.lineno())
        t = self.tok[self.pos]
        self.pos += 1
        return t

    def next_int(self, what: str, lo: int | None = 0) -> int:
        i = self.pos
        t = self.next(what)
        try:
            v = int(t)
        except ValueError:
            raise InputError(f"expected {what} (an integer), found {t!r}",
                             path=self.path, line=self.lineno(i)) from None
        if lo is not None and v < lo:
            raise InputError(f"{what} must be >= {lo}, found {v}",
                             path=self.path, line=self.lineno(i))
        return v

    def block(
        self, count: int, width: int, what: str, dtype: type
    ) -> tuple[np.ndarray, np.ndarray]:
        """Take ``count`` records of ``width`` numeric tokens.

        Returns
        -------
        values : (count, width) ``dtype``
        lines : (count,) int64, the line of each record's first token.
        """
        a = self.pos
        b = a + count * width
        if b > len(self.tok):
            have = (len(self.tok) - a) // width if width else 0
            kw = next((i for i in range(a, len(self.tok))
                       if self.tok[i].lower() in _MEDIT_KEYWORDS), None)
            if kw is not None:
                raise InputError(
                    f"{what} section declares {count} entries but keyword {self.tok[kw]!r} "
                    f"comes after {(kw - a) // width} (wrong count or missing data)",
                    path=self.path, line=self.lineno(kw),
                )
            raise InputError(
                f"file ends early (truncated?): {what} section declares {count} entries of "
                f"{width} numbers, only {have} complete entries follow",
                path=self.path, line=self.lineno(len(self.tok) - 1),
            )
        chunk = self.tok[a:b]
        try:
            values = np.array(chunk, dtype=dtype).reshape(count, width)
        except (ValueError, OverflowError, TypeError):
            ok = _is_number if dtype is np.float64 else _is_int
            k = next((i for i, t in enumerate(chunk) if not ok(t)), 0)
            t = chunk[k]
            kind = "a number" if dtype is np.float64 else "an integer"
            if t[:1].isalpha() and t.lower() in _MEDIT_KEYWORDS:
                msg = (f"{what} section declares {count} entries but keyword {t!r} comes after "
                       f"{k // width} (wrong count or missing data)")
            else:
                msg = f"non-numeric token {t!r} in {what} entry {k // width} (expected {kind})"
            raise InputError(msg, path=self.path, line=self.lineno(a + k),
                             element=k // width) from None
        self.pos = b
        lines = self.line[a:b:width] if width else np.zeros(0, dtype=np.int64)
        return values, lines


def _read_text(path: Path) -> str:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except IsADirectoryError:
        raise InputError("is a directory, not a mesh file", path=path) from None
    except OSError as exc:
        raise InputError(f"cannot read file: {exc.strerror or exc}", path=path) from None
    if not data.strip():
        raise InputError("empty file", path=path)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        # e.g. Latin-1 comments or names: decode anyway, numbers are ASCII in any case
        text = data.decode("latin-1")
    if "\x00" in text:
        raise InputError("not a text file (contains NUL bytes)", path=path,
                         line=text.count("\n", 0, text.index("\x00")) + 1)
    return text


# --------------------------------------------------------------------------------------
# MEDIT .mesh
# --------------------------------------------------------------------------------------

# entries per record (excluding the per-record reference label handled below)
_MEDIT_SECTIONS: dict[str, int] = {
    "vertices": -1,  # dim + 1, set once Dimension is known
    "edges": 3,
    "triangles": 4,
    "quadrilaterals": 5,
    "tetrahedra": 5,
    "hexahedra": 9,
    "prisms": 7,
    "pyramids": 6,
    "corners": 1,
    "requiredvertices": 1,
    "ridges": 1,
    "requirededges": 1,
    "requiredtriangles": 1,
    "requiredquadrilaterals": 1,
    "normals": -1,  # dim
    "normalatvertices": 2,
    "normalattriangleverices": 3,
    "normalattrianglevertices": 3,
    "tangents": -1,  # dim
    "tangentatvertices": 2,
    "tangentatedges": 3,
}
_MEDIT_KEYWORDS = set(_MEDIT_SECTIONS) | {"meshversionformatted", "dimension", "end"}


def _read_medit(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Parse an ASCII MEDIT file into ``{section: (records, lines)}``."""
    tk = _Tokens(path)
    dim = 3
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    saw_end = False
    last_section = None
    while not tk.at_end():
        i = tk.pos
        word = tk.next("a keyword")
        key = word.lower()
        if key == "end":
            saw_end = True
            break
        if key == "meshversionformatted":
            v = tk.next_int("the MeshVersionFormatted number", lo=0)
            if v not in (0, 1, 2, 3, 4):
                raise InputError(f"unknown MeshVersionFormatted {v}", path=path,
                                 line=tk.lineno(i))
            continue
        if key == "dimension":
            dim = tk.next_int("the dimension", lo=0)
            if dim != 3:
                raise InputError(f"only 3-D meshes are supported, file says Dimension {dim}",
                                 path=path, line=tk.lineno(i))
            continue
        if key not in _MEDIT_SECTIONS:
            if _is_number(word):
                hint = (f" (the count of the {last_section} section may be wrong)"
                        if last_section else "")
                raise InputError(f"expected a keyword, found the number {word!r}{hint}",
                                 path=path, line=tk.lineno(i))
            raise InputError(f"unknown MEDIT keyword {word!r}", path=path, line=tk.lineno(i))
        width = _MEDIT_SECTIONS[key]
        if width < 0:
            width = dim + 1 if key == "vertices" else dim
        count = tk.next_int(f"the number of {word}", lo=0)
        dtype = np.float64 if key in ("vertices", "normals", "tangents") else np.int64
        if key in out:
            raise InputError(f"section {word!r} appears twice", path=path, line=tk.lineno(i))
        out[key] = tk.block(count, width, word, dtype)
        last_section = word
    if not saw_end:
        raise InputError("file ends without the 'End' keyword (truncated?)", path=path,
                         line=tk.n_lines)
    if not tk.at_end():
        raise InputError(f"unexpected data after 'End': {tk.peek()!r}", path=path,
                         line=tk.lineno())
    return out


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def _is_int(word: str) -> bool:
    try:
        return abs(int(word)) < 2**62
    except ValueError:
        return False


def _medit_tet_mesh(path: Path) -> TetMesh:
    sec = _read_medit(path)
    if "vertices" not in sec:
        raise InputError("no Vertices section", path=path)
    Xr, vlines = sec["vertices"]
    if "tetrahedra" not in sec or sec["tetrahedra"][0].shape[0] == 0:
        raise InputError("mesh has no tetrahedra (no or empty Tetrahedra section)", path=path)
    Tr, tlines = sec["tetrahedra"]
    return validate_tet_mesh(Xr[:, :3], Tr[:, :4] - 1, path=path, vertex_lines=vlines,
                             tet_lines=tlines, index_base=1)


# --------------------------------------------------------------------------------------
# TetGen .node / .ele
# --------------------------------------------------------------------------------------


def _tetgen_paths(path: Path) -> tuple[Path, Path]:
    suffix = path.suffix.lower()
    if suffix in (".node", ".ele"):
        stem = path.with_suffix("")
    else:
        stem = path
    return Path(str(stem) + ".node"), Path(str(stem) + ".ele")


def _header(tk: _Tokens, names: Sequence[str], defaults: Sequence[int]) -> list[int]:
    """Read the integers of a TetGen header line (those on the first data line)."""
    first_line = tk.lineno(0)
    vals = []
    for k, name in enumerate(names):
        if k > 0 and (tk.at_end() or tk.lineno() != first_line):
            vals.append(defaults[k])
            continue
        vals.append(tk.next_int(name, lo=0))
    if not tk.at_end() and tk.lineno() == first_line:
        raise InputError(f"unexpected extra token {tk.peek()!r} on the header line",
                         path=tk.path, line=first_line)
    return vals


def _tetgen_tet_mesh(path: Path) -> TetMesh:
    node_path, ele_path = _tetgen_paths(path)
    for p in (node_path, ele_path):
        if not p.exists() and not p.is_symlink():
            raise InputError(f"file not found (TetGen meshes need both {node_path.name} and "
                             f"{ele_path.name})", path=p)
        check_input_file(p, "mesh")
    tk = _Tokens(node_path)
    n, dim, nattr, nmark = _header(tk, ["the number of points", "the dimension",
                                       "the number of attributes",
                                       "the boundary-marker flag"], [0, 3, 0, 0])
    if dim != 3:
        raise InputError(f"only 3-D meshes are supported, header says dimension {dim}",
                         path=node_path, line=tk.lineno(0))
    if nmark not in (0, 1):
        raise InputError(f"boundary-marker flag must be 0 or 1, found {nmark}",
                         path=node_path, line=tk.lineno(0))
    if n == 0:
        raise InputError("mesh has no vertices (header says 0 points)", path=node_path,
                         line=tk.lineno(0))
    width = 1 + dim + nattr + nmark
    rec, vlines = tk.block(n, width, "node", np.float64)
    if not tk.at_end():
        raise InputError(f"more data than the header's {n} points: {tk.peek()!r} (wrong count?)",
                         path=node_path, line=tk.lineno())
    idx = rec[:, 0]
    base = idx[0]
    if base not in (0.0, 1.0):
        raise InputError(f"first node index must be 0 or 1, found {idx[0]:g}",
                         path=node_path, line=int(vlines[0]), element=0)
    wrong = np.flatnonzero(idx != np.arange(n) + base)
    if wrong.size:
        i = int(wrong[0])
        raise InputError(f"node indices must be consecutive: expected {i + int(base)}, found "
                         f"{idx[i]:g}", path=node_path, line=int(vlines[i]), element=i)
    base = int(base)
    X = rec[:, 1:4]
    bad = np.flatnonzero(~np.isfinite(X).all(axis=1))
    if bad.size:  # report against the .node file
        validate_tet_mesh(X, np.zeros((0, 4), np.int64), path=node_path, vertex_lines=vlines,
                          index_base=base)

    te = _Tokens(ele_path)
    m, per, rattr = _header(te, ["the number of tetrahedra", "the nodes per tetrahedron",
                                 "the number of region attributes"], [0, 4, 0])
    if per != 4:
        raise InputError(f"only linear (4-node) tetrahedra are supported, header says {per}",
                         path=ele_path, line=te.lineno(0))
    if m == 0:
        raise InputError("mesh has no tetrahedra (header says 0)", path=ele_path,
                         line=te.lineno(0))
    erec, tlines = te.block(m, 1 + per + rattr, "tetrahedron", np.float64)
    if not te.at_end():
        raise InputError(f"more data than the header's {m} tetrahedra: {te.peek()!r} "
                         "(wrong count?)", path=ele_path, line=te.lineno())
    Tf = erec[:, 1:5]
    nonint = np.flatnonzero(~(Tf == np.round(Tf)).all(axis=1))
    if nonint.size:
        j = int(nonint[0])
        raise InputError(f"tetrahedron {j} has a non-integer vertex index {Tf[j].tolist()}",
                         path=ele_path, line=int(tlines[j]), element=j)
    Tf = np.clip(Tf, -(2.0**62), 2.0**62)
    return validate_tet_mesh(X, Tf.astype(np.int64) - base, path=ele_path, vertex_lines=vlines,
                             tet_lines=tlines, index_base=base)


# --------------------------------------------------------------------------------------
# meshio fallback
# --------------------------------------------------------------------------------------


def _meshio_extensions() -> set[str]:
    try:
        from meshio._helpers import extension_to_filetypes
    except ImportError:  # pragma: no cover - meshio layout changed
        return {".msh", ".vtu", ".vtk", ".xdmf", ".inp", ".off", ".ply", ".stl"}
    return set(extension_to_filetypes)


def _meshio_read(path: Path):  # -> meshio.Mesh
    import meshio

    check_input_file(path, "mesh")
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
    except OSError as exc:
        raise InputError(f"cannot read file: {exc.strerror or exc}", path=path) from None
    if size == 0 or (size <= len(head) and not head.strip()):
        raise InputError("empty file", path=path)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()), \
                contextlib.redirect_stderr(io.StringIO()):
            warnings.simplefilter("ignore")
            mesh = _meshio_read_quietly(meshio, path)
        points = np.asarray(mesh.points, dtype=np.float64)
    except InputError:
        raise
    except MemoryError:
        raise InputError("cannot read file: it asks for more memory than available "
                         "(corrupt counts?)", path=path) from None
    except Exception as exc:  # noqa: BLE001 - any meshio/parser failure is bad input
        raise InputError(_parser_failure(exc, meshio, path), path=path) from None
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise InputError(f"points must be 3-D, got an array of shape {points.shape}", path=path)
    if points.shape[1] == 2:
        raise InputError("only 3-D meshes are supported, file has 2-D points", path=path)
    return mesh, points


def _parser_failure(exc: BaseException, meshio: Any, path: Path) -> str:
    """What is wrong with a file a parser choked on, in terms of the file (not of the
    parser's internals such as ``IndexError: list index out of range``)."""
    fmt = path.suffix.lstrip(".").upper() or "mesh"
    msg = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else ""
    if isinstance(exc, getattr(meshio, "ReadError", ())) and msg:
        what = msg[0].lower() + msg[1:]
    elif isinstance(exc, UnicodeDecodeError):
        what = "it holds binary or wrongly encoded data where text is expected"
    elif isinstance(exc, SyntaxError) and msg:  # XML (VTU) parse errors
        what = f"malformed XML ({msg})"
    elif isinstance(exc, (IndexError, EOFError, struct.error)):
        what = "it ends early, or a count in it does not match the data that follows"
    elif isinstance(exc, KeyError):
        what = "a section or field the format requires is missing"
    elif isinstance(exc, (ValueError, TypeError)):
        what = "a value is not a number where the format expects one, or a count is wrong"
    else:
        what = "its contents do not follow the format"
    return f"not a readable {fmt} file: {what}"


def _meshio_read_quietly(meshio, path: Path):  # -> meshio.Mesh
    """meshio.read without its ``print`` + ``sys.exit(1)`` on a ReadError (meshio 5.3)."""
    try:
        from meshio._helpers import _filetypes_from_path, reader_map
    except ImportError:  # pragma: no cover - meshio layout changed
        try:
            return meshio.read(path)
        except SystemExit:
            raise ValueError("meshio could not read the file") from None
    last: Exception | None = None
    for fmt in _filetypes_from_path(path):
        try:
            return reader_map[fmt](str(path))
        except Exception as exc:  # noqa: BLE001 - try the next format, report the last
            last = exc
    raise last if last is not None else ValueError("no meshio reader for this extension")


def _meshio_cells(mesh, names: Sequence[str]) -> dict[str, np.ndarray]:
    out: dict[str, list[np.ndarray]] = {}
    for block in mesh.cells:
        if block.type in names:
            out.setdefault(block.type, []).append(np.asarray(block.data))
    return {k: np.concatenate(v) for k, v in out.items()}


def _meshio_tet_mesh(path: Path) -> TetMesh:
    mesh, points = _meshio_read(path)
    cells = _meshio_cells(mesh, ["tetra", "tetra10"])
    if "tetra10" in cells:
        raise InputError("quadratic (10-node) tetrahedra are not supported", path=path)
    if "tetra" not in cells:
        raise InputError("mesh has no tetrahedra", path=path)
    T = cells["tetra"]
    if not np.issubdtype(T.dtype, np.integer):
        raise InputError("tetrahedron indices are not integers", path=path)
    return validate_tet_mesh(points, T, path=path)


# --------------------------------------------------------------------------------------
# public readers
# --------------------------------------------------------------------------------------


def _check_path(path: PathArg) -> Path:
    try:
        p = Path(path)
    except TypeError:
        raise InputError(f"not a file path: {path!r}") from None
    return p


def read_tet_mesh(path: PathArg) -> TetMesh:
    """Read a tetrahedral mesh.

    Parameters
    ----------
    path : str or PathLike
        ``.mesh`` (MEDIT ASCII), ``.node`` / ``.ele`` / TetGen stem, or any volume format
        meshio reads (``.msh``, ``.vtu``, ``.vtk``, ...).

    Returns
    -------
    TetMesh
        Validated, 0-based, positively oriented.

    Raises
    ------
    InputError
        Missing, unreadable or malformed file, or an invalid mesh (see
        :func:`validate_tet_mesh`).
    """
    p = _check_path(path)
    suffix = p.suffix.lower()
    if suffix in (".node", ".ele") or (not p.exists() and Path(str(p) + ".node").exists()):
        return replace(_tetgen_tet_mesh(p), path=str(path))
    check_input_file(p, "mesh")
    if suffix == ".mesh":
        return _medit_tet_mesh(p)
    if suffix in _meshio_extensions() and suffix not in (".obj", ".stl", ".off", ".ply"):
        return _meshio_tet_mesh(p)
    raise InputError(
        f"unknown tet-mesh file extension {p.suffix!r} (use .mesh, .node/.ele, .msh, .vtu, "
        "or another volume format meshio reads)", path=p,
    )


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    text = _read_text(path)
    v_rows: list[list[str]] = []
    v_lines: list[int] = []
    f_rows: list[list[str]] = []
    f_lines: list[int] = []
    f_nv: list[int] = []
    for lineno, raw in enumerate(text.split("\n"), 1):
        s = raw.lstrip()
        if not s or s[0] not in "vf":
            continue
        parts = s.split()
        tag = parts[0]
        if tag == "v":
            if len(parts) < 4:
                raise InputError(f"vertex needs 3 coordinates, found {len(parts) - 1}",
                                 path=path, line=lineno, element=len(v_rows))
            v_rows.append(parts[1:4])
            v_lines.append(lineno)
        elif tag == "f":
            if len(parts) < 4:
                raise InputError(f"face needs at least 3 vertices, found {len(parts) - 1}",
                                 path=path, line=lineno, element=len(f_rows))
            f_rows.append([p.split("/", 1)[0] for p in parts[1:]])
            f_lines.append(lineno)
            f_nv.append(len(v_rows))
    if not v_rows:
        raise InputError("display mesh has no vertices", path=path)
    vl = np.array(v_lines, dtype=np.int64)
    try:
        V = np.array(v_rows, dtype=np.float64)
    except ValueError:
        for i, row in enumerate(v_rows):
            for t in row:
                if not _is_number(t):
                    raise InputError(f"non-numeric coordinate {t!r} in vertex {i + 1}",
                                     path=path, line=v_lines[i], element=i) from None
        raise  # pragma: no cover
    if not f_rows:
        raise InputError("display mesh has no faces", path=path)
    fl = np.array(f_lines, dtype=np.int64)
    nv_before = np.array(f_nv, dtype=np.int64)
    sizes = np.fromiter(map(len, f_rows), dtype=np.int64, count=len(f_rows))
    tris: list[np.ndarray] = []
    tri_src: list[np.ndarray] = []
    for k in np.unique(sizes):
        sel = np.flatnonzero(sizes == k)
        rows = [f_rows[i] for i in sel]
        try:
            idx = np.array(rows, dtype=np.int64)
        except (ValueError, OverflowError):
            for j, row in zip(sel, rows, strict=True):
                for t in row:
                    try:
                        if abs(int(t)) >= 2**62:
                            raise OverflowError
                    except (ValueError, OverflowError):
                        raise InputError(f"bad vertex index {t!r} in face {j + 1}",
                                         path=path, line=f_lines[j], element=int(j)) from None
            raise  # pragma: no cover
        nb = nv_before[sel][:, None]
        zero = np.flatnonzero((idx == 0).any(axis=1))
        if zero.size:
            j = int(sel[zero[0]])
            raise InputError("vertex index 0 in a face (OBJ indices are 1-based)",
                             path=path, line=f_lines[j], element=j)
        idx = np.where(idx < 0, idx + nb, idx - 1)
        fan = np.stack([np.zeros(k - 2, np.int64), np.arange(1, k - 1), np.arange(2, k)], 1)
        tris.append(idx[:, fan].reshape(-1, 3))
        tri_src.append(np.repeat(sel, k - 2))
    src = np.concatenate(tri_src)
    order = np.argsort(src, kind="stable")
    F = np.concatenate(tris)[order]
    src = src[order]
    n = V.shape[0]
    out = np.flatnonzero(((F < 0) | (F >= n)).any(axis=1))
    if out.size:
        j = int(src[out[0]])
        raise InputError(
            f"index out of range: face {j + 1} refers to a vertex outside 1..{n} "
            f"(or before the start for a negative index){_more(out.size)}",
            path=path, line=f_lines[j], element=j,
        )
    return validate_surface_mesh(V, F, path=path, vertex_lines=vl, face_lines=fl[src],
                                 index_base=1)


def read_surface_mesh(path: PathArg) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle surface (display / skin) mesh.

    Parameters
    ----------
    path : str or PathLike
        ``.obj`` (own parser: ``v``, ``f a``, ``f a/b``, ``f a//c``, ``f a/b/c``, polygons,
        negative indices), ``.mesh`` (MEDIT Triangles/Quadrilaterals, else the boundary of
        its Tetrahedra), or anything meshio reads (``.stl``, ``.off``, ``.ply``, ``.vtu``...).

    Returns
    -------
    V : (n_vertices, 3) float64
    F : (n_faces, 3) int64
        0-based triangles; polygons are fan-triangulated.

    Raises
    ------
    InputError
    """
    p = _check_path(path)
    check_input_file(p, "mesh")
    suffix = p.suffix.lower()
    if suffix == ".obj":
        return _read_obj(p)
    if suffix == ".mesh":
        sec = _read_medit(p)
        if "vertices" not in sec:
            raise InputError("display mesh has no vertices", path=p)
        V, vlines = sec["vertices"]
        parts = []
        if "triangles" in sec:
            parts.append(sec["triangles"][0][:, :3] - 1)
        if "quadrilaterals" in sec:
            q = sec["quadrilaterals"][0][:, :4] - 1
            parts.append(q[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3))
        F = np.concatenate(parts) if parts else np.zeros((0, 3), np.int64)
        if F.shape[0] == 0 and "tetrahedra" in sec and sec["tetrahedra"][0].shape[0]:
            tm = _medit_tet_mesh(p)
            V, F, vlines = np.asarray(tm.X), boundary_faces(tm.T), None
        return validate_surface_mesh(V[:, :3], F, path=p, vertex_lines=vlines, index_base=1)
    if suffix in _meshio_extensions() and suffix not in (".node", ".ele"):
        mesh, points = _meshio_read(p)
        cells = _meshio_cells(mesh, ["triangle", "quad", "tetra"])
        parts = []
        if "triangle" in cells:
            parts.append(cells["triangle"])
        if "quad" in cells:
            parts.append(cells["quad"][:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3))
        if parts:
            F = np.concatenate(parts)
        elif "tetra" in cells:
            tm = validate_tet_mesh(points, cells["tetra"], path=p)
            points, F = np.asarray(tm.X), boundary_faces(tm.T)
        else:
            F = np.zeros((0, 3), np.int64)
        if not np.issubdtype(F.dtype, np.integer):
            raise InputError("face indices are not integers", path=p)
        return validate_surface_mesh(points, F, path=p)
    raise InputError(
        f"unknown surface-mesh file extension {p.suffix!r} (use .obj, .stl, .off, .ply, .mesh, "
        ".vtu, or another format meshio reads)", path=p,
    )


# --------------------------------------------------------------------------------------
# writers
# --------------------------------------------------------------------------------------


def write_tet_mesh(path: PathArg, mesh: TetMesh) -> None:
    """Write a tet mesh.

    Parameters
    ----------
    path : str or PathLike
        ``.mesh`` (MEDIT, version 2 i.e. double precision, 1-based), ``.node`` / ``.ele`` /
        stem (TetGen, 0-based; writes both files) or any meshio format (``.vtu``, ``.msh``).
    mesh : TetMesh
    """
    p = Path(path)
    X, T = np.asarray(mesh.X, np.float64), np.asarray(mesh.T, np.int64)
    suffix = p.suffix.lower()
    if suffix == ".mesh":
        with open(p, "w", encoding="utf-8") as fh:
            fh.write("MeshVersionFormatted 2\nDimension 3\n")
            fh.write(f"Vertices\n{len(X)}\n")
            np.savetxt(fh, np.column_stack([X, np.zeros(len(X))]), fmt="%.17g %.17g %.17g %d")
            fh.write(f"Tetrahedra\n{len(T)}\n")
            np.savetxt(fh, np.column_stack([T + 1, np.zeros(len(T), np.int64)]), fmt="%d")
            fh.write("End\n")
        return
    if suffix in (".node", ".ele", ""):
        node_path, ele_path = _tetgen_paths(p)
        with open(node_path, "w", encoding="utf-8") as fh:
            fh.write(f"{len(X)} 3 0 0\n")
            np.savetxt(fh, np.column_stack([np.arange(len(X)), X]), fmt="%d %.17g %.17g %.17g")
        with open(ele_path, "w", encoding="utf-8") as fh:
            fh.write(f"{len(T)} 4 0\n")
            np.savetxt(fh, np.column_stack([np.arange(len(T)), T]), fmt="%d")
        return
    import meshio

    kwargs = {"file_format": "gmsh22", "binary": False} if suffix == ".msh" else {}
    meshio.write(p, meshio.Mesh(X, [("tetra", T)]), **kwargs)


def write_surface_mesh(path: PathArg, V: np.ndarray, F: np.ndarray, header: str = "") -> None:
    """Write a triangle mesh (``.obj`` by own writer, anything else through meshio).

    Parameters
    ----------
    path : str or PathLike
    V : (n_vertices, 3) float64
    F : (n_faces, 3) int64, 0-based
    header : str
        Comment lines put at the top of an OBJ file.
    """
    p = Path(path)
    if p.suffix.lower() == ".obj":
        with open(p, "w", encoding="utf-8") as fh:
            for ln in header.splitlines():
                fh.write(f"# {ln}\n")
            np.savetxt(fh, np.asarray(V, np.float64), fmt="v %.9g %.9g %.9g")
            np.savetxt(fh, np.asarray(F, np.int64) + 1, fmt="f %d %d %d")
        return
    import meshio

    meshio.write(p, meshio.Mesh(np.asarray(V, np.float64), [("triangle", np.asarray(F))]))


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
    T : (n_tets, 4) int64, optional
        Without it the distance is to the bounding box of ``X``.
    k : int
        Candidate tets / boundary faces looked at per vertex (nearest by centroid).

    Returns
    -------
    d : (n_skin,) float64
        0 for vertices inside (a tet of) the mesh, else the distance to its boundary
        (an upper bound when the true closest face is not among the ``k`` candidates).
    """
    from scipy.spatial import cKDTree

    P = np.asarray(skin_V, np.float64)
    X = np.asarray(X, np.float64)
    lo, hi = X.min(axis=0), X.max(axis=0)
    d_box = np.linalg.norm(np.maximum(0.0, np.maximum(lo - P, P - hi)), axis=1)
    if T is None:
        return d_box
    T = np.asarray(T, np.int64)
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
    T : (n_tets, 4) int64, optional
        Simulation tets: measure to the mesh itself, not just its bounding box.
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
