"""Surface loads on quadratic (P2) tets (issue 43): the 6-node face kernels of the follower
pressure (``pressure.p2_*``, generated from ``codegen/pressure.py``) against differences and
the linear face, the consistent follower load on a closed curved surface, and a P2 patch
under uniform tractions: the exact total force, corners unloaded, and the exact uniform
linear-elastic state.
"""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.kernels.backend import c_extension
from fem3d.kernels.dispatch import kernel_module
from fem3d.mesh.element import ELEMENTS
from fem3d.mesh.quadratic import lift_to_p2
from fem3d.mesh.tetmesh import box_tet_mesh
from fem3d.physics.model import build_model
from fem3d.physics.stress import element_stress
from fem3d.physics.terms.surface import FollowerPressure
from fem3d.scene import scene_from_arrays
from fem3d.simulation import Simulation

BACKENDS = ["numpy", pytest.param("c", marks=pytest.mark.skipif(
    c_extension() is None or not hasattr(c_extension(), "pressure_p2_energy"),
    reason="C extension not built with the P2 face kernels"))]
P2 = ELEMENTS["p2"]


def _flat_faces(rng, m: int) -> np.ndarray:
    """``m`` random flat 6-node triangles (mid-edge nodes at the midpoints)."""
    c = rng.normal(size=(m, 3, 3))
    mid = np.stack([(c[:, 0] + c[:, 1]) / 2, (c[:, 1] + c[:, 2]) / 2, (c[:, 2] + c[:, 0]) / 2],
                   axis=1)
    return np.concatenate([c, mid], axis=1)


@pytest.mark.parametrize("backend", BACKENDS)
def test_p2_face_kernels_match_differences_and_the_flat_face(backend):
    """On curved 6-node faces the generated gradient and Hessian match central differences
    of the generated energy and gradient; on flat faces the energy is the linear face's, the
    traction weights are 0 at the corners and ``A / 3`` at the edge nodes, and the follower
    load of unit pressure is ``-A n / 3`` at the edge nodes only."""
    k = kernel_module("pressure", backend)
    rng = np.random.default_rng(5)
    x = _flat_faces(rng, 4) + 0.1 * rng.normal(size=(4, 6, 3))  # curved
    p = (1.5,)
    g = k.p2_gradient(x, p).reshape(4, 18)
    H = k.p2_hessian(x, p).reshape(4, 18, 18)
    h = 1e-6
    for i in range(18):
        d = np.zeros(18)
        d[i] = h
        plus, minus = x + d.reshape(6, 3), x - d.reshape(6, 3)
        fd = (k.p2_energy(plus, p) - k.p2_energy(minus, p)) / (2 * h)
        assert np.abs(fd - g[:, i]).max() < 1e-8 * (1 + np.abs(g).max())
        fd_g = (k.p2_gradient(plus, p) - k.p2_gradient(minus, p)).reshape(4, 18) / (2 * h)
        assert np.abs(fd_g - H[:, :, i]).max() < 1e-7 * (1 + np.abs(H).max())
    assert np.array_equal(H, H.transpose(0, 2, 1))
    flat = _flat_faces(rng, 6)
    assert np.allclose(k.p2_energy(flat, p), k.energy(flat[:, :3], p), rtol=1e-12, atol=1e-14)
    an = 0.5 * np.cross(flat[:, 1] - flat[:, 0], flat[:, 2] - flat[:, 0])
    area = np.linalg.norm(an, axis=1)
    w = k.p2_traction_weights(flat)
    assert np.abs(w[:, :3]).max() < 1e-14 * area.max()
    assert np.allclose(w[:, 3:], area[:, None] / 3, rtol=1e-13)
    load = k.p2_follower_load(flat).reshape(6, 6, 3)
    assert np.abs(load[:, :3]).max() < 1e-14 * area.max()
    assert np.allclose(load[:, 3:], np.repeat(-an[:, None] / 3, 3, axis=1), rtol=1e-12,
                       atol=1e-15)


def _curved_p2_box():
    """A P2 box of 2 x 2 x 2 cells whose edge nodes are moved off the straight edges (the
    boundary faces curved) and its boundary's 6-node faces."""
    X, T = lift_to_p2(*box_tet_mesh((2, 2, 2), (1.0, 0.8, 0.6)))
    X = X.copy()
    edge_nodes = np.unique(T[:, 4:])
    X[edge_nodes] += 0.01 * np.sin(5 * X[edge_nodes][:, [1, 2, 0]])
    return X, T, P2.boundary_faces(T)


def test_p2_pressure_on_a_closed_curved_surface_is_the_consistent_follower_load():
    """On a P2 body's whole (curved) boundary the potential's force is the consistent
    follower load ``-p integral N_i n dA`` of every 6-node face, at rest and deformed; it sums
    to zero (a closed surface), and at rest the open-patch check finds no edge forces."""
    X, T, faces = _curved_p2_box()
    model = build_model(X, T, E=1e5, nu=0.3, rho=1000.0, element="p2")
    term = FollowerPressure(model, faces, 3.0)
    assert np.abs(term.edge_forces()).max() < 1e-13
    k = kernel_module("pressure", model.backend)
    rng = np.random.default_rng(2)
    for q in (X, X + 0.02 * rng.normal(size=X.shape)):
        f = -term.gradient(q.reshape(-1)).reshape(-1, 3)
        expected = np.zeros_like(X)
        np.add.at(expected, faces.reshape(-1), 3.0 * k.p2_follower_load(q[faces]).reshape(-1, 3))
        assert np.abs(f - expected).max() < 1e-12 * np.abs(expected).max()
        assert np.abs(f.sum(axis=0)).max() < 1e-12 * np.abs(f).max()


def test_p2_patch_under_uniform_traction_is_exact():
    """A distorted P2 box on three symmetry planes, tractions ``(sx, 0, 0)``, ``(0, sy, 0)``,
    ``(0, 0, sz)`` on its faces x = 1, y = 1, z = 1, linear material, one static step: each
    load totals traction x area exactly with nothing on the face corners, and the solution is
    the uniform state ``u = eps X`` (``eps = C^-1 sigma``) at every node to round-off, so the
    stress in every element is ``sigma`` (to the strain's order: Cauchy vs small strain)."""
    E, nu = 1e5, 0.3
    s = np.array([2.0, -1.0, 0.5])
    X, T = box_tet_mesh((2, 2, 2), (1.0, 1.0, 1.0))
    X = X + 0.05 * np.sin(np.pi * X[:, [0]]) * np.sin(np.pi * X[:, [1]]) * \
        np.sin(np.pi * X[:, [2]]) * np.array([1.0, -0.7, 0.4])  # interior nodes only
    lo, hi = -1e-6, 1 + 1e-6

    def plane(axis: int, value: float) -> dict:
        box = [[lo - 1] * 3, [hi + 1] * 3]
        box[0][axis], box[1][axis] = value - 1e-6, value + 1e-6
        return {"box": box}

    pins = [{"select": plane(a, 0.0), "dofs": "xyz"[a]} for a in range(3)]
    loads = [{"select": plane(a, 1.0), "traction": list(s[a] * np.eye(3)[a])} for a in range(3)]
    sim = Simulation(scene_from_arrays(X, T, {
        "bodies[0].element": "p2", "bodies[0].pins": pins, "bodies[0].loads": loads,
        "bodies[0].material": {"model": "linear", "E": E, "nu": nu, "density": 1.0},
        "simulation.integrator": "static", "simulation.dt": 1.0, "simulation.steps": 1,
        "simulation.newton.tolerance": 1e-14, "pulls": [], "simulation.gravity": [0.0, 0.0, 0.0]},
        name="p2_patch"))
    model = sim.model
    assert model.T.shape[1] == 10
    corners = np.unique(model.T[:, :4])
    for a, load in enumerate(sim.system.loads.surface):
        f = load.applied().reshape(-1, 3)
        assert np.allclose(f.sum(axis=0), s[a] * np.eye(3)[a], rtol=1e-13, atol=1e-15)
        assert np.all(f[corners] == 0.0) or np.abs(f[corners]).max() < 1e-15
    sim.step()
    eps = (np.diag(s) * (1 + nu) - nu * s.sum() * np.eye(3)) / E
    u = sim.q - model.X
    assert np.abs(u - model.X @ eps.T).max() < 1e-9 * np.abs(model.X @ eps.T).max()
    sigma = element_stress(model, sim.q).cauchy
    assert np.abs(sigma - np.diag(s)).max() < 1e-4 * np.abs(s).max()


def _lame(mesh: str, scene: str = "lame_sphere_eighth") -> Simulation:
    from fem3d.scene import load_scene

    sim = Simulation(load_scene(scene, {"bodies[0].mesh": f"meshes/{mesh}",
                                        "bodies[0].element": "p2"}))
    sim.step()
    return sim


def test_lame_sphere_on_curved_p2_within_one_percent_and_octant_equals_whole():
    """Lame's thick-walled sphere (docs/loads.md) on the isoparametric P2 octant
    ``lame_eighth_8_p2.vtu``: the radial displacement of every inner and outer surface node
    within 1 % of ``u(r)`` (measured: 0.50 % at the worst node, means +0.03 % and +0.12 %);
    the octant on three symmetry planes equals the whole sphere (``lame_sphere_4_p2.vtu``,
    the octant ``lame_eighth_4_p2.vtu`` mirrored) at the octant's nodes."""
    from scipy.spatial import cKDTree

    a, b, E, nu, p = 1.0, 2.0, 1000.0, 0.3, 1.0
    sim = _lame("lame_eighth_8_p2.vtu")
    X = sim.model.X
    r = np.linalg.norm(X, axis=1)
    ur = np.einsum("ij,ij->i", sim.q - X, X) / r
    exact = p * a**3 * r / (E * (b**3 - a**3)) * ((1 - 2 * nu) + (1 + nu) * b**3 / (2 * r**3))
    surface = (np.abs(r - a) < 1e-9) | (np.abs(r - b) < 1e-9)
    assert surface.sum() > 500
    rel = ur[surface] / exact[surface] - 1
    assert np.abs(rel).max() < 0.01
    assert abs(rel[np.abs(r[surface] - a) < 1e-9].mean()) < 0.002
    eighth, whole = _lame("lame_eighth_4_p2.vtu"), _lame("lame_sphere_4_p2.vtu", "lame_sphere")
    dist, idx = cKDTree(whole.model.X).query(eighth.model.X)
    assert dist.max() < 1e-12
    u = eighth.q - eighth.model.X
    assert np.abs(u - (whole.q - whole.model.X)[idx]).max() < 1e-9 * np.abs(u).max()


def test_symmetry_plane_reactions_are_the_pressures_resultant():
    """The three symmetry planes of the P2 octant (``lame_eighth_4_p2.vtu``) each hold the
    inner pressure's resultant on the cut, ``-p pi (a + u(a))^2 / 4`` along their normal
    (measured 7.8e-5 off): the reactions count the follower load, not the open patch
    potential's edge forces (which made them -0.262 instead of -0.787)."""
    a, p, ua = 1.0, 1.0, (0.4 + 1.3 * 4.0) / 7000.0  # u(a) = p a (1 - 2 nu + (1 + nu) 4) / 7E
    sim = _lame("lame_eighth_4_p2.vtu")
    R = sim.reactions()
    expected = -p * np.pi * (a + ua) ** 2 / 4
    assert np.allclose(np.diag(R), expected, rtol=5e-4)
    assert np.abs(R - np.diag(np.diag(R))).max() == 0.0  # each plane holds its normal only
