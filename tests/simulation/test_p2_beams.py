"""The P1-vs-P2 gallery pair (data/scenes/beam_p1.toml, beam_p2.toml): the same beam with
the same nodes, linear tets against quadratic ones. At equal DOFs the P2 beam sags to within
a few percent of the converged answer; the P1 beam locks and sags about half as far (the
figures of docs/elements.md, ``python scripts/p2_gallery.py --figures``)."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.scene import load_scene
from fem3d.simulation import Simulation

#: Static tip deflection of the beam (m): Richardson extrapolation of P2 at 10 x 1 x 1,
#: 20 x 2 x 2 and 40 x 4 x 4 cells (``python scripts/p2_gallery.py --figures``).
CONVERGED_TIP = 0.14491


def _tip(sim: Simulation) -> float:
    X, q = sim.model.X, np.asarray(sim.q)
    tip = np.flatnonzero(np.isclose(X[:, 0], X[:, 0].max()))
    return float(-(q[tip, 1] - X[tip, 1]).mean())


def _static_tip(name: str) -> tuple[Simulation, float]:
    sim = Simulation(load_scene(name, {"simulation.integrator": "static",
                                       "simulation.steps": 1}))
    sim.step()
    return sim, _tip(sim)


def test_p2_beam_sags_to_the_converged_answer_where_p1_locks_at_equal_dofs():
    p1, tip1 = _static_tip("beam_p1")
    p2, tip2 = _static_tip("beam_p2")
    assert (p1.model.element.name, p2.model.element.name) == ("p1", "p2")
    assert p1.model.n_dofs == p2.model.n_dofs == 567  # the same 189 nodes
    assert (p1.model.n_tets, p2.model.n_tets) == (480, 60)
    assert tip2 == pytest.approx(CONVERGED_TIP, rel=0.03)  # 0.978 measured
    assert tip1 < 0.55 * CONVERGED_TIP  # 0.513 measured: linear tets lock in bending
    # side by side, apart: the P2 beam 0.5 m behind the P1 beam (0.4 m between their faces)
    gap = p2.model.X[:, 2].min() - p1.model.X[:, 2].max()
    assert gap == pytest.approx(0.4)


@pytest.mark.parametrize("name", ["beam_p1", "beam_p2"])
def test_gallery_beam_settles_near_its_static_tip(name):
    """The gallery run (backward Euler, mass damping) ends where the static solve is: within
    1 % at t = 2 s (0.07436 against 0.07436 m for P1, 0.14134 against 0.14177 for P2)."""
    scene = load_scene(name)
    sim = Simulation(scene)
    for _ in range(scene.n_steps):
        sim.step()
    _, static = _static_tip(name)
    assert np.isfinite(sim.q).all()
    assert _tip(sim) == pytest.approx(static, rel=0.01)
