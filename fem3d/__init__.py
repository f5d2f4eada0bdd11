"""fem3d: linear tetrahedral FEM elastodynamics with SymPy-derived generated kernels."""

from fem3d.errors import Fem3dError, InputError, ParameterError, SimulationError

__all__ = ["Fem3dError", "InputError", "ParameterError", "SimulationError", "Scene"]
__version__ = "0.1.0"


def __getattr__(name: str):
    """``fem3d.Scene``: the scene description (:mod:`fem3d.scene.spec`), imported on first use."""
    if name == "Scene":
        from fem3d.scene.spec import Scene

        return Scene
    raise AttributeError(f"module 'fem3d' has no attribute {name!r}")
