"""The adjoint's terms: each term of backward Euler's step equation, linearized.

A step solves ``g(u; q_n, v_n, p) = P sum_terms g_t = 0`` for the full velocity ``u``
(``u = P^T x + F^T w``: ``x`` the free velocities, ``w = (p_{n+1} - q_n[F]) / dt`` the pinned
vertices' prescribed ones), with ``q_{n+1} = q_n + dt u`` and ``v_{n+1} = u``::

    inertia      g = M (u - v_n)
    elasticity   g = dt dV/dq(q_n + dt u)
    gravity      g = -dt M g_grav
    damping      g = dt D(q_n) u,  D = alpha M + beta K_psd(q_n)

An :class:`AdjointTerm` gives, at one step:

* :meth:`~AdjointTerm.matrix`: ``dg_t/du`` over every DOF (CSR ``data`` on
  ``model.pattern``, or any sparse ``(n_dofs, n_dofs)`` matrix); the step's transposed system
  is their sum restricted to the free DOFs;
* :meth:`~AdjointTerm.state_vjp`: ``-lambda^T dg_t/dq_n`` and ``-lambda^T dg_t/dv_n`` at fixed
  ``u`` (contributions to ``dL/dq_n``, ``dL/dv_n``);
* :meth:`~AdjointTerm.param_vjp`: ``-lambda^T dg_t/dp`` added into a :class:`Gradients`.

Another scheme (:mod:`fem3d.diff.schemes`) has the same terms with its ``h`` (``dq_{n+1}/du``)
in place of ``dt``, its base positions ``q_B`` in place of ``q_n`` and inertia target
``v_hat`` in place of ``v_n`` (:class:`StepPair`'s ``h``, ``qb``, ``vh``); damping's ``D``
stays at the start of the step (:meth:`AdjointTerm.start_vjp`).

Another term (contact, friction) plugs in through :func:`fem3d.diff.adjoint.register_term`:
a factory that returns such a term (plus the forward terms it adds to each step).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from fem3d.diff.damping import (
    DampingLinearization,
    linearize_damping,
    per_point,
    point_kernels,
    quadrature_points,
)
from fem3d.physics.assembly import hessian_data
from fem3d.physics.materials import info

__all__ = ["StepPair", "Gradients", "AdjointTerm", "InertiaAdjoint", "ElasticAdjoint",
           "GravityAdjoint", "DampingAdjoint", "element_groups", "psd_bilinear_vjp",
           "projection_weights"]


@dataclass
class StepPair:
    """One step, flat: ``q0, v0`` before, ``q1, u`` (``= v1`` in a dynamic scheme) after,
    ``dt``; ``step`` the step's number (``q0`` is the state after ``step`` steps) and ``t0``,
    ``t1`` its times; ``h``, ``qb``, ``vh``: the scheme's step map (backward Euler: ``dt``,
    ``q0``, ``v0``)."""

    q0: np.ndarray
    v0: np.ndarray
    q1: np.ndarray
    u: np.ndarray
    dt: float
    t1: float
    t0: float = 0.0
    step: int = 0
    #: the scheme's ``dq_{n+1}/du`` (None: ``dt``, backward Euler), base positions ``q_B``
    #: (``q_{n+1} = q_B + h u``; None: ``q0``) and inertia target (None: ``v0``)
    h: float | None = None
    qb: np.ndarray | None = None
    vh: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.h is None:
            self.h = self.dt
        if self.qb is None:
            self.qb = self.q0
        if self.vh is None:
            self.vh = self.v0


@dataclass
class Gradients:
    """What the backward pass accumulates (contributions to ``dL/dp``).

    Attributes
    ----------
    material : list of (k, n_params) float64 or None
        Per material group (:func:`element_groups`' order): ``dL/d(kernel params)`` per
        element (None when no material key is asked).
    density, rayleigh_mass, rayleigh_stiffness : (n_bodies,) float64
    gravity : (3,) float64
    extra : dict of str -> float or ndarray
        Keys of registered terms (:func:`fem3d.diff.adjoint.register_term`).
    """

    material: list | None
    density: np.ndarray
    rayleigh_mass: np.ndarray
    rayleigh_stiffness: np.ndarray
    gravity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    extra: dict = field(default_factory=dict)


class AdjointTerm:
    """One term of the step equation, linearized at a step (see the module docstring).

    ``linearize`` is called first at every step; the others may use what it kept.
    """

    name = "term"
    #: ``"velocity"``: its matrix is its derivative by the velocity ``u`` itself (inertia,
    #: damping); ``"position"``: through ``q_{n+1} = q_B + h u``
    variable = "position"
    #: the extra parameter keys (:func:`fem3d.diff.adjoint.register_term`) this term answers
    #: in this scene
    keys: tuple[str, ...] = ()

    def forward_terms(self) -> list:
        """Terms this one adds to the forward step's objective (default: none)."""
        return []

    def before_step(self, state) -> None:
        """Called before each forward step from ``state`` (first run and recomputations)."""

    def after_step(self, state) -> None:
        """Called after each forward step from ``state``."""

    def check_step(self, state, new) -> None:
        """Raise where the forward step from ``state`` to ``new`` is not one a run takes
        (default: every step is)."""

    def linearize(self, pair: StepPair) -> None:
        """Keep what the step needs (matrices at ``q_{n+1}`` or ``q_n``)."""

    def matrix(self):
        """``dg/du``: CSR ``data`` on ``model.pattern``, a sparse matrix, or None."""
        return None

    def state_vjp(self, lf: np.ndarray):
        """``(-lambda^T dg/dq_B, -lambda^T dg/dv_hat)`` (each ``(n_dofs,)`` or None): by the
        scheme's base positions and inertia target (backward Euler: ``q_n``, ``v_n``)."""
        return None, None

    def start_vjp(self, lf: np.ndarray):
        """``-lambda^T dg/dq_t`` by the positions at the start of the step where the term
        reads them directly (damping's ``D(q_t)``), ``(n_dofs,)`` or None; called after
        :meth:`state_vjp`, before :meth:`param_vjp`."""
        return None

    def param_vjp(self, lf: np.ndarray, grads: Gradients) -> None:
        """Add ``-lambda^T dg/dp`` into ``grads``."""


class _Bodies:
    """Per-body DOF ranges and element ranges of a model."""

    def __init__(self, arrays) -> None:
        self.vertices = arrays.body_vertices
        self.tets = arrays.body_tets

    def dot(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``a . b`` over each body's DOFs, ``(n_bodies,)``."""
        return np.array([float(a[3 * s.start:3 * s.stop] @ b[3 * s.start:3 * s.stop])
                         for s in self.vertices])


class InertiaAdjoint(AdjointTerm):
    """``M (u - v_n)``: ``M`` in ``u``, ``-M`` in ``v_n``, linear in density."""

    name = "inertia"
    variable = "velocity"

    def __init__(self, model, arrays, density: np.ndarray) -> None:
        self.model, self.bodies, self.rho = model, _Bodies(arrays), density

    def linearize(self, pair: StepPair) -> None:
        self.pair = pair

    def matrix(self):
        return self.model.mass.data

    def state_vjp(self, lf):
        self.Mlf = self.model.mass @ lf
        return None, self.Mlf

    def param_vjp(self, lf, grads):
        grads.density -= self.bodies.dot(self.Mlf, self.pair.u - self.pair.vh) / self.rho


class GravityAdjoint(AdjointTerm):
    """``-dt M g``: linear in ``g`` and in density."""

    name = "gravity"

    def __init__(self, model, arrays, gravity, density: np.ndarray) -> None:
        self.model, self.bodies, self.rho = model, _Bodies(arrays), density
        n = model.n_vertices
        self.g_full = np.zeros(3 * n) if gravity is None else np.tile(gravity, n)

    def linearize(self, pair: StepPair) -> None:
        self.dt = pair.h

    def param_vjp(self, lf, grads):
        Mlf = self.model.mass @ lf
        grads.gravity += self.dt * Mlf.reshape(-1, 3).sum(axis=0)
        grads.density += self.dt * self.bodies.dot(Mlf, self.g_full) / self.rho


def element_groups(model) -> list[tuple]:
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


def _lam_e(model, lf: np.ndarray, els: np.ndarray) -> np.ndarray:
    """``lf``'s values at the nodes of elements ``els``, node-major ``(k, 3 n_nodes)``."""
    return lf.reshape(-1, 3)[model.T[els]].reshape(-1, model.element.n_dofs)


class ElasticAdjoint(AdjointTerm):
    """``dt dV/dq(q_n + dt u)``: ``dt^2 H(q_{n+1})`` in ``u``, ``dt H`` in ``q_n``; the
    kernel parameters through the generated ``dgradient_dparams`` (one call per group)."""

    name = "elasticity"

    def __init__(self, model, groups: list[tuple]) -> None:
        self.model, self.groups = model, groups

    def linearize(self, pair: StepPair) -> None:
        self.pair = pair
        self.H = hessian_data(self.model, pair.q1)

    def matrix(self):
        return (self.pair.h * self.pair.h) * self.H

    def state_vjp(self, lf):
        return -self.pair.h * (self.model.csr(self.H) @ lf), None

    def param_vjp(self, lf, grads):
        if grads.material is None:
            return
        model, dt = self.model, self.pair.h
        x = self.pair.q1.reshape(-1, 3)
        for acc, (g, els, params, inputs) in zip(grads.material, self.groups, strict=True):
            G = g.kernels.dgradient_dparams(x[model.T[els]], model.dphi_dX[els],
                                            model.vol[els], *inputs, params)
            acc -= dt * np.einsum("ea,eap->ep", _lam_e(model, lf, els), G)


class DampingAdjoint(AdjointTerm):
    """``dt D(q_n) u`` with ``D = alpha M + beta K_psd(q_n)``: linear in ``alpha``, ``beta``
    and density (through ``M``). ``K_psd``'s derivatives by ``q_n`` and by the kernel
    parameters: exact, from the generated ``d3psi_contract`` (the third derivative of ``psi``
    contracted with a 9x9 matrix) and the derivative of the PSD projection (Daleckii-Krein:
    :func:`projection_weights`), from the eigendecompositions of the step's
    :class:`~fem3d.diff.damping.DampingLinearization` (kept by the run's
    :class:`~fem3d.diff.damping.RecordingDamping` when the forward step was recorded, else
    made here, once for ``D`` and the derivative); central differences per element
    (relative step ``1e-6``) only for a kernel module without ``d3psi_contract`` (an old C
    build)."""

    name = "damping"
    variable = "velocity"

    def __init__(self, system, arrays, groups: list[tuple], density: np.ndarray,
                 recorder=None) -> None:
        self.system, self.model, self.groups = system, system.model, groups
        #: the run's :class:`~fem3d.diff.damping.RecordingDamping` (None: the system's own
        #: damping term builds ``D``, as in an old C build without ``d3psi_contract``)
        self.recorder = recorder
        self.lin = None
        self.bodies, self.rho = _Bodies(arrays), density
        n_tets = self.model.n_tets
        self.alpha_b = np.array([float(np.broadcast_to(system.loads.rayleigh_alpha,
                                                       (self.model.n_vertices,))[s.start])
                                 if s.stop > s.start else 0.0 for s in arrays.body_vertices])
        self.beta = np.broadcast_to(np.asarray(system.loads.rayleigh_beta, dtype=np.float64),
                                    (n_tets,))
        self.beta_any = bool(np.any(self.beta > 0))

    def linearize(self, pair: StepPair) -> None:
        self.pair = pair
        self._exact = None
        rec = self.recorder
        if rec is not None:  # D and the eigendecompositions of one linearization
            lin = rec.take(pair.step, pair.q0)
            self.lin = lin if lin is not None else linearize_damping(rec, self.groups, pair.q0,
                                                                     rec.B)
            self.D = pair.h * self.lin.data
            return
        data = self.system.loads.damping_data(pair.q0)
        self.D = None if data is None else pair.h * data

    def matrix(self):
        return self.D

    @property
    def exact(self) -> bool:
        """Whether every group's per-``F`` kernels have ``d3psi_contract`` (else:
        differences)."""
        return all(hasattr(point_kernels(g), "d3psi_contract") for g, _, _, _ in self.groups)

    def start_vjp(self, lf):
        self._exact = None
        if not self.beta_any:
            return None
        if self.exact:
            self._exact = _damping_exact(self, lf, None if self.recorder is None else self.lin)
            return -self.pair.h * self._exact[0]
        return -self.pair.h * _damping_state_vjp(self, self.pair.q0, lf, self.pair.u)

    def param_vjp(self, lf, grads):
        dt, u = self.pair.h, self.pair.u
        Mlf_u = self.bodies.dot(self.model.mass @ lf, u)
        grads.rayleigh_mass -= dt * Mlf_u
        grads.density -= dt * self.alpha_b * Mlf_u / self.rho
        if not self.beta_any:
            return
        if self._exact is not None:
            _, per_tet, per_group = self._exact
        else:
            per_tet = _bilinear(self, self.pair.q0, lf, u, with_beta=False)
            per_group = _damping_param_vjp(self, lf) if grads.material is not None else None
        grads.rayleigh_stiffness -= dt * np.array(
            [float(per_tet[s].sum()) for s in self.bodies.tets])
        if grads.material is not None:
            for acc, d in zip(grads.material, per_group, strict=True):
                acc -= dt * d


def projection_weights(values: np.ndarray) -> np.ndarray:
    """``Gamma_ij`` of the PSD projection ``f(A) = V max(Lambda, 0) V^T``: its derivative is
    ``V (Gamma o (V^T dA V)) V^T`` with ``Gamma_ij = (f(l_i) - f(l_j)) / (l_i - l_j)`` (1
    where both eigenvalues are positive, 0 where neither is). ``values``: ``(m, n)``."""
    pos = values > 0
    f = np.maximum(values, 0.0)
    li, lj = values[:, :, None], values[:, None, :]
    mixed = pos[:, :, None] != pos[:, None, :]
    denom = np.where(mixed, li - lj, 1.0)
    return np.where(mixed, (f[:, :, None] - f[:, None, :]) / denom,
                    (pos[:, :, None] & pos[:, None, :]).astype(np.float64))


def psd_bilinear_vjp(kernels, F: np.ndarray, a: np.ndarray, b: np.ndarray, inputs,
                     params, eig=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``s = a^T A_psd(F) b`` per element and its exact derivatives by ``F`` and by the
    parameters (``A = dP/dF``, projected to PSD where indefinite, as ``hessian_psd`` does).

    Parameters
    ----------
    kernels : KernelModule
        The material's (``d2psi_dF2``, ``d3psi_contract``).
    F : (k, 3, 3) float64
    a, b : (k, 9) float64
    inputs : tuple of (k, ...) float64
        The material's per-element inputs.
    params : (k, n_params) float64
    eig : (bad, values, V), optional
        The projected elements and their eigendecompositions at ``F``
        (:class:`fem3d.diff.damping.DampingLinearization`); None: from ``eigh`` here.

    Returns
    -------
    s : (k,), dF : (k, 3, 3), dparams : (k, n_params)
    """
    A = kernels.d2psi_dF2(F, *inputs, params).reshape(-1, 9, 9)
    if eig is None:
        values, V = np.linalg.eigh(A)
        bad = np.flatnonzero((values < 0.0).any(axis=1))  # as hessian_psd: PSD A kept
        lb, Vb = values[bad], V[bad]
    else:
        bad, lb, Vb = eig
    C = a[:, :, None] * b[:, None, :]
    s = np.einsum("ei,eij,ej->e", a, A, b)
    if bad.size:  # batched matmul (BLAS), not einsum: 4x faster on 9x9 blocks
        VbT = Vb.transpose(0, 2, 1)
        at, bt = (VbT @ a[bad][:, :, None])[:, :, 0], (VbT @ b[bad][:, :, None])[:, :, 0]
        G = projection_weights(lb) * at[:, :, None] * bt[:, None, :]
        C[bad] = Vb @ G @ VbT
        s[bad] = np.sum(at * np.maximum(lb, 0.0) * bt, axis=1)
    dF, dp = kernels.d3psi_contract(F, C, *inputs, params)
    return s, dF, dp


def _damping_exact(adj: DampingAdjoint, lf: np.ndarray,
                   lin: DampingLinearization | None = None):
    """Exact ``d/dq_n`` and ``d/dparams`` of ``sum_e beta_e sum_q w_q a_q^T A_psd(F_q) b_q``
    over the elements' quadrature points (``a_q = B_q lambda_e``, ``b_q = B_q u_e``; ``B_q``:
    ``dF_q/dx_e``, :func:`~fem3d.diff.damping.quadrature_points`) and the per-element
    ``sum_q w_q a_q^T A_psd b_q`` (for ``d/dbeta``): ``(dq (n_dofs,), (n_tets,), [per group
    (k, n_params)])``; ``lin``: the eigendecompositions at ``q_n`` (None: computed here)."""
    model, pair = adj.model, adj.pair
    x = pair.q0.reshape(-1, 3)
    lam, u = lf.reshape(-1, 3), pair.u.reshape(-1, 3)
    dq = np.zeros((model.n_vertices, 3))
    per_tet = np.zeros(model.n_tets)
    per_group = []
    for i, (g, els, params, inputs) in enumerate(adj.groups):
        D, w_q = quadrature_points(model, els)  # (k nq, n, 3), (k, nq)
        nq = w_q.shape[1]
        T = per_point(model.T[els], nq)
        F = np.einsum("evc,evj->ecj", x[T], D)
        a = np.einsum("evc,evj->ecj", lam[T], D).reshape(-1, 9)
        b = np.einsum("evc,evj->ecj", u[T], D).reshape(-1, 9)
        s, dF, dp = psd_bilinear_vjp(point_kernels(g), F, a, b,
                                     tuple(per_point(v, nq) for v in inputs),
                                     per_point(params, nq),
                                     None if lin is None else lin.eig[i])
        w = (adj.beta[els][:, None] * w_q).reshape(-1)
        f = (w[:, None, None] * dF) @ D.transpose(0, 2, 1)  # (k nq, 3 c, n v)
        for c in range(3):
            dq[:, c] += np.bincount(T.reshape(-1), weights=f[:, c, :].reshape(-1),
                                    minlength=model.n_vertices)
        per_tet[els] = (w_q * s.reshape(w_q.shape)).sum(axis=1)
        per_group.append((w[:, None] * dp).reshape(els.size, nq, -1).sum(axis=1))
    return dq.reshape(-1), per_tet, per_group


def _bilinear(adj: DampingAdjoint, q0, lf, v, *, with_beta: bool = True,
              group_params=None, x_e=None) -> np.ndarray:
    """``beta_e lambda_e^T H_psd,e v_e`` of every element (``with_beta=False``: without
    ``beta_e``), at ``q0`` or at element positions ``x_e (m, n_nodes, 3)``; ``group_params``: a
    function of the group index giving its (perturbed) parameters."""
    model = adj.model
    if x_e is None:
        x_e = np.take(q0.reshape(-1, 3), model.T, axis=0)
    lam, vv = lf.reshape(-1, 3), v.reshape(-1, 3)
    out = np.zeros(model.n_tets)
    for i, (g, els, params, inputs) in enumerate(adj.groups):
        p = params if group_params is None else group_params(i)
        H = g.kernels.hessian_psd(x_e[els], model.dphi_dX[els], model.vol[els], *inputs, p)
        d = model.element.n_dofs
        out[els] = np.einsum("ea,eab,eb->e", lam[model.T[els]].reshape(-1, d), H,
                             vv[model.T[els]].reshape(-1, d))
    return out * adj.beta if with_beta else out


def _damping_param_vjp(adj: DampingAdjoint, lf) -> list[np.ndarray]:
    """``d/dp_j (beta_e lambda_e^T H_psd,e(q_n) u_e)`` per element and kernel parameter
    ``j`` of each group: central differences (step ``1e-6`` of the parameter's size)."""
    out = []
    q0, u = adj.pair.q0, adj.pair.u
    for i, (_, els, params, _) in enumerate(adj.groups):
        d = np.zeros_like(params)
        size = np.maximum(np.abs(params), np.abs(params).max(axis=1, keepdims=True) * 1e-3)
        size[size == 0] = 1.0
        for j in range(params.shape[1]):
            h = 1e-6 * size[:, j]
            diff = 0.0
            for sign in (1.0, -1.0):
                shifted = params.copy()
                shifted[:, j] += sign * h

                def group_params(k, i=i, shifted=shifted):
                    return shifted if k == i else adj.groups[k][2]
                diff = diff + sign * _bilinear(adj, q0, lf, u, group_params=group_params)[els]
            d[:, j] = diff / (2 * h)
        out.append(d)
    return out


def _damping_state_vjp(adj: DampingAdjoint, q0, lf, v1) -> np.ndarray:
    """``d/dq0`` of ``lambda^T beta K_psd(q0) v1``: central differences per element DOF."""
    model = adj.model
    L = float(np.linalg.norm(np.ptp(model.X, axis=0)))
    h = 1e-6 * L
    out = np.zeros(model.n_dofs)
    base = q0.reshape(-1, 3)
    for a in range(model.element.n_dofs):
        vert, comp = divmod(a, 3)
        diffs = 0.0
        for sign in (1.0, -1.0):
            x = np.take(base, model.T, axis=0)
            x[:, vert, comp] += sign * h
            diffs = diffs + sign * _bilinear(adj, q0, lf, v1, x_e=x)
        np.add.at(out, 3 * model.T[:, vert] + comp, diffs / (2 * h))
    return out


def sparse_of(model, m) -> sp.csr_matrix:
    """A term's matrix as a full ``(n_dofs, n_dofs)`` CSR matrix."""
    return model.csr(m) if isinstance(m, np.ndarray) else sp.csr_matrix(m)
