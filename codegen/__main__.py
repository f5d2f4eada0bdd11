"""Stage 4: write, check or show the generated files.

    python -m codegen                 # regenerate generated/ and docs/materials.md
    python -m codegen --check         # fail with a diff when either is stale
    python -m codegen show neo_hookean.hessian [--backend c]
    python -m codegen show p2_stvk.gradient     # a quadratic tet's quadrature kernel
    python -m codegen show p2_quadrature.hessian   # one point's terms, shared by the materials
    python -m codegen show stable_neo_hookean   # a material's formulas
    python -m codegen docs            # write docs/materials.md only

Modules are derived in parallel (``FEM3D_CODEGEN_JOBS`` processes, default: the CPUs this
process may use); the output does not depend on it.
"""

from __future__ import annotations

import argparse
import difflib
import os
import sys
from pathlib import Path

from codegen.render import ROOT, render_all

GENERATED = ROOT / "generated"
DOCS = ROOT / "docs" / "materials.md"
UPDATE_COMMAND = "make codegen"


def _ensure_fixed_hash_seed(argv: list[str]) -> None:
    """SymPy's CSE output can depend on set ordering: pin the hash seed for byte-stable output."""
    if os.environ.get("PYTHONHASHSEED") != "0":
        env = dict(os.environ, PYTHONHASHSEED="0")
        os.execve(sys.executable, [sys.executable, "-m", "codegen", *argv], env)


def _jobs() -> int:
    value = os.environ.get("FEM3D_CODEGEN_JOBS")
    return max(1, int(value)) if value else len(os.sched_getaffinity(0))


def modules(names: list[str] | None = None) -> list:
    """The :class:`~codegen.spec.ModuleSpec` of every module (or of ``names``), in
    :func:`codegen.derive.module_names` order, derived in parallel."""
    from concurrent.futures import ProcessPoolExecutor

    from codegen.derive import build_module, module_names

    names = module_names() if names is None else names
    jobs = min(_jobs(), len(names))
    if jobs <= 1:
        return [build_module(n) for n in names]
    with ProcessPoolExecutor(jobs) as pool:
        return list(pool.map(build_module, names))


def generate(names: list[str] | None = None) -> tuple[dict[str, str], list]:
    """Relative path under ``generated/`` -> text for every generated file, and the specs."""
    specs = modules(names)
    return render_all(specs), specs


def write(files: dict[str, str], target: Path) -> None:
    """Write ``files`` under ``target``, removing stale generated files no longer produced."""
    for rel, text in files.items():
        path = target / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        if not path.exists() or path.read_text() != text:
            path.write_text(text)
    for path in sorted(target.rglob("*")):
        if path.is_file() and path.suffix in (".py", ".c") and \
                path.relative_to(target).as_posix() not in files:
            path.unlink()


def check(files: dict[str, str], target: Path) -> int:
    """Print a unified diff of stale files; 0 when ``target`` is up to date."""
    stale = 0
    committed = {p.relative_to(target).as_posix() for p in target.rglob("*")
                 if p.is_file() and p.suffix in (".py", ".c")}
    for rel in sorted(set(files) | committed):
        old = (target / rel).read_text() if rel in committed else ""
        new = files.get(rel, "")
        if old != new:
            stale += 1
            sys.stdout.writelines(difflib.unified_diff(
                old.splitlines(keepends=True), new.splitlines(keepends=True),
                fromfile=f"generated/{rel} (committed)", tofile=f"generated/{rel} (regenerated)"))
    if stale:
        print(f"\n{stale} generated file(s) are stale; run `{UPDATE_COMMAND}` and commit.")
        return 1
    print(f"generated/ is up to date ({len(files)} files).")
    return 0


def show_material(name: str) -> int:
    """Print a material's formulas: psi, parameters, the E/nu mapping, inversion, source."""
    from codegen.derive import material_info

    info = material_info(name)
    print(f"{name}: {info['description']}")
    print(f"\npsi = {info['psi_text']}")
    print(f"\nparameters: {', '.join(info['param_names'])}")
    for n, shape in info["element_inputs"]:
        print(f"per-element input: {n} {shape}")
    exact = "exact small-strain linear elasticity" if info["exact_small_strain"] else \
        "NOT exact small-strain linear elasticity"
    print(f"\nfrom E, nu ({exact}):")
    for p, text in info["mapping_text"].items():
        free = "  (free: does not change the small-strain response)" \
            if p in info["shape_params"] else ""
        print(f"  {p} = {text}{free}")
    print(f"\nallows inversion: {info['allows_inversion']}; J <= 0: {info['inversion']}")
    print(f"\n{info['doc']}")
    return 0


def show(kernel: str, backend: str) -> int:
    """Print the source of one kernel (``module.kernel``) for one back end, or a material's
    formulas (a bare material name)."""
    from codegen.derive import all_modules, material_module, spring_module, tet_module
    from codegen.materials import MATERIALS
    from codegen.render import BACKENDS, module_files

    if kernel in MATERIALS:
        return show_material(kernel)
    module_name, _, kernel_name = kernel.partition(".")
    builders = {"tet": tet_module, "spring": spring_module}
    from codegen import element_kernels

    if module_name in MATERIALS:
        modules = [material_module(module_name)]
    elif module_name in element_kernels.module_names():
        modules = [element_kernels.build_module(module_name)]
    elif module_name in builders:
        modules = [builders[module_name]()]
    else:
        modules = all_modules()
    for module in modules:
        spec = next((k for k in module.kernels if k.name == kernel_name), None)
        if module.name != module_name or spec is None:
            continue
        # the module's files (a material's C kernels at one F are a file of their own)
        files = module_files(module)
        text = "".join(files.get(f"{backend}/{module.name}{part}{BACKENDS[backend].suffix}", "")
                       for part in ("_pointwise", ""))
        if backend == "numpy":
            # an element's quadrature pieces are its functions of one point, _<kind>_point
            name = f"_{kernel_name}_point" if module.role == "quadrature" else kernel_name
            start = text.index(f"\ndef {name}(")
            end = text.find("\ndef ", start + 1)
        elif module.role == "quadrature":
            start = text.index(f"\n// {spec.doc}\n")
            end = text.find("\n\n", text.index("\n}\n", start))
        else:
            start = text.index(f"\n// {spec.doc}\n")
            end = text.find("\n// ", text.index(f"py_{spec.qualified_name}(", start))
        print(text[start : len(text) if end < 0 else end].strip())
        return 0
    names = [f"{m.name}.{k.name}" for m in modules for k in m.kernels]
    print(f"unknown kernel {kernel!r}; known: {', '.join(names)}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="python -m codegen", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true",
                        help="diff against generated/, write nothing")
    parser.add_argument("--out", type=Path, default=GENERATED, help="target folder")
    sub = parser.add_subparsers(dest="command")
    show_parser = sub.add_parser("show", help="print one kernel's generated source")
    show_parser.add_argument("kernel", help="module.kernel (e.g. neo_hookean.hessian), or a "
                             "material name for its formulas")
    show_parser.add_argument("--backend", choices=("numpy", "c"), default="numpy")
    sub.add_parser("docs", help=f"write {DOCS.relative_to(ROOT)} only")
    parser.add_argument("--only", nargs="+", metavar="MODULE",
                        help="derive only these modules (with --out: a partial tree, for tests)")
    args = parser.parse_args(argv)
    if args.command == "show":
        return show(args.kernel, args.backend)
    from codegen.derive import module_names

    unknown = sorted(set(args.only or ()) - set(module_names()))
    if unknown:
        print(f"unknown module(s) {', '.join(unknown)}; known: {', '.join(module_names())}",
              file=sys.stderr)
        return 2
    _ensure_fixed_hash_seed(argv)
    from codegen.docs import render_docs

    files, specs = generate(args.only)
    docs = render_docs(specs) if args.only is None else None
    if args.command == "docs":
        DOCS.write_text(docs)
        print(f"wrote {DOCS}")
        return 0
    if args.check:
        status = check(files, args.out) if args.only is None else check_subset(files, args.out)
        if docs is not None and args.out == GENERATED:
            if not DOCS.exists() or DOCS.read_text() != docs:
                print(f"{DOCS.relative_to(ROOT)} is stale; run `{UPDATE_COMMAND}` and commit.")
                status = 1
        return status
    if args.only is None:
        write(files, args.out)
        if args.out == GENERATED:
            DOCS.write_text(docs)
    else:
        for rel, text in files.items():
            (args.out / rel).parent.mkdir(parents=True, exist_ok=True)
            (args.out / rel).write_text(text)
    print(f"wrote {len(files)} files to {args.out}")
    return 0


def check_subset(files: dict[str, str], target: Path) -> int:
    """Like :func:`check` for the modules' own files only (``--only``)."""
    stale = [rel for rel, text in files.items() if rel.split("/")[-1] not in
             ("__init__.py", "_ckernels.c") and
             (not (target / rel).exists() or (target / rel).read_text() != text)]
    for rel in stale:
        print(f"generated/{rel} is stale")
    print(f"{len(files) - len(stale)} of {len(files)} checked files are up to date.")
    return 1 if stale else 0


if __name__ == "__main__":
    raise SystemExit(main())
