#!/usr/bin/env bash
# SuiteSparse headers + OpenBLAS, then scikit-sparse (CHOLMOD), fem3d's default sparse solver.
# Without it fem3d falls back to PARDISO (pypardiso) or SciPy's SuperLU (slower on large
# meshes; see docs/benchmarks.md).
#
#   bash scripts/install_cholmod.sh [--if-possible] [python]
#
# Strict (default, .ci/run): any failure is an error. --if-possible (make install, make test,
# make run): installs the system library only when it can (root, or password-less sudo), and
# otherwise prints one line saying which solver fem3d falls back to, and exits 0.
set -uo pipefail
IF_POSSIBLE=0
if [ "${1:-}" = "--if-possible" ]; then IF_POSSIBLE=1; shift; fi
PYTHON="${1:-${PYTHON:-python3}}"

fallback() {  # $1: why CHOLMOD is missing
    if [ "$IF_POSSIBLE" -eq 0 ]; then
        echo "install_cholmod.sh: $1" >&2
        exit 1
    fi
    local used
    used="$("$PYTHON" -c 'from fem3d.solve.linear import resolve_linear_solver; print(resolve_linear_solver(direct=True))' \
        2>/dev/null || echo superlu)"
    echo "CHOLMOD not installed ($1): fem3d falls back to '$used'" \
         "(run 'sudo bash scripts/install_cholmod.sh' to get the fast default)"
    exit 0
}

if "$PYTHON" -c "import sksparse.cholmod" 2>/dev/null; then
    echo "CHOLMOD available (scikit-sparse)"
    exit 0
fi
if ! [ -e /usr/include/suitesparse/cholmod.h ]; then
    SUDO=""
    if [ "$(id -u)" -ne 0 ]; then
        if command -v sudo >/dev/null && { [ "$IF_POSSIBLE" -eq 0 ] || sudo -n true 2>/dev/null; }; then
            SUDO="sudo"
        else
            fallback "the SuiteSparse headers need root to install (apt-get install libsuitesparse-dev)"
        fi
    fi
    command -v apt-get >/dev/null || fallback "no apt-get to install libsuitesparse-dev"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get update -q >/dev/null || fallback "apt-get update failed"
    # OpenBLAS, not the reference BLAS: CHOLMOD's factorization is ~5-17x slower without it.
    $SUDO apt-get install -y -q --no-install-recommends libsuitesparse-dev libopenblas-dev \
        >/dev/null || fallback "apt-get install libsuitesparse-dev libopenblas-dev failed"
fi
"$PYTHON" -m pip install -q "scikit-sparse==0.4.16" || fallback "pip install scikit-sparse failed"
"$PYTHON" -c "import sksparse.cholmod; print('CHOLMOD available (scikit-sparse)')" 2>/dev/null \
    || fallback "scikit-sparse does not import"
