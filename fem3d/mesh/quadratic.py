"""Quadratic (P2) tet meshes: lifting a linear mesh and reading 10-node tets.

A P2 mesh has the nodes of :class:`fem3d.mesh.element.P2Tet`: each element's four corners,
then one node on each of its six edges (:data:`fem3d.mesh.element.TET_EDGES` order, VTK's
``tetra10``). :func:`lift_to_p2` makes one from any linear mesh (the edge nodes at the edges'
midpoints, each shared edge once); :func:`read_p2_mesh` reads the ``tetra10`` cells of a file
meshio reads (Gmsh ``.msh``: meshio maps Gmsh's node order to VTK's; ``.vtu``/``.vtk``) or
the ``TetrahedraP2`` section of a MEDIT ``.mesh`` (an own reader: meshio has none).
Whether the elements are valid (the Jacobian positive at every quadrature point) is the
model's check (:func:`fem3d.physics.model.build_model`).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from fem3d.errors import InputError
from fem3d.mesh.element import TET_EDGES, Element
from fem3d.mesh.medit import has_tetrahedra_p2, medit_p2_tets

__all__ = ["edge_nodes", "has_p2_cells", "lift_to_p2", "read_p2_mesh", "write_element_mesh"]


def edge_nodes(T: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The unique edges of tets ``T`` and each tet's edge numbers.

    Parameters
    ----------
    T : (m, 4) int64
        Tets over ``n`` vertices.
    n : int
        Number of vertices.

    Returns
    -------
    edges : (n_edges, 2) int64
        Each edge once, its smaller vertex first, sorted.
    tet_edges : (m, 6) int64
        The edge (row of ``edges``) of each tet's :data:`TET_EDGES`.
    """
    T = np.asarray(T, dtype=np.int64)
    pairs = np.sort(T[:, TET_EDGES], axis=2).reshape(-1, 2)  # (6 m, 2)
    keys, inverse = np.unique(pairs[:, 0] * np.int64(n) + pairs[:, 1], return_inverse=True)
    edges = np.stack(np.divmod(keys, np.int64(n)), axis=1)
    return edges, inverse.reshape(T.shape[0], 6)


def lift_to_p2(X: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A linear tet mesh as a P2 mesh: a node at the midpoint of every edge.

    Parameters
    ----------
    X : (n, 3) float64
        Vertices.
    T : (m, 4) int64
        Tets (positively oriented).

    Returns
    -------
    X2 : (n + n_edges, 3) float64
        ``X``, then the edge midpoints (in :func:`edge_nodes` order).
    T2 : (m, 10) int64
        The corners of ``T``, then the nodes of the tets' edges in :data:`TET_EDGES` order;
        an edge two tets share has one node.
    """
    X = np.asarray(X, dtype=np.float64)
    T = np.asarray(T, dtype=np.int64)
    if T.ndim != 2 or T.shape[1] != 4:
        raise ValueError(f"T must be (m, 4) to lift to P2, got {T.shape}")
    n = X.shape[0]
    edges, tet_edges = edge_nodes(T, n)
    mid = 0.5 * (X[edges[:, 0]] + X[edges[:, 1]])
    return np.concatenate([X, mid]), np.concatenate([T, n + tet_edges], axis=1)


def has_p2_cells(path: str | Path) -> bool:
    """Whether ``path`` is a file meshio reads that holds ``tetra10`` cells, or a MEDIT
    ``.mesh`` with a ``TetrahedraP2`` section (False for any other file: those are read as
    linear)."""
    p = Path(path)
    if p.suffix.lower() == ".mesh":
        return has_tetrahedra_p2(p)
    if p.suffix.lower() not in _MESHIO_SUFFIXES:
        return False
    try:
        st = p.stat()
    except OSError:
        return False
    return _has_p2_cells(str(p.resolve()), st.st_mtime_ns, st.st_size)


@lru_cache(maxsize=32)
def _has_p2_cells(path: str, mtime_ns: int, size: int) -> bool:
    """:func:`has_p2_cells` of one version of a file (read once)."""
    try:
        import meshio
        mesh = meshio.read(path)
    except Exception:  # noqa: BLE001 - not ours to read: the linear readers report it
        return False
    return any(c.type == "tetra10" for c in mesh.cells)


#: Volume formats read through meshio that can hold ``tetra10`` cells.
_MESHIO_SUFFIXES = (".msh", ".vtu", ".vtk", ".xdmf", ".xmf")


def read_p2_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read the 10-node tets of a mesh file (through meshio; MEDIT's ``TetrahedraP2`` by
    :func:`fem3d.mesh.medit.medit_p2_tets`, which meshio does not read).

    Parameters
    ----------
    path : str or Path
        A Gmsh ``.msh``, VTK ``.vtu``/``.vtk`` or XDMF file with ``tetra10`` cells, or a
        MEDIT ``.mesh`` with a ``TetrahedraP2`` section.

    Returns
    -------
    X : (n, 3) float64
        The nodes the tets use (others dropped, renumbered in order).
    T : (m, 10) int64
        Corners then edge nodes (:data:`TET_EDGES` order).

    Raises
    ------
    InputError
        No ``tetra10`` cells, linear and quadratic tets mixed, an index out of range, a
        non-finite coordinate or an edge node that two tets number differently.
    """
    p = Path(path)
    if p.suffix.lower() == ".mesh":
        points, T = medit_p2_tets(p)
    else:
        points, T = _meshio_p2_cells(p)
    if T.min() < 0 or T.max() >= points.shape[0]:
        e = int(np.flatnonzero(((T < 0) | (T >= points.shape[0])).any(axis=1))[0])
        raise InputError(f"10-node tet refers to node {int(T[e].max())}, outside "
                         f"[0, {points.shape[0]})", path=p, element=e)
    used, T = np.unique(T, return_inverse=True)
    T = T.reshape(-1, 10)
    X = np.ascontiguousarray(points[used])
    if not np.isfinite(X).all():
        raise InputError("node has a non-finite coordinate", path=p,
                         element=int(np.flatnonzero(~np.isfinite(X).all(axis=1))[0]))
    _check_shared_edges(T, p)
    return X, T


def _meshio_p2_cells(p: Path) -> tuple[np.ndarray, np.ndarray]:
    """The points ``(n, 3)`` and ``tetra10`` cells ``(m, 10)`` of a file meshio reads."""
    import meshio

    try:
        mesh = meshio.read(p)
    except Exception as exc:  # noqa: BLE001 - meshio raises many kinds
        raise InputError(f"cannot read a quadratic tet mesh: {exc}", path=p) from None
    blocks = [np.asarray(c.data) for c in mesh.cells if c.type == "tetra10"]
    if not blocks:
        raise InputError("mesh has no 10-node (tetra10) tetrahedra", path=p)
    if any(c.type == "tetra" for c in mesh.cells):
        raise InputError("mesh mixes 4-node and 10-node tetrahedra", path=p)
    T = np.concatenate(blocks).astype(np.int64)
    points = np.asarray(mesh.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] < 3:
        points = np.pad(points, ((0, 0), (0, 3 - points.shape[1])))
    return points[:, :3], T


def _check_shared_edges(T: np.ndarray, path: Path) -> None:
    """Refuse a mesh in which two tets give the same corner edge different edge nodes."""
    edges, tet_edges = edge_nodes(T[:, :4], int(T.max()) + 1)
    node = np.full(edges.shape[0], -1, dtype=np.int64)
    node[tet_edges.reshape(-1)] = T[:, 4:].reshape(-1)
    bad = node[tet_edges] != T[:, 4:]
    if bad.any():
        e = int(np.flatnonzero(bad.any(axis=1))[0])
        raise InputError("10-node tet has an edge node that a neighbour on the same edge "
                         "numbers differently (not a conforming P2 mesh)", path=path, element=e)


def write_element_mesh(path: str | Path, X: np.ndarray, T: np.ndarray, element: Element,
                       point_data: dict[str, np.ndarray] | None = None) -> None:
    """Write a mesh of ``element`` cells through meshio (VTU: ``tetra10`` is VTK's quadratic
    tetrahedron, which ParaView draws curved).

    Parameters
    ----------
    path : str or Path
        Any volume format meshio writes (``.vtu``, ``.msh``, ...).
    X : (n, 3) float64
        Node positions (deformed or rest).
    T : (m, element.n_nodes) int64
    element : Element
        Gives the cell type (:attr:`Element.cell_type`).
    point_data : dict, optional
        Per-node arrays (a displacement ``(n, 3)``, ...).
    """
    import meshio

    meshio.write(Path(path), meshio.Mesh(np.asarray(X, dtype=np.float64),
                                         [(element.cell_type, np.asarray(T, dtype=np.int64))],
                                         point_data=point_data or {}))
