"""Material registry: a material is one module exposing ``PARAM_NAMES`` and ``psi(F, params)``.

To add a material, write ``codegen/materials/<name>.py`` and add one line to ``MATERIALS``.
Everything else (stress, Hessian, element kernels, NumPy and C back ends, runtime dispatch,
the docs page) follows from the registry.

A material module declares:

* ``PARAM_NAMES``: its parameters (scalars per mesh, or per element at run time);
* ``psi(F, params)``: the strain energy density in SymPy (``params`` maps names to symbols,
  and each ``ELEMENT_INPUTS`` name to a matrix of symbols);
* ``from_E_nu(E, nu, params)``: its parameters from Young's modulus and Poisson's ratio,
  exact small-strain linear elasticity unless ``EXACT_SMALL_STRAIN = False``;
* ``SHAPE_PARAMS``: parameters that do not change the small-strain response (the user may
  set them next to ``E, nu``); ``ELEMENT_INPUTS`` (optional): per-element inputs such as a
  fibre direction, ``{name: shape}``; ``POSITIVE``: parameters that must be ``> 0``;
* ``ALLOWS_INVERSION`` (whether it is defined for ``J <= 0``: the line search then allows
  inverted tets) and ``INVERSION`` (what happens there, in words); ``DESCRIPTION``.
"""

from __future__ import annotations

from types import ModuleType

from codegen.materials import (
    fibre_reinforced,
    fung,
    linear,
    mooney_rivlin,
    neo_hookean,
    neo_hookean_lame,
    stable_neo_hookean,
    stvk,
)

MATERIALS: dict[str, ModuleType] = {
    "neo_hookean": neo_hookean,
    "stvk": stvk,
    "stable_neo_hookean": stable_neo_hookean,
    "mooney_rivlin": mooney_rivlin,
    "linear": linear,
    "fung": fung,
    "neo_hookean_lame": neo_hookean_lame,
    "fibre_reinforced": fibre_reinforced,
}
