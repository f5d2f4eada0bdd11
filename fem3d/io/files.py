"""Files every reader and writer shares: atomic writes, input checks, safe reads, temp cleanup.

Every file fem3d writes is written atomically: into a temporary file in the target's folder,
flushed and fsync'ed, then moved over the target with :func:`os.replace`. A reader (ParaView
polling the ``.pvd``, a plot script reading ``energy.csv``) therefore sees either the previous
complete file or the new complete file, never a truncated one. A writer that raises leaves no
temporary file behind; only a killed process can leave a hidden ``.<name>.tmp*`` file
(:func:`clean_temp_files` removes those).

:func:`check_input_file` is what every reader calls first: it refuses FIFOs, devices and
sockets (reading one would block forever), symlink loops and folders with one clear line.

Contents
--------
- :func:`atomic_write`, :func:`atomic_path` - the primitive every writer uses.
- :func:`check_input_file` - refuse what cannot be read as a regular file.
- :func:`read_text_file` - a text file's contents, or one line saying why not
  (:func:`read_file_bytes` then :func:`decode_text`, for a reader that parses bytes).
- :func:`clean_temp_files` - remove the temporary files a killed writer left behind.
- :func:`cache_dir` - fem3d's cache folder.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from fem3d.errors import InputError

__all__ = [
    "PathLike",
    "atomic_path",
    "atomic_write",
    "cache_dir",
    "check_input_file",
    "clean_temp_files",
    "decode_text",
    "read_file_bytes",
    "read_text_file",
]

PathLike = str | os.PathLike[str]


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_FILE_MODE = 0o666 & ~_current_umask()


def _fsync_dir(folder: Path) -> None:
    """Make a rename durable (POSIX); silently skipped where directories cannot be opened."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path`` atomically.

    The temporary name keeps the target's suffix (``.frame_00001.tmpXXXX.vtu``) so writers
    that guess the format from the name still work. If the body raises, the temporary file
    is removed and ``path`` is left untouched.

    Examples
    --------
    >>> with atomic_path("mesh.vtu") as tmp:          # doctest: +SKIP
    ...     meshio.write(tmp, mesh, file_format="vtu")
    """
    target = Path(path)
    folder = target.parent
    fd, tmp_name = tempfile.mkstemp(dir=folder, prefix=f".{target.stem}.tmp", suffix=target.suffix)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, target)
    except OSError as exc:  # disk full, quota, ...: name the file being written
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise OSError(exc.errno, f"{exc.strerror or exc} while writing", str(target)) from None
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    _fsync_dir(folder)


def atomic_write(path: PathLike, content: bytes | str | Callable[[Path], Any]) -> Path:
    """Write ``path`` atomically.

    Parameters
    ----------
    path : str or PathLike
        Target file; its folder must exist.
    content : bytes, str or callable
        Bytes, text (UTF-8), or a function called with the temporary path that writes the
        whole file there (e.g. ``lambda p: meshio.write(p, mesh, file_format="vtu")``).

    Returns
    -------
    Path
        ``path``.
    """
    target = Path(path)
    with atomic_path(target) as tmp:
        if isinstance(content, str):
            tmp.write_bytes(content.encode("utf-8"))
        elif isinstance(content, bytes | bytearray | memoryview):
            tmp.write_bytes(bytes(content))
        elif callable(content):
            content(tmp)
        else:
            raise TypeError(f"content must be bytes, str or a callable, got {type(content)}")
    return target


def check_input_file(path: str | os.PathLike[str], what: str = "file") -> Path:
    """Refuse what cannot be read as a regular file, with one line naming the path.

    Parameters
    ----------
    path : str or PathLike
    what : str
        What the file is for (``"mesh"``, ``"scene file"``), used in the message.

    Returns
    -------
    Path

    Raises
    ------
    InputError
        Missing, a symlink loop, a folder, a FIFO, a device or a socket.
    """
    p = Path(path)
    try:
        st = os.stat(p)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise InputError(f"symbolic link loop: the {what} path never reaches a file",
                             path=p) from None
        if exc.errno == errno.ENOENT:
            if p.is_symlink():
                raise InputError(f"broken symbolic link (its target {os.readlink(p)!r} "
                                 f"does not exist)", path=p) from None
            raise InputError("file not found", path=p) from None
        if exc.errno == errno.ENOTDIR:
            raise InputError("file not found (a parent of it is not a folder)",
                             path=p) from None
        raise InputError(f"cannot read {what}: {exc.strerror}", path=p) from None
    mode = st.st_mode
    if stat.S_ISREG(mode):
        return p
    if stat.S_ISDIR(mode):
        raise InputError(f"is a directory, not a {what} file", path=p)
    kind = ("a named pipe (FIFO)" if stat.S_ISFIFO(mode) else
            "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else
            "a socket" if stat.S_ISSOCK(mode) else "not a regular file")
    raise InputError(f"is {kind}, not a regular {what} file; fem3d reads regular files only",
                     path=p)


def read_file_bytes(path: PathLike, what: str = "text") -> bytes:
    """The bytes of a text file, or one line saying why it cannot be read (the checks of
    :func:`read_text_file` that need no decoding; :func:`decode_text` does the rest).

    Raises
    ------
    InputError
        Missing, a folder, unreadable, or empty (or only white space).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except IsADirectoryError:
        raise InputError(f"is a directory, not a {what} file", path=path) from None
    except OSError as exc:
        raise InputError(f"cannot read file: {exc.strerror or exc}", path=path) from None
    if not data or data.isspace():  # (not strip(): no copy of a large file)
        raise InputError("empty file", path=path)
    return data


def decode_text(data: bytes, path: PathLike) -> str:
    """``data`` (of :func:`read_file_bytes`) as text: UTF-8 (a byte-order mark dropped),
    else Latin-1 (e.g. Latin-1 comments or names: numbers are ASCII in any case).

    Raises
    ------
    InputError
        It holds NUL bytes (the line of the first).
    """
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = data.decode("latin-1")
    if "\x00" in text:
        raise InputError("not a text file (contains NUL bytes)", path=path,
                         line=text.count("\n", 0, text.index("\x00")) + 1)
    return text


def read_text_file(path: PathLike, what: str = "text") -> str:
    """The text of a file, or one line saying why it cannot be read.

    Decoded as UTF-8 (a byte-order mark is dropped), else as Latin-1 (e.g. Latin-1
    comments or names: numbers are ASCII in any case).

    Parameters
    ----------
    path : str or PathLike
    what : str
        What the file is (``"mesh"``), used in the message about a folder.

    Returns
    -------
    str

    Raises
    ------
    InputError
        Missing, a folder, unreadable, empty (or only white space), or holding NUL bytes.
    """
    return decode_text(read_file_bytes(path, what), path)


def clean_temp_files(*folders: PathLike) -> list[Path]:
    """Remove the ``.<name>.tmp*`` files a killed writer left in ``folders``.

    Call only while no live writer may own them (a run holds its output folder's lock,
    :func:`fem3d.io.rundir.claim`). Folders that do not exist are skipped.

    Returns
    -------
    list of Path
        The removed files.
    """
    removed = []
    for folder in map(Path, folders):
        if not folder.is_dir():
            continue
        for f in folder.iterdir():
            if f.name.startswith(".") and ".tmp" in f.name and f.is_file():
                with contextlib.suppress(FileNotFoundError):
                    f.unlink()
                    removed.append(f)
    return removed


def cache_dir() -> Path:
    """fem3d's cache folder: ``$FEM3D_CACHE``, else ``~/.cache/fem3d`` (created)."""
    env = os.environ.get("FEM3D_CACHE")
    d = (Path(env) if env else Path.home() / ".cache" / "fem3d").expanduser().resolve()
    d.mkdir(parents=True, exist_ok=True)
    return d
