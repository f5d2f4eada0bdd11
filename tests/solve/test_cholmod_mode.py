"""``simulation.cholmod``: CHOLMOD's factorization chosen by the pattern or forced per scene."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.errors import InputError
from fem3d.scene import apply_overrides, load_scene
from fem3d.simulation import Simulation

pytest.importorskip("sksparse")


def _run(mode: str, steps: int = 5) -> tuple[Simulation, np.ndarray]:
    sim = Simulation(apply_overrides(load_scene("arma"), {"simulation.cholmod": mode,
                                                          "simulation.linear_solver": "cholmod"}),
                     scripted=True)
    for _ in range(steps):
        sim.step()
    return sim, sim.q.copy()


def test_the_mode_reaches_the_factorization_and_solves_the_same_steps():
    auto, q_auto = _run("auto")
    forced, q_forced = _run("supernodal")
    assert auto.system._solver.cholmod_mode == "simplicial"  # the armadillo's factor is cheap
    assert forced.system._solver.cholmod_mode == "supernodal"
    moved = np.abs(q_auto - auto.model.X).max()
    assert moved > 1e-3  # the pull moved the hand
    np.testing.assert_allclose(q_forced, q_auto, rtol=0, atol=1e-9 * moved)


@pytest.mark.parametrize("overrides, message", [
    ({"simulation.cholmod": "fast"}, "simulation.cholmod: Input should be 'auto', "
                                     "'simplicial' or 'supernodal'"),
    ({"simulation.cholmod": "simplicial", "simulation.linear_solver": "amg"},
     "simulation: cholmod = 'simplicial' applies to linear_solver = 'cholmod' (or 'auto'), "
     "not 'amg'"),
])
def test_a_bad_mode_is_one_line_naming_the_key(overrides, message):
    with pytest.raises(InputError) as err:
        apply_overrides(load_scene("bunny"), overrides)
    assert message in str(err.value) and "\n" not in str(err.value)
