"""Frozen, back-end independent description of generated kernels (stage 2 of the pipeline)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import sympy as sp


@dataclass(frozen=True)
class Argument:
    """A kernel input.

    ``per_element`` inputs have shape ``(m, *shape)``; parameters (``per_element=False``) are
    scalars shared by all elements of a call. ``symbols`` lists the entries in row-major order.
    """

    name: str
    shape: tuple[int, ...]
    symbols: tuple[sp.Symbol, ...]
    per_element: bool = True
    doc: str = ""
    per_point: bool = False
    """A quadrature kernel's input with a leading quadrature-point axis (``shape[0]`` points):
    ``symbols`` are one point's entries, read afresh at each point of the kernel's loop."""

    @property
    def size(self) -> int:
        return math.prod(self.shape)

    @property
    def point_size(self) -> int:
        """Entries read at one quadrature point (``size`` unless ``per_point``)."""
        return len(self.symbols) if self.per_point else self.size


@dataclass(frozen=True)
class Output:
    """A kernel output of shape ``(m, *shape)``; ``exprs`` row-major, over the CSE'd symbols.

    ``symmetric`` outputs are square matrices whose upper triangle is computed and mirrored.
    """

    name: str
    shape: tuple[int, ...]
    exprs: tuple[sp.Expr, ...]
    symmetric: bool = False

    @property
    def size(self) -> int:
        return math.prod(self.shape)

    def entries(self) -> list[tuple[int, sp.Expr, tuple[int, ...]]]:
        """``(flat index, expression, mirrored flat indices)`` of the entries to compute."""
        if not self.symmetric:
            return [(k, e, ()) for k, e in enumerate(self.exprs)]
        n = self.shape[0]
        rows = []
        for i in range(n):
            for j in range(i, n):
                mirror = () if i == j else (j * n + i,)
                rows.append((i * n + j, self.exprs[i * n + j], mirror))
        return rows


@dataclass(frozen=True)
class Projection:
    """Project a symmetric ``n x n`` matrix to positive semi-definite: eigenvalues below zero
    are clamped to zero. An intermediate step between assignments; ``inputs`` and ``outputs``
    are the row-major entries before and after. ``method`` names the C kernels' eigen-solver
    where the matrix is indefinite: ``"ql"`` (Householder tridiagonalization and implicit QL)
    or ``"jacobi"`` (cyclic Jacobi rotations: slower; kept because its round-off is that of
    every run before it was replaced) or ``"svd"`` (``dP/dF`` of an isotropic ``psi`` rotated
    into the singular frame of ``frame``, the entries of ``F``, where it is block diagonal;
    QL where ``frame`` is empty); the NumPy kernels use LAPACK's for all."""

    n: int
    inputs: tuple[sp.Symbol, ...]
    outputs: tuple[sp.Symbol, ...]
    method: str = "ql"
    frame: tuple[sp.Symbol, ...] = ()


Step = tuple[sp.Symbol, sp.Expr] | Projection


@dataclass(frozen=True)
class KernelSpec:
    """One kernel: inputs, parameters, CSE'd intermediates and outputs."""

    module: str
    name: str
    doc: str
    inputs: tuple[Argument, ...]
    params: tuple[Argument, ...]
    intermediates: tuple[Step, ...]
    outputs: tuple[Output, ...]
    twin_of: str | None = None
    """This kernel is that one of the same module with its :class:`Projection` steps by
    another method: the C back end renders a wrapper passing its projection to the twin's
    element body, the NumPy back end (LAPACK for every method) an alias; neither a copy."""
    points: int = 0
    """A quadrature kernel (``points > 0``): the intermediates and outputs are one quadrature
    point's, in the symbols of the ``per_point`` inputs at that point; the kernel loops over
    the ``points`` points and returns the sum of the outputs (0: no loop)."""
    positive: tuple[str, ...] = ()
    """Outputs every entry of which must be ``> 0`` (a rest shape's ``det J``): both back
    ends raise ``ValueError`` naming the first element and entry that is not."""
    quadrature: str = ""
    """A quadrature kernel of a material on a higher-order element: the kind of the element's
    shared quadrature loop both back ends call (``energy``, ``gradient``,
    ``dgradient_dparams``, ``hessian``; :attr:`ModuleSpec.role` ``"quadrature"``) with the
    material's steps at one ``F`` (:class:`MaterialSteps`), instead of writing the whole sum
    out per material; ``intermediates`` and ``outputs`` still give its operation count."""

    @property
    def projection_method(self) -> str | None:
        """The method of its :class:`Projection` steps (None without one)."""
        methods = {s.method for s in self.intermediates if isinstance(s, Projection)}
        if len(methods) > 1:
            raise ValueError(f"{self.qualified_name}: projections by several methods")
        return methods.pop() if methods else None

    def projected_by(self, name: str, method: str, doc: str) -> KernelSpec:
        """This kernel as ``name`` with its projections by ``method`` (a twin, not derived
        again)."""
        steps = tuple(replace(s, method=method) if isinstance(s, Projection) else s
                      for s in self.intermediates)
        return replace(self, name=name, doc=doc, intermediates=steps, twin_of=self.name)

    def requiring_positive(self, *outputs: str) -> KernelSpec:
        """This kernel refusing elements where an entry of ``outputs`` is not ``> 0``."""
        known = {o.name for o in self.outputs}
        if not set(outputs) <= known:
            raise ValueError(f"{self.qualified_name} has no output {set(outputs) - known}")
        return replace(self, positive=tuple(outputs))

    @property
    def op_count(self) -> int:
        """Arithmetic operations per element, as counted by ``sympy.count_ops``
        (a :class:`Projection` counts as zero: it is an eigen-solve, not an expression);
        a quadrature kernel's are one point's (plus the sum's additions) times ``points``."""
        exprs = [s[1] for s in self.intermediates if not isinstance(s, Projection)]
        exprs += [e for out in self.outputs for _, e, _ in out.entries()]
        ops = int(sum(sp.count_ops(e) for e in exprs))
        if not self.points:
            return ops
        return self.points * (ops + sum(len(out.entries()) for out in self.outputs))

    @property
    def qualified_name(self) -> str:
        return f"{self.module}_{self.name}"


@dataclass(frozen=True)
class MaterialSteps:
    """The steps at one ``F`` a higher-order element's quadrature kernels of one material call
    at each point: ``psi``, ``P`` and ``dP/dF`` are the pointwise kernels of the material's
    own module (``<name>_pointwise.c``; in NumPy ``<name>.py``'s ``_<kernel>_body``),
    ``point_kernels`` the ones of its own (``dP/dp``)."""

    name: str
    n_inputs: int
    """The material's per-element inputs (after ``F``)."""
    n_params: int
    isotropic: bool
    """``F`` is the frame of the ``"svd"`` projection (else QL)."""
    point_kernels: tuple[KernelSpec, ...] = ()


@dataclass(frozen=True)
class ModuleSpec:
    """A group of kernels rendered into one file per back end (a material, or the tet)."""

    name: str
    doc: str
    source: str
    param_names: tuple[str, ...]
    kernels: tuple[KernelSpec, ...]
    info: dict | None = None
    """Materials only: :func:`codegen.derive.material_info` (mapping, inversion, formulas)."""
    unit: str = ""
    """The C translation unit the module is compiled in: ``""`` the extension's own file
    (``_ckernels.c``), else ``_ckernels_<unit>.c`` (the quadratic elements': ``p2``)."""
    constants: tuple[tuple[str, str], ...] = ()
    """Module-level constants of the NumPy module, ``(name, Python literal)`` (an element's
    node layout, its quadrature rule)."""
    pointwise: tuple[str, ...] = ()
    """A P1 material's leading kernels at one ``F`` (``psi``, ``dpsi_dF``, ``d2psi_dF2``):
    the C back end writes them to ``<name>_pointwise.c``, which ``<name>.c`` includes and the
    higher-order elements' units include for their element functions; the NumPy back end
    writes each body as ``_<kernel>_body``, which the public kernel and the higher-order
    elements' material modules call."""
    material_steps: MaterialSteps | None = None
    """A higher-order element's material module: the steps its quadrature kernels call."""
    role: str = "kernels"
    """``"kernels"``: a module of kernels for every back end; ``"quadrature"``: a higher-order
    element's shared quadrature pieces (one point's ``F`` and terms) and the loops around them,
    rendered by ``templates/<backend>/quadrature.<c|py>.jinja`` into
    ``<element>_quadrature.c`` and ``.py`` (no kernels of its own in the runtime's tables)."""


def make_kernel(
    module: str,
    name: str,
    doc: str,
    inputs: Sequence[Argument],
    params: Sequence[Argument],
    outputs: Sequence[tuple[str, tuple[int, ...], Sequence[sp.Expr], bool]],
    prelude: Sequence[Step] = (),
    points: int = 0,
) -> KernelSpec:
    """Run common-subexpression elimination over all outputs and freeze a :class:`KernelSpec`.

    ``prelude`` holds named assignments (and projections) computed before the CSE'd block
    (for example ``F`` from the element DOFs), which the outputs may reference by symbol.
    Only the entries a symmetric output actually computes take part in the CSE.
    ``points``: a quadrature kernel's point count (:attr:`KernelSpec.points`).
    """
    pending = []
    for out_name, shape, exprs, symmetric in outputs:
        probe = Output(out_name, shape, tuple(exprs), symmetric)
        pending.append((probe, [e for _, e, _ in probe.entries()]))
    flat = [e for _, exprs in pending for e in exprs]
    # "basic" also pulls out common factors and negations (18 % fewer operations in P)
    replacements, reduced = sp.cse(flat, symbols=sp.numbered_symbols("t"), order="canonical",
                                   optimizations="basic")
    outs = []
    position = 0
    for probe, exprs in pending:
        computed = reduced[position : position + len(exprs)]
        position += len(exprs)
        full = list(probe.exprs)
        for (k, _, mirror), value in zip(probe.entries(), computed, strict=True):
            full[k] = value
            for k2 in mirror:
                full[k2] = value
        outs.append(Output(probe.name, probe.shape, tuple(full), probe.symmetric))
    steps, outs = name_cube_roots(list(prelude) + list(replacements), outs)
    return KernelSpec(
        module=module,
        name=name,
        doc=doc,
        inputs=tuple(inputs),
        params=tuple(params),
        intermediates=_live(steps, outs),
        outputs=tuple(outs),
        points=points,
    )


def name_cube_roots(steps: list[Step], outputs: list[Output]) -> tuple[list[Step],
                                                                        list[Output]]:
    """Compute each symbol's cube root once: every ``b^(p/3)`` becomes ``r^n b^m`` with the
    step ``r = b^(-1/3)`` (``p = 3 m - n``, ``n`` in 0..2), so ``J^(-2/3)`` and ``J^(-5/3)``
    share one root (``r^2``, ``r^2 / J``) where they were separate powers."""
    def thirds(expr: sp.Expr) -> set[sp.Pow]:
        return {e for e in sp.preorder_traversal(expr) if e.is_Pow and e.base.is_Symbol
                and e.exp.is_Rational and e.exp.q == 3}

    found: set[sp.Pow] = set()
    for step in steps:
        if not isinstance(step, Projection):
            found |= thirds(step[1])
    for out in outputs:
        for _, e, _ in out.entries():
            found |= thirds(e)
    bases = sorted({p.base for p in found}, key=str)
    if not bases:
        return steps, outputs
    roots = {b: sp.Symbol(f"rcbrt_{b}", real=True) for b in bases}
    rewrite = {}
    for power in found:
        m = -(-int(power.exp.p) // 3)  # ceil(p / 3)
        n = 3 * m - int(power.exp.p)
        rewrite[power] = roots[power.base] ** n * power.base ** m
    new_steps: list[Step] = [(roots[b], b ** sp.Rational(-1, 3)) for b in bases
                             if not any(not isinstance(s, Projection) and s[0] == b
                                        for s in steps)]
    for step in steps:
        if isinstance(step, Projection):
            new_steps.append(step)
            continue
        new_steps.append((step[0], step[1].xreplace(rewrite)))
        if step[0] in roots:
            new_steps.append((roots[step[0]], step[0] ** sp.Rational(-1, 3)))
    new_outputs = [Output(o.name, o.shape, tuple(e.xreplace(rewrite) for e in o.exprs),
                          o.symmetric) for o in outputs]
    return new_steps, new_outputs


def _live(steps: list[Step], outputs: list[Output]) -> tuple[Step, ...]:
    """Drop assignments no output depends on (e.g. the lower half of a symmetric contraction)."""
    needed: set[sp.Symbol] = set()
    for out in outputs:
        for _, e, _ in out.entries():
            needed |= e.free_symbols
    kept: list[Step] = []
    for step in reversed(steps):
        if isinstance(step, Projection):
            if needed & set(step.outputs):
                kept.append(step)
                needed |= set(step.inputs)
        elif step[0] in needed:
            kept.append(step)
            needed |= step[1].free_symbols
    return tuple(reversed(kept))
