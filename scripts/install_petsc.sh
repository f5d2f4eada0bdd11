#!/usr/bin/env bash
# PETSc + MPI (Debian's petsc-dev, which brings Open MPI and MUMPS), then mpi4py and petsc4py
# built against that PETSc with the matching version: fem3d's `[mpi]` extra, what
# `linear_solver = "petsc"` and `mpiexec -n N fem3d run` need (docs/parallel.md).
#
#   bash scripts/install_petsc.sh [--if-possible] [python]
#
# Strict (default, .ci/run): any failure is an error. --if-possible: installs the system
# library only when it can (root, or password-less sudo), and otherwise prints one line saying
# fem3d runs in one process without PETSc, and exits 0.
# Time measured on the project's 2-core machine: apt-get install petsc-dev 1-2 min (download
# included), pip's build of petsc4py 3.18.5 about 6 min (one C file, 2 cores shared), mpi4py
# a wheel (seconds). See docs/parallel.md.
set -uo pipefail
IF_POSSIBLE=0
if [ "${1:-}" = "--if-possible" ]; then IF_POSSIBLE=1; shift; fi
PYTHON="${1:-${PYTHON:-python3}}"

fallback() {  # $1: why PETSc is missing
    if [ "$IF_POSSIBLE" -eq 0 ]; then
        echo "install_petsc.sh: $1" >&2
        exit 1
    fi
    echo "PETSc not installed ($1): fem3d runs in one process without it" \
         "(run 'sudo bash scripts/install_petsc.sh' for linear_solver = \"petsc\" and mpiexec runs)"
    exit 0
}

check() {
    "$PYTHON" - <<'PY'
import mpi4py
import pymetis  # noqa: F401 (the deterministic partition of mpiexec runs)
from petsc4py import PETSc
print(f"PETSc {'.'.join(map(str, PETSc.Sys.getVersion()))} available (petsc4py "
      f"{__import__('petsc4py').__version__}, mpi4py {mpi4py.__version__})")
PY
}

# METIS (pymetis, a wheel: seconds): the partition of mpiexec runs, the same in every run
"$PYTHON" -c "import pymetis" 2>/dev/null || "$PYTHON" -m pip install -q "pymetis>=2023.1" \
    || fallback "pip install pymetis failed"
if check 2>/dev/null; then exit 0; fi

petsc_dir() {  # the newest Debian PETSc (real scalars), or empty
    ls -d /usr/lib/petscdir/petsc3.*/x86_64-linux-gnu-real /usr/lib/petscdir/petsc3.*/*-real \
        2>/dev/null | sort -V | tail -1
}

if [ -z "${PETSC_DIR:-}" ] && [ -z "$(petsc_dir)" ]; then
    SUDO=""
    if [ "$(id -u)" -ne 0 ]; then
        if command -v sudo >/dev/null && { [ "$IF_POSSIBLE" -eq 0 ] || sudo -n true 2>/dev/null; }; then
            SUDO="sudo"
        else
            fallback "PETSc needs root to install (apt-get install petsc-dev)"
        fi
    fi
    command -v apt-get >/dev/null || fallback "no apt-get to install petsc-dev"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get update -q >/dev/null || fallback "apt-get update failed"
    # petsc-dev: PETSc with Open MPI, MUMPS, hypre, PT-Scotch (the partitioner)
    $SUDO apt-get install -y -q --no-install-recommends petsc-dev openmpi-bin >/dev/null \
        || fallback "apt-get install petsc-dev failed"
fi
export PETSC_DIR="${PETSC_DIR:-$(petsc_dir)}"
[ -n "$PETSC_DIR" ] && [ -e "$PETSC_DIR/include/petscversion.h" ] \
    || fallback "no PETSc found under /usr/lib/petscdir (set PETSC_DIR)"
version() {
    sed -n "s/^#define PETSC_VERSION_$1 *\([0-9]*\).*/\1/p" "$PETSC_DIR/include/petscversion.h"
}
MAJOR="$(version MAJOR)"; MINOR="$(version MINOR)"
# petsc4py X.Y.* builds against PETSc X.Y.* only. Its wheel is built in a throw-away venv:
# petsc4py 3.18's build hooks break with setuptools >= 70 (a list where they expect a string)
# and need numpy's headers at build time (pip's isolated build has none).
BUILD="$(mktemp -d)"
trap 'rm -rf "$BUILD"' EXIT
NUMPY="$("$PYTHON" -c 'import numpy; print(numpy.__version__)')" || fallback "numpy is missing"
"$PYTHON" -m venv "$BUILD/venv" || fallback "python -m venv failed"
"$BUILD/venv/bin/python" -m pip install -q "setuptools<70" wheel "numpy==$NUMPY" \
    || fallback "pip install setuptools<70 wheel numpy (the build venv) failed"
echo "install_petsc.sh: building petsc4py $MAJOR.$MINOR.* against $PETSC_DIR (a few minutes)"
PETSC_DIR="$PETSC_DIR" "$BUILD/venv/bin/python" -m pip wheel -q --no-build-isolation --no-deps \
    -w "$BUILD/wheels" "petsc4py>=$MAJOR.$MINOR,<$MAJOR.$((MINOR + 1))" \
    || fallback "building petsc4py $MAJOR.$MINOR.* against $PETSC_DIR failed"
"$PYTHON" -m pip install -q "mpi4py>=3.1" "pymetis>=2023.1" "$BUILD"/wheels/petsc4py-*.whl \
    || fallback "pip install mpi4py pymetis petsc4py failed"
check || fallback "petsc4py does not import"
