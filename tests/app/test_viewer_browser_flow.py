"""The viewer as a user sees it: what reaches the browser after each key, click and drag.

Headless Debian chromium (Playwright, as ``tests/app/test_viewer_browser.py``) loads the page;
the test decodes every websocket frame the page receives (viser's wire format: a
zstd-compressed msgpack header followed by raw binary buffers) and checks, after each user
action, that the page keeps receiving updates: the status line's simulated time advances,
mesh vertex updates arrive, and the mesh moves on screen after a drag. A script injected
into the page counts animation frames, so the test can also measure how many mesh updates
the page received and how many it drew (an update is drawn when it is the newest one at an
animation frame; updates overtaken before the next frame are wasted).

Any exception the viewer's threads print (a traceback on stderr) or log fails the test.

* :func:`test_user_sequence`: drag, mesh key, N, space, space, R, scene dropdown, a
  slider, in that order, with the checks after each.
* :func:`test_three_clients_two_dragging`: three pages connected for
  ``FEM3D_VIEWER_SOAK_SECONDS`` (default 60; CI may set less, see docs/viewer.md), two of
  them dragging all the time: no exception, every page keeps updating.
"""

from __future__ import annotations

import logging
import math
import os
import re
import shutil
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.app.test_viewer_browser import (
    _REASON,
    CHROMIUM,
    CHROMIUM_FLAGS,
    VIEWPORT,
    _grab_pixel,
    _image,
    _mesh_centroid,
    _mesh_change,
    _mesh_mask,
    project,
)

pytestmark = [pytest.mark.browser, pytest.mark.slow]
if _REASON is not None:
    pytestmark = [*pytestmark, pytest.mark.skip(reason=_REASON)]

SOAK_SECONDS = float(os.environ.get("FEM3D_VIEWER_SOAK_SECONDS", "60"))

#: Counts animation frames and websocket arrivals inside the page (times in ms).
PAGE_PROBE = """
(() => {
  // viser's client runs its websocket in a Web Worker that posts the decoded messages to
  // the page: count those that carry mesh vertices, when the page receives them.
  const probe = {arrivals: [], frames: []};
  window.__fem3dProbe = probe;
  const hasVertices = (obj, depth) => {
    if (!obj || typeof obj !== 'object' || depth > 4) return false;
    if (obj.type === 'SceneNodeUpdateMessage' && obj.updates && obj.updates.vertices) return true;
    const vals = Array.isArray(obj) ? obj : Object.values(obj);
    for (const v of vals) if (v && typeof v === 'object' && !ArrayBuffer.isView(v)
                               && hasVertices(v, depth + 1)) return true;
    return false;
  };
  const Native = window.Worker;
  window.Worker = class extends Native {
    constructor(...args) {
      super(...args);
      this.addEventListener('message', (ev) => {
        if (hasVertices(ev.data, 0)) probe.arrivals.push(performance.now());
      });
    }
  };
  const tick = (t) => { probe.frames.push(t); requestAnimationFrame(tick); };
  requestAnimationFrame(tick);
})();
"""

#: The pages whose events must be pumped while waiting: Playwright's sync API delivers
#: websocket events only while one of its calls runs, so waits sleep through the page.
_PAGES: list[Any] = []


def _sleep(seconds: float) -> None:
    if _PAGES:
        per = max(1, int(1e3 * seconds / len(_PAGES)))
        for p in list(_PAGES):
            p.wait_for_timeout(per)
    else:
        time.sleep(seconds)


def wait_for(predicate: Any, timeout: float, what: str, interval: float = 0.05) -> Any:
    """Poll ``predicate`` until it returns a result (not None/False/a str saying why not)."""
    deadline = time.monotonic() + timeout
    last: Any = None
    while time.monotonic() < deadline:
        last = predicate()
        if last is not None and last is not False and not isinstance(last, str):
            return last
        _sleep(interval)
    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what} (last: {last!r})")


_T_RE = re.compile(r"t[ \u00a0]=[ \u00a0](-?[0-9.]+)[ \u00a0]s")


def _decode_frame(payload: bytes) -> tuple[list[dict], list[bytes]]:
    """viser 1.x wire frame -> (messages, binary buffers)."""
    import msgspec
    import zstandard

    raw_len = int.from_bytes(payload[0:8], "little")
    comp_len = int.from_bytes(payload[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(
        payload[16 : 16 + comp_len], max_output_size=raw_len
    )
    head = msgspec.msgpack.decode(inner)
    buffers = []
    off = 16 + comp_len
    for n in head.get("binaryBufferLengths", ()):
        off += (8 - off % 8) % 8
        buffers.append(payload[off : off + n])
        off += n
    return list(head.get("messages", ())), buffers


def _strings(obj: Any) -> list[str]:
    if isinstance(obj, str):
        return [obj]
    if isinstance(obj, dict):
        return [s for v in obj.values() for s in _strings(v)]
    if isinstance(obj, (list, tuple)):
        return [s for v in obj for s in _strings(v)]
    return []


class WireLog:
    """What one page received, decoded (filled from Playwright's websocket events)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.frames = 0
        self.bytes = 0
        #: (payload size, carries a mesh vertex update) per frame, in arrival order.
        self.sizes: list[tuple[int, bool]] = []
        #: (wall time, node name, float32 vertex array) of mesh vertex updates.
        self.vertices: list[tuple[float, str, np.ndarray]] = []
        #: (wall time, status markdown) of status-line texts.
        self.status: list[tuple[float, str]] = []
        self.errors: list[str] = []

    def attach(self, page: Any) -> None:
        def on_ws(ws: Any) -> None:
            ws.on("framereceived", self.on_frame)

        page.on("websocket", on_ws)

    def on_frame(self, payload: Any) -> None:
        if isinstance(payload, str):
            return
        now = time.monotonic()
        try:
            messages, buffers = _decode_frame(payload)
        except Exception as exc:  # noqa: BLE001 - recorded, fails the test
            with self.lock:
                self.errors.append(f"undecodable frame: {exc!r}")
            return
        with self.lock:
            self.frames += 1
            self.bytes += len(payload)
            mesh = False
            for m in messages:
                if m.get("type") == "SceneNodeUpdateMessage" and "vertices" in m.get(
                    "updates", {}
                ):
                    ph = m["updates"]["vertices"]
                    arr = np.zeros(0, np.float32)
                    if isinstance(ph, dict) and "__binary_index" in ph:
                        arr = np.frombuffer(buffers[ph["__binary_index"]], dtype=ph["dtype"])
                    self.vertices.append((now, str(m.get("name")), arr.copy()))
                    mesh = True
                for s in _strings(m):
                    if _T_RE.search(s):
                        self.status.append((now, s))
            self.sizes.append((len(payload), mesh))

    # ---- queries
    def last_status(self) -> str | None:
        with self.lock:
            return self.status[-1][1] if self.status else None

    def last_t(self) -> float | None:
        s = self.last_status()
        if s is None:
            return None
        return float(_T_RE.search(s).group(1))

    def n_vertices(self) -> int:
        with self.lock:
            return len(self.vertices)

    def last_vertices(self) -> np.ndarray | None:
        with self.lock:
            return self.vertices[-1][2] if self.vertices else None


class Faults:
    """Exceptions the server side printed or logged while the test ran."""

    def __init__(self, capfd: Any) -> None:
        self.capfd = capfd
        self.seen: list[str] = []
        self.records: list[str] = []

        class _H(logging.Handler):
            def emit(h, record: logging.LogRecord) -> None:  # noqa: N805
                if record.levelno >= logging.ERROR or record.exc_info:
                    self.records.append(f"{record.name}: {record.getMessage()}")

        self.handler = _H()
        logging.getLogger().addHandler(self.handler)
        self._old_hook = threading.excepthook
        threading.excepthook = lambda args: self.records.append(
            f"thread {args.thread.name}: {args.exc_type.__name__}: {args.exc_value}"
        )

    def close(self) -> None:
        logging.getLogger().removeHandler(self.handler)
        threading.excepthook = self._old_hook

    def check(self, viewer: Any, where: str) -> None:
        out, err = self.capfd.readouterr()
        self.seen.append(err)
        text = "".join(self.seen)
        problems = []
        if "Traceback" in text:
            i = text.index("Traceback")
            problems.append(text[i : i + 1500])
        problems += self.records
        problems += list(getattr(viewer, "exceptions", []))
        if problems:
            pytest.fail(f"the server raised after {where}:\n" + "\n".join(problems))


def _hotkey(name: str) -> str:
    """The viewer's hotkey for ``name`` (today's code: the S/N/space/R of the issue)."""
    import fem3d.app.viewer.logic as fv

    keys = getattr(fv, "HOTKEYS", {"mesh": "S", "integrator": "N", "pause": "space", "reset": "R"})
    k = keys[name]
    return "Space" if k.lower() == "space" else k.lower()


def _launch(pw: Any, profile: Path) -> Any:
    return pw.chromium.launch_persistent_context(
        str(profile), executable_path=CHROMIUM, headless=True, args=CHROMIUM_FLAGS,
        viewport=VIEWPORT,
    )


def _open(ctx: Any, url: str, viewport: dict[str, int] | None = None) -> tuple[Any, WireLog]:
    page = ctx.new_page()
    if viewport is not None:
        page.set_viewport_size(viewport)
    page.add_init_script(PAGE_PROBE)
    log = WireLog()
    log.attach(page)
    page.goto(url)
    page.wait_for_selector("canvas", state="attached", timeout=60_000)
    _PAGES.append(page)
    return page, log


def _client_camera(viewer: Any, n_clients: int = 1) -> Any:
    want = np.asarray(viewer.camera["position"])
    cams = [
        c.camera for c in viewer.server.get_clients().values()
        if c.camera.update_timestamp and np.allclose(c.camera.position, want, rtol=1e-3)
    ]
    return cams[0] if len(cams) >= n_clients else None


def _shot(page: Any) -> np.ndarray:
    return _image(page.screenshot(timeout=60_000))


def _visible_mesh(page: Any) -> np.ndarray:
    return wait_for(
        lambda: (lambda im: im if _mesh_mask(im).mean() > 0.01 else None)(_shot(page)),
        60, "the mesh to appear in a screenshot", interval=0.3,
    )


def _keeps_updating(log: WireLog, what: str, *, timeout: float = 30.0, need_mesh: bool = False,
                    dt_min: float = 0.02) -> None:
    """The page's status time advances by ``dt_min`` and (optionally) vertex updates arrive.

    The viewer sends no vertices while the mesh is at rest, so vertex updates are checked
    where the mesh moves (drags, :func:`_drag_and_check`).
    """
    t0 = wait_for(log.last_t, timeout, f"a status line in the page ({what})")
    n0 = log.n_vertices()
    wait_for(
        lambda: (lambda t: t is not None and t >= t0 + dt_min or f"page shows t = {t}")(
            log.last_t()
        ),
        timeout, f"the page's simulated time to advance after {what}",
    )
    if need_mesh:
        wait_for(lambda: log.n_vertices() > n0 or "no vertex update", timeout,
                 f"vertex updates to reach the page after {what}")


def _drag_and_check(page: Any, log: WireLog, viewer: Any, what: str) -> dict[str, float]:
    """Drag the mesh on screen; the mesh must move in the page. Returns rate figures."""
    cam = wait_for(lambda: _client_camera(viewer), 60, "the browser to report the camera")
    shot0 = _visible_mesh(page)
    x0, y0 = _grab_pixel(_mesh_mask(shot0), viewer.positions(), cam)
    dx = -90.0 if x0 > 250 else 90.0
    n0 = log.n_vertices()
    v0 = log.last_vertices()
    page.mouse.move(x0, y0)
    page.mouse.down()
    t_start = time.monotonic()
    rate = _page_counts(page)
    kb0 = log.bytes
    for i in range(1, 13):  # each move waits for the (software-rendered) page
        page.mouse.move(x0 + dx * min(1.0, i / 8), y0 - 0.25 * dx * min(1.0, i / 8))
        _sleep(0.1)
    rate_end = _page_counts(page)
    wait_for(
        lambda: (lambda s: s if s["pull"] and s["pull"]["ids"] else None)(viewer.snapshot()),
        20, f"the drag to pick vertices ({what})",
    )
    wait_for(lambda: log.n_vertices() > n0 + 2 or "few vertex updates", 30,
             f"vertex updates during the drag ({what})")
    with log.lock:  # the updates that reached the page during the drag (v0: before it)
        during = [v for _t, _n, v in log.vertices[n0:]]
    first = v0 if v0 is not None and v0.shape == during[-1].shape else during[0]
    assert during[-1].shape == first.shape, f"vertex updates changed size ({what})"
    assert np.abs(during[-1] - first).max() > 0, (
        f"the vertices the page received did not move ({what})")
    c0 = _mesh_centroid(shot0)

    def mesh_followed() -> Any:
        im = _shot(page)
        change, shift = _mesh_change(im, shot0), (_mesh_centroid(im) - c0)[0]
        if change > 2.0 and math.copysign(1.0, dx) * shift > 0.5:
            return im
        return f"mesh change {change:.2f}, centroid shift {shift:+.2f} px (dx {dx:+})"

    shot1 = wait_for(mesh_followed, 30, f"the drawn mesh to follow the drag ({what})",
                     interval=0.3)
    page.mouse.up()
    wait_for(lambda: viewer.snapshot()["pull"] is None, 20, f"the release ({what})")
    elapsed = time.monotonic() - t_start
    assert _mesh_change(shot1, shot0) > 2.0, f"the drawn mesh did not change ({what})"
    with log.lock:
        sent = [t for t, _n, _v in log.vertices if t >= t_start]
    with log.lock:
        kb = (log.bytes - kb0) / 1e3
    return {"seconds": elapsed, "kB_per_s": kb / elapsed, **_rates(rate, rate_end),
            "sent_hz": len(sent) / elapsed}


def _page_counts(page: Any) -> dict[str, Any]:
    return page.evaluate(
        "() => ({a: window.__fem3dProbe.arrivals.slice(), f: window.__fem3dProbe.frames.slice(),"
        " now: performance.now()})"
    )


def _rates(a: dict[str, Any], b: dict[str, Any]) -> dict[str, float]:
    """Mesh updates the page received and drew per second between two probe readings.

    An update is drawn when it is the newest one at an animation frame: updates that reach
    the page between two frames are drawn once (the others were wasted).
    """
    t0, t1 = a["now"], b["now"]
    arr = [t for t in b["a"] if t0 <= t < t1]
    frames = np.asarray([f for f in b["f"] if t0 <= f < t1], dtype=np.float64)
    drawn = 0
    if frames.size and arr:
        idx = np.searchsorted(frames, arr)  # the first frame after each arrival
        drawn = int(np.unique(idx[idx < frames.size]).size)
    secs = max((t1 - t0) / 1e3, 1e-9)
    return {"received_hz": len(arr) / secs, "drawn_hz": drawn / secs, "fps": frames.size / secs}


def _select_scene(page: Any, name: str) -> None:
    page.get_by_label("Scene", exact=True).click()
    page.get_by_role("option", name=name, exact=True).click()


@pytest.fixture
def viewer() -> Any:
    from fem3d.app.viewer.app import Viewer

    v = Viewer("bunny", port=0, integrator="implicit", mesh_mode="sim")
    v.start()
    try:
        yield v
    finally:
        v.stop()


def test_user_sequence(viewer: Any, tmp_path: Path, capfd: Any) -> None:
    from playwright.sync_api import sync_playwright

    faults = Faults(capfd)
    figures: dict[str, Any] = {}
    try:
        with sync_playwright() as pw:
            ctx = _launch(pw, tmp_path / "profile")
            try:
                page, log = _open(ctx, viewer.url)
                _keeps_updating(log, "loading the page", timeout=60)
                _visible_mesh(page)
                faults.check(viewer, "loading the page")

                figures["drag sim mesh"] = _drag_and_check(page, log, viewer, "sim mesh")
                _keeps_updating(log, "the drag")
                faults.check(viewer, "the first drag")

                mode0 = viewer.snapshot()["mesh_mode"]
                page.keyboard.press(_hotkey("mesh"))
                wait_for(lambda: viewer.snapshot()["mesh_mode"] != mode0, 20,
                         "the mesh key to switch the mesh")
                _keeps_updating(log, "the mesh key")
                faults.check(viewer, "the mesh key")
                figures["drag skinned mesh"] = _drag_and_check(page, log, viewer, "skinned mesh")
                _keeps_updating(log, "the drag on the skinned mesh")
                faults.check(viewer, "the drag on the skinned mesh")

                # N cycles through the dynamic integrators and comes back to the first
                from fem3d.solve.schemes.registry import dynamic_scheme_names

                integ0 = viewer.snapshot()["integrator"]
                seen = [integ0]
                for _ in range(len(dynamic_scheme_names()) - 1):
                    page.keyboard.press(_hotkey("integrator"))
                    wait_for(lambda seen=seen: viewer.snapshot()["integrator"] != seen[-1], 20,
                             "N")
                    seen.append(viewer.snapshot()["integrator"])
                    _keeps_updating(log, f"N to {seen[-1]}")
                assert sorted(seen) == sorted(dynamic_scheme_names()), seen
                page.keyboard.press(_hotkey("integrator"))
                wait_for(lambda: viewer.snapshot()["integrator"] == integ0, 20, "N again")
                _keeps_updating(log, "N again")
                faults.check(viewer, "N")

                page.keyboard.press(_hotkey("pause"))
                wait_for(lambda: "paused" in (log.last_status() or ""), 20,
                         "the page to show 'paused'")
                t_paused = log.last_t()
                _sleep(1.0)
                assert viewer.snapshot()["paused"]
                assert log.last_t() == pytest.approx(t_paused, abs=0.011)
                page.keyboard.press(_hotkey("pause"))
                _keeps_updating(log, "resuming")
                faults.check(viewer, "space")

                t_before = log.last_t()
                page.keyboard.press(_hotkey("reset"))
                wait_for(lambda: (lambda t: t is not None and t < t_before - 0.05)(log.last_t()),
                         20, "the page's time to restart after R")
                _keeps_updating(log, "R")
                faults.check(viewer, "R")

                # Back to the simulation mesh first: the armadillo's 26002-vertex skin in
                # software GL would take most of the test's time (CI's budget is 10 min).
                page.keyboard.press(_hotkey("mesh"))
                wait_for(lambda: viewer.snapshot()["mesh_mode"] == mode0, 20,
                         "the mesh key to switch back")
                _keeps_updating(log, "the mesh key again")
                _select_scene(page, "arma")
                wait_for(lambda: viewer.snapshot()["scene"] == "arma", 90,
                         "the dropdown to load the armadillo")
                wait_for(lambda: "arma" in (log.last_status() or ""), 30,
                         "the page's status line to name the armadillo")
                _keeps_updating(log, "the scene switch", timeout=60)
                faults.check(viewer, "the scene switch")
                figures["drag armadillo"] = _drag_and_check(page, log, viewer, "armadillo")
                faults.check(viewer, "the drag on the armadillo")

                e0 = viewer.snapshot()["material"]["E"]
                slider = page.get_by_role("slider").first
                slider.focus()
                for _ in range(3):
                    slider.press("ArrowRight")
                wait_for(lambda: viewer.snapshot()["material"]["E"] != e0, 20,
                         "the slider to change the material")
                _keeps_updating(log, "the slider")
                faults.check(viewer, "the slider")
                assert not log.errors, log.errors
            finally:
                _PAGES.clear()
                ctx.close()
    finally:
        faults.close()
        print("update rates while dragging:", figures)
        shutil.rmtree(tmp_path / "profile", ignore_errors=True)


def _size(viewer: Any) -> float:
    return float(np.ptp(viewer.positions(), axis=0).max())


def _two_grabs(viewer: Any, cam: Any) -> tuple[list[tuple[float, float]], list[int]]:
    """Two screen points on the mesh far apart: the projections of the front-most upper
    vertices in two columns left and right of the mesh's middle (and those vertices)."""
    q = viewer.positions()
    uv, depth = project(q, cam)
    upper = q[:, 1] > q[:, 1].min() + 0.45 * np.ptp(q[:, 1])
    lo, hi = np.percentile(uv[upper, 0], [10, 90])
    grabs, picked = [], []
    for col in (lo + 0.25 * (hi - lo), hi - 0.25 * (hi - lo)):  # inside the silhouette
        cand = np.flatnonzero(upper & (np.abs(uv[:, 0] - col) < 8))
        k = int(cand[np.argmin(depth[cand])])
        grabs.append(tuple(float(c) for c in uv[k]))
        picked.append(k)
    return grabs, picked


def _near(viewer: Any, pull: dict[str, Any], k: int) -> bool:
    """The pull's vertices lie around vertex ``k`` (within a few pick radii)."""
    q = np.asarray(pull["start_positions"])
    r = viewer.snapshot()["pick_radius"]
    return bool(np.linalg.norm(q.mean(axis=0) - viewer.positions()[k]) < 4 * r)


def _two_pulls(viewer: Any) -> list[dict[str, Any]] | str:
    """The two pages' pulls when both are active at once (two owners, vertices picked)."""
    snap = viewer.snapshot()
    pulls = [p for p in snap["pulls"] if p["ids"]]
    owners = {p["owner"] for p in pulls}
    if len(pulls) == 2 and len(owners) == 2 and None not in owners:
        return pulls
    return (f"pulls of owners {[p['owner'] for p in snap['pulls']]}, "
            f"{snap['drag_events']} drag events")


def test_three_clients_two_dragging(viewer: Any, tmp_path: Path, capfd: Any) -> None:
    from playwright.sync_api import sync_playwright

    faults = Faults(capfd)
    try:
        with sync_playwright() as pw:
            ctx = _launch(pw, tmp_path / "profile")
            try:
                small = {"width": 480, "height": 360}  # less software rendering per page
                pages = [_open(ctx, viewer.url, small) for _ in range(3)]
                for _p, log in pages:
                    _keeps_updating(log, "loading", timeout=90)
                cam = wait_for(lambda: _client_camera(viewer, 3), 60, "three cameras")
                # No screenshots here: three software-GL pages on two cores draw too slowly
                # for them. The two dragging pages press on two different places: the
                # front-most upper vertex left and right of the middle.
                grabs, picked = _two_grabs(viewer, cam)
                for (p, _log), (x, y) in zip(pages[:2], grabs, strict=True):
                    p.mouse.move(x, y)
                    p.mouse.down()
                for i in range(1, 6):  # a drag starts with the first moves after the press
                    for p, (x, y) in zip([pg for pg, _ in pages[:2]], grabs, strict=True):
                        p.mouse.move(x, y - 8 * i)
                    _sleep(0.1)
                both = wait_for(lambda: _two_pulls(viewer), 30, "both pages' pulls at once")
                assert set(both[0]["ids"]).isdisjoint(both[1]["ids"]), "the pulls share vertices"
                for pull, near in zip(sorted(both, key=lambda d: np.mean(
                        np.asarray(d["grab_point"])[0])), picked, strict=True):
                    assert near in pull["ids"] or _near(viewer, pull, near), (
                        "a page picked vertices away from where it pressed")
                t_end = time.monotonic() + SOAK_SECONDS
                last_check = time.monotonic()
                counts = [(log.n_vertices(), log.last_t()) for _p, log in pages]
                i = 0
                while time.monotonic() < t_end:
                    i += 1
                    for k, ((p, _log), (x, y)) in enumerate(zip(pages[:2], grabs, strict=True)):
                        a = 0.3 * i + k
                        p.mouse.move(x + 40 * math.sin(a), y - 40 + 20 * math.cos(a))
                    _sleep(0.1)
                    if time.monotonic() - last_check > min(10.0, 0.5 * SOAK_SECONDS):
                        last_check = time.monotonic()  # every page still updates
                        for k, (_p, log) in enumerate(pages):
                            # a new update and a later time, waited for (not a rate: a
                            # loaded machine draws slower, only a stall fails)
                            n0, t0 = counts[k]
                            wait_for(lambda log=log, n0=n0: log.n_vertices() > n0, 60,
                                     f"page {k}: a vertex update")
                            wait_for(lambda log=log, t0=t0: (log.last_t() or -1.0) > t0, 60,
                                     f"page {k}: its status time to advance")
                            counts[k] = (log.n_vertices(), log.last_t())
                        faults.check(viewer, f"{i} drag moves")
                # Still two pulls, and every page (the watching one too) sees both pulled
                # places away from where they were picked: each client sees both drags.
                both = _two_pulls(viewer)
                assert isinstance(both, list), f"not two pulls at the end: {both}"
                for k, (_p, log) in enumerate(pages):
                    seen = log.last_vertices().reshape(-1, 3)
                    for pull in both:
                        ids, start = pull["ids"], np.asarray(pull["start_positions"])
                        moved = np.linalg.norm(seen[ids] - start, axis=1).mean()
                        assert moved > 0.02 * _size(viewer), (
                            f"page {k} does not show the pull of client {pull['owner']}: its "
                            f"vertices moved {moved:.3g}")
                for p, _log in pages[:2]:
                    p.mouse.up()
                for _p, log in pages:
                    _keeps_updating(log, "the soak")
                    assert not log.errors, log.errors
                faults.check(viewer, "the soak")
                assert viewer.snapshot()["error"] is None
            finally:
                _PAGES.clear()
                ctx.close()
    finally:
        faults.close()
        shutil.rmtree(tmp_path / "profile", ignore_errors=True)
