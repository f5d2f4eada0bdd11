"""The collision mesh: the bodies' boundary surface and the mesh obstacles as one
``ipctk.CollisionMesh``, and the maps between its vertices and fem3d's degrees of freedom.

The boundary surface of the simulation mesh (the element's
:meth:`~fem3d.mesh.element.Element.surface_triangles`: the boundary faces, each quadratic face
split into four linear triangles through its corner and edge nodes; interior nodes are not in
it) comes first, followed by the vertices and triangles of the
triangle-mesh obstacles (static, or kinematic: their positions are a function of time).
Collision vertex ``i < n_surface`` is fem3d vertex :attr:`CollisionGeometry.surface` ``[i]``;
the obstacles' vertices are not degrees of freedom. Which pairs can touch: different bodies
always; a body with itself only with ``self_contact``; obstacles never with each other (an
``ipctk.CollisionFilter`` over vertex groups, evaluated in C++). Planes are not in the mesh
(:mod:`.planes`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import ipctk
import numpy as np
import scipy.sparse as sp

from fem3d.mesh.element import ELEMENTS, Element
from fem3d.physics.contact.obstacles import MeshObstacle

__all__ = ["CollisionGeometry", "Entries", "group_chain"]


class Entries(NamedTuple):
    """COO triplets of a sparse matrix (duplicates summed later), without building a SciPy
    matrix: its construction checks the indices, which costs more than the contact blocks
    themselves on a Newton iteration."""

    row: np.ndarray
    col: np.ndarray
    data: np.ndarray

    def tocoo(self) -> Entries:
        """Itself (the duck type of ``scipy.sparse`` matrices' ``tocoo``)."""
        return self


def group_chain(groups: np.ndarray) -> np.ndarray:
    """Synthetic triangles ``(k, 3) int32`` that connect each group's vertices (a fan; a
    degenerate triangle for a pair): one connected component per group."""
    tris = [np.zeros((0, 3), dtype=np.int64)]
    for g in np.unique(groups):
        ids = np.flatnonzero(groups == g)
        if ids.size >= 3:
            tris.append(np.stack([np.full(ids.size - 2, ids[0]), ids[1:-1], ids[2:]],
                                 axis=1))
        elif ids.size == 2:
            tris.append(np.array([[ids[0], ids[1], ids[1]]]))
    return np.ascontiguousarray(np.concatenate(tris), dtype=np.int32)


class CollisionGeometry:
    """The collision mesh of one fem3d mesh and its mesh obstacles.

    Parameters
    ----------
    X : (n, 3) float64
        Rest positions of the simulation mesh (every body, concatenated).
    T : (m, k) int64
        Elements of ``element``, indexing ``X``.
    body_ids : (n,) int, optional
        Body of each vertex (default: all one body, 0).
    body_names : sequence of str, optional
        Names for messages (default ``"body 0"``, ...).
    meshes : sequence of MeshObstacle
    self_contact : bool
        Let a body touch itself.
    element : Element, optional
        The finite element of ``T`` (default P1), asked for the surface triangles.
    triangles : (f, 3) int64, optional
        The surface triangles when given (bodies of several elements); ``T`` is not asked.

    Attributes
    ----------
    surface : (n_surface,) int64
        fem3d vertex of each dynamic collision vertex.
    faces : (f, 3) int32
        The collision mesh's triangles (surface, then each mesh obstacle's).
    groups : (n_collision_vertices,) int64
        Body of each collision vertex (-1: an obstacle's).
    mesh : ipctk.CollisionMesh
        Every surface and mesh obstacle (no planes), with the filter of the pairs that can
        touch.
    bbox_diagonal : float
        Diagonal of the scene's bounding box (bodies and mesh obstacles at rest).
    dof : (3 n_collision_vertices,) int64
        fem3d DOF of each collision DOF (-1: an obstacle's).
    obstacles_at : (n_collision_vertices - n_surface, 3) float64
        Where the mesh obstacles are now (:meth:`set_time`).
    """

    def __init__(self, X: np.ndarray, T: np.ndarray, *, body_ids: np.ndarray | None = None,
                 body_names: Sequence[str] | None = None,
                 meshes: Sequence[MeshObstacle] = (), self_contact: bool = False,
                 element: Element = ELEMENTS["p1"],
                 triangles: np.ndarray | None = None) -> None:
        X = np.ascontiguousarray(X, dtype=np.float64)
        n = X.shape[0]
        self.n_vertices = n
        self.meshes = tuple(meshes)
        self.self_contact = bool(self_contact)
        if body_ids is None:
            body_ids = np.zeros(n, dtype=np.int64)
        body_ids = np.asarray(body_ids, dtype=np.int64).reshape(-1)
        if body_ids.shape != (n,):
            raise ValueError(f"body_ids must be ({n},), got {body_ids.shape}")
        self.body_ids = body_ids
        self.body_names = (list(body_names) if body_names is not None else
                           [f"body {i}" for i in range(int(body_ids.max()) + 1 if n else 0)])
        # dynamic part: the boundary surface, renumbered
        F = (element.surface_triangles(np.ascontiguousarray(T, dtype=np.int64))
             if triangles is None else np.asarray(triangles, dtype=np.int64))
        self.surface = surface = np.unique(F)
        renum = np.full(n, -1, dtype=np.int64)
        renum[surface] = np.arange(surface.size)
        faces, verts, groups = [renum[F]], [X[surface]], [body_ids[surface]]
        # kinematic / static meshes
        offset = surface.size
        self.mesh_offsets: list[int] = []
        for m in self.meshes:
            faces.append(m.faces + offset)
            verts.append(m.vertices)
            groups.append(np.full(m.vertices.shape[0], -1, dtype=np.int64))
            self.mesh_offsets.append(offset)
            offset += m.vertices.shape[0]
        self.n_surface = surface.size
        self.n_collision_vertices = offset
        self.faces = Fc = np.ascontiguousarray(np.concatenate(faces), dtype=np.int32)
        self.rest = V0 = np.asfortranarray(np.concatenate(verts))
        self.groups = np.concatenate(groups)
        self.mesh = ipctk.CollisionMesh(V0, ipctk.edges(Fc), Fc)
        self.mesh.can_collide = self._filter(self.groups)
        pts = np.concatenate([X] + [m.vertices for m in self.meshes])
        self.bbox_diagonal = float(np.linalg.norm(np.ptp(pts, axis=0))) if pts.size else 1.0
        dof = np.full((offset, 3), -1, dtype=np.int64)
        dof[: surface.size] = 3 * surface[:, None] + np.arange(3)
        self.dof = dof.reshape(-1)
        self.n_dyn_dofs = 3 * surface.size
        self.obstacles_at = self.rest[surface.size:].copy()

    def _filter(self, groups: np.ndarray) -> ipctk.CollisionFilter:
        """Vertices of one group cannot touch: a group is one body (unless self-contact) or
        all the obstacles together."""
        if self.self_contact:
            return ipctk.make_static_obstacle_filter(self.n_surface)
        # ipctk's connected-components filter over synthetic faces chaining each group
        return ipctk.make_connected_components_filter(group_chain(groups))

    @property
    def can_touch(self) -> bool:
        """Whether two primitives of the mesh can touch at all (a lone body without
        self-contact cannot: it needs no mesh broad phase)."""
        return self.self_contact or np.unique(self.groups).size > 1

    # -- positions ----------------------------------------------------------------------------
    def obstacle_positions(self, t: float) -> np.ndarray:
        """Positions of every mesh obstacle's vertices at time ``t``, ``(k, 3)``."""
        if not self.meshes:
            return self.rest[self.n_surface:]
        return np.concatenate([m.positions(t) for m in self.meshes])

    def set_time(self, t: float) -> None:
        """Place the kinematic obstacles at time ``t``."""
        self.obstacles_at = np.asarray(self.obstacle_positions(t), dtype=np.float64)

    def collision_vertices(self, q: np.ndarray, obstacles: np.ndarray | None = None
                           ) -> np.ndarray:
        """Collision-mesh vertex positions ``(n_collision, 3)`` (Fortran order) of ``q``, the
        obstacles at ``obstacles`` (default: where they are now)."""
        q3 = np.asarray(q, dtype=np.float64).reshape(-1, 3)
        obs = self.obstacles_at if obstacles is None else obstacles
        V = np.empty((self.n_collision_vertices, 3), order="F")
        V[: self.n_surface] = q3[self.surface]
        V[self.n_surface:] = obs
        return V

    # -- maps to fem3d DOFs -------------------------------------------------------------------
    def to_full_vector(self, g: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Add the collision-DOF vector ``g`` to ``out`` (``(3n,)``; default zeros) on the
        bodies' DOFs (obstacles' rows dropped)."""
        if out is None:
            out = np.zeros(3 * self.n_vertices)
        out[self.dof[: self.n_dyn_dofs]] += g[: self.n_dyn_dofs]
        return out

    def to_full_matrix(self, Hs: Sequence, triplets: bool = False):
        """The collision-DOF matrices ``Hs`` (sparse or :class:`Entries`) in full DOFs, as
        one COO matrix or (``triplets``) :class:`Entries`."""
        N = 3 * self.n_vertices
        rows, cols, vals = [], [], []
        nd = self.n_dyn_dofs
        for H in Hs:
            H = H.tocoo()
            keep = (H.row < nd) & (H.col < nd)
            rows.append(self.dof[H.row[keep]])
            cols.append(self.dof[H.col[keep]])
            vals.append(H.data[keep])
        if triplets:
            if not rows:
                return Entries(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
            return Entries(np.concatenate(rows), np.concatenate(cols), np.concatenate(vals))
        if not rows:
            return sp.coo_matrix((N, N))
        return sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                     np.concatenate(cols))), shape=(N, N))
