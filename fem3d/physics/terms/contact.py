"""IPC contact as objective terms: the barrier and the lagged friction of a
:class:`~fem3d.physics.contact.model.ContactModel`, and the group they form.

Barrier and friction share one contact set, one adaptive stiffness and one lagging per step,
so :class:`ContactTerm` groups them (:class:`~fem3d.physics.terms.base.TermGroup`): they
enter the objective as one sum, with each one's own hooks.
"""

from __future__ import annotations

import math

import ipctk
import numpy as np

from fem3d.errors import ParameterError, SimulationError
from fem3d.physics.contact.model import ContactModel
from fem3d.physics.contact.path import straight_path_is_free
from fem3d.physics.terms.base import HessianSink, NewtonPolicy, StepMap, Term, TermGroup

__all__ = ["BarrierTerm", "FrictionTerm", "ContactTerm", "NEWTON_STARTS", "FIRST_STEPS"]

#: Where a contact step's Newton starts when CCD cuts its free flight (:class:`BarrierTerm`).
NEWTON_STARTS = ("clamped", "q_t")
#: What IPC's stopping rule does with Newton's first direction: nothing ("confirm": the
#: first step is always taken and judged by a second direction) or judge it ("accept": one
#: that passes is taken and ends the solve; :attr:`NewtonPolicy.accept_first_step`).
FIRST_STEPS = ("confirm", "accept")


class BarrierTerm(Term):
    """IPC's log barrier over the contact pairs within ``dhat``, in positions ``q``
    (PSD-projected Hessian; ``max_step`` by CCD), with the hooks:

    * :meth:`begin_step` — obstacles to their end-of-step positions, the moving pins' and
      obstacles' own motion checked by CCD, the pattern hint;
    * :meth:`initialize_stiffness` — IPC's initial ``kappa`` when contact first appears;
    * :meth:`after_iteration` — IPC's adaptive ``kappa`` update (True when the objective
      changed);
    * :meth:`newton_converged` — IPC's velocity-based stopping: the Newton step's largest
      position change divided by ``dt`` is below ``tolerance * bbox_diagonal`` (per second).

    Parameters
    ----------
    contact : ContactModel
    tolerance : float, optional
        IPC's Newton tolerance, relative to the scene's bounding-box diagonal (per second).
    pattern_margin : float, optional
        When a contact block outside the solver's pattern appears (a re-analysis is due
        anyway), the pattern is widened also by the blocks of the mesh-mesh pairs closer
        than ``pattern_margin * dhat`` there, so that the contact region can spread without
        a re-analysis per new pair (0: only by the active blocks).
        ``python -m bench.contact`` measures it.
    newton_start : {"clamped", "q_t"}, optional
        Where Newton starts when CCD cuts the step's free flight (``v_t``): at ``v_t`` scaled
        back by CCD (``"clamped"``, the default) or at ``q_t`` (``"q_t"``: ``v = 0``, IPC's
        start; :attr:`NewtonPolicy.restart_when_clamped`).
    first_step : {"confirm", "accept"}, optional
        :data:`FIRST_STEPS`: whether a first Newton direction that already passes the
        stopping rule ends the solve once taken (``"accept"``) or is confirmed by a second
        one (``"confirm"``, the default).
    """

    name = "barrier"
    #: Newton runs to convergence (not to the contact-free scenes' 5-iteration cap).
    requires_convergence = True
    #: the adaptive stiffness changes the objective between iterates
    allows_lagged_matrix = False

    def __init__(self, contact: ContactModel, *, tolerance: float = 1e-3,
                 pattern_margin: float = 4.0, newton_start: str = "clamped",
                 first_step: str = "confirm") -> None:
        for key, value, allowed in (("newton_start", newton_start, NEWTON_STARTS),
                                    ("first_step", first_step, FIRST_STEPS)):
            if value not in allowed:
                raise ParameterError(f"contact.{key} must be one of {', '.join(allowed)}, "
                                     f"got {value!r}")
        #: a stiff barrier, and where Newton starts and stops by the scene's contact keys
        self.newton_policy = NewtonPolicy(stiff=True, restart_when_clamped=newton_start == "q_t",
                                          accept_first_step=first_step == "accept")
        tolerance = float(tolerance)
        if not (math.isfinite(tolerance) and tolerance > 0):
            raise ParameterError(f"contact.tolerance must be a finite number > 0, got "
                                 f"{tolerance}")
        self.contact = contact
        self.tolerance = tolerance
        self.pattern_margin = float(pattern_margin)
        self._dt = 1.0
        self._had_contact = False

    def energy(self, q: np.ndarray) -> float:
        return self.contact.barrier_energy(q)

    def gradient(self, q: np.ndarray) -> np.ndarray:
        return self.contact.barrier_gradient(q)

    def hessian(self, q: np.ndarray, covered=None, psd: bool = True):
        """Hessian as ``(rows, cols, values)`` triplets in full DOFs, PSD-projected per pair
        unless ``contact.hessian_projection = "exact"`` and Newton did not ask for a PSD
        matrix (``psd``; :meth:`ContactModel.projects`). When
        ``covered(rows, cols)`` (the solver's pattern holds those entries) says no, explicit
        zeros are added on the blocks of the pairs within the pattern margin at ``q`` (see
        :meth:`_pattern_hint`), so that the pattern, re-analysed now anyway, grows ahead of
        the contact set."""
        H = self.contact.barrier_hessian(q, project=self.contact.projects(psd), triplets=True)
        if covered is None or not self.contact.collisions.parts or self.pattern_margin <= 0 or \
                covered(H.row, H.col):  # planes' blocks are in the elastic pattern
            return H.row, H.col, H.data
        hint = self._pattern_hint(q)
        if hint is None:
            return H.row, H.col, H.data
        r, c = hint
        return (np.concatenate([H.row, r]), np.concatenate([H.col, c]),
                np.concatenate([H.data, np.zeros(r.size)]))

    def add_hessian(self, q: np.ndarray, sink: HessianSink) -> None:
        system = getattr(sink, "system", None)
        covered = getattr(system, "pattern_covers", None)
        sink.add_entries(self.hessian(q, covered, sink.psd), sink.position_scale)

    def max_step(self, q: np.ndarray, dq: np.ndarray) -> float:
        """CCD: the largest collision-free fraction of ``dq``."""
        q = np.asarray(q, dtype=np.float64).reshape(-1)
        return self.contact.max_step(q, q + np.asarray(dq, dtype=np.float64).reshape(-1))

    def begin_step(self, step_map: StepMap) -> None:
        """Prepare a step from ``(q_t, v_t)`` at time ``t`` whose Newton start is ``q_base``
        (``q_t`` with the pins at their end-of-step positions).

        Raises
        ------
        SimulationError
            A kinematic obstacle or the moving pins would pass through a body within the
            step (the message says which).
        """
        cm = self.contact
        t, dt, step = step_map.t, step_map.dt, step_map.step
        self._dt = float(dt)
        q_t = np.asarray(step_map.q_t, dtype=np.float64).reshape(-1)
        q_base = np.asarray(step_map.start_positions(), dtype=np.float64).reshape(-1)
        # the obstacles' motion over the step, the bodies held at q_t
        if cm.obstacle_step(q_t, t, t + dt) < 1.0:
            moving = ", ".join(m.name for m in cm.meshes if m.motion is not None)
            raise SimulationError(f"contact: the moving obstacle ({moving}) would pass through "
                                  "a body within one step (it may advance by less than its "
                                  "gap to the bodies per step); use a smaller dt or a slower "
                                  "motion", step=step)
        cm.set_time(t + dt)
        # the step's candidates: around its start, the pins' jump and the free flight
        # at the scheme's target velocity (where Newton starts, clamped); grown when an
        # iterate leaves them
        q_free = np.asarray(step_map.positions(step_map.v_hat_free), dtype=np.float64)
        cm.start_step(q_t, q_base, q_free)
        if not np.array_equal(q_base, q_t) and cm.max_step(q_t, q_base) < 1.0:
            raise SimulationError("contact: the moving pins would drive the surface through "
                                  "itself or an obstacle within one step; use a smaller dt",
                                  step=step)

    def _pattern_hint(self, q: np.ndarray):
        """``(rows, cols)`` of the 3 x 3 blocks between the vertices of each mesh-mesh pair
        closer than the margin ``pattern_margin * dhat`` at ``q`` (None without mesh-mesh
        contact). The solver's pattern is the union of the elastic one and every block seen
        so far, and is re-analysed only when a block appears that was never seen: widening
        it then by the pairs within a margin makes that rare. Whole blocks, read from the
        pairs' vertices: a barrier Hessian at the margin was 16 of the hint's 49 ms on the
        pile (32 ms now) and leaves out its exact zeros, which a pattern need not."""
        cm = self.contact
        parts = cm.collisions.parts
        if not parts or self.pattern_margin <= 0:
            return None
        V = cm.collision_vertices(q)
        margin = self.pattern_margin * cm.dhat
        pairs = []
        for part in parts:
            Vp = part.view(V)
            cands = cm.collisions.candidates_within(part, Vp, 0.5 * margin)
            col = ipctk.NormalCollisions()
            col.build(cands, part.mesh, Vp, margin)
            pairs += _vertex_pairs(col, part.mesh.edges, part.mesh.faces)
        if not pairs:
            return None
        return _block_entries(np.unique(np.concatenate(pairs)), cm)

    def initialize_stiffness(self, q: np.ndarray, grad_rest: np.ndarray,
                             average_mass: float) -> None:
        """IPC's initial ``kappa`` (adaptive stiffness only), from the gradient of the rest of
        the objective in positions (``grad_rest``, ``(3n,)``; fixed DOFs zeroed) and the mean
        vertex mass. In fem3d's objective (energy units, ``1/(2 dt^2) |x - x~|_M^2 + ...``)
        IPC's mass-based bounds scale with ``average_mass / dt^2``."""
        cm = self.contact
        if not cm.adaptive:
            return
        active = cm.n_active(q) > 0
        # once at the start, and again when contact (re)appears, as IPC does
        if not cm.barrier.initialized or (active and not self._had_contact):
            cm.initialize_stiffness(q, grad_rest, average_mass / (self._dt * self._dt))
        self._had_contact = active

    def after_iteration(self, q: np.ndarray) -> bool:
        """IPC's adaptive ``kappa`` update after a Newton iteration; True when it changed."""
        before = self.contact.kappa
        return self.contact.update_stiffness(q) != before

    def newton_converged(self, dq: np.ndarray) -> bool:
        """IPC's stopping rule on the Newton step's position change ``dq`` (``(3n,)``)."""
        dq = np.asarray(dq)
        if dq.size == 0:
            return True
        return float(np.abs(dq).max()) / self._dt < self.tolerance * self.contact.bbox_diagonal


class FrictionTerm(Term):
    """IPC's lagged friction (smoothed Coulomb, ``mu_s``/``mu_k``, static below ``eps_v dt``
    of slip): normal forces and tangent bases fixed at the step's start (:meth:`begin_step`),
    lagged again when the barrier's stiffness is set at Newton's start (the normal forces
    scale with it), and, with ``iterations > 1``, at each converged Newton solution until two
    solutions differ by less than ``tolerance`` (PolyFEM's friction iterations).

    Parameters
    ----------
    contact : ContactModel
    iterations : int, optional
        Newton solves per step at most (1: lagged once, at the step's start).
    tolerance : float, optional
        Re-lagging stops when a solve moves the positions by less than ``tolerance`` times
        the scene's bounding-box diagonal (largest vertex coordinate change).
    """

    name = "friction"
    allows_lagged_matrix = False

    def __init__(self, contact: ContactModel, *, iterations: int = 1,
                 tolerance: float = 1e-6) -> None:
        if int(iterations) < 1:
            raise ParameterError(f"contact.friction_iterations must be >= 1, got {iterations}")
        tolerance = float(tolerance)
        if not (math.isfinite(tolerance) and tolerance > 0):
            raise ParameterError(f"contact.friction_tolerance must be a finite number > 0, "
                                 f"got {tolerance}")
        self.contact = contact
        self.iterations, self.tolerance = int(iterations), tolerance
        self._lag: tuple[np.ndarray, float, float] | None = None
        self._basis: np.ndarray | None = None
        self._solves = 0
        self._kappa_at_lag = math.nan

    def energy(self, q: np.ndarray) -> float:
        return self.contact.friction_energy(q)

    def gradient(self, q: np.ndarray) -> np.ndarray:
        return self.contact.friction_gradient(q)

    def add_hessian(self, q: np.ndarray, sink: HessianSink) -> None:
        if self.contact.n_friction_pairs:
            H = self.contact.friction_hessian(q, project=self.contact.projects(sink.psd),
                                              triplets=True)
            sink.add_entries((H.row, H.col, H.data), sink.position_scale)

    def begin_step(self, step_map: StepMap) -> None:
        """Lag the friction at the step's start (obstacles where they are at ``t``)."""
        q_t = np.asarray(step_map.q_t, dtype=np.float64).reshape(-1)
        self._lag = (q_t, step_map.t, step_map.dt)
        self._basis, self._solves = None, 0
        self._relag()

    def _relag(self) -> None:
        q_t, t, dt = self._lag
        self.contact.lag_friction(q_t, dt, t_start=t, q_basis=self._basis)
        self._kappa_at_lag = self.contact.kappa

    def initialize_stiffness(self, q: np.ndarray, grad_rest: np.ndarray,
                             average_mass: float) -> None:
        """Lag again when the barrier's stiffness changed since this step's lagging."""
        cm = self.contact
        if self._lag is not None and cm.mu > 0 and cm.kappa != self._kappa_at_lag:
            self._relag()

    def relag(self, q: np.ndarray) -> bool:
        """Newton converged at ``q``: lag the normal forces and bases there and ask for
        another solve, unless the cap is reached, there is no friction, or ``q`` moved by
        less than the tolerance since the last solve."""
        self._solves += 1
        if self._solves >= self.iterations or self._lag is None or self.contact.mu == 0.0:
            return False
        q = np.asarray(q, dtype=np.float64).reshape(-1)
        if self._basis is not None:
            moved = float(np.abs(q - self._basis).max()) if q.size else 0.0
            if moved < self.tolerance * self.contact.bbox_diagonal:
                return False
        self._basis = q.copy()
        self._relag()
        return True

    @property
    def lagged_stiffness(self) -> float:
        """The barrier stiffness the current normal forces were lagged with (nan before the
        first step): the adaptive stiffness may change after the lagging within a step."""
        return self._kappa_at_lag


def _vertex_pairs(collisions: ipctk.NormalCollisions, edges: np.ndarray,
                  faces: np.ndarray) -> list[np.ndarray]:
    """Keys ``i * 2**32 + j`` of every ordered pair of collision-mesh vertices that share one
    of ``collisions`` (its 2-4 vertices: both ends, the edges', the face's)."""
    E, F = np.asarray(edges, dtype=np.int64), np.asarray(faces, dtype=np.int64)
    sets = []  # (k, 2-4) vertices of each kind's k pairs
    if len(vv := collisions.vv_collisions):
        sets.append(np.array([(c.vertex0_id, c.vertex1_id) for c in vv], np.int64))
    if len(ev := collisions.ev_collisions):
        ids = np.array([(c.edge_id, c.vertex_id) for c in ev], np.int64)
        sets.append(np.c_[E[ids[:, 0]], ids[:, 1]])
    if len(ee := collisions.ee_collisions):
        ids = np.array([(c.edge0_id, c.edge1_id) for c in ee], np.int64)
        sets.append(np.c_[E[ids[:, 0]], E[ids[:, 1]]])
    if len(fv := collisions.fv_collisions):
        ids = np.array([(c.face_id, c.vertex_id) for c in fv], np.int64)
        sets.append(np.c_[F[ids[:, 0]], ids[:, 1]])
    return [(np.repeat(s, s.shape[1], axis=1) << 32 | np.tile(s, (1, s.shape[1]))).ravel()
            for s in sets]


def _block_entries(pairs: np.ndarray, cm: ContactModel) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, cols)`` in full DOFs of the 3 x 3 blocks of the vertex pairs ``pairs``
    (:func:`_vertex_pairs`' keys) between the bodies' vertices (obstacles left out)."""
    i, j = pairs >> 32, pairs & 0xFFFFFFFF
    body = (i < cm.n_surface) & (j < cm.n_surface)
    i, j = i[body], j[body]
    d = np.arange(3)
    r = np.broadcast_to((3 * i)[:, None, None] + d[None, :, None], (i.size, 3, 3)).ravel()
    c = np.broadcast_to((3 * j)[:, None, None] + d[None, None, :], (i.size, 3, 3)).ravel()
    return cm.geometry.dof[r], cm.geometry.dof[c]


class ContactTerm(TermGroup):
    """IPC contact: :class:`BarrierTerm` and :class:`FrictionTerm` of one
    :class:`ContactModel`, as one group (the objective sees barrier + friction); the
    checkpoint state of the adaptive stiffness.

    Parameters
    ----------
    contact : ContactModel
    tolerance, pattern_margin, newton_start, first_step : optional
        The barrier's (:class:`BarrierTerm`).
    friction_iterations, friction_tolerance : optional
        The friction's re-lagging (:class:`FrictionTerm` ``iterations``, ``tolerance``).
    """

    name = "contact"

    def __init__(self, contact: ContactModel, *, tolerance: float = 1e-3,
                 pattern_margin: float = 4.0, friction_iterations: int = 1,
                 friction_tolerance: float = 1e-6, newton_start: str = "clamped",
                 first_step: str = "confirm") -> None:
        self.contact = contact
        self.barrier = BarrierTerm(contact, tolerance=tolerance, pattern_margin=pattern_margin,
                                   newton_start=newton_start, first_step=first_step)
        self.friction = FrictionTerm(contact, iterations=friction_iterations,
                                     tolerance=friction_tolerance)
        super().__init__([self.barrier, self.friction])
        self._initial = self.state_array()

    @property
    def tolerance(self) -> float:
        """IPC's Newton tolerance (the barrier's)."""
        return self.barrier.tolerance

    def straight_path_is_free(self, q0: np.ndarray, q1: np.ndarray, t0: float,
                              t1: float) -> bool:
        """Whether a step's own straight motion from ``q0`` (at ``t0``) to ``q1`` (at ``t1``)
        meets no surface (:func:`fem3d.physics.contact.path.straight_path_is_free`): the
        check :mod:`fem3d.solve.substeps` makes after each contact step."""
        return straight_path_is_free(self.contact.collisions, q0, q1, t0, t1)

    # -- checkpoints ----------------------------------------------------------------------------
    def reset(self) -> None:
        """Back to the adaptive state at construction (a :meth:`Simulation.reset`)."""
        self.load_state_array(self._initial)

    def state_array(self) -> np.ndarray:
        """The adaptive stiffness as a ``(5,) float64`` array (for ``.npz`` checkpoints):
        ``kappa, max_kappa, initialized, prev_min_distance (nan: none), had_contact``."""
        return np.append(self.contact.barrier.state_array(), float(self.barrier._had_contact))

    def load_state_array(self, a: np.ndarray) -> None:
        """Undo to a :meth:`state_array`."""
        a = np.asarray(a, dtype=np.float64).reshape(-1)
        if a.shape != (5,):
            raise ValueError(f"contact state must have 5 values, got {a.shape}")
        self.contact.barrier.load_state_array(a[:4])
        self.barrier._had_contact = bool(a[4])
