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

Quadratic (6-node) faces of P2 tets (nodes: corners ``a, b, c``, then the edge nodes ``ab,
bc, ca``; :func:`face_shape_functions`) have the same potential on the curved triangle
``x(xi, eta) = sum_i N_i x_i``: ``p/3 integral x . (x_xi x x_eta) dxi deta`` (the cone volume
by the divergence theorem; ``p/6 x_0 . (x_1 x x_2)`` for a flat face with mid-edge nodes),
integrated exactly term by term (:func:`integrate_triangle`): ``p2_energy``,
``p2_gradient`` (18), ``p2_hessian`` (18 x 18). ``p2_follower_load`` (18) is the consistent
follower load of unit pressure ``-integral N_i (x_xi x x_eta)`` (what the potential's force
is on a closed surface: the runtime's check of open patches), and ``p2_traction_weights``
(6) the consistent nodal weights of a dead traction, ``integral N_i |X_xi x X_eta|`` by
Radon's 7-point rule of degree 5 (exact for a flat face: corners 0, edge nodes ``A/3``).
"""

from __future__ import annotations

import sympy as sp

from codegen.conventions import flatten, symbol_matrix
from codegen.spec import Argument, ModuleSpec, make_kernel

__all__ = ["face_potential", "face_shape_functions", "integrate_triangle",
           "quadratic_face_potential", "pressure_raw", "pressure_module", "DOCS"]

DOCS = {
    "energy": "Pressure potential p/6 x_0 . (x_1 x x_2) of one triangle.",
    "gradient": "Its gradient (d/dx_0, d/dx_1, d/dx_2), length 9.",
    "hessian": "Its Hessian (9x9, symmetric, indefinite).",
    "p2_energy": "Pressure potential p/3 int x . (x_xi x x_eta) of one 6-node triangle.",
    "p2_gradient": "Its gradient (d/dx_0 .. d/dx_5), length 18.",
    "p2_hessian": "Its Hessian (18x18, symmetric, indefinite).",
    "p2_follower_load": "Consistent load of unit pressure, -int N_i (x_xi x x_eta), 18.",
    "p2_traction_weights": "Consistent traction weights int N_i dA of a 6-node triangle, 6.",
}

XI, ETA = sp.symbols("xi eta", real=True)


def face_potential(x: sp.Matrix, p: sp.Symbol) -> sp.Expr:
    """``p/6 x_0 . (x_1 x x_2)``: ``p`` times the signed volume of the cone from the origin
    over the triangle whose vertices are the rows of ``x`` (3 x 3)."""
    x0, x1, x2 = (x[i, :].T for i in range(3))
    return p / 6 * x0.dot(x1.cross(x2))


def face_shape_functions() -> list[sp.Expr]:
    """The 6-node triangle's shape functions in ``(xi, eta)`` (corners at ``(0, 0)``,
    ``(1, 0)``, ``(0, 1)``; then the edges ``01, 12, 20``)."""
    lam = (1 - XI - ETA, XI, ETA)
    corners = [c * (2 * c - 1) for c in lam]
    return corners + [4 * lam[a] * lam[b] for a, b in ((0, 1), (1, 2), (2, 0))]


def integrate_triangle(expr: sp.Expr) -> sp.Expr:
    """``integral expr dxi deta`` over the reference triangle, exactly, for a polynomial in
    ``xi, eta``: term by term, ``integral xi^i eta^j = i! j! / (i + j + 2)!``."""
    total = sp.Integer(0)
    for (i, j), c in sp.Poly(sp.expand(expr), XI, ETA).terms():
        total += c * sp.factorial(i) * sp.factorial(j) / sp.factorial(i + j + 2)
    return total


def _quadratic_face(x: sp.Matrix) -> tuple[sp.Matrix, sp.Matrix]:
    """The point ``x(xi, eta)`` and ``x_xi x x_eta`` of the face whose nodes are rows of
    ``x`` (6 x 3)."""
    N = sp.Matrix(face_shape_functions())
    point = x.T * N
    return point, point.diff(XI).cross(point.diff(ETA))


def quadratic_face_potential(x: sp.Matrix, p: sp.Symbol) -> sp.Expr:
    """``p/3 integral x . (x_xi x x_eta)``: ``p`` times the signed volume of the cone from the
    origin over the 6-node triangle whose nodes are the rows of ``x`` (6 x 3)."""
    point, normal = _quadratic_face(x)
    return p / 3 * integrate_triangle(point.dot(normal))


def _radon7() -> list[tuple[tuple[sp.Expr, sp.Expr], sp.Expr]]:
    """Radon's 7-point rule of degree 5 on the reference triangle: ``((xi, eta), weight)``
    (weights sum to the area 1/2)."""
    r = sp.sqrt(15)
    out = [((sp.Rational(1, 3), sp.Rational(1, 3)), sp.Rational(9, 80))]
    for a, w in (((6 - r) / 21, (155 - r) / 2400), ((6 + r) / 21, (155 + r) / 2400)):
        out += [((a, a), w), ((1 - 2 * a, a), w), ((a, 1 - 2 * a), w)]
    return out


def _quadratic_raw() -> dict[str, tuple[list[Argument], list[Argument], list[tuple]]]:
    """The 6-node face's kernels (see the module docstring)."""
    x = symbol_matrix("x", 6, 3)
    p = sp.Symbol("p", real=True)
    energy = quadratic_face_potential(x, p)
    dofs = flatten(x)
    gradient = [sp.diff(energy, s) for s in dofs]
    hessian = [sp.diff(g, s) for g in gradient for s in dofs]
    _, normal = _quadratic_face(x)
    N = face_shape_functions()
    load = [-integrate_triangle(Ni * normal[c]) for Ni in N for c in range(3)]
    weights = []
    for Ni in N:
        weights.append(sum(w * (Ni * sp.sqrt(normal.dot(normal))).subs({XI: a, ETA: b})
                           for (a, b), w in _radon7()))
    inputs = [Argument("x_f", (6, 3), tuple(dofs),
                       doc="6-node triangle (corners, then edges ab, bc, ca), current")]
    params = [Argument("p", (), (p,), per_element=False)]
    return {
        "p2_energy": (inputs, params, [("energy", (), [energy], False)]),
        "p2_gradient": (inputs, params, [("gradient", (18,), gradient, False)]),
        "p2_hessian": (inputs, params, [("hessian", (18, 18), hessian, True)]),
        "p2_follower_load": (inputs, [], [("load", (18,), load, False)]),
        "p2_traction_weights": (inputs, [], [("weights", (6,), weights, False)]),
    }


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
        **_quadratic_raw(),
    }


def pressure_module() -> ModuleSpec:
    """The ``pressure`` module: the kernels of :func:`pressure_raw`."""
    kernels = tuple(make_kernel("pressure", name, DOCS[name], inputs, params, outputs)
                    for name, (inputs, params, outputs) in pressure_raw().items())
    return ModuleSpec(name="pressure", doc="follower pressure on a surface triangle (3 or 6 nodes)",
                      source=__name__, param_names=("p",), kernels=kernels)
