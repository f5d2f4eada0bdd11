"""MEDIT ``.mesh`` files (ASCII): tet meshes and surfaces, read by an own parser, 1-based.

Why an own parser: meshio's MEDIT reader stores the coordinates of a ``MeshVersionFormatted 1``
file in single precision (the shipped bunny files are version 1 but carry 16 significant
digits), and its error messages carry no line numbers.

- :func:`read_medit` - ``{section: (records, lines)}`` of a file: a plain file parsed in C
  (:func:`_read_medit_plain`), anything else token by token with line numbers
  (:func:`_read_medit_tokens`, :class:`fem3d.mesh.textscan.Tokens`).
- :func:`medit_tet_mesh`, :func:`medit_surface_mesh` - the validated meshes of a file.
- :func:`medit_p2_tets` - the 10-node tets of a ``TetrahedraP2`` section (:func:`has_tetrahedra_p2`
  says whether a file has one without parsing it).
- :func:`write_medit` - version 2 (double precision).
"""

from __future__ import annotations

import logging
import re
import warnings
from pathlib import Path

import numpy as np

from fem3d.errors import InputError
from fem3d.io.files import decode_text, read_file_bytes
from fem3d.mesh.tetmesh import TetMesh, boundary_faces, validate_surface_mesh, validate_tet_mesh
from fem3d.mesh.textscan import Tokens, is_number

__all__ = ["MEDIT_KEYWORDS", "has_tetrahedra_p2", "medit_p2_tets", "medit_surface_mesh",
           "medit_tet_mesh", "read_medit", "write_medit"]

_stages = logging.getLogger("fem3d.stages")  # stage marks (fem3d run --profile)

# entries per record (excluding the per-record reference label handled below)
_MEDIT_SECTIONS: dict[str, int] = {
    "vertices": -1,  # dim + 1, set once Dimension is known
    "edges": 3,
    "triangles": 4,
    "quadrilaterals": 5,
    "tetrahedra": 5,
    "tetrahedrap2": 11,  # 4 corners, 6 edge nodes (edges 12, 23, 13, 14, 24, 34), reference
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
#: Every MEDIT keyword (lower case): a section running into one has a wrong count.
MEDIT_KEYWORDS = frozenset(_MEDIT_SECTIONS) | {"meshversionformatted", "dimension", "end"}


class _NotPlain(Exception):
    """The fast MEDIT reader met something only the token reader handles (a comment, a
    malformed section, ...): that reader then reads the file and says what is wrong."""


#: Bytes of the file scanned or parsed at a time (cut at a line's end): the file's bytes and the
#: records are all a read holds, not a copy of the section.
_PARSE_CHUNK = 1 << 22
#: A word at the start of a line.
_WORD = re.compile(rb"\S*")


def _keyword_lines(data: bytes) -> list[tuple[int, int, str]]:
    """``(start, end, word)`` of every line's first word that starts with a letter (a keyword
    after white space is left to the token reader: the number parser stops at it); a block
    of the file at a time, so the temporaries stay small."""
    b = np.frombuffer(data, dtype=np.uint8)
    marks = []
    for a in range(0, b.size, _PARSE_CHUNK):
        stop = min(b.size, a + _PARSE_CHUNK)
        first = b[a:stop] | 0x20  # (lower case)
        before = b[a - 1:stop - 1] if a else np.concatenate(([10], b[:stop - 1]))
        for s in (np.flatnonzero((before == 10) & (first >= 97) & (first <= 122)) + a).tolist():
            word = _WORD.match(data, s).group()
            marks.append((s, s + len(word), word.decode()))
    return marks


#: The first word from a position on.
_TOKEN = re.compile(rb"\s*(\S+)")


class _RecordLines:
    """The line of each record of one section, found only when a message needs one: the
    token reader reads the file again then (the fast reader keeps neither per-token lines nor
    the file's bytes: a mesh's checks run without them)."""

    def __init__(self, path: Path, section: str) -> None:
        self.path, self.section = path, section
        self._lines: np.ndarray | None = None

    def __getitem__(self, i):
        if self._lines is None:
            tokens = Tokens(self.path, keywords=MEDIT_KEYWORDS)
            self._lines = _read_medit_tokens(self.path, tokens)[self.section][1]
        return self._lines[i]


def _section_values(data: bytes, start: int, stop: int, count: int, width: int,
                    dtype: type) -> np.ndarray:
    """``count`` records of ``width`` numbers parsed from ``data[start:stop]`` in C
    (``np.fromstring``; float64 rounds like ``float()``), a chunk at a time, or
    :class:`_NotPlain` when it holds anything else."""
    if count * width > (stop - start + 1) // 2:
        raise _NotPlain  # more numbers than the section has room for (a digit and a space)
    values = np.empty(count * width, dtype=dtype)
    filled = 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a token that is not a number stops fromstring
        while start < stop:
            end = data.find(b"\n", min(start + _PARSE_CHUNK, stop), stop) + 1 or stop
            chunk = data[start:end]
            start = end
            if chunk.isspace():
                continue  # (fromstring makes a number, 0 or -1, of white space alone)
            try:
                part = np.fromstring(chunk, dtype=dtype, sep=" ")
            except (ValueError, DeprecationWarning):
                raise _NotPlain from None
            if filled + part.size > values.size:
                raise _NotPlain
            values[filled:filled + part.size] = part
            filled += part.size
    if filled != values.size:
        raise _NotPlain
    if dtype is not np.float64 and values.size and \
            (values.max() >= 2**62 or values.min() <= -2**62):
        raise _NotPlain  # (out of range either way; the token reader says so)
    return values.reshape(count, width)


def _read_medit_plain(path: Path, data: bytes) -> dict[str, tuple[np.ndarray, _RecordLines]]:
    """:func:`read_medit` of a plain file (ASCII, keywords at line starts, no comments, every
    section exactly its declared count of numbers) without a Python object per number.

    Raises
    ------
    _NotPlain
        Anything else: the token reader reads the file (and reports what is wrong).
    """
    if b"#" in data or b"\0" in data or not data.isascii():
        raise _NotPlain
    marks = _keyword_lines(data)
    if not marks or data[:marks[0][0]].strip():
        raise _NotPlain
    stops = [s for s, _, _ in marks[1:]] + [len(data)]
    dim, out = 3, {}
    for (_, end, word), stop in zip(marks, stops, strict=True):
        key = word.lower()
        if key == "end":
            if data[end:stop].strip() or stop != len(data):
                raise _NotPlain
            return out
        if key in ("meshversionformatted", "dimension"):
            words = data[end:stop].split()
            if len(words) != 1 or not words[0].isdigit() or \
                    int(words[0]) not in ((0, 1, 2, 3, 4) if key[0] == "m" else (3,)):
                raise _NotPlain
            continue
        width = _MEDIT_SECTIONS.get(key, 0)
        if width == 0 or key in out:
            raise _NotPlain
        if width < 0:
            width = dim + 1 if key == "vertices" else dim
        head = _TOKEN.match(data, end, stop)
        if head is None or not head.group(1).isdigit():
            raise _NotPlain
        dtype = np.float64 if key in ("vertices", "normals", "tangents") else np.int64
        values = _section_values(data, head.end(), stop, int(head.group(1)), width, dtype)
        out[key] = (values, _RecordLines(path, key))
    raise _NotPlain  # no End


def read_medit(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Parse an ASCII MEDIT file into ``{section: (records, lines)}``: a plain file in C
    (:func:`_read_medit_plain`), anything else token by token with line numbers."""
    data = read_file_bytes(path, "mesh")
    try:
        return _read_medit_plain(path, data)
    except _NotPlain:
        text = decode_text(data, path)
    del data  # (the text replaces it)
    return _read_medit_tokens(path, Tokens(path, text=text, keywords=MEDIT_KEYWORDS))


def _read_medit_tokens(path: Path, tk: Tokens) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Parse the tokens of an ASCII MEDIT file into ``{section: (records, lines)}``."""
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
            if is_number(word):
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


def medit_tet_mesh(path: Path) -> TetMesh:
    sec = read_medit(path)
    if "vertices" not in sec:
        raise InputError("no Vertices section", path=path)
    Xr, vlines = sec["vertices"]
    if "tetrahedra" not in sec or sec["tetrahedra"][0].shape[0] == 0:
        raise InputError("mesh has no tetrahedra (no or empty Tetrahedra section)", path=path)
    Tr, tlines = sec["tetrahedra"]
    _stages.debug("read mesh")
    T = Tr[:, :4]
    T -= 1  # (in place: the parser's records are this function's own)
    return validate_tet_mesh(Xr[:, :3], T, path=path, vertex_lines=vlines,
                             tet_lines=tlines, index_base=1)


#: A ``TetrahedraP2`` keyword at a line's start (any case).
_TETRAHEDRA_P2 = re.compile(rb"(?im)^[ \t]*tetrahedrap2\b")


def has_tetrahedra_p2(path: Path) -> bool:
    """Whether the MEDIT file ``path`` has a ``TetrahedraP2`` keyword (a byte scan, no
    parsing: a linear mesh is parsed once, by its own reader)."""
    try:
        return _TETRAHEDRA_P2.search(Path(path).read_bytes()) is not None
    except OSError:
        return False


def medit_p2_tets(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The vertices and 10-node tets of a MEDIT file's ``TetrahedraP2`` section.

    The node order of a record is MEDIT's (P. L. Georges, *Génération automatique de
    maillages*, 1994): the four corners, then the nodes of edges 12, 23, 13, 14, 24, 34 (1-based
    corners), which is VTK's ``tetra10`` and :data:`fem3d.mesh.element.TET_EDGES`.

    Returns
    -------
    X : (n, 3) float64
        Every vertex of the file.
    T : (m, 10) int64
        0-based.

    Raises
    ------
    InputError
        No vertices, no or an empty ``TetrahedraP2`` section, linear tetrahedra beside it,
        an index outside the vertices (naming the line), a non-finite coordinate.
    """
    sec = read_medit(path)
    if "vertices" not in sec:
        raise InputError("no Vertices section", path=path)
    X, vlines = sec["vertices"]
    if "tetrahedrap2" not in sec or sec["tetrahedrap2"][0].shape[0] == 0:
        raise InputError("mesh has no 10-node tetrahedra (no or empty TetrahedraP2 section)",
                         path=path)
    if "tetrahedra" in sec and sec["tetrahedra"][0].shape[0]:
        raise InputError("mesh mixes 4-node (Tetrahedra) and 10-node (TetrahedraP2) "
                         "tetrahedra", path=path)
    records, lines = sec["tetrahedrap2"]
    T = records[:, :10] - 1
    bad = ((T < 0) | (T >= X.shape[0])).any(axis=1)
    if bad.any():
        e = int(np.flatnonzero(bad)[0])
        v = int(records[e, :10][(T[e] < 0) | (T[e] >= X.shape[0])][0])
        raise InputError(f"TetrahedraP2 record {e + 1} refers to vertex {v}, outside "
                         f"1..{X.shape[0]}", path=path, line=int(lines[e]))
    finite = np.isfinite(X[:, :3]).all(axis=1)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise InputError(f"vertex {i + 1} has a non-finite coordinate", path=path,
                         line=int(vlines[i]))
    _stages.debug("read mesh")
    return np.ascontiguousarray(X[:, :3]), np.ascontiguousarray(T)


def medit_surface_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The surface of a MEDIT file: its Triangles and Quadrilaterals (split in two), else
    the boundary of its Tetrahedra; validated, 0-based."""
    sec = read_medit(path)
    if "vertices" not in sec:
        raise InputError("display mesh has no vertices", path=path)
    V, vlines = sec["vertices"]
    parts = []
    if "triangles" in sec:
        parts.append(sec["triangles"][0][:, :3] - 1)
    if "quadrilaterals" in sec:
        q = sec["quadrilaterals"][0][:, :4] - 1
        parts.append(q[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3))
    F = np.concatenate(parts) if parts else np.zeros((0, 3), np.int64)
    if F.shape[0] == 0 and "tetrahedra" in sec and sec["tetrahedra"][0].shape[0]:
        tm = medit_tet_mesh(path)
        V, F, vlines = np.asarray(tm.X), boundary_faces(tm.T), None
    return validate_surface_mesh(V[:, :3], F, path=path, vertex_lines=vlines, index_base=1)


def write_medit(path: Path, X: np.ndarray, T: np.ndarray) -> None:
    """Write vertices ``X`` (``(n, 3)`` float64) and tets ``T`` (``(m, 4)`` int64, 0-based)
    as MEDIT version 2 (double precision, 1-based, reference labels 0)."""
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("MeshVersionFormatted 2\nDimension 3\n")
        fh.write(f"Vertices\n{len(X)}\n")
        np.savetxt(fh, np.column_stack([X, np.zeros(len(X))]), fmt="%.17g %.17g %.17g %d")
        fh.write(f"Tetrahedra\n{len(T)}\n")
        np.savetxt(fh, np.column_stack([T + 1, np.zeros(len(T), np.int64)]), fmt="%d")
        fh.write("End\n")
