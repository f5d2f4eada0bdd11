"""The viewer's colour map: the body's surface coloured by von Mises stress or strain energy
density (issue 43), without viser.

A field is computed per element (:data:`FIELDS`: :func:`fem3d.physics.stress.element_stress`'s
von Mises stress, or each element's strain energy over its rest volume), averaged at the
nodes weighted by the elements' volumes, carried to the display vertices (the skin's, by its
skinning matrix: ``W @ nodal``; the simulation mesh's surface: the nodes themselves) and
mapped to colours over ``[0, max]`` of the current frame (:func:`colours`, a viridis-like
ramp). viser's plain meshes carry one colour, so a coloured surface is sent as a GLB with
vertex colours (:func:`coloured_glb`); :func:`legend` is the panel's line for the range.
"""

from __future__ import annotations

import io
from collections.abc import Callable
from typing import Any

import numpy as np

from fem3d.physics.assembly import element_energies
from fem3d.physics.model import Model
from fem3d.physics.stress import element_stress, node_weights

__all__ = ["FIELDS", "NONE", "RAMP", "SurfaceColouring", "colours", "coloured_glb",
           "display_values", "element_field", "legend", "nodal_average"]

#: The choice that shows the plain surface.
NONE = "none"


def _von_mises(model: Model, q: np.ndarray) -> np.ndarray:
    return element_stress(model, q).von_mises


def _energy_density(model: Model, q: np.ndarray) -> np.ndarray:
    return element_energies(model, q) / model.element_volumes()


#: The colour fields by the name the panel shows: ``(unit label, per-element values (m,))``.
FIELDS: dict[str, tuple[str, Callable[[Model, np.ndarray], np.ndarray]]] = {
    "von Mises stress": ("Pa", _von_mises),
    "strain energy density": ("J/m³", _energy_density),
}

#: The colour ramp: RGB stops at equal spacing from 0 to the frame's largest value
#: (viridis's, sampled at 0, 1/4, 1/2, 3/4, 1).
RAMP = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]],
                dtype=np.float64)


def element_field(model: Model, q: np.ndarray, name: str) -> np.ndarray:
    """``(m,)`` the field ``name`` (a key of :data:`FIELDS`) of every element at ``q``."""
    if name not in FIELDS:
        raise ValueError(f"unknown colour field {name!r}; choose from {', '.join(FIELDS)}")
    return np.asarray(FIELDS[name][1](model, np.asarray(q, dtype=np.float64)),
                      dtype=np.float64)


def nodal_average(model: Model, values: np.ndarray) -> np.ndarray:
    """``(n,)`` the per-element ``values (m,)`` averaged at each node, weighted by the
    elements' volumes (a node of no element gets 0)."""
    k, w, idx = node_weights(model)
    total = np.bincount(idx, weights=w, minlength=model.n_vertices)
    out = np.bincount(idx, weights=w * np.repeat(values, k), minlength=model.n_vertices)
    return np.divide(out, total, out=np.zeros_like(out), where=total > 0)


def display_values(model: Model, q: np.ndarray, name: str, skinning: Any = None) -> np.ndarray:
    """``(k,)`` the field at the display vertices: the nodes' averages, through the sparse
    skinning matrix ``(k, n)`` when the skin is shown (None: the simulation mesh)."""
    nodal = nodal_average(model, element_field(model, q, name))
    return nodal if skinning is None else np.asarray(skinning @ nodal).reshape(-1)


def colours(values: np.ndarray, top: float) -> np.ndarray:
    """``(k, 3) uint8``: ``values`` on :data:`RAMP` over ``[0, top]`` (clipped; a zero or
    non-finite ``top`` shows the ramp's start)."""
    v = np.asarray(values, dtype=np.float64)
    s = np.clip(v / top, 0.0, 1.0) if top > 0 and np.isfinite(top) else np.zeros_like(v)
    s = np.where(np.isfinite(s), s, 1.0) * (len(RAMP) - 1)
    i = np.minimum(s.astype(np.int64), len(RAMP) - 2)
    f = (s - i)[:, None]
    return np.rint(RAMP[i] * (1 - f) + RAMP[i + 1] * f).astype(np.uint8)


def legend(name: str, top: float) -> str:
    """The panel's line for the colour map's range (markdown)."""
    if name == NONE:
        return ""
    unit = FIELDS[name][0]
    stops = " → ".join(f"<span style='color:rgb{tuple(int(c) for c in rgb)}'>■</span>"
                       for rgb in RAMP)
    return f"**{name}**: 0 {stops} {top:.4g} {unit}"


def coloured_glb(vertices: np.ndarray, faces: np.ndarray, rgb: np.ndarray) -> bytes:
    """A GLB of the triangle mesh with vertex colours ``rgb (k, 3) uint8`` (trimesh)."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64),
                           np.asarray(faces, dtype=np.int64), process=False,
                           vertex_colors=np.column_stack([rgb, np.full(len(rgb), 255, np.uint8)]))
    with io.BytesIO() as buffer:
        mesh.export(buffer, file_type="glb")
        return buffer.getvalue()


class SurfaceColouring:
    """The viewer's choice of colour field and what it last drew (simulation thread only).

    Attributes
    ----------
    field : str
        :data:`NONE` or a key of :data:`FIELDS`.
    values : (k,) float64 or None
        The field at the display vertices of the last frame drawn.
    rgb : (k, 3) uint8 or None
        Their colours.
    top : float
        The ramp's upper end in the last frame (its largest value).
    legend_text : str
        :func:`legend` of the last frame (empty when off).
    """

    def __init__(self) -> None:
        self.field = NONE
        self.values: np.ndarray | None = None
        self.rgb: np.ndarray | None = None
        self.top = 0.0
        self.legend_text = ""

    @property
    def active(self) -> bool:
        """Whether the surface is coloured by a field."""
        return self.field != NONE

    def select(self, name: str) -> None:
        """Colour by ``name`` from the next frame on (:data:`NONE`: off)."""
        if name != NONE and name not in FIELDS:
            raise ValueError(f"unknown colour field {name!r}; choose from "
                             f"{', '.join((NONE, *FIELDS))}")
        self.field = name
        self.values = self.rgb = None
        self.top = 0.0
        self.legend_text = ""

    def glb(self, sim: Any, mode: str) -> bytes:
        """The GLB of ``sim``'s display mesh (``mode``: ``"skin"`` or ``"sim"``) coloured by
        the field at its current positions."""
        q = np.asarray(sim.q, dtype=np.float64)
        if mode == "skin":
            verts, faces = sim.skin_positions(), sim.display_faces
            values = display_values(sim.model, q, self.field, sim.skinning_matrix)
        else:
            verts, faces = q, sim.surface_faces
            values = display_values(sim.model, q, self.field)
        finite = values[np.isfinite(values)]
        self.top = float(finite.max()) if finite.size else 0.0
        self.values, self.rgb = values, colours(values, self.top)
        self.legend_text = legend(self.field, self.top)
        return coloured_glb(verts, faces, self.rgb)
