"""``fem3d run`` wall time with frame output, old and new checkouts side by side.

    python -m bench.output --old /tmp/fem3d-old-23 [--repeats 3] [--long 1000,10000]

Each row runs ``python -m fem3d run arma --steps 100 --no-preview --quiet`` (per format) as a
subprocess with ``PYTHONPATH`` at the new checkout (this one) and at ``--old``, alternately,
``--repeats`` times, and reports the best process wall time and the run loop's own wall time
(the "N steps in X s" line: steps and frames, after start-up). ``--long`` then runs the USD
armadillo (``--checkpoint-every 50``) for each number of steps under ``/usr/bin/time -v``:
wall time and peak RSS (``--long-old`` the same for the old checkout).
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

NEW = Path(__file__).resolve().parent.parent


def _run(root: Path, args: list[str], timed: bool = False) -> tuple[float, float, float]:
    """(process wall s, loop wall s, peak RSS MiB) of ``fem3d run`` with ``root`` first on
    the path."""
    env = dict(os.environ, PYTHONPATH=str(root), OMP_NUM_THREADS="1")
    with tempfile.TemporaryDirectory() as d:
        cmd = [sys.executable, "-m", "fem3d", "run", *args, "--out", f"{d}/o", "--quiet"]
        if timed:
            cmd = ["/usr/bin/time", "-v", *cmd]
        start = time.perf_counter()
        # cwd: a neutral folder (python -m puts the working folder before PYTHONPATH)
        r = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False, cwd=d)
        wall = time.perf_counter() - start
    if r.returncode:
        raise RuntimeError(f"{cmd}: {r.stderr[-2000:]}")
    m = re.search(r"(\d+) steps in ([\d.]+) s", r.stderr)
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", r.stderr)
    return wall, float(m.group(2)) if m else float("nan"), int(rss.group(1)) / 1024 if rss else 0


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--old", type=Path, required=True, help="the old checkout")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--formats", default="vtu,obj,usd")
    parser.add_argument("--long", default="", help="steps of the long USD runs, e.g. 1000,10000")
    parser.add_argument("--long-old", default="", help="the same for the old checkout")
    args = parser.parse_args(argv)
    print("| `fem3d run arma --steps 100 --no-preview` | old wall s | old loop s | new wall s "
          "| new loop s |\n| --- | ---: | ---: | ---: | ---: |", flush=True)
    for fmt in args.formats.split(","):
        cmd = ["arma", "--steps", "100", "--no-preview", "--format", fmt]
        best = {"old": (1e9, 1e9), "new": (1e9, 1e9)}
        for _ in range(args.repeats):
            for name, root in (("old", args.old), ("new", NEW)):
                wall, loop, _ = _run(root, cmd)
                best[name] = (min(best[name][0], wall), min(best[name][1], loop))
        print(f"| `--format {fmt}` | {best['old'][0]:.2f} | {best['old'][1]:.2f} "
              f"| {best['new'][0]:.2f} | {best['new'][1]:.2f} |", flush=True)
    runs = [("new", NEW, s) for s in args.long.split(",") if s]
    runs += [("old", args.old, s) for s in args.long_old.split(",") if s]
    if runs:
        print("\n| USD armadillo, `--checkpoint-every 50` | steps | wall s | loop s "
              "| peak RSS MiB |"
              "\n| --- | ---: | ---: | ---: | ---: |", flush=True)
    for name, root, steps in runs:
        wall, loop, rss = _run(root, ["arma", "--steps", steps, "--no-preview", "--format", "usd",
                                      "--checkpoint-every", "50"], timed=True)
        print(f"| {name} | {steps} | {wall:.1f} | {loop:.1f} | {rss:.0f} |", flush=True)


if __name__ == "__main__":
    main()
