"""Material groups, per-element parameters and inputs, per-element density in the model and
the assembly, on both kernel back ends."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.errors import ParameterError
from fem3d.kernels.backend import c_extension
from fem3d.physics import materials
from fem3d.physics.assembly import assemble_gradient, hessian_data, potential_energy
from fem3d.physics.model import GROUP_PARAMS, MaterialGroup, build_model
from tests.physics.test_assembly import box_mesh

BACKENDS = ["numpy"] + (["c"] if c_extension() is not None else [])


@pytest.fixture(scope="module")
def mesh():
    return box_mesh(2, 2, 2, size=(1.0, 1.5, 0.8))


def _q(X, seed=0, scale=0.04):
    return X + scale * np.random.default_rng(seed).standard_normal(X.shape)


def _reference(X, T, groups, q):
    """Energy, gradient and Hessian data summed from one-material models of each group's
    tets alone (same vertices, so the same DOFs; the pattern differs, so compare dense)."""
    energy, grad, hess = 0.0, 0.0, 0.0
    for g in groups:
        sub = build_model(X, T[g.elements], groups=[MaterialGroup(g.material, None, g.params)],
                          density=1.0, backend="numpy")
        energy += potential_energy(sub, q)
        grad = grad + assemble_gradient(sub, q)
        hess = hess + sub.csr(hessian_data(sub, q)).toarray()
    return energy, grad, hess


@pytest.mark.parametrize("backend", BACKENDS)
def test_groups_sum_their_materials(mesh, backend) -> None:
    X, T = mesh
    m = len(T)
    rng = np.random.default_rng(1)
    order = rng.permutation(m)
    a, b, c = (np.sort(part) for part in np.array_split(order, 3))
    fibres = rng.normal(size=(len(c), 3))
    groups = [
        MaterialGroup("stable_neo_hookean", a, {"E": 1e4, "nu": 0.3}),
        MaterialGroup("fung", b, {"E": rng.uniform(5e3, 2e4, len(b)), "nu": 0.35, "b": 2.0}),
        MaterialGroup("fibre_reinforced", c, {"E": 2e4, "nu": 0.25, "a": fibres, "k1": 3e4}),
    ]
    model = build_model(X, T, groups=groups, density=2.0, backend=backend)
    assert model.params is GROUP_PARAMS and model.material == "stable_neo_hookean+fung+" \
        "fibre_reinforced"
    assert not model.allows_inversion  # fung and the fibre model are not defined at J <= 0
    q = _q(X)
    e_ref, g_ref, H_ref = _reference(X, T, groups, q)
    assert potential_energy(model, q) == pytest.approx(e_ref, rel=1e-12)
    np.testing.assert_allclose(assemble_gradient(model, q), g_ref, rtol=1e-10,
                               atol=1e-10 * np.abs(g_ref).max())
    for psd in (False, True):
        H = model.csr(hessian_data(model, q, psd=psd)).toarray()
        if not psd:
            np.testing.assert_allclose(H, H_ref, rtol=1e-10, atol=1e-10 * np.abs(H_ref).max())
    # the same arrays through model.mat, as fem3d.solve.integrators calls it (scaled volumes and a
    # scatter of its own)
    vol = model.vol * 0.5
    vol.setflags(write=False)
    x_e = q[model.T]
    H_e = model.mat.hessian(x_e, model.dphi_dX, vol, model.params)
    data = model.assemble_blocks(H_e)
    np.testing.assert_allclose(data, 0.5 * hessian_data(model, q), rtol=1e-12,
                               atol=1e-12 * np.abs(data).max())
    if model.mat.has_assemble("hessian"):
        out = np.zeros(model.nnz)
        model.mat.hessian_assemble(q, model.T, model.dphi_dX, vol, model.params, model.scatter,
                                   out)
        np.testing.assert_allclose(out, data, rtol=1e-12, atol=1e-12 * np.abs(data).max())
    with pytest.raises(TypeError, match="model.params"):
        model.mat.energy(x_e, model.dphi_dX, model.vol, (1.0, 2.0))


def test_both_back_ends_agree_on_a_grouped_model(mesh) -> None:
    if c_extension() is None:
        pytest.skip("C extension not built")
    X, T = mesh
    groups = [MaterialGroup("mooney_rivlin", np.arange(0, len(T), 2), {"E": 1e4, "nu": 0.4}),
              MaterialGroup("fibre_reinforced", None, {"E": 1e4, "nu": 0.3, "a": (0, 1, 1)})]
    q = _q(X, 3)
    models = [build_model(X, T, groups=groups, density=1.0, backend=b) for b in ("numpy", "c")]
    e = [potential_energy(mo, q) for mo in models]
    g = [assemble_gradient(mo, q) for mo in models]
    H = [hessian_data(mo, q) for mo in models]
    assert e[0] == pytest.approx(e[1], rel=1e-12)
    np.testing.assert_allclose(g[0], g[1], rtol=1e-11, atol=1e-11 * np.abs(g[0]).max())
    np.testing.assert_allclose(H[0], H[1], rtol=1e-11, atol=1e-11 * np.abs(H[0]).max())


@pytest.mark.parametrize("backend", BACKENDS)
def test_one_group_equals_the_old_keywords(mesh, backend) -> None:
    X, T = mesh
    old = build_model(X, T, E=1e5, nu=0.3, rho=7.0, material="stvk", backend=backend)
    new = build_model(X, T, groups=[MaterialGroup("stvk", None, {"E": 1e5, "nu": 0.3})],
                      density=7.0, backend=backend)
    assert new.mat is old.mat and np.array_equal(new.params, old.params)
    assert (new.E, new.nu, new.rho) == pytest.approx((1e5, 0.3, 7.0), rel=1e-12)
    q = _q(X)
    assert potential_energy(new, q) == potential_energy(old, q)
    # a uniform field is the uniform material, and a per-element density equals the scalar
    field = build_model(X, T, groups=[MaterialGroup("stvk", None, {
        "E": np.full(len(T), 1e5), "nu": 0.3})], density=np.full(len(T), 7.0), backend=backend)
    assert field.params is GROUP_PARAMS
    assert potential_energy(field, q) == pytest.approx(potential_energy(old, q), rel=1e-13)
    np.testing.assert_allclose(field.mass.data, old.mass.data, rtol=1e-14)
    assert field.E == pytest.approx(1e5, rel=1e-10) and field.nu == pytest.approx(0.3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_stiffness_field_scales_element_energies(mesh, backend) -> None:
    X, T = mesh
    scale = np.random.default_rng(4).uniform(0.5, 3.0, len(T))
    base = build_model(X, T, E=1e4, nu=0.3, rho=1.0, material="neo_hookean_lame",
                       backend=backend)
    field = build_model(X, T, groups=[MaterialGroup("neo_hookean_lame", None, {
        "E": 1e4 * scale, "nu": 0.3})], density=1.0, backend=backend)
    q = _q(X, 5)
    x_e = q[T]
    e_base = base.mat.energy(x_e, base.dphi_dX, base.vol, base.params)
    e_field = field.mat.energy(x_e, field.dphi_dX, field.vol, field.params)
    np.testing.assert_allclose(e_field, scale * e_base, rtol=1e-12)
    assert field.E == pytest.approx(1e4 * (scale * base.vol).sum() / base.vol.sum(), rel=1e-10)


def test_allows_inversion_and_with_material(mesh) -> None:
    X, T = mesh
    snh = build_model(X, T, E=1e4, nu=0.3, rho=1.0, material="stable_neo_hookean")
    assert snh.allows_inversion
    assert not build_model(X, T, E=1e4, nu=0.3, rho=1.0).allows_inversion
    groups = [MaterialGroup("stable_neo_hookean", np.arange(5), {"E": 1e4, "nu": 0.3}),
              MaterialGroup("linear", None, {"E": 3e4, "nu": 0.2})]
    mixed = build_model(X, T, groups=groups, density=np.linspace(1.0, 2.0, len(T)))
    assert mixed.allows_inversion
    q = X.copy()
    q[:, 2] *= -1  # every tet inverted: finite energy for materials defined there
    assert np.isfinite(potential_energy(mixed, q))
    stiffer = mixed.with_material(E=6e4, rho=3.0)
    assert stiffer.pattern is mixed.pattern and stiffer.E == 6e4
    for g in stiffer.groups:
        expected = materials.parameters_from(g.material, E=6e4, nu=mixed.nu)
        assert g.values == pytest.approx(expected)
    np.testing.assert_allclose(stiffer.mass.data, mixed.mass.data * 3.0 / mixed.rho)
    fibre = build_model(X, T, groups=[MaterialGroup("fibre_reinforced", None, {
        "E": 1e4, "nu": 0.3, "a": (0.0, 0.0, 2.0), "k2": 7.0})], density=1.0)
    switched = mixed.with_material(material="fung")
    assert switched.material == "fung" and switched.mat is not mixed.mat
    assert switched.groups[0].values == pytest.approx(
        materials.parameters_from("fung", E=mixed.E, nu=mixed.nu))
    assert not switched.allows_inversion and switched.scatter is mixed.scatter
    softer = fibre.with_material(E=5e3)
    assert softer.groups[0].values["k2"] == 7.0  # shape parameters are kept
    np.testing.assert_array_equal(softer.groups[0].inputs[0], fibre.groups[0].inputs[0])


def test_bad_groups_name_the_group_and_parameter(mesh) -> None:
    X, T = mesh
    m = len(T)
    cases = [
        ([MaterialGroup("rubber")], "unknown material 'rubber'"),
        ([MaterialGroup("stvk", np.arange(3), {"E": 1.0, "nu": 0.3}),
          MaterialGroup("linear", np.arange(2, 5), {"E": 1.0, "nu": 0.3})],
         "group 1 \\(linear\\): element 2 is already in material group 0"),
        ([MaterialGroup("stvk", np.arange(3), {"E": 1.0, "nu": 0.3})], "tet 3 is in no"),
        ([MaterialGroup("stvk", np.array([0, m]), {"E": 1.0, "nu": 0.3})], f"outside \\[0, {m}\\)"),
        ([MaterialGroup("stvk", None, {"E": np.ones(m - 1), "nu": 0.3})],
         f"parameter 'E' has {m - 1} values for {m} elements"),
        ([MaterialGroup("stvk", None, {"E": 1.0, "nu": 0.7})], "group 0 \\(stvk\\).*Poisson"),
        ([MaterialGroup("fibre_reinforced", None, {"E": 1.0, "nu": 0.3, "a": (0, 0, 0)})],
         "input 'a' of element 0 is zero"),
        ([MaterialGroup("fung", None, {"E": 1.0, "nu": 0.3, "kappa": 2.0})],
         "'kappa' is set by E and nu"),
        ([MaterialGroup("stvk"), MaterialGroup("linear")], "both have elements=None"),
    ]
    for groups, message in cases:
        with pytest.raises(ParameterError, match=message):
            build_model(X, T, groups=groups, density=1.0)
    with pytest.raises(ParameterError, match="density of tet 2"):
        build_model(X, T, E=1.0, nu=0.3, density=np.r_[1.0, 1.0, -1.0, np.ones(m - 3)])
    with pytest.raises(ParameterError, match="give E and nu in each"):
        build_model(X, T, E=1.0, groups=[MaterialGroup("stvk")], density=1.0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_backward_euler_steps_a_grouped_model(mesh, backend) -> None:
    """fem3d.solve.integrators takes a model with groups through model.mat / model.params (its
    Newton matrix with scaled volumes and its own scatter) unchanged."""
    from fem3d.physics.constraints import Constraints, fixed_vertices_lowest_y
    from fem3d.solve.integrators import State, System, implicit_euler

    X, T = mesh
    groups = [MaterialGroup("stable_neo_hookean", np.arange(0, len(T), 3), {"E": 2e4, "nu": 0.3}),
              MaterialGroup("fibre_reinforced", None, {"E": 1e4, "nu": 0.3, "a": (1, 0, 0)})]
    model = build_model(X, T, groups=groups, density=10.0, backend=backend)
    fixed = fixed_vertices_lowest_y(X, 1e-9)
    system = System(model, Constraints.from_fixed_vertices(X, fixed))
    v = np.zeros_like(X)
    v[:, 0] = 0.5 * X[:, 1]  # shear the box
    state, stats = implicit_euler(system, State(q=X.copy(), v=v), 0.02, max_iterations=None)
    assert stats.converged and stats.newton_iterations > 1
    assert np.isfinite(state.q).all() and np.abs(state.q - X).max() > 1e-4
    np.testing.assert_array_equal(state.q[fixed], X[fixed])
