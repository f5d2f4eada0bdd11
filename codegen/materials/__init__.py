"""Material registry: a material is one module exposing ``PARAM_NAMES`` and ``psi(F, params)``.

To add a material, write ``codegen/materials/<name>.py`` and add one line to ``MATERIALS``.
Everything else (stress, Hessian, element kernels, NumPy and C back ends, runtime dispatch)
follows from the registry.
"""

from __future__ import annotations

from types import ModuleType

from codegen.materials import neo_hookean, stvk

MATERIALS: dict[str, ModuleType] = {
    "neo_hookean": neo_hookean,
    "stvk": stvk,
}
