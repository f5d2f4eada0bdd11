"""Sweep throughput: 16 armadillo cases with 1 and 2 Dask workers, against plain `fem3d run`.

    python -m bench.sweep [--cases 16] [--steps 20] [--every 5] [--workers 1,2] [--plain 4]
                          [--scene arma] [--markdown FILE] [--keep DIR]

Writes a sweep file (the ``--scene`` with ``simulation.steps = --steps``, a frame every
``--every`` steps (``output.every``), Young's modulus
swept over ``--cases`` values from 2e5 to 2e6) and times, as subprocesses, what a user runs:

* ``fem3d sweep FILE --workers W --out DIR`` for each ``W`` (fresh ``DIR``: every case runs):
  wall time, cases per second, speed-up and scaling efficiency against 1 worker;
* ``fem3d run SCENE --set ... --out DIR`` for the first ``--plain`` cases one by one (the
  shell loop a sweep replaces): mean wall time per case; half of them before the sweeps and
  half after, so that a load that drifts during the benchmark hits both sides.

Per-case overhead of the engine: ``T_sweep(1 worker) / cases - T_plain``: what a case costs
in a 1-worker sweep beyond a plain run (negative: the sweep is cheaper, because a worker
imports fem3d once for all its cases); also in CPU seconds (user + system of the process and
its workers, from ``getrusage``), which a machine shared with other work disturbs much less
than wall time. Also printed: the part of ``T_sweep(1)`` outside the
cases themselves (Python start, planning, cluster start-up, scheduling, results), per case.
The 1-minute load average is printed before and after: on a shared machine the figures are
only as good as that load.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _fem3d(args: list[str]) -> tuple[float, float]:
    """Wall and CPU seconds (the process and its children: the workers) of ``fem3d ARGS``."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    cpu, start = _cpu(), time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "fem3d", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"fem3d {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr}")
    return seconds, _cpu() - cpu


def _load() -> str:
    try:
        return f"{os.getloadavg()[0]:.2f}"
    except OSError:
        return "?"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=16)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--every", type=int, default=5, help="a frame every N steps")
    parser.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    parser.add_argument("--plain", type=int, default=4,
                        help="cases also run one by one with `fem3d run` (default 4)")
    parser.add_argument("--scene", default="arma")
    parser.add_argument("--markdown", type=Path, help="also write the table here")
    parser.add_argument("--keep", type=Path, help="keep the outputs in this folder")
    args = parser.parse_args(argv)
    workers = [int(w) for w in args.workers.split(",")]
    root = Path(args.keep or tempfile.mkdtemp(prefix="fem3d-bench-sweep-"))
    root.mkdir(parents=True, exist_ok=True)
    values = [round(2e5 * 10 ** (i / max(args.cases - 1, 1)), 3) for i in range(args.cases)]
    spec = root / "bench_sweep.toml"
    spec.write_text(
        f'name = "bench_sweep"\nscene = "{args.scene}"\n[set]\n"simulation.steps" = '
        f'{args.steps}\n"output.every" = {args.every}\n'
        f'[grid]\n"bodies[0].material.E" = {json.dumps(values)}\n',
        encoding="utf-8",
    )
    print(f"load average before: {_load()} ({os.cpu_count()} cores)", flush=True)
    lines = ["| run | wall s | cases / s | speed-up | efficiency | CPU s per case |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    print(*lines, sep="\n", flush=True)
    plain: list[float] = []
    plain_cpu: list[float] = []

    def run_plain(indices: range) -> None:
        for i in indices:
            out = root / f"plain_{i}"
            shutil.rmtree(out, ignore_errors=True)
            wall, cpu = _fem3d(["run", args.scene, "--set", f"bodies[0].material.E={values[i]!r}",
                                "--set", f"output.every={args.every}", "--steps",
                                str(args.steps), "--no-preview", "--quiet", "--out", str(out)])
            plain.append(wall)
            plain_cpu.append(cpu)

    n_plain = min(args.plain, args.cases)
    run_plain(range(n_plain // 2))
    sweep_s: dict[int, float] = {}
    sweep_cpu: dict[int, float] = {}
    inside: dict[int, float] = {}
    for w in workers:
        out = root / f"workers_{w}"
        shutil.rmtree(out, ignore_errors=True)
        sweep_s[w], sweep_cpu[w] = _fem3d(["sweep", str(spec), "--workers", str(w),
                                           "--out", str(out), "--quiet"])
        summaries = [json.loads(p.read_text()) for p in out.glob("cases/*/summary.json")]
        assert len(summaries) == args.cases and all(s["status"] == "ok" for s in summaries)
        inside[w] = sum(s["case_seconds"] for s in summaries)
        ratio = ""
        if 1 in sweep_s:
            speedup = sweep_s[1] / sweep_s[w]
            ratio = f"{speedup:.2f}x | {100 * speedup / w:.0f} %"
        lines.append(f"| sweep, {w} worker{'s' if w > 1 else ''} | {sweep_s[w]:.1f} | "
                     f"{args.cases / sweep_s[w]:.2f} | {ratio or ' | '} | "
                     f"{sweep_cpu[w] / args.cases:.2f} |")
        print(lines[-1], flush=True)
    run_plain(range(n_plain // 2, n_plain))
    t_plain = sum(plain) / max(len(plain), 1)
    c_plain = sum(plain_cpu) / max(len(plain), 1)
    if plain:
        lines.append(f"| fem3d run, one by one ({len(plain)} cases) | {t_plain:.2f} per case "
                     f"| {1 / t_plain:.2f} | | | {c_plain:.2f} |")
        print(lines[-1], flush=True)
    notes = []
    if 1 in sweep_s:
        per_case = sweep_s[1] / args.cases
        if plain:
            notes.append(f"per-case overhead of the engine (1 worker), wall: {per_case:.2f} - "
                         f"{t_plain:.2f} = {per_case - t_plain:+.2f} s per case; CPU: "
                         f"{sweep_cpu[1] / args.cases:.2f} - {c_plain:.2f} = "
                         f"{sweep_cpu[1] / args.cases - c_plain:+.2f} s per case")
        notes.append(f"outside the cases (Python start, planning, cluster start, scheduling, "
                     f"results), 1 worker: {(sweep_s[1] - inside[1]) / args.cases:.2f} s per "
                     f"case ({sweep_s[1] - inside[1]:.1f} s in all)")
    notes.append(f"load average after: {_load()}; {args.cases} cases x {args.steps} steps of "
                 f"{args.scene}, a frame every {args.every}; `python -m bench.sweep --cases "
                 f"{args.cases} --steps {args.steps} --every {args.every} --workers "
                 f"{args.workers} --plain {args.plain}`")
    print(*notes, sep="\n")
    if args.markdown:
        args.markdown.write_text("\n".join(lines) + "\n\n" + "\n".join(notes) + "\n")
    if args.keep is None:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
