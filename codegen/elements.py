"""Lagrange tetrahedra of any degree in SymPy: nodes, shape functions, mass, quadrature.

An element is described by its polynomial degree ``k`` (:class:`LagrangeTet`): P1 (4 nodes),
P2 (10 nodes), P3 (20 nodes) ... on the reference tetrahedron with vertices ``(0,0,0)``,
``(1,0,0)``, ``(0,1,0)``, ``(0,0,1)`` and reference coordinates ``xi = (xi_0, xi_1, xi_2)``
(barycentric ``lambda = (1 - xi_0 - xi_1 - xi_2, xi_0, xi_1, xi_2)``). SymPy builds each
shape function from the barycentric coordinates, so everything else (reference gradients,
the exact mass matrix, the element kernels of :mod:`codegen.element_kernels`) is derived.

Node order (the order of ``x_e``'s rows): the 4 vertices, then ``k - 1`` nodes on each edge
in :data:`EDGES` order (from the edge's first vertex to its second), then the nodes inside
each face in :data:`FACES` order, then the interior nodes. For P2 this is VTK's and meshio's
``tetra10`` order: nodes 4..9 are the midpoints of edges (0,1), (1,2), (0,2), (0,3), (1,3),
(2,3) (Gmsh's order swaps the last two, which meshio converts).

Quadrature (:data:`RULES`): symmetric rules with positive weights and interior points (a
PSD-projected integrand stays PSD), weights summing to the reference volume 1/6.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import cache, cached_property

import sympy as sp

#: The six edges of a tet, VTK's order.
EDGES: tuple[tuple[int, int], ...] = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))
#: The four faces, each opposite the vertex missing from it (face f opposite vertex 3 - f).
FACES: tuple[tuple[int, int, int], ...] = ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))


def reference_coordinates() -> sp.Matrix:
    """The reference coordinates ``xi_0, xi_1, xi_2`` as a column of real symbols."""
    return sp.Matrix(sp.symbols("xi_0 xi_1 xi_2", real=True))


def barycentric(xi: sp.Matrix) -> list[sp.Expr]:
    """``lambda_0 ... lambda_3`` of the reference point ``xi``."""
    return [1 - xi[0] - xi[1] - xi[2], xi[0], xi[1], xi[2]]


@dataclass(frozen=True)
class QuadratureRule:
    """A symmetric quadrature rule on the reference tet.

    ``points`` are barycentric coordinates (4 per point, exact SymPy numbers), ``weights``
    sum to the reference volume 1/6; the rule integrates every polynomial of total degree
    ``degree`` exactly.
    """

    name: str
    degree: int
    points: tuple[tuple[sp.Expr, ...], ...]
    weights: tuple[sp.Expr, ...]
    source: str

    @property
    def n_points(self) -> int:
        return len(self.points)

    def reference_points(self) -> list[tuple[sp.Expr, sp.Expr, sp.Expr]]:
        """The points as reference coordinates ``xi`` (barycentric ``lambda_1..3``)."""
        return [tuple(p[1:]) for p in self.points]


def _orbit(*barycentric_coordinates: sp.Expr) -> list[tuple[sp.Expr, ...]]:
    """The distinct permutations of one barycentric point, in lexicographic order of the
    positions (a fixed, reproducible order)."""
    seen: list[tuple[sp.Expr, ...]] = []
    for perm in itertools.permutations(range(4)):
        p = tuple(barycentric_coordinates[i] for i in perm)
        if p not in seen:
            seen.append(p)
    return seen


def _rule(name: str, degree: int, orbits: list[tuple[tuple[sp.Expr, ...], sp.Expr]],
          source: str) -> QuadratureRule:
    points, weights = [], []
    for point, weight in orbits:
        for p in _orbit(*point):
            points.append(p)
            weights.append(weight)
    return QuadratureRule(name, degree, tuple(points), tuple(weights), source)


def _degree5_orbits() -> list[tuple[tuple[sp.Expr, ...], sp.Expr]]:
    """The 14-point degree-5 rule: two ``S31`` orbits ``(a, a, a, 1 - 3a)`` and one ``S22``
    orbit ``(b, b, 1/2 - b, 1/2 - b)``, the published 16-digit values (exact to 4e-16 on
    every monomial of degree <= 5: ``tests/codegen/test_p2_kernels_vs_sympy.py``)."""
    a1, w1 = sp.Float("0.0927352503108912", 16), sp.Float("0.01224884051939366", 16)
    a2, w2 = sp.Float("0.3108859192633006", 16), sp.Float("0.01878132095300264", 16)
    b, w3 = sp.Float("0.04550370412564965", 16), sp.Float("0.007091003462846911", 16)
    half = sp.Float("0.5", 16)
    return [((a1, a1, a1, 1 - 3 * a1), w1), ((a2, a2, a2, 1 - 3 * a2), w2),
            ((b, b, half - b, half - b), w3)]


def integrate_reference(expr: sp.Expr) -> sp.Expr:
    """``integral expr dxi`` over the reference tet, exactly, for a polynomial ``expr`` in
    the reference coordinates: term by term, ``integral xi_0^i xi_1^j xi_2^k dxi =
    i! j! k! / (i + j + k + 3)!``."""
    return _integrate_poly(sp.Poly(sp.expand(expr), *reference_coordinates()))


def _integrate_poly(poly: sp.Poly) -> sp.Expr:
    """:func:`integrate_reference` of a polynomial already in the reference coordinates."""
    return sum((c * sp.factorial(i) * sp.factorial(j) * sp.factorial(k) /
                sp.factorial(i + j + k + 3) for (i, j, k), c in poly.terms()), sp.Integer(0))


@cache
def rule(name: str) -> QuadratureRule:
    """The quadrature rule ``name`` (a key of :data:`RULES`)."""
    if name == "centroid":
        q = sp.Rational(1, 4)
        return _rule(name, 1, [((q, q, q, q), sp.Rational(1, 6))], "the centroid (midpoint) rule")
    if name == "keast4":
        a, b = (5 + 3 * sp.sqrt(5)) / 20, (5 - sp.sqrt(5)) / 20
        return _rule(name, 2, [((a, b, b, b), sp.Rational(1, 24))],
                     "Keast (1986), Comput. Methods Appl. Mech. Eng. 55, rule 2: four points "
                     "(a, b, b, b), a = (5 + 3 sqrt 5)/20, b = (5 - sqrt 5)/20, weights 1/24")
    if name == "walkington14":
        return _rule(name, 5, _degree5_orbits(),
                     "Walkington (2000), 'Quadrature on simplices of arbitrary dimension', the "
                     "14-point degree-5 rule (two S31 orbits, one S22 orbit, positive weights)")
    raise ValueError(f"unknown quadrature rule {name!r}; known: {', '.join(RULES)}")


#: The rules the generator knows, by name: (degree, points).
RULES: dict[str, tuple[int, int]] = {"centroid": (1, 1), "keast4": (2, 4), "walkington14": (5, 14)}


@dataclass(frozen=True)
class LagrangeTet:
    """The Lagrange tetrahedron of degree ``degree``; its energy kernels integrate with the
    quadrature rule ``quadrature`` (a key of :data:`RULES`)."""

    name: str
    degree: int
    quadrature: str

    @cached_property
    def multi_indices(self) -> tuple[tuple[int, int, int, int], ...]:
        """Each node as a barycentric multi-index ``alpha`` (``sum alpha = degree``; the node
        sits at ``alpha / degree``), in the node order of the module docstring."""
        k = self.degree
        all_nodes = [a for a in itertools.product(range(k + 1), repeat=4) if sum(a) == k]
        vertices = [tuple(k if i == v else 0 for i in range(4)) for v in range(4)]
        edges = []
        for v, w in EDGES:
            for s in range(1, k):  # from v towards w
                edges.append(tuple(k - s if i == v else s if i == w else 0 for i in range(4)))
        faces = []
        for face in FACES:
            faces += sorted((a for a in all_nodes
                             if all(a[i] > 0 for i in face) and
                             all(a[i] == 0 for i in range(4) if i not in face)), reverse=True)
        interior = sorted((a for a in all_nodes if min(a) > 0), reverse=True)
        nodes = [*vertices, *edges, *faces, *interior] if k > 1 else vertices
        assert len(nodes) == len(all_nodes) == len(set(nodes))
        return tuple(nodes)

    @property
    def n_nodes(self) -> int:
        return len(self.multi_indices)

    def nodes(self) -> list[tuple[sp.Expr, sp.Expr, sp.Expr]]:
        """Reference coordinates ``xi`` of the nodes."""
        return [tuple(sp.Rational(a[i], self.degree) for i in (1, 2, 3))
                for a in self.multi_indices]

    def shape_functions(self, xi: sp.Matrix | None = None) -> sp.Matrix:
        """``N`` (``n_nodes x 1``) at ``xi`` (default: the symbols of
        :func:`reference_coordinates`): ``N_alpha = prod_v prod_{s < alpha_v}
        (k lambda_v - s) / (s + 1)``, one at its node and zero at every other."""
        xi = reference_coordinates() if xi is None else xi
        lam = barycentric(xi)
        k = self.degree
        rows = []
        for alpha in self.multi_indices:
            value = sp.Integer(1)
            for v in range(4):
                for s in range(alpha[v]):
                    value *= (k * lam[v] - s) / sp.Integer(s + 1)
            rows.append(sp.expand(value))
        return sp.Matrix(rows)

    def reference_gradients(self, xi: sp.Matrix | None = None) -> sp.Matrix:
        """``dN/dxi`` (``n_nodes x 3``), at ``xi`` or as polynomials."""
        symbols = reference_coordinates()
        G = self.shape_functions().jacobian(symbols)
        if xi is None:
            return G
        return G.subs(dict(zip(symbols, xi, strict=True)))

    @cached_property
    def mass_coefficients(self) -> sp.Matrix:
        """``integral N_i N_j dV / volume`` (``n_nodes x n_nodes``), exact, for an element
        whose map from the reference tet is affine (straight edges, edge nodes at their
        reference positions): ``detJ`` is then constant and the integral is ``6 vol``
        times the reference integral."""
        N = self.shape_functions()
        n = self.n_nodes
        M = sp.zeros(n, n)
        for i in range(n):
            for j in range(i, n):
                M[i, j] = M[j, i] = 6 * integrate_reference(sp.expand(N[i] * N[j]))
        return M

    @cached_property
    def curved_mass_weights(self) -> tuple[tuple[tuple[sp.Expr, ...], ...],
                                           tuple[sp.Matrix, ...]]:
        """The exact mass of a curved element from its ``det J`` at a few points.

        ``J = dX/dxi`` has entries of degree ``k - 1`` in ``xi``, so ``det J`` is a polynomial
        of degree ``3 (k - 1)`` and equals its Lagrange interpolant ``sum_p det J(xi_p)
        L_p(xi)`` on the ``xi_p`` nodes of that degree (at least 1). Then ``integral N_i N_j
        det J dxi = sum_p det J(xi_p) C_p[i, j]`` with ``C_p = integral N_i N_j L_p dxi``,
        exact rationals: no quadrature error for any position of the nodes.

        Returns
        -------
        points : the ``xi_p`` (reference coordinates)
        C : one ``n_nodes x n_nodes`` matrix per point
        """
        xi = reference_coordinates()
        d = max(1, 3 * (self.degree - 1))  # (P1: det J is constant, linear interpolates it)
        interpolation = LagrangeTet(f"p{d}", d, "centroid")
        L = [sp.Poly(f, *xi) for f in interpolation.shape_functions()]
        N = [sp.Poly(f, *xi) for f in self.shape_functions()]
        n = self.n_nodes
        C = []
        for Lp in L:
            Cp = sp.zeros(n, n)
            for i in range(n):
                for j in range(i, n):
                    Cp[i, j] = Cp[j, i] = _integrate_poly(N[i] * N[j] * Lp)
            C.append(Cp)
        return tuple(interpolation.nodes()), tuple(C)

    def quadrature_rule(self) -> QuadratureRule:
        """The rule of this element's energy kernels."""
        return rule(self.quadrature)


#: The elements the generator emits kernels for (P1's are the hand-laid-out :mod:`codegen.tet`
#: kernels; its description here is for the tests and for degree-generic code).
ELEMENTS: dict[str, LagrangeTet] = {
    "p1": LagrangeTet("p1", 1, "centroid"),
    "p2": LagrangeTet("p2", 2, "keast4"),
}
#: The elements with quadrature kernels of their own (modules ``<element>_<material>``).
QUADRATURE_ELEMENTS: tuple[str, ...] = ("p2",)
