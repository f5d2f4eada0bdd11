"""Whitespace tokens of mesh files with their line numbers, what the MEDIT and TetGen readers
read (:class:`Tokens`), and its fast path for large ASCII texts without a Python string per
token (:class:`TokenSpans`)."""

from __future__ import annotations

import itertools
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fem3d.errors import InputError
from fem3d.io.files import read_text_file

__all__ = ["TokenSpans", "Tokens", "is_int", "is_number"]

#: The bytes ``str.split()`` splits ASCII text at.
_ASCII_SPACE = np.zeros(256, dtype=bool)
_ASCII_SPACE[[9, 10, 11, 12, 13, 28, 29, 30, 31, 32]] = True


class TokenSpans:
    """The tokens of an ASCII text as a sequence (``tok[i]``, ``tok[a:b]``, ``len``) held as
    start and end offsets: no Python string per token until one is asked for."""

    def __init__(self, text: str) -> None:
        self.text = text
        b = np.frombuffer(text.encode("ascii"), dtype=np.uint8)
        space = _ASCII_SPACE[b]
        edge = np.flatnonzero(np.diff(space.view(np.int8), prepend=1, append=1))
        # non-space runs start where space falls to 0 and end where it rises back
        self.starts, self.ends = edge[0::2], edge[1::2]
        newlines = np.flatnonzero(b == 10)
        self.line = np.searchsorted(newlines, self.starts) + 1
        self.n_lines = newlines.size + 1

    def __len__(self) -> int:
        return self.starts.size

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self.text[s:e] for s, e in zip(self.starts[i].tolist(),
                                                   self.ends[i].tolist(), strict=True)]
        return self.text[int(self.starts[i]):int(self.ends[i])]

    def values(self, a: int, b: int, dtype: type) -> np.ndarray | None:
        """Tokens ``a .. b - 1`` parsed in C (None: one of them is not a plain number)."""
        if b <= a:
            return None
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            try:
                v = np.fromstring(self.text[self.starts[a]:self.ends[b - 1]], dtype=dtype,
                                  sep=" ")
            except (ValueError, DeprecationWarning):
                return None
        if v.size != b - a or (dtype is not np.float64 and np.abs(v).max() >= 2**62):
            return None
        return v


def is_number(word: str) -> bool:
    """Whether ``word`` parses as a float."""
    try:
        float(word)
    except ValueError:
        return False
    return True


def is_int(word: str) -> bool:
    """Whether ``word`` parses as an integer of magnitude below 2**62."""
    try:
        return abs(int(word)) < 2**62
    except ValueError:
        return False


class Tokens:
    """Whitespace tokens of a text file with their 1-based line numbers.

    Parameters
    ----------
    path : Path
        The file (read here unless ``text`` is given; named in every error).
    comment : str
        What starts a comment (to the end of its line).
    text : str, optional
        The file's text, already read.
    keywords : set of str
        The format's keywords (lower case): a section that runs into one is reported as a
        wrong count rather than as a non-numeric token.
    """

    def __init__(self, path: Path, comment: str = "#", text: str | None = None,
                 keywords: frozenset[str] = frozenset()) -> None:
        self.path = path
        self.keywords = keywords
        text = read_text_file(path, "mesh") if text is None else text
        if comment not in text and text.isascii():  # offsets, parsed in C by blocks
            spans = TokenSpans(text)
            self.tok: Sequence[str] = spans
            self.line, self.n_lines, self._spans = spans.line, spans.n_lines, spans
        else:
            lines = text.split("\n")
            if comment in text:
                lines = [ln.split(comment, 1)[0] for ln in lines]
            split = [ln.split() for ln in lines]
            counts = np.fromiter(map(len, split), dtype=np.int64, count=len(split))
            self.tok = list(itertools.chain.from_iterable(split))
            self.line = np.repeat(np.arange(1, len(lines) + 1, dtype=np.int64), counts)
            self.n_lines, self._spans = len(lines), None
        self.pos = 0
        if not len(self.tok):
            raise InputError("empty file (no data)", path=path)

    def lineno(self, i: int | None = None) -> int:
        i = self.pos if i is None else i
        if i >= len(self.tok):
            return int(self.line[-1]) if len(self.tok) else 1
        return int(self.line[i])

    def at_end(self) -> bool:
        return self.pos >= len(self.tok)

    def peek(self) -> str:
        return self.tok[self.pos]

    def next(self, what: str) -> str:
        if self.pos >= len(self.tok):
            raise InputError(f"file ends early (truncated?): expected {what}",
                             path=self.path, line=self.lineno())
        t = self.tok[self.pos]
        self.pos += 1
        return t

    def next_int(self, what: str, lo: int | None = 0) -> int:
        i = self.pos
        t = self.next(what)
        try:
            v = int(t)
        except ValueError:
            raise InputError(f"expected {what} (an integer), found {t!r}",
                             path=self.path, line=self.lineno(i)) from None
        if lo is not None and v < lo:
            raise InputError(f"{what} must be >= {lo}, found {v}",
                             path=self.path, line=self.lineno(i))
        return v

    def block(
        self, count: int, width: int, what: str, dtype: type
    ) -> tuple[np.ndarray, np.ndarray]:
        """Take ``count`` records of ``width`` numeric tokens.

        Returns
        -------
        values : (count, width) ``dtype``
        lines : (count,) int64, the line of each record's first token.
        """
        a = self.pos
        b = a + count * width
        if b > len(self.tok):
            have = (len(self.tok) - a) // width if width else 0
            kw = next((i for i in range(a, len(self.tok))
                       if self.tok[i].lower() in self.keywords), None)
            if kw is not None:
                raise InputError(
                    f"{what} section declares {count} entries but keyword {self.tok[kw]!r} "
                    f"comes after {(kw - a) // width} (wrong count or missing data)",
                    path=self.path, line=self.lineno(kw),
                )
            raise InputError(
                f"file ends early (truncated?): {what} section declares {count} entries of "
                f"{width} numbers, only {have} complete entries follow",
                path=self.path, line=self.lineno(len(self.tok) - 1),
            )
        parsed = None if self._spans is None else self._spans.values(a, b, dtype)
        if parsed is not None:
            self.pos = b
            return parsed.reshape(count, width), self.line[a:b:width] if width else \
                np.zeros(0, dtype=np.int64)
        chunk = self.tok[a:b]
        try:
            values = np.array(chunk, dtype=dtype).reshape(count, width)
        except (ValueError, OverflowError, TypeError):
            ok = is_number if dtype is np.float64 else is_int
            k = next((i for i, t in enumerate(chunk) if not ok(t)), 0)
            t = chunk[k]
            kind = "a number" if dtype is np.float64 else "an integer"
            if t[:1].isalpha() and t.lower() in self.keywords:
                msg = (f"{what} section declares {count} entries but keyword {t!r} comes after "
                       f"{k // width} (wrong count or missing data)")
            else:
                msg = f"non-numeric token {t!r} in {what} entry {k // width} (expected {kind})"
            raise InputError(msg, path=self.path, line=self.lineno(a + k),
                             element=k // width) from None
        self.pos = b
        lines = self.line[a:b:width] if width else np.zeros(0, dtype=np.int64)
        return values, lines
