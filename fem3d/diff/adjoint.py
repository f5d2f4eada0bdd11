"""The discrete adjoint of a backward-Euler trajectory (no pulls, fixed pins).

Each step solves ``g(x; q_n, v_n, p) = 0`` over the free velocities ``x = v_{n+1}`` (``g``:
the gradient of backward Euler's objective, :mod:`fem3d.solve.backward_euler`)::

    g = M (v_{n+1} - v_n) + dt dV/dq(q_n + dt v_{n+1}) - dt M g_grav + dt D(q_n) v_{n+1}

with ``D = alpha M + beta K_psd(q_n)``. The backward pass runs the steps in reverse: with
``(q_bar, v_bar)`` the loss's total derivative by ``(q_{n+1}, v_{n+1})`` it solves the
transposed (symmetric) Newton matrix ``A lambda = P (v_bar + dt q_bar)``, ``A = M + dt^2
H(q_{n+1}) + dt D(q_n)`` on the free DOFs, with the :class:`~fem3d.solve.system.System`'s
sparse direct solver, and accumulates ``-lambda^T dg/dp`` for every parameter and
``-lambda^T dg/d(q_n, v_n)`` for the state.

What is exact and what is not:

* The gradient is the derivative of the procedure that ran only if Newton ran to
  convergence: :func:`simulate` runs every step to ``rtol`` (default ``1e-11`` of the first
  gradient norm, no iteration cap). A run capped at a few Newton iterations (``fem3d run``'s
  default) is a different map; its data is still a fine fitting target.
* Elastic parameter derivatives use the generated ``dgradient_dparams`` kernels and the
  generated Jacobian of each material's ``E, nu`` mapping: exact.
* The stiffness-proportional damping ``beta K_psd(q_n)`` depends on ``q_n`` and on the
  material parameters through the PSD-projected element Hessians; the generator has no third
  derivatives, so these two pieces are central finite differences per element (relative error
  about ``1e-9``). With ``rayleigh_stiffness = 0`` (the default) everything is exact.
* Terms beyond the model's (IPC contact and friction) enter through a term adjoint
  (:class:`TermAdjoint`; :mod:`fem3d.diff.contact` says what it differentiates and holds).
* Held fixed / not supported: pull springs, moving pins, material
  ``regions`` and ``cell_fields`` (the body's ``E, nu`` derivative covers the tets that take
  them), angular velocity.

Memory: the states at every ``checkpoint_every``-th step are kept; the backward pass
recomputes each segment from its checkpoint (one extra forward run in total), so memory is
``O(N / k + k)`` states for ``N`` steps.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fem3d.diff.contact import CONTACT_KEYS, contact_adjoint
from fem3d.errors import ParameterError, SimulationError
from fem3d.physics.assembly import hessian_data
from fem3d.physics.materials import info, parameters_jacobian_from
from fem3d.scene.build import build
from fem3d.scene.load import apply_overrides
from fem3d.scene.spec import Scene
from fem3d.solve.backward_euler import backward_euler, model_terms, newton_options
from fem3d.solve.state import State
from fem3d.solve.system import System

__all__ = ["PositionLoss", "simulate", "trajectory_gradient", "PARAMETER_KEYS"]

#: The parameter keys :func:`trajectory_gradient` differentiates (``i``: a body index).
PARAMETER_KEYS = (
    "bodies[i].material.E", "bodies[i].material.nu", "bodies[i].material.density",
    "bodies[i].damping.rayleigh_mass", "bodies[i].damping.rayleigh_stiffness",
    "bodies[i].velocity", "simulation.gravity",
)
#: the term adjoints' keys (:class:`TermAdjoint`)
PARAMETER_KEYS = PARAMETER_KEYS + CONTACT_KEYS
_TERM_KEYS = frozenset(CONTACT_KEYS)
_BODY_KEY = re.compile(r"^bodies\[(\d+)\]\.(material\.E|material\.nu|material\.density|"
                       r"damping\.rayleigh_mass|damping\.rayleigh_stiffness|velocity)$")


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


class TermAdjoint(Protocol):
    """The adjoint of objective terms beyond the model's (:mod:`fem3d.diff.contact`): what
    they add to the forward step and to each backward step ``s0 -> s1``, all in positions.

    ``keys``: the parameters it differentiates; ``terms``: the forward step's extra terms;
    ``check_start``: refuse an inadmissible initial state; ``before_step``/``after_step``:
    around each forward step (record, or replay on a recomputation, what the terms hold
    fixed); ``linearize``: set up step ``s0 -> s1``; ``hessian``: the terms' exact Hessian
    at ``s1`` (3n, 3n); ``state_vjp(lf)``: ``d/dq0`` of ``lf^T`` their gradient at fixed
    unknowns (3n,); ``param_vjp(key, lf)``: ``lf^T d grad / d key``.
    """

    keys: tuple[str, ...]
    terms: list

    def check_start(self, q: np.ndarray) -> None: ...
    def before_step(self, state: State) -> None: ...
    def after_step(self, state: State) -> None: ...
    def linearize(self, s0: State, s1: State, dt: float, keys: Sequence[str]) -> None: ...
    def hessian(self) -> sp.spmatrix: ...
    def state_vjp(self, lf: np.ndarray) -> np.ndarray: ...
    def param_vjp(self, key: str, lf: np.ndarray) -> float: ...


@dataclass
class _Run:
    scene: Scene
    system: System
    arrays: object
    state0: State
    dt: float
    rtol: float
    atol_factor: float
    extensions: list = field(default_factory=list)  # TermAdjoint

    def step(self, state: State) -> State:
        extra = [t for e in self.extensions for t in e.terms]
        for e in self.extensions:
            e.before_step(state)
        new, stats = backward_euler(
            self.system, [*model_terms(self.system), *extra], state, self.dt,
            max_iterations=None, rtol=self.rtol, atol_factor=self.atol_factor,
            linear_solver="direct", options=newton_options("exact"))
        if not stats.converged:
            raise SimulationError("Newton did not converge: the adjoint needs converged steps",
                                  step=state.step)
        for e in self.extensions:
            e.after_step(state)
        return new


def _prepare(scene: Scene, rtol: float, atol_factor: float) -> _Run:
    if scene.pulls:  # a run applies them: differentiating without them would be wrong
        raise ParameterError("trajectory_gradient: scripted pulls are not differentiated yet "
                             f"(the scene has {len(scene.pulls)}; remove them with pulls = [])")
    if scene.simulation.integrator != "implicit":
        raise ParameterError("trajectory_gradient: only simulation.integrator = 'implicit' "
                             f"(backward Euler) is differentiated, got "
                             f"{scene.simulation.integrator!r}")
    built = build(scene)
    system = System(built.model, built.constraints, scene.simulation.linear_solver,
                    gravity=built.gravity, rayleigh_alpha=built.rayleigh_alpha,
                    rayleigh_beta=built.rayleigh_beta)
    if built.motions:
        raise ParameterError("trajectory_gradient: moving pins are not supported yet")
    a = built.arrays
    v0 = np.array(a.v0, dtype=np.float64)
    v0[built.constraints.fixed_vertices] = 0.0
    state = State(q=built.model.X.copy(), v=v0, t=0.0, step=0)
    extensions = [e for e in (contact_adjoint(scene, built),) if e is not None]
    for e in extensions:
        e.check_start(state.q)
    return _Run(scene, system, a, state, float(scene.simulation.dt), rtol, atol_factor,
                extensions)


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


def trajectory_gradient(
    scene: Scene,
    loss: PositionLoss | Callable,
    params: Sequence[str],
    *,
    steps: int | None = None,
    checkpoint_every: int = 10,
    rtol: float = 1e-11,
    atol_factor: float = 1e-16,
) -> tuple[float, dict[str, float | np.ndarray]]:
    """The loss of a backward-Euler run of ``scene`` and its gradient by ``params``.

    Parameters
    ----------
    scene : Scene
    loss : PositionLoss, or an object with ``frame(step, q) -> (value, dL/dq or None)``
        and ``last_step``.
    params : sequence of str
        Keys of :data:`PARAMETER_KEYS` (``bodies[0].material.E``, ``simulation.gravity``).
    steps : int, optional
        Steps to run (default: ``loss.last_step``).
    checkpoint_every : int, optional
        States kept every ``k`` steps; the backward pass recomputes the others.
    rtol, atol_factor : float, optional
        Newton's tolerances (run to convergence: see the module docstring).

    Returns
    -------
    (float, dict of str -> float or (3,) float64)
    """
    for key in params:
        if key != "simulation.gravity" and key not in _TERM_KEYS and not _BODY_KEY.match(key):
            raise ParameterError(f"trajectory_gradient: cannot differentiate {key!r}; "
                                 f"supported: {', '.join(PARAMETER_KEYS)}")
    run = _prepare(scene, rtol, atol_factor)
    for key in set(params) & _TERM_KEYS - {k for e in run.extensions for k in e.keys}:
        raise ParameterError(f"trajectory_gradient: cannot differentiate {key!r} in this "
                             "scene (contact keys need contact.enabled = true, contact.kappa "
                             "a fixed kappa)")
    n_steps = int(loss.last_step if steps is None else steps)
    k = max(1, int(checkpoint_every))
    checkpoints = {0: run.state0}
    state, value = run.state0, 0.0
    for n in range(n_steps):
        state = run.step(state)
        value += loss.frame(n + 1, state.q)[0]
        if (n + 1) % k == 0 and n + 1 < n_steps:
            checkpoints[n + 1] = state
    grads = _backward(run, loss, params, checkpoints, n_steps, k)
    return value, grads


def _backward(run: _Run, loss, params, checkpoints: dict, n_steps: int, k: int) -> dict:
    adj = _Adjoint(run, params)
    n_dof = run.state0.q.size
    q_bar, v_bar = np.zeros(n_dof), np.zeros(n_dof)
    for start in sorted(checkpoints, reverse=True):
        segment = [checkpoints[start]]
        for _ in range(start, min(start + k, n_steps)):
            segment.append(run.step(segment[-1]))
        for i in range(len(segment) - 1, 0, -1):
            n = start + i  # the state after step n
            grad = loss.frame(n, segment[i].q)[1]
            if grad is not None:
                q_bar += grad.reshape(-1)
            q_bar, v_bar = adj.step(segment[i - 1], segment[i], q_bar, v_bar)
    return adj.result(v_bar)


class _Adjoint:
    """One backward step at a time; accumulates the parameters' gradients."""

    def __init__(self, run: _Run, params: Sequence[str]) -> None:
        self.run, self.params = run, list(params)
        system = run.system
        self.model, self.c = system.model, system.constraints
        self.free = self.c.free_dofs
        self.dt = run.dt
        self.a = run.arrays
        self.acc = {key: np.zeros(3) if key.endswith(("velocity", "gravity")) else 0.0
                    for key in self.params}
        self.groups = _element_groups(self.model)
        n_tets = self.model.n_tets
        alpha = np.broadcast_to(np.asarray(system.rayleigh_alpha, dtype=np.float64),
                                (self.model.n_vertices,))
        self.alpha_dof = np.repeat(alpha, 3)
        self.beta = np.broadcast_to(np.asarray(system.rayleigh_beta, dtype=np.float64),
                                    (n_tets,))
        g = system.gravity
        n = self.model.n_vertices
        self.g_full = np.zeros(3 * n) if g is None else np.tile(g, n)

    def _newton_matrix(self, q0: np.ndarray, q1: np.ndarray) -> sp.csr_matrix:
        model, dt = self.model, self.dt
        data = model.mass.data + dt * dt * hessian_data(model, q1)
        damping = self.run.system.damping_data(q0)
        if damping is not None:
            data = data + dt * damping
        A = model.csr(data)[self.free][:, self.free].tocsr()
        for e in self.run.extensions:  # entries between bodies widen the solver's pattern
            A = self.run.system.add_hessian(A, e.hessian(), dt * dt)
        return A

    def _solve(self, A: sp.csr_matrix, b: np.ndarray) -> np.ndarray:
        system = self.run.system
        try:
            system.factorize(A, shifts=False)
            return system.solve(b)
        except SimulationError:  # indefinite at this state: a general sparse LU
            return spla.spsolve(A.tocsc(), b)

    def step(self, s0: State, s1: State, q_bar: np.ndarray, v_bar: np.ndarray):
        dt, model = self.dt, self.model
        q0, q1 = s0.q.reshape(-1), s1.q.reshape(-1)
        v0, v1 = s0.v.reshape(-1), s1.v.reshape(-1)
        for e in self.run.extensions:
            e.linearize(s0, s1, dt, self.params)
        rhs = (v_bar + dt * q_bar)[self.free]
        lam = self._solve(self._newton_matrix(q0, q1), rhs)
        lf = np.zeros(model.n_dofs)
        lf[self.free] = lam
        H1 = model.csr(hessian_data(model, q1))
        q_bar_new = q_bar - dt * (H1 @ lf)  # q_{n+1} = q_n + dt P^T x
        for e in self.run.extensions:
            q_bar_new -= dt * e.state_vjp(lf)
        beta_any = bool(np.any(self.beta > 0))
        if beta_any:
            q_bar_new -= dt * _damping_state_vjp(self, q0, lf, v1)
        Mlf = model.mass @ lf
        v_bar_new = np.zeros_like(Mlf)  # the pinned DOFs' velocities are prescribed (0)
        v_bar_new[self.free] = Mlf[self.free]
        self._accumulate(q0, q1, v0, v1, lf, Mlf, beta_any)
        return q_bar_new, v_bar_new

    def _accumulate(self, q0, q1, v0, v1, lf, Mlf, beta_any: bool) -> None:
        dt = self.dt
        for key in self.params:
            if key == "simulation.gravity":
                self.acc[key] += dt * Mlf.reshape(-1, 3).sum(axis=0)
                continue
            if key in _TERM_KEYS:
                self.acc[key] -= dt * sum(e.param_vjp(key, lf) for e in self.run.extensions
                                          if key in e.keys)
                continue
            b, what = _body_key(key)
            dofs = _body_dofs(self.a.body_vertices[b])
            tets = np.arange(self.a.body_tets[b].start, self.a.body_tets[b].stop)
            if what in ("material.E", "material.nu"):
                which = 0 if what == "material.E" else 1
                mat = self.run.scene.bodies[b].material
                if mat.E is None:
                    raise ParameterError(f"{key}: body {b}'s material is given by its own "
                                         "parameters; E and nu derivatives need E and nu")
                E_nu = (float(mat.E), float(mat.nu))
                self.acc[key] -= dt * _elastic_vjp(self, q1, lf, tets, which, E_nu)
                if beta_any:
                    self.acc[key] -= dt * _damping_param_vjp(self, q0, lf, v1, tets, which,
                                                             E_nu)
            elif what == "material.density":
                rho = float(self.run.scene.bodies[b].material.density)
                u = (v1 - v0) - dt * self.g_full + dt * self.alpha_dof * v1
                self.acc[key] -= float(Mlf[dofs] @ u[dofs]) / rho
            elif what == "damping.rayleigh_mass":
                self.acc[key] -= dt * float(Mlf[dofs] @ v1[dofs])
            elif what == "damping.rayleigh_stiffness":
                self.acc[key] -= dt * float(np.sum(_element_bilinear(self, q0, lf, v1, tets,
                                                                     with_beta=False)))

    def result(self, v_bar0: np.ndarray) -> dict:
        out = {}
        for key in self.params:
            if key.endswith("velocity"):
                b, _ = _body_key(key)
                vb = v_bar0.reshape(-1, 3)[self.a.body_vertices[b]]
                out[key] = vb.sum(axis=0)  # 0 on pinned vertices: they start at rest
            else:
                out[key] = self.acc[key] if isinstance(self.acc[key], np.ndarray) \
                    else float(self.acc[key])
        return out


def _body_key(key: str) -> tuple[int, str]:
    match = _BODY_KEY.match(key)
    assert match is not None
    return int(match.group(1)), match.group(2)


def _body_dofs(vertices: slice) -> np.ndarray:
    return np.arange(3 * vertices.start, 3 * vertices.stop)


def _element_groups(model) -> list[tuple]:
    """``(group, element indices, params (k, n_params), inputs)`` of every material group."""
    out = []
    for g in model.groups:
        els = np.arange(model.n_tets) if g.elements is None else np.asarray(g.elements)
        params = np.asarray(g.params, dtype=np.float64)
        params = np.broadcast_to(params, (els.size, params.shape[-1])).copy()
        inputs = tuple(np.broadcast_to(np.asarray(x, dtype=np.float64),
                                       (els.size, *np.shape(x)[-len(s):]))
                       for x, s in zip(g.inputs, info(g.material).per_element_inputs.values(),
                                       strict=True))
        out.append((g, els, params, inputs))
    return out


def _group_E_nu_jacobian(g, els: np.ndarray, which: int, E_nu: tuple) -> np.ndarray:
    """``d params / d E`` (``which = 0``) or ``/ d nu`` per element, ``(k, n_params)``, at the
    body's ``E, nu``."""
    jac = parameters_jacobian_from(g.material, *E_nu)
    row = np.array([jac[p][which] for p in info(g.material).param_names], dtype=np.float64)
    return np.broadcast_to(row, (els.size, row.size))


def _elastic_vjp(adj: _Adjoint, q1: np.ndarray, lf: np.ndarray, tets: np.ndarray,
                 which: int, E_nu: tuple) -> float:
    """``lambda^T d(dV/dq)/dE`` (or ``/dnu``) over the elements ``tets``."""
    model = adj.model
    x = q1.reshape(-1, 3)
    lam = lf.reshape(-1, 3)
    total = 0.0
    for g, els, params, inputs in adj.groups:
        sel = np.isin(els, tets)
        if not sel.any():
            continue
        e = els[sel]
        G = g.kernels.dgradient_dparams(x[model.T[e]], model.dphi_dX[e], model.vol[e],
                                        *(a[sel] for a in inputs), params[sel])
        contrib = np.einsum("ea,eap->ep", lam[model.T[e]].reshape(-1, 12), G)
        jac = _group_E_nu_jacobian(g, els, which, E_nu)[sel]
        total += float(np.sum(contrib * jac))
    return total


def _element_bilinear(adj: _Adjoint, q0, lf, v1, tets, *, params_of=None,
                      with_beta: bool = True) -> np.ndarray:
    """``beta_e lambda_e^T H_psd,e(q0) v1_e`` per element of ``tets`` (``H_psd`` with the
    volume; ``with_beta=False``: without ``beta_e``)."""
    model = adj.model
    x = q0.reshape(-1, 3)
    lam, v = lf.reshape(-1, 3), v1.reshape(-1, 3)
    out = []
    for g, els, params, inputs in adj.groups:
        sel = np.isin(els, tets)
        if not sel.any():
            continue
        e = els[sel]
        p = params[sel] if params_of is None else params_of(g, els, params, sel)
        H = g.kernels.hessian_psd(x[model.T[e]], model.dphi_dX[e], model.vol[e],
                                  *(a[sel] for a in inputs), p)
        out.append(np.einsum("ea,eab,eb->e", lam[model.T[e]].reshape(-1, 12), H,
                             v[model.T[e]].reshape(-1, 12)) * (adj.beta[e] if with_beta else 1.0))
    return np.concatenate(out) if out else np.zeros(0)


def _damping_param_vjp(adj: _Adjoint, q0, lf, v1, tets, which: int, E_nu: tuple) -> float:
    """``d/dE`` (or ``nu``) of ``lambda^T beta K_psd(q0) v1``: central differences of the
    element parameters along the mapping's Jacobian (a relative step of ``1e-6``)."""
    steps = {}

    def shifted(sign):
        def params_of(g, els, params, sel):
            jac = _group_E_nu_jacobian(g, els, which, E_nu)[sel]
            scale = np.abs(params[sel]).max(axis=1) / np.maximum(np.abs(jac).max(axis=1),
                                                                 1e-300)
            h = 1e-6 * scale
            steps[id(g)] = h
            return params[sel] + sign * h[:, None] * jac
        return params_of

    plus = _element_bilinear(adj, q0, lf, v1, tets, params_of=shifted(1.0))
    minus = _element_bilinear(adj, q0, lf, v1, tets, params_of=shifted(-1.0))
    h = np.concatenate([steps[id(g)] for g, els, _, _ in adj.groups
                        if np.isin(els, tets).any()])
    return float(np.sum((plus - minus) / (2 * h)))


def _damping_state_vjp(adj: _Adjoint, q0, lf, v1) -> np.ndarray:
    """``d/dq0`` of ``lambda^T beta K_psd(q0) v1``: central differences per element DOF."""
    model = adj.model
    L = float(np.linalg.norm(np.ptp(model.X, axis=0)))
    h = 1e-6 * L
    out = np.zeros(model.n_dofs)
    tets = np.arange(model.n_tets)
    base = q0.reshape(-1, 3)
    for a in range(12):
        vert, comp = divmod(a, 3)
        diffs = 0.0
        for sign in (1.0, -1.0):
            x = np.take(base, model.T, axis=0)
            x[:, vert, comp] += sign * h
            diffs = diffs + sign * _bilinear_at(adj, x, lf, v1)
        np.add.at(out, 3 * model.T[tets, vert] + comp, diffs / (2 * h))
    return out


def _bilinear_at(adj: _Adjoint, x_e: np.ndarray, lf, v1) -> np.ndarray:
    """``beta vol lambda_e^T H_psd(x_e) v1_e`` of every element at element positions
    ``x_e (m, 4, 3)``."""
    model = adj.model
    lam, v = lf.reshape(-1, 3), v1.reshape(-1, 3)
    out = np.zeros(model.n_tets)
    for g, els, params, inputs in adj.groups:
        H = g.kernels.hessian_psd(x_e[els], model.dphi_dX[els], model.vol[els], *inputs, params)
        out[els] = np.einsum("ea,eab,eb->e", lam[model.T[els]].reshape(-1, 12), H,
                             v[model.T[els]].reshape(-1, 12)) * adj.beta[els]
    return out


def scene_with(scene: Scene, values: Mapping[str, object]) -> Scene:
    """``scene`` with ``values`` set by key path (vectors as lists)."""
    return apply_overrides(scene, {k: (list(map(float, v)) if np.ndim(v) else float(v))
                                   for k, v in values.items()})
