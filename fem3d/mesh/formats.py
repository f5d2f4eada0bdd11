"""Mesh file formats: the readers and writers of tet meshes and triangle surfaces, chosen by
the file's suffix. Each family of formats is a module of its own:

- :mod:`.medit` - MEDIT ``.mesh`` (ASCII, own parser, 1-based): tet meshes and surfaces.
- :mod:`.tetgen` - TetGen ``.node``/``.ele`` (either file or the stem; 0- or 1-based, from the
  ``.node`` file's first index): tet meshes.
- :mod:`.obj` - Wavefront ``.obj`` (own fast parser): surfaces.
- :mod:`.meshio_formats` - every other format meshio reads (Gmsh ``.msh``, ``.vtu``, ``.vtk``,
  ``.stl``, ``.off``, ``.ply``, ...): tet meshes and surfaces.

``read_tet_mesh(path) -> TetMesh`` and ``read_surface_mesh(path) -> (V, F)`` either return a
fully validated mesh or raise :class:`fem3d.errors.InputError` naming the file, the line and/or
element and what is wrong; lower-level exceptions (``ValueError``, ``UnicodeDecodeError``,
meshio's errors, ...) never escape and no half-read mesh is ever returned. Quads and polygons
of a surface are split into triangles.

The checks every reader applies (:func:`fem3d.mesh.tetmesh.validate_tet_mesh`,
:func:`fem3d.mesh.tetmesh.validate_surface_mesh`) and the orientation convention (tets come
back positively oriented) are in :mod:`fem3d.mesh.tetmesh`.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import meshio
import numpy as np

from fem3d.errors import InputError
from fem3d.io.files import check_input_file
from fem3d.mesh.medit import medit_surface_mesh, medit_tet_mesh, write_medit
from fem3d.mesh.meshio_formats import meshio_extensions, meshio_surface_mesh, meshio_tet_mesh
from fem3d.mesh.obj import read_obj, write_obj
from fem3d.mesh.tetgen import tetgen_tet_mesh, write_tetgen
from fem3d.mesh.tetmesh import PathArg, TetMesh

__all__ = [
    "read_surface_mesh",
    "read_tet_mesh",
    "write_surface_mesh",
    "write_tet_mesh",
]

#: Surface formats meshio reads that are never tet meshes.
_SURFACE_ONLY = (".obj", ".stl", ".off", ".ply")


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
        :func:`~fem3d.mesh.tetmesh.validate_tet_mesh`).
    """
    p = _check_path(path)
    suffix = p.suffix.lower()
    if suffix in (".node", ".ele") or (not p.exists() and Path(str(p) + ".node").exists()):
        return replace(tetgen_tet_mesh(p), path=str(path))
    check_input_file(p, "mesh")
    if suffix == ".mesh":
        return medit_tet_mesh(p)
    if suffix in meshio_extensions() and suffix not in _SURFACE_ONLY:
        return meshio_tet_mesh(p)
    raise InputError(
        f"unknown tet-mesh file extension {p.suffix!r} (use .mesh, .node/.ele, .msh, .vtu, "
        "or another volume format meshio reads)", path=p,
    )


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
        return read_obj(p)
    if suffix == ".mesh":
        return medit_surface_mesh(p)
    if suffix in meshio_extensions() and suffix not in (".node", ".ele"):
        return meshio_surface_mesh(p)
    raise InputError(
        f"unknown surface-mesh file extension {p.suffix!r} (use .obj, .stl, .off, .ply, .mesh, "
        ".vtu, or another format meshio reads)", path=p,
    )


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
        write_medit(p, X, T)
    elif suffix in (".node", ".ele", ""):
        write_tetgen(p, X, T)
    else:
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
        write_obj(p, V, F, header)
    else:
        meshio.write(p, meshio.Mesh(np.asarray(V, np.float64), [("triangle", np.asarray(F))]))
