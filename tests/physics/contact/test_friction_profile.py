"""Static and kinetic friction (``mu_s``, ``mu_k``): the smoothed profile, its derivatives,
and a block on an incline that holds below ``atan(mu_s)`` and slides with ``mu_k`` above it."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.physics.contact import ContactModel, PlaneObstacle
from fem3d.physics.contact.friction_profile import friction_profile, point_plane_friction
from fem3d.physics.terms.contact import ContactTerm
from fem3d.solve.integrators import State, implicit_euler
from tests.physics.contact.test_potentials import box_mesh
from tests.solve.test_contact_steps import DT, free_system

EPS = 1e-3


def test_one_coefficient_is_ipcs_mollifier() -> None:
    y = np.linspace(0.0, 3 * EPS, 31)
    F, g_y, _ = friction_profile(y, EPS, 0.4, 0.4)
    small = y < EPS
    f0 = np.where(small, -y ** 3 / (3 * EPS ** 2) + y * y / EPS + EPS / 3, y)
    np.testing.assert_array_equal(F, 0.4 * f0)


def test_the_force_rises_to_mu_s_then_falls_to_mu_k_smoothly() -> None:
    mu_s, mu_k = 0.6, 0.3
    y = np.linspace(1e-6, 3 * EPS, 3001)
    F, g_y, c2 = friction_profile(y, EPS, mu_s, mu_k)
    g = g_y * y
    assert g.max() == pytest.approx(mu_s, rel=1e-6)  # static: holds up to mu_s lambda
    assert y[np.argmax(g)] == pytest.approx(EPS, rel=2e-3)
    np.testing.assert_allclose(g[y >= 2 * EPS], mu_k, rtol=1e-12)  # kinetic
    # F' = g and g' = c2 + g / y (finite differences)
    h = 1e-9
    Fp, gp_y, _ = friction_profile(y + h, EPS, mu_s, mu_k)
    Fm, gm_y, _ = friction_profile(y - h, EPS, mu_s, mu_k)
    np.testing.assert_allclose((Fp - Fm) / (2 * h), g, atol=1e-5)
    dg = ((gp_y * (y + h)) - (gm_y * (y - h))) / (2 * h)
    np.testing.assert_allclose(dg, c2 + g_y, atol=2e-3 / EPS)
    assert np.abs(np.diff(g)).max() < 1.5e-3  # continuous (slope at most 2 mu_s / eps)


def test_point_plane_friction_derivatives() -> None:
    rng = np.random.default_rng(0)
    n = np.tile([0.0, 1.0, 0.0], (20, 1))
    w = rng.normal(scale=1.5 * EPS, size=(20, 3))
    lam = rng.uniform(0.5, 2.0, 20)
    args = (n, None, lam, EPS, 0.6, 0.3)

    def energy(w_):
        return point_plane_friction(n, w_.reshape(-1, 3), lam, EPS, 0.6, 0.3, 0)

    g = point_plane_friction(n, w, lam, EPS, *args[4:], 1).reshape(-1)
    H = point_plane_friction(n, w, lam, EPS, *args[4:], 2, project=False)
    h = 1e-9
    for k in range(0, 60, 7):
        e = np.zeros(60)
        e[k] = h
        fd = (energy(w.reshape(-1) + e) - energy(w.reshape(-1) - e)) / (2 * h)
        assert fd == pytest.approx(g[k], rel=1e-4, abs=1e-9)
        gp = point_plane_friction(n, (w.reshape(-1) + e).reshape(-1, 3), lam, EPS, 0.6, 0.3, 1)
        gm = point_plane_friction(n, (w.reshape(-1) - e).reshape(-1, 3), lam, EPS, 0.6, 0.3, 1)
        col = ((gp - gm) / (2 * h))[k // 3]
        np.testing.assert_allclose(col, H[k // 3][:, k % 3], rtol=1e-4, atol=1e-4)


def incline(tan_theta: float, mu_s: float, mu_k: float, steps: int, iterations: int = 1,
            tolerance: float = 1e-6, eps_v: float = EPS, settle: int = 0):
    """A stiff block on a plane inclined by theta: COM velocity along the slope (positive
    uphill) after each step, and its displacement along it. With ``settle``, the block
    first comes to rest for that many steps with ``mu_k = mu_s`` (it starts ``dhat / 2`` off
    the plane: the barrier's first push is a jolt that would break it loose), then
    ``mu_k`` applies; the arrays start after the settling."""
    theta = np.arctan(tan_theta)
    c, s = np.cos(theta), np.sin(theta)
    dhat = 1e-3
    X, T = box_mesh((1, 1, 1), size=(0.1, 0.05, 0.1))
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    X = X @ R.T + np.array([0.0, 0.5 * dhat / c, 0.0])
    model, system = free_system(X, T, E=1e6)
    cm = ContactModel(X, T, planes=[PlaneObstacle([0, 0, 0], [-s, c, 0])], dhat=dhat,
                      mu=mu_s, mu_k=mu_s if settle else mu_k, eps_v=eps_v)
    term = ContactTerm(cm, tolerance=1e-4, friction_iterations=iterations,
                       friction_tolerance=tolerance)
    state = State.at_rest(model)
    for _ in range(settle):
        state, _ = implicit_euler(system, state, DT, terms=[term])
    cm.mu_k = mu_k
    q0 = state.q.copy()
    mass = model.mass.sum() / 3
    uphill = np.array([c, s, 0.0])
    vs, xs = [], []
    for _ in range(steps):
        state, _ = implicit_euler(system, state, DT, terms=[term])
        v_com = (model.mass @ state.v.reshape(-1)).reshape(-1, 3).sum(axis=0) / mass
        x_com = (model.mass @ (state.q - q0).reshape(-1)).reshape(-1, 3).sum(axis=0) / mass
        vs.append(float(v_com @ uphill))
        xs.append(float(x_com @ uphill))
    return np.array(vs), np.array(xs), theta


def test_static_friction_holds_between_atan_mu_k_and_atan_mu_s() -> None:
    # tan(theta) = 0.45: mu_k = 0.3 alone would slide at g (sin - 0.3 cos) = 1.5 m/s^2
    eps_v = 2e-4
    vs, xs, _ = incline(0.45, 0.6, 0.3, steps=200, iterations=4, eps_v=eps_v, settle=20)
    assert np.abs(vs).max() < eps_v  # IPC's static friction: a creep below eps_v
    assert abs(xs[-1]) < 1e-3  # under 1 mm of slip in 2 s
    # the same block with mu_s = mu_k = 0.3 slides away
    vs, _, _ = incline(0.45, 0.3, 0.3, steps=10, eps_v=eps_v, settle=20)
    assert vs[-1] < -0.1


def test_above_atan_mu_s_it_slides_with_the_kinetic_coefficient() -> None:
    vs, _, theta = incline(0.8, 0.6, 0.3, steps=24)
    t = DT * np.arange(1, vs.size + 1)
    a = np.polyfit(t[8:], vs[8:], 1)[0]
    assert a == pytest.approx(-9.81 * (np.sin(theta) - 0.3 * np.cos(theta)), rel=1e-2)


def test_relagging_converges_to_the_20_relag_acceleration() -> None:
    accel = []
    for iterations in (10, 20):
        vs, _, _ = incline(0.8, 0.6, 0.3, steps=16, iterations=iterations)
        t = DT * np.arange(1, vs.size + 1)
        accel.append(np.polyfit(t[4:], vs[4:], 1)[0])
    assert accel[0] == pytest.approx(accel[1], rel=1e-3)


def test_mu_k_above_mu_s_is_refused() -> None:
    from fem3d.errors import ParameterError

    X, T = box_mesh((1, 1, 1), size=(0.1, 0.1, 0.1))
    with pytest.raises(ParameterError, match="mu_k"):
        ContactModel(X, T, dhat=1e-3, mu=0.2, mu_k=0.3)


def test_scene_keys_mu_s_mu_k_and_the_friction_iterations() -> None:
    from fem3d.errors import InputError
    from fem3d.scene import apply_overrides, load_scene
    from fem3d.simulation import Simulation

    base = load_scene("contact_incline")
    sim = Simulation(apply_overrides(base, {"contact.mu_s": 0.7, "contact.mu_k": 0.25,
                                            "contact.friction_iterations": 5}))
    cm = sim.contact.contact
    assert (cm.mu, cm.mu_k) == (0.7, 0.25)
    assert sim.contact.friction.iterations == 5
    one = Simulation(base).contact  # mu sets both; one Newton solve per step by default
    assert one.contact.mu == one.contact.mu_k == base.contact.mu
    assert one.friction.iterations == 1
    with pytest.raises((InputError, ValueError), match="mu_k"):
        apply_overrides(base, {"contact.mu_s": 0.2, "contact.mu_k": 0.3})
