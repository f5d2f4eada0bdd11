"""Parameter sweeps on Dask distributed: ``fem3d sweep SWEEP.toml``.

A sweep file names a base scene and the fields to vary, as dotted key paths of the scene
(``bodies[0].material.E``, ``simulation.dt``); every combination is one *case*: the base
scene with those overrides (:func:`fem3d.scene.load.apply_overrides`), run by the code of
``fem3d run`` (:func:`fem3d.app.cli.run_scene`) as one Dask task in a worker process. See
``docs/sweeps.md`` for the file format, the output layout and cluster use.

Stages
------
1. :func:`load_sweep_file` - TOML -> :class:`SweepFile` (pydantic; one-line errors that
   name the key path, exit status 2 on the command line).
2. :func:`expand_cases` - the cases' overrides: the cartesian product of ``[grid]``, the
   rows of ``[zip]``, of ``[sample]`` (seeded random, Latin hypercube, Sobol, Halton) and of
   ``[[cases]]``; each non-empty part is one factor of the product.
3. :func:`plan_sweep` - resolved scenes and case ids (the first 16 hex digits of the resolved
   scene's :meth:`~fem3d.scene.spec.Scene.digest`), which cases are already complete.
4. :func:`run_sweep` - the Dask part: one task per case to run (embedded ``LocalCluster``
   with single-threaded worker processes, or an existing scheduler), a progress bar, fault
   tolerance (a worker that dies has its case rescheduled elsewhere by the scheduler), then
   ``results.csv`` and ``results.png``.

Output folder ``DIR``
---------------------
``DIR/sweep.json`` (the sweep and its case list), ``DIR/results.csv``, ``DIR/results.png``,
and per case ``DIR/cases/<id>/``: ``scene.json`` (the resolved scene), what ``fem3d run``
writes (frames, ``energy.csv``), ``trajectory.npz`` in dataset mode (:mod:`fem3d.io.dataset`),
``started.json`` (which worker, process and attempt) and, written last by an atomic rename,
``summary.json``: a case folder holding ``summary.json`` is complete; any other is partial
and is cleared and run again by the next invocation.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import hashlib
import io
import itertools
import json
import logging
import math
import os
import re
import shutil
import signal
import socket
import sys
import threading
import time
import tomllib
import traceback
import uuid
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from fem3d.errors import Fem3dError, InputError

__all__ = [
    "SweepFile",
    "SampleSpec",
    "RangeSpec",
    "Case",
    "SweepPlan",
    "SweepReport",
    "THREAD_ENV",
    "METRICS",
    "load_sweep_file",
    "expand_cases",
    "check_key_path",
    "plan_sweep",
    "run_case",
    "run_sweep",
    "add_sweep_subcommand",
]

#: Environment of every worker process of the embedded cluster: one BLAS / OpenMP thread,
#: set before the process starts (the Nanny's ``env``), so parallelism comes from the cases.
THREAD_ENV: dict[str, str] = {
    name: "1"
    for name in (
        "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
        "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS",
    )
}

#: Columns of ``results.csv`` that ``[results] metric`` may name (numbers of every case).
METRICS: tuple[str, ...] = (
    "wall_seconds", "steps", "newton_iterations", "kinetic_final", "potential_final",
    "total_final", "total_max", "max_displacement",
)

SUMMARY_NAME = "summary.json"
STARTED_NAME = "started.json"
SCENE_NAME = "scene.json"
TRAJECTORY_NAME = "trajectory.npz"
LOG_NAME = "run.log"
MAX_CASES = 100_000
_KEY_SEGMENT = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)((?:\[\d+\])*)$")
_INDEX = re.compile(r"\[(\d+)\]")


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
    """The first error of ``exc`` on one line: ``key.path: what is wrong``."""
    err = exc.errors(include_url=False)[0]
    loc = [p for p in err["loc"] if not (isinstance(p, str) and p.startswith("function-"))]
    msg = err["msg"].removeprefix("Value error, ")
    if err["type"] == "extra_forbidden":
        msg = "unknown key"
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


# --------------------------------------------------------------------------------------
# cases


def _sample_rows(sample: SampleSpec) -> list[dict[str, Any]]:
    from scipy.stats import qmc

    keys = list(sample.ranges)
    d = len(keys)
    if sample.method == "random":
        u = np.random.default_rng(sample.seed).random((sample.n, d))
    else:
        engine = {"latin_hypercube": qmc.LatinHypercube, "sobol": qmc.Sobol,
                  "halton": qmc.Halton}[sample.method](d, rng=np.random.default_rng(sample.seed))
        with warnings.catch_warnings():  # Sobol: "balance properties need n = 2**m"
            warnings.simplefilter("ignore", UserWarning)
            u = engine.random(sample.n)
    rows: list[dict[str, Any]] = [{} for _ in range(sample.n)]
    for j, key in enumerate(keys):
        r = sample.ranges[key]
        col = u[:, j]
        if r.integer:
            lo, hi = int(r.low), int(r.high)
            if r.log:
                x = np.exp(np.log(lo) + col * (np.log(hi + 1) - np.log(lo)))
                vals = np.minimum(np.floor(x), hi).astype(np.int64)
            else:
                vals = np.minimum(lo + np.floor(col * (hi - lo + 1)), hi).astype(np.int64)
            for row, v in zip(rows, vals, strict=True):
                row[key] = int(v)
            continue
        if r.log:
            x = np.exp(np.log(r.low) + col * (np.log(r.high) - np.log(r.low)))
        else:
            x = r.low + col * (r.high - r.low)
        x = np.clip(x, r.low, r.high)
        for row, v in zip(rows, x, strict=True):
            row[key] = float(v)
    return rows


def expand_cases(spec: SweepFile) -> list[dict[str, Any]]:
    """The overrides of every case, in a fixed order (``[set]`` not included).

    Every non-empty part is one factor of a cartesian product, in the order ``grid`` (itself
    the product of its keys, the last key varying fastest), ``zip``, ``sample``, ``cases``.

    Returns
    -------
    list of dict
        Key path -> value per case; ``[{}]`` for a sweep without axes (one case).
    """
    factors: list[list[dict[str, Any]]] = []
    if spec.grid:
        keys = list(spec.grid)
        factors.append([dict(zip(keys, combo, strict=True))
                        for combo in itertools.product(*(spec.grid[k] for k in keys))])
    if spec.zip:
        n = len(next(iter(spec.zip.values())))
        factors.append([{k: v[i] for k, v in spec.zip.items()} for i in range(n)])
    if spec.sample is not None:
        factors.append(_sample_rows(spec.sample))
    if spec.cases:
        factors.append([dict(c) for c in spec.cases])
    cases = []
    for combo in itertools.product(*factors):
        merged: dict[str, Any] = {}
        for part in combo:
            merged.update(part)
        cases.append(merged)
    return cases


def _split_key(path: str) -> list[str | int]:
    parts: list[str | int] = []
    if not path:
        raise ValueError("an empty key path")
    for seg in path.split("."):
        m = _KEY_SEGMENT.match(seg)
        if m is None:
            raise ValueError(f"bad key path segment {seg!r} (expected name or name[index])")
        parts.append(m.group(1))
        parts.extend(int(i) for i in _INDEX.findall(m.group(2)))
    return parts


def check_key_path(path: str, schema: Mapping[str, Any], data: Any = None) -> str | None:
    """Whether ``path`` names a field of a model (its JSON Schema) and, where present, of
    ``data`` (its dumped value, used to check list indices).

    Parameters
    ----------
    path : str
        Dotted key path, ``bodies[0].material.E``.
    schema : dict
        JSON Schema of the model (``$defs``/``$ref``, ``anyOf``/``oneOf``/``allOf``,
        ``properties``, ``additionalProperties``, ``items``/``prefixItems``).
    data : optional
        The model's current value as JSON-safe data.

    Returns
    -------
    str or None
        None when the path is valid, else what is wrong (in a few words).
    """
    try:
        parts = _split_key(path)
    except ValueError as exc:
        return str(exc)
    defs = schema.get("$defs", {})

    def resolve(node: Any) -> Any:
        while isinstance(node, dict) and "$ref" in node:
            node = defs.get(node["$ref"].rsplit("/", 1)[-1], {})
        return node

    def walk(node: Any, value: Any, i: int) -> str | None:
        node = resolve(node)
        if i == len(parts):
            return None
        if not isinstance(node, dict) or node is True or not node:
            return None  # any value: nothing more to check
        for combo in ("anyOf", "oneOf", "allOf"):
            if combo in node:
                errors = [walk(b, value, i) for b in node[combo]]
                if any(e is None for e in errors):
                    return None
                real = [e for e in errors if e and not e.startswith("cannot")]
                return real[0] if real else errors[0]
        part = parts[i]
        here = _loc(parts[:i]) or "the scene"
        if isinstance(part, int):
            if node.get("type") != "array" and "items" not in node and "prefixItems" not in node:
                return f"{here} is not a list"
            if isinstance(value, list) and part >= len(value):
                return f"index {part} out of range: {here} has {len(value)} entries"
            if "prefixItems" in node:
                items = node["prefixItems"]
                if part >= len(items):
                    return f"index {part} out of range: {here} has {len(items)} entries"
                sub = items[part]
            else:
                sub = node.get("items", True)
            child = value[part] if isinstance(value, list) and part < len(value) else None
            return walk(sub, child, i + 1)
        props = node.get("properties")
        extra = node.get("additionalProperties")
        if props is not None and part in props:
            sub = props[part]
        elif extra not in (None, False):
            sub = extra
        elif props is not None or node.get("type") == "object":
            known = ", ".join(sorted(props or ()))
            return f"{here} has no field {part!r}" + (f" (known: {known})" if known else "")
        else:
            return f"cannot go into {here} ({node.get('type', 'a value')}) with {part!r}"
        child = value.get(part) if isinstance(value, dict) else None
        return walk(sub, child, i + 1)

    return walk(schema, data, 0)


@dataclasses.dataclass(frozen=True)
class Case:
    """One case of a sweep.

    Attributes
    ----------
    index : int
        Position in the sweep (row of ``results.csv``).
    params : dict
        Its overrides (the swept key paths only).
    id : str
        Folder name under ``DIR/cases/``: the first 16 hex digits of the resolved scene's
        digest (of the base digest and the overrides when the case does not resolve).
    digest : str or None
        Full digest of the resolved scene; None when the overrides are rejected.
    scene : dict or None
        The resolved scene (``Scene.to_dict()``) sent to the worker.
    error : str or None
        Why the overrides were rejected (the case fails without running).
    """

    index: int
    params: dict[str, Any]
    id: str
    digest: str | None
    scene: dict[str, Any] | None
    error: str | None = None


@dataclasses.dataclass
class SweepPlan:
    """The cases of a sweep and what is left to run in ``out``."""

    spec: SweepFile
    out: Path
    cases: list[Case]
    todo: list[Case]  # one per id, incomplete (or failed with ``retry_failed``)
    done: list[Case]  # complete before this invocation


# --------------------------------------------------------------------------------------
# glue to the scenes layer (fem3d.scene.spec / fem3d.app.cli.run_scene): every use is here


def _load_base(spec: SweepFile) -> Any:
    from fem3d.scene.load import load_scene

    return load_scene(spec.scene, dict(spec.set) or None)


def _resolve(base: Any, overrides: Mapping[str, Any], source: str) -> Any:
    from fem3d.scene.load import apply_overrides

    return apply_overrides(base, dict(overrides), source=source) if overrides else base


def _scene_schema() -> dict[str, Any]:
    from fem3d.scene.spec import scene_schema

    return scene_schema()


def _scene_from_dict(d: Mapping[str, Any]) -> Any:
    from fem3d.scene.spec import Scene

    return Scene.from_dict(dict(d))


def _frame_format(scene_dict: Mapping[str, Any]) -> Any:
    return (scene_dict.get("output") or {}).get("format", "vtu")


def _run_scene(scene: Any, out: Path) -> dict[str, Any]:
    """Run ``scene`` into ``out`` with the code of ``fem3d run``; the RunSummary as a dict."""
    from fem3d.app.cli import run_scene

    summary = run_scene(scene, out, quiet=True, preview=False)
    return dataclasses.asdict(summary)


# --------------------------------------------------------------------------------------
# planning


def _json_safe(value: Any) -> Any:
    return json.loads(json.dumps(value, allow_nan=False, default=str))


def _read_summary(case_dir: Path) -> dict[str, Any] | None:
    try:
        data = json.loads((case_dir / SUMMARY_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def plan_sweep(spec: SweepFile, out: Path, *, retry_failed: bool = False,
               sweep_path: str | os.PathLike[str] | None = None) -> SweepPlan:
    """Resolve every case and find what is left to run in ``out``.

    Raises
    ------
    InputError
        The base scene or ``[set]`` is bad, or a swept key path names no scene field (a
        value the scene rejects only fails its own cases).
    """
    where = "" if sweep_path is None else f"{sweep_path}: "
    try:
        base = _load_base(spec)
    except InputError as exc:
        raise InputError(f"{where}scene {spec.scene!r}: {exc}") from None
    schema = _scene_schema()
    data = base.to_dict()
    for key in spec.swept_keys:
        problem = check_key_path(key, schema, data)
        if problem is not None:
            raise InputError(f"{where}{key}: {problem}")
    base_digest = base.digest()
    cases: list[Case] = []
    for index, params in enumerate(expand_cases(spec)):
        try:
            scene = _resolve(base, params, f"{sweep_path or spec.name} case {index}")
        except InputError as exc:
            token = json.dumps([base_digest, _json_safe(params)], sort_keys=True)
            cid = hashlib.sha256(token.encode()).hexdigest()[:16]
            cases.append(Case(index, params, cid, None, None, f"invalid: {exc}"))
            continue
        digest = scene.digest()
        d = scene.to_dict()
        fmt = _frame_format(d)
        error = None
        if spec.dataset is not None and fmt not in ("vtu", "obj"):
            error = (f"invalid: dataset mode reads the run's frames: output.format must be "
                     f"'vtu' or 'obj', got {fmt!r}")
        cases.append(Case(index, params, digest[:16], digest, d, error))
    todo: dict[str, Case] = {}
    done: dict[str, Case] = {}
    for case in cases:
        if case.error is not None or case.id in todo or case.id in done:
            continue
        summary = _read_summary(out / "cases" / case.id)
        complete = summary is not None and summary.get("digest") == case.digest
        if complete and not (retry_failed and summary.get("status") != "ok"):
            done[case.id] = case
        else:
            todo[case.id] = case
    return SweepPlan(spec, out, cases, list(todo.values()), list(done.values()))


# --------------------------------------------------------------------------------------
# one case (runs in a worker process)


def _write_json(path: Path, data: Any) -> None:
    from fem3d.io.files import atomic_write

    atomic_write(path, json.dumps(data, indent=1, allow_nan=False, default=str) + "\n")


def _worker_address() -> str | None:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return None


def run_case(task: Mapping[str, Any]) -> dict[str, Any]:
    """Run one case into its folder; the body of each Dask task.

    Clears the folder (a partial earlier attempt), writes ``started.json`` and
    ``scene.json``, runs the scene with the code of ``fem3d run``, writes
    ``trajectory.npz`` in dataset mode, and last, atomically, ``summary.json``. A case
    that fails (bad parameter, explosion) is recorded as failed, never raised: only a dying
    process leaves the folder without ``summary.json``.

    Parameters
    ----------
    task : dict
        ``dir`` (the case folder), ``id``, ``digest``, ``params``, ``scene`` (the resolved
        scene's ``to_dict()``), ``dataset`` (None or ``{"dtype": ...}``).

    Returns
    -------
    dict
        The summary written to ``summary.json``.
    """
    case_dir = Path(task["dir"])
    attempt = 1
    if case_dir.exists():  # a partial earlier attempt (its process died): start afresh
        with contextlib.suppress(OSError, ValueError, TypeError, AttributeError):
            earlier = json.loads((case_dir / STARTED_NAME).read_text(encoding="utf-8"))
            attempt = int(earlier.get("attempt", 1)) + 1
        shutil.rmtree(case_dir)
    case_dir.mkdir(parents=True)
    started = {
        "id": task["id"], "attempt": attempt, "host": socket.gethostname(), "pid": os.getpid(),
        "worker": _worker_address(), "started": time.time(),
        "threads": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")},
    }
    _write_json(case_dir / STARTED_NAME, started)
    _write_json(case_dir / SCENE_NAME, task["scene"])
    t0 = time.perf_counter()
    record: dict[str, Any] = {"status": "failed", "message": ""}
    try:
        scene = _scene_from_dict(task["scene"])
        digest = scene.digest()
        if digest != task["digest"]:
            raise InputError(
                "the scene's mesh files differ on this worker from the ones the sweep was "
                f"planned with (digest {digest[:16]} != {task['id']})"
            )
        with open(case_dir / LOG_NAME, "w", encoding="utf-8") as log, \
                contextlib.redirect_stderr(log), contextlib.redirect_stdout(log):
            record.update(_run_scene(scene, case_dir))
        if task.get("dataset") and record.get("status") == "ok":
            from fem3d.io.dataset import write_case_trajectory

            write_case_trajectory(case_dir, dtype=task["dataset"]["dtype"],
                                  meta={"id": task["id"], "params": task["params"]})
    except Fem3dError as exc:
        record.update(status="failed", message=str(exc))
    except Exception as exc:  # an unexpected error: recorded, with its traceback beside it
        record.update(status="failed", message=f"{type(exc).__name__}: {exc}")
        (case_dir / "error.txt").write_text(traceback.format_exc(), encoding="utf-8")
    summary = {
        "id": task["id"], "digest": task["digest"], "params": task["params"],
        **_json_safe(record),
        "case_seconds": time.perf_counter() - t0, "attempt": attempt,
        "worker": started["worker"], "host": started["host"], "pid": started["pid"],
        "threads": started["threads"], "finished": time.time(),
    }
    _write_json(case_dir / SUMMARY_NAME, summary)
    return summary


# --------------------------------------------------------------------------------------
# the engine


@dataclasses.dataclass
class SweepReport:
    """What an invocation did.

    Attributes
    ----------
    rows : list of dict
        One per case, in sweep order (the rows of ``results.csv``).
    ran, skipped : int
        Cases that ran to an end now (ok, failed or lost) / complete before.
    lost : list of str
        Ids of cases whose workers kept dying (left partial; the next invocation retries).
    interrupted : bool
    """

    rows: list[dict[str, Any]]
    ran: int
    skipped: int
    lost: list[str]
    interrupted: bool = False

    def count(self, status: str) -> int:
        return sum(1 for r in self.rows if r["status"] == status)


def _open_client(workers: int | None, scheduler: str | None, stack: contextlib.ExitStack):
    import dask
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            return stack.enter_context(Client(scheduler, timeout="20s"))
        except (OSError, TimeoutError) as exc:
            raise InputError(f"--scheduler {scheduler}: cannot connect: {exc}") from None
    # a task whose worker dies is rescheduled; after this many deaths it is given up (lost)
    stack.enter_context(dask.config.set({"distributed.scheduler.allowed-failures": 3}))
    cluster = stack.enter_context(LocalCluster(
        n_workers=workers or _cores(), threads_per_worker=1, processes=True,
        dashboard_address=None,  # no dashboard; its HTTP server on a free local port
        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
        silence_logs=logging.CRITICAL, env=dict(THREAD_ENV),
    ))
    return stack.enter_context(Client(cluster))


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def _task(plan: SweepPlan, case: Case) -> dict[str, Any]:
    ds = plan.spec.dataset
    return {
        "dir": str((plan.out / "cases" / case.id).resolve()), "id": case.id,
        "digest": case.digest, "params": _json_safe(case.params), "scene": case.scene,
        "dataset": None if ds is None else {"dtype": ds.dtype},
    }


def run_sweep(
    plan: SweepPlan,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    quiet: bool = False,
) -> SweepReport:
    """Run the incomplete cases of ``plan`` on Dask and write the results.

    Parameters
    ----------
    plan : SweepPlan
        From :func:`plan_sweep`.
    workers : int, optional
        Worker processes of the embedded ``LocalCluster`` (default: one per core).
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://host:8786``) instead.
    quiet : bool
        No progress bar.

    Returns
    -------
    SweepReport
    """
    from tqdm import tqdm

    out = plan.out
    (out / "cases").mkdir(parents=True, exist_ok=True)
    _write_json(out / "sweep.json", {
        "name": plan.spec.name, "spec": plan.spec.model_dump(mode="json"),
        "keys": plan.spec.swept_keys,
        "cases": [{"index": c.index, "id": c.id, "params": _json_safe(c.params),
                   "error": c.error} for c in plan.cases],
    })
    lost: dict[str, str] = {}
    interrupted = False
    ran = 0
    if plan.todo:
        from distributed import as_completed

        with contextlib.ExitStack() as stack:
            client = _open_client(workers, scheduler, stack)
            token = uuid.uuid4().hex[:8]
            futures = {
                client.submit(run_case, _task(plan, c), key=f"fem3d-case-{c.id}-{token}",
                              pure=False, retries=1): c
                for c in plan.todo
            }
            try:  # distributed >= 2025 lists only 5 workers unless asked for all
                info = client.scheduler_info(n_workers=-1)
            except TypeError:
                info = client.scheduler_info()
            n_workers = len(info.get("workers", {}))
            bar = tqdm(total=len(futures), unit="case", disable=quiet or None,
                       file=sys.stderr, dynamic_ncols=True,
                       desc=f"{plan.spec.name} ({n_workers} workers)")
            done = failed = 0
            try:
                for fut in as_completed(futures):
                    case = futures[fut]
                    if fut.status == "finished":
                        ok = fut.result().get("status") == "ok"
                    else:  # KilledWorker after allowed-failures deaths, or a lost task
                        ok = False
                        exc = fut.exception()
                        why = " ".join(str(exc).split())[:300]
                        lost[case.id] = f"lost: {type(exc).__name__}: {why}"
                    done += ok
                    failed += not ok
                    ran += 1
                    bar.update(1)
                    bar.set_postfix_str(
                        f"done {done} failed {failed} remaining {len(futures) - done - failed}",
                        refresh=True,
                    )
            except KeyboardInterrupt:
                interrupted = True
            finally:
                bar.close()
                if interrupted:
                    client.cancel(list(futures), force=True)
    rows = _rows(plan, lost)
    write_results(out, plan.spec, rows)
    return SweepReport(rows=rows, ran=ran, skipped=len(plan.done),
                       lost=sorted(lost), interrupted=interrupted)


def _rows(plan: SweepPlan, lost: Mapping[str, str]) -> list[dict[str, Any]]:
    rows = []
    cache: dict[str, dict[str, Any] | None] = {}
    for case in plan.cases:
        row: dict[str, Any] = {"case": case.index, "id": case.id}
        row.update({k: case.params.get(k) for k in plan.spec.swept_keys})
        if case.error is not None:
            row.update(status="failed", message=case.error)
            rows.append(row)
            continue
        if case.id not in cache:
            cache[case.id] = _read_summary(plan.out / "cases" / case.id)
        s = cache[case.id]
        if s is None or s.get("digest") != case.digest:
            status = "lost" if case.id in lost else "pending"
            row.update(status=status, message=lost.get(case.id, "not run yet"))
        else:
            row.update(status=s.get("status", "failed"), message=s.get("message", ""))
            row.update(_metrics(s))
            row.update(worker=s.get("worker"), attempt=s.get("attempt"))
        rows.append(row)
    return rows


def _metrics(s: Mapping[str, Any]) -> dict[str, Any]:
    """``results.csv`` metrics from a case summary (the fields of ``RunSummary``)."""
    names = {
        "wall_seconds": ("wall_seconds",),
        "steps": ("steps",),
        "newton_iterations": ("newton_iterations",),
        "kinetic_final": ("kinetic_final", "final_kinetic", "kinetic"),
        "potential_final": ("potential_final", "final_potential", "potential"),
        "total_final": ("total_final", "final_total", "total"),
        "total_max": ("total_max", "max_total", "max_total_energy"),
        "max_displacement": ("max_displacement",),
    }
    out = {}
    for col, keys in names.items():
        out[col] = next((s[k] for k in keys if k in s), None)
    return out


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, list | dict):
        return json.dumps(value)
    return str(value)


def write_results(out: Path, spec: SweepFile, rows: Sequence[Mapping[str, Any]]) -> None:
    """``out/results.csv`` (one row per case) and ``out/results.png`` (the metric against
    each swept parameter), both written atomically."""
    from fem3d.io.files import atomic_write

    columns = ["case", "id", *spec.swept_keys, "status", "message", *METRICS, "worker",
               "attempt"]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([_cell(r.get(c)) for c in columns])
    atomic_write(out / "results.csv", buf.getvalue())
    plot_results(out / "results.png", spec, rows)


def _numeric(values: Sequence[Any]) -> bool:
    return all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)


def plot_results(path: Path, spec: SweepFile, rows: Sequence[Mapping[str, Any]]) -> None:
    """One panel per swept key path: ``spec.results.metric`` of each ok case against the
    key's value; failed (or not yet run) cases as red crosses along the bottom."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from fem3d.io.files import atomic_write

    metric = spec.results.metric
    keys = spec.swept_keys or ["case"]
    ncol = min(3, len(keys))
    nrow = math.ceil(len(keys) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.4 * nrow), squeeze=False)
    good = [r for r in rows if r["status"] == "ok" and isinstance(r.get(metric), int | float)]
    bad = [r for r in rows if r not in good]
    ys = [float(r[metric]) for r in good]
    floor = min(ys) if ys else 0.0
    for ax, key in zip(axes.flat, keys, strict=False):
        values = [r.get(key) for r in rows]
        if _numeric([v for v in values if v is not None]):
            pos = lambda r, k=key: r.get(k)  # noqa: E731
            xs = [v for v in values if v is not None]
            if xs and min(xs) > 0 and max(xs) / min(xs) > 30:
                ax.set_xscale("log")
            else:
                ax.ticklabel_format(axis="x", style="sci", scilimits=(-3, 4))
        else:
            labels = sorted({_cell(v) for v in values}, key=str)
            pos = lambda r, k=key, lab=labels: lab.index(_cell(r.get(k)))  # noqa: E731
            ax.set_xticks(range(len(labels)), labels, rotation=30, ha="right", fontsize=7)
        if good:
            ax.plot([pos(r) for r in good], ys, "o", ms=5, alpha=0.8, label="ok")
        if bad:
            ax.plot([pos(r) for r in bad if r.get(key) is not None or key == "case"],
                    [floor for r in bad if r.get(key) is not None or key == "case"],
                    "x", color="tab:red", ms=7, label="failed / not run")
        ax.tick_params(labelsize=7)
        ax.set_xlabel(key, fontsize=8)
        ax.set_ylabel(metric, fontsize=8)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(keys):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(f"{spec.name}: {metric} ({len(good)} ok of {len(rows)} cases)", fontsize=10)
    fig.tight_layout()
    try:
        atomic_write(path, lambda p: fig.savefig(p, dpi=110, format="png"))
    finally:
        plt.close(fig)


# --------------------------------------------------------------------------------------
# command line


def add_sweep_subcommand(subparsers) -> argparse.ArgumentParser:
    """Register ``fem3d sweep``."""
    p = subparsers.add_parser(
        "sweep",
        help="run a parameter sweep of a scene on Dask (local processes or a cluster)",
        description="Run every case of a sweep file (a base scene and the key paths to "
        "vary: grid, zip, sampled, explicit cases) as one Dask task each, in DIR/cases/<id>/, "
        "and write DIR/results.csv and DIR/results.png. Complete cases are skipped, so an "
        "interrupted sweep continues where it stopped. See docs/sweeps.md.",
    )
    p.add_argument("sweep", help="sweep file (.toml)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="worker processes of the embedded cluster (default: one per core)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="use an existing Dask scheduler (tcp://host:8786) instead")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="output folder (default out/<sweep name>)")
    p.add_argument("--retry-failed", action="store_true",
                   help="run the cases recorded as failed again")
    p.add_argument("--metric", choices=METRICS, default=None, metavar="NAME",
                   help="the results.csv column plotted in results.png: "
                   f"{', '.join(METRICS)} (default: the sweep file's [results] metric, else "
                   "max_displacement)")
    p.add_argument("--list", action="store_true", dest="list_cases",
                   help="print the cases (id, state, overrides) and run nothing")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks"
    )
    p.set_defaults(func=_sweep_command)
    return p


@contextlib.contextmanager
def _sigterm_interrupts():
    """SIGTERM (a batch system stopping the job) acts as Ctrl-C: the cluster is shut down,
    the results so far are written, and the next invocation continues."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _sweep_command(args: argparse.Namespace) -> int:
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be >= 1, got {args.workers}")
    if args.workers is not None and args.scheduler is not None:
        raise InputError("--workers and --scheduler exclude each other")
    spec = load_sweep_file(args.sweep)
    if args.metric is not None:
        spec = spec.model_copy(update={"results": ResultsSpec(metric=args.metric)})
    out = Path(args.out) if args.out else Path("out") / spec.name
    plan = plan_sweep(spec, out, retry_failed=args.retry_failed, sweep_path=args.sweep)
    if args.list_cases:
        todo = {c.id for c in plan.todo}
        for c in plan.cases:
            state = "invalid" if c.error else ("to run" if c.id in todo else "complete")
            print(f"{c.index}\t{c.id}\t{state}\t{json.dumps(_json_safe(c.params))}")
        return 0
    invalid = sum(1 for c in plan.cases if c.error is not None)
    print(
        f"fem3d sweep {spec.name}: {len(plan.cases)} cases ({len(plan.todo)} to run, "
        f"{len(plan.done)} complete before, {invalid} rejected) -> {out}",
        file=sys.stderr,
    )
    with _sigterm_interrupts():
        report = run_sweep(plan, workers=args.workers, scheduler=args.scheduler,
                           quiet=args.quiet)
    ok, failed = report.count("ok"), report.count("failed")
    print(
        f"fem3d sweep {spec.name}: {ok} ok, {failed} failed, {len(report.lost)} lost, "
        f"{report.count('pending')} not run; ran {report.ran}, skipped {report.skipped}; "
        f"{out / 'results.csv'}",
        file=sys.stderr,
    )
    if report.interrupted:
        print("fem3d sweep: interrupted; run the same command again to continue",
              file=sys.stderr)
        return 130
    return 0 if ok == len(report.rows) else 1
