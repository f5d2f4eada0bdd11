"""The output formats by name: the one place the scene's ``output.format`` choices, the CLI's
``--format``, the sweeps' checks and the run loop's writer are derived from.

Adding a format is one module (a :class:`~fem3d.io.frames.base.FrameFormat` whose ``open``
makes a :class:`~fem3d.io.frames.base.FrameSink`), its import and its entry in
:data:`FRAME_FORMATS` below, or a call of :func:`register_frame_format` from outside fem3d (before
:mod:`fem3d.scene` is imported: the scene schema's enum is read at import).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fem3d.errors import InputError
from fem3d.io.files import PathLike
from fem3d.io.frames.base import Bodies, FrameFormat, FrameSink
from fem3d.io.frames.obj import FORMAT as OBJ
from fem3d.io.frames.usd import FORMAT as USD
from fem3d.io.frames.vtu import FORMAT as VTU
from fem3d.io.obstacles import ObstacleMesh

__all__ = ["FRAME_FORMATS", "frame_format", "frame_format_names", "make_frame_writer",
           "register_frame_format"]

#: The output formats by name, the default first.
FRAME_FORMATS: dict[str, FrameFormat] = {
    f.name: f for f in (VTU, OBJ, USD)
}


def register_frame_format(fmt: FrameFormat) -> None:
    """Add ``fmt`` under ``fmt.name`` (a plug-in format; a name taken is replaced)."""
    if not isinstance(fmt, FrameFormat) or not fmt.name.isidentifier():
        raise ValueError(f"an output format is a FrameFormat with an identifier for a name, "
                         f"got {fmt!r}")
    FRAME_FORMATS[fmt.name] = fmt


def frame_format_names() -> tuple[str, ...]:
    """Every choice of ``output.format``, the default first."""
    return tuple(FRAME_FORMATS)


def frame_format(name: str) -> FrameFormat:
    """The format called ``name``.

    Raises
    ------
    InputError
        An unknown name (the line names the registered ones).
    """
    try:
        return FRAME_FORMATS[name]
    except KeyError:
        raise InputError(f"unknown output format {name!r}; available: "
                         f"{', '.join(FRAME_FORMATS)}") from None


def make_frame_writer(out_dir: PathLike, faces: np.ndarray, fmt: str, *,
                      bodies: Bodies | None = None, dt: float = 1.0,
                      obstacles: Sequence[ObstacleMesh] = ()) -> FrameSink:
    """The writer of the frames of a run in format ``fmt`` (a registered name).

    Parameters
    ----------
    out_dir : str or PathLike
        The run's output folder.
    faces : (n_faces, 3) int
        Triangles of the display mesh.
    fmt : str
        A name of :data:`FRAME_FORMATS`.
    bodies : list of (name, vertex slice, face slice), optional
        Each body's part of the display mesh (formats with a part per body: USD's prims);
        default one body holding the whole mesh.
    dt : float
        Seconds per step (USD's time codes).
    obstacles : sequence of ObstacleMesh
        The contact scene's obstacles, written with the frames.

    Raises
    ------
    InputError
        An unknown format.
    """
    return frame_format(fmt).open(out_dir, faces, bodies=bodies, dt=dt, obstacles=obstacles)
