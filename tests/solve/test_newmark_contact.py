"""Newmark with IPC contact: the dissipative member of the family (``gamma = 1/2 + alpha``,
``beta = gamma^2``, ``fem3d.solve.schemes.newmark.CONTACT_ALPHA``) keeps the bunny drop's energy
bounded, where average acceleration (``alpha = 0``) gains energy at every impact."""

from __future__ import annotations

import numpy as np
import pytest

import fem3d.solve.schemes.newmark as newmark_module
from fem3d.scene import load_scene
from fem3d.simulation import Simulation


def drop(steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Kinetic and total energy after each of ``steps`` steps of the bunny drop (newmark)."""
    # the drop undamped, as measured: the scheme's own energy behaviour, not the scene's damping
    sim = Simulation(load_scene("contact_bunny_drop", {
        "simulation.integrator": "newmark", "contact.self_contact": False,
        "bodies[0].damping.rayleigh_stiffness": 0.0}), scripted=True)
    kinetic, total = [], []
    for _ in range(steps):
        sim.step()
        e = sim.energies()
        kinetic.append(e["kinetic"])
        total.append(e["total"])
        assert sim.q[:, 1].min() > 0.0
    return np.array(kinetic), np.array(total)


def test_newmark_with_contact_does_not_gain_energy():
    """60 steps (landing at t ~ 0.25 s, then bounces on the ground with friction): total energy
    never above its start (~0) plus 5 % of the impact's kinetic energy (21.4 J), and the bunny
    is settling (kinetic energy at the end below a quarter of the impact's)."""
    kinetic, total = drop(60)
    k_max = kinetic.max()
    assert k_max > 20.0  # it has fallen and landed
    assert total.max() <= 0.05 * k_max, total.max()
    assert total[-1] < -10.0  # friction and the scheme's damping took energy out
    assert kinetic[-1] < 0.25 * k_max, kinetic[-1]


def test_average_acceleration_with_contact_gains_energy(monkeypatch):
    """Why the contact case is dissipative: with ``alpha = 0`` (the trapezoidal rule) the same
    drop gains energy (measured +12.5 J by step 50)."""
    monkeypatch.setattr(newmark_module, "CONTACT_ALPHA", 0.0)
    _, total = drop(50)
    assert total.max() > 2.0, total.max()


def test_newmark_without_contact_is_average_acceleration():
    """``gamma`` is 1/2 without a contact term (energy-conserving tests: test_time_integrators)."""
    assert newmark_module.newmark_gamma([]) == 0.5
    assert newmark_module.CONTACT_ALPHA == pytest.approx(0.05)
