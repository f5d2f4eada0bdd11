"""From a sweep file to cases: :func:`expand_cases` (the axes -> the cases' overrides),
:func:`check_key_path` and :func:`plan_sweep` (resolved scenes, case ids, what is left to run
in the output folder).

The cases' overrides are the cartesian product of ``[grid]``, the rows of ``[zip]``, of
``[sample]`` (seeded random, Latin hypercube, Sobol, Halton) and of ``[[cases]]``; each
non-empty part is one factor of the product. A case's id is the first 16 hex digits of the
resolved scene's :meth:`~fem3d.scene.spec.Scene.digest`.

Per case the output folder holds ``DIR/cases/<id>/`` (:data:`SUMMARY_NAME` written last: a
case folder holding it is complete).
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import os
import re
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from fem3d.app.sweep.spec import SampleSpec, SweepFile, _loc
from fem3d.errors import InputError
from fem3d.io.frames import FRAME_FORMATS, frame_format
from fem3d.scene import apply_overrides, load_scene, scene_schema

__all__ = ["Case", "SweepPlan", "expand_cases", "check_key_path", "plan_sweep", "SUMMARY_NAME",
           "STARTED_NAME", "SCENE_NAME", "TRAJECTORY_NAME", "LOG_NAME"]

SUMMARY_NAME = "summary.json"
STARTED_NAME = "started.json"
SCENE_NAME = "scene.json"
TRAJECTORY_NAME = "trajectory.npz"
LOG_NAME = "run.log"
_KEY_SEGMENT = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)((?:\[\d+\])*)$")
_INDEX = re.compile(r"\[(\d+)\]")


# --------------------------------------------------------------------------------------
# cases


def _sample_rows(sample: SampleSpec) -> list[dict[str, Any]]:
    # imported here, not at module level: scipy.stats takes ~0.35 s to import and every
    # `fem3d` command imports this module (the sweep registers its sub-command)
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
# glue to the scenes layer (fem3d.scene.spec): every use of the planning is here


def _load_base(spec: SweepFile) -> Any:
    return load_scene(spec.scene, dict(spec.set) or None)


def _resolve(base: Any, overrides: Mapping[str, Any], source: str) -> Any:
    return apply_overrides(base, dict(overrides), source=source) if overrides else base


def _scene_schema() -> dict[str, Any]:
    return scene_schema()


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
        fmt = scene.output.format
        error = None
        if spec.dataset is not None and not frame_format(fmt).reads_back:
            readable = [f.name for f in FRAME_FORMATS.values() if f.reads_back]
            error = (f"invalid: dataset mode reads the run's frames: output.format must be "
                     f"{' or '.join(map(repr, readable))}, got {fmt!r}")
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


