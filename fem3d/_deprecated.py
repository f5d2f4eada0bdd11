"""Old import paths kept for one release: a module-level ``__getattr__`` that forwards to the
module's new home with a :class:`DeprecationWarning` (docs/architecture.md lists them)."""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable
from typing import Any


def forward(old: str, new: str, renamed: dict[str, str] | None = None
            ) -> Callable[[str], Any]:
    """``__getattr__`` for the old module ``old``: each name is looked up in ``new`` (the
    first of several comma-separated modules that has it), with a DeprecationWarning;
    ``renamed`` maps old names to ``"module.new_name"``."""
    homes = [m.strip() for m in new.split(",")]
    renamed = renamed or {}

    def __getattr__(name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        if name in renamed:
            home, _, new_name = renamed[name].rpartition(".")
            warnings.warn(f"{old}.{name} is deprecated: use {renamed[name]} (removed in fem3d "
                          "0.3)", DeprecationWarning, stacklevel=2)
            return getattr(importlib.import_module(home), new_name)
        for home in homes:
            module = importlib.import_module(home)
            if hasattr(module, name):
                warnings.warn(f"{old} is deprecated: import {name} from {home} (removed in "
                              "fem3d 0.3)", DeprecationWarning, stacklevel=2)
                return getattr(module, name)
        raise AttributeError(f"module {old!r} has no attribute {name!r} (moved to {new})")

    return __getattr__
