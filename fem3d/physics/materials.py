"""The material library at run time: names, what each material is, its parameters from E, nu.

Everything here is read from the generated kernel modules (``generated/numpy/<name>.py``),
which the generator renders from ``codegen/materials/<name>.py``: the runtime never names a
material itself. ``python -m codegen show <name>`` prints a material's formulas, and
``docs/materials.md`` lists them all.

Examples
--------
>>> names()                                         # doctest: +SKIP
['fibre_reinforced', 'fung', 'linear', 'mooney_rivlin', 'neo_hookean', ...]
>>> parameters_from("stable_neo_hookean", E=1e5, nu=0.3)   # doctest: +SKIP
{'mu': 51282.05..., 'lam': 89743.58...}
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cache
from types import ModuleType

import numpy as np

from fem3d._generated import MATERIALS
from fem3d.errors import ParameterError
from fem3d.kernels.dispatch import material_kernels

__all__ = ["MaterialInfo", "info", "names", "parameters_from", "parameters_jacobian_from",
           "validate_E_nu"]


@dataclass(frozen=True)
class MaterialInfo:
    """What a registered material is (read from its generated module).

    Attributes
    ----------
    name : str
        Registry name (``fem3d run --material NAME``).
    param_names : tuple of str
        Kernel parameters, in kernel order.
    allows_inversion : bool
        Whether the energy is defined for ``J <= 0`` (the line search then accepts inverted
        tets); declared by the material file.
    per_element_inputs : dict of str -> tuple of int
        Inputs every element carries besides its parameters (e.g. ``{"a": (3,)}``, a fibre
        direction); a :class:`fem3d.physics.model.MaterialGroup` gives them as ``(k, *shape)`` or as
        one ``shape`` value for all its elements.
    doc : str
        The material file's docstring (formula, source, notes).
    description : str
        One line: name and formula.
    shape_params : tuple of str
        Parameters that do not change the small-strain response: they may be given next to
        ``E, nu``.
    positive : tuple of str
        Parameters that must be ``> 0``.
    exact_small_strain : bool
        Whether :func:`parameters_from` with ``E, nu`` gives exactly the linear elasticity of
        ``E, nu`` at small strain (False only for the assignment's ``neo_hookean``).
    rotation_invariant : bool
        ``psi(R F) = psi(F)`` (False for small-strain ``linear``).
    inversion : str
        What happens at ``J <= 0``, in words.
    psi : str
        The strain energy density as text.
    mapping : dict of str -> str
        Each parameter as a formula of ``E`` and ``nu``.
    """

    name: str
    param_names: tuple[str, ...]
    allows_inversion: bool
    per_element_inputs: dict[str, tuple[int, ...]]
    doc: str
    description: str = ""
    shape_params: tuple[str, ...] = ()
    positive: tuple[str, ...] = ()
    exact_small_strain: bool = True
    rotation_invariant: bool = True
    inversion: str = ""
    psi: str = ""
    mapping: dict[str, str] = field(default_factory=dict)


def names() -> list[str]:
    """Names of every registered (generated) material, sorted."""
    return sorted(MATERIALS)


def _module(name: str) -> ModuleType:
    if name not in MATERIALS:
        raise ParameterError(f"unknown material {name!r}; available: {', '.join(names())}")
    return importlib.import_module(f"fem3d._generated.{name}")


@cache
def info(name: str) -> MaterialInfo:
    """The :class:`MaterialInfo` of material ``name`` (ParameterError when unknown)."""
    mod = _module(name)
    return MaterialInfo(
        name=name,
        param_names=tuple(mod.PARAM_NAMES),
        allows_inversion=bool(mod.ALLOWS_INVERSION),
        per_element_inputs={n: tuple(s) for n, s in mod.ELEMENT_INPUTS},
        doc=mod.DOC,
        description=mod.DESCRIPTION,
        shape_params=tuple(mod.SHAPE_PARAMS),
        positive=tuple(mod.POSITIVE),
        exact_small_strain=bool(mod.EXACT_SMALL_STRAIN),
        rotation_invariant=bool(mod.ROTATION_INVARIANT),
        inversion=mod.INVERSION,
        psi=mod.PSI,
        mapping=dict(mod.MAPPING),
    )


def validate_E_nu(E, nu):
    """Check Young's modulus (finite, ``> 0``) and Poisson's ratio (``-1 < nu < 0.5``).

    Scalars or arrays (per-element fields); returns them as floats or float64 arrays.
    """
    E_a, nu_a = np.asarray(E, dtype=np.float64), np.asarray(nu, dtype=np.float64)
    if not (np.isfinite(E_a).all() and (E_a > 0).all()):
        bad = E_a.flat[int(np.flatnonzero(~(np.isfinite(E_a) & (E_a > 0)).ravel())[0])]
        raise ParameterError(f"Young's modulus E must be a finite number > 0, got {bad}")
    if not (np.isfinite(nu_a).all() and ((nu_a > -1.0) & (nu_a < 0.5)).all()):
        ok = np.isfinite(nu_a) & (nu_a > -1.0) & (nu_a < 0.5)
        bad = nu_a.flat[int(np.flatnonzero(~ok.ravel())[0])]
        raise ParameterError(f"Poisson's ratio nu must satisfy -1 < nu < 0.5, got {bad}")
    return _plain(E_a), _plain(nu_a)


def _plain(a: np.ndarray):
    return float(a) if a.ndim == 0 else a


def parameters_from(
    name: str,
    E: float | np.ndarray | None = None,
    nu: float | np.ndarray | None = None,
    params: Mapping[str, float | np.ndarray] | None = None,
) -> dict[str, float | np.ndarray]:
    """A material's own parameters from ``E, nu`` and/or given values.

    Parameters
    ----------
    name : str
        Registered material.
    E, nu : float or (k,) array, optional
        Young's modulus and Poisson's ratio (both or neither). The material's mapping makes
        it exactly the linear elasticity of ``E, nu`` at small strain (every material but
        the assignment's ``neo_hookean``, whose mapping ``C = mu/2, D = lambda/2`` is fixed:
        its small-strain Lame ``lambda`` is ``2 D - 4 C / 3``).
    params : mapping, optional
        The material's own parameters by name (floats or per-element ``(k,)`` arrays).
        With ``E, nu``: only the ``shape_params`` (those that do not change the small-strain
        response, e.g. Fung's ``b``); without: every parameter.

    Returns
    -------
    dict of str -> float or (k,) float64
        Every parameter in ``info(name).param_names`` order.

    Raises
    ------
    ParameterError
        Unknown material or parameter, a parameter set twice (by ``E, nu`` and by name), a
        missing one, or a value out of range; the message names the parameter.
    """
    mod = _module(name)
    material = info(name)
    given = dict(params or {})
    for key in given:
        if key not in material.param_names:
            raise ParameterError(f"material {name!r} has no parameter {key!r}; its parameters: "
                                 f"{', '.join(material.param_names)} (or E and nu)")
    if (E is None) != (nu is None):
        missing = "nu" if nu is None else "E"
        raise ParameterError(f"material {name!r}: E and nu go together; {missing} is missing")
    if E is not None:
        E, nu = validate_E_nu(E, nu)
        for key in given:
            if key not in material.shape_params:
                raise ParameterError(
                    f"material {name!r}: parameter {key!r} is set by E and nu; give either "
                    f"E and nu or {key} (free next to E and nu: "
                    f"{', '.join(material.shape_params) or 'none'})")
        values = {k: v for k, v in mod.parameters_from_E_nu(E, nu).items()}
        values.update(given)
    else:
        missing = [p for p in material.param_names if p not in given]
        if missing:
            raise ParameterError(f"material {name!r} needs E and nu, or all of its parameters; "
                                 f"missing: {', '.join(missing)}")
        values = given
    out: dict[str, float | np.ndarray] = {}
    for key in material.param_names:
        a = np.asarray(values[key], dtype=np.float64)
        if a.ndim > 1:
            raise ParameterError(f"material {name!r}: parameter {key!r} must be a number or a "
                                 f"per-element (k,) array, got shape {a.shape}")
        if not np.isfinite(a).all():
            raise ParameterError(f"material {name!r}: parameter {key!r} must be finite, got "
                                 f"{a.flat[int(np.flatnonzero(~np.isfinite(a).ravel())[0])]}")
        if key in material.positive and not (a > 0).all():
            raise ParameterError(f"material {name!r}: parameter {key!r} must be > 0, got "
                                 f"{a.flat[int(np.flatnonzero(~(a > 0).ravel())[0])]}")
        out[key] = _plain(a)
    return out


def parameters_jacobian_from(name: str, E, nu) -> dict[str, tuple]:
    """``{p: (dp/dE, dp/dnu)}`` of the material's ``E, nu`` mapping (:func:`parameters_from`),
    in ``info(name).param_names`` order.

    The mapping is symbolic in the generator (``codegen/materials/<name>.py: from_E_nu``):
    its derivatives are SymPy's, rendered into the generated module next to the mapping
    (``parameters_jacobian_from_E_nu``). Shape parameters (e.g. Fung's ``b``) have zero
    derivatives. Scalars give floats, ``(k,)`` arrays give ``(k,)`` arrays.
    """
    mod = _module(name)
    E, nu = validate_E_nu(E, nu)
    shape = np.broadcast(np.asarray(E), np.asarray(nu)).shape
    jac = mod.parameters_jacobian_from_E_nu(E, nu)
    return {p: tuple(_plain(np.broadcast_to(np.asarray(d, dtype=np.float64), shape).copy())
                     for d in jac[p]) for p in info(name).param_names}


def small_strain_lame(name: str, values: Mapping[str, float | np.ndarray],
                      inputs: Mapping[str, np.ndarray] | None = None) -> tuple:
    """Effective small-strain Lame parameters ``(mu, lambda)`` of a material with parameter
    ``values``, read from its generated ``d2psi_dF2`` at ``F = I`` (``mu = dP_12/dF_12``,
    ``lambda = dP_11/dF_22``; fibres along x do not enter either)."""
    material = info(name)
    columns = [np.asarray(values[p], dtype=np.float64) for p in material.param_names]
    given = {n: np.asarray(v, dtype=np.float64) for n, v in (inputs or {}).items()}
    per_element = [a.shape[0] for n, a in given.items()
                   if a.ndim == 1 + len(material.per_element_inputs.get(n, ()))]
    scalar = all(c.ndim == 0 for c in columns) and not per_element
    k = max([c.size for c in columns] + per_element)
    P = np.stack([np.broadcast_to(c.reshape(-1) if c.ndim else c, (k,)) for c in columns], 1)
    extra = []
    for n, shape in material.per_element_inputs.items():
        if n not in given:
            a = np.zeros((k, *shape))
            a.reshape(k, -1)[:, 0] = 1.0
        else:
            a = np.broadcast_to(given[n], (k, *shape))
        extra.append(a)
    A = material_kernels(name, "numpy").d2psi_dF2(np.broadcast_to(np.eye(3), (k, 3, 3)),
                                                  *extra, P)
    mu, lam = A[:, 5, 5], A[:, 4, 8]
    return (float(mu[0]), float(lam[0])) if scalar else (mu, lam)


def lame_to_E_nu(mu, lam):
    """Young's modulus and Poisson's ratio of Lame parameters (scalars or arrays)."""
    return mu * (3 * lam + 2 * mu) / (lam + mu), lam / (2 * (lam + mu))
