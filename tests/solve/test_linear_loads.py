"""The linearly-implicit scheme applies the bodies' surface and point loads (tractions, point
forces, follower pressures) like the implicit schemes: before, it left them out silently."""

from __future__ import annotations

import numpy as np

from fem3d.scene import apply_overrides, load_scene
from fem3d.simulation import Simulation
from tests.parallel.helpers import relative_difference, write_scene
from tests.parallel.test_mpi_loads import LOADS


def _run(scene, integrator: str, dt: float, duration: float) -> Simulation:
    sim = Simulation(apply_overrides(scene, {"simulation.integrator": integrator,
                                             "simulation.dt": dt}))
    for _ in range(int(round(duration / dt))):
        sim.step()
    return sim


def test_linear_material_under_a_traction_is_backward_euler():
    """Cook's membrane (a linear material, a shear traction on its edge): the elastic force
    is linear, so one linearly-implicit step is one backward Euler step, loads included."""
    scene = load_scene("cook_membrane")
    lin, imp = (_run(scene, name, scene.simulation.dt, 3 * scene.simulation.dt)
                for name in ("linear", "implicit"))
    motion = np.abs(imp.q - imp.model.X).max()
    assert motion > 0.1  # the traction moves it (0.29 after 3 steps)
    assert relative_difference(lin.q, imp.q, imp.model.X) <= 1e-9


def test_loads_converge_to_backward_euler_as_dt_shrinks(tmp_path):
    """The two-material box, each bar with a traction, a ramped follower pressure and a
    point force, over 0.1 s: the linearly-implicit run approaches the backward-Euler run as
    dt shrinks (1.4e-3 of the motion at dt = 0.01, 9.2e-5 at 0.0025; measured), where
    leaving the loads out would miss most of the motion."""
    path = write_scene(tmp_path, steps=10)
    first, second = path.read_text().rsplit("\n[[bodies]]\n", 1)
    path.write_text(first + LOADS + "\n[[bodies]]\n" + second + LOADS)
    scene = load_scene(str(path))
    diffs = []
    for dt in (0.01, 0.0025):
        lin, imp = (_run(scene, name, dt, 0.1) for name in ("linear", "implicit"))
        diffs.append(relative_difference(lin.q, imp.q, imp.model.X))
    print(f"linear vs implicit with loads: {diffs[0]:.2e} (dt 0.01), {diffs[1]:.2e} (0.0025)")
    assert diffs[0] <= 5e-3 and diffs[1] <= diffs[0] / 8
