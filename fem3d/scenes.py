"""Built-in scenes (the assignment's bunny and armadillo) and scenes from any tet mesh.

=========  ======================  ===============  ======  ========  =====  ======  =========
scene      simulation mesh         display (skin)   E       spring k  fix    pick    integrator
=========  ======================  ===============  ======  ========  =====  ======  =========
bunny      coarser_bunny.mesh      bunny_skin.obj   6e6     1e8       3      1.0     linear
arma       arma_6.node / .ele      armadillo.obj    6e5     1e5       0.1    0.01    implicit
=========  ======================  ===============  ======  ========  =====  ======  =========

Both: ``dt = 0.01``, ``rho = 0.1``, ``nu = 0.4``, no gravity, Neo-Hookean; fixed vertices
are those within ``fix`` of the lowest ``y``.

Scripted pull (what ``fem3d run`` does, so a headless run shows motion): zero-rest-length
springs of stiffness ``spring k`` attach the vertices within ``pick`` of a chosen vertex to
that vertex's rest position plus an offset, for ``PULL_DURATION = 0.3`` s from ``t = 0``,
then are released.

* bunny: the top-most vertex (max ``y``: the tip of the ear); offset ``+0.15 h`` along x
  (``h`` the mesh height, about 165 units).
* armadillo: its raised hand, chosen as the vertex with the largest ``x`` among the
  vertices above mid-height (``y > (y_min + y_max) / 2``; vertex 61 of ``arma_6``);
  offset ``+0.20 h`` along z (sideways, across the arm). With this pull the
  linearly-implicit scheme explodes on the armadillo a few steps after the release (about
  step 45), as the assignment expects, while backward Euler stays stable.
* a mesh from a path: the top-most vertex, ``+0.15 h`` along x.

A path scene (``load_scene("my.mesh")``) uses the armadillo's material and backward Euler,
with the lengths scaled to the mesh: ``fixed_tol = 0.02 h``, ``pick_radius = 0.01 h`` and
``spring_k = 0.15 E h`` (the two built-in scenes have ``k / (E h)`` of 0.1 and 0.17).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fem3d.errors import InputError, ParameterError
from fem3d.mesh import check_skin_placement, read_surface_mesh, read_tet_mesh
from fem3d.model import validate_dt, validate_material

__all__ = ["Scene", "PullScript", "SCENES", "load_scene", "data_dir", "PULL_DURATION"]

#: Seconds the scripted pull lasts before release.
PULL_DURATION = 0.3
#: Offset of the scripted pull target as a fraction of the mesh height.
PULL_FRACTION = 0.15


def data_dir() -> Path:
    """Folder of the shipped meshes: ``$FEM3D_DATA`` if set, else the checkout's ``data/``."""
    env = os.environ.get("FEM3D_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parent.parent / "data"


@dataclass(frozen=True, eq=False)
class PullScript:
    """A scripted pull: springs from the picked vertices to their rest position + offset.

    Attributes
    ----------
    vertex : int
        The chosen vertex (picking centre).
    point : (3,) float64
        Its rest position.
    offset : (3,) float64
        Target displacement applied to every picked vertex.
    start : float
        Time the springs attach.
    duration : float
        How long they stay.
    """

    vertex: int
    point: np.ndarray
    offset: np.ndarray
    start: float = 0.0
    duration: float = PULL_DURATION

    def active(self, t: float, dt: float) -> bool:
        """Whether the pull acts during the step that starts at ``t``."""
        eps = 1e-9 * dt
        return self.start - eps <= t < self.start + self.duration - eps


@dataclass(frozen=True, eq=False)
class Scene:
    """Everything needed to set up a simulation.

    Attributes
    ----------
    name : str
    X : (n, 3) float64
        Rest positions of the simulation mesh.
    T : (m, 4) int64
        Tets (positively oriented).
    skin_V : (k, 3) float64 or None
        Display mesh vertices (rest), skinned to the tets.
    skin_F : (f, 3) int64 or None
        Display mesh triangles.
    E, nu, rho, dt : float
        Young's modulus, Poisson's ratio, density, time step.
    spring_k : float
        Pull-spring stiffness.
    fixed_tol : float
        Vertices within this of the lowest y are fixed.
    pick_radius : float
        Picking radius around a pick point.
    integrator : {"linear", "implicit"}
        Default integrator.
    pull : PullScript or None
        Scripted pull used by headless runs.
    material : str
        Material name (``"neo_hookean"``).
    mesh_path, skin_path : str or None
        Source files.
    """

    name: str
    X: np.ndarray
    T: np.ndarray
    skin_V: np.ndarray | None
    skin_F: np.ndarray | None
    E: float
    nu: float
    rho: float
    dt: float
    spring_k: float
    fixed_tol: float
    pick_radius: float
    integrator: str
    pull: PullScript | None = None
    material: str = "neo_hookean"
    mesh_path: str | None = None
    skin_path: str | None = None
    extra: dict = field(default_factory=dict, repr=False)

    @property
    def height(self) -> float:
        """Extent of the rest mesh along y."""
        return float(np.ptp(self.X[:, 1]))

    def replace(self, **changes) -> Scene:
        """A copy with some fields changed (validated)."""
        new = dataclasses.replace(self, **changes)
        _validate(new)
        return new


def _validate(s: Scene) -> None:
    validate_material(s.E, s.nu, s.rho)
    validate_dt(s.dt)
    for name in ("spring_k", "fixed_tol", "pick_radius"):
        v = float(getattr(s, name))
        if not np.isfinite(v) or v < 0 or (name == "spring_k" and v == 0):
            op = ">" if name == "spring_k" else ">="
            raise ParameterError(f"{name} must be a finite number {op} 0, got {v}")
    from fem3d.integrators import INTEGRATORS

    if s.integrator not in INTEGRATORS:
        raise ParameterError(
            f"unknown integrator {s.integrator!r}; choose one of {', '.join(INTEGRATORS)}"
        )


def _pull_script(X: np.ndarray, vertex: int, axis: int, fraction: float) -> PullScript:
    offset = np.zeros(3)
    offset[axis] = fraction * float(np.ptp(X[:, 1]))
    return PullScript(vertex=int(vertex), point=X[vertex].copy(), offset=offset)


def top_vertex(X: np.ndarray) -> int:
    """Index of the vertex with the largest y (ties: lowest index)."""
    return int(np.argmax(X[:, 1]))


def hand_vertex(X: np.ndarray) -> int:
    """The vertex with the largest x among those above mid-height (the armadillo's hand)."""
    y = X[:, 1]
    upper = np.flatnonzero(y > 0.5 * (y.min() + y.max()))
    return int(upper[np.argmax(X[upper, 0])])


def _bunny() -> Scene:
    d = data_dir()
    mesh = read_tet_mesh(d / "coarser_bunny.mesh")
    skin_path = d / "bunny_skin.obj"
    skin_V, skin_F = read_surface_mesh(skin_path)
    return Scene(
        name="bunny", X=mesh.X, T=mesh.T, skin_V=skin_V, skin_F=skin_F,
        E=6e6, nu=0.4, rho=0.1, dt=0.01, spring_k=1e8, fixed_tol=3.0, pick_radius=1.0,
        integrator="linear",
        pull=_pull_script(mesh.X, top_vertex(mesh.X), axis=0, fraction=0.15),
        mesh_path=str(mesh.path), skin_path=str(skin_path),
    )


def _arma() -> Scene:
    d = data_dir()
    mesh = read_tet_mesh(d / "arma_6.node")
    skin_path = d / "armadillo.obj"
    skin_V, skin_F = read_surface_mesh(skin_path)
    return Scene(
        name="arma", X=mesh.X, T=mesh.T, skin_V=skin_V, skin_F=skin_F,
        E=6e5, nu=0.4, rho=0.1, dt=0.01, spring_k=1e5, fixed_tol=0.1, pick_radius=0.01,
        integrator="implicit",
        pull=_pull_script(mesh.X, hand_vertex(mesh.X), axis=2, fraction=0.20),
        mesh_path=str(mesh.path), skin_path=str(skin_path),
    )


#: Built-in scene factories by name.
SCENES = {"bunny": _bunny, "arma": _arma}


def _from_path(path: str | os.PathLike[str], skin: str | os.PathLike[str] | None) -> Scene:
    mesh = read_tet_mesh(path)
    h = float(np.ptp(mesh.X[:, 1]))
    if not h > 0:
        raise InputError("mesh has no extent along y", path=path)
    skin_V = skin_F = None
    if skin is not None:
        skin_V, skin_F = read_surface_mesh(skin)
        check_skin_placement(skin_V, mesh.X, mesh.T, path=skin)
    E = 6e5
    return Scene(
        name=Path(path).stem, X=mesh.X, T=mesh.T, skin_V=skin_V, skin_F=skin_F,
        E=E, nu=0.4, rho=0.1, dt=0.01, spring_k=0.15 * E * h, fixed_tol=0.02 * h,
        pick_radius=0.01 * h, integrator="implicit",
        pull=_pull_script(mesh.X, top_vertex(mesh.X), axis=0, fraction=PULL_FRACTION),
        mesh_path=str(path), skin_path=None if skin is None else str(skin),
    )


def load_scene(
    name_or_path: str | os.PathLike[str],
    *,
    skin: str | os.PathLike[str] | None = None,
    **overrides,
) -> Scene:
    """A built-in scene by name, or a scene around any tet mesh file.

    Parameters
    ----------
    name_or_path : str or PathLike
        ``"bunny"``, ``"arma"``, or a path read by :func:`fem3d.mesh.read_tet_mesh`.
    skin : str or PathLike, optional
        Display mesh for a path scene (any format ``read_surface_mesh`` reads).
    **overrides
        Scene fields to change (``E=``, ``dt=``, ``integrator=``, ...); ``None`` values are
        ignored.

    Returns
    -------
    Scene

    Raises
    ------
    InputError
        Unknown name / unreadable mesh (naming file, line, element).
    ParameterError
        An override out of range.
    """
    key = str(name_or_path)
    if key in SCENES:
        if skin is not None:
            raise InputError(f"--skin is only for mesh files, not the built-in scene {key!r}")
        scene = SCENES[key]()
    elif Path(key).suffix or Path(key).exists():
        scene = _from_path(name_or_path, skin)
    else:
        raise InputError(
            f"unknown scene {key!r}: use one of {', '.join(SCENES)} or a tet mesh file path"
        )
    changes = {k: v for k, v in overrides.items() if v is not None}
    unknown = set(changes) - {f.name for f in dataclasses.fields(Scene)}
    if unknown:
        raise ParameterError(f"unknown scene field(s): {', '.join(sorted(unknown))}")
    scene = dataclasses.replace(scene, **changes)
    _validate(scene)
    return scene
