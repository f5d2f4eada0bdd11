"""Steps/s of each time integrator on the contact bunny drop and the armadillo drag.

Run: ``python -m bench.integrators [--steps N]``; prints one row per scene and scheme.
"""

from __future__ import annotations

import argparse
import time

from fem3d.scene import load_scene
from fem3d.simulation import Simulation

SCENES = {"contact_bunny_drop": ("implicit", "bdf2", "newmark", "static"),
          "arma": ("implicit", "bdf2", "newmark")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=35)
    args = ap.parse_args()
    print(f"{'scene':<22}{'integrator':<12}{'steps/s':>10}{'Newton it/step':>16}")
    for scene, schemes in SCENES.items():
        for name in schemes:
            sim = Simulation(load_scene(scene, {"simulation.integrator": name}),
                             scripted=True)
            newton = 0
            t0 = time.perf_counter()
            for _ in range(args.steps):
                newton += sim.step().newton_iterations
            rate = args.steps / (time.perf_counter() - t0)
            print(f"{scene:<22}{name:<12}{rate:>10.1f}{newton / args.steps:>16.2f}")


if __name__ == "__main__":
    main()
