"""Integrators: Newton convergence, energy behaviour, explosions, constraints, pulls."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fem3d.errors import SimulationError
from fem3d.scene import Scene, load_scene, scene_from_arrays
from fem3d.simulation import Simulation
from fem3d.solve.integrators import (
    State,
    implicit_euler,
    linearly_implicit_euler,
)
from fem3d.solve.newton import NewtonResult, newtons_method
from tests.physics.test_assembly import box_mesh

_BOX_KEYS = {"E": "bodies[0].material.E", "nu": "bodies[0].material.nu",
             "rho": "bodies[0].material.density", "dt": "simulation.dt",
             "spring_k": "interaction.spring_k", "pick_radius": "interaction.pick_radius",
             "integrator": "simulation.integrator"}


def box_scene(**kw) -> Scene:
    X, T = box_mesh(2, 3, 2, size=(1.0, 1.5, 1.0))
    args = dict(E=1e5, nu=0.4, rho=1000.0, dt=0.01, spring_k=1e4, pick_radius=0.01,
                integrator="implicit") | kw
    overrides = {_BOX_KEYS[k]: v for k, v in args.items()}
    overrides["bodies[0].pins"] = [{"select": {"lowest_y": {"tol": 1e-9}}}]
    return scene_from_arrays(X, T, overrides, name="box")


def swinging_state(X: np.ndarray) -> State:
    y = X[:, 1]
    v = np.zeros_like(X)
    v[:, 0] = 3.0 * y**2
    v[:, 2] = -2.0 * y
    v[y <= y.min()] = 0.0
    return State(q=X.copy(), v=v)


def test_newton_converges_quadratically():
    sim = Simulation(box_scene())
    state = swinging_state(sim.model.X)
    _, stats = implicit_euler(
        sim.system, state, 0.05, max_iterations=None, rtol=1e-15, atol_factor=0.0
    )
    g_all = np.array(stats.gradient_norms)
    print("gradient norms:", g_all)
    assert stats.converged
    assert stats.gradient_tolerance == pytest.approx(1e-15 * g_all[0])
    assert g_all[-1] < 1e-12 * g_all[0]  # down to round-off
    g = g_all[g_all > 1e-11 * g_all[0]]  # the iterates above the round-off floor
    print("g[k+1] / g[k]^2:", g[1:] / g[:-1] ** 2)
    orders = np.log(g[2:] / g[1:-1]) / np.log(g[1:-1] / g[:-2])
    print("convergence order estimates:", orders)
    assert len(g) >= 4
    # quadratic: the order estimates of the last iterations approach 2 ...
    assert orders[-1] > 1.8 and orders[-2] > 1.6
    # ... and the quadratic constant g[k+1] / g[k]^2 stays bounded
    c = g[1:] / g[:-1] ** 2
    assert c.max() < 10 * c.min()


def test_newtons_method_on_a_convex_function():
    A = np.array([[3.0, 1.0], [1.0, 2.0]])

    def energy(x):
        return 0.25 * float(x @ x) ** 2 + 0.5 * float(x @ A @ x) - x[0]

    def grad(x):
        return float(x @ x) * x + A @ x - np.array([1.0, 0.0])

    def direction(x, g):
        H = float(x @ x) * np.eye(2) + 2 * np.outer(x, x) + A
        return -np.linalg.solve(H, g)

    res = newtons_method(np.array([3.0, -2.0]), energy, grad, direction, max_iterations=None)
    assert isinstance(res, NewtonResult) and res.converged
    assert np.linalg.norm(grad(res.x)) < 1e-9
    capped = newtons_method(np.array([3.0, -2.0]), energy, grad, direction, max_iterations=2)
    assert capped.iterations == 2 and not capped.converged


def test_the_step_rule_does_not_judge_the_gradient_fallback():
    """``converged_step`` (IPC's rule on the Newton step's length) is not asked about the
    ``-g`` that replaces a failed direction: a short gradient step says nothing of the way
    left to the minimum."""
    A = np.diag([1.0, 1e-3])
    directions, judged = [], []

    def direction(x, g):  # a linear solver that fails from the second iteration on
        directions.append(x)
        return -0.5 * np.linalg.solve(A, g) if len(directions) == 1 else np.full_like(g, np.nan)

    def rule(x, d):
        judged.append(d)
        return True

    res = newtons_method(np.array([1.0, 1.0]), lambda x: 0.5 * float(x @ A @ x),
                         lambda x: A @ x, direction, max_iterations=4, converged_step=rule)
    assert res.iterations == 4 and judged == []


def test_a_first_step_that_passes_the_rule_ends_the_solve_only_when_accepted():
    """``accept_first_step``: a first Newton direction that passes ``converged_step`` is
    taken and ends the solve (one direction); without it the rule is first asked at the
    second direction, which confirms the step (two directions, the same point here: a
    quadratic's Newton step lands on its minimum). A first direction that fails the rule,
    and a stiffness change at the accepted point (``after_step``), keep Newton going; a first
    step too small for Armijo's test (the round-off branch) ends it as well."""
    A = np.diag([2.0, 1.0])
    b = np.array([1e-3, -2e-3])

    def solve(accept, x0, limit=1e-2, changed=False, energy_scale=0.0):
        directions = []

        def direction(x, g):
            directions.append(x.copy())
            return -np.linalg.solve(A, g)

        res = newtons_method(x0, lambda x: 0.5 * float(x @ A @ x) - float(b @ x),
                             lambda x: A @ x - b, direction, max_iterations=None,
                             rtol=0.0, atol=1e-300,
                             converged_step=lambda x, d: float(np.abs(d).max()) < limit,
                             after_step=lambda x: changed, accept_first_step=accept,
                             energy_scale=energy_scale)
        return res, len(directions)

    minimum = np.linalg.solve(A, b)
    x0 = minimum + np.array([4e-3, 1e-3])  # a first step of 4e-3: passes 1e-2
    taken, n_taken = solve(True, x0)
    confirmed, n_confirmed = solve(False, x0)
    assert (n_taken, taken.iterations, taken.converged) == (1, 1, True)
    assert (n_confirmed, confirmed.iterations, confirmed.converged) == (2, 1, True)
    np.testing.assert_allclose(taken.x, minimum, atol=1e-15)
    np.testing.assert_array_equal(taken.x, confirmed.x)
    # a first step longer than the rule allows is judged again at the second direction
    assert solve(True, x0, limit=1e-3)[1] == 2
    # the objective changed at the accepted point: its step is judged again, not accepted
    assert solve(True, x0, changed=True)[1] == 2
    # a decrease below the objective's round-off (the full step taken without Armijo's
    # test) ends the solve the same way
    assert solve(True, x0, energy_scale=1e30)[1] == 1
    assert solve(False, x0, energy_scale=1e30)[1] == 2


def test_parabolic_line_search_lands_nearer_the_minimum_along_the_direction():
    """A friction-like objective: weak curvature (``m``) plus a smoothed ``k |x|`` whose
    curvature jumps near 0. The full Newton step from the sliding side overshoots far past
    the kink; backtracking accepts the first halving that passes Armijo, the parabolic
    search then moves it to the parabola's vertex through the bracket: the same minimiser
    in fewer iterations."""
    m, b, k, eps = 0.1, 0.5, 1.0, 1e-3

    def energy(x):
        return 0.5 * m * float((x[0] - b) ** 2) + k * math.sqrt(float(x[0]) ** 2 + eps * eps)

    def grad(x):
        return np.array([m * (x[0] - b) + k * x[0] / math.sqrt(x[0] ** 2 + eps * eps)])

    def direction(x, g):
        h = m + k * eps * eps / (x[0] ** 2 + eps * eps) ** 1.5
        return -g / h

    x0 = np.array([2.0])
    seen = {}
    for search in ("backtrack", "parabolic"):
        res = newtons_method(x0, energy, grad, direction, max_iterations=None, rtol=1e-10,
                             line_search=search)
        assert res.converged
        seen[search] = res
    back, para = seen["backtrack"], seen["parabolic"]
    assert abs(para.x[0] - back.x[0]) < 1e-9  # the same minimiser (near 0: it sticks)
    assert para.iterations < back.iterations
    with pytest.raises(ValueError, match="line_search"):
        newtons_method(x0, energy, grad, direction, line_search="golden")


def test_newton_judges_round_off_by_the_energy_scale():
    """An objective that is a difference of large terms (an elastic energy near rest: element
    energies of size E vol cancel) rounds to multiples of ulp(C) far above its value: with
    ``energy_scale`` the full Newton step is taken there instead of halving through noise."""
    C = 1e6
    A = np.array([[2.0, 0.5], [0.5, 1.0]])

    def energy(x):
        return (C + 0.5 * float(x @ A @ x)) - C  # 0.0 below ulp(C) ~ 1e-10

    def grad(x):
        return A @ x

    def direction(x, g):
        return -np.linalg.solve(A, g)

    x0 = np.array([1e-6, -2e-6])
    blind = newtons_method(x0, energy, grad, direction, max_iterations=None)
    assert blind.iterations == 0 and blind.line_search_halvings == 30  # noise: no decrease
    assert blind.gradient_norms[-1] == blind.gradient_norms[0]
    seen = newtons_method(x0, energy, grad, direction, max_iterations=None, energy_scale=C)
    assert seen.converged and seen.line_search_halvings == 0
    assert seen.gradient_norms[-1] < 1e-10 * seen.gradient_norms[0]


def test_newton_takes_the_start_energy_from_the_caller():
    calls = []

    def energy(x):
        calls.append(1)
        return 0.5 * float(x @ x)

    x0 = np.array([1.0, 2.0])
    a = newtons_method(x0, energy, lambda x: x, lambda x, g: -g)
    n_plain = len(calls)
    calls.clear()
    b = newtons_method(x0, energy, lambda x: x, lambda x, g: -g, f0=energy(x0))
    assert len(calls) == n_plain  # energy(x0) here instead of inside
    assert np.array_equal(a.x, b.x)


def test_newton_reports_when_every_trial_is_inadmissible():
    def energy(x):
        return 0.0 if np.all(x == 0) else math.inf

    calls = []

    def no_step(x, d):
        calls.append(d)
        raise SimulationError("no step")

    with pytest.raises(SimulationError):
        newtons_method(np.zeros(2), energy, lambda x: np.ones(2), lambda x, g: -g,
                       on_no_step=no_step)
    assert calls


def test_backward_euler_never_increases_energy_without_external_force():
    sim = Simulation(box_scene(dt=0.02))
    X = sim.model.X
    q = X.copy()
    free = X[:, 1] > X[:, 1].min()
    q[free, 1] *= 1.15  # stretched, released from rest
    q[free, 0] += 0.1 * X[free, 1] ** 2
    sim.set_state(q, np.zeros_like(X))
    energies = [sim.energies()["total"]]
    for _ in range(30):
        energies.append(sim.step().total)
    e = np.array(energies)
    print("total energy:", e)
    assert e[0] > 0
    assert np.all(np.diff(e) <= 1e-10 * e[0])
    assert e[-1] < 0.9 * e[0]  # and it does dissipate


def test_fixed_vertices_never_move():
    sim = Simulation(box_scene())
    fixed = sim.fixed_vertices
    assert fixed.size == 9  # the bottom layer (3 x 3 vertices) of the 2x3x2 box
    sim.set_state(sim.model.X, swinging_state(sim.model.X).v)
    top = int(np.argmax(sim.model.X[:, 1]))
    sim.set_pull([top], sim.model.X[top] + [0.3, 0.0, 0.0])
    for integrator in ("implicit", "linear"):
        sim.integrator = integrator
        for _ in range(10):
            sim.step()
            assert np.array_equal(sim.q[fixed], sim.model.X[fixed])
            assert not np.any(sim.v[fixed])
    assert np.abs(sim.q - sim.model.X).max() > 0.05  # the rest did move


def test_pull_moves_vertex_toward_target_and_release_returns():
    sim = Simulation(box_scene(spring_k=1e5))
    top = int(np.argmax(sim.model.X[:, 1]))
    target = sim.model.X[top] + np.array([0.2, 0.0, 0.0])
    sim.set_pull([top], target)
    for _ in range(30):
        info = sim.step()
    assert info.pull > 0
    assert sim.q[top, 0] - sim.model.X[top, 0] > 0.1
    sim.clear_pull()
    closest = math.inf
    for _ in range(60):
        sim.step()
        closest = min(closest, abs(sim.q[top, 0] - sim.model.X[top, 0]))
    assert closest < 0.02  # released, it swings back through the rest position


def test_linear_step_raises_on_energy_bound_and_keeps_state():
    sim = Simulation(box_scene(integrator="linear"))
    state = swinging_state(sim.model.X)
    with pytest.raises(SimulationError, match="exploded"):
        linearly_implicit_euler(sim.system, state, 0.01, energy_bound=1e-12)
    new, stats = linearly_implicit_euler(sim.system, state, 0.01)
    assert stats.newton_iterations == 1 and np.isfinite(new.q).all()
    assert state.t == 0.0 and new.t == pytest.approx(0.01)


def test_reset_and_set_material():
    sim = Simulation(box_scene())
    sim.set_state(sim.model.X, swinging_state(sim.model.X).v)
    sim.step()
    sim.set_material(E=2e5)
    assert sim.model.E == 2e5 and sim.system.model is sim.model
    sim.step()
    sim.reset()
    assert sim.t == 0.0 and np.array_equal(sim.q, sim.model.X) and not sim.v.any()


def test_linear_bunny_stays_bounded_for_200_steps():
    scene = load_scene("bunny", {"simulation.integrator": "linear"})
    sim = Simulation(scene, scripted=True)
    h = sim.assembled.height
    worst = 0.0
    for _ in range(200):
        info = sim.step()
        worst = max(worst, float(np.abs(sim.q - sim.model.X).max()))
        assert math.isfinite(info.total)
    print(f"bunny linear: max displacement {worst:.3f} (height {h:.1f}); final {info}")
    assert worst < 0.25 * h
    # released at t = 0.3 s: by t = 2 s most of the energy has been dissipated
    assert info.total < 0.01 * sim._injected


def test_linear_armadillo_explodes_and_is_reported():
    scene = load_scene("arma", {"simulation.integrator": "linear"})
    sim = Simulation(scene, scripted=True)
    with pytest.raises(SimulationError, match="exploded") as err:
        for _ in range(100):
            sim.step()
    print("reported:", err.value)
    assert err.value.step is not None and err.value.step == sim.step_index
    assert np.isfinite(sim.q).all() and np.isfinite(sim.v).all()  # last good state kept
    assert sim.step_index > 30  # it fails after the release, as the assignment expects


def test_implicit_armadillo_is_stable_with_the_same_pull():
    scene = load_scene("arma", {"simulation.integrator": "implicit"})
    sim = Simulation(scene, scripted=True)
    for _ in range(60):
        info = sim.step()
        assert info.newton_iterations <= 5
    X = sim.model.X
    assert np.abs(sim.q - X).max() < 0.05 * sim.assembled.height
    assert np.array_equal(sim.q[sim.fixed_vertices], X[sim.fixed_vertices])


def test_indefinite_hessian_uses_shifted_factorization():
    """A strongly compressed box: M + dt^2 H is indefinite, Newton still converges."""
    from fem3d.physics.assembly import count_inverted

    sim = Simulation(box_scene(rho=1.0, dt=0.1))
    X = sim.model.X
    q = X.copy()
    q[:, 1] *= 0.5
    q[:, 0] += 0.3 * np.sin(3.0 * X[:, 1])
    q[sim.fixed_vertices] = X[sim.fixed_vertices]
    state = State(q=q, v=np.zeros_like(X))
    new, stats = implicit_euler(sim.system, state, 0.1, max_iterations=20)
    print("shifted:", stats.shifted_factorizations, "norms:", stats.gradient_norms)
    assert stats.shifted_factorizations >= 1
    assert stats.converged and stats.gradient_norms[-1] < 1e-8 * stats.gradient_norms[0]
    assert count_inverted(sim.model, new.q) == 0


def compressed_box_state(sim: Simulation) -> State:
    """Half-height, sheared box at rest: ``M + dt^2 H`` is indefinite at dt = 0.1."""
    X = sim.model.X
    q = X.copy()
    q[:, 1] *= 0.5
    q[:, 0] += 0.3 * np.sin(3.0 * X[:, 1])
    q[sim.fixed_vertices] = X[sim.fixed_vertices]
    return State(q=q, v=np.zeros_like(X))


def test_exhausted_shift_ladder_falls_back_to_the_psd_hessian():
    sim = Simulation(box_scene(rho=1.0, dt=0.1))
    state = compressed_box_state(sim)
    reference, _ = implicit_euler(sim.system, state, 0.1, max_iterations=None)
    sim.system.max_shift_tries = 0  # no shift: every indefinite Hessian exhausts the ladder
    new, stats = implicit_euler(sim.system, state, 0.1, max_iterations=None)
    print("fallbacks:", stats.psd_fallbacks, "norms:", stats.gradient_norms)
    assert stats.psd_fallbacks >= 1 and stats.shifted_factorizations == 0
    assert stats.converged
    assert np.abs(new.q - reference.q).max() < 1e-6 * np.abs(reference.q - state.q).max()


def test_reuse_on_an_indefinite_hessian_reaches_the_direct_answer():
    """CG on indefinite Newton matrices (negative curvature, non-descent results) hands over to
    a factorization, of the PSD-projected Hessian where the exact one is indefinite (no shift
    ladder): reuse ends where direct does."""
    finals = {}
    for mode, budget in (("direct", 16), ("reuse", 16), ("reuse", 2)):
        sim = Simulation(box_scene(rho=1.0, dt=0.1))
        state = compressed_box_state(sim)
        new, stats = implicit_euler(sim.system, state, 0.1, max_iterations=None,
                                    linear_solver=mode, cg_maxiter=budget)
        assert stats.converged
        finals[mode, budget] = (new.q, stats)
    q_ref = finals["direct", 16][0]
    for key in (("reuse", 16), ("reuse", 2)):
        q, stats = finals[key]
        print(key, "factorizations", stats.factorizations, "cg", stats.cg_iterations,
              "psd", stats.psd_fallbacks, "shifted", stats.shifted_factorizations)
        assert np.abs(q - q_ref).max() < 1e-6 * np.abs(q_ref - state.q).max()  # vs the motion
        assert stats.psd_fallbacks > 0 and stats.shifted_factorizations == 0
    assert finals["direct", 16][1].shifted_factorizations > 0
    # a smaller CG budget refactorizes at least as often
    assert finals["reuse", 2][1].factorizations >= finals["reuse", 16][1].factorizations


def test_psd_projected_hessian_needs_no_shift():
    sim = Simulation(box_scene(rho=1.0, dt=0.1))
    X = sim.model.X
    q = X.copy()
    q[:, 1] *= 0.5
    q[:, 0] += 0.3 * np.sin(3.0 * X[:, 1])
    q[sim.fixed_vertices] = X[sim.fixed_vertices]
    state = State(q=q, v=np.zeros_like(X))
    exact, _ = implicit_euler(sim.system, state, 0.1, max_iterations=None)
    new, stats = implicit_euler(sim.system, state, 0.1, max_iterations=100, hessian="psd")
    print("psd iterations:", stats.newton_iterations, "norms:", stats.gradient_norms[-3:])
    assert stats.shifted_factorizations == 0 and stats.converged
    assert np.abs(new.q - exact.q).max() < 1e-6 * np.abs(exact.q - q).max()
    with pytest.raises(ValueError):
        implicit_euler(sim.system, state, 0.1, hessian="bfgs")


def test_reused_factorization_reaches_the_same_answer_with_fewer_factorizations():
    """linear_solver="reuse" (CG preconditioned by the step's first factorization) converges
    to the same minimiser as refactorizing at every Newton iteration."""
    results = {}
    for mode in ("direct", "reuse"):
        sim = Simulation(box_scene())
        state = swinging_state(sim.model.X)
        new, stats = implicit_euler(sim.system, state, 0.05, max_iterations=None, rtol=1e-12,
                                    atol_factor=0.0, linear_solver=mode, cg_rtol=1e-6)
        assert stats.converged
        results[mode] = (new, stats)
    direct, reuse = results["direct"], results["reuse"]
    assert reuse[1].factorizations == 1 < direct[1].factorizations
    assert reuse[1].cg_iterations > 0
    scale = np.abs(direct[0].v).max()
    np.testing.assert_allclose(reuse[0].v, direct[0].v, rtol=0, atol=1e-9 * scale)
    with pytest.raises(ValueError, match="linear_solver"):
        implicit_euler(Simulation(box_scene()).system, state, 0.05, linear_solver="magic")


def test_reuse_across_steps_factorizes_rarely_and_tracks_direct():
    """On the armadillo (about one Newton iteration per step) reuse keeps one factorization
    for many steps and stays on the trajectory of refactorizing every iteration."""
    runs = {}
    for mode in ("direct", "reuse"):
        sim = Simulation(load_scene("arma", {"simulation.newton.solver": mode}), scripted=True)
        factorizations = 0
        for _ in range(40):
            sim.step()
            factorizations += sim.last_stats.factorizations
        runs[mode] = (sim.q.copy(), factorizations)
    (q_direct, f_direct), (q_reuse, f_reuse) = runs["direct"], runs["reuse"]
    assert f_reuse < f_direct / 4
    size = np.ptp(q_direct, axis=0).max()
    assert np.abs(q_reuse - q_direct).max() < 1e-6 * size


def test_reuse_lags_the_newton_matrix_and_keeps_the_tolerance():
    """The dragged armadillo refined x8 (the interactive benchmark): "reuse" solves some
    Newton iterations with the previous iterate's matrix, its CG solves are loose where a
    tight one buys nothing, and every step still ends below its gradient tolerance, on the
    trajectory of refactorizing every iteration."""
    from bench.newton_step import armadillo
    from fem3d.solve.integrators import System

    work = armadillo(1, 36)
    assert System(work.model, work.constraints).solver.cholmod_mode in (None, "supernodal")
    runs = {}
    for mode in ("direct", "reuse"):
        system = System(work.model, work.constraints)
        state, lagged, newton = work.start, 0, 0
        for pull in work.pulls[:16]:
            state, stats = implicit_euler(system, state, work.dt, pull, max_iterations=None,
                                          linear_solver=mode)
            assert stats.converged
            assert stats.gradient_norms[-1] <= stats.gradient_tolerance
            lagged += stats.lagged_matrices
            newton += stats.newton_iterations
        runs[mode] = (state.q, lagged, newton)
    (q_direct, lag_direct, n_direct), (q_reuse, lag_reuse, n_reuse) = runs["direct"], \
        runs["reuse"]
    assert lag_direct == 0 < lag_reuse
    assert n_reuse <= n_direct + 2
    assert np.abs(q_reuse - q_direct).max() < 1e-6 * work.size


@pytest.mark.parametrize("backend", ["numpy", "c"])
@pytest.mark.parametrize("psd", [False, True])
def test_newton_matrix_equals_the_reduced_full_matrix(backend: str, psd: bool):
    from fem3d.kernels.backend import c_extension
    from fem3d.physics.assembly import hessian_data
    from fem3d.physics.springs import Pull

    if backend == "c" and c_extension() is None:
        pytest.skip("C extension not built")
    sim = Simulation(box_scene(), backend=backend)
    system, model = sim.system, sim.model
    rng = np.random.default_rng(4)
    q = model.X + 0.05 * rng.normal(size=model.X.shape)
    # one free and one fixed vertex pulled: the fixed one's block must be dropped
    pulled = np.array([int(np.argmax(model.X[:, 1])), int(sim.fixed_vertices[0])])
    pull = Pull.make(pulled, model.X[pulled] + 0.3, 1e4, model.n_vertices)
    dt = 0.02
    H = hessian_data(model, q.reshape(-1), psd=psd)
    blocks = pull.hessian_blocks(system.spring, q)
    for v, block in zip(pulled, blocks, strict=True):
        d = 3 * v + np.arange(3)
        H[system.data_positions(np.repeat(d, 3), np.tile(d, 3))] += block.reshape(-1)
    expected = system.reduced(model.mass.data + dt * dt * H)
    A = system.newton_matrix(q, dt, pull, psd=psd)
    assert A.shape == expected.shape and A.nnz == expected.nnz
    np.testing.assert_array_equal(A.indices, expected.indices)
    np.testing.assert_allclose(A.data, expected.data, rtol=1e-12,
                               atol=1e-13 * np.abs(expected.data).max())
    # a later call does not reuse the earlier matrix's data
    before = A.data.copy()
    system.newton_matrix(model.X, dt)
    np.testing.assert_array_equal(A.data, before)


@pytest.mark.parametrize("psd", [False, True])
def test_lean_assembly_gives_the_same_newton_matrix_bit_for_bit(monkeypatch, psd: bool):
    """Big meshes (``LEAN_ASSEMBLY_MIN_TETS``) sum on the full pattern and gather the kept
    entries once (no element-to-reduced-slot map): the same bits as the direct path, and a
    later matrix does not overwrite an earlier one's data."""
    from fem3d.physics.springs import Pull
    from fem3d.solve import system as system_module

    sim = Simulation(box_scene())
    model = sim.model
    rng = np.random.default_rng(5)
    q = model.X + 0.05 * rng.normal(size=model.X.shape)
    pulled = np.array([int(np.argmax(model.X[:, 1]))])
    pull = Pull.make(pulled, model.X[pulled] + 0.3, 1e4, model.n_vertices)
    expected = sim.system.newton_matrix(q, 0.02, pull, psd=psd)
    monkeypatch.setattr(system_module, "LEAN_ASSEMBLY_MIN_TETS", 0)
    lean = system_module.System(model, sim.system.constraints)
    assert lean._free_scatter is None
    A = lean.newton_matrix(q, 0.02, pull, psd=psd)
    np.testing.assert_array_equal(A.indptr, expected.indptr)
    np.testing.assert_array_equal(A.indices, expected.indices)
    np.testing.assert_array_equal(A.data, expected.data)
    before = A.data.copy()
    lean.newton_matrix(model.X, 0.02)
    np.testing.assert_array_equal(A.data, before)


# ---------------------------------------------------------------------------------------------
# gravity, Rayleigh damping, moving pins, several pulls, objective terms

G = np.array([0.0, -9.81, 0.0])


def small_model(nx=2, ny=2, nz=2, size=(1.0, 1.0, 1.0), E=1e5, nu=0.35, rho=1000.0):
    from fem3d.physics.model import build_model

    X, T = box_mesh(nx, ny, nz, size=size)
    return build_model(X, T, E=E, nu=nu, rho=rho)


def make_system(model, fixed=(), gravity=None, rayleigh_alpha=0.0, rayleigh_beta=0.0,
                **options):
    from fem3d.physics.constraints import Constraints
    from fem3d.scene.build import build_loads
    from fem3d.solve.integrators import System

    c = Constraints.from_fixed_vertices(model.X, np.asarray(fixed, dtype=np.int64))
    loads = build_loads(model, gravity, rayleigh_alpha, rayleigh_beta)
    return System(model, c, loads=loads, **options)


STEPPERS = {
    "implicit": lambda system, state, dt, **kw: implicit_euler(system, state, dt, **kw),
    "linear": lambda system, state, dt, **kw: linearly_implicit_euler(system, state, dt, **kw),
}


@pytest.mark.parametrize("integrator", ["implicit", "linear"])
def test_free_fall_matches_backward_euler_closed_form(integrator):
    """An unpinned body under gravity: both schemes update ``v+ = v + dt g``, ``q+ = q + dt
    v+``, so after n steps ``v = n dt g`` and ``q - X = g dt^2 n (n + 1) / 2 = g t^2 / 2 + g t
    dt / 2``: the exact parabola plus backward Euler's known first-order error ``g t dt / 2``.
    Checked to round-off (1e-9 of the fall)."""
    model = small_model()
    system = make_system(model, gravity=G)
    state, dt, n = State.at_rest(model), 0.01, 30
    for _ in range(n):
        state, _ = STEPPERS[integrator](system, state, dt)
    t = n * dt
    fall = G * dt * dt * n * (n + 1) / 2
    np.testing.assert_allclose(fall, G * t * t / 2 + G * t * dt / 2, rtol=1e-12)
    scale = np.abs(fall).max()
    assert np.abs(state.q - model.X - fall).max() < 1e-9 * scale
    assert np.abs(state.v - n * dt * G).max() < 1e-9 * np.abs(n * dt * G).max()


def test_pinned_cantilever_settles_at_the_static_solution():
    """A cantilever under gravity with mass damping settles where ``dV/dq = M g`` (the static
    problem, solved separately by plain Newton on ``dV/dq - f_g = 0``)."""
    import scipy.sparse.linalg as spla

    from fem3d.physics.assembly import assemble_gradient, hessian_data

    model = small_model(4, 1, 1, size=(2.0, 0.5, 0.5), E=1e7, rho=500.0)
    fixed = np.flatnonzero(model.X[:, 0] <= 1e-12)
    system = make_system(model, fixed, gravity=G, rayleigh_alpha=50.0)
    c, free = system.constraints, system.constraints.free_dofs
    f = system.loads.gravity_force
    np.testing.assert_allclose(f.reshape(-1, 3).sum(axis=0), G * model.rho * 0.5, rtol=1e-12)
    u = model.X.reshape(-1)[free]
    for _ in range(8):
        q = c.expand(u)
        u = u - spla.spsolve(system.reduced(hessian_data(model, q)).tocsc(),
                             (assemble_gradient(model, q) - f)[free])
    q_static = c.expand(u).reshape(-1, 3)
    assert np.abs((assemble_gradient(model, q_static) - f)[free]).max() < 1e-8
    sag = np.abs(q_static - model.X).max()
    assert sag > 1e-2  # it does sag
    state = State.at_rest(model)
    for _ in range(60):
        state, _ = implicit_euler(system, state, 0.05, max_iterations=None)
    assert np.abs(state.q - q_static).max() < 1e-7 * sag
    assert np.array_equal(state.q[fixed], model.X[fixed])


@pytest.mark.parametrize("integrator", ["implicit", "linear"])
def test_mass_damping_decays_a_translation_at_the_discrete_rate(integrator):
    """``M dv/dt = -alpha M v``: backward Euler gives ``v_n = v_0 / (1 + alpha dt)^n`` exactly
    (the continuous ``exp(-alpha t)`` to first order in ``dt``); alpha per vertex equal to a
    constant is the same damping."""
    model = small_model()
    v0 = np.tile([0.3, -0.2, 0.5], (model.n_vertices, 1))
    alpha, dt, n = 2.0, 0.01, 40
    expected = v0 / (1 + alpha * dt) ** n
    for a in (alpha, np.full(model.n_vertices, alpha)):
        system = make_system(model, rayleigh_alpha=a)
        state = State(q=model.X.copy(), v=v0.copy())
        speeds = []
        for _ in range(n):
            state, _ = STEPPERS[integrator](system, state, dt)
            speeds.append(np.linalg.norm(state.v[0]))
        assert np.all(np.diff(speeds) < 0)
        assert np.abs(state.v - expected).max() < 1e-9 * np.abs(v0).max()
    continuous = v0 * math.exp(-alpha * n * dt)
    assert np.abs(expected - continuous).max() < alpha * alpha * n * dt * dt * np.abs(v0).max()


@pytest.mark.parametrize("integrator", ["implicit", "linear"])
def test_rayleigh_damping_decays_energy_monotonically(integrator):
    """A swinging clamped box: with ``alpha M + beta K`` the total energy never increases and
    ends well below the undamped run's."""
    from fem3d.physics.assembly import kinetic_energy, potential_energy

    model = small_model(2, 3, 2, size=(1.0, 1.5, 1.0))
    fixed = np.flatnonzero(model.X[:, 1] <= 1e-12)
    start = swinging_state(model.X)
    finals = {}
    for damping in ({}, {"rayleigh_alpha": 3.0, "rayleigh_beta": 0.02}):
        system = make_system(model, fixed, **damping)
        state = start
        energies = [kinetic_energy(model, state.v) + potential_energy(model, state.q)]
        for _ in range(40):
            state, _ = STEPPERS[integrator](system, state, 0.01)
            energies.append(kinetic_energy(model, state.v) + potential_energy(model, state.q))
        e = np.array(energies)
        if damping:
            assert np.all(np.diff(e) <= 1e-12 * e[0]), e
        finals[bool(damping)] = e[-1]
    assert finals[True] < 0.5 * finals[False]


def test_damping_per_tet_and_per_vertex_arrays_equal_the_scalars():
    model = small_model()
    q = model.X + 0.05 * np.random.default_rng(1).normal(size=model.X.shape)
    a = make_system(model, rayleigh_alpha=0.3, rayleigh_beta=0.02).loads.damping_data(q)
    b = make_system(model, rayleigh_alpha=np.full(model.n_vertices, 0.3),
                    rayleigh_beta=np.full(model.n_tets, 0.02)).loads.damping_data(q)
    np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-14 * np.abs(a).max())
    assert make_system(model).loads.damping_data(q) is None


def test_bad_gravity_and_damping_are_parameter_errors():
    from fem3d.errors import ParameterError

    model = small_model()
    with pytest.raises(ParameterError, match="gravity"):
        make_system(model, gravity=[0.0, -9.81])
    with pytest.raises(ParameterError, match="rayleigh_alpha"):
        make_system(model, rayleigh_alpha=-1.0)
    with pytest.raises(ParameterError, match="rayleigh_beta of tet 2"):
        beta = np.zeros(model.n_tets)
        beta[2] = np.nan
        make_system(model, rayleigh_beta=beta)
    with pytest.raises(ParameterError, match="one per vertex"):
        make_system(model, rayleigh_alpha=np.zeros(3))
    system = make_system(model, [0, 1])
    with pytest.raises(ParameterError, match="fixed_positions"):
        implicit_euler(system, State.at_rest(model), 0.01, fixed_positions=np.zeros((3, 3)))


def test_zero_gravity_and_damping_are_the_plain_step():
    model = small_model(2, 3, 2, size=(1.0, 1.5, 1.0))
    fixed = np.flatnonzero(model.X[:, 1] <= 1e-12)
    start = swinging_state(model.X)
    plain = make_system(model, fixed)
    zero = make_system(model, fixed, gravity=[0, 0, 0], rayleigh_alpha=0.0,
                       rayleigh_beta=np.zeros(model.n_tets))
    for step in STEPPERS.values():
        a, _ = step(plain, start, 0.01)
        b, _ = step(zero, start, 0.01)
        assert np.array_equal(a.q, b.q) and np.array_equal(a.v, b.v)


@pytest.mark.parametrize("integrator", ["implicit", "linear"])
def test_moving_pins_reach_their_keyframes_and_carry_the_body(integrator):
    """The clamped end follows a keyframed rotation + translation exactly; the body, damped,
    ends close to the rigidly moved rest shape."""
    from fem3d.physics.motion import Keyframes

    model = small_model(3, 1, 1, size=(1.5, 0.5, 0.5), E=1e8)
    fixed = np.flatnonzero(model.X[:, 0] <= 1e-12)
    pivot = model.X[fixed].mean(axis=0)
    kf = Keyframes([0.0, 0.4, 1.0], [[0, 0, 0], [0.1, 0.05, 0], [0.1, 0.05, 0]],
                   [[0, 0, 0], [0, 0, 30], [0, 0, 30]], pivot, interpolation="smooth")
    system = make_system(model, fixed, rayleigh_beta=0.01)
    state, dt = State.at_rest(model), 0.01
    for _ in range(100):
        target = kf.apply(model.X[fixed], state.t + dt)
        prev = state.q[fixed].copy()
        state, _ = STEPPERS[integrator](system, state, dt, fixed_positions=target)
        assert np.array_equal(state.q[fixed], target)
        np.testing.assert_allclose(state.v[fixed], (target - prev) / dt, rtol=1e-12,
                                   atol=1e-12)
    rigid = kf.apply(model.X, 1.0)
    moved = np.abs(rigid - model.X).max()
    assert moved > 0.2
    assert np.abs(state.q - rigid).max() < 0.05 * moved
    # pins released (fixed_positions=None): they stay where they are, at rest
    state, _ = STEPPERS[integrator](system, state, dt)
    assert np.array_equal(state.q[fixed], rigid[fixed]) and not state.v[fixed].any()


def test_moving_pins_agree_between_the_schemes_for_a_small_step():
    """The same keyframed drive through both schemes: trajectories agree to O(dt)."""
    from fem3d.physics.motion import Keyframes

    model = small_model(3, 1, 1, size=(1.5, 0.5, 0.5))
    fixed = np.flatnonzero(model.X[:, 0] <= 1e-12)
    kf = Keyframes([0.0, 0.2], [[0, 0, 0], [0, 0.05, 0]], [[0, 0, 0], [0, 0, 0]],
                   [0, 0, 0])
    system = make_system(model, fixed)
    ends = {}
    for name, step in STEPPERS.items():
        state = State.at_rest(model)
        for _ in range(40):
            state, _ = step(system, state, 0.005,
                            fixed_positions=kf.apply(model.X[fixed], state.t + 0.005))
        ends[name] = state.q
    tip = np.abs(ends["implicit"] - model.X).max()
    assert tip > 0.04
    assert np.abs(ends["implicit"] - ends["linear"]).max() < 0.05 * tip


def test_pull_with_per_spring_stiffness_and_combined_pulls():
    from fem3d.physics.springs import Pull

    model = small_model()
    system = make_system(model, [0])
    q = model.X + 0.01
    a = Pull.make([5, 3], [[0, 0, 1], [1, 1, 1]], np.array([10.0, 20.0]), model.n_vertices)
    assert a.vertices.tolist() == [3, 5]  # sorted with their targets and stiffness
    np.testing.assert_array_equal(a.targets, [[1, 1, 1], [0, 0, 1]])
    np.testing.assert_array_equal(a.stiffness, [20.0, 10.0])
    expected = 0.5 * (20 * np.sum((q[3] - 1) ** 2) + 10 * np.sum((q[5] - [0, 0, 1]) ** 2))
    assert a.energy(system.spring, q) == pytest.approx(expected, rel=1e-14)
    b = Pull.make([5], [2.0, 0.0, 0.0], 5.0, model.n_vertices)
    both = Pull.combine([a, None, b], model.n_vertices)
    assert both.vertices.tolist() == [3, 5, 5]
    assert both.energy(system.spring, q) == pytest.approx(
        a.energy(system.spring, q) + b.energy(system.spring, q), rel=1e-14)
    np.testing.assert_allclose(both.gradient(system.spring, q),
                               a.gradient(system.spring, q) + b.gradient(system.spring, q),
                               rtol=1e-14)
    A = system.newton_matrix(q, 0.01, both)
    B = system.newton_matrix(q, 0.01, a)
    C = system.newton_matrix(q, 0.01, b)
    M = system.newton_matrix(q, 0.01)
    np.testing.assert_allclose(A.data, B.data + C.data - M.data, rtol=1e-12,
                               atol=1e-12 * np.abs(M.data).max())
    assert Pull.combine([None], model.n_vertices) is None
    from fem3d.errors import ParameterError
    with pytest.raises(ParameterError, match="stiffness"):
        Pull.make([1, 2], [0, 0, 0], np.array([1.0, -1.0]), model.n_vertices)


class PairSprings:
    """An objective term: zero-rest-length springs between vertex pairs that share no tet
    (entries outside the mesh's sparsity pattern)."""

    def __init__(self, pairs, k):
        self.pairs = np.asarray(pairs)
        self.k = k

    def energy(self, q):
        x = q.reshape(-1, 3)
        d = x[self.pairs[:, 0]] - x[self.pairs[:, 1]]
        return 0.5 * self.k * float((d * d).sum())

    def gradient(self, q):
        x = q.reshape(-1, 3)
        d = x[self.pairs[:, 0]] - x[self.pairs[:, 1]]
        g = np.zeros_like(x)
        np.add.at(g, self.pairs[:, 0], self.k * d)
        np.add.at(g, self.pairs[:, 1], -self.k * d)
        return g.reshape(-1)

    def hessian(self, q):
        rows, cols, vals = [], [], []
        for a, b in self.pairs:
            for i in range(3):
                for (r, cc, s) in ((a, a, 1), (b, b, 1), (a, b, -1), (b, a, -1)):
                    rows.append(3 * r + i)
                    cols.append(3 * cc + i)
                    vals.append(s * self.k)
        return np.array(rows), np.array(cols), np.array(vals)


def test_objective_term_outside_the_pattern_widens_it_once():
    model = small_model(3, 1, 1, size=(1.5, 0.5, 0.5))
    fixed = np.flatnonzero(model.X[:, 0] <= 1e-12)
    far = [int(np.argmax(model.X.sum(axis=1))),
           int(np.argmin(np.linalg.norm(model.X - [0.5, 0.0, 0.0], axis=1)))]
    term = PairSprings([far], 2e4)
    system = make_system(model, fixed)
    state = State.at_rest(model)
    v = np.zeros_like(model.X)
    v[far[0]] = [0.0, 0.0, 2.0]
    state = State(q=state.q, v=v)
    from fem3d.physics.assembly import assemble_gradient

    for mode in ("direct", "reuse"):
        s = state
        for _ in range(3):
            before = s
            s, stats = implicit_euler(system, s, 0.01, terms=[term], max_iterations=None,
                                      linear_solver=mode)
            assert stats.converged
            assert system.pattern_generation == 1  # widened on the first use only
            # stationary point of the whole objective, checked independently
            q = s.q.reshape(-1)
            g = model.mass @ (s.v - before.v).reshape(-1) + 0.01 * (
                assemble_gradient(model, q) + term.gradient(q))
            assert np.abs(g[system.constraints.free_dofs]).max() < 1e-8 * np.abs(
                model.mass @ state.v.reshape(-1)).max()
    # the springs did pull the two vertices together
    d0 = np.linalg.norm(model.X[far[0]] - model.X[far[1]])
    assert np.linalg.norm(s.q[far[0]] - s.q[far[1]]) < d0


class Floor:
    """A log barrier keeping every vertex above ``y = level`` with a CCD-like ``max_step``."""

    requires_convergence = True

    def __init__(self, level, kappa, dhat):
        self.level, self.kappa, self.dhat = level, kappa, dhat

    def _gap(self, q):
        return q.reshape(-1, 3)[:, 1] - self.level

    def energy(self, q):
        d = self._gap(q)
        if (d <= 0).any():
            return math.inf
        a = np.minimum(d, self.dhat)
        return float(-self.kappa * ((a - self.dhat) ** 2 * np.log(a / self.dhat)).sum())

    def gradient(self, q):
        d = np.minimum(self._gap(q), self.dhat)
        g = -self.kappa * (2 * (d - self.dhat) * np.log(d / self.dhat) + (d - self.dhat) ** 2 / d)
        out = np.zeros(q.size)
        out[1::3] = g
        return out

    def hessian(self, q):
        d = np.minimum(self._gap(q), self.dhat)
        h = -self.kappa * (2 * np.log(d / self.dhat) + 4 * (d - self.dhat) / d
                           - (d - self.dhat) ** 2 / d**2)
        idx = np.arange(1, q.size, 3)
        return idx, idx, np.maximum(h, 0.0)

    def max_step(self, q, dq):
        d, dy = self._gap(q), dq[1::3]
        down = dy < 0
        if not down.any():
            return 1.0
        return float(min(1.0, 0.8 * (d[down] / -dy[down]).min()))


def test_max_step_keeps_a_falling_body_above_a_barrier_floor():
    model = small_model(size=(0.2, 0.2, 0.2), E=1e5)
    floor = Floor(level=-0.05, kappa=1e3, dhat=0.02)
    system = make_system(model, gravity=[0, -9.81, 0])
    state = State(q=model.X.copy(), v=np.tile([0.0, -3.0, 0.0], (model.n_vertices, 1)))
    lowest = []
    for _ in range(15):
        state, stats = implicit_euler(system, state, 0.01, terms=[floor])
        lowest.append(state.q[:, 1].min())
        assert stats.converged
    assert min(lowest) > floor.level  # without the clamp a step of 3 cm crosses the floor
    assert min(lowest) < floor.level + floor.dhat  # it did reach the barrier
