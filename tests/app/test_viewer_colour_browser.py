"""Real-browser check of the viewer's colour map (issue 43): with "Colour by: von Mises
stress" chosen, headless chromium draws the body in the ramp's colours (the GLB's vertex
colours reach WebGL), and "none" brings the plain blue back. Needs chromium, playwright and
viser as tests/app/test_viewer_browser.py does (skipped with the reason otherwise).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from fem3d.app.viewer.colour import NONE, RAMP
from fem3d.app.viewer.scene_graph import SIM_COLOR
from tests.app.test_viewer_browser import (
    CHROMIUM,
    CHROMIUM_FLAGS,
    VIEWPORT,
    _image,
    _mesh_mask,
    _missing,
    wait_for,
)

pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(_missing() is not None, reason=str(_missing()))]


def _red_minus_green(img: np.ndarray) -> float | None:
    """The median of red - green over the mesh's pixels (None: no mesh drawn): about -70 for
    the plain blue surface (SIM_COLOR (90, 160, 230), shaded), positive for the ramp's low
    end (viridis' purple (68, 1, 84))."""
    mask = _mesh_mask(img)
    if mask.mean() < 0.01:
        return None
    return float(np.median(img[..., 0][mask] - img[..., 1][mask]))


def test_browser_draws_the_colour_map(tmp_path: Path) -> None:
    from playwright.sync_api import sync_playwright

    from fem3d.app.viewer.app import Viewer

    with Viewer("bunny", port=0, integrator="implicit", mesh_mode="sim", push_hz=10.0,
                plot_hz=4.0) as viewer, sync_playwright() as pw:
        ctx = pw.chromium.launch_persistent_context(
            str(tmp_path / "profile"), executable_path=CHROMIUM, headless=True,
            args=CHROMIUM_FLAGS, viewport=VIEWPORT)
        try:
            page = ctx.pages[0] if ctx.pages else ctx.new_page()
            page.goto(viewer.url)
            page.wait_for_selector("canvas", timeout=30_000)
            wait_for(lambda: viewer.snapshot()["steps"] > 5, 60, "the simulation to run")
            assert SIM_COLOR[1] - SIM_COLOR[0] > 50 and RAMP[0][0] - RAMP[0][1] > 50

            def shade(sign: float):
                def check():
                    d = _red_minus_green(_image(page.screenshot(timeout=60_000)))
                    return d if d is not None and sign * d > 30 else None
                return check

            wait_for(shade(-1.0), 60, "the plain blue mesh", interval=0.3)
            viewer.set_colour_field("von Mises stress")
            wait_for(shade(+1.0), 60, "the ramp's colours on the mesh", interval=0.3)
            if os.environ.get("FEM3D_TEST_ARTIFACTS"):
                page.screenshot(path=str(Path(os.environ["FEM3D_TEST_ARTIFACTS"]) /
                                         "viewer_colour.png"))
            wait_for(lambda: "von Mises stress" in page.content() or None, 30,
                     "the legend on the page")
            viewer.set_colour_field(NONE)
            wait_for(shade(-1.0), 60, "the plain mesh back", interval=0.3)
            assert viewer.exceptions == [], viewer.exceptions
        finally:
            ctx.close()
