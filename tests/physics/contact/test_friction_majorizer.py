"""The friction majorizer (``contact.friction_hessian = "majorizer"``): the same friction
gradient as ipctk's, a quadratic that lies above the lagged friction and touches it, ipctk's
Hessian at zero slip, and Newton steps that reach the same solution as the exact Hessian's."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.errors import ParameterError
from fem3d.physics.contact import ContactModel, PlaneObstacle
from fem3d.physics.contact.friction_majorizer import FrictionMajorizer
from fem3d.physics.terms.contact import ContactTerm
from fem3d.solve.integrators import State, implicit_euler
from tests.physics.contact.test_potentials import two_boxes
from tests.solve.test_contact_steps import DT, free_system

DHAT = 1e-3


def lagged_pairs(mu_s: float, mu_k: float, eps_v: float = 1e-3):
    """Two unit boxes a third of ``dhat`` apart, their friction lagged there: the model, its
    mesh-mesh part and the majorizer of its pairs."""
    X, T, ids = two_boxes(DHAT / 3)
    cm = ContactModel(X, T, body_ids=ids, dhat=DHAT, mu=mu_s, mu_k=mu_k, eps_v=eps_v,
                      friction_hessian="majorizer")
    cm.initialize_stiffness(X.reshape(-1), np.zeros(X.size), 1.0)
    cm.lag_friction(X, DT)
    (part,) = [p for p in cm.collisions.parts if p.tangential is not None]
    return cm, part, FrictionMajorizer(part.tangential, part.mesh, cm.friction.potential.eps_v)


def slip(part, rng, scale: float) -> np.ndarray:
    """Random tangential-ish displacements of the collision vertices, ``(n, 3)``."""
    U = np.zeros((part.mesh.num_vertices, 3))
    U[:, [0, 2]] = scale * rng.standard_normal((U.shape[0], 2))
    U[:, 1] = 1e-2 * scale * rng.standard_normal(U.shape[0])
    return np.asfortranarray(U)


@pytest.mark.parametrize("mu_s, mu_k", [(0.5, 0.5), (0.6, 0.3)])
def test_its_gradient_is_ipctks(mu_s: float, mu_k: float) -> None:
    cm, part, maj = lagged_pairs(mu_s, mu_k)
    assert len(maj) > 10
    rng = np.random.default_rng(1)
    eps = cm.friction.potential.eps_v
    for scale in (0.1 * eps, eps, 30 * eps):  # static, transition, sliding
        U = slip(part, rng, scale)
        want = np.asarray(cm.friction.potential.gradient(part.tangential, part.mesh, U))
        got = maj.gradient(U)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())


@pytest.mark.parametrize("mu_s, mu_k", [(0.5, 0.5), (0.6, 0.3), (0.8, 0.0)])
def test_its_force_over_slip_is_ipctks(mu_s: float, mu_k: float) -> None:
    import ipctk

    _, _, maj = lagged_pairs(mu_s, mu_k)
    y = np.linspace(0.0, 3.0, 601) * maj.eps
    maj.mu = np.tile([mu_s, mu_k], (y.size, 1))
    want = [ipctk.smooth_mu_f1_over_x(float(v), mu_s, mu_k, maj.eps) for v in y]
    # round-off of ipctk's own cancellations near y = eps, relative to the largest value
    np.testing.assert_allclose(maj.force_over_slip(y), want, rtol=1e-12,
                               atol=1e-14 * max(want))


def test_at_zero_slip_it_is_ipctks_hessian() -> None:
    import ipctk

    cm, part, maj = lagged_pairs(0.5, 0.5)
    U = np.asfortranarray(np.zeros((part.mesh.num_vertices, 3)))
    exact = cm.friction.potential.hessian(part.tangential, part.mesh, U,
                                 ipctk.PSDProjectionMethod.NONE).toarray()
    got = maj.hessian(U).toarray()
    np.testing.assert_allclose(got, exact, rtol=0, atol=1e-9 * np.abs(exact).max())


@pytest.mark.parametrize("mu_s, mu_k", [(0.5, 0.5), (0.6, 0.3)])
def test_its_quadratic_lies_above_the_friction_where_ipctks_does_not(mu_s: float,
                                                                     mu_k: float) -> None:
    import ipctk

    cm, part, maj = lagged_pairs(mu_s, mu_k)
    rng = np.random.default_rng(2)
    eps = cm.friction.potential.eps_v

    def energy(U):
        return float(cm.friction.potential(part.tangential, part.mesh, np.asfortranarray(U)))

    exact_violations = 0
    for _ in range(30):
        U = slip(part, rng, eps * 10 ** rng.uniform(-1, 1.5))
        dU = slip(part, rng, eps * 10 ** rng.uniform(-1, 1.5))
        e0, g, d = energy(U), maj.gradient(U), dU.reshape(-1)
        e1 = energy(U + dU)
        H = maj.hessian(U).tocsr()
        model = e0 + g @ d + 0.5 * d @ (H @ d)
        assert e1 <= model + 1e-12 * max(abs(e1), abs(model))
        assert d @ (H @ d) >= 0.0
        Hx = cm.friction.potential.hessian(part.tangential, part.mesh, U,
                                  ipctk.PSDProjectionMethod.CLAMP).tocsr()
        exact_violations += e1 > e0 + g @ d + 0.5 * d @ (Hx @ d) + 1e-12 * abs(e1)
    assert exact_violations > 0  # the property is not a given: the exact model undershoots


def test_newton_with_it_reaches_the_exact_hessians_solution() -> None:
    # the top box slides across the bottom one, which rests on the ground: each step's
    # Newton solve, run to a tight tolerance with either matrix, ends at the same minimiser
    X, T, ids = two_boxes(DHAT / 3)
    model, system = free_system(X, T, E=1e6)
    ground = PlaneObstacle([0.0, -DHAT / 3, 0.0], [0.0, 1.0, 0.0])
    finals, iterations, pairs = [], [], []
    for kind in ("exact", "majorizer"):
        cm = ContactModel(X, T, body_ids=ids, planes=[ground], dhat=DHAT, mu=0.3, eps_v=1e-3,
                          friction_hessian=kind)
        term = ContactTerm(cm, tolerance=1e-7)
        v0 = np.zeros_like(X)
        v0[ids == 1] = (0.5, 0.0, 0.0)
        state = State(X.copy(), v0)
        newton = 0
        for _ in range(5):
            state, stats = implicit_euler(system, state, DT, terms=[term])
            newton += stats.newton_iterations
            pairs.append(sum(len(p.tangential or ()) for p in cm.collisions.parts))
        finals.append(state.q.copy())
        iterations.append(newton)
    gap = np.abs(finals[0] - finals[1]).max()
    print(f"iterations exact / majorizer: {iterations}, apart {gap:.2e} m")
    assert gap < 1e-7
    assert min(pairs) > 0  # the boxes' own friction pairs in every step
    assert np.abs(finals[1][ids == 1, 0] - X[ids == 1, 0]).min() > 1e-3  # it did slide


def test_an_unknown_kind_is_refused() -> None:
    X, T, ids = two_boxes(0.1)
    with pytest.raises(ParameterError, match="contact.friction_hessian"):
        ContactModel(X, T, body_ids=ids, dhat=DHAT, mu=0.3, friction_hessian="fast")
