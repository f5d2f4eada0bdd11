"""Static load stepping (issue 43): moved pins ramped with their forces, the Newton cap and
the gradient tolerance of ``[simulation.newton]`` honoured by ``static``.

Each case is a 1.0 x 0.2 x 0.2 beam (Neo-Hookean), clamped at ``x = 0``; one to eight
static steps, under a second each.
"""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.errors import SimulationError
from fem3d.mesh.tetmesh import box_tet_mesh
from fem3d.physics.constraints import Constraints
from fem3d.physics.model import build_model
from fem3d.scene import scene_from_arrays
from fem3d.scene.build import build_loads
from fem3d.simulation import Simulation
from fem3d.solve.integrators import State, System, model_terms
from fem3d.solve.settings import NewtonSettings
from fem3d.solve.static import static

CLAMP = {"select": {"box": [[-1, -1, -1], [1e-6, 1, 1]]}}


def moving_beam(move, steps, cells=(20, 4, 4), **extra):
    """The beam with its ``x = 1`` face moved by ``move`` over one second of static steps."""
    X, T = box_tet_mesh(cells, (1.0, 0.2, 0.2))
    far = {"select": {"box": [[1 - 1e-6, -1, -1], [2, 1, 1]]},
           "motion": {"keyframes": [{"t": 0.0}, {"t": 1.0, "translate": list(move)}]}}
    over = {"bodies[0].pins": [CLAMP, far], "simulation.integrator": "static",
            "simulation.dt": 1.0 / steps, "simulation.steps": steps, "pulls": []} | extra
    return scene_from_arrays(X, T, over, name="beam")


def run_static(scene):
    sim = Simulation(scene)
    for _ in range(scene.simulation.n_steps):
        sim.step()
    return sim


@pytest.mark.parametrize(("move", "material"), [
    ((-0.05, 0.08, -0.25), {"bodies[0].material.E": 1e6, "bodies[0].material.nu": 0.3,
                            "simulation.gravity": [0.0, -9.81, 0.0]}),
    ((-0.1, 0.0, 0.0), {"bodies[0].material.E": None, "bodies[0].material.nu": None,
                        "bodies[0].material.params": {"C": 1e5, "D": 2.5e5}}),
])
def test_moved_pins_in_one_static_step_equal_eight(move, material):
    """The issue's cases: one static step (Newton fails on the whole step, so the load path
    is taken in increments) ends where eight steps of 1/8 do, to Newton's tolerance."""
    one = run_static(moving_beam(move, 1, **material))
    eight = run_static(moving_beam(move, 8, **material))
    assert one.last_stats.load_increments > 1  # the load-stepping path was taken
    err = np.abs(one.q - eight.q).max()
    print("load increments", one.last_stats.load_increments, "max |one - eight|", err)
    assert err < 1e-9 * np.linalg.norm(move)


#: Newton to convergence in each increment (no cap of a scene's: the scheme's 50)
TO_CONVERGENCE = NewtonSettings(max_iterations=None)


def _beam_system(g, E=1e7):
    X, T = box_tet_mesh((20, 4, 4), (1.0, 0.2, 0.2))
    model = build_model(X, T, E=E, nu=0.3, rho=1000.0)
    c = Constraints.from_fixed_vertices(X, np.flatnonzero(X[:, 0] <= 1e-12))
    system = System(model, c, loads=build_loads(model, gravity=[0.0, -g, 0.0]))
    return model, system


def test_gravity_ramp_equals_the_whole_load():
    """Gravity applied in increments (the default Newton cap of 5 is too few for the whole load)
    ends at the equilibrium a solve to convergence finds in one increment; every increment
    honours the cap."""
    model, system = _beam_system(9.81, E=1e6)
    whole, st_whole = static(system, model_terms(system), State.at_rest(model), 1.0,
                             TO_CONVERGENCE)
    ramped, st = static(system, model_terms(system), State.at_rest(model), 1.0,
                        NewtonSettings(max_iterations=5))
    print("increments", st.load_increments, "iterations", st.newton_iterations,
          "whole", st_whole.newton_iterations)
    assert st_whole.load_increments == 1 and st_whole.newton_iterations > 5
    assert st.load_increments > 1
    assert st.newton_iterations <= 5 * st.load_increments
    tip = np.abs(whole.q - model.X).max()
    assert np.abs(ramped.q - whole.q).max() < 1e-9 * tip


def test_tiny_load_converges_relative_to_itself():
    """A 3e-7 m tip deflection: the absolute floor (near round-off) no longer stops Newton
    after one step; the answer is that of a solve to round-off (atol 0) to 1e-9."""
    model, system = _beam_system(1e-4)
    default, st = static(system, model_terms(system), State.at_rest(model), 1.0,
                         TO_CONVERGENCE)
    tight, _ = static(system, model_terms(system), State.at_rest(model), 1.0,
                      TO_CONVERGENCE, atol_factor=0.0)
    tip = np.abs(tight.q - model.X).max()
    err = np.abs(default.q - tight.q).max() / tip
    print("tip", tip, "relative error", err, "iterations", st.newton_iterations)
    assert tip < 1e-6 and err < 1e-9


@pytest.mark.parametrize("integrator", ["implicit", "bdf2", "newmark", "static"])
def test_scene_newton_tolerance_and_cap_reach_every_scheme(integrator):
    """``simulation.newton.tolerance`` sets the gradient tolerance of each implicit scheme
    (relative to the first gradient), ``max_iterations`` caps its Newton iterations (static:
    per load increment)."""
    X, T = box_tet_mesh((6, 2, 2), (1.0, 0.2, 0.2))

    def first_step(**newton):
        scene = scene_from_arrays(X, T, {
            "bodies[0].pins": [CLAMP], "bodies[0].material.E": 1e5,
            "simulation.integrator": integrator, "simulation.gravity": [0.0, -9.81, 0.0],
            **{f"simulation.newton.{k}": v for k, v in newton.items()}})
        sim = Simulation(scene)
        sim.step()
        return sim.last_stats

    loose = first_step(tolerance=0.1, max_iterations=30)
    tight = first_step(tolerance=1e-12, max_iterations=30)
    print(integrator, loose.gradient_norms, tight.gradient_norms)
    assert loose.gradient_tolerance == pytest.approx(0.1 * loose.gradient_norms[0])
    assert loose.converged and tight.converged
    assert tight.gradient_norms[-1] < 1e-3 * loose.gradient_norms[-1]
    assert loose.gradient_norms[-1] <= loose.gradient_tolerance
    assert tight.newton_iterations > loose.newton_iterations
    if integrator == "static":  # one iteration per increment never reaches 1e-12
        with pytest.raises(SimulationError, match="no equilibrium"):
            first_step(tolerance=1e-12, max_iterations=1)
    else:  # the dynamic schemes keep the capped iterate
        capped = first_step(tolerance=1e-12, max_iterations=1)
        assert capped.newton_iterations == 1 < tight.newton_iterations
        assert not capped.converged
