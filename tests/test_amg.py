"""AMG-preconditioned CG for backward Euler's Newton systems (``"amg"`` back end)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pyamg")

from test_assembly import box_mesh  # noqa: E402

from fem3d import linsolve  # noqa: E402
from fem3d.constraints import Constraints  # noqa: E402
from fem3d.integrators import State, System, implicit_euler, linearly_implicit_euler  # noqa: E402
from fem3d.model import build_model  # noqa: E402


def clamped_box(n=(6, 6, 6), E=6e5, rho=100.0):
    X, T = box_mesh(*n, size=(1.0, 1.0, 1.0))
    model = build_model(X, T, E=E, nu=0.4, rho=rho)
    fixed = np.flatnonzero(X[:, 2] <= 1e-12)
    return model, Constraints.from_fixed_vertices(X, fixed)


def swinging(model, constraints, a=4.0):
    X = model.X
    v = np.zeros_like(X)
    v[:, 0] = a * X[:, 2] ** 2
    v[:, 1] = -0.75 * a * X[:, 2] * X[:, 0]
    v[constraints.fixed_vertices] = 0.0
    return State(q=X.copy(), v=v)


def run(system, state, steps, dt=0.01, **kw):
    out, all_stats = [], []
    for _ in range(steps):
        state, stats = implicit_euler(system, state, dt, max_iterations=None, **kw)
        assert stats.converged
        out.append(state.q)
        all_stats.append(stats)
    return out, all_stats


def test_amg_trajectory_agrees_with_the_direct_solve():
    """Both Newton runs stop at the same gradient tolerance ``|g| <= tol`` (rtol 1e-10 of the
    first gradient), so their end points differ by at most ``2 tol |A^-1|``: here 1e-8 of the
    mesh size over 6 steps (measured about 1e-10); the inexact Newton needs more iterations
    but no factorization."""
    model, c = clamped_box()
    start = swinging(model, c)
    direct, dstats = run(System(model, c, linsolve.default_backend()), start, 6)
    amg_system = System(model, c, "amg")
    assert amg_system.linear_backend == "amg"
    amg, astats = run(amg_system, start, 6)
    size = np.ptp(model.X, axis=0).max()
    motion = max(np.abs(q - model.X).max() for q in direct)
    assert motion > 0.02 * size
    deviation = max(np.abs(a - b).max() for a, b in zip(amg, direct, strict=True))
    print("max deviation / size", deviation / size)
    assert deviation < 1e-8 * size
    assert sum(s.factorizations for s in astats) == 0
    assert sum(s.cg_iterations for s in astats) > 0
    setups = sum(s.amg_setups for s in astats)
    assert 1 <= setups < sum(s.newton_iterations for s in astats)  # the hierarchy is reused
    for s in astats:
        assert s.gradient_norms[-1] <= s.gradient_tolerance or s.newton_iterations
    assert {"matrix", "cg", "objective"} <= set(astats[0].seconds)


def test_amg_falls_back_to_the_psd_hessian_on_an_indefinite_system():
    """A half-height sheared box at dt = 0.1: ``M + dt^2 H`` is indefinite; CG meets negative
    curvature, the step switches to the PSD-projected Hessian and ends where direct does."""
    model, c = clamped_box((4, 4, 4), E=1e5, rho=1.0)
    X = model.X
    q = X.copy()
    q[:, 2] *= 0.5
    q[:, 0] += 0.3 * np.sin(3.0 * X[:, 2])
    q[c.fixed_vertices] = X[c.fixed_vertices]
    state = State(q=q, v=np.zeros_like(X))
    ref, rstats = implicit_euler(System(model, c, linsolve.default_backend()), state, 0.1,
                                 max_iterations=None)
    assert rstats.shifted_factorizations >= 1  # the exact Hessian is indefinite here
    new, stats = implicit_euler(System(model, c, "amg"), state, 0.1, max_iterations=None)
    print("psd fallbacks", stats.psd_fallbacks, "cg", stats.cg_iterations)
    assert stats.psd_fallbacks == 1 and stats.converged
    assert np.abs(new.q - ref.q).max() < 1e-6 * np.abs(ref.q - state.q).max()


def test_rigid_body_modes_are_the_null_space_of_the_rest_stiffness():
    from fem3d.assembly import hessian_data

    model, _ = clamped_box((3, 3, 3))
    B = linsolve.rigid_body_modes(model.X)
    H = model.csr(hessian_data(model, model.X))
    assert B.shape == (model.n_dofs, 6)
    assert np.abs(H @ B).max() < 1e-9 * np.abs(H.data).max()
    assert np.linalg.matrix_rank(B) == 6


def test_auto_picks_amg_by_size_and_env_and_missing_pyamg(monkeypatch):
    model, c = clamped_box((3, 3, 3))
    monkeypatch.delenv("FEM3D_SOLVER", raising=False)
    assert System(model, c).linear_backend == linsolve.default_backend()
    monkeypatch.setattr(linsolve, "AMG_AUTO_MIN_FREE_DOFS", c.n_free)
    assert System(model, c).linear_backend == "amg"
    monkeypatch.setenv("FEM3D_SOLVER", "superlu")  # a forced direct back end wins over auto
    assert System(model, c).linear_backend == "superlu"
    monkeypatch.delenv("FEM3D_SOLVER")
    monkeypatch.setattr(linsolve, "amg_available", lambda: False)
    assert System(model, c).linear_backend == linsolve.default_backend()
    with pytest.raises(ImportError, match="pyamg"):
        System(model, c, "amg")


def test_a_saved_hierarchy_resumes_bit_for_bit():
    """``factorized_data`` records the matrix the hierarchy was built from; a fresh System
    rebuilds the same hierarchy from it and continues exactly (checkpoint/resume)."""
    model, c = clamped_box((4, 4, 4))
    start = swinging(model, c)
    first = System(model, c, "amg")
    mid, _ = implicit_euler(first, start, 0.01, max_iterations=None)
    saved = first.factorized_data.copy()
    a, _ = implicit_euler(first, mid, 0.01, max_iterations=None)
    fresh = System(model, c, "amg")
    fresh.refactorize_saved(saved)
    b, _ = implicit_euler(fresh, mid, 0.01, max_iterations=None)
    assert np.array_equal(a.q, b.q) and np.array_equal(a.v, b.v)


def test_linear_scheme_and_objective_terms_with_the_amg_back_end():
    from test_integrators import PairSprings

    model, c = clamped_box((3, 3, 3))
    system = System(model, c, "amg")
    start = swinging(model, c)
    lin, _ = linearly_implicit_euler(system, start, 0.01)  # factorizes (direct solver made lazily)
    ref, _ = linearly_implicit_euler(System(model, c, linsolve.default_backend()), start, 0.01)
    np.testing.assert_allclose(lin.q, ref.q, rtol=0, atol=1e-12)
    far = [int(np.argmax(model.X.sum(axis=1))), int(np.argmax(model.X[:, 2] - model.X[:, 0]))]
    term = PairSprings([far], 1e4)
    new, stats = implicit_euler(system, start, 0.01, terms=[term], max_iterations=None)
    assert stats.converged and system.pattern_generation == 1 and stats.amg_setups >= 1
    assert system.amg_current
