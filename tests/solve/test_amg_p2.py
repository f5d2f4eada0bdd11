"""AMG on quadratic (P2) bodies: the near-nullspace is the rigid-body modes of every free
node's rest position (corner and edge nodes), exact for the P2 stiffness, and AMG-PCG steps
the P2 cantilever to the same positions as the direct solver."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fem3d.mesh.formats import write_tet_mesh
from fem3d.mesh.tetmesh import TetMesh
from fem3d.physics.assembly import hessian_data
from fem3d.scene import load_scene
from fem3d.simulation import Simulation
from fem3d.solve.linear.amg import rigid_body_modes
from tests.physics.test_assembly import box_mesh


def p2_beam(folder: Path, solver: str) -> Simulation:
    """A 1 x 0.25 x 0.25 beam of 6x1x1 boxes (36 elements, 175 nodes) clamped at x = 0,
    StVK with E = 1e6, sagging for 3 implicit steps, Newton run to a tight tolerance."""
    X, T = box_mesh(6, 1, 1, size=(1.0, 0.25, 0.25))
    path = folder / "beam.mesh"
    write_tet_mesh(path, TetMesh(X, T))
    return Simulation(load_scene("cantilever", {
        "bodies[0].mesh": str(path), "bodies[0].element": "p2", "bodies[0].material.E": 1e6,
        "simulation.steps": 3, "simulation.linear_solver": solver,
        "simulation.newton.max_iterations": None}))


def test_p2_near_nullspace_is_every_free_nodes_rigid_modes(tmp_path) -> None:
    sim = p2_beam(tmp_path, "amg")
    model, system = sim.model, sim.system
    free = system.constraints.free_dofs[0::3] // 3
    assert np.isin(model.T[:, 4:], free).any()  # edge nodes are unknowns
    B = system.amg.hierarchy.B
    np.testing.assert_array_equal(B, rigid_body_modes(model.X[free]))
    # the rigid modes of all nodes are the P2 stiffness's null space at rest (to round-off)
    K = model.csr(hessian_data(model, model.X.reshape(-1)))
    R = rigid_body_modes(model.X)
    assert np.abs(K @ R).max() < 1e-9 * abs(K).max()


def test_amg_steps_the_p2_beam_like_the_direct_solver(tmp_path) -> None:
    """Three implicit steps with AMG-PCG and with the default direct solver: the same
    positions to 1e-6 of the sag (both Newton solves converged to 1e-10 of the gradient)."""
    runs = {}
    for solver in ("amg", "auto"):
        sim = p2_beam(tmp_path, solver)
        for _ in range(3):
            sim.step()
        runs[solver] = (sim.q.copy(), sim.system)
    (q_amg, amg), (q_direct, direct) = runs["amg"], runs["auto"]
    assert amg.linear_backend == "amg" and direct.linear_backend != "amg"
    report = amg.amg.report
    assert report.converged and report.iterations > 0
    sag = np.abs(q_direct - sim.model.X).max()
    assert sag > 1e-4 and np.abs(q_amg - q_direct).max() < 1e-6 * sag
