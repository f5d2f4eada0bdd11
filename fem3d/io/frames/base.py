"""What every output format is and what every frame writer does.

- :class:`FrameFormat` - one output format: its name (``output.format``, ``--format``), the
  suffix of its files, the extra it needs, whether its frames are read back, and ``open``,
  which makes its writer.
- :class:`FrameSink` - the writer's protocol: ``write`` appends a frame, ``flush`` puts
  everything on disk, ``close`` ends, ``restore`` continues a run from a checkpoint's list,
  ``read_frames`` reads frames back.
- :func:`check_faces`, :func:`check_cells`, :func:`check_vertices` - the input checks every
  writer makes.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from fem3d.errors import SimulationError
from fem3d.io import extras

__all__ = ["Bodies", "FrameFormat", "FrameSink", "check_cells", "check_faces", "check_vertices"]

#: Each body's part of the display mesh: ``(name, vertex slice, face slice)``.
Bodies = Sequence[tuple[str, slice, slice]]


def check_faces(faces: np.ndarray) -> np.ndarray:
    """``faces`` as a contiguous int64 ``(n_faces, 3)`` array.

    Raises
    ------
    ValueError
        Not an integer ``(f, 3)`` array, or a negative index.
    """
    F = np.asarray(faces)
    if F.ndim != 2 or F.shape[1] != 3 or not np.issubdtype(F.dtype, np.integer):
        raise ValueError(f"faces must be an integer (f, 3) array, got {F.dtype} {F.shape}")
    if F.size and F.min() < 0:
        raise ValueError("faces hold a negative vertex index")
    return np.ascontiguousarray(F, dtype=np.int64)


def check_cells(cells: np.ndarray) -> np.ndarray:
    """``cells`` as a contiguous int64 ``(n_cells, k)`` array, ``k >= 1`` nodes per cell.

    Raises
    ------
    ValueError
        Not a 2-D integer array, or a negative index.
    """
    C = np.asarray(cells)
    if C.ndim != 2 or C.shape[1] < 1 or not np.issubdtype(C.dtype, np.integer):
        raise ValueError(f"cells must be an integer (m, k) array, got {C.dtype} {C.shape}")
    if C.size and C.min() < 0:
        raise ValueError("cells hold a negative vertex index")
    return np.ascontiguousarray(C, dtype=np.int64)


def check_vertices(V: np.ndarray, faces: np.ndarray, step: int | None) -> np.ndarray:
    """``V`` as float64 ``(k, 3)`` positions that ``faces`` may index, all finite.

    Raises
    ------
    ValueError
        Wrong shape, or faces referencing a vertex ``V`` lacks.
    SimulationError
        A non-finite coordinate (of step ``step``).
    """
    V = np.asarray(V, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3:
        raise ValueError(f"vertices must have shape (k, 3), got {V.shape}")
    if faces.size and faces.max() >= V.shape[0]:
        raise ValueError(f"faces reference vertex {int(faces.max())} but only {V.shape[0]} given")
    finite = np.isfinite(V).all(axis=1)
    if not finite.all():
        raise SimulationError(
            f"refusing to write non-finite coordinates (vertex {int(np.argmin(finite))})",
            step=step,
        )
    return V


class FrameSink(Protocol):
    """A frame writer as the run loop (:mod:`fem3d.io.framequeue`) uses it.

    Attributes
    ----------
    fmt : str
        The format's name.
    faces : (n_faces, 3) int64
        Triangles of every frame.
    frames : dict[int, tuple[float, str]]
        step index -> (time, path relative to the output folder) of every frame written
        (what a checkpoint stores).
    """

    fmt: str
    faces: np.ndarray
    frames: dict[int, tuple[float, str]]

    def write(self, step_index: int, t: float, V: np.ndarray,
              point_data: Mapping[str, np.ndarray] | None = None) -> Path:
        """Append the frame of step ``step_index`` (time ``t``, positions ``(n, 3)``)."""

    def flush(self) -> None:
        """Put every frame written so far on disk (called before each checkpoint)."""

    def close(self) -> None:
        """Flush; the run is over."""

    def restore(self, frames: Mapping[int, tuple[float, str]], step: int) -> None:
        """Continue a run: the frames up to ``step`` (a checkpoint's list) are kept, later
        ones removed."""

    def read_frames(self, stride: int = 1) -> Iterator[tuple[int, np.ndarray]]:
        """``(step, (n, 3) positions)`` of every ``stride``-th frame, read back from disk."""


#: ``open(out_dir, faces, bodies=..., dt=..., obstacles=...)`` of a format.
Opener = Callable[..., FrameSink]


@dataclass(frozen=True)
class FrameFormat:
    """One output format of ``fem3d run`` (one module of :mod:`fem3d.io.frames` each).

    Parameters
    ----------
    name : str
        The choice of ``output.format`` and ``--format``.
    suffix : str
        Suffix of its frame files (``".vtu"``).
    summary : str
        What it writes, in a few words (the CLI's help).
    open : callable
        ``open(out_dir, faces, *, bodies, dt, obstacles) -> FrameSink``: the writer of a
        run's frames into ``out_dir`` (``faces``: the display mesh's ``(n_faces, 3)``
        triangles; ``bodies``: each body's ``(name, vertex slice, face slice)`` of it;
        ``dt``: seconds per step; ``obstacles``: :class:`ObstacleMesh` list).
    extra : str or None
        Top-level module of an optional dependency it needs (a key of
        :data:`fem3d.io.extras.EXTRAS`), checked before a run writes anything.
    reads_back : bool
        Its frames are numbered files ``frames/frame_NNNNN<suffix>`` that meshio reads
        (:func:`fem3d.io.dataset.read_run_frames`: a sweep's dataset mode, ``fem3d fit``'s
        target).
    """

    name: str
    suffix: str
    summary: str
    open: Opener
    extra: str | None = None
    reads_back: bool = False

    def require(self) -> None:
        """Raise :class:`~fem3d.io.extras.MissingExtra` (one line naming what to install)
        when the format's extra is missing."""
        if self.extra is not None:
            extras.require(self.extra, f"--format {self.name} (output.format)")


def whole_mesh(faces: np.ndarray, bodies: Bodies | None) -> Bodies:
    """``bodies``, or one body ``"body"`` holding every vertex the faces use (and below)."""
    if bodies is not None:
        return bodies
    return [("body", slice(0, int(np.max(faces)) + 1), slice(0, len(faces)))]

