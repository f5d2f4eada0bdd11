"""The :class:`Simulation` object: a scene, a frozen model, a moving state and an integrator.

Used by the headless ``fem3d run``, the viewer and the benchmarks::

    from fem3d.scene import load_scene
    from fem3d.simulation import Simulation

    sim = Simulation(load_scene("bunny"))          # everything from data/scenes/bunny.toml
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
import re
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fem3d.errors import ParameterError, SimulationError
from fem3d.io.obstacles import ObstacleMesh, plane_square
from fem3d.physics.assembly import kinetic_energy, potential_energy
from fem3d.physics.constraints import Constraints, pick_nearest_vertices
from fem3d.physics.model import Model, validate_dt
from fem3d.physics.springs import Pull
from fem3d.physics.terms.loads import Loads
from fem3d.scene.build import build
from fem3d.scene.share import Share, build_share
from fem3d.scene.spec import Scene
from fem3d.solve.schemes.base import Scheme, model_terms
from fem3d.solve.schemes.registry import get_scheme
from fem3d.solve.settings import NewtonSettings
from fem3d.solve.state import State, StepStats
from fem3d.solve.system import System

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


def _check_supported(scene: Scene) -> None:
    """Refuse, naming the key, the settings this build validates but cannot run yet."""
    if scene.obstacles and not scene.contact.enabled:
        raise scene.error("obstacles", "obstacles act through contact: set [contact] enabled "
                          "= true")
    name = scene.simulation.integrator
    try:
        scheme = get_scheme(name)
    except ParameterError as exc:
        raise scene.error("simulation.integrator", str(exc)) from None
    if scene.contact.enabled and not scheme.contact:
        raise scene.error("simulation.integrator", CONTACT_NEEDS_IMPLICIT)
    if not scheme.dynamic:
        for i, body in enumerate(scene.bodies):
            if any(body.velocity) or any(body.angular_velocity):
                raise scene.error(f"bodies[{i}].velocity", f"the {name} integrator has no "
                                  "velocities (an equilibrium per step): remove the initial "
                                  "velocity or choose a dynamic integrator")


#: Why the linearly-implicit scheme refuses contact scenes (one line, CLI and viewer).
CONTACT_NEEDS_IMPLICIT = ("contact needs backward Euler (integrator = \"implicit\"): the "
                          "linearly-implicit scheme cannot keep IPC's no-intersection "
                          "guarantee")


def _stiffness(k) -> float | np.ndarray:
    a = np.asarray(k, dtype=np.float64)
    return float(a) if a.ndim == 0 else a


class Simulation:
    """A running simulation of one scene.

    Parameters
    ----------
    scene : fem3d.scene.spec.Scene
        Everything about the run (from :func:`fem3d.scene.load.load_scene`); read here, once.
    backend : {None, "numpy", "c"}, optional
        Kernel back end (None: C if built).
    scripted : bool, optional
        Apply the scene's scripted pulls (each attaches at its ``start`` and is released
        after its ``duration``) inside :meth:`step`. Default False (interactive use).
    make_system : callable ``(model, constraints, loads) -> System``, optional
        Makes the system instead of :class:`System` on the scene's linear solver (one MPI
        rank's share of a distributed run: :func:`fem3d.parallel.run.distributed_simulation`).
    restrict_model : fem3d.scene.share.Share, optional
        The model of a share of the tets instead of the whole (one MPI rank's:
        :func:`fem3d.scene.share.build_share`); :attr:`model` is then the share's.

    Raises
    ------
    InputError
        ``FILE: key.path: ...``: a bad mesh, a selector that selects nothing, a setting this
        build cannot run yet.

    Attributes
    ----------
    scene : Scene
    assembled : fem3d.scene.arrays.SceneArrays
        The scene in arrays (rest positions, tets, pins, pulls, display mesh).
    model : Model
        Frozen model (replaced by :meth:`set_material`).
    constraints : Constraints
        The pinned vertices.
    surface_faces : (f, 3) int64
        Outward boundary triangles of the simulation mesh.
    pick_radius, spring_k : float
        Interactive picking radius and pull-spring stiffness (``scene.interaction``,
        resolved); settable.
    newton : NewtonSettings
        Newton's settings for every scheme (from ``scene.simulation.newton``; settable).
    max_substeps : int
        Contact steps whose straight motion passes through a surface are redone in up to
        this many substeps (``scene.contact.max_substeps``; :mod:`fem3d.solve.substeps`;
        not ``static``).
    last_stats : StepStats or None
        Details of the last step (Newton gradient norms, shifts, ...).
    """

    def __init__(self, scene: Scene, *, backend: str | None = None,
                 scripted: bool = False,
                 make_system: Callable[[Model, Constraints, Loads], System] | None = None,
                 restrict_model: Share | None = None) -> None:
        self.scene = scene
        _check_supported(scene)
        # arrays, model, pins, motions, contact
        built = build(scene, backend=backend) if restrict_model is None else \
            build_share(scene, backend, restrict_model)
        a = built.arrays
        self.assembled = a
        self.model: Model = built.model
        self.constraints = built.constraints
        sim = scene.simulation
        try:
            if make_system is not None:  # e.g. one rank's share (fem3d.parallel)
                self.system = make_system(self.model, self.constraints, built.loads)
            else:
                self.system = System(self.model, self.constraints, sim.linear_solver,
                                     loads=built.loads, cholmod_mode=sim.cholmod,
                                     petsc_options=sim.petsc_options)
        except (ValueError, ImportError) as exc:
            raise scene.error("simulation.linear_solver", str(exc)) from None
        self._motions = built.motions
        #: each pin's key and the DOFs it holds (:meth:`reactions`' groups)
        self.pin_groups = built.pin_groups
        self._before: State | None = None
        #: The IPC contact term of a contact scene
        #: (:class:`fem3d.physics.terms.contact.ContactTerm`).
        self.contact = built.contact
        if self.contact is not None:
            try:
                self.contact.contact.check_admissible(self._initial_positions())
            except SimulationError as exc:
                raise scene.error("bodies", f"in the initial state, {exc.reason.split(': ', 1)[1]}"
                                  ) from None
        self.surface_faces = a.surface_triangles()
        self._dt = validate_dt(sim.dt)
        self._scheme: Scheme | None = None
        self.integrator = sim.integrator
        self.scripted = scripted
        self.newton = NewtonSettings.from_spec(sim.newton)
        self.max_substeps = scene.contact.max_substeps
        self.pick_radius = built.pick_radius
        self.spring_k = built.spring_k
        self._W = None
        self.last_stats: StepStats | None = None
        self.reset()

    def _initial_positions(self) -> np.ndarray:
        """Rest positions with the moving pins at their ``t = 0`` positions."""
        q = self.model.X.copy()
        p = self.fixed_positions(0.0)
        if p is not None:
            c = self.constraints
            q.reshape(-1)[c.fixed_dofs] = p.reshape(-1)[c.fixed_slots]
        return q

    def obstacles(self, t: float | None = None) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """The contact scene's mesh obstacles at time ``t`` (default: now), for display:
        ``(name, vertices (k, 3), faces (f, 3))`` each; planes are
        ``self.contact.contact.planes`` (point, normal). Empty without contact."""
        if self.contact is None:
            return []
        t = self.t if t is None else t
        return [(m.name, m.positions(t), m.faces) for m in self.contact.contact.meshes]

    def obstacle_meshes(self) -> list[ObstacleMesh]:
        """The contact scene's obstacles as triangle meshes for the outputs (frames, preview):
        each plane a square three diagonals of the bodies' rest bounding box wide, centred
        below the bodies (a 10 x 10 grid of quads), each mesh obstacle with its motion. Empty
        without contact."""
        if self.contact is None:
            return []
        cm = self.contact.contact
        X = self.model.X
        lo, hi = X.min(axis=0), X.max(axis=0)
        center, half = 0.5 * (lo + hi), 1.5 * float(np.linalg.norm(hi - lo))
        out = []
        for p in cm.planes:
            V, F = plane_square(p.point, p.normal, center, half, cells=10)
            out.append(ObstacleMesh(p.name, V, F, plane=(p.point, p.normal)))
        for m in cm.meshes:
            motion = None if m.motion is None else (lambda t, m=m: m.positions(t))
            out.append(ObstacleMesh(m.name, m.vertices, m.faces, motion=motion))
        # in the scene's order (obstacles[i]): planes and meshes are kept apart above
        return sorted(out, key=lambda o: int(re.search(r"\d+", o.name + "0").group()))

    def fixed_positions(self, t: float) -> np.ndarray | None:
        """Positions of the pinned vertices at time ``t`` (None: no moving pin).

        Returns
        -------
        (n_fixed, 3) float64 or None
            In the order of :attr:`fixed_vertices`; static pins at their rest positions.
        """
        if not self._motions:
            return None
        p = self.model.X[self.constraints.fixed_vertices].copy()
        for slots, rest, kf in self._motions:
            p[slots] = kf.apply(rest, t)
        return p

    @property
    def motion_end(self) -> float:
        """Time after which no pin moves any more (0 without moving pins)."""
        return max((float(kf.times[-1]) for _, _, kf in self._motions), default=0.0)

    # ------------------------------------------------------------------ properties
    @property
    def integrator(self) -> str:
        """The scheme's name (:mod:`fem3d.solve.schemes.registry`; ``docs/integrators.md``);
        settable, by name."""
        return self._scheme.name

    @integrator.setter
    def integrator(self, name: str) -> None:
        scheme = get_scheme(name)
        if not scheme.contact and getattr(self, "contact", None) is not None:
            raise ParameterError(CONTACT_NEEDS_IMPLICIT)
        self._scheme = scheme

    @property
    def scheme(self) -> Scheme:
        """The time integrator (:class:`fem3d.solve.schemes.base.Scheme`)."""
        return self._scheme

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
        if self._W is None:
            self._W = self.assembled.skinning_matrix()
        return self._W

    @property
    def display_faces(self) -> np.ndarray:
        """Triangles of :meth:`skin_positions`: the skin's, or the surface of the tet mesh."""
        return self.assembled.skin_F if self.assembled.skin_F is not None else self.surface_faces

    @property
    def has_skin(self) -> bool:
        """Whether the display mesh is a skin (not the simulation mesh's boundary)."""
        return self.assembled.skin_F is not None

    @property
    def rest_skin(self) -> np.ndarray:
        """Rest display vertices, ``(k, 3) float64`` (the rest mesh without a skin)."""
        a = self.assembled
        return a.X if a.skin_V is None else a.skin_V

    def skin_positions(self) -> np.ndarray:
        """Skinned display vertices ``W @ q``, ``(k, 3) float64``; ``q`` itself without a skin."""
        W = self.skinning_matrix
        return self.q.copy() if W is None else np.asarray(W @ self.q)

    # ------------------------------------------------------------------ state changes
    def _set_state(self, state: State) -> None:
        for a in (state.q, state.v, *state.history.values()):
            a.setflags(write=False)
        self._state = state

    def reset(self) -> None:
        """Back to rest, zero velocity, ``t = 0``, no pull."""
        self._pull: Pull | None = None
        self._script_active: tuple[int, ...] = ()
        rest = State.at_rest(self.model)
        v0 = self.assembled.v0.copy()
        v0.reshape(-1)[self.constraints.fixed_dofs] = 0.0  # pinned DOFs start at rest
        self._set_state(State(q=rest.q, v=v0, t=0.0, step=0))
        self._injected = self.system.summed(kinetic_energy(self.model, self.v))
        self._before = None
        if self.contact is not None:
            self.contact.reset()

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

    @property
    def _keeps_solver_state(self) -> bool:
        """Whether later steps reuse a factorization or AMG hierarchy (a checkpoint must
        rebuild it for a bit-exact resume)."""
        return self.newton.solver == "reuse" or self.system.linear_backend == "amg"

    def snapshot(self) -> dict:
        """Everything that determines the next steps, for a bit-exact :meth:`restore`.

        Returns
        -------
        dict
            ``q, v`` (n, 3) float64, ``t`` float, ``step`` int, ``injected`` float (energy
            put in so far: the linearly-implicit runaway bound), ``script_active``
            (j,) int64 (the scripted pulls attached: indices into ``scene.pulls``),
            ``pull_vertices`` (k,) int64, ``pull_targets`` (k, 3) float64
            and ``pull_k`` () or (k,) float64 (one stiffness or one per spring; ``k = 0`` and
            empty arrays: no pull),
            ``history_<name>`` (n, 3) float64: the scheme's history
            (:meth:`Scheme.save_history <fem3d.solve.schemes.base.Scheme.save_history>`:
            BDF2's previous state, Newmark's acceleration; none for one-step schemes),
            ``preconditioner`` (nnz,) float64: with ``newton.solver="reuse"`` or AMG the reduced
            matrix whose factorization later steps reuse (empty otherwise).
            Arrays are the simulation's own read-only arrays, not copies.
        """
        pull = self._pull
        kept = self.system.factorized_data if self._keeps_solver_state else None
        return {
            "preconditioner": np.zeros(0) if kept is None else kept,
            "q": self._state.q, "v": self._state.v, "t": float(self._state.t),
            "step": int(self._state.step), "injected": float(self._injected),
            "script_active": np.asarray(self._script_active, dtype=np.int64),
            "pull_vertices": (np.zeros(0, np.int64) if pull is None else pull.vertices),
            "pull_targets": (np.zeros((0, 3)) if pull is None else pull.targets),
            "pull_k": np.asarray(0.0 if pull is None else pull.k, dtype=np.float64),
            "contact": (np.zeros(0) if self.contact is None else self.contact.state_array()),
            "pattern_keys": self.system.pattern_keys(),
            **{f"history_{k}": a for k, a in self._scheme.save_history(self._state).items()},
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
        # an MPI rank's share of an attached pull may hold none of its springs
        attached = bool(np.asarray(snap.get("pull_attached", verts.size > 0)))
        if verts.size or (attached and self.system.is_share):
            pull = Pull.make(verts, np.asarray(snap["pull_targets"], dtype=np.float64),
                             _stiffness(snap["pull_k"]), self.model.n_vertices)
        saved = {k[len("history_"):]: a for k, a in snap.items() if k.startswith("history_")}
        history = self._scheme.restore_history(saved, self.model.X.shape)
        self._set_state(State(q=q, v=v, t=float(snap["t"]), step=int(snap["step"]),
                              history=history))
        self._pull = pull
        self._script_active = tuple(
            int(i) for i in np.asarray(snap["script_active"], dtype=np.int64).reshape(-1))
        self._injected = float(snap["injected"])
        contact = np.asarray(snap.get("contact", np.zeros(0)), dtype=np.float64)
        if self.contact is not None and contact.size:
            self.contact.load_state_array(contact)
        keys = np.asarray(snap.get("pattern_keys", np.zeros(0, np.int64)), dtype=np.int64)
        self.system.restore_pattern(keys)
        saved = np.asarray(snap.get("preconditioner", np.zeros(0)), dtype=np.float64)
        if self._keeps_solver_state and saved.size:
            self.system.refactorize_saved(saved)

    def pick(self, point: np.ndarray, radius: float | None = None) -> np.ndarray:
        """Vertices within ``radius`` (default the scene's) of ``point`` in the current shape.

        Returns the nearest vertex when none is that close; ``(k,) int64``.
        """
        r = self.pick_radius if radius is None else radius
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
        self._attach(Pull.make(
            vertex_ids, target, self.spring_k if k is None else k, self.model.n_vertices
        ))

    def _pull_energy(self, q: np.ndarray) -> float:
        """The pull springs' energy at ``q`` (0 without a pull; an MPI rank's springs
        summed over the ranks)."""
        if self._pull is None:
            return 0.0
        return float(self.system.summed(self._pull.energy(self.system.spring, q)))

    def _attach(self, pull: Pull | None) -> None:
        before = self._pull_energy(self.q)
        # a rank's share of a pull may hold none of its springs: attached all the same
        keep = pull is not None and (pull.vertices.size or self.system.is_share)
        self._pull = pull if keep else None
        if self._pull is not None:
            # work done on the system by attaching / moving the springs: with the energy at
            # reset, an upper bound on the energy a stable scheme can hold
            self._injected += max(0.0, self._pull_energy(self.q) - before)

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
        """``{"kinetic", "potential", "pull", "total", "strain", "gravity"}`` of the current
        state (``potential = strain + gravity``, gravity's ``-M g . (q - X)``); the whole
        model's on MPI ranks too (:meth:`System.summed`)."""
        kin = self.system.summed(kinetic_energy(self.model, self.v))
        strain = self.system.summed(potential_energy(self.model, self.q))
        gravity = self.gravity_energy()
        pot = strain + gravity
        pull = self._pull_energy(self.q)
        return {"kinetic": kin, "potential": pot, "pull": pull, "total": kin + pot,
                "strain": strain, "gravity": gravity}

    def reactions(self) -> np.ndarray:
        """``(n_pins, 3)``: the force each pin exerts on the body in the current state, in
        the order of :attr:`pin_groups` (zero in the components a pin leaves free).

        ``R = dV/dq - f_ext + M a`` on the pin's DOFs: ``V`` the position terms' potentials
        (strain, pull springs, surface and point loads, contact; a term's
        ``reaction_gradient`` where it has one: a follower pressure counts its follower load,
        not its potential's edge forces), ``f_ext`` gravity, ``a``
        the acceleration of the last step's equation of motion (:meth:`_acceleration`; zero
        in ``static``); Rayleigh damping's force is left out. In a static equilibrium the
        reactions balance the applied loads (docs/loads.md).

        A rank of a distributed run holds a share of each pin's DOFs (those of the vertices
        it owns, :attr:`pin_groups`) and its tets' part of the forces: the forces are
        summed at its vertices and the pins' totals over the ranks (collective).
        """
        q = self.q.reshape(-1)
        g = np.zeros(q.size)
        for term in self.objective_terms():
            if getattr(term, "variable", "position") == "position" and term.active:
                g += getattr(term, "reaction_gradient", term.gradient)(q)
        summed = self.system.summed  # (the terms' gradients are summed already)
        if self.system.loads.gravity is not None:
            g -= summed(self.system.loads.gravity.force)
        a = self._acceleration()
        if a is not None:
            g += summed(self.model.mass @ a)
        out = np.zeros((len(self.pin_groups), 3))
        for k, (_, dofs) in enumerate(self.pin_groups):
            np.add.at(out[k], dofs % 3, g[dofs])
        return self.system.total(out)

    def _acceleration(self) -> np.ndarray | None:
        """``(3n,)`` the acceleration the last step's equation of motion holds at its end
        (:meth:`Scheme.acceleration`); None before a step and without inertia."""
        if self._before is None:
            return None
        return self._scheme.acceleration(self._before, self._state, self._dt)

    def gravity_energy(self) -> float:
        """Gravity's potential ``-M g . (q - X)`` of the current state (the part of
        ``energies()["potential"]`` that is not strain)."""
        return float(self.system.loads.gravity_energy(self.q))

    def _energy_with_pull(self) -> float:
        e = self.energies()
        return e["total"] + e["pull"]

    def _energy_bound(self) -> float:
        floor = 1e-9 * self.model.E * self.system.summed(self.model.total_volume)
        return RUNAWAY_FACTOR * max(self._injected, floor)

    # ------------------------------------------------------------------ stepping
    def _apply_script(self) -> None:
        """Attach / release the scene's scripted pulls for the step that starts now."""
        pulls = self.assembled.pulls
        if not self.scripted or not pulls:
            return
        active = tuple(j for j, p in enumerate(pulls) if p.active(self.t, self.dt))
        if active == self._script_active:
            return
        if len(active) == 1:
            self._attach(pulls[active[0]].pull)
        elif active:  # every spring of every active pull (a vertex may carry several)
            both = Pull.combine([pulls[j].pull for j in active], self.model.n_vertices)
            self._attach(pulls[active[0]].pull if both is None else both)
        else:
            self.clear_pull()
        self._script_active = active

    def objective_terms(self) -> list:
        """The terms the scheme minimises this step, in order: the model's (inertia,
        elasticity, the current pull, gravity, damping) and contact."""
        extra = [] if self.contact is None else [self.contact]
        return [*model_terms(self.system, self._pull), *extra]

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
        driven = bool(self._motions) and self.t < self.motion_end
        before = self._energy_with_pull() if driven else 0.0
        fixed = self.fixed_positions(self.t + self._dt)
        self._before = self._state
        t0 = time.perf_counter()
        new, stats = self._scheme.advance(
            self.system, self.objective_terms(), self._state, self._dt, self.newton,
            fixed_positions=fixed, fixed_at=self.fixed_positions,
            max_substeps=self.max_substeps,
            # the runaway guard of a scheme without line search: while pins move they do
            # work the bound cannot know in advance: it applies again (with that work added
            # to the budget) once they stop
            energy_bound=None if driven or self._scheme.minimises else self._energy_bound(),
        )
        seconds = time.perf_counter() - t0
        kin = self.system.summed(kinetic_energy(self.model, new.v))
        pot = self.system.summed(potential_energy(self.model, new.q)) + \
            self.system.loads.gravity_energy(new.q)
        if not (math.isfinite(kin) and math.isfinite(pot)):
            raise SimulationError(
                f"{self.integrator} integrator exploded: non-finite energy", step=new.step - 1
            )
        pull = self._pull_energy(new.q)
        self._set_state(new)
        if driven:  # work done by the moving pins: part of the runaway bound's budget
            self._injected += max(0.0, kin + pot + pull - before)
        self.last_stats = stats
        return StepInfo(
            t=new.t, kinetic=kin, potential=pot, total=kin + pot,
            newton_iterations=stats.newton_iterations, seconds=seconds, pull=pull,
            step=new.step,
        )
