"""The frames of a run, one module per output format.

=========  ==========================================================  ==============
format     files                                                        module
=========  ==========================================================  ==============
``vtu``    ``frames/frame_00042.vtu`` + ``frames.pvd`` (ParaView)       :mod:`.vtu`
``obj``    ``frames/frame_00042.obj`` (Blender)                         :mod:`.obj`
``usd``    ``frames.usdc`` + value clips in ``frames_clips/``           :mod:`.usd`
=========  ==========================================================  ==============

- :mod:`.base` - :class:`FrameFormat` (name, suffix, extra, ``open``), the writers'
  protocol :class:`FrameSink` (``write`` appends a frame, ``flush``, ``close``, ``restore``,
  ``read_frames``) and the input checks.
- :mod:`.numbered` - what the one-file-per-frame formats share (numbering, obstacles,
  resuming).
- :mod:`.registry` - the formats by name (the scene's enum, ``--format``, the sweeps).
- :mod:`.volume` - the volume mesh beside the frames (``output.volume``: ``volume/*.vtu`` +
  ``volume.pvd``, the element's own cells, per-element fields as cell data).

A new format is one module here with its ``FORMAT``, imported into
:mod:`.registry` and listed in :data:`~fem3d.io.frames.registry.FRAME_FORMATS`. Every file is
written atomically (:func:`fem3d.io.files.atomic_write`).
"""

from fem3d.io.frames.base import FrameFormat, FrameSink, check_faces, check_vertices
from fem3d.io.frames.numbered import NumberedFilesWriter
from fem3d.io.frames.obj import ObjWriter
from fem3d.io.frames.registry import (
    FRAME_FORMATS,
    frame_format,
    frame_format_names,
    make_frame_writer,
    register_frame_format,
)
from fem3d.io.frames.usd import UsdWriter
from fem3d.io.frames.vtu import RawVtu, VtuWriter

__all__ = [
    "FRAME_FORMATS",
    "FrameFormat",
    "FrameSink",
    "NumberedFilesWriter",
    "ObjWriter",
    "RawVtu",
    "UsdWriter",
    "VtuWriter",
    "check_faces",
    "check_vertices",
    "frame_format",
    "frame_format_names",
    "make_frame_writer",
    "register_frame_format",
]
