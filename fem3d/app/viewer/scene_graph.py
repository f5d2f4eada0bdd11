"""The viewer's scene nodes: the displayed mesh, the obstacles and the pull's spring.

:class:`SceneGraph` owns the viser handles of what the simulation shows and is used by the
simulation thread only (:mod:`fem3d.app.viewer.app`): it adds, replaces and moves nodes, so a
handle that was replaced (mesh mode or scene switch) is never written after its removal.
The geometry it draws (plane squares, grid lines, spring segments, a mesh's surface) comes
from :mod:`fem3d.app.viewer.logic`, which needs no viser.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from fem3d.app.viewer.colour import SurfaceColouring
from fem3d.app.viewer.logic import (
    PullState,
    _surface_faces,
    plane_grid_segments,
    plane_quad,
    spring_segments,
)

__all__ = ["SceneGraph"]

OBSTACLE_COLOR = (150, 150, 150)
PLANE_GRID_COLOR = (90, 90, 90)

SKIN_COLOR = (236, 196, 150)
SIM_COLOR = (90, 160, 230)
SPRING_COLOR = (220, 40, 40)


class SceneGraph:
    """The scene nodes of one viewer (simulation thread only).

    Parameters
    ----------
    server : viser.ViserServer
        Where the nodes live.

    Attributes
    ----------
    mesh_mode : {"skin", "sim", None}
        The mesh shown (None before the first :meth:`rebuild_mesh`).
    mesh_serial : int
        Incremented whenever the mesh node is replaced (viser's handles compare their vertex
        arrays, so a replaced mesh is told apart by this number).
    obstacle_handles, plane_grid_handles : list
        The obstacles' mesh nodes (planes first, then mesh obstacles) and the planes' grid
        lines.
    """

    def __init__(self, server: Any) -> None:
        self.server = server
        self.mesh_handle: Any = None
        self.mesh_mode: str | None = None
        self.mesh_serial = 0
        self.spring_handle: Any = None
        self._spring_key: tuple[int, ...] | None = None
        self.obstacle_handles: list[Any] = []
        self._obstacle_shown: list[np.ndarray | None] = []  # None: static
        self.plane_grid_handles: list[Any] = []
        #: The surface's colour map (:mod:`fem3d.app.viewer.colour`; off: the plain colour).
        self.colouring = SurfaceColouring()

    def display_positions(self, sim: Any) -> np.ndarray:
        """``(n, 3)`` positions of the mesh shown: the skin's or the simulation mesh's."""
        if self.mesh_mode == "skin":
            return np.asarray(sim.skin_positions(), dtype=np.float64)
        return np.asarray(sim.q, dtype=np.float64)

    def rebuild_mesh(self, sim: Any, mode: str, on_drag: Callable[[Any], None]) -> None:
        """Replace the displayed mesh node by ``sim``'s skin (``mode = "skin"``) or its
        simulation mesh's surface; ``on_drag`` handles left-button drags on it."""
        if self.mesh_handle is not None:
            old, self.mesh_handle = self.mesh_handle, None
            old.remove()
        self.mesh_mode = mode
        self.mesh_serial += 1
        if self.colouring.active:  # a GLB: viser's plain meshes have one colour
            handle = self.server.scene.add_glb(
                f"/fem3d/{mode}_coloured", self.colouring.glb(sim, mode),
                cast_shadow=False, receive_shadow=False)
        elif mode == "skin":
            verts = np.asarray(sim.skin_positions(), dtype=np.float64)
            faces = np.asarray(sim.display_faces, dtype=np.uint32)
            handle = self.server.scene.add_mesh_simple(
                "/fem3d/skin", verts, faces, color=SKIN_COLOR, flat_shading=False,
                cast_shadow=False, receive_shadow=False,
            )
        else:
            verts = np.asarray(sim.q, dtype=np.float64)
            handle = self.server.scene.add_mesh_simple(
                "/fem3d/sim", verts, _surface_faces(sim), color=SIM_COLOR, flat_shading=True,
                cast_shadow=False, receive_shadow=False,
            )
        handle.on_drag("left")(on_drag)
        self.mesh_handle = handle

    def show_positions(self, sim: Any, verts: np.ndarray) -> None:
        """Move the mesh node to the display positions ``verts`` (coloured: the GLB of the
        current frame); inside ``server.atomic()``."""
        if self.colouring.active:
            self.mesh_handle.glb_data = self.colouring.glb(sim, self.mesh_mode or "sim")
        else:
            self.mesh_handle.vertices = verts.astype(np.float32)

    def rebuild_obstacles(self, sim: Any) -> None:
        """Draw the contact scene's obstacles: planes as squares three mesh diagonals wide
        (with grid lines), mesh obstacles at their current positions."""
        for h in self.obstacle_handles + self.plane_grid_handles:
            h.remove()
        self.obstacle_handles, self._obstacle_shown, self.plane_grid_handles = [], [], []
        contact = getattr(sim, "contact", None)
        if contact is None:
            return
        q = np.asarray(sim.q, dtype=np.float64)
        center = 0.5 * (q.min(axis=0) + q.max(axis=0))
        half = 1.5 * float(np.linalg.norm(q.max(axis=0) - q.min(axis=0)))
        scene = self.server.scene
        for k, plane in enumerate(contact.contact.planes):
            V, F = plane_quad(plane.point, plane.normal, center, half)
            self.obstacle_handles.append(scene.add_mesh_simple(
                f"/fem3d/obstacles/plane_{k}", V, F, color=OBSTACLE_COLOR, opacity=0.5,
                side="double", cast_shadow=False, receive_shadow=False))
            self._obstacle_shown.append(None)  # static
            seg = plane_grid_segments(plane.point, plane.normal, center, half)
            self.plane_grid_handles.append(scene.add_line_segments(
                f"/fem3d/obstacles/plane_{k}_grid", seg, PLANE_GRID_COLOR, thickness=1.0,
                thickness_units="screen"))
        for k, (_name, V, F) in enumerate(sim.obstacles()):
            V = np.asarray(V, dtype=np.float64)
            self.obstacle_handles.append(scene.add_mesh_simple(
                f"/fem3d/obstacles/mesh_{k}", V, np.asarray(F, dtype=np.uint32),
                color=OBSTACLE_COLOR, flat_shading=True, side="double", cast_shadow=False,
                receive_shadow=False))
            self._obstacle_shown.append(V.copy())

    def update_obstacles(self, sim: Any) -> None:
        """Move the mesh obstacles that moved (keyframed); inside ``server.atomic()``."""
        moving = [i for i, v in enumerate(self._obstacle_shown) if v is not None]
        if not moving:
            return
        for i, (_name, V, _F) in zip(moving, sim.obstacles(), strict=True):
            V = np.asarray(V, dtype=np.float64)
            if not np.array_equal(V, self._obstacle_shown[i]):
                self.obstacle_handles[i].vertices = V.astype(np.float32)
                self._obstacle_shown[i] = V.copy()

    def update_spring(self, pull: PullState | None, q: np.ndarray, generation: int) -> None:
        """Draw the pull's springs from ``q`` to the target (none: no pull, or a pull of an
        older ``generation`` of the simulation)."""
        if pull is None or pull.generation != generation or pull.ids.size == 0:
            if self.spring_handle is not None:
                self.spring_handle.remove()
                self.spring_handle = None
                self._spring_key = None
            return
        seg = spring_segments(q, pull.ids, pull.target)
        key = tuple(pull.ids.tolist())
        if self.spring_handle is None or self._spring_key != key:
            if self.spring_handle is not None:
                self.spring_handle.remove()
            self.spring_handle = self.server.scene.add_line_segments(
                "/fem3d/spring", seg, SPRING_COLOR, thickness=3.0, thickness_units="screen"
            )
            self._spring_key = key
        else:
            self.spring_handle.points = seg
