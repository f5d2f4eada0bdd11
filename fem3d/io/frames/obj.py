"""OBJ frames for Blender: ``frames/frame_00042.obj`` (Blender's "import OBJ as sequence").

- :class:`ObjFile` - plain Wavefront OBJ of one triangle mesh, 1-based faces encoded once.
- :class:`ObjWriter` - the numbered frames (no index: the numbers are the order).
- :data:`FORMAT` - the ``"obj"`` output format.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from fem3d.io.files import PathLike, atomic_write
from fem3d.io.frames.base import Bodies, FrameFormat
from fem3d.io.frames.numbered import FileEncoder, NumberedFilesWriter
from fem3d.io.obstacles import ObstacleMesh

__all__ = ["FORMAT", "ObjFile", "ObjWriter"]


class ObjFile:
    """Wavefront OBJ files of one triangle mesh (positions as ``%.9g``, per-vertex fields
    left out).

    Parameters
    ----------
    faces : (n_faces, 3) int64
        Triangles (0-based, checked).
    """

    def __init__(self, faces: np.ndarray) -> None:
        buf = io.StringIO()
        np.savetxt(buf, faces + 1, fmt="f %d %d %d")
        self._faces = buf.getvalue().encode("ascii")

    def write(self, path: PathLike, V: np.ndarray,
              point_data: Mapping[str, np.ndarray] | None = None) -> Path:
        """Write one frame to ``path`` atomically."""
        # one % over every coordinate: np.savetxt's text, in half its time
        text = ("v %.9g %.9g %.9g\n" * V.shape[0]) % tuple(V.ravel().tolist())
        return atomic_write(path, text.encode("ascii") + self._faces)


class ObjWriter(NumberedFilesWriter):
    """Numbered OBJ frames (see :class:`~fem3d.io.frames.numbered.NumberedFilesWriter`)."""

    fmt = "obj"
    suffix = ".obj"

    def encoder(self, faces: np.ndarray) -> FileEncoder:
        """:class:`ObjFile`."""
        return ObjFile(faces)


def _open(out_dir: PathLike, faces: np.ndarray, *, bodies: Bodies | None = None,
          dt: float = 1.0, obstacles: Sequence[ObstacleMesh] = ()) -> ObjWriter:
    return ObjWriter(out_dir, faces, obstacles=obstacles)


#: Wavefront OBJ, one file per frame.
FORMAT = FrameFormat(name="obj", suffix=".obj", open=_open, reads_back=True,
                     summary="frames/*.obj (Blender)")
