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
  paced to wall time while a page is connected (it sleeps otherwise), and pushes display
  updates at up to ``push_hz``.
* **viser's event loop / thread pool**: GUI and drag callbacks. They never block on a
  simulation step: they take the lock of the viewer's shared state
  (:class:`~fem3d.app.viewer.logic.ViewerState`) for a few microseconds to record a
  pull request or queue a command, and wake the simulation thread.

Because only the simulation thread adds, removes and writes scene nodes, a mesh handle
that was replaced (mesh mode or scene switch) is never written after its removal.

Tests read the viewer's state with :meth:`Viewer.snapshot` (a JSON-serialisable dict) and
drive it with the same methods the GUI calls (:meth:`Viewer.toggle_mesh_mode`,
:meth:`Viewer.begin_pull`, ...).

The package: this module wires the viewer (server, scene graph, simulation thread) and holds
the entry points (``fem3d view``, :func:`serve`); :mod:`~fem3d.app.viewer.panel` the panel,
:mod:`~fem3d.app.viewer.clients` the browser clients (frame acknowledgements, notifications,
drags), :mod:`~fem3d.app.viewer.logic` the shared state and the logic that needs no viser,
:mod:`~fem3d.app.viewer.scene_graph` the scene nodes (mesh, obstacles, spring),
:mod:`~fem3d.app.viewer.pacing` when to step (only while a page watches, at wall time),
:mod:`~fem3d.app.viewer.plots` the energy history and the plots' axes,
:mod:`~fem3d.app.viewer.ports` the port checks. viser is an optional dependency
(``fem3d[view]``): it is imported when a viewer starts (:func:`.ports.import_viser`), so that
``fem3d`` registers ``fem3d view`` without it.
"""

from __future__ import annotations

import argparse
import math
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fem3d.app.viewer.clients import (
    FrameAcks,
    Notifications,
    drag_handler,
    set_client_camera,
)
from fem3d.app.viewer.logic import (
    DEFAULT_VIEW_DIRECTION,
    INTEGRATOR_LABELS,
    MESH_MODE_LABELS,
    PLOT_POINTS,
    VIEW_DIRECTIONS,
    PullState,
    RealtimePacer,
    StepGate,
    ViewerState,
    _builtin_scene_names,
    _material_names,
    camera_for_points,
    console_help,
    scene_points,
)
from fem3d.app.viewer.panel import Panel
from fem3d.app.viewer.ports import check_port_free, free_port, import_viser
from fem3d.app.viewer.scene_graph import SceneGraph
from fem3d.errors import Fem3dError, InputError, ParameterError

if TYPE_CHECKING:  # pragma: no cover - typing only
    import viser

__all__ = ["Viewer", "add_view_subcommand", "serve"]

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
    run_unwatched : bool
        Step with no browser page connected too (scripts and tests driving the viewer from
        Python). By default the simulation steps only while a page is connected and idles
        (no CPU) otherwise; it goes on from where it was left when a page connects again.
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
        run_unwatched: bool = False,
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

        # The simulation and the state the threads share (loaded now so that bad input
        # fails before a server starts).
        self._state = ViewerState(scene, integrator=integrator, backend=backend,
                                  mesh_mode=mesh_mode,
                                  pacer=RealtimePacer(enabled=realtime, rate=time_scale))
        self._gate = StepGate(self._state.pacer, self._state.wake, unwatched=run_unwatched)
        self._acks = FrameAcks(self._state.lock, self._state.wake)
        self._notes = Notifications(self._state.lock)
        self._panel = Panel(self)
        self._stop = threading.Event()

        # Simulation-thread-only state.
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self._graph: SceneGraph | None = None  # the scene nodes (after start)
        self._last_push = 0.0
        self._last_plot = 0.0
        self._loops = 0  # passes of the simulation loop (an idle viewer makes none)
        self._shown: tuple[Any, Any] | None = None  # (mesh serial, pull) last sent
        self._shown_q = np.zeros((0, 3))
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
        with self._state.lock:
            return dict(self._camera)

    @property
    def exceptions(self) -> list[str]:
        """Tracebacks of exceptions caught on the viewer's threads (tests assert it stays
        empty; each is also printed)."""
        return self._state.exceptions

    @property
    def _sim(self) -> Any:
        """The running :class:`~fem3d.simulation.Simulation`."""
        return self._state.sim

    @property
    def _gui(self) -> dict[str, Any]:
        """The panel's elements by name (empty before :meth:`start`)."""
        return self._panel.widgets

    # ---------------------------------------------------------------- life cycle
    def start(self) -> str:
        """Start the viser server and the simulation thread; return the URL.

        Raises
        ------
        InputError
            The port is taken (viser would silently move to the next free one; an SSH
            forward to the requested port would then reach something else).
        """
        viser = import_viser()
        port = free_port(self.host) if self.port == 0 else self.port
        check_port_free(self.host, port)
        self._server = viser.ViserServer(host=self.host, port=port, verbose=False)
        if self._server.get_port() != port:
            got = self._server.get_port()
            self._server.stop()
            self._server = None
            raise InputError(f"port {port} on {self.host} is in use (viser moved to {got}); "
                             "pick another with --port N, or --port 0 for a free one")
        self._server.scene.set_up_direction("+y")
        s = self._state
        self._panel.build(
            self._server.gui, scenes=_builtin_scene_names(), scene_label=s.scene_label,
            models=_material_names(), model=s.material_model(), material=s.material,
            radius_range=s.radius_range(), history=s.history, plot_window=self.plot_window,
        )
        self._apply_camera(initial=True)
        self._graph = SceneGraph(self._server)
        self._rebuild_mesh()
        self._graph.rebuild_obstacles(self._sim)
        self._server.on_client_connect(self._on_client_connect)
        self._server.on_client_disconnect(self._on_client_disconnect)
        self._thread = threading.Thread(target=self._run, name="fem3d-view-sim", daemon=True)
        self._thread.start()
        return self.url

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the simulation thread and the server (idempotent)."""
        self._stop.set()
        self._state.wake.set()
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
    def toggle_mesh_mode(self) -> None:
        """Switch between the skinned display mesh and the simulation mesh (``S``)."""
        self._state.post(self._do_toggle_mesh_mode)

    def toggle_integrator(self) -> None:
        """Switch linearly-implicit / backward Euler (``N``)."""
        self._state.post(self._do_toggle_integrator)

    def toggle_pause(self) -> None:
        """Pause or resume (space)."""
        self._state.post(self._state.toggle_pause)

    def set_paused(self, paused: bool) -> None:
        self._state.post(lambda: self._state.set_paused(paused))

    def reset(self) -> None:
        """Back to rest, t = 0; clears an error (``R``)."""
        self._state.post(self._do_reset)

    def switch_material(self, name: str) -> None:
        """Change every body's material model (a name of :func:`fem3d.physics.materials.names`),
        keeping the motion: positions, velocities and time carry over."""
        self._state.post(lambda: self._do_switch_material(name))

    def switch_scene(self, name: str) -> None:
        """Load another scene (runs on the simulation thread)."""
        self._state.post(lambda: self._do_switch_scene(name))

    def set_colour_field(self, name: str) -> None:
        """Colour the surface by ``name`` (``"none"`` or a key of
        :data:`fem3d.app.viewer.colour.FIELDS`)."""
        self._state.post(lambda: self._do_set_colour_field(name))

    def set_material(
        self, E: float | None = None, nu: float | None = None, rho: float | None = None
    ) -> None:
        """Change material parameters live."""
        self._state.post(lambda: self._do_set_material(E, nu, rho))

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
        self._state.begin_pull(grab, tgt, owner)

    def move_pull(self, target: Sequence[float], owner: int | None = None) -> None:
        """Move the pull target (world space)."""
        tgt = np.asarray(target, dtype=np.float64).reshape(3)
        if not np.isfinite(tgt).all():
            return
        self._state.move_pull(tgt, owner)

    def end_pull(self, owner: int | None = None) -> None:
        """Release the pull."""
        self._state.end_pull(owner)

    def set_pick_radius(self, radius: float) -> None:
        """Grab radius (world units) for the next drag."""
        r = float(radius)
        if not (math.isfinite(r) and r > 0):
            raise ParameterError(f"grab radius must be positive, got {radius}")
        self._state.set_pick_radius(r)

    # ---------------------------------------------------------------- state for tests
    def snapshot(self) -> dict[str, Any]:
        """A JSON-serialisable copy of the viewer's state.

        Keys: ``scene``, ``integrator``, ``mesh_mode``, ``paused``, ``error``, ``errors``,
        ``t``, ``steps``, ``pushes``, ``ms_per_step``, ``newton_per_step``,
        ``steps_per_second``, ``material``, ``pull`` (None or ``ids``, ``grab_point``,
        ``target``, ``start_positions``, ``positions``: the newest pull), ``pulls`` (every active
        pull, one per dragging page, each as ``pull`` plus ``owner``), ``energy`` (list of
        ``[t, T, V, T+V]``), ``drag_events``, ``generation``, ``pick_radius``, ``acked``
        (mesh updates the pages acknowledged), ``held_back`` (mesh updates not sent because
        a page had not processed the previous one), ``clients``, ``watchers`` (pages
        connected: the simulation steps only while there is one), ``loops`` (passes of the
        simulation loop), ``exceptions``.
        """
        with self._state.lock:
            return {
                **self._state.snapshot_locked(),
                "acked": self._acks.acked,
                "held_back": self._acks.held_back,
                "clients": len(self._acks),
                "watchers": self._gate.watchers,
                "loops": self._loops,
                "exceptions": list(self._state.exceptions),
            }

    def positions(self) -> np.ndarray:
        """(n_vertices, 3) float64: the latest simulation positions (a copy)."""
        with self._state.lock:
            return self._state.q_view.copy()

    # ---------------------------------------------------------------- clients
    def _gui_toggle_pause(self) -> None:
        """Pause/resume from the panel: a focused button receives space as a click too, so
        the hotkey and the click of one key press count once."""
        if self._state.gui_pause_debounced():
            return
        self.toggle_pause()

    def _on_client_connect(self, client: Any) -> None:
        self._acks.register(client)
        self._gate.connect(int(client.client_id))
        with self._state.lock:
            cam = dict(self._camera)
            error = self._state.error
        set_client_camera(client, cam)
        if error is not None:
            self._notify_client(client, error)

    def _on_client_disconnect(self, client: Any) -> None:
        s = self._state
        cid = int(client.client_id)
        self._gate.disconnect(cid)
        with s.lock:
            self._acks.drop(cid)
            s.drop_pulls(cid)

    def _scene_camera(self) -> dict[str, Any]:
        s = self._state
        direction = VIEW_DIRECTIONS.get(str(s.scene.name), DEFAULT_VIEW_DIRECTION)
        contact = getattr(s.sim, "contact", None)
        planes = [] if contact is None else [(p.point, p.normal)
                                             for p in contact.contact.planes]
        meshes = [V for _n, V, _F in s.sim.obstacles()] if contact is not None else []
        return camera_for_points(scene_points(s.sim.q, planes, meshes), direction=direction)

    def _apply_camera(self, *, initial: bool = False) -> None:
        cam = self._scene_camera()
        with self._state.lock:
            self._camera = cam
        ic = self._server.initial_camera
        ic.near = float(cam["near"])
        ic.far = float(cam["far"])
        ic.position = tuple(cam["position"])
        ic.look_at = tuple(cam["look_at"])
        if not initial:
            for client in self._server.get_clients().values():
                set_client_camera(client, cam)

    def _error_text(self, error: str) -> str:
        hint = ""
        scheme = self._state.sim.scheme
        if not scheme.minimises:  # no line search: nothing keeps its energy down
            hint = f" (the {scheme.label} integrator is unstable here: press N for another)"
        return (
            f"{error}. The viewer paused at the last good step; press R (Reset) to restart"
            f"{hint}."
        )

    def _notify_client(self, client: Any, error: str) -> None:
        self._notes.notify_client(client, "Simulation stopped", self._error_text(error),
                                  color="red")

    def _notify_all(self, title: str, body: str, color: str = "blue", seconds: float = 6.0) -> None:
        self._notes.notify_all(self._server.get_clients().values(), title, body, color=color,
                               seconds=seconds)

    # ---------------------------------------------------------------- scene graph
    def _rebuild_mesh(self) -> None:
        """Replace the displayed mesh node (simulation thread only)."""
        mode = self._state.mesh_mode if self._state.has_skin() else "sim"
        self._graph.rebuild_mesh(self._sim, mode,
                                 drag_handler(self.begin_pull, self.move_pull, self.end_pull))

    # ---------------------------------------------------------------- commands (sim thread)
    def _do_toggle_mesh_mode(self) -> None:
        self._state.toggle_mesh_mode()
        if not self._state.has_skin():
            self._notify_all("No skinned mesh", "This scene has only its simulation mesh.")
        self._rebuild_mesh()
        self._state.gui_dirty = True

    def _do_toggle_integrator(self) -> None:
        try:
            self._state.toggle_integrator()
        except Fem3dError as exc:  # e.g. a contact scene refuses the linearly-implicit scheme
            self._notify_all("Integrator not switched", str(exc), color="yellow", seconds=8.0)

    def _do_reset(self) -> None:
        self._state.reset()
        self._notes.clear()
        self._state.pacer.reset()
        self._state.gui_dirty = True

    def _do_set_material(self, E: float | None, nu: float | None, rho: float | None) -> None:
        try:
            self._state.set_material(E, nu, rho)
        except Fem3dError as exc:
            self._notify_all("Material not changed", str(exc), color="yellow")
            return
        if E is not None and self._panel.widgets:
            self._panel.sync_E(float(E))
        self._state.gui_dirty = True

    def _do_switch_material(self, name: str) -> None:
        try:
            self._state.switch_material(name)
        except Fem3dError as exc:
            self._notify_all("Material not changed", str(exc), color="yellow", seconds=10.0)
            self._panel.widgets["material"].value = self._state.material_model()

    def _do_set_colour_field(self, name: str) -> None:
        self._graph.colouring.select(name)
        menu = self._panel.widgets.get("colour")
        if menu is not None and menu.value != name:  # chosen by a call, not on the page
            menu.value = name
        self._rebuild_mesh()
        self._state.gui_dirty = True

    def _do_switch_scene(self, name: str) -> None:
        s = self._state
        if name == s.scene_label:
            return
        try:
            scene, sim = s.load(name)
        except Fem3dError as exc:
            self._notify_all("Could not load scene", str(exc), color="red", seconds=10.0)
            self._panel.widgets["scene"].value = s.scene_label
            return
        self._notes.clear()
        s.install(name, scene, sim)
        self._rebuild_mesh()
        self._graph.rebuild_obstacles(sim)
        self._graph.update_spring(None, sim.q, s.generation)
        self._apply_camera()
        self._panel.show_scene(s.material, s.material_model(), s.radius_range())
        s.pacer.reset()
        s.gui_dirty = True

    # ---------------------------------------------------------------- main loop
    def _fail(self, message: str) -> None:
        self._state.fail(message)
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
        graph = self._graph
        shown = (graph.mesh_serial, pull_key)
        changed = (
            self._shown is None or shown[0] != self._shown[0] or shown[1] != self._shown[1]
            or q.shape != self._shown_q.shape or not np.array_equal(q, self._shown_q)
        )
        if not (force or changed):
            pass  # nothing moved (paused, or at rest): send nothing
        elif not force and self._acks.busy(now):
            self._acks.hold_back()  # a page is still busy with the last update
        else:
            verts = graph.display_positions(self._sim)
            if np.isfinite(verts).all():
                with self._server.atomic():
                    graph.show_positions(self._sim, verts)
                    graph.update_spring(pull, q, self._state.generation)
                    graph.update_obstacles(self._sim)
                self._acks.request(self._server.get_clients().values(), now)
                self._shown, self._shown_q = shown, q.copy()
                with self._state.lock:
                    self._state.pushes += 1
        if force or self._state.gui_dirty or now - self._last_plot >= 1.0 / self.plot_hz:
            self._last_plot = now
            self._state.gui_dirty = False
            self._push_gui()

    def _push_gui(self) -> None:
        s = self._state
        with s.lock:
            shown = None if self._graph is None else self._graph.mesh_mode
            text = s.status_locked(shown or s.mesh_mode)
            x, *series = s.history.plot_series(self.plot_window, n=PLOT_POINTS)
            latest = s.history.latest_split()
            peaks = s.history.peaks()
        self._panel.update(text, latest, x, series, peaks)
        self._panel.show_legend(self._graph.colouring.legend_text)

    def _run_commands(self) -> None:
        """Apply the queued commands (a bad one fails the simulation, not the loop)."""
        while (command := self._state.next_command()) is not None:
            try:
                command()
            except Exception as exc:  # noqa: BLE001 - a bad command must not stop the loop
                self._state.log_exception()
                self._fail(f"{type(exc).__name__}: {exc}")

    def _run(self) -> None:
        """The simulation thread: commands, pull, a paced step, display updates; while no
        page is connected it sleeps on the wake event (a page, a command or stop wakes it)."""
        s = self._state
        while not self._stop.is_set():
            s.wake.clear()
            self._loops += 1
            self._run_commands()
            try:
                pull = s.sync_pull()
            except Exception as exc:  # noqa: BLE001 - e.g. a rejected pull
                s.log_exception()
                self._fail(f"{type(exc).__name__}: {exc}")
                with s.lock:
                    s.drop_pulls()
                    pull = None
            with s.lock:
                running, t_sim = not s.paused, s.t
            wait = self._gate.next_wait(t_sim, running)
            if wait is None:  # nobody watches: no step, no CPU
                s.wake.wait()
                continue
            if wait == 0.0:
                error = s.step()
                if error is not None:
                    self._fail(error)
            try:
                self._push(pull)
            except Exception:  # noqa: BLE001 - e.g. the server is stopping
                if self._stop.is_set():
                    break
                s.log_exception()
            if wait > 0.0:
                due = self._last_push + 1.0 / self.push_hz - time.perf_counter()
                s.wake.wait(max(0.0, min(wait, due)))


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
    import_viser()
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
    print(f"fem3d view: {url}  ({console_help()}; it simulates while a page is open)",
          flush=True)
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

