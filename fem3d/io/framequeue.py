"""Frames written off the stepping thread: a bounded queue and one writer thread.

:class:`BackgroundWriter` wraps a frame writer (a :class:`fem3d.io.frames.FrameSink` of any
output format). :meth:`~BackgroundWriter.write` checks the positions
(a non-finite coordinate is refused at once, with its step), copies them and puts them in a
queue of ``depth`` frames; one thread takes them in order and writes them with the wrapped
writer. The caller waits only when the queue is full (the disk is slower than the steps).

- **Order and bytes.** One thread, first in first out: the same calls as writing in the
  caller's thread, in the same order, so the files are the same byte for byte whatever the
  timing. The format's index (VTU's ``frames.pvd``) is rewritten when the queue runs dry
  (at most every ``index_seconds``) and by :meth:`~BackgroundWriter.flush`; its last contents do not
  depend on the timing either.
- **Errors.** The first exception of the writer thread (disk full: an ``OSError`` naming
  the file) is raised in the caller's thread by the next :meth:`~BackgroundWriter.write` or
  :meth:`~BackgroundWriter.flush`; frames queued after it are dropped, so none is written
  after a lost one.
- **Checkpoints.** :meth:`~BackgroundWriter.flush` waits until every frame queued is on disk
  (and raises the writer's error, if any): the run loop calls it before it saves a
  checkpoint, so a checkpoint never lists a frame that is not on disk.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from fem3d.io.frames.base import check_vertices

__all__ = ["BackgroundWriter"]

#: The queue's end marker.
_STOP = object()


class _Abandoned(Exception):
    """Marks a writer stopped by :meth:`BackgroundWriter.abandon` (frames left are dropped)."""


class BackgroundWriter:
    """A frame writer that writes in its own thread (see the module).

    Parameters
    ----------
    writer : FrameSink
        The writer doing the work (used by the thread only, until :meth:`flush` returns).
    depth : int
        Frames queued at most; a :meth:`write` finding the queue full waits for the thread.
    index_seconds : float
        The writer's index (``frames.pvd``) is rewritten at most this often while frames
        come (and at every :meth:`flush`).

    Attributes
    ----------
    waited_seconds : float
        Time :meth:`write` spent waiting for room in the queue.
    """

    def __init__(self, writer: Any, *, depth: int = 8, index_seconds: float = 1.0) -> None:
        self.writer = writer
        self.fmt = getattr(writer, "fmt", "")
        self.faces = writer.faces
        if hasattr(writer, "index_every_frame"):
            writer.index_every_frame = False  # rewritten here, when the queue runs dry
        self.index_seconds = float(index_seconds)
        self.waited_seconds = 0.0
        self._queue: queue.Queue = queue.Queue(maxsize=max(1, int(depth)))
        self._error: BaseException | None = None
        self._last_index = 0.0
        self._thread = threading.Thread(target=self._work, name="fem3d-frames", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ the writer thread
    def _work(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is _STOP:
                    return
                if self._error is None:
                    self._write_one(*item)
            finally:
                self._queue.task_done()

    def _write_one(self, step: int, t: float, V: np.ndarray,
                   point_data: Mapping[str, np.ndarray] | None,
                   cell_data: Mapping[str, np.ndarray] | None) -> None:
        try:
            if cell_data is None:
                self.writer.write(step, t, V, point_data)
            else:
                self.writer.write(step, t, V, point_data, cell_data=cell_data)
            now = time.monotonic()
            if self._queue.empty() and now - self._last_index >= self.index_seconds:
                self._write_index()
                self._last_index = now
        except BaseException as exc:  # raised again in the caller's thread
            self._error = exc

    def _write_index(self) -> None:
        write_index = getattr(self.writer, "write_index", None)
        if write_index is not None:
            write_index()

    # ------------------------------------------------------------------ the caller's thread
    def _raise_error(self) -> None:
        if self._error is not None:
            raise self._error

    @property
    def failed(self) -> bool:
        """Whether the writer thread stopped on an error."""
        return self._error is not None

    def write(self, step_index: int, t: float, V: np.ndarray,
              point_data: Mapping[str, np.ndarray] | None = None,
              cell_data: Mapping[str, np.ndarray] | None = None) -> None:
        """Queue one frame (a copy of ``V``; ``cell_data`` only for a writer that takes it,
        :class:`~fem3d.io.frames.volume.VolumeVtuWriter`); wait if ``depth`` frames are
        queued.

        Raises
        ------
        SimulationError
            ``V`` holds a non-finite coordinate (nothing queued).
        ValueError
            Wrong shapes.
        OSError, Exception
            The writer thread's error on an earlier frame.
        """
        self._raise_error()
        if not self._thread.is_alive():
            raise RuntimeError("frame writer closed: no frame can be queued after close()")
        V = np.array(check_vertices(V, self.faces, int(step_index)), dtype=np.float64)
        data = None if point_data is None else {k: np.array(v) for k, v in point_data.items()}
        cells = None if cell_data is None else {k: np.array(v) for k, v in cell_data.items()}
        item = (int(step_index), float(t), V, data, cells)
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            start = time.perf_counter()
            self._queue.put(item)
            self.waited_seconds += time.perf_counter() - start

    def flush(self) -> None:
        """Wait until every frame queued is written, then flush the writer (``frames.pvd``,
        the USD writer's current chunk).

        Raises
        ------
        OSError, Exception
            The writer thread's error (nothing more is written).
        """
        self._queue.join()
        self._raise_error()
        self.writer.flush()

    def close(self) -> None:
        """:meth:`flush` and stop the thread (also when the flush raises)."""
        try:
            if self._thread.is_alive():
                self.flush()
        finally:
            self._stop()

    def abandon(self) -> None:
        """Stop the thread without writing what is still queued (a run ending on an
        error); raises nothing. Nothing to do after :meth:`close`."""
        if self._thread.is_alive() and self._error is None:
            self._error = _Abandoned()
        self._stop()

    def _stop(self) -> None:
        if self._thread.is_alive():
            self._queue.put(_STOP)
            self._thread.join()

    # ------------------------------------------------------------------ the writer's state
    @property
    def frames(self) -> dict[int, tuple[float, str]]:
        """The wrapped writer's frame list (complete after :meth:`flush`)."""
        return self.writer.frames

    def restore(self, frames: Mapping[int, tuple[float, str]], step: int) -> None:
        """Continue a run (see the wrapped writer's ``restore``)."""
        self._queue.join()
        self.writer.restore(frames, step)

    def read_frames(self, stride: int = 1) -> Iterator[tuple[int, np.ndarray]]:
        """Frames read back from disk (after :meth:`flush`)."""
        self.flush()
        yield from self.writer.read_frames(stride)
