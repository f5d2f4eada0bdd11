"""What the multi-step and static schemes share: an affine :class:`StepMap` from the
scheme's ``h``, base offset and inertia target, and the state at the end of the step.

Pins (fixed DOFs) are not unknowns: every scheme puts them at their end-of-step positions
``p`` and gives them the secant velocity ``(p - q_t) / dt`` (backward Euler's), so keyframed
pins drive each scheme the same way.
"""

from __future__ import annotations

import numpy as np

from fem3d.errors import ParameterError
from fem3d.physics.terms.base import StepMap
from fem3d.solve.state import State
from fem3d.solve.system import System

__all__ = ["affine_step_map", "fixed_dofs", "end_positions"]


def fixed_dofs(system: System) -> np.ndarray:
    """``(k,)`` the fixed DOFs (:attr:`Constraints.fixed_dofs`)."""
    return system.constraints.fixed_dofs


def end_positions(system: System, state: State, fixed_positions) -> np.ndarray:
    """The fixed vertices at the end of the step, ``(n_fixed, 3)`` (None: where they are).

    Raises
    ------
    ParameterError
        Wrong shape or non-finite.
    """
    fv = system.constraints.fixed_vertices
    if fixed_positions is None:
        return state.q[fv]
    p = np.array(fixed_positions, dtype=np.float64)
    if p.shape != (fv.size, 3):
        raise ParameterError(f"fixed_positions must have shape ({fv.size}, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise ParameterError("fixed_positions are not finite")
    return p


def affine_step_map(system: System, state: State, dt: float, p: np.ndarray, *, h: float,
                    offset: np.ndarray | None, v_hat: np.ndarray,
                    moving_pins: bool = True) -> StepMap:
    """``q(x) = q_t + offset + h P^T x`` (pins at ``p``), inertia toward ``v_hat``.

    Parameters
    ----------
    system : System
    state : State
        The state at the start of the step.
    dt : float
    p : (n_fixed, 3) float64
        The fixed vertices at the end of the step (:func:`end_positions`).
    h : float
        ``dq/dx``.
    offset : (3n,) float64 or None
        ``q_base - q_t`` on the free DOFs (None: zero; its fixed entries are not used).
    v_hat : (3n,) float64
        The inertia target over every DOF (its fixed entries give the pins' velocity change).
    moving_pins : bool, optional
        False: the pins get no velocity (the static scheme's unknowns are displacements).

    Returns
    -------
    StepMap
        ``x_start = -offset / h`` on the free DOFs (None without an offset).
    """
    c = system.constraints
    q_t = state.q.reshape(-1)
    fd = fixed_dofs(system)
    p_fixed = p.reshape(-1)[c.fixed_slots]
    q_base = q_t.copy() if offset is None else q_t + offset
    q_base[fd] = p_fixed
    v_prescribed = dv = None
    if fd.size and moving_pins:
        vp = np.zeros(c.n_dofs)
        vp[fd] = (p_fixed - q_t[fd]) / dt
        if np.any(vp):
            v_prescribed = vp
        d = np.zeros(c.n_dofs)
        d[fd] = vp[fd] - v_hat[fd]
        if np.any(d):
            dv = d
    x_start = None if offset is None else -offset[c.free_dofs] / h
    return StepMap(constraints=c, h=h, dt=dt, t=state.t, step=state.step, q_t=q_t,
                   v_t=state.v.reshape(-1), q_base=q_base,
                   v_hat_free=np.ascontiguousarray(v_hat[c.free_dofs]),
                   v_prescribed=v_prescribed, dv_prescribed=dv, x_start=x_start)
