"""Every material against an independent NumPy implementation written from its source (not
from the generated code), its small-strain limit, and its symmetries; the runtime registry."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.errors import ParameterError
from fem3d.kernels.backend import c_extension
from fem3d.kernels.dispatch import kernel_module, material_kernels
from fem3d.physics import materials

BACKENDS = ["numpy", pytest.param("c", marks=pytest.mark.skipif(
    c_extension() is None, reason="C extension not built"))]


# ---- independent implementations: psi(F, p, a) and P(F, p, a), from the papers ------------


def _inv_T(F):
    return np.linalg.inv(F).transpose(0, 2, 1)


def _cof(F):
    """Cofactor matrix dJ/dF (defined for every F, also singular or inverted)."""
    c = np.empty_like(F)
    for i in range(3):
        for j in range(3):
            r = [k for k in range(3) if k != i]
            s = [k for k in range(3) if k != j]
            minor = F[:, r][:, :, s]
            c[:, i, j] = (-1) ** (i + j) * (minor[:, 0, 0] * minor[:, 1, 1]
                                            - minor[:, 0, 1] * minor[:, 1, 0])
    return c


def _invariants(F):
    C = F.transpose(0, 2, 1) @ F
    I1 = np.trace(C, axis1=1, axis2=2)
    I2 = 0.5 * (I1**2 - np.trace(C @ C, axis1=1, axis2=2))
    return C, I1, I2, np.linalg.det(F)


def neo_hookean(F, p, a=None):
    """The assignment: C (J^(-2/3) I1 - 3) + D (J - 1)^2."""
    C_, D = p
    _, I1, _, J = _invariants(F)
    psi = C_ * (J ** (-2 / 3) * I1 - 3) + D * (J - 1) ** 2
    dI1b = J[:, None, None] ** (-2 / 3) * (2 * F - 2 / 3 * I1[:, None, None] * _inv_T(F))
    return psi, C_ * dI1b + 2 * D * (J - 1)[:, None, None] * _cof(F)


def stvk(F, p, a=None):
    """Bonet & Wood 6.4.1: P = F S, S = 2 mu E + lam tr(E) I."""
    mu, lam = p
    E = 0.5 * (F.transpose(0, 2, 1) @ F - np.eye(3))
    trE = np.trace(E, axis1=1, axis2=2)
    psi = mu * np.einsum("mij,mij->m", E, E) + 0.5 * lam * trE**2
    return psi, F @ (2 * mu * E + lam * trE[:, None, None] * np.eye(3))


def linear(F, p, a=None):
    """Hooke: sigma = 2 mu eps + lam tr(eps) I."""
    mu, lam = p
    eps = 0.5 * (F + F.transpose(0, 2, 1)) - np.eye(3)
    tr = np.trace(eps, axis1=1, axis2=2)
    psi = mu * np.einsum("mij,mij->m", eps, eps) + 0.5 * lam * tr**2
    return psi, 2 * mu * eps + lam * tr[:, None, None] * np.eye(3)


def neo_hookean_lame(F, p, a=None):
    """Bonet & Wood (6.28): P = mu (F - F^-T) + lam ln J F^-T."""
    mu, lam = p
    _, I1, _, J = _invariants(F)
    lnJ = np.log(J)
    psi = 0.5 * mu * (I1 - 3) - mu * lnJ + 0.5 * lam * lnJ**2
    return psi, mu * (F - _inv_T(F)) + lam * lnJ[:, None, None] * _inv_T(F)


def stable_neo_hookean(F, p, a=None):
    """Smith, de Goes, Kim 2018, eq. (14) with alpha = 1 + 3 mu / (4 lam), minus its value
    at rest (fem3d's psi(I) = 0)."""
    mu, lam = p
    alpha = 1 + mu / lam - mu / (4 * lam)

    def paper(F):
        _, I1, _, J = _invariants(F)
        return 0.5 * mu * (I1 - 3) + 0.5 * lam * (J - alpha) ** 2 - 0.5 * mu * np.log(I1 + 1)

    _, I1, _, J = _invariants(F)
    P = mu * (1 - 1 / (I1 + 1))[:, None, None] * F + lam * (J - alpha)[:, None, None] * _cof(F)
    return paper(F) - paper(np.eye(3)[None]), P


def mooney_rivlin(F, p, a=None):
    """C10 (I1b - 3) + C01 (I2b - 3) + kappa/2 (J - 1)^2 with dI2/dF = 2 (I1 F - F C)."""
    C10, C01, kappa = p
    C, I1, I2, J = _invariants(F)
    Jb = J[:, None, None]
    psi = C10 * (J ** (-2 / 3) * I1 - 3) + C01 * (J ** (-4 / 3) * I2 - 3) \
        + 0.5 * kappa * (J - 1) ** 2
    dI1b = Jb ** (-2 / 3) * (2 * F - 2 / 3 * I1[:, None, None] * _inv_T(F))
    dI2b = Jb ** (-4 / 3) * (2 * (I1[:, None, None] * F - F @ C)
                             - 4 / 3 * I2[:, None, None] * _inv_T(F))
    return psi, C10 * dI1b + C01 * dI2b + kappa * (Jb - 1) * _cof(F)


def fung(F, p, a=None):
    """Demiray 1972: mu/(2b) (exp(b (I1b - 3)) - 1) + kappa/2 (J - 1)^2."""
    mu, kappa, b = p
    _, I1, _, J = _invariants(F)
    I1b = J ** (-2 / 3) * I1
    psi = mu / (2 * b) * (np.exp(b * (I1b - 3)) - 1) + 0.5 * kappa * (J - 1) ** 2
    dI1b = J[:, None, None] ** (-2 / 3) * (2 * F - 2 / 3 * I1[:, None, None] * _inv_T(F))
    P = 0.5 * mu * np.exp(b * (I1b - 3))[:, None, None] * dI1b \
        + kappa * (J - 1)[:, None, None] * _cof(F)
    return psi, P


def fibre_reinforced(F, p, a):
    """HGO 2000 fibre term minus its quadratic part, on the Neo-Hookean (Lame) matrix."""
    mu, lam, k1, k2 = p
    psi_m, P_m = neo_hookean_lame(F, (mu, lam))
    n = a / np.linalg.norm(a, axis=1, keepdims=True)
    I4 = np.einsum("mi,mij,mj->m", n, F.transpose(0, 2, 1) @ F, n)
    x = I4 - 1
    psi_f = k1 / (2 * k2) * (np.exp(k2 * x**2) - 1 - k2 * x**2)
    dpsi_dI4 = k1 * x * (np.exp(k2 * x**2) - 1)
    P_f = dpsi_dI4[:, None, None] * 2 * F @ (n[:, :, None] * n[:, None, :])
    return psi_m + psi_f, P_m + P_f


REFERENCE = {f.__name__: f for f in (neo_hookean, stvk, linear, neo_hookean_lame,
                                      stable_neo_hookean, mooney_rivlin, fung, fibre_reinforced)}
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


def test_every_material_has_a_reference() -> None:
    assert sorted(REFERENCE) == materials.names() == sorted(PARAMS)
    assert len(materials.names()) >= 8


def random_rotations(rng, m):
    q, r = np.linalg.qr(rng.normal(size=(m, 3, 3)))
    q *= np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    return q


def gradients(rng, m=40, inverted=False):
    """Stretch, compression, shear and near-singular F (J down to 1e-3); inverted ones
    (J < 0) too when asked."""
    U, V = random_rotations(rng, m), random_rotations(rng, m)
    s = rng.uniform(0.5, 1.6, size=(m, 3))
    s[:4] = [[0.05, 1.0, 1.0], [0.1, 0.1, 0.1], [1e-3, 1.0, 1.0], [0.2, 3.0, 0.02]]
    if inverted:
        s[-8:, 0] *= -1
    return U @ (s[:, :, None] * V)


def inputs_of(material, rng, m):
    shapes = materials.info(material).per_element_inputs
    return [rng.normal(size=(m, *shape)) for shape in shapes.values()]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(REFERENCE))
def test_psi_and_stress_equal_the_independent_implementation(material, backend) -> None:
    rng = np.random.default_rng(21)
    defined_inverted = materials.info(material).allows_inversion
    F = gradients(rng, inverted=defined_inverted)
    extra = inputs_of(material, rng, len(F))
    k = material_kernels(material, backend)
    p = PARAMS[material]
    psi_ref, P_ref = REFERENCE[material](F, p, *extra)
    psi, P = k.psi(F, *extra, p), k.dpsi_dF(F, *extra, p)
    assert np.isfinite(psi).all() and np.isfinite(P).all()
    scale = np.maximum(np.abs(psi_ref), 1.0)
    np.testing.assert_allclose(psi / scale, psi_ref / scale, rtol=0, atol=1e-10)
    P_scale = np.maximum(np.abs(P_ref).max(axis=(1, 2)), 1.0)[:, None, None]
    np.testing.assert_allclose(P / P_scale, P_ref / P_scale, rtol=0, atol=1e-10)
    if defined_inverted:
        assert (np.linalg.det(F) < 0).sum() == 8  # the comparison met inverted elements


def linear_elastic_stiffness(E, nu, dphi, vol):
    """vol B^T C B of isotropic Hooke (Voigt-free: C_ijkl = lam d_ij d_kl + mu (d_ik d_jl +
    d_il d_jk)), for displacement DOFs vertex-major."""
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    d = np.eye(3)
    C = lam * np.einsum("ij,kl->ijkl", d, d) + mu * (np.einsum("ik,jl->ijkl", d, d)
                                                      + np.einsum("il,jk->ijkl", d, d))
    # u_i of vertex v contributes dphi[v, j] to du_i/dX_j
    K = np.einsum("m,vj,ijkl,wl->mviwk", vol, dphi[0], C, dphi[0])
    return K.reshape(len(vol), 12, 12)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("material", sorted(REFERENCE))
def test_hessian_at_rest_is_linear_elasticity_of_E_nu(material, backend) -> None:
    E, nu = 3.7e4, 0.31
    rng = np.random.default_rng(5)
    X = np.array([[0.0, 0, 0], [1, 0.1, 0], [0.2, 1.1, 0], [0.1, 0.3, 0.9]]) \
        + 0.05 * rng.normal(size=(4, 3))
    dphi, vol = kernel_module("tet", backend).rest_shape(X[None])
    values = materials.parameters_from(material, E=E, nu=nu)
    params = [values[p] for p in materials.info(material).param_names]
    extra = inputs_of(material, rng, 1)
    H = material_kernels(material, backend).hessian(X[None], dphi, vol, *extra, params)
    if materials.info(material).exact_small_strain:
        expected = linear_elastic_stiffness(E, nu, dphi, vol)
    else:  # the assignment's mapping: shear 2C = mu, lambda_eff = 2D - 4C/3
        C, D = values["C"], values["D"]
        mu_eff, lam_eff = 2 * C, 2 * D - 4 * C / 3
        E_eff = mu_eff * (3 * lam_eff + 2 * mu_eff) / (lam_eff + mu_eff)
        expected = linear_elastic_stiffness(E_eff, lam_eff / (2 * (lam_eff + mu_eff)), dphi, vol)
        assert not np.allclose(H, linear_elastic_stiffness(E, nu, dphi, vol), rtol=1e-3)
    np.testing.assert_allclose(H, expected, rtol=1e-10, atol=1e-10 * np.abs(expected).max())


@pytest.mark.parametrize("material", sorted(REFERENCE))
def test_symmetries(material) -> None:
    """Frame invariance psi(R F) = psi(F) (all but small-strain linear), and material
    symmetry psi(F Q) = psi(F): every Q for the isotropic materials, rotations about the
    fibre for the fibre model (and not others)."""
    rng = np.random.default_rng(9)
    m = 32
    F = gradients(rng, m)[4:]
    m = len(F)
    k = material_kernels(material, "numpy")
    p = PARAMS[material]
    extra = inputs_of(material, rng, m)
    psi = k.psi(F, *extra, p)
    R = random_rotations(rng, m)
    frame = np.allclose(k.psi(R @ F, *extra, p), psi, rtol=1e-10, atol=1e-12)
    assert frame == materials.info(material).rotation_invariant
    Q = random_rotations(rng, m)
    isotropic = np.allclose(k.psi(F @ Q, *extra, p), psi, rtol=1e-10, atol=1e-12)
    if not extra:
        assert isotropic == materials.info(material).rotation_invariant
        return
    assert not isotropic
    a = extra[0] / np.linalg.norm(extra[0], axis=1, keepdims=True)
    angle = rng.uniform(0, 2 * np.pi, m)[:, None, None]
    zero = np.zeros(m)
    K = np.stack([np.stack([zero, -a[:, 2], a[:, 1]], 1), np.stack([a[:, 2], zero, -a[:, 0]], 1),
                  np.stack([-a[:, 1], a[:, 0], zero], 1)], 1)  # K v = a x v
    Q_a = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    np.testing.assert_allclose(Q_a @ a[:, :, None], a[:, :, None], atol=1e-12)
    np.testing.assert_allclose(k.psi(F @ Q_a, *extra, p), psi, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(k.psi(F @ Q_a.transpose(0, 2, 1), *extra, p), psi, rtol=1e-10,
                               atol=1e-12)


def test_fibres_stiffen_only_beyond_small_strain() -> None:
    k = material_kernels("fibre_reinforced", "numpy")
    matrix = material_kernels("neo_hookean_lame", "numpy")
    a = np.array([[1.0, 0.0, 0.0]])
    values = materials.parameters_from("fibre_reinforced", E=1.0, nu=0.3)
    p = [values[n] for n in materials.info("fibre_reinforced").param_names]
    for stretch, more in ((1.001, 1e-6), (1.3, 0.05)):
        F = np.diag([stretch, 1.0, 1.0])[None]
        extra = k.psi(F, a, p)[0] - matrix.psi(F, p[:2])[0]
        assert extra > 0
        assert (extra > more) == (stretch > 1.1)
        across = np.diag([1.0, stretch, 1.0])[None]  # across the fibre: the matrix alone
        np.testing.assert_allclose(k.psi(across, a, p), matrix.psi(across, p[:2]), rtol=1e-12)


# ---- the runtime registry -----------------------------------------------------------------


def test_info_declares_inversion_by_property_not_name() -> None:
    assert materials.info("stable_neo_hookean").allows_inversion
    assert not materials.info("neo_hookean").allows_inversion
    for name in materials.names():
        i = materials.info(name)
        assert i.name == name and i.param_names and i.doc and i.inversion and i.psi
        assert set(i.mapping) == set(i.param_names)
    assert materials.info("fibre_reinforced").per_element_inputs == {"a": (3,)}
    with pytest.raises(ParameterError, match="unknown material 'rubber'.*stable_neo_hookean"):
        materials.info("rubber")


def test_parameters_from() -> None:
    mu, lam = 1e5 / 2.6, 1e5 * 0.3 / (1.3 * 0.4)
    snh = materials.parameters_from("stable_neo_hookean", E=1e5, nu=0.3)
    assert snh == pytest.approx({"mu": 4 / 3 * mu, "lam": lam + 5 / 6 * mu}, rel=1e-14)
    assert materials.parameters_from("fung", E=1e5, nu=0.3, params={"b": 4.0})["b"] == 4.0
    own = materials.parameters_from("stvk", params={"mu": 2.0, "lam": 3.0})
    assert own == {"mu": 2.0, "lam": 3.0}
    field = materials.parameters_from("linear", E=np.array([1.0, 2.0]), nu=0.25)
    np.testing.assert_allclose(field["mu"], [0.4, 0.8])
    cases = [
        (dict(E=1.0, nu=0.3, params={"mu": 2.0}), "'mu' is set by E and nu"),
        (dict(E=1.0), "nu is missing"),
        (dict(params={"mu": 1.0}), "missing: lam"),
        (dict(params={"mu": 1.0, "lam": 1.0, "zeta": 1.0}), "no parameter 'zeta'"),
        (dict(E=-1.0, nu=0.3), "Young's modulus"),
        (dict(E=1.0, nu=0.5), "Poisson"),
        (dict(params={"mu": 0.0, "lam": 1.0}), "'mu' must be > 0"),
        (dict(params={"mu": np.nan, "lam": 1.0}), "'mu' must be finite"),
    ]
    for kwargs, message in cases:
        with pytest.raises(ParameterError, match=message):
            materials.parameters_from("stvk", **kwargs)
    with pytest.raises(ParameterError, match="'b' must be > 0"):
        materials.parameters_from("fung", E=1.0, nu=0.3, params={"b": 0.0})
