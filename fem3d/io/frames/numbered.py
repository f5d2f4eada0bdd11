"""Frames as numbered files, one per frame: what the VTU and OBJ formats share.

``out_dir/frames/frame_00042<suffix>`` per frame, the obstacles beside them in
``out_dir/obstacles/`` (``obstacle_<i><suffix>`` once for a static one,
``obstacle_<i>_00042<suffix>`` per frame for a moving one). A format subclasses
:class:`NumberedFilesWriter` and says how one file is encoded (:meth:`~NumberedFilesWriter.encoder`)
and, if it has one, how its index of frames is written (:meth:`~NumberedFilesWriter.write_index`,
ParaView's ``frames.pvd``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Protocol

import meshio
import numpy as np

from fem3d.io.files import PathLike
from fem3d.io.frames.base import check_faces, check_vertices
from fem3d.io.obstacles import ObstacleMesh

__all__ = ["FileEncoder", "NumberedFilesWriter"]


class FileEncoder(Protocol):
    """Writes the files of one triangle mesh (the bodies' or one obstacle's)."""

    def write(self, path: Path, V: np.ndarray,
              point_data: Mapping[str, np.ndarray] | None) -> object:
        """Write positions ``V`` (``(n, 3)`` float64, checked) to ``path`` atomically."""


class NumberedFilesWriter:
    """Numbered frame files of a triangle mesh and of the obstacles (see the module).

    Subclasses set :attr:`fmt` and :attr:`suffix` and implement :meth:`encoder`.

    Parameters
    ----------
    out_dir : str or PathLike
        Output folder; frames go to ``out_dir/frames/`` (created if missing).
    faces : (n_faces, 3) int
        Triangles (0-based) of every frame.
    digits : int
        Zero padding of the frame number (``frame_00042``).
    obstacles : sequence of ObstacleMesh
        The contact scene's obstacles, written beside the frames.

    Attributes
    ----------
    frames : dict[int, tuple[float, str]]
        step index -> (time, path relative to ``out_dir``) of every frame written.
    index_every_frame : bool
        Rewrite the index (:meth:`write_index`) after every frame; the background writer
        (:mod:`fem3d.io.framequeue`) turns it off and writes the index when its queue runs dry.
    """

    #: The format's name.
    fmt = ""
    #: Suffix of every file (``".vtu"``).
    suffix = ""
    #: Folder of the frames in ``out_dir`` and the files' stem (``frames/frame_00042``).
    folder = "frames"
    stem = "frame"

    def __init__(self, out_dir: PathLike, faces: np.ndarray, *, digits: int = 5,
                 obstacles: Sequence[ObstacleMesh] = ()) -> None:
        self.out_dir = Path(out_dir)
        self.frame_dir = self.out_dir / self.folder
        self.frame_dir.mkdir(parents=True, exist_ok=True)
        self.faces = self.check_cells(faces)
        self.digits = int(digits)
        self.index_every_frame = True
        self.frames: dict[int, tuple[float, str]] = {}
        self._encoder = self.encoder(self.faces)
        self.obstacles = tuple(obstacles)
        #: the obstacles' files, beside (not among) the bodies' frames
        self.obstacle_dir = self.out_dir / "obstacles"
        if self.obstacles:
            self.obstacle_dir.mkdir(parents=True, exist_ok=True)
        self._obstacle_faces = [check_faces(ob.faces) for ob in self.obstacles]
        self._obstacle_encoders = [self.encoder(F) for F in self._obstacle_faces]
        self._static_written = False

    def check_cells(self, faces: np.ndarray) -> np.ndarray:
        """The frames' cells, checked (triangles: :func:`~fem3d.io.frames.base.check_faces`)."""
        return check_faces(faces)

    def encoder(self, faces: np.ndarray) -> FileEncoder:
        """The encoder of the files of the triangle mesh ``faces`` (checked int64)."""
        raise NotImplementedError

    def write_index(self) -> None:
        """Bring the format's index of frames up to date (none here)."""

    # ------------------------------------------------------------------ paths
    def path_of(self, step_index: int) -> Path:
        """File of frame ``step_index``."""
        return self.frame_dir / f"{self.stem}_{int(step_index):0{self.digits}d}{self.suffix}"

    def obstacle_path(self, i: int, step_index: int) -> Path:
        """File of obstacle ``i`` at frame ``step_index`` (one file for a static one)."""
        if self.obstacles[i].moving:
            number = f"{int(step_index):0{self.digits}d}"
            return self.obstacle_dir / f"obstacle_{i}_{number}{self.suffix}"
        return self.obstacle_dir / f"obstacle_{i}{self.suffix}"

    # ------------------------------------------------------------------ writing
    def write(
        self,
        step_index: int,
        t: float,
        V: np.ndarray,
        point_data: Mapping[str, np.ndarray] | None = None,
        cell_data: Mapping[str, np.ndarray] | None = None,
    ) -> Path:
        """Write one frame.

        Parameters
        ----------
        step_index : int
            Frame number in the file name (usually the step index); writing the same index
            again replaces that frame.
        t : float
            Simulated time (listed in the index).
        V : (n_skin, 3) float64
            Vertex positions.
        point_data : mapping of str to (n_skin, ...) arrays, optional
            Extra per-vertex fields (where the format has them).
        cell_data : mapping of str to (n_cells, ...) arrays, optional
            Per-cell fields (only to an encoder that takes them: the VTU volume frames).

        Returns
        -------
        Path
            The frame file.

        Raises
        ------
        SimulationError
            ``V`` holds a non-finite coordinate (nothing is written).
        ValueError
            Wrong shapes.
        """
        step_index = int(step_index)
        V = check_vertices(V, self.faces, step_index)
        path = self.path_of(step_index)
        if cell_data is None:
            self._encoder.write(path, V, point_data)
        else:
            self._encoder.write(path, V, point_data, cell_data=cell_data)
        self._write_obstacles(step_index, t)
        self.frames[step_index] = (float(t), path.relative_to(self.out_dir).as_posix())
        if self.index_every_frame:
            self.write_index()
        return path

    def _write_obstacles(self, step_index: int, t: float) -> None:
        for i, ob in enumerate(self.obstacles):
            if ob.moving or not self._static_written:
                V = check_vertices(ob.positions(t), self._obstacle_faces[i], step_index)
                self._obstacle_encoders[i].write(self.obstacle_path(i, step_index), V, None)
        self._static_written = True

    def flush(self) -> None:
        """Every frame is on disk once :meth:`write` returns; bring the index up to date."""
        self.write_index()

    def close(self) -> None:
        """Same as :meth:`flush`."""
        self.flush()

    # ------------------------------------------------------------------ continuing, reading
    def restore(self, frames: Mapping[int, tuple[float, str]], step: int) -> None:
        """Continue a run: the frames written up to ``step`` (a checkpoint's list); files of
        later frames (written after the checkpoint by an interrupted run) are removed."""
        self.frames = {int(k): (float(t), str(r)) for k, (t, r) in frames.items()}
        for folder, pattern in ((self.frame_dir, f"{self.stem}_*{self.suffix}"),
                                (self.obstacle_dir, f"obstacle_*_*{self.suffix}")):
            for f in folder.glob(pattern):
                with contextlib.suppress(ValueError):
                    if int(f.stem.split("_")[-1]) > step:
                        f.unlink()
        self._static_written = False  # written again with the next frame
        self.write_index()

    def read_frames(self, stride: int = 1) -> Iterator[tuple[int, np.ndarray]]:
        """``(step, (n_skin, 3) vertices)`` of every ``stride``-th frame listed, read back
        from disk."""
        for step in sorted(self.frames)[::max(1, int(stride))]:
            with contextlib.suppress(Exception):
                yield step, meshio.read(self.out_dir / self.frames[step][1]).points
