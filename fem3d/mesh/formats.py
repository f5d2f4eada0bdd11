"""Mesh file formats: the readers and writers of tet meshes and triangle surfaces.

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

The checks every reader applies (:func:`fem3d.mesh.tetmesh.validate_tet_mesh`,
:func:`fem3d.mesh.tetmesh.validate_surface_mesh`) and the orientation convention (tets come
back positively oriented) are in :mod:`fem3d.mesh.tetmesh`.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import logging
import re
import struct
import warnings
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import meshio
import numpy as np

from fem3d.errors import InputError
from fem3d.io.files import check_input_file, read_text_file
from fem3d.mesh.tetmesh import (
    PathArg,
    TetMesh,
    _more,
    boundary_faces,
    validate_surface_mesh,
    validate_tet_mesh,
)
from fem3d.mesh.textscan import TokenSpans

__all__ = [
    "read_surface_mesh",
    "read_tet_mesh",
    "write_surface_mesh",
    "write_tet_mesh",
]

_stages = logging.getLogger("fem3d.stages")  # stage marks (fem3d run --profile)


# --------------------------------------------------------------------------------------
# text tokenizer shared by the MEDIT and TetGen readers
# --------------------------------------------------------------------------------------


class _Tokens:
    """Whitespace tokens of a text file with their 1-based line numbers."""

    def __init__(self, path: Path, comment: str = "#", text: str | None = None) -> None:
        self.path = path
        text = read_text_file(path, "mesh") if text is None else text
        if comment not in text and text.isascii():  # offsets, parsed in C by blocks
            spans = TokenSpans(text)
            self.tok: Sequence[str] = spans
            self.line, self.n_lines, self._spans = spans.line, spans.n_lines, spans
        else:
            lines = text.split("\n")
            if comment in text:
                lines = [ln.split(comment, 1)[0] for ln in lines]
            split = [ln.split() for ln in lines]
            counts = np.fromiter(map(len, split), dtype=np.int64, count=len(split))
            self.tok = list(itertools.chain.from_iterable(split))
            self.line = np.repeat(np.arange(1, len(lines) + 1, dtype=np.int64), counts)
            self.n_lines, self._spans = len(lines), None
        self.pos = 0
        if not len(self.tok):
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
        parsed = None if self._spans is None else self._spans.values(a, b, dtype)
        if parsed is not None:
            self.pos = b
            return parsed.reshape(count, width), self.line[a:b:width] if width else \
                np.zeros(0, dtype=np.int64)
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


class _NotPlain(Exception):
    """The fast MEDIT reader met something only the token reader handles (a comment, a
    malformed section, ...): that reader then reads the file and says what is wrong."""


#: A word at the start of a line.
_WORD = re.compile(r"\S*")


def _keyword_lines(text: str) -> list[tuple[int, int, str]]:
    """``(start, end, word)`` of every line's first word that starts with a letter (an ASCII
    text; a keyword after white space is left to the token reader: fromstring stops at it)."""
    b = np.frombuffer(text.encode("ascii"), dtype=np.uint8)
    starts = np.flatnonzero(b == 10) + 1
    starts = np.concatenate(([0], starts[starts < b.size]))
    lower = b[starts] | 0x20
    marks = []
    for s in starts[(lower >= ord("a")) & (lower <= ord("z"))].tolist():
        word = _WORD.match(text, s).group()
        marks.append((s, s + len(word), word))
    return marks


class _RecordLines:
    """The line of each record of one section, found only when a message needs one: the
    token reader re-reads the file then (the fast reader keeps no per-token lines)."""

    def __init__(self, path: Path, text: str, section: str) -> None:
        self.path, self.text, self.section = path, text, section
        self._lines: np.ndarray | None = None

    def __getitem__(self, i):
        if self._lines is None:
            self._lines = _read_medit_tokens(self.path, _Tokens(self.path, text=self.text)
                                             )[self.section][1]
        return self._lines[i]


def _section_values(body: str, count: int, width: int, dtype: type) -> np.ndarray:
    """``count`` records of ``width`` numbers parsed from ``body`` in C (``np.fromstring``;
    float64 rounds like ``float()``), or :class:`_NotPlain` when it holds anything else."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a token that is not a number stops fromstring
        try:
            values = np.fromstring(body, dtype=dtype, sep=" ")
        except (ValueError, DeprecationWarning):
            raise _NotPlain from None
    if values.size != count * width:
        raise _NotPlain
    if dtype is not np.float64 and values.size and np.abs(values).max() >= 2**62:
        raise _NotPlain  # (out of range either way; the token reader says so)
    return values.reshape(count, width)


def _read_medit_plain(path: Path, text: str) -> dict[str, tuple[np.ndarray, _RecordLines]]:
    """:func:`_read_medit` of a plain file (keywords at line starts, no comments, every
    section exactly its declared count of numbers) without a Python object per number.

    Raises
    ------
    _NotPlain
        Anything else: the token reader reads the file (and reports what is wrong).
    """
    if "#" in text or not text.isascii():
        raise _NotPlain
    marks = _keyword_lines(text)
    if not marks or text[:marks[0][0]].strip():
        raise _NotPlain
    stops = [s for s, _, _ in marks[1:]] + [len(text)]
    dim, out = 3, {}
    for (_, end, word), stop in zip(marks, stops, strict=True):
        key, body = word.lower(), text[end:stop]
        if key == "end":
            if body.strip() or stop != len(text):
                raise _NotPlain
            return out
        if key in ("meshversionformatted", "dimension"):
            words = body.split()
            if len(words) != 1 or not words[0].isdigit() or \
                    int(words[0]) not in ((0, 1, 2, 3, 4) if key[0] == "m" else (3,)):
                raise _NotPlain
            continue
        width = _MEDIT_SECTIONS.get(key, 0)
        if width == 0 or key in out:
            raise _NotPlain
        if width < 0:
            width = dim + 1 if key == "vertices" else dim
        head = body.split(None, 1)
        if not head or not head[0].isdigit() or (len(head) == 1 and int(head[0])):
            raise _NotPlain
        count = int(head[0])
        dtype = np.float64 if key in ("vertices", "normals", "tangents") else np.int64
        values = _section_values(head[1] if len(head) > 1 else "", count, width, dtype)
        out[key] = (values, _RecordLines(path, text, key))
    raise _NotPlain  # no End


def _read_medit(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Parse an ASCII MEDIT file into ``{section: (records, lines)}``: a plain file in C
    (:func:`_read_medit_plain`), anything else token by token with line numbers."""
    text = read_text_file(path, "mesh")
    try:
        return _read_medit_plain(path, text)
    except _NotPlain:
        return _read_medit_tokens(path, _Tokens(path, text=text))


def _read_medit_tokens(path: Path, tk: _Tokens) -> dict[str, tuple[np.ndarray, np.ndarray]]:
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
    _stages.debug("read mesh")
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
    _stages.debug("read mesh")
    return validate_tet_mesh(X, Tf.astype(np.int64) - base, path=ele_path, vertex_lines=vlines,
                             tet_lines=tlines, index_base=base)


# --------------------------------------------------------------------------------------
# meshio fallback
# --------------------------------------------------------------------------------------


def _meshio_extensions() -> set[str]:
    try:
        from meshio._helpers import extension_to_filetypes  # private API: guarded, see below
    except ImportError:  # pragma: no cover - meshio layout changed
        return {".msh", ".vtu", ".vtk", ".xdmf", ".inp", ".off", ".ply", ".stl"}
    return set(extension_to_filetypes)


def _meshio_read(path: Path):  # -> meshio.Mesh
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
        from meshio._helpers import _filetypes_from_path, reader_map  # private API: guarded
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
    _stages.debug("read mesh")
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
    text = read_text_file(path, "mesh")
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
    meshio.write(p, meshio.Mesh(np.asarray(V, np.float64), [("triangle", np.asarray(F))]))
