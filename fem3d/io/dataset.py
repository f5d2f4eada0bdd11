"""Sweep datasets: each case's trajectory in one ``.npz``, and loaders.

A sweep with a ``[dataset]`` table (``dtype = "float32"`` or ``"float64"``) writes, per
complete case, ``DIR/cases/<id>/trajectory.npz`` (read with :func:`load_case`; the whole
sweep with :func:`load_sweep`). Layout (``numpy.load(path)`` keys, no pickles):

=============  ============================  ====================================================
key            shape, dtype                  content
=============  ============================  ====================================================
``positions``  ``(n_frames, n_points, 3)``   vertex positions of every frame that ``fem3d run``
               float32 or float64            wrote (the scene's ``output.every``), the dtype asked
``times``      ``(n_frames,)`` float64       simulated time of each frame
``steps``      ``(n_frames,)`` int64         step index of each frame
``rest``       ``(n_points, 3)`` float64     positions at step 0 (the mesh, stored once)
``faces``      ``(n_faces, 3)`` int32        triangles of the frames (0-based, into the points)
``meta``       ``()`` str (JSON)             ``format`` ("fem3d-trajectory"), ``version``,
                                             ``id``, ``params`` (the case's overrides),
                                             ``dtype``, ``points`` (what the points are)
=============  ============================  ====================================================

The points are those of the frames ``fem3d run`` writes: the display (skin) mesh, or the
simulation mesh's vertices for a body without a skin. The frames are the positions in
float64 (exactly what the run computed); ``positions`` holds them cast to the dtype asked.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import re
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import meshio
import numpy as np

from fem3d.errors import InputError
from fem3d.io.files import atomic_write

__all__ = [
    "FORMAT",
    "VERSION",
    "CaseData",
    "SweepData",
    "read_run_frames",
    "write_trajectory",
    "write_case_trajectory",
    "load_case",
    "load_sweep",
]

FORMAT = "fem3d-trajectory"
VERSION = 1
TRAJECTORY_NAME = "trajectory.npz"
_FRAME_NUMBER = re.compile(r"_(\d+)$")


def read_run_frames(run_dir: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The frames a ``fem3d run`` wrote into ``run_dir``.

    Parameters
    ----------
    run_dir : str or Path
        Output folder of a run: ``frames.pvd`` + ``frames/*.vtu``, or ``frames/*.obj``
        (times then from ``energy.csv``, one row per step).

    Returns
    -------
    steps : (n_frames,) int64
    times : (n_frames,) float64
    positions : (n_frames, n_points, 3) float64
    faces : (n_faces, 3) int64

    Raises
    ------
    InputError
        No frames, or frames of different sizes.
    """
    run_dir = Path(run_dir)
    entries: list[tuple[int, float | None, Path]] = []
    pvd = run_dir / "frames.pvd"
    if pvd.exists():
        for ds in ET.parse(pvd).getroot().iter("DataSet"):
            if ds.attrib.get("part", "0") != "0":
                continue  # a contact scene's obstacles (part 1, 2, ...), not the bodies
            f = run_dir / ds.attrib["file"]
            m = _FRAME_NUMBER.search(f.stem)
            if m is not None:
                entries.append((int(m.group(1)), float(ds.attrib["timestep"]), f))
    else:
        for f in (run_dir / "frames").glob("frame_*.*"):
            m = _FRAME_NUMBER.search(f.stem)
            if m is not None and not f.name.startswith("."):
                entries.append((int(m.group(1)), None, f))
    if not entries:
        raise InputError("no frames to read", path=run_dir)
    entries.sort(key=lambda e: e[0])
    if any(t is None for _, t, _ in entries):
        t_of = _energy_times(run_dir / "energy.csv")
        entries = [(s, t_of[s] if s < len(t_of) else float("nan"), f) for s, _, f in entries]
    frames, faces = [], None
    for _, _, f in entries:
        mesh = meshio.read(f)
        frames.append(np.asarray(mesh.points, dtype=np.float64))
        if faces is None:
            faces = np.asarray(mesh.get_cells_type("triangle"), dtype=np.int64)
        if frames[-1].shape != frames[0].shape:
            raise InputError(f"frame has {frames[-1].shape[0]} points, the first "
                             f"{frames[0].shape[0]}", path=f)
    steps = np.array([s for s, _, _ in entries], dtype=np.int64)
    times = np.array([t for _, t, _ in entries], dtype=np.float64)
    return steps, times, np.stack(frames), faces


def _energy_times(path: Path) -> list[float]:
    with open(path, newline="", encoding="utf-8") as fh:
        return [float(row["t"]) for row in csv.DictReader(fh)]


def write_trajectory(
    path: str | Path,
    *,
    positions: np.ndarray,
    times: np.ndarray,
    steps: np.ndarray,
    faces: np.ndarray,
    rest: np.ndarray | None = None,
    dtype: str = "float32",
    meta: dict[str, Any] | None = None,
) -> Path:
    """Write one trajectory ``.npz`` (layout in the module docstring), atomically.

    Parameters
    ----------
    positions : (n_frames, n_points, 3) float
        Stored as ``dtype``.
    times : (n_frames,) float
    steps : (n_frames,) int
    faces : (n_faces, 3) int
    rest : (n_points, 3) float, optional
        Default: ``positions[0]`` (float64).
    dtype : {"float32", "float64"}
    meta : dict, optional
        Extra JSON-safe entries of ``meta``.
    """
    if dtype not in ("float32", "float64"):
        raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
    P = np.asarray(positions, dtype=np.float64)
    if P.ndim != 3 or P.shape[2] != 3 or P.shape[0] == 0:
        raise ValueError(f"positions must have shape (n_frames >= 1, n_points, 3), got {P.shape}")
    info = {"format": FORMAT, "version": VERSION, "dtype": dtype, **(meta or {})}
    arrays = {
        "positions": P.astype(dtype),
        "times": np.asarray(times, dtype=np.float64).reshape(P.shape[0]),
        "steps": np.asarray(steps, dtype=np.int64).reshape(P.shape[0]),
        "rest": np.asarray(P[0] if rest is None else rest, dtype=np.float64).reshape(P.shape[1:]),
        "faces": np.asarray(faces, dtype=np.int32).reshape(-1, 3),
        "meta": np.array(json.dumps(info, allow_nan=False, default=str)),
    }
    return atomic_write(Path(path), lambda p: np.savez_compressed(p, **arrays))


def write_case_trajectory(case_dir: str | Path, *, dtype: str = "float32",
                          meta: dict[str, Any] | None = None) -> Path:
    """Pack the frames of the run in ``case_dir`` into ``case_dir/trajectory.npz``."""
    case_dir = Path(case_dir)
    steps, times, positions, faces = read_run_frames(case_dir)
    info = dict(meta or {})
    info.setdefault("points", "the frames of fem3d run (display mesh, or simulation mesh "
                              "vertices without a skin)")
    return write_trajectory(case_dir / TRAJECTORY_NAME, positions=positions, times=times,
                            steps=steps, faces=faces, dtype=dtype, meta=info)


@dataclasses.dataclass(frozen=True)
class CaseData:
    """One case's trajectory (see the module docstring for the arrays).

    Attributes
    ----------
    path : Path
        The ``trajectory.npz``.
    positions : (n_frames, n_points, 3) float32 or float64
    times : (n_frames,) float64
    steps : (n_frames,) int64
    rest : (n_points, 3) float64
    faces : (n_faces, 3) int32
    meta : dict
    summary : dict or None
        The case's ``summary.json`` (status, energies, ...) when beside the file.
    """

    path: Path
    positions: np.ndarray
    times: np.ndarray
    steps: np.ndarray
    rest: np.ndarray
    faces: np.ndarray
    meta: dict[str, Any]
    summary: dict[str, Any] | None = None

    @property
    def id(self) -> str:
        """The case id (its folder name)."""
        return str(self.meta.get("id", self.path.parent.name))

    @property
    def params(self) -> dict[str, Any]:
        """The case's overrides, key path -> value."""
        return dict(self.meta.get("params", {}))

    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    def displacements(self) -> np.ndarray:
        """``positions - rest``, ``(n_frames, n_points, 3)`` in the stored dtype."""
        return self.positions - self.rest.astype(self.positions.dtype)


def load_case(path: str | Path) -> CaseData:
    """Load one case: its folder (``DIR/cases/<id>``) or its ``trajectory.npz``.

    Raises
    ------
    InputError
        No trajectory there, or not a fem3d trajectory file.
    """
    p = Path(path)
    if p.is_dir():
        p = p / TRAJECTORY_NAME
    try:
        with np.load(p, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise InputError("no trajectory (was the sweep run with a [dataset] table?)",
                         path=p) from None
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read the trajectory: {exc}", path=p) from None
    missing = {"positions", "times", "steps", "rest", "faces", "meta"} - set(data)
    if missing:
        raise InputError(f"not a fem3d trajectory: no {', '.join(sorted(missing))}", path=p)
    meta = json.loads(str(data["meta"]))
    if meta.get("format") != FORMAT:
        raise InputError(f"not a fem3d trajectory (format {meta.get('format')!r})", path=p)
    summary = None
    with_summary = p.parent / "summary.json"
    if with_summary.exists():
        summary = json.loads(with_summary.read_text(encoding="utf-8"))
    return CaseData(path=p, positions=data["positions"], times=data["times"],
                    steps=data["steps"], rest=data["rest"], faces=data["faces"], meta=meta,
                    summary=summary)


@dataclasses.dataclass(frozen=True)
class SweepData:
    """The trajectories of a sweep, in sweep order.

    Attributes
    ----------
    keys : list of str
        The swept key paths.
    cases : list of CaseData
        The ok cases with a trajectory (one per distinct id).
    """

    keys: list[str]
    cases: list[CaseData]

    def __len__(self) -> int:
        return len(self.cases)

    def __iter__(self) -> Iterator[CaseData]:
        return iter(self.cases)

    def params(self, keys: Sequence[str] | None = None) -> np.ndarray:
        """``(n_cases, n_keys)`` float64 matrix of numeric parameters (``keys``, default
        :attr:`keys`); NaN where a case does not set a key."""
        keys = list(self.keys if keys is None else keys)
        return np.array([[float(c.params.get(k, np.nan)) for k in keys] for c in self.cases],
                        dtype=np.float64).reshape(len(self.cases), len(keys))

    def positions(self) -> np.ndarray:
        """``(n_cases, n_frames, n_points, 3)``: every case's positions stacked (the cases
        must have the same frame count and mesh)."""
        shapes = {c.positions.shape for c in self.cases}
        if len(shapes) > 1:
            raise ValueError(f"the cases' trajectories differ in shape: {sorted(shapes)}")
        return np.stack([c.positions for c in self.cases])


def load_sweep(path: str | Path, *, cases: Sequence[str] | None = None) -> SweepData:
    """Load the trajectories of a sweep's output folder (written by ``fem3d sweep`` with a
    ``[dataset]`` table): the ok cases in the order of ``DIR/sweep.json``.

    Parameters
    ----------
    path : str or Path
        The sweep's ``--out`` folder.
    cases : sequence of str, optional
        Only these case ids.

    Raises
    ------
    InputError
        Not a sweep folder.
    """
    root = Path(path)
    try:
        plan = json.loads((root / "sweep.json").read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("not a sweep output folder (no sweep.json)", path=root) from None
    wanted = None if cases is None else set(cases)
    seen: set[str] = set()
    out: list[CaseData] = []
    for entry in plan["cases"]:
        cid = entry["id"]
        if cid in seen or (wanted is not None and cid not in wanted):
            continue
        seen.add(cid)
        folder = root / "cases" / cid
        try:
            summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if summary.get("status") == "ok" and (folder / TRAJECTORY_NAME).exists():
            out.append(load_case(folder))
    return SweepData(keys=list(plan.get("keys", [])), cases=out)
