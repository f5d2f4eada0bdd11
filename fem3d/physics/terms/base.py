"""The interface every term of a time step's objective shares, and the step's unknowns.

A time step minimises one objective ``E(x)`` over its unknowns ``x`` (backward Euler: the free
velocities). :class:`StepMap` says how ``x`` gives the positions and velocities of every
DOF; a :class:`Term` is one summand of ``E``, written either in the positions ``q(x)``
(``variable = "position"``: elasticity, pull springs, contact; an integrator applies the
chain rule ``dq/dx``) or in the unknowns themselves (``variable = "velocity"``: inertia,
gravity's work, Rayleigh dissipation). An integrator sums terms; it knows none by name.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, fields
from typing import Any, ClassVar, Protocol

import numpy as np
import scipy.sparse as sp

from fem3d.physics.constraints import Constraints

__all__ = ["StepMap", "NewtonPolicy", "Term", "HessianSink", "PositionTerm", "TermGroup",
           "as_term", "overrides"]


@dataclass(frozen=True, eq=False)
class StepMap:
    """The affine map from one step's unknowns ``x`` (free DOFs) to positions and velocities.

    ``q(x) = q_base + h P^T x`` and ``v(x) = P^T x + v_prescribed``, with ``P`` the selection
    of the free DOFs; the inertia term measures ``v(x) - v_hat``. Backward Euler: ``h = dt``,
    ``q_base = q_t`` with the pins at their end-of-step positions, ``v_hat = v_t``.

    Attributes
    ----------
    constraints : Constraints
    h : float
        ``dq / dx`` on the free DOFs.
    dt : float
        The time step.
    t : float
        Time at the start of the step.
    step : int
        Index of the step (steps taken before it).
    q_t, v_t : (3n,) float64
        Positions and velocities at the start of the step.
    q_base : (3n,) float64
        ``q(0)``: the positions with the free DOFs' unknowns at zero.
    v_hat_free : (n_free,) float64
        The inertia term's target velocity on the free DOFs.
    v_prescribed : (3n,) float64 or None
        Velocity of the fixed DOFs (moving pins; zero on free DOFs); None: pins at rest.
    dv_prescribed : (3n,) float64 or None
        Their velocity change over the step (``v_prescribed - v_hat`` on fixed DOFs).
    x_start : (n_free,) float64 or None
        The unknowns at which the free DOFs are at ``q_t`` (None: zero, as in backward
        Euler); Newton's admissible fallback start. BDF2 and Newmark extrapolate, so their
        ``q_base`` is not ``q_t``.
    """

    constraints: Constraints
    h: float
    dt: float
    t: float
    step: int
    q_t: np.ndarray
    v_t: np.ndarray
    q_base: np.ndarray
    v_hat_free: np.ndarray
    v_prescribed: np.ndarray | None = None
    dv_prescribed: np.ndarray | None = None
    x_start: np.ndarray | None = None

    def start_positions(self) -> np.ndarray:
        """``q(x_start)``: ``q_t`` with the pins at their end-of-step positions, ``(3n,)``."""
        return self.q_base if self.x_start is None else self.positions(self.x_start)

    def positions(self, x: np.ndarray) -> np.ndarray:
        """``q(x)``, ``(3n,)``."""
        return self.q_base + self.h * self.constraints.expand_zero(x)

    def velocity(self, x: np.ndarray) -> np.ndarray:
        """``v(x)``, ``(3n,)``."""
        v = self.constraints.expand_zero(x)
        return v if self.v_prescribed is None else v + self.v_prescribed

    def position_change(self, dx: np.ndarray) -> np.ndarray:
        """``dq`` of a change ``dx`` of the unknowns, ``(3n,)``."""
        return self.h * self.constraints.expand_zero(dx)


class HessianSink(Protocol):
    """Where a term adds its Hessian (:class:`fem3d.solve.newton_matrix.NewtonMatrixBuilder`).

    ``position_scale`` is ``h^2`` (the chain rule of a position term); ``psd`` asks for the
    PSD-projected element Hessians. Position terms add ``position_scale`` times their
    Hessian in positions, velocity terms their Hessian in the unknowns.
    """

    position_scale: float
    psd: bool

    def add_elements(self, model: Any, kernel: str, q: np.ndarray) -> None: ...

    def add_vertex_blocks(self, vertices: np.ndarray, blocks: np.ndarray,
                          scale: float) -> None: ...

    def add_pattern_values(self, values: np.ndarray, scale: float | None = None, *,
                           reduced: np.ndarray | None = None) -> None: ...

    def add_reduced_values(self, values: np.ndarray) -> None: ...

    def add_entries(self, H: Any, scale: float) -> None: ...


@dataclass(frozen=True)
class NewtonPolicy:
    """What a term asks of the Newton solve that minimises a step (beyond its value and
    derivatives). The minimiser reads the policy of the step's active terms, combined
    (:meth:`combine`: a field is on when any term's is); a new potential sets its own policy
    object, and a new kind of request is one more field here, not a flag on :class:`Term`.

    Attributes
    ----------
    stiff : bool
        A term stiffens by orders of magnitude within a step (a log barrier at contact): a
        scheme without numerical dissipation (Newmark) damps its highest modes while it is
        active, and Newton tries no extrapolated warm start.
    restart_when_clamped : bool
        When a term's ``max_step`` cuts the way from the scheme's start ``x_start`` to its
        target ``v_hat`` (free flight into a contact), Newton starts at ``x_start`` itself
        (backward Euler: ``q_t``) instead of the clamped target, whose contacts are squeezed
        to a tenth of their gap and more (IPC's own start).
    accept_first_step : bool
        A term's stopping rule (:meth:`Term.newton_converged`) also judges Newton's first
        direction: one that passes is taken and ends the solve, where a second direction
        would otherwise confirm it (one factorization instead of two in a resting step).
    """

    stiff: bool = False
    restart_when_clamped: bool = False
    accept_first_step: bool = False

    @classmethod
    def combine(cls, policies: Iterable[NewtonPolicy]) -> NewtonPolicy:
        """The policy of several terms: each field on when it is on in any of ``policies``."""
        policies = list(policies)
        return cls(**{f.name: any(getattr(p, f.name) for p in policies) for f in fields(cls)})


class Term:
    """One summand of a time step's objective; subclasses override what they have.

    ``u`` below is what the term is written in: the positions ``q (3n,)`` for
    ``variable = "position"``, the step's unknowns ``x`` for ``variable = "velocity"``.
    Velocity terms read the step's :class:`StepMap` from :meth:`begin_step`.

    Attributes
    ----------
    name : str
        What statistics and error messages call it.
    variable : {"position", "velocity"}
    requires_convergence : bool
        The step runs Newton to its tolerance instead of the iteration cap (contact).
    allows_lagged_matrix : bool
        A Newton matrix of one iterate may serve the next (False where the term changes
        between iterates, e.g. an adaptive barrier stiffness).
    newton_policy : NewtonPolicy
        What the term asks of the Newton solve (default: nothing).
    inertial, dissipative : bool
        The term is the kinetic (mass) term, or a dissipation in the velocities: a static
        equilibrium leaves both out, an initial acceleration ``M a = f`` every inertial one.
    active : bool
        Whether the term takes part in the next step (checked once per step).
    energy_scale : float
        The size of the term's summands when they cancel (the elastic energy near rest sums
        element energies of about ``E vol`` each to much less): the line search judges
        round-off against it.
    """

    name: ClassVar[str] = "term"
    variable: ClassVar[str] = "position"
    requires_convergence: ClassVar[bool] = False
    allows_lagged_matrix: ClassVar[bool] = True
    newton_policy: NewtonPolicy = NewtonPolicy()
    inertial: ClassVar[bool] = False
    dissipative: ClassVar[bool] = False
    energy_scale: float = 0.0

    @property
    def active(self) -> bool:
        """Whether the term takes part in the next step (e.g. a pull term without springs
        does not); checked once per step."""
        return True

    def energy(self, u: np.ndarray) -> float:
        """The term's value (``+inf``: an inadmissible point)."""
        raise NotImplementedError

    def gradient(self, u: np.ndarray) -> np.ndarray:
        """``dE/du``: ``(3n,)`` for a position term, ``(n_free,)`` for a velocity term."""
        raise NotImplementedError

    def add_hessian(self, u: np.ndarray, sink: HessianSink) -> None:
        """Add the term's Hessian to the Newton matrix (default: none, a linear term)."""

    def max_step(self, q: np.ndarray, dq: np.ndarray) -> float:
        """Largest admissible fraction of the position change ``dq`` from ``q`` (CCD)."""
        return 1.0

    def begin_step(self, step: StepMap) -> None:
        """Called once before each step's Newton iterations (lagging, per-step data)."""

    def initialize_stiffness(self, q: np.ndarray, grad_rest: np.ndarray,
                             average_mass: float) -> None:
        """Called at the Newton start with the gradient of the rest of the objective (in
        positions, per unit ``h``)."""

    def after_iteration(self, q: np.ndarray) -> bool:
        """Called at every accepted iterate; True when the term's energy changed there."""
        return False

    def newton_converged(self, dq: np.ndarray) -> bool | None:
        """A further stopping rule on a Newton step's position change ``dq`` (None: no
        opinion)."""
        return None

    def relag(self, q: np.ndarray) -> bool:
        """Called when Newton has converged at ``q``; True: the term lagged its data again
        there and asks for another Newton solve (friction's re-lagging)."""
        return False

    def with_model(self, model: Any) -> Term:
        """The term for a model with new material values (default: itself)."""
        return self


class PositionTerm(Term):
    """A plain object with ``energy(q)``, ``gradient(q)`` and optionally ``hessian(q)``,
    ``max_step(q, dq)``, ``begin_step(step)``, ``after_iteration(q)``,
    ``newton_converged(dq)``, ``initialize_stiffness(...)`` and ``requires_convergence``,
    as a position :class:`Term` (the protocol user terms and tests write)."""

    def __init__(self, obj: Any) -> None:
        self.obj = obj
        self.name = type(obj).__name__
        self.requires_convergence = bool(getattr(obj, "requires_convergence", False))
        self.allows_lagged_matrix = False  # nothing known about how it changes
        self.energy = obj.energy
        self.gradient = obj.gradient
        for hook in ("max_step", "begin_step", "initialize_stiffness", "after_iteration",
                     "newton_converged"):
            if callable(getattr(obj, hook, None)):
                setattr(self, hook, getattr(obj, hook))

    def add_hessian(self, q: np.ndarray, sink: HessianSink) -> None:
        hessian = getattr(self.obj, "hessian", None)
        if callable(hessian):
            sink.add_entries(hessian(q), sink.position_scale)


class TermGroup(Term):
    """Terms that enter the objective as one summand: their energies and gradients are
    added among themselves first, in order, and their Hessian entries outside the mesh's
    pattern are added in one go (one widening of the solver's pattern). Members that share
    state (a contact set and its stiffness: barrier and friction) form a group; every member
    keeps its own hooks, called in order.

    Parameters
    ----------
    terms : sequence of Term
        All of one ``variable``.
    """

    name = "group"

    def __init__(self, terms) -> None:
        self.terms = list(terms)
        variables = {t.variable for t in self.terms}
        if len(variables) != 1:
            raise ValueError(f"a term group needs one variable, got {sorted(variables)}")
        self.variable = variables.pop()
        self.requires_convergence = any(t.requires_convergence for t in self.terms)
        self.allows_lagged_matrix = all(t.allows_lagged_matrix for t in self.terms)
        self.newton_policy = NewtonPolicy.combine(t.newton_policy for t in self.terms)
        self.energy_scale = sum(t.energy_scale for t in self.terms)

    @property
    def active(self) -> bool:
        return any(t.active for t in self.terms)

    def energy(self, u: np.ndarray) -> float:
        e = 0.0
        for term in self.terms:
            e += float(term.energy(u))
            if not math.isfinite(e):
                return math.inf
        return e

    def gradient(self, u: np.ndarray) -> np.ndarray:
        g = np.array(self.terms[0].gradient(u), dtype=np.float64)
        for term in self.terms[1:]:
            g += term.gradient(u)
        return g

    def add_hessian(self, u: np.ndarray, sink: HessianSink) -> None:
        gathered = _GatheredEntries(sink)
        for term in self.terms:
            term.add_hessian(u, gathered)
        gathered.flush()

    def max_step(self, q: np.ndarray, dq: np.ndarray) -> float:
        return min([1.0] + [float(t.max_step(q, dq)) for t in self.terms
                            if overrides(t, "max_step")])

    def begin_step(self, step: StepMap) -> None:
        for term in self.terms:
            term.begin_step(step)

    def initialize_stiffness(self, q: np.ndarray, grad_rest: np.ndarray,
                             average_mass: float) -> None:
        for term in self.terms:
            term.initialize_stiffness(q, grad_rest, average_mass)

    def after_iteration(self, q: np.ndarray) -> bool:
        return any([t.after_iteration(q) for t in self.terms])

    def newton_converged(self, dq: np.ndarray) -> bool | None:
        votes = [t.newton_converged(dq) for t in self.terms if overrides(t, "newton_converged")]
        return None if not votes else all(v is None or bool(v) for v in votes)

    def relag(self, q: np.ndarray) -> bool:
        return any([t.relag(q) for t in self.terms])

    def with_model(self, model: Any) -> TermGroup:
        terms = [t.with_model(model) for t in self.terms]
        if all(a is b for a, b in zip(terms, self.terms, strict=True)):
            return self
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        new.terms = terms
        return new


class _GatheredEntries:
    """A Hessian sink that passes everything through except ``add_entries``, which it keeps
    to add once (:meth:`flush`): concatenated triplets, each pre-scaled."""

    def __init__(self, sink: HessianSink) -> None:
        self._sink = sink
        self.position_scale = sink.position_scale
        self.psd = sink.psd
        self._entries: list[tuple[Any, float]] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sink, name)

    def add_entries(self, H: Any, scale: float) -> None:
        self._entries.append((H, scale))

    def flush(self) -> None:
        if len(self._entries) == 1:
            self._sink.add_entries(*self._entries[0])
        elif self._entries:
            rows, cols, vals = [], [], []
            for H, scale in self._entries:
                if H is None:
                    continue
                if sp.issparse(H):
                    H = sp.coo_matrix(H)
                    H = (H.row, H.col, H.data)
                rows.append(np.asarray(H[0]))
                cols.append(np.asarray(H[1]))
                vals.append(scale * np.asarray(H[2], dtype=np.float64))
            self._sink.add_entries((np.concatenate(rows), np.concatenate(cols),
                                    np.concatenate(vals)), 1.0)
        self._entries = []


def overrides(term: Term, hook: str) -> bool:
    """Whether ``term`` has its own ``hook`` (not :class:`Term`'s default)."""
    return hook in vars(term) or getattr(type(term), hook) is not getattr(Term, hook)


def as_term(obj: Any) -> Term:
    """``obj`` itself when it is a :class:`Term`, else wrapped as a :class:`PositionTerm`."""
    return obj if isinstance(obj, Term) else PositionTerm(obj)
