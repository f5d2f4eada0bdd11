"""The load benchmarks of docs/loads.md on their smaller meshes (the scenes as shipped):
Lamé's sphere (octant = whole sphere; the radial displacement against Lamé's), Cook's
membrane (converging to the published 23.96 from below). About 10 s together.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from fem3d.scene import load_scene
from fem3d.simulation import Simulation

A, B, E, NU, P = 1.0, 2.0, 1000.0, 0.3, 1.0


def _static(name, mesh=None):
    sim = Simulation(load_scene(name, {"bodies[0].mesh": mesh} if mesh else None))
    sim.step()
    assert sim.last_stats.converged
    return sim


def _lame_errors(sim):
    """Relative error of the radial displacement, averaged over the inner / outer surface."""
    X = sim.model.X
    r = np.linalg.norm(X, axis=1)
    ur = np.einsum("ij,ij->i", sim.q - X, X) / r
    exact = P * A**3 * r / (E * (B**3 - A**3)) * ((1 - 2 * NU) + (1 + NU) * B**3 / (2 * r**3))
    rel = ur / exact - 1.0
    return np.array([rel[np.abs(r - A) < 1e-6].mean(), rel[np.abs(r - B) < 1e-6].mean()])


def test_lame_octant_with_symmetry_planes_equals_the_whole_sphere():
    eighth = _static("lame_sphere_eighth")
    whole = _static("lame_sphere")
    dist, idx = cKDTree(whole.model.X).query(eighth.model.X)
    assert dist.max() < 1e-12
    moved = np.abs(eighth.q - eighth.model.X).max()
    diff = np.abs(eighth.q - whole.q[idx]).max()
    print("octant vs whole", diff, "of", moved)
    assert diff < 1e-9 * moved


def test_lame_radial_displacement_converges_to_lames():
    """Second order: the 8- and 16-cell octants' errors extrapolate (Richardson, order 2) to
    within 0.5 % of Lamé's on both surfaces; each mesh is stiff (too small a displacement)."""
    e8 = _lame_errors(_static("lame_sphere_eighth"))
    e16 = _lame_errors(_static("lame_sphere_eighth", "meshes/lame_eighth_16.mesh"))
    extrapolated = (4 * e16 - e8) / 3
    print("errors 8", e8, "16", e16, "extrapolated", extrapolated)
    assert np.all(e8 < e16) and np.all(e16 < 0)
    assert np.all(np.abs(extrapolated) < 5e-3)


def test_cook_membrane_converges_from_below_to_the_published_value():
    corner = []
    for n in (8, 16, 32):
        sim = _static("cook_membrane", f"meshes/cook_{n}.mesh")
        X = sim.model.X
        c = (np.abs(X[:, 0] - 48) < 1e-9) & (np.abs(X[:, 1] - 60) < 1e-9)
        corner.append(float((sim.q - X)[c, 1].mean()))
    print("corner displacement", corner)
    assert corner[0] < corner[1] < corner[2] < 23.96
    assert corner[2] > 0.995 * 23.96
