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
from fem3d.physics.contact import ContactModel, MeshObstacle, PlaneObstacle
from fem3d.physics.model import build_model
from fem3d.physics.terms.contact import ContactTerm
from fem3d.scene.build import build_loads
from fem3d.solve.integrators import State, System, implicit_euler
from tests.physics.contact.test_potentials import box_mesh

G = np.array([0.0, -9.81, 0.0])
DT = 0.01


def free_system(X, T, *, E=1e5, rho=1000.0, gravity=G):
    model = build_model(X, T, E=E, nu=0.3, rho=rho)
    return model, System(model, Constraints.from_fixed_vertices(X, np.zeros(0, int)),
                         loads=build_loads(model, gravity))


def total_energy(model, state, contact):
    """Kinetic + strain + gravity (``-M g . q``) + barrier."""
    fg = model.mass @ np.tile(G, model.n_vertices)
    q = state.q.reshape(-1)
    return (kinetic_energy(model, state.v) + potential_energy(model, state.q) - fg @ q
            + contact.barrier_energy(q))


#: The default Newton of a contact step and issue 21's opt-in settings (the start at q_t
#: when CCD cuts the free flight, the parabolic line search): (newton_start, line_search).
NEWTON_SETTINGS = pytest.mark.parametrize(("newton_start", "line_search"), [
    ("clamped", "backtrack"), ("q_t", "parabolic")], ids=["default", "q_t-parabolic"])


@NEWTON_SETTINGS
def test_drop_on_ground_never_penetrates_never_gains_energy_and_comes_to_rest(newton_start,
                                                                              line_search):
    dhat = 1e-3
    X, T = box_mesh((2, 2, 2), size=(0.1, 0.1, 0.1), origin=(0.0, 0.02, 0.0))
    model, system = free_system(X, T)
    cm = ContactModel(X, T, planes=[PlaneObstacle([0, 0, 0], [0, 1, 0])], dhat=dhat)
    term = ContactTerm(cm, tolerance=1e-2, newton_start=newton_start)
    state = State.at_rest(model)
    e_prev = total_energy(model, state, cm)
    e0 = e_prev
    kinetic = []
    for _ in range(60):
        state, stats = implicit_euler(system, state, DT, terms=[term], line_search=line_search)
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


@NEWTON_SETTINGS
def test_a_fast_body_does_not_tunnel_through_the_ground_in_one_step(newton_start, line_search):
    # 50 m/s toward a ground 0.05 m away: v_t dt alone would put the box 0.45 m below it
    X, T = box_mesh((1, 1, 1), size=(0.1, 0.1, 0.1), origin=(0.0, 0.05, 0.0))
    model, system = free_system(X, T, E=1e6, gravity=None)
    cm = ContactModel(X, T, planes=[PlaneObstacle([0, 0, 0], [0, 1, 0])], dhat=1e-3)
    term = ContactTerm(cm, newton_start=newton_start)
    v = np.zeros_like(X)
    v[:, 1] = -50.0
    state = State(q=X.copy(), v=v)
    for _ in range(3):
        state, stats = implicit_euler(system, state, DT, terms=[term], line_search=line_search)
        assert stats.converged
        assert state.q[:, 1].min() > 0.0
    # stopped by the barrier, not merely slowed: after three steps the box is no longer
    # moving into the ground (an elastic box rebounds; the sign test allows a rest, too)
    mass = model.mass.sum() / 3
    v_com = (model.mass @ state.v.reshape(-1)).reshape(-1, 3).sum(axis=0) / mass
    print("centre-of-mass velocity after the impact", v_com)
    assert v_com[1] > -1.0
    assert state.q[:, 1].min() < 0.05  # and it did reach the ground


@pytest.mark.parametrize("speed", [5.0, 20.0])
def test_a_fast_body_hits_a_free_body_without_tunnelling_and_conserves_momentum(speed):
    """Body into body (``speed`` over a 0.03 m gap, no gravity, no obstacle): every step
    converges, no intersection at any step's end (a fresh ipctk mesh), the moving box never
    gets past the struck one, which is pushed along, and the total momentum is conserved
    (the barrier's forces are equal and opposite).

    At 20 m/s (0.2 m per step, twice a box's width) the first step's Newton chain of
    CCD-safe iterates turns both boxes until b slides past a's corner, while the step's own
    straight motion passes through a (issue 24): with substeps that step is redone as
    substeps (4 of dt/4, measured) and b stays on its side; without them (``max_substeps =
    1``) b ends the second step wholly past a."""
    Xa, Ta = box_mesh((1, 1, 1), size=(0.1, 0.1, 0.1), origin=(0.0, 0.0, 0.0))
    Xb, Tb = box_mesh((1, 1, 1), size=(0.1, 0.1, 0.1), origin=(0.13, 0.02, 0.01))
    X = np.vstack([Xa, Xb])
    T = np.vstack([Ta, Tb + len(Xa)])
    ids = np.r_[np.zeros(len(Xa), int), np.ones(len(Xb), int)]
    model, system = free_system(X, T, E=1e6, gravity=None)
    cm = ContactModel(X, T, body_ids=ids, dhat=1e-3)
    term = ContactTerm(cm, tolerance=1e-2)
    v = np.zeros_like(X)
    v[ids == 1, 0] = -speed  # box b flies into box a
    state = State(q=X.copy(), v=v)
    masses = model.mass.diagonal().reshape(-1, 3)[:, 0]

    def momentum(st):
        return (masses[:, None] * st.v).sum(axis=0)

    def centre(st, body):
        return masses[ids == body] @ st.q[ids == body] / masses[ids == body].sum()

    p0 = momentum(state)
    substeps = []
    for _ in range(4):
        state, stats = implicit_euler(system, state, DT, terms=[term], max_substeps=8)
        substeps.append(stats.substeps)
        assert stats.converged
        assert not independent_intersections(X, T, state.q)
        assert centre(state, 1)[0] - centre(state, 0)[0] > 0.05  # b never gets past a
        np.testing.assert_allclose(momentum(state), p0, atol=1e-9 * np.abs(p0).max())
    va = (masses[ids == 0] @ state.v[ids == 0, 0]) / masses[ids == 0].sum()
    print("struck box's velocity after the impact", va, "substeps per step", substeps)
    assert va < -0.2 * speed  # the struck box was pushed along
    assert substeps[1:] == [1, 1, 1] and (substeps[0] > 1) == (speed > 10)


@pytest.mark.parametrize("mu, slide, sink", [(0.5, 0.0, 0.0), (0.0, 0.2, 0.0),
                                             (0.5, 0.0, 0.05)],
                         ids=["friction", "sliding-floor", "friction-sinking-floor"])
def test_energy_never_grows_with_friction_and_with_a_moving_obstacle(mu, slide, sink):
    """A box thrown sideways, 5 mm above the ground. With friction (lagged, IPC's): the total energy
    never grows, and the sliding stops. A frictionless floor sliding under the box (its normal
    force does no work) or a floor sinking away from it (negative work) adds none either."""
    dhat = 1e-3
    X, T = box_mesh((2, 1, 2), size=(0.1, 0.05, 0.1), origin=(0.0, 0.005, 0.0))
    model, system = free_system(X, T)
    V = np.array([[-2.0, 0.0, -2.0], [2.0, 0.0, -2.0], [2.0, 0.0, 2.0], [-2.0, 0.0, 2.0]])
    F = np.array([[0, 2, 1], [0, 3, 2]])

    def move(rest, t):
        return rest + np.array([slide * t, -sink * t, 0.0])

    cm = ContactModel(X, T, meshes=[MeshObstacle(V, F, motion=move, name="floor")],
                      dhat=dhat, mu=mu, eps_v=1e-3)
    term = ContactTerm(cm, tolerance=1e-3)
    v = np.zeros_like(X)
    v[:, 0] = 0.5
    state = State(q=X.copy(), v=v)
    e_prev = total_energy(model, state, cm)
    e0 = abs(e_prev)
    for _ in range(30):
        state, stats = implicit_euler(system, state, DT, terms=[term])
        assert stats.converged
        e = total_energy(model, state, cm)
        # 1e-5: a frictionless mesh floor, static or sliding, was measured to add up to
        # 1e-6 (static) and 4e-6 (sliding) of e0 per step (the barrier's adaptive stiffness);
        # a real energy source (friction pushing, the floor's work) adds 1e-3 and more
        assert e <= e_prev + 1e-5 * e0, (e, e_prev)
        e_prev = e
    if mu > 0 and sink == 0.0:
        assert np.abs(state.v[:, 0]).max() < 0.05  # friction stopped the sliding
    if mu == 0.0:
        assert state.v[:, 0].mean() > 0.45  # frictionless: the sideways motion is kept


def independent_intersections(X, T, q):
    """Any triangle-triangle intersection between different connected components of the
    surface: a fresh ipctk mesh of the boundary, not the model's collision set."""
    F = boundary_faces(T).astype(np.int32)
    cm = ipctk.CollisionMesh.build_from_full_mesh(np.asfortranarray(X), ipctk.edges(F), F)
    return ipctk.has_intersections(cm, cm.vertices(np.asfortranarray(q)))


@NEWTON_SETTINGS
def test_two_boxes_fall_onto_each_other_and_the_ground_without_intersecting(newton_start,
                                                                            line_search):
    Xa, Ta = box_mesh((2, 1, 2), size=(0.1, 0.05, 0.1), origin=(0.0, 0.005, 0.0))
    Xb, Tb = box_mesh((2, 1, 2), size=(0.1, 0.05, 0.1), origin=(0.03, 0.07, 0.02))
    X = np.vstack([Xa, Xb])
    T = np.vstack([Ta, Tb + len(Xa)])
    ids = np.r_[np.zeros(len(Xa), int), np.ones(len(Xb), int)]
    model, system = free_system(X, T, E=2e5)
    cm = ContactModel(X, T, body_ids=ids, planes=[PlaneObstacle([0, 0, 0], [0, 1, 0])],
                      dhat=5e-4, mu=0.2, eps_v=1e-3)
    term = ContactTerm(cm, tolerance=1e-2, newton_start=newton_start)
    state = State.at_rest(model)
    min_between = np.inf
    for _ in range(25):
        state, stats = implicit_euler(system, state, DT, terms=[term], line_search=line_search)
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
