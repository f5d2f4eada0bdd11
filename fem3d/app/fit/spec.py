"""The fit file: its pydantic model (:class:`FitFile`) and :func:`load_fit_file`.

Example (paths relative to the fit file)::

    scene = "bar.toml"                 # the base scene
    target = "runs/target"             # a folder written by `fem3d run` (or a trajectory.npz)
    [loss]
    every = 2                          # every 2nd frame of the target (or frames = [10, 20])
    select = {lowest_y = {tol = 0.0}}  # the vertices compared (default: all; body = 0)
    [[params]]
    key = "bodies[0].material.E"
    start = 1e5
    bounds = [1e3, 1e8]                # log = true: searched in log(E) (default: low > 0)
    [optimizer]
    max_iterations = 30

:func:`load_fit_file` turns TOML into a :class:`FitFile` with one-line errors that name the
file and the key path (exit status 2 on the command line).
"""

from __future__ import annotations

import difflib
import math
import os
import re
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from fem3d.app.sweep.spec import _loc
from fem3d.diff.params import KEY_PATTERNS, PARAMETER_KEYS, is_field_key
from fem3d.errors import InputError
from fem3d.scene.spec import Selector

__all__ = ["FitFile", "ParamSpec", "LossSpec", "OptimizerSpec", "load_fit_file",
           "VECTOR_KEYS", "key_pattern"]

#: Key endings whose value is a 3-vector.
VECTOR_KEYS = ("velocity", "gravity", "translate")

_KEY = re.compile("|".join(f"(?:{p.pattern})" for p in KEY_PATTERNS))


def key_pattern() -> re.Pattern[str]:
    """The regular expression of the parameter keys :mod:`fem3d.diff` differentiates."""
    return _KEY


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Bound = float | None


class ParamSpec(_Spec):
    """``[[params]]``: one parameter by key path.

    Attributes
    ----------
    key : str
        One of :data:`fem3d.diff.adjoint.PARAMETER_KEYS` (``bodies[0].material.E``).
    start : float or list of 3 floats, optional
        Starting value (default: the base scene's; a per-tet field
        ``bodies[i].material.cell_fields.NAME``: one number for every tet, default the
        mesh's values).
    bounds : [low, high], optional
        Finite or ``inf`` (left out: unbounded); vectors: the same bounds for every
        component.
    log : bool, optional
        Search in ``log(value)`` (default: true when ``low > 0``; needs ``low > 0``).
    """

    key: str
    start: float | list[float] | None = None
    bounds: tuple[float, float] | None = None
    log: bool | None = None

    @model_validator(mode="after")
    def _check(self) -> ParamSpec:
        if not _KEY.match(self.key):
            raise ValueError(f"key: cannot fit {self.key!r}; supported: "
                             f"{', '.join(PARAMETER_KEYS)} (i, j, k: indices; NAME: a "
                             "material parameter)")
        if is_field_key(self.key) and isinstance(self.start, list):
            raise ValueError(f"start: {self.key} is a per-tet field: start is one number "
                             "for every tet (left out: the mesh's values)")
        vector = self.key.endswith(VECTOR_KEYS)
        if self.start is not None:
            if vector != isinstance(self.start, list) or (vector and len(self.start) != 3):
                raise ValueError(f"start: {self.key} takes "
                                 f"{'a list of 3 numbers' if vector else 'a number'}")
            values = self.start if vector else [self.start]
            if not all(math.isfinite(v) for v in values):
                raise ValueError("start: must be finite")
        if self.bounds is not None:
            low, high = self.bounds
            if math.isnan(low) or math.isnan(high) or not low < high:
                raise ValueError(f"bounds: need low < high, got [{low:g}, {high:g}]")
            if self.log and not low > 0:
                raise ValueError(f"bounds: log = true needs low > 0, got {low:g}")
            if self.start is not None:
                values = self.start if vector else [self.start]
                if any(not low <= v <= high for v in values):
                    raise ValueError(f"bounds: start {self.start} is outside "
                                     f"[{low:g}, {high:g}]")
        elif self.log:
            raise ValueError("log: log = true needs bounds with low > 0")
        return self

    @property
    def is_log(self) -> bool:
        """Whether the parameter is searched in ``log(value)``."""
        if self.log is not None:
            return self.log
        return self.bounds is not None and self.bounds[0] > 0


class LossSpec(_Spec):
    """``[loss]``: which frames and vertices the loss compares.

    ``L = sum_frames 1/2 weight sum_vertices |q - target|^2`` (see
    :class:`fem3d.diff.PositionLoss`).

    Attributes
    ----------
    frames : list of int, optional
        Step indices of target frames (each must be one of the target's); default: every
        ``every``-th frame of the target after step 0.
    every : int
        Stride through the target's frames (with ``frames`` left out).
    body : int
        The body ``select`` chooses from.
    select : Selector, optional
        The vertices compared, like a pin's ``select`` (default: every vertex of every body).
    weight : float
    """

    frames: list[int] | None = Field(default=None, min_length=1)
    every: int = Field(default=1, ge=1)
    body: int = Field(default=0, ge=0)
    select: Selector | None = None
    weight: float = Field(default=1.0, gt=0)

    @model_validator(mode="after")
    def _check(self) -> LossSpec:
        if self.frames is not None and any(f < 1 for f in self.frames):
            raise ValueError("frames: step indices >= 1 (step 0 is the initial state)")
        return self


class OptimizerSpec(_Spec):
    """``[optimizer]``: :func:`scipy.optimize.minimize` settings.

    The optimiser sees the loss divided by its value at the start and each parameter
    scaled (``log(value / start)``, or ``(value - start) / scale``), so ``ftol`` and
    ``gtol`` do not depend on units.
    """

    method: Literal["L-BFGS-B", "TNC", "SLSQP"] = "L-BFGS-B"
    max_iterations: int = Field(default=30, ge=1)
    ftol: float = Field(default=1e-12, gt=0)
    gtol: float = Field(default=1e-8, gt=0)
    checkpoint_every: int = Field(default=10, ge=1)


class FitFile(_Spec):
    """A validated fit file (see the module docstring and ``docs/differentiable.md``).

    Attributes
    ----------
    name : str
        Default: the file's stem.
    scene : str
        Base scene: a name of ``data/scenes`` or a ``.toml`` path (relative to the fit file;
        made absolute by :func:`load_fit_file`).
    target : str
        A ``fem3d run`` output folder (its frames) or a ``trajectory.npz`` (absolute after
        loading).
    set : dict
        Overrides of the base scene, key path -> value.
    steps : int, optional
        Steps simulated (default: the last frame compared).
    loss : LossSpec
    params : list of ParamSpec
    optimizer : OptimizerSpec
    """

    name: str = Field(default="fit", min_length=1, pattern=r"^[A-Za-z0-9_.\-]+$")
    description: str = ""
    scene: str = Field(min_length=1)
    target: str = Field(min_length=1)
    set: dict[str, Any] = Field(default_factory=dict)
    steps: int | None = Field(default=None, ge=1)
    loss: LossSpec = Field(default_factory=LossSpec)
    params: list[ParamSpec] = Field(min_length=1)
    optimizer: OptimizerSpec = Field(default_factory=OptimizerSpec)

    @model_validator(mode="after")
    def _unique(self) -> FitFile:
        seen: set[str] = set()
        for i, p in enumerate(self.params):
            if p.key in seen:
                raise ValueError(f"params[{i}].key: {p.key} is given twice")
            seen.add(p.key)
        return self


def _flatten_set(table: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in table.items():
        path = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict):
            out.update(_flatten_set(v, path))
        else:
            out[path] = v
    return out


def _message(exc: ValidationError) -> str:
    """One line ``key.path: what``: an unknown key first (a misspelt key also leaves its
    right name missing), a model validator's own ``key: ...`` joined to its location."""
    errors = exc.errors(include_url=False)
    unknown = [e for e in errors if e["type"] == "extra_forbidden"]
    err = (unknown or errors)[0]
    if err["type"] == "extra_forbidden":
        where = _loc(err["loc"])
        parent = _model_at(err["loc"][:-1])
        near = difflib.get_close_matches(str(err["loc"][-1]), list(parent.model_fields), n=1,
                                         cutoff=0.5) if parent else []
        hint = f"; did you mean {near[0]!r}?" if near else ""
        return f"{where}: unknown key{hint}"
    if err["type"] == "missing":
        return f"{_loc(err['loc'])}: missing (required)"
    loc = [p for p in err["loc"] if not (isinstance(p, str) and p.startswith("function-"))]
    msg = err["msg"].removeprefix("Value error, ")
    text = f"{_loc(loc)}: {msg}" if loc else msg
    m = re.match(r"^(params\[\d+\]): (key|start|bounds|log): (.*)$", text)
    return f"{m.group(1)}.{m.group(2)}: {m.group(3)}" if m else text


def _model_at(loc: tuple) -> type[BaseModel] | None:
    models: dict[str, type[BaseModel]] = {"params": ParamSpec, "loss": LossSpec,
                                          "optimizer": OptimizerSpec}
    parts = [p for p in loc if isinstance(p, str)]
    if not parts:
        return FitFile
    return models.get(parts[0]) if len(parts) == 1 else None


def load_fit_file(path: str | os.PathLike[str]) -> FitFile:
    """Read and validate a fit file.

    Parameters
    ----------
    path : str or PathLike

    Returns
    -------
    FitFile
        ``scene`` (when a file beside the fit file) and ``target`` made absolute.

    Raises
    ------
    InputError
        ``FILE: key.path: what is wrong`` (unreadable file, TOML syntax, a bad value, a
        target that does not exist).
    """
    p = Path(path)
    try:
        raw = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("no such fit file", path=p) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the fit file: {exc}", path=p) from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", path=p) from None
    raw.setdefault("name", re.sub(r"[^A-Za-z0-9_.\-]", "_", p.stem) or "fit")
    if isinstance(raw.get("set"), dict):
        raw["set"] = _flatten_set(raw["set"])
    try:
        spec = FitFile.model_validate(raw)
    except ValidationError as exc:
        raise InputError(_message(exc), path=p) from None
    base = p.parent
    scene = base / spec.scene
    if scene.suffix:
        if not scene.exists():
            raise InputError(f"scene: no such file {scene}", path=p)
        spec = spec.model_copy(update={"scene": str(scene.resolve())})
    target = base / spec.target
    if not target.exists():
        missing = os.path.normpath(target.absolute())
        raise InputError(
            f"target = {spec.target!r}: {missing} does not exist (the target run's folder or "
            "frames file, relative to this file; make it with fem3d run SCENE --out DIR)",
            path=p)
    return spec.model_copy(update={"target": str(target.resolve())})
