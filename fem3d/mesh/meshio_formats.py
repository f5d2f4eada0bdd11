"""Every other mesh format, through meshio (Gmsh ``.msh``, ``.vtu``, ``.vtk``, ``.stl``, ...).

meshio's failures (a parser's ``IndexError``, its ``print`` + ``sys.exit`` on a ReadError)
become one line naming the file and what is wrong with it (:func:`_parser_failure`).

- :func:`meshio_extensions` - the suffixes meshio reads.
- :func:`meshio_tet_mesh`, :func:`meshio_surface_mesh` - the validated meshes of a file.
"""

from __future__ import annotations

import contextlib
import io
import logging
import struct
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import meshio
import numpy as np

from fem3d.errors import InputError
from fem3d.io.files import check_input_file
from fem3d.mesh.tetmesh import TetMesh, boundary_faces, validate_surface_mesh, validate_tet_mesh

__all__ = ["meshio_extensions", "meshio_surface_mesh", "meshio_tet_mesh"]

_stages = logging.getLogger("fem3d.stages")  # stage marks (fem3d run --profile)


def meshio_extensions() -> set[str]:
    """The file suffixes meshio reads (``".msh"``, ...)."""
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


def meshio_tet_mesh(path: Path) -> TetMesh:
    """The validated tet mesh of a file meshio reads (linear tets only)."""
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


def meshio_surface_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The surface of a file meshio reads: its triangles and quads (split in two), else the
    boundary of its tets; validated, 0-based."""
    mesh, points = _meshio_read(path)
    cells = _meshio_cells(mesh, ["triangle", "quad", "tetra"])
    parts = []
    if "triangle" in cells:
        parts.append(cells["triangle"])
    if "quad" in cells:
        parts.append(cells["quad"][:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3))
    if parts:
        F = np.concatenate(parts)
    elif "tetra" in cells:
        tm = validate_tet_mesh(points, cells["tetra"], path=path)
        points, F = np.asarray(tm.X), boundary_faces(tm.T)
    else:
        F = np.zeros((0, 3), np.int64)
    if not np.issubdtype(F.dtype, np.integer):
        raise InputError("face indices are not integers", path=path)
    return validate_surface_mesh(points, F, path=path)
