"""The output folder of a run: lock, overwrite check, temp-file cleanup.

``fem3d run`` and ``fem3d resume`` hold :func:`claim` for the run's lifetime::

    with rundir.claim(out, inputs={"mesh": mesh_path, "skin": skin_path}, command="run"):
        ...  # write frames, energy.csv, checkpoint.npz

* **Lock**: ``DIR/.fem3d.lock`` is locked with ``flock`` (released by the kernel when the
  process dies, even after ``kill -9``: a stale lock file is simply taken over) and holds
  the owner's pid and command line, so a second run into the same folder refuses with one
  line naming the other process. It is removed when the run ends (normally, failed, or
  interrupted), so a finished run folder holds only the run's outputs.
* **Overwrite check**: the run refuses when a file it writes (``frames/*``, ``frames.pvd``,
  ``volume/*``, ``volume.pvd``, ``energy.csv``, ``energy.png``, ``preview.gif``,
  ``checkpoint.npz``) is one of its inputs (mesh, skin, scene file, ...). ``fem3d resume``
  passes the checkpoint it resumes as ``allow`` (it replaces it atomically, on purpose).
* **Temp cleanup**: the hidden ``.<name>.tmp*`` files that only a killed writer leaves
  behind (:func:`fem3d.io.files.atomic_path`) in ``DIR`` and its output folders are removed
  once the lock is held (:func:`fem3d.io.files.clean_temp_files`).

The checks every reader makes (:func:`fem3d.io.files.check_input_file`) and the atomic writes
live in :mod:`fem3d.io.files`.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import socket
import sys
import time
import warnings
from collections.abc import Iterator, Mapping
from pathlib import Path

from fem3d.errors import InputError
from fem3d.io.files import clean_temp_files

__all__ = ["LOCK_NAME", "OUTPUT_NAMES", "OUTPUT_FOLDERS", "claim",
           "check_overwrite", "warnings_as_lines"]

LOCK_NAME = ".fem3d.lock"
#: Files a run writes into its output folder (``frames/``, ``obstacles/`` and ``volume/`` are
#: written as wholes).
OUTPUT_NAMES = ("frames.pvd", "volume.pvd", "energy.csv", "energy.png", "preview.gif",
                "checkpoint.npz")
#: The folders of files a run writes.
OUTPUT_FOLDERS = ("frames", "obstacles", "volume")


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:  # one does not exist (yet)
        return os.path.realpath(a) == os.path.realpath(b)


def check_overwrite(
    out: str | os.PathLike[str],
    inputs: Mapping[str, str | os.PathLike[str] | None],
    *,
    allow: tuple[str | os.PathLike[str], ...] = (),
) -> None:
    """Refuse a run whose outputs in ``out`` would overwrite one of its ``inputs``.

    Parameters
    ----------
    out : folder the run writes into
    inputs : {role: path}, e.g. ``{"mesh": ..., "skin": ..., "scene file": ...}``; None
        values are skipped
    allow : paths the run may replace although they are inputs (the checkpoint a resume
        continues from)

    Raises
    ------
    InputError
        Naming the input, its role and the output folder.
    """
    out = Path(out)
    folders = [os.path.realpath(out / f) for f in OUTPUT_FOLDERS]
    written = [out / n for n in OUTPUT_NAMES]
    for role, path in inputs.items():
        if path is None:
            continue
        p = Path(path)
        if any(_same_file(p, Path(a)) for a in allow):
            continue
        hit = any(_same_file(p, w) for w in written)
        in_frames = os.path.realpath(p.parent) in folders
        if hit or in_frames:
            raise InputError(
                f"the run would overwrite its own {role} {p}: it writes its outputs "
                f"(frames/, energy.csv, checkpoint.npz, ...) into {out}; choose another --out",
                path=p,
            )


def _owner_text(lock: Path) -> str:
    try:
        text = lock.read_text(encoding="utf-8", errors="replace").strip()
    except OSError:
        return "another process"
    parts = dict(line.split("=", 1) for line in text.splitlines() if "=" in line)
    pid = parts.get("pid", "?")
    cmd = parts.get("command", "")
    since = parts.get("since", "")
    return f"process {pid}" + (f" ({cmd})" if cmd else "") + (f", since {since}" if since else "")


@contextlib.contextmanager
def claim(
    out: str | os.PathLike[str],
    *,
    inputs: Mapping[str, str | os.PathLike[str] | None] | None = None,
    allow: tuple[str | os.PathLike[str], ...] = (),
    command: str | None = None,
) -> Iterator[Path]:
    """Hold the output folder for a run: check, lock, clean; release on exit.

    Raises
    ------
    InputError
        An input would be overwritten (:func:`check_overwrite`), or another live process
        holds the folder (named in the message).
    """
    out = Path(out)
    check_overwrite(out, inputs or {}, allow=allow)
    out.mkdir(parents=True, exist_ok=True)
    lock = out / LOCK_NAME
    fd = _lock(lock, out)
    try:
        cmd = command or " ".join(Path(a).name if i == 0 else a for i, a in enumerate(sys.argv))
        info = (f"pid={os.getpid()}\nhost={socket.gethostname()}\ncommand={cmd}\n"
                f"since={time.strftime('%Y-%m-%d %H:%M:%S')}\n")
        os.ftruncate(fd, 0)
        os.pwrite(fd, info.encode("utf-8"), 0)
        clean_temp_files(out, *(out / f for f in OUTPUT_FOLDERS))
        try:
            yield out
        finally:
            # Unlinked while still locked: a run that opened it meanwhile finds, once it
            # holds the lock, that the name no longer leads to its file, and starts over.
            with contextlib.suppress(OSError):
                os.unlink(lock)
    finally:
        os.close(fd)


def _lock(lock: Path, out: Path) -> int:
    """Open and ``flock`` ``lock``; the descriptor. Retries when the file was unlinked (or
    replaced) by its previous holder between the open and the lock.

    Raises
    ------
    InputError
        Another live process holds it.
    """
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            raise InputError(
                f"output folder is in use by {_owner_text(lock)}; wait for it to finish "
                "or choose another --out", path=out,
            ) from None
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)


@contextlib.contextmanager
def warnings_as_lines(prefix: str) -> Iterator[None]:
    """Print each warning as one line ``<prefix>: warning: <message>`` on stderr.

    Python's default format takes two lines and quotes the source line that warned; with
    this, a command's output stays one line per message and an error printed after the
    warnings is the last line.
    """
    old = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):  # noqa: ANN001
        text = " ".join(str(message).split())
        print(f"{prefix}: warning: {text}", file=sys.stderr, flush=True)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = old
