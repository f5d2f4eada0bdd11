"""A toy output format from outside fem3d: one NumPy ``.npz`` per frame (``positions``,
``time``), registered on import (before :mod:`fem3d.scene`, whose schema reads the names).

Used by ``tests/io/test_frame_formats.py``: a format is this module (a writer and a
:class:`~fem3d.io.frames.FrameFormat`) and one registration.
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from fem3d.io.files import atomic_write
from fem3d.io.frames import FrameFormat, NumberedFilesWriter, register_frame_format


class NpzFile:
    """One ``.npz`` per frame: the positions (float64, as given)."""

    def __init__(self, faces: np.ndarray) -> None:
        self.faces = faces

    def write(self, path: Path, V: np.ndarray,
              point_data: Mapping[str, np.ndarray] | None) -> Path:
        buf = io.BytesIO()
        np.savez(buf, positions=V, faces=self.faces)
        return atomic_write(path, buf.getvalue())


class NpzWriter(NumberedFilesWriter):
    fmt = "npz"
    suffix = ".npz"

    def encoder(self, faces: np.ndarray) -> NpzFile:
        return NpzFile(faces)


NPZ = FrameFormat(name="npz", suffix=".npz", summary="frames/*.npz (NumPy)",
                  open=lambda out, faces, *, bodies, dt, obstacles: NpzWriter(
                      out, faces, obstacles=obstacles))
register_frame_format(NPZ)
