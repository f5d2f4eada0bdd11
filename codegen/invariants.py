"""The chain rule through the invariants of ``F``, found automatically in a material's ``psi``.

Continuum-mechanics energies are mostly functions of a few invariants of ``F``: ``J = det F``,
``I1 = tr(F^T F)``, ``tr((F^T F)^2)`` and, for a per-element direction ``a``, the squared
stretch ``|F a|^2``. Written out in the entries of ``F`` they hide that structure: the
determinant of ``(J - 1)^2`` and of ``J^(-2/3)`` are separate expanded sums to the CSE. This
module finds each invariant where it occurs in ``psi`` (as a whole sub-expression, or as an
exact polynomial part of one: ``J - 1``, ``(I1 + 1) / 4``, ``tr(E^2)`` of Green's strain), and
rewrites ``psi(F) = psi~(F, g(F))`` with the invariants ``g`` as symbols. Every derivative is
still SymPy's own (``sp.diff``), taken by the chain rule

    dX/dF = dX/dF|explicit + sum_k dX/dg_k dg_k/dF + sum_k,ij dX/d(dg_k/dF_ij) d2g_k/dF_ij dF

so the kernels compute each invariant and its gradient (e.g. the cofactors) once and share
them. The decomposition is checked exact at random points (:func:`check_decomposition`); a
material whose ``psi`` holds no invariant gets ``None`` and keeps the direct derivation.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

import sympy as sp

from codegen.conventions import flatten


@dataclass(frozen=True)
class Invariant:
    """One invariant ``g(F)``: its symbol, its expression, how kernels compute it and its
    gradient (entries with more than one operation become named symbols ``d<name>_i_j``)."""

    symbol: sp.Symbol
    expr: sp.Expr
    """Structured form (e.g. ``|F a|^2`` as a sum of squares), differentiated for the gradient."""
    expanded: sp.Expr
    form: sp.Expr
    """How a kernel computes ``g`` from ``F`` and the raw gradient entries (shares them)."""
    gradient: tuple[tuple[sp.Symbol, sp.Expr, sp.Expr], ...]
    """``(F_ij, dg/dF_ij as used in expressions, raw dg/dF_ij)`` for the nine entries of F."""


@dataclass(frozen=True)
class Decomposition:
    """``psi(F) == psi_tilde(F, g(F))`` for the invariants ``g`` found in ``psi``."""

    F: sp.Matrix
    psi_tilde: sp.Expr
    invariants: tuple[Invariant, ...]

    def total_diff(self, expr: sp.Expr, F_ab: sp.Symbol) -> sp.Expr:
        """``d expr / dF_ab`` with the invariants and their named gradients as functions of F."""
        out = sp.diff(expr, F_ab)
        for inv in self.invariants:
            d_g = sp.diff(expr, inv.symbol)
            if d_g != 0:
                out += d_g * dict((f, used) for f, used, _ in inv.gradient)[F_ab]
            for _, used, raw in inv.gradient:
                if isinstance(used, sp.Symbol) and used in expr.free_symbols:
                    out += sp.diff(expr, used) * sp.diff(raw, F_ab)
        return out

    def stress(self, F_flat: list[sp.Symbol]) -> tuple[list, list[sp.Expr]]:
        """``P = dpsi~/dF|explicit + sum_k w_k dg_k/dF`` with the invariants' derivatives
        ``w_k = dpsi~/dg_k`` as named steps ``dpsi_d<name>`` (a numeric factor common to a
        gradient's entries, like the 2 of ``dI1/dF = 2 F``, is folded into ``w_k``).
        Returns ``(steps [(w_k, expression)], the nine entries of P row-major)``."""
        steps, P = [], [sp.diff(self.psi_tilde, f) for f in F_flat]
        for inv in self.invariants:
            w = sp.diff(self.psi_tilde, inv.symbol)
            if w == 0:
                continue
            used = dict((f, u) for f, u, _ in inv.gradient)
            scale = _common_factor([used[f] for f in F_flat])
            symbol = sp.Symbol(f"dpsi_d{inv.symbol}", real=True)
            steps.append((symbol, scale * w))
            P = [p + symbol * (used[f] / scale) for p, f in zip(P, F_flat, strict=True)]
        return steps, P

    def prelude(self, used: set[sp.Symbol]) -> tuple[list[sp.Expr], list[sp.Symbol]]:
        """The raw expressions and names of the invariants and named gradient entries that the
        expressions in ``used`` need, gradients first (one CSE over them shares the cofactors
        between ``J`` and ``dJ/dF``)."""
        needed = set(used)
        for inv in self.invariants:
            if inv.symbol in needed:
                needed |= inv.form.free_symbols
        exprs, names = [], []
        for inv in self.invariants:
            for _, sym, raw in inv.gradient:
                if isinstance(sym, sp.Symbol) and sym in needed:
                    exprs.append(raw)
                    names.append(sym)
        raw_of = {sym: raw for inv in self.invariants for _, sym, raw in inv.gradient
                  if isinstance(sym, sp.Symbol)}
        for inv in self.invariants:
            if inv.symbol in needed:
                exprs.append(inv.form.xreplace(raw_of))
                names.append(inv.symbol)
        return exprs, names


def _common_factor(entries: list[sp.Expr]) -> sp.Expr:
    """The rational number every non-zero entry is a multiple of (its leading coefficient),
    or 1."""
    factors = {e.as_coeff_Mul()[0] for e in entries if e != 0}
    return factors.pop() if len(factors) == 1 else sp.Integer(1)


def _candidates(F: sp.Matrix, inputs: dict[str, sp.Matrix]) -> list[tuple[str, sp.Expr]]:
    C = F.T * F
    found = [("J", F.det()), ("I1", sum(f**2 for f in flatten(F))),
             ("I2", sum(c**2 for c in flatten(C)))]
    for name, m in inputs.items():
        if m.shape == (3, 1):
            Fa = F * m
            found.append((f"I4_{name}", sum(v**2 for v in Fa)))
    return found


def _invariant(name: str, expr: sp.Expr, F: sp.Matrix) -> Invariant:
    symbol = sp.Symbol(name, real=True)
    gradient = []
    for i in range(3):
        for j in range(3):
            raw = sp.diff(expr, F[i, j])
            used = sp.Symbol(f"d{name}_{i}_{j}", real=True) if sp.count_ops(raw) > 1 else raw
            gradient.append((F[i, j], used, raw))
    # Euler: a function homogeneous of degree d in row i is (1/d) sum_j F_ij dg/dF_ij (the
    # determinant's Laplace expansion); it reuses the gradient the kernels compute anyway.
    form = expr
    for i in range(3):
        row = [F[i, j] for j in range(3)]
        poly = sp.Poly(sp.expand(expr), *row)
        if poly.is_homogeneous and poly.total_degree() > 0:
            form = sum(F[i, j] * gradient[3 * i + j][1] for j in range(3)) / poly.total_degree()
            break
    return Invariant(symbol, expr, sp.expand(expr), form, tuple(gradient))


def _match(node: sp.Expr, invariants: list[Invariant], F_syms: set[sp.Symbol]) -> sp.Expr:
    """``node`` as ``sum_k c_k g_k + rest`` with ``rest`` and the ``c_k`` free of F, or as is."""
    try:
        expanded = sp.expand(node)
        poly = sp.Poly(expanded, *sorted(F_syms, key=str))
    except sp.PolynomialError:
        return node
    pieces = sp.Integer(0)
    for inv in invariants:
        g = sp.Poly(inv.expanded, *poly.gens)
        monomials = g.monoms()
        ratio = sp.cancel(poly.coeff_monomial(monomials[0]) / g.coeff_monomial(monomials[0]))
        if ratio == 0 or any(sp.cancel(poly.coeff_monomial(m) - ratio * g.coeff_monomial(m))
                             != 0 for m in monomials[1:]):
            continue
        poly = poly - g * ratio
        pieces += ratio * inv.symbol
    if pieces == 0 or not poly.is_ground:
        return node
    return pieces + poly.as_expr()


def _substitute(expr: sp.Expr, invariants: list[Invariant], F_syms: set[sp.Symbol]) -> sp.Expr:
    if expr.is_Atom or not expr.free_symbols & F_syms:
        return expr
    new = expr.func(*(_substitute(a, invariants, F_syms) for a in expr.args))
    if new.is_Add and new.free_symbols & F_syms:
        return _match(new, invariants, F_syms)
    return new


def decompose(psi: sp.Expr, F: sp.Matrix, inputs: dict[str, sp.Matrix]) -> Decomposition | None:
    """The invariants of ``psi`` and ``psi~`` (``None`` when ``psi`` holds none of them)."""
    F_syms = set(flatten(F))
    invariants = [_invariant(n, e, F) for n, e in _candidates(F, inputs)]
    psi_tilde = _substitute(psi, invariants, F_syms)
    used = tuple(inv for inv in invariants if inv.symbol in psi_tilde.free_symbols)
    if not used:
        return None
    decomposition = Decomposition(F, psi_tilde, used)
    check_decomposition(psi, decomposition)
    return decomposition


def check_decomposition(psi: sp.Expr, d: Decomposition, points: int = 3, seed: int = 0) -> None:
    """Raise ``AssertionError`` unless ``psi~(F, g(F)) == psi(F)`` at random points (40 digits;
    ``F`` near the identity, every other symbol in ``(0.5, 2)``)."""
    rng = random.Random(seed)
    F_syms = flatten(d.F)
    others = sorted((psi.free_symbols | d.psi_tilde.free_symbols) - set(F_syms)
                    - {inv.symbol for inv in d.invariants}, key=str)
    for _ in range(points):
        values = {f: sp.Rational(int(i == j) * 100 + rng.randint(-20, 20), 100)
                  for (i, j), f in zip(((i, j) for i in range(3) for j in range(3)), F_syms,
                                       strict=True)}
        values |= {s: sp.Rational(rng.randint(50, 200), 100) for s in others}
        values |= {inv.symbol: inv.expr.xreplace(values) for inv in d.invariants}
        exact = sp.N(psi.xreplace(values), 40)
        rewritten = sp.N(d.psi_tilde.xreplace(values), 40)
        assert abs(exact - rewritten) <= sp.Float(1e-30, 40) * (1 + abs(exact)), \
            f"invariant decomposition is not exact: {exact} != {rewritten}"
