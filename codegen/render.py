"""Stage 3: render :class:`~codegen.spec.ModuleSpec` objects through Jinja2 templates.

Each back end is a template folder plus an expression printer; both render the same spec.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import jinja2
import sympy as sp
from sympy.printing.c import C99CodePrinter
from sympy.printing.numpy import NumPyPrinter

from codegen.elements import QUADRATURE_ELEMENTS
from codegen.materials import MATERIALS
from codegen.spec import Argument, KernelSpec, ModuleSpec, Projection

ROOT = Path(__file__).resolve().parent.parent
TEMPLATES = ROOT / "templates"


class _PowerMixin:
    """Integer powers as products, halves as sqrt, thirds as cbrt: faster than pow().

    ``x**(p/q)`` is printed as ``x**whole * root(x)**part`` with ``whole, part = divmod(p, q)``.
    Compound bases go through :meth:`_integer_power` so they are evaluated once.
    """

    _sqrt = "sqrt"
    _cbrt = "cbrt"

    def _integer_power(self, base: str, n: int, atomic: bool) -> str:
        return "*".join([base] * n)

    def _print_Pow(self, expr: sp.Pow, rational: bool = False) -> str:  # noqa: ARG002
        base, exp = expr.as_base_exp()
        if not (exp.is_Rational and exp.q in (1, 2, 3) and abs(exp.p) <= 4 * exp.q):
            return super()._print_Pow(expr)
        atomic = base.is_Atom
        b = self.parenthesize(base, 100) if atomic else f"({self._print(base)})"
        whole, part = divmod(int(exp.p), int(exp.q))
        factors = []
        if part:
            root = f"{self._sqrt if exp.q == 2 else self._cbrt}({self._print(base)})"
            factors.append(self._integer_power(root, part, False))  # one root call
        if whole > 0:
            factors.append(self._integer_power(b, whole, atomic))
        text = "*".join(factors) if factors else "1.0"
        if whole < 0:
            text = f"{text}/({self._integer_power(b, -whole, atomic)})"
        return f"({text})"


class NumPyExpressionPrinter(_PowerMixin, NumPyPrinter):
    """Vectorized NumPy expressions; symbols are arrays of shape ``(m,)``."""

    _sqrt = "numpy.sqrt"
    _cbrt = "numpy.cbrt"

    def _integer_power(self, base: str, n: int, atomic: bool) -> str:
        if atomic or n == 1:
            return "*".join([base] * n)
        return f"{base}**{n}"


class CExpressionPrinter(_PowerMixin, C99CodePrinter):
    """C99 expressions over doubles; compound bases use the inline ``fem3d_powi``.

    Negative thirds go through ``fem3d_rcbrt(x) = x^(-1/3)`` (no cbrt, no division):
    ``x^(-k/3) = rcbrt(x)^(k mod 3) / x^(k div 3)``, ``J^(-2/3)`` is ``rcbrt(J)*rcbrt(J)``.
    """

    def _integer_power(self, base: str, n: int, atomic: bool) -> str:
        if atomic or n == 1:
            return "*".join([base] * n)
        return f"fem3d_powi({base}, {n})"

    @staticmethod
    def _negative_third(expr: sp.Expr) -> bool:
        return bool(expr.is_Pow and expr.exp.is_Rational and expr.exp.q == 3
                    and expr.exp.p < 0)

    def _print_Pow(self, expr: sp.Pow, rational: bool = False) -> str:
        if not self._negative_third(expr):
            return super()._print_Pow(expr, rational)
        base = expr.base
        atomic = base.is_Atom
        b = self.parenthesize(base, 100) if atomic else f"({self._print(base)})"
        whole, part = divmod(-int(expr.exp.p), 3)
        text = self._integer_power(f"fem3d_rcbrt({self._print(base)})", part, True) if part \
            else "1.0"
        if whole:
            text = f"{text}/({self._integer_power(b, whole, atomic)})"
        return f"({text})"

    def _print_Mul(self, expr: sp.Mul) -> str:
        # SymPy prints a negative power as a division by the positive one (C/J^(2/3)):
        # print negative thirds as factors instead, so they keep fem3d_rcbrt
        if any(self._negative_third(f) for f in expr.args):
            factors = [sp.Symbol(self._print_Pow(f)) if self._negative_third(f) else f
                       for f in expr.args]
            return super()._print_Mul(sp.Mul(*factors, evaluate=False))
        return super()._print_Mul(expr)


@dataclass(frozen=True)
class Backend:
    """A template folder, its module template, the printer and the output file suffix."""

    name: str
    template: str
    printer: type
    suffix: str


BACKENDS = {
    "numpy": Backend("numpy", "numpy/module.py.jinja", NumPyExpressionPrinter, ".py"),
    "c": Backend("c", "c/module.c.jinja", CExpressionPrinter, ".c"),
}


def _environment() -> jinja2.Environment:
    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(TEMPLATES),
        undefined=jinja2.StrictUndefined,
        keep_trailing_newline=True,
        trim_blocks=True,
        lstrip_blocks=True,
    )


def _arg_view(arg: Argument, used: set[sp.Symbol]) -> dict:
    return {
        "name": arg.name,
        "shape": arg.shape,
        "size": arg.size,
        "symbols": [str(s) for s in arg.symbols],
        # (position, name) of the entries the kernel reads; unused ones are not unpacked
        "used": [(i, str(s)) for i, s in enumerate(arg.symbols) if s in used],
        "doc": arg.doc,
        "per_element": arg.per_element,
        "per_point": arg.per_point,
        "point_size": arg.point_size,
    }


def kernel_view(kernel: KernelSpec, printer) -> dict:
    """Everything a template needs about one kernel, with expressions already printed.

    A higher-order element's quadrature kernel (:attr:`~codegen.spec.KernelSpec.quadrature`)
    is rendered as a call of the element's shared loops on every back end: its steps and
    expressions are not printed (no template reads them)."""
    used: set[sp.Symbol] = set()
    steps = []
    for step in () if kernel.quadrature else kernel.intermediates:
        if isinstance(step, Projection):
            used |= set(step.inputs) | set(step.frame)
            steps.append({"kind": "project", "n": step.n, "inputs": [str(s) for s in step.inputs],
                          "outputs": [str(s) for s in step.outputs],
                          "frame": [str(s) for s in step.frame]})
        else:
            used |= step[1].free_symbols
            steps.append({"kind": "assign", "name": str(step[0]),
                          "code": printer.doprint(step[1])})
    for out in () if kernel.quadrature else kernel.outputs:
        for _, e, _ in out.entries():
            used |= e.free_symbols
    return {
        "name": kernel.name,
        "twin_of": kernel.twin_of,
        "projection_method": kernel.projection_method,
        "qualified_name": kernel.qualified_name,
        "doc": kernel.doc,
        "inputs": [_arg_view(a, used) for a in kernel.inputs],
        "params": [_arg_view(a, used) for a in kernel.params],
        "param_symbols": ", ".join(str(a.symbols[0]) for a in kernel.params),
        "param_names": tuple(a.name for a in kernel.params),
        "intermediates": steps,
        "outputs": [
            {
                "name": out.name,
                "shape": out.shape,
                "size": out.size,
                "symmetric": out.symmetric,
                "entries": [] if kernel.quadrature else
                [(k, printer.doprint(e), list(m)) for k, e, m in out.entries()],
            }
            for out in kernel.outputs
        ],
        "op_count": kernel.op_count,
        "assemble": kernel_view_assemble(kernel),
        "points": kernel.points,
        "quadrature": kernel.quadrature,
        "positive": kernel.positive,
        "module": kernel.module,
        # nodes of the element (x_e's rows): the fused assembly's gather
        "nodes": kernel.inputs[0].shape[0] if kernel_view_assemble(kernel) else 0,
    }


def kernel_view_assemble(kernel: KernelSpec) -> bool:
    """Whether the C back end adds a fused ``*_assemble`` entry point for this kernel: element
    kernels of deformed node positions ``x_e`` (``(nodes, 3)``) with one output (materials and
    tet geometry, of every element)."""
    return (bool(kernel.inputs)
            and kernel.name != "dgradient_dparams"  # per element, not scattered
            and kernel.inputs[0].name == "x_e"
            and len(kernel.inputs[0].shape) == 2 and kernel.inputs[0].shape[1] == 3
            and len(kernel.outputs) == 1)


def material_view(module: ModuleSpec, printer) -> dict | None:
    """A material's metadata for the NumPy module: Python literals (``repr``) and the
    ``E, nu`` mapping printed as code."""
    info = module.info
    if info is None:
        return None
    from codegen.derive import small_strain_mapping

    mapping = small_strain_mapping(module.name)
    literals = {key: repr(info[key]) for key in (
        "allows_inversion", "exact_small_strain", "rotation_invariant", "element_inputs",
        "shape_params", "positive", "description", "inversion", "psi_text", "psi_latex", "doc",
        "mapping_text")}
    return {**literals,
            "mapping_code": [(p, printer.doprint(e)) for p, e in mapping.exprs.items()],
            "mapping_jacobian_code": [
                (p, printer.doprint(sp.diff(e, mapping.E)), printer.doprint(sp.diff(e, mapping.nu)))
                for p, e in mapping.exprs.items()]}


def _printer(backend: str):
    spec = BACKENDS[backend]
    return spec.printer({"strict": False}) if backend == "numpy" else spec.printer()


def render_module(module: ModuleSpec, backend: str, part: str = "all") -> str:
    """Source text of one module for one back end. C only: ``part`` ``"pointwise"`` is a
    material's kernels at one ``F`` (:attr:`~codegen.spec.ModuleSpec.pointwise`, its
    ``<name>_pointwise.c``), ``"rest"`` the module's file that includes them."""
    if module.role == "quadrature":
        return render_quadrature(module, backend)
    spec = BACKENDS[backend]
    printer = _printer(backend)
    kernels = list(module.kernels)
    if part != "all":
        n = len(module.pointwise)
        if tuple(k.name for k in kernels[:n]) != module.pointwise:
            raise ValueError(f"{module.name}: the pointwise kernels {module.pointwise} must "
                             "lead its kernels")
        kernels = kernels[:n] if part == "pointwise" else kernels[n:]
    steps = module.material_steps
    return _environment().get_template(spec.template).render(
        module=module,
        part=part,
        pointwise_file=f"{module.name}_pointwise.c" if part == "rest" else "",
        refuses=any(k.positive for k in module.kernels),
        material=material_view(module, printer),
        kernels=[kernel_view(k, printer) for k in kernels],
        point_kernels=[kernel_view(k, printer) for k in steps.point_kernels] if steps else [],
        quadrature_module=f"{module.unit}_quadrature",
        template_name=f"templates/{spec.template}",
        sympy_version=sp.__version__,
    )


def render_quadrature(module: ModuleSpec, backend: str) -> str:
    """``<element>_quadrature.c`` or ``.py``: an element's quadrature loops, shared by every
    material, from ``templates/<backend>/quadrature<suffix>.jinja``."""
    constants = {name: int(value) for name, value in module.constants}
    spec = BACKENDS[backend]
    template = f"{backend}/quadrature{spec.suffix}.jinja"
    printer = _printer(backend)
    return _environment().get_template(template).render(
        module=module,
        nodes=constants["N_NODES"],
        points=constants["N_POINTS"],
        kernels={k.name: kernel_view(k, printer) for k in module.kernels},
        template_name=f"templates/{template}",
        sympy_version=sp.__version__,
    )


def _method_views(modules: list[ModuleSpec]) -> list[dict]:
    return [{"name": m.name, "kernels": [
        {"qualified_name": k.qualified_name, "doc": k.doc, "assemble": kernel_view_assemble(k)}
        for k in m.kernels]} for m in modules if m.role == "kernels"]


def units(modules: list[ModuleSpec]) -> list[str]:
    """The extra C translation units (``_ckernels_<unit>.c``) of ``modules``, in order."""
    return list(dict.fromkeys(m.unit for m in modules if m.unit and m.role == "kernels"))


def render_extension(modules: list[ModuleSpec]) -> str:
    """The C extension's entry file: includes every module of its own unit and lists its
    kernels; adds the method tables of the other units."""
    template = _environment().get_template("c/extension.c.jinja")
    return template.render(
        modules=_method_views([m for m in modules if not m.unit]),
        units=units(modules),
        template_name="templates/c/extension.c.jinja",
        sympy_version=sp.__version__,
    )


def render_unit(unit: str, modules: list[ModuleSpec]) -> str:
    """The translation unit ``_ckernels_<unit>.c``: its modules and its method table."""
    mine = [m for m in modules if m.unit == unit and m.role == "kernels"]
    nodes = {k.inputs[0].shape[0] for m in mine for k in m.kernels if kernel_view_assemble(k)}
    if len(nodes) != 1:
        raise ValueError(f"unit {unit}: the fused kernels must share one node count, got {nodes}")
    return _environment().get_template("c/unit.c.jinja").render(
        unit=unit, nodes=nodes.pop(), modules=_method_views(mine),
        refuses=any(k.positive for m in mine for k in m.kernels),
        pointwise=[m.material_steps.name for m in mine if m.material_steps],
        quadrature=next((m.name for m in modules if m.unit == unit and m.role == "quadrature"),
                        ""),
        template_name="templates/c/unit.c.jinja", sympy_version=sp.__version__)


def module_files(module: ModuleSpec) -> dict[str, str]:
    """Relative path under ``generated/`` -> file text, for one module on every back end."""
    if module.role == "quadrature":
        return {f"{name}/{module.name}{backend.suffix}": render_quadrature(module, name)
                for name, backend in BACKENDS.items()}
    files = {}
    for name, backend in BACKENDS.items():
        if name == "c" and module.pointwise:
            files[f"c/{module.name}_pointwise.c"] = render_module(module, name, "pointwise")
            files[f"c/{module.name}.c"] = render_module(module, name, "rest")
        else:
            files[f"{name}/{module.name}{backend.suffix}"] = render_module(module, name)
    return files


def render_all(modules: list[ModuleSpec]) -> dict[str, str]:
    """Relative path under ``generated/`` -> file text, for every module and back end."""
    files = {}
    for module in modules:
        files.update(module_files(module))
    kernel_modules = [m for m in modules if m.role == "kernels"]
    files["numpy/__init__.py"] = _environment().get_template("numpy/package.py.jinja").render(
        modules=tuple(m.name for m in kernel_modules),
        materials=tuple(m.name for m in kernel_modules if m.name in MATERIALS),
        elements={unit: tuple(m.name for m in kernel_modules if m.unit == unit)
                  for unit in units(modules) if unit in QUADRATURE_ELEMENTS},
        template_name="templates/numpy/package.py.jinja",
        sympy_version=sp.__version__,
    )
    files["numpy/_support.py"] = _environment().get_template("numpy/support.py.jinja").render(
        template_name="templates/numpy/support.py.jinja", sympy_version=sp.__version__)
    files["c/_ckernels.c"] = render_extension(modules)
    for unit in units(modules):
        files[f"c/_ckernels_{unit}.c"] = render_unit(unit, modules)
    return files
