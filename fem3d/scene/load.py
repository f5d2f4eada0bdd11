"""Reading a scene: by name, from a TOML file, around a mesh or arrays; changing it by key paths.

::

    from fem3d.scene.load import load_scene, apply_overrides
    scene = load_scene("bunny")                            # data/scenes/bunny.toml
    scene = load_scene("my_scene.toml")                    # a scene file
    scene = load_scene("beam.msh")                         # a one-body scene around a mesh
    scene = apply_overrides(scene, {"bodies[0].material.E": 1e5, "simulation.dt": 0.005})

What a scene holds (the pydantic models, their checks and conventions) is
:mod:`fem3d.scene.spec`; this module only finds, parses and validates it. Errors are
:class:`~fem3d.errors.InputError` with one line ``FILE: key.path: what is wrong``.
"""

from __future__ import annotations

import copy
import difflib
import hashlib
import os
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from fem3d.errors import InputError
from fem3d.io.files import atomic_write, cache_dir, check_input_file
from fem3d.mesh.formats import read_surface_mesh, write_tet_mesh
from fem3d.mesh.tetmesh import TetMesh
from fem3d.scene.arrays import is_surface_file, rest_positions
from fem3d.scene.keys import format_key, parse_key, set_path
from fem3d.scene.spec import Scene, describe_error, primary_error

__all__ = ["load_scene", "apply_overrides", "read_scene_file", "mesh_scene",
           "scene_from_arrays", "scene_names", "scenes_dir", "data_dir", "cache_dir", "SCENES",
           "MESH_SCENE_DEFAULTS"]

#: What ``load_scene(MESH)`` puts around a bare mesh (lengths as fractions of its height).
MESH_SCENE_DEFAULTS = {
    "E": 6e5, "nu": 0.4, "density": 0.1, "dt": 0.01, "integrator": "implicit",
    "fix_fraction": 0.02, "pick_fraction": 0.01, "spring_fraction": 0.15,
    "pull_fraction": 0.15, "pull_duration": 0.3,
}


# ------------------------------------------------------------------------------ folders
def data_dir() -> Path:
    """Folder of the shipped meshes: ``$FEM3D_DATA`` if set, else the checkout's ``data/``
    (a source checkout or an editable install), else the installed package's copy
    (``fem3d/_data``, the package data of a wheel)."""
    env = os.environ.get("FEM3D_DATA")
    if env:
        return Path(env)
    here = Path(__file__).resolve()
    checkout = here.parents[2] / "data"
    if (checkout / "scenes").is_dir():
        return checkout
    return here.parents[1] / "_data"


def scenes_dir() -> Path:
    """Folder of the named scenes: ``$FEM3D_SCENES``, else the checkout's ``data/scenes``."""
    env = os.environ.get("FEM3D_SCENES")
    if env:
        return Path(env)
    return data_dir() / "scenes"


# ------------------------------------------------------------------------------ names
def scene_names() -> list[str]:
    """Names ``load_scene`` accepts (the ``*.toml`` files of :func:`scenes_dir`), sorted,
    the classic ``bunny`` and ``arma`` first."""
    names = sorted(p.stem for p in scenes_dir().glob("*.toml"))
    first = [n for n in ("bunny", "arma") if n in names]
    return first + [n for n in names if n not in first]


class _Names(Sequence):
    """The named scenes, listed from ``data/scenes`` each time (``for name in SCENES``)."""

    def __getitem__(self, i):
        return scene_names()[i]

    def __len__(self) -> int:
        return len(scene_names())

    def __contains__(self, name: object) -> bool:
        return name in scene_names()

    def __repr__(self) -> str:
        return repr(scene_names())


#: Names of the scenes in ``data/scenes`` (a live view: ``list(SCENES)``).
SCENES = _Names()


# ------------------------------------------------------------------------------ reading
def read_scene_file(path: str | os.PathLike[str]) -> Scene:
    """Parse and validate one TOML scene file (relative paths: relative to its folder)."""
    path = check_input_file(path, "scene file")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read scene file ({exc.strerror or exc})", path=path) from None
    try:
        text = raw.decode("utf-8")
        data = tomllib.loads(text)
    except UnicodeDecodeError as exc:
        raise InputError(f"not UTF-8 text ({exc.reason} at byte {exc.start})",
                         path=path) from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", path=path) from None
    data.setdefault("name", path.stem)
    if "base_dir" in data:
        raise InputError("base_dir: set by the loader (the file's folder), not in the file",
                         path=path)
    if "source" in data:
        raise InputError("source: set by the loader, not in the file", path=path)
    data["base_dir"] = str(path.resolve().parent)
    data["source"] = str(path)
    scene = Scene.from_dict(data, source=str(path))
    scene.check_files()
    return scene


def mesh_scene(path: str | os.PathLike[str]) -> Scene:
    """A one-body scene around a tet mesh or closed surface file (see
    :data:`MESH_SCENE_DEFAULTS`): lowest-y pins within ``0.02 h``, the vertices within
    ``0.01 h`` of the top-most vertex pulled ``0.15 h`` along +x for 0.3 s by springs of
    ``interaction.spring_k`` (``0.15 E h``), picking radius ``0.01 h``."""
    p = check_input_file(path, "mesh")
    dflt = MESH_SCENE_DEFAULTS
    body = {"mesh": str(p.resolve()), "material": {
        "model": "neo_hookean", "E": dflt["E"], "nu": dflt["nu"], "density": dflt["density"]}}
    if is_surface_file(p):  # the surface's own extent: no tetrahedralization here
        X = read_surface_mesh(p)[0]
    else:
        draft = Scene.from_dict({"name": p.stem, "source": str(p), "bodies": [body]},
                                source=str(p))
        X = rest_positions(draft, 0)
    h = float(X[:, 1].max() - X[:, 1].min())
    if not h > 0:
        raise InputError("mesh has no extent along y", path=p)
    top = int(X[:, 1].argmax())
    pick = dflt["pick_fraction"] * h
    select = ({"nearest_to": {"point": [float(c) for c in X[top]], "radius": pick}}
              if is_surface_file(p) else {"near_vertex": {"vertex": top, "radius": pick}})
    body["pins"] = [{"select": {"lowest_y": {"tol": dflt["fix_fraction"] * h}}}]
    d = {
        "name": p.stem, "base_dir": str(p.resolve().parent), "source": str(p),
        "simulation": {"integrator": dflt["integrator"], "dt": dflt["dt"]},
        "bodies": [body],
        "pulls": [{"select": select, "offset": [dflt["pull_fraction"] * h, 0.0, 0.0],
                   "duration": dflt["pull_duration"]}],
    }  # interaction left out: 0.01 h and 0.15 E h (E as overridden)
    return Scene.from_dict(d, source=str(p))


def scene_from_arrays(X: Any, T: Any, overrides: Mapping[str, Any] | None = None, *,
                      name: str = "arrays") -> Scene:
    """A one-body scene (:func:`mesh_scene`) around a tet mesh given as arrays.

    The mesh is stored once in :func:`cache_dir` ``/arrays/<sha256>.mesh`` (named by its
    content), so the scene stays data: a path, serialisable and digestible.

    Parameters
    ----------
    X : (n, 3) float64
    T : (m, 4) int
    overrides : mapping, optional
        :func:`apply_overrides` on the result (``{"bodies[0].material.E": 1e5}``).
    name : str
    """
    X = np.ascontiguousarray(X, dtype=np.float64)
    T = np.ascontiguousarray(T, dtype=np.int64)
    h = hashlib.sha256(repr((X.shape, T.shape)).encode() + X.tobytes() + T.tobytes())
    folder = cache_dir() / "arrays"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{h.hexdigest()[:32]}.mesh"
    if not path.is_file():
        atomic_write(path, lambda p: write_tet_mesh(p, TetMesh(X, T)))
    scene = mesh_scene(path)
    return apply_overrides(apply_overrides(scene, {"name": name}), overrides)


def load_scene(
    name_or_path: str | os.PathLike[str], overrides: Mapping[str, Any] | None = None
) -> Scene:
    """A scene by name (``data/scenes/<name>.toml``), from a ``.toml`` file, or around a mesh.

    Parameters
    ----------
    name_or_path : str or PathLike
        A name of :func:`scene_names`, a scene file, or a tet mesh / closed surface file
        (then a one-body scene, :func:`mesh_scene`).
    overrides : mapping, optional
        Passed to :func:`apply_overrides`.

    Returns
    -------
    Scene

    Raises
    ------
    InputError
        Unknown name, unreadable or invalid file (``FILE: key.path: what is wrong``).
    """
    key = str(name_or_path)
    p = Path(key)
    named = scenes_dir() / f"{key}.toml"
    if p.suffix.lower() == ".toml":
        scene = read_scene_file(p)
    elif not p.suffix and "/" not in key and named.is_file():
        scene = read_scene_file(named)
    elif p.suffix or p.exists():
        scene = mesh_scene(p)
    else:
        if not named.is_file():
            names = scene_names()
            near = difflib.get_close_matches(key, names, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else ""
            if not names:  # an install without the built-in scenes (or a wrong FEM3D_SCENES)
                raise InputError(f"unknown scene {key!r}: no built-in scenes in "
                                 f"{scenes_dir()} (set FEM3D_SCENES to a folder of .toml "
                                 "scenes, e.g. a checkout's data/scenes; or give a .toml "
                                 "scene file or a mesh file)")
            raise InputError(f"unknown scene {key!r}{hint} (use one of {', '.join(names)}, a "
                             f".toml scene file or a mesh file)")
        scene = read_scene_file(named)
    scene = apply_overrides(scene, overrides)
    scene.check_files()
    return scene


# ------------------------------------------------------------------------------ overrides
def apply_overrides(
    scene: Scene, overrides: Mapping[str, Any] | None, *, source: str = "override"
) -> Scene:
    """A copy of ``scene`` with fields changed by dotted key paths, validated again.

    Parameters
    ----------
    scene : Scene
    overrides : mapping of str to value
        ``{"bodies[0].material.E": 1e5, "simulation.dt": 0.005, "pulls": []}``. Setting
        ``simulation.steps`` clears ``simulation.duration`` and vice versa. Values are what
        the scene file would hold (TOML types); ``None`` removes an optional value.

    source : str, optional
        What error messages name (``"--dt"`` for a command-line flag).

    Returns
    -------
    Scene

    Raises
    ------
    InputError
        ``SOURCE: key.path: what is wrong`` (the scene's own file when the error is
        elsewhere).
    """
    if not overrides:
        return scene
    d = scene.model_dump(mode="json")  # lists, not tuples: items settable by index
    for key, value in overrides.items():
        parts = parse_key(str(key), source)
        if isinstance(value, tuple):
            value = list(value)
        set_path(d, parts, copy.deepcopy(value), str(key), source)
        if parts == ["simulation", "steps"] and value is not None:
            d["simulation"]["duration"] = None
        elif parts == ["simulation", "duration"] and value is not None:
            d["simulation"]["steps"] = None
    try:
        return Scene.model_validate(d)
    except ValidationError as exc:
        err = primary_error(exc.errors(include_url=False))[0]
        loc = format_key(tuple(err["loc"]))
        given = [format_key(tuple(parse_key(str(k), source))) for k in overrides]
        src = source if any(loc.startswith(k) or k.startswith(loc) for k in given) \
            else scene.where
        raise InputError(f"{loc}: {describe_error(err)}", path=src) from None
