"""Newton's settings: one frozen object, built once (from the scene's ``simulation.newton``)
and handed to every scheme, :func:`fem3d.solve.minimise.minimise_step` and the Newton
directions (:mod:`fem3d.solve.directions`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

__all__ = ["NewtonSettings", "DIRECTION_NAMES", "WARM_STARTS", "LINE_SEARCHES",
           "AMG_ITERATIONS_PER_DECADE", "FORCING_MAX"]

#: The Newton directions by name (:data:`fem3d.solve.directions.DIRECTIONS`).
DIRECTION_NAMES = ("direct", "reuse", "amg")

#: Where backward Euler's Newton starts (``warm_start``): ``"previous"`` at the last step's
#: velocity ``v_t`` (the classic start); ``"extrapolate"`` at the lower-energy of ``v_t`` and
#: the linear extrapolation ``2 v_t - v_t-1`` (constant acceleration), the state carrying
#: ``v_t-1`` in its history from step to step. On a smooth drag the extrapolated start is
#: often within one Newton iteration of the solution (``python -m bench.newton_step
#: --warm-start extrapolate``); it changes the trajectory only at the Newton tolerance's level.
#: Objectives with contact (a CCD-limited or stiff-barrier term) keep the classic start.
WARM_STARTS = ("previous", "extrapolate")

#: The line searches of :func:`fem3d.solve.newton.newtons_method`: ``"backtrack"`` accepts the
#: first trial of ``a0, a0 p, a0 p^2, ...`` that passes Armijo's test; ``"parabolic"`` does the
#: same and then, when that took a halving, moves the accepted step to the minimum of the
#: parabola through the energies at the bracket ``0 < a < a / p``.
LINE_SEARCHES = ("backtrack", "parabolic")

#: ``"amg"``: rebuild the hierarchy when a solve needs more CG iterations than this per decade
#: of residual reduction (a fresh hierarchy needs about 3-4 on the swinging box; a setup costs
#: about 15 iterations).
AMG_ITERATIONS_PER_DECADE = 8.0
#: ``"amg"``: the loosest forcing term (relative CG residual) of the inexact Newton.
FORCING_MAX = 0.1


@dataclass(frozen=True)
class NewtonSettings:
    """How every step's Newton solve runs (the same object for every scheme).

    Attributes
    ----------
    max_iterations : int or None
        The scene's ``simulation.newton.max_iterations`` (default 5). ``implicit``, ``bdf2``,
        ``newmark``: Newton iterations per step, the step keeping its last iterate (None: until
        converged); a term that ``requires_convergence`` (contact) raises it to
        ``converged_max_iterations``. ``static``: per load increment, an increment that does
        not converge within it being halved (None: ``converged_max_iterations``, 50).
        ``linear``: not used (one linear solve per step).
    rtol, atol_factor : float
        The scene's ``simulation.newton.tolerance`` (default ``1e-10``): the gradient
        tolerance relative to its norm at Newton's start; and the absolute floor as a
        fraction of ``h E L^2`` (``L`` the diagonal of the rest bounding box, ``h`` the
        scheme's ``dq/dx``): ``1e-12`` for the dynamic schemes; ``static`` replaces it by
        :data:`fem3d.solve.static.STATIC_ATOL_FACTOR` (``1e-15``, ``h = 1``). Neither is used
        by ``linear``.
    solver : {"direct", "reuse", "amg"}
        The Newton direction (:mod:`fem3d.solve.directions`); a system whose linear back end
        is AMG always uses ``"amg"``.
    converged_max_iterations : int or None
        The cap of a solve run to convergence (None: the scheme's own,
        :attr:`fem3d.solve.schemes.base.Scheme.converged_max_iterations`: 100, static 50).
    psd : bool
        Per-element ``dP/dF`` projected to positive semi-definite (generated ``hessian_psd``):
        always SPD, linear convergence near the solution (``hessian = "psd"``).
    cg_rtol, cg_maxiter : float, int
        ``"reuse"``: the tightest relative CG residual, and CG iterations per solve before
        refactorizing (16: about the cost of one factorization on armadillo-class meshes).
    amg_maxiter, amg_budget, forcing_max : int, float, float
        ``"amg"``: CG iterations per solve, the rebuild threshold in iterations per decade
        and the loosest forcing term.
    warm_start : {"previous", "extrapolate"}
        Newton's start (:data:`WARM_STARTS`; backward Euler only).
    line_search : {"backtrack", "parabolic"}
        :data:`LINE_SEARCHES`.

    Raises
    ------
    ValueError
        A name outside its choices.
    """

    max_iterations: int | None = 5
    rtol: float = 1e-10
    atol_factor: float = 1e-12
    solver: str = "direct"
    converged_max_iterations: int | None = None
    psd: bool = False
    cg_rtol: float = 1e-6
    cg_maxiter: int = 16
    amg_maxiter: int = 200
    amg_budget: float = AMG_ITERATIONS_PER_DECADE
    forcing_max: float = FORCING_MAX
    warm_start: str = "previous"
    line_search: str = "backtrack"

    def __post_init__(self) -> None:
        for name, value, choices in (("linear_solver", self.solver, DIRECTION_NAMES),
                                     ("warm_start", self.warm_start, WARM_STARTS),
                                     ("line_search", self.line_search, LINE_SEARCHES)):
            if value not in choices:
                raise ValueError(f"{name} must be one of {', '.join(choices)}, got {value!r}")

    @classmethod
    def make(cls, hessian: str = "exact", linear_solver: str = "direct",
             **settings) -> NewtonSettings:
        """The settings with the Hessian and the direction named as the scene names them.

        Parameters
        ----------
        hessian : {"exact", "psd"}, optional
        linear_solver : {"direct", "reuse", "amg"}, optional
        **settings
            Any other attribute.
        """
        if hessian not in ("exact", "psd"):
            raise ValueError(f"hessian must be 'exact' or 'psd', got {hessian!r}")
        return cls(psd=hessian == "psd", solver=linear_solver, **settings)

    @classmethod
    def from_spec(cls, newton) -> NewtonSettings:
        """The settings of a scene's ``simulation.newton`` (:class:`fem3d.scene.spec.
        NewtonSpec`: ``max_iterations``, ``tolerance``, ``hessian``, ``solver``,
        ``warm_start``, ``line_search``)."""
        return cls.make(newton.hessian, newton.solver, max_iterations=newton.max_iterations,
                        rtol=newton.tolerance, warm_start=newton.warm_start,
                        line_search=newton.line_search)

    def with_(self, **changes) -> NewtonSettings:
        """A copy with ``changes``."""
        return replace(self, **changes)

    def converged_cap(self, default: int) -> int:
        """:attr:`converged_max_iterations`, or the scheme's ``default`` when it is None."""
        return default if self.converged_max_iterations is None else \
            self.converged_max_iterations
