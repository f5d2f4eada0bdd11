"""The generated quadratic-tetrahedron (P2) kernels against SymPy and independent arithmetic.

The element description (:mod:`codegen.elements`), the geometry kernels (``p2_tet``) and the
quadrature kernels of every material (``p2_<material>``), on both back ends: SymPy's own
``psi``, ``P``, ``dP/dF`` evaluated at each quadrature point and summed in NumPy, SymPy's
direct differentiation of a whole P2 element's energy in its 30 DOFs (StVK), finite
differences, the exact mass matrix, and P1's energy on straight-edged elements.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
import sympy as sp

from codegen.derive import derive_material, reference_outputs
from codegen.elements import (
    ELEMENTS,
    RULES,
    LagrangeTet,
    integrate_reference,
    reference_coordinates,
    rule,
)
from codegen.materials import MATERIALS
from fem3d.kernels.backend import c_extension
from fem3d.kernels.dispatch import kernel_module

BACKENDS = ["numpy", pytest.param("c", marks=pytest.mark.skipif(
    c_extension() is None, reason="C extension not built"))]
PARAMS = {
    "neo_hookean": (0.7, 3.1),
    "stvk": (0.9, 2.3),
    "stable_neo_hookean": (0.8, 2.9),
    "mooney_rivlin": (0.4, 0.3, 3.3),
    "linear": (0.9, 2.3),
    "fung": (0.6, 3.2, 0.7),
    "neo_hookean_lame": (0.7, 2.6),
    "fibre_reinforced": (0.6, 2.4, 1.3, 0.8),
}
P2 = ELEMENTS["p2"]
REST = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
EDGES = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))


def corner_tets(rng: np.random.Generator, m: int) -> np.ndarray:
    """``m`` random positively oriented tets (4 corners)."""
    X = REST + 0.15 * rng.normal(size=(m, 4, 3))
    flip = np.linalg.det(X[:, 1:] - X[:, :1]) < 0
    X[flip, :2] = X[flip, 1::-1]
    return X


def lift(corners: np.ndarray) -> np.ndarray:
    """Straight-edged P2 elements: the corners, then the edge midpoints (VTK order)."""
    mids = np.stack([(corners[:, a] + corners[:, b]) / 2 for a, b in EDGES], axis=1)
    return np.concatenate([corners, mids], axis=1)


def p2_elements(rng: np.random.Generator, m: int, curved: float = 0.04):
    """Rest P2 elements (edge nodes moved off the midpoints by ``curved``) and deformed node
    positions: a random gradient, a translation and node noise (curved deformed edges)."""
    X = lift(corner_tets(rng, m))
    X[:, 4:] += curved * rng.normal(size=(m, 6, 3))
    F = np.eye(3) + 0.25 * rng.normal(size=(m, 3, 3))
    F[np.linalg.det(F) < 0.3] = np.eye(3)
    x = np.einsum("mij,mvj->mvi", F, X) + rng.normal(size=(m, 1, 3))
    x += 0.02 * rng.normal(size=x.shape)
    # an element whose rest or deformed det J is not well above 0 at a point: the unit tet
    G = [np.array(reference_gradient_function()(*(float(c) for c in p)), float)
         for p in P2.quadrature_rule().reference_points()]
    low = np.zeros(m, bool)
    for g in G:
        J = np.linalg.det(np.einsum("mai,aj->mij", X, g))
        low |= (J < 0.05) | (np.linalg.det(np.einsum("mai,aj->mij", x, g)) < 0.05 * J)
    X[low] = lift(REST[None])[0]
    x[low] = X[low] + 0.01 * rng.normal(size=x[low].shape)
    return X, x


def material_inputs(material: str, rng: np.random.Generator, m: int) -> list[np.ndarray]:
    shapes = getattr(MATERIALS[material], "ELEMENT_INPUTS", {})
    return [rng.normal(size=(m, *shape)) for shape in shapes.values()]


@cache
def sympy_pointwise(material: str, kernel: str):
    """SymPy's own ``psi`` / ``P`` / ``dP/dF`` / ``dP/dparams`` of ``material``, lambdified."""
    symbols, (exprs,) = reference_outputs(material, kernel)
    return sp.lambdify(symbols, exprs, "numpy", cse=True)


def pointwise(material: str, kernel: str, F: np.ndarray, extra: list, params) -> np.ndarray:
    """``kernel`` at each ``F`` (``(m, nq, 3, 3)``) -> ``(m, nq, size)``."""
    m, nq = F.shape[:2]
    columns = [*F.reshape(m * nq, 9).T,
               *(c for a in extra for c in np.repeat(a.reshape(m, -1), nq, axis=0).T), *params]
    values = sympy_pointwise(material, kernel)(*columns)
    return np.stack([np.broadcast_to(np.asarray(v, float), (m * nq,)) for v in values],
                    1).reshape(m, nq, -1)


def reference(material: str, kernel: str, x, dN, w, extra, params) -> np.ndarray:
    """The element kernel from SymPy's pointwise derivatives, summed over the points in
    NumPy (no generated code involved)."""
    F = np.einsum("mai,mqaj->mqij", x, dN)
    m, nq, n = dN.shape[:3]
    if kernel == "energy":
        return np.einsum("mq,mq->m", w, pointwise(material, "psi", F, extra, params)[..., 0])
    if kernel == "gradient":
        P = pointwise(material, "dpsi_dF", F, extra, params).reshape(m, nq, 3, 3)
        return np.einsum("mq,mqcj,mqaj->mac", w, P, dN).reshape(m, 3 * n)
    if kernel == "dgradient_dparams":
        dP = pointwise(material, "dpsi_dF_dparams", F, extra, params)
        dP = dP.reshape(m, nq, 3, 3, len(params))
        return np.einsum("mq,mqcjk,mqaj->mack", w, dP, dN).reshape(m, 3 * n, len(params))
    A = pointwise(material, "d2psi_dF2", F, extra, params).reshape(m, nq, 3, 3, 3, 3)
    return np.einsum("mq,mqaj,mqcjdl,mqbl->macbd", w, dN, A, dN).reshape(m, 3 * n, 3 * n)


def relative_error(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.reshape(len(a), -1), b.reshape(len(b), -1)
    scale = np.maximum(np.abs(b).max(axis=1), 1e-300)
    return float((np.abs(a - b).max(axis=1) / scale).max())


# ---- the element description ---------------------------------------------------------------


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_lagrange_shape_functions_are_a_nodal_basis(degree: int) -> None:
    element = LagrangeTet(f"p{degree}", degree, "keast4")
    xi = reference_coordinates()
    N = element.shape_functions()
    values = sp.Matrix(element.n_nodes, element.n_nodes, lambda i, j: N[i].subs(
        dict(zip(xi, element.nodes()[j], strict=True))))
    assert values == sp.eye(element.n_nodes)
    assert sp.expand(sum(N)) == 1
    assert element.n_nodes == (degree + 1) * (degree + 2) * (degree + 3) // 6
    # every gradient sums to zero (the constants are reproduced)
    G = element.reference_gradients()
    assert all(sp.expand(sum(G[:, j])) == 0 for j in range(3))


def test_p2_nodes_are_vtk_tetra10_order() -> None:
    nodes = [tuple(float(c) for c in p) for p in P2.nodes()]
    corners = [tuple(r) for r in REST]
    assert nodes[:4] == corners
    for k, (a, b) in enumerate(EDGES):
        assert nodes[4 + k] == tuple((np.array(corners[a]) + np.array(corners[b])) / 2)
    geo = kernel_module("p2_tet", "numpy")
    assert geo._numpy.EDGES == EDGES and geo._numpy.N_NODES == 10


@pytest.mark.parametrize("name", sorted(RULES))
def test_quadrature_rules_have_their_degree_and_no_more(name: str) -> None:
    r = rule(name)
    xi = reference_coordinates()
    assert (r.degree, r.n_points) == RULES[name]
    assert all(w > 0 for w in r.weights) and abs(sum(r.weights) - sp.Rational(1, 6)) < 1e-15
    assert all(min(p) > 0 for p in r.points)  # interior points
    worst, beyond = 0.0, 0.0
    for i in range(r.degree + 2):
        for j in range(r.degree + 2 - i):
            for k in range(r.degree + 2 - i - j):
                mono = xi[0] ** i * xi[1] ** j * xi[2] ** k
                exact = integrate_reference(mono)
                value = sum(w * mono.subs(dict(zip(xi, p, strict=True)))
                            for p, w in zip(r.reference_points(), r.weights, strict=True))
                error = abs(float((value - exact) / exact))
                if i + j + k <= r.degree:
                    worst = max(worst, error)
                else:
                    beyond = max(beyond, error)
    assert worst < 1e-14
    assert beyond > 1e-4  # the degree is the rule's own, not a lower bound


def test_mass_coefficients_are_exact() -> None:
    M = P2.mass_coefficients
    assert sum(M) == 1  # integral of sum_i N_i sum_j N_j = volume
    assert M[0, 0] == sp.Rational(1, 70) and M[0, 1] == sp.Rational(1, 420)
    assert M[0, 4] == -sp.Rational(1, 105) and M[4, 4] == sp.Rational(8, 105)
    assert M == M.T and min(M.eigenvals()) > 0


def test_curved_mass_weights_integrate_every_cubic_det_j() -> None:
    """``sum_p f(xi_p) C_p = integral N_i N_j f`` for a cubic ``f`` (what ``det J`` of a P2
    element is), exactly; a constant gives the straight-edged coefficients."""
    points, C = P2.curved_mass_weights
    assert len(points) == 20 and sum(C, sp.zeros(10, 10)) * 6 == P2.mass_coefficients
    P1 = ELEMENTS["p1"]  # det J constant: the corners, summing to the straight coefficients
    points1, C1 = P1.curved_mass_weights
    assert len(points1) == 4 and sum(C1, sp.zeros(4, 4)) * 6 == P1.mass_coefficients
    xi = reference_coordinates()
    f = 2 + xi[0] * xi[1] * xi[2] - 3 * xi[0] ** 3 + xi[1] ** 2 * xi[2] - xi[2]
    at = [f.subs(dict(zip(xi, point, strict=True))) for point in points]
    N = P2.shape_functions()
    for i, j in ((0, 0), (0, 5), (4, 4), (6, 9), (2, 7)):
        assert sum(a * Cp[i, j] for a, Cp in zip(at, C, strict=True)) == \
            integrate_reference(N[i] * N[j] * f)


# ---- geometry kernels ----------------------------------------------------------------------


@cache
def reference_gradient_function():
    xi = reference_coordinates()
    return sp.lambdify(list(xi), P2.reference_gradients(), "numpy")


@pytest.mark.parametrize("backend", BACKENDS)
def test_rest_shape_matches_the_isoparametric_map(backend: str) -> None:
    rng = np.random.default_rng(1)
    X, _ = p2_elements(rng, 16)
    dN, detJ, w_detJ = kernel_module("p2_tet", backend).rest_shape(X)
    r = P2.quadrature_rule()
    for q, (point, weight) in enumerate(zip(r.reference_points(), r.weights, strict=True)):
        G = np.array(reference_gradient_function()(*(float(c) for c in point)), float)
        J = np.einsum("mai,aj->mij", X, G)
        np.testing.assert_allclose(detJ[:, q], np.linalg.det(J), rtol=1e-12)
        np.testing.assert_allclose(w_detJ[:, q], float(weight) * np.linalg.det(J), rtol=1e-12)
        expected = np.einsum("aj,mjk->mak", G, np.linalg.inv(J))
        assert relative_error(dN[:, q], expected) < 1e-12
    # straight edges: det J = 6 vol at every point, the weights sum to the volume
    corners = corner_tets(rng, 16)
    _, detJ, w_detJ = kernel_module("p2_tet", backend).rest_shape(lift(corners))
    vol = np.linalg.det(corners[:, 1:] - corners[:, :1]) / 6
    np.testing.assert_allclose(detJ, 6 * vol[:, None].repeat(4, 1), rtol=1e-12)
    np.testing.assert_allclose(w_detJ.sum(axis=1), vol, rtol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_rest_shape_refuses_inverted_and_flat_elements(backend: str) -> None:
    rng = np.random.default_rng(2)
    X, _ = p2_elements(rng, 5)
    geo = kernel_module("p2_tet", backend)
    bad = X.copy()
    bad[3, :, 0] *= -1.0  # mirrored: inverted
    with pytest.raises(ValueError, match=r"p2_tet.rest_shape: element 3 has detJ\[0\]"):
        geo.rest_shape(bad)
    flat = X.copy()
    flat[1, :, 2] = 0.0  # every node in one plane
    with pytest.raises(ValueError, match="element 1 has detJ"):
        geo.rest_shape(flat)
    curled = X.copy()  # an edge node pulled through the opposite face: det J < 0 somewhere
    curled[0, 4] = X[0, 3] + 2.0 * (X[0, 3] - (X[0, 0] + X[0, 1]) / 2)
    with pytest.raises(ValueError, match="element 0 has detJ"):
        geo.rest_shape(curled)


@pytest.mark.parametrize("backend", BACKENDS)
def test_shape_functions_kernel(backend: str) -> None:
    geo = kernel_module("p2_tet", backend)
    nodes = np.array(geo._numpy.NODES)
    N, dN = geo.shape_functions(nodes)
    np.testing.assert_allclose(N, np.eye(10), atol=1e-15)
    xi = np.random.default_rng(3).uniform(0, 0.3, size=(7, 3))
    N, dN = geo.shape_functions(xi)
    np.testing.assert_allclose(N.sum(axis=1), 1.0, rtol=1e-14)
    expected = np.array([reference_gradient_function()(*p) for p in xi], float)
    np.testing.assert_allclose(dN, expected, atol=1e-14)


@pytest.mark.parametrize("backend", BACKENDS)
def test_deformation_gradient_and_jacobian_per_point(backend: str) -> None:
    rng = np.random.default_rng(4)
    X, x = p2_elements(rng, 12)
    geo = kernel_module("p2_tet", backend)
    dN, _, _ = geo.rest_shape(X)
    F = geo.deformation_gradient(x, dN)
    np.testing.assert_allclose(F, np.einsum("mai,mqaj->mqij", x, dN), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(geo.deformation_jacobian(x, dN), np.linalg.det(F), rtol=1e-11)
    A = np.eye(3) + 0.3 * rng.normal(size=(3, 3))
    np.testing.assert_allclose(geo.deformation_gradient(X @ A.T, dN), np.broadcast_to(A, F.shape),
                               atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_mass_matrix_sum_and_exactness_on_quadratics(backend: str) -> None:
    rng = np.random.default_rng(5)
    corners = corner_tets(rng, 3)
    X = lift(corners)
    vol = np.linalg.det(corners[:, 1:] - corners[:, :1]) / 6
    rho = 1.7
    geo = kernel_module("p2_tet", backend)
    M = geo.mass_matrix(vol, (rho,))
    np.testing.assert_allclose(M.sum(axis=(1, 2)), 3 * rho * vol, rtol=1e-13)
    assert np.linalg.eigvalsh(M).min() > 0
    Ms = geo.mass_coefficients(vol, (rho,))
    np.testing.assert_allclose(M, np.einsum("mij,cd->micjd", Ms, np.eye(3)).reshape(M.shape),
                               rtol=1e-15)
    # u^T M v = rho * integral u v dV exactly for any two quadratics u, v (P2 interpolates them)
    X0, Y0, Z0 = sp.symbols("X0 Y0 Z0", real=True)
    monomials = [sp.Integer(1), X0, Y0, Z0, X0 * X0, Y0 * Y0, Z0 * Z0, X0 * Y0, Y0 * Z0, X0 * Z0]
    xi = reference_coordinates()
    for e in range(3):
        a, b = rng.normal(size=10), rng.normal(size=10)
        u = sum(c * p for c, p in zip(a, monomials, strict=True))
        v = sum(c * p for c, p in zip(b, monomials, strict=True))
        Xe = sp.Matrix(corners[e])
        point = Xe[0, :].T + (Xe[1:, :] - sp.ones(3, 1) * Xe[0, :]).T * xi  # affine map
        sub = dict(zip((X0, Y0, Z0), point, strict=True))
        exact = rho * 6 * vol[e] * float(integrate_reference(sp.expand((u * v).subs(sub))))
        nodal = [[float(f.subs(dict(zip((X0, Y0, Z0), X[e, k], strict=True)))) for k in range(10)]
                 for f in (u, v)]
        np.testing.assert_allclose(np.array(nodal[0]) @ Ms[e] @ np.array(nodal[1]), exact,
                                   rtol=1e-12)


def conical_product_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Stroud's conical product rule on the reference tet (``n^3`` points, Gauss-Jacobi in
    each collapsed direction): exact for degree ``2 n - 1``, independent of the generator."""
    from scipy.special import roots_jacobi

    (a, wa), (b, wb), (c, wc) = (roots_jacobi(n, alpha, 0) for alpha in (2, 1, 0))
    a, b, c = (a + 1) / 2, (b + 1) / 2, (c + 1) / 2
    A, B, Cc = np.meshgrid(a, b, c, indexing="ij")
    points = np.stack([A, B * (1 - A), Cc * (1 - A) * (1 - B)], axis=-1).reshape(-1, 3)
    weights = np.einsum("i,j,k->ijk", wa / 8, wb / 4, wc / 2).reshape(-1)
    return points, weights


@pytest.mark.parametrize("backend", BACKENDS)
def test_curved_mass_matrix_is_exact(backend: str) -> None:
    """``rho integral N_i N_j det J dxi`` of curved elements (degree 7 in ``xi``) against a
    degree-7 conical product rule; the straight-edged kernel's matrix on straight ones."""
    rng = np.random.default_rng(8)
    geo = kernel_module("p2_tet", backend)
    X, _ = p2_elements(rng, 24, curved=0.08)
    points, weights = conical_product_rule(4)
    assert weights.sum() == pytest.approx(1 / 6, rel=1e-15)
    N, dN = geo.shape_functions(points)
    detJ = np.linalg.det(np.einsum("mai,paj->mpij", X, dN))
    expected = 1.7 * np.einsum("p,pi,pj,mp->mij", weights, N, N, detJ)
    M = geo.curved_mass_matrix(X, (1.7,))
    assert relative_error(M, np.einsum("mij,cd->micjd", expected, np.eye(3)).reshape(M.shape)) \
        < 1e-13
    rho = rng.uniform(0.5, 2.0, size=(24, 1))  # per element
    np.testing.assert_allclose(geo.curved_mass_matrix(X, rho), M / 1.7 * rho[:, :, None],
                               rtol=1e-14, atol=1e-18)
    corners = corner_tets(rng, 8)
    vol = np.linalg.det(corners[:, 1:] - corners[:, :1]) / 6
    assert relative_error(geo.curved_mass_matrix(lift(corners), (1.7,)),
                          geo.mass_matrix(vol, (1.7,))) < 1e-14


# ---- material kernels ----------------------------------------------------------------------


def material_case(material: str, m: int = 24, seed: int = 7):
    rng = np.random.default_rng(seed)
    X, x = p2_elements(rng, m)
    dN, _, w = kernel_module("p2_tet", "numpy").rest_shape(X)
    return x, dN, w, material_inputs(material, rng, m), PARAMS[material]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(MATERIALS))
@pytest.mark.parametrize("kernel", ["energy", "gradient", "dgradient_dparams", "hessian"])
def test_p2_kernels_match_sympy_at_each_point(material: str, kernel: str, backend: str) -> None:
    x, dN, w, extra, params = material_case(material)
    result = getattr(kernel_module(f"p2_{material}", backend), kernel)(x, dN, w, *extra, params)
    expected = reference(material, kernel, x, dN, w, extra, params)
    assert result.shape == expected.shape
    assert relative_error(result, expected) < 1e-10


@pytest.mark.parametrize("material", ["stvk", "fibre_reinforced"])
def test_p2_numpy_energy_is_p1_psi_summed_over_the_points(material: str) -> None:
    """The NumPy P2 kernels call the P1 module's own kernels at each point's F: the energy is
    P1's psi at p2_tet's F times w det J, summed point by point, to the bit."""
    x, dN, w, extra, params = material_case(material)
    F = kernel_module("p2_tet", "numpy").deformation_gradient(x, dN)
    psi = kernel_module(material, "numpy").psi
    expected = np.zeros(len(x))
    for q in range(F.shape[1]):
        expected += psi(F[:, q], *extra, params) * w[:, q]
    energy = kernel_module(f"p2_{material}", "numpy").energy(x, dN, w, *extra, params)
    np.testing.assert_array_equal(energy, expected)


def stvk_along(x: np.ndarray, dN: np.ndarray, w: np.ndarray, params, u: np.ndarray,
               v: np.ndarray) -> tuple[float, float, float]:
    """SymPy's direct derivatives of one whole P2 element's StVK energy in its 30 node
    coordinates, along directions: ``E(x)``, ``dE/dx . u`` and ``u^T d2E/dx2 v`` as
    ``d/dt`` and ``d2/dt ds`` of ``E(x + t u + s v)`` at 0 (the element's energy written out
    from ``psi`` at each point; no chain rule, no generated code)."""
    d = derive_material("stvk")
    t, s = sp.symbols("t s", real=True)
    moved = sp.Matrix(x) + t * sp.Matrix(u.reshape(10, 3)) + s * sp.Matrix(v.reshape(10, 3))
    values = {d.params["mu"]: params[0], d.params["lam"]: params[1]}
    energy = sp.Integer(0)
    for D, weight in zip(dN, w, strict=True):
        F = moved.T * sp.Matrix(D)
        energy += float(weight) * d.psi.xreplace({**values, **dict(zip(d.F, F, strict=True))})
    at_zero = {t: 0, s: 0}
    return (float(energy.subs(at_zero)), float(sp.diff(energy, t).subs(at_zero)),
            float(sp.diff(energy, t, s).subs(at_zero)))


@pytest.mark.parametrize("backend", BACKENDS)
def test_stvk_element_matches_direct_differentiation(backend: str) -> None:
    x, dN, w, _, params = material_case("stvk", m=1)
    k = kernel_module("p2_stvk", backend)
    energy = k.energy(x, dN, w, params)[0]
    g, H = k.gradient(x, dN, w, params)[0], k.hessian(x, dN, w, params)[0]
    rng = np.random.default_rng(29)
    unit = np.eye(30)
    for u, v in ((rng.normal(size=30), rng.normal(size=30)), (unit[0], unit[13]),
                 (unit[29], rng.normal(size=30)), (unit[4], unit[4])):
        e, du, duv = stvk_along(x[0], dN[0], w[0], params, u, v)
        np.testing.assert_allclose(energy, e, rtol=1e-12)
        np.testing.assert_allclose(g @ u, du, rtol=1e-11, atol=1e-12 * np.abs(g).max())
        np.testing.assert_allclose(u @ H @ v, duv, rtol=1e-11, atol=1e-11 * np.abs(H).max())


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_p2_gradient_and_hessian_by_finite_differences(material: str, backend: str) -> None:
    x, dN, w, extra, params = material_case(material, m=4, seed=11)
    k = kernel_module(f"p2_{material}", backend)
    g = k.gradient(x, dN, w, *extra, params)
    H = k.hessian(x, dN, w, *extra, params)
    h = 1e-6
    for dof in (0, 7, 13, 29):
        shift = np.zeros((4, 30))
        shift[:, dof] = h
        xp, xm = x + shift.reshape(4, 10, 3), x - shift.reshape(4, 10, 3)
        de = (k.energy(xp, dN, w, *extra, params) - k.energy(xm, dN, w, *extra, params)) / (2 * h)
        np.testing.assert_allclose(de, g[:, dof], rtol=1e-6, atol=1e-7 * np.abs(g).max())
        dg = (k.gradient(xp, dN, w, *extra, params) - k.gradient(xm, dN, w, *extra, params))
        np.testing.assert_allclose(dg / (2 * h), H[:, :, dof], rtol=1e-5,
                                   atol=1e-6 * np.abs(H).max())
    np.testing.assert_allclose(H, H.transpose(0, 2, 1), rtol=0, atol=0)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_p2_projected_hessian_is_psd(material: str, backend: str) -> None:
    x, dN, w, extra, params = material_case(material, seed=13)
    k = kernel_module(f"p2_{material}", backend)
    H = k.hessian(x, dN, w, *extra, params)
    for name in ("hessian_psd", "hessian_psd_svd"):
        Hp = getattr(k, name)(x, dN, w, *extra, params)
        scale = np.abs(H).max(axis=(1, 2))
        assert (np.linalg.eigvalsh(Hp).min(axis=1) >= -1e-10 * scale).all()
    # each point's dP/dF projected: equal to the same sum of SymPy's dP/dF projected in NumPy
    F = np.einsum("mai,mqaj->mqij", x, dN)
    A = pointwise(material, "d2psi_dF2", F, extra, params).reshape(-1, 9, 9)
    values, vectors = np.linalg.eigh(A)
    Ap = np.einsum("pik,pk,pjk->pij", vectors, np.maximum(values, 0.0), vectors)
    Ap = Ap.reshape(len(x), 4, 3, 3, 3, 3)
    expected = np.einsum("mq,mqaj,mqcjdl,mqbl->macbd", w, dN, Ap, dN).reshape(H.shape)
    assert relative_error(k.hessian_psd(x, dN, w, *extra, params), expected) < 1e-9
    assert relative_error(k.hessian_psd_svd(x, dN, w, *extra, params), expected) < 1e-9


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_straight_p2_reproduces_p1_energy_of_a_linear_displacement(material: str,
                                                                   backend: str) -> None:
    rng = np.random.default_rng(17)
    m = 10
    corners = corner_tets(rng, m)
    A = np.eye(3) + 0.3 * rng.normal(size=(m, 3, 3))
    A[np.linalg.det(A) < 0.3] = np.eye(3)
    b = rng.normal(size=(m, 1, 3))
    extra = material_inputs(material, rng, m)
    params = PARAMS[material]
    x4 = np.einsum("mij,mvj->mvi", A, corners) + b
    dphi, vol = kernel_module("tet", backend).rest_shape(corners)
    p1 = kernel_module(material, backend)
    X = lift(corners)
    dN, _, w = kernel_module("p2_tet", backend).rest_shape(X)
    p2 = kernel_module(f"p2_{material}", backend)
    x10 = np.einsum("mij,mvj->mvi", A, X) + b
    e1 = p1.energy(x4, dphi, vol, *extra, params)  # 0 where A is a rotation
    np.testing.assert_allclose(p2.energy(x10, dN, w, *extra, params), e1, rtol=1e-12,
                               atol=1e-14 * np.abs(e1).max())
    # and the P1 gradient is the P2 one lumped to the corners (edge forces split in half)
    g2 = p2.gradient(x10, dN, w, *extra, params).reshape(m, 10, 3)
    lumped = g2[:, :4].copy()
    for k, (a, c) in enumerate(EDGES):
        lumped[:, a] += g2[:, 4 + k] / 2
        lumped[:, c] += g2[:, 4 + k] / 2
    g1 = p1.gradient(x4, dphi, vol, *extra, params).reshape(m, 4, 3)
    np.testing.assert_allclose(lumped, g1, rtol=1e-10, atol=1e-12 * np.abs(g1).max())


@pytest.mark.skipif(c_extension() is None, reason="C extension not built")
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_p2_numpy_and_c_agree_on_many_elements(material: str) -> None:
    x, dN, w, extra, params = material_case(material, m=2000, seed=19)
    for kernel in kernel_module(f"p2_{material}", "numpy").SIGNATURES:
        a = getattr(kernel_module(f"p2_{material}", "numpy"), kernel)(x, dN, w, *extra, params)
        b = getattr(kernel_module(f"p2_{material}", "c"), kernel)(x, dN, w, *extra, params)
        assert a.shape == b.shape
        assert relative_error(b, a) < 1e-11, kernel


@pytest.mark.skipif(c_extension() is None, reason="C extension not built")
@pytest.mark.parametrize("material", ["neo_hookean", "fibre_reinforced"])
@pytest.mark.parametrize("kernel", ["energy", "gradient", "hessian", "hessian_psd"])
def test_p2_fused_assemble_equals_kernel_then_scatter(material: str, kernel: str) -> None:
    rng = np.random.default_rng(23)
    m = 40
    x, dN, w, extra, params = material_case(material, m=m, seed=23)
    T = rng.permutation(10 * m).reshape(m, 10).astype(np.int64)
    q = np.empty((10 * m, 3))
    q[T] = x
    k = kernel_module(f"p2_{material}", "c")
    values = getattr(k, kernel)(x, dN, w, *extra, params).reshape(m, -1)
    index = rng.integers(0, 70, size=values.shape).astype(np.int32)
    expected = np.bincount(index.ravel(), weights=values.ravel(), minlength=70)
    out = np.full(70, 1.0)
    getattr(k, f"{kernel}_assemble")(q, T, dN, w, *extra, params, index, out)
    np.testing.assert_allclose(out - 1.0, expected, rtol=1e-12,
                               atol=1e-12 * np.abs(expected).max())
    with pytest.raises(ValueError, match="m \\* 120 values"):  # a P1 T: 4 of 10 nodes
        getattr(k, f"{kernel}_assemble")(q, T[:, :4].copy(), dN, w, *extra, params, index, out)
