"""Stress in the outputs (issue 43): the VTU frames carry the von Mises stress, the Cauchy
stress and the principal stretches; checked on a uniaxial tension test (symmetry planes on
three faces, the far face moved), where every element has ``sigma_xx = E eps``.
"""

from __future__ import annotations

import meshio
import numpy as np

from fem3d.app.run import run_scene
from fem3d.mesh.tetmesh import box_tet_mesh
from fem3d.physics.stress import element_stress
from fem3d.scene import scene_from_arrays
from fem3d.simulation import Simulation

EPS = 1e-9


def _plane(axis, value, dofs, motion=None):
    lo, hi = [-9.0] * 3, [9.0] * 3
    lo[axis], hi[axis] = value - EPS, value + EPS
    pin = {"select": {"box": [lo, hi]}, "dofs": dofs}
    if motion is not None:
        pin["motion"] = {"keyframes": [{"t": 0.0}, {"t": 1.0, "translate": motion}]}
    return pin


def _tension(material="linear", strain=1e-3):
    X, T = box_tet_mesh((4, 2, 2), (1.0, 0.5, 0.5))
    pins = [_plane(0, 0.0, "x"), _plane(1, 0.0, "y"), _plane(2, 0.0, "z"),
            _plane(0, 1.0, "x", [strain, 0.0, 0.0])]
    return scene_from_arrays(X, T, {
        "bodies[0].pins": pins, "bodies[0].material.model": material,
        "bodies[0].material.E": 200.0, "bodies[0].material.nu": 0.3,
        "simulation.integrator": "static", "simulation.dt": 1.0, "simulation.steps": 1,
        "simulation.newton.tolerance": 1e-12, "pulls": []}, name="tension")


def test_uniaxial_tension_in_the_frames(tmp_path):
    summary = run_scene(_tension(), tmp_path / "run")
    assert summary.status == "ok"
    frame = meshio.read(tmp_path / "run" / "frames" / "frame_00001.vtu")
    vm = frame.point_data["von_mises"]
    sigma = frame.point_data["cauchy_stress"].reshape(-1, 3, 3)
    stretch = frame.point_data["principal_stretches"]
    print("von Mises", vm.min(), vm.max())
    # the linear material's P = E eps = 0.2 along x, pushed forward: sigma = P F^T / J
    expected = 0.2 / (1 - 0.3e-3) ** 2
    assert np.allclose(vm, expected, rtol=1e-8)
    assert np.allclose(sigma[:, 0, 0], expected, rtol=1e-8)
    assert np.abs(sigma.reshape(-1, 9)[:, 1:]).max() < 1e-9
    assert np.allclose(stretch[:, 2], 1.001, rtol=1e-12)
    assert np.allclose(stretch[:, :2], 1 - 0.3e-3, rtol=1e-9)  # Poisson's contraction


def test_element_stress_is_the_material_s_cauchy_stress():
    """Neo-Hookean in finite tension: sigma = P F^T / J from the generated P, von Mises of a
    uniaxial state = |sigma_xx - sigma_yy|."""
    sim = Simulation(_tension("stable_neo_hookean", 0.2))
    sim.step()
    e = element_stress(sim.model, sim.q)
    s = e.cauchy
    assert np.abs(s - s[:1]).max() < 1e-9 * np.abs(s).max()  # uniform
    assert np.allclose(e.von_mises, np.abs(s[:, 0, 0] - s[:, 1, 1]), rtol=1e-9)
    assert np.allclose(e.stretches[:, 2], 1.2, rtol=1e-9)
    assert np.abs(s[:, 1, 1]).max() < 1e-9 * s[0, 0, 0]  # free lateral faces
