"""Build the generated C kernels as the optional extension ``fem3d._ckernels``.

The extension is optional: without a C compiler fem3d falls back to the NumPy kernels.
Every build (``pip install .``, ``pip wheel .``, ``pip install -e .``) targets the
architecture's portable baseline (x86-64 without AVX, armv8-a on aarch64), so a wheel runs
on any CPU of its architecture. ``FEM3D_NATIVE=1`` opts in to ``-march=native`` for a
developer's in-place build; ``FEM3D_PORTABLE=1`` is still accepted and is the default.
OpenMP is used when the compiler accepts it (``FEM3D_NO_OPENMP=1`` turns it off).
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import tempfile
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

SOURCE = "generated/c/_ckernels.c"
# The translation units of the extension: the units codegen deals the kernels to
# (_ckernels_p1a.c, _ckernels_p1b.c: P1's materials, codegen.derive.P1_UNITS; _ckernels_p2.c:
# the quadratic tets'; see codegen.render.render_unit), then the entry file (with the support,
# the tet and two materials: the smallest, so last). The threads of _parallel_compile take
# them in this order; the build's wall time is about the sum of their compile times over the
# threads (12-16 s of CPU each on a shared 2-core machine).
SOURCES = [*sorted(str(p) for p in Path("generated/c").glob("_ckernels_*.c")), SOURCE]
# -ffp-contract=fast: fused multiply-adds where the target has them (native x86-64, and the
# armv8-a baseline itself); the x86-64 baseline has no FMA, so it changes nothing there
# -g0: Python's own CFLAGS carry -g; the debug info of the generated straight-line kernels is
# a fifth of the compile time (the P1 unit: 49 s of CPU with it, 39 s without) and two thirds
# of the extension's size, and changes no instruction
BASE_FLAGS = ["-O3", "-std=c99", "-fno-math-errno", "-ffp-contract=fast", "-g0"]
# Baseline per machine (platform.machine()); a compiler refusing it builds with its default.
BASELINE = {"x86_64": "-march=x86-64", "amd64": "-march=x86-64", "aarch64": "-march=armv8-a",
            "arm64": "-march=armv8-a"}


def _compiler_accepts(compiler: list[str], flags: list[str]) -> bool:
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "probe.c"
        src.write_text("#include <omp.h>\nint main(void) { return omp_get_max_threads() < 0; }\n"
                       if "-fopenmp" in flags else "int main(void) { return 0; }\n")
        try:
            result = subprocess.run([*compiler, *flags, str(src), "-o", str(Path(tmp) / "a.out")],
                                    capture_output=True, check=False)
        except OSError:
            return False
        return result.returncode == 0


def choose_flags(env: Mapping[str, str], machine: str,
                 accepts: Callable[[list[str]], bool]) -> tuple[list[str], list[str]]:
    """Choose the extension's compile and link flags.

    Parameters
    ----------
    env
        The environment: ``FEM3D_NATIVE=1`` selects ``-march=native``; ``FEM3D_NO_OPENMP=1``
        leaves OpenMP out. ``FEM3D_NATIVE=1`` together with ``FEM3D_PORTABLE=1`` is an error.
    machine
        ``platform.machine()`` of the build, which picks the baseline ``-march``.
    accepts
        Whether the compiler accepts a list of flags (a trial compile).

    Returns
    -------
    tuple of list of str
        The compile flags and the link flags.

    Raises
    ------
    ValueError
        When FEM3D_NATIVE or FEM3D_PORTABLE is set to something other than 0 or 1, or both are 1.
    """
    for key in ("FEM3D_NATIVE", "FEM3D_PORTABLE"):
        if env.get(key, "0") not in ("0", "1", ""):
            raise ValueError(f"{key}={env[key]!r}: expected 1 (on) or 0 (off)")
    native = env.get("FEM3D_NATIVE") == "1"
    if native and env.get("FEM3D_PORTABLE") == "1":
        raise ValueError("FEM3D_NATIVE=1 and FEM3D_PORTABLE=1 ask for opposite builds: set one")
    compile_args = list(BASE_FLAGS)
    link_args: list[str] = []
    arch = ["-march=native"] if native else []
    if not native and machine.lower() in BASELINE:
        arch = [BASELINE[machine.lower()]]
    if arch and accepts(arch):
        compile_args += arch
    if env.get("FEM3D_NO_OPENMP") != "1" and accepts(["-fopenmp"]):
        compile_args.append("-fopenmp")
        link_args.append("-fopenmp")
    return compile_args, link_args


def _parallel_compile(compiler, jobs: int) -> None:
    """Make ``compiler.compile`` compile its translation units on ``jobs`` threads (the
    extension's units at once, each thread taking the next unit of :data:`SOURCES`)."""
    def compile_all(sources, output_dir=None, macros=None, include_dirs=None, debug=0,
                    extra_preargs=None, extra_postargs=None, depends=None):
        macros, objects, extra_postargs, pp_opts, build = compiler._setup_compile(
            output_dir, macros, include_dirs, sources, depends, extra_postargs)
        cc_args = compiler._get_cc_args(pp_opts, debug, extra_preargs)

        def one(obj):
            if obj in build:
                src, ext = build[obj]
                compiler._compile(obj, src, ext, cc_args, extra_postargs, pp_opts)

        with ThreadPoolExecutor(jobs) as pool:
            list(pool.map(one, objects))
        return objects

    compiler.compile = compile_all


class BuildExt(build_ext):
    """Add -O3, OpenMP and the baseline (or, opted in, native) -march; compile the
    translation units in parallel (``FEM3D_BUILD_JOBS``, default: the CPUs, at most one per
    unit)."""

    def build_extensions(self) -> None:
        jobs = int(os.environ.get("FEM3D_BUILD_JOBS") or len(os.sched_getaffinity(0)))
        if min(jobs, len(SOURCES)) > 1 and hasattr(self.compiler, "_setup_compile"):
            _parallel_compile(self.compiler, min(jobs, len(SOURCES)))
        compiler = list(getattr(self.compiler, "compiler_so", None) or ["cc"])[:1]
        try:
            compile_args, link_args = choose_flags(
                os.environ, platform.machine(), lambda flags: _compiler_accepts(compiler, flags))
        except ValueError as err:
            print(f"setup.py: {err}", file=sys.stderr)
            sys.exit(2)
        print("fem3d._ckernels flags: " + " ".join(compile_args), file=sys.stderr)
        for ext in self.extensions:
            ext.extra_compile_args = compile_args
            ext.extra_link_args = link_args
        super().build_extensions()


if __name__ == "__main__":
    setup(
        ext_modules=[
            Extension(
                "fem3d._ckernels",
                SOURCES,
                depends=sorted(str(p) for p in Path("generated/c").glob("*.c")),
                optional=True,
            )
        ],
        cmdclass={"build_ext": BuildExt},
    )
