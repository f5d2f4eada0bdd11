"""Loads on a body's surface and nodes: dead tractions and point forces, follower pressure.

Each is a position :class:`~fem3d.physics.terms.base.Term` of the objective (so every
scheme, static's load stepping and the adjoint's forward pass see it), scaled over time by
an optional :class:`Amplitude` evaluated at the end of the step (``t + dt``: the time the
implicit schemes and ``static`` solve for).

* :class:`DeadLoad`: nodal forces ``f`` fixed in direction and size, potential ``-s(t) f .
  (q - X)``. A traction ``t`` (force per unit *reference* area) on the selected faces
  gives each face's vertices ``t A_f / 3`` (exact for linear triangles); on the 6-node faces
  of P2 tets each node gets ``t integral N_i dA`` (the generated ``pressure.p2_traction_weights``:
  corners 0 and edge nodes ``A_f / 3`` on a flat face); a point force ``F`` on selected
  vertices gives each ``F / k``.
* :class:`FollowerPressure`: pressure ``p`` on the selected faces of the *current* surface
  pushing against its outward normal (``p > 0`` pushes in), potential ``s(t) p (V(q) -
  V(X))`` with ``V`` the signed volume of the cones from the origin over the faces
  (``codegen/pressure.py``: the generated ``pressure`` kernels give the value, gradient and
  Hessian; on 6-node faces the ``p2_`` kernels, the cone volume over the curved quadratic
  triangle). On a closed loaded surface the force is exactly the consistent follower load
  (``-p/3`` of the area-weighted normals of the faces around each vertex; ``-p integral N_i
  n dA`` on 6-node faces); a pressure on an
  open patch has no potential, and this one's edge terms (:meth:`FollowerPressure.
  edge_forces`) must do no work: the scene refuses a patch whose edge is not held in their
  direction (it is where the edge slides in symmetry planes through the origin).

A face belongs to a selection when all its nodes do (3 on a P1 face, 6 on a P2 face).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from fem3d.errors import ParameterError
from fem3d.kernels.dispatch import kernel_module
from fem3d.physics.model import Model
from fem3d.physics.terms.base import HessianSink, StepMap, Term

__all__ = ["Amplitude", "DeadLoad", "FollowerPressure", "faces_within", "faces_among",
           "traction_forces", "point_forces"]


class Amplitude:
    """A load's scale over time: piecewise linear through ``(t_i, s_i)``, held outside.

    Parameters
    ----------
    times : (k,) float64
        Increasing.
    scales : (k,) float64
    """

    def __init__(self, times, scales) -> None:
        self.times = np.asarray(times, dtype=np.float64).reshape(-1)
        self.scales = np.asarray(scales, dtype=np.float64).reshape(-1)
        if self.times.size == 0 or self.times.shape != self.scales.shape or \
                not (np.isfinite(self.times).all() and np.isfinite(self.scales).all()) or \
                np.any(np.diff(self.times) <= 0):
            raise ParameterError("a load's keyframes need increasing times and finite scales")

    def __call__(self, t: float) -> float:
        return float(np.interp(t, self.times, self.scales))


def faces_within(faces: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """The faces ``(f, k)`` (``k`` = 3 or 6 nodes) whose nodes are all in ``vertices``."""
    mask = np.zeros(int(max(faces.max(initial=-1), vertices.max(initial=-1))) + 1, bool)
    mask[vertices] = True
    return faces[mask[faces].all(axis=1)]


def faces_among(faces: np.ndarray, others: np.ndarray) -> np.ndarray:
    """The rows of ``faces`` ``(f, k)`` that are faces of ``others`` ``(g, k)`` (the same
    corners, the first 3 nodes, in any order): e.g. the loaded faces of one rank's tets
    among its tets' boundary faces."""
    def corners(F: np.ndarray) -> np.ndarray:
        c = np.ascontiguousarray(np.sort(np.asarray(F, dtype=np.int64)[:, :3], axis=1))
        return c.view([("a", np.int64), ("b", np.int64), ("c", np.int64)]).reshape(-1)

    return faces[np.isin(corners(faces), corners(others))]


def traction_forces(X: np.ndarray, faces: np.ndarray, traction,
                    backend: str | None = None) -> np.ndarray:
    """``(3n,)`` consistent nodal forces of a traction ``(3,)`` per unit reference area.

    Parameters
    ----------
    X : (n, 3) float64
        Rest positions.
    faces : (f, 3) or (f, 6) int64
        Linear faces (each vertex gets ``t A_f / 3``) or the 6-node faces of P2 tets (each
        node gets ``t integral N_i dA``, the generated ``pressure.p2_traction_weights``).
    traction : (3,) float
    backend : str, optional
        The kernels' back end (6-node faces).
    """
    faces = _face_array(faces)
    x = X[faces]
    if faces.shape[1] == 6:
        weights = kernel_module("pressure", backend).p2_traction_weights(x)
    else:
        area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
        weights = np.repeat(area / 3.0, 3)
    f = np.zeros_like(X)
    np.add.at(f, faces.reshape(-1), weights.reshape(-1)[:, None] *
              np.asarray(traction, dtype=np.float64))
    return f.reshape(-1)


def _face_array(faces: np.ndarray) -> np.ndarray:
    """``faces`` as ``(f, 3)`` or ``(f, 6)`` int64 (ValueError otherwise)."""
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    if faces.ndim != 2 or faces.shape[1] not in (3, 6):
        raise ValueError(f"faces must be (f, 3) or (f, 6) node indices, got {faces.shape}")
    return faces


def point_forces(n_vertices: int, vertices: np.ndarray, force) -> np.ndarray:
    """``(3n,)`` nodal forces: the total ``force (3,)`` split evenly over ``vertices``."""
    f = np.zeros((n_vertices, 3))
    f[vertices] = np.asarray(force, dtype=np.float64) / vertices.size
    return f.reshape(-1)


class _TimedLoad(Term):
    """A position term scaled by an :class:`Amplitude` at each step's end time."""

    def __init__(self, amplitude: Amplitude | None) -> None:
        self.amplitude = amplitude
        self.scale = 1.0 if amplitude is None else amplitude(0.0)

    def begin_step(self, step: StepMap) -> None:
        self.at_time(step.t + step.dt)

    def at_time(self, t: float) -> None:
        """Scale the load to its amplitude at time ``t`` (the end of the step a scheme
        solves for; :meth:`begin_step` for the minimising schemes)."""
        if self.amplitude is not None:
            self.scale = self.amplitude(t)

    def hessian_data(self, q: np.ndarray, scale: float | None = None) -> np.ndarray | None:
        """``(nnz,)`` the Hessian at ``q`` as CSR data on ``model.pattern``; None: zero (a
        dead load)."""
        return None


class DeadLoad(_TimedLoad):
    """Nodal forces ``s(t) f`` that keep their direction: ``-s(t) f . (q - X)``.

    Parameters
    ----------
    model : Model
    force : (3n,) float64
        The nodal forces at scale 1 (:func:`traction_forces`, :func:`point_forces`).
    amplitude : Amplitude, optional
        None: constant.
    name : str, optional
        What statistics and errors call it (the scene key).
    """

    name = "dead load"

    def __init__(self, model: Model, force: np.ndarray, amplitude: Amplitude | None = None,
                 name: str = "dead load") -> None:
        super().__init__(amplitude)
        self.model = model
        self.force = np.asarray(force, dtype=np.float64).reshape(-1)
        self.force.setflags(write=False)
        self.name = name
        self._X = model.X.reshape(-1)

    def applied(self) -> np.ndarray:
        """``(3n,)`` the forces now (at the last step's scale)."""
        return self.scale * self.force

    def energy(self, q: np.ndarray) -> float:
        return -self.scale * float(self.force @ (q - self._X))

    def gradient(self, q: np.ndarray) -> np.ndarray:
        return -self.scale * self.force

    def with_model(self, model: Model) -> DeadLoad:
        new = DeadLoad(model, self.force, self.amplitude, self.name)
        new.scale = self.scale
        return new


class _RestGeometry(NamedTuple):
    """What :class:`FollowerPressure`'s forces read of a model: rest positions, kernels."""

    X: np.ndarray
    backend: str | None

    @property
    def n_vertices(self) -> int:
        return self.X.shape[0]


class FollowerPressure(_TimedLoad):
    """Pressure ``s(t) p`` on ``faces`` of the current surface (see the module docstring).

    Parameters
    ----------
    model : Model
    faces : (f, 3) or (f, 6) int64
        Outward-oriented boundary faces (:meth:`fem3d.mesh.element.Element.boundary_faces`:
        3 corners, or 3 corners and the edge nodes ``ab, bc, ca`` of a P2 face).
    pressure : float
        ``p > 0`` pushes into the body.
    amplitude : Amplitude, optional
    name : str, optional
    """

    name = "pressure"
    energy_scale = 0.0

    def __init__(self, model: Model, faces: np.ndarray, pressure: float,
                 amplitude: Amplitude | None = None, name: str = "pressure") -> None:
        super().__init__(amplitude)
        self.model = model
        self.faces = _face_array(faces)
        self.pressure = float(pressure)
        self.name = name
        kernels = kernel_module("pressure", model.backend)
        prefix = "p2_" if self.faces.shape[1] == 6 else ""
        self._energy, self._gradient, self._hessian = (
            getattr(kernels, prefix + k) for k in ("energy", "gradient", "hessian"))
        self._kernels = kernels
        self._dofs = (3 * self.faces[:, :, None] + np.arange(3)).reshape(
            len(self.faces), 3 * self.faces.shape[1])  # no faces: one rank's share may have none
        self._V0 = self.volume(model.X.reshape(-1))
        self._slots: np.ndarray | None = None
        x = model.X[self.faces]
        area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
        self.energy_scale = abs(self.pressure) * float(area.sum()) * \
            float(np.linalg.norm(np.ptp(model.X, axis=0)))

    def _params(self) -> tuple[float]:
        return (self.scale * self.pressure,)

    def volume(self, q: np.ndarray) -> float:
        """``V(q)``: the signed volume of the cones from the origin over the faces."""
        return float(self._energy(self._x(q), (1.0,)).sum())

    def _x(self, q: np.ndarray) -> np.ndarray:
        return np.asarray(q, dtype=np.float64).reshape(-1, 3)[self.faces]

    def energy(self, q: np.ndarray) -> float:
        return self.scale * self.pressure * (self.volume(q) - self._V0)

    def gradient(self, q: np.ndarray) -> np.ndarray:
        g = self._gradient(self._x(q), self._params())
        return np.bincount(self._dofs.reshape(-1), weights=g.reshape(-1),
                           minlength=3 * self.model.n_vertices)

    def consistent_load(self, q: np.ndarray, scale: float | None = None) -> np.ndarray:
        """``(3n,)`` the follower load of the pressure on the faces at ``q``: ``-s p A_f n_f /
        3`` on each face's vertices (``-s p integral N_i n dA`` on 6-node faces: the generated
        ``pressure.p2_follower_load``); ``scale``: ``s`` (None: the last step's)."""
        x = self._x(q)
        p = (self.scale if scale is None else scale) * self.pressure
        if self.faces.shape[1] == 6:
            load = p * self._kernels.p2_follower_load(x).reshape(-1, 3)
        else:
            area_normals = 0.5 * np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
            load = np.repeat(-p / 3.0 * area_normals, 3, axis=0)
        out = np.zeros((self.model.n_vertices, 3))
        np.add.at(out, self.faces.reshape(-1), load)
        return out.reshape(-1)

    def applied(self, q: np.ndarray) -> np.ndarray:
        """``(3n,)`` the pressure's nodal forces at ``q``: :meth:`consistent_load` (minus
        :meth:`gradient` on a closed loaded surface; on an open patch without the potential's
        edge forces, which only held DOFs take)."""
        return self.consistent_load(q)

    def reaction_gradient(self, q: np.ndarray) -> np.ndarray:
        """``(3n,)`` what the pins' reactions count of this term: minus the follower load
        (:meth:`gradient` less the edge forces: a pin holding an open patch's edge reports
        the physical reaction, not the potential's edge forces)."""
        return -self.consistent_load(q)

    @classmethod
    def rest_edge_forces(cls, X: np.ndarray, faces: np.ndarray, pressure: float,
                         backend: str | None = None) -> np.ndarray:
        """:meth:`edge_forces` of ``pressure`` on ``faces`` of the rest positions ``X``
        ``(n, 3)`` without a model (a scene's whole patch, checked on an MPI rank that
        holds part of it)."""
        return cls(_RestGeometry(np.asarray(X, dtype=np.float64), backend), faces,
                   pressure).edge_forces()

    def edge_forces(self) -> np.ndarray:
        """``(3n,)`` at rest and scale 1: the potential's forces less the consistent follower
        load (:meth:`consistent_load`; zero on a closed loaded surface; on an open patch, the
        forces along its edge that only held DOFs may take)."""
        X = self.model.X.reshape(-1)
        scale, self.scale = self.scale, 1.0
        potential = -self.gradient(X)
        self.scale = scale
        return potential - self.consistent_load(X, 1.0)

    def hessian_data(self, q: np.ndarray, scale: float | None = None) -> np.ndarray:
        """``(nnz,)`` the Hessian at ``q`` as CSR data on ``model.pattern`` (``scale``: the
        amplitude's value to use; None: the last step's)."""
        s = self.scale if scale is None else scale
        H = self._hessian(self._x(q), (s * self.pressure,))
        return np.bincount(self._pattern_slots(), weights=H.reshape(-1),
                           minlength=self.model.nnz)

    def add_hessian(self, q: np.ndarray, sink: HessianSink) -> None:
        sink.add_pattern_values(self.hessian_data(q), sink.position_scale)

    def _pattern_slots(self) -> np.ndarray:
        """Where each face Hessian entry goes in ``model.pattern``'s data (built once: a
        face's nodes share a tet, so every entry is in the pattern)."""
        if self._slots is None:
            P = self.model.pattern
            index = P.copy()
            index.data = np.arange(1, P.nnz + 1, dtype=np.float64)
            rows = np.repeat(self._dofs, self._dofs.shape[1], axis=1).reshape(-1)
            cols = np.tile(self._dofs, (1, self._dofs.shape[1])).reshape(-1)
            if rows.size == 0:  # no faces (a rank's share may have none)
                self._slots = np.zeros(0, dtype=np.int64)
                return self._slots
            slots = np.asarray(index[rows, cols]).reshape(-1).astype(np.int64) - 1
            if np.any(slots < 0):
                raise ParameterError(f"{self.name}: a loaded face is not a face of a tet")
            self._slots = slots
        return self._slots

    def with_model(self, model: Model) -> FollowerPressure:
        new = FollowerPressure(model, self.faces, self.pressure, self.amplitude, self.name)
        new.scale = self.scale
        return new
