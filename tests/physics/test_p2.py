"""Quadratic (P2) tetrahedra at work: the patch test, the consistent mass, the Jacobian check,
the cantilever against Euler-Bernoulli, and P2 scenes through every integrator and contact."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import sympy as sp

from fem3d.errors import InputError
from fem3d.mesh.element import ELEMENTS
from fem3d.mesh.formats import write_tet_mesh
from fem3d.mesh.quadratic import lift_to_p2
from fem3d.mesh.tetmesh import TetMesh, box_tet_mesh
from fem3d.physics.assembly import assemble_hessian, count_inverted
from fem3d.physics.model import build_model
from fem3d.scene import load_scene
from fem3d.simulation import Simulation

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("make_gallery",
                                               ROOT / "examples" / "make_gallery.py")
make_gallery = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(make_gallery)

P2 = ELEMENTS["p2"]


def _patch_field(E: float, nu: float):
    """A full quadratic displacement ``u(x)`` and the constant body force ``b = -div sigma``
    that makes it the solution of linear elasticity (SymPy derives ``b``)."""
    x = sp.symbols("x0:3")
    u = sp.Matrix([1e-3 * (x[0] ** 2 + 2 * x[0] * x[1] - x[2] ** 2 + x[1] - 0.5),
                   1e-3 * (x[1] ** 2 - x[0] * x[2] + 3 * x[0] + 0.25 * x[2] ** 2),
                   1e-3 * (x[2] ** 2 + x[0] * x[1] - 2 * x[1] * x[2] + x[0])])
    grad = u.jacobian(x)
    eps = (grad + grad.T) / 2
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    sigma = 2 * mu * eps + lam * eps.trace() * sp.eye(3)
    b = [-sum(sp.diff(sigma[i, j], x[j]) for j in range(3)) for i in range(3)]
    return sp.lambdify([x], list(u), "numpy"), np.array([float(v) for v in b])


def _static_solve(element: str, cells=(2, 2, 2)) -> float:
    """Largest nodal error of the static linear-elastic solve with the patch field on the
    boundary and its body force inside, relative to the largest displacement."""
    E, nu, rho = 1e5, 0.3, 1.0
    u_of, b = _patch_field(E, nu)
    X, T = box_tet_mesh(cells, size=(1.0, 0.8, 1.2))
    X = X + 0.02 * np.sin(7 * X[:, [1, 2, 0]])  # distorted (still straight-edged) tets
    if element == "p2":
        X, T = lift_to_p2(X, T)
    model = build_model(X, T, E=E, nu=nu, rho=rho, material="linear", element=element)
    K = assemble_hessian(model, model.X).tocsr()
    f = model.mass @ np.tile(b / rho, model.n_vertices)  # consistent body force
    u = np.stack(u_of(X.T), axis=1).reshape(-1)
    faces = model.element.boundary_faces(model.T)
    boundary = np.zeros(model.n_vertices, bool)
    boundary[faces] = True
    fixed = np.repeat(boundary, 3)
    free = ~fixed
    uh = u.copy()
    rhs = f[free] - K[free][:, fixed] @ u[fixed]
    uh[free] = spla.spsolve(K[free][:, free].tocsc(), rhs)
    return float(np.abs(uh - u).max() / np.abs(u).max())


def test_patch_test_quadratic_field_to_round_off():
    """P2 reproduces a quadratic displacement of linear elasticity exactly (round-off);
    P1 cannot."""
    err2 = _static_solve("p2")
    err1 = _static_solve("p1")
    print(f"patch test: P2 {err2:.2e}, P1 {err1:.2e}")
    assert err2 < 1e-10
    assert err1 > 1e-6  # 1e-4 measured: far above round-off


def test_p2_mass_is_consistent():
    X, T = box_tet_mesh((2, 1, 1), size=(2.0, 1.0, 1.0))
    X2, T2 = lift_to_p2(X, T)
    model = build_model(X2, T2, E=1e5, nu=0.3, rho=3.0, element="p2")
    ones = np.tile([1.0, 0.0, 0.0], model.n_vertices)
    assert ones @ model.mass @ ones == pytest.approx(3.0 * 2.0, rel=1e-13)
    # exact for linear velocity fields too: 1/2 v M v of v = (y, 0, 0) is rho int y^2 / 2
    v = np.zeros((model.n_vertices, 3))
    v[:, 0] = X2[:, 1]
    assert 0.5 * v.reshape(-1) @ model.mass @ v.reshape(-1) == pytest.approx(
        0.5 * 3.0 * 2.0 / 3.0, rel=1e-12)
    assert model.mass.shape == (3 * X2.shape[0],) * 2
    np.testing.assert_allclose((model.mass - model.mass.T).data, 0.0, atol=1e-15)


def test_p2_mass_is_exact_on_curved_elements():
    """A lifted box bent by the quadratic map ``phi = (x + y^2/10, y + z^2/10, z + x^2/10)``
    applied to every node: P2 represents the bent box exactly, and its ``det J`` is cubic in
    each element (the straight-edged mass, or any rule of degree < 7, would miss). The
    mass, and the kinetic energy of the velocity ``(y', 0, 0)`` (``y'`` the bent box's
    coordinate), equal SymPy's integrals over the box to round-off; straight elements
    beside curved ones keep the straight-edged kernel's matrices bit for bit."""
    X, T = box_tet_mesh((2, 1, 1), size=(2.0, 1.0, 1.0))
    X2, T2 = lift_to_p2(X, T)
    x, y, z = X2.T
    bent = np.stack([x + y**2 / 10, y + z**2 / 10, z + x**2 / 10], axis=1)
    model = build_model(bent, T2, E=1e5, nu=0.3, rho=3.0, element="p2")
    xs, ys, zs = sp.symbols("x y z", real=True)
    phi = sp.Matrix([xs + ys**2 / 10, ys + zs**2 / 10, zs + xs**2 / 10])
    det = phi.jacobian([xs, ys, zs]).det()
    box = ((xs, 0, 2), (ys, 0, 1), (zs, 0, 1))
    ones = np.tile([1.0, 0.0, 0.0], model.n_vertices)
    assert ones @ model.mass @ ones == pytest.approx(3.0 * float(sp.integrate(det, *box)),
                                                     rel=1e-13)
    v = np.zeros((model.n_vertices, 3))
    v[:, 0] = bent[:, 1]
    kinetic = 0.5 * 3.0 * float(sp.integrate(phi[1] ** 2 * det, *box))
    assert 0.5 * v.reshape(-1) @ model.mass @ v.reshape(-1) == pytest.approx(kinetic, rel=1e-12)
    # half the elements straight (their edge nodes back at the midpoints): the volume's kernel
    p2 = ELEMENTS["p2"]
    geo = p2.geometry("numpy")
    mixed = X2.copy()
    curved_nodes = T2[0, 4:]
    mixed[curved_nodes] += 0.01
    straight = np.flatnonzero(~np.isin(T2[:, 4:], curved_nodes).any(axis=1))
    assert 0 < straight.size < len(T2)
    _, vol = p2.rest_shape(geo, mixed[T2])
    volumes = p2.volumes(vol)
    blocks = p2.mass_matrices(geo, mixed, T2, volumes, 3.0, None, 0, len(T2))
    assert blocks[straight].tobytes() == geo.mass_matrix(volumes[straight], (3.0,)).tobytes()


def test_p2_refuses_inverted_elements(tmp_path):
    X, T = box_tet_mesh((1, 1, 1))
    X2, T2 = lift_to_p2(X, T)
    bad = X2.copy()
    node = T2[0, 4]  # an edge node pushed far beyond its edge's far corner
    bad[node] = X2[T2[0, 0]] + 3.0 * (X2[T2[0, 1]] - X2[T2[0, 0]])
    with pytest.raises(InputError, match="Jacobian"):
        build_model(bad, T2, E=1e5, nu=0.3, rho=1.0, element="p2")
    model = build_model(X2, T2, E=1e5, nu=0.3, rho=1.0, element="p2")
    assert count_inverted(model, model.X) == 0
    assert count_inverted(model, bad) >= 1


def _tip_deflection(cells, tmp_path: Path, element: str) -> float:
    """The static tip deflection of the docs' cantilever (E = 1e9, nu = 0)."""
    X, T = make_gallery.box_mesh(cells, (1.0, 0.1, 0.1))
    mesh = tmp_path / f"beam_{'x'.join(map(str, cells))}.mesh"
    write_tet_mesh(mesh, TetMesh(X, T))
    scene = load_scene("cantilever", {
        "bodies[0].mesh": str(mesh), "bodies[0].material.E": 1e9, "bodies[0].material.nu": 0.0,
        "bodies[0].damping.rayleigh_stiffness": 0.0, "simulation.integrator": "static",
        "simulation.steps": 1, "bodies[0].element": element})
    sim = Simulation(scene)
    sim.step()
    Xn = sim.model.X
    tip = np.flatnonzero(np.isclose(Xn[:, 0], 1.0))
    return float(-(sim.q[tip, 1] - Xn[tip, 1]).mean())


def test_p2_cantilever_within_one_percent_of_euler_bernoulli(tmp_path):
    eb = 1.5 * 1000.0 * 9.81 / (1e9 * 0.1 ** 2)
    d1 = _tip_deflection((10, 1, 1), tmp_path, "p2")
    d2 = _tip_deflection((20, 2, 2), tmp_path, "p2")
    p1 = _tip_deflection((10, 1, 1), tmp_path, "p1")
    print(f"P2 10x1x1 {d1 / eb:.4f}, 20x2x2 {d2 / eb:.4f}; P1 10x1x1 {p1 / eb:.4f}")
    assert abs(d1 / eb - 1) < 0.01 and abs(d2 / eb - 1) < 0.01
    assert p1 / eb < 0.5  # P1 locks


@pytest.mark.parametrize("integrator", ["implicit", "bdf2", "newmark", "static", "linear"])
def test_p2_scene_runs_every_integrator(integrator, tmp_path):
    X, T = make_gallery.box_mesh((4, 1, 1), (1.0, 0.25, 0.25))
    mesh = tmp_path / "beam.mesh"
    write_tet_mesh(mesh, TetMesh(X, T))
    scene = load_scene("cantilever", {
        "bodies[0].mesh": str(mesh), "bodies[0].element": "p2", "bodies[0].material.E": 1e6,
        "simulation.integrator": integrator, "simulation.steps": 3})
    sim = Simulation(scene)
    assert sim.model.element is P2 and sim.model.T.shape[1] == 10
    pinned = sim.fixed_vertices
    assert np.isin(sim.model.T[:, 4:], pinned).any()  # edge nodes on the clamp are pinned
    for _ in range(3):
        sim.step()
    assert np.isfinite(sim.q).all()
    assert np.array_equal(sim.q[pinned], sim.model.X[pinned])
    assert (sim.q[:, 1] - sim.model.X[:, 1]).min() < 0  # sags
    # the display is the subdivided quadratic surface: 4 triangles per boundary face
    assert sim.display_faces.shape[0] == 4 * P2.boundary_faces(sim.model.T).shape[0]


def _walkington14() -> tuple[np.ndarray, np.ndarray]:
    """The 14-point degree-5 rule on a tet: barycentric points ``(14, 4)`` and weights summing
    to 1 (fractions of the volume), for measuring L2 errors."""
    pts, wts = [], []
    for a, w in ((0.0927352503108912, 0.01224884051939366),
                 (0.3108859192633006, 0.01878132095300264)):
        for i in range(4):
            p = np.full(4, a)
            p[i] = 1 - 3 * a
            pts.append(p)
            wts.append(w)
    b, w = 0.04550370412564965, 0.007091003462846911
    for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)):
        p = np.full(4, 0.5 - b)
        p[[i, j]] = b
        pts.append(p)
        wts.append(w)
    return np.array(pts), 6.0 * np.array(wts)


def _l2_error(element: str, n: int) -> tuple[float, float]:
    """``(h, ||u_h - u||_L2 / ||u||_L2)`` of the static linear-elastic solve of a smooth
    manufactured field on the unit cube of ``n^3`` cells (body force interpolated into the
    element's space, boundary nodes interpolated)."""
    E, nu = 1.0, 0.3
    x = sp.symbols("x0:3")
    u = sp.Matrix([sp.sin(2 * x[0]) * sp.cos(x[1]) * 1e-2, sp.exp(x[2] * x[0]) * 1e-2,
                   sp.sin(x[1] + 2 * x[2]) * x[0] * 1e-2])
    grad = u.jacobian(x)
    eps = (grad + grad.T) / 2
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    sigma = 2 * mu * eps + lam * eps.trace() * sp.eye(3)
    b = [-sum(sp.diff(sigma[i, j], x[j]) for j in range(3)) for i in range(3)]
    u_of, b_of = sp.lambdify([x], list(u), "numpy"), sp.lambdify([x], b, "numpy")
    X, T = box_tet_mesh((n, n, n))
    if element == "p2":
        X, T = lift_to_p2(X, T)
    model = build_model(X, T, E=E, nu=nu, rho=1.0, material="linear", element=element)
    K = assemble_hessian(model, model.X).tocsr()
    f = model.mass @ np.stack(np.broadcast_arrays(*b_of(X.T)), axis=1).reshape(-1)
    u_nodes = np.stack(u_of(X.T), axis=1).reshape(-1)
    boundary = np.zeros(model.n_vertices, bool)
    boundary[model.element.boundary_faces(model.T)] = True
    fixed = np.repeat(boundary, 3)
    uh = u_nodes.copy()
    uh[~fixed] = spla.spsolve(K[~fixed][:, ~fixed].tocsc(),
                              f[~fixed] - K[~fixed][:, fixed] @ u_nodes[fixed])
    lam_q, w_q = _walkington14()
    N = model.element.shape_values(lam_q)  # (14, k)
    corners = X[T[:, :4]]  # (m, 4, 3)
    xq = np.einsum("qa,mai->mqi", lam_q, corners)
    exact = np.stack(u_of(xq.reshape(-1, 3).T), axis=1).reshape(xq.shape)
    approx = np.einsum("qa,mai->mqi", N, uh.reshape(-1, 3)[T])
    vol = model.element.volumes(model.vol)[:, None]
    err = np.sqrt((vol * w_q * ((approx - exact) ** 2).sum(axis=2)).sum())
    norm = np.sqrt((vol * w_q * (exact ** 2).sum(axis=2)).sum())
    return 1.0 / n, float(err / norm)


def test_l2_convergence_h3_for_p2_h2_for_p1():
    p2 = [_l2_error("p2", n) for n in (2, 4, 8)]
    p1 = [_l2_error("p1", n) for n in (4, 8, 16)]
    slope = [np.log(a[1] / b[1]) / np.log(a[0] / b[0]) for a, b in ((p2[1], p2[2]),
                                                                     (p1[1], p1[2]))]
    print(f"P2 errors {[e for _, e in p2]}, slope {slope[0]:.3f}; "
          f"P1 errors {[e for _, e in p1]}, slope {slope[1]:.3f}")
    assert abs(slope[0] - 3) < 0.2 and abs(slope[1] - 2) < 0.2


def _p2_stack(tmp_path: Path) -> Path:
    text = f"""
[simulation]
integrator = "implicit"
dt = 0.01
steps = 40
gravity = [0.0, -9.81, 0.0]

[[bodies]]
name = "bottom"
mesh = "{ROOT / 'data' / 'contact_block.mesh'}"
element = "p2"
transform = {{ translate = [0.0, 0.0006, 0.0] }}
material = {{ model = "neo_hookean", E = 2e5, nu = 0.4, density = 1000.0 }}

[[bodies]]
name = "top"
mesh = "{ROOT / 'data' / 'contact_block.mesh'}"
element = "p2"
transform = {{ rotate_deg = [10.0, 0.0, 15.0], translate = [0.01, 0.1, 0.0] }}
material = {{ model = "neo_hookean", E = 2e5, nu = 0.4, density = 1000.0 }}

[contact]
enabled = true
dhat = 1e-3
mu = 0.3

[[obstacles]]
plane = {{ point = [0.0, 0.0, 0.0], normal = [0.0, 1.0, 0.0] }}
"""
    path = tmp_path / "p2_stack.toml"
    path.write_text(text)
    return path


def test_p2_contact_stack_stays_intersection_free(tmp_path):
    """Two P2 blocks, the upper dropped on the lower: IPC on the subdivided quadratic
    surface (4 triangles per face through corner and edge nodes); every step converges, no
    triangle pair of the surfaces intersects (a fresh ipctk mesh) and nothing goes below the
    ground; the upper block lands."""
    import ipctk

    sim = Simulation(load_scene(str(_p2_stack(tmp_path))))
    F = P2.surface_triangles(sim.model.T).astype(np.int32)
    g = sim.contact.contact.geometry
    assert np.array_equal(g.surface[g.faces[:F.shape[0]]], F)  # edge nodes collide directly
    cm = ipctk.CollisionMesh.build_from_full_mesh(np.asfortranarray(sim.model.X),
                                                  ipctk.edges(F), F)
    top = sim.assembled.body_vertices[1]
    y0 = sim.q[top, 1].min()
    for _ in range(40):
        sim.step()
        assert sim.last_stats.converged
        assert sim.q[:, 1].min() > 0.0
        assert not ipctk.has_intersections(cm, cm.vertices(np.asfortranarray(sim.q)))
    bottom = sim.assembled.body_vertices[0]
    # fell 2.8 cm and rests on the lower block's (indented) top: the two within 3 mm
    assert abs(sim.q[top, 1].min() - sim.q[bottom, 1].max()) < 3e-3
    assert sim.q[top, 1].min() < y0 - 0.02


def test_p2_resume_is_bit_exact(tmp_path):
    """A P2 run interrupted at step 4 and resumed to 8 ends bit for bit where the
    uninterrupted run does (the checkpoint holds the scene; the lift is redone identically)."""
    from fem3d.app.cli import main

    X, T = make_gallery.box_mesh((8, 2, 2), (1.0, 0.1, 0.1))
    write_tet_mesh(tmp_path / "beam.mesh", TetMesh(X, T))
    common = ["--set", f'bodies[0].mesh="{tmp_path / "beam.mesh"}"', "--set",
              'bodies[0].element="p2"', "--set", "bodies[0].material.E=1e6", "--quiet",
              "--no-preview"]
    assert main(["run", "cantilever", *common, "--steps", "8", "--checkpoint-every", "8",
                 "--out", str(tmp_path / "a")]) == 0
    assert main(["run", "cantilever", *common, "--steps", "4", "--checkpoint-every", "4",
                 "--out", str(tmp_path / "b")]) == 0
    assert main(["resume", str(tmp_path / "b"), "--steps", "8", "--quiet", "--no-preview"]) == 0
    a, b = np.load(tmp_path / "a" / "checkpoint.npz"), np.load(tmp_path / "b" / "checkpoint.npz")
    assert a["state_q"].shape == lift_to_p2(X, T)[0].shape  # the P2 nodes
    assert np.array_equal(a["state_q"], b["state_q"]) and np.array_equal(a["state_v"], b["state_v"])
    assert not np.array_equal(a["state_q"][:X.shape[0]], X)  # it moved
