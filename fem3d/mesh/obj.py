"""Wavefront ``.obj`` surfaces, read by an own parser: ``v``, ``f a``, ``f a/b``, ``f a//c``,
``f a/b/c``, polygons (fan-triangulated) and negative (relative) indices.

Why an own parser: meshio 5.3's OBJ reader cannot read the shipped ``armadillo.obj`` at all
(it has 51986 ``vn`` lines for 26002 vertices); this one reads it in about 0.2 s, with the
line of every error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fem3d.errors import InputError
from fem3d.io.files import read_text_file
from fem3d.mesh.tetmesh import _more, validate_surface_mesh
from fem3d.mesh.textscan import is_number

__all__ = ["read_obj", "write_obj"]


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(V, F)`` of an OBJ file: validated, 0-based triangles."""
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
                if not is_number(t):
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


def write_obj(path: Path, V: np.ndarray, F: np.ndarray, header: str = "") -> None:
    """Write a triangle mesh (``F`` 0-based) as OBJ, ``header`` as comment lines on top."""
    with open(path, "w", encoding="utf-8") as fh:
        for ln in header.splitlines():
            fh.write(f"# {ln}\n")
        np.savetxt(fh, np.asarray(V, np.float64), fmt="v %.9g %.9g %.9g")
        np.savetxt(fh, np.asarray(F, np.int64) + 1, fmt="f %d %d %d")
