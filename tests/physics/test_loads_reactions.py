"""Reactions (issue 43): ``reactions.csv`` holds the force each pin exerts per step; in a
static equilibrium they balance the applied loads (gravity + tractions + pressure + point
forces) to 1e-10; a resumed run continues the file.
"""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.app.run import run_scene
from fem3d.io.reactions import read_reactions_csv
from fem3d.mesh.tetmesh import box_tet_mesh
from fem3d.scene import scene_from_arrays
from fem3d.simulation import Simulation

CLAMP = {"select": {"box": [[-1, -1, -1], [1e-6, 1, 1]]}}
FLOOR = {"select": {"box": [[-1, -1e-6, -1], [2, 1e-6, 1]]}, "dofs": "y"}
TIP = {"box": [[1 - 1e-6, -1, -1], [2, 1, 1]]}
EVERYWHERE = {"box": [[-9, -9, -9], [9, 9, 9]]}


def _scene(integrator="static", steps=2, **extra):
    X, T = box_tet_mesh((8, 2, 2), (1.0, 0.2, 0.2))
    over = {"bodies[0].pins": [CLAMP, FLOOR],
            "bodies[0].loads": [
                {"select": TIP, "traction": [0.0, -2e3, 500.0]},
                {"select": EVERYWHERE, "pressure": 4e4,
                 "keyframes": [{"t": 0.0, "scale": 0.0}, {"t": 1.0, "scale": 1.0}]},
                {"select": {"vertices": [5]}, "force": [30.0, 0.0, 0.0]}],
            "bodies[0].material.E": 1e6, "simulation.gravity": [1.0, -9.81, 2.0],
            "simulation.integrator": integrator, "simulation.dt": 0.5,
            "simulation.steps": steps, "simulation.newton.tolerance": 1e-12,
            "pulls": []} | extra
    return scene_from_arrays(X, T, over, name="beam")


def test_reactions_balance_the_applied_loads_in_a_static_run():
    """Sum over the pins of the reaction = minus the sum of the applied loads, to 1e-10 of
    their size, at each static step (the pressure ramps, so the loads change per step)."""
    sim = Simulation(_scene())
    for _ in range(2):
        sim.step()
        R = sim.reactions()
        applied = sim.system.loads.applied_forces(sim.q.reshape(-1)).reshape(-1, 3)
        total = applied.sum(axis=0)
        print("reactions", R.sum(axis=0), "applied", total)
        assert np.abs(R.sum(axis=0) + total).max() < 1e-10 * np.abs(applied).sum(axis=0).max()
        assert R[1, 0] == 0.0 and R[1, 2] == 0.0  # the floor rollers hold y only
        assert abs(R[1, 1]) > 1.0  # and carry part of the load


def test_reactions_csv_of_a_run_and_its_resume(tmp_path):
    """``fem3d run``'s reactions.csv: a header naming each pin's components, one row per
    step equal to :meth:`Simulation.reactions`; a resume continues it row for row."""
    from fem3d.app.cli import main

    whole = run_scene(_scene("implicit", 6), tmp_path / "whole", checkpoint_every=3)
    assert whole.status == "ok"
    path = tmp_path / "whole" / "reactions.csv"
    header = path.read_text().splitlines()[0]
    assert header == ("step,t," + ",".join(f"bodies[0].pins[{k}].f{a}" for k in (0, 1)
                                           for a in "xyz"))
    rows = read_reactions_csv(path)
    assert rows.shape == (7, 8) and np.array_equal(rows[:, 0], np.arange(7))  # step 0 too
    sim = Simulation(_scene("implicit", 6))
    for _ in range(6):
        sim.step()
    assert np.array_equal(rows[-1, 2:], sim.reactions().reshape(-1))
    split = tmp_path / "split"
    assert run_scene(_scene("implicit", 3), split, checkpoint_every=3).status == "ok"
    assert main(["resume", str(split), "--steps", "6", "--quiet", "--no-preview"]) == 0
    assert np.array_equal(read_reactions_csv(split / "reactions.csv"), rows)


@pytest.mark.parametrize("integrator", ["implicit", "bdf2", "newmark"])
def test_dynamic_reactions_include_inertia(integrator):
    """The reactions plus the applied loads equal the rate of change of momentum ``sum M a``
    with ``a`` the scheme's own acceleration at the step's end (backward Euler's difference,
    BDF2's two-step difference, Newmark's ``a``), no damping here."""
    sim = Simulation(_scene(integrator, 3, **{"simulation.dt": 0.01, "bodies[0].pins": [CLAMP],
                                              "bodies[0].material.E": 1e4,
                                              "bodies[0].material.density": 1000.0}))
    history = [sim.v.copy()]
    for _ in range(3):
        sim.step()
        history.append(sim.v.copy())
    v2, v1, v0 = history[-1], history[-2], history[-3]
    a = {"implicit": lambda: (v2 - v1) / sim.dt,
         "bdf2": lambda: (3 * v2 - 4 * v1 + v0) / (2 * sim.dt),
         "newmark": lambda: sim.state.history["a"]}[integrator]().reshape(-1)
    momentum_rate = (sim.model.mass @ a).reshape(-1, 3).sum(axis=0)
    applied = sim.system.loads.applied_forces(sim.q.reshape(-1)).reshape(-1, 3)
    R = sim.reactions()
    print(integrator, R.sum(axis=0), applied.sum(axis=0), momentum_rate)
    assert np.abs(momentum_rate).max() > 1.0  # the pins' reactions are not static ones
    assert np.abs(R.sum(axis=0) + applied.sum(axis=0) - momentum_rate).max() < \
        1e-8 * np.abs(applied).sum(axis=0).max()
