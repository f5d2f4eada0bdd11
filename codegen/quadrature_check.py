"""How exact is a P2 element's energy under each quadrature rule? A measurement, not a test.

    python -m codegen.quadrature_check [--bend 0.5 1.0] [--size 0.1]

A straight-edged P2 tet of edge ``size`` (the corners of a right tet, the edge nodes at the
midpoints) is deformed by bending about the z axis, ``x = (R + y) sin(s X / R), (R + y)
cos(s X / R) - R, z`` at its nodes with curvature ``1 / R = bend / size`` (strains up to
``bend``; the quadratic interpolant of the bend is what the element holds) and a stretch
``s`` along x (``--stretch``, default 1). Its energy
``sum_q w_q psi(F_q)`` is evaluated with every rule of :data:`codegen.elements.RULES` and
compared with a conical Gauss-Jacobi product rule of degree 23 (1728 points, exact for
polynomials of that degree): the relative error of each rule, per material, printed as a
table. ``F`` is a polynomial of degree 1 in the reference coordinates, so ``psi(F)`` is a
polynomial of degree 2 (linear elasticity), 4 (StVK) or not a polynomial (the others).
"""

from __future__ import annotations

import argparse

import numpy as np
import sympy as sp
from scipy.special import roots_jacobi

from codegen.derive import derive_material, small_strain_mapping
from codegen.elements import ELEMENTS, RULES, reference_coordinates, rule
from codegen.materials import MATERIALS


def conical_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n^3`` points and weights on the reference tet, exact to degree ``2 n - 1``
    (Stroud's conical product of Gauss-Jacobi rules)."""
    a, wa = roots_jacobi(n, 2, 0)
    b, wb = roots_jacobi(n, 1, 0)
    c, wc = roots_jacobi(n, 0, 0)
    a, b, c = (a + 1) / 2, (b + 1) / 2, (c + 1) / 2
    wa, wb, wc = wa / 8, wb / 4, wc / 2
    A, B, C = np.meshgrid(a, b, c, indexing="ij")
    W = wa[:, None, None] * wb[None, :, None] * wc[None, None, :]
    x = A
    y = (1 - A) * B
    z = (1 - A) * (1 - B) * C
    return np.stack([x, y, z], -1).reshape(-1, 3), W.reshape(-1)


def bent_element(size: float, bend: float, stretch: float) -> tuple[np.ndarray, np.ndarray]:
    """Rest and deformed node positions (10 x 3) of the bent P2 element."""
    nodes = np.array([[float(c) for c in p] for p in ELEMENTS["p2"].nodes()]) * size
    R = size / bend
    X, Y, Z = nodes.T
    x = np.stack([(R + Y) * np.sin(stretch * X / R), (R + Y) * np.cos(stretch * X / R) - R, Z],
                 1)
    return nodes, x


def energies(material: str, X: np.ndarray, x: np.ndarray,
             rules: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    """The element's energy under each rule (E = 1, nu = 0.3; a fibre along x)."""
    d = derive_material(material)
    mapping = small_strain_mapping(material)
    values = {p: float(e.subs({mapping.E: 1.0, mapping.nu: 0.3}))
              for p, e in mapping.exprs.items()}
    extra = {s: 1.0 if i == 0 else 0.0 for m in d.inputs.values()
             for i, s in enumerate(m)}
    psi = sp.lambdify(list(d.F), d.psi.subs({d.params[p]: v for p, v in values.items()})
                      .subs(extra), "numpy")
    xi = reference_coordinates()
    G = sp.lambdify(list(xi), ELEMENTS["p2"].reference_gradients(), "numpy")
    out = {}
    for name, (points, weights) in rules.items():
        total = 0.0
        for p, w in zip(points, weights, strict=True):
            g = np.array(G(*p), float)
            J = X.T @ g
            F = (x.T @ g) @ np.linalg.inv(J)
            total += w * np.linalg.det(J) * float(psi(*F.reshape(9)))
        out[name] = total
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bend", type=float, nargs="+", default=[0.1, 0.3],
                        help="edge length / bend radius")
    parser.add_argument("--stretch", type=float, default=1.0)
    parser.add_argument("--size", type=float, default=0.1)
    args = parser.parse_args(argv)
    rules = {n: (np.array([[float(c) for c in p] for p in rule(n).reference_points()]),
                 np.array([float(w) for w in rule(n).weights])) for n in RULES}
    rules["reference"] = conical_rule(12)
    names = [n for n in RULES if n != "centroid"]
    print(f"relative energy error of each rule against a degree-23 rule (1728 points); "
          f"edge {args.size}, stretch {args.stretch}")
    print(f"{'material':<20} {'bend':>5} " + " ".join(
        f"{n + f' ({RULES[n][1]} pts, deg {RULES[n][0]})':>28}" for n in names))
    for material in sorted(MATERIALS):
        for bend in args.bend:
            X, x = bent_element(args.size, bend, args.stretch)
            e = energies(material, X, x, rules)
            errors = [abs(e[n] - e["reference"]) / abs(e["reference"]) for n in names]
            print(f"{material:<20} {bend:5.2f} " + " ".join(f"{v:28.2e}" for v in errors))


if __name__ == "__main__":
    main()
