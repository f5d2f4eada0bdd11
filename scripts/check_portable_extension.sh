#!/usr/bin/env bash
# The C extension runs on any CPU of its architecture: its machine code uses no register of an
# instruction set beyond the baseline setup.py builds for (issue 39). x86-64: no zmm
# (AVX-512) anywhere, and no ymm (AVX/AVX2) outside run-time dispatched clones (functions
# named *.arch_x86_64_v3*, chosen only on CPUs that have AVX2 and FMA); aarch64: no SVE
# z registers. Fails with one line naming the first offending function.
# Usage: bash scripts/check_portable_extension.sh FILE.so|FILE.whl   (a wheel: its fem3d/_ckernels*.so)
set -euo pipefail
TARGET="${1:?usage: check_portable_extension.sh FILE.so|FILE.whl}"
if ! command -v objdump >/dev/null; then
    echo "check_portable_extension: objdump not found (install binutils)" >&2; exit 2
fi
TMP="$(mktemp -d)"
trap 'rm -rf "$TMP"' EXIT
SO="$TARGET"
if [[ "$TARGET" == *.whl ]]; then
    python3 - "$TARGET" "$TMP" <<'PY'
import sys, zipfile
names = [n for n in zipfile.ZipFile(sys.argv[1]).namelist()
         if n.startswith("fem3d/_ckernels") and n.endswith((".so", ".pyd"))]
for n in names:
    zipfile.ZipFile(sys.argv[1]).extract(n, sys.argv[2])
PY
    SO="$(find "$TMP" -name '_ckernels*' -type f | head -n 1)"
    if [[ -z "$SO" ]]; then
        echo "check_portable_extension: $(basename "$TARGET") holds no fem3d/_ckernels extension" >&2
        exit 1
    fi
fi
[[ -f "$SO" ]] || { echo "check_portable_extension: no such file $SO" >&2; exit 2; }
ARCH="$(objdump -f "$SO" | sed -n 's/^architecture: \([^,]*\).*/\1/p')"
ARCH="${ARCH#i386:}"
# per function: the instructions that name a register beyond the baseline
objdump -d --no-show-raw-insn "$SO" | awk -v arch="$ARCH" '
    /^[0-9a-f]+ <.*>:$/ { fn = $2; gsub(/[<>:]/, "", fn); next }
    arch ~ /x86-64/ && /%zmm[0-9]/ { print fn "\tzmm (AVX-512)\t" $0; next }
    arch ~ /x86-64/ && /%ymm[0-9]/ && fn !~ /\.arch_x86_64_v3/ { print fn "\tymm (AVX)\t" $0; next }
    arch ~ /aarch64/ && /[ ,{]z[0-9]+\.[bhsdq]/ { print fn "\tz register (SVE)\t" $0 }
' > "$TMP/found"
if [[ -s "$TMP/found" ]]; then
    # AVX-512 is the one that kills on most CPUs: name it first where there is any
    { grep -m 1 zmm "$TMP/found" || head -n 1 "$TMP/found"; } > "$TMP/first"
    IFS=$'\t' read -r FN WHAT INSN < "$TMP/first"
    echo "check_portable_extension: $(basename "$SO") is not portable: $(wc -l < "$TMP/found")" \
         "instructions beyond the $ARCH baseline, the first $WHAT in $FN:$(echo "$INSN" | tr -s ' \t' ' ')" >&2
    exit 1
fi
CLONES="$(objdump -d --no-show-raw-insn "$SO" | grep -c '^[0-9a-f]* <.*\.arch_x86_64_v3.*>:$' || true)"
echo "$(basename "$SO"): no instruction beyond the $ARCH baseline ($CLONES dispatched v3 clones)"
