"""The sweep file: its pydantic model (:class:`SweepFile`) and :func:`load_sweep_file`.

A sweep file names a base scene and the fields to vary, as dotted key paths of the scene
(``bodies[0].material.E``, ``simulation.dt``); see ``docs/sweeps.md`` for the format.
:func:`load_sweep_file` turns TOML into a :class:`SweepFile` with one-line errors that name
the key path (exit status 2 on the command line).
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from fem3d.errors import InputError
from fem3d.scene.spec import describe_error, primary_error

__all__ = ["SweepFile", "SampleSpec", "RangeSpec", "ResultsSpec", "DatasetSpec", "METRICS",
           "MAX_CASES", "load_sweep_file", "validation_message"]

#: Columns of ``results.csv`` that ``[results] metric`` may name (numbers of every case).
METRICS: tuple[str, ...] = (
    "wall_seconds", "steps", "newton_iterations", "kinetic_final", "potential_final",
    "total_final", "total_max", "max_displacement",
)


#: Most cases a sweep may have.
MAX_CASES = 100_000


# --------------------------------------------------------------------------------------
# the sweep file


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RangeSpec(_Spec):
    """A sampled parameter's interval ``[low, high]``.

    ``log``: uniform in ``log(x)`` (needs ``low > 0``); ``integer``: whole numbers from
    ``low`` to ``high`` inclusive.
    """

    low: float
    high: float
    log: bool = False
    integer: bool = False

    @model_validator(mode="after")
    def _check(self) -> RangeSpec:
        if not (math.isfinite(self.low) and math.isfinite(self.high)):
            raise ValueError("low and high must be finite numbers")
        if self.high < self.low:
            raise ValueError(f"high ({self.high:g}) is below low ({self.low:g})")
        if self.log and self.low <= 0:
            raise ValueError(f"log = true needs low > 0, got {self.low:g}")
        if self.integer and (self.low != int(self.low) or self.high != int(self.high)):
            raise ValueError("integer = true needs whole-number low and high")
        return self


class SampleSpec(_Spec):
    """``[sample]``: ``n`` points of ``ranges`` drawn by ``method`` with ``seed``."""

    method: Literal["latin_hypercube", "random", "sobol", "halton"] = "latin_hypercube"
    n: int = Field(ge=1, le=MAX_CASES)
    seed: int = 0
    ranges: dict[str, RangeSpec] = Field(min_length=1)


class ResultsSpec(_Spec):
    """``[results]``: ``metric`` is the ``results.csv`` column plotted in ``results.png``."""

    metric: Literal[METRICS] = "max_displacement"  # type: ignore[valid-type]


class DatasetSpec(_Spec):
    """``[dataset]``: write ``trajectory.npz`` per case (see :mod:`fem3d.io.dataset`)."""

    enabled: bool = True
    dtype: Literal["float32", "float64"] = "float32"


class SweepFile(_Spec):
    """A validated sweep file (see ``docs/sweeps.md``).

    Attributes
    ----------
    name : str
        Sweep name (default: the file's stem); the default output folder is ``out/<name>``.
    scene : str
        Base scene: a name (``data/scenes/<name>.toml``) or a path, relative to the sweep
        file's folder (made absolute by :func:`load_sweep_file`).
    set : dict
        Overrides of every case, key path -> value.
    grid : dict
        Key path -> list of values; every combination (cartesian product).
    zip : dict
        Key path -> list of values, all of one length; varied together.
    sample : SampleSpec or None
        Sampled key paths.
    cases : list of dict
        Explicit cases, each key path -> value.
    results : ResultsSpec
    dataset : DatasetSpec or None
        Dataset mode (a ``[dataset]`` table) or not.
    """

    name: str = Field(default="sweep", min_length=1, pattern=r"^[A-Za-z0-9_.\-]+$")
    description: str = ""
    scene: str = Field(min_length=1)
    set: dict[str, Any] = Field(default_factory=dict)
    grid: dict[str, list[Any]] = Field(default_factory=dict)
    zip: dict[str, list[Any]] = Field(default_factory=dict)
    sample: SampleSpec | None = None
    cases: list[dict[str, Any]] = Field(default_factory=list)
    results: ResultsSpec = Field(default_factory=ResultsSpec)
    dataset: DatasetSpec | None = None

    @field_validator("grid", "zip")
    @classmethod
    def _non_empty_lists(cls, v: dict[str, list[Any]]) -> dict[str, list[Any]]:
        for key, values in v.items():
            if not values:
                raise ValueError(f"{key}: an empty list of values")
        return v

    @model_validator(mode="after")
    def _check(self) -> SweepFile:
        lengths = {k: len(v) for k, v in self.zip.items()}
        if len(set(lengths.values())) > 1:
            raise ValueError(
                "zip: the lists must have one length, got "
                + ", ".join(f"{k} ({n})" for k, n in lengths.items())
            )
        owner: dict[str, str] = {}
        parts: list[tuple[str, Iterable[str]]] = [
            ("set", self.set), ("grid", self.grid), ("zip", self.zip),
            ("sample.ranges", self.sample.ranges if self.sample else ()),
        ]
        keys_of_cases: set[str] = set()
        for c in self.cases:
            keys_of_cases.update(c)
        parts.append(("cases", sorted(keys_of_cases)))
        for part, keys in parts:
            for key in keys:
                if key in owner and owner[key] != part:
                    raise ValueError(f"{key}: given in both {owner[key]} and {part}")
                owner[key] = part
        n = 1
        for size in (_grid_size(self.grid), len(next(iter(self.zip.values()), [None])),
                     self.sample.n if self.sample else 1, max(1, len(self.cases))):
            n *= size
        if n > MAX_CASES:
            raise ValueError(f"the sweep has {n} cases, more than the limit of {MAX_CASES}")
        return self

    @property
    def swept_keys(self) -> list[str]:
        """The key paths that vary between cases, in file order."""
        keys = list(self.grid) + list(self.zip)
        if self.sample is not None:
            keys += list(self.sample.ranges)
        for c in self.cases:
            keys += [k for k in c if k not in keys]
        return keys


def _grid_size(grid: Mapping[str, Sequence[Any]]) -> int:
    return math.prod(len(v) for v in grid.values()) if grid else 1


def _flatten(table: Mapping[str, Any], *, leaf: Callable[[Any], bool], prefix: str = "") -> dict:
    """``{"simulation": {"dt": x}}`` -> ``{"simulation.dt": x}``: TOML reads a bare dotted key
    (``simulation.dt = 0.01``) as nested tables; every non-``leaf`` table is one level of
    the key path."""
    flat: dict[str, Any] = {}
    for key, value in table.items():
        path = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, dict) and not leaf(value):
            flat.update(_flatten(value, leaf=leaf, prefix=path))
        else:
            flat[path] = value
    return flat


def _is_range(value: dict) -> bool:
    return "low" in value or "high" in value


def _normalize(raw: dict[str, Any]) -> dict[str, Any]:
    """Flatten the key-path tables of a parsed sweep file (before validation)."""
    doc = dict(raw)
    never = lambda v: False  # noqa: E731 - a table is always a level of the key path
    for part in ("set", "grid", "zip"):
        if isinstance(doc.get(part), dict):
            doc[part] = _flatten(doc[part], leaf=never)
    sample = doc.get("sample")
    if isinstance(sample, dict) and isinstance(sample.get("ranges"), dict):
        doc["sample"] = dict(sample, ranges=_flatten(sample["ranges"], leaf=_is_range))
    if isinstance(doc.get("cases"), list):
        doc["cases"] = [_flatten(c, leaf=never) if isinstance(c, dict) else c
                        for c in doc["cases"]]
    return doc


def _loc(loc: Sequence[Any]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            text = str(part)
            if re.search(r"[.\[\]\s]", text):
                text = f'"{text}"'
            out += f".{text}" if out else text
    return out


def validation_message(exc: ValidationError) -> str:
    """The first error of ``exc`` on one line: ``key.path: what is wrong`` (a misspelled
    required key as the unknown key with its "did you mean", as in scene files)."""
    err = primary_error(exc.errors(include_url=False), root=SweepFile)[0]
    loc = [p for p in err["loc"] if not (isinstance(p, str) and p.startswith("function-"))]
    msg = err["msg"].removeprefix("Value error, ")
    if err["type"] == "extra_forbidden":
        msg = describe_error(err, root=SweepFile)
    where = _loc(loc)
    return f"{where}: {msg}" if where else msg


def load_sweep_file(path: str | os.PathLike[str]) -> SweepFile:
    """Read and validate a sweep file.

    Parameters
    ----------
    path : str or PathLike
        The ``.toml`` sweep file.

    Returns
    -------
    SweepFile
        With ``scene`` made absolute when it names a file beside the sweep file, and
        ``name`` defaulting to the file's stem.

    Raises
    ------
    InputError
        Unreadable file, TOML syntax, or a bad value (the message names the key path).
    """
    p = Path(path)
    try:
        raw = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("no such sweep file", path=p) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the sweep file: {exc}", path=p) from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", path=p) from None
    raw = _normalize(raw)
    raw.setdefault("name", re.sub(r"[^A-Za-z0-9_.\-]", "_", p.stem) or "sweep")
    if isinstance(raw.get("dataset"), dict):
        raw["dataset"] = {"enabled": True, **raw["dataset"]}
    try:
        spec = SweepFile.model_validate(raw)
    except ValidationError as exc:
        raise InputError(validation_message(exc), path=p) from None
    if spec.dataset is not None and not spec.dataset.enabled:
        spec = spec.model_copy(update={"dataset": None})
    local = (p.parent / spec.scene)
    if local.suffix and local.exists():
        spec = spec.model_copy(update={"scene": str(local.resolve())})
    return spec


