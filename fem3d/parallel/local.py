"""A rank's own model: the tets the partition gave it, over the whole vertex numbering.

Built by :func:`~fem3d.physics.model.build_model` like any model (the same generated
kernels, material groups, mass and Rayleigh damping), so every term of it is the part of
the whole model's term that its tets contribute: summed over the ranks, energies,
gradients and Newton matrices are the whole model's.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from fem3d.physics.materials import info
from fem3d.physics.model import GroupData, MaterialGroup, Model, build_model
from fem3d.physics.terms.damping import RayleighDamping
from fem3d.physics.terms.gravity import Gravity
from fem3d.physics.terms.loads import Loads

__all__ = ["local_loads", "local_model"]


def _subset(value, rows: np.ndarray):
    """``value`` (a number, or one row per element of its group) at ``rows``."""
    return value if np.ndim(value) == 0 else np.asarray(value)[rows]


def _local_group(g: GroupData, mine: np.ndarray, local_of: np.ndarray) -> MaterialGroup | None:
    """Group ``g`` restricted to the tets ``mine`` (``local_of``: a tet's local index, -1
    for another rank's), or None when it has none of them."""
    elements = np.arange(g.n_tets) if g.elements is None else np.asarray(g.elements)
    keep = np.flatnonzero(local_of[elements] >= 0)
    if keep.size == 0:
        return None
    params = {name: _subset(value, keep) for name, value in g.values.items()}
    for name, value in zip(info(g.material).per_element_inputs, g.inputs, strict=True):
        params[name] = value[keep]
    return MaterialGroup(g.material, local_of[elements[keep]], params)


def local_model(model: Model, tets: np.ndarray) -> Model:
    """``model`` on its tets ``tets`` alone (every vertex kept, its numbering too).

    Parameters
    ----------
    model : Model
    tets : (k,) int64
        Sorted tet indices (one rank's).

    Returns
    -------
    Model
        The summary values ``E, nu, rho`` are the whole model's (Newton's absolute tolerance
        is made from them: every rank must use the same).
    """
    local_of = np.full(model.n_tets, -1, dtype=np.int64)
    local_of[tets] = np.arange(tets.size)
    groups = [g for g in (_local_group(g, tets, local_of) for g in model.groups)
              if g is not None]
    density = model.rho if model.density is None else model.density[tets]
    local = build_model(model.X, model.T[tets], groups=groups, density=density,
                        backend=model.backend)
    return replace(local, E=model.E, nu=model.nu, rho=model.rho,
                   psd_projection=model.psd_projection)


def local_loads(loads: Loads, model: Model, tets: np.ndarray) -> Loads:
    """``loads`` (of the whole model) for the local ``model`` of the tets ``tets``:
    gravity on its mass, Rayleigh damping on its mass and stiffness (a per-tet ``beta``
    restricted to ``tets``)."""
    beta = loads.rayleigh_beta
    beta = beta if np.ndim(beta) == 0 else np.asarray(beta)[tets]
    damping = RayleighDamping(model, loads.rayleigh_alpha, beta)
    gravity = None if loads.gravity is None else Gravity(model, loads.gravity.g)
    return Loads(gravity, damping if damping.active else None, loads.rayleigh_alpha, beta)
