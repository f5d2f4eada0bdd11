"""What ``reactions.csv`` reports in a damped dynamic run (docs/loads.md "Reactions"): the
pins' forces hold the inertia of the held DOFs but not Rayleigh damping's force, so the
reactions plus the applied loads equal the rate of change of momentum plus the damping force
on the free DOFs, not the applied loads (those balance only at equilibrium).
"""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.simulation import Simulation
from tests.physics.test_loads_reactions import CLAMP, _scene


@pytest.mark.parametrize("integrator", ["implicit", "bdf2", "newmark"])
def test_damped_reactions_leave_out_the_damping_force(integrator):
    sim = Simulation(_scene(integrator, 3, **{
        "simulation.dt": 0.01, "bodies[0].pins": [CLAMP], "bodies[0].material.E": 1e4,
        "bodies[0].material.density": 1000.0, "bodies[0].damping.rayleigh_mass": 2.0,
        "bodies[0].damping.rayleigh_stiffness": 0.01}))
    history = [sim.v.copy()]
    for _ in range(3):
        sim.step()
        history.append(sim.v.copy())
    v2, v1, v0 = history[-1], history[-2], history[-3]
    a = {"implicit": lambda: (v2 - v1) / sim.dt,
         "bdf2": lambda: (3 * v2 - 4 * v1 + v0) / (2 * sim.dt),
         "newmark": lambda: sim.state.history["a"]}[integrator]().reshape(-1)
    momentum_rate = (sim.model.mass @ a).reshape(-1, 3).sum(axis=0)
    applied = sim.system.loads.applied_forces(sim.q.reshape(-1)).reshape(-1, 3).sum(axis=0)
    damping = sim.system.loads.damping._D @ sim.v.reshape(-1)  # D v, D lagged at the step
    free = np.ones(damping.size, dtype=bool)
    for _, dofs in sim.pin_groups:
        free[dofs] = False
    damping_free = np.zeros(3)
    np.add.at(damping_free, np.flatnonzero(free) % 3, damping[free])
    R = sim.reactions().sum(axis=0)
    scale = np.abs(applied).max()
    assert np.abs(damping_free).max() > 0.01 * scale  # the damping force is not negligible
    assert np.abs(R + applied - momentum_rate - damping_free).max() < 1e-8 * scale
    assert np.abs(R + applied - momentum_rate).max() > 0.01 * scale
