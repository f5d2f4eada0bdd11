"""``simulation.newton``'s ``max_iterations`` and ``tolerance`` per scheme (issue 43): the
schema documents what each registered scheme does with them, and the one scheme that solves
no Newton system (``linear``) is unaffected by them. That ``implicit``, ``bdf2``, ``newmark``
and ``static`` honour them is tests/solve/test_static_load_stepping.py's
``test_scene_newton_tolerance_and_cap_reach_every_scheme``.
"""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.mesh.tetmesh import box_tet_mesh
from fem3d.scene import scene_from_arrays
from fem3d.scene.spec import scene_schema
from fem3d.simulation import Simulation
from fem3d.solve.schemes.registry import SCHEMES

CLAMP = {"select": {"box": [[-1, -1, -1], [1e-6, 1, 1]]}}


@pytest.mark.parametrize("key", ["max_iterations", "tolerance"])
def test_the_schema_says_what_every_scheme_does_with_the_key(key):
    newton = scene_schema()["$defs"]["NewtonSpec"]
    text = newton["properties"][key]["description"] + " " + newton["description"]
    for name in SCHEMES:
        assert name in text, f"simulation.newton.{key}'s description does not name {name!r}"


def test_linear_scheme_is_unaffected_by_the_newton_keys():
    """One linear solve per step: a loose tolerance and a cap of 1 give the same trajectory,
    bit for bit, as the defaults (the keys are documented as not used by ``linear``)."""
    X, T = box_tet_mesh((6, 2, 2), (1.0, 0.2, 0.2))

    def run(**newton):
        sim = Simulation(scene_from_arrays(X, T, {
            "bodies[0].pins": [CLAMP], "bodies[0].material.E": 1e5, "pulls": [],
            "simulation.integrator": "linear", "simulation.gravity": [0.0, -9.81, 0.0],
            **{f"simulation.newton.{k}": v for k, v in newton.items()}}))
        for _ in range(3):
            sim.step()
        return sim.q.copy(), sim.v.copy()

    q0, v0 = run()
    q1, v1 = run(tolerance=0.5, max_iterations=1)
    assert np.array_equal(q0, q1) and np.array_equal(v0, v1)
    assert np.abs(q0 - X).max() > 1e-6  # it moved
