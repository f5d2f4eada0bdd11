"""fem3d.physics.contact: the IPC barrier, lagged friction, CCD and intersection checks on
fem3d DOFs.

Derivatives are checked against central finite differences of the energies (not against
ipctk's own derivatives), the PSD projection by eigenvalues, CCD by an independent
intersection test at the returned step, and the body filter by the pairs it lets through.
"""

from __future__ import annotations

import ipctk
import numpy as np
import pytest

from fem3d.errors import ParameterError, SimulationError
from fem3d.mesh.tetmesh import boundary_faces, box_tet_mesh
from fem3d.physics.contact import ContactModel, MeshObstacle, PlaneObstacle


def box_mesh(n=(2, 2, 2), size=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0)):
    """Kuhn-subdivided box: 6 positively oriented tets per cell."""
    return box_tet_mesh(n, size, origin)


def two_boxes(gap: float):
    """Two unit boxes, the second above the first by ``gap``, as one mesh with body ids."""
    Xa, Ta = box_mesh()
    Xb, Tb = box_mesh(origin=(0.2, 1.0 + gap, 0.1))
    X = np.vstack([Xa, Xb])
    T = np.vstack([Ta, Tb + Xa.shape[0]])
    ids = np.r_[np.zeros(len(Xa), int), np.ones(len(Xb), int)]
    return X, T, ids


def fd_check(f, g, x, d, h):
    """Central difference of ``f`` along ``d`` vs ``g(x) . d``: relative error."""
    fd = (f(x + h * d) - f(x - h * d)) / (2 * h)
    exact = float(g(x) @ d)
    return abs(fd - exact) / max(abs(exact), 1e-300)


# ---------------------------------------------------------------------------------------------
# barrier


@pytest.fixture
def plane_contact():
    X, T = box_mesh()
    # lowest vertices 0.3 above the plane; dhat 0.5: the bottom layer is active
    cm = ContactModel(X, T, planes=[PlaneObstacle([0, -0.3, 0], [0, 1, 0])], dhat=0.5,
                      kappa=7.0)
    return X, T, cm


def test_plane_barrier_value_is_ipc_log_barrier_on_squared_distance(plane_contact):
    X, T, cm = plane_contact
    q = X.reshape(-1)
    bottom = np.flatnonzero(X[:, 1] == 0.0)
    expected = 7.0 * bottom.size * ipctk.barrier(0.3 ** 2, 0.5 ** 2)
    assert cm.barrier_energy(q) == pytest.approx(expected, rel=1e-12)
    # active over the whole support (ipctk alone activates planes only within dhat / 2)
    q2 = X.copy()
    q2[:, 1] += 0.15  # gap 0.45 < dhat
    assert cm.barrier_energy(q2) == pytest.approx(
        7.0 * bottom.size * ipctk.barrier(0.45 ** 2, 0.5 ** 2), rel=1e-12)
    q2[:, 1] += 0.1  # gap 0.55 > dhat
    assert cm.barrier_energy(q2) == 0.0
    # interior vertex moves: no effect (not on the collision surface)
    assert cm.n_surface < X.shape[0]


def test_barrier_gradient_and_hessian_match_finite_differences():
    X, T, ids = two_boxes(gap=0.05)
    planes = [PlaneObstacle([0, -0.04, 0], [0.1, 1, 0])]
    cm = ContactModel(X, T, body_ids=ids, planes=planes, dhat=0.1, kappa=3.0)
    rng = np.random.default_rng(1)
    q = X.reshape(-1) + 0.003 * rng.standard_normal(X.size)
    assert cm.n_active(q) > 10
    d = rng.standard_normal(q.size)
    assert fd_check(cm.barrier_energy, cm.barrier_gradient, q, d, 1e-6) < 1e-6
    H = cm.barrier_hessian(q, project=False).tocsr()
    h = 1e-7
    fd = (cm.barrier_gradient(q + h * d) - cm.barrier_gradient(q - h * d)) / (2 * h)
    assert np.linalg.norm(fd - H @ d) < 1e-5 * np.linalg.norm(H @ d)
    # projected: symmetric positive semi-definite, and no coupling to interior vertices
    Hp = cm.barrier_hessian(q).tocsr().toarray()
    assert np.abs(Hp - Hp.T).max() <= 1e-12 * np.abs(Hp).max()
    assert np.linalg.eigvalsh(Hp).min() >= -1e-9 * np.abs(Hp).max()
    interior = np.setdiff1d(np.arange(X.shape[0]), cm.surface)
    idof = (3 * interior[:, None] + np.arange(3)).reshape(-1)
    assert not Hp[idof].any() and not cm.barrier_gradient(q)[idof].any()


def test_mesh_obstacle_barrier_and_its_kinematic_motion():
    X, T = box_mesh()
    V = np.array([[-1.0, -0.1, -1], [3, -0.1, -1], [3, -0.1, 3], [-1, -0.1, 3]])
    F = np.array([[0, 2, 1], [0, 3, 2]])

    def lift(rest, t):
        return rest + np.array([0.0, 0.05 * t, 0.0])

    cm = ContactModel(X, T, meshes=[MeshObstacle(V, F, motion=lift, name="floor")],
                      dhat=0.2, kappa=1.0)
    q = X.reshape(-1)
    bottom = np.count_nonzero(X[:, 1] == 0.0)
    # face-vertex pairs; a vertex over the shared diagonal is counted once per triangle
    # only by ipctk's de-duplication, so compare with the distance law instead of a count
    e0 = cm.barrier_energy(q)
    assert e0 > 0
    cm.set_time(1.0)  # floor at -0.05: closer, larger barrier
    assert cm.barrier_energy(q) > e0
    assert cm.minimum_distance(q) == pytest.approx(0.05, rel=1e-9)
    assert bottom > 0
    rng = np.random.default_rng(2)
    d = rng.standard_normal(q.size)
    qp = q + 1e-3 * rng.standard_normal(q.size)
    assert fd_check(cm.barrier_energy, cm.barrier_gradient, qp, d, 1e-7) < 1e-6
    # the obstacle moving up by 0.2 in one step passes through the box's bottom
    assert cm.obstacle_step(q, 0.0, 4.0) < 1.0
    assert cm.obstacle_step(q, 0.0, 0.5) == 1.0


def test_self_contact_switch_and_body_filter():
    X, T, ids = two_boxes(gap=0.02)
    off = ContactModel(X, T, body_ids=ids, dhat=0.05, kappa=1.0)
    # with dhat above the edge length of a box, a body would see its own surface
    own = ContactModel(X[ids == 0], T[: T.shape[0] // 2], dhat=0.6, kappa=1.0)
    own_on = ContactModel(X[ids == 0], T[: T.shape[0] // 2], dhat=0.6, kappa=1.0,
                          self_contact=True)
    q = X.reshape(-1)
    assert off.n_active(q) > 0  # the two bodies see each other
    assert own.n_active(X[ids == 0].reshape(-1)) == 0
    assert own_on.n_active(X[ids == 0].reshape(-1)) > 0
    # pairs between bodies only: moving body 0's surface alone changes nothing within body 1
    g = off.barrier_gradient(q).reshape(-1, 3)
    top_of_b = (ids == 1) & (X[:, 1] > 1.5)
    assert not g[top_of_b].any()


# ---------------------------------------------------------------------------------------------
# friction


def test_friction_is_coulomb_when_sliding_and_matches_finite_differences():
    X, T = box_mesh()
    cm = ContactModel(X, T, planes=[PlaneObstacle([0, -0.1, 0], [0, 1, 0])], dhat=0.2,
                      kappa=5.0, mu=0.4, eps_v=1e-2)
    dt = 0.01
    q0 = X.reshape(-1).copy()
    cm.lag_friction(q0, dt)
    assert cm.n_friction_pairs == np.count_nonzero(X[:, 1] == 0.0)
    # normal force of the lagged contacts: |dB/dy| summed over the bottom vertices
    lam = -cm.barrier_gradient(q0).reshape(-1, 3)[:, 1].sum()
    # slide along x by far more than eps_v dt: tangential force = mu * lambda, along -x
    q = q0.reshape(-1, 3).copy()
    q[:, 0] += 0.01
    gf = cm.friction_gradient(q.reshape(-1)).reshape(-1, 3)
    assert gf[:, 0].sum() == pytest.approx(0.4 * lam, rel=1e-9)
    assert np.abs(gf[:, 1:]).max() == 0.0
    assert cm.friction_energy(q.reshape(-1)) > 0
    # smooth (static) regime and the Hessian, against finite differences
    rng = np.random.default_rng(3)
    qs = q0 + 3e-5 * rng.standard_normal(q0.size)
    d = rng.standard_normal(q0.size)
    assert fd_check(cm.friction_energy, cm.friction_gradient, qs, d, 1e-8) < 1e-5
    Hf = cm.friction_hessian(qs, project=False).tocsr()
    h = 1e-9
    fd = (cm.friction_gradient(qs + h * d) - cm.friction_gradient(qs - h * d)) / (2 * h)
    assert np.linalg.norm(fd - Hf @ d) < 1e-4 * np.linalg.norm(Hf @ d)
    Hp = cm.friction_hessian(qs).tocsr().toarray()
    assert np.linalg.eigvalsh(Hp).min() >= -1e-9 * np.abs(Hp).max()


def test_frictionless_has_no_friction_terms():
    X, T = box_mesh()
    cm = ContactModel(X, T, planes=[PlaneObstacle([0, -0.1, 0], [0, 1, 0])], dhat=0.2,
                      kappa=5.0, mu=0.0)
    cm.lag_friction(X.reshape(-1), 0.01)
    q = X.reshape(-1) + 0.01
    assert cm.n_friction_pairs == 0
    assert cm.friction_energy(q) == 0.0 and not cm.friction_gradient(q).any()
    assert cm.energy(q) == cm.barrier_energy(q)


# ---------------------------------------------------------------------------------------------
# CCD and intersections


def independent_intersection(X, T, ids, q3):
    """Triangle-triangle intersection between the two bodies, by a fresh ipctk mesh built
    here (not the ContactModel's)."""
    F = boundary_faces(T)
    Fi = F.astype(np.int32)
    cm = ipctk.CollisionMesh.build_from_full_mesh(np.asfortranarray(X), ipctk.edges(Fi), Fi)
    V = cm.vertices(np.asfortranarray(q3))
    return ipctk.has_intersections(cm, V)


def test_max_step_stops_before_intersection():
    X, T, ids = two_boxes(gap=0.05)
    cm = ContactModel(X, T, body_ids=ids, planes=[PlaneObstacle([0, -0.05, 0], [0, 1, 0])],
                      dhat=0.01, kappa=1.0)
    q0 = X.copy()
    q1 = X.copy()
    q1[ids == 1, 1] -= 0.5  # the upper box moves through the lower one
    assert independent_intersection(X, T, ids, q1)
    a = cm.max_step(q0.reshape(-1), q1.reshape(-1))
    assert 0.0 < a < 0.1  # the gap is 0.05 out of 0.5
    qa = q0 + a * (q1 - q0)
    assert not independent_intersection(X, T, ids, qa)
    assert not cm.has_intersections(qa.reshape(-1))
    # into the plane
    q2 = X.copy()
    q2[:, 1] -= 0.2
    a2 = cm.max_step(q0.reshape(-1), q2.reshape(-1))
    assert 0.0 < a2 < 0.25
    assert (q0 + a2 * (q2 - q0))[:, 1].min() > -0.05
    # a free motion is not clamped
    q3 = X.copy()
    q3[ids == 1, 1] += 0.5
    assert cm.max_step(q0.reshape(-1), q3.reshape(-1)) == 1.0


def test_the_steps_candidates_answer_as_a_fresh_broad_phase_and_are_reused():
    """One candidate set per step (``start_step``), grown only when a query leaves its boxes:
    CCD, the collision set (pairs, order, values), its derivatives and the minimum distance
    equal those of a fresh broad phase at each query, bit for bit; queries inside the step's
    boxes run no broad phase, one far outside grows them."""
    X, T, ids = two_boxes(gap=0.004)
    rng = np.random.default_rng(3)

    def model():
        return ContactModel(X, T, body_ids=ids, dhat=0.01, kappa=1.0, mu=0.3, eps_v=1e-3)

    cm = model()
    q_t = X.reshape(-1).copy()
    q_pred = q_t.copy()
    q_pred.reshape(-1, 3)[ids == 1, 1] -= 0.01  # the upper box falls onto the lower one
    cm.start_step(q_t, q_pred, pad=0.02)
    built = cm.stats.broad_phases
    mesh = cm.mesh
    for k in range(12):
        # iterates around the predicted motion; the last ones far outside the step's boxes
        q = q_t + rng.uniform(0.0, 1.0) * (q_pred - q_t) + 1e-3 * rng.standard_normal(q_t.size)
        if k >= 10:
            q = q + 0.3 * k
        q1 = q + 0.003 * rng.standard_normal(q_t.size)
        fresh = model()  # no step: candidates built around each query only
        assert cm.max_step(q, q1) == fresh.max_step(q, q1)
        V0, V1 = cm.collision_vertices(q), cm.collision_vertices(q1)
        assert cm.max_step(q, q1) == min(1.0, ipctk.compute_collision_free_stepsize(
            mesh, V0, V1, broad_phase=ipctk.HashGrid(), narrow_phase_ccd=ipctk.AdditiveCCD()))
        col = ipctk.NormalCollisions()
        col.build(mesh, V0, cm.dhat, broad_phase=ipctk.HashGrid())
        assert cm.n_active(q) == len(col)
        assert cm.barrier_energy(q) == fresh.barrier_energy(q)
        assert np.array_equal(cm.barrier_gradient(q), fresh.barrier_gradient(q))
        Ha, Hb = cm.barrier_hessian(q), fresh.barrier_hessian(q)
        assert np.array_equal(Ha.row, Hb.row) and np.array_equal(Ha.data, Hb.data)
        assert cm.minimum_distance(q) == fresh.minimum_distance(q)
        if k == 9:
            assert len(col) > 0  # the boxes did come within dhat
            assert cm.stats.broad_phases == built  # every query so far reused the set
    assert cm.stats.broad_phases > built  # the far queries grew the boxes


def test_initial_intersection_names_the_bodies():
    X, T, ids = two_boxes(gap=-0.2)
    cm = ContactModel(X, T, body_ids=ids, body_names=["jelly", "cube"],
                      planes=[PlaneObstacle([0, 0.1, 0], [0, 1, 0], name="ground")],
                      dhat=0.01, kappa=1.0)
    with pytest.raises(SimulationError) as err:
        cm.check_admissible(X.reshape(-1))
    msg = str(err.value)
    assert "jelly and cube" in msg and "jelly and ground" in msg
    assert "cube and ground" not in msg
    ok = ContactModel(*two_boxes(gap=0.1)[:2], body_ids=ids, dhat=0.01, kappa=1.0)
    ok.check_admissible(two_boxes(gap=0.1)[0].reshape(-1))


# ---------------------------------------------------------------------------------------------
# barrier stiffness


def test_adaptive_stiffness_initial_and_update():
    X, T = box_mesh()
    cm = ContactModel(X, T, planes=[PlaneObstacle([0, -0.01, 0], [0, 1, 0])], dhat=0.05)
    assert cm.adaptive
    q = X.reshape(-1)
    # an objective pushing down (gravity-like): kappa balances it against the barrier
    ge = np.zeros(q.size)
    ge[1::3] = 1.0
    unit = ContactModel(X, T, planes=cm.planes, dhat=0.05, kappa=1.0)
    gb = unit.barrier_gradient(q)
    k_balance = -(gb @ ge) / (gb @ gb)
    # a light body: clamped to IPC's ceiling (100x the minimum, which scales with the mass)
    assert cm.initialize_stiffness(q, ge, average_mass=1e-3) == cm.max_kappa < k_balance
    k = cm.initialize_stiffness(q, ge, average_mass=50.0)
    assert cm.max_kappa / 100 < k < cm.max_kappa
    assert k == pytest.approx(k_balance, rel=1e-12)
    # distances shrinking below 1e-9 of the scene: doubled, capped at max_kappa
    qc = X.copy()
    qc[:, 1] -= 0.01 - 1e-12
    cm.update_stiffness(qc.reshape(-1))
    qc[:, 1] -= 5e-13
    k2 = cm.update_stiffness(qc.reshape(-1))
    assert k2 == pytest.approx(min(2 * k, cm.max_kappa))


def test_bad_parameters_are_parameter_errors():
    X, T = box_mesh()
    with pytest.raises(ParameterError, match="dhat"):
        ContactModel(X, T, dhat=0.0)
    with pytest.raises(ParameterError, match="mu"):
        ContactModel(X, T, dhat=0.1, mu=-1)
    with pytest.raises(ParameterError, match="normal is zero"):
        PlaneObstacle([0, 0, 0], [0, 0, 0], name="ground")
    with pytest.raises(ParameterError, match="broad phase"):
        ContactModel(X, T, dhat=0.1, broad_phase="octree")


def test_plane_pairs_agree_with_ipctks_own_plane_implementation():
    """fem3d evaluates point-plane pairs itself; ipctk's planes (with candidates inflated by
    dhat so that its plane set is complete) are the reference."""
    X, T = box_mesh()
    rng = np.random.default_rng(4)
    planes = [PlaneObstacle([0, -0.05, 0], [0.2, 1, 0.1]), PlaneObstacle([-0.04, 0, 0],
                                                                          [1, 0, 0])]
    dhat, kappa, mu, eps_v, dt = 0.12, 3.0, 0.4, 0.5, 0.01
    cm = ContactModel(X, T, planes=planes, dhat=dhat, kappa=kappa, mu=mu, eps_v=eps_v)
    q_lag = X.reshape(-1) + 0.01 * rng.standard_normal(X.size)
    q = q_lag + 0.003 * rng.standard_normal(X.size)
    # reference: ipctk on the surface vertices with its own planes
    surf = cm.surface
    ref = ipctk.CollisionMesh(np.asfortranarray(X[surf]))
    ref.planes = [ipctk.Hyperplane(p.normal, p.point) for p in planes]
    ref.can_collide = ipctk.CollisionFilter(lambda i, j: False)

    def ref_set(qq):
        V = np.asfortranarray(qq.reshape(-1, 3)[surf])
        cands = ipctk.Candidates()
        cands.build(ref, V, dhat)
        col = ipctk.NormalCollisions()
        col.build(cands, ref, V, dhat)
        return V, col

    B = ipctk.BarrierPotential(dhat, kappa)
    V, col = ref_set(q)
    assert len(col) == cm.n_active(q) > 5
    assert cm.barrier_energy(q) == pytest.approx(B(col, ref, V), rel=1e-12)
    dof = (3 * surf[:, None] + np.arange(3)).reshape(-1)
    np.testing.assert_allclose(cm.barrier_gradient(q)[dof], B.gradient(col, ref, V),
                               rtol=1e-11, atol=1e-12)
    H = cm.barrier_hessian(q).tocsr()[dof][:, dof].toarray()
    Href = B.hessian(col, ref, V, ipctk.PSDProjectionMethod.CLAMP).toarray()
    np.testing.assert_allclose(H, Href, rtol=1e-10, atol=1e-10 * np.abs(Href).max())
    # friction, lagged at q_lag, slip measured from there
    cm.lag_friction(q_lag, dt)
    Vl, coll = ref_set(q_lag)
    tc = ipctk.TangentialCollisions()
    tc.build(ref, Vl, coll, B, mu)
    assert cm.n_friction_pairs == len(tc)
    Fp = ipctk.FrictionPotential(eps_v * dt)
    U = np.asfortranarray(V - Vl)
    assert cm.friction_energy(q) == pytest.approx(Fp(tc, ref, U), rel=1e-11)
    np.testing.assert_allclose(cm.friction_gradient(q)[dof], Fp.gradient(tc, ref, U),
                               rtol=1e-10, atol=1e-12)
    Hf = cm.friction_hessian(q).tocsr()[dof][:, dof].toarray()
    Hfref = Fp.hessian(tc, ref, U, ipctk.PSDProjectionMethod.CLAMP).toarray()
    np.testing.assert_allclose(Hf, Hfref, rtol=1e-9, atol=1e-9 * np.abs(Hfref).max())
