"""The one place a scene is built: from its description to the objects a run steps.

:func:`build` turns a :class:`~fem3d.scene.spec.Scene` into a :class:`Built`: the scene in
arrays (:func:`fem3d.scene.arrays.build_arrays`: meshes, selections, scripted pulls), the
frozen :class:`~fem3d.physics.model.Model` of every body's material (regions, cell fields),
the pinned vertices, the moving pins' :class:`~fem3d.physics.motion.Keyframes`, gravity,
Rayleigh damping, the obstacles and the IPC contact term, and the resolved interaction values
(picking radius, pull-spring stiffness). :class:`fem3d.simulation.Simulation` takes a
``Built`` and adds what is not the scene's: the linear system, the integrator, the state.

Why one function returning one dataclass (and not a Simulation calling a few builders): the
stages depend on each other in one order (arrays, then the model, the pins, the motions, the
obstacles and contact), and that order also decides which error a scene with several
problems reports first; in one function it is written once, and every caller (the
simulation, tests, benchmarks) gets the same objects from the same call. The stages stay
public functions (:func:`model_from_scene`, :func:`pin_motions`, :func:`contact_from_scene`,
...) for a caller that needs one piece.

Errors are :class:`~fem3d.errors.InputError` ``FILE: key.path: what is wrong``, naming the
scene's key (a bad mesh, a selector that selects nothing, a bad motion or obstacle file).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from typing import Any, NamedTuple

import meshio
import numpy as np

from fem3d.errors import InputError, ParameterError
from fem3d.mesh.formats import read_surface_mesh
from fem3d.physics.constraints import Constraints, free_rigid_modes
from fem3d.physics.contact import ContactModel, MeshObstacle, PlaneObstacle
from fem3d.physics.model import (
    MaterialGroup,
    Model,
    build_model,
    mixed_model,
    with_psd_projection,
)
from fem3d.physics.motion import Keyframes
from fem3d.physics.terms.contact import ContactTerm
from fem3d.physics.terms.damping import RayleighDamping, check_coefficient
from fem3d.physics.terms.gravity import Gravity, check_gravity
from fem3d.physics.terms.loads import Loads
from fem3d.physics.terms.surface import (
    Amplitude,
    DeadLoad,
    FollowerPressure,
    faces_among,
    faces_within,
    point_forces,
    traction_forces,
)
from fem3d.scene.arrays import (
    SceneArrays,
    build_arrays,
    default_spring_k,
    select_vertices,
    transform_points,
)
from fem3d.scene.local import LocalNumbering
from fem3d.scene.spec import MaterialSpec, MotionSpec, Scene
from fem3d.solve.schemes.registry import get_scheme

__all__ = ["Built", "PinMotion", "build", "refuse_mixed_elements", "build_loads",
           "surface_loads_from_scene", "surface_load_specs", "select_loads", "SelectedLoad",
           "loads_of", "LoadSpec",
           "ModelInputs", "model_inputs", "model_of",
           "model_from_scene", "damping_from_scene", "pin_motions",
           "pin_groups", "keyframes_from_spec", "obstacles_from_scene", "contact_from_scene"]

_stages = logging.getLogger("fem3d.stages")  # stage marks (fem3d run --profile)


class PinMotion(NamedTuple):
    """A moving pin: which pinned vertices, where they rest, how they move.

    Attributes
    ----------
    slots : (k,) int64
        Indices into :attr:`Constraints.fixed_vertices`.
    rest : (k, 3) float64
        Rest positions of those vertices.
    keyframes : Keyframes
        Their motion (``keyframes.apply(rest, t)``).
    """

    slots: np.ndarray
    rest: np.ndarray
    keyframes: Keyframes


@dataclass(frozen=True, eq=False)
class Built:
    """A scene built (:func:`build`).

    Attributes
    ----------
    arrays : SceneArrays
        The scene in arrays (rest positions, tets, pins, scripted pulls, display mesh).
    model : Model
        Every body's material, frozen.
    constraints : Constraints
        The pinned vertices.
    gravity : (3,) tuple of float or None
        ``simulation.gravity``; None when it is zero.
    rayleigh_alpha, rayleigh_beta : float or ndarray
        Rayleigh damping ``alpha M + beta K`` (:func:`damping_from_scene`).
    loads : Loads
        Gravity and damping as terms (:func:`build_loads`).
    motions : list of PinMotion
        The moving pins (empty: every pin is fixed).
    contact : ContactTerm or None
        The IPC contact term of a contact scene (:func:`contact_from_scene`).
    pick_radius, spring_k : float
        Interaction values: ``interaction.pick_radius`` / ``spring_k``, or their defaults
        ``0.01 h`` / ``0.15 E h`` (``E`` the first body's, else the model's).
    pin_groups : tuple of (str, ndarray)
        Each pin's key (``bodies[0].pins[1]``) and the fixed DOFs it holds (``(k,) int64``;
        a DOF two pins hold counts for the first): the reactions' groups
        (:func:`pin_groups`).
    """

    arrays: SceneArrays
    model: Model
    constraints: Constraints
    gravity: tuple[float, float, float] | None
    rayleigh_alpha: float | np.ndarray
    rayleigh_beta: float | np.ndarray
    loads: Loads
    motions: list[PinMotion]
    contact: ContactTerm | None
    pick_radius: float
    spring_k: float
    pin_groups: tuple = ()


def build(scene: Scene, *, backend: str | None = None) -> Built:
    """Everything a run of ``scene`` needs that the scene decides.

    Parameters
    ----------
    scene : Scene
    backend : {None, "numpy", "c"}, optional
        Kernel back end of the model (None: C if built).

    Returns
    -------
    Built

    Raises
    ------
    InputError
        ``FILE: key.path: ...``: a bad mesh, a selector that selects nothing, no pinned
        vertex in a scene without contact, a bad material, motion or obstacle.
    """
    a = build_arrays(scene)
    _stages.debug("scene arrays (transforms, selections)")
    model = with_psd_projection(model_from_scene(scene, a, backend),
                                scene.simulation.psd_projection)
    constraints = _constraints(scene, a)
    check_static_support(scene, a, constraints)
    alpha, beta = damping_from_scene(scene, a)
    loads = _loads(scene, model, alpha, beta, surface_loads_from_scene(scene, a, model))
    return _built(scene, a, model, constraints, alpha, beta, loads,
                  pin_motions(scene, a, constraints.fixed_vertices), pin_groups(scene, a))


def _loads(scene: Scene, model: Model, alpha, beta, surface: list,
           keep_damping: bool = False) -> Loads:
    gravity = scene.simulation.gravity
    try:
        return build_loads(model, gravity if any(g != 0 for g in gravity) else None, alpha,
                           beta, surface=surface, keep_damping=keep_damping)
    except ParameterError as exc:
        raise scene.error("simulation", str(exc)) from None


def _built(scene: Scene, a: SceneArrays, model: Model, constraints: Constraints, alpha, beta,
           loads: Loads, motions: list, groups: tuple) -> Built:
    gravity = scene.simulation.gravity
    contact = contact_from_scene(scene, a) if scene.contact.enabled else None
    spring_k = (a.spring_k if a.spring_k is not None
                else default_spring_k(float(model.E), a.height))
    _stages.debug("pins, motions, damping, contact")
    return Built(arrays=a, model=model, constraints=constraints,
                 gravity=gravity if any(g != 0 for g in gravity) else None,
                 rayleigh_alpha=alpha, rayleigh_beta=beta, loads=loads, motions=motions,
                 contact=contact, pick_radius=a.pick_radius, spring_k=spring_k,
                 pin_groups=groups)


def refuse_mixed_elements(scene: Scene, what: str) -> None:
    """Refuse ``what`` (``"fem3d fit"``) for a scene whose bodies mix elements: one line naming
    the first body whose element differs from the first body's (nothing when they do not).

    Raises
    ------
    InputError
        ``FILE: bodies[i].element: 'p2' beside bodies[0]'s 'p1': ... need every body on one
        element ...``.
    """
    first = scene.bodies[0].element
    i = next((i for i, b in enumerate(scene.bodies) if b.element != first), None)
    if i is None:
        return
    raise scene.error(f"bodies[{i}].element", f"{scene.bodies[i].element!r} beside bodies[0]'s "
                      f"{first!r}: {what} need every body on one element (mixed elements run "
                      "with fem3d run, resume, view and sweep)")


def _constraints(scene: Scene, a: SceneArrays) -> Constraints:
    """The pinned vertices (or DOFs); refuses a scene without contact that pins none."""
    if a.fixed.size == 0 and not scene.contact.enabled:
        raise scene.error(
            "bodies[0].pins", "no pinned vertex: a run needs at least one (add pins = "
            "[{ select = { lowest_y = { tol = 0.0 } } }])")
    return (Constraints.from_fixed_vertices(a.X, a.fixed) if a.fixed_dofs is None
            else Constraints.from_fixed_dofs(a.X, a.fixed_dofs))


def check_static_support(scene: Scene, a: SceneArrays, constraints: Constraints) -> None:
    """Refuse a scheme without inertia (``static``) where a body has neither pins nor contact
    to hold it, or pins that leave a rigid motion free (its equilibrium is not unique: that
    motion costs nothing).

    Raises
    ------
    InputError
        ``FILE: simulation.integrator: ...`` or ``FILE: bodies[i].pins: ...``.
    """
    scheme = get_scheme(scene.simulation.integrator)
    if scheme.dynamic or scene.contact.enabled:
        return
    name = scheme.name
    fixed = np.zeros(a.X.shape[0], dtype=bool)
    fixed[constraints.fixed_vertices] = True
    fd = constraints.fixed_dofs
    for i, vs in enumerate(a.body_vertices):
        label = f"body {i} ({scene.bodies[i].label})"
        if not fixed[vs].any():
            raise scene.error(
                "simulation.integrator", f"{name} needs every body held by pins or "
                f"contact: {label} has neither, so it has no unique equilibrium")
        mine = fd[(fd >= 3 * vs.start) & (fd < 3 * vs.stop)] - 3 * vs.start
        free = free_rigid_modes(a.X[vs], mine)
        if free:
            raise scene.error(
                f"bodies[{i}].pins", f"{name}: {label} is under-supported: its pins "
                f"leave the rigid motion{'s' if len(free) > 1 else ''} {', '.join(free)} free "
                "(it costs nothing: no unique equilibrium; hold more dofs)")


def pin_groups(scene: Scene, a: SceneArrays) -> tuple:
    """``((key, dofs), ...)``: each pin's key and the DOFs it holds, in scene order (a DOF
    that two pins hold belongs to the first)."""
    out, taken = [], np.zeros(3 * a.X.shape[0], dtype=bool)
    for i, body in enumerate(scene.bodies):
        off = a.body_vertices[i].start
        for j, pin in enumerate(body.pins):
            key = f"bodies[{i}].pins[{j}]"
            ids = select_vertices(scene, a.X[a.body_vertices[i]], pin.select,
                                  f"{key}.select") + off
            dofs = (3 * ids[:, None] + np.array(pin.axes)).reshape(-1)
            dofs = np.sort(dofs[~taken[dofs]])
            taken[dofs] = True
            out.append((key, dofs))
    return tuple(out)


def build_loads(model: Model, gravity=None, rayleigh_alpha=0.0, rayleigh_beta=0.0, *,
                surface=(), keep_damping: bool = False) -> Loads:
    """Gravity, Rayleigh damping and the surface and point loads of ``model`` as terms.

    Parameters
    ----------
    model : Model
    gravity : (3,) float or None
        None or zero: no gravity term.
    rayleigh_alpha, rayleigh_beta : float or (n_vertices,) / (n_tets,) float64
        Damping ``alpha M + beta K`` (zero: no damping term).
    surface : sequence of DeadLoad or FollowerPressure, optional
        The bodies' loads (:func:`surface_loads_from_scene`).
    keep_damping : bool, optional
        Keep the damping term when its coefficients are zero here (an MPI rank's share of
        a scene that damps elsewhere: every rank keeps the same terms).

    Raises
    ------
    ParameterError
        Gravity not 3 finite numbers, a coefficient negative, non-finite or of the wrong
        shape.
    """
    g = check_gravity(gravity)
    alpha = check_coefficient(rayleigh_alpha, "rayleigh_alpha", model.n_vertices, "vertex")
    beta = check_coefficient(rayleigh_beta, "rayleigh_beta", model.n_tets, "tet")
    damping = RayleighDamping(model, alpha, beta)
    return Loads(None if g is None else Gravity(model, g),
                 damping if damping.active or keep_damping else None, alpha, beta,
                 tuple(surface))


class LoadSpec(NamedTuple):
    """A body's load in numbers (plain data: the rank that reads the scene sends a share's
    to its rank): a dead load's nodal forces at scale 1 (``kind`` ``"dead"``, ``data``
    ``(3n,)``) or a follower pressure's faces (``"pressure"``, ``data`` ``(f, 3 or 6)``)."""

    kind: str
    key: str
    amplitude: Amplitude | None
    data: np.ndarray
    pressure: float = 0.0


def surface_loads_from_scene(scene: Scene, a: SceneArrays, model: Model) -> list:
    """The bodies' ``loads`` as terms, in scene order: a traction or a point force as a
    :class:`DeadLoad`, a pressure as a :class:`FollowerPressure` (docs/loads.md).

    Raises
    ------
    InputError
        ``FILE: bodies[i].loads[j].select: ...``: a traction or pressure whose selection
        holds no whole boundary face, a selector that selects nothing.
    """
    return loads_of(model, surface_load_specs(scene, a, model.backend))


def loads_of(model: Model, specs: list[LoadSpec]) -> list:
    """The terms of :func:`surface_load_specs` on ``model``."""
    return [DeadLoad(model, s.data, s.amplitude, s.key) if s.kind == "dead" else
            FollowerPressure(model, s.data, s.pressure, s.amplitude, s.key) for s in specs]


class SelectedLoad(NamedTuple):
    """A body's load as selected on the whole scene and checked (:func:`select_loads`): a
    point force's vertices, or a traction's or pressure's whole patch of boundary faces."""

    spec: Any  # the scene's LoadSpec of the body (kind, force, traction, pressure)
    key: str
    amplitude: Amplitude | None
    ids: np.ndarray
    faces: np.ndarray | None


def select_loads(scene: Scene, a: SceneArrays, backend: str | None = None
                 ) -> list[SelectedLoad]:
    """Every body's loads selected on the whole scene, in scene order (done once: each MPI
    rank's share of them is cut from these).

    Raises
    ------
    InputError
        ``FILE: bodies[i].loads[j].select: ...``: a traction or pressure whose selection
        holds no whole boundary face, a follower pressure on an open patch, a selector that
        selects nothing.
    """
    out: list[SelectedLoad] = []
    faces: dict[int, np.ndarray] = {}  # each element block's boundary faces, once
    for i, body in enumerate(scene.bodies):
        off = a.body_vertices[i].start
        for j, load in enumerate(body.loads):
            key = f"bodies[{i}].loads[{j}]"
            ids = select_vertices(scene, a.X[a.body_vertices[i]], load.select,
                                  f"{key}.select") + off
            amplitude = None if load.keyframes is None else Amplitude(
                [k.t for k in load.keyframes], [k.scale for k in load.keyframes])
            mine = None
            if load.kind != "force":
                b = next(j for j, blk in enumerate(a.blocks) if i in blk.bodies)
                if b not in faces:
                    faces[b] = a.blocks[b].element.boundary_faces(a.blocks[b].T)
                mine = faces_within(faces[b], ids)
                if mine.size == 0:
                    raise scene.error(f"{key}.select", "selects no whole boundary face (a "
                                      "face is loaded when all its nodes are selected)")
                if load.kind == "pressure":
                    _check_open_edge(scene, a, mine, load.pressure, backend, key)
            out.append(SelectedLoad(load, key, amplitude, ids, mine))
    return out


def surface_load_specs(scene: Scene, a: SceneArrays, backend: str | None = None,
                       numbering: LocalNumbering | None = None,
                       owns: np.ndarray | None = None,
                       selected: list[SelectedLoad] | None = None) -> list[LoadSpec]:
    """The bodies' loads in numbers (:func:`surface_loads_from_scene`), of ``selected``
    (:func:`select_loads`, made here when not given).

    With ``numbering`` (one MPI rank's share, over its vertices) each load is the share's
    part, so that summed over the shares every face and point is counted once: a face
    belongs to the share of the tet it bounds, a point force's vertex to the share that
    owns it (``owns``: ``(n,) bool`` over the scene's vertices).
    """
    selected = select_loads(scene, a, backend) if selected is None else selected
    X, own_faces, local = a.X, None, (lambda ids: ids)
    if numbering is not None:
        # the share's boundary faces (scene numbers): the loaded faces of its own tets are
        # among them (a share is of one element: mixed elements are refused on ranks)
        X, local = a.X[numbering.vertices], numbering.local
        own_faces = a.element.boundary_faces(a.T[numbering.tets])
    out: list[LoadSpec] = []
    for load, key, amplitude, ids, mine in selected:
        if load.kind == "force":
            force = point_forces(a.X.shape[0], ids, load.force)
            if numbering is not None:  # F / k on each selected vertex the share owns
                force.reshape(-1, 3)[ids[~owns[ids]]] = 0.0
                force = numbering.dofs(force)
            out.append(LoadSpec("dead", key, amplitude, force))
            continue
        ours = local(mine if own_faces is None else faces_among(mine, own_faces))
        if load.kind == "traction":
            out.append(LoadSpec("dead", key, amplitude,
                                traction_forces(X, ours, load.traction, backend)))
        else:
            out.append(LoadSpec("pressure", key, amplitude, ours, load.pressure))
    return out


def _check_open_edge(scene: Scene, a: SceneArrays, faces: np.ndarray, pressure: float,
                     backend: str | None, key: str) -> None:
    """Refuse a pressure on an open patch ``faces`` (the whole patch, scene numbers) whose
    edge forces (the potential's, which a true follower pressure does not have) would act
    on free DOFs."""
    edge = FollowerPressure.rest_edge_forces(a.X, faces, pressure, backend)
    held = np.zeros(edge.size, dtype=bool)
    held[a.fixed_dofs if a.fixed_dofs is not None else
         (3 * a.fixed[:, None] + np.arange(3)).reshape(-1)] = True
    scale = abs(pressure) * float(np.linalg.norm(np.ptp(a.X, axis=0))) ** 2
    n = int(np.count_nonzero(np.abs(edge[~held]) > 1e-9 * scale))
    if n:
        raise scene.error(f"{key}.select", "a follower pressure needs a closed loaded surface, "
                          "or an open patch whose edge is held or lies in symmetry planes "
                          f"through the origin; this patch's edge leaves {n} DOFs free (use "
                          "traction for a dead load on an open patch)")


# ------------------------------------------------------------------------------ materials
def _simple_material(m: MaterialSpec) -> bool:
    return m.E is not None and not (m.params or m.regions or m.cell_fields)


def _cell_field(scene: Scene, a: SceneArrays, i: int, param: str, name: str) -> np.ndarray:
    """Body ``i``'s per-tet values of cell-data array ``name`` from its mesh file."""
    key = f"bodies[{i}].material.cell_fields.{param}"
    path = scene.path(scene.bodies[i].mesh)
    try:
        mesh = meshio.read(path)
    except Exception as exc:  # noqa: BLE001 - any reader failure is the user's file
        raise scene.error(key, f"cannot read cell data of {path} ({type(exc).__name__}: "
                          f"{exc}); cell fields need a mesh format with cell data (.vtu, .msh)"
                          ) from None
    blocks = [j for j, c in enumerate(mesh.cells)
              if c.type in ("tetra", a.body_element(i).cell_type)]
    if name not in mesh.cell_data or not blocks:
        have = ", ".join(sorted(mesh.cell_data)) or "none"
        raise scene.error(key, f"{path} has no tet cell data {name!r} (it has: {have})")
    vals = np.concatenate([np.asarray(mesh.cell_data[name][j], dtype=np.float64).reshape(-1)
                           for j in blocks])
    n = a.body_tets[i].stop - a.body_tets[i].start
    if vals.shape != (n,):
        raise scene.error(key, f"{path}: {name!r} has {vals.size} values for {n} tets")
    return vals


@dataclass(frozen=True, eq=False)
class ModelInputs:
    """What :func:`build_model` is given for a scene or one MPI rank's share of it (plain
    data: the rank that reads the scene sends a share's to its rank).

    Attributes
    ----------
    X, T : ndarray
        Rest positions and elements (a share's over its own vertices).
    element : Element
    path : str or None
        The mesh file the model's errors name.
    material : MaterialSpec or None
        One plain body's material; None: :attr:`groups`.
    groups : list of (key, MaterialGroup)
        One group per body and per region (elements numbered in :attr:`T`).
    rho : float or ndarray
        The density, or one per element.
    """

    X: np.ndarray
    T: np.ndarray
    element: Any
    path: str | None
    material: MaterialSpec | None
    groups: list
    rho: float | np.ndarray


def model_from_scene(scene: Scene, a: SceneArrays, backend: str | None = None, *,
                     share: LocalNumbering | None = None) -> Model:
    """The model of every body's material (one material form when there is one plain body,
    else ``build_model(groups=)``: one group per body and per region).

    ``share`` (optional): the model of its tets alone over its vertices (one MPI rank's),
    built from them: the groups, per-tet parameters and densities are restricted before
    :func:`build_model`, which sees only the share's tets and vertices; its summary
    ``E, nu, rho`` are then the share's.
    """
    if a.is_mixed:
        groups, density = _material_groups(scene, a)
        return _mixed_from_groups(scene, a, groups, density, backend)
    return model_of(scene, model_inputs(scene, a, share), backend)


def model_inputs(scene: Scene, a: SceneArrays, share: LocalNumbering | None = None,
                 groups: tuple[list, np.ndarray] | None = None) -> ModelInputs:
    """:class:`ModelInputs` of the scene (its bodies on one element), or of ``share``'s
    tets over its vertices (:func:`model_from_scene`); ``groups``: the scene's material
    groups and densities when made already."""
    bodies = scene.bodies
    path = a.mesh_paths[0] if len(a.mesh_paths) == 1 else None
    tets = None if share is None else share.tets
    X, T = (a.X, a.T) if share is None else (a.X[share.vertices], share.local(a.T[tets]))
    if len(bodies) == 1 and _simple_material(bodies[0].material):
        m = bodies[0].material
        return ModelInputs(X, T, a.element, path, m, [], m.density)
    groups, density = _material_groups(scene, a) if groups is None else groups
    rho = float(density[0]) if (density == density[0]).all() else density
    if tets is not None:
        groups, rho = _share_groups(groups, tets, a.T.shape[0]), _share_values(rho, tets)
    return ModelInputs(X, T, a.element, path, None, groups, rho)


def model_of(scene: Scene, inputs: ModelInputs, backend: str | None = None) -> Model:
    """:func:`build_model` of ``inputs``; a bad material or mesh is refused naming its key."""
    m = inputs.material
    if m is None:
        return _model_of_groups(scene, inputs.X, inputs.T, inputs.groups, inputs.rho, backend,
                                inputs.path, inputs.element)
    try:
        return build_model(inputs.X, inputs.T, E=m.E, nu=m.nu, rho=m.density,
                           material=m.model, backend=backend, path=inputs.path,
                           element=inputs.element)
    except InputError as exc:
        key = "bodies[0].material" if isinstance(exc, ParameterError) else "bodies[0].mesh"
        raise scene.error(key, str(exc)) from None


def _material_groups(scene: Scene, a: SceneArrays) -> tuple[list, np.ndarray]:
    """``(key, MaterialGroup)`` of every body and region, and the density of every tet."""
    groups, density = [], np.empty(a.body_tets[-1].stop)
    for i, body in enumerate(scene.bodies):
        m = body.material
        mine = np.arange(a.body_tets[i].start, a.body_tets[i].stop)
        density[mine] = m.density
        base = dict(m.params)
        if m.E is not None:
            base.update(E=m.E, nu=m.nu)
        for param, name in m.cell_fields.items():
            base[param] = _cell_field(scene, a, i, param, name)
        region = np.full(mine.size, -1)
        if m.regions:
            Xb = a.X[a.body_vertices[i]]
            Tb = a.body_elements(i) - a.body_vertices[i].start
            for j, r in enumerate(m.regions):
                ids = select_vertices(scene, Xb, r.select,
                                      f"bodies[{i}].material.regions[{j}].select")
                inside = np.isin(Tb, ids).all(axis=1)
                if not inside.any():
                    raise scene.error(f"bodies[{i}].material.regions[{j}].select",
                                      "selects no whole tet (a region is the tets whose four "
                                      "vertices are all selected)")
                region[inside] = j
        for j in range(-1, len(m.regions)):
            mask = region == j
            if not mask.any():
                continue
            values = {k: (v[mask] if isinstance(v, np.ndarray) else v) for k, v in base.items()}
            if j >= 0:
                r = m.regions[j]
                values.update(r.params)
                if r.E is not None:
                    values["E"] = r.E
                if r.nu is not None:
                    values["nu"] = r.nu
            groups.append((f"bodies[{i}].material" + (f".regions[{j}]" if j >= 0 else ""),
                           MaterialGroup(m.model, mine[mask], values)))
    return groups, density


def _mixed_from_groups(scene: Scene, a: SceneArrays, groups: list, density: np.ndarray,
                       backend: str | None) -> Model:
    """The model of bodies on several elements: one :func:`build_model` per element block
    (its bodies' material groups and densities), joined by :func:`mixed_model`."""
    blocks = []
    for blk in a.blocks:
        s = blk.tets
        mine = [(key, MaterialGroup(g.material, g.elements - s.start, g.params))
                for key, g in groups if s.start <= g.elements[0] < s.stop]
        rho = density[s]
        rho = float(rho[0]) if (rho == rho[0]).all() else rho
        path = a.mesh_paths[blk.bodies[0]] if len(blk.bodies) == 1 else None
        blocks.append(_model_of_groups(scene, a.X, blk.T, mine, rho, backend, path,
                                       blk.element))
    return mixed_model(blocks, [blk.tets for blk in a.blocks])


def _model_of_groups(scene: Scene, X: np.ndarray, T: np.ndarray, groups: list, rho,
                     backend: str | None, path: str | None, element) -> Model:
    """:func:`build_model` of ``(key, MaterialGroup)`` pairs; a bad group is refused naming
    its key."""
    try:
        return build_model(X, T, groups=[g for _, g in groups], density=rho,
                           backend=backend, path=path, element=element)
    except ParameterError as exc:
        # name the group the message is about when it says which (else the first body's)
        hit = re.search(r"material group (\d+)", str(exc))
        key = groups[int(hit.group(1))][0] if hit and int(hit.group(1)) < len(groups) \
            else groups[0][0]
        raise scene.error(key, str(exc)) from None
    except InputError as exc:
        raise scene.error("bodies", str(exc)) from None


def _share_values(value, rows: np.ndarray):
    """``value`` (a number, or an array of one row per element) at ``rows``."""
    return value[rows] if isinstance(value, np.ndarray) else value


def _share_groups(groups: list, tets: np.ndarray, n_tets: int) -> list:
    """``(key, MaterialGroup)`` pairs restricted to the sorted ``tets`` (numbered by their
    place in ``tets``); a group with none of them is dropped."""
    local_of = np.full(n_tets, -1, dtype=np.int64)
    local_of[tets] = np.arange(tets.size)
    out = []
    for key, g in groups:
        keep = np.flatnonzero(local_of[g.elements] >= 0)
        if keep.size:
            values = {k: _share_values(v, keep) for k, v in g.params.items()}
            out.append((key, MaterialGroup(g.material, local_of[g.elements[keep]], values)))
    return out


def damping_from_scene(scene: Scene, a: SceneArrays) -> tuple:
    """Rayleigh ``alpha`` (scalar or per vertex) and ``beta`` (scalar or per tet)."""
    alphas = [b.damping.rayleigh_mass for b in scene.bodies]
    betas = [b.damping.rayleigh_stiffness for b in scene.bodies]
    if len(set(alphas)) == 1 and len(set(betas)) == 1:
        return float(alphas[0]), float(betas[0])
    alpha = np.zeros(a.X.shape[0])
    beta = np.zeros(a.body_tets[-1].stop)
    for i in range(len(scene.bodies)):
        alpha[a.body_vertices[i]] = alphas[i]
        beta[a.body_tets[i]] = betas[i]
    return alpha, beta


# ------------------------------------------------------------------------------ motions
def keyframes_from_spec(scene: Scene, spec: MotionSpec, rest: np.ndarray,
                        key: str) -> Keyframes:
    """The :class:`Keyframes` of a motion spec, a moving pin's or a mesh obstacle's.

    Parameters
    ----------
    scene : Scene
    spec : MotionSpec
    rest : (k, 3) float64
        Rest positions of what moves: the pivot defaults to their centroid.
    key : str
        Key path of ``spec`` (for the error message).

    Raises
    ------
    InputError
        ``FILE: key: ...`` when the keyframes are invalid.
    """
    pivot = rest.mean(axis=0) if spec.pivot is None else np.asarray(spec.pivot, float)
    try:
        return Keyframes([k.t for k in spec.keyframes], [k.translate for k in spec.keyframes],
                         [k.rotate_deg for k in spec.keyframes], pivot, spec.interpolation)
    except ParameterError as exc:
        raise scene.error(key, str(exc)) from None


def pin_motions(scene: Scene, a: SceneArrays, fixed: np.ndarray) -> list[PinMotion]:
    """The moving pins of every body.

    Parameters
    ----------
    scene : Scene
    a : SceneArrays
    fixed : (n_fixed,) int64
        The pinned vertices, sorted (:attr:`Constraints.fixed_vertices`).

    Raises
    ------
    InputError
        A vertex that two moving pins select, invalid keyframes.
    """
    out, taken = [], np.zeros(fixed.size, dtype=bool)
    for i, body in enumerate(scene.bodies):
        off = a.body_vertices[i].start
        for j, pin in enumerate(body.pins):
            if pin.motion is None:
                continue
            key = f"bodies[{i}].pins[{j}]"
            ids = select_vertices(scene, a.X[a.body_vertices[i]], pin.select,
                                  f"{key}.select") + off
            slots = np.searchsorted(fixed, ids)
            if taken[slots].any():
                raise scene.error(f"{key}.select", "shares pinned vertices with another "
                                  "moving pin; a vertex can follow one motion only")
            taken[slots] = True
            rest = a.X[ids]
            out.append(PinMotion(slots, rest,
                                 keyframes_from_spec(scene, pin.motion, rest, f"{key}.motion")))
    return out


# ------------------------------------------------------------------------------ contact
def obstacles_from_scene(scene: Scene) -> tuple[list[PlaneObstacle], list[MeshObstacle]]:
    """The runtime obstacles of ``scene.obstacles``: planes, and mesh obstacles (a surface
    file, OBJ, STL, ... read by :func:`fem3d.mesh.formats.read_surface_mesh`, under its
    ``transform``, moving by its keyframed ``motion`` as moving pins do; the pivot defaults
    to the obstacle's vertex centroid).

    Raises
    ------
    InputError
        ``FILE: obstacles[i]...: ...`` for a bad obstacle file or motion.
    """
    planes, meshes = [], []
    for i, ob in enumerate(scene.obstacles):
        key = f"obstacles[{i}]"
        if ob.plane is not None:
            planes.append(PlaneObstacle(ob.plane.point, ob.plane.normal, name=f"{key} (plane)"))
            continue
        m = ob.mesh
        path = scene.path(m.path)
        if not path.is_file():
            raise scene.error(f"{key}.mesh.path", f"no such file {path}")
        try:
            V, F = read_surface_mesh(path)
        except InputError as exc:
            raise scene.error(f"{key}.mesh.path", str(exc)) from None
        V = transform_points(V, m.transform)
        motion = None
        if m.motion is not None:
            motion = keyframes_from_spec(scene, m.motion, V, f"{key}.mesh.motion").apply
        try:
            meshes.append(MeshObstacle(V, F, motion=motion, name=f"{key} ({path.name})"))
        except ParameterError as exc:
            raise scene.error(f"{key}.mesh", str(exc)) from None
    return planes, meshes


def contact_from_scene(scene: Scene, a: SceneArrays) -> ContactTerm:
    """The :class:`ContactTerm` of a scene (``scene.contact``, ``scene.obstacles``).

    ``dhat`` is relative to the diagonal of the scene's bounding box at rest (bodies and
    mesh obstacles), ``eps_v`` and ``tolerance`` to that diagonal per second; the obstacles
    are :func:`obstacles_from_scene`'s.

    Parameters
    ----------
    scene : Scene
    a : SceneArrays

    Raises
    ------
    InputError
        ``FILE: key.path: ...`` for a bad obstacle file or motion.
    """
    spec = scene.contact
    planes, meshes = obstacles_from_scene(scene)
    body_ids = np.zeros(a.X.shape[0], dtype=np.int64)
    for b, sl in enumerate(a.body_vertices):
        body_ids[sl] = b
    names = [f"bodies[{b}] ({body.label})" for b, body in enumerate(scene.bodies)]
    pts = np.concatenate([a.X] + [m.vertices for m in meshes])
    L = float(np.linalg.norm(np.ptp(pts, axis=0)))
    cm = ContactModel(a.X, None if a.is_mixed else a.T, body_ids=body_ids, body_names=names,
                      planes=planes, meshes=meshes, dhat=spec.dhat * L, kappa=spec.kappa,
                      mu=spec.static_mu, mu_k=spec.kinetic_mu,
                      eps_v=spec.eps_v * L, self_contact=spec.self_contact,
                      hessian_projection=spec.hessian_projection,
                      friction_hessian=spec.friction_hessian,
                      element=a.blocks[0].element,
                      triangles=a.surface_triangles() if a.is_mixed else None)
    return ContactTerm(cm, tolerance=spec.tolerance,
                       friction_iterations=spec.friction_iterations,
                       friction_tolerance=spec.friction_tolerance,
                       newton_start=spec.newton_start, first_step=spec.first_step)
