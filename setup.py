"""Build the generated C kernels as the optional extension ``fem3d._ckernels``.

The extension is optional: without a C compiler fem3d falls back to the NumPy kernels.
OpenMP and -march=native are used when the compiler accepts them
(set FEM3D_PORTABLE=1 to build without -march=native).
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

SOURCE = "generated/c/_ckernels.c"


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


class BuildExt(build_ext):
    """Add -O3, OpenMP and -march=native where the compiler supports them."""

    def build_extensions(self) -> None:
        compiler = list(getattr(self.compiler, "compiler_so", None) or ["cc"])[:1]
        compile_args = ["-O3", "-std=c99", "-fno-math-errno", "-ffp-contract=fast"]
        link_args: list[str] = []
        portable = os.environ.get("FEM3D_PORTABLE") == "1"
        if not portable and _compiler_accepts(compiler, ["-march=native"]):
            compile_args.append("-march=native")
        if os.environ.get("FEM3D_NO_OPENMP") != "1" and _compiler_accepts(compiler, ["-fopenmp"]):
            compile_args.append("-fopenmp")
            link_args.append("-fopenmp")
        for ext in self.extensions:
            ext.extra_compile_args = compile_args
            ext.extra_link_args = link_args
        super().build_extensions()


setup(
    ext_modules=[
        Extension(
            "fem3d._ckernels",
            [SOURCE],
            depends=sorted(str(p) for p in Path("generated/c").glob("*.c")),
            optional=True,
        )
    ],
    cmdclass={"build_ext": BuildExt},
)
