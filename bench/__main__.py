"""``python -m bench``: run the benchmark cases and write docs/benchmarks.{md,png}.

Examples
--------
python -m bench --quick                          # 1e3 and 1e4 tets, a few minutes
python -m bench --sizes 1e3,1e4,1e5 --repeats 5  # the documented run
python -m bench --sizes 1e6 --groups factor,solve,analyze   # add rows (merged into the JSONL)
python -m bench --report-only                    # re-render from bench/results/benchmarks.jsonl
python -m bench --list
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

from bench import GROUPS, load_cases
from bench.report import (
    machine_info,
    merge,
    read_jsonl,
    render_markdown,
    render_plot,
    versions,
    write_jsonl,
)
from bench.worker import RESULT_PREFIX


def _parse_sizes(text: str) -> list[float]:
    try:
        sizes = [float(s) for s in text.split(",") if s.strip()]
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"--sizes: {err}") from err
    if not sizes or any(s < 6 for s in sizes):
        raise argparse.ArgumentTypeError("--sizes: comma-separated tet counts >= 6")
    return sizes


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=_parse_sizes, default=None,
                   help="approximate tet counts, comma-separated (default 1e3,1e4,1e5)")
    p.add_argument("--repeats", type=int, default=None, help="timed calls per case (default 5)")
    p.add_argument("--budget", type=float, default=None,
                   help="seconds of timed calls per case before cutting repeats (default 30)")
    p.add_argument("--timeout", type=float, default=900.0,
                   help="seconds before a worker is killed (recorded as timeout)")
    p.add_argument("--threads", type=int, default=None,
                   help="OMP/OpenBLAS/MKL threads of the workers (default: the libraries' own)")
    p.add_argument("--quick", action="store_true",
                   help="sizes 1e3,1e4, 3 repeats, 5 s budget (unless given)")
    p.add_argument("--out", type=Path, default=Path("docs"),
                   help="folder for benchmarks.md and benchmarks.png (default docs/)")
    p.add_argument("--jsonl", type=Path, default=Path("bench/results/benchmarks.jsonl"),
                   help="the records (merged across runs; default bench/results/benchmarks.jsonl)")
    p.add_argument("--cases", default="",
                   help="only cases whose name contains one of these comma-separated strings")
    p.add_argument("--groups", default="", help=f"only these groups ({', '.join(GROUPS)})")
    p.add_argument("--stat", choices=("median", "min"), default="median",
                   help="statistic of the timed calls shown in the report (default median; "
                        "min is the robust choice on a machine shared with other work)")
    p.add_argument("--fresh", action="store_true",
                   help="discard earlier records in OUT/benchmarks.jsonl (default: merge)")
    p.add_argument("--report-only", action="store_true", help="only re-render the report")
    p.add_argument("--list", action="store_true", help="list the cases and exit")
    return p


def _select(cases: dict, args: argparse.Namespace) -> list:
    names = [c for c in args.cases.split(",") if c]
    groups = [g for g in args.groups.split(",") if g]
    bad = [g for g in groups if g not in GROUPS]
    if bad:
        raise SystemExit(f"python -m bench: unknown group(s) {bad}; choose from {list(GROUPS)}")
    out = []
    for case in cases.values():
        if names and not any(n in case.name for n in names):
            continue
        if groups and case.group not in groups:
            continue
        out.append(case)
    return sorted(out, key=lambda c: (list(GROUPS).index(c.group), c.name))


def _run_worker(case, size: float, args: argparse.Namespace) -> dict:
    cmd = [sys.executable, "-m", "bench.worker", case.name, repr(size), str(args.repeats),
           str(args.budget)]
    base = {"case": case.name, "group": case.group, "library": case.library, "size": size}
    env = dict(os.environ)
    if args.threads:
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            env[var] = str(args.threads)
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout,
                              cwd=Path(__file__).resolve().parent.parent, env=env)
    except subprocess.TimeoutExpired:
        return {**base, "status": "timeout", "reason": f"killed after {args.timeout:.0f} s"}
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith(RESULT_PREFIX):
            return json.loads(line[len(RESULT_PREFIX):])
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    return {**base, "status": "error",
            "reason": f"worker exited {proc.returncode}: {' | '.join(tail)}"}


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.quick:
        args.sizes = args.sizes or [1e3, 1e4]
        args.repeats = args.repeats or 3
        args.budget = args.budget or 5.0
    args.sizes = args.sizes or [1e3, 1e4, 1e5]
    args.repeats = args.repeats or 5
    args.budget = args.budget or 30.0
    cases = load_cases()
    if args.list:
        for c in sorted(cases.values(), key=lambda c: (list(GROUPS).index(c.group), c.name)):
            miss = c.missing()
            extra = f"  [missing: {', '.join(miss)}]" if miss else ""
            print(f"{c.name:45s} {c.group:17s} {c.library}{extra}")
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    jsonl = args.jsonl
    jsonl.parent.mkdir(parents=True, exist_ok=True)
    records = [] if args.fresh else read_jsonl(jsonl)
    command = "python -m bench " + " ".join(shlex.quote(a) for a in
                                            (sys.argv[1:] if argv is None else argv))
    if not args.report_only:
        selected = _select(cases, args)
        date = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
        commit = versions().get("git")
        new = []
        for size in args.sizes:
            for case in selected:
                if size > case.max_tets:
                    print(f"[skip] {case.name} @ {size:g}: above its size limit "
                          f"{case.max_tets:g}", flush=True)
                    continue
                miss = case.missing()
                if miss:
                    rec = {"case": case.name, "group": case.group, "library": case.library,
                           "size": size, "status": "skip",
                           "reason": f"not installed: {', '.join(miss)}"}
                else:
                    t0 = time.perf_counter()
                    rec = _run_worker(case, size, args)
                    rec["wall_s"] = time.perf_counter() - t0
                rec.update(command=command, date=date, threads=args.threads, git=commit)
                new.append(rec)
                if rec["status"] == "ok":
                    print(f"[ok]   {case.name} @ {size:g} ({rec['n_tets']} tets): median "
                          f"{rec['median_s']:.4g} s over {rec['repeats']}, peak "
                          f"{rec['peak_rss_mb']:.0f} MiB", flush=True)
                else:
                    print(f"[{rec['status']}] {case.name} @ {size:g}: {rec.get('reason')}",
                          flush=True)
                write_jsonl(jsonl, merge(records, new))  # keep what is done if interrupted
        records = merge(records, new)
    try:
        from fem3d.solve.linear import resolve_linear_solver

        solver = resolve_linear_solver(direct=True)
    except Exception:  # noqa: BLE001 - the report still renders
        solver = None
    meta = {"machine": machine_info(), "versions": versions(), "default_solver": solver}
    md = args.out / "benchmarks.md"
    md.write_text(render_markdown(records, meta, args.stat))
    render_plot(records, args.out / "benchmarks.png", args.stat)
    print(f"wrote {md}, {args.out / 'benchmarks.png'}, {jsonl}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
