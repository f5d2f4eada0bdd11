"""The adjoint's cost: one forward run against one adjoint pass, and memory by checkpointing.

    python -m bench.adjoint                                   # the fit example's beam, 30 steps
    python -m bench.adjoint --scene examples/fit/two_halves.toml --steps 30
    python -m bench.adjoint --set bodies[0].damping.rayleigh_stiffness=0.002

For each ``checkpoint_every`` k (default 1, 10, 100), in a subprocess of its own (so that its
peak RSS is its own): one :func:`fem3d.diff.simulate` of the scene (the forward run the
adjoint differentiates: Newton to convergence), then one :func:`fem3d.diff.
trajectory_gradient` of the loss ``1/2 |q_n - target_n|^2`` over every frame with the
parameters ``--params``. Printed: CPU seconds (``time.process_time``; one BLAS thread) of
the forward run, of the gradient's own forward run, its recomputation of the segments and its
backward (adjoint) steps; the ratio of the adjoint pass (recomputation + backward) to the
forward run; the most states held at once and their size; with stiffness damping, the most
megabytes of damping linearizations kept for the backward steps; the peak RSS. Timings on a shared
machine are noisy: read the ratios, and the load printed with them.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

PARAMS = "bodies[0].material.E,bodies[0].material.nu"


def _one(args: argparse.Namespace) -> dict:
    import resource

    import numpy as np

    from fem3d.app.cli import parse_assignments
    from fem3d.diff import PositionLoss, simulate, trajectory_gradient
    from fem3d.diff.adjoint import Stats
    from fem3d.scene import load_scene

    overrides = dict(parse_assignments(args.set))
    scene = load_scene(args.scene, overrides)
    t0 = time.process_time()
    qs = simulate(scene, args.steps)
    forward = time.process_time() - t0
    rng = np.random.default_rng(0)
    scale = 1e-3 * float(np.linalg.norm(np.ptp(qs[0], axis=0)))
    loss = PositionLoss({n: qs[n] + scale * rng.normal(size=qs[n].shape)
                         for n in range(1, args.steps + 1)})
    stats = Stats()
    t0 = time.process_time()
    trajectory_gradient(scene, loss, args.params.split(","), checkpoint_every=args.k,
                        stats=stats)
    total = time.process_time() - t0
    state_bytes = 2 * qs[0].nbytes
    return {"k": args.k, "forward": forward, "gradient": total,
            "gradient_forward": stats.forward_seconds, "recompute": stats.recompute_seconds,
            "backward": stats.backward_seconds, "recomputed_steps": stats.recomputed_steps,
            "peak_states": stats.peak_states, "state_mb": state_bytes / 2**20,
            "damping_mb": stats.peak_damping_bytes / 2**20,
            "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "vertices": int(qs[0].shape[0])}


def main(argv: list[str] | None = None) -> int:
    """Run the cases (one subprocess per k) and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="examples/fit/cantilever.toml")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--params", default=PARAMS)
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE override")
    ap.add_argument("--ks", default="1,10,100")
    ap.add_argument("--k", type=int, default=None, help=argparse.SUPPRESS)  # the subprocess
    args = ap.parse_args(argv)
    if args.k is not None:
        print(json.dumps(_one(args)))
        return 0
    print(f"# {args.scene}, {args.steps} steps, params {args.params}, "
          f"sets {args.set or 'none'}; load {os.getloadavg()[0]:.1f}; CPU seconds")
    print("| k | forward run | gradient: forward | recompute | backward (adjoint) | "
          "adjoint / forward | (recompute + backward) / forward | states held (MB) | "
          "damping kept MB | peak RSS MB |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for k in (int(x) for x in args.ks.split(",")):
        cmd = [sys.executable, "-m", "bench.adjoint", "--scene", args.scene, "--steps",
               str(args.steps), "--params", args.params, "--k", str(k),
               *(a for s in args.set for a in ("--set", s))]
        r = json.loads(subprocess.run(cmd, check=True, capture_output=True,
                                      text=True).stdout.strip().splitlines()[-1])
        f = r["forward"]
        print(f"| {k} | {f:.2f} s | {r['gradient_forward']:.2f} s | {r['recompute']:.2f} s "
              f"({r['recomputed_steps']} steps) | {r['backward']:.2f} s | "
              f"{r['backward'] / f:.2f} | {(r['recompute'] + r['backward']) / f:.2f} | "
              f"{r['peak_states']} ({r['peak_states'] * r['state_mb']:.2f}) | "
              f"{r.get('damping_mb', 0.0):.1f} | {r['rss_mb']:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
