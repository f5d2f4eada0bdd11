"""Follower pressure on a triangle of the current surface, as a potential (issue 43).

A pressure ``p`` pushing on the surface against its outward normal ``n`` (positive pushes in)
does the work ``-p dV`` when the body's volume changes by ``dV``; its potential is ``p V``
with ``V = sum_f (1/6) x_0 . (x_1 x x_2)``, the signed volume of the cone from the origin over
each loaded triangle ``(x_0, x_1, x_2)`` (counter-clockwise seen from outside). The force on
a vertex is ``-dV/dx``: ``-p/3`` of the area-weighted normals of the triangles around it
(the consistent nodal load of linear triangles) where the loaded surface is closed around
the vertex; along the edge of an open loaded patch the potential adds ``p (x - o) x
(edge) / 6`` (``o`` the origin), which does no work where the edge slides in planes through
the origin (symmetry planes) or is held.

Kernels (vectorized over triangles, as every generated module): ``energy``, ``gradient``
(9: d/dx_0, d/dx_1, d/dx_2) and ``hessian`` (9 x 9, symmetric, indefinite: zero trace),
derived by SymPy from the one expression in :func:`face_potential`.
"""

from __future__ import annotations

import sympy as sp

from codegen.conventions import flatten, symbol_matrix
from codegen.spec import Argument, ModuleSpec, make_kernel

__all__ = ["face_potential", "pressure_raw", "pressure_module", "DOCS"]

DOCS = {
    "energy": "Pressure potential p/6 x_0 . (x_1 x x_2) of one triangle.",
    "gradient": "Its gradient (d/dx_0, d/dx_1, d/dx_2), length 9.",
    "hessian": "Its Hessian (9x9, symmetric, indefinite).",
}


def face_potential(x: sp.Matrix, p: sp.Symbol) -> sp.Expr:
    """``p/6 x_0 . (x_1 x x_2)``: ``p`` times the signed volume of the cone from the origin
    over the triangle whose vertices are the rows of ``x`` (3 x 3)."""
    x0, x1, x2 = (x[i, :].T for i in range(3))
    return p / 6 * x0.dot(x1.cross(x2))


def pressure_raw() -> dict[str, tuple[list[Argument], list[Argument], list[tuple]]]:
    """The exact (un-CSE'd) outputs of each kernel, with its inputs and parameters."""
    x = symbol_matrix("x", 3, 3)
    p = sp.Symbol("p", real=True)
    energy = face_potential(x, p)
    dofs = flatten(x)
    gradient = [sp.diff(energy, s) for s in dofs]
    hessian = [sp.diff(g, s) for g in gradient for s in dofs]
    inputs = [Argument("x_f", (3, 3), tuple(dofs), doc="triangle vertices (rows), current")]
    params = [Argument("p", (), (p,), per_element=False)]
    return {
        "energy": (inputs, params, [("energy", (), [energy], False)]),
        "gradient": (inputs, params, [("gradient", (9,), gradient, False)]),
        "hessian": (inputs, params, [("hessian", (9, 9), hessian, True)]),
    }


def pressure_module() -> ModuleSpec:
    """The ``pressure`` module: the kernels of :func:`pressure_raw`."""
    kernels = tuple(make_kernel("pressure", name, DOCS[name], inputs, params, outputs)
                    for name, (inputs, params, outputs) in pressure_raw().items())
    return ModuleSpec(name="pressure", doc="follower pressure on a surface triangle",
                      source=__name__, param_names=("p",), kernels=kernels)
