"""The generated kernels against SymPy's own evaluation and against independent arithmetic."""

from __future__ import annotations

import os
import subprocess
import sys
from functools import cache
from pathlib import Path

import numpy as np
import pytest
import sympy as sp
from fem3d._generated import ELEMENT_MODULES, MODULES

from codegen.derive import P1_UNITS, reference_outputs
from codegen.materials import MATERIALS
from fem3d.kernels.backend import c_extension
from fem3d.kernels.dispatch import kernel_module, material_kernels

ROOT = Path(__file__).resolve().parents[2]
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
REST_TET = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def random_rotations(rng: np.random.Generator, m: int) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(m, 3, 3)))
    q *= np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    return q


def deformation_gradients(rng: np.random.Generator, m: int = 48) -> np.ndarray:
    """Rotations, stretches, compressions and near-singular F (J down to 0.05)."""
    U, V = random_rotations(rng, m), random_rotations(rng, m)
    s = rng.uniform(0.4, 1.8, size=(m, 3))
    s[: m // 4] = 1.0  # pure rotations
    s[m // 4 : m // 2, 0] = rng.uniform(2.0, 3.0, size=m // 4)  # strong stretch
    s[m // 2 : 3 * m // 4] = rng.uniform(0.3, 0.6, size=(m // 4, 3))  # compression
    s[-4:] = [[0.2, 0.5, 0.5], [0.05, 1.0, 1.0], [0.1, 0.8, 0.9], [1.5, 0.1, 0.4]]  # J 0.05..0.06
    return U @ (s[:, :, None] * V)


def random_elements(rng: np.random.Generator, m: int = 48):
    """Random rest tets, deformed by the gradients above plus noise."""
    X = REST_TET + 0.2 * rng.normal(size=(m, 4, 3))
    X[np.linalg.det(X[:, 1:] - X[:, :1]) < 0, :2] = X[np.linalg.det(X[:, 1:] - X[:, :1]) < 0, 1::-1]
    dphi, vol = kernel_module("tet", "numpy").rest_shape(X)
    F = deformation_gradients(rng, m)
    x = np.einsum("mij,mvj->mvi", F, X) + rng.normal(size=(m, 1, 3))
    return X, x, dphi, vol


@cache
def _reference_outputs(module: str, kernel: str) -> tuple[list, list[list]]:
    """:func:`codegen.derive.reference_outputs`, but a directly differentiated element Hessian
    is built from the gradient's upper triangle: ``d(dE/dx_i)/dx_j`` is the same expression as
    ``d(dE/dx_j)/dx_i`` (Schwarz), so 78 SymPy derivatives instead of 144 (half the time)."""
    if not (module in DIRECT_REFERENCE and kernel == "hessian"):
        return reference_outputs(module, kernel)
    symbols, (gradient,) = _reference_outputs(module, "gradient")
    dofs = symbols[:12]  # the element's x, then D, vol and the parameters
    upper = {(i, j): sp.diff(gradient[i], dofs[j]) for i in range(12) for j in range(i, 12)}
    return symbols, [[upper[min(i, j), max(i, j)] for i in range(12) for j in range(12)]]


@cache
def sympy_reference(module: str, kernel: str):
    symbols, outputs = _reference_outputs(module, kernel)
    # SymPy's own CSE inside lambdify only speeds up printing; the expressions are the
    # directly differentiated ones, independent of the generator's chain rule and CSE.
    return [sp.lambdify(symbols, exprs, "numpy", cse=True) for exprs in outputs]


def evaluate_reference(module: str, kernel: str, columns: list[np.ndarray], m: int):
    results = []
    for function in sympy_reference(module, kernel):
        values = function(*columns)
        results.append(np.stack([np.broadcast_to(np.asarray(v, float), (m,)) for v in values], 1))
    return results


def assert_close(generated: np.ndarray, reference: np.ndarray, rtol: float = 1e-10) -> None:
    """Per-element relative error; elements whose exact value is ~0 (psi of a pure rotation)
    are measured against the typical magnitude of the batch instead."""
    generated = generated.reshape(len(generated), -1)
    magnitude = np.abs(reference).max(axis=1)
    scale = np.maximum(magnitude, 1e-3 * magnitude.max() + 1e-300)
    error = np.abs(generated - reference).max(axis=1) / scale
    assert error.max() <= rtol, f"max relative error {error.max():.3e} (element {error.argmax()})"


def kernel_cases():
    """(module, kernel) of every generated P1 kernel, from the generated signatures (deriving
    every module again would take minutes); the higher-order elements' kernels are
    tests/codegen/test_p2_kernels_vs_sympy.py's."""
    elements = {m for modules in ELEMENT_MODULES.values() for m in modules}
    for module in (m for m in MODULES if m not in elements):
        for kernel in kernel_module(module, "numpy").SIGNATURES:
            yield module, kernel


def material_args(material: str, m: int) -> list:
    """Fixed per-element inputs of ``m`` elements, then the parameters: ``kernel(F, *args)``."""
    return [*material_inputs(material, np.random.default_rng(99), m), PARAMS[material]]


def material_inputs(module: str, rng: np.random.Generator, m: int) -> list[np.ndarray]:
    """Random per-element inputs of a material (fibre directions of any length)."""
    shapes = getattr(MATERIALS[module], "ELEMENT_INPUTS", {})
    return [rng.normal(size=(m, *shape)) for shape in shapes.values()]


def kernel_inputs(module: str, kernel: str, rng: np.random.Generator, m: int):
    """Arguments for the generated kernel and flat columns for the SymPy reference."""
    X, x, dphi, vol = random_elements(rng, m)
    if module in MATERIALS:
        params = PARAMS[module]
        extra = material_inputs(module, rng, m)
        columns = [c for a in extra for c in a.reshape(m, -1).T]
        if kernel in ("psi", "dpsi_dF", "d2psi_dF2"):
            F = deformation_gradients(rng, m)
            return (F, *extra, params), [*F.reshape(m, 9).T, *columns, *params]
        if kernel == "d3psi_contract":
            F, C = deformation_gradients(rng, m), rng.normal(size=(m, 9, 9))
            return (F, C, *extra, params), [*F.reshape(m, 9).T, *C.reshape(m, 81).T,
                                            *columns, *params]
        return ((x, dphi, vol, *extra, params),
                [*x.reshape(m, 12).T, *dphi.reshape(m, 12).T, vol, *columns, *params])
    if module == "spring":
        a, b = rng.normal(size=(m, 3)), rng.normal(size=(m, 3))
        return (a, b, (123.0,)), [*a.T, *b.T, 123.0]
    if module == "pressure":  # 3-node faces, or 6-node (P2) faces: the p2_ kernels
        xf = rng.normal(size=(m, 6 if kernel.startswith("p2_") else 3, 3))
        if kernel in ("p2_follower_load", "p2_traction_weights"):  # no parameter
            return (xf,), [*xf.reshape(m, -1).T]
        return (xf, (2.5,)), [*xf.reshape(m, -1).T, 2.5]
    if kernel == "rest_shape":
        return (X,), [*X.reshape(m, 12).T]
    if kernel == "phi":
        p = rng.normal(size=(m, 3))
        return (X, p), [*X.reshape(m, 12).T, *p.T]
    if kernel == "mass_matrix":
        return (vol, (0.1,)), [vol, 0.1]
    if kernel == "deformed_volume":
        return (x,), [*x.reshape(m, 12).T]
    return (x, dphi), [*x.reshape(m, 12).T, *dphi.reshape(m, 12).T]


# hessian_psd (and its Jacobi and svd twins) has no closed form to compare with; it has its
# own tests below.
# d3psi_contract: SymPy's third derivatives take minutes per material; it is compared with
# SymPy's dP/dF differenced in 40-digit arithmetic below.
EXACT_CASES = [case for case in kernel_cases()
               if case[1] not in ("hessian_psd", "hessian_psd_jacobi", "hessian_psd_svd",
                                    "d3psi_contract")]


# The element kernels of these materials are compared with SymPy's direct differentiation by
# the 12 DOFs, which checks the generator's chain rule symbolically; for the others (minutes
# of SymPy each) with SymPy's own P and dP/dF through the chain rule in NumPy, and every
# material's element derivatives with finite differences below.
DIRECT_REFERENCE = ("neo_hookean", "stvk")


def _chain_rule_reference(module: str, kernel: str, args: tuple, m: int) -> list[np.ndarray]:
    x, dphi, vol, *extra, params = args
    F = kernel_module("tet", "numpy").deformation_gradient(x, dphi)
    columns = [*F.reshape(m, 9).T, *(c for a in extra for c in a.reshape(m, -1).T), *params]
    if kernel == "gradient":
        P = evaluate_reference(module, "dpsi_dF", columns, m)[0].reshape(m, 3, 3)
        return [(vol[:, None, None] * np.einsum("mcj,mvj->mvc", P, dphi)).reshape(m, 12)]
    if kernel == "dgradient_dparams":
        dP = evaluate_reference(module, "dpsi_dF_dparams", columns, m)[0]
        dP = dP.reshape(m, 3, 3, len(params))
        return [(vol[:, None, None, None] * np.einsum("mcjk,mvj->mvck", dP, dphi)).reshape(m, -1)]
    A = evaluate_reference(module, "d2psi_dF2", columns, m)[0].reshape(m, 9, 9)
    return [_chain_rule_hessian(A, dphi, vol).reshape(m, 144)]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(("module", "kernel"), EXACT_CASES)
def test_generated_kernel_matches_sympy(module: str, kernel: str, backend: str) -> None:
    rng = np.random.default_rng(7)
    m = 48
    args, columns = kernel_inputs(module, kernel, rng, m)
    result = getattr(kernel_module(module, backend), kernel)(*args)
    results = result if isinstance(result, tuple) else (result,)
    if module in MATERIALS and module not in DIRECT_REFERENCE and \
            kernel in ("gradient", "hessian", "dgradient_dparams"):
        references = _chain_rule_reference(module, kernel, args, m)
    else:
        references = evaluate_reference(module, kernel, columns, m)
    for generated, reference in zip(results, references, strict=True):
        assert generated.shape[0] == m
        assert_close(generated, reference)


@cache
def _contracted_reference(material: str):
    """Inputs of ``d3psi_contract`` on two elements (a strong stretch, a near-singular F) and
    its reference: central differences of SymPy's exact ``dP/dF : C`` in 40-digit arithmetic
    (step 1e-15: error ~1e-30)."""
    import mpmath

    symbols, outputs = reference_outputs(material, "d2psi_dF2")
    # cse: the same exact expressions with their shared parts evaluated once (the same
    # figures to the last bit, measured; 10-15x faster than re-evaluating each of the 81)
    f = sp.lambdify(symbols, outputs[0], "mpmath", cse=True)
    args, _ = kernel_inputs(material, "d3psi_contract", np.random.default_rng(13), 8)
    args = [a[[2, 6]] for a in args[:-1]] + [args[-1]]
    F, C, *extra, params = args
    m = 2
    n_in = 9 + sum(a[0].size for a in extra)
    refs = []
    with mpmath.workdps(40):
        h = mpmath.mpf("1e-15")
        for e in range(m):
            point = [mpmath.mpf(float(v)) for v in F[e].reshape(9)] + \
                [mpmath.mpf(float(v)) for a in extra for v in a[e].reshape(-1)] + \
                [mpmath.mpf(float(v)) for v in params]
            weights = [mpmath.mpf(float(c)) for c in C[e].reshape(81)]

            def contracted(i, shift, point=point, weights=weights):
                x = list(point)
                x[i] += shift
                return mpmath.fsum(w * a for w, a in zip(weights, f(*x), strict=True))
            refs.append([float((contracted(i, h) - contracted(i, -h)) / (2 * h))
                         for i in [*range(9), *range(n_in, n_in + len(params))]])
    return args, np.array(refs)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_contracted_third_derivative_matches_sympy(material: str, backend: str) -> None:
    """``d3psi_contract``: ``d/dF`` and ``d/dparams`` of ``sum dP/dF : C`` against SymPy's
    exact ``dP/dF`` differenced in 40-digit arithmetic, on two elements."""
    args, ref = _contracted_reference(material)
    dF, dp = kernel_module(material, backend).d3psi_contract(*args)
    assert_close(dF.reshape(len(ref), 9), ref[:, :9])
    assert_close(dp.reshape(len(ref), -1), ref[:, 9:])


@pytest.mark.skipif(c_extension() is None, reason="C extension not built")
@pytest.mark.parametrize(("module", "kernel"), list(kernel_cases()))
def test_numpy_and_c_agree_on_many_elements(module: str, kernel: str) -> None:
    rng = np.random.default_rng(11)
    args, _ = kernel_inputs(module, kernel, rng, 10_000)
    a = getattr(kernel_module(module, "numpy"), kernel)(*args)
    b = getattr(kernel_module(module, "c"), kernel)(*args)
    for x, y in zip(a if isinstance(a, tuple) else (a,), b if isinstance(b, tuple) else (b,),
                    strict=True):
        assert x.shape == y.shape
        assert_close(y, x.reshape(len(x), -1), rtol=1e-11)


# ---- independent checks that do not trust SymPy ------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_stress_is_finite_difference_of_energy(material: str, backend: str) -> None:
    k = material_kernels(material, backend)
    F = deformation_gradients(np.random.default_rng(1), 16)[:12]
    p, h = material_args(material, 12), 1e-6
    P = k.dpsi_dF(F, *p).reshape(-1, 9)
    fd = np.empty_like(P)
    for a in range(9):
        dF = np.zeros(9)
        dF[a] = h
        fd[:, a] = (k.psi(F + dF.reshape(3, 3), *p) - k.psi(F - dF.reshape(3, 3), *p)) / (2 * h)
    np.testing.assert_allclose(P, fd, rtol=1e-5, atol=1e-6 * np.abs(P).max())


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_stress_derivative_is_finite_difference_of_stress(material: str, backend: str) -> None:
    k = material_kernels(material, backend)
    F = deformation_gradients(np.random.default_rng(2), 16)[:12]
    p, h = material_args(material, 12), 1e-6
    A = k.d2psi_dF2(F, *p)
    fd = np.empty_like(A)
    for b in range(9):
        dF = np.zeros(9)
        dF[b] = h
        plus = k.dpsi_dF(F + dF.reshape(3, 3), *p).reshape(-1, 9)
        minus = k.dpsi_dF(F - dF.reshape(3, 3), *p).reshape(-1, 9)
        fd[:, :, b] = (plus - minus) / (2 * h)
    np.testing.assert_allclose(A, fd, rtol=1e-4, atol=1e-6 * np.abs(A).max())
    np.testing.assert_allclose(A, A.transpose(0, 2, 1), rtol=0, atol=1e-12 * np.abs(A).max())


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_rest_state_and_rotation_invariance(material: str, backend: str) -> None:
    k = material_kernels(material, backend)
    identity = np.broadcast_to(np.eye(3), (5, 3, 3))
    np.testing.assert_allclose(k.psi(identity, *material_args(material, 5)), 0.0, atol=1e-14)
    np.testing.assert_allclose(k.dpsi_dF(identity, *material_args(material, 5)), 0.0, atol=1e-14)
    rng = np.random.default_rng(3)
    F = deformation_gradients(rng, 32)
    RF = random_rotations(rng, 32) @ F
    p = material_args(material, 32)
    invariant = np.isclose(k.psi(RF, *p), k.psi(F, *p), rtol=1e-10, atol=1e-12)
    # small-strain linear elasticity is the one material that is not frame invariant
    assert invariant.all() == getattr(MATERIALS[material], "ROTATION_INVARIANT", True)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_element_gradient_and_hessian_by_finite_differences(material: str, backend: str) -> None:
    k = material_kernels(material, backend)
    p, h = material_args(material, 12), 1e-6
    _, x, dphi, vol = random_elements(np.random.default_rng(4), 12)
    g = k.gradient(x, dphi, vol, *p)
    H = k.hessian(x, dphi, vol, *p)
    fd_g, fd_H = np.empty_like(g), np.empty_like(H)
    for a in range(12):
        dx = np.zeros(12)
        dx[a] = h
        dx = dx.reshape(4, 3)
        fd_g[:, a] = (k.energy(x + dx, dphi, vol, *p) - k.energy(x - dx, dphi, vol, *p)) / (2 * h)
        plus, minus = k.gradient(x + dx, dphi, vol, *p), k.gradient(x - dx, dphi, vol, *p)
        fd_H[:, :, a] = (plus - minus) / (2 * h)
    np.testing.assert_allclose(g, fd_g, rtol=1e-5, atol=1e-6 * np.abs(g).max())
    np.testing.assert_allclose(H, fd_H, rtol=1e-4, atol=1e-6 * np.abs(H).max())
    np.testing.assert_allclose(H, H.transpose(0, 2, 1), atol=1e-12 * np.abs(H).max())


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_gradient_parameter_derivative_by_finite_differences(material: str,
                                                             backend: str) -> None:
    k = material_kernels(material, backend)
    *extra, params = material_args(material, 12)
    _, x, dphi, vol = random_elements(np.random.default_rng(4), 12)
    G = k.dgradient_dparams(x, dphi, vol, *extra, params)
    assert G.shape == (12, 12, len(params))
    for j, p in enumerate(params):
        h = 1e-6 * abs(p)
        up, down = np.array(params, float), np.array(params, float)
        up[j] += h
        down[j] -= h
        plus, minus = (k.gradient(x, dphi, vol, *extra, v) for v in (up, down))
        fd = (plus - minus) / (2 * h)
        np.testing.assert_allclose(G[:, :, j], fd, rtol=1e-5, atol=1e-7 * np.abs(G).max())


@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_parameter_jacobian_of_E_nu_by_finite_differences(material: str) -> None:
    from fem3d.physics.materials import parameters_from, parameters_jacobian_from

    E, nu = 3.1e5, 0.27
    jac = parameters_jacobian_from(material, E, nu)
    for which, (dE, dnu) in ((0, (E * 1e-6, 0.0)), (1, (0.0, 1e-6))):
        plus = parameters_from(material, E + dE, nu + dnu)
        minus = parameters_from(material, E - dE, nu - dnu)
        for p, (d_E, d_nu) in jac.items():
            fd = (plus[p] - minus[p]) / (2 * (dE + dnu))
            exact = (d_E, d_nu)[which]
            assert abs(exact - fd) <= 1e-6 * max(abs(exact), abs(fd), 1e-12 * E), (p, which)


def _chain_rule_hessian(A: np.ndarray, dphi: np.ndarray, vol: np.ndarray) -> np.ndarray:
    """vol B^T A B with B = dF/dx formed explicitly (row-major F, vertex-major x)."""
    m = len(vol)
    B = np.zeros((m, 9, 12))
    for i in range(3):
        for j in range(3):
            B[:, 3 * i + j, i::3] = dphi[:, :, j]
    return vol[:, None, None] * np.einsum("mai,mab,mbj->mij", B, A, B)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_projected_hessian_is_psd_and_projects_dP_dF(material: str, backend: str) -> None:
    k = material_kernels(material, backend)
    p = material_args(material, 64)
    _, x, dphi, vol = random_elements(np.random.default_rng(6), 64)
    H, H_psd = k.hessian(x, dphi, vol, *p), k.hessian_psd(x, dphi, vol, *p)
    eig = np.linalg.eigvalsh(H_psd)
    assert eig.min() >= -1e-12 * np.abs(eig).max()
    F = kernel_module("tet", backend).deformation_gradient(x, dphi)
    A = k.d2psi_dF2(F, *p)
    values, vectors = np.linalg.eigh(A)
    if (values < -1e-9 * np.abs(values).max()).any():  # not for the convex linear elasticity
        assert np.linalg.eigvalsh(H).min() < -1e-6 * np.abs(eig).max()  # meets indefinite H
    A_psd = np.einsum("mik,mk,mjk->mij", vectors, np.maximum(values, 0), vectors)
    np.testing.assert_allclose(H_psd, _chain_rule_hessian(A_psd, dphi, vol),
                               rtol=1e-9, atol=1e-10 * np.abs(H).max())
    # where dP/dF is already PSD (to round-off: linear elasticity's rotation modes) nothing
    # changes
    psd_elements = values.min(axis=1) >= -1e-12 * np.abs(values).max()
    assert psd_elements.any()
    np.testing.assert_allclose(H_psd[psd_elements], H[psd_elements], rtol=1e-12,
                               atol=1e-13 * np.abs(H).max())


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(MATERIALS))
@pytest.mark.parametrize("method", ["jacobi", "svd"])
def test_each_projection_equals_the_ql_one_to_round_off(material: str, backend: str,
                                                        method: str) -> None:
    k = material_kernels(material, backend)
    p = material_args(material, 64)
    _, x, dphi, vol = random_elements(np.random.default_rng(6), 64)
    H = k.hessian(x, dphi, vol, *p)
    ql = k.hessian_psd(x, dphi, vol, *p)
    twin = getattr(k, f"hessian_psd_{method}")(x, dphi, vol, *p)
    changed = np.abs(ql - H).max(axis=(1, 2)) > 1e-9 * np.abs(H).max()
    assert changed.any() or material == "linear"  # both meet indefinite elements
    np.testing.assert_allclose(twin, ql, rtol=1e-9, atol=1e-11 * np.abs(H).max())
    if method == "svd" and material in ("linear", "fibre_reinforced"):
        np.testing.assert_array_equal(twin, ql)  # not isotropic: no frame given, QL itself
    if backend != "c":
        return  # NumPy's twin is the QL kernel itself
    # where the shared LDL^T test proves dP/dF PSD neither projects: one element body, the same
    # bits (not where an eigen-solver finds no eigenvalue below zero: that is round-off)
    from fem3d.kernels.backend import c_extension

    F = kernel_module("tet", backend).deformation_gradient(x, dphi)
    A = np.ascontiguousarray(k.d2psi_dF2(F, *p), dtype=np.float64).reshape(-1, 9, 9)
    values, vectors = np.empty((len(A), 9)), np.empty((len(A), 9, 9))
    flags = np.empty(len(A), dtype=np.int32)
    c_extension().psd_eigen(A, values, vectors, flags)
    proven = flags == 0
    assert proven.any()
    np.testing.assert_array_equal(twin[proven], ql[proven])


def test_the_generator_finds_which_materials_are_isotropic() -> None:
    from codegen.derive import is_isotropic

    assert [m for m in sorted(MATERIALS) if not is_isotropic(m)] == ["fibre_reinforced",
                                                                    "linear"]


def _rotation(rng: np.random.Generator) -> np.ndarray:
    Q, R = np.linalg.qr(rng.normal(size=(3, 3)))
    Q = Q * np.sign(np.diag(R))
    return Q * [np.sign(np.linalg.det(Q)), 1.0, 1.0]  # proper: J > 0


@pytest.mark.skipif(c_extension() is None, reason="C extension not built")
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_the_svd_projection_holds_in_degenerate_singular_frames(material: str) -> None:
    """Repeated, nearly repeated and small singular values, rigid rotations and the identity:
    the singular frame is not unique there, and the svd projection must not care."""
    rng = np.random.default_rng(21)
    stretches = [(1.0, 1.0, 1.0), (0.8, 0.8, 0.8), (1.3, 1.3, 0.7), (0.6, 1.2, 1.2),
                 (0.7, 0.7 + 1e-9, 1.1), (0.9, 0.9 - 1e-13, 0.9 + 1e-13), (1.5, 0.5, 0.02),
                 (0.55, 0.6, 0.65), (1.0, 1.0, 0.999999)]
    F = np.array([_rotation(rng) @ np.diag(s) @ _rotation(rng).T for s in stretches
                  for _ in range(3)] + [_rotation(rng) for _ in range(3)])
    m = len(F)
    X = REST_TET + 0.2 * rng.normal(size=(m, 4, 3))
    X[np.linalg.det(X[:, 1:] - X[:, :1]) < 0, :2] = X[np.linalg.det(X[:, 1:] - X[:, :1]) < 0, 1::-1]
    dphi, vol = kernel_module("tet", "numpy").rest_shape(X)
    x = np.einsum("mij,mvj->mvi", F, X)
    k = material_kernels(material, "c")
    p = material_args(material, m)
    H = k.hessian(x, dphi, vol, *p)
    svd, ql = k.hessian_psd_svd(x, dphi, vol, *p), k.hessian_psd(x, dphi, vol, *p)
    scale = np.abs(H).max(axis=(1, 2))[:, None, None]
    assert (np.abs(ql - H) > 1e-9 * scale).any() or material == "linear"
    error = (np.abs(svd - ql) / scale).max(axis=(1, 2))  # relative to each element's H
    assert error.max() <= 1e-11, (error.argmax(), error.max())
    assert np.linalg.eigvalsh(svd).min(axis=1).min() >= -1e-12 * scale.max()


@pytest.mark.parametrize("backend", BACKENDS)
def test_mass_matrix_closed_form(backend: str) -> None:
    rho, vol = 0.37, np.array([0.5, 2.0, 1e-3])
    M = kernel_module("tet", backend).mass_matrix(vol, (rho,))
    expected = (rho * vol / 20)[:, None, None] * np.kron(np.eye(4) + 1.0, np.eye(3))
    np.testing.assert_allclose(M, expected, rtol=1e-15)
    np.testing.assert_allclose(M.sum(axis=(1, 2)), 3 * rho * vol, rtol=1e-14)
    assert np.all(np.linalg.eigvalsh(M) > 0)


def test_mass_matrix_is_symbolically_exact() -> None:
    from codegen import tet

    coefficients = tet.reference_mass_coefficients()
    assert coefficients == (sp.ones(4, 4) + sp.eye(4)) / 20


@pytest.mark.parametrize("backend", BACKENDS)
def test_shape_functions_interpolate_vertices(backend: str) -> None:
    geo = kernel_module("tet", backend)
    X, _, _, _ = random_elements(np.random.default_rng(5), 8)
    for v in range(4):
        np.testing.assert_allclose(geo.phi(X, X[:, v]), np.eye(4)[v][None].repeat(8, 0),
                                   atol=1e-12)
    dphi, vol = geo.rest_shape(X)
    np.testing.assert_allclose(dphi.sum(axis=1), 0.0, atol=1e-12)
    # F of the rest pose is the identity; an affine map A gives F = A.
    np.testing.assert_allclose(geo.deformation_gradient(X, dphi), np.eye(3)[None].repeat(8, 0),
                               atol=1e-12)
    np.testing.assert_allclose(vol, np.linalg.det(X[:, 1:] - X[:, :1]) / 6, rtol=1e-12)


# ---- C wrapper validation, registry, drift -----------------------------------------------


@pytest.mark.skipif(c_extension() is None, reason="C extension not built")
def test_c_extension_rejects_bad_buffers() -> None:
    ext = c_extension()
    F = np.zeros((4, 9))
    out = np.empty(4)
    params = np.array([1.0, 2.0])
    with pytest.raises(ValueError, match="float64"):
        ext.neo_hookean_psi(F.astype(np.float32), params, out)
    with pytest.raises(ValueError, match="C-contiguous"):
        ext.neo_hookean_psi(np.zeros((9, 4)).T, params, out)
    with pytest.raises(ValueError, match="parameters"):
        ext.neo_hookean_psi(F, params[:1], out)
    with pytest.raises(ValueError, match="output"):
        ext.neo_hookean_psi(F, params, np.empty(3))
    with pytest.raises(ValueError, match="m \\* 9"):
        ext.neo_hookean_psi(np.zeros(10), params, out)
    with pytest.raises(TypeError):
        ext.neo_hookean_psi(F, params)
    with pytest.raises(ValueError, match="writable"):
        ext.neo_hookean_psi(F, params, np.frombuffer(b"\0" * 32))


@pytest.mark.parametrize("backend", BACKENDS)
def test_kernel_wrappers_reject_bad_shapes(backend: str) -> None:
    nh = material_kernels("neo_hookean", backend)
    with pytest.raises(ValueError):
        nh.psi(np.zeros((4, 2, 2)), (1.0, 1.0))
    with pytest.raises(ValueError):
        nh.psi(np.zeros((4, 3, 3)), (1.0,))
    with pytest.raises(ValueError):
        nh.energy(np.zeros((4, 4, 3)), np.zeros((3, 4, 3)), np.ones(4), (1.0, 1.0))
    # a single parameter may be given bare
    spring = kernel_module("spring", backend)
    a, b = np.zeros((2, 3)), np.ones((2, 3))
    np.testing.assert_array_equal(spring.energy(a, b, 2.0), spring.energy(a, b, (2.0,)))


@pytest.mark.parametrize("backend", BACKENDS)
def test_out_keyword_fills_the_given_arrays(backend: str) -> None:
    rng = np.random.default_rng(3)
    args, _ = kernel_inputs("neo_hookean", "hessian", rng, 20)
    nh = material_kernels("neo_hookean", backend)
    out = np.full((20, 12, 12), np.nan)
    result = nh.hessian(*args, out=out)
    assert result is out
    np.testing.assert_array_equal(out, nh.hessian(*args))
    (X,), _ = kernel_inputs("tet", "rest_shape", rng, 20)
    geo = kernel_module("tet", backend)
    outs = (np.empty((20, 4, 3)), np.empty(20))
    dphi, vol = geo.rest_shape(X, out=outs)
    assert dphi is outs[0] and vol is outs[1]
    np.testing.assert_array_equal(vol, geo.rest_shape(X)[1])
    for bad in (np.empty((20, 12, 11)), np.empty((20, 12, 12), np.float32),
                np.empty((20, 12, 24))[:, :, ::2], (out, out)):
        with pytest.raises(ValueError, match="out must"):
            nh.hessian(*args, out=bad)


def test_every_registered_material_is_generated() -> None:
    from fem3d._generated import MATERIALS as generated

    assert tuple(sorted(MATERIALS)) == tuple(sorted(generated))


def test_backend_can_be_forced_by_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    from fem3d.kernels.backend import resolve_backend

    monkeypatch.setenv("FEM3D_KERNELS", "numpy")
    assert resolve_backend() == "numpy"
    monkeypatch.setenv("FEM3D_KERNELS", "fortran")
    with pytest.raises(ValueError, match="fortran"):
        resolve_backend()


def test_generated_files_are_up_to_date_and_deterministic(tmp_path: Path) -> None:
    """Regenerate a few modules into a temporary folder (under another hash seed) and diff
    them with generated/. The whole tree is CI's drift check (`make check-generated`): all
    materials take minutes to derive."""
    env = dict(os.environ, PYTHONHASHSEED="123")  # the generator pins its own seed
    only = ["tet", "spring", "linear", "stvk"]
    subprocess.run([sys.executable, "-m", "codegen", "--out", str(tmp_path), "--only", *only],
                   cwd=ROOT, env=env, check=True, capture_output=True)
    fresh = {p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.suffix in (".py", ".c")}
    assert {p.stem for p in fresh} >= set(only)
    for rel in sorted(fresh):
        if rel.name == "__init__.py" or rel.name.startswith("_ckernels"):  # they list
            continue  # every module (of their translation unit)
        old, new = (ROOT / "generated" / rel).read_text(), (tmp_path / rel).read_text()
        assert old == new, f"generated/{rel} is stale: run `make codegen` and commit"
        assert "do not edit" in old.splitlines()[0]
    committed = {p.stem for p in (ROOT / "generated").rglob("*") if p.suffix in (".py", ".c")}
    units = {f"_ckernels_{e}" for e in ELEMENT_MODULES}
    # C only: the translation units P1's materials are dealt to, each material's kernels at
    # one F (shared by P1's file and the element units) and each element's quadrature loops
    # (shared by its materials)
    p1_units = {f"_ckernels_{u}" for u in P1_UNITS if u}
    assert committed == {"__init__", "_support", "_ckernels", "tet", "spring", "pressure",
                         *MATERIALS, *units, *p1_units, *(f"{m}_pointwise" for m in MATERIALS),
                         *(f"{e}_quadrature" for e in ELEMENT_MODULES),
                         *(m for modules in ELEMENT_MODULES.values() for m in modules)}
    assert units == {"_ckernels_p2"} and p1_units == {"_ckernels_p1a", "_ckernels_p1b"}


def test_show_prints_a_materials_formulas() -> None:
    result = subprocess.run([sys.executable, "-m", "codegen", "show", "stable_neo_hookean"],
                            cwd=ROOT, capture_output=True, text=True, check=True)
    assert "psi = " in result.stdout and "log(Trace(F.T*F)/4 + 1/4)" in result.stdout
    assert "mu = 4*E/(3*(2*nu + 2))" in result.stdout
    assert "allows inversion: True" in result.stdout and "Smith" in result.stdout


def test_show_prints_one_kernel() -> None:
    # the linear material: the same command path, its module derived in a fraction of
    # neo_hookean's time
    result = subprocess.run([sys.executable, "-m", "codegen", "show", "linear.hessian",
                             "--backend", "c"], cwd=ROOT, capture_output=True, text=True,
                            check=True)
    assert "static void linear_hessian(" in result.stdout
    assert "linear_gradient(" not in result.stdout


@pytest.mark.skipif(c_extension() is None, reason="C extension not built")
@pytest.mark.parametrize("material", sorted(MATERIALS))
@pytest.mark.parametrize("kernel", ["energy", "gradient", "hessian", "hessian_psd",
                                    "hessian_psd_jacobi", "hessian_psd_svd"])
def test_fused_assemble_equals_kernel_then_scatter(material: str, kernel: str) -> None:
    rng = np.random.default_rng(12)
    m = 80
    _, x, dphi, vol = random_elements(rng, m)  # moderate F, J > 0: ln J and exp are finite
    T = rng.permutation(4 * m).reshape(m, 4).astype(np.int64)  # corners of a shuffled array
    q = np.empty((4 * m, 3))
    q[T] = x
    k = material_kernels(material, "c")
    p = material_args(material, m)
    values = getattr(k, kernel)(x, dphi, vol, *p).reshape(m, -1)
    index = rng.integers(0, 50, size=values.shape).astype(np.int64)
    expected = np.bincount(index.ravel(), weights=values.ravel(), minlength=50)
    out = np.full(50, 1.0)  # accumulates
    getattr(k, f"{kernel}_assemble")(q, T, dphi, vol, *p, index, out)
    assert np.isfinite(expected).all()
    np.testing.assert_allclose(out - 1.0, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_per_element_parameters_equal_one_call_per_element(material: str, backend: str) -> None:
    rng = np.random.default_rng(8)
    m = 5
    _, x, dphi, vol = random_elements(rng, m)
    extra = material_inputs(material, rng, m)
    P = np.array(PARAMS[material]) * rng.uniform(0.5, 2.0, size=(m, len(PARAMS[material])))
    k = material_kernels(material, backend)
    F = kernel_module("tet", backend).deformation_gradient(x, dphi)
    for kernel, args in (("hessian", (x, dphi, vol)), ("gradient", (x, dphi, vol)),
                         ("dpsi_dF", (F,))):
        together = getattr(k, kernel)(*args, *extra, P)
        for e in range(m):
            alone = getattr(k, kernel)(*(a[e:e + 1] for a in (*args, *extra)), P[e])
            np.testing.assert_allclose(together[e], alone[0], rtol=1e-13, atol=1e-13)
    with pytest.raises(ValueError):
        k.hessian(x, dphi, vol, *extra, P[:-1])
    if backend == "c":
        T = np.arange(4 * m, dtype=np.int64).reshape(m, 4)
        q = x.reshape(-1, 3)
        index = np.arange(m * 144, dtype=np.int32).reshape(m, 144)
        out = k.hessian_assemble(q, T, dphi, vol, *extra, P, index, np.zeros(m * 144))
        np.testing.assert_allclose(out.reshape(m, 12, 12), k.hessian(x, dphi, vol, *extra, P),
                                   rtol=1e-14, atol=1e-14)


@pytest.mark.skipif(c_extension() is None, reason="C extension not built")
@pytest.mark.parametrize("kernel", ["deformed_volume", "deformation_gradient"])
def test_fused_geometry_kernels_equal_kernel_then_scatter(kernel: str) -> None:
    rng = np.random.default_rng(5)
    n, m = 20, 60
    T = np.array([rng.choice(n, 4, replace=False) for _ in range(m)], dtype=np.int64)
    q = rng.normal(size=(n, 3))
    _, _, dphi, _ = random_elements(rng, m)
    geo = kernel_module("tet", "c")
    rest = () if kernel == "deformed_volume" else (dphi,)
    values = getattr(geo, kernel)(q[T], *rest).reshape(m, -1)
    index = np.arange(values.size, dtype=np.int32).reshape(values.shape)
    out = getattr(geo, f"{kernel}_assemble")(q, T, *rest, (), index, np.zeros(values.size))
    np.testing.assert_allclose(out, values.ravel(), rtol=1e-14, atol=1e-15)


@pytest.mark.skipif(c_extension() is None, reason="C extension not built")
def test_fused_assemble_validates_indices_and_types() -> None:
    ext = c_extension()
    q, dphi, vol = np.zeros((5, 3)), np.zeros((2, 4, 3)), np.ones(2)
    T = np.array([[0, 1, 2, 3], [1, 2, 3, 4]], dtype=np.int64)
    params, index, out = np.array([1.0, 1.0]), np.zeros((2, 12), dtype=np.int32), np.zeros(3)
    ext.neo_hookean_gradient_assemble(q, T, dphi, vol, params, index, out)
    with pytest.raises(ValueError, match="vertex index"):
        ext.neo_hookean_gradient_assemble(q, T + 1, dphi, vol, params, index, out)
    with pytest.raises(ValueError, match="outside"):
        ext.neo_hookean_gradient_assemble(q, T, dphi, vol, params, index + 3, out)
    with pytest.raises(ValueError, match="element 1"):  # the first bad element is named
        ext.neo_hookean_gradient_assemble(q, np.array([[0, 1, 2, 3], [1, 2, 3, 5]]), dphi, vol,
                                          params, index, out)
    with pytest.raises(ValueError, match="int64"):
        ext.neo_hookean_gradient_assemble(q, T.astype(np.int32), dphi, vol, params, index, out)
    with pytest.raises(ValueError, match="int32"):
        ext.neo_hookean_gradient_assemble(q, T, dphi, vol, params, index.astype(np.int64), out)
    with pytest.raises(ValueError, match="m \\* 12"):
        ext.neo_hookean_gradient_assemble(q, T, dphi[:1], vol, params, index, out)
    with pytest.raises(TypeError):
        ext.neo_hookean_gradient_assemble(q, T, dphi, vol, params, index)


def test_p2_c_files_share_the_quadrature_loops() -> None:
    """Each material's P2 C file holds only its steps at one F (P1's pointwise kernels, from
    their one file) and the kernels' entry points; the loops over the quadrature points and
    the chain rule to the nodes are p2_quadrature.c's, once for every material (the P2
    unit's compile time, issue 39)."""
    check_p2_c_files(ROOT / "generated" / "c")


def test_p2_numpy_files_share_the_quadrature_loops() -> None:
    """As the C files: each material's P2 NumPy module holds only its dP/dp at one F and the
    kernels' entry points, which call p2_quadrature.py's loops with the P1 module's own psi,
    P and dP/dF bodies; the loops and the chain rule to the nodes are written once."""
    numpy_dir = ROOT / "generated" / "numpy"
    shared = (numpy_dir / "p2_quadrature.py").read_text()
    for kind in ("energy", "gradient", "dgradient_dparams", "hessian"):
        assert shared.count(f"\ndef {kind}(m, inputs, params, material, project):") == 1
    assert shared.count("T_0_0 = ") == 1
    for material in MATERIALS:
        text = (numpy_dir / f"p2_{material}.py").read_text()
        assert "for q in range(" not in text and "T_0_0" not in text
        assert f"from .{material} import _d2psi_dF2_body, _dpsi_dF_body, _psi_body" in text
        assert "\ndef _d2psi_dF2_body(m, _in_F, " in (numpy_dir / f"{material}.py").read_text()
        assert len(text.splitlines()) < 500


def check_p2_c_files(c_dir: Path) -> None:
    """The assertions of :func:`test_p2_c_files_share_the_quadrature_loops` on ``c_dir``."""
    shared = (c_dir / "p2_quadrature.c").read_text()
    for kind in ("energy", "gradient", "dgradient_dparams", "hessian"):
        assert shared.count(f" static void fem3d_p2_{kind}(") == 1
    unit = (c_dir / "_ckernels_p2.c").read_text()
    for material in MATERIALS:
        text = (c_dir / f"p2_{material}.c").read_text()
        assert "for (int q = 0;" not in text and "T_0_0" not in text
        assert f"{material}_d2psi_dF2_element(in, params, out);" in text
        assert f'#include "{material}_pointwise.c"' in unit
        assert f'#include "{material}_pointwise.c"' in (c_dir / f"{material}.c").read_text()
        assert len(text.splitlines()) < 1000
