"""The :class:`Simulation` object: a scene, a frozen model, a moving state and an integrator.

Used by the headless ``fem3d run``, the viewer and the benchmarks::

    from fem3d.scenes import load_scene
    from fem3d.simulation import Simulation

    sim = Simulation(load_scene("bunny"))          # scene's default integrator
    sim.set_pull(sim.pick(sim.q[155]), sim.q[155] + [20.0, 0.0, 0.0])
    info = sim.step()                               # StepInfo(t, kinetic, potential, ...)
    sim.clear_pull()
    display = sim.skin_positions()                  # (k, 3) skinned display vertices

Energies: ``kinetic = 1/2 v^T M v``, ``potential`` = strain energy ``V(q)``,
``total = kinetic + potential``; the pull springs' energy is reported separately
(``StepInfo.pull``), because it is external work.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from fem3d.assembly import kinetic_energy, potential_energy
from fem3d.constraints import Constraints, fixed_vertices_lowest_y, pick_nearest_vertices
from fem3d.errors import ParameterError, SimulationError
from fem3d.integrators import INTEGRATORS, Pull, State, StepStats, System
from fem3d.mesh import boundary_faces
from fem3d.model import Model, build_model, validate_dt
from fem3d.scenes import Scene

__all__ = ["Simulation", "StepInfo", "RUNAWAY_FACTOR"]

#: The linearly-implicit scheme is declared exploded when its total energy (kinetic + strain
#: + pull springs) exceeds this factor times the energy put in so far.
RUNAWAY_FACTOR = 1e3


@dataclass(frozen=True)
class StepInfo:
    """What one :meth:`Simulation.step` did.

    Attributes
    ----------
    t : float
        Time after the step.
    kinetic, potential, total : float
        ``1/2 v^T M v``, strain energy, and their sum, after the step.
    newton_iterations : int
        Newton iterations (1 for the linearly-implicit scheme).
    seconds : float
        Wall time of the step.
    pull : float
        Energy of the pull springs after the step (0 without a pull).
    step : int
        Number of steps taken so far.
    """

    t: float
    kinetic: float
    potential: float
    total: float
    newton_iterations: int
    seconds: float
    pull: float = 0.0
    step: int = 0


class Simulation:
    """A running simulation of one scene.

    Parameters
    ----------
    scene : Scene
        From :func:`fem3d.scenes.load_scene`.
    integrator : {"linear", "implicit"}, optional
        None: the scene's default.
    backend : {None, "numpy", "c"}, optional
        Kernel back end (None: C if built).
    scripted : bool, optional
        Apply the scene's scripted pull (attach at ``pull.start``, release after
        ``pull.duration``) inside :meth:`step`. Default False (interactive use).
    solver_backend : str, optional
        Sparse solver back end (``fem3d.linsolve``; default ``"auto"``).
    max_newton_iterations : int or None, optional
        Newton iterations per backward-Euler step (default 5; None: until converged).
    newton_hessian : {"exact", "psd"}, optional
        Newton's Hessian in backward Euler (see :func:`fem3d.integrators.implicit_euler`).
    newton_solver : {"direct", "reuse"}, optional
        Newton's linear solves: refactorize every iteration, or keep a factorization as the
        CG preconditioner across iterations and steps, refactorizing when CG needs more than
        its budget (see :func:`fem3d.integrators.implicit_euler`).
    fixed_vertices : (n_fixed,) int, optional
        Explicit fixed vertices instead of the scene's lowest-y rule; must not be empty
        (every run is anchored: a free body would only drift with the pull).

    Raises
    ------
    ParameterError
        An empty fixed-vertex set, or (``scripted``) a picking radius that selects no vertex
        around the scripted pull's point.

    Attributes
    ----------
    scene : Scene
    model : Model
        Frozen model (replaced by :meth:`set_material`).
    constraints : Constraints
        The fixed vertices (lowest y within ``scene.fixed_tol``).
    surface_faces : (f, 3) int64
        Outward boundary triangles of the simulation mesh.
    last_stats : StepStats or None
        Details of the last step (Newton gradient norms, shifts, ...).
    """

    def __init__(
        self,
        scene: Scene,
        integrator: str | None = None,
        backend: str | None = None,
        *,
        scripted: bool = False,
        solver_backend: str = "auto",
        max_newton_iterations: int | None = 5,
        newton_hessian: str = "exact",
        fixed_vertices: np.ndarray | None = None,
        newton_solver: str = "direct",
    ) -> None:
        self.scene = scene
        self.model: Model = build_model(
            scene.X, scene.T, E=scene.E, nu=scene.nu, rho=scene.rho,
            material=scene.material, backend=backend, path=scene.mesh_path,
        )
        if fixed_vertices is None:
            fixed = fixed_vertices_lowest_y(scene.X, scene.fixed_tol)
        else:
            fixed = np.unique(np.asarray(fixed_vertices, dtype=np.int64).reshape(-1))
            if fixed.size == 0:
                raise ParameterError(
                    "the fixed-vertex set is empty: a run needs at least one fixed vertex"
                )
        self.constraints = Constraints.from_fixed_vertices(scene.X, fixed)
        self.system = System(self.model, self.constraints, solver_backend)
        self.surface_faces = boundary_faces(scene.T)
        self._dt = validate_dt(scene.dt)
        self._integrator = ""
        self.integrator = integrator or scene.integrator
        self.scripted = scripted
        self._script_ids: np.ndarray | None = None
        if scripted and scene.pull is not None:
            self._script_ids = self._pick_script_vertices()
        self.max_newton_iterations = max_newton_iterations
        if newton_hessian not in ("exact", "psd"):
            raise ParameterError(f"newton_hessian must be 'exact' or 'psd', got {newton_hessian!r}")
        self.newton_hessian = newton_hessian
        if newton_solver not in ("direct", "reuse"):
            raise ParameterError(
                f"newton_solver must be 'direct' or 'reuse', got {newton_solver!r}"
            )
        self.newton_solver = newton_solver
        self._W = None
        self.last_stats: StepStats | None = None
        self.reset()

    # ------------------------------------------------------------------ properties
    @property
    def integrator(self) -> str:
        """``"linear"`` (linearly-implicit Euler) or ``"implicit"`` (backward Euler)."""
        return self._integrator

    @integrator.setter
    def integrator(self, name: str) -> None:
        if name not in INTEGRATORS:
            raise ParameterError(
                f"unknown integrator {name!r}; choose one of {', '.join(INTEGRATORS)}"
            )
        self._integrator = name

    @property
    def dt(self) -> float:
        """Time step (settable, validated)."""
        return self._dt

    @dt.setter
    def dt(self, value: float) -> None:
        self._dt = validate_dt(value)

    @property
    def state(self) -> State:
        """The current (immutable) state."""
        return self._state

    @property
    def q(self) -> np.ndarray:
        """Current positions, ``(n, 3) float64`` (a read-only view)."""
        return self._state.q

    @property
    def v(self) -> np.ndarray:
        """Current velocities, ``(n, 3) float64`` (a read-only view)."""
        return self._state.v

    @property
    def t(self) -> float:
        """Current time."""
        return self._state.t

    @property
    def step_index(self) -> int:
        """Steps taken since :meth:`reset`."""
        return self._state.step

    @property
    def pull(self) -> Pull | None:
        """The active pull springs, if any."""
        return self._pull

    @property
    def fixed_vertices(self) -> np.ndarray:
        """``(n_fixed,) int64`` fixed vertices."""
        return self.constraints.fixed_vertices

    @property
    def skinning_matrix(self):
        """``(k, n)`` sparse skinning matrix (built on first use), or None without a skin."""
        if self._W is None and self.scene.skin_V is not None:
            from fem3d.skinning import build_skinning_matrix

            self._W = build_skinning_matrix(self.scene.X, self.scene.T, self.scene.skin_V)
        return self._W

    @property
    def display_faces(self) -> np.ndarray:
        """Triangles of :meth:`skin_positions`: the skin's, or the surface of the tet mesh."""
        return self.scene.skin_F if self.scene.skin_F is not None else self.surface_faces

    def skin_positions(self) -> np.ndarray:
        """Skinned display vertices ``W @ q``, ``(k, 3) float64``; ``q`` itself without a skin."""
        W = self.skinning_matrix
        return self.q.copy() if W is None else np.asarray(W @ self.q)

    # ------------------------------------------------------------------ state changes
    def _set_state(self, state: State) -> None:
        state.q.setflags(write=False)
        state.v.setflags(write=False)
        self._state = state

    def reset(self) -> None:
        """Back to rest, zero velocity, ``t = 0``, no pull."""
        self._pull: Pull | None = None
        self._script_on = False
        self._set_state(State.at_rest(self.model))
        self._injected = 0.0

    def set_state(self, q: np.ndarray, v: np.ndarray, t: float = 0.0, step: int = 0) -> None:
        """Replace positions and velocities (e.g. from a checkpoint).

        Parameters
        ----------
        q, v : (n, 3) float64
        t : float
        step : int
        """
        q = np.array(q, dtype=np.float64).reshape(self.model.X.shape)
        v = np.array(v, dtype=np.float64).reshape(self.model.X.shape)
        if not (np.isfinite(q).all() and np.isfinite(v).all()):
            raise ParameterError("state has non-finite positions or velocities")
        self._set_state(State(q=q, v=v, t=float(t), step=int(step)))
        self._injected = max(self._injected, self._energy_with_pull())

    def snapshot(self) -> dict:
        """Everything that determines the next steps, for a bit-exact :meth:`restore`.

        Returns
        -------
        dict
            ``q, v`` (n, 3) float64, ``t`` float, ``step`` int, ``injected`` float (energy
            put in so far: the linearly-implicit runaway bound), ``script_on`` bool (the
            scripted pull is attached), ``pull_vertices`` (k,) int64, ``pull_targets``
            (k, 3) float64 and ``pull_k`` float (``k = 0`` and empty arrays: no pull),
            ``preconditioner`` (nnz,) float64: with ``newton_solver="reuse"`` the reduced
            matrix whose factorization later steps reuse (empty otherwise).
            Arrays are the simulation's own read-only arrays, not copies.
        """
        pull = self._pull
        kept = self.system.factorized_data if self.newton_solver == "reuse" else None
        return {
            "preconditioner": np.zeros(0) if kept is None else kept,
            "q": self._state.q, "v": self._state.v, "t": float(self._state.t),
            "step": int(self._state.step), "injected": float(self._injected),
            "script_on": bool(self._script_on),
            "pull_vertices": (np.zeros(0, np.int64) if pull is None else pull.vertices),
            "pull_targets": (np.zeros((0, 3)) if pull is None else pull.targets),
            "pull_k": 0.0 if pull is None else float(pull.k),
        }

    def restore(self, snap: dict) -> None:
        """Set the state saved by :meth:`snapshot` (also one read back from a checkpoint).

        Raises
        ------
        ParameterError
            Wrong shapes or non-finite values.
        """
        q = np.array(snap["q"], dtype=np.float64)
        v = np.array(snap["v"], dtype=np.float64)
        if q.shape != self.model.X.shape or v.shape != self.model.X.shape:
            raise ParameterError(
                f"state has shape {q.shape} / {v.shape}, the mesh {self.model.X.shape}"
            )
        if not (np.isfinite(q).all() and np.isfinite(v).all()):
            raise ParameterError("state has non-finite positions or velocities")
        verts = np.asarray(snap["pull_vertices"], dtype=np.int64).reshape(-1)
        pull = None
        if verts.size:
            pull = Pull.make(verts, np.asarray(snap["pull_targets"], dtype=np.float64),
                             float(snap["pull_k"]), self.model.n_vertices)
        self._set_state(State(q=q, v=v, t=float(snap["t"]), step=int(snap["step"])))
        self._pull = pull
        self._script_on = bool(snap["script_on"])
        self._injected = float(snap["injected"])
        saved = np.asarray(snap.get("preconditioner", np.zeros(0)), dtype=np.float64)
        if self.newton_solver == "reuse" and saved.size:
            self.system.refactorize_saved(saved)

    def pick(self, point: np.ndarray, radius: float | None = None) -> np.ndarray:
        """Vertices within ``radius`` (default the scene's) of ``point`` in the current shape.

        Returns the nearest vertex when none is that close; ``(k,) int64``.
        """
        r = self.scene.pick_radius if radius is None else radius
        return pick_nearest_vertices(self.q, point, r, nearest_if_empty=True)

    def set_pull(self, vertex_ids, target, k: float | None = None) -> None:
        """Attach zero-rest-length springs from vertices to a target.

        Parameters
        ----------
        vertex_ids : (k,) int
            Pulled vertices (fixed ones are allowed but do not move).
        target : (3,) or (k, 3) float64
            One target point for all, or one per vertex.
        k : float, optional
            Stiffness (default the scene's ``spring_k``).
        """
        pull = Pull.make(
            vertex_ids, target, self.scene.spring_k if k is None else k, self.model.n_vertices
        )
        before = 0.0 if self._pull is None else self._pull.energy(self.system.spring, self.q)
        self._pull = pull if pull.vertices.size else None
        if self._pull is not None:
            # work done on the system by attaching / moving the springs: with the energy at
            # reset, an upper bound on the energy a stable scheme can hold
            after = self._pull.energy(self.system.spring, self.q)
            self._injected += max(0.0, after - before)

    def clear_pull(self) -> None:
        """Remove the pull springs."""
        self._pull = None

    def set_material(
        self, E: float | None = None, nu: float | None = None, rho: float | None = None
    ) -> None:
        """Change material values live (the pattern and solver analysis are kept)."""
        before = self._energy_with_pull()
        self.model = self.model.with_material(E=E, nu=nu, rho=rho)
        self.system = self.system.with_model(self.model)
        self._injected += max(0.0, self._energy_with_pull() - before)

    # ------------------------------------------------------------------ energies
    def energies(self) -> dict[str, float]:
        """``{"kinetic", "potential", "pull", "total"}`` of the current state."""
        kin = kinetic_energy(self.model, self.v)
        pot = potential_energy(self.model, self.q)
        pull = 0.0 if self._pull is None else self._pull.energy(self.system.spring, self.q)
        return {"kinetic": kin, "potential": pot, "pull": pull, "total": kin + pot}

    def _energy_with_pull(self) -> float:
        e = self.energies()
        return e["total"] + e["pull"]

    def _energy_bound(self) -> float:
        floor = 1e-9 * self.model.E * self.model.total_volume
        return RUNAWAY_FACTOR * max(self._injected, floor)

    # ------------------------------------------------------------------ stepping
    def _pick_script_vertices(self) -> np.ndarray:
        """Rest-shape vertices within ``pick_radius`` of the scripted pull's point."""
        script = self.scene.pull
        r = self.scene.pick_radius
        ids = pick_nearest_vertices(self.model.X, script.point, r)
        if ids.size == 0:
            d = float(np.sqrt(((self.model.X - script.point) ** 2).sum(axis=1).min()))
            p = ", ".join(f"{c:.6g}" for c in script.point)
            raise ParameterError(
                f"picking radius {r:g} selects no vertex around the pull point ({p}); "
                f"the nearest vertex is {d:.4g} away"
            )
        return ids

    def _apply_script(self) -> None:
        script = self.scene.pull
        if not self.scripted or script is None:
            return
        active = script.active(self.t, self.dt)
        if active and not self._script_on:
            if self._script_ids is None:
                self._script_ids = self._pick_script_vertices()
            ids = self._script_ids
            self.set_pull(ids, self.model.X[ids] + script.offset)
            self._script_on = True
        elif not active and self._script_on:
            self.clear_pull()
            self._script_on = False

    def step(self) -> StepInfo:
        """Advance one time step with the current integrator.

        Returns
        -------
        StepInfo

        Raises
        ------
        SimulationError
            The step failed (explosion, no admissible Newton step); the state stays at the
            last good step.
        """
        self._apply_script()
        t0 = time.perf_counter()
        if self._integrator == "linear":
            new, stats = INTEGRATORS["linear"](
                self.system, self._state, self._dt, self._pull,
                energy_bound=self._energy_bound(),
            )
        else:
            new, stats = INTEGRATORS["implicit"](
                self.system, self._state, self._dt, self._pull,
                max_iterations=self.max_newton_iterations, hessian=self.newton_hessian,
                linear_solver=self.newton_solver,
            )
        seconds = time.perf_counter() - t0
        kin = kinetic_energy(self.model, new.v)
        pot = potential_energy(self.model, new.q)
        if not (math.isfinite(kin) and math.isfinite(pot)):
            raise SimulationError(
                f"{self._integrator} integrator exploded: non-finite energy", step=new.step - 1
            )
        pull = 0.0 if self._pull is None else self._pull.energy(self.system.spring, new.q)
        self._set_state(new)
        self.last_stats = stats
        return StepInfo(
            t=new.t, kinetic=kin, potential=pot, total=kin + pot,
            newton_iterations=stats.newton_iterations, seconds=seconds, pull=pull,
            step=new.step,
        )
