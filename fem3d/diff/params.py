"""The parameters :mod:`fem3d.diff` differentiates: their keys, and where each tet's material
values come from (body, region, per-tet cell field).

A key names a field of the scene format (:mod:`fem3d.scene.spec`):

* ``simulation.gravity`` (3-vector), ``bodies[i].velocity`` (3-vector),
  ``bodies[i].material.density``, ``bodies[i].damping.rayleigh_mass``,
  ``bodies[i].damping.rayleigh_stiffness``;
* material values: ``bodies[i].material.E`` / ``.nu`` / ``.params.NAME`` (the tets that take
  the body's value), ``bodies[i].material.regions[j].E`` / ``.nu`` / ``.params.NAME`` (the
  region's tets; the region must give that value), ``bodies[i].material.cell_fields.NAME``
  (a per-tet field: the gradient is an array over the body's tets, zero on the tets of a
  region that sets ``NAME``);
* ``bodies[i].pins[j].motion.keyframes[k].translate`` (3-vector): a moving pin's keyframe.

Each tet's kernel parameters are a function of its *source values* (``E, nu`` through the
material's generated mapping, or the material's own parameters by name); the adjoint
accumulates ``dL/d(kernel params)`` per tet and :class:`TetSources` turns it into
``dL/d(source value)`` per tet, then into the keys (sums over the tets a key owns).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from fem3d.errors import ParameterError
from fem3d.physics.materials import info, parameters_jacobian_from
from fem3d.scene.arrays import SceneArrays, select_vertices
from fem3d.scene.build import _cell_field
from fem3d.scene.spec import Scene

__all__ = ["PARAMETER_KEYS", "KEY_PATTERNS", "ParamKey", "parse_param_key", "TetSources",
           "is_vector_key", "is_field_key"]

#: The parameter keys (``i``, ``j``, ``k``: indices; ``NAME``: a material parameter).
PARAMETER_KEYS = (
    "bodies[i].material.E", "bodies[i].material.nu", "bodies[i].material.params.NAME",
    "bodies[i].material.regions[j].E", "bodies[i].material.regions[j].nu",
    "bodies[i].material.regions[j].params.NAME", "bodies[i].material.cell_fields.NAME",
    "bodies[i].material.density",
    "bodies[i].damping.rayleigh_mass", "bodies[i].damping.rayleigh_stiffness",
    "bodies[i].velocity", "bodies[i].pins[j].motion.keyframes[k].translate",
    "simulation.gravity",
)

_NAME = r"[A-Za-z_][A-Za-z0-9_]*"
#: One regular expression per entry of :data:`PARAMETER_KEYS`.
KEY_PATTERNS = tuple(
    re.compile("^" + re.escape(k).replace(r"\[i\]", r"\[(\d+)\]").replace(r"\[j\]", r"\[(\d+)\]")
               .replace(r"\[k\]", r"\[(\d+)\]").replace("NAME", f"({_NAME})") + "$")
    for k in PARAMETER_KEYS)


def is_vector_key(key: str) -> bool:
    """Whether the key's value is a 3-vector."""
    return key.endswith(("velocity", "gravity", "translate"))


def is_field_key(key: str) -> bool:
    """Whether the key is a per-tet field (its gradient: one value per tet of the body)."""
    return ".cell_fields." in key


@dataclass(frozen=True)
class ParamKey:
    """A parsed parameter key.

    Attributes
    ----------
    key : str
    kind : str
        ``"material"``, ``"field"``, ``"density"``, ``"rayleigh_mass"``,
        ``"rayleigh_stiffness"``, ``"velocity"``, ``"keyframe"`` or ``"gravity"``.
    body, region, pin, keyframe : int or None
    name : str or None
        The material value (``E``, ``nu`` or a parameter's name).
    """

    key: str
    kind: str
    body: int | None = None
    region: int | None = None
    pin: int | None = None
    keyframe: int | None = None
    name: str | None = None


def parse_param_key(key: str, extra: tuple[re.Pattern[str], ...] = ()) -> ParamKey:
    """Parse ``key`` (:data:`PARAMETER_KEYS`; ``extra``: further patterns, kind ``"extra"``).

    Raises
    ------
    ParameterError
        Not a supported key (the message lists them).
    """
    for pattern, template in zip(KEY_PATTERNS, PARAMETER_KEYS, strict=True):
        m = pattern.match(key)
        if m is None:
            continue
        g = m.groups()
        if template == "simulation.gravity":
            return ParamKey(key, "gravity")
        body = int(g[0])
        tail = template.split(".", 1)[1]
        if tail.startswith("material.regions"):
            return ParamKey(key, "material", body, region=int(g[1]), name=g[2] if len(g) > 2
                            else tail.rsplit(".", 1)[1])
        if tail.startswith("material.cell_fields"):
            return ParamKey(key, "field", body, name=g[1])
        if tail.startswith("material.params"):
            return ParamKey(key, "material", body, name=g[1])
        if tail in ("material.E", "material.nu"):
            return ParamKey(key, "material", body, name=tail[-1] if tail.endswith("E")
                            else "nu")
        if tail.startswith("pins"):
            return ParamKey(key, "keyframe", body, pin=int(g[1]), keyframe=int(g[2]))
        return ParamKey(key, tail.rsplit(".", 1)[-1], body)
    for pattern in extra:
        if pattern.match(key):
            return ParamKey(key, "extra")
    raise ParameterError(f"trajectory_gradient: cannot differentiate {key!r}; supported: "
                         f"{', '.join(PARAMETER_KEYS)}"
                         + "".join(f", {p.pattern}" for p in extra))


class TetSources:
    """Where every tet's material values come from, and the keys' tets.

    Parameters
    ----------
    scene : Scene
    a : SceneArrays
        The scene's arrays (:func:`fem3d.scene.arrays.build_arrays`).
    """

    def __init__(self, scene: Scene, a: SceneArrays) -> None:
        self.scene, self.a = scene, a
        m = a.T.shape[0]
        self.body = np.empty(m, dtype=np.int64)
        self.region = np.full(m, -1, dtype=np.int64)
        self.values: dict[str, np.ndarray] = {}  # source name -> (m,) (NaN: not given)
        for i, body in enumerate(scene.bodies):
            tets = a.body_tets[i]
            self.body[tets] = i
            mat = body.material
            given: dict[str, object] = dict(mat.params)
            if mat.E is not None:
                given.update(E=mat.E, nu=mat.nu)
            for param, name in mat.cell_fields.items():
                given[param] = _cell_field(scene, a, i, param, name)
            region = self.region[tets]
            if mat.regions:
                Xb = a.X[a.body_vertices[i]]
                Tb = a.T[tets] - a.body_vertices[i].start
                for j, r in enumerate(mat.regions):
                    ids = select_vertices(scene, Xb, r.select,
                                          f"bodies[{i}].material.regions[{j}].select")
                    region[np.isin(Tb, ids).all(axis=1)] = j
                self.region[tets] = region
            for name, value in given.items():
                self._column(name)[tets] = value
            for j, r in enumerate(mat.regions):
                own = {**r.params, **({"E": r.E} if r.E is not None else {}),
                       **({"nu": r.nu} if r.nu is not None else {})}
                sel = np.flatnonzero(region == j) + tets.start
                for name, value in own.items():
                    self._column(name)[sel] = value

    def _column(self, name: str) -> np.ndarray:
        if name not in self.values:
            self.values[name] = np.full(self.a.T.shape[0], np.nan)
        return self.values[name]

    def check(self, p: ParamKey) -> None:
        """Refuse a material or field key that names no value of the scene (one line)."""
        if p.kind not in ("material", "field"):
            return
        if p.body >= len(self.scene.bodies):
            raise ParameterError(f"{p.key}: the scene has {len(self.scene.bodies)} bodies")
        mat = self.scene.bodies[p.body].material
        if p.kind == "field":
            if p.name not in mat.cell_fields:
                raise ParameterError(f"{p.key}: bodies[{p.body}].material has no cell field "
                                     f"{p.name!r} (it has: {', '.join(mat.cell_fields) or 'none'})")
        elif p.region is not None:
            if p.region >= len(mat.regions):
                raise ParameterError(f"{p.key}: bodies[{p.body}].material has "
                                     f"{len(mat.regions)} regions")
            r = mat.regions[p.region]
            value = getattr(r, p.name) if p.name in ("E", "nu") else r.params.get(p.name)
            if value is None:
                raise ParameterError(f"{p.key}: the region gives no {p.name} of its own "
                                     "(its tets take the body's)")
        else:
            if p.name in mat.cell_fields:
                raise ParameterError(f"{p.key}: {p.name} is a per-tet field here; use "
                                     f"bodies[{p.body}].material.cell_fields.{p.name}")
            value = getattr(mat, p.name) if p.name in ("E", "nu") else mat.params.get(p.name)
            if value is None:
                raise ParameterError(f"{p.key}: bodies[{p.body}].material gives no {p.name}")
        names = info(mat.model).param_names
        if p.name not in ("E", "nu") and p.name not in names:
            raise ParameterError(f"{p.key}: material {mat.model!r} has no parameter "
                                 f"{p.name!r} (its parameters: {', '.join(names)}, E, nu)")

    def tets_of(self, p: ParamKey) -> np.ndarray:
        """The tets whose value ``p.name`` is the key's (global indices, sorted)."""
        tets = np.arange(self.a.body_tets[p.body].start, self.a.body_tets[p.body].stop)
        region = self.region[tets]
        if p.region is not None:
            return tets[region == p.region]
        regions = self.scene.bodies[p.body].material.regions
        own = np.array([(r.E if p.name == "E" else r.nu if p.name == "nu"
                         else r.params.get(p.name)) is not None for r in regions] + [False])
        return tets[~own[region]]  # region -1 picks the trailing False

    def jacobian(self, group_material: str, els: np.ndarray, name: str) -> np.ndarray:
        """``d kernel params / d name`` per element of ``els``, ``(k, n_params)``."""
        names = info(group_material).param_names
        if name in ("E", "nu"):
            E, nu = self.values["E"][els], self.values["nu"][els]
            jac = parameters_jacobian_from(group_material, E, nu)
            which = 0 if name == "E" else 1
            return np.stack([np.broadcast_to(np.asarray(jac[q][which], dtype=np.float64),
                                             (els.size,)) for q in names], axis=1)
        out = np.zeros((els.size, len(names)))
        out[:, names.index(name)] = 1.0
        return out
