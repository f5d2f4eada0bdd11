"""Stage 1 and 2 for higher-order tets: the kernels of a :class:`~codegen.elements.LagrangeTet`.

Three kinds of module per element ``e`` (``p2``):

* ``e_tet``: the geometry, written out for every quadrature point of the element's rule
  (:mod:`codegen.elements`): the rest-shape precompute ``rest_shape`` (``dN/dX``, ``det J``
  and ``weight * det J`` per point; it refuses ``det J <= 0``), the shape functions at a
  reference point, the exact consistent mass matrix (straight edges: from the volume; any
  element: from ``det J`` at the 20 nodes of degree 3 that interpolate it), and ``F`` and
  ``det F`` per point.
* ``e_<material>``: quadrature kernels (:attr:`codegen.spec.KernelSpec.points`): the energy,
  gradient, parameter derivative of the gradient, Hessian and PSD-projected Hessian of
  ``sum_q w_q psi(F_q)``, where the body of the sum is one point's: ``F_q`` from the node
  positions and that point's ``dN/dX``, then the material's own CSE'd ``psi``, ``P`` or
  ``dP/dF`` steps (:func:`codegen.derive.derivative_steps`, the P1 kernels' very steps), then
  the chain rule to the nodes. Both back ends call the element's shared loops
  (``e_quadrature``, below) with the material's steps at one ``F``
  (:class:`codegen.spec.MaterialSteps`: P1's pointwise kernels, from the P1 module's own
  source, and ``dP/dp``); the material's module holds only ``dP/dp`` and the entry points.
* ``e_quadrature`` (:func:`quadrature_module`): what every material's quadrature kernels
  share: ``F`` at a point and the terms a point adds to the energy, gradient and Hessian,
  around which ``templates/c/quadrature.c.jinja`` and ``templates/numpy/quadrature.py.jinja``
  write one loop per kernel kind (``e_quadrature.c``, ``e_quadrature.py``).

Calling convention (``n`` nodes, ``nq`` quadrature points; P2: ``n = 10``, ``nq = 4``):

==========================================  ==============================================
``p2_tet.rest_shape(X_e)``                  ``X_e (m, n, 3)`` rest node positions ->
                                            ``dN_dX (m, nq, n, 3)``, ``detJ (m, nq)``,
                                            ``w_detJ (m, nq)`` (= rule weight * detJ);
                                            ``ValueError`` naming the element and point
                                            when a ``detJ <= 0``
``p2_tet.shape_functions(xi)``              ``xi (m, 3)`` reference coordinates ->
                                            ``N (m, n)``, ``dN_dxi (m, n, 3)``
``p2_tet.mass_matrix(vol, (rho,))``         ``vol (m,)`` -> ``mass (m, 3n, 3n)``, exact for
                                            straight-edged elements (node-major DOFs,
                                            ``3 * node + coordinate``)
``p2_tet.mass_coefficients(vol, (rho,))``   the same as the ``(m, n, n)`` scalar matrix
``p2_tet.curved_mass_matrix(X_e, (rho,))``  ``X_e (m, n, 3)`` rest node positions ->
                                            ``mass (m, 3n, 3n)``, exact for any element:
                                            ``det J`` (cubic for P2) interpolated at the
                                            20 nodes of degree 3
``p2_tet.deformation_gradient(x_e, dN_dX)`` ``-> F (m, nq, 3, 3)``
``p2_tet.deformation_jacobian(x_e, dN_dX)`` ``-> J (m, nq)``: ``det F`` per point
``p2_<mat>.energy(x_e, dN_dX, w_detJ,       ``x_e (m, n, 3)`` deformed node positions,
*inputs, params)``                          ``dN_dX (m, nq, n, 3)``, ``w_detJ (m, nq)``, the
                                            material's per-element inputs (a fibre
                                            direction ``(m, 3)``), params ``(n_params,)``
                                            or ``(m, n_params)`` -> ``energy (m,)``
``.gradient(...)``                          ``-> gradient (m, 3n)``
``.dgradient_dparams(...)``                 ``-> (m, 3n, n_params)``
``.hessian(...)``, ``.hessian_psd(...)``,   ``-> hessian (m, 3n, 3n)``; ``_psd``: ``dP/dF``
``.hessian_psd_svd(...)``                   projected per point (QL, or in ``F``'s singular
                                            frame), so each element Hessian is PSD
``<kernel>_assemble(q, T, dN_dX, w_detJ,    C only, as P1's: ``T (m, n)`` int64, ``index
*inputs, params, index, out)``              (m, size)`` int32; adds into ``out``
==========================================  ==============================================

The same names exist in the C extension (``fem3d._ckernels.p2_neo_hookean_hessian``...) and
the NumPy modules (``fem3d._generated.p2_neo_hookean``); ``kernel_module("p2_stvk")`` gives
either. The NumPy module ``p2_tet`` also holds the node layout and the rule as constants
(``NODES``, ``EDGES``, ``QUADRATURE_POINTS``, ``QUADRATURE_WEIGHTS``, ...).
"""

from __future__ import annotations

from dataclasses import replace

import sympy as sp

from codegen import derive
from codegen.conventions import flatten, symbol_matrix, symbol_vector
from codegen.elements import EDGES, ELEMENTS, LagrangeTet, reference_coordinates
from codegen.materials import MATERIALS
from codegen.spec import (
    Argument,
    KernelSpec,
    MaterialSteps,
    ModuleSpec,
    Projection,
    make_kernel,
)


def _point_symbols(n: int) -> tuple[sp.Matrix, sp.Matrix, sp.Symbol]:
    """Node positions ``x`` (n x 3), one point's ``dN/dX`` (n x 3) and ``w * det J``."""
    return symbol_matrix("x", n, 3), symbol_matrix("dN", n, 3), sp.Symbol("wdetJ", real=True)


def _element_arguments(element: LagrangeTet, extra: list[Argument]) -> list[Argument]:
    n, nq = element.n_nodes, element.quadrature_rule().n_points
    x, D, w = _point_symbols(n)
    return [
        Argument("x_e", (n, 3), tuple(flatten(x)), doc="deformed node positions of each tet"),
        Argument("dN_dX", (nq, n, 3), tuple(flatten(D)), per_point=True,
                 doc="rest-shape gradients of the shape functions at each quadrature point"),
        Argument("w_detJ", (nq,), (w,), per_point=True,
                 doc="quadrature weight times det J at each quadrature point"),
        *extra,
    ]


def _contraction(A: sp.Matrix, D: sp.Matrix, w: sp.Symbol, prelude: list) -> tuple[list, list]:
    """``w B^T A B`` for one point, ``B = dF/dx`` applied implicitly: ``T = w A B`` (9 x 3n),
    then ``B^T T`` (upper triangle). Returns (outputs, steps)."""
    n = D.rows
    steps = list(prelude)
    T = sp.Matrix(9, 3 * n, lambda a, s: sp.Symbol(f"T_{a}_{s}"))
    for a in range(9):
        for b in range(n):
            for d in range(3):
                value = w * sum(A[a, 3 * d + ll] * D[b, ll] for ll in range(3))
                steps.append((T[a, 3 * b + d], value))
    hessian = sp.Matrix(3 * n, 3 * n, lambda r, s: sum(
        D[r // 3, j] * T[3 * (r % 3) + j, s] for j in range(3)))
    return [("hessian", (3 * n, 3 * n), flatten(hessian), True)], steps


#: ``FEM3D_MAX_ARGS`` of ``templates/c/support.c.jinja``: the C quadrature loops' buffers hold
#: ``F`` and at most this many less one per-element inputs, and ``dP/dp`` of at most this many
#: parameters.
C_MAX_ARGS = 16


def _material_steps(module: str, name: str, d: derive.MaterialDerivation,
                    params) -> MaterialSteps:
    """What the quadrature kernels (C and NumPy) of material ``name`` call at one ``F``: its
    pointwise kernels, and ``dP/dp`` (9 x n_params, row-major), a step of its own."""
    F_args = [derive._matrix_arg("F", d.F, "deformation gradient"), *derive._input_args(d)]
    k_params = len(d.params)
    if k_params > C_MAX_ARGS or 1 + len(d.inputs) > C_MAX_ARGS:
        raise ValueError(f"{name}: {k_params} parameters and {len(d.inputs)} per-element "
                         f"inputs; the C quadrature loops take at most {C_MAX_ARGS} and "
                         f"{C_MAX_ARGS - 1} (FEM3D_MAX_ARGS)")
    dP = [sp.Symbol(f"dP_{i}_{j}_{k}") for i in range(3) for j in range(3)
          for k in range(k_params)]
    dP_dparams = make_kernel(
        module, "dP_dparams",
        "dP/dp at one F: (9, n_params), the row-major flattening of F by the parameters.",
        F_args, params, [("dP_dparams", (9, k_params), dP, False)],
        list(derive.stress_param_steps(name)))
    return MaterialSteps(name=name, n_inputs=len(d.inputs), n_params=k_params,
                         isotropic=derive.is_isotropic(name), point_kernels=(dP_dparams,))


def material_module(element: LagrangeTet, name: str) -> ModuleSpec:
    """Quadrature kernels of material ``name`` on ``element`` (module ``<element>_<name>``)."""
    material = MATERIALS[name]
    d = derive.derive_material(name)
    params = derive._param_args(material.PARAM_NAMES, d.params)
    args = _element_arguments(element, derive._input_args(d))
    n, nq = element.n_nodes, element.quadrature_rule().n_points
    x, D, w = _point_symbols(n)
    module = f"{element.name}_{name}"
    prelude_F = list(zip(flatten(d.F), flatten(x.T * D), strict=True))
    psi_steps, P_steps, A_steps = derive.derivative_steps(name)
    P = symbol_matrix("P", 3, 3)
    size = f"{3 * n}"
    kernels: list[KernelSpec] = [
        make_kernel(module, "energy", "Element energy sum_q w_q psi(F_q).", args, params,
                    [("energy", (), [w * sp.Symbol("psi")], False)], prelude_F + psi_steps,
                    points=nq),
        make_kernel(module, "gradient", f"Element gradient, node-major ({size}).", args, params,
                    [("gradient", (3 * n,), _gradient_terms(P, D, w), False)],
                    prelude_F + P_steps, points=nq),
    ]
    k_params = len(d.params)
    dP = [sp.Matrix(3, 3, lambda i, j, k=k: sp.Symbol(f"dP_{i}_{j}_{k}")) for k in range(k_params)]
    kernels.append(make_kernel(
        module, "dgradient_dparams",
        f"Element gradient's derivative by each parameter, ({size}, n_params), node-major.",
        args, params,
        [("dgradient_dparams", (3 * n, k_params),
          [g for terms in zip(*(_gradient_terms(dP[k], D, w) for k in range(k_params)),
                              strict=True) for g in terms], False)],
        prelude_F + list(derive.stress_param_steps(name)), points=nq))
    A = sp.Matrix(9, 9, lambda a, b: sp.Symbol(f"A_{min(a, b)}_{max(a, b)}"))
    hess_doc = f"Element Hessian ({size}x{size}, node-major)."
    kernels.append(make_kernel(module, "hessian", hess_doc, args, params,
                               *_contraction(A, D, w, prelude_F + A_steps), points=nq))
    A_psd = sp.Matrix(9, 9, lambda a, b: sp.Symbol(f"Ap_{a}_{b}"))
    frame = tuple(flatten(d.F)) if derive.is_isotropic(name) else ()
    projection = Projection(9, tuple(flatten(A)), tuple(flatten(A_psd)), frame=frame)
    psd_doc = hess_doc[:-1] + " with dP/dF projected to positive semi-definite at each point"
    kernels.append(make_kernel(module, "hessian_psd", psd_doc + ".", args, params,
                               *_contraction(A_psd, D, w, [*prelude_F, *A_steps, projection]),
                               points=nq))
    svd_doc = (" in the singular frame of F (block diagonal there: psi is isotropic)." if frame
               else " by QL (psi is not isotropic: no block-diagonal frame).")
    kernels.append(kernels[-1].projected_by("hessian_psd_svd", "svd", psd_doc + svd_doc))
    kinds = {"energy": "energy", "gradient": "gradient", "dgradient_dparams": "dgradient_dparams",
             "hessian": "hessian", "hessian_psd": "hessian", "hessian_psd_svd": "hessian"}
    kernels = [replace(k, quadrature=kinds[k.name]) for k in kernels]
    return ModuleSpec(name=module, doc=f"{material.DESCRIPTION}; {_element_doc(element)}",
                      source=f"{__name__} ({material.__name__})",
                      param_names=tuple(material.PARAM_NAMES), kernels=tuple(kernels),
                      unit=element.name, constants=_element_constants(element),
                      material_steps=_material_steps(module, name, d, params))


def _gradient_terms(P: sp.Matrix, D: sp.Matrix, w: sp.Symbol) -> list[sp.Expr]:
    """One point's gradient terms ``w P dN/dX^T``, node-major (``3 n``), of a 3 x 3 ``P``."""
    return [w * sum(P[c, j] * D[a, j] for j in range(3)) for a in range(D.rows) for c in range(3)]


def quadrature_module(element: LagrangeTet) -> ModuleSpec:
    """The material-independent pieces of ``element``'s quadrature kernels at one point
    (module ``<element>_quadrature``): ``F`` from the node positions and the point's
    ``dN/dX``, and the terms the point adds to the energy (of ``psi``), the gradient (of
    ``P``; the parameter derivative's too, of each ``dP/dp_k``) and the Hessian (of
    ``dP/dF``, all 81 entries read, the projected ones as the projection returns them)."""
    n, nq = element.n_nodes, element.quadrature_rule().n_points
    x, D, w = _point_symbols(n)
    module = f"{element.name}_quadrature"
    P = symbol_matrix("P", 3, 3)
    A = symbol_matrix("A", 9, 9)
    dN_arg = Argument("dN", (n, 3), tuple(flatten(D)), doc="dN/dX at the point")
    w_arg = Argument("w_detJ", (), (w,), doc="weight * det J at the point")
    kernels = [
        make_kernel(module, "F", "F = x_e^T dN/dX at one point.",
                    [Argument("x_e", (n, 3), tuple(flatten(x))), dN_arg], [],
                    [("F", (3, 3), flatten(x.T * D), False)]),
        make_kernel(module, "energy", "One point's energy term w psi.",
                    [Argument("psi", (), (sp.Symbol("psi"),)), w_arg], [],
                    [("energy", (), [w * sp.Symbol("psi")], False)]),
        make_kernel(module, "gradient", f"One point's gradient terms ({3 * n}) of P.",
                    [Argument("P", (3, 3), tuple(flatten(P))), dN_arg, w_arg], [],
                    [("gradient", (3 * n,), _gradient_terms(P, D, w), False)]),
        make_kernel(module, "hessian", f"One point's Hessian terms ({3 * n}x{3 * n}) of dP/dF.",
                    [Argument("A", (9, 9), tuple(flatten(A))), dN_arg, w_arg], [],
                    *_contraction(A, D, w, [])),
    ]
    return ModuleSpec(name=module, doc=_element_doc(element), source=__name__, param_names=(),
                      kernels=tuple(kernels), unit=element.name, role="quadrature",
                      constants=(("N_NODES", repr(n)), ("N_POINTS", repr(nq))))


def _element_doc(element: LagrangeTet) -> str:
    r = element.quadrature_rule()
    return (f"{element.name.upper()} tetrahedra ({element.n_nodes} nodes), "
            f"{r.n_points}-point degree-{r.degree} quadrature ({r.name})")


def _element_constants(element: LagrangeTet) -> tuple[tuple[str, str], ...]:
    r = element.quadrature_rule()
    return (
        ("ELEMENT", repr(element.name)),
        ("DEGREE", repr(element.degree)),
        ("N_NODES", repr(element.n_nodes)),
        ("NODES", repr(tuple(tuple(float(c) for c in p) for p in element.nodes()))),
        ("EDGES", repr(EDGES)),
        ("EDGE_NODES", repr(tuple(range(4, 4 + len(EDGES))) if element.degree == 2 else ())),
        ("QUADRATURE_RULE", repr(r.name)),
        ("QUADRATURE_DEGREE", repr(r.degree)),
        ("QUADRATURE_POINTS", repr(tuple(tuple(float(c) for c in p)
                                         for p in r.reference_points()))),
        ("QUADRATURE_WEIGHTS", repr(tuple(float(w) for w in r.weights))),
    )


def _det_steps(prefix: str, M: sp.Matrix) -> tuple[list, sp.Matrix, sp.Symbol]:
    """Steps naming the entries of ``M`` (3 x 3) ``<prefix>_i_j`` and its determinant
    ``<prefix>_det``: the symbol matrix and the determinant's symbol, so that the kernels'
    expressions stay in nine symbols, not in the sums behind them."""
    S = symbol_matrix(prefix, 3, 3)
    det = sp.Symbol(f"{prefix}_det", real=True)
    return [*zip(flatten(S), flatten(M), strict=True), (det, S.det(method="berkowitz"))], S, det


def _geometry_raw(element: LagrangeTet) -> dict[str, tuple[list, list, list, list]]:
    """Exact expressions of the geometry kernels, written out for every quadrature point:
    name -> (inputs, params, outputs, prelude steps)."""
    n = element.n_nodes
    r = element.quadrature_rule()
    nq = r.n_points
    X = symbol_matrix("X", n, 3)
    x = symbol_matrix("x", n, 3)
    Dq = [symbol_matrix(f"dN{q}", n, 3) for q in range(nq)]
    dN_arg = Argument("dN_dX", (nq, n, 3), tuple(s for D in Dq for s in flatten(D)),
                      doc="rest-shape gradients of the shape functions at each quadrature point")
    x_arg = Argument("x_e", (n, 3), tuple(flatten(x)), doc="deformed node positions")
    rest_steps, gradients, dets, wdets = [], [], [], []
    for q, (xi, weight) in enumerate(zip(r.reference_points(), r.weights, strict=True)):
        # dN/dxi at the point: numbers (printed as floating-point literals)
        G = element.reference_gradients(sp.Matrix(xi)).evalf(20)
        steps, J, det = _det_steps(f"J{q}", X.T * G)  # J = dX/dxi
        rest_steps += steps
        gradients += flatten(G * J.adjugate() / det)
        dets.append(det)
        wdets.append(sp.Float(weight, 20) * det)
    F_steps, J_dets = [], []
    for q, D in enumerate(Dq):
        steps, _, det = _det_steps(f"F{q}", x.T * D)
        F_steps += steps
        J_dets.append(det)
    xi = symbol_vector("xi", 3)
    rho, vol = sp.Symbol("rho", real=True), sp.Symbol("vol", real=True)
    M = element.mass_coefficients
    # the curved mass: det J at the interpolation points (exact rational dN/dxi there)
    points, C = element.curved_mass_weights
    curved_steps, curved_dets = [], []
    for p, point in enumerate(points):
        steps, _, det = _det_steps(f"K{p}", X.T * element.reference_gradients(sp.Matrix(point)))
        curved_steps += steps
        curved_dets.append(det)
    M_curved = sp.Matrix(n, n, lambda i, j: rho * sum(
        (Cp[i, j] * det for Cp, det in zip(C, curved_dets, strict=True)), sp.Integer(0)))
    return {
        "rest_shape": (
            [Argument("X_e", (n, 3), tuple(flatten(X)), doc="rest node positions of each tet")],
            [], [("dN_dX", (nq, n, 3), gradients, False), ("detJ", (nq,), dets, False),
                 ("w_detJ", (nq,), wdets, False)], rest_steps),
        "shape_functions": (
            [Argument("xi", (3,), tuple(xi), doc="reference coordinates")], [],
            [("N", (n,), list(element.shape_functions(xi)), False),
             ("dN_dxi", (n, 3), flatten(element.reference_gradients(xi)), False)], []),
        "mass_matrix": (
            [Argument("vol", (), (vol,), doc="rest volumes")],
            [Argument("rho", (), (rho,), per_element=False)],
            [("mass", (3 * n, 3 * n),
              flatten(rho * vol * sp.kronecker_product(M, sp.eye(3))), True)], []),
        "mass_coefficients": (
            [Argument("vol", (), (vol,), doc="rest volumes")],
            [Argument("rho", (), (rho,), per_element=False)],
            [("mass", (n, n), flatten(rho * vol * M), True)], []),
        "curved_mass_matrix": (
            [Argument("X_e", (n, 3), tuple(flatten(X)), doc="rest node positions of each tet")],
            [Argument("rho", (), (rho,), per_element=False)],
            [("mass", (3 * n, 3 * n), flatten(sp.kronecker_product(M_curved, sp.eye(3))),
              True)], curved_steps),
        "deformation_gradient": (
            [x_arg, dN_arg], [], [("F", (nq, 3, 3), [s for D in Dq for s in flatten(x.T * D)],
                                   False)], []),
        "deformation_jacobian": ([x_arg, dN_arg], [], [("J", (nq,), J_dets, False)], F_steps),
    }


def geometry_module(element: LagrangeTet) -> ModuleSpec:
    """Material-independent kernels of ``element`` (module ``<element>_tet``)."""
    r = element.quadrature_rule()
    docs = {
        "rest_shape": f"dN/dX, det J and weight * det J at the {r.n_points} quadrature points "
                      "of rest tets (refuses det J <= 0).",
        "shape_functions": "Shape functions N and their gradients dN/dxi at reference points.",
        "mass_matrix": f"Exact consistent mass matrix rho * integral N^T N dV "
                       f"({3 * element.n_nodes}x{3 * element.n_nodes}, straight edges).",
        "mass_coefficients": "Exact consistent scalar mass matrix rho * integral N_i N_j dV "
                             f"({element.n_nodes}x{element.n_nodes}, straight edges).",
        "curved_mass_matrix": "Exact consistent mass matrix rho * integral N^T N det J dxi of "
                              "any element, straight or curved: det J (a polynomial of "
                              f"degree {3 * (element.degree - 1)}) interpolated exactly at "
                              f"{len(element.curved_mass_weights[0])} points "
                              f"({3 * element.n_nodes}x{3 * element.n_nodes}).",
        "deformation_gradient": "Deformation gradient F = sum_a x_a dN_a/dX^T at each point.",
        "deformation_jacobian": "det F at each quadrature point (<= 0: inverted there).",
    }
    module = f"{element.name}_tet"
    kernels = []
    for name, (inputs, params, outputs, prelude) in _geometry_raw(element).items():
        spec = make_kernel(module, name, docs[name], inputs, params, outputs, prelude)
        if name == "rest_shape":
            spec = spec.requiring_positive("detJ")
        kernels.append(spec)
    return ModuleSpec(name=module, doc=_element_doc(element), source=__name__,
                      param_names=(), kernels=tuple(kernels), unit=element.name,
                      constants=_element_constants(element))


def module_names() -> list[str]:
    """The modules of every element with quadrature kernels, in a fixed order."""
    from codegen.elements import QUADRATURE_ELEMENTS

    return [f"{e}_{m}" for e in QUADRATURE_ELEMENTS
            for m in ("tet", "quadrature", *sorted(MATERIALS))]


def build_module(name: str) -> ModuleSpec:
    """The spec of one module ``<element>_tet`` or ``<element>_<material>``."""
    element_name, _, rest = name.partition("_")
    element = ELEMENTS[element_name]
    if rest == "tet":
        return geometry_module(element)
    if rest == "quadrature":
        return quadrature_module(element)
    return material_module(element, rest)


def reference_points(element: LagrangeTet) -> list[sp.Matrix]:
    """The element's quadrature points as reference-coordinate columns (for the tests)."""
    return [sp.Matrix(p) for p in element.quadrature_rule().reference_points()]


__all__ = ["build_module", "geometry_module", "material_module", "module_names",
           "reference_coordinates"]
