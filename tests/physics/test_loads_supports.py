"""Partial supports (issue 43): pins that hold some components (``dofs``): rollers and
symmetry planes, in the Newton system, every scheme, snapshots; the under-supported static
problem named by its free rigid motion. Small meshes; each test runs in about a second.
"""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.errors import InputError
from fem3d.mesh.tetmesh import box_tet_mesh
from fem3d.physics.constraints import Constraints, free_rigid_modes
from fem3d.scene import scene_from_arrays
from fem3d.simulation import Simulation

EPS = 1e-9


def face(axis: int, value: float, dofs: str = "xyz", motion=None) -> dict:
    """A pin on the vertices with coordinate ``axis`` equal to ``value``."""
    lo, hi = [-9.0] * 3, [9.0] * 3
    lo[axis], hi[axis] = value - EPS, value + EPS
    pin = {"select": {"box": [lo, hi]}, "dofs": dofs}
    if motion is not None:
        pin["motion"] = {"keyframes": [{"t": 0.0}, {"t": 1.0, "translate": list(motion)}]}
    return pin


def mirrored(X: np.ndarray, T: np.ndarray):
    """The mesh and its mirror image in the plane ``x = 0`` as one mesh (the plane's
    vertices shared): a mesh exactly symmetric about ``x = 0``."""
    n = X.shape[0]
    on = np.flatnonzero(np.abs(X[:, 0]) < EPS)
    off = np.setdiff1d(np.arange(n), on)
    Xm = X[off] * np.array([-1.0, 1.0, 1.0])
    index = np.arange(n)
    index[off] = n + np.arange(off.size)
    Tm = index[T][:, [1, 0, 2, 3]]  # the reflection flips orientation
    return np.vstack([X, Xm]), np.vstack([T, Tm])


def _scene(X, T, pins, integrator="static", steps=1, **extra):
    over = {"bodies[0].pins": pins, "bodies[0].material.E": 1e5,
            "bodies[0].material.nu": 0.3, "simulation.integrator": integrator,
            "simulation.dt": 1.0 / steps, "simulation.steps": steps, "pulls": []} | extra
    return scene_from_arrays(X, T, over, name="block")


def _run(scene):
    sim = Simulation(scene)
    for _ in range(scene.simulation.n_steps):
        sim.step()
    return sim


@pytest.mark.parametrize("integrator", ["static", "implicit"])
def test_symmetry_plane_gives_the_whole_body(integrator):
    """A block stretched by its two end faces = its half with a symmetry plane ``dofs =
    "x"`` at ``x = 0`` (the mesh is mirror-symmetric), statically and dynamically."""
    Xh, Th = box_tet_mesh((3, 2, 2), (0.6, 0.3, 0.3))
    Xh = Xh + np.array([0.0, -0.15, -0.15])
    Xf, Tf = mirrored(Xh, Th)
    pull = (0.12, 0.03, 0.0)  # outward and sideways: bends the block too
    extra = {"simulation.gravity": [0.0, -9.81, 0.0]}
    steps = 1 if integrator == "static" else 5
    whole = _run(_scene(Xf, Tf, [face(0, 0.6, motion=pull),
                                 face(0, -0.6, motion=(-pull[0], pull[1], pull[2]))],
                        integrator, steps, **extra))
    half = _run(_scene(Xh, Th, [face(0, 0.6, motion=pull), face(0, 0.0, "x")],
                       integrator, steps, **extra))
    err = np.abs(whole.q[: Xh.shape[0]] - half.q).max()
    moved = np.abs(half.q - Xh).max()
    print(integrator, "max |whole - half|", err, "of", moved)
    plane = np.abs(Xh[:, 0]) < EPS
    assert np.all(half.q[plane, 0] == 0.0)  # the plane's x held exactly
    assert np.abs(half.q[plane, 1:] - Xh[plane, 1:]).max() > 1e-3  # y, z free to move
    assert err < 1e-8 * moved


def test_roller_holds_one_component_in_every_scheme():
    """A beam clamped at ``x = 0`` on a roller (``dofs = "y"``) at ``x = 1`` under gravity:
    the roller's y stays, its x and z move (gravity along -y and z bends and shortens it)."""
    X, T = box_tet_mesh((6, 2, 2), (1.0, 0.2, 0.2))
    for integrator in ("implicit", "bdf2", "newmark", "static", "linear"):
        sim = _run(_scene(X, T, [face(0, 0.0), face(0, 1.0, "y")], integrator, 3,
                          **{"simulation.gravity": [0.0, -9.81, 30.0],
                             "bodies[0].material.E": 1e4}))
        tip = np.abs(X[:, 0] - 1.0) < EPS
        print(integrator, np.abs(sim.q[tip] - X[tip]).max(axis=0))
        assert np.array_equal(sim.q[tip, 1], X[tip, 1]), integrator
        assert np.all(sim.v[tip, 1] == 0.0), integrator
        assert np.abs(sim.q[tip, 2] - X[tip, 2]).min() > 1e-4, integrator
        assert np.abs(sim.q[tip, 0] - X[tip, 0]).max() > 1e-7, integrator


def test_partial_pins_in_the_newton_system():
    """Fixed DOFs, not vertices, leave the unknowns: ``dofs = "z"`` removes one DOF each."""
    X, T = box_tet_mesh((2, 1, 1))
    sim = Simulation(_scene(X, T, [face(0, 0.0), face(0, 1.0, "z")]))
    c = sim.constraints
    clamp, roller = (np.flatnonzero(np.abs(X[:, 0] - v) < EPS) for v in (0.0, 1.0))
    assert c.partial and c.n_free == 3 * X.shape[0] - 3 * clamp.size - roller.size
    assert np.array_equal(c.fixed_dofs, np.sort(np.concatenate(
        [3 * clamp[:, None] + np.arange(3), 3 * roller[:, None] + 2], axis=None)))
    assert sim.system.pattern_free.shape == (c.n_free, c.n_free)
    p = 3 * c.fixed_vertices[:, None] + np.arange(3)  # each fixed vertex's DOF indices
    assert np.array_equal(p.reshape(-1)[c.fixed_slots], c.fixed_dofs)


def test_snapshot_resume_is_bit_exact_with_partial_pins():
    """Six steps, a snapshot restored into a new simulation, six more = twelve in one go
    (a keyframed roller, a dynamic scheme: what a checkpoint carries)."""
    X, T = box_tet_mesh((4, 1, 1), (1.0, 0.25, 0.25))
    scene = _scene(X, T, [face(0, 0.0), face(0, 1.0, "xz", motion=(0.05, 0.0, 0.1))],
                   "implicit", 12, **{"simulation.gravity": [0.0, -9.81, 0.0]})
    whole = _run(scene)
    first = Simulation(scene)
    for _ in range(6):
        first.step()
    second = Simulation(scene)
    second.restore(first.snapshot())
    for _ in range(6):
        second.step()
    assert np.array_equal(whole.q, second.q) and np.array_equal(whole.v, second.v)
    tip = np.abs(X[:, 0] - 1.0) < EPS
    assert np.allclose(whole.q[tip][:, [0, 2]], X[tip][:, [0, 2]] + [0.05, 0.1], atol=1e-15)


@pytest.mark.parametrize(("pins", "named"), [
    ([face(1, 0.0, "y")], "translation along x"),
    ([face(1, 0.0, "xy")], "translation along z"),
    ([face(0, 0.0, "y"), face(2, 0.0, "z")], "translation along x"),
])
def test_under_supported_static_names_the_free_rigid_motion(pins, named):
    """Static refuses pins that leave a rigid motion free, in one line naming it."""
    X, T = box_tet_mesh((2, 2, 2))
    with pytest.raises(InputError) as info:
        Simulation(_scene(X, T, pins))
    message = str(info.value)
    print(message)
    assert "under-supported" in message and named in message and "\n" not in message


def test_free_rigid_modes():
    """Three symmetry planes hold an octant's rigid motions; a floor of z-rollers leaves the
    translations along x and y and the rotation about z free."""
    X, _ = box_tet_mesh((2, 2, 2))
    n = np.arange(X.shape[0])
    planes = np.concatenate([3 * n[X[:, a] < EPS] + a for a in range(3)])
    assert free_rigid_modes(X, planes) == []
    floor = n[X[:, 2] < EPS]  # z-rollers on the floor: x, y and the spin about z are free
    free = free_rigid_modes(X, 3 * floor + 2)
    print(free)
    assert len(free) == 3 and sum(f.startswith("translation along") for f in free) == 2
    assert "rotation about an axis along z" in free
    line = n[(X[:, 0] < EPS) & (X[:, 1] < EPS)]  # z-rollers on a line along z: one holds
    assert len(free_rigid_modes(X, 3 * line + 2)) == 5
    held = Constraints.from_fixed_dofs(X, planes)
    assert held.partial and held.fixed_vertices.size == np.unique(planes // 3).size


@pytest.mark.parametrize(("lines", "key", "says"), [
    ('pins = [{ select = { lowest_y = {} }, dofs = "zz" }]', "bodies[0].pins[0].dofs",
     "dofs = 'zz'"),
    ('pins = [{ select = { lowest_y = {} }, dofs = "w" }]', "bodies[0].pins[0].dofs",
     "dofs = 'w'"),
    ("loads = [{ select = { vertices = [0] } }]", "bodies[0].loads[0]",
     "give exactly one of traction, pressure, force (got none)"),
    ("loads = [{ select = { vertices = [0] }, force = [1.0, 0.0, 0.0], pressure = 1.0 }]",
     "bodies[0].loads[0]", "(got pressure, force)"),
    ("loads = [{ select = { vertices = [0] }, force = [1.0, 0.0, 0.0], keyframes = "
     "[{ t = 1.0, scale = 1.0 }, { t = 0.5, scale = 0.0 }] }]", "bodies[0].loads[0]",
     "must be after"),
    ("loads = [{ select = { vertices = [0, 1] }, traction = [1.0, 0.0, 0.0] }]",
     "bodies[0].loads[0].select", "selects no whole boundary face"),
])
def test_bad_support_and_load_keys_are_one_line_errors(lines, key, says, tmp_path, capsys):
    """``fem3d run`` on a scene with a bad ``dofs`` or load: exit 2, one line naming the
    key and what is wrong."""
    from fem3d.app.cli import main

    X, T = box_tet_mesh((2, 1, 1))
    mesh = _scene(X, T, [face(0, 0.0)]).bodies[0].mesh
    pins = "" if lines.startswith("pins") else "pins = [{ select = { lowest_y = {} } }]\n"
    path = tmp_path / "s.toml"
    path.write_text(f'[[bodies]]\nmesh = "{mesh}"\nmaterial = {{ E = 1e5, nu = 0.3 }}\n'
                    f"{pins}{lines}\n")
    status = main(["run", str(path), "--steps", "1", "--out", str(tmp_path / "out"),
                   "--quiet", "--no-preview"])
    err = capsys.readouterr().err.strip()
    print(err)
    assert status == 2 and "\n" not in err and key in err and says in err
