"""The viewer's logic that needs no viser: the state the viewer's threads share and its
transitions (pause, failure, reset, stepping with its energy and timing bookkeeping, pulls,
material and scene switches), and the pure helpers (pacing, energy history, status text,
camera, spring and plane geometry).

Everything here is unit-tested without a browser and without viser; the viser side (the
server, the panel, the browser clients) is :mod:`fem3d.app.viewer.app`,
:mod:`fem3d.app.viewer.panel` and :mod:`fem3d.app.viewer.clients`.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from fem3d.app.viewer.pacing import RealtimePacer, StepGate
from fem3d.app.viewer.plots import ENERGY_PLOTS, HISTORY_COLUMNS, EnergyHistory
from fem3d.errors import SimulationError
from fem3d.physics.constraints import pick_nearest_vertices
from fem3d.scene import apply_overrides, material_names
from fem3d.scene.load import SCENES, load_scene
from fem3d.simulation import Simulation
from fem3d.solve.schemes.registry import SCHEMES, dynamic_scheme_names

__all__ = [
    "ENERGY_PLOTS",
    "HISTORY_COLUMNS",
    "EnergyHistory",
    "PullState",
    "RealtimePacer",
    "StepGate",
    "ViewerState",
    "HOTKEYS",
    "camera_for_points",
    "scene_points",
    "plane_quad",
    "energy_text",
    "format_energy",
    "format_status",
    "spring_segments",
]

INTEGRATOR_LABELS = {name: s.label for name, s in SCHEMES.items()}
MESH_MODE_LABELS = {"skin": "skinned display mesh", "sim": "simulation mesh"}

#: Hotkeys. S is not used: viser's camera moves with W/A/S/D (and Q/E), so the mesh
#: toggle is M.
HOTKEYS = {"mesh": "M", "integrator": "N", "pause": "space", "reset": "R"}


def console_help() -> str:
    """The keys line ``fem3d view`` prints, built from :data:`HOTKEYS` (one source of truth)."""
    k = HOTKEYS
    return (f"drag the mesh; {k['mesh']} mesh, {k['integrator']} integrator, {k['pause']} pause, "
            f"{k['reset']} reset; Ctrl-C stops")

# The energy plots and their history (ENERGY_PLOTS, HISTORY_COLUMNS, EnergyHistory) are
# in fem3d.app.viewer.plots, the pacing (RealtimePacer, StepGate) in
# fem3d.app.viewer.pacing, imported above and re-exported.

#: Samples per energy plot (5 plots x 2 float32 arrays: 8 kB per update at 200).
PLOT_POINTS = 200


# --------------------------------------------------------------------------------------
# Runtime access
# --------------------------------------------------------------------------------------


def _load_scene(name: str | Path) -> Any:
    return load_scene(str(name))


def _make_simulation(scene: Any, integrator: str | None, backend: str | None) -> Any:
    sim = Simulation(scene, backend=backend)
    if integrator is not None:
        sim.integrator = integrator
    return sim


def _material_names() -> list[str]:
    return [str(n) for n in material_names()]


def _with_material(scene: Any, name: str) -> Any:
    """``scene`` with every body's material model set to ``name`` (validated)."""
    keys = {f"bodies[{i}].material.model": name for i in range(len(scene.bodies))}
    return apply_overrides(scene, keys, source="the viewer's material menu")


def _builtin_scene_names() -> list[str]:
    return [str(name) for name in SCENES]


def _pick(positions: np.ndarray, point: np.ndarray, radius: float) -> np.ndarray:
    return pick_nearest_vertices(positions, point, radius, nearest_if_empty=True)


# --------------------------------------------------------------------------------------
# Small pieces of logic, free of viser (unit-tested)
# --------------------------------------------------------------------------------------


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
    seg[:, 1] = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    return seg


#: Viewing direction (from the object toward the camera) per built-in scene; y is up.
VIEW_DIRECTIONS = {"arma": (0.0, 0.25, -1.0)}  # the armadillo faces -z
DEFAULT_VIEW_DIRECTION = (0.0, 0.25, 1.0)


def scene_points(q: np.ndarray, planes: Sequence[tuple[Any, Any]] = (),
                 meshes: Sequence[np.ndarray] = ()) -> np.ndarray:
    """The points a scene's first view frames: the bodies' vertices, their shadows on each
    obstacle plane (where a dropped body lands: the ground under it stays in view) and the
    mesh obstacles' vertices.

    Parameters
    ----------
    q : (n, 3) float64
    planes : sequence of (point (3,), normal (3,))
    meshes : sequence of (k, 3) float64
    """
    q = np.asarray(q, dtype=np.float64).reshape(-1, 3)
    out = [q]
    for point, normal in planes:
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        out.append(q - ((q - np.asarray(point, dtype=np.float64)) @ n)[:, None] * n)
    out += [np.asarray(V, dtype=np.float64).reshape(-1, 3) for V in meshes]
    return np.concatenate(out)


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
    row = list(latest) + [0.0] * 7
    _t, T, V, tot, pull = row[:5]
    strain, gravity = (row[5], row[6]) if len(latest) >= 7 else (V, 0.0)
    parts = [f"T = {format_energy(T)}", f"strain = {format_energy(strain)}",
             f"gravity = {format_energy(gravity)}", f"V = {format_energy(V)}",
             f"T+V = {format_energy(tot)}", f"pull = {format_energy(pull)}"]
    return "now: " + " · ".join(_nb(p) for p in parts)


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


def plane_grid_segments(point: np.ndarray, normal: np.ndarray, center: np.ndarray,
                        half: float, cells: int = 12) -> np.ndarray:
    """Grid lines on the square of :func:`plane_quad` (``cells`` squares a side), lifted
    by ``1e-3 half`` along the normal so they draw over it: ``(2 (cells + 1), 2, 3)``."""
    V, _ = plane_quad(point, normal, center, half)
    n = np.asarray(normal, dtype=np.float64)
    V = V + 1e-3 * half * n / np.linalg.norm(n)
    s = np.linspace(0.0, 1.0, cells + 1)[:, None]
    a0, a1 = V[0] + s * (V[1] - V[0]), V[3] + s * (V[2] - V[3])  # lines from edge 01 to 32
    b0, b1 = V[0] + s * (V[3] - V[0]), V[1] + s * (V[2] - V[1])  # lines from edge 03 to 12
    return np.concatenate([np.stack([a0, a1], 1), np.stack([b0, b1], 1)])


def _surface_faces(sim: Any) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(sim.surface_faces, dtype=np.uint32))



# --------------------------------------------------------------------------------------
# The state the viewer's threads share
# --------------------------------------------------------------------------------------


class ViewerState:
    """The simulation a viewer runs and the state its threads share, with the transitions
    that need no viser: pause, failure, reset, stepping (energy and timing bookkeeping),
    pulls, material and scene switches.

    Every attribute but :attr:`applied_pull_version` and :attr:`pacer` is guarded by
    :attr:`lock` (held for microseconds, never across a step or a viser write); the
    simulation thread is the only one that touches :attr:`sim`.

    Parameters
    ----------
    scene : str or Path
        Built-in scene name or a scene file / mesh path (loaded now, so that bad input fails
        before a server starts).
    integrator : {"linear", "implicit"}, optional
        Overrides the scene's integrator.
    backend : {"numpy", "c"}, optional
        Kernel back end.
    mesh_mode : {"skin", "sim"}
        Mesh shown first.
    pacer : RealtimePacer
        Paces the steps to wall time (reset on a pause, a reset, a failure, a switch).
    """

    def __init__(self, scene: str | Path, *, integrator: str | None, backend: str | None,
                 mesh_mode: str, pacer: RealtimePacer) -> None:
        self.backend = backend
        self.pacer = pacer
        self.scene = _load_scene(scene)
        self.scene_label = str(scene)
        self.sim = _make_simulation(self.scene, integrator, backend)

        # Shared state (guarded by lock; never held across a step or a viser write).
        self.lock = threading.Lock()
        self.wake = threading.Event()
        self.commands: collections.deque[Callable[[], None]] = collections.deque()
        self.generation = 0
        #: The active pulls, one per owner (a browser client; None for calls without one),
        #: oldest first: two pages can drag at once, each its own vertices.
        self.pulls: dict[int | None, PullState] = {}
        self.pull_version = 0
        self.q_view = np.array(self.sim.q, dtype=np.float64, copy=True)
        self.paused = False
        self.error: str | None = None
        self.errors: list[str] = []
        self.mesh_mode = mesh_mode
        self.history = EnergyHistory()
        self.recent: collections.deque[tuple[float, float, int]] = collections.deque(maxlen=30)
        self.steps = 0
        self.pushes = 0
        self.t = 0.0
        self.material = self.scene_material()
        self.drag_events = 0
        self.last_gui_pause = -1e9
        self.pick_radius = float(self.sim.pick_radius)
        #: Tracebacks of exceptions caught on the viewer's threads (tests assert it stays
        #: empty; each is also printed).
        self.exceptions: list[str] = []
        #: The panel needs an update (set by either thread).
        self.gui_dirty = True
        self.history_reset()

        # Simulation-thread-only state.
        self.applied_pull_version = -1

    # ---------------------------------------------------------------- reading
    @property
    def integrator(self) -> str:
        return str(self.sim.integrator)

    def material_model(self) -> str:
        return str(self.scene.bodies[0].material.model)

    def has_skin(self) -> bool:
        return bool(self.sim.has_skin)

    def scene_material(self) -> dict[str, float]:
        m = self.sim.model  # summary values (a scene may give its materials by params)
        return {"E": float(m.E), "nu": float(m.nu), "rho": float(m.rho)}

    def radius_range(self) -> tuple[float, float, float]:
        """(min, max, initial) of the grab-radius slider: 0.1 % to 20 % of the mesh's
        bounding-box diagonal, starting at the scene's ``pick_radius``."""
        q = np.asarray(self.sim.q, dtype=np.float64)
        diag = float(np.linalg.norm(q.max(axis=0) - q.min(axis=0))) or 1.0
        r0 = float(self.sim.pick_radius)
        lo, hi = min(1e-3 * diag, r0), max(0.2 * diag, r0)
        return lo, hi, r0

    def stats_locked(self) -> dict[str, float]:
        """Milliseconds and Newton iterations per step, steps per second (recent steps;
        the caller holds :attr:`lock`)."""
        if not self.recent:
            return {"ms_per_step": 0.0, "newton_per_step": 0.0, "steps_per_second": 0.0}
        r = np.asarray(self.recent, dtype=np.float64)
        span = r[-1, 0] - r[0, 0]
        rate = (len(r) - 1) / span if len(r) > 1 and span > 0 else 0.0
        return {
            "ms_per_step": float(1e3 * r[:, 1].mean()),
            "newton_per_step": float(r[:, 2].mean()),
            "steps_per_second": float(rate),
        }

    @property
    def pull(self) -> PullState | None:
        """The newest active pull (None without one)."""
        return next(reversed(self.pulls.values()), None)

    def drop_pulls(self, owner: Any = ...) -> None:
        """Release ``owner``'s pull (every pull by default); the caller holds :attr:`lock`."""
        if owner is ...:
            self.pulls.clear()
        elif self.pulls.pop(owner, None) is None:
            return
        self.gui_dirty = True
        self.pull_version += 1

    def _pull_dict(self, p: PullState) -> dict[str, Any]:
        return {
            "owner": p.owner,
            "ids": p.ids.tolist(),
            "grab_point": p.grab_point.tolist(),
            "target": p.target.tolist(),
            "start_positions": p.start_positions.tolist(),
            "positions": self.q_view[p.ids].tolist(),
        }

    def snapshot_locked(self) -> dict[str, Any]:
        """The shared state as a JSON-serialisable dict (the caller holds :attr:`lock`);
        see :meth:`fem3d.app.viewer.app.Viewer.snapshot`."""
        pull = None if self.pull is None else self._pull_dict(self.pull)
        stats = self.stats_locked()
        return {
            "scene": self.scene.name,
            "integrator": str(self.integrator),
            "mesh_mode": self.mesh_mode,
            "paused": self.paused,
            "error": self.error,
            "errors": list(self.errors),
            "t": self.t,
            "steps": self.steps,
            "pushes": self.pushes,
            **stats,
            "material": dict(self.material),
            "material_model": self.material_model(),
            "pull": pull,
            "pulls": [self._pull_dict(p) for p in self.pulls.values()],
            "energy": [list(r) for r in self.history.rows()],
            "drag_events": self.drag_events,
            "generation": self.generation,
            "pick_radius": self.pick_radius,
        }

    def status_locked(self, mesh_mode: str) -> str:
        """The panel's status text (the caller holds :attr:`lock`)."""
        live = [p for p in self.pulls.values() if p.generation == self.generation]
        grabbed = sum(int(p.ids.size) for p in live) if live else None
        return format_status(
            scene=self.scene_label,
            integrator=self.integrator,
            mesh_mode=mesh_mode,
            paused=self.paused,
            error=self.error,
            t=self.t,
            E=self.material["E"],
            nu=self.material["nu"],
            rho=self.material["rho"],
            grabbed=grabbed,
            pick_radius=self.pick_radius,
            **self.stats_locked(),
        )

    # ---------------------------------------------------------------- any thread
    def post(self, command: Callable[[], None]) -> None:
        """Queue ``command`` for the simulation thread and wake it."""
        with self.lock:
            self.commands.append(command)
        self.wake.set()

    def next_command(self) -> Callable[[], None] | None:
        """The oldest queued command, or None."""
        with self.lock:
            if not self.commands:
                return None
            return self.commands.popleft()

    def log_exception(self) -> None:
        """Print the current exception's traceback and keep it in :attr:`exceptions`."""
        text = traceback.format_exc()
        print(text, end="", file=sys.stderr, flush=True)
        with self.lock:
            self.exceptions.append(text)

    def gui_pause_debounced(self) -> bool:
        """True when a panel pause comes within 0.3 s of the previous one: a focused button
        receives space as a click too, so the hotkey and the click of one key press count
        once."""
        now = time.monotonic()
        with self.lock:
            if now - self.last_gui_pause < 0.3:
                return True
            self.last_gui_pause = now
        return False

    def begin_pull(self, grab: np.ndarray, tgt: np.ndarray, owner: int | None) -> None:
        """Pick the vertices within the grab radius of ``grab`` (see
        :meth:`fem3d.app.viewer.app.Viewer.begin_pull`)."""
        with self.lock:
            q = self.q_view
            ids = _pick(q, grab, self.pick_radius)
            self.pulls.pop(owner, None)  # a new press of the same owner: the newest pull
            self.pulls[owner] = PullState(
                ids=ids,
                grab_point=grab,
                target=tgt,
                start_positions=q[ids].copy(),
                generation=self.generation,
                owner=owner,
            )
            self.gui_dirty = True
            self.pull_version += 1
            self.drag_events += 1
        self.wake.set()

    def move_pull(self, tgt: np.ndarray, owner: int | None) -> None:
        """Move the pull target (only ``owner``'s pull, when given)."""
        with self.lock:
            pull = self.pulls.get(owner) if owner is not None else self.pull
            if pull is None:
                return
            pull.target = tgt
            self.pull_version += 1
            self.drag_events += 1
        self.wake.set()

    def end_pull(self, owner: int | None) -> None:
        """Release the pull (only ``owner``'s pull, when given)."""
        with self.lock:
            pull = self.pulls.get(owner) if owner is not None else self.pull
            if pull is None:
                return
            self.drop_pulls(pull.owner)
            self.drag_events += 1
        self.wake.set()

    def set_pick_radius(self, r: float) -> None:
        with self.lock:
            self.pick_radius = r
            self.gui_dirty = True
        self.wake.set()

    # ---------------------------------------------------------------- simulation thread
    def history_reset(self) -> None:
        """Start the energy history at the current state (a real sample, not padding)."""
        self.history.clear()
        try:
            e = self.sim.energies()
        except Exception:  # noqa: BLE001 - an exotic simulation without energies
            return
        self.history.append(float(self.sim.t), e["kinetic"], e["potential"], e["total"],
                            e.get("pull", 0.0), e.get("gravity", 0.0))

    def sync_pull(self) -> PullState | None:
        """Hand changed pulls to the simulation; the active pulls as one (None without).

        Several owners' pulls become one set of springs, each vertex toward its owner's
        target."""
        with self.lock:
            live = [p for p in self.pulls.values()
                    if p.generation == self.generation and p.ids.size]
            version = self.pull_version
            pull = None
            if len(live) == 1:
                pull = live[0]
            elif live:
                pull = PullState(
                    ids=np.concatenate([p.ids for p in live]),
                    grab_point=live[-1].grab_point,
                    target=np.concatenate([np.broadcast_to(p.target, (p.ids.size, 3))
                                           for p in live]),
                    start_positions=np.concatenate([p.start_positions for p in live]),
                    generation=self.generation,
                )
        if version != self.applied_pull_version:
            if pull is not None:
                self.sim.set_pull(pull.ids, pull.target)
            else:
                self.sim.clear_pull()
            self.applied_pull_version = version
        return pull

    def step(self) -> str | None:
        """One simulation step and its bookkeeping; the failure message, or None.

        A :class:`~fem3d.errors.SimulationError` or non-finite positions or energy fail the
        step; any other exception too (its traceback is logged): the viewer stays alive
        and shows the error.
        """
        t0 = time.perf_counter()
        try:
            info = self.sim.step()
            q = np.asarray(self.sim.q, dtype=np.float64)
            if not np.isfinite(q).all() or not math.isfinite(float(info.total)):
                raise SimulationError("non-finite positions or energy")
            gravity = float(getattr(self.sim, "gravity_energy", lambda: 0.0)())
        except SimulationError as exc:
            return str(exc)
        except Exception as exc:  # noqa: BLE001 - keep the viewer alive, show the error
            self.log_exception()
            return f"{type(exc).__name__}: {exc}"
        now = time.perf_counter()
        seconds = float(getattr(info, "seconds", now - t0))
        with self.lock:
            self.steps += 1
            self.t = float(info.t)
            self.q_view = np.array(q, dtype=np.float64, copy=True)
            self.history.append(info.t, info.kinetic, info.potential, info.total,
                                float(getattr(info, "pull", 0.0)), gravity)
            self.recent.append((now, seconds, int(info.newton_iterations)))
        return None

    def fail(self, message: str) -> None:
        """Pause at the last good step with ``message`` as the error."""
        with self.lock:
            self.paused = True
            self.error = message
            self.errors.append(message)
        self.pacer.reset()
        self.gui_dirty = True

    def toggle_mesh_mode(self) -> None:
        with self.lock:
            self.mesh_mode = "sim" if self.mesh_mode == "skin" else "skin"

    def toggle_integrator(self) -> None:
        """Cycle through the dynamic schemes of the registry (:func:`dynamic_scheme_names`:
        linear, implicit, BDF2, Newmark), skipping those without contact in a contact scene.

        Raises
        ------
        Fem3dError
            The simulation refuses.
        """
        contact = getattr(self.sim, "contact", None) is not None
        names = [n for n in dynamic_scheme_names() if SCHEMES[n].contact or not contact]
        now = self.integrator
        new = names[(names.index(now) + 1) % len(names)] if now in names else names[0]
        self.sim.integrator = new
        self.gui_dirty = True

    def set_paused(self, paused: bool) -> None:
        with self.lock:
            self.paused = paused
        self.pacer.reset()
        self.gui_dirty = True

    def toggle_pause(self) -> None:
        """Pause or resume; resuming clears an error."""
        with self.lock:
            self.paused = not self.paused
            if not self.paused:
                self.error = None
        self.pacer.reset()
        self.gui_dirty = True

    def reset(self) -> None:
        """Back to rest, t = 0; clears an error (re-applies an active pull)."""
        self.sim.reset()
        self.applied_pull_version = -1  # re-apply an active pull after the reset
        with self.lock:
            self.error = None
            self.paused = False
            self.history_reset()
            self.recent.clear()
            self.t = 0.0
            self.q_view = np.array(self.sim.q, dtype=np.float64, copy=True)

    def set_material(self, E: float | None, nu: float | None, rho: float | None) -> None:
        """Change material parameters live.

        Raises
        ------
        Fem3dError
            A rejected value (nothing changed).
        """
        self.sim.set_material(E=E, nu=nu, rho=rho)
        with self.lock:
            for k, v in (("E", E), ("nu", nu), ("rho", rho)):
                if v is not None:
                    self.material[k] = float(v)

    def switch_material(self, name: str) -> bool:
        """Every body's material model to ``name``, keeping the motion (positions,
        velocities, time) and the panel's edits; False when it is the current one.

        Raises
        ------
        Fem3dError
            An unknown model or a scene that refuses it (nothing changed).
        """
        if name == self.material_model():
            return False
        old = self.sim
        scene = _with_material(self.scene, name)
        sim = _make_simulation(scene, self.integrator, self.backend)
        sim.set_state(old.q, old.v, old.t, old.step_index)
        with self.lock:
            mat = dict(self.material)
        if mat != self.scene_material():  # keep the panel's edits (body 0's values)
            sim.set_material(E=mat["E"], nu=mat["nu"], rho=mat["rho"])
        with self.lock:
            self.scene, self.sim = scene, sim
            self.error = None
        self.applied_pull_version = -1  # re-apply an active pull to the new simulation
        self.pacer.reset()
        self.gui_dirty = True
        return True

    def load(self, name: str) -> tuple[Any, Any]:
        """The scene ``name`` and a simulation of it (nothing changed yet).

        Raises
        ------
        Fem3dError
            A bad scene.
        """
        scene = _load_scene(name)
        return scene, _make_simulation(scene, None, self.backend)

    def install(self, name: str, scene: Any, sim: Any) -> None:
        """Run ``sim`` of ``scene`` from now on (a scene switch): a new generation, no pull,
        no error, running, a fresh history and material."""
        with self.lock:
            self.scene, self.sim, self.scene_label = scene, sim, name
            self.generation += 1
            self.drop_pulls()
            self.error = None
            self.paused = False
            self.history_reset()
            self.recent.clear()
            self.t = 0.0
            self.q_view = np.array(sim.q, dtype=np.float64, copy=True)
            self.material = self.scene_material()
            self.pick_radius = float(self.sim.pick_radius)
        self.applied_pull_version = -1
