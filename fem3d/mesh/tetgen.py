"""TetGen ``.node`` / ``.ele`` tet meshes: either file or their common stem; 0- or 1-based,
detected from the ``.node`` file's first index.

- :func:`tetgen_tet_mesh` - the validated mesh (errors name the file and line).
- :func:`write_tetgen` - both files, 0-based.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fem3d.errors import InputError
from fem3d.io.files import check_input_file
from fem3d.mesh.tetmesh import TetMesh, validate_tet_mesh
from fem3d.mesh.textscan import Tokens

__all__ = ["tetgen_paths", "tetgen_tet_mesh", "write_tetgen"]

_stages = logging.getLogger("fem3d.stages")  # stage marks (fem3d run --profile)


def tetgen_paths(path: Path) -> tuple[Path, Path]:
    """``(stem.node, stem.ele)`` of a ``.node``, ``.ele`` or stem path."""
    suffix = path.suffix.lower()
    if suffix in (".node", ".ele"):
        stem = path.with_suffix("")
    else:
        stem = path
    return Path(str(stem) + ".node"), Path(str(stem) + ".ele")


def _header(tk: Tokens, names: Sequence[str], defaults: Sequence[int]) -> list[int]:
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


def tetgen_tet_mesh(path: Path) -> TetMesh:
    """The validated tet mesh of a TetGen pair (``path``: either file or the stem)."""
    node_path, ele_path = tetgen_paths(path)
    for p in (node_path, ele_path):
        if not p.exists() and not p.is_symlink():
            raise InputError(f"file not found (TetGen meshes need both {node_path.name} and "
                             f"{ele_path.name})", path=p)
        check_input_file(p, "mesh")
    tk = Tokens(node_path)
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

    te = Tokens(ele_path)
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


def write_tetgen(path: Path, X: np.ndarray, T: np.ndarray) -> None:
    """Write vertices ``X`` and tets ``T`` (0-based) as ``.node`` and ``.ele`` beside
    ``path`` (either file or the stem)."""
    node_path, ele_path = tetgen_paths(path)
    with open(node_path, "w", encoding="utf-8") as fh:
        fh.write(f"{len(X)} 3 0 0\n")
        np.savetxt(fh, np.column_stack([np.arange(len(X)), X]), fmt="%d %.17g %.17g %.17g")
    with open(ele_path, "w", encoding="utf-8") as fh:
        fh.write(f"{len(T)} 4 0\n")
        np.savetxt(fh, np.column_stack([np.arange(len(T)), T]), fmt="%d")
