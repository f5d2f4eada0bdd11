"""Adding a scheme is one class and one registration: the implicit midpoint rule, defined and
registered here alone, runs through ``Simulation``, ``fem3d run`` and the registry's readers
(schema, CLI, viewer cycle) and has the physics it should (docs/architecture.md, "Adding a
scheme").
"""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.physics.assembly import kinetic_energy, potential_energy
from fem3d.physics.constraints import Constraints
from fem3d.physics.model import build_model
from fem3d.scene import scene_from_arrays
from fem3d.scene.spec import scene_schema
from fem3d.simulation import Simulation
from fem3d.solve.schemes.base import Scheme, Step
from fem3d.solve.schemes.registry import SCHEMES, dynamic_scheme_names, register_scheme
from fem3d.solve.state import State
from fem3d.solve.step_maps import affine_step_map, end_positions, fixed_dofs
from fem3d.solve.system import System
from tests.physics.test_assembly import box_mesh


# ---------------------------------------------------------------- the toy scheme: one class
class Midpoint(Scheme):
    """Implicit midpoint: ``q+ = q + dt y``, ``v+ = 2 y - v``, ``M (y - v) = dt/2 f(q + dt/2
    y)``: the minimiser ``y`` (the step's mean velocity) of backward Euler's objective with
    ``h = dt / 2``, ``q_base = q``, ``v_hat = v``. Symplectic, second order, no numerical
    damping: a linear vibration keeps its energy exactly. Pins sit at their end positions
    through the step (exact for pins that stay)."""

    name = "midpoint"
    label = "implicit midpoint"

    def prepare(self, system, terms, state, dt, fixed_positions, settings):
        p = end_positions(system, state, fixed_positions)
        step = affine_step_map(system, state, dt, p, h=0.5 * dt, offset=None,
                               v_hat=state.v.reshape(-1), moving_pins=False)
        return Step(step, data={"p": p})

    def finish(self, system, state, step, x, settings):
        q = 2.0 * step.map.positions(x) - state.q.reshape(-1)
        v = 2.0 * step.map.velocity(x) - state.v.reshape(-1)
        fd, p = fixed_dofs(system), step.data["p"].reshape(-1)
        q[fd], v[fd] = p, (p - state.q.reshape(-1)[fd]) / step.map.dt
        return State(q=q.reshape(-1, 3), v=v.reshape(-1, 3), t=state.t + step.map.dt,
                     step=state.step + 1)


# ------------------------------------------------------------------------------ the tests
@pytest.fixture
def midpoint():
    """The toy scheme registered (the one line a new scheme adds) for one test."""
    scheme = register_scheme(Midpoint())
    yield scheme
    del SCHEMES[scheme.name]


def _bar_scene(integrator: str, material: str = "linear"):
    X, T = box_mesh(3, 1, 1, size=(1.0, 0.25, 0.25))
    return scene_from_arrays(X, T, {
        "bodies[0].material.model": material, "bodies[0].material.E": 1e4,
        "bodies[0].material.density": 1000.0,
        "bodies[0].pins": [{"select": {"box": [[-1, -1, -1], [1e-6, 1, 1]]}}],
        "simulation.integrator": integrator, "simulation.dt": 0.01}, name="bar")


def _swing(sim: Simulation, amplitude: float) -> None:
    """The bar at rest, its velocity ``amplitude x^2`` across it (pins at rest)."""
    v = np.zeros_like(sim.q)
    v[:, 1] = amplitude * sim.model.X[:, 0] ** 2
    v[sim.fixed_vertices] = 0.0
    sim.set_state(sim.model.X, v)


def _energy(sim: Simulation) -> float:
    return kinetic_energy(sim.model, sim.v) + potential_energy(sim.model, sim.q)


def test_the_registered_scheme_keeps_a_linear_vibrations_energy_in_a_simulation(midpoint):
    """Through ``Simulation`` (a scene naming it): kinetic + strain energy of a linear
    vibration constant to 1e-9 over 300 steps; backward Euler on the same scene loses more
    than 5 % of it."""
    energies = {}
    for name in ("midpoint", "implicit"):
        sim = Simulation(_bar_scene(name))
        _swing(sim, 0.01)
        e0, e = _energy(sim), []
        for _ in range(300):
            sim.step()
            e.append(_energy(sim) / e0)
        energies[name] = np.array(e)
    assert Simulation(_bar_scene("midpoint")).scheme is midpoint
    print("midpoint", np.abs(energies["midpoint"] - 1).max(), "implicit",
          energies["implicit"][-1])
    assert np.abs(energies["midpoint"] - 1.0).max() < 1e-9
    assert energies["implicit"][-1] < 0.95


def test_the_registered_scheme_is_second_order(midpoint):
    """Tip position at t = 0.2 s of a Neo-Hookean swing against the scheme at dt/16, for
    dt = 0.01, 0.005, 0.0025: error slopes 2 +- 0.2 (backward Euler's are 1)."""
    X, T = box_mesh(4, 1, 1, size=(1.0, 0.25, 0.25))
    model = build_model(X, T, E=1e4, nu=0.3, rho=1000.0, material="neo_hookean")
    fixed = np.flatnonzero(X[:, 0] <= 1e-12)
    system = System(model, Constraints.from_fixed_vertices(X, fixed))
    v = np.zeros_like(X)
    v[:, 1] = 0.5 * X[:, 0] ** 2
    v[fixed] = 0.0
    tip = X[:, 0] > 1 - 1e-9

    def run(dt: float, n: int) -> np.ndarray:
        state = State(q=X.copy(), v=v)
        for _ in range(n):
            state, _ = midpoint.model_step(system, state, dt, max_iterations=None, rtol=1e-12)
        return state.q

    ref = run(0.01 / 16, 320)
    errs = [np.abs((run(0.01 / k, 20 * k) - ref)[tip].mean(axis=0)).max() for k in (1, 2, 4)]
    slopes = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    print("midpoint errors", errs, "slopes", slopes)
    assert np.all(np.abs(slopes - 2.0) < 0.2), slopes


def test_the_registry_readers_see_it_and_fem3d_run_runs_it(midpoint, tmp_path, capsys):
    """The schema's enum, ``--integrator``'s help, the viewer's N cycle and ``fem3d run``
    (then ``fem3d resume``) take the scheme by its name."""
    from fem3d.app.cli import main

    enum = scene_schema()["$defs"]["SimulationSpec"]["properties"]["integrator"]["enum"]
    assert "midpoint" in enum and "bdf2" in enum
    assert "midpoint" in dynamic_scheme_names()
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    assert "midpoint" in capsys.readouterr().out
    out = tmp_path / "run"
    assert main(["run", "bunny", "--integrator", "midpoint", "--steps", "3", "--out", str(out),
                 "--no-preview", "--quiet", "--checkpoint-every", "2"]) == 0
    rows = (out / "energy.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + 4  # header, t = 0 and three steps
    assert main(["resume", str(out), "--steps", "4", "--quiet"]) == 0
    assert len((out / "energy.csv").read_text().strip().splitlines()) == 1 + 5
    capsys.readouterr()
    assert main(["run", "bunny", "--integrator", "midpoint2", "--steps", "1",
                 "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "midpoint" in err and "\n" not in err.strip()
