"""IPC contact and friction in the adjoint of a trajectory (every implicit scheme).

A contact scene's step minimises the model's terms plus the contact group
(:class:`~fem3d.physics.terms.contact.ContactTerm`): the barrier ``kappa B(q_{n+1})`` and the
friction ``D(q_{n+1}; q_t, mu)`` lagged at the step's start ``q_t = q_n`` (its normal forces
and bases there, its slip ``q_{n+1} - q_t`` against ``eps_v dt``), both in positions. With
the scheme's step map ``q_{n+1} = q_B + h u`` (:mod:`fem3d.diff.schemes`: backward Euler
``h = dt``, ``q_B = q_n``; BDF2, Newmark, static their own) the step's stationarity condition
(:mod:`fem3d.diff.adjoint`) gains ``g = h (grad B(q_{n+1}) + grad_1 D(q_{n+1}; q_t))``.
:class:`ContactAdjoint`, an :class:`~fem3d.diff.terms.AdjointTerm` registered with
:func:`fem3d.diff.adjoint.register_term` for every scene with contact, supplies that term's
pieces of the adjoint step:

* :meth:`ContactAdjoint.hessian`: the **exact** Hessian ``kappa H_B + H_D`` at ``q_{n+1}``
  (not the per-pair PSD projection Newton uses: the adjoint differentiates what was
  minimised; ``ipctk``'s ``PSDProjectionMethod.NONE`` and the planes' unprojected blocks of
  :class:`~fem3d.physics.contact.ContactModel`), ``dg/du = h^2 (kappa H_B + H_D)``;
* ``d/dq_B`` at fixed ``u`` (:meth:`ContactAdjoint.state_vjp`): ``q_{n+1}`` moves, the lag
  does not: ``h (kappa H_B + H_D) lambda``;
* ``d/dq_t`` at fixed ``q_{n+1}`` (:meth:`ContactAdjoint.start_vjp`): the slip (``-h H_D
  lambda``) and the lagged quantities (:meth:`ContactAdjoint.friction_lag_vjp`): the normal
  forces and, between meshes, the tangent bases and closest points taken at ``q_t``.
  Planes: ``d lambda_k / d s_k`` of IPC's normal force ``kappa |b'(s^2) 2 s|`` in NumPy;
  meshes: ``ipctk``'s ``force_jacobian(..., wrt=LAGGED_DISPLACEMENTS)``. With ``q_B = q_t``
  (backward Euler) the two friction Hessian products cancel: :meth:`ContactAdjoint.
  lagged_vjp` is their sum there;
* :meth:`ContactAdjoint.coefficient_vjp`: ``lambda^T d grad D / d mu`` (``mu``, ``mu_s``,
  ``mu_k``): the friction is linear in the two coefficients, so each derivative is the
  friction gradient lagged with that coefficient 1 and the other 0; ``d / d kappa`` (a fixed
  stiffness): the barrier and the lagged normal forces are linear in it, so it is
  ``grad (B + D) / kappa``.

Held fixed within a step (each a discrete choice, not a function of the parameters):

* the barrier stiffness ``kappa``. With ``contact.kappa`` given it is a constant and the
  gradient is exact. With the adaptive stiffness (``kappa`` unset) the value each step used
  is recorded in the forward pass and replayed: the derivative of IPC's initial ``kappa``
  (the larger of a bound proportional to the mean vertex mass over ``dt^2`` and a balance
  against the elastic gradient: it moves with the density, and with ``E`` where the balance
  decides) and of its doublings is left out (measured on the tests' box drop: the density's
  gradient off by ``2.4e-3``, the others unaffected; docs/differentiable.md); a doubling
  between two finite-difference runs is a jump no derivative sees. Fix ``contact.kappa`` to
  differentiate exactly;
* the contact set: the barrier is C2 at ``d = dhat`` (its value, slope and curvature vanish
  there), so pairs entering or leaving it change the gradient continuously; the friction's
  lagged pairs carry normal forces that vanish with their first derivative at ``dhat``;
* the friction is lagged once per step, at the step's start (``friction_iterations = 1``;
  more re-lag at the Newton solution, a fixed point that is refused here).

Newton runs to the adjoint's tight tolerance: the contact term is rebuilt with IPC's
velocity-based stopping rule out of the way (:data:`_NO_VELOCITY_STOP`).
"""

from __future__ import annotations

import math

import ipctk
import numpy as np
import scipy.sparse as sp

from fem3d.diff.adjoint import register_term
from fem3d.diff.terms import AdjointTerm, Gradients, StepPair
from fem3d.errors import ParameterError, SimulationError
from fem3d.physics.contact.friction_profile import point_plane_friction
from fem3d.physics.terms.contact import ContactTerm
from fem3d.solve.state import State

__all__ = ["ContactAdjoint", "CONTACT_KEYS", "contact_adjoint"]

#: The contact parameters :class:`ContactAdjoint` differentiates (``contact.kappa``: a fixed
#: stiffness only).
CONTACT_KEYS = ("contact.mu", "contact.mu_s", "contact.mu_k", "contact.kappa")

#: IPC's stopping rule (the Newton step's position change per second below this times the
#: scene's size) is kept from stopping Newton before the adjoint's gradient tolerance.
_NO_VELOCITY_STOP = 1e-300


def contact_adjoint(scene, built) -> ContactAdjoint | None:
    """The :class:`ContactAdjoint` of a built contact scene (None without contact).

    Raises
    ------
    ParameterError
        ``contact.friction_iterations > 1`` (friction re-lagged at the Newton solution), or a
        start that intersects or touches.
    """
    if built.contact is None:
        return None
    spec = scene.contact
    if spec.friction_iterations != 1:
        raise ParameterError("trajectory_gradient: contact.friction_iterations = "
                             f"{spec.friction_iterations}: the adjoint differentiates friction "
                             "lagged once per step (set it to 1)")
    term = ContactTerm(built.contact.contact, tolerance=_NO_VELOCITY_STOP,
                       pattern_margin=built.contact.barrier.pattern_margin)
    return ContactAdjoint(term, {"mu_s": spec.mu_s is None, "mu_k": spec.mu_k is None},
                          check_paths=spec.max_substeps > 1)


class ContactAdjoint(AdjointTerm):
    """The contact group's part of the forward run and of each adjoint step.

    Parameters
    ----------
    term : ContactTerm
        The scene's contact group (friction lagged once per step).
    follows_mu : dict, optional
        ``{"mu_s": bool, "mu_k": bool}``: whether ``contact.mu`` sets that coefficient (the
        scene leaves its own key unset; default both).
    check_paths : bool, optional
        Check each forward step's straight motion as a run with ``contact.max_substeps > 1``
        does (:mod:`fem3d.solve.substeps`), and stop where the run would take substeps.

    Attributes
    ----------
    keys : tuple of str
        The parameters :meth:`coefficient_vjp` answers (:data:`CONTACT_KEYS`).
    terms : list
        What the forward step adds to the model's terms.
    run : fem3d.diff.adjoint._Run or None
        The run this term belongs to (set by the registered factory): its ``extra_keys``
        are the keys a gradient asks for.
    """

    name = "contact"

    def __init__(self, term: ContactTerm, follows_mu: dict | None = None, *,
                 check_paths: bool = False) -> None:
        self.term = term
        self.check_paths = check_paths
        self.follows_mu = follows_mu or {"mu_s": True, "mu_k": True}
        self.cm = term.contact
        self.keys = tuple(k for k in CONTACT_KEYS
                          if k != "contact.kappa" or not self.cm.adaptive)
        self.terms = [term]
        self.run = None  # the adjoint's run (fem3d.diff.adjoint._Run): its keys asked for
        self._before: dict[int, np.ndarray] = {}   # adaptive state before step n
        self._kappas: dict[int, tuple[float, float]] = {}  # (at the friction lag, at the end)
        # the step linearize() set up: q_n, q_{n+1}, the friction's kappa, the planes' lag
        self._q0: np.ndarray | None = None
        self._q1: np.ndarray | None = None
        self._kappa_lag = math.nan
        self._dt = math.nan
        self._planes = None
        self._mesh = None
        self._h = math.nan  # the scheme's dq_{n+1}/du (backward Euler: dt)
        self._HB: sp.csr_matrix | None = None
        self._HD: sp.csr_matrix | None = None
        self._unit: dict[str, np.ndarray] = {}

    # -- the adjoint's term interface (fem3d.diff.terms.AdjointTerm) ----------------------------
    @property
    def requested(self) -> tuple[str, ...]:
        """The keys of :attr:`keys` the run's gradient asks for."""
        asked = () if self.run is None else self.run.extra_keys
        return tuple(k for k in asked if k in self.keys)

    def forward_terms(self) -> list:
        """The contact group, added to every forward step."""
        return self.terms

    def linearize(self, pair: StepPair) -> None:
        """Set up the step ``pair`` (:meth:`set_step`): the friction lagged at ``pair.q0``
        (the step's start ``q_t``), the scheme's ``h`` (``pair.h``) scaling the term."""
        s0 = State(q=pair.q0.reshape(-1, 3), v=pair.v0.reshape(-1, 3), t=pair.t0,
                   step=pair.step)
        s1 = State(q=pair.q1.reshape(-1, 3), v=pair.u.reshape(-1, 3), t=pair.t1,
                   step=pair.step + 1)
        self.set_step(s0, s1, pair.dt, self.requested)
        self._h = float(pair.h)

    def matrix(self) -> sp.csr_matrix:
        """``dg/du = h^2 (kappa H_B + H_D)``, exact (:meth:`hessian`)."""
        return self._h * self._h * self.hessian()

    def state_vjp(self, lf: np.ndarray):
        """``(-lf^T dg/dq_B, None)`` at fixed ``u``: ``q_{n+1} = q_B + h u`` moves, the lag
        ``q_t`` does not, so ``-h (kappa H_B + H_D) lf`` (``g`` has no ``v_hat``)."""
        return -self._h * (self.hessian() @ lf), None

    def start_vjp(self, lf: np.ndarray):
        """``-lf^T dg/dq_t`` at fixed ``q_{n+1}``: the slip ``q_{n+1} - q_t`` (``+h H_D lf``)
        and the friction's lagged normal forces and bases (:meth:`friction_lag_vjp`). With
        ``q_B = q_t`` (backward Euler) the two products sum to ``-h`` :meth:`lagged_vjp`."""
        if not self.cm.n_friction_pairs:
            return None
        return self._h * (self._friction_hessian() @ lf - self.friction_lag_vjp(lf))

    def param_vjp(self, lf: np.ndarray, grads: Gradients) -> None:
        """``-lf^T dg/dp`` of the requested keys into ``grads.extra``."""
        for key in self.requested:
            grads.extra[key] = grads.extra.get(key, 0.0) - self._h * self.coefficient_vjp(
                key, lf)

    # -- the forward run ------------------------------------------------------------------------
    def check_start(self, q: np.ndarray) -> None:
        """Refuse an intersecting or touching start (as a run does)."""
        self.cm.check_admissible(q)

    def before_step(self, state: State) -> None:
        """Record the adaptive stiffness before step ``state.step`` (first run) or restore it
        (a recomputation from a checkpoint repeats the first run's steps)."""
        saved = self._before.get(state.step)
        if saved is None:
            self._before[state.step] = self.term.state_array()
        else:
            self.term.load_state_array(saved)

    def after_step(self, state: State) -> None:
        """Record the stiffness step ``state.step`` (its start) lagged the friction with and
        the one its minimiser holds."""
        kappa_lag = self.term.friction.lagged_stiffness
        kappa = self.cm.kappa
        self._kappas[state.step] = (kappa if math.isnan(kappa_lag) else kappa_lag, kappa)

    def check_step(self, state: State, new: State) -> None:
        """Stop where ``fem3d run`` would redo the step as substeps (its straight motion
        passes through a surface): the adjoint differentiates whole steps."""
        if self.check_paths and not self.term.straight_path_is_free(state.q, new.q, state.t,
                                                                    new.t):
            raise SimulationError(
                f"step {state.step}: its straight motion passes through a surface, so a run "
                "takes it as substeps (contact.max_substeps); the adjoint differentiates whole "
                "steps only (a smaller simulation.dt avoids it)", step=state.step)

    def start_force_vjp(self, q0: np.ndarray, t0: float, lf: np.ndarray,
                        grads: Gradients) -> np.ndarray:
        """The contact's part of an initial acceleration ``M a_0 = f(q_0)`` (Newmark's, as
        :func:`fem3d.solve.schemes.newmark.initial_acceleration` takes it before the first step: the
        barrier ``kappa grad B(q_0)`` at the stiffness then, the friction not lagged yet, so
        zero): ``-lf^T d/dq_0`` of it, ``(3n,)``, and ``-lf^T d/d kappa`` into ``grads``."""
        cm = self.cm
        kappa_now, kappa = cm.kappa, float(self._before[0][0])  # the state before step 0
        q0 = np.asarray(q0, dtype=np.float64).reshape(-1)
        cm.set_time(t0)
        cm.set_kappa(kappa)
        out = -(cm.barrier_hessian(q0, project=False).tocsr() @ lf)
        if "contact.kappa" in self.requested:
            grads.extra["contact.kappa"] = grads.extra.get("contact.kappa", 0.0) - float(
                lf @ cm.barrier_gradient(q0)) / kappa
        cm.set_kappa(kappa_now)
        return out

    # -- one adjoint step -----------------------------------------------------------------------
    def set_step(self, s0: State, s1: State, dt: float, keys) -> None:
        """Put the contact model in step ``s0 -> s1``'s configuration: the friction lagged at
        ``s0`` with the stiffness it used, the obstacles at ``s1``'s time, the barrier's
        stiffness at convergence; the unit-coefficient friction gradients of ``keys``."""
        cm = self.cm
        kappa_lag, kappa = self._kappas[s0.step]
        q0 = np.asarray(s0.q, dtype=np.float64).reshape(-1)
        q1 = np.asarray(s1.q, dtype=np.float64).reshape(-1)
        cm.set_time(s0.t + dt)
        cm.set_kappa(kappa_lag)
        cm.lag_friction(q0, dt, t_start=s0.t)
        self._q0, self._q1, self._kappa_lag, self._dt = q0, q1, kappa_lag, float(dt)
        self._HB = self._HD = None
        self._planes = self._plane_lag()
        self._mesh = self._mesh_lag(s0.t)
        self._unit = {}
        if any(k in CONTACT_KEYS for k in keys):
            for which, coeffs in (("mu_s", (1.0, 0.0)), ("mu_k", (0.0, 1.0))):
                self._unit[which] = self._plane_gradient(*coeffs) + self._mesh_gradient(*coeffs)
        cm.set_kappa(kappa)

    def hessian(self) -> sp.csr_matrix:
        """The exact (unprojected) Hessian of barrier + friction at ``q_{n+1}``, ``(3n, 3n)``
        in positions."""
        H = self._barrier_hessian()
        if self.cm.n_friction_pairs:
            H = H + self._friction_hessian()
        return H

    def _friction_hessian(self) -> sp.csr_matrix:
        """``H_D(q_{n+1}; q_n)``, unprojected (computed once per step)."""
        if self._HD is None:
            self._HD = self.cm.friction_hessian(self._q1, project=False).tocsr()
        return self._HD

    def _barrier_hessian(self) -> sp.csr_matrix:
        """``kappa H_B(q_{n+1})``, unprojected (computed once per step)."""
        if self._HB is None:
            self._HB = self.cm.barrier_hessian(self._q1, project=False).tocsr()
        return self._HB

    def lagged_vjp(self, lf: np.ndarray) -> np.ndarray:
        """``d/dq_n`` of ``lf^T grad(B + D)(q_{n+1}; q_n)`` with the step's unknowns held:
        ``H_B lf`` plus the friction's lagged normal forces and bases, ``(3n,)``."""
        out = self._barrier_hessian() @ lf
        if self.cm.n_friction_pairs:
            out += self.friction_lag_vjp(lf)
        return out

    def friction_lag_vjp(self, lf: np.ndarray) -> np.ndarray:
        """``d/dq_t`` of ``lf^T grad D(q_{n+1}; q_t)`` through what is lagged at ``q_t`` only
        (the normal forces and, between meshes, tangent bases and closest points), the slip
        held, ``(3n,)``."""
        return self._plane_lag_vjp(lf) + self._mesh_lag_vjp(lf)

    def coefficient_vjp(self, key: str, lf: np.ndarray) -> float:
        """``lf^T d grad(B + D) / d key`` for a key of :attr:`keys`."""
        cm = self.cm
        if key == "contact.kappa":
            g = cm.barrier_gradient(self._q1) + cm.friction_gradient(self._q1)
            return float(lf @ g) / cm.kappa
        g = 0.0
        for which in ("mu_s", "mu_k"):
            if key == f"contact.{which}" or (key == "contact.mu" and self.follows_mu[which]):
                g += float(lf @ self._unit[which])
        return g

    # -- the friction's lagged quantities (public ContactModel API and ipctk only) -------------
    def _plane_lag(self):
        """``(surface vertices, normals, lambda, d lambda / d s)`` of the point-plane pairs
        active at ``q_n``: IPC's normal force ``lambda = kappa |b'(s^2) 2 s|`` (as
        :class:`ContactModel` lags it, whatever ``mu``) and its derivative by the signed
        distance ``s``, ``kappa (-2 b' - 4 s^2 b'')``."""
        cm = self.cm
        if not cm.planes:
            return None
        P0 = self._q0.reshape(-1, 3)[cm.surface]
        S = np.stack([p.signed_distance(P0) for p in cm.planes])
        pl, vi = np.nonzero((S < cm.dhat) & (S > 0))
        if pl.size == 0:
            return None
        s = S[pl, vi]
        z, zh = s * s, cm.dhat * cm.dhat
        b1 = -2.0 * (z - zh) * np.log(z / zh) - (z - zh) ** 2 / z
        b2 = -2.0 * np.log(z / zh) - 4.0 * (z - zh) / z + (z - zh) ** 2 / (z * z)
        k = self._kappa_lag
        normals = np.array([p.normal for p in cm.planes])[pl]
        return vi, normals, k * np.abs(b1 * 2.0 * s), k * (-2.0 * b1 - 4.0 * z * b2)

    def _plane_slip_forces(self, lam, mu_s: float, mu_k: float) -> np.ndarray:
        """Each lagged point-plane pair's friction gradient ``(k, 3)`` at ``q_{n+1}``."""
        cm = self.cm
        vi, n, _, _ = self._planes
        P0 = self._q0.reshape(-1, 3)[cm.surface[vi]]
        P1 = self._q1.reshape(-1, 3)[cm.surface[vi]]
        return point_plane_friction(n, P1 - P0, lam, cm.eps_v * self._dt, mu_s, mu_k, 1)

    def _plane_gradient(self, mu_s: float, mu_k: float) -> np.ndarray:
        """The point-plane friction's gradient ``(3n,)`` with coefficients ``mu_s, mu_k``."""
        out = np.zeros(3 * self.cm.n_vertices)
        if self._planes is not None:
            vi, _, lam, _ = self._planes
            np.add.at(out.reshape(-1, 3), self.cm.surface[vi],
                      self._plane_slip_forces(lam, mu_s, mu_k))
        return out

    def _plane_lag_vjp(self, lf: np.ndarray) -> np.ndarray:
        """Point-plane pairs: ``sum_k (lf_k . G_k) d lambda_k / d q_n``, ``G_k`` the pair's
        friction gradient per unit normal force (the normals are the planes': fixed)."""
        cm = self.cm
        out = np.zeros(3 * cm.n_vertices)
        if self._planes is None or cm.mu == 0.0:
            return out
        vi, n, _, dlam_ds = self._planes
        G = self._plane_slip_forces(np.ones(vi.size), cm.mu, cm.mu_k)
        verts = cm.surface[vi]
        coef = (lf.reshape(-1, 3)[verts] * G).sum(axis=1) * dlam_ds
        np.add.at(out.reshape(-1, 3), verts, coef[:, None] * n)
        return out

    def _mesh_lag(self, t0: float):
        """``(lagged collision vertices, their normal collisions)`` of the mesh pairs (bodies
        against each other, themselves or mesh obstacles) within ``dhat`` at ``q_n``, the
        obstacles where they were at ``t0``; None where no two meshes can touch."""
        cm = self.cm
        can_touch = (cm.self_contact or len(cm.meshes) > 0
                     or np.unique(cm.body_ids).size > 1)
        if not can_touch:
            return None
        V = np.asfortranarray(cm.collision_vertices(self._q0, cm.obstacle_positions(t0)))
        cands = ipctk.Candidates()
        cands.build(cm.mesh, V, 0.5 * cm.dhat)  # pairs closer than dhat are candidates
        col = ipctk.NormalCollisions()
        col.build(cands, cm.mesh, V, cm.dhat)
        return (V, col) if len(col) else None

    def _tangential(self, mu_s: float, mu_k: float):
        """ipctk's lagged friction pairs for coefficients ``mu_s, mu_k`` (None: none)."""
        V, col = self._mesh
        tc = ipctk.TangentialCollisions()
        tc.build(self.cm.mesh, V, col, ipctk.BarrierPotential(self.cm.dhat, self._kappa_lag),
                 mu_s, mu_k)
        return tc if len(tc) else None

    def _to_fem3d(self, g: np.ndarray) -> np.ndarray:
        """A collision-vertex vector ``(3 n_collision,)`` on fem3d's DOFs ``(3n,)`` (the
        obstacles' entries dropped)."""
        cm = self.cm
        out = np.zeros((cm.n_vertices, 3))
        np.add.at(out, cm.surface, np.asarray(g).reshape(-1, 3)[: cm.n_surface])
        return out.reshape(-1)

    def _slip(self) -> np.ndarray:
        """The collision vertices' displacement over the step (obstacles: their motion)."""
        return np.asfortranarray(self.cm.collision_vertices(self._q1) - self._mesh[0])

    def _mesh_gradient(self, mu_s: float, mu_k: float) -> np.ndarray:
        """The mesh-mesh friction's gradient ``(3n,)`` at ``q_{n+1}`` lagged at ``q_n`` with
        coefficients ``mu_s, mu_k``."""
        tc = None if self._mesh is None else self._tangential(mu_s, mu_k)
        if tc is None:
            return np.zeros(3 * self.cm.n_vertices)
        potential = ipctk.FrictionPotential(self.cm.eps_v * self._dt)
        return self._to_fem3d(potential.gradient(tc, self.cm.mesh, self._slip()))

    def _mesh_lag_vjp(self, lf: np.ndarray) -> np.ndarray:
        """Mesh-mesh pairs: ``-J^T lf`` with ``J`` ipctk's Jacobian of the friction force
        (``-grad D``) by the lagged positions at a fixed slip."""
        cm = self.cm
        tc = None if self._mesh is None or cm.mu == 0.0 else self._tangential(cm.mu, cm.mu_k)
        if tc is None:
            return np.zeros(3 * cm.n_vertices)
        V, U = self._mesh[0], self._slip()
        w = np.zeros((cm.n_collision_vertices, 3))
        w[: cm.n_surface] = lf.reshape(-1, 3)[cm.surface]
        J = ipctk.FrictionPotential(cm.eps_v * self._dt).force_jacobian(
            tc, cm.mesh, V, np.zeros_like(U, order="F"), U,
            ipctk.BarrierPotential(cm.dhat, self._kappa_lag),
            ipctk.TangentialPotential.DiffWRT.LAGGED_DISPLACEMENTS)
        return self._to_fem3d(-(J.T @ w.reshape(-1)))


def _factory(run) -> ContactAdjoint | None:
    """The adjoint's contact term of ``run`` (:func:`fem3d.diff.adjoint.register_term`)."""
    adjoint = contact_adjoint(run.scene, run.built)
    if adjoint is not None:
        adjoint.check_start(run.state0.q)
        adjoint.run = run
    return adjoint


def _has_contact(scene) -> bool:
    return scene.contact is not None and bool(getattr(scene.contact, "enabled", True))


register_term(_factory, keys=[r"contact\.(mu|mu_s|mu_k|kappa)$"], accepts=_has_contact)
