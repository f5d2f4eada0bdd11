#!/usr/bin/env bash
# SuiteSparse headers + OpenBLAS, then scikit-sparse (CHOLMOD), fem3d's default sparse solver.
# Without it fem3d falls back to SciPy's SuperLU (slower on large meshes; see docs/benchmarks.md).
#
#   bash scripts/install_cholmod.sh [python]
set -euo pipefail
PYTHON="${1:-${PYTHON:-python3}}"
if ! [ -e /usr/include/suitesparse/cholmod.h ]; then
    SUDO=""
    [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get update -q
    # OpenBLAS, not the reference BLAS: CHOLMOD's factorization is ~5-17x slower without it.
    $SUDO apt-get install -y -q --no-install-recommends libsuitesparse-dev libopenblas-dev
fi
"$PYTHON" -m pip install -q "scikit-sparse==0.4.16"
"$PYTHON" -c "import sksparse.cholmod; print('CHOLMOD available (scikit-sparse)')"
