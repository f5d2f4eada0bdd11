"""Contact scenes, this tree against an older checkout: speed and how far the trajectories part.

    python -m bench.tools.contact_oldnew --old /path/to/old/checkout [--scenes contact_stack ...]
                                   [--steps N] [--repeat 1] [--new-set KEY=VALUE ...]

Each scene runs in a fresh process per code version (``OMP_NUM_THREADS=1``, alternating old
and new so both see the same load): steps per second by wall clock and by CPU time of the
stepping loop alone. Then the positions after every step are compared: new against old, and
the old code against itself with gravity changed by one unit in the last place
(``-9.81 -> -9.810000000000002``), the size of a round-off difference. A scene whose bodies
tumble and slide (``contact_stack``) amplifies any last-bit difference to centimetres within
a hundred steps; a change that moves only round-off then parts from the old trajectory no
faster than the old code parts from itself.

``--new-set KEY=VALUE`` (repeatable) runs the new tree with scene overrides, e.g.
``--new-set simulation.newton.line_search=parabolic``: an opt-in algorithm against the old
default, side by side.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

_CHILD = r"""
import json, os, sys, time
import numpy as np
from fem3d.scene import apply_overrides, load_scene
from fem3d.simulation import Simulation
name, steps, out, ov = sys.argv[1], int(sys.argv[2]), sys.argv[3], json.loads(sys.argv[4])
sim = Simulation(apply_overrides(load_scene(name), ov), scripted=True)
Q, iters, facts, cg, halvings, substepped = [], 0, 0, 0, 0, 0
a0 = getattr(sim.system, "analyses", 0)
w0, c0 = time.perf_counter(), time.process_time()
for _ in range(steps):
    sim.step()
    Q.append(sim.q.copy())
    iters += sim.last_stats.newton_iterations
    facts += sim.last_stats.factorizations
    cg += sim.last_stats.cg_iterations
    halvings += sim.last_stats.line_search_halvings
    substepped += getattr(sim.last_stats, "substeps", 1) > 1
wall, cpu = time.perf_counter() - w0, time.process_time() - c0
np.save(out, np.array(Q))
print(json.dumps({"wall": wall, "cpu": cpu, "newton": iters / steps, "fact": facts / steps,
                  "cg": cg / steps, "halvings": halvings / steps,
                  "analyses": getattr(sim.system, "analyses", -1) - a0,
                  "widenings": getattr(sim.system, "pattern_generation", -1),
                  "substepped": substepped}))
"""


def run(tree: Path, scene: str, steps: int, out: Path, overrides: dict) -> dict:
    """One scene in a fresh process with ``tree`` first on the path."""
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1")
    res = subprocess.run([sys.executable, "-c", _CHILD, scene, str(steps), str(out),
                          json.dumps(overrides)], env=env, cwd=tree, capture_output=True,
                         text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def parting(a: np.ndarray, b: np.ndarray) -> str:
    """First steps at which two trajectories differ by more than 1e-12, 1e-9, 1e-6, 1e-3 m,
    and the largest difference."""
    d = np.abs(a - b).reshape(len(a), -1).max(axis=1)
    first = []
    for tol in (1e-12, 1e-9, 1e-6, 1e-3):
        k = np.flatnonzero(d > tol)
        first.append(f">{tol:g} at {k[0] + 1 if k.size else '-'}")
    return ", ".join(first) + f"; max {d.max():.3g} m"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", type=Path, required=True, help="the older checkout")
    ap.add_argument("--scenes", nargs="*", default=["contact_stack", "contact_bunny_drop",
                                                    "contact_twisted_bar"])
    ap.add_argument("--steps", type=int, default=0, help="0: the scene's own duration")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--newton-solver", default="", help="simulation.newton.solver of both "
                    "(default: the scene's)")
    ap.add_argument("--no-parting", action="store_true",
                    help="speed only: skip the run with gravity one ulp off")
    ap.add_argument("--new-set", action="extend", nargs="+", default=[], metavar="KEY=VALUE",
                    help="scene overrides for the new tree only (VALUE as fem3d run --set "
                         "reads it; repeatable), e.g. contact.max_substeps=8")
    args = ap.parse_args(argv)
    from fem3d.app.cli import parse_assignments

    new_overrides = dict(parse_assignments(args.new_set, "--new-set"))
    base = {"simulation.newton.solver": args.newton_solver} if args.newton_solver else {}
    perturbed = {**base, "simulation.gravity": [0.0, float(np.nextafter(-9.81, -10.0)), 0.0]}
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes:
            if args.steps:
                steps = args.steps
            else:
                from fem3d.scene import load_scene
                steps = load_scene(scene).simulation.n_steps
            paths = {k: Path(tmp) / f"{scene}_{k}.npy" for k in ("old", "new", "pert")}
            figures: dict[str, list[dict]] = {"old": [], "new": []}
            for _ in range(args.repeat):
                for key, tree in (("old", args.old), ("new", ROOT)):
                    figures[key].append(run(tree, scene, steps, paths[key],
                                            {**base, **new_overrides} if key == "new" else base))
            for key in ("old", "new"):
                best = min(figures[key], key=lambda f: f["cpu"])
                print(f"{scene:22s} {key}: {steps} steps  {steps / best['wall']:6.2f} steps/s wall"
                      f"  {steps / best['cpu']:6.2f} steps/s CPU  {best['newton']:.2f} Newton/step"
                      f"  {best.get('fact', float('nan')):.2f} fact/step  "
                      f"{best.get('halvings', float('nan')):.2f} halvings/step  "
                      f"{best.get('cg', float('nan')):.1f} CG/step  widenings "
                      f"{best.get('widenings')}  analyses {best.get('analyses')}  "
                      f"{best.get('substepped', 0)} steps substepped", flush=True)
            old, new = (np.load(paths[k]) for k in ("old", "new"))
            print(f"{'':22s} new vs old:               {parting(old, new)}")
            if args.no_parting:
                continue
            run(args.old, scene, steps, paths["pert"], perturbed)
            pert = np.load(paths["pert"])
            print(f"{'':22s} old vs old, gravity 1 ulp: {parting(old, pert)}", flush=True)


if __name__ == "__main__":
    main()
