"""Tests of the viewer's logic without a browser.

The pure helpers are tested directly; the :class:`fem3d.app.viewer.app.Viewer` tests start a real
viser server (no client connected) on a free port with the real simulation and drive it
through the same methods the GUI callbacks call.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from fem3d.app.viewer.app import add_view_subcommand
from fem3d.app.viewer.logic import (
    EnergyHistory,
    RealtimePacer,
    StepGate,
    camera_for_points,
    energy_text,
    format_energy,
    format_status,
    spring_segments,
)
from fem3d.errors import ParameterError, SimulationError


def _has(mod: str) -> bool:
    try:
        return importlib.util.find_spec(mod) is not None
    except ModuleNotFoundError:
        return False


needs_viser = pytest.mark.skipif(
    not (_has("viser") and _has("fem3d.simulation")),
    reason="needs viser (pip install 'fem3d[view]') and the fem3d runtime",
)


def wait_for(predicate: Callable[[], Any], timeout: float, what: str) -> Any:
    """Poll until ``predicate`` returns something other than None/False/a str (why not)."""
    deadline = time.monotonic() + timeout
    last: Any = None
    while time.monotonic() < deadline:
        last = predicate()
        if last is not None and last is not False and not isinstance(last, str):
            return last
        time.sleep(0.02)
    pytest.fail(f"timed out after {timeout} s waiting for {what} (last: {last!r})")


# ------------------------------------------------------------------------- helpers


def test_pacer_keeps_sim_time_with_wall_time() -> None:
    p = RealtimePacer(max_lag=0.1)
    assert p.delay(0.0, 100.0) == 0.0  # anchors
    assert p.delay(0.5, 100.2) == pytest.approx(0.3)  # ahead: wait
    assert p.delay(0.5, 100.5) == 0.0  # on time
    assert p.delay(0.55, 100.52) == pytest.approx(0.03)
    # Fell behind by more than max_lag: re-anchor instead of racing to catch up.
    assert p.delay(0.6, 101.5) == 0.0
    assert p.delay(0.61, 101.5) == pytest.approx(0.01)
    p.reset()
    assert p.delay(5.0, 0.0) == 0.0
    assert RealtimePacer(enabled=False).delay(10.0, 0.0) == 0.0
    slow = RealtimePacer(rate=0.25)  # slow motion: 0.1 s simulated takes 0.4 s
    slow.delay(0.0, 0.0)
    assert slow.delay(0.1, 0.0) == pytest.approx(0.4)
    with pytest.raises(ParameterError):
        RealtimePacer(rate=0.0)


class _FakeClock:
    """A wall clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _drive(gate: StepGate, clock: _FakeClock, t: float, dt: float, cost: float,
           wall: float) -> tuple[float, int, list[float]]:
    """Run the simulation loop's decisions for ``wall`` seconds of the fake clock: a step
    costs ``cost`` seconds and advances ``dt``; a wait sleeps the time asked for. Returns
    (t, steps, the lead of simulated over wall time after each step)."""
    start, steps, lead = clock.now, 0, []
    t0 = t
    while clock.now - start < wall:
        w = gate.next_wait(t, True)
        assert w is not None, "idle while watched"
        if w > 0.0:
            clock.now += w
            continue
        clock.now += cost
        t += dt
        steps += 1
        lead.append((t - t0) - (clock.now - start))
    return t, steps, lead


def test_step_gate_idles_unwatched_and_paces_to_wall_time() -> None:
    """Unwatched: no step and an idle wait (None); watched: simulated time no faster than
    the clock (a step is due once its dt has passed), as fast as it can when a step costs
    more than dt; a page that comes later continues where it was left, without a burst of
    catch-up steps."""
    clock, wake = _FakeClock(), threading.Event()
    # A large max_lag: the pacer alone would race to catch up after an idle spell.
    gate = StepGate(RealtimePacer(max_lag=1e3), wake, clock=clock)
    assert gate.next_wait(0.0, True) is None and gate.watchers == 0
    clock.now += 30.0  # nobody watches for 30 s: time does not move
    gate.connect(7)
    assert wake.is_set() and gate.watchers == 1
    t, steps, lead = _drive(gate, clock, 0.0, dt=0.01, cost=0.002, wall=5.0)
    assert 495 <= steps <= 501 and t == pytest.approx(steps * 0.01)
    assert max(lead) <= 0.01 + 1e-9  # never ahead of the clock by more than one step
    assert gate.next_wait(t, False) == math.inf  # paused: nothing to step
    gate.disconnect(7)
    assert gate.next_wait(t, True) is None  # the last page left: idle
    clock.now += 100.0
    gate.connect(8)  # where it was left, re-anchored: no 100 s of catch-up steps
    t2, steps2, lead2 = _drive(gate, clock, t, dt=0.01, cost=0.002, wall=1.0)
    assert 95 <= steps2 <= 101 and min(lead2) > -0.2
    # A step that costs more than dt: back to back (never a wait), slower than real time.
    t3, steps3, _ = _drive(gate, clock, t2, dt=0.01, cost=0.03, wall=3.0)
    assert 100 <= steps3 <= 101  # 3 s / 0.03 s: not one wait
    assert StepGate(RealtimePacer(), wake, unwatched=True, clock=clock).next_wait(0.0, True) == 0.0


def test_energy_history_window_and_empty() -> None:
    h = EnergyHistory(maxlen=5)
    t, T, V, tot = h.window(1.0)
    assert t.shape == (1,) and tot[0] == 0.0
    for i in range(8):
        h.append(0.1 * i, i, 2 * i, 3 * i)
    assert len(h) == 5  # rolling
    t, T, V, tot = h.window(0.25)
    np.testing.assert_allclose(t, [0.5, 0.6, 0.7])
    np.testing.assert_allclose(tot, T + V)
    assert all(a.flags.c_contiguous and a.dtype == np.float64 for a in (t, T, V, tot))
    assert len(h.window(None)[0]) == 5
    h.append(0.8, 8, 16, 24, 99.0)  # the pull spring's energy rides along
    assert h.latest() == (0.8, 8.0, 16.0, 24.0, 99.0)
    x, T, V, tot, pull = h.recent(0.25)  # real samples only, relative to the newest
    np.testing.assert_allclose(x, [-0.2, -0.1, 0.0], atol=1e-12)
    np.testing.assert_allclose(T, [6, 7, 8])
    np.testing.assert_allclose(pull, [0, 0, 99])
    x, T, *_ = h.recent(10.0, n=2)  # decimated, newest kept
    assert x[-1] == 0.0 and T[-1] == 8.0 and len(x) <= 3
    h.clear()
    assert len(h) == 0 and h.latest() is None
    assert all(a.size == 0 for a in h.recent(1.0))  # nothing invented after a reset


def _check_axis(ax: Any, y: np.ndarray, min_span: float, what: str) -> None:
    """The axis holds ``y``, spans at least ``min_span``, and its >= 2 ticks read apart."""
    assert len(ax.ticks) >= 2 and len(set(ax.labels)) == len(ax.labels), (what, ax)
    assert ax.lo <= y.min() and y.max() <= ax.hi and ax.hi - ax.lo >= min_span, (what, ax)
    assert ax.ticks[0] == ax.lo and ax.ticks[-1] == ax.hi
    step = ax.ticks[1] - ax.ticks[0]
    for label, tick in zip(ax.labels, ax.ticks, strict=True):
        assert abs(float(label) - tick) <= 0.01 * step, (what, label, tick)


def test_tick_labels_never_repeat_at_any_scale() -> None:
    from fem3d.app.viewer.plots import y_axis

    rng = np.random.default_rng(3)
    for _ in range(400):
        mag = 10.0 ** rng.uniform(-25, 12)
        y = mag * (rng.uniform(-1, 1) + 10.0 ** rng.uniform(-9, 0) * rng.normal(size=20))
        ax = y_axis(y, float(np.abs(y).max()), 0.0)
        _check_axis(ax, y, 1e-3 * np.abs(y).max(), f"magnitude {mag:.3g}")
        assert max(len(label) for label in ax.labels) <= 11, ax.labels  # "-1.0335e-11"
    ax = y_axis(np.zeros(5), 0.0, 0.0)  # nothing at all (the pull plot without a drag)
    _check_axis(ax, np.zeros(5), 1.0, "zeros")
    assert ax.labels[0] == "0" and y_axis(np.zeros(0), 0.0, 0.0).hi > 0.0


def test_plots_of_a_resting_scene_read_apart() -> None:
    """The bunny at rest: T is round-off (~1e-21) and used to fill its plot, read "0", "0".
    Each plot now spans at least a fraction of its history's and the scene's energy scale,
    and its tick labels differ."""
    from fem3d.app.viewer.logic import ENERGY_PLOTS, ViewerState
    from fem3d.app.viewer.plots import SPAN_OWN, SPAN_SCENE, y_axis

    state = ViewerState("bunny", integrator=None, backend=None, mesh_mode="sim",
                        pacer=RealtimePacer(enabled=False))
    for _ in range(15):
        assert state.step() is None
    x, *series = state.history.plot_series(10.0)
    peaks, scene = state.history.peaks()
    kinetic = series[0]
    assert kinetic.max() < 1e-9 * scene  # at rest: round-off
    for (key, _label, _color), y, peak in zip(ENERGY_PLOTS, series, peaks, strict=True):
        assert peak == pytest.approx(np.abs(y).max())
        ax = y_axis(y, peak, scene)
        _check_axis(ax, y, max(SPAN_OWN * peak, SPAN_SCENE * scene), key)
        if key == "kinetic":  # a flat line at 0 on the scene's scale
            assert ax.lo == 0.0 and ax.hi >= SPAN_SCENE * scene and ax.labels[0] == "0"
        assert y_axis(y * (1 + 1e-6), peak, scene, ax) is ax  # kept: no chart rebuild


def test_spring_segments() -> None:
    q = np.arange(15, dtype=np.float64).reshape(5, 3)
    seg = spring_segments(q, np.array([1, 4]), np.array([9.0, 8.0, 7.0]))
    assert seg.shape == (2, 2, 3) and seg.dtype == np.float32
    np.testing.assert_allclose(seg[:, 0], q[[1, 4]])
    np.testing.assert_allclose(seg[:, 1], [[9, 8, 7], [9, 8, 7]])
    assert spring_segments(q, np.zeros(0, dtype=np.int64), np.zeros(3)).shape == (0, 2, 3)


@pytest.mark.parametrize(
    ("scale", "direction"), [(1.0, (0.0, 0.25, 1.0)), (165.0, (0.0, 0.25, -1.0))]
)
def test_camera_frames_all_points(scale: float, direction: tuple[float, ...]) -> None:
    rng = np.random.default_rng(0)
    pts = scale * rng.normal(size=(200, 3)) + np.array([3.0, -2.0, 1.0]) * scale
    fov = 75.0 * math.pi / 180.0
    cam = camera_for_points(pts, fov, direction=direction)
    lo, hi = pts.min(0), pts.max(0)
    np.testing.assert_allclose(cam["center"], 0.5 * (lo + hi))
    # The camera looks along -direction; the object sits left of the view centre.
    view = cam["look_at"] - cam["position"]
    np.testing.assert_allclose(
        -view / np.linalg.norm(view), np.asarray(direction) / np.linalg.norm(direction)
    )
    # Every point lies inside the vertical and (square-aspect) horizontal field of view.
    fwd = cam["look_at"] - cam["position"]
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    d = pts - cam["position"]
    z = d @ fwd
    assert (z > cam["near"]).all() and (z < cam["far"]).all()
    assert (np.abs(d @ up / z) < math.tan(fov / 2)).all()
    assert (np.abs(d @ right / z) < math.tan(fov / 2)).all()
    c = cam["center"] - cam["position"]
    assert c @ right < 0  # the centre projects left of the middle


def test_energy_text_shows_every_current_value() -> None:
    assert format_energy(0.0) == "0"
    assert format_energy(1.5e-6) == "1.500e-06" and format_energy(1.2e9) == "1.200e+09"
    assert format_energy(0.5) == "0.5"
    s = energy_text((1.0, 1e-6, 2e-6, 3e-6, 4e9)).replace("\u00a0", " ")
    for part in ("T = 1.000e-06", "V = 2.000e-06", "T+V = 3.000e-06", "pull = 4.000e+09"):
        assert part in s, part
    assert "none" in energy_text(None)


def test_format_status() -> None:
    kw = dict(
        scene="bunny", integrator="linear", mesh_mode="skin", paused=False, error=None,
        t=1.234, ms_per_step=12.34, newton_per_step=1.0, steps_per_second=80.0,
        E=6e6, nu=0.4, rho=0.1,
    )
    s = format_status(**kw)
    # Phrases keep non-breaking spaces: the panel wraps only between phrases.
    for phrase in s.replace("  \n", " · ").split(" · "):
        assert " " not in phrase, phrase
    s = s.replace("\u00a0", " ")
    for part in ("bunny", "linearly-implicit Euler", "skinned", "running", "t = 1.23 s",
                 "12.3 ms/step", "1.00 Newton", "E = 6e+06"):
        assert part in s, part
    def plain(**over: Any) -> str:
        return format_status(**{**kw, **over}).replace("\u00a0", " ")

    assert "paused" in plain(paused=True)
    assert "simulation error" in plain(paused=True, error="boom")
    assert "backward Euler" in plain(integrator="implicit")
    g = format_status(**kw, grabbed=7, pick_radius=2.5).replace("\u00a0", " ")
    assert "grab radius 2.5" in g and "dragging 7 vertices" in g


def test_cli_subcommand_parses() -> None:
    parser = argparse.ArgumentParser(prog="fem3d")
    sub = parser.add_subparsers(dest="command")
    add_view_subcommand(sub)
    args = parser.parse_args(["view"])
    assert (args.scene, args.host, args.port, args.integrator) == (
        "bunny", "127.0.0.1", 8080, None
    )
    assert callable(args.func)
    args = parser.parse_args(
        ["view", "arma", "--port", "0", "--integrator", "linear", "--no-realtime",
         "--time-scale", "0.5"]
    )
    assert (args.scene, args.port, args.integrator, args.no_realtime, args.time_scale) == (
        "arma", 0, "linear", True, 0.5
    )
    assert parser.parse_args(["view", "--kernels", "numpy"]).backend == "numpy"
    with pytest.raises(SystemExit):
        parser.parse_args(["view", "--integrator", "rk4"])


@needs_viser
def test_cli_view_serves_and_stops_on_ctrl_c() -> None:
    """``fem3d view`` prints its URL, serves the page, and exits 0 on SIGINT."""
    import signal
    import urllib.request

    proc = subprocess.Popen(
        [sys.executable, "-m", "fem3d", "view", "bunny", "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        # Ctrl-C as in a terminal, even when the tests run as a background job (SIGINT ignored)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        url = None
        lines = []
        deadline = time.monotonic() + 60
        while url is None and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("fem3d view: http"):
                url = line.split()[2]
        assert url, "no URL printed:\n" + "".join(lines)
        with urllib.request.urlopen(url, timeout=20) as r:  # the viser client page
            assert r.status == 200 and b"<html" in r.read().lower()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
        assert proc.returncode == 0, out
        assert "stopping" in out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_cli_registration_does_not_import_viser() -> None:
    code = (
        "import argparse, sys\n"
        "from fem3d.app.viewer.app import add_view_subcommand\n"
        "p = argparse.ArgumentParser(); add_view_subcommand(p.add_subparsers())\n"
        "p.parse_args(['view'])\n"
        "assert 'viser' not in sys.modules, 'viser imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def test_bad_viewer_arguments() -> None:
    from fem3d.app.viewer.app import Viewer

    with pytest.raises(ParameterError, match="integrator"):
        Viewer("bunny", integrator="rk4")
    with pytest.raises(ParameterError, match="port"):
        Viewer("bunny", port=70000)
    with pytest.raises(ParameterError, match="mesh_mode"):
        Viewer("bunny", mesh_mode="points")


# ------------------------------------------------------------------------- the viewer


@pytest.fixture
def viewer():
    from fem3d.app.viewer.app import Viewer

    v = Viewer("bunny", port=0, realtime=False, push_hz=30.0, run_unwatched=True)
    v.start()
    try:
        yield v
    finally:
        v.stop()
    assert v._thread is not None and not v._thread.is_alive(), "sim thread did not stop"


@needs_viser
def test_pull_moves_picked_vertices_and_raises_energy(viewer: Any) -> None:
    wait_for(lambda: viewer.snapshot()["steps"] > 3, 30, "steps")
    q = viewer.positions()
    top = int(np.argmax(q[:, 1]))
    target = q[top] + np.array([-8.0, 4.0, 0.0])
    viewer.begin_pull(q[top])
    viewer.move_pull(target)
    snap = viewer.snapshot()
    assert top in snap["pull"]["ids"]
    np.testing.assert_allclose(snap["pull"]["target"], target)

    def closer() -> Any:
        p = viewer.snapshot()["pull"]
        tg = np.asarray(p["target"])
        d0 = np.linalg.norm(np.asarray(p["start_positions"]) - tg, axis=1).mean()
        d1 = np.linalg.norm(np.asarray(p["positions"]) - tg, axis=1).mean()
        return bool(d1 < 0.8 * d0) or f"{d0:.3g} -> {d1:.3g}"

    wait_for(closer, 30, "picked vertices to approach the target")
    energy = np.asarray(viewer.snapshot()["energy"])
    assert energy[:, 3].max() > 1.0  # at rest the total is ~0
    assert np.isfinite(energy).all()
    viewer.end_pull()
    assert viewer.snapshot()["pull"] is None
    assert viewer.snapshot()["error"] is None


@needs_viser
def test_toggles_pause_reset_material(viewer: Any) -> None:
    s0 = viewer.snapshot()
    assert (s0["mesh_mode"], s0["integrator"]) == ("skin", "linear")
    viewer.toggle_mesh_mode()
    wait_for(lambda: viewer.snapshot()["mesh_mode"] == "sim", 10, "mesh mode")
    viewer.toggle_integrator()
    wait_for(lambda: viewer.snapshot()["integrator"] == "implicit", 10, "integrator")
    viewer.toggle_pause()
    wait_for(lambda: viewer.snapshot()["paused"], 10, "pause")
    time.sleep(0.1)
    n, pushes = viewer.snapshot()["steps"], viewer.snapshot()["pushes"]
    time.sleep(0.3)
    assert viewer.snapshot()["steps"] == n, "stepped while paused"
    assert viewer.snapshot()["pushes"] == pushes, "re-sent an unchanged mesh while paused"
    viewer._gui_toggle_pause()  # space on a focused button: hotkey + click = one toggle
    viewer._gui_toggle_pause()
    wait_for(lambda: viewer.snapshot()["steps"] > n, 10, "resume")
    wait_for(lambda: viewer.snapshot()["t"] > 0.05, 30, "time to advance")
    t_before = viewer.snapshot()["t"]
    viewer.reset()  # t only grows otherwise: a smaller t proves the reset
    snap = wait_for(
        lambda: (lambda s: s if s["t"] < t_before and s["energy"] else None)(viewer.snapshot()),
        10,
        "reset",
    )
    assert snap["energy"][0][0] < t_before  # the history restarted
    viewer.set_material(E=1e6, nu=0.3, rho=0.2)
    wait_for(
        lambda: viewer.snapshot()["material"] == {"E": 1e6, "nu": 0.3, "rho": 0.2}, 10, "material"
    )
    viewer.set_material(nu=0.7)  # rejected by the runtime: no change, no crash
    time.sleep(0.2)
    snap = viewer.snapshot()
    assert snap["material"]["nu"] == 0.3
    assert snap["error"] is None and not snap["paused"]


@needs_viser
def test_the_plots_get_their_axes_at_rest(viewer: Any) -> None:
    """What the viewer sends each uPlot chart for the resting bunny: a fixed y range that
    holds the data, explicit ticks, and labels that differ (T read "0" and "0")."""
    wait_for(lambda: viewer.snapshot()["steps"] > 10, 30, "steps")
    viewer.set_paused(True)
    wait_for(lambda: viewer.snapshot()["paused"], 10, "pause")
    time.sleep(0.5)  # a panel update after the last step
    for key in ("kinetic", "strain", "gravity", "total", "pull"):
        plot = viewer._gui[f"plot_{key}"]
        lo, hi = plot.scales["y"]["range"]
        assert plot.scales["y"]["auto"] is False and lo < hi, key
        axis = plot.axes[1]
        labels, ticks = axis["values"], axis["splits"]
        assert len(labels) == len(ticks) >= 2 and len(set(labels)) == len(labels), (key, labels)
        assert ticks[0] == lo and ticks[-1] == hi
        y = np.asarray(plot.data[1], dtype=np.float64)
        assert y.size and lo <= y.min() and y.max() <= hi + 1e-6 * abs(hi), (key, lo, hi, y)
        assert viewer._panel.y_axes[key].labels == tuple(labels)
    assert viewer._gui["plot_kinetic"].axes[1]["values"][0] == "0"


@needs_viser
def test_simulation_error_pauses_and_reset_recovers(viewer: Any, monkeypatch) -> None:
    wait_for(lambda: viewer.snapshot()["steps"] > 3, 30, "steps")
    sim = viewer._sim
    real_step = sim.step

    def exploding_step() -> Any:
        raise SimulationError("energy exploded (test)", step=7)

    monkeypatch.setattr(sim, "step", exploding_step)
    snap = wait_for(lambda: (lambda s: s if s["error"] else None)(viewer.snapshot()), 10, "error")
    assert snap["paused"] and "exploded" in snap["error"]
    assert np.isfinite(viewer.positions()).all()
    n = snap["steps"]
    time.sleep(0.2)
    assert viewer.snapshot()["steps"] == n  # stays paused, the thread is alive
    assert viewer._thread.is_alive()
    monkeypatch.setattr(sim, "step", real_step)
    viewer.reset()
    wait_for(lambda: viewer.snapshot()["steps"] > n, 10, "steps after reset")
    snap = viewer.snapshot()
    assert snap["error"] is None and not snap["paused"]
    assert snap["errors"] == ["step 7: energy exploded (test)"]


@needs_viser
def test_real_blow_up_is_caught(viewer: Any) -> None:
    """A huge pull on the bunny's back with the linearly-implicit integrator blows up."""
    viewer.set_paused(True)
    wait_for(lambda: viewer.snapshot()["paused"], 30, "pause")
    q = viewer._sim.model.X
    v = int(np.argmin(np.linalg.norm(q - [-68.96, 131.42, 55.16], axis=1)))  # vertex 47
    viewer.begin_pull(q[v], q[v] + np.array([-100.0, 20.0, 0.0]))
    viewer.reset()  # from rest, with the pull from step 0 (reset re-applies the pull)
    n0 = 0
    snap = wait_for(
        lambda: (lambda s: s if s["error"] or s["steps"] > n0 + 300 else None)(viewer.snapshot()),
        40,
        "a SimulationError or 300 steps",
    )
    # deterministic: from rest with this pull the linearly-implicit bunny always blows up
    assert snap["error"], "the runtime no longer blows up on this pull: pick a harder one"
    assert snap["paused"]
    assert np.isfinite(viewer.positions()).all()
    assert np.isfinite(np.asarray(snap["energy"])).all()
    viewer.end_pull()
    viewer.toggle_integrator()
    viewer.reset()
    wait_for(
        lambda: (lambda s: s["error"] is None and s["steps"] > snap["steps"])(viewer.snapshot()),
        10,
        "recovery",
    )


@needs_viser
def test_concurrent_drags_and_mesh_swaps(viewer: Any) -> None:
    """GUI-thread drags racing with mesh replacement never break the simulation thread."""
    viewer.toggle_integrator()  # backward Euler: random pulls must not blow the bunny up
    wait_for(lambda: viewer.snapshot()["integrator"] == "implicit", 10, "backward Euler")
    wait_for(lambda: viewer.snapshot()["steps"] > 3, 30, "steps")
    q = viewer.positions()
    stop = threading.Event()
    failures: list[BaseException] = []

    def dragger() -> None:
        rng = np.random.default_rng(1)
        try:
            while not stop.is_set():
                i = int(rng.integers(len(q)))
                viewer.begin_pull(q[i])
                for _ in range(3):
                    viewer.move_pull(q[i] + rng.normal(size=3))
                viewer.end_pull()
        except BaseException as exc:  # noqa: BLE001
            failures.append(exc)

    threads = [threading.Thread(target=dragger) for _ in range(2)]
    for t in threads:
        t.start()
    for _ in range(6):
        viewer.toggle_mesh_mode()
        time.sleep(0.05)
    stop.set()
    for t in threads:
        t.join(10)
    assert not failures, failures
    n = viewer.snapshot()["steps"]
    wait_for(
        lambda: (lambda s: s["steps"] > n or f"paused={s['paused']} error={s['error']}")(
            viewer.snapshot()
        ),
        10,
        "the loop to keep stepping",
    )
    # Six toggles: the commands run before the next step (a step already under way when
    # they were posted may finish first).
    snap = wait_for(lambda: (lambda s: s if s["mesh_mode"] == "skin" else s["mesh_mode"])(
        viewer.snapshot()), 20, "six toggles to be applied")
    assert snap["error"] is None, snap["error"]
    assert viewer.exceptions == [], viewer.exceptions
    assert viewer._thread.is_alive()


@needs_viser
def test_viewer_steps_only_while_a_page_is_connected() -> None:
    """No page: no step and an idle simulation thread (it waits on an event: a loop that
    polls would count passes). A page connects: the scene runs from t = 0 at about wall
    time. It leaves: the simulation stops where it was; the next page continues there."""
    from types import SimpleNamespace

    from fem3d.app.viewer.app import Viewer

    def page(cid: int) -> Any:
        return SimpleNamespace(client_id=cid, camera=SimpleNamespace())

    with Viewer("bunny", port=0, mesh_mode="sim") as v:
        time.sleep(1.0)
        snap = v.snapshot()
        assert (snap["steps"], snap["t"], snap["watchers"]) == (0, 0.0, 0)
        assert snap["loops"] <= 2, f"{snap['loops']} loop passes with nobody watching"
        v._on_client_connect(page(1))
        wall0 = time.monotonic()
        wait_for(lambda: v.snapshot()["steps"] > 0, 10, "a step once a page connects")
        time.sleep(1.0)
        t1, wall1 = v.snapshot()["t"], time.monotonic() - wall0
        assert 0.2 < t1 <= wall1 + 0.05, f"t = {t1:.3f} s after {wall1:.3f} s of wall time"
        v._on_client_disconnect(page(1))
        time.sleep(0.2)  # a step under way finishes
        snap = v.snapshot()
        time.sleep(0.5)
        assert v.snapshot()["steps"] == snap["steps"] and snap["watchers"] == 0
        v._on_client_connect(page(2))
        wait_for(lambda: v.snapshot()["steps"] > snap["steps"], 10, "steps for the next page")
        assert v.snapshot()["t"] > snap["t"]  # it continues: no reset to t = 0
        assert v.exceptions == [], v.exceptions


@needs_viser
def test_switch_scene() -> None:
    from fem3d.app.viewer.app import Viewer

    with Viewer("bunny", port=0, realtime=False, mesh_mode="sim",
                run_unwatched=True) as v:
        wait_for(lambda: v.snapshot()["steps"] > 3, 30, "steps")
        v.switch_scene("arma")
        snap = wait_for(
            lambda: (lambda s: s if s["scene"] == "arma" and s["steps"] else None)(v.snapshot()),
            60, "the arma scene",
        )
        assert snap["generation"] == 1
        assert snap["integrator"] == "implicit"
        assert snap["material"]["E"] == pytest.approx(6e5)
        assert v.positions().shape == (259, 3)
        v.switch_scene("no-such-scene")  # an error notification, the scene stays
        time.sleep(0.3)
        assert v.snapshot()["scene"] == "arma" and v.snapshot()["error"] is None


@needs_viser
def test_port_in_use_is_refused_in_one_line_and_port_0_is_free() -> None:
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        r = subprocess.run([sys.executable, "-m", "fem3d", "view", "bunny", "--port", str(port)],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 2, r.stderr
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1, r.stderr
        assert f"port {port} on 127.0.0.1 is in use" in lines[0] and "--port 0" in lines[0]
    from fem3d.app.viewer.app import Viewer

    with Viewer("bunny", port=0, realtime=False, mesh_mode="sim") as v:
        assert v.server.get_port() != 0 and v.url.endswith(f":{v.server.get_port()}")


@needs_viser
def test_scene_file_radius_and_mesh_swaps_keep_pushing(tmp_path) -> None:  # noqa: ANN001
    """A .toml scene opens; the grab radius follows set_pick_radius; the mesh toggle (the S
    freeze of issue 12) and a scene switch keep mesh updates going, with no exception."""
    from pathlib import Path

    from fem3d.app.viewer.app import Viewer

    toml = Path(__file__).resolve().parents[2] / "data" / "scenes" / "arma.toml"
    with Viewer(str(toml), port=0, realtime=False, mesh_mode="skin",
                run_unwatched=True) as v:
        snap = wait_for(lambda: (lambda s: s if s["steps"] > 2 else None)(v.snapshot()), 60,
                        "steps")
        assert snap["scene"] == "arma"
        r0 = snap["pick_radius"]
        q = v.positions()
        v.set_pick_radius(50 * r0)
        wait_for(lambda: v.snapshot()["pick_radius"] == 50 * r0, 10, "the radius")
        v.begin_pull(q[0], q[0] + 0.1)
        many = len(v.snapshot()["pull"]["ids"])
        v.end_pull()
        v.set_pick_radius(r0)
        wait_for(lambda: v.snapshot()["pick_radius"] == r0, 10, "the radius back")
        v.begin_pull(q[0], q[0] + 0.1)
        assert len(v.snapshot()["pull"]["ids"]) < many
        for action in (v.toggle_mesh_mode, v.toggle_mesh_mode, lambda: v.switch_scene("bunny")):
            action()
            n = v.snapshot()["pushes"]
            v.begin_pull(v.positions()[0], v.positions()[0] + 1.0)  # keeps the mesh moving
            wait_for(lambda n=n: v.snapshot()["pushes"] > n + 2, 60, "mesh updates")
            v.end_pull()
        assert v.snapshot()["scene"] == "bunny"
        assert v.exceptions == [], v.exceptions
        with pytest.raises(ParameterError, match="radius"):
            v.set_pick_radius(0.0)


@needs_viser
def test_material_menu_switches_the_model_and_keeps_the_motion() -> None:
    from fem3d.app.viewer.app import Viewer
    from fem3d.scene.spec import material_names

    names = material_names()
    other = next((n for n in names if n != "neo_hookean"), None)
    if other is None:
        pytest.skip("only one material is generated")
    with Viewer("bunny", port=0, realtime=False, integrator="implicit", mesh_mode="sim",
                run_unwatched=True) as v:
        assert v.snapshot()["material_model"] == "neo_hookean"
        assert tuple(v._gui["material"].options) == tuple(names)
        q = v.positions()
        v.begin_pull(q[0], q[0] + np.array([5.0, 0.0, 0.0]))
        wait_for(lambda: v.snapshot()["steps"] > 3, 60, "steps")
        t0 = v.snapshot()["t"]
        v.switch_material(other)
        snap = wait_for(lambda: (lambda s: s if s["material_model"] == other else None)(
            v.snapshot()), 60, "the new material")
        assert snap["t"] >= t0  # the motion carried over, no reset
        wait_for(lambda: v.snapshot()["t"] > snap["t"] + 0.02, 60, "steps with the new model")
        assert v._sim.scene.bodies[0].material.model == other
        v.switch_material("no_such_material")  # refused with a notification
        v.switch_material(other)  # a no-op
        time.sleep(0.3)
        s = v.snapshot()
        assert s["material_model"] == other and s["error"] is None
        assert v.exceptions == [], v.exceptions


def test_plane_grid_lines_cover_the_plane_square() -> None:
    from fem3d.app.viewer.logic import plane_grid_segments, plane_quad

    n = np.array([0.0, 1.0, 0.0])
    seg = plane_grid_segments(np.zeros(3), n, np.array([1.0, 5.0, 2.0]), 2.0, cells=4)
    assert seg.shape == (10, 2, 3)
    V, _ = plane_quad(np.zeros(3), n, np.array([1.0, 5.0, 2.0]), 2.0)
    np.testing.assert_allclose(seg[..., 1], 2e-3)  # lifted over the square
    for k in (0, 2):
        assert seg[..., k].min() == pytest.approx(V[:, k].min())
        assert seg[..., k].max() == pytest.approx(V[:, k].max())


def test_plane_quad_lies_in_the_plane_around_the_centre() -> None:
    from fem3d.app.viewer.logic import plane_quad

    point, normal = np.array([0.0, 1.0, 0.0]), np.array([0.0, 2.0, 0.0])
    V, F = plane_quad(point, normal, np.array([3.0, 7.0, -1.0]), 2.0)
    assert V.shape == (4, 3) and F.shape == (2, 3)
    np.testing.assert_allclose(V[:, 1], 1.0)  # in the plane
    np.testing.assert_allclose(V.mean(axis=0), [3.0, 1.0, -1.0])  # the centre's projection
    np.testing.assert_allclose(np.linalg.norm(V[0] - V[2]), 4.0 * math.sqrt(2.0))
    tilted = np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0)
    V, _ = plane_quad(np.zeros(3), tilted, np.array([1.0, 0.0, 0.0]), 1.0)
    np.testing.assert_allclose(V @ tilted, 0.0, atol=1e-12)


@needs_viser
def test_obstacles_are_drawn_and_moving_ones_follow(tmp_path) -> None:  # noqa: ANN001
    from pathlib import Path

    from fem3d.app.viewer.app import Viewer

    data = Path(__file__).resolve().parents[2] / "data"
    scene = tmp_path / "obstacles.toml"
    scene.write_text(f"""
[simulation]
integrator = "implicit"
dt = 0.01
gravity = [0.0, -9.81, 0.0]

[[bodies]]
mesh = "{data / 'contact_block.mesh'}"
transform = {{ translate = [0.0, 0.3, 0.0] }}
material = {{ model = "neo_hookean", E = 1e5, nu = 0.3, density = 1000.0 }}

[contact]
enabled = true

[[obstacles]]
plane = {{ point = [0.0, 0.0, 0.0], normal = [0.0, 1.0, 0.0] }}

[[obstacles]]
mesh = {{ path = "{data / 'coarser_bunny.obj'}", transform = {{ scale = 0.001, translate = [1.0, 0.0, 0.0] }}, motion = {{ keyframes = [{{ t = 0.0, translate = [0.0, 0.0, 0.0] }}, {{ t = 1.0, translate = [0.0, 0.5, 0.0] }}] }} }}
""")  # noqa: E501
    with Viewer(str(scene), port=0, realtime=False, mesh_mode="sim",
                run_unwatched=True) as v:
        wait_for(lambda: len(v._graph.obstacle_handles) == 2 or None, 60, "the obstacles")
        plane, mesh = v._graph.obstacle_handles
        assert np.allclose(np.asarray(plane.vertices)[:, 1], 0.0)  # the floor
        (grid,) = v._graph.plane_grid_handles  # and its grid lines, just above it
        pts = np.asarray(grid.points).reshape(-1, 3)
        assert pts.shape[0] == 2 * 2 * 13 and np.ptp(pts[:, 1]) < 1e-9 and pts[0, 1] > 0
        assert np.ptp(pts[:, 0]) == pytest.approx(np.ptp(np.asarray(plane.vertices)[:, 0]))
        y0 = float(np.asarray(mesh.vertices)[:, 1].min())
        wait_for(lambda: float(np.asarray(mesh.vertices)[:, 1].min()) > y0 + 0.05 or None, 120,
                 "the keyframed obstacle to move up on screen")
        v.toggle_integrator()  # N: a contact scene skips linearly-implicit Euler: BDF2 next
        steps = v.snapshot()["steps"]
        wait_for(lambda: v.snapshot()["steps"] > steps + 2 or None, 60, "stepping after N")
        assert v.snapshot()["integrator"] == "bdf2"
        assert v.exceptions == [], v.exceptions


def test_energy_split_strain_gravity_pull_for_a_falling_bunny() -> None:
    """The viewer's plots and "now:" line split V into strain and gravity (gravity's
    potential is negative for a body that fell: it is not strain; V = -22.11 was shown as
    "V (strain)" for a resting bunny)."""
    from fem3d.app.viewer.logic import ENERGY_PLOTS, ViewerState

    state = ViewerState("contact_bunny_drop", integrator="implicit", backend=None, mesh_mode="sim",
                        pacer=RealtimePacer(enabled=False))
    for _ in range(30):  # it lands at step 25 and squashes
        assert state.step() is None
    e = state.sim.energies()
    assert e["potential"] == pytest.approx(e["strain"] + e["gravity"], rel=1e-12, abs=1e-15)
    assert e["gravity"] < 0.0 < e["strain"]  # fell and squashed on landing
    latest = state.history.latest_split()
    t, T, V, tot, pull, strain, gravity = latest
    assert gravity == pytest.approx(e["gravity"]) and strain == pytest.approx(e["strain"])
    assert strain > 0.0 and strain == pytest.approx(V - gravity)
    text = energy_text(latest).replace("\u00a0", " ")
    assert f"strain = {format_energy(strain)}" in text
    assert f"gravity = {format_energy(gravity)}" in text
    labels = {key: label for key, label, _c in ENERGY_PLOTS}
    assert "strain" in labels["strain"] and "gravity" in labels["gravity"]
    assert not any(label == "V (strain)" for label in labels.values())
    x, *series = state.history.plot_series(10.0)
    cols = dict(zip([k for k, _l, _c in ENERGY_PLOTS], series, strict=True))
    assert cols["strain"][-1] == strain and cols["gravity"][-1] == gravity
    assert (cols["strain"] >= -1e-9 * abs(gravity)).all()  # strain is never negative


@needs_viser
def test_contact_scene_camera_frames_the_ground_under_the_body() -> None:
    """contact_bunny_drop: the viewer's first view holds the bunny and the ground where it
    lands (it used to frame the bunny alone, the ground below the viewport)."""
    from fem3d.app.viewer.app import Viewer

    v = Viewer("contact_bunny_drop", port=0, integrator="implicit", mesh_mode="sim")
    try:
        cam, q = v.camera, v.positions()
    finally:
        v.stop()
    ground = q.copy()
    ground[:, 1] = 0.0  # the plane y = 0 under the bunny
    pos, look = np.asarray(cam["position"]), np.asarray(cam["look_at"])
    fwd = (look - pos) / np.linalg.norm(look - pos)
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    half = math.tan(0.5 * 75.0 * math.pi / 180.0)  # camera_for_points' default fov
    for name, P in (("bunny", q), ("ground under it", ground)):
        d = P - pos
        z = d @ fwd
        assert (z > 0).all(), name
        assert (np.abs(d @ up / z) < half).all(), f"the {name} leaves the view vertically"


@needs_viser
def test_a_p2_body_is_drawn_subdivided_and_dragged(tmp_path) -> None:  # noqa: ANN001
    """A P2 scene opens; the mesh node sent to the browser holds every node (corners and edge
    nodes) and the subdivided quadratic surface (4 triangles per boundary face); a drag picks
    nodes (edge nodes among them), the body follows it and the node's vertices move."""
    from fem3d.app.viewer.app import Viewer
    from fem3d.mesh.element import ELEMENTS
    from fem3d.mesh.formats import write_tet_mesh
    from fem3d.mesh.tetmesh import TetMesh, box_tet_mesh

    write_tet_mesh(tmp_path / "beam.mesh", TetMesh(*box_tet_mesh((4, 1, 1), (1.0, 0.25, 0.25))))
    (tmp_path / "p2.toml").write_text(
        'name = "p2_beam"\n[simulation]\nintegrator = "implicit"\ndt = 0.01\n'
        '[[bodies]]\nmesh = "beam.mesh"\nelement = "p2"\n'
        'material = { model = "neo_hookean", E = 1e5, nu = 0.3, density = 1000.0 }\n'
        'pins = [{ select = { box = [[-1, -1, -1], [1e-6, 1, 1]] } }]\n')
    p2 = ELEMENTS["p2"]
    with Viewer(str(tmp_path / "p2.toml"), port=0, realtime=False, run_unwatched=True,
                push_hz=30.0) as v:
        wait_for(lambda: v.snapshot()["steps"] > 2, 60, "steps")
        sim = v._sim
        assert sim.model.element is p2
        T = sim.model.T
        handle = v._graph.mesh_handle
        faces = np.asarray(handle.faces)
        assert faces.shape == (4 * p2.boundary_faces(T).shape[0], 3)
        assert np.array_equal(faces, p2.surface_triangles(T))
        assert np.asarray(handle.vertices).shape == (sim.model.n_vertices, 3) == (81, 3)
        assert np.isin(faces, T[:, 4:]).any()  # the edge nodes are drawn
        q = v.positions()
        tip = int(np.argmax(q[:, 0] + q[:, 1] + q[:, 2]))  # a corner at the free end
        shown0 = np.asarray(handle.vertices, dtype=np.float64)[tip].copy()
        target = q[tip] + np.array([0.0, 0.3, 0.0])
        v.set_pick_radius(0.2)
        v.begin_pull(q[tip], target)
        ids = np.asarray(v.snapshot()["pull"]["ids"])
        assert tip in ids and np.isin(ids, T[:, 4:]).any()  # edge nodes picked too

        def followed() -> Any:
            y = float(np.asarray(handle.vertices, dtype=np.float64)[tip, 1])
            return y > shown0[1] + 0.1 or f"tip drawn at y {y:.4f} (from {shown0[1]:.4f})"

        wait_for(followed, 60, "the drawn P2 body to follow the drag")
        assert v.positions()[tip, 1] > q[tip, 1] + 0.1
        v.end_pull()
        wait_for(lambda: v.snapshot()["pull"] is None, 10, "the release")
        snap = v.snapshot()
        assert snap["error"] is None and v.exceptions == [], (snap["error"], v.exceptions)
