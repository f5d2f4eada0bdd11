"""Interactive browser viewer (``fem3d view``), built on viser.

The viewer runs a :class:`fem3d.simulation.Simulation` in a background thread and shows it
in a web page (three.js through viser). Drag the mesh with the left mouse button to pull
it with a zero-rest-length spring; the panel has buttons, hotkeys, material sliders, a
status line and a live energy plot.

Threads and ownership
---------------------
* **Simulation thread** (:meth:`Viewer._run`): the only thread that touches the
  :class:`~fem3d.simulation.Simulation` object and the only one that writes scene nodes
  and panel elements. It applies queued commands between steps, steps the simulation
  paced to wall time, and pushes display updates at up to ``push_hz``.
* **viser's event loop / thread pool**: GUI and drag callbacks. They never block on a
  simulation step: they take :attr:`Viewer._lock` for a few microseconds to record a
  pull request or queue a command, and wake the simulation thread.

Because only the simulation thread adds, removes and writes scene nodes, a mesh handle
that was replaced (mesh mode or scene switch) is never written after its removal.

Tests read the viewer's state with :meth:`Viewer.snapshot` (a JSON-serialisable dict) and
drive it with the same methods the GUI calls (:meth:`Viewer.toggle_mesh_mode`,
:meth:`Viewer.begin_pull`, ...).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import math
import socket
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fem3d.errors import Fem3dError, InputError, ParameterError, SimulationError

if TYPE_CHECKING:  # pragma: no cover - typing only
    import viser

__all__ = [
    "EnergyHistory",
    "PullState",
    "RealtimePacer",
    "Viewer",
    "add_view_subcommand",
    "HOTKEYS",
    "camera_for_points",
    "plane_quad",
    "energy_text",
    "format_energy",
    "format_status",
    "serve",
    "spring_segments",
]

INTEGRATOR_LABELS = {"linear": "linearly-implicit Euler", "implicit": "backward Euler"}
MESH_MODE_LABELS = {"skin": "skinned display mesh", "sim": "simulation mesh"}

#: Hotkeys. S is not used: viser's camera moves with W/A/S/D (and Q/E), so the mesh
#: toggle is M.
HOTKEYS = {"mesh": "M", "integrator": "N", "pause": "space", "reset": "R"}

#: A mesh update waits until every page has processed the previous one (frame
#: acknowledgement), but never longer than this (seconds): a stalled tab cannot freeze the
#: others for good.
ACK_TIMEOUT = 1.0
_ACK_KEY = "fem3d-frame-ack"

#: The energy plots: (key, label, colour). Each has its own y scale: the pull spring's
#: energy (up to 1e9 on the bunny) must not flatten the elastic energies (1e-6 at rest).
ENERGY_PLOTS = (
    ("kinetic", "T (kinetic)", "#1f77b4"),
    ("potential", "V (strain)", "#ff7f0e"),
    ("total", "T+V", "#2ca02c"),
    ("pull", "pull spring", "#d62728"),
)

#: Samples per energy plot (4 plots x 2 float32 arrays: 6.4 kB per update at 200).
PLOT_POINTS = 200

OBSTACLE_COLOR = (150, 150, 150)

SKIN_COLOR = (236, 196, 150)
SIM_COLOR = (90, 160, 230)
SPRING_COLOR = (220, 40, 40)


# --------------------------------------------------------------------------------------
# Runtime access (late imports: the runtime and viser are imported only when needed)
# --------------------------------------------------------------------------------------


def _load_scene(name: str | Path) -> Any:
    from fem3d.scene.load import load_scene

    return load_scene(str(name))


def _make_simulation(scene: Any, integrator: str | None, backend: str | None) -> Any:
    from fem3d.simulation import Simulation

    sim = Simulation(scene, backend=backend)
    if integrator is not None:
        sim.integrator = integrator
    return sim


def _material_names() -> list[str]:
    try:
        from fem3d.scene.spec import material_names
    except ImportError:  # pragma: no cover - runtime missing
        return []
    return [str(n) for n in material_names()]


def _with_material(scene: Any, name: str) -> Any:
    """``scene`` with every body's material model set to ``name`` (validated)."""
    from fem3d.scene.load import apply_overrides

    keys = {f"bodies[{i}].material.model": name for i in range(len(scene.bodies))}
    return apply_overrides(scene, keys, source="the viewer's material menu")


def _builtin_scene_names() -> list[str]:
    try:
        from fem3d.scene.load import SCENES
    except ImportError:  # pragma: no cover - runtime missing
        return ["bunny", "arma"]
    return [str(name) for name in SCENES]


def _pick(positions: np.ndarray, point: np.ndarray, radius: float) -> np.ndarray:
    from fem3d.physics.constraints import pick_nearest_vertices

    return pick_nearest_vertices(positions, point, radius, nearest_if_empty=True)


def _import_viser() -> Any:
    try:
        import viser
    except ImportError as exc:
        raise InputError(
            "the viewer needs viser: pip install 'fem3d[view]' (viser==1.1.1)"
        ) from exc
    return viser


# --------------------------------------------------------------------------------------
# Small pieces of logic, free of viser (unit-tested)
# --------------------------------------------------------------------------------------


class RealtimePacer:
    """Keep simulated time advancing about as fast as wall time.

    Parameters
    ----------
    max_lag : float
        When the simulation falls behind wall time by more than this (seconds), the
        pacer re-anchors instead of letting it race to catch up.
    enabled : bool
        When False, :meth:`delay` is always 0 (run as fast as possible).
    rate : float
        Simulated seconds per wall-clock second (``< 1``: slow motion).
    """

    def __init__(self, max_lag: float = 0.1, *, enabled: bool = True, rate: float = 1.0) -> None:
        if not rate > 0:
            raise ParameterError(f"time scale must be positive, got {rate}")
        self.max_lag = float(max_lag)
        self.enabled = enabled
        self.rate = float(rate)
        self._anchor: tuple[float, float] | None = None

    def reset(self) -> None:
        """Forget the anchor (after a pause, a reset or a scene switch)."""
        self._anchor = None

    def delay(self, t_sim: float, now: float) -> float:
        """Seconds to wait before the next step.

        Parameters
        ----------
        t_sim : float
            Current simulated time (s).
        now : float
            Current wall-clock time (s, monotonic).
        """
        if not self.enabled:
            return 0.0
        if self._anchor is None:
            self._anchor = (t_sim, now)
            return 0.0
        t0, w0 = self._anchor
        d = (w0 + (t_sim - t0) / self.rate) - now
        if d < -self.max_lag:
            self._anchor = (t_sim, now)
            return 0.0
        return max(d, 0.0)


class EnergyHistory:
    """Rolling history of (t, kinetic, potential, total[, pull]) for the energy plots.

    Parameters
    ----------
    maxlen : int
        Number of samples kept.
    """

    def __init__(self, maxlen: int = 4000) -> None:
        self._rows: collections.deque[tuple[float, ...]] = collections.deque(maxlen=maxlen)

    def __len__(self) -> int:
        return len(self._rows)

    def clear(self) -> None:
        self._rows.clear()

    def append(
        self, t: float, kinetic: float, potential: float, total: float, pull: float = 0.0
    ) -> None:
        self._rows.append(
            (float(t), float(kinetic), float(potential), float(total), float(pull))
        )

    def window(self, seconds: float | None = None) -> tuple[np.ndarray, ...]:
        """The samples of the last ``seconds`` of simulated time.

        Returns
        -------
        (t, kinetic, potential, total) : four (n,) float64 arrays
            ``n >= 1``: an empty history gives one sample of zeros, so the plot always has
            data.
        """
        if not self._rows:
            return tuple(np.zeros(1) for _ in range(4))
        a = np.asarray(self._rows, dtype=np.float64)
        if seconds is not None:
            a = a[a[:, 0] >= a[-1, 0] - seconds]
        return tuple(np.ascontiguousarray(a[:, i]) for i in range(4))

    def recent(self, seconds: float, n: int = 400) -> tuple[np.ndarray, ...]:
        """The real samples of the last ``seconds``, at most ``n`` of them (every k-th).

        Nothing is invented: before the first sample (after a reset) the plot stays
        empty, and between samples uPlot draws straight lines.

        Returns
        -------
        (x, kinetic, potential, total, pull) : five (m,) float64 arrays
            ``x = t - t_newest`` (seconds before the newest sample, ``<= 0``); ``m = 0``
            for an empty history.
        """
        if not self._rows:
            return tuple(np.zeros(0) for _ in range(5))
        a = np.asarray(self._rows, dtype=np.float64)
        a = a[a[:, 0] >= a[-1, 0] - seconds]
        k = max(1, math.ceil(a.shape[0] / int(n)))
        a = a[::-1][::k][::-1]  # keep the newest sample
        x = a[:, 0] - a[-1, 0]
        return (np.ascontiguousarray(x), *(np.ascontiguousarray(a[:, i]) for i in range(1, 5)))

    def latest(self) -> tuple[float, ...] | None:
        """The newest (t, kinetic, potential, total, pull), or None."""
        return self._rows[-1] if self._rows else None

    def rows(self) -> list[tuple[float, float, float, float]]:
        """(t, kinetic, potential, total) per sample."""
        return [r[:4] for r in self._rows]


@dataclasses.dataclass
class PullState:
    """An active mouse pull.

    Attributes
    ----------
    ids : (n_picked,) int64
        Picked simulation vertices.
    grab_point : (3,) float64
        World-space point where the mesh was grabbed.
    target : (3,) float64
        World-space pointer position the vertices are pulled toward.
    start_positions : (n_picked, 3) float64
        Positions of the picked vertices when they were picked.
    generation : int
        Scene generation the pick belongs to (a scene switch invalidates it).
    """

    ids: np.ndarray
    grab_point: np.ndarray
    target: np.ndarray
    start_positions: np.ndarray
    generation: int
    owner: int | None = None


def spring_segments(positions: np.ndarray, ids: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Line segments from each picked vertex to the pull target.

    Parameters
    ----------
    positions : (n_vertices, 3) float64
    ids : (n_picked,) int
    target : (3,) float64

    Returns
    -------
    (n_picked, 2, 3) float32
    """
    p = np.asarray(positions, dtype=np.float64)[np.asarray(ids, dtype=np.int64)]
    seg = np.empty((p.shape[0], 2, 3), dtype=np.float32)
    seg[:, 0] = p
    seg[:, 1] = np.asarray(target, dtype=np.float64).reshape(3)
    return seg


#: Viewing direction (from the object toward the camera) per built-in scene; y is up.
VIEW_DIRECTIONS = {"arma": (0.0, 0.25, -1.0)}  # the armadillo faces -z
DEFAULT_VIEW_DIRECTION = (0.0, 0.25, 1.0)


def camera_for_points(
    points: np.ndarray,
    fov: float = 75.0 * math.pi / 180.0,
    *,
    direction: Sequence[float] = DEFAULT_VIEW_DIRECTION,
    shift: float = 0.3,
) -> dict[str, Any]:
    """A camera that frames a point set, y up.

    Parameters
    ----------
    points : (n, 3) float64
    fov : float
        Vertical field of view (radians).
    direction : (3,) float
        From the box centre toward the camera (need not be unit length).
    shift : float
        Sideways offset of the camera (and its target) in bounding-sphere radii, so the
        object sits left of the centre, clear of the control panel on the right.

    Returns
    -------
    dict
        ``position`` (3,), ``look_at`` (3,), ``near``, ``far``, ``radius`` (bounding-sphere
        radius about the box centre), ``center`` (3,).
    """
    p = np.asarray(points, dtype=np.float64)
    lo, hi = p.min(axis=0), p.max(axis=0)
    center = 0.5 * (lo + hi)
    radius = float(max(np.linalg.norm(hi - lo) * 0.5, 1e-9))
    dist = 1.15 * radius / math.sin(0.5 * fov)
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    right = np.cross(-d, [0.0, 1.0, 0.0])  # camera's right for a y-up view along -d
    n = np.linalg.norm(right)
    right = right / n if n > 1e-12 else np.array([1.0, 0.0, 0.0])
    look_at = center + shift * radius * right
    return {
        "position": look_at + dist * d,
        "look_at": look_at,
        "near": dist * 1e-3,
        "far": dist * 100.0,
        "radius": radius,
        "center": center,
    }


def _nb(text: str) -> str:
    """Non-breaking spaces inside a phrase: the status line wraps only between phrases."""
    return text.replace(" ", "\u00a0")


def format_energy(value: float) -> str:
    """An energy for the panel: ``1.23e-06``, ``0.0123``, ``4.56e+09``; ``0`` for zero."""
    v = float(value)
    if v == 0.0:
        return "0"
    if 1e-3 <= abs(v) < 1e5:
        return f"{v:.4g}"
    return f"{v:.3e}"


def format_status(
    *,
    scene: str,
    integrator: str,
    mesh_mode: str,
    paused: bool,
    error: str | None,
    t: float,
    ms_per_step: float,
    newton_per_step: float,
    steps_per_second: float,
    E: float,
    nu: float,
    rho: float,
    grabbed: int | None = None,
    pick_radius: float | None = None,
) -> str:
    """The panel's markdown status text.

    Phrases are joined by `` · `` and keep their own spaces non-breaking, so a narrow panel
    wraps the line between phrases, never inside one (``t = 1.23 s`` stays whole).
    ``grabbed`` (vertices held by the current drag, None: no drag) and ``pick_radius`` add
    a grabbing line.
    """
    if error is not None:
        state = "**stopped: simulation error** (R resets)"
    else:
        state = "paused" if paused else "running"
    lines = [
        [f"**{scene}**", INTEGRATOR_LABELS.get(integrator, integrator),
         MESH_MODE_LABELS.get(mesh_mode, mesh_mode), state],
        [f"t = {t:.2f} s", f"{ms_per_step:.1f} ms/step",
         f"{newton_per_step:.2f} Newton it/step", f"{steps_per_second:.0f} steps/s"],
        [f"E = {E:.4g}", f"ν = {nu:.3g}", f"ρ = {rho:.3g}"],
    ]
    if pick_radius is not None or grabbed is not None:
        grab = []
        if pick_radius is not None:
            grab.append(f"grab radius {pick_radius:.3g}")
        grab.append("not dragging" if grabbed is None else
                    f"dragging {grabbed} " + ("vertex" if grabbed == 1 else "vertices"))
        lines.append(grab)
    return "  \n".join(" · ".join(_nb(p) for p in line) for line in lines)


def energy_text(latest: Sequence[float] | None) -> str:
    """The current energies above the plots (markdown), one phrase per energy."""
    if latest is None:
        return "energies: none yet"
    _t, T, V, tot, pull = (list(latest) + [0.0])[:5]
    parts = [f"T = {format_energy(T)}", f"V = {format_energy(V)}",
             f"T+V = {format_energy(tot)}", f"pull = {format_energy(pull)}"]
    return "now: " + " · ".join(_nb(p) for p in parts)


def _free_port(host: str) -> int:
    """A port nobody listens on now (``--port 0``)."""
    with socket.socket(_family(host), socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def _family(host: str) -> socket.AddressFamily:
    return socket.AF_INET6 if ":" in host else socket.AF_INET


def _check_port_free(host: str, port: int) -> None:
    """Raise InputError (one line) when ``host:port`` cannot be listened on."""
    with socket.socket(_family(host), socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as exc:
            why = "is in use" if exc.errno in (98, 48) else f"cannot be used ({exc.strerror})"
            raise InputError(
                f"port {port} on {host} {why}; pick another with --port N, "
                "or --port 0 for a free one"
            ) from None


def plane_quad(point: np.ndarray, normal: np.ndarray, center: np.ndarray,
               half: float) -> tuple[np.ndarray, np.ndarray]:
    """A square piece of a plane for display: ``2 half`` wide, centred on ``center``'s
    projection onto the plane.

    Returns
    -------
    vertices : (4, 3) float64
    faces : (2, 3) uint32
    """
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    c = np.asarray(center, dtype=np.float64)
    c = c - ((c - np.asarray(point, dtype=np.float64)) @ n) * n
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    corners = [c + half * (sa * a + sb * b) for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    return np.asarray(corners), np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)


def _surface_faces(sim: Any) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(sim.surface_faces, dtype=np.uint32))


# --------------------------------------------------------------------------------------
# The viewer
# --------------------------------------------------------------------------------------


class Viewer:
    """A viser server showing a running simulation.

    Parameters
    ----------
    scene : str or Path
        Built-in scene name (``"bunny"``, ``"arma"``) or a tet-mesh path.
    host, port : str, int
        Where viser listens (``port=0``: any free port).
    integrator : {"linear", "implicit"}, optional
        Overrides the scene's integrator.
    backend : {"numpy", "c"}, optional
        Kernel back end passed to :class:`~fem3d.simulation.Simulation`.
    realtime : bool
        Pace simulated time to wall time (False: step as fast as possible).
    push_hz : float
        Maximum rate of mesh updates sent to the browser.
    plot_hz : float
        Maximum rate of status/plot updates.
    plot_window : float
        Seconds of simulated time shown in the energy plot.
    mesh_mode : {"skin", "sim"}
        Mesh shown first: the skinned display mesh or the simulation mesh's surface.
    time_scale : float
        Simulated seconds per wall-clock second when ``realtime`` (``< 1``: slow motion).
    """

    def __init__(
        self,
        scene: str | Path = "bunny",
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        integrator: str | None = None,
        backend: str | None = None,
        realtime: bool = True,
        push_hz: float = 30.0,
        plot_hz: float = 5.0,
        plot_window: float = 10.0,
        mesh_mode: str = "skin",
        time_scale: float = 1.0,
    ) -> None:
        if mesh_mode not in MESH_MODE_LABELS:
            raise ParameterError(
                f"mesh_mode must be one of {sorted(MESH_MODE_LABELS)}, got {mesh_mode!r}"
            )
        if integrator is not None and integrator not in INTEGRATOR_LABELS:
            raise ParameterError(
                f"integrator must be one of {sorted(INTEGRATOR_LABELS)}, got {integrator!r}"
            )
        if not 0 <= int(port) <= 65535:
            raise ParameterError(f"port must be in [0, 65535], got {port}")
        if push_hz <= 0 or plot_hz <= 0:
            raise ParameterError("push_hz and plot_hz must be positive")
        self.host = host
        self.port = int(port)
        self.backend = backend
        self.push_hz = float(push_hz)
        self.plot_hz = float(plot_hz)
        self.plot_window = float(plot_window)
        self._pacer = RealtimePacer(enabled=realtime, rate=time_scale)

        # Loaded now so that bad input fails before a server starts.
        self._scene = _load_scene(scene)
        self._scene_label = str(scene)
        self._sim = _make_simulation(self._scene, integrator, backend)

        # Shared state (guarded by _lock; never held across a step or a viser write).
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._commands: collections.deque[Callable[[], None]] = collections.deque()
        self._generation = 0
        self._pull: PullState | None = None
        self._pull_version = 0
        self._q_view = np.array(self._sim.q, dtype=np.float64, copy=True)
        self._paused = False
        self._error: str | None = None
        self._errors: list[str] = []
        self._mesh_mode = mesh_mode
        self._history = EnergyHistory()
        self._recent: collections.deque[tuple[float, float, int]] = collections.deque(maxlen=30)
        self._steps = 0
        self._pushes = 0
        self._t = 0.0
        self._material = self._scene_material()
        self._drag_events = 0
        self._last_gui_pause = -1e9
        self._pick_radius = float(self._sim.pick_radius)
        #: Tracebacks of exceptions caught on the viewer's threads (tests assert it stays
        #: empty; each is also printed).
        self.exceptions: list[str] = []
        # Frame acknowledgements: client id -> [last seq sent, last seq acked, time sent].
        self._acks: dict[int, list[float]] = {}
        self._ack_seq = 0
        self._acked = 0
        self._held_back = 0
        self._history_reset()

        # Simulation-thread-only state.
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self._mesh_handle: Any = None
        self._mesh_handle_mode: str | None = None
        self._spring_handle: Any = None
        self._obstacle_handles: list[Any] = []
        self._obstacle_shown: list[np.ndarray | None] = []
        self._spring_key: tuple[int, ...] | None = None
        self._gui: dict[str, Any] = {}
        self._notifications: list[Any] = []
        self._applied_pull_version = -1
        self._applied_generation = -1
        self._last_push = 0.0
        self._last_plot = 0.0
        self._mesh_serial = 0  # incremented whenever the mesh node is replaced
        self._shown: tuple[Any, Any] | None = None  # (mesh serial, pull) last sent
        self._shown_q = np.zeros((0, 3))
        self._gui_dirty = True
        self._camera: dict[str, Any] = self._scene_camera()

    # ---------------------------------------------------------------- properties
    @property
    def server(self) -> viser.ViserServer:
        """The viser server (after :meth:`start`)."""
        return self._server

    @property
    def url(self) -> str:
        host = "localhost" if self.host in ("0.0.0.0", "::") else self.host
        return f"http://{host}:{self._server.get_port()}"

    @property
    def camera(self) -> dict[str, Any]:
        """The camera the viewer sets for the current scene (``camera_for_points``)."""
        with self._lock:
            return dict(self._camera)

    def _scene_material(self) -> dict[str, float]:
        m = self._sim.model  # summary values (a scene may give its materials by params)
        return {"E": float(m.E), "nu": float(m.nu), "rho": float(m.rho)}

    def _radius_range(self) -> tuple[float, float, float]:
        """(min, max, initial) of the grab-radius slider: 0.1 % to 20 % of the mesh's
        bounding-box diagonal, starting at the scene's ``pick_radius``."""
        q = np.asarray(self._sim.q, dtype=np.float64)
        diag = float(np.linalg.norm(q.max(axis=0) - q.min(axis=0))) or 1.0
        r0 = float(self._sim.pick_radius)
        lo, hi = min(1e-3 * diag, r0), max(0.2 * diag, r0)
        return lo, hi, r0

    def _history_reset(self) -> None:
        """Start the energy history at the current state (a real sample, not padding)."""
        self._history.clear()
        try:
            e = self._sim.energies()
        except Exception:  # noqa: BLE001 - an exotic simulation without energies
            return
        self._history.append(float(self._sim.t), e["kinetic"], e["potential"], e["total"],
                             e.get("pull", 0.0))

    def _log_exception(self) -> None:
        text = traceback.format_exc()
        print(text, end="", file=sys.stderr, flush=True)
        with self._lock:
            self.exceptions.append(text)

    # ---------------------------------------------------------------- life cycle
    def start(self) -> str:
        """Start the viser server and the simulation thread; return the URL.

        Raises
        ------
        InputError
            The port is taken (viser would silently move to the next free one; an SSH
            forward to the requested port would then reach something else).
        """
        viser = _import_viser()
        port = _free_port(self.host) if self.port == 0 else self.port
        _check_port_free(self.host, port)
        self._server = viser.ViserServer(host=self.host, port=port, verbose=False)
        if self._server.get_port() != port:
            got = self._server.get_port()
            self._server.stop()
            self._server = None
            raise InputError(f"port {port} on {self.host} is in use (viser moved to {got}); "
                             "pick another with --port N, or --port 0 for a free one")
        self._server.scene.set_up_direction("+y")
        self._build_gui()
        self._apply_camera(initial=True)
        self._rebuild_mesh()
        self._rebuild_obstacles()
        self._server.on_client_connect(self._on_client_connect)
        self._server.on_client_disconnect(self._on_client_disconnect)
        self._thread = threading.Thread(target=self._run, name="fem3d-view-sim", daemon=True)
        self._thread.start()
        return self.url

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the simulation thread and the server (idempotent)."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout)
        if self._server is not None:
            self._server.stop()
            self._server = None

    def wait(self) -> None:
        """Block until :meth:`stop` (KeyboardInterrupt propagates)."""
        while not self._stop.wait(0.25):
            pass

    def __enter__(self) -> Viewer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ---------------------------------------------------------------- public actions
    def _post(self, command: Callable[[], None]) -> None:
        with self._lock:
            self._commands.append(command)
        self._wake.set()

    def toggle_mesh_mode(self) -> None:
        """Switch between the skinned display mesh and the simulation mesh (``S``)."""
        self._post(self._do_toggle_mesh_mode)

    def toggle_integrator(self) -> None:
        """Switch linearly-implicit / backward Euler (``N``)."""
        self._post(self._do_toggle_integrator)

    def toggle_pause(self) -> None:
        """Pause or resume (space)."""
        self._post(self._do_toggle_pause)

    def set_paused(self, paused: bool) -> None:
        self._post(lambda: self._do_set_paused(paused))

    def reset(self) -> None:
        """Back to rest, t = 0; clears an error (``R``)."""
        self._post(self._do_reset)

    def switch_material(self, name: str) -> None:
        """Change every body's material model (a name of :func:`fem3d.physics.materials.names`),
        keeping the motion: positions, velocities and time carry over."""
        self._post(lambda: self._do_switch_material(name))

    def switch_scene(self, name: str) -> None:
        """Load another scene (runs on the simulation thread)."""
        self._post(lambda: self._do_switch_scene(name))

    def set_material(
        self, E: float | None = None, nu: float | None = None, rho: float | None = None
    ) -> None:
        """Change material parameters live."""
        self._post(lambda: self._do_set_material(E, nu, rho))

    def begin_pull(
        self,
        grab_point: Sequence[float],
        target: Sequence[float] | None = None,
        owner: int | None = None,
    ) -> None:
        """Pick the vertices within the grab radius of ``grab_point``.

        The grab radius starts at the scene's ``pick_radius`` and follows the panel's
        slider (:meth:`set_pick_radius`); the nearest vertex is picked when none is
        within it.

        Parameters
        ----------
        grab_point : (3,) float
            World-space point on the displayed mesh.
        target : (3,) float, optional
            Initial pull target (default: the grab point).
        owner : int, optional
            The browser client that drags (its moves and release then apply to this pull
            only, so two clients dragging at once cannot end each other's drag).
        """
        grab = np.asarray(grab_point, dtype=np.float64).reshape(3)
        tgt = grab.copy() if target is None else np.asarray(target, dtype=np.float64).reshape(3)
        if not (np.isfinite(grab).all() and np.isfinite(tgt).all()):
            return
        with self._lock:
            q = self._q_view
            ids = _pick(q, grab, self._pick_radius)
            self._pull = PullState(
                ids=ids,
                grab_point=grab,
                target=tgt,
                start_positions=q[ids].copy(),
                generation=self._generation,
                owner=owner,
            )
            self._gui_dirty = True
            self._pull_version += 1
            self._drag_events += 1
        self._wake.set()

    def move_pull(self, target: Sequence[float], owner: int | None = None) -> None:
        """Move the pull target (world space)."""
        tgt = np.asarray(target, dtype=np.float64).reshape(3)
        if not np.isfinite(tgt).all():
            return
        with self._lock:
            if self._pull is None or (owner is not None and self._pull.owner != owner):
                return
            self._pull.target = tgt
            self._pull_version += 1
            self._drag_events += 1
        self._wake.set()

    def end_pull(self, owner: int | None = None) -> None:
        """Release the pull."""
        with self._lock:
            if self._pull is None or (owner is not None and self._pull.owner != owner):
                return
            self._pull = None
            self._gui_dirty = True
            self._pull_version += 1
            self._drag_events += 1
        self._wake.set()

    def set_pick_radius(self, radius: float) -> None:
        """Grab radius (world units) for the next drag."""
        r = float(radius)
        if not (math.isfinite(r) and r > 0):
            raise ParameterError(f"grab radius must be positive, got {radius}")
        with self._lock:
            self._pick_radius = r
            self._gui_dirty = True
        self._wake.set()

    # ---------------------------------------------------------------- state for tests
    def snapshot(self) -> dict[str, Any]:
        """A JSON-serialisable copy of the viewer's state.

        Keys: ``scene``, ``integrator``, ``mesh_mode``, ``paused``, ``error``, ``errors``,
        ``t``, ``steps``, ``pushes``, ``ms_per_step``, ``newton_per_step``,
        ``steps_per_second``, ``material``, ``pull`` (None or ``ids``, ``grab_point``,
        ``target``, ``start_positions``, ``positions``), ``energy`` (list of
        ``[t, T, V, T+V]``), ``drag_events``, ``generation``, ``pick_radius``, ``acked``
        (mesh updates the pages acknowledged), ``held_back`` (mesh updates not sent because
        a page had not processed the previous one), ``clients``, ``exceptions``.
        """
        with self._lock:
            pull = None
            if self._pull is not None:
                p = self._pull
                pull = {
                    "ids": p.ids.tolist(),
                    "grab_point": p.grab_point.tolist(),
                    "target": p.target.tolist(),
                    "start_positions": p.start_positions.tolist(),
                    "positions": self._q_view[p.ids].tolist(),
                }
            stats = self._stats_locked()
            return {
                "scene": self._scene.name,
                "integrator": str(self._sim_integrator),
                "mesh_mode": self._mesh_mode,
                "paused": self._paused,
                "error": self._error,
                "errors": list(self._errors),
                "t": self._t,
                "steps": self._steps,
                "pushes": self._pushes,
                **stats,
                "material": dict(self._material),
                "material_model": self._material_model(),
                "pull": pull,
                "energy": [list(r) for r in self._history.rows()],
                "drag_events": self._drag_events,
                "generation": self._generation,
                "pick_radius": self._pick_radius,
                "acked": self._acked,
                "held_back": self._held_back,
                "clients": len(self._acks),
                "exceptions": list(self.exceptions),
            }

    def positions(self) -> np.ndarray:
        """(n_vertices, 3) float64: the latest simulation positions (a copy)."""
        with self._lock:
            return self._q_view.copy()

    @property
    def _sim_integrator(self) -> str:
        return str(self._sim.integrator)

    def _stats_locked(self) -> dict[str, float]:
        if not self._recent:
            return {"ms_per_step": 0.0, "newton_per_step": 0.0, "steps_per_second": 0.0}
        r = np.asarray(self._recent, dtype=np.float64)
        span = r[-1, 0] - r[0, 0]
        rate = (len(r) - 1) / span if len(r) > 1 and span > 0 else 0.0
        return {
            "ms_per_step": float(1e3 * r[:, 1].mean()),
            "newton_per_step": float(r[:, 2].mean()),
            "steps_per_second": float(rate),
        }

    # ---------------------------------------------------------------- GUI
    def _build_gui(self) -> None:
        gui = self._server.gui
        g: dict[str, Any] = {}
        g["status"] = gui.add_markdown("starting…")
        g["mesh"] = gui.add_button(f"Mesh: skinned ⇄ simulation ({HOTKEYS['mesh']})")
        g["integrator"] = gui.add_button("Integrator: linear ⇄ backward Euler (N)")
        g["pause"] = gui.add_button("Pause / resume (space)")
        g["reset"] = gui.add_button("Reset (R)")
        names = _builtin_scene_names()
        if self._scene_label not in names:
            names.append(self._scene_label)
        g["scene"] = gui.add_dropdown("Scene", tuple(names), initial_value=self._scene_label)
        models = _material_names()
        current = self._material_model()
        if current not in models:
            models.append(current)
        g["material"] = gui.add_dropdown("Material", tuple(models), initial_value=current)
        E, nu, rho = self._material["E"], self._material["nu"], self._material["rho"]
        g["E_value"] = gui.add_number("Young's modulus E", initial_value=E, min=1e-12)
        g["E"] = gui.add_slider(
            "E (slider)", min=E / 10.0, max=E * 10.0, step=E / 10.0, initial_value=E
        )
        g["nu"] = gui.add_slider("Poisson's ratio", min=0.0, max=0.49, step=0.01, initial_value=nu)
        g["rho"] = gui.add_slider(
            "Density", min=rho / 10.0, max=rho * 10.0, step=rho / 10.0, initial_value=rho
        )
        lo, hi, r0 = self._radius_range()
        g["radius"] = gui.add_slider(
            "Grab radius", min=lo, max=hi, step=(hi - lo) / 200.0, initial_value=r0
        )
        g["energy"] = gui.add_markdown("")
        x, *series = self._history.recent(self.plot_window)
        for (key, label, color), y in zip(ENERGY_PLOTS, series, strict=True):
            g[f"plot_{key}"] = gui.add_uplot(
                data=(x, y),
                series=({"label": "t - now (s)"}, {"label": label, "stroke": color, "width": 2}),
                scales={"x": {"time": False, "auto": False, "range": [-self.plot_window, 0.0]},
                        "y": {"auto": True}},
                legend={"show": False},
                title=label,
                aspect=3.0,
            )
        g["mesh"].on_click(lambda _e: self.toggle_mesh_mode())
        g["integrator"].on_click(lambda _e: self.toggle_integrator())
        g["pause"].on_click(lambda _e: self._gui_toggle_pause())
        g["reset"].on_click(lambda _e: self.reset())

        def _on_scene(event: Any) -> None:
            if event.client is not None:
                self.switch_scene(str(event.target.value))

        def _on_E(event: Any) -> None:
            if event.client is not None:
                self.set_material(E=float(event.target.value))

        def _on_E_value(event: Any) -> None:
            if event.client is not None:
                value = float(event.target.value)
                if value > 0 and math.isfinite(value):
                    self.set_material(E=value)

        def _on_radius(event: Any) -> None:
            if event.client is not None:
                self.set_pick_radius(float(event.target.value))

        def _on_nu(event: Any) -> None:
            if event.client is not None:
                self.set_material(nu=float(event.target.value))

        def _on_rho(event: Any) -> None:
            if event.client is not None:
                self.set_material(rho=float(event.target.value))

        g["scene"].on_update(_on_scene)

        def _on_material(event: Any) -> None:
            if event.client is not None:
                self.switch_material(str(event.target.value))

        g["material"].on_update(_on_material)
        g["E"].on_update(_on_E)
        g["E_value"].on_update(_on_E_value)
        g["radius"].on_update(_on_radius)
        g["nu"].on_update(_on_nu)
        g["rho"].on_update(_on_rho)

        for label, key, action in (
            ("Toggle skinned / simulation mesh", HOTKEYS["mesh"], self.toggle_mesh_mode),
            ("Toggle linearly-implicit / backward Euler", HOTKEYS["integrator"],
             self.toggle_integrator),
            ("Pause / resume", HOTKEYS["pause"], self._gui_toggle_pause),
            ("Reset", HOTKEYS["reset"], self.reset),
        ):
            cmd = gui.add_command(label, hotkey=key)
            cmd.on_trigger(lambda _e, a=action: a())
        self._gui = g

    def _sync_E_widgets(self, E: float) -> None:
        """Show ``E`` in the number field and on the slider (re-centring the slider's range
        on a value typed outside it)."""
        g = self._gui
        if abs(float(g["E_value"].value) - E) > 1e-9 * E:
            g["E_value"].value = E
        if not (g["E"].min <= E <= g["E"].max):
            g["E"].min, g["E"].max, g["E"].step = E / 10.0, E * 10.0, E / 10.0
        if abs(float(g["E"].value) - E) > 1e-9 * E:
            g["E"].value = E

    def _gui_toggle_pause(self) -> None:
        """Pause/resume from the panel: a focused button receives space as a click too, so
        the hotkey and the click of one key press count once."""
        now = time.monotonic()
        with self._lock:
            if now - self._last_gui_pause < 0.3:
                return
            self._last_gui_pause = now
        self.toggle_pause()

    def _on_client_connect(self, client: Any) -> None:
        self._register_acks(client)
        with self._lock:
            cam = dict(self._camera)
            error = self._error
        self._set_client_camera(client, cam)
        if error is not None:
            self._notify_client(client, error)

    def _on_client_disconnect(self, client: Any) -> None:
        with self._lock:
            self._acks.pop(int(client.client_id), None)
            if self._pull is not None and self._pull.owner == int(client.client_id):
                self._pull = None
                self._pull_version += 1

    def _register_acks(self, client: Any) -> None:
        """Listen for the page's frame acknowledgements (see :meth:`_request_acks`)."""
        try:
            from viser import _messages as vm

            conn = client._websock_connection
        except (ImportError, AttributeError):  # pragma: no cover - another viser
            return
        cid = int(client.client_id)

        def got(_client_id: int, message: Any) -> None:
            uid = str(getattr(message, "request_uuid", ""))
            if not uid.startswith("fem3d-ack-"):
                return
            seq = int(uid.rsplit("-", 1)[1])
            with self._lock:
                st = self._acks.get(cid)
                if st is not None and seq > st[1]:
                    st[1] = seq
                    self._acked += 1
            self._wake.set()

        conn.register_handler(vm.LocalStorageGetItemResponseMessage, got)
        with self._lock:
            self._acks[cid] = [0, 0, 0.0]

    def _clients_busy(self, now: float) -> bool:
        """True while some page has not yet processed the last mesh update (for at most
        :data:`ACK_TIMEOUT` seconds)."""
        with self._lock:
            return any(st[1] < st[0] and now - st[2] < ACK_TIMEOUT for st in self._acks.values())

    def _request_acks(self, now: float) -> None:
        """Ask every page to answer once it has processed the messages sent so far.

        The request is a localStorage read, which viser's client answers from the page's
        main thread (the one that draws): a page busy drawing answers late, and the next
        mesh update waits for the answer. This is the viewer's backpressure: the pages get
        the updates they can draw instead of a queue of stale ones.
        """
        try:
            from viser import _messages as vm
        except ImportError:  # pragma: no cover
            return
        self._ack_seq += 1
        seq = self._ack_seq
        for client in self._server.get_clients().values():
            cid = int(client.client_id)
            with self._lock:
                st = self._acks.get(cid)
                if st is None:
                    continue
                st[0], st[2] = seq, now
            try:
                client._websock_connection.queue_message(
                    vm.LocalStorageGetItemRequestMessage(key=_ACK_KEY,
                                                         request_uuid=f"fem3d-ack-{seq}")
                )
            except Exception:  # noqa: BLE001 - a closing client
                with self._lock:
                    self._acks.pop(cid, None)

    @staticmethod
    def _set_client_camera(client: Any, cam: dict[str, Any]) -> None:
        client.camera.near = float(cam["near"])
        client.camera.far = float(cam["far"])
        client.camera.position = tuple(cam["position"])
        client.camera.look_at = tuple(cam["look_at"])

    def _scene_camera(self) -> dict[str, Any]:
        direction = VIEW_DIRECTIONS.get(str(self._scene.name), DEFAULT_VIEW_DIRECTION)
        return camera_for_points(self._sim.q, direction=direction)

    def _apply_camera(self, *, initial: bool = False) -> None:
        cam = self._scene_camera()
        with self._lock:
            self._camera = cam
        ic = self._server.initial_camera
        ic.near = float(cam["near"])
        ic.far = float(cam["far"])
        ic.position = tuple(cam["position"])
        ic.look_at = tuple(cam["look_at"])
        if not initial:
            for client in self._server.get_clients().values():
                self._set_client_camera(client, cam)

    def _error_text(self, error: str) -> str:
        hint = ""
        if self._sim_integrator == "linear":
            hint = (
                " (the linearly-implicit integrator is unstable here:"
                " press N for backward Euler)"
            )
        return (
            f"{error}. The viewer paused at the last good step; press R (Reset) to restart"
            f"{hint}."
        )

    def _notify_client(self, client: Any, error: str) -> None:
        try:
            h = client.add_notification(
                "Simulation stopped", self._error_text(error), color="red"
            )
        except Exception:  # noqa: BLE001 - a closing client must not kill the sim thread
            return
        with self._lock:  # also called from viser's thread (client connect)
            self._notifications.append(h)

    def _notify_all(self, title: str, body: str, color: str = "blue", seconds: float = 6.0) -> None:
        for client in self._server.get_clients().values():
            try:
                client.add_notification(title, body, color=color, auto_close_seconds=seconds)
            except Exception:  # noqa: BLE001
                pass

    def _clear_notifications(self) -> None:
        with self._lock:
            handles, self._notifications = self._notifications, []
        for h in handles:
            try:
                h.remove()
            except Exception:  # noqa: BLE001 - the client may be gone
                pass

    # ---------------------------------------------------------------- scene graph
    def _display_positions(self) -> np.ndarray:
        if self._mesh_handle_mode == "skin":
            return np.asarray(self._sim.skin_positions(), dtype=np.float64)
        return np.asarray(self._sim.q, dtype=np.float64)

    def _has_skin(self) -> bool:
        return bool(self._sim.has_skin)

    def _rebuild_mesh(self) -> None:
        """Replace the displayed mesh node (simulation thread only)."""
        mode = self._mesh_mode if self._has_skin() else "sim"
        if self._mesh_handle is not None:
            old, self._mesh_handle = self._mesh_handle, None
            old.remove()
        self._mesh_handle_mode = mode
        self._mesh_serial += 1
        if mode == "skin":
            verts = np.asarray(self._sim.skin_positions(), dtype=np.float64)
            faces = np.asarray(self._sim.display_faces, dtype=np.uint32)
            handle = self._server.scene.add_mesh_simple(
                "/fem3d/skin", verts, faces, color=SKIN_COLOR, flat_shading=False,
                cast_shadow=False, receive_shadow=False,
            )
        else:
            verts = np.asarray(self._sim.q, dtype=np.float64)
            handle = self._server.scene.add_mesh_simple(
                "/fem3d/sim", verts, _surface_faces(self._sim), color=SIM_COLOR, flat_shading=True,
                cast_shadow=False, receive_shadow=False,
            )

        async def _on_drag(event: Any) -> None:
            owner = getattr(event, "client_id", None)
            if event.phase == "start":
                self.begin_pull(event.start_position, event.end_position, owner=owner)
            elif event.phase == "update":
                self.move_pull(event.end_position, owner=owner)
            else:
                self.end_pull(owner=owner)

        handle.on_drag("left")(_on_drag)
        self._mesh_handle = handle

    def _rebuild_obstacles(self) -> None:
        """Draw the contact scene's obstacles (simulation thread only): planes as squares
        three mesh diagonals wide, mesh obstacles at their current positions."""
        for h in self._obstacle_handles:
            h.remove()
        self._obstacle_handles, self._obstacle_shown = [], []
        contact = getattr(self._sim, "contact", None)
        if contact is None:
            return
        q = np.asarray(self._sim.q, dtype=np.float64)
        center = 0.5 * (q.min(axis=0) + q.max(axis=0))
        half = 1.5 * float(np.linalg.norm(q.max(axis=0) - q.min(axis=0)))
        for k, plane in enumerate(contact.contact.planes):
            V, F = plane_quad(plane.point, plane.normal, center, half)
            self._obstacle_handles.append(self._server.scene.add_mesh_simple(
                f"/fem3d/obstacles/plane_{k}", V, F, color=OBSTACLE_COLOR, opacity=0.5,
                side="double", cast_shadow=False, receive_shadow=False))
            self._obstacle_shown.append(None)  # static
        for k, (_name, V, F) in enumerate(self._sim.obstacles()):
            V = np.asarray(V, dtype=np.float64)
            self._obstacle_handles.append(self._server.scene.add_mesh_simple(
                f"/fem3d/obstacles/mesh_{k}", V, np.asarray(F, dtype=np.uint32),
                color=OBSTACLE_COLOR, flat_shading=True, side="double", cast_shadow=False,
                receive_shadow=False))
            self._obstacle_shown.append(V.copy())

    def _update_obstacles(self) -> None:
        """Move the mesh obstacles that moved (keyframed); inside ``atomic()``."""
        moving = [i for i, v in enumerate(self._obstacle_shown) if v is not None]
        if not moving:
            return
        for i, (_name, V, _F) in zip(moving, self._sim.obstacles(), strict=True):
            V = np.asarray(V, dtype=np.float64)
            if not np.array_equal(V, self._obstacle_shown[i]):
                self._obstacle_handles[i].vertices = V.astype(np.float32)
                self._obstacle_shown[i] = V.copy()

    def _update_spring(self, pull: PullState | None, q: np.ndarray) -> None:
        if pull is None or pull.generation != self._generation or pull.ids.size == 0:
            if self._spring_handle is not None:
                self._spring_handle.remove()
                self._spring_handle = None
                self._spring_key = None
            return
        seg = spring_segments(q, pull.ids, pull.target)
        key = tuple(pull.ids.tolist())
        if self._spring_handle is None or self._spring_key != key:
            if self._spring_handle is not None:
                self._spring_handle.remove()
            self._spring_handle = self._server.scene.add_line_segments(
                "/fem3d/spring", seg, SPRING_COLOR, thickness=3.0, thickness_units="screen"
            )
            self._spring_key = key
        else:
            self._spring_handle.points = seg

    # ---------------------------------------------------------------- commands (sim thread)
    def _do_toggle_mesh_mode(self) -> None:
        with self._lock:
            self._mesh_mode = "sim" if self._mesh_mode == "skin" else "skin"
        if not self._has_skin():
            self._notify_all("No skinned mesh", "This scene has only its simulation mesh.")
        self._rebuild_mesh()
        self._gui_dirty = True

    def _do_toggle_integrator(self) -> None:
        new = "implicit" if self._sim_integrator == "linear" else "linear"
        try:
            self._sim.integrator = new
        except Fem3dError as exc:  # e.g. a contact scene refuses the linearly-implicit scheme
            self._notify_all("Integrator not switched", str(exc), color="yellow", seconds=8.0)
            return
        self._gui_dirty = True

    def _do_set_paused(self, paused: bool) -> None:
        with self._lock:
            self._paused = paused
        self._pacer.reset()
        self._gui_dirty = True

    def _do_toggle_pause(self) -> None:
        with self._lock:
            self._paused = not self._paused
            if not self._paused:
                self._error = None
        self._pacer.reset()
        self._gui_dirty = True

    def _do_reset(self) -> None:
        self._sim.reset()
        self._applied_pull_version = -1  # re-apply an active pull after the reset
        with self._lock:
            self._error = None
            self._paused = False
            self._history_reset()
            self._recent.clear()
            self._t = 0.0
            self._q_view = np.array(self._sim.q, dtype=np.float64, copy=True)
        self._clear_notifications()
        self._pacer.reset()
        self._gui_dirty = True

    def _do_set_material(self, E: float | None, nu: float | None, rho: float | None) -> None:
        try:
            self._sim.set_material(E=E, nu=nu, rho=rho)
        except Fem3dError as exc:
            self._notify_all("Material not changed", str(exc), color="yellow")
            return
        with self._lock:
            for k, v in (("E", E), ("nu", nu), ("rho", rho)):
                if v is not None:
                    self._material[k] = float(v)
        if E is not None and self._gui:
            self._sync_E_widgets(float(E))
        self._gui_dirty = True

    def _material_model(self) -> str:
        return str(self._scene.bodies[0].material.model)

    def _do_switch_material(self, name: str) -> None:
        if name == self._material_model():
            return
        old = self._sim
        try:
            scene = _with_material(self._scene, name)
            sim = _make_simulation(scene, self._sim_integrator, self.backend)
            sim.set_state(old.q, old.v, old.t, old.step_index)
            with self._lock:
                mat = dict(self._material)
            if mat != self._scene_material():  # keep the panel's edits (body 0's values)
                sim.set_material(E=mat["E"], nu=mat["nu"], rho=mat["rho"])
        except Fem3dError as exc:
            self._notify_all("Material not changed", str(exc), color="yellow", seconds=10.0)
            self._gui["material"].value = self._material_model()
            return
        with self._lock:
            self._scene, self._sim = scene, sim
            self._error = None
        self._applied_pull_version = -1  # re-apply an active pull to the new simulation
        self._pacer.reset()
        self._gui_dirty = True

    def _do_switch_scene(self, name: str) -> None:
        if name == self._scene_label:
            return
        try:
            scene = _load_scene(name)
            sim = _make_simulation(scene, None, self.backend)
        except Fem3dError as exc:
            self._notify_all("Could not load scene", str(exc), color="red", seconds=10.0)
            self._gui["scene"].value = self._scene_label
            return
        self._clear_notifications()
        with self._lock:
            self._scene, self._sim, self._scene_label = scene, sim, name
            self._generation += 1
            self._pull = None
            self._pull_version += 1
            self._error = None
            self._paused = False
            self._history_reset()
            self._recent.clear()
            self._t = 0.0
            self._q_view = np.array(sim.q, dtype=np.float64, copy=True)
            self._material = self._scene_material()
            self._pick_radius = float(self._sim.pick_radius)
        self._applied_pull_version = -1
        self._rebuild_mesh()
        self._rebuild_obstacles()
        self._update_spring(None, sim.q)
        self._apply_camera()
        g = self._gui
        E = self._material["E"]
        rho = self._material["rho"]
        g["E"].min, g["E"].max, g["E"].step = E / 10.0, E * 10.0, E / 10.0
        g["E"].value = E
        g["E_value"].value = E
        if self._material_model() not in g["material"].options:
            g["material"].options = (*g["material"].options, self._material_model())
        g["material"].value = self._material_model()
        lo, hi, r0 = self._radius_range()
        g["radius"].min, g["radius"].max, g["radius"].step = lo, hi, (hi - lo) / 200.0
        g["radius"].value = r0
        g["nu"].value = self._material["nu"]
        g["rho"].min, g["rho"].max, g["rho"].step = rho / 10.0, rho * 10.0, rho / 10.0
        g["rho"].value = rho
        self._pacer.reset()
        self._gui_dirty = True

    # ---------------------------------------------------------------- main loop
    def _sync_pull(self) -> PullState | None:
        with self._lock:
            pull, version = self._pull, self._pull_version
        if version != self._applied_pull_version:
            if pull is not None and pull.generation == self._generation and pull.ids.size:
                self._sim.set_pull(pull.ids, pull.target)
            else:
                self._sim.clear_pull()
            self._applied_pull_version = version
        return pull

    def _step_once(self) -> None:
        t0 = time.perf_counter()
        try:
            info = self._sim.step()
            q = np.asarray(self._sim.q, dtype=np.float64)
            if not np.isfinite(q).all() or not math.isfinite(float(info.total)):
                raise SimulationError("non-finite positions or energy")
        except SimulationError as exc:
            self._fail(str(exc))
            return
        except Exception as exc:  # noqa: BLE001 - keep the viewer alive, show the error
            self._log_exception()
            self._fail(f"{type(exc).__name__}: {exc}")
            return
        now = time.perf_counter()
        seconds = float(getattr(info, "seconds", now - t0))
        with self._lock:
            self._steps += 1
            self._t = float(info.t)
            self._q_view = np.array(q, dtype=np.float64, copy=True)
            self._history.append(info.t, info.kinetic, info.potential, info.total,
                                 float(getattr(info, "pull", 0.0)))
            self._recent.append((now, seconds, int(info.newton_iterations)))

    def _fail(self, message: str) -> None:
        with self._lock:
            self._paused = True
            self._error = message
            self._errors.append(message)
        self._pacer.reset()
        self._gui_dirty = True
        for client in self._server.get_clients().values():
            self._notify_client(client, message)

    def _push(self, pull: PullState | None, *, force: bool = False) -> None:
        now = time.perf_counter()
        if not force and now - self._last_push < 1.0 / self.push_hz:
            return
        self._last_push = now
        q = np.asarray(self._sim.q, dtype=np.float64)
        pull_key = None if pull is None else (pull.ids.tobytes(), pull.target.tobytes())
        # The mesh node is identified by a serial number: viser's handles compare their
        # vertex arrays, so comparing handles raises once the mesh is replaced.
        shown = (self._mesh_serial, pull_key)
        changed = (
            self._shown is None or shown[0] != self._shown[0] or shown[1] != self._shown[1]
            or q.shape != self._shown_q.shape or not np.array_equal(q, self._shown_q)
        )
        if not (force or changed):
            pass  # nothing moved (paused, or at rest): send nothing
        elif not force and self._clients_busy(now):
            with self._lock:
                self._held_back += 1  # a page is still busy with the last update
        else:
            verts = self._display_positions()
            if np.isfinite(verts).all():
                with self._server.atomic():
                    self._mesh_handle.vertices = verts.astype(np.float32)
                    self._update_spring(pull, q)
                    self._update_obstacles()
                self._request_acks(now)
                self._shown, self._shown_q = shown, q.copy()
                with self._lock:
                    self._pushes += 1
        if force or self._gui_dirty or now - self._last_plot >= 1.0 / self.plot_hz:
            self._last_plot = now
            self._gui_dirty = False
            self._push_gui()

    def _push_gui(self) -> None:
        with self._lock:
            stats = self._stats_locked()
            pull = self._pull
            grabbed = None if pull is None or pull.generation != self._generation else int(
                pull.ids.size)
            text = format_status(
                scene=self._scene_label,
                integrator=self._sim_integrator,
                mesh_mode=self._mesh_handle_mode or self._mesh_mode,
                paused=self._paused,
                error=self._error,
                t=self._t,
                E=self._material["E"],
                nu=self._material["nu"],
                rho=self._material["rho"],
                grabbed=grabbed,
                pick_radius=self._pick_radius,
                **stats,
            )
            x, *series = self._history.recent(self.plot_window, n=PLOT_POINTS)
            latest = self._history.latest()
        self._gui["status"].content = text
        self._gui["energy"].content = energy_text(latest)
        x32 = x.astype(np.float32)  # half the bytes; plenty for a plot
        for (key, _label, _color), y in zip(ENERGY_PLOTS, series, strict=True):
            self._gui[f"plot_{key}"].data = (x32, y.astype(np.float32))

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.clear()
            while True:
                with self._lock:
                    if not self._commands:
                        break
                    command = self._commands.popleft()
                try:
                    command()
                except Exception as exc:  # noqa: BLE001 - a bad command must not stop the loop
                    self._log_exception()
                    self._fail(f"{type(exc).__name__}: {exc}")
            try:
                pull = self._sync_pull()
            except Exception as exc:  # noqa: BLE001 - e.g. a rejected pull
                self._log_exception()
                self._fail(f"{type(exc).__name__}: {exc}")
                with self._lock:
                    self._pull = None
                    pull = None
            with self._lock:
                running = not self._paused
            wait = 1.0 / self.push_hz
            if running:
                with self._lock:
                    t_sim = self._t
                delay = self._pacer.delay(t_sim, time.perf_counter())
                if delay <= 0.0:
                    self._step_once()
                    wait = 0.0
                else:
                    wait = delay
            try:
                self._push(pull)
            except Exception:  # noqa: BLE001 - e.g. the server is stopping
                if self._stop.is_set():
                    break
                self._log_exception()
            if wait > 0.0:
                due = self._last_push + 1.0 / self.push_hz - time.perf_counter()
                self._wake.wait(max(0.0, min(wait, due)))


# --------------------------------------------------------------------------------------
# Entry points
# --------------------------------------------------------------------------------------


def serve(
    scene_name_or_path: str | Path = "bunny",
    host: str = "127.0.0.1",
    port: int = 8080,
    integrator: str | None = None,
    backend: str | None = None,
    *,
    realtime: bool = True,
    time_scale: float = 1.0,
) -> None:
    """Run the viewer until Ctrl-C.

    Parameters
    ----------
    scene_name_or_path : str or Path
        ``"bunny"``, ``"arma"`` or a tet-mesh path.
    host, port : str, int
        Where to listen.
    integrator : {"linear", "implicit"}, optional
        Overrides the scene's integrator.
    backend : {"numpy", "c"}, optional
        Kernel back end.
    realtime : bool
        Pace simulated time to wall time.
    time_scale : float
        Simulated seconds per wall second (``< 1``: slow motion).
    """
    _import_viser()
    viewer = Viewer(
        scene_name_or_path,
        host=host,
        port=port,
        integrator=integrator,
        backend=backend,
        realtime=realtime,
        time_scale=time_scale,
    )
    url = viewer.start()
    print(f"fem3d view: {url}  (drag the mesh; S mesh, N integrator, space pause, R reset;"
          " Ctrl-C stops)", flush=True)
    try:
        viewer.wait()
    except KeyboardInterrupt:
        print("fem3d view: stopping", flush=True)
    finally:
        viewer.stop()


def _run_view(args: argparse.Namespace) -> int:
    serve(
        args.scene,
        host=args.host,
        port=args.port,
        integrator=args.integrator,
        backend=args.backend,
        realtime=not args.no_realtime,
        time_scale=args.time_scale,
    )
    return 0


def add_view_subcommand(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``fem3d view`` on an ``argparse`` sub-parser collection.

    The sub-command stores its handler in ``func`` (``args.func(args) -> int``). viser is
    imported only when the command runs.
    """
    p = subparsers.add_parser(
        "view",
        help="interactive browser viewer (needs fem3d[view])",
        description="Run a scene in a browser viewer (viser): drag the mesh to pull it; "
        "M toggles skinned/simulation mesh, N the integrator, space pauses, R resets.",
    )
    p.add_argument("scene", nargs="?", default="bunny",
                   help="bunny | arma | other name in data/scenes | FILE.toml | a tet mesh or "
                   "closed surface")
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; 0 = any free port)")
    p.add_argument(
        "--integrator", choices=sorted(INTEGRATOR_LABELS), default=None,
        help="override the scene's integrator",
    )
    p.add_argument(
        "--kernels", "--backend", dest="backend", choices=("numpy", "c"), default=None,
        help="kernel back end (default: C if built)",
    )
    p.add_argument(
        "--no-realtime", action="store_true", help="step as fast as possible (no wall-time pacing)"
    )
    p.add_argument(
        "--time-scale", type=float, default=1.0,
        help="simulated seconds per wall second (default 1; 0.25 = slow motion)",
    )
    p.set_defaults(func=_run_view)
    return p
