"""CCD of queries that carry the bodies far (:mod:`fem3d.physics.contact.far_travel`): bodies that
travel far along one CCD query (``static``'s first load step drops them to the ground in one
Newton direction) are checked on their motion relative to each other, with the same steps as
in the world frame; with a mesh obstacle (it stays behind) in the world frame; and a query
that moves a vertex by more than a tenth of their size (relative to that frame) is cut to
that length.
"""

from __future__ import annotations

import ipctk
import numpy as np
import pytest

from fem3d.errors import SimulationError
from fem3d.physics.contact import ContactModel, MeshObstacle
from fem3d.physics.contact.candidates import StepCandidates
from fem3d.physics.contact.far_travel import FAR_TRAVEL
from fem3d.scene import load_scene
from fem3d.simulation import Simulation
from tests.physics.contact.test_potentials import independent_intersection, two_boxes


@pytest.fixture(scope="module")
def one_body():
    """The two boxes of ``two_boxes`` as one body with self-contact (0.05 apart)."""
    X, T, _ = two_boxes(gap=0.05)
    cm = ContactModel(X, T, dhat=0.01, kappa=1.0, self_contact=True)
    upper = X[:, 1] > 1.0 + 1e-9
    return X, T, cm, upper


def world_frame_step(cm: ContactModel, q0: np.ndarray, q1: np.ndarray) -> float:
    """The world-frame CCD step with a fresh brute-force broad phase (the reference)."""
    V0, V1 = cm.collision_vertices(q0), cm.collision_vertices(q1)
    return float(ipctk.compute_collision_free_stepsize(
        cm.mesh, V0, V1, broad_phase=ipctk.BruteForce(), narrow_phase_ccd=cm.collisions.ccd))


def test_a_far_travelling_body_gets_the_world_frames_step(one_body):
    X, T, cm, upper = one_body
    q0 = X.copy()
    q1 = X + [3.0, -100.0, 1.0]  # travels about 40 times its size
    q1[upper, 1] -= 0.5  # and its upper half moves through the lower one
    before = cm.stats.far_ccd_calls
    a = cm.max_step(q0.reshape(-1), q1.reshape(-1))
    assert cm.stats.far_ccd_calls == before + 1
    reference = world_frame_step(cm, q0, q1)
    assert 0.0 < reference < 0.1
    assert a == pytest.approx(reference, rel=1e-6)
    ids = np.zeros(len(X), int)
    assert not independent_intersection(X, T, ids, q0 + a * (q1 - q0))


def test_a_short_query_uses_the_steps_shared_candidates(one_body):
    X, _, cm, upper = one_body
    q0 = X.copy()
    q1 = X.copy()
    q1[upper, 1] -= 0.5  # the same collision, no travel
    before = cm.stats.far_ccd_calls
    a = cm.max_step(q0.reshape(-1), q1.reshape(-1))
    assert cm.stats.far_ccd_calls == before
    assert a == pytest.approx(world_frame_step(cm, q0, q1), rel=1e-6)


def test_a_query_that_deforms_the_body_by_kilometres_is_cut(one_body):
    X, _, cm, _ = one_body
    centre = X.mean(axis=0)
    q0 = X.copy()
    q1 = centre + 1e5 * (X - centre) + [0.0, -1e4, 0.0]  # blown up: nothing collides
    assert world_frame_step(cm, q0, q1) == 1.0
    a = cm.max_step(q0.reshape(-1), q1.reshape(-1))
    size = np.linalg.norm(np.ptp(X, axis=0))
    largest = np.abs((q1 - q1.mean(axis=0)) - (q0 - q0.mean(axis=0))).max()
    assert a == pytest.approx(FAR_TRAVEL * size / largest, rel=1e-12)


def test_two_bodies_travelling_together_get_the_world_frames_step():
    X, T, ids = two_boxes(gap=0.05)
    cm = ContactModel(X, T, body_ids=ids, dhat=0.01, kappa=1.0)
    q0 = X.copy()
    q1 = X + [0.0, -100.0, 2.0]
    q1[ids == 1, 1] -= 0.5  # the upper box through the lower one on the way
    a = cm.max_step(q0.reshape(-1), q1.reshape(-1))
    assert cm.stats.far_ccd_calls == 1
    reference = world_frame_step(cm, q0, q1)
    assert 0.0 < reference < 0.1
    assert a == pytest.approx(reference, rel=1e-6)


def test_with_a_mesh_obstacle_a_far_query_is_cut_in_the_world_frame():
    X, T, _ = two_boxes(gap=0.05)
    floor = MeshObstacle(np.array([[-5.0, -0.1, -5.0], [5.0, -0.1, -5.0], [0.0, -0.1, 5.0]]),
                         np.array([[0, 2, 1]]), name="floor")
    cm = ContactModel(X, T, meshes=[floor], dhat=0.01, kappa=1.0)
    cut = FAR_TRAVEL * np.linalg.norm(np.ptp(X, axis=0)) / 100.0
    # 100 m down: the floor, 0.1 below, stops it as the world frame's CCD says
    down = X + [0.0, -100.0, 0.0]
    a = cm.max_step(X.reshape(-1), down.reshape(-1))
    assert cm.stats.far_ccd_calls == 1
    assert 0.0 < a < cut
    assert a == pytest.approx(world_frame_step(cm, X, down), rel=1e-2)
    assert (X + a * (down - X))[:, 1].min() > -0.1
    # 100 m up: nothing in the way, the step is the cut
    up = X + [0.0, 100.0, 0.0]
    assert cm.max_step(X.reshape(-1), up.reshape(-1)) == pytest.approx(cut, rel=1e-12)


def test_static_lands_the_self_contact_bunny_drop_without_intersecting():
    """The gallery drop as shipped (self-contact) under ``static``: its first load step took
    51 s (every surface pair a CCD candidate along the fall), now under a second."""
    sim = Simulation(load_scene("contact_bunny_drop", {"simulation.integrator": "static"}),
                     scripted=True)
    cm = sim.contact.contact
    assert not cm.has_intersections(sim.q.reshape(-1))
    for _ in range(3):
        sim.step()
        assert not cm.has_intersections(sim.q.reshape(-1))
    assert cm.stats.far_ccd_calls > 0
    assert 0.0 < sim.q[:, 1].min() < 1e-3  # on the ground, not through it


def test_static_on_the_stack_says_why_it_stops():
    """The stack's top block is unsupported, so ``static`` has no equilibrium to find; with
    the scene's ``reuse`` solver it died on CG's factorization of an indefinite first matrix
    (``NotPositiveDefinite``) before it could say so. (With ``direct`` it died in ipctk's
    broad phase, ``std::bad_alloc``; now it gives the same message after its load
    increments: the far-travelling queries are the tests above.)"""
    sim = Simulation(load_scene("contact_stack", {"simulation.integrator": "static"}),
                     scripted=True)
    with pytest.raises(SimulationError, match="no equilibrium found"):
        sim.step()


def test_the_steps_candidates_grow_only_up_to_a_limit():
    """A step's shared candidate boxes hold every position it asked about while they stay
    narrower than ``max_extent`` (the model gives a far query's reach); beyond, the set is
    rebuilt around the query alone, which then holds it."""
    X, T, _ = two_boxes(gap=0.05)
    cm = ContactModel(X, T, dhat=0.01, kappa=1.0, self_contact=True)
    V = cm.collision_vertices(X.reshape(-1))
    step = StepCandidates(cm.mesh, ipctk.HashGrid(), pad=0.01, max_extent=0.5)
    step.reset(V)
    nearby = V + [0.0, -0.2, 0.0]
    step.near(nearby, 0.005)  # grown: both positions inside
    assert (step.lo <= V).all() and (step.hi >= V).all()
    assert (step.lo <= nearby).all() and (step.hi >= nearby).all()
    far = V + [0.0, -10.0, 0.0]
    pairs = step.near(far, 0.005)
    assert (step.hi - step.lo).max() <= 0.5 + 1e-12  # rebuilt around the far query
    assert (step.lo <= far).all() and (step.hi >= far).all()
    assert not (step.hi >= V).all()  # the first positions are no longer held
    fresh = ipctk.Candidates()
    fresh.build(cm.mesh, far, 0.01, broad_phase=ipctk.BruteForce())
    assert len(pairs) >= len(fresh)
