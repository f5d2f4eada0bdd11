"""Whitespace tokens of a large ASCII text without a Python string per token: the fast path
of the mesh readers' tokenizer (:class:`fem3d.mesh.formats._Tokens`)."""

from __future__ import annotations

import warnings

import numpy as np

__all__ = ["TokenSpans"]

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
