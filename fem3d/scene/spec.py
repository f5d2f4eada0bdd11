"""A scene as data: one frozen, validated description of a run, read from a TOML file.

A scene file is TOML (read with :mod:`tomllib`) checked against the pydantic v2 models below,
which are the single source of truth: ``fem3d schema`` prints them as JSON Schema
(:func:`scene_schema`). Every model forbids unknown keys (the error suggests the nearest
known one) and is frozen; paths are relative to the scene file's folder (``base_dir``).
Reading a scene (by name, from a file, around a mesh) and changing it by key paths is
:mod:`fem3d.scene.load`; turning it into arrays and runtime objects is :mod:`fem3d.scene.build`.

::

    from fem3d.scene import load_scene, apply_overrides
    scene = load_scene("bunny")                            # data/scenes/bunny.toml
    scene = load_scene("my_scene.toml")                    # a scene file
    scene = load_scene("beam.msh")                         # a one-body scene around a mesh
    scene = apply_overrides(scene, {"bodies[0].material.E": 1e5, "simulation.dt": 0.005})
    scene.digest()                                         # sha256: settings + mesh contents

Errors are :class:`~fem3d.errors.InputError` with one line ``FILE: key.path: what is wrong``
(``override`` instead of ``FILE`` for :func:`~fem3d.scene.load.apply_overrides`).

Conventions
-----------
* ``transform``: ``x' = R (scale x) + translate`` with ``R = Rz Ry Rx`` of ``rotate_deg``
  (degrees about the x, then y, then z axis).
* Selectors pick vertices of a body's rest positions after its transform: ``lowest_y {tol}``
  (``y <= min y + tol``), ``box [[min], [max]]`` (closed), ``half_space {point, normal}``
  (the side the normal points to, boundary included), ``sphere {center, radius}`` (closed),
  ``vertices [ids]``, ``vertices_file`` (whitespace-separated ids, ``#`` comments),
  ``near_vertex {vertex, radius}`` (closed ball around that vertex's position),
  ``nearest_to {point, radius}`` (the vertex nearest to ``point`` and those within
  ``radius`` of it: never empty).
* A pull's ``offset`` moves each selected vertex's target by ``offset`` from its rest
  position; ``target`` moves the selection's centroid to ``target`` (the same offset for all).
* ``simulation.steps`` or ``simulation.duration`` (steps = round(duration / dt)); neither:
  :data:`DEFAULT_STEPS`. Setting one by :func:`~fem3d.scene.load.apply_overrides` clears
  the other.
* ``interaction.pick_radius`` / ``spring_k`` left out: ``0.01 h`` and ``0.15 E h`` (``h`` the
  height of the rest mesh along y, ``E`` the first body's Young's modulus).
"""

from __future__ import annotations

import difflib
import hashlib
import json
import os
import re
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    StrictStr,
    ValidationError,
    field_validator,
    model_validator,
)

from fem3d.errors import InputError
from fem3d.io.files import check_input_file
from fem3d.io.frames.registry import frame_format_names
from fem3d.mesh.element import element_names
from fem3d.physics.materials import names as material_names
from fem3d.scene.keys import format_key, parse_key, set_path
from fem3d.scene.selection import (  # re-exported: the scene's one description
    ZERO3,
    HalfSpace,
    Index,
    LoadKeyframe,
    LoadSpec,
    LowestY,
    NearestTo,
    NearVertex,
    NonNegative,
    Positive,
    Selector,
    Sphere,
    Vec3,
    _nonzero,
    _Spec,
)
from fem3d.solve.linear.petsc import parse_options
from fem3d.solve.linear.registry import linear_solver_names
from fem3d.solve.schemes.registry import DEFAULT_SCHEME, SCHEMES, get_scheme

__all__ = [
    "Scene", "SimulationSpec", "NewtonSpec", "BodySpec", "MaterialSpec", "RegionSpec",
    "Selector", "PinSpec", "MotionSpec", "Keyframe", "PullSpec", "ContactSpec",
    "ObstacleSpec", "PlaneObstacleSpec", "MeshObstacleSpec", "OutputSpec", "PreviewSpec",
    "InteractionSpec", "TransformSpec", "TetrahedralizeSpec", "DampingSpec", "LoadSpec",
    "LoadKeyframe", "LowestY", "HalfSpace", "Sphere", "NearVertex", "NearestTo", "scene_schema",
    "material_names", "DEFAULT_STEPS", "SURFACE_SUFFIXES",
]

#: Steps of a run whose scene gives neither ``steps`` nor ``duration``.
DEFAULT_STEPS = 100

#: Closed-surface file types a body's ``mesh`` may be (tetrahedralized with fTetWild).
SURFACE_SUFFIXES = (".obj", ".stl", ".ply", ".off")

#: ``simulation.linear_solver``'s choices: ``"auto"`` and the registered linear solvers.
LinearSolverName = Literal[linear_solver_names()]  # type: ignore[valid-type]
#: ``output.format``'s choices: the registered output formats (:mod:`fem3d.io.frames`).
FrameFormatName = Literal[frame_format_names()]  # type: ignore[valid-type]
#: ``bodies[].element``'s choices: the registered finite elements (``"p1"``, ``"p2"``).
ElementName = Literal[element_names()]  # type: ignore[valid-type]


def _registered_scheme(name: str) -> str:
    """``name`` when a scheme of that name is registered (read when a scene is checked, so a
    scheme registered after import, by a plug-in or a test, is accepted)."""
    if name not in SCHEMES:
        raise ValueError(f"unknown integrator {name!r}; choose one of {', '.join(SCHEMES)}")
    return name


#: ``simulation.integrator``'s choices: the registered schemes
#: (:mod:`fem3d.solve.schemes.registry`; the JSON Schema lists those registered when printed).
IntegratorName = Annotated[StrictStr, AfterValidator(_registered_scheme), Field(
    json_schema_extra=lambda schema: schema.update(enum=list(SCHEMES)))]


# ------------------------------------------------------------------------------ motion
class Keyframe(_Spec):
    """Rigid pose of pinned vertices at time ``t``: rotate about the pivot, then translate."""

    t: NonNegative
    translate: Vec3 = ZERO3
    rotate_deg: Vec3 = ZERO3


class MotionSpec(_Spec):
    """Keyframed rigid motion (between keyframes: interpolated; outside: held)."""

    keyframes: Annotated[list[Keyframe], Field(min_length=1)]
    pivot: Vec3 | None = None
    interpolation: Literal["linear", "smooth"] = "linear"

    @field_validator("keyframes")
    @classmethod
    def _ordered(cls, frames: list[Keyframe]) -> list[Keyframe]:
        for i in range(1, len(frames)):
            if not frames[i].t > frames[i - 1].t:
                raise ValueError(
                    f"keyframes[{i}].t = {frames[i].t:g} must be after keyframes[{i - 1}].t "
                    f"= {frames[i - 1].t:g} (times must increase)"
                )
        return frames


class PinSpec(_Spec):
    """Fixed vertices (``motion``: prescribed keyframed positions instead of fixed); ``dofs``:
    the components held (``"z"``: a roller or symmetry plane normal to z; default all)."""

    select: Selector
    motion: MotionSpec | None = None
    dofs: StrictStr = "xyz"

    @field_validator("dofs")
    @classmethod
    def _axes(cls, dofs: str) -> str:
        if not dofs or set(dofs) - set("xyz") or len(set(dofs)) != len(dofs):
            raise ValueError(f"dofs = {dofs!r}: give the held components as x, y and/or z, "
                             "each once (e.g. \"z\", \"xy\"; default \"xyz\")")
        return dofs

    @property
    def axes(self) -> list[int]:
        """The fixed components, ``0, 1, 2`` for x, y, z."""
        return sorted("xyz".index(c) for c in self.dofs)


# ------------------------------------------------------------------------------ bodies
class RegionSpec(_Spec):
    """Material values of the elements whose vertices all lie in ``select``."""

    select: Selector
    E: Positive | None = None
    nu: Annotated[StrictFloat, Field(gt=-1.0, lt=0.5)] | None = None
    params: dict[str, StrictFloat] = Field(default_factory=dict)


class MaterialSpec(_Spec):
    """A generated material by name, with ``E``/``nu`` or its own ``params`` (those that keep
    the small-strain response, e.g. Fung's ``b``, may go next to ``E``/``nu``), density,
    ``regions`` (other values on the tets whose vertices a selector picks) and ``cell_fields``
    (a parameter per tet from a cell-data array of the mesh file)."""

    model: StrictStr = "neo_hookean"
    density: Positive = 1000.0
    E: Positive | None = None
    nu: Annotated[StrictFloat, Field(gt=-1.0, lt=0.5)] | None = None
    params: dict[str, StrictFloat] = Field(default_factory=dict)
    regions: list[RegionSpec] = Field(default_factory=list)
    cell_fields: dict[str, StrictStr] = Field(default_factory=dict)

    @field_validator("model")
    @classmethod
    def _known(cls, name: str) -> str:
        names = material_names()
        if name not in names:
            near = difflib.get_close_matches(name, names, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else ""
            raise ValueError(f"unknown material {name!r} (known: {', '.join(names)}){hint}")
        return name

    @model_validator(mode="after")
    def _values(self) -> MaterialSpec:
        if (self.E is None) != (self.nu is None):
            raise ValueError("E and nu go together (or give the model's own params)")
        if self.E is None and not self.params and not self.cell_fields:
            raise ValueError("give E and nu, or the model's own params")
        return self


class TransformSpec(_Spec):
    """``x' = Rz Ry Rx (scale x) + translate`` (degrees)."""

    scale: Positive = 1.0
    rotate_deg: Vec3 = ZERO3
    translate: Vec3 = ZERO3


class TetrahedralizeSpec(_Spec):
    """fTetWild options for a surface body: target edge length (the size knob) and envelope
    (how far the boundary may stray from the surface), both relative to the surface's
    bounding-box diagonal (smaller: finer, slower); ``stop_quality``: the max AMIPS energy
    fTetWild optimises down to (the quality knob; larger: faster, worse tets)."""

    edge_length: Annotated[StrictFloat, Field(gt=0, le=1)] = 0.05
    epsilon: Annotated[StrictFloat, Field(gt=0, le=0.1)] = 1e-3
    stop_quality: Annotated[StrictFloat, Field(ge=3)] = 10.0


class DampingSpec(_Spec):
    """Rayleigh damping ``alpha M + beta K``."""

    rayleigh_mass: NonNegative = 0.0
    rayleigh_stiffness: NonNegative = 0.0


class BodySpec(_Spec):
    """One elastic body: a tet mesh, or a closed surface tetrahedralized with fTetWild."""

    name: StrictStr | None = None
    mesh: StrictStr
    skin: StrictStr | None = None
    tetrahedralize: TetrahedralizeSpec = TetrahedralizeSpec()
    transform: TransformSpec = TransformSpec()
    velocity: Vec3 = ZERO3
    angular_velocity: Vec3 = ZERO3
    material: MaterialSpec
    damping: DampingSpec = DampingSpec()
    pins: list[PinSpec] = Field(default_factory=list)
    loads: list[LoadSpec] = Field(default_factory=list)
    #: The finite element (docs/elements.md): ``"p1"`` linear tets, ``"p2"`` quadratic tets
    #: (a 4-node mesh or a surface is lifted: a node on every edge); bodies may mix them.
    element: ElementName = "p1"

    @property
    def label(self) -> str:
        """``name``, or the mesh file's stem."""
        return self.name or Path(self.mesh).stem


# ------------------------------------------------------------------------------ the rest
class NewtonSpec(_Spec):
    """Each step's Newton solve, per scheme: implicit, bdf2, newmark: max_iterations per step
    (default 5, the step keeps its last iterate; contact raises it to 100; none: until
    converged), tolerance relative to the step's first gradient with the floor 1e-12 h E L^2;
    static: max_iterations per load increment (an unconverged increment is halved; none: 50),
    tolerance with the floor 1e-15 E L^2; linear: one linear solve per step, neither key
    applies (docs/loads.md)."""

    #: Newton iterations per step (dynamic schemes: the step keeps its last iterate; contact
    #: raises it to 100) or per load increment (static: an unconverged increment is halved);
    #: none: until converged (static: at most 50)
    max_iterations: Annotated[StrictInt, Field(ge=1)] | None = Field(5, description=(
        "Newton iterations: per step for implicit, bdf2 and newmark (the step keeps its last "
        "iterate; contact raises the cap to 100; null: until converged), per load increment "
        "for static (an increment that does not converge within it is halved, down to 1/64 "
        "of the step; null: 50); not used by linear (one linear solve per step)"))
    #: converged when the gradient norm is below this fraction of its norm at Newton's start,
    #: or below the scheme's absolute floor (dynamic: 1e-12 h E L^2; static: 1e-15 E L^2,
    #: about ten times round-off; L the diagonal of the rest bounding box)
    tolerance: Annotated[StrictFloat, Field(gt=0, lt=1, description=(
        "Newton has converged when the gradient norm is below this fraction of its norm at "
        "Newton's start, or below the scheme's absolute floor: 1e-12 h E L^2 for implicit, "
        "bdf2 and newmark (h the scheme's dq/dv), 1e-15 E L^2 for static (L the diagonal of "
        "the rest bounding box); not used by linear"))] = 1e-10
    hessian: Literal["exact", "psd"] = "exact"
    solver: Literal["direct", "reuse"] = "direct"
    #: where each step's Newton starts: the last velocity, or the lower-energy of it and its
    #: linear extrapolation (fewer iterations on smooth drags; backward Euler only)
    warm_start: Literal["previous", "extrapolate"] = "previous"
    #: Newton's line search: Armijo backtracking by halving, or the same with the accepted
    #: step moved to the minimum of a parabola through the bracket when it took a halving
    #: (fewer Newton iterations where lagged friction makes full steps overshoot)
    line_search: Literal["backtrack", "parabolic"] = "backtrack"


class SimulationSpec(_Spec):
    """Time stepping."""

    integrator: IntegratorName = DEFAULT_SCHEME
    dt: Positive = 0.01
    steps: Annotated[StrictInt, Field(ge=0)] | None = None
    duration: NonNegative | None = None
    gravity: Vec3 = ZERO3
    newton: NewtonSpec = NewtonSpec()
    linear_solver: LinearSolverName = "auto"
    #: CHOLMOD's factorization: chosen from the pattern ("auto": simplicial for small factors
    #: with short columns), or forced (multi-body contact patterns mislead the rule: the
    #: gallery stack factorizes 2x faster simplicial; docs/contact.md)
    cholmod: Literal["auto", "simplicial", "supernodal"] = "auto"
    #: PETSc options of linear_solver = "petsc" ("-ksp_type cg -pc_type gamg -ksp_rtol
    #: 1e-10"; docs/parallel.md); FEM3D_PETSC_OPTIONS adds to them
    petsc_options: str = ""
    #: eigen-solver of the per-element PSD projection (Newton's "psd" Hessian, stiffness
    #: damping) where dP/dF is indefinite: "svd" (dP/dF block diagonal in F's singular frame,
    #: for isotropic materials; QL for the others), "ql" (tridiagonal QL: the round-off of
    #: stops 31-35) or "jacobi" (cyclic Jacobi: that of every run before stop 31)
    psd_projection: Literal["svd", "ql", "jacobi"] = "svd"

    @model_validator(mode="after")
    def _one_length(self) -> SimulationSpec:
        if self.steps is not None and self.duration is not None:
            raise ValueError("give steps or duration, not both")
        if self.cholmod != "auto" and self.linear_solver not in ("auto", "cholmod"):
            raise ValueError(f"cholmod = {self.cholmod!r} applies to linear_solver = 'cholmod' "
                             f"(or 'auto'), not {self.linear_solver!r}")
        if self.petsc_options and self.linear_solver != "petsc":
            raise ValueError("petsc_options applies to linear_solver = 'petsc', not "
                             f"{self.linear_solver!r}")
        if self.petsc_options:
            parse_options(self.petsc_options)  # a stray word: one line naming the key
        scheme = get_scheme(self.integrator)
        if self.newton.warm_start != "previous" and not scheme.warm_starts:
            warm = " or ".join(repr(n) for n, s in SCHEMES.items() if s.warm_starts)
            raise ValueError(f"newton.warm_start = {self.newton.warm_start!r} applies to "
                             f"integrator = {warm} only, not {self.integrator!r}")
        if self.newton.line_search != "backtrack" and not scheme.minimises:
            newton = ", ".join(repr(n) for n, s in SCHEMES.items() if s.minimises)
            raise ValueError(f"newton.line_search = {self.newton.line_search!r} needs a Newton "
                             f"solve (integrator = {newton}); the {scheme.label} scheme has no "
                             "line search")
        return self

    @property
    def n_steps(self) -> int:
        """``steps``, or ``round(duration / dt)``, or :data:`DEFAULT_STEPS`."""
        if self.steps is not None:
            return self.steps
        if self.duration is not None:
            return int(round(self.duration / self.dt))
        return DEFAULT_STEPS


class PullSpec(_Spec):
    """A scripted pull: zero-rest-length springs on the selected vertices of ``body`` from
    ``start`` for ``duration`` seconds (stiffness: ``interaction.spring_k`` if left out)."""

    body: Index = 0
    select: Selector
    offset: Vec3 | None = None
    target: Vec3 | None = None
    start: NonNegative = 0.0
    duration: Positive = 0.3
    stiffness: Positive | None = None

    @model_validator(mode="after")
    def _where(self) -> PullSpec:
        if (self.offset is None) == (self.target is None):
            raise ValueError("give exactly one of offset, target")
        return self


class ContactSpec(_Spec):
    """Contact (IPC barrier); distances relative to the scene's bounding-box diagonal."""

    enabled: StrictBool = False
    dhat: Positive = 1e-3
    kappa: Positive | None = None
    mu: NonNegative = 0.0
    #: static and kinetic friction coefficients (each defaults to ``mu``)
    mu_s: NonNegative | None = None
    mu_k: NonNegative | None = None
    eps_v: Positive = 1e-3
    self_contact: StrictBool = False
    tolerance: Positive = 1e-2
    #: Newton solves per step, each with the friction lagged at the last one's solution
    #: (1: friction lagged once, at the step's start)
    friction_iterations: Annotated[StrictInt, Field(ge=1)] = 1
    #: stop re-lagging when a solve moves the positions by less than this, relative to the
    #: scene's bounding-box diagonal
    friction_tolerance: Positive = 1e-6
    #: a step whose own straight motion from q_t to q_t+1 passes through a surface (or whose
    #: Newton solve fails) is redone as 2, 4, ... substeps of dt/n, up to this many (a power
    #: of two; 1: never, the step is not checked). fem3d.solve.substeps
    max_substeps: Annotated[StrictInt, Field(ge=1, le=1024)] = 1
    #: where Newton starts when CCD cuts the step's free flight: v_t scaled back by CCD
    #: ("clamped"; it lets a resting vertex creep toward a plane while the barrier's gradient
    #: grows) or q_t (v = 0, IPC's start; fewer Newton iterations at impacts and resting
    #: contacts; the gallery's contact scenes set it). The default stays "clamped": a
    #: checkpoint written before the key existed resumes as it was run
    newton_start: Literal["clamped", "q_t"] = "clamped"
    #: IPC's stopping rule (tolerance) on Newton's first direction: "confirm" (the first step
    #: is always taken and a second direction judged, as every run before this key did) or
    #: "accept" (a first direction that already passes is taken and ends the step's solve:
    #: one factorization instead of two in a resting step). docs/contact.md "Stop 34"
    first_step: Literal["confirm", "accept"] = "confirm"
    #: how the per-pair barrier and friction Hessians enter Newton's matrix: negative
    #: eigenvalues clamped at zero ("clamp"), mirrored to their absolute value ("abs", Chen et
    #: al. 2024), or not projected ("exact": Newton's shift ladder handles an indefinite
    #: matrix; clamped only where Newton asks for a PSD one). docs/contact.md. The default
    #: stays "clamp": recorded runs and old checkpoints resume as they were run
    hessian_projection: Literal["clamp", "abs", "exact"] = "clamp"
    #: the friction's part of Newton's matrix: ipctk's Hessian ("exact"), or that of a
    #: quadratic that lies above the friction and touches it at the iterate ("majorizer":
    #: no overshoot when a step carries a slip back into the static zone, fewer line-search
    #: halvings at impacts; the same minimiser, but IPC's stopping rule then measures a
    #: shorter step). fem3d.physics.contact.friction_majorizer, docs/contact.md "Stop 32"
    friction_hessian: Literal["exact", "majorizer"] = "exact"

    @field_validator("max_substeps")
    @classmethod
    def _power_of_two(cls, n: int) -> int:
        if n & (n - 1):
            raise ValueError(f"must be a power of two (1, 2, 4, ..., 1024), got {n}")
        return n

    @property
    def static_mu(self) -> float:
        """The static coefficient (``mu_s``, else ``mu``)."""
        return self.mu if self.mu_s is None else self.mu_s

    @property
    def kinetic_mu(self) -> float:
        """The kinetic coefficient (``mu_k``, else ``mu``)."""
        return self.mu if self.mu_k is None else self.mu_k

    @model_validator(mode="after")
    def _friction(self) -> ContactSpec:
        if self.kinetic_mu > self.static_mu:
            raise ValueError(f"mu_k ({self.kinetic_mu}) must not exceed mu_s "
                             f"({self.static_mu})")
        return self


class PlaneObstacleSpec(_Spec):
    """An infinite plane; the free side is the one the normal points to."""

    point: Vec3
    normal: Vec3

    @field_validator("normal")
    @classmethod
    def _normal(cls, v: Vec3) -> Vec3:
        return _nonzero(v, "normal")


class MeshObstacleSpec(_Spec):
    """A rigid surface mesh, optionally moving like a keyframed pin."""

    path: StrictStr
    transform: TransformSpec = TransformSpec()
    motion: MotionSpec | None = None


class ObstacleSpec(_Spec):
    """Exactly one of ``plane``, ``mesh``."""

    plane: PlaneObstacleSpec | None = None
    mesh: MeshObstacleSpec | None = None

    @model_validator(mode="after")
    def _one(self) -> ObstacleSpec:
        if (self.plane is None) == (self.mesh is None):
            raise ValueError("give exactly one of plane, mesh")
        return self


class PreviewSpec(_Spec):
    """Camera of ``preview.gif``: elevation and azimuth (degrees), and whether the view box
    fits the first frame or every frame."""

    elev: Annotated[StrictFloat, Field(ge=-90, le=90)] = 15.0
    azim: StrictFloat = 30.0
    bounds: Literal["first", "all"] = "first"


class OutputSpec(_Spec):
    """Frames written by ``fem3d run``: format and stride (steps); the volume mesh beside them;
    the preview's camera."""

    format: FrameFormatName = "vtu"
    every: Annotated[StrictInt, Field(ge=1)] = 1
    volume: StrictBool = Field(
        default=False,
        description="also write the volume mesh at every frame: volume/*.vtu + volume.pvd, "
                    "the element's own cells (tetra, tetra10) with per-element stress")
    preview: PreviewSpec = PreviewSpec()


class InteractionSpec(_Spec):
    """Mouse interaction in the viewer (left out: derived from the mesh, see the module)."""

    pick_radius: NonNegative | None = None
    spring_k: Positive | None = None


class Scene(_Spec):
    """Everything a run needs, as data (see :mod:`fem3d.scene.spec`)."""

    name: StrictStr = "scene"
    base_dir: StrictStr = "."
    source: StrictStr | None = Field(
        default=None, description="the file the scene was read from (messages only)")
    simulation: SimulationSpec = SimulationSpec()
    bodies: Annotated[list[BodySpec], Field(min_length=1)]
    pulls: list[PullSpec] = Field(default_factory=list)
    contact: ContactSpec = ContactSpec()
    obstacles: list[ObstacleSpec] = Field(default_factory=list)
    output: OutputSpec = OutputSpec()
    interaction: InteractionSpec = InteractionSpec()

    @model_validator(mode="after")
    def _exact_contact_hessian(self) -> Scene:
        if self.contact.hessian_projection == "exact" and self.simulation.newton.solver != \
                "direct":
            raise ValueError("contact.hessian_projection = 'exact' needs simulation.newton."
                             "solver = 'direct' (its shift ladder takes an indefinite Newton "
                             f"matrix), not {self.simulation.newton.solver!r}")
        return self

    @model_validator(mode="after")
    def _pull_bodies(self) -> Scene:
        for i, p in enumerate(self.pulls):
            if p.body >= len(self.bodies):
                raise ValueError(
                    f"pulls[{i}].body = {p.body}: there are only {len(self.bodies)} bodies")
        return self

    # ----------------------------------------------------------------- paths
    def path(self, p: str) -> Path:
        """``p`` resolved against :attr:`base_dir` (absolute paths stay)."""
        q = Path(os.path.expanduser(p))
        return q if q.is_absolute() else Path(self.base_dir) / q

    @property
    def where(self) -> str:
        """What error messages name: the source file, or the scene's name."""
        return self.source or f"scene {self.name!r}"

    def error(self, key: str, message: str) -> InputError:
        """An :class:`InputError` ``FILE: key: message`` for this scene."""
        return InputError(f"{key}: {message}", path=self.where)

    def files(self) -> list[tuple[str, Path]]:
        """``(key path, resolved path)`` of every file the scene refers to."""
        out: list[tuple[str, Path]] = []
        for i, b in enumerate(self.bodies):
            out.append((f"bodies[{i}].mesh", self.path(b.mesh)))
            if b.skin is not None:
                out.append((f"bodies[{i}].skin", self.path(b.skin)))
            sels = [(f"bodies[{i}].pins[{j}].select", p.select) for j, p in enumerate(b.pins)]
            sels += [(f"bodies[{i}].material.regions[{j}].select", r.select)
                     for j, r in enumerate(b.material.regions)]
            out += [(f"{k}.vertices_file", self.path(s.vertices_file))
                    for k, s in sels if s.vertices_file is not None]
        for j, p in enumerate(self.pulls):
            if p.select.vertices_file is not None:
                out.append((f"pulls[{j}].select.vertices_file", self.path(p.select.vertices_file)))
        for j, o in enumerate(self.obstacles):
            if o.mesh is not None:
                out.append((f"obstacles[{j}].mesh.path", self.path(o.mesh.path)))
        return out

    def check_files(self) -> None:
        """Every referenced file exists (else ``FILE: key: no such file PATH``)."""
        for key, p in self.files():
            if not (p.exists() or p.is_symlink()):
                raise self.error(key, f"no such file {p}")
            try:  # missing, a FIFO or device (would block), a folder, a symlink loop
                check_input_file(p)
            except InputError as exc:
                raise self.error(key, f"{p}: {exc.reason}") from None

    # ----------------------------------------------------------------- serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict; every path absolute (so the dict means the same anywhere)."""
        d = self.model_dump(mode="json")
        for key, p in self.files():
            set_path(d, parse_key(key), str(p.resolve()))
        d["base_dir"] = str(Path(self.base_dir).resolve())
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], *, source: str | None = None) -> Scene:
        """Validate a dict (e.g. :meth:`to_dict`'s or a parsed TOML file's).

        Raises
        ------
        InputError
            ``SOURCE: key.path: what is wrong``.
        """
        return _validate(d, source or (d.get("source") if isinstance(d, Mapping) else None)
                         or "scene")

    def digest(self) -> str:
        """sha256 of the canonical JSON of :meth:`to_dict` (without ``source``) and of the
        contents of every file the scene refers to."""
        d = self.to_dict()
        d.pop("source", None)
        h = hashlib.sha256(json.dumps(d, sort_keys=True, separators=(",", ":")).encode())
        for key, p in self.files():
            h.update(key.encode())
            h.update(_file_sha256(p).encode())
        return h.hexdigest()

    # ----------------------------------------------------------------- derived
    @property
    def n_steps(self) -> int:
        """Steps of a run (see :attr:`SimulationSpec.n_steps`)."""
        return self.simulation.n_steps


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    except OSError:
        return "missing"
    return h.hexdigest()


# ------------------------------------------------------------------------------ errors
def _unwrap_models(ann: Any) -> list[type[BaseModel]]:
    """Pydantic model classes inside an annotation (through Optional, list, tuple, ...)."""
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return [ann]
    out: list[type[BaseModel]] = []
    origin = typing.get_origin(ann)
    if origin is Annotated:
        return _unwrap_models(typing.get_args(ann)[0])
    if origin is not None or isinstance(ann, types.UnionType):
        for a in typing.get_args(ann):
            out += _unwrap_models(a)
    return out


def _model_at(loc: tuple, root: type[BaseModel] | None = None) -> type[BaseModel] | None:
    cls: type[BaseModel] | None = Scene if root is None else root
    for part in loc:
        if isinstance(part, int) or cls is None:
            continue
        field = cls.model_fields.get(str(part))
        if field is None:
            return None
        models = _unwrap_models(field.annotation)
        cls = models[0] if models else None
    return cls


def describe_error(err: dict, root: type[BaseModel] | None = None) -> str:
    """The text after ``key.path:`` for one pydantic error (``ValidationError.errors()``) of
    a ``root`` model (default: :class:`Scene`)."""
    kind = err["type"]
    loc = tuple(err["loc"])
    if kind == "extra_forbidden":
        parent = _model_at(loc[:-1], root)
        names = list(parent.model_fields) if parent is not None else []
        near = difflib.get_close_matches(str(loc[-1]), names, n=1, cutoff=0.5)
        hint = f"; did you mean {near[0]!r}?" if near else ""
        return f"unknown key{hint} (known: {', '.join(names)})" if names else "unknown key"
    if kind == "missing":
        return "missing (required)"
    msg = str(err["msg"])
    msg = re.sub(r"^(Value error|Assertion failed), ", "", msg)
    if kind in ("float_type", "int_type", "string_type", "bool_type", "list_type",
                "tuple_type", "dict_type", "model_type", "literal_error", "model_attributes_type",
                "too_short", "too_long", "greater_than", "greater_than_equal", "less_than",
                "less_than_equal", "finite_number", "int_from_float"):
        value = err.get("input")
        shown = repr(value)
        if len(shown) > 60:
            shown = shown[:57] + "..."
        msg = f"{msg}, got {shown}"
    return msg


def _misspelling(missing: dict, errors: list[dict],
                 root: type[BaseModel] | None) -> dict | None:
    """The unknown key beside a missing required one whose "did you mean" names it."""
    loc = tuple(missing["loc"])
    parent = _model_at(loc[:-1], root)
    if parent is None:
        return None
    names = list(parent.model_fields)
    for err in errors:
        eloc = tuple(err["loc"])
        if err["type"] == "extra_forbidden" and eloc[:-1] == loc[:-1]:
            near = difflib.get_close_matches(str(eloc[-1]), names, n=1, cutoff=0.5)
            if near and near[0] == loc[-1]:
                return err
    return None


def primary_error(errors: list[dict], root: type[BaseModel] | None = None) -> tuple[dict, int]:
    """The pydantic error to report and how many others it leaves unexplained.

    The first error is the one nearest to the file's own words, except that a required key
    reported missing because it was misspelled is reported as the misspelled key (its
    "did you mean" explains both).

    Parameters
    ----------
    errors : list of dict
        ``ValidationError.errors()``, in pydantic's order.
    root : pydantic model class, optional
        The model validated (default :class:`Scene`; a sweep file passes its own).

    Returns
    -------
    err : dict
        The error to report.
    n_more : int
        How many of the other errors it does not explain.
    """
    pairs = [(m, _misspelling(m, errors, root)) for m in errors if m["type"] == "missing"]
    pairs = [(m, e) for m, e in pairs if e is not None]
    if not pairs:
        return errors[0], len(errors) - 1
    explained = {id(m) for m, _ in pairs} | {id(e) for _, e in pairs}
    return pairs[0][1], sum(id(e) not in explained for e in errors)


def _validate(d: Any, source: str) -> Scene:
    if not isinstance(d, Mapping):
        raise InputError(f"a scene must be a table of keys, got {type(d).__name__}", path=source)
    try:
        return Scene.model_validate(dict(d))
    except ValidationError as exc:
        errors = exc.errors(include_url=False)
        err, n_more = primary_error(errors)
        more = f" (and {n_more} more)" if n_more else ""
        raise InputError(f"{format_key(tuple(err['loc']))}: {describe_error(err)}{more}",
                         path=source) from None
    except (TypeError, ValueError, RecursionError) as exc:  # pragma: no cover - defensive
        raise InputError(f"invalid scene ({type(exc).__name__}: {exc})", path=source) from None


def scene_schema() -> dict[str, Any]:
    """JSON Schema of a scene file (what ``fem3d schema`` prints)."""
    schema = Scene.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "fem3d scene"
    props = schema.get("properties", {})
    for k in ("base_dir", "source"):
        props.pop(k, None)
    return schema

