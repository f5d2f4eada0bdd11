"""fem3d: linear tetrahedral FEM elastodynamics with SymPy-derived generated kernels."""

from fem3d.errors import Fem3dError, InputError, ParameterError, SimulationError

__all__ = ["Fem3dError", "InputError", "ParameterError", "SimulationError"]
__version__ = "0.1.0"
