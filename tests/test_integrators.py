"""Integrators: Newton convergence, energy behaviour, explosions, constraints, pulls."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_assembly import box_mesh

from fem3d.errors import SimulationError
from fem3d.integrators import (
    NewtonResult,
    State,
    implicit_euler,
    linearly_implicit_euler,
    newtons_method,
)
from fem3d.scene import Scene, load_scene, scene_from_arrays
from fem3d.simulation import Simulation

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
    from fem3d.assembly import count_inverted

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
    the shifted factorization: reuse ends where direct does."""
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
        print(key, "factorizations", stats.factorizations, "cg", stats.cg_iterations)
        assert np.abs(q - q_ref).max() < 1e-6 * np.abs(q_ref - state.q).max()  # vs the motion
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


@pytest.mark.parametrize("backend", ["numpy", "c"])
@pytest.mark.parametrize("psd", [False, True])
def test_newton_matrix_equals_the_reduced_full_matrix(backend: str, psd: bool):
    from fem3d.assembly import hessian_data
    from fem3d.integrators import Pull
    from fem3d.kernels import c_extension

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
