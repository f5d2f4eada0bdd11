"""Fitting: the target's frames, the loss, scipy's minimiser and the output files.

:func:`fit` reads the target (:func:`read_target`), builds the
:class:`~fem3d.diff.PositionLoss` of the frames and vertices the fit file names, and runs
:func:`scipy.optimize.minimize` with ``jac=True`` on the adjoint gradient of
:func:`fem3d.diff.trajectory_gradient`. The optimiser's variables are scaled: a log
parameter is ``u = log(value / start)``, a linear one ``u = (value - start) / s`` with ``s``
its start's magnitude (else the bounds' width, else 1); the loss is divided by its value at
the start. :func:`write_outputs` writes ``fit.json``, ``fit.png`` and ``fitted.toml``.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.optimize

from fem3d.app.fit.spec import VECTOR_KEYS, FitFile
from fem3d.diff import PositionLoss, trajectory_gradient
from fem3d.diff.adjoint import scene_with
from fem3d.diff.params import is_field_key, parse_param_key
from fem3d.errors import InputError, ParameterError, SimulationError
from fem3d.io.dataset import read_run_frames
from fem3d.io.files import atomic_write
from fem3d.mesh.element import element
from fem3d.scene import apply_overrides, load_scene
from fem3d.scene.arrays import build_arrays, select_vertices
from fem3d.scene.build import _cell_field, refuse_mixed_elements
from fem3d.scene.keys import parse_key
from fem3d.scene.spec import Scene

__all__ = ["FitResult", "fit", "read_target", "write_outputs", "scene_toml", "OUTPUT_NAMES"]

#: Files ``fem3d fit`` writes into its output folder.
OUTPUT_NAMES = ("fit.json", "fit.png", "fitted.toml")


@dataclass
class FitResult:
    """What a fit found.

    Attributes
    ----------
    params : dict of str -> float or list of float
        The fitted values (the best point the optimiser returned).
    start : dict
        The starting values.
    history : list of dict
        Per iteration (0: the start): ``iteration``, ``params``, ``loss``,
        ``gradient_norm`` (of the scaled variables), ``evaluations``.
    loss, gradient_norm : float
        At the fitted values.
    success : bool
    message : str
        scipy's message (or the simulation's error).
    iterations, evaluations : int
    scene : Scene
        The base scene with the fitted values.
    meshes : dict of int -> Path
        Bodies with a fitted per-tet field: the mesh holding it (a temporary file;
        :func:`write_outputs` copies it into the output folder).
    frames : list of int
        The step indices the loss compared.
    n_vertices : int
        Vertices compared per frame.
    """

    params: dict[str, Any]
    start: dict[str, Any]
    history: list[dict[str, Any]]
    loss: float
    gradient_norm: float
    success: bool
    message: str
    iterations: int
    evaluations: int
    scene: Scene
    frames: list[int] = field(default_factory=list)
    n_vertices: int = 0
    meshes: dict[int, Path] = field(default_factory=dict)


def read_target(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(steps (k,), times (k,), positions (k, n, 3))`` of a target: a ``fem3d run``
    folder's frames (VTU or OBJ) or a ``trajectory.npz`` (:mod:`fem3d.io.dataset`)."""
    p = Path(path)
    if p.is_file() and p.suffix == ".npz":
        try:
            with np.load(p, allow_pickle=False) as data:
                return (np.asarray(data["steps"], dtype=np.int64),
                        np.asarray(data["times"], dtype=np.float64),
                        np.asarray(data["positions"], dtype=np.float64))
        except (OSError, KeyError, ValueError) as exc:
            raise InputError(f"not a trajectory.npz ({exc})", path=p) from None
    if (p / "frames.usdc").exists() and not (p / "frames").is_dir():
        raise InputError("target: USD frames are not read back; run the target with "
                         "output.format = 'vtu'", path=p)
    steps, times, positions, _ = read_run_frames(p)
    return steps, times, positions


def _frames(spec: FitFile, steps: np.ndarray, where: str) -> list[int]:
    listed = [int(s) for s in steps if s >= 1]
    if spec.loss.frames is not None:
        missing = sorted(set(spec.loss.frames) - set(listed))
        if missing:
            raise InputError(f"loss.frames: step {missing[0]} is not among the target's frames "
                             f"({_short(listed)})", path=where)
        chosen = sorted(set(spec.loss.frames))
    else:
        chosen = listed[::spec.loss.every]
    if spec.steps is not None:
        chosen = [s for s in chosen if s <= spec.steps]
    if not chosen:
        raise InputError("target: no frame after step 0 to compare"
                         + (f" up to steps = {spec.steps}" if spec.steps else ""), path=where)
    return chosen


def _short(values: list[int]) -> str:
    return ", ".join(map(str, values[:6])) + (", ..." if len(values) > 6 else "")


def _vertices(spec: FitFile, scene: Scene, where: str) -> np.ndarray | None:
    if spec.loss.select is None:
        return None
    a = build_arrays(scene)
    if spec.loss.body >= len(scene.bodies):
        raise InputError(f"loss.body: {spec.loss.body}, but the scene has "
                         f"{len(scene.bodies)} bodies", path=where)
    vs = a.body_vertices[spec.loss.body]
    try:
        ids = select_vertices(scene, a.X[vs], spec.loss.select, "loss.select")
    except InputError as exc:
        raise InputError(exc.reason, path=where) from None
    return ids + vs.start


def _value_of(scene: Scene, key: str) -> Any:
    if is_field_key(key):  # the field's values, read from the body's mesh
        p = parse_param_key(key)
        name = scene.bodies[p.body].material.cell_fields[p.name]
        return _cell_field(scene, build_arrays(scene), p.body, p.name, name)
    d: Any = scene.model_dump(mode="json")
    for part in parse_key(key):
        d = d[part]
    return d


@dataclass
class _Param:
    key: str
    start: np.ndarray
    log: bool
    scale: float
    low: float
    high: float

    @property
    def size(self) -> int:
        return self.start.size

    def value(self, u: np.ndarray) -> np.ndarray:
        return self.start * np.exp(u) if self.log else self.start + self.scale * u

    def dvalue(self, u: np.ndarray) -> np.ndarray:
        return self.value(u) if self.log else np.full(u.shape, self.scale)

    def u_bounds(self) -> list[tuple[float | None, float | None]]:
        out = []
        for s in self.start:
            if self.log:
                out.append((math.log(self.low / s), None if math.isinf(self.high)
                            else math.log(self.high / s)))
            else:
                out.append((None if math.isinf(self.low) else (self.low - s) / self.scale,
                            None if math.isinf(self.high) else (self.high - s) / self.scale))
        return out

    def public(self, values: np.ndarray) -> float | list[float]:
        return [float(v) for v in values] if self.key.endswith(VECTOR_KEYS) or \
            is_field_key(self.key) else float(values[0])


def _params(spec: FitFile, scene: Scene, where: str) -> list[_Param]:
    out = []
    for i, p in enumerate(spec.params):
        try:
            current = _value_of(scene, p.key)
        except (KeyError, IndexError, InputError):
            raise InputError(f"params[{i}].key: {p.key}: no such field in the scene",
                             path=where) from None
        start = p.start if p.start is not None else current
        if start is None:
            raise InputError(f"params[{i}].start: the scene gives no {p.key}; give start",
                             path=where)
        if is_field_key(p.key):  # one number: every tet
            start = np.broadcast_to(np.asarray(start, dtype=np.float64), np.shape(current))
        start = np.atleast_1d(np.array(start, dtype=np.float64))
        low, high = p.bounds if p.bounds is not None else (-math.inf, math.inf)
        if np.any(start < low) or np.any(start > high):
            raise InputError(f"params[{i}].bounds: the start {start} is outside "
                             f"[{low:g}, {high:g}]", path=where)
        if p.is_log and np.any(start <= 0):
            raise InputError(f"params[{i}].log: needs a start > 0", path=where)
        mag = float(np.abs(start).max())
        scale = mag if mag > 0 else (high - low if math.isfinite(high - low) else 1.0)
        out.append(_Param(p.key, start, p.is_log, scale, low, high))
    return out


class FieldMeshes:
    """Scenes with fitted per-tet fields: each body with a field key gets its mesh written
    again (VTU, in a temporary folder) with the field's values as its cell data."""

    def __init__(self) -> None:
        self.folder: Path | None = None
        self.meshes: dict[int, Path] = {}  # body -> the mesh of the latest scene
        self.count = 0

    def scene(self, base: Scene, values: dict[str, Any]) -> Scene:
        """``base`` with ``values`` set (fields: through a mesh written for them)."""
        plain = {k: v for k, v in values.items() if not is_field_key(k)}
        scene = scene_with(base, plain)
        by_body: dict[int, dict[str, np.ndarray]] = {}
        for k, v in values.items():
            if is_field_key(k):
                p = parse_param_key(k)
                by_body.setdefault(p.body, {})[p.name] = np.asarray(v, dtype=np.float64)
        for body, fields in by_body.items():
            path = self._write(base, body, fields)
            scene = apply_overrides(scene, {f"bodies[{body}].mesh": str(path)})
        return scene

    def _write(self, base: Scene, body: int, fields: dict[str, np.ndarray]) -> Path:
        import tempfile

        import meshio

        if self.folder is None:
            self.folder = Path(tempfile.mkdtemp(prefix="fem3d-fit-"))
        mesh = meshio.read(base.path(base.bodies[body].mesh))
        kinds = ("tetra", element(base.bodies[body].element).cell_type)  # as _cell_field reads
        blocks = [j for j, c in enumerate(mesh.cells) if c.type in kinds]
        cells = [(mesh.cells[j].type, mesh.cells[j].data) for j in blocks]
        cuts = np.cumsum([len(mesh.cells[j].data) for j in blocks])[:-1]
        data = {n: [np.asarray(a[j]) for j in blocks] for n, a in mesh.cell_data.items()}
        names = base.bodies[body].material.cell_fields
        for param, v in fields.items():
            data[names[param]] = np.split(v, cuts)
        self.count += 1
        path = self.folder / f"body{body}_{self.count}.vtu"
        meshio.write(path, meshio.Mesh(mesh.points, cells, cell_data=data))
        old = self.meshes.get(body)
        self.meshes[body] = path
        if old is not None and old != path:
            old.unlink(missing_ok=True)
        return path


class _Objective:
    """The scaled loss and its gradient, cached by point; records what it evaluated."""

    def __init__(self, scene: Scene, loss: PositionLoss, params: list[_Param], steps: int,
                 checkpoint_every: int) -> None:
        self.scene, self.loss, self.params = scene, loss, params
        self.steps, self.k = steps, checkpoint_every
        self.cache: dict[bytes, tuple[float, np.ndarray, dict]] = {}
        self.norm: float | None = None
        self.evaluations = 0
        self.fields = FieldMeshes()

    def split(self, u: np.ndarray) -> list[np.ndarray]:
        return np.split(np.asarray(u, dtype=np.float64),
                        np.cumsum([p.size for p in self.params])[:-1])

    def values(self, u: np.ndarray) -> dict[str, Any]:
        return {p.key: p.public(p.value(x)) for p, x in zip(self.params, self.split(u),
                                                             strict=True)}

    def raw(self, u: np.ndarray) -> tuple[float, np.ndarray, dict]:
        """``(loss, dloss/du, values)`` unscaled by the start's loss."""
        key = np.asarray(u, dtype=np.float64).tobytes()
        if key not in self.cache:
            values = self.values(u)
            scene = self.fields.scene(self.scene, values)
            value, grads = trajectory_gradient(scene, self.loss, [p.key for p in self.params],
                                               steps=self.steps, checkpoint_every=self.k)
            self.evaluations += 1
            g = np.concatenate([np.atleast_1d(grads[p.key]) * p.dvalue(x)
                                for p, x in zip(self.params, self.split(u), strict=True)])
            self.cache = {key: (float(value), g, values)}  # one point: what minimize asks
            if self.norm is None:
                self.norm = float(value) if value > 0 else 1.0
        return self.cache[key]

    def __call__(self, u: np.ndarray) -> tuple[float, np.ndarray]:
        value, g, _ = self.raw(u)
        return value / self.norm, g / self.norm


def _record(obj: _Objective, u: np.ndarray, iteration: int) -> dict[str, Any]:
    value, g, values = obj.raw(u)
    return {"iteration": iteration, "params": values, "loss": value,
            "gradient_norm": float(np.linalg.norm(g / obj.norm)),
            "evaluations": obj.evaluations}


def progress_line(rec: dict[str, Any]) -> str:
    """One line: iteration, loss, gradient norm and the parameter values."""
    vals = "  ".join(f"{k}={_fmt(v)}" for k, v in rec["params"].items())
    return (f"fem3d fit: iter {rec['iteration']:3d}  loss {rec['loss']:.6e}  "
            f"|grad| {rec['gradient_norm']:.3e}  {vals}")


def _fmt(v: Any) -> str:
    if isinstance(v, list) and len(v) > 3:  # a per-tet field
        return f"[{min(v):.6g} .. {max(v):.6g}, {len(v)} tets]"
    return "[" + ", ".join(f"{x:.6g}" for x in v) + "]" if isinstance(v, list) else f"{v:.6g}"


def fit(spec: FitFile, *, where: str = "fit file",
        progress: Callable[[str], None] | None = None) -> FitResult:
    """Run the fit a fit file describes.

    Parameters
    ----------
    spec : FitFile
    where : str
        What error messages name (the fit file).
    progress : callable, optional
        Called with one line per iteration (:func:`progress_line`).

    Returns
    -------
    FitResult
        ``success`` False when the optimiser failed or a simulation could not go on (its
        message then says why; the history holds the iterations before it).

    Raises
    ------
    InputError
        A bad target, frames, vertices or parameter (``FILE: key: ...``).
    """
    scene = load_scene(spec.scene)
    if spec.set:
        scene = apply_overrides(scene, spec.set, source=f"{where}: set")
    if scene.pulls:
        raise InputError("scene: the base scene has scripted pulls, which fem3d.diff does not "
                         "differentiate yet (set pulls = [] in the fit file's [set])", path=where)
    refuse_mixed_elements(scene, "fem3d fit (the adjoint)")
    try:
        steps, times, positions = read_target(spec.target)
    except InputError as exc:
        raise InputError(f"target: {exc}", path=where) from None
    frames = _frames(spec, steps, where)
    dt = scene.simulation.dt
    for s, t in zip(steps, times, strict=True):
        if s in frames and math.isfinite(t) and abs(t - s * dt) > 1e-6 * max(1.0, abs(t)):
            raise InputError(f"target: its frame of step {s} is at t = {t:g}, the scene's "
                             f"simulation.dt = {dt:g} puts step {s} at {s * dt:g} (the "
                             "target was run with another dt)", path=where)
    n = build_arrays(scene).X.shape[0]
    if positions.shape[1] != n:
        raise InputError(f"target: its frames have {positions.shape[1]} points, the scene's "
                         f"simulation mesh {n} vertices (a skinned run's frames are its "
                         "skin: fit a run without a skin)", path=where)
    ids = _vertices(spec, scene, where)
    by_step = {int(s): positions[i] for i, s in enumerate(steps)}
    loss = PositionLoss({s: by_step[s] if ids is None else by_step[s][ids] for s in frames},
                        vertices=ids, weight=spec.loss.weight)
    params = _params(spec, scene, where)
    obj = _Objective(scene, loss, params, spec.steps or max(frames),
                     spec.optimizer.checkpoint_every)
    u0 = np.zeros(sum(p.size for p in params))
    try:
        history = [_record(obj, u0, 0)]
    except ParameterError as exc:  # what fem3d.diff cannot differentiate (pulls, ...)
        raise InputError(f"scene: {exc}", path=where) from None
    if progress:
        progress(progress_line(history[0]))

    def callback(xk, *_):
        history.append(_record(obj, np.asarray(xk), len(history)))
        if progress:
            progress(progress_line(history[-1]))

    opt = spec.optimizer
    options: dict[str, Any] = {"maxiter": opt.max_iterations}
    if opt.method == "L-BFGS-B":
        options.update(ftol=opt.ftol, gtol=opt.gtol)
    elif opt.method == "TNC":
        options.update(ftol=opt.ftol, gtol=opt.gtol)
    else:
        options.update(ftol=opt.ftol)
    bounds = [b for p in params for b in p.u_bounds()]
    try:
        res = scipy.optimize.minimize(obj, u0, jac=True, method=opt.method, bounds=bounds,
                                      callback=callback, options=options)
        u, success, message = np.asarray(res.x), bool(res.success), str(res.message)
        iterations = int(getattr(res, "nit", len(history) - 1))
    except SimulationError as exc:
        best = min(history, key=lambda r: r["loss"])
        u = np.concatenate([_to_u(p, best["params"][p.key]) for p in params])
        success, message, iterations = False, f"simulation failed: {exc}", len(history) - 1
    final = _record(obj, u, iterations)
    values = final["params"]
    return FitResult(params=values, start=history[0]["params"], history=history,
                     loss=final["loss"], gradient_norm=final["gradient_norm"], success=success,
                     message=message, iterations=iterations, evaluations=obj.evaluations,
                     scene=obj.fields.scene(scene, values), frames=frames,
                     n_vertices=n if ids is None else int(ids.size),
                     meshes=dict(obj.fields.meshes))


def _to_u(p: _Param, value: Any) -> np.ndarray:
    v = np.atleast_1d(np.asarray(value, dtype=np.float64))
    return np.log(v / p.start) if p.log else (v - p.start) / p.scale


# ------------------------------------------------------------------------------ outputs
def _toml_key(k: Any) -> str:
    k = str(k)
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else json.dumps(k)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v if x is not None) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}"
                               for k, x in v.items() if x is not None) + "}"
    raise TypeError(f"no TOML for {type(v).__name__}")


def scene_toml(scene: Scene, header: str = "") -> str:
    """``scene`` as a scene file (every path absolute; ``None`` values left out, so they
    take their defaults)."""
    d = scene.to_dict()
    d.pop("base_dir", None)
    d.pop("source", None)
    lines = [f"# {line}" for line in header.splitlines()]
    tables = []
    for k, v in d.items():
        if v is None:
            continue
        if isinstance(v, dict):
            tables.append(f"\n[{k}]")
            tables += [f"{_toml_key(a)} = {_toml_value(b)}" for a, b in v.items()
                       if b is not None]
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for item in v:
                tables.append(f"\n[[{k}]]")
                tables += [f"{_toml_key(a)} = {_toml_value(b)}" for a, b in item.items()
                           if b is not None]
        elif isinstance(v, list) and not v:
            continue
        else:
            lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
    return "\n".join(lines + tables) + "\n"


def _plot(result: FitResult, path: Path) -> None:
    # imported here: pyplot only after choosing the Agg back end (headless), and slow to import
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    it = [r["iteration"] for r in result.history]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8))
    a1.semilogy(it, [max(r["loss"], 1e-300) for r in result.history], "o-")
    a1.set_xlabel("iteration")
    a1.set_ylabel("loss")
    a1.set_title("loss")
    for key in result.params:
        final = np.atleast_1d(np.asarray(result.params[key], dtype=np.float64))
        path_k = np.array([np.atleast_1d(r["params"][key]) for r in result.history])
        if final.size > 3:  # a per-tet field: its median ratio to the fitted values
            ratio = path_k / np.where(final != 0, final, 1.0)
            a2.plot(it, np.median(ratio, axis=1), "o-", label=f"{key} (median of {final.size})")
            continue
        for c in range(final.size):
            ref = final[c] if final[c] != 0 else 1.0
            label = key if final.size == 1 else f"{key}[{c}]"
            a2.plot(it, path_k[:, c] / ref, "o-", label=label)
    a2.axhline(1.0, color="0.6", lw=0.8)
    a2.set_xlabel("iteration")
    a2.set_ylabel("value / fitted value")
    a2.set_title("parameters")
    a2.legend(fontsize=7)
    fig.tight_layout()
    try:
        atomic_write(path, lambda p: fig.savefig(p, format="png", dpi=110))
    finally:
        plt.close(fig)


def write_outputs(result: FitResult, spec: FitFile, out: Path, *,
                  fit_file: str | None = None) -> list[Path]:
    """Write ``fit.json``, ``fit.png`` and ``fitted.toml`` into ``out`` (atomically)."""
    out.mkdir(parents=True, exist_ok=True)
    doc = {
        "name": spec.name, "fit_file": fit_file, "scene": spec.scene, "target": spec.target,
        "frames": result.frames, "vertices_per_frame": result.n_vertices,
        "params": result.params, "start": result.start, "loss": result.loss,
        "gradient_norm": result.gradient_norm,
        "result": {"success": result.success, "message": result.message,
                   "iterations": result.iterations, "evaluations": result.evaluations,
                   "method": spec.optimizer.method},
        "history": result.history,
    }
    written = [atomic_write(out / "fit.json", json.dumps(doc, indent=2, allow_nan=True) + "\n")]
    _plot(result, out / "fit.png")
    written.append(out / "fit.png")
    header = (f"fitted by `fem3d fit` ({spec.name}): "
              + ", ".join(f"{k} = {_fmt(v)}" for k, v in result.params.items())
              + f"\nfrom {spec.scene}")
    scene = result.scene
    for body, mesh in result.meshes.items():  # the fitted fields' meshes, beside fitted.toml
        target = out / f"fitted_body{body}.vtu"
        atomic_write(target, mesh.read_bytes())
        written.append(target)
        scene = apply_overrides(scene, {f"bodies[{body}].mesh": str(target.resolve())})
    written.append(atomic_write(out / "fitted.toml", scene_toml(scene, header)))
    return written
