"""``fem3d fit FIT.toml --out DIR``: the command line of fits (see :mod:`fem3d.app.fit`).

Exit status: 0 the optimiser converged; 1 it did not (iteration limit, line search, a
simulation that could not go on: the files are still written); 2 bad input (one line naming
the file and key path; nothing written).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from fem3d.app.fit.run import OUTPUT_NAMES, fit, write_outputs
from fem3d.app.fit.spec import load_fit_file
from fem3d.errors import InputError

__all__ = ["add_fit_subcommand"]


def add_fit_subcommand(subparsers) -> argparse.ArgumentParser:
    """Register ``fem3d fit``."""
    p = subparsers.add_parser(
        "fit",
        help="fit material / initial-state parameters to a run's frames (adjoint gradients)",
        description="Fit the parameters a fit file names (bodies[0].material.E, ...) so that "
        "the base scene's motion matches a target run's frames, with scipy's L-BFGS-B and "
        "the exact adjoint gradient (fem3d.diff). Writes DIR/fit.json, DIR/fit.png and "
        "DIR/fitted.toml. See docs/differentiable.md.",
    )
    p.add_argument("fit", help="fit file (.toml)")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="output folder (default out/<fit name>)")
    p.add_argument("--max-iterations", type=int, default=None, metavar="N",
                   help="override [optimizer] max_iterations")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks"
    )
    p.set_defaults(func=_fit_command)
    return p


def _same(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def check_overwrite(out: Path, inputs: dict[str, str]) -> None:
    """Refuse an output folder whose files would replace one of the fit's ``inputs``."""
    for role, path in inputs.items():
        for name in OUTPUT_NAMES:
            if _same(Path(path), out / name):
                raise InputError(f"the fit would overwrite its own {role} {path}: it writes "
                                 f"{', '.join(OUTPUT_NAMES)} into {out}; choose another --out",
                                 path=path)


def _fit_command(args: argparse.Namespace) -> int:
    if args.max_iterations is not None and args.max_iterations < 1:
        raise InputError(f"--max-iterations must be >= 1, got {args.max_iterations}")
    spec = load_fit_file(args.fit)
    if args.max_iterations is not None:
        spec = spec.model_copy(update={"optimizer": spec.optimizer.model_copy(
            update={"max_iterations": args.max_iterations})})
    out = Path(args.out) if args.out else Path("out") / spec.name
    inputs = {"fit file": args.fit, "target": spec.target}
    if Path(spec.scene).suffix:
        inputs["scene file"] = spec.scene
    check_overwrite(out, inputs)
    progress = None if args.quiet else (lambda line: print(line, file=sys.stderr, flush=True))
    result = fit(spec, where=str(args.fit), progress=progress)
    write_outputs(result, spec, out, fit_file=str(Path(args.fit).resolve()))
    state = "converged" if result.success else "did not converge"
    print(f"fem3d fit {spec.name}: {state} after {result.iterations} iterations "
          f"({result.evaluations} gradient evaluations): {result.message}; "
          f"{out / 'fit.json'}", file=sys.stderr)
    return 0 if result.success else 1
