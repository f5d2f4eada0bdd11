#!/usr/bin/env bash
# Every figure of docs/benchmarks.md and the README's performance section, in one run
# (~35 min on the 2-core machine): a fresh bench/results/benchmarks.jsonl, then the report.
# Logs of the scripts that print rather than record go to bench/results/*.txt.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-python3}"
for arg in "$@"; do case "$arg" in PYTHON=*) PYTHON="${arg#PYTHON=}";; esac; done
R=bench/results
TIMED=()  # the 1e6 step's peak RSS and wall time as the OS sees them, where GNU time exists
[ -x /usr/bin/time ] && TIMED=(/usr/bin/time -v)
: > "$R/newton_step.jsonl"
"$PYTHON" -m bench --fresh --sizes 1e3,1e4,1e5 --repeats 5 --threads 1 --stat min \
    --groups energy,gradient,hessian_elements,hessian_csr,step
"$PYTHON" -m bench --sizes 1e3,1e4,1e5 --repeats 5 --stat min --groups analyze,factor,solve
"$PYTHON" -m bench --sizes 1e6 --repeats 3 --threads 1 --timeout 900 --stat min \
    --groups energy,gradient,hessian_elements,hessian_csr
"$PYTHON" -m bench --sizes 1e6 --repeats 3 --timeout 900 --stat min \
    --cases linsolve-cholmod,fem3d-amg --groups analyze,factor,solve
"$PYTHON" -m bench.assembly_threads --sizes 1e5,1e6 --repeats 5 | tee "$R/assembly_threads.txt"
"$PYTHON" -m bench.scenes | tee "$R/scenes.txt"
{
  "$PYTHON" -m bench.newton_step --mesh arma --refine 0,1 --steps 80 --modes direct,reuse \
      --jsonl "$R/newton_step.jsonl"
  "$PYTHON" -m bench.newton_step --mesh arma --refine 2 --steps 40 --modes direct,reuse \
      --repeats 1 --jsonl "$R/newton_step.jsonl"
  "$PYTHON" -m bench.newton_step --mesh box --tets 1e5 --steps 1 --swing 4 \
      --modes direct,reuse,amg --repeats 2 --jsonl "$R/newton_step.jsonl"
  "${TIMED[@]}" "$PYTHON" -m bench.newton_step --mesh box --tets 1e6 --steps 1 --swing 4 \
      --modes amg --repeats 1 --jsonl "$R/newton_step.jsonl"
} 2>&1 | tee "$R/newton_step.txt"
"$PYTHON" -m bench --report-only --stat min
