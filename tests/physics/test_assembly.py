"""Model precomputation and global assembly: mass matrix, forces, stiffness, sparsity."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from fem3d.errors import InputError, ParameterError
from fem3d.kernels.backend import c_extension
from fem3d.mesh.tetmesh import box_tet_mesh
from fem3d.physics.assembly import (
    assemble_forces,
    assemble_gradient,
    assemble_hessian,
    assemble_stiffness,
    count_inverted,
    mass_matrix_mesh,
    potential_energy,
)
from fem3d.physics.model import build_model, material_parameters

ROOT = Path(__file__).resolve().parents[2]

BACKENDS = ["numpy"] + (["c"] if c_extension() is not None else [])


def box_mesh(nx: int = 2, ny: int = 2, nz: int = 2, size=(1.0, 1.0, 1.0)):
    """Kuhn-subdivided box: (nx+1)(ny+1)(nz+1) vertices, 6 nx ny nz positive tets."""
    return box_tet_mesh((nx, ny, nz), size)


def rotation(axis, angle):
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


@pytest.fixture(params=BACKENDS)
def model(request):
    X, T = box_mesh(2, 2, 2, size=(1.0, 1.5, 0.8))
    return build_model(X, T, E=1e5, nu=0.3, rho=7.0, backend=request.param)


def deformed(model, scale=0.05, seed=0):
    rng = np.random.default_rng(seed)
    return model.X + scale * rng.standard_normal(model.X.shape)


def rigid_modes(q):
    """(3n, 6) translations and infinitesimal rotations about the centroid of q."""
    q = q.reshape(-1, 3)
    c = q - q.mean(axis=0)
    modes = []
    for a in range(3):
        t = np.zeros_like(q)
        t[:, a] = 1.0
        modes.append(t.reshape(-1))
    for a in range(3):
        w = np.zeros(3)
        w[a] = 1.0
        modes.append(np.cross(w, c).reshape(-1))
    return np.array(modes).T


def test_material_parameters_from_E_nu():
    E, nu = 6e5, 0.4
    C, D = material_parameters("neo_hookean", E, nu, ("C", "D"))
    assert C == pytest.approx(0.5 * E / (2 * (1 + nu)))
    assert D == pytest.approx(0.5 * E * nu / ((1 + nu) * (1 - 2 * nu)))


@pytest.mark.parametrize(
    "kw", [dict(rho=0.0), dict(rho=-1.0), dict(E=0.0), dict(nu=0.5), dict(nu=-1.0),
           dict(E=float("nan"))],
)
def test_bad_parameters_raise(kw):
    X, T = box_mesh(1, 1, 1)
    args = dict(E=1e5, nu=0.3, rho=1.0) | kw
    with pytest.raises(ParameterError):
        build_model(X, T, **args)


def test_bad_mesh_raises():
    X, T = box_mesh(1, 1, 1)
    bad = T.copy()
    bad[3, 2] = 99
    with pytest.raises(InputError, match="element 3"):
        build_model(X, bad, E=1.0, nu=0.3, rho=1.0)
    flat = X.copy()
    flat[:, 2] = 0.0  # every tet degenerate
    with pytest.raises(InputError, match="non-positive volume"):
        build_model(flat, T, E=1.0, nu=0.3, rho=1.0)


def test_mass_matrix_symmetric_spd_total_mass(model):
    M = mass_matrix_mesh(model)
    assert M.shape == (model.n_dofs, model.n_dofs)
    assert abs(M - M.T).max() == 0.0
    eig = np.linalg.eigvalsh(M.toarray())
    assert eig.min() > 0
    total = model.rho * model.total_volume
    for axis in range(3):
        e = np.zeros(model.n_dofs)
        e[axis::3] = 1.0
        assert e @ (M @ e) == pytest.approx(total, rel=1e-12)
    assert model.total_volume == pytest.approx(1.0 * 1.5 * 0.8, rel=1e-12)


def test_forces_vanish_at_rest_and_under_rigid_motion(model):
    scale = model.E * model.total_volume ** (2 / 3)
    assert np.abs(assemble_forces(model, model.X)).max() < 1e-9 * scale
    assert abs(potential_energy(model, model.X)) < 1e-9 * scale
    R = rotation([1.0, 2.0, 0.5], 0.7)
    q = model.X @ R.T + np.array([3.0, -1.0, 2.0])
    assert np.abs(assemble_forces(model, q)).max() < 1e-9 * scale
    # stiffness annihilates the rigid modes of a stress-free state (at rest and rotated)
    for state in (model.X, q):
        K = assemble_stiffness(model, state)
        Kr = K @ rigid_modes(state)
        assert np.abs(Kr).max() < 1e-8 * abs(K).max()


def test_internal_forces_sum_to_zero_and_no_torque(model):
    q = deformed(model, 0.1)
    f = assemble_forces(model, q).reshape(-1, 3)
    scale = np.abs(f).max()
    assert scale > 0
    assert np.abs(f.sum(axis=0)).max() < 1e-10 * scale * len(f)
    torque = np.cross(q, f).sum(axis=0)
    assert np.abs(torque).max() < 1e-10 * scale * len(f) * np.abs(q).max()


def test_forces_are_minus_energy_gradient(model):
    q = deformed(model, 0.05, seed=3)
    f = assemble_forces(model, q)
    rng = np.random.default_rng(1)
    for _ in range(3):
        d = rng.standard_normal(q.size)
        h = 1e-6
        fd = (potential_energy(model, q.reshape(-1) + h * d)
              - potential_energy(model, q.reshape(-1) - h * d)) / (2 * h)
        assert -f @ d == pytest.approx(fd, rel=1e-6)
    assert np.array_equal(assemble_gradient(model, q), -f)


def test_stiffness_is_jacobian_of_forces(model):
    q = deformed(model, 0.05, seed=5).reshape(-1)
    K = assemble_stiffness(model, q).toarray()
    assert np.allclose(K, K.T, rtol=0, atol=1e-10 * np.abs(K).max())
    h = 1e-6
    J = np.empty_like(K)
    for j in range(q.size):
        e = np.zeros_like(q)
        e[j] = h
        J[:, j] = (assemble_forces(model, q + e) - assemble_forces(model, q - e)) / (2 * h)
    assert np.abs(J - K).max() < 1e-5 * np.abs(K).max()
    H = assemble_hessian(model, q)
    assert np.array_equal(H.toarray(), -K)


def test_scatter_matches_coo_assembly(model):
    """The precomputed CSR scatter equals a plain COO sum of the element blocks."""
    q = deformed(model, 0.05, seed=7)
    x_e = q[model.T]
    H_e = model.mat.hessian(x_e, model.dphi_dX, model.vol, model.params)
    dofs = model.elem_dofs
    rows = np.repeat(dofs, 12, axis=1).reshape(-1)
    cols = np.tile(dofs, (1, 12)).reshape(-1)
    ref = sp.coo_matrix((H_e.reshape(-1), (rows, cols)), shape=(model.n_dofs,) * 2).tocsr()
    H = assemble_hessian(model, q)
    assert abs(H - ref).max() < 1e-12 * abs(ref).max()
    # the pattern is shared by the mass matrix and every stiffness (never rebuilt)
    assert H.indices is model.pattern.indices or np.array_equal(H.indices, model.pattern.indices)
    assert np.array_equal(model.mass.indptr, model.pattern.indptr)
    assert model.scatter.shape == (model.n_tets * 144,)
    assert model.scatter.dtype == np.int32
    # the pattern is exactly the COO structure: every DOF pair sharing a tet, nothing else
    ones = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(model.n_dofs,) * 2).tocsr()
    np.testing.assert_array_equal(model.pattern.indptr, ones.indptr)
    np.testing.assert_array_equal(model.pattern.indices, ones.indices)
    # and the scatter sends each element entry to its own (row, col)
    pattern_rows = np.repeat(np.arange(model.n_dofs), np.diff(model.pattern.indptr))
    np.testing.assert_array_equal(pattern_rows[model.scatter], rows)
    np.testing.assert_array_equal(model.pattern.indices[model.scatter], cols)


def test_count_inverted(model):
    assert count_inverted(model, model.X) == 0
    q = model.X.copy()
    q[:, 2] *= -1.0  # mirror: every tet inverted
    assert count_inverted(model, q) == model.n_tets


def test_with_material_shares_pattern_and_scales_mass(model):
    m2 = model.with_material(E=2e5, rho=14.0)
    assert m2.pattern is model.pattern and m2.scatter is model.scatter
    assert np.allclose(m2.mass.data, 2.0 * model.mass.data)
    q = deformed(model, 0.05)
    assert np.allclose(assemble_forces(m2, q), 2.0 * assemble_forces(model, q))
    with pytest.raises(ParameterError):
        model.with_material(nu=0.7)


def test_assignment_wrappers_match_kernels(model):
    """examples/assignment.py: the CSC417 assignment's names over the runtime."""
    spec = importlib.util.spec_from_file_location("assignment", ROOT / "examples" / "assignment.py")
    a = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(a)

    X_e = model.X[model.T]
    assert np.allclose(a.dphi_linear_tetrahedron_dX(X_e), model.dphi_dX)
    centroid = X_e.mean(axis=1)
    assert np.allclose(a.phi_linear_tetrahedron(X_e, centroid), 0.25)
    q = deformed(model, 0.05)
    C, D = model.params
    x_e = q[model.T]
    V = a.V_linear_tetrahedron(x_e, model.dphi_dX, model.vol, C, D)
    assert a.quadrature_single_point(lambda: np.ones(model.n_tets), model.vol) == pytest.approx(
        model.vol)
    assert V.sum() == pytest.approx(potential_energy(model, q), rel=1e-12)
    dV = a.dV_linear_tetrahedron_dq(x_e, model.dphi_dX, model.vol, C, D)
    assert np.allclose(model.assemble_vectors(dV), -a.assemble_forces(model, q))
    K = a.assemble_stiffness(model, q)
    H_e = a.d2V_linear_tetrahedron_dq2(x_e, model.dphi_dX, model.vol, C, D)
    assert np.allclose(model.assemble_blocks(H_e), -K.data)
    v = np.random.default_rng(0).standard_normal(q.shape)
    kin = a.T_linear_tetrahedron(v[model.T], model.vol, model.rho).sum()
    assert kin == pytest.approx(0.5 * v.reshape(-1) @ (a.mass_matrix_mesh(model) @ v.reshape(-1)))
    F = np.eye(3)[None] * 1.1
    assert a.psi_neo_hookean(F, C, D).shape == (1,)
    assert a.dpsi_neo_hookean_dF(F, C, D).shape == (1, 3, 3)
    assert a.d2psi_neo_hookean_dF2(F, C, D).shape == (1, 9, 9)
    g = a.dV_spring_particle_particle_dq(np.zeros(3), np.ones(3), 0.0, 2.0)
    assert np.allclose(g, [[-2, -2, -2, 2, 2, 2]])
    assert a.V_spring_particle_particle(np.zeros(3), np.ones(3), 0.0, 2.0)[0] == pytest.approx(3)
    with pytest.raises(ValueError):
        a.V_spring_particle_particle(np.zeros(3), np.ones(3), 1.0, 2.0)
