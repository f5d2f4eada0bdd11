"""A P2 body in the browser: what reaches the page and a mouse drag on it.

Headless Debian chromium (Playwright, as ``tests/app/test_viewer_browser_flow.py``, whose
helpers this uses) loads the viewer of a quadratic beam held by one corner; the test decodes the
websocket frames the page receives and checks that the mesh node it gets holds every node
(corners and edge nodes) and the subdivided quadratic surface (4 linear triangles per
boundary face, :meth:`fem3d.mesh.element.P2Tet.surface_triangles`); then it drags the beam
with the mouse: nodes are picked (edge nodes among them), the vertices the page receives
move, and the drawn mesh follows the mouse.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.app.test_viewer_browser import _REASON
from tests.app.test_viewer_browser_flow import (
    _PAGES,
    PAGE_PROBE,
    Faults,
    WireLog,
    _decode_frame,
    _drag_and_check,
    _keeps_updating,
    _launch,
    _visible_mesh,
    wait_for,
)

pytestmark = [pytest.mark.browser]
if _REASON is not None:
    pytestmark = [*pytestmark, pytest.mark.skip(reason=_REASON)]

#: A 1 x 0.25 x 0.25 beam of 4 x 1 x 1 cells lifted to P2, held by one corner (no gravity):
#: wherever the mouse grabs it, it swings after the mouse.
SCENE = """name = "p2_beam"
[simulation]
integrator = "implicit"
dt = 0.01
[[bodies]]
mesh = "beam.mesh"
element = "p2"
material = { model = "neo_hookean", E = 1e5, nu = 0.3, density = 1000.0 }
pins = [{ select = { vertices = [0] } }]
"""


class MeshNodes:
    """The mesh nodes (``MeshMessage``) a page received under ``/fem3d``: name -> (vertices
    ``(n, 3)`` float32, faces ``(f, 3)`` uint32), the latest of each."""

    def __init__(self, page: Any) -> None:
        self.lock = threading.Lock()
        self.nodes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        page.on("websocket", lambda ws: ws.on("framereceived", self.on_frame))

    def on_frame(self, payload: Any) -> None:
        if isinstance(payload, str):
            return
        messages, buffers = _decode_frame(payload)
        for m in messages:
            name = str(m.get("name", ""))
            if m.get("type") != "MeshMessage" or not name.startswith("/fem3d/"):
                continue
            props = m["props"]
            arrays = [np.frombuffer(buffers[props[k]["__binary_index"]],
                                    dtype=props[k]["dtype"]).reshape(-1, 3)
                      for k in ("vertices", "faces")]
            with self.lock:
                self.nodes[name] = (arrays[0].copy(), arrays[1].copy())

    def get(self, name: str) -> tuple[np.ndarray, np.ndarray] | None:
        with self.lock:
            return self.nodes.get(name)


@pytest.fixture
def viewer(tmp_path: Path) -> Any:
    from fem3d.app.viewer.app import Viewer
    from fem3d.mesh.formats import write_tet_mesh
    from fem3d.mesh.tetmesh import TetMesh, box_tet_mesh

    write_tet_mesh(tmp_path / "beam.mesh", TetMesh(*box_tet_mesh((4, 1, 1), (1.0, 0.25, 0.25))))
    (tmp_path / "p2_beam.toml").write_text(SCENE)
    v = Viewer(str(tmp_path / "p2_beam.toml"), port=0, mesh_mode="sim", push_hz=10.0)
    v.start()
    try:
        yield v
    finally:
        v.stop()


def test_p2_body_reaches_the_page_subdivided_and_follows_a_drag(viewer: Any, tmp_path: Path,
                                                                 capfd: Any) -> None:
    from playwright.sync_api import sync_playwright

    from fem3d.mesh.element import ELEMENTS

    p2 = ELEMENTS["p2"]
    T = viewer._sim.model.T
    assert viewer._sim.model.element is p2 and T.shape == (24, 10)
    faults = Faults(capfd)
    try:
        with sync_playwright() as pw:
            ctx = _launch(pw, tmp_path / "profile")
            try:
                page = ctx.new_page()
                page.add_init_script(PAGE_PROBE)
                nodes, log = MeshNodes(page), WireLog()  # from the page's first frame
                log.attach(page)
                page.goto(viewer.url)
                page.wait_for_selector("canvas", state="attached", timeout=60_000)
                _PAGES.append(page)
                got = wait_for(lambda: nodes.get("/fem3d/sim"), 60,
                               "the P2 mesh node to reach the page")
                verts, faces = got
                assert verts.shape == (viewer._sim.model.n_vertices, 3) == (81, 3)
                assert np.array_equal(faces.astype(np.int64), p2.surface_triangles(T))
                assert faces.shape[0] == 4 * p2.boundary_faces(T).shape[0]
                assert np.isin(faces, T[:, 4:]).any()  # edge nodes drawn
                _visible_mesh(page)
                _keeps_updating(log, "loading the page", timeout=60)
                faults.check(viewer, "loading the page")

                _drag_and_check(page, log, viewer, "P2 beam")
                last = log.last_vertices().reshape(-1, 3)  # the newest update the page got
                assert last.shape == (81, 3)
                edge = np.unique(T[:, 4:])
                assert np.abs(last[edge] - verts[edge]).max() > 1e-3  # edge nodes moved too
                faults.check(viewer, "the drag")
            finally:
                _PAGES.clear()
                ctx.close()
    finally:
        faults.close()
    snap = viewer.snapshot()
    assert snap["error"] is None, snap["error"]
