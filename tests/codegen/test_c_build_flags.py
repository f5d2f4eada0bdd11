"""The C extension's build flags (issue 39): every build targets the architecture's portable
baseline, ``FEM3D_NATIVE=1`` opts in to ``-march=native``; and the check that a built
extension stays within the baseline (``scripts/check_portable_extension.sh``, run by
``scripts/check_wheel.sh``) finds AVX-512 and AVX where they are."""

from __future__ import annotations

import importlib.util
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("fem3d_setup", ROOT / "setup.py")
assert _spec is not None and _spec.loader is not None
setup_py = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(setup_py)  # __name__ is not "__main__": setup() does not run


def _flags(env: dict[str, str], machine: str = "x86_64",
           refuse: tuple[str, ...] = ()) -> tuple[list[str], list[str]]:
    return setup_py.choose_flags(env, machine, lambda flags: not set(flags) & set(refuse))


def test_default_build_is_the_portable_baseline() -> None:
    compile_args, link_args = _flags({})
    assert "-march=x86-64" in compile_args and "-march=native" not in compile_args
    assert {"-O3", "-fno-math-errno", "-fopenmp"} <= set(compile_args)
    assert link_args == ["-fopenmp"]
    assert _flags({"FEM3D_PORTABLE": "1"}) == (compile_args, link_args)  # the old switch
    assert _flags({"FEM3D_NATIVE": "0"}) == (compile_args, link_args)
    arm, _ = _flags({}, machine="aarch64")
    assert "-march=armv8-a" in arm and not any(a.startswith("-march=x86") for a in arm)
    # an architecture without a known baseline: the compiler's default target, never native
    assert not any(a.startswith("-march") for a in _flags({}, machine="ppc64le")[0])


def test_native_is_opt_in() -> None:
    compile_args, _ = _flags({"FEM3D_NATIVE": "1"})
    assert "-march=native" in compile_args and "-march=x86-64" not in compile_args
    # a compiler refusing -march=native (or OpenMP) builds without it
    refused, link_args = _flags({"FEM3D_NATIVE": "1"}, refuse=("-march=native", "-fopenmp"))
    assert not any(a.startswith("-march") for a in refused) and "-fopenmp" not in refused
    assert link_args == []
    assert "-fopenmp" not in _flags({"FEM3D_NO_OPENMP": "1"})[0]


@pytest.mark.parametrize("env", [{"FEM3D_NATIVE": "1", "FEM3D_PORTABLE": "1"},
                                 {"FEM3D_NATIVE": "yes"}, {"FEM3D_PORTABLE": "true"}])
def test_contradictory_or_unknown_switches_are_refused(env: dict[str, str]) -> None:
    with pytest.raises(ValueError, match="FEM3D_"):
        _flags(env)


def test_setup_py_names_a_bad_switch_in_one_line(tmp_path: Path) -> None:
    env = {**os.environ, "FEM3D_NATIVE": "yes"}
    # fails in build_extensions, before compiling anything (and never in place)
    result = subprocess.run(
        [sys.executable, "setup.py", "-q", "build_ext", "--build-lib", str(tmp_path / "lib"),
         "--build-temp", str(tmp_path / "tmp")],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 2, result.stderr
    lines = [line for line in result.stderr.splitlines() if "FEM3D_NATIVE" in line]
    assert lines == ["setup.py: FEM3D_NATIVE='yes': expected 1 (on) or 0 (off)"], result.stderr
    assert "Traceback" not in result.stderr


CHECK = ROOT / "scripts" / "check_portable_extension.sh"
SOURCE = """
#include <immintrin.h>
#if defined(CLONES)  /* the run-time dispatch of templates/c/extension.c.jinja */
__attribute__((target_clones("default", "arch=x86-64-v3")))
void axpy(double a, const double *restrict x, double *restrict y, int n)
{
    for (int i = 0; i < n; ++i) y[i] += a * x[i];
}
#endif
double sum(const double *x, int n)
{
#if defined(WIDTH512)
    __m512d s = _mm512_setzero_pd();
    for (int i = 0; i + 8 <= n; i += 8) s = _mm512_add_pd(s, _mm512_loadu_pd(x + i));
    return _mm512_reduce_add_pd(s);
#elif defined(WIDTH256)
    __m256d s = _mm256_setzero_pd();
    for (int i = 0; i + 4 <= n; i += 4) s = _mm256_add_pd(s, _mm256_loadu_pd(x + i));
    double t[4];
    _mm256_storeu_pd(t, s);
    return t[0] + t[1] + t[2] + t[3];
#else
    double s = 0.0;
    for (int i = 0; i < n; ++i) s += x[i];
    return s;
#endif
}
"""


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64")
                    or not (shutil.which("cc") and shutil.which("objdump")),
                    reason="needs an x86-64 C compiler and objdump")
@pytest.mark.parametrize(("flags", "found"), [
    ([], None), (["-mavx512f", "-DWIDTH512"], "zmm (AVX-512)"),
    (["-mavx", "-DWIDTH256"], "ymm (AVX)"), (["-DCLONES", "-O3"], None)])
def test_the_portability_check_finds_wide_registers(tmp_path: Path, flags: list[str],
                                                    found: str | None) -> None:
    (tmp_path / "k.c").write_text(SOURCE)
    so = tmp_path / "k.so"
    subprocess.run(["cc", "-O2", "-shared", "-fPIC", *flags, str(tmp_path / "k.c"), "-o", str(so)],
                   check=True)
    result = subprocess.run(["bash", str(CHECK), str(so)], capture_output=True, text=True,
                            check=False)
    if found is None:
        assert result.returncode == 0, result.stderr
        clones = 1 if "-DCLONES" in flags else 0
        assert f"no instruction beyond the x86-64 baseline ({clones} dispatched" in result.stdout
        if clones:  # the clone is vectorized with ymm: allowed only there
            dump = subprocess.run(["objdump", "-d", str(so)], capture_output=True, text=True,
                                  check=True).stdout
            assert "%ymm" in dump
    else:
        assert result.returncode == 1
        assert result.stderr.count("\n") == 1 and f"the first {found} in sum:" in result.stderr
