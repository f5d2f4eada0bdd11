#!/usr/bin/env bash
# The installed wheel, as Python users install tools: `pip wheel .`, install it into a fresh
# venv, run `fem3d run bunny` from another folder (no checkout on the path). Uses no index for
# fem3d's dependencies (--no-deps into a venv with --system-site-packages); the build itself
# runs without isolation when setuptools can build wheels here, else pip's isolated build.
# The wheel's C extension must be portable (scripts/check_portable_extension.sh: no AVX-512,
# no AVX outside dispatched clones); FEM3D_NATIVE=1 in the environment shows the check failing.
# Usage: bash scripts/check_wheel.sh [PYTHON]   (~20-60 s)
set -euo pipefail
PYTHON="${1:-${PYTHON:-python3}}"
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
TMP="$(mktemp -d)"
trap 'rm -rf "$TMP"' EXIT
ISOLATION=()
if "$PYTHON" -c "import wheel" 2>/dev/null; then ISOLATION=(--no-build-isolation); fi
# from a copy of the checkout's files (tracked and untracked, not ignored): a stale build/
# of an earlier install must not fill in what the package data leaves out; a tracked file
# deleted in the working tree (not yet committed) is left out, as the commit will
mkdir "$TMP/src"
(cd "$ROOT" && git ls-files -co --exclude-standard -z \
    | while IFS= read -r -d '' f; do if [[ -e "$f" ]]; then printf '%s\0' "$f"; fi; done \
    | xargs -0 tar -c) | tar -x -C "$TMP/src"
"$PYTHON" -m pip wheel "$TMP/src" -w "$TMP/wheel" --no-deps -q "${ISOLATION[@]}"
WHEEL="$(ls "$TMP"/wheel/fem3d-*.whl)"
echo "wheel: $(basename "$WHEEL") ($(du -k "$WHEEL" | cut -f1) kB)"
bash "$ROOT/scripts/check_portable_extension.sh" "$WHEEL"
"$PYTHON" -m venv --system-site-packages "$TMP/venv"
"$TMP/venv/bin/python" -m pip install -q --no-deps "$WHEEL"
mkdir "$TMP/elsewhere"
cd "$TMP/elsewhere"
env -u PYTHONPATH -u FEM3D_DATA -u FEM3D_SCENES "$TMP/venv/bin/python" - <<'PY'
import fem3d, sys
from pathlib import Path
where = Path(fem3d.__file__).resolve()
assert "venv" in where.parts, f"fem3d imported from {where}, not the installed wheel"
print("fem3d from", where.parent)
PY
env -u PYTHONPATH -u FEM3D_DATA -u FEM3D_SCENES "$TMP/venv/bin/fem3d" run bunny --steps 3 --out X
test "$(wc -l < X/energy.csv)" -eq 5
test -s X/frames.pvd
echo "the installed wheel runs the bunny from $PWD: ok"
