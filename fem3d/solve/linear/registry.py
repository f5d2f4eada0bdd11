"""The linear solvers by name: the one place ``"auto"``, ``FEM3D_SOLVER``, the scene's
``simulation.linear_solver`` choices and the error messages are derived from.

Adding a solver is one module (a class with the :class:`~fem3d.solve.linear.base.LinearSolver`
methods and class attributes) and one line in :data:`LINEAR_SOLVERS` below, or a call of
:func:`register_linear_solver` from outside fem3d.

``"auto"`` takes, among the solvers that import here, the one with the largest
``auto_min_free_dofs`` not above the system's free DOFs (ties: the first registered): AMG-CG
from :data:`~fem3d.solve.linear.amg_cg.AMG_AUTO_MIN_FREE_DOFS` free DOFs, else the first
direct solver. ``FEM3D_SOLVER`` names a direct solver that wins over ``"auto"`` and over the
direct solver a caller asked for.
"""

from __future__ import annotations

import os

from fem3d.solve.linear.amg_cg import AMGCGSolver
from fem3d.solve.linear.base import LinearSolver, SolverOptions
from fem3d.solve.linear.cholmod import CholmodSolver
from fem3d.solve.linear.pardiso import PardisoSolver
from fem3d.solve.linear.petsc import PetscSolver
from fem3d.solve.linear.superlu import SuperLUSolver

__all__ = ["AUTO", "ENV_VAR", "LINEAR_SOLVERS", "available_linear_solvers", "direct_solver_names",
           "linear_solver_names", "make_linear_solver", "register_linear_solver",
           "resolve_linear_solver"]

#: The choice that picks by availability and size.
AUTO = "auto"
#: The environment variable that forces a direct solver.
ENV_VAR = "FEM3D_SOLVER"

#: The solvers by name, the direct ones in the order ``"auto"`` tries them.
LINEAR_SOLVERS: dict[str, type[LinearSolver]] = {
    cls.name: cls
    for cls in (CholmodSolver, PardisoSolver, SuperLUSolver, AMGCGSolver, PetscSolver)
}


def register_linear_solver(cls: type[LinearSolver]) -> None:
    """Add ``cls`` under ``cls.name`` (a plug-in solver, e.g. a distributed or GPU one)."""
    name = getattr(cls, "name", "")
    if not name or name == AUTO:
        raise ValueError(f"a linear solver needs a name other than {AUTO!r}, got {name!r}")
    missing = [m for m in ("available", "analyse", "factorize", "solve", "report",
                           "iterative", "auto_min_free_dofs") if not hasattr(cls, m)]
    if missing:
        raise TypeError(f"linear solver {name!r} lacks {', '.join(missing)}")
    LINEAR_SOLVERS[name] = cls


def linear_solver_names() -> tuple[str, ...]:
    """Every choice of ``simulation.linear_solver``: ``"auto"`` and the registered names."""
    return (AUTO, *LINEAR_SOLVERS)


def direct_solver_names() -> tuple[str, ...]:
    """The registered direct solvers, in ``"auto"``'s order (what ``FEM3D_SOLVER`` takes)."""
    return tuple(n for n, cls in LINEAR_SOLVERS.items() if not cls.iterative)


def available_linear_solvers(*, direct: bool = False) -> list[str]:
    """The registered solvers whose libraries import here (``direct``: the direct ones)."""
    return [n for n, cls in LINEAR_SOLVERS.items()
            if not (direct and cls.iterative) and cls.available()]


def _auto(n_free_dofs: int, direct: bool) -> str:
    best: str | None = None
    for name in available_linear_solvers(direct=direct):
        threshold = LINEAR_SOLVERS[name].auto_min_free_dofs
        if threshold <= n_free_dofs and \
                (best is None or threshold > LINEAR_SOLVERS[best].auto_min_free_dofs):
            best = name
    if best is None:
        raise ImportError(f"no linear solver is installed (registered: "
                          f"{', '.join(LINEAR_SOLVERS)})")
    return best


def _checked(name: str, source: str) -> str:
    """``name`` when it is registered and imports; else the one-line error."""
    if name not in LINEAR_SOLVERS:
        choices = direct_solver_names() if source else linear_solver_names()
        raise ValueError(f"unknown linear solver {name!r}{source}; available: "
                         f"{', '.join(choices)}")
    if not LINEAR_SOLVERS[name].available():
        hint = getattr(LINEAR_SOLVERS[name], "install_hint", "")
        raise ImportError(f"linear solver {name!r}{source} is not installed"
                          + (f": {hint}" if hint else ""))
    return name


def resolve_linear_solver(name: str | None = AUTO, n_free_dofs: int = 0, *,
                          direct: bool = False) -> str:
    """The registered solver a choice stands for.

    Parameters
    ----------
    name : str or None
        ``"auto"`` (None) or a registered name.
    n_free_dofs : int
        The system's size (``"auto"`` picks by it).
    direct : bool
        A direct solver is needed (the linearly-implicit scheme's factorization): an
        iterative ``name`` stands for ``"auto"``'s direct choice.

    Returns
    -------
    str

    Raises
    ------
    ValueError
        An unknown name (of ``FEM3D_SOLVER`` too), naming the available ones.
    ImportError
        The solver's library is not installed (the line says how to install it).
    """
    name = (name or AUTO).strip().lower()
    if name != AUTO:
        _checked(name, "")
    env = os.environ.get(ENV_VAR, "").strip().lower()
    iterative = name != AUTO and LINEAR_SOLVERS[name].iterative
    if iterative and not direct:
        return name
    if env:
        if env not in direct_solver_names():
            raise ValueError(f"unknown linear solver {env!r} ({ENV_VAR}); available: "
                             f"{', '.join(direct_solver_names())}")
        return _checked(env, f" ({ENV_VAR})")
    if name == AUTO or iterative:
        return _auto(n_free_dofs, direct or iterative)
    return name


def make_linear_solver(name: str | None = AUTO, options: SolverOptions | None = None, *,
                       n_free_dofs: int = 0, direct: bool = False) -> LinearSolver:
    """A new solver for the choice ``name`` (:func:`resolve_linear_solver`), not analysed
    yet.

    Parameters
    ----------
    name, n_free_dofs, direct
        As :func:`resolve_linear_solver`.
    options : SolverOptions, optional
        What the solver may need (CHOLMOD's mode, AMG's vertex positions).
    """
    return LINEAR_SOLVERS[resolve_linear_solver(name, n_free_dofs, direct=direct)](options)
