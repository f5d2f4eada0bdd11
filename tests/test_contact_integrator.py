"""Backward Euler with IPC contact (fem3d.physics.terms.contact.ContactTerm in implicit_euler).

Physics checked against theory and against code that does not use the solver's contact set:
no vertex ever below a plane, no triangle intersection between bodies (a fresh ipctk mesh),
a resting body's gap in (0, dhat] with its kinetic energy decaying to round-off, a
frictionless drop never gaining energy, and friction on an incline: sticking when
tan(theta) < mu, sliding with acceleration g (sin(theta) - mu cos(theta)) otherwise.
"""

from __future__ import annotations

import ipctk
import numpy as np
import pytest

from fem3d.errors import SimulationError
from fem3d.mesh.tetmesh import boundary_faces
from fem3d.physics.assembly import kinetic_energy, potential_energy
from fem3d.physics.constraints import Constraints
from fem3d.physics.contact import ContactModel, PlaneObstacle
from fem3d.physics.model import build_model
from fem3d.physics.terms.contact import ContactTerm
from fem3d.solve.integrators import State, System, implicit_euler
from tests.test_contact import box_mesh

G = np.array([0.0, -9.81, 0.0])
DT = 0.01


def free_system(X, T, *, E=1e5, rho=1000.0, gravity=G):
    model = build_model(X, T, E=E, nu=0.3, rho=rho)
    return model, System(model, Constraints.from_fixed_vertices(X, np.zeros(0, int)),
                         gravity=gravity)


def total_energy(model, state, contact):
    """Kinetic + strain + gravity (``-M g . q``) + barrier."""
    fg = model.mass @ np.tile(G, model.n_vertices)
    q = state.q.reshape(-1)
    return (kinetic_energy(model, state.v) + potential_energy(model, state.q) - fg @ q
            + contact.barrier_energy(q))


def test_drop_on_ground_never_penetrates_never_gains_energy_and_comes_to_rest():
    dhat = 1e-3
    X, T = box_mesh((2, 2, 2), size=(0.1, 0.1, 0.1), origin=(0.0, 0.02, 0.0))
    model, system = free_system(X, T)
    cm = ContactModel(X, T, planes=[PlaneObstacle([0, 0, 0], [0, 1, 0])], dhat=dhat)
    term = ContactTerm(cm, tolerance=1e-2)
    state = State.at_rest(model)
    e_prev = total_energy(model, state, cm)
    e0 = e_prev
    kinetic = []
    for _ in range(60):
        state, stats = implicit_euler(system, state, DT, terms=[term])
        assert stats.converged
        # independent of the contact set: every vertex strictly above the plane
        assert state.q[:, 1].min() > 0.0
        e = total_energy(model, state, cm)
        assert e <= e_prev + 1e-12 * abs(e0)  # backward Euler dissipates, never creates
        e_prev = e
        kinetic.append(kinetic_energy(model, state.v))
    assert max(kinetic) > 1e-3  # it did fall (0.02 m: 1 kg * g * 0.02 = 0.2 J available)
    gaps = state.q[:, 1][X[:, 1] == X[:, 1].min()]
    assert (gaps > 0).all() and (gaps <= dhat).all()
    assert kinetic[-1] < 1e-15 * max(kinetic)


def test_a_fast_body_does_not_tunnel_through_the_ground_in_one_step():
    # 50 m/s toward a ground 0.05 m away: v_t dt alone would put the box 0.45 m below it
    X, T = box_mesh((1, 1, 1), size=(0.1, 0.1, 0.1), origin=(0.0, 0.05, 0.0))
    model, system = free_system(X, T, E=1e6, gravity=None)
    cm = ContactModel(X, T, planes=[PlaneObstacle([0, 0, 0], [0, 1, 0])], dhat=1e-3)
    term = ContactTerm(cm)
    v = np.zeros_like(X)
    v[:, 1] = -50.0
    state = State(q=X.copy(), v=v)
    for _ in range(3):
        state, _ = implicit_euler(system, state, DT, terms=[term])
        assert state.q[:, 1].min() > 0.0
    assert state.v[:, 1].mean() > -50.0  # it was stopped by the barrier


def independent_intersections(X, T, q):
    """Any triangle-triangle intersection between different connected components of the
    surface: a fresh ipctk mesh of the boundary, not the model's collision set."""
    F = boundary_faces(T).astype(np.int32)
    cm = ipctk.CollisionMesh.build_from_full_mesh(np.asfortranarray(X), ipctk.edges(F), F)
    return ipctk.has_intersections(cm, cm.vertices(np.asfortranarray(q)))


def test_two_boxes_fall_onto_each_other_and_the_ground_without_intersecting():
    Xa, Ta = box_mesh((2, 1, 2), size=(0.1, 0.05, 0.1), origin=(0.0, 0.005, 0.0))
    Xb, Tb = box_mesh((2, 1, 2), size=(0.1, 0.05, 0.1), origin=(0.03, 0.07, 0.02))
    X = np.vstack([Xa, Xb])
    T = np.vstack([Ta, Tb + len(Xa)])
    ids = np.r_[np.zeros(len(Xa), int), np.ones(len(Xb), int)]
    model, system = free_system(X, T, E=2e5)
    cm = ContactModel(X, T, body_ids=ids, planes=[PlaneObstacle([0, 0, 0], [0, 1, 0])],
                      dhat=5e-4, mu=0.2, eps_v=1e-3)
    term = ContactTerm(cm, tolerance=1e-2)
    state = State.at_rest(model)
    min_between = np.inf
    for _ in range(25):
        state, stats = implicit_euler(system, state, DT, terms=[term])
        assert stats.converged
        assert state.q[:, 1].min() > 0.0
        assert not independent_intersections(X, T, state.q)
        min_between = min(min_between, state.q[ids == 1, 1].min() - state.q[ids == 0, 1].max())
    # the upper box came down onto the lower one (its 0.015 m gap closed; it may tilt over
    # the lower one's edge, which is why "below the top" is allowed: no intersection is the
    # check above)
    assert min_between < 2e-3


def incline_run(tan_theta, mu, steps, eps_v=1e-3):
    """A stiff block resting on a plane inclined by theta; returns COM velocity along the
    slope (positive uphill) at each step, and the contact model."""
    theta = np.arctan(tan_theta)
    c, s = np.cos(theta), np.sin(theta)
    dhat = 1e-3
    X, T = box_mesh((2, 1, 2), size=(0.1, 0.05, 0.1))
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    X = X @ R.T + np.array([0.0, 0.5 * dhat / c, 0.0])  # bottom face dhat/2 off the plane
    model, system = free_system(X, T, E=1e6)
    cm = ContactModel(X, T, planes=[PlaneObstacle([0, 0, 0], [-s, c, 0])], dhat=dhat, mu=mu,
                      eps_v=eps_v)
    term = ContactTerm(cm, tolerance=1e-4)
    state = State.at_rest(model)
    mass = model.mass.sum() / 3
    uphill = np.array([c, s, 0.0])
    vs = []
    for _ in range(steps):
        state, _ = implicit_euler(system, state, DT, terms=[term])
        assert (cm.plane_gaps(state.q) > 0).all()
        v_com = (model.mass @ state.v.reshape(-1)).reshape(-1, 3).sum(axis=0) / mass
        vs.append(float(v_com @ uphill))
    return np.array(vs), theta


def test_block_on_incline_sticks_when_tan_theta_below_mu():
    eps_v = 1e-3
    vs, _ = incline_run(0.3, 0.5, steps=20, eps_v=eps_v)
    # IPC's smoothed static friction: creep below eps_v (sliding would reach -0.4 m/s here)
    # once the lagged normal forces have caught up with the weight (the block starts at
    # dhat / 2, not at its equilibrium gap; friction is lagged once per step)
    assert np.abs(vs[:3]).max() < 10 * eps_v
    assert np.abs(vs[3:]).max() < eps_v


@pytest.mark.parametrize("mu", [0.0, 0.5])
def test_block_on_incline_slides_with_coulomb_acceleration(mu):
    vs, theta = incline_run(0.8, mu, steps=24)
    t = DT * np.arange(1, vs.size + 1)
    a = np.polyfit(t[8:], vs[8:], 1)[0]  # after the first contact transient
    expected = -9.81 * (np.sin(theta) - mu * np.cos(theta))
    # tolerance: 1% (measured: agreement to 4 digits with lagged friction at dt = 0.01)
    assert a == pytest.approx(expected, rel=1e-2)


def test_intersecting_start_is_an_error_naming_the_bodies():
    Xa, Ta = box_mesh((1, 1, 1), size=(0.1, 0.1, 0.1))
    Xb, Tb = box_mesh((1, 1, 1), size=(0.1, 0.1, 0.1), origin=(0.05, 0.05, 0.05))
    X = np.vstack([Xa, Xb])
    T = np.vstack([Ta, Tb + len(Xa)])
    ids = np.r_[np.zeros(len(Xa), int), np.ones(len(Xb), int)]
    cm = ContactModel(X, T, body_ids=ids, body_names=["left", "right"], dhat=1e-3)
    with pytest.raises(SimulationError, match="left and right intersect"):
        cm.check_admissible(X.reshape(-1))
