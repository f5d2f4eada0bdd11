"""Surface and point loads (issue 43): dead tractions and point forces, the follower
pressure's generated kernels (against finite differences and the consistent load), static
load stepping with each load and all together, the dynamic schemes and the adjoint.
"""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.errors import InputError
from fem3d.kernels.dispatch import kernel_module
from fem3d.mesh.tetmesh import boundary_faces, box_tet_mesh
from fem3d.physics.model import build_model
from fem3d.physics.terms.surface import FollowerPressure, traction_forces
from fem3d.scene import scene_from_arrays
from fem3d.simulation import Simulation

BACKENDS = ["numpy", pytest.param("c", marks=pytest.mark.skipif(
    not hasattr(kernel_module("pressure", "numpy"), "energy"), reason="no C build"))]
CLAMP = {"select": {"box": [[-1, -1, -1], [1e-6, 1, 1]]}}
TIP = {"box": [[1 - 1e-6, -1, -1], [2, 1, 1]]}
EVERYWHERE = {"box": [[-9, -9, -9], [9, 9, 9]]}
RAMP = [{"t": 0.0, "scale": 0.0}, {"t": 1.0, "scale": 1.0}]


@pytest.mark.parametrize("backend", BACKENDS)
def test_pressure_kernels_match_differences(backend):
    """The generated gradient and Hessian of ``p/6 x0.(x1 x x2)`` against central
    differences of the generated energy and gradient; the Hessian symmetric."""
    k = kernel_module("pressure", backend)
    rng = np.random.default_rng(3)
    x = rng.normal(size=(5, 3, 3))
    p = (2.5,)
    g = k.gradient(x, p).reshape(5, 9)
    H = k.hessian(x, p).reshape(5, 9, 9)
    h = 1e-6
    for i in range(9):
        d = np.zeros(9)
        d[i] = h
        plus, minus = x + d.reshape(3, 3), x - d.reshape(3, 3)
        fd = (k.energy(plus, p) - k.energy(minus, p)) / (2 * h)
        assert np.abs(fd - g[:, i]).max() < 1e-8 * (1 + np.abs(g).max())
        fd_g = (k.gradient(plus, p) - k.gradient(minus, p)).reshape(5, 9) / (2 * h)
        assert np.abs(fd_g - H[:, :, i]).max() < 1e-7 * (1 + np.abs(H).max())
    assert np.array_equal(H, H.transpose(0, 2, 1))
    assert np.allclose(k.energy(x, p), p[0] / 6 * np.einsum(
        "mi,mi->m", x[:, 0], np.cross(x[:, 1], x[:, 2])), rtol=1e-13, atol=1e-14)


def test_pressure_on_a_closed_surface_is_the_consistent_follower_load():
    """On a body's whole boundary the potential's force is ``-p/3`` of the area-weighted
    normals at each vertex (no edge terms), it sums to zero, and the energy is ``p`` times
    the change of the body's volume, at a deformed state too."""
    X, T = box_tet_mesh((3, 2, 2), (1.0, 0.5, 0.5))
    model = build_model(X, T, E=1e5, nu=0.3, rho=1000.0)
    term = FollowerPressure(model, boundary_faces(T), 7.0)
    assert np.abs(term.edge_forces()).max() < 1e-12
    rng = np.random.default_rng(0)
    q = (X + 0.02 * rng.normal(size=X.shape)).reshape(-1)
    f = -term.gradient(q).reshape(-1, 3)
    x = q.reshape(-1, 3)[term.faces]
    an = 0.5 * np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    expected = np.zeros_like(X)
    np.add.at(expected, term.faces.reshape(-1), np.repeat(-7.0 / 3.0 * an, 3, axis=0))
    assert np.abs(f - expected).max() < 1e-12 * np.abs(expected).max()
    assert np.abs(f.sum(axis=0)).max() < 1e-12
    xt = q.reshape(-1, 3)[T]
    volume = np.einsum("mi,mi->m", xt[:, 1] - xt[:, 0], np.cross(xt[:, 2] - xt[:, 0],
                                                                  xt[:, 3] - xt[:, 0])).sum() / 6
    assert term.energy(q) == pytest.approx(7.0 * (volume - 0.25), rel=1e-12)


def test_dead_loads_total_what_the_scene_says():
    """A traction on the tip face totals traction x area; a point force totals itself."""
    X, T = box_tet_mesh((4, 2, 2), (1.0, 0.2, 0.3))
    tip = np.flatnonzero(np.abs(X[:, 0] - 1.0) < 1e-9)
    faces = boundary_faces(T)
    mine = faces[np.isin(faces, tip).all(axis=1)]
    f = traction_forces(X, mine, [1.0, -2.0, 3.0]).reshape(-1, 3)
    assert np.allclose(f.sum(axis=0), np.array([1.0, -2.0, 3.0]) * 0.06, rtol=1e-13)
    assert np.all(f[np.setdiff1d(np.arange(len(X)), tip)] == 0.0)
    sim = _sim(X, T, [{"select": TIP, "force": [0.0, -5.0, 0.0]},
                      {"select": TIP, "traction": [0.0, 0.0, 10.0]}])
    total = sim.system.loads.applied_forces(sim.q.reshape(-1)).reshape(-1, 3).sum(axis=0)
    assert np.allclose(total, [0.0, -5.0, 0.6], rtol=1e-13)


def _sim(X, T, loads, integrator="static", steps=1, pins=(CLAMP,), **extra):
    over = {"bodies[0].pins": list(pins), "bodies[0].loads": loads,
            "bodies[0].material.E": 1e6, "bodies[0].material.nu": 0.3,
            "simulation.integrator": integrator, "simulation.dt": 1.0 / steps,
            "simulation.steps": steps, "pulls": []} | extra
    return Simulation(scene_from_arrays(X, T, over, name="beam"))


def _run(sim):
    for _ in range(sim.scene.simulation.n_steps):
        sim.step()
    return sim


MOVE = {"select": {"box": [[1 - 1e-6, -1, -1], [2, 1, 1]]},
        "motion": {"keyframes": [{"t": 0.0}, {"t": 1.0, "translate": [-0.05, 0.0, 0.1]}]}}


@pytest.mark.parametrize("case", ["traction", "force", "pressure", "together"])
def test_static_load_stepping_with_each_load(case):
    """A load ramped 0 -> 1 over a second: one static step (Newton cannot take it at once,
    so the load path is taken in increments) ends where eight steps do, to Newton's
    tolerance. ``together``: gravity, traction, pressure and moved pins at once."""
    X, T = box_tet_mesh((12, 3, 3), (1.0, 0.2, 0.2))
    loads = {"traction": [{"select": TIP, "traction": [0.0, -1.5e4, 0.0], "keyframes": RAMP}],
             "force": [{"select": TIP, "force": [0.0, 0.0, 600.0], "keyframes": RAMP}],
             "pressure": [{"select": EVERYWHERE, "pressure": 2e5, "keyframes": RAMP}]}
    pins, extra = [CLAMP], {}
    if case == "together":
        loads["together"] = [*loads["traction"], *loads["pressure"]]
        pins = [CLAMP, {**MOVE, "dofs": "xz"}]
        extra = {"simulation.gravity": [0.0, -9.81, 0.0]}
    one = _run(_sim(X, T, loads[case], pins=pins, **extra))
    eight = _run(_sim(X, T, loads[case], steps=8, pins=pins, **extra))
    moved = np.abs(eight.q - X).max()
    err = np.abs(one.q - eight.q).max()
    print(case, "increments", one.last_stats.load_increments, "moved", moved, "err", err)
    assert one.last_stats.load_increments > 1
    assert moved > 0.02 and err < 1e-9 * moved


def test_pressure_on_an_open_patch_with_free_edges_is_refused():
    X, T = box_tet_mesh((4, 2, 2), (1.0, 0.2, 0.2))
    top = {"box": [[-1, 0.2 - 1e-6, -1], [2, 1, 1]]}
    with pytest.raises(InputError, match=r"loads\[0\]\.select: a follower pressure needs"):
        _sim(X, T, [{"select": top, "pressure": 1.0}])
    with pytest.raises(InputError, match="selects no whole boundary face"):
        _sim(X, T, [{"select": {"vertices": [0, 1]}, "traction": [1.0, 0.0, 0.0]}])


@pytest.mark.parametrize("integrator", ["implicit", "bdf2", "newmark"])
def test_dynamic_schemes_carry_the_loads(integrator):
    """A tip force switched on at t = 0 swings the beam toward the static answer's side;
    the applied forces follow the keyframes."""
    X, T = box_tet_mesh((6, 2, 2), (1.0, 0.2, 0.2))
    sim = _sim(X, T, [{"select": TIP, "force": [0.0, -400.0, 0.0],
                       "keyframes": [{"t": 0.0, "scale": 0.0}, {"t": 0.05, "scale": 1.0}]}],
               integrator, steps=10, **{"simulation.dt": 0.01})
    sim.step()
    sim.step()  # the step to t = 0.02 applied 0.4 of the force
    f = sim.system.loads.applied_forces(sim.q.reshape(-1)).reshape(-1, 3)
    assert f[:, 1].sum() == pytest.approx(-160.0, rel=1e-13)
    for _ in range(8):
        sim.step()
    tip = np.abs(X[:, 0] - 1.0) < 1e-9
    assert (sim.q - X)[tip, 1].mean() < -1e-3
    f = sim.system.loads.applied_forces(sim.q.reshape(-1)).reshape(-1, 3)
    assert f[:, 1].sum() == pytest.approx(-400.0, rel=1e-13)


def test_adjoint_sees_the_pressure():
    """dL/dE of a short backward-Euler run under a keyframed pressure (closed surface) and
    a tip traction: the adjoint (with the pressure's Hessian) against central differences."""
    from fem3d.diff import PositionLoss, simulate, trajectory_gradient
    from fem3d.scene import apply_overrides

    X, T = box_tet_mesh((3, 1, 1), (1.0, 0.25, 0.25))
    scene = _sim(X, T, [{"select": EVERYWHERE, "pressure": 3e4, "keyframes": RAMP},
                        {"select": TIP, "traction": [0.0, -2e3, 0.0]}], "implicit",
                 **{"simulation.dt": 0.02, "simulation.steps": 4,
                    "bodies[0].material.E": 1e5}).scene
    rng = np.random.default_rng(1)
    qs = simulate(scene, 4)
    loss = PositionLoss({n: qs[n] + 1e-3 * rng.normal(size=qs[n].shape) for n in (2, 4)})
    _, grads = trajectory_gradient(scene, loss, ["bodies[0].material.E"])

    def total(E):
        q = simulate(apply_overrides(scene, {"bodies[0].material.E": E}), 4)
        return sum(loss.frame(n, q[n])[0] for n in loss.targets)
    h = 1e-5 * 1e5
    fd = (total(1e5 + h) - total(1e5 - h)) / (2 * h)
    print("adjoint", grads["bodies[0].material.E"], "differences", fd)
    assert abs(grads["bodies[0].material.E"] - fd) < 1e-5 * abs(fd)
