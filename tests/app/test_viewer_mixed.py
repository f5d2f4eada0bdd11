"""The viewer on a scene whose bodies mix elements: a P1 bar beside a P2 bar is drawn (both
surfaces, the P2 one subdivided), coloured by stress, dragged by the P2 bar's edge nodes, and
its material changed live."""

from __future__ import annotations

from typing import Any

import numpy as np

from fem3d.mesh.element import ELEMENTS
from fem3d.mesh.formats import write_tet_mesh
from fem3d.mesh.tetmesh import TetMesh, box_tet_mesh
from tests.app.test_viewer import wait_for


def test_a_mixed_scene_is_drawn_coloured_dragged_and_restiffened(tmp_path) -> None:  # noqa: ANN001
    from fem3d.app.viewer.app import Viewer

    write_tet_mesh(tmp_path / "bar.mesh", TetMesh(*box_tet_mesh((4, 1, 1), (1.0, 0.25, 0.25))))
    body = ('[[bodies]]\nmesh = "bar.mesh"\nelement = "{e}"\n'
            'transform = {{ translate = [0.0, 0.0, {z}] }}\n'
            'material = {{ model = "neo_hookean", E = 1e5, nu = 0.3, density = 1000.0 }}\n'
            'pins = [{{ select = {{ box = [[-1, -1, -1], [1e-6, 1, 2]] }} }}]\n')
    (tmp_path / "mixed.toml").write_text(
        'name = "mixed_bars"\n[simulation]\nintegrator = "implicit"\ndt = 0.01\n'
        + body.format(e="p1", z=0.0) + body.format(e="p2", z=0.5))
    p1, p2 = ELEMENTS["p1"], ELEMENTS["p2"]
    with Viewer(str(tmp_path / "mixed.toml"), port=0, realtime=False, run_unwatched=True,
                push_hz=30.0) as v:
        wait_for(lambda: v.snapshot()["steps"] > 2, 60, "steps")
        sim = v._sim
        a = sim.assembled
        faces = np.asarray(v._graph.mesh_handle.faces)
        assert np.array_equal(faces, np.concatenate([p1.surface_triangles(a.blocks[0].T),
                                                     p2.surface_triangles(a.blocks[1].T)]))
        v.set_colour_field("von Mises stress")
        wait_for(lambda: v._graph.colouring.top > 0 or "no colour range", 30, "the colours")
        q = v.positions()
        bar2 = a.body_vertices[1]
        tip = bar2.start + int(np.argmax(q[bar2, 0] + q[bar2, 1]))  # the P2 bar's free end
        target = q[tip] + np.array([0.0, 0.3, 0.0])
        v.set_pick_radius(0.2)
        v.begin_pull(q[tip], target)
        ids = np.asarray(v.snapshot()["pull"]["ids"])
        assert np.isin(ids, a.blocks[1].T[:, 4:]).any()  # the P2 bar's edge nodes picked

        def followed() -> Any:
            y = float(v.positions()[tip, 1])
            return y > q[tip, 1] + 0.1 or f"tip at y {y:.4f}"

        wait_for(followed, 60, "the P2 bar to follow the drag")
        v.end_pull()
        v.set_material(E=3e5)
        wait_for(lambda: v._sim.model.E == 3e5 or f"E {v._sim.model.E}", 30, "the new E")
        assert [b.E for b in v._sim.model.blocks] == [3e5, 3e5]
        steps = v.snapshot()["steps"]
        wait_for(lambda: v.snapshot()["steps"] > steps + 2, 60, "steps after the change")
        snap = v.snapshot()
        assert snap["error"] is None and v.exceptions == [], (snap["error"], v.exceptions)
