"""Stage 1 and 2: derive exact expressions with SymPy and freeze them into kernel specs."""

from __future__ import annotations

import math
import random
from dataclasses import dataclass
from functools import cache
from types import ModuleType

import sympy as sp

from codegen import tet
from codegen.conventions import deformation_gradient, flatten, symbol_matrix, symbol_vector
from codegen.invariants import Decomposition, decompose
from codegen.materials import MATERIALS
from codegen.spec import Argument, KernelSpec, ModuleSpec, Projection, make_kernel, name_cube_roots


@dataclass(frozen=True)
class MaterialDerivation:
    """Exact, un-CSE'd expressions of one material in the symbols ``F_i_j`` and its params."""

    F: sp.Matrix
    params: dict[str, sp.Symbol]
    inputs: dict[str, sp.Matrix]
    psi: sp.Expr
    P: sp.Matrix
    dP_dF: sp.Matrix


@cache
def derive_material(name: str) -> MaterialDerivation:
    """``psi``, ``P = dpsi/dF`` (3x3) and ``dP/dF`` (9x9, row-major flattening of F)."""
    material = MATERIALS[name]
    F = symbol_matrix("F", 3, 3)
    params = {p: sp.Symbol(p, real=True) for p in material.PARAM_NAMES}
    inputs = {n: _input_symbols(n, shape) for n, shape in element_inputs(name)}
    # doit: identities written as sp.Identity (for the displayed formula) become explicit
    psi = sp.sympify(material.psi(F, {**params, **inputs})).doit()
    P = sp.Matrix(3, 3, lambda i, j: sp.diff(psi, F[i, j]))
    F_flat = flatten(F)
    P_flat = flatten(P)
    dP_dF = sp.Matrix(9, 9, lambda a, b: sp.diff(P_flat[a], F_flat[b]))
    return MaterialDerivation(F, params, inputs, psi, P, dP_dF)


@cache
def material_decomposition(name: str) -> Decomposition | None:
    """``psi`` of material ``name`` through its invariants (``None`` when it holds none)."""
    d = derive_material(name)
    return decompose(d.psi, d.F, d.inputs)


@cache
def is_isotropic(name: str) -> bool:
    """Whether material ``name``'s ``psi(F)`` is unchanged by rotations on both sides,
    ``psi(Q F R) == psi(F)`` (frame-indifferent and isotropic), checked to 1e-10 relative at
    random ``F`` (``J > 0``), rotations, parameters in ``[0.5, 2]`` and element inputs."""
    d = derive_material(name)
    inputs = [s for m in d.inputs.values() for s in flatten(m)]
    psi = sp.lambdify([*flatten(d.F), *d.params.values(), *inputs], d.psi, "math")
    rng = random.Random(f"isotropy of {name}")

    def rotation() -> sp.Matrix:
        w, x, y, z = (rng.gauss(0, 1) for _ in range(4))
        n = math.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = w / n, x / n, y / n, z / n
        return sp.Matrix([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                          [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                          [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])

    for _ in range(4):
        F = sp.eye(3) + sp.Matrix(3, 3, lambda i, j: rng.uniform(-0.3, 0.3))
        rest = [rng.uniform(0.5, 2.0) for _ in d.params] + [rng.uniform(-1, 1) for _ in inputs]
        value = psi(*[float(v) for v in F], *rest)
        turned = psi(*[float(v) for v in rotation() * F * rotation()], *rest)
        if not abs(turned - value) <= 1e-10 * max(abs(value), 1.0):
            return False
    return True


def _steps_ops(steps: list) -> int:
    steps, _ = name_cube_roots(list(steps), [])  # as make_kernel will emit them
    return int(sum(sp.count_ops(s[1]) for s in steps if not isinstance(s, Projection)))


def _invariant_steps(dec: Decomposition, exprs: list[sp.Expr], names: list[sp.Symbol],
                     prefix: str, named: list | None = None) -> list:
    """CSE'd steps computing ``names = exprs`` (in ``F``, the invariants and their named
    gradients): first the invariants and gradients ``exprs`` need, in one CSE (``J`` shares
    the cofactors of ``dJ/dF``), then ``exprs`` with those as atoms."""
    named = named or []
    used = set().union(*(e.free_symbols for e in [*exprs, *(v for _, v in named)]))
    pre_exprs, pre_names = dec.prelude(used)
    steps = []
    if pre_exprs:
        # no "basic" optimizations here: they would pull the signs out of the cofactors
        replacements, reduced = sp.cse(pre_exprs, symbols=sp.numbered_symbols(prefix + "g"),
                                       order="canonical")
        # a named result that is a bare CSE symbol takes over that symbol (no alias steps)
        rename = {}
        for name, value in zip(pre_names, reduced, strict=True):
            if isinstance(value, sp.Symbol) and value not in rename and \
                    any(value == r for r, _ in replacements):
                rename[value] = name
        steps += [(rename.get(r, r), v.xreplace(rename)) for r, v in replacements]
        steps += [(n, v.xreplace(rename)) for n, v in zip(pre_names, reduced, strict=True)
                  if n not in rename.values()]
    if named:
        return steps + _cse_prelude([v for _, v in named] + exprs,
                                    [n for n, _ in named] + names, prefix)
    return steps + _cse_prelude(exprs, names, prefix)


_DERIVATIVES = ("psi", "P", "dP_dF")
#: A material module's kernels at one F, its first three (``<name>_pointwise.c`` in C).
POINTWISE = ("psi", "dpsi_dF", "d2psi_dF2")
#: The C translation units P1's material modules are dealt to in turn (sorted by name): ``""``
#: is the extension's entry file, which also holds the support, the AMG sweeps and the tet,
#: spring and pressure kernels; the others are ``_ckernels_<unit>.c``. Units compile in
#: parallel (setup.py), so the build's wall time is the slowest unit's.
P1_UNITS = ("p1a", "p1b", "")


def p1_unit(name: str) -> str:
    """The C translation unit of P1 material ``name``'s module (:data:`P1_UNITS`)."""
    return P1_UNITS[sorted(MATERIALS).index(name) % len(P1_UNITS)]
_UPPER = tuple((a, b) for a in range(9) for b in range(a, 9))  # dP/dF is symmetric
_PREFIX = {"psi": "e", "P": "s", "dP_dF": "h"}


def _derivative_names(which: str) -> list[sp.Symbol]:
    if which == "psi":
        return [sp.Symbol("psi")]
    if which == "P":
        return flatten(symbol_matrix("P", 3, 3))
    return [sp.Symbol(f"A_{a}_{b}") for a, b in _UPPER]


@cache
def direct_steps(name: str, which: str) -> tuple:
    """CSE'd steps computing ``which`` (``psi``, ``P`` as ``P_i_j`` or the upper triangle of
    ``dP/dF`` as ``A_a_b``) from ``F``, differentiated directly in the entries of ``F``."""
    d = derive_material(name)
    exprs = {"psi": lambda: [d.psi], "P": lambda: flatten(d.P),
             "dP_dF": lambda: [d.dP_dF[a, b] for a, b in _UPPER]}[which]()
    return tuple(_cse_prelude(exprs, _derivative_names(which), _PREFIX[which]))


@cache
def chain_steps(name: str, which: str) -> tuple | None:
    """Like :func:`direct_steps`, by the chain rule through the invariants found in ``psi``
    (:mod:`codegen.invariants`); ``None`` when ``psi`` holds none."""
    dec = material_decomposition(name)
    if dec is None:
        return None
    F_flat = flatten(derive_material(name).F)
    names, prefix = _derivative_names(which), _PREFIX[which]
    if which == "psi":
        return tuple(_invariant_steps(dec, [dec.psi_tilde], names, prefix))
    if which == "P":
        w_steps, P = dec.stress(F_flat)
        return tuple(_invariant_steps(dec, P, names, prefix, w_steps))
    P = [dec.total_diff(dec.psi_tilde, f) for f in F_flat]
    A = [dec.total_diff(P[a], F_flat[b]) for a, b in _UPPER]
    return tuple(_invariant_steps(dec, A, names, prefix))


def steps_op_count(steps) -> int:
    """Operations in a list of steps, as :attr:`codegen.spec.KernelSpec.op_count` counts."""
    return _steps_ops(list(steps))


def derivative_steps(name: str) -> tuple[list, list, list]:
    """CSE'd steps computing ``psi``, ``P`` (``P_i_j``) and the upper triangle of ``dP/dF``
    (``A_a_b``) from ``F``: each the direct derivation or the chain rule through the
    invariants, whichever has fewer operations (ties: the direct one)."""
    chosen = []
    for which in _DERIVATIVES:
        direct, chain = direct_steps(name, which), chain_steps(name, which)
        better = chain is not None and steps_op_count(chain) < steps_op_count(direct)
        chosen.append(list(chain if better else direct))
    return chosen[0], chosen[1], chosen[2]


def element_inputs(name: str) -> tuple[tuple[str, tuple[int, ...]], ...]:
    """A material's per-element inputs ``(name, shape)`` (e.g. a fibre direction ``(3,)``)."""
    return tuple((n, tuple(s)) for n, s in getattr(MATERIALS[name], "ELEMENT_INPUTS", {}).items())


def _input_symbols(name: str, shape: tuple[int, ...]) -> sp.Matrix:
    if len(shape) == 1:
        return symbol_vector(name, shape[0])
    return symbol_matrix(name, *shape)


def _input_args(d: MaterialDerivation) -> list[Argument]:
    return [_matrix_arg(n, m, f"per-element material input {n}") for n, m in d.inputs.items()]


@dataclass(frozen=True)
class Mapping:
    """A material's parameters as SymPy expressions of ``E``, ``nu``."""

    E: sp.Symbol
    nu: sp.Symbol
    exprs: dict[str, sp.Expr]


@cache
def small_strain_mapping(name: str) -> Mapping:
    """``from_E_nu`` of material ``name`` in the symbols ``E`` and ``nu``."""
    material = MATERIALS[name]
    E, nu = sp.Symbol("E", positive=True), sp.Symbol("nu", real=True)
    params = {p: sp.Symbol(p, real=True) for p in material.PARAM_NAMES}
    exprs = material.from_E_nu(E, nu, params)
    if set(exprs) != set(material.PARAM_NAMES):
        raise ValueError(f"{name}.from_E_nu must return {material.PARAM_NAMES}, got {set(exprs)}")
    return Mapping(E, nu, {p: sp.sympify(exprs[p]) for p in material.PARAM_NAMES})


_DISPLAY_NAMES = {"lam": "lambda"}


def display_psi(name: str) -> sp.Expr:
    """``psi`` of material ``name`` with ``F`` (and element inputs) as matrix symbols: the
    formula as written, ``tr``/``det`` unexpanded, for ``show`` and the docs."""
    material = MATERIALS[name]
    symbols: dict = {p: sp.Symbol(_DISPLAY_NAMES.get(p, p), real=True)
                     for p in material.PARAM_NAMES}
    for n, shape in element_inputs(name):
        symbols[n] = sp.MatrixSymbol(n, *shape, *((1,) if len(shape) == 1 else ()))
    return material.psi(sp.MatrixSymbol("F", 3, 3), symbols)


def material_info(name: str) -> dict:
    """Everything the runtime and the docs need about a material besides its kernels."""
    material = MATERIALS[name]
    mapping = small_strain_mapping(name)
    display = display_psi(name)
    return {
        "param_names": tuple(material.PARAM_NAMES),
        "element_inputs": element_inputs(name),
        "shape_params": tuple(getattr(material, "SHAPE_PARAMS", ())),
        "positive": tuple(getattr(material, "POSITIVE", ())),
        "allows_inversion": bool(material.ALLOWS_INVERSION),
        "exact_small_strain": bool(getattr(material, "EXACT_SMALL_STRAIN", True)),
        "rotation_invariant": bool(getattr(material, "ROTATION_INVARIANT", True)),
        "isotropic": is_isotropic(name),
        "inversion": material.INVERSION,
        "description": material.DESCRIPTION,
        "doc": (material.__doc__ or "").strip(),
        "psi_text": sp.sstr(display),
        "psi_latex": sp.latex(display),
        "mapping": {p: sp.pycode(e) for p, e in mapping.exprs.items()},
        "mapping_text": {p: sp.sstr(e) for p, e in mapping.exprs.items()},
        "mapping_latex": {p: sp.latex(e) for p, e in mapping.exprs.items()},
    }


def _param_args(names: tuple[str, ...], symbols: dict[str, sp.Symbol]) -> tuple[Argument, ...]:
    return tuple(Argument(n, (), (symbols[n],), per_element=False) for n in names)


def _matrix_arg(name: str, matrix: sp.Matrix, doc: str) -> Argument:
    shape = (matrix.rows, matrix.cols) if matrix.cols > 1 else (matrix.rows,)
    return Argument(name, shape, tuple(flatten(matrix)), doc=doc)


def _element_symbols() -> tuple[sp.Matrix, sp.Matrix, sp.Symbol]:
    return symbol_matrix("x", 4, 3), symbol_matrix("dphi", 4, 3), sp.Symbol("vol", real=True)


def _cse_prelude(exprs: list[sp.Expr], names: list[sp.Symbol], prefix: str):
    """CSE ``exprs`` and name each result, so later expressions can reference ``names``."""
    replacements, reduced = sp.cse(
        exprs, symbols=sp.numbered_symbols(prefix), order="canonical", optimizations="basic"
    )
    return list(replacements) + list(zip(names, reduced, strict=True))


def material_module(name: str) -> ModuleSpec:
    """All kernels of one material: pointwise ``psi``, ``P``, ``dP/dF`` and per-element energy,
    gradient and Hessian of ``vol * psi(F(x))`` by the chain rule through ``F``."""
    material: ModuleType = MATERIALS[name]
    d = derive_material(name)
    params = _param_args(material.PARAM_NAMES, d.params)
    extra = _input_args(d)
    F_args = [_matrix_arg("F", d.F, "deformation gradients"), *extra]
    # Each derivative is CSE'd once, in the symbols of F, and shared by the pointwise kernel
    # and the element kernel (which computes F from x_e first): the CSE is the slow stage.
    psi_sym, P_sym = sp.Symbol("psi"), symbol_matrix("P", 3, 3)
    A_sym = sp.Matrix(9, 9, lambda a, b: sp.Symbol(f"A_{min(a, b)}_{max(a, b)}"))
    psi_steps, P_steps, A_steps = derivative_steps(name)
    kernels: list[KernelSpec] = [
        make_kernel(name, "psi", "Strain energy density psi(F).", F_args, params,
                    [("psi", (), [psi_sym], False)], psi_steps),
        make_kernel(name, "dpsi_dF", "First Piola-Kirchhoff stress P = dpsi/dF.", F_args, params,
                    [("P", (3, 3), flatten(P_sym), False)], P_steps),
        make_kernel(name, "d2psi_dF2", "dP/dF, 9x9 in the row-major flattening of F.", F_args,
                    params, [("dP_dF", (9, 9), flatten(A_sym), True)], A_steps),
    ]

    x, D, vol = _element_symbols()
    element_inputs = [
        _matrix_arg("x_e", x, "deformed vertex positions of each tet"),
        _matrix_arg("dphi_dX", D, "rest-shape gradients of the shape functions"),
        Argument("vol", (), (vol,), doc="rest volumes"),
        *extra,
    ]
    F_def = deformation_gradient(x, D)
    prelude_F = list(zip(flatten(d.F), flatten(F_def), strict=True))

    kernels.append(make_kernel(
        name, "energy", "Element potential energy vol * psi(F(x_e)).", element_inputs, params,
        [("energy", (), [vol * psi_sym], False)], prelude_F + psi_steps))

    gradient = [vol * sum(P_sym[c, j] * D[v, j] for j in range(3))
                for v in range(4) for c in range(3)]
    kernels.append(make_kernel(
        name, "gradient", "Element gradient d(vol psi)/dx_e, vertex-major (12).", element_inputs,
        params, [("gradient", (12,), gradient, False)], prelude_F + P_steps))

    kernels.append(_dgradient_dparams_kernel(name, d, element_inputs, params, D, vol,
                                             prelude_F))
    kernels.append(_d3psi_contract_kernel(name, d, F_args, params))

    stress_derivative = prelude_F + A_steps
    hess_doc = "Element Hessian d2(vol psi)/dx_e2 (12x12, vertex-major)."
    kernels.append(make_kernel(
        name, "hessian", hess_doc, element_inputs, params,
        *_hessian_contraction(A_sym, D, vol, stress_derivative)))
    # Projecting dP/dF (not the 12x12) keeps B^T A B positive semi-definite at a 9x9 cost.
    A_psd = sp.Matrix(9, 9, lambda a, b: sp.Symbol(f"Ap_{a}_{b}"))
    # F is the singular frame the "svd" projection needs, given where psi is isotropic
    frame = tuple(flatten(d.F)) if is_isotropic(name) else ()
    projection = Projection(9, tuple(flatten(A_sym)), tuple(flatten(A_psd)), frame=frame)
    psd_doc = hess_doc[:-1] + " with dP/dF projected to positive semi-definite"
    kernels.append(make_kernel(
        name, "hessian_psd", psd_doc + ".", element_inputs, params,
        *_hessian_contraction(A_psd, D, vol, [*stress_derivative, projection])))
    psd = kernels[-1]
    kernels.append(psd.projected_by("hessian_psd_jacobi", "jacobi", psd_doc + " by cyclic Jacobi."))
    svd_doc = (" in the singular frame of F (block diagonal there: psi is isotropic)." if frame
               else " by QL (psi is not isotropic: no block-diagonal frame).")
    kernels.append(psd.projected_by("hessian_psd_svd", "svd", psd_doc + svd_doc))

    return ModuleSpec(name=name, doc=material.DESCRIPTION, source=material.__name__,
                      param_names=tuple(material.PARAM_NAMES), kernels=tuple(kernels),
                      info=material_info(name), pointwise=POINTWISE, unit=p1_unit(name))


@cache
def stress_param_steps(name: str) -> tuple:
    """CSE'd steps computing ``dP/dp`` (``dP_i_j_k`` for the ``k``-th parameter) from ``F``:
    SymPy's derivative of the direct ``P`` with respect to each parameter."""
    d = derive_material(name)
    names, exprs = [], []
    for k, p in enumerate(MATERIALS[name].PARAM_NAMES):
        for i in range(3):
            for j in range(3):
                names.append(sp.Symbol(f"dP_{i}_{j}_{k}"))
                exprs.append(sp.diff(d.P[i, j], d.params[p]))
    return tuple(_cse_prelude(exprs, names, "p"))


def _dgradient_dparams_kernel(name: str, d: MaterialDerivation, element_inputs, params,
                              D: sp.Matrix, vol: sp.Symbol, prelude_F: list) -> KernelSpec:
    """``d gradient / d params`` (12 x n_params): ``vol dP/dp : dphi_dX`` per parameter."""
    n = len(d.params)
    dP = [sp.Matrix(3, 3, lambda i, j, k=k: sp.Symbol(f"dP_{i}_{j}_{k}")) for k in range(n)]
    out = [vol * sum(dP[k][c, j] * D[v, j] for j in range(3))
           for v in range(4) for c in range(3) for k in range(n)]
    return make_kernel(
        name, "dgradient_dparams",
        "Element gradient's derivative by each parameter, (12, n_params), vertex-major.",
        element_inputs, params, [("dgradient_dparams", (12, n), out, False)],
        prelude_F + list(stress_param_steps(name)))


def contracted_third_steps(name: str) -> tuple[list, list, list]:
    """Reverse-mode derivative of ``s = sum_kl dP/dF_kl C_kl`` through the CSE'd steps of
    ``dP/dF`` (:func:`derivative_steps`): ``(steps, ds/dF (9), ds/dparams)``.

    Each step ``y = e(x, ...)`` of ``dP/dF`` gets an adjoint ``r = ds/dy`` (a new step, once
    every later step that reads ``y`` has added its part), which adds ``r de/dx`` to each
    argument's: SymPy differentiates one small step at a time, never the expanded ``dP/dF``.
    """
    d = derive_material(name)
    _, _, A_steps = derivative_steps(name)
    C = symbol_matrix("C", 9, 9)
    bar: dict = {sp.Symbol(f"A_{a}_{b}"): C[a, b] + C[b, a] if a != b else C[a, a]
                 for a, b in _UPPER}
    defined = {sym for sym, _ in A_steps}
    targets = set(flatten(d.F)) | set(d.params.values())
    steps = []
    for sym, expr in reversed(A_steps):
        adjoint = bar.pop(sym, None)
        if adjoint is None:
            continue
        r = sp.Symbol(f"r{len(steps)}")
        steps.append((r, adjoint))
        for x in sorted(expr.free_symbols & (defined | targets), key=sp.default_sort_key):
            dx = sp.diff(expr, x)
            if dx != 0:
                bar[x] = bar.get(x, sp.Integer(0)) + r * dx
    zero = sp.Integer(0)
    return (list(A_steps) + steps, [bar.get(f, zero) for f in flatten(d.F)],
            [bar.get(d.params[p], zero) for p in MATERIALS[name].PARAM_NAMES])


def _d3psi_contract_kernel(name: str, d: MaterialDerivation, F_args: list,
                           params) -> KernelSpec:
    """``d/dF`` and ``d/dparams`` of ``sum_kl dP/dF_kl C_kl`` (a third derivative of ``psi``
    contracted with a 9x9 ``C``): the adjoint of Rayleigh stiffness damping."""
    steps, dF, dp = contracted_third_steps(name)
    C_arg = _matrix_arg("C", symbol_matrix("C", 9, 9), "9x9 weights contracted with dP/dF")
    return make_kernel(
        name, "d3psi_contract",
        "d/dF (3x3) and d/dparams of sum_kl dP/dF_kl C_kl: the third derivative of psi "
        "contracted with C.", [F_args[0], C_arg, *F_args[1:]], params,
        [("dF", (3, 3), dF, False), ("dparams", (len(dp),), dp, False)], steps)


def _hessian_contraction(A: sp.Matrix, D: sp.Matrix, vol: sp.Symbol, prelude: list):
    """``H = vol B^T A B`` with ``B = dF/dx`` applied implicitly (it is sparse and linear):
    contract over ``l`` into ``T`` (9x12), then over ``j``. Returns (outputs, prelude)."""
    steps = list(prelude)
    T = sp.Matrix(9, 12, lambda a, q: sp.Symbol(f"T_{a}_{q}"))
    for c in range(3):
        for j in range(3):
            for w in range(4):
                for dd in range(3):
                    value = sum(A[3 * c + j, 3 * dd + ll] * D[w, ll] for ll in range(3))
                    steps.append((T[3 * c + j, 3 * w + dd], value))
    hessian = sp.Matrix(12, 12, lambda r, s: vol * sum(
        D[r // 3, j] * T[3 * (r % 3) + j, s] for j in range(3)))
    return [("hessian", (12, 12), flatten(hessian), True)], steps


def _tet_raw() -> dict[str, tuple[list[Argument], list[Argument], list[tuple]]]:
    """Exact expressions of the tet kernels: name -> (inputs, params, outputs)."""
    X = tet.rest_symbols()
    X_arg = _matrix_arg("X_e", X, "rest vertex positions of each tet")
    p = symbol_vector("p", 3)
    rho, vol = sp.Symbol("rho", real=True), sp.Symbol("vol", real=True)
    x, D, _ = _element_symbols()
    return {
        "rest_shape": (
            [X_arg], [],
            [("dphi_dX", (4, 3), flatten(tet.shape_gradients(X)), False),
             ("volume", (), [tet.signed_volume(X)], False)]),
        "phi": (
            [X_arg, _matrix_arg("p", p, "points")], [],
            [("phi", (4,), list(tet.barycentric(X, p)), False)]),
        "mass_matrix": (
            [Argument("vol", (), (vol,), doc="rest volumes")],
            [Argument("rho", (), (rho,), per_element=False)],
            [("mass", (12, 12), flatten(tet.mass_matrix(rho, vol)), True)]),
        "deformation_gradient": (
            [_matrix_arg("x_e", x, "deformed vertex positions"),
             _matrix_arg("dphi_dX", D, "shape-function gradients")], [],
            [("F", (3, 3), flatten(deformation_gradient(x, D)), False)]),
        "deformed_volume": (
            [_matrix_arg("x_e", x, "deformed vertex positions")], [],
            [("volume", (), [tet.signed_volume(x)], False)]),
    }


_TET_DOCS = {
    "rest_shape": "Shape-function gradients dphi/dX and signed volume of rest tets.",
    "phi": "Shape functions (barycentric coordinates) of each tet at a point p.",
    "mass_matrix": "Exact consistent mass matrix rho * integral N^T N dV (12x12).",
    "deformation_gradient": "Deformation gradient F = sum_v x_v dphi_v/dX^T.",
    "deformed_volume": "Signed volume of deformed tets (<= 0: inverted or flat).",
}


def _spring_raw() -> dict[str, tuple[list[Argument], list[Argument], list[tuple]]]:
    """Exact expressions of the zero-rest-length spring ``1/2 k |x_a - x_b|^2``."""
    xa, xb = symbol_vector("xa", 3), symbol_vector("xb", 3)
    k = sp.Symbol("k", real=True)
    energy = k / 2 * ((xa - xb).T * (xa - xb))[0, 0]
    dofs = list(xa) + list(xb)
    gradient = [sp.diff(energy, s) for s in dofs]
    hessian = [sp.diff(g, s) for g in gradient for s in dofs]
    inputs = [_matrix_arg("x_a", xa, "first end points"),
              _matrix_arg("x_b", xb, "second end points")]
    params = [Argument("k", (), (k,), per_element=False)]
    return {
        "energy": (inputs, params, [("energy", (), [energy], False)]),
        "gradient": (inputs, params, [("gradient", (6,), gradient, False)]),
        "hessian": (inputs, params, [("hessian", (6, 6), hessian, True)]),
    }


_SPRING_DOCS = {
    "energy": "Spring energy 1/2 k |x_a - x_b|^2.",
    "gradient": "Spring gradient (d/dx_a, d/dx_b), length 6.",
    "hessian": "Spring Hessian (6x6).",
}


def tet_module() -> ModuleSpec:
    """Material-independent kernels of the linear tetrahedron."""
    kernels = tuple(make_kernel("tet", name, _TET_DOCS[name], inputs, params, outputs)
                    for name, (inputs, params, outputs) in _tet_raw().items())
    return ModuleSpec(name="tet", doc="linear tetrahedron geometry", source=tet.__name__,
                      param_names=(), kernels=kernels)


def spring_module() -> ModuleSpec:
    """Zero-rest-length spring ``1/2 k |x_a - x_b|^2`` (the user's pull spring)."""
    kernels = tuple(make_kernel("spring", name, _SPRING_DOCS[name], inputs, params, outputs)
                    for name, (inputs, params, outputs) in _spring_raw().items())
    return ModuleSpec(name="spring", doc="zero-rest-length spring", source=__name__,
                      param_names=("k",), kernels=kernels)


def module_names() -> list[str]:
    """Every module the generator emits, in a fixed order: P1's, then the higher-order
    elements' (:func:`codegen.element_kernels.module_names`)."""
    from codegen import element_kernels  # it builds on this module

    return ["tet", "spring", "pressure", *sorted(MATERIALS), *element_kernels.module_names()]


def build_module(name: str) -> ModuleSpec:
    """The spec of one module (``tet``, ``spring``, a material, or a higher-order element's
    ``<element>_tet`` / ``<element>_<material>``)."""
    if name == "tet":
        return tet_module()
    if name == "spring":
        return spring_module()
    if name == "pressure":  # codegen/pressure.py (imported here: it imports codegen.spec)
        from codegen.pressure import pressure_module
        return pressure_module()
    if name in MATERIALS:
        return material_module(name)
    from codegen import element_kernels  # it builds on this module

    return element_kernels.build_module(name)


def all_modules() -> list[ModuleSpec]:
    """Every module the generator emits, in a fixed order."""
    return [build_module(n) for n in module_names()]


def reference_outputs(module: str, kernel: str) -> tuple[list[sp.Symbol], list[list[sp.Expr]]]:
    """Un-CSE'd expressions of a kernel's outputs, straight from SymPy, for the diff tests.

    Element kernels are differentiated directly with respect to the 12 DOFs, not through the
    chain rule the generated code uses. Returns ``(input symbols, [flat exprs per output])``
    with the input symbols in the kernel's argument order (inputs, then parameters; a
    material's element inputs are the last inputs).
    """
    if module in MATERIALS:
        d = derive_material(module)
        params = [d.params[n] for n in MATERIALS[module].PARAM_NAMES]
        params = [s for m in d.inputs.values() for s in flatten(m)] + params
        if kernel == "dpsi_dF_dparams":  # not a kernel: dP/dp (9, n_params), for the tests
            names = MATERIALS[module].PARAM_NAMES
            return flatten(d.F) + params, [[sp.diff(P, d.params[p]) for P in flatten(d.P)
                                            for p in names]]
        if kernel in ("psi", "dpsi_dF", "d2psi_dF2"):
            out = {"psi": [d.psi], "dpsi_dF": flatten(d.P), "d2psi_dF2": flatten(d.dP_dF)}[kernel]
            return flatten(d.F) + params, [out]
        x, D, vol = _element_symbols()
        F_of_x = dict(zip(flatten(d.F), flatten(deformation_gradient(x, D)), strict=True))
        energy = vol * d.psi.xreplace(F_of_x)
        dofs = flatten(x)
        symbols = dofs + flatten(D) + [vol] + params
        if kernel == "energy":
            return symbols, [[energy]]
        gradient = [sp.diff(energy, s) for s in dofs]
        if kernel == "gradient":
            return symbols, [gradient]
        if kernel == "dgradient_dparams":
            names = MATERIALS[module].PARAM_NAMES
            return symbols, [[sp.diff(g, d.params[p]) for g in gradient for p in names]]
        return symbols, [[sp.diff(g, s) for g in gradient for s in dofs]]
    if module == "pressure":
        from codegen.pressure import pressure_raw
        raw = pressure_raw()
    else:
        raw = {"tet": _tet_raw, "spring": _spring_raw}[module]()
    inputs, params, outputs = raw[kernel]
    symbols = [s for a in (*inputs, *params) for s in a.symbols]
    return symbols, [list(exprs) for _, _, exprs, _ in outputs]
