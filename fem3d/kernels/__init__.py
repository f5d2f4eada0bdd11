"""Generated kernels at run time: the back-end choice (:mod:`.backend`), dispatch
(:mod:`.dispatch`) and the race-free thread schedule of the fused C assemblies
(:mod:`.schedule`).

Names imported from ``fem3d.kernels`` itself (the module it was before 0.2) still resolve, with
a DeprecationWarning, until 0.3.
"""

from fem3d._deprecated import forward

__getattr__ = forward(__name__, "fem3d.kernels.dispatch, fem3d.kernels.backend")
