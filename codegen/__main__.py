"""Stage 4: write, check or show the generated files.

    python -m codegen                 # regenerate generated/
    python -m codegen --check         # fail with a diff when generated/ is stale
    python -m codegen show neo_hookean.hessian [--backend c]
"""

from __future__ import annotations

import argparse
import difflib
import os
import sys
from pathlib import Path

from codegen.render import ROOT, render_all

GENERATED = ROOT / "generated"
UPDATE_COMMAND = "make codegen"


def _ensure_fixed_hash_seed(argv: list[str]) -> None:
    """SymPy's CSE output can depend on set ordering: pin the hash seed for byte-stable output."""
    if os.environ.get("PYTHONHASHSEED") != "0":
        env = dict(os.environ, PYTHONHASHSEED="0")
        os.execve(sys.executable, [sys.executable, "-m", "codegen", *argv], env)


def generate() -> dict[str, str]:
    """Relative path under ``generated/`` -> text, for every generated file."""
    from codegen.derive import all_modules

    return render_all(all_modules())


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


def show(kernel: str, backend: str) -> int:
    """Print the source of one kernel (``module.kernel``) for one back end."""
    from codegen.derive import all_modules, material_module, spring_module, tet_module
    from codegen.materials import MATERIALS
    from codegen.render import BACKENDS

    module_name, _, kernel_name = kernel.partition(".")
    builders = {"tet": tet_module, "spring": spring_module}
    if module_name in MATERIALS:
        modules = [material_module(module_name)]
    elif module_name in builders:
        modules = [builders[module_name]()]
    else:
        modules = all_modules()
    for module in modules:
        spec = next((k for k in module.kernels if k.name == kernel_name), None)
        if module.name != module_name or spec is None:
            continue
        text = render_all([module])[f"{backend}/{module.name}{BACKENDS[backend].suffix}"]
        if backend == "numpy":
            start = text.index(f"\ndef {kernel_name}(")
            end = text.find("\ndef ", start + 1)
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
    show_parser.add_argument("kernel", help="module.kernel, e.g. neo_hookean.hessian")
    show_parser.add_argument("--backend", choices=("numpy", "c"), default="numpy")
    args = parser.parse_args(argv)
    if args.command == "show":
        return show(args.kernel, args.backend)
    _ensure_fixed_hash_seed(argv)
    files = generate()
    if args.check:
        return check(files, args.out)
    write(files, args.out)
    print(f"wrote {len(files)} files to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
