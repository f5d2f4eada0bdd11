"""fem3d: linear tetrahedral FEM elastodynamics with SymPy-derived generated kernels.

The public entry points, imported on first use: :class:`Scene`, :func:`load_scene`
(:mod:`fem3d.scene`), :class:`Simulation` (:mod:`fem3d.simulation`) and :func:`run_scene`
(:mod:`fem3d.app.run`, the code path of ``fem3d run``). The layout is described in
``docs/architecture.md``.
"""

from fem3d.errors import Fem3dError, InputError, ParameterError, SimulationError

__all__ = ["Fem3dError", "InputError", "ParameterError", "SimulationError", "Scene",
           "Simulation", "load_scene", "run_scene"]
__version__ = "0.1.0"

#: name -> the module it is imported from on first use (keeps ``import fem3d`` light)
_LAZY = {
    "Scene": "fem3d.scene",
    "load_scene": "fem3d.scene",
    "Simulation": "fem3d.simulation",
    "run_scene": "fem3d.app.run",
}


def __getattr__(name: str):
    """``fem3d.Scene``, ``fem3d.load_scene``, ``fem3d.Simulation``, ``fem3d.run_scene``."""
    if name in _LAZY:
        import importlib  # lazy: `import fem3d` stays light

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'fem3d' has no attribute {name!r}")
