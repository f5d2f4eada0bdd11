"""The discrete adjoint of a trajectory (backward Euler below; static, BDF2 and Newmark:
:mod:`fem3d.diff.schemes`, each scheme's own module, registered by integrator name).

Each step solves ``g(u; q_n, v_n, p) = 0`` over the free velocities (``u``: the full
velocity, the pinned DOFs' part ``w = (p_{n+1} - q_n[F]) / dt`` prescribed by the pins'
positions ``p_{n+1}``; ``g``: the gradient of backward Euler's objective,
:mod:`fem3d.solve.schemes.implicit`)::

    g = P [M (u - v_n) + dt dV/dq(q_n + dt u) - dt M g_grav + dt D(q_n) u]

with ``D = alpha M + beta K_psd(q_n)``, ``q_{n+1} = q_n + dt u``, ``v_{n+1} = u``. The
backward pass runs the steps in reverse: with ``(q_bar, v_bar)`` the loss's total derivative
by ``(q_{n+1}, v_{n+1})`` it solves the transposed (symmetric) Newton matrix
``A lambda = P (v_bar + dt q_bar)``, ``A = P K P^T``, ``K = dg/du = M + dt^2 H(q_{n+1}) +
dt D(q_n)``, with the :class:`~fem3d.solve.system.System`'s sparse direct solver, and
accumulates ``-lambda^T dg/dp`` for every parameter, ``-lambda^T dg/d(q_n, v_n)`` for the
state and ``w_bar = (v_bar + dt q_bar - K P^T lambda)[F]`` for the pins' positions
(``dL/dp_{n+1} = w_bar / dt``). Each term of ``g`` is an :class:`~fem3d.diff.terms.
AdjointTerm` (its matrix, its state and parameter products); :func:`register_term` adds
another (contact).

What is exact and what is not:

* The gradient is the derivative of the procedure that ran only if Newton ran to
  convergence: :func:`simulate` runs every step to ``rtol`` (default ``1e-11`` of the first
  gradient norm, no iteration cap). A run capped at a few Newton iterations (``fem3d run``'s
  default) is a different map; its data is still a fine fitting target.
* Material values (per body, per region, per tet: :mod:`fem3d.diff.params`) use the
  generated ``dgradient_dparams`` kernels (one call per material group and step) and the
  generated Jacobian of each material's ``E, nu`` mapping: exact.
* The stiffness-proportional damping ``beta K_psd(q_n)`` depends on ``q_n`` and on the
  material parameters through the PSD-projected element Hessians: exact through the
  generated ``d3psi_contract`` and the projection's derivative (:mod:`fem3d.diff.terms`).
* Moving pins: the gradient by each keyframe's ``translate`` is exact (the translation is
  linear in the keyframes; rotations are held fixed).
* Not supported: contact and friction (unless a registered term handles them), pull
  springs, angular velocity.

Memory: the states at every ``checkpoint_every``-th step are kept, and the whole last
segment (where the backward pass starts); the backward pass recomputes each other segment
from its checkpoint (at most one extra forward run in total), so memory is ``O(N / k + k)``
states for ``N`` steps. With stiffness damping the forward steps of the segment about to be
read back keep their damping linearizations (:mod:`fem3d.diff.damping`: ``D(q_n)`` and the
projected elements' eigendecompositions, at most ``k``, within ``cache_bytes``), so its
backward steps neither assemble ``D`` nor decompose an element again.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse.linalg as spla

from fem3d.diff.damping import DEFAULT_CACHE_BYTES, RecordingDamping, point_kernels
from fem3d.diff.loads import PressureAdjoint
from fem3d.diff.params import (
    PARAMETER_KEYS,
    ParamKey,
    TetSources,
    parse_param_key,
)
from fem3d.diff.schemes import SCHEMES, SchemeAdjoint
from fem3d.diff.terms import (
    AdjointTerm,
    DampingAdjoint,
    ElasticAdjoint,
    Gradients,
    GravityAdjoint,
    InertiaAdjoint,
    StepPair,
    element_groups,
    sparse_of,
)
from fem3d.errors import ParameterError, SimulationError
from fem3d.physics.terms.surface import FollowerPressure
from fem3d.scene.arrays import select_vertices
from fem3d.scene.build import Built, build, refuse_mixed_elements
from fem3d.scene.load import apply_overrides
from fem3d.scene.spec import Scene
from fem3d.solve.schemes.base import model_terms
from fem3d.solve.state import State
from fem3d.solve.system import System

__all__ = ["PositionLoss", "simulate", "trajectory_gradient", "PARAMETER_KEYS",
           "register_term", "TermFactory"]


class PositionLoss:
    """``L = sum_frames 1/2 sum_i w |q_n[i] - target_n[i]|^2`` over selected vertices.

    Parameters
    ----------
    targets : mapping of int -> (k, 3) or (n, 3) float64
        Target positions by step index (``1..N``: the state after that many steps).
    vertices : (k,) int, optional
        The vertices compared (None: all).
    weight : float, optional
    """

    def __init__(self, targets: Mapping[int, np.ndarray], vertices=None,
                 weight: float = 1.0) -> None:
        self.targets = {int(n): np.asarray(t, dtype=np.float64) for n, t in targets.items()}
        self.vertices = None if vertices is None else np.asarray(vertices, dtype=np.int64)
        self.weight = float(weight)

    @property
    def last_step(self) -> int:
        """The last step the loss reads."""
        return max(self.targets)

    def frame(self, step: int, q: np.ndarray) -> tuple[float, np.ndarray | None]:
        """``(value, dL/dq (n, 3))`` of frame ``step`` (``(0.0, None)`` when not compared)."""
        target = self.targets.get(step)
        if target is None:
            return 0.0, None
        q = q.reshape(-1, 3)
        sel = slice(None) if self.vertices is None else self.vertices
        r = q[sel] - target
        grad = np.zeros_like(q)
        grad[sel] = self.weight * r
        return 0.5 * self.weight * float(np.sum(r * r)), grad


#: ``factory(run) -> AdjointTerm or None``: a term the adjoint adds to every run it applies
#: to (its :meth:`~fem3d.diff.terms.AdjointTerm.forward_terms` join the forward step).
TermFactory = Callable[["_Run"], AdjointTerm | None]
_FACTORIES: list[tuple[TermFactory, tuple[re.Pattern[str], ...], Callable | None]] = []


def register_term(factory: TermFactory, keys: Sequence[str] = (),
                  accepts: Callable[[Scene], bool] | None = None) -> None:
    """Add a term to the adjoint (contact, friction: :mod:`fem3d.diff.contact`).

    Parameters
    ----------
    factory : callable
        ``factory(run) -> AdjointTerm or None`` (None: not in this scene). ``run`` has
        ``scene``, ``built``, ``system``, ``dt``.
    keys : sequence of str
        Regular expressions of the parameter keys the term differentiates: its
        :meth:`~fem3d.diff.terms.AdjointTerm.param_vjp` adds them into ``grads.extra[key]``
        (``float`` or an array), which :func:`trajectory_gradient` returns as they are.
    accepts : callable, optional
        ``accepts(scene) -> bool``: the term handles a scene the adjoint would otherwise
        refuse (contact).
    """
    _FACTORIES.append((factory, tuple(re.compile(k) for k in keys), accepts))


@dataclass
class _Run:
    scene: Scene
    built: Built
    system: System
    state0: State
    dt: float
    rtol: float
    atol_factor: float
    scheme: SchemeAdjoint | None = None  # the integrator (fem3d.diff.schemes)
    terms: list[AdjointTerm] = field(default_factory=list)  # registered (extra) terms
    extra_keys: tuple[str, ...] = ()  # the registered terms' keys asked for
    groups: list = field(default_factory=list)  # element_groups(model)
    #: the forward step's stiffness damping, keeping its linearizations for the backward
    #: pass (None: no stiffness damping, or kernels without d3psi_contract)
    damping: RecordingDamping | None = None

    def fixed_positions(self, t: float) -> np.ndarray | None:
        """The pinned vertices' positions at ``t`` (None: no moving pin), as a run's."""
        motions = self.built.motions
        if not motions:
            return None
        p = self.built.model.X[self.system.constraints.fixed_vertices].copy()
        for slots, rest, kf in motions:
            p[slots] = kf.apply(rest, t)
        return p

    def step(self, state: State, record: bool = False) -> State:
        """One converged step from ``state``; ``record``: keep its damping linearization
        (:class:`~fem3d.diff.damping.RecordingDamping`) for the backward pass."""
        extra = [t for term in self.terms for t in term.forward_terms()]
        for term in self.terms:
            term.before_step(state)
        own = self.system.loads.damping
        terms = [self.damping if t is own and self.damping is not None else t
                 for t in model_terms(self.system)]
        if self.damping is not None:
            self.damping.recording = record
        new, stats = self.scheme.forward(self, state, [*terms, *extra])
        if not stats.converged:
            raise SimulationError("Newton did not converge: the adjoint needs converged steps",
                                  step=state.step)
        for term in self.terms:
            term.check_step(state, new)
            term.after_step(state)
        return new


def _prepare(scene: Scene, rtol: float, atol_factor: float,
             cache_bytes: int = DEFAULT_CACHE_BYTES) -> _Run:
    accepted = any(a is not None and a(scene) for _, _, a in _FACTORIES)
    if scene.contact is not None and getattr(scene.contact, "enabled", True) and not accepted:
        raise ParameterError("trajectory_gradient: contact scenes are not supported yet")
    if scene.pulls:  # a run applies them: differentiating without them would be wrong
        raise ParameterError("trajectory_gradient: scripted pulls are not differentiated yet "
                             f"(the scene has {len(scene.pulls)}; remove them with pulls = [])")
    scheme = SCHEMES.get(scene.simulation.integrator)
    if scheme is None:
        raise ParameterError("trajectory_gradient: simulation.integrator = "
                             f"{scene.simulation.integrator!r} is not differentiated "
                             f"(differentiated: {', '.join(sorted(SCHEMES))})")
    if accepted and not scheme.contact and scene.contact is not None and \
            getattr(scene.contact, "enabled", True):
        with_contact = ", ".join(sorted(n for n, s in SCHEMES.items() if s.contact))
        raise ParameterError("trajectory_gradient: contact is not differentiated with "
                             f"simulation.integrator = {scene.simulation.integrator!r} "
                             f"(differentiated with contact: {with_contact})")
    refuse_mixed_elements(scene, "the adjoint (trajectory_gradient, fem3d fit)")
    built = build(scene)
    system = System(built.model, built.constraints, scene.simulation.linear_solver,
                    loads=built.loads)
    a = built.arrays
    v0 = np.array(a.v0, dtype=np.float64)
    v0.reshape(-1)[built.constraints.fixed_dofs] = 0.0  # pinned DOFs start at rest
    state = State(q=built.model.X.copy(), v=v0, t=0.0, step=0)
    run = _Run(scene, built, system, state, float(scene.simulation.dt), rtol, atol_factor,
               scheme)
    run.groups = element_groups(built.model)
    term = system.loads.damping
    if scheme.dynamic and term is not None and term._beta_vol is not None and all(
            hasattr(k, "d3psi_contract") and hasattr(k, "d2psi_dF2")
            for k in (point_kernels(g) for g, _, _, _ in run.groups)):
        run.damping = RecordingDamping(term, run.groups, cache_bytes)
    run.terms = [t for f, _, _ in _FACTORIES if (t := f(run)) is not None]
    run.state0 = scheme.start(run, state)
    return run


def simulate(scene: Scene, steps: int, *, rtol: float = 1e-11,
             atol_factor: float = 1e-16) -> list[np.ndarray]:
    """Positions ``q_0 .. q_steps`` (each ``(n, 3)``) of the converged backward-Euler run
    that :func:`trajectory_gradient` differentiates."""
    run = _prepare(scene, rtol, atol_factor)
    state, out = run.state0, [run.state0.q.copy()]
    for _ in range(steps):
        state = run.step(state)
        out.append(state.q.copy())
    return out


@dataclass
class Stats:
    """What one :func:`trajectory_gradient` call held and did (for the cost figures)."""

    forward_steps: int = 0
    recomputed_steps: int = 0
    backward_steps: int = 0
    peak_states: int = 0
    #: the most bytes of stiffness damping's linearizations kept at once (``D(q_n)`` and the
    #: eigendecompositions of the projected elements: :mod:`fem3d.diff.damping`)
    peak_damping_bytes: int = 0
    #: CPU seconds (``time.process_time``) of the forward run, of the recomputation of the
    #: segments and of the backward (adjoint) steps
    forward_seconds: float = 0.0
    recompute_seconds: float = 0.0
    backward_seconds: float = 0.0


def trajectory_gradient(
    scene: Scene,
    loss: PositionLoss | Callable,
    params: Sequence[str],
    *,
    steps: int | None = None,
    checkpoint_every: int = 10,
    rtol: float = 1e-11,
    atol_factor: float = 1e-16,
    stats: Stats | None = None,
    cache_bytes: int = DEFAULT_CACHE_BYTES,
) -> tuple[float, dict[str, float | np.ndarray]]:
    """The loss of a backward-Euler run of ``scene`` and its gradient by ``params``.

    Parameters
    ----------
    scene : Scene
    loss : PositionLoss, or an object with ``frame(step, q) -> (value, dL/dq or None)``
        and ``last_step``.
    params : sequence of str
        Keys of :data:`PARAMETER_KEYS` (``bodies[0].material.E``,
        ``bodies[0].material.regions[1].E``, ``bodies[0].material.cell_fields.E``,
        ``bodies[0].pins[0].motion.keyframes[1].translate``, ``simulation.gravity``).
    steps : int, optional
        Steps to run (default: ``loss.last_step``).
    checkpoint_every : int, optional
        States kept every ``k`` steps (and the last segment's: the backward pass starts
        there); the backward pass recomputes the others, one segment at a time.
    rtol, atol_factor : float, optional
        Newton's tolerances (run to convergence: see the module docstring).
    stats : Stats, optional
        Filled with the steps run and the most states held at once.
    cache_bytes : int, optional
        With stiffness damping: the most bytes of the damping's linearizations (``D(q_n)``
        and the projected elements' eigendecompositions) kept from the forward steps of a
        segment for its backward steps (at most ``k`` of them); a step beyond it makes its
        own in the backward pass.

    Returns
    -------
    (float, dict of str -> float or ndarray)
        Scalars as floats, vectors ``(3,)``, per-tet fields ``(body's tets,)``.
    """
    extra = tuple(p for _, keys, _ in _FACTORIES for p in keys)
    parsed = [parse_param_key(k, extra) for k in params]
    run = _prepare(scene, rtol, atol_factor, cache_bytes)
    run.extra_keys = tuple(p.key for p in parsed if p.kind == "extra")
    sources = TetSources(scene, run.built.arrays) if any(
        p.kind in ("material", "field") for p in parsed) else None
    for p in parsed:
        _check_key(run, sources, p)
    stats = Stats() if stats is None else stats
    n_steps = int(loss.last_step if steps is None else steps)
    k = max(1, int(checkpoint_every))
    checkpoints = {0: run.state0}
    state, value = run.state0, 0.0
    last = (max(n_steps - 1, 0) // k) * k  # the last segment's start: kept, not recomputed
    t0 = time.process_time()
    for n in range(n_steps):
        state = run.step(state, record=n >= last)
        value += loss.frame(n + 1, state.q)[0]
        if (n + 1) % k == 0 or n + 1 >= last:  # the last segment too: never recomputed
            checkpoints[n + 1] = state
    stats.forward_steps += n_steps
    stats.forward_seconds += time.process_time() - t0
    adj = _Adjoint(run, parsed, sources)
    _backward(run, adj, loss, checkpoints, n_steps, k, stats)
    return value, adj.result()


def _check_key(run: _Run, sources: TetSources | None, p: ParamKey) -> None:
    if p.kind == "extra" and not any(p.key in term.keys for term in run.terms):
        raise ParameterError(f"trajectory_gradient: cannot differentiate {p.key!r} in this "
                             "scene: none of its terms has it (contact keys need contact, "
                             "contact.kappa a fixed kappa)")
    n_bodies = len(run.scene.bodies)
    if p.kind == "velocity" and not run.scheme.dynamic:
        raise ParameterError(f"{p.key}: simulation.integrator = {run.scheme.name!r} has no "
                             "velocities (its steps are equilibria)")
    if p.body is not None and p.body >= n_bodies:
        raise ParameterError(f"{p.key}: the scene has {n_bodies} bodies")
    if sources is not None:
        sources.check(p)
    if p.kind == "material" and p.name in ("E", "nu") and p.region is None and \
            run.scene.bodies[p.body].material.E is None:
        raise ParameterError(f"{p.key}: body {p.body}'s material is given by its own "
                             "parameters; E and nu derivatives need E and nu")
    if p.kind == "keyframe":
        pins = run.scene.bodies[p.body].pins
        if p.pin >= len(pins) or pins[p.pin].motion is None:
            raise ParameterError(f"{p.key}: bodies[{p.body}].pins[{p.pin}] is not a moving pin")
        if p.keyframe >= len(pins[p.pin].motion.keyframes):
            raise ParameterError(f"{p.key}: the motion has "
                                 f"{len(pins[p.pin].motion.keyframes)} keyframes")


def _backward(run: _Run, adj: _Adjoint, loss, checkpoints: dict, n_steps: int, k: int,
              stats: Stats) -> None:
    bar = None
    starts = sorted((n for n in checkpoints if n % k == 0 and n < n_steps), reverse=True)
    stats.peak_states = max(stats.peak_states, len(checkpoints))
    for start in starts:
        t0 = time.process_time()
        segment = [checkpoints[start]]
        for _ in range(start, min(start + k, n_steps)):
            kept = checkpoints.get(start + len(segment))
            if kept is None:
                kept = run.step(segment[-1], record=True)
                stats.recomputed_steps += 1
            segment.append(kept)
        t1 = time.process_time()
        stats.recompute_seconds += t1 - t0
        held = sum(1 for n in range(start + 1, start + len(segment)) if n not in checkpoints)
        stats.peak_states = max(stats.peak_states, len(checkpoints) + held)
        if run.damping is not None:
            stats.peak_damping_bytes = max(stats.peak_damping_bytes, run.damping.peak_bytes)
        for i in range(len(segment) - 1, 0, -1):
            n = start + i  # the state after step n
            if bar is None:
                bar = run.scheme.zero(segment[i])
            grad = loss.frame(n, segment[i].q)[1]
            if grad is not None:
                bar["q"] += grad.reshape(-1)
            bar = adj.step(segment[i - 1], segment[i], bar)
            stats.backward_steps += 1
        for n in [n for n in checkpoints if n > start]:  # read: no longer needed
            del checkpoints[n]
        if run.damping is not None:
            run.damping.clear()
        stats.backward_seconds += time.process_time() - t1
    if bar is None:
        bar = run.scheme.zero(run.state0)
    run.scheme.finish(adj, run.state0, bar)
    adj.q_bar0, adj.v_bar0 = bar["q"], bar["v"]


class _Adjoint:
    """One backward step at a time; accumulates the parameters' gradients."""

    def __init__(self, run: _Run, params: list[ParamKey], sources: TetSources | None) -> None:
        self.run, self.params, self.sources = run, params, sources
        system = run.system
        self.model, self.c = system.model, system.constraints
        self.free = self.c.free_dofs
        self.fixed = self.c.fixed_dofs
        self.dt = run.dt
        a = run.built.arrays
        self.groups = run.groups
        density = np.array([float(b.material.density) for b in run.scene.bodies])
        dynamic = run.scheme.dynamic  # static: no inertia, no damping
        self.terms: list[AdjointTerm] = [
            *([InertiaAdjoint(self.model, a, density)] if dynamic else []),
            ElasticAdjoint(self.model, self.groups),
            GravityAdjoint(self.model, a, run.built.gravity, density),
            *[PressureAdjoint(t) for t in system.loads.surface
              if isinstance(t, FollowerPressure)],
            *([DampingAdjoint(system, a, self.groups, density, run.damping)] if dynamic
              else []),
            *run.terms]
        n_bodies = len(run.scene.bodies)
        wants_material = any(p.kind in ("material", "field") for p in params)
        self.grads = Gradients(
            material=[np.zeros_like(p) for _, _, p, _ in self.groups] if wants_material
            else None,
            density=np.zeros(n_bodies), rayleigh_mass=np.zeros(n_bodies),
            rayleigh_stiffness=np.zeros(n_bodies))
        self.keyframes = {p.key: _keyframe_weights(run, p) for p in params
                          if p.kind == "keyframe"}
        self.pin_grads = {key: np.zeros(3) for key in self.keyframes}

    def step(self, s0: State, s1: State, bar1: dict) -> dict:
        """The cotangent of the state before a step from the one after it (fields of
        :class:`State`, flat); accumulates the parameters' gradients."""
        scheme, model = self.run.scheme, self.model
        lin = scheme.linear(s0, self.dt)
        q1_bar, v1_bar, bar0 = scheme.split(s0, s1, bar1, self.fixed)
        u = s1.v.reshape(-1) if scheme.dynamic else np.zeros(model.n_dofs)
        pair = StepPair(q0=s0.q.reshape(-1), v0=s0.v.reshape(-1), q1=s1.q.reshape(-1),
                        u=u, dt=self.dt, t1=s1.t, t0=s0.t, step=s0.step, h=lin.h, qb=lin.qb,
                        vh=lin.vh)
        K, K_free = self._matrix(pair)
        u_bar = lin.h * q1_bar + (v1_bar if scheme.dynamic else 0.0)
        lf = np.zeros(model.n_dofs)
        lf[self.free] = self._solve(K_free, u_bar[self.free])
        qb_bar, vh_bar, qt_bar = q1_bar.copy(), np.zeros(model.n_dofs), np.zeros(model.n_dofs)
        for term in self.terms:
            dq, dv = term.state_vjp(lf)
            if dq is not None:
                qb_bar += dq
            if dv is not None:
                vh_bar += dv
            dq = term.start_vjp(lf)
            if dq is not None:
                qt_bar += dq
            term.param_vjp(lf, self.grads)
        if self.fixed.size:  # u[F] = w = (p - q_t[F]) / tau, q_B[F] = p - h w
            F, r = self.fixed, lin.h / lin.tau
            w_bar = u_bar[F] - (K @ lf)[F]
            p_bar = np.zeros(3 * self.c.fixed_vertices.size)  # per fixed vertex, (k, 3)
            p_bar[self.c.fixed_slots] = w_bar / lin.tau + (1.0 - r) * qb_bar[F]
            p_bar = p_bar.reshape(-1, 3)
            qt_bar[F] += r * qb_bar[F] - w_bar / lin.tau
            qb_bar[F] = 0.0
            for key, (slots, weights) in self.keyframes.items():
                self.pin_grads[key] += weights(s1.t) * p_bar[slots].sum(axis=0)
        scheme.pull_back(s0, lin, bar0, qb_bar, vh_bar)
        bar0["q"] += qt_bar
        return bar0

    def _matrix(self, pair: StepPair):
        """``K = dg/du`` over every DOF and on the free DOFs (the solver's pattern)."""
        model = self.model
        data, others = np.zeros(model.nnz), []
        for term in self.terms:
            term.linearize(pair)
            m = term.matrix()
            if isinstance(m, np.ndarray):
                data += m
            elif m is not None:
                others.append(m)
        K = model.csr(data)
        K_free = K[self.free][:, self.free].tocsr()
        for m in others:  # entries between bodies (contact) widen the solver's pattern
            K_free = self.run.system.add_hessian(K_free, m)
            K = K + sparse_of(model, m)
        return K, K_free

    def _solve(self, A, b: np.ndarray) -> np.ndarray:
        system = self.run.system
        try:
            system.factorize(A, shifts=False)
            return system.solve(b)
        except SimulationError:  # indefinite at this state: a general sparse LU
            return spla.spsolve(A.tocsc(), b)

    def result(self) -> dict:
        out: dict[str, float | np.ndarray] = {}
        a = self.run.built.arrays
        per_tet = self._material_per_tet()
        g = self.grads
        for p in self.params:
            if p.kind == "gravity":
                out[p.key] = g.gravity.copy()
            elif p.kind == "velocity":
                vb = self.v_bar0.reshape(-1, 3).copy()
                vb.reshape(-1)[self.c.fixed_dofs] = 0.0  # pinned DOFs start at rest
                out[p.key] = vb[a.body_vertices[p.body]].sum(axis=0)
            elif p.kind in ("density", "rayleigh_mass", "rayleigh_stiffness"):
                out[p.key] = float(getattr(g, p.kind)[p.body])
            elif p.kind == "keyframe":
                out[p.key] = self.pin_grads[p.key].copy()
            elif p.kind == "field":
                d = per_tet[p.name].copy()
                d[np.setdiff1d(np.arange(d.size), self.sources.tets_of(
                    ParamKey(p.key, "material", p.body, name=p.name)))] = 0.0
                out[p.key] = d[a.body_tets[p.body]]
            elif p.kind == "material":
                out[p.key] = float(per_tet[p.name][self.sources.tets_of(p)].sum())
            else:
                out[p.key] = g.extra.get(p.key, 0.0)
        return out

    def _material_per_tet(self) -> dict[str, np.ndarray]:
        """``dL/d(value)`` per tet of every material value a key asks for."""
        names = {p.name for p in self.params if p.kind in ("material", "field")}
        out = {}
        for name in names:
            d = np.zeros(self.model.n_tets)
            for acc, (g, els, _, _) in zip(self.grads.material, self.groups, strict=True):
                d[els] = np.sum(acc * self.sources.jacobian(g.material, els, name), axis=1)
            out[name] = d
        return out


def _keyframe_weights(run: _Run, p: ParamKey):
    """``(slots, weight(t))`` of a keyframe key: its pin's slots among the pinned vertices
    and ``d translation(t) / d translate_k`` (a scalar: the translation is interpolated)."""
    c = run.system.constraints
    body = run.scene.bodies[p.body]
    a = run.built.arrays
    ids = select_vertices(run.scene, a.X[a.body_vertices[p.body]], body.pins[p.pin].select,
                          f"bodies[{p.body}].pins[{p.pin}].select") + a.body_vertices[p.body].start
    slots = np.searchsorted(c.fixed_vertices, ids)
    kf = next(m.keyframes for m in run.built.motions if np.array_equal(m.slots, slots))
    unit = np.zeros(kf.times.size)
    unit[p.keyframe] = 1.0

    def weight(t: float) -> float:
        return float(np.interp(kf._warped_time(t), kf.times, unit))
    return slots, weight


def scene_with(scene: Scene, values: Mapping[str, object]) -> Scene:
    """``scene`` with ``values`` set by key path (vectors as lists)."""
    return apply_overrides(scene, {k: (list(map(float, v)) if np.ndim(v) else float(v))
                                   for k, v in values.items()})
