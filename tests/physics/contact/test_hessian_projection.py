"""``contact.hessian_projection``: how the per-pair barrier and friction Hessians enter Newton's
matrix (clamped, mirrored or exact), against NumPy's own eigendecomposition."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.errors import InputError, ParameterError
from fem3d.mesh.tetmesh import tet_signed_volumes
from fem3d.physics.contact import ContactModel
from fem3d.physics.contact.friction_profile import point_plane_friction
from fem3d.physics.terms.contact import ContactTerm
from fem3d.scene import apply_overrides, load_scene
from fem3d.scene.spec import ContactSpec
from fem3d.simulation import Simulation


def apexes() -> tuple[np.ndarray, np.ndarray]:
    """Two tets apex to apex, 2 cm apart."""
    A = np.array([[0.0, 0.0, 0.0], [-1.0, -1.0, -0.5], [1.0, -1.0, -0.5], [0.0, -1.0, 1.0]])
    B = A * np.array([1.0, -1.0, 1.0]) + np.array([0.0, 0.02, 0.0])
    X = np.vstack([A, B])
    T = np.array([[0, 1, 2, 3], [4, 5, 6, 7]])
    flip = tet_signed_volumes(X, T) < 0
    T[flip] = T[flip][:, [0, 2, 1, 3]]
    return X, T


def apex_pair(projection: str) -> tuple[ContactModel, np.ndarray]:
    """:func:`apexes` as one vertex-vertex pair, whose barrier Hessian ``b'' g g^T + b' H(d^2)``
    (``b' < 0``) has two negative eigenvalues."""
    X, T = apexes()
    cm = ContactModel(X, T, body_ids=np.r_[0, 0, 0, 0, 1, 1, 1, 1], dhat=0.05, kappa=1.0,
                      hessian_projection=projection)
    return cm, X.reshape(-1)


@pytest.mark.parametrize("projection", ["clamp", "abs", "exact"])
def test_the_projection_clamps_or_mirrors_the_pairs_negative_eigenvalues(projection):
    cm, q = apex_pair(projection)
    assert cm.n_active(q) == 1 and len(cm.collisions.parts[0].collisions) == 1
    dofs = np.r_[0:3, 12:15]  # the two apexes
    exact = cm.barrier_hessian(q, project=False).toarray()
    block = exact[np.ix_(dofs, dofs)]
    assert not np.delete(exact, dofs, axis=0).any()
    w, V = np.linalg.eigh(block)
    assert (w < -1e-3 * np.abs(w).max()).sum() == 2  # nonconvex: two negative eigenvalues
    mirrored = (V * np.abs(w)) @ V.T
    clamped = (V * np.maximum(w, 0.0)) @ V.T
    expected = mirrored if projection == "abs" else clamped
    H = cm.barrier_hessian(q).toarray()
    assert np.abs(H[np.ix_(dofs, dofs)] - expected).max() <= 1e-9 * np.abs(block).max()
    got = np.linalg.eigvalsh(H[np.ix_(dofs, dofs)])
    want = np.sort(np.abs(w) if projection == "abs" else np.maximum(w, 0.0))
    np.testing.assert_allclose(got, want, atol=1e-9 * np.abs(w).max())
    # what Newton's matrix gets: the exact one unless it asks for a PSD matrix
    term = ContactTerm(cm)
    for psd in (False, True):
        r, c, v = term.barrier.hessian(q, psd=psd)
        N = q.size
        Hn = np.zeros((N, N))
        np.add.at(Hn, (r, c), v)
        ref = exact if projection == "exact" and not psd else H
        assert np.abs(Hn - ref).max() <= 1e-12 * np.abs(block).max()
    assert cm.projects(True) and cm.projects(False) == (projection != "exact")


def test_plane_friction_blocks_mirror_the_negative_eigenvalue_of_the_kinetic_transition():
    """Two coefficients (``mu_s > mu_k``): in the static-to-kinetic transition the friction
    force falls with the slip, ``d2F/dy2 < 0`` along it; ``"abs"`` mirrors that eigenvalue,
    the default clamps it."""
    n = np.array([[0.0, 1.0, 0.0]])
    eps = 1e-3
    w = np.array([[1.5 * eps, 0.0, 0.0]])  # slipping along x, in the transition
    lam = np.array([2.0])
    raw = point_plane_friction(n, w, lam, eps, 0.5, 0.2, 2, project=False)[0]
    ev = np.linalg.eigvalsh(raw)
    assert ev.min() < -1e-6 * np.abs(ev).max()
    for how, f in (("abs", np.abs), (True, lambda x: np.maximum(x, 0.0))):
        blk = point_plane_friction(n, w, lam, eps, 0.5, 0.2, 2, project=how)[0]
        np.testing.assert_allclose(np.linalg.eigvalsh(blk), np.sort(f(ev)),
                                   atol=1e-12 * np.abs(ev).max())


def test_a_bad_projection_is_one_line_naming_the_key():
    with pytest.raises(InputError) as info:
        apply_overrides(load_scene("contact_stack"), {"contact.hessian_projection": "mirror"})
    msg = str(info.value)
    assert "contact.hessian_projection" in msg and "\n" not in msg
    with pytest.raises(InputError) as info:  # "reuse" refactorizes its kept matrix as is
        apply_overrides(load_scene("contact_stack"), {"contact.hessian_projection": "exact",
                                                      "simulation.newton.solver": "reuse"})
    msg = str(info.value)
    assert "contact.hessian_projection = 'exact' needs simulation.newton.solver = 'direct'" \
        in msg and "\n" not in msg, msg
    X, T = apexes()
    with pytest.raises(ParameterError, match="contact.hessian_projection must be one of"):
        ContactModel(X, T, body_ids=np.r_[0, 0, 0, 0, 1, 1, 1, 1], dhat=0.05,
                     hessian_projection="mirror")


def test_the_default_stays_clamp_and_the_key_reaches_the_model():
    assert ContactSpec().hessian_projection == "clamp"
    sim = Simulation(apply_overrides(load_scene("contact_stack"),
                                     {"contact.hessian_projection": "exact",
                                      "simulation.newton.solver": "direct"}))
    assert sim.contact.contact.hessian_projection == "exact"


def test_a_shifted_step_is_not_taken_for_converged():
    """The gallery stack's bunny lands on the bottom block at step 9. With the exact contact
    Hessian the direct solver meets an indefinite Newton matrix there and shifts it
    (``A + mu M``): such a step is short because of its shift, and IPC's rule on
    a step's length once took it for converged, so the landing bunny lost 93 % of its
    kinetic energy in one step (2.41 -> 0.18 J). Only Newton's own step is judged now, and the
    exact Hessian's steps end where the clamped one's do (the same minimiser, to IPC's
    tolerance)."""
    kinetic, shifted = {}, {}
    for projection in ("clamp", "exact"):
        sim = Simulation(apply_overrides(load_scene("contact_stack"), {
            "contact.hessian_projection": projection, "simulation.newton.solver": "direct"}))
        kinetic[projection], shifted[projection] = [], 0
        for _ in range(10):
            info = sim.step()
            assert sim.last_stats.converged
            kinetic[projection].append(info.kinetic)
            shifted[projection] += sim.last_stats.shifted_factorizations
    assert shifted["clamp"] == 0 and shifted["exact"] > 0
    np.testing.assert_allclose(kinetic["exact"], kinetic["clamp"], rtol=1e-2)
