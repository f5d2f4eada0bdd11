"""Linear solvers of the Newton systems: one protocol, implementations, a registry by name.

* :mod:`~fem3d.solve.linear.base`: the :class:`LinearSolver` protocol (``analyse`` once per
  pattern, ``factorize`` per matrix, ``solve`` per right-hand side, ``report``), the
  :class:`SolveReport`, :class:`NotPositiveDefinite`, and :class:`DirectSolver`, the direct
  solvers' shared part (pattern embedding, the shifted retry ``factorize_shifted``);
* implementations: :mod:`~fem3d.solve.linear.cholmod`, :mod:`~fem3d.solve.linear.pardiso`,
  :mod:`~fem3d.solve.linear.superlu` (direct), :mod:`~fem3d.solve.linear.amg_cg` (CG
  preconditioned by the AMG hierarchy of :mod:`~fem3d.solve.linear.amg`);
* :mod:`~fem3d.solve.linear.krylov`: CG preconditioned by an older factorization (the
  ``"reuse"`` Newton direction);
* :mod:`~fem3d.solve.linear.registry`: the solvers by name, ``"auto"`` and ``FEM3D_SOLVER``.

A matrix that is not positive definite makes a direct solver's ``factorize`` raise
:class:`NotPositiveDefinite`; :meth:`DirectSolver.factorize_shifted` retries with ``A + mu S``
for increasing ``mu``.
"""

from fem3d.solve.linear.base import (
    DirectSolver,
    IterativeSolver,
    LinearSolver,
    NotPositiveDefinite,
    SolveReport,
    SolverOptions,
)
from fem3d.solve.linear.registry import (
    LINEAR_SOLVERS,
    available_linear_solvers,
    direct_solver_names,
    linear_solver_names,
    make_linear_solver,
    register_linear_solver,
    resolve_linear_solver,
)

__all__ = ["DirectSolver", "IterativeSolver", "LINEAR_SOLVERS", "LinearSolver",
           "NotPositiveDefinite", "SolveReport", "SolverOptions", "available_linear_solvers",
           "direct_solver_names", "linear_solver_names", "make_linear_solver",
           "register_linear_solver", "resolve_linear_solver"]
