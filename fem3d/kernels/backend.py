"""The kernels' back end: the compiled C extension when built, NumPy otherwise.

Both back ends are rendered from the same kernel specs (see ``codegen``). Choose explicitly
with a ``backend`` argument or the ``FEM3D_KERNELS`` environment variable (``numpy`` or
``c``); :func:`resolve_backend` turns that choice into one back end, :func:`c_extension`
loads the extension ``fem3d._ckernels``. :mod:`fem3d.kernels.dispatch` (the kernels) and
:mod:`fem3d.kernels.schedule` (the thread schedules of the fused C loops) both build on this.
"""

from __future__ import annotations

import importlib
import os
from types import ModuleType

__all__ = ["BACKENDS", "c_extension", "resolve_backend"]

BACKENDS = ("numpy", "c")


def c_extension() -> ModuleType | None:
    """The compiled extension ``fem3d._ckernels``, or ``None`` when it is not built."""
    try:
        return importlib.import_module("fem3d._ckernels")
    except ImportError:
        return None


def resolve_backend(backend: str | None = None) -> str:
    """``backend``, else ``$FEM3D_KERNELS``, else ``"c"`` when built, else ``"numpy"``."""
    choice = backend or os.environ.get("FEM3D_KERNELS") or None
    if choice is None:
        return "c" if c_extension() is not None else "numpy"
    if choice not in BACKENDS:
        raise ValueError(f"unknown kernel back end {choice!r}; choose one of {BACKENDS}")
    if choice == "c" and c_extension() is None:
        raise ImportError(
            "the C kernels (fem3d._ckernels) are not built; run `pip install -e .` with a C "
            "compiler, or use FEM3D_KERNELS=numpy"
        )
    return choice
