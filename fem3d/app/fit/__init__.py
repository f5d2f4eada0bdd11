"""``fem3d fit FIT.toml``: material and initial-state parameters fitted to a recorded motion.

A fit file (:mod:`fem3d.app.fit.spec`) names a base scene, a target (the frames of a
``fem3d run`` folder, or a sweep's ``trajectory.npz``), the frames and vertices the loss
compares, the parameters by key path with bounds, and the optimiser. :mod:`fem3d.app.fit.run`
minimises the loss with :func:`scipy.optimize.minimize` and the exact adjoint gradient of
:func:`fem3d.diff.trajectory_gradient`, and writes ``fit.json``, ``fit.png`` and
``fitted.toml``; :mod:`fem3d.app.fit.cli` is the command line. See ``docs/differentiable.md``.
"""

from fem3d.app.fit.run import FitResult, fit
from fem3d.app.fit.spec import FitFile, load_fit_file

__all__ = ["FitFile", "FitResult", "fit", "load_fit_file"]
