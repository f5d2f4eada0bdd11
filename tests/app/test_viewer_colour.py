"""The viewer's colour map by von Mises stress or strain energy density (issue 43): the ramp,
the averaging to the display vertices, and what reaches the browser (the mesh node becomes a
GLB whose vertex colours are the field's, with the panel's legend naming the range).
"""

from __future__ import annotations

import importlib.util
import io
from pathlib import Path

import numpy as np
import pytest

from fem3d.app.viewer.colour import (
    NONE,
    RAMP,
    SurfaceColouring,
    colours,
    display_values,
    element_field,
    nodal_average,
)
from fem3d.mesh.tetmesh import box_tet_mesh
from fem3d.physics.model import build_model
from fem3d.physics.stress import element_stress

ROOT = Path(__file__).resolve().parents[2]
needs_viser = pytest.mark.skipif(importlib.util.find_spec("viser") is None or
                                 importlib.util.find_spec("trimesh") is None,
                                 reason="needs viser and trimesh (pip install 'fem3d[view]')")


def test_ramp_ends_and_clipping():
    rgb = colours(np.array([-1.0, 0.0, 0.5, 1.0, 3.0, np.nan]), 1.0)
    assert rgb.dtype == np.uint8 and rgb.shape == (6, 3)
    assert np.array_equal(rgb[0], RAMP[0]) and np.array_equal(rgb[1], RAMP[0])
    assert np.array_equal(rgb[2], RAMP[2]) and np.array_equal(rgb[3], RAMP[-1])
    assert np.array_equal(rgb[4], RAMP[-1]) and np.array_equal(rgb[5], RAMP[-1])
    assert np.all(colours(np.array([0.0, 2.0]), 0.0) == RAMP[0])  # a body at rest


def test_fields_average_to_the_vertices_by_volume():
    """A uniaxial stretch of a box: every element's von Mises is ``E eps`` pushed forward and
    its energy density ``psi``; the vertex averages equal them; a two-valued element field
    averages by the elements' volumes."""
    X, T = box_tet_mesh((2, 1, 1), (2.0, 1.0, 1.0))
    model = build_model(X, T, E=1e4, nu=0.0, rho=1.0, material="stvk")
    q = X * np.array([1.01, 1.0, 1.0])
    vm = element_field(model, q, "von Mises stress")
    assert np.allclose(vm, element_stress(model, q).von_mises, rtol=0, atol=0)
    assert np.ptp(vm) < 1e-9 * vm.max() and vm.max() > 0
    sed = element_field(model, q, "strain energy density")
    e = 0.5 * (1.01**2 - 1)  # Green strain; StVK with nu = 0: psi = E e^2 / 2
    assert np.allclose(sed, 1e4 * e**2 / 2, rtol=1e-12)
    assert np.allclose(display_values(model, q, "strain energy density"), sed[0], rtol=1e-12)
    half = np.where(model.X[model.T].mean(axis=1)[:, 0] < 1.0, 1.0, 3.0)
    nodal = nodal_average(model, half)
    mid = np.abs(model.X[:, 0] - 1.0) < 1e-12
    vol = model.element.volumes(model.vol)
    for v in np.flatnonzero(mid):
        around = np.any(model.T == v, axis=1)
        assert nodal[v] == pytest.approx((half * vol)[around].sum() / vol[around].sum())
    assert np.allclose(nodal[model.X[:, 0] < 1e-12], 1.0, rtol=1e-14)
    assert np.allclose(nodal[model.X[:, 0] > 2 - 1e-12], 3.0, rtol=1e-14)
    with pytest.raises(ValueError, match="unknown colour field"):
        SurfaceColouring().select("temperature")


def _glb_colours(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and RGB vertex colours of the (single) mesh of a GLB."""
    import trimesh

    scene = trimesh.load(io.BytesIO(data), file_type="glb", process=False)
    (mesh,) = scene.geometry.values()
    return np.asarray(mesh.vertices), np.asarray(mesh.visual.vertex_colors)[:, :3]


@needs_viser
def test_the_panel_colours_the_surface_and_shows_the_range(tmp_path):
    """Choosing a field in the panel's "Colour by" menu turns the mesh node into a GLB whose
    vertex colours are the field at the display vertices (sim mesh: the nodes on the surface)
    and writes the range into the legend; "none" brings the plain mesh back."""
    from fem3d.app.viewer.app import Viewer
    from tests.app.test_viewer import wait_for

    scene = tmp_path / "sag.toml"
    scene.write_text(f"""
[simulation]
integrator = "implicit"
dt = 0.01
gravity = [0.0, -9.81, 0.0]

[[bodies]]
mesh = "{ROOT / 'data' / 'contact_block.mesh'}"
material = {{ model = "neo_hookean", E = 1e5, nu = 0.3, density = 1000.0 }}
pins = [{{ select = {{ box = [[-9, -9, -9], [-0.0499, 9, 9]] }} }}]   # x = -0.05: a cantilever
""")
    with Viewer(str(scene), port=0, realtime=False, mesh_mode="sim", push_hz=50.0,
                run_unwatched=True) as v:
        wait_for(lambda: v.snapshot()["steps"] > 5, 60, "steps")
        assert "colour" in v._panel.widgets
        assert v._panel.widgets["colour"].options == (NONE, "von Mises stress",
                                                      "strain energy density")
        v.set_colour_field("von Mises stress")
        graph = v._graph
        wait_for(lambda: hasattr(graph.mesh_handle, "glb_data") or None, 30, "a GLB mesh node")
        steps = v.snapshot()["steps"]
        wait_for(lambda: v.snapshot()["steps"] > steps + 3 or None, 60, "more steps")
        wait_for(lambda: "von Mises stress" in v._panel.widgets["legend"].content or None, 30,
                 "the legend")
        verts, sent = _glb_colours(bytes(graph.mesh_handle.glb_data))
        model = v._sim.model
        assert verts.shape[0] == model.n_vertices  # the sim mesh: one display vertex a node
        values = display_values(model, verts, "von Mises stress")  # from what was sent
        expected = colours(values, values.max())
        surface = np.unique(np.asarray(v._sim.surface_faces))
        assert np.abs(sent[surface].astype(int) - expected[surface]).max() <= 2
        assert len(np.unique(sent[surface], axis=0)) > 3  # a map, not one colour
        assert graph.colouring.top > 0
        assert "Pa" in v._panel.widgets["legend"].content
        v.set_colour_field(NONE)
        wait_for(lambda: not hasattr(graph.mesh_handle, "glb_data") or None, 30,
                 "the plain mesh back")
        assert v._panel.widgets["legend"].content == "" or wait_for(
            lambda: v._panel.widgets["legend"].content == "" or None, 10, "no legend")
        assert v.exceptions == [], v.exceptions
