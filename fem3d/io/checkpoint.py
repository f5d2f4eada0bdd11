"""Checkpoints: ``.npz`` files of arrays and JSON metadata; the run checkpoints of ``fem3d run``
/ ``fem3d resume``, which hold everything needed to continue a run.

:func:`save_checkpoint` / :func:`load_checkpoint` write and read one ``.npz`` (atomically)
holding arrays bit for bit and every other item in one JSON document stored inside the file
(the array ``__fem3d_metadata__``, with ``format`` and ``version``).

A run checkpoint is one such file (``DIR/checkpoint.npz``, :func:`save_run_checkpoint`). It
holds

* the simulation state of :meth:`fem3d.simulation.Simulation.snapshot`: positions ``q`` and
  velocities ``v`` ``(n, 3) float64``, time, step index, the scripted pulls' state (which
  are attached, the springs) and the energy put in so far (the linearly-implicit runaway
  bound), and the scheme's history (``history_<name>``, whatever the scheme saves through
  :meth:`fem3d.solve.schemes.base.Scheme.save_history`: BDF2's previous state, Newmark's
  acceleration; none for one-step schemes and in checkpoints written before 0.3; empty
  arrays in those written before the schemes were objects);
* ``settings``: ``scene`` - the whole scene (:meth:`fem3d.scene.spec.Scene.to_dict`: every path
  absolute, the target step count in ``simulation.steps``), so ``fem3d resume DIR`` needs
  nothing else - and the run's own options: ``kernels`` and ``solver`` (the resolved back
  ends), ``checkpoint_every``, ``preview``;
* the output bookkeeping: the energy rows so far ``(n_rows, 4)`` (the exact values written
  to ``energy.csv``), the frames written (step, time, relative path) and the frame counter;
* a SHA-256 digest of the rest mesh, so a resume refuses a mesh file changed in between.

Floats are stored exactly (arrays bit for bit, scalars through JSON, whose ``repr`` round
trip is exact), so a resumed run computes bit for bit what an uninterrupted one computes
(same kernels, same solver back end).
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fem3d.errors import InputError, ParameterError
from fem3d.io.files import PathLike, atomic_write, check_input_file

__all__ = ["CHECKPOINT_NAME", "RunCheckpoint", "save_run_checkpoint", "load_run_checkpoint",
           "restore_run_checkpoint",
           "mesh_digest", "save_checkpoint", "load_checkpoint"]

# --------------------------------------------------------------------------------------
# .npz with JSON metadata

_META_KEY = "__fem3d_metadata__"
_FORMAT = "fem3d-checkpoint"
_VERSION = 1


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return value


def save_checkpoint(path: PathLike, **items: Any) -> Path:
    """Save arrays and metadata atomically into one ``.npz``.

    Parameters
    ----------
    path : str or PathLike
        Target file (used as given; no ``.npz`` is appended).
    **items
        ``numpy.ndarray`` values are stored as arrays (bit-exact, any numeric dtype; object
        arrays are refused); everything else (numbers, strings, bools, None, lists and
        dicts of those, NumPy scalars) goes into a JSON document stored inside the file.

    Returns
    -------
    Path
    """
    if _META_KEY in items:
        raise ValueError(f"{_META_KEY!r} is reserved")
    arrays: dict[str, np.ndarray] = {}
    meta: dict[str, Any] = {}
    for key, value in items.items():
        if isinstance(value, np.ndarray):
            if value.dtype.hasobject:
                raise ValueError(f"checkpoint item {key!r}: object arrays are not supported")
            arrays[key] = value
        else:
            meta[key] = _jsonable(value)
    try:
        doc = json.dumps({"format": _FORMAT, "version": _VERSION, "metadata": meta}, allow_nan=True)
    except TypeError as exc:
        raise ValueError(f"checkpoint metadata is not JSON-serializable: {exc}") from None
    arrays[_META_KEY] = np.frombuffer(doc.encode("utf-8"), dtype=np.uint8)

    def _write(p: Path) -> None:
        with open(p, "wb") as fh:
            np.savez(fh, **arrays)

    return atomic_write(path, _write)


def load_checkpoint(path: PathLike) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Returns
    -------
    dict
        Arrays and metadata under the names they were saved with.

    Raises
    ------
    InputError
        Missing file, not a fem3d checkpoint, or unreadable.
    """
    path = check_input_file(path, "checkpoint")
    try:
        with np.load(path, allow_pickle=False) as z:
            if _META_KEY not in z.files:
                raise InputError("not a fem3d checkpoint (no metadata)", path=path)
            doc = json.loads(bytes(z[_META_KEY]).decode("utf-8"))
            out: dict[str, Any] = {k: z[k] for k in z.files if k != _META_KEY}
    except InputError:
        raise
    except (zipfile.BadZipFile, EOFError, ValueError, KeyError):
        # np.load's own words ("File is not a zip file", pickles, ...) say nothing to a user
        raise InputError("not a readable checkpoint: not a complete .npz archive (truncated, "
                         "or another kind of file)", path=path) from None
    except OSError as exc:
        raise InputError(f"cannot read checkpoint: {exc.strerror or exc}", path=path) from None
    if not isinstance(doc, dict) or doc.get("format") != _FORMAT:
        raise InputError("not a fem3d checkpoint (bad metadata)", path=path)
    if doc.get("version") != _VERSION:
        raise InputError(f"unsupported checkpoint version {doc.get('version')!r}", path=path)
    out.update(doc.get("metadata", {}))
    return out

# --------------------------------------------------------------------------------------
# run checkpoints

#: File name of the checkpoint in a run's output folder.
CHECKPOINT_NAME = "checkpoint.npz"

_KIND = "fem3d-run"
_SNAPSHOT_SCALARS = ("t", "step", "injected")
_SNAPSHOT_ARRAYS = ("q", "v", "pull_vertices", "pull_targets", "pull_k", "preconditioner",
                    "script_active", "contact", "pattern_keys")
#: Snapshot arrays that older checkpoints do not have (restored as empty).
_SNAPSHOT_OPTIONAL = ("preconditioner", "contact", "pattern_keys")
#: The prefix of the scheme's history arrays in a snapshot (``history_<name>``), saved as
#: they come, whatever their names.
_HISTORY = "history_"


def mesh_digest(X: np.ndarray, T) -> str:
    """SHA-256 of the rest positions ``X (n, 3) float64`` and elements ``T (m, k) int64``
    (or a sequence of them: the element blocks of bodies on several elements)."""
    h = hashlib.sha256()
    Ts = list(T) if isinstance(T, (list, tuple)) else [T]
    for a, dtype in ((X, np.float64), *((t, np.int64) for t in Ts)):
        a = np.ascontiguousarray(a, dtype=dtype)
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


@dataclass
class RunCheckpoint:
    """What ``fem3d resume`` needs.

    Attributes
    ----------
    settings : dict
        JSON-able options of the run (see :mod:`fem3d.app.cli`).
    snapshot : dict
        :meth:`fem3d.simulation.Simulation.snapshot`.
    energy : (n_rows, 4) float64
        Rows ``t, kinetic, potential, total`` logged so far.
    frames : dict[int, tuple[float, str]]
        Step index -> (time, path relative to the output folder) of each frame written.
    frame_count : int
        Frames written so far.
    mesh_digest : str
        :func:`mesh_digest` of the rest mesh.
    partition : (m,) int32 or None
        The rank of each tet of a run on ranks (``mpiexec``; None in one process): a
        resume on as many ranks takes it rather than partitioning anew, so that every sum
        runs in the same order as in the uninterrupted run whichever partitioner cut it
        (PT-Scotch, the fallback without pymetis, cuts differently each run:
        docs/parallel.md).
    """

    settings: dict[str, Any]
    snapshot: dict[str, Any]
    energy: np.ndarray
    frames: dict[int, tuple[float, str]] = field(default_factory=dict)
    frame_count: int = 0
    mesh_digest: str = ""
    partition: np.ndarray | None = None

    @property
    def step(self) -> int:
        """Step index of the saved state."""
        return int(self.snapshot["step"])


def save_run_checkpoint(path: PathLike, ckpt: RunCheckpoint) -> Path:
    """Write ``ckpt`` atomically to ``path`` (a ``.npz``)."""
    snap = ckpt.snapshot
    steps = sorted(ckpt.frames)
    arrays = {f"state_{k}": np.asarray(snap[k]) for k in _SNAPSHOT_ARRAYS}
    arrays.update({f"state_{k}": np.asarray(a) for k, a in snap.items()
                   if k.startswith(_HISTORY)})
    scalars = {k: snap[k] for k in _SNAPSHOT_SCALARS}
    if ckpt.partition is not None:
        arrays["partition"] = np.asarray(ckpt.partition, dtype=np.int32)
    return save_checkpoint(
        path,
        kind=_KIND,
        settings=ckpt.settings,
        state=scalars,
        energy=_energy_rows(ckpt.energy),
        frame_steps=np.asarray(steps, dtype=np.int64),
        frame_times=np.asarray([ckpt.frames[s][0] for s in steps], dtype=np.float64),
        frame_paths=[ckpt.frames[s][1] for s in steps],
        frame_count=int(ckpt.frame_count),
        mesh_digest=ckpt.mesh_digest,
        **arrays,
    )


def load_run_checkpoint(path: PathLike) -> RunCheckpoint:
    """Read a checkpoint written by :func:`save_run_checkpoint`.

    Raises
    ------
    InputError
        Missing, unreadable, not a run checkpoint, or inconsistent (naming the file).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("no checkpoint here (run with --checkpoint-every N, or interrupt "
                         "a run with Ctrl-C, to get one)", path=path)
    d = load_checkpoint(path)
    if d.get("kind") != _KIND:
        raise InputError("not a fem3d run checkpoint", path=path)
    try:
        snap: dict[str, Any] = dict(d["state"])
        for k in _SNAPSHOT_ARRAYS:
            if k in _SNAPSHOT_OPTIONAL and f"state_{k}" not in d:
                continue  # checkpoints written before that state existed
            snap[k] = np.array(d[f"state_{k}"])
        snap.update({k[len("state_"):]: np.array(a) for k, a in d.items()
                     if k.startswith(f"state_{_HISTORY}")})
        energy = np.asarray(d["energy"], dtype=np.float64)
        steps = [int(s) for s in np.asarray(d["frame_steps"]).reshape(-1)]
        times = [float(t) for t in np.asarray(d["frame_times"]).reshape(-1)]
        paths = [str(p) for p in d["frame_paths"]]
        settings = dict(d["settings"])
        ckpt = RunCheckpoint(
            settings=settings, snapshot=snap, energy=energy,
            frames={s: (t, p) for s, t, p in zip(steps, times, paths, strict=True)},
            frame_count=int(d["frame_count"]), mesh_digest=str(d["mesh_digest"]),
            partition=np.array(d["partition"]) if "partition" in d else None,
        )
    except KeyError as exc:
        raise InputError(f"incomplete run checkpoint: it has no saved {exc.args[0]!r}",
                         path=path) from None
    except (TypeError, ValueError):
        raise InputError("incomplete run checkpoint: a saved field has the wrong type or "
                         "shape", path=path) from None
    q = snap["q"]
    if q.ndim != 2 or q.shape[1] != 3 or snap["v"].shape != q.shape:
        raise InputError(f"checkpoint state has bad shapes {q.shape}, {snap['v'].shape}",
                         path=path)
    finite = np.isfinite(energy[..., :4]).all()  # (the split of inherited rows is nan)
    if not (np.isfinite(q).all() and np.isfinite(snap["v"]).all() and finite):
        raise InputError("checkpoint holds non-finite values", path=path)
    if energy.ndim != 2 or energy.shape[1] not in (4, 7) or energy.shape[0] != ckpt.step + 1:
        raise InputError(f"checkpoint energy history has shape {energy.shape}, expected "
                         f"({ckpt.step + 1}, 4) or ({ckpt.step + 1}, 7)", path=path)
    return ckpt


def restore_run_checkpoint(sim: Any, ckpt: RunCheckpoint, digest: str, mesh_path: PathLike,
                           out: PathLike) -> None:
    """Set ``sim`` (a :class:`~fem3d.simulation.Simulation`) to the state of ``ckpt``, the
    checkpoint in the run folder ``out`` (``fem3d resume``, in one process or on ranks).

    Parameters
    ----------
    sim : Simulation
    ckpt : RunCheckpoint
    digest : str
        :func:`mesh_digest` of the whole mesh the scene gives now.
    mesh_path : path
        The mesh file the error names.
    out : path
        The run folder.

    Raises
    ------
    InputError
        A mesh other than the checkpoint's, or a state that does not fit it.
    """
    if digest != ckpt.mesh_digest:
        raise InputError("the mesh differs from the one the checkpoint was made with",
                         path=mesh_path)
    try:
        sim.restore(ckpt.snapshot)
    except (ParameterError, KeyError) as exc:
        raise InputError(f"bad checkpoint state: {exc}",
                         path=Path(out) / CHECKPOINT_NAME) from None


def _energy_rows(energy: np.ndarray) -> np.ndarray:
    """The energy rows as saved: ``(n, 4)`` (before the split) or ``(n, 7)`` (with strain,
    gravity and pull; ``nan`` in the split of rows inherited from an older run)."""
    a = np.asarray(energy, dtype=np.float64)
    return a if a.ndim == 2 and a.shape[1] == 7 else a.reshape(-1, 4)
