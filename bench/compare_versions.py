"""Two checkouts of fem3d measured alternately in one run: classic scenes, the contact drop,
the 1e5-tet AMG step and the element kernels; medians and new/old ratios.

Each round runs every case in the old checkout, then in the new one (the order flips every
round), each command in its own process from its checkout with ``PYTHONPATH`` pointing at it,
so both versions see the same machine load. Figures are the ones each checkout's own
benchmark prints (``bench.scenes``, ``bench.contact``, ``bench.newton_step``,
``bench.kernel_throughput``). Used for the restructuring of issue 19 (docs/benchmarks.md)::

    git worktree add /tmp/fem3d-old 6cbcdd9 && cp fem3d/_ckernels*.so /tmp/fem3d-old/fem3d/
    python -m bench.compare_versions --old /tmp/fem3d-old --new . --rounds 3

Every command runs with ``OMP_NUM_THREADS=1`` unless ``--threads`` lists counts (e.g.
``--threads 1,2``: each case on each count, the figures labelled ``OMP=n``; the thread policy
of issue 23, docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

#: case -> (command, parser of its output -> {figure name: value}, unit, lower is better)
_SCENE_ROW = re.compile(r"^\| (\w+) \(\d+ tets\) \| (\w+) \| (\w+) \(.*?\) \| ([\d.]+) \|", re.M)
_CONTACT_ROW = re.compile(r"^(bunny_drop(?: \[reuse\])?)\s+\d+ tets\s+\d+ steps\s+([\d.]+) steps/s",
                          re.M)
_KERNEL_ROW = re.compile(r"^neo_hookean\s+(energy|gradient|hessian)\s+c\s+\d+\s+([\d.]+)", re.M)


def _scenes(out: str, _: Path) -> dict[str, float]:
    return {f"{s} {i} {m} (ms/step)": float(v) for s, i, m, v in _SCENE_ROW.findall(out)}


def _contact(out: str, _: Path) -> dict[str, float]:
    return {f"{name} (ms/step)": 1e3 / float(v) for name, v in _CONTACT_ROW.findall(out)}


def _kernels(out: str, _: Path) -> dict[str, float]:
    return {f"1e5 tets neo_hookean {k}, C (ms)": 1e3 * float(v)
            for k, v in _KERNEL_ROW.findall(out)}


def _amg(_: str, jsonl: Path) -> dict[str, float]:
    rec = json.loads(jsonl.read_text().splitlines()[-1])
    parts = {f"1e5-tet box, AMG step: {k} (ms)": 1e3 * v
             for k, v in rec.get("parts_per_step", {}).items()}
    return {"1e5-tet box, one AMG step (ms)": 1e3 * rec["seconds_per_step"],
            "1e5-tet box, one AMG step, CPU (ms)": 1e3 * rec["cpu_seconds_per_step"], **parts}


CASES = {
    "scenes": (["-m", "bench.scenes", "--steps", "100", "--repeats", "3"], _scenes),
    "contact": (["-m", "bench.contact", "--steps", "60", "--cases", "bunny_drop", "--refine",
                 "0", "--no-peer", "--newton-solver", "direct", "reuse"], _contact),
    "amg": (["-m", "bench.newton_step", "--mesh", "box", "--tets", "1e5", "--steps", "1",
             "--swing", "4", "--modes", "amg", "--repeats", "1", "--jsonl", "{jsonl}"], _amg),
    "kernels": (["-m", "bench.kernel_throughput", "--elements", "100000", "--repeats", "5",
                 "--material", "neo_hookean", "--backend", "c", "--kernel", "energy",
                 "gradient", "hessian"], _kernels),
}


def run(checkout: Path, case: str, threads: str = "1") -> dict[str, float]:
    """One case in one checkout (``OMP_NUM_THREADS=threads``): its figures."""
    args, parse = CASES[case]
    with tempfile.TemporaryDirectory() as tmp:
        jsonl = Path(tmp) / "rec.jsonl"
        cmd = [sys.executable] + [a.replace("{jsonl}", str(jsonl)) for a in args]
        env = dict(os.environ, PYTHONPATH=str(checkout), OMP_NUM_THREADS=threads,
                   OPENBLAS_NUM_THREADS="1")
        proc = subprocess.run(cmd, cwd=checkout, env=env, capture_output=True, text=True,
                              timeout=1800)
        if proc.returncode != 0:
            raise RuntimeError(f"{case} in {checkout} failed:\n{proc.stderr[-2000:]}")
        return parse(proc.stdout + proc.stderr, jsonl)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--old", type=Path, required=True, help="checkout of the old version")
    p.add_argument("--new", type=Path, default=Path("."), help="checkout of the new version")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    p.add_argument("--threads", default="1",
                   help="OMP_NUM_THREADS of the commands; several separated by commas")
    a = p.parse_args(argv)
    counts = [t.strip() for t in a.threads.split(",") if t.strip()]
    figures: dict[str, dict[str, list[float]]] = {"old": {}, "new": {}}
    for r in range(a.rounds):
        order = [("old", a.old), ("new", a.new)]
        if r % 2:
            order.reverse()
        for case in a.cases:
            for threads in counts:
                tag = f"OMP={threads}, " if len(counts) > 1 else ""
                for label, checkout in order:
                    for name, value in run(checkout.resolve(), case, threads).items():
                        figures[label].setdefault(tag + name, []).append(value)
        print(f"round {r + 1} of {a.rounds} done", file=sys.stderr, flush=True)
    threads = "one thread" if counts == ["1"] else f"OMP_NUM_THREADS {', '.join(counts)}"
    print(f"| {a.rounds} rounds, median, {threads} | old | new | new / old |")
    print("| --- | ---: | ---: | ---: |")
    for name, old in figures["old"].items():
        new = figures["new"].get(name)
        if not new:
            continue
        mo, mn = statistics.median(old), statistics.median(new)
        print(f"| {name} | {mo:.3g} | {mn:.3g} | {mn / mo:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
