"""The straight-motion check of contact substeps (``fem3d/physics/contact/path.py``) timed
inside a run, this tree's against an older checkout's, on the same steps.

    python -m bench.tools.path_check --old /path/to/old/checkout contact_stack contact_fold
    python -m bench.tools.path_check --old ../old contact_pile --steps 40
    python -m bench.tools.path_check --old ../old contact_stack --set contact.newton_start=clamped

Each scene runs as :class:`fem3d.simulation.Simulation` steps it, with
``contact.max_substeps = 1`` (so the trajectory is the same whichever check says what).
After every step both checks (``straight_path_is_free``: this tree's, and the one in
``OLD/fem3d/physics/contact_path.py``) are called on the step's motion, twice each, in
alternating order, and timed by ``time.process_time``. Prints per scene: the step's CPU time,
each check's, the new check's share of the step, and the steps each check flags (1-based; a
flagged step would be redone in substeps).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path


def old_check(old: Path):
    """``straight_path_is_free`` of the checkout at ``old``."""
    path = old / "fem3d" / "physics" / "contact_path.py"
    spec = importlib.util.spec_from_file_location("_old_contact_path", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.straight_path_is_free


def measure(name: str, steps: int | None, old, overrides: dict | None = None) -> str:
    """One scene's line (``overrides``: scene overrides, as ``--set``)."""
    from fem3d.physics.contact.path import straight_path_is_free
    from fem3d.scene import apply_overrides, load_scene
    from fem3d.simulation import Simulation

    def new(contact, *motion):  # this tree's check reads the model's collision sets
        return straight_path_is_free(contact.collisions, *motion)

    scene = apply_overrides(load_scene(name), {**(overrides or {}), "contact.max_substeps": 1})
    sim = Simulation(scene, scripted=True)
    steps = steps or scene.n_steps
    contact = sim.contact.contact
    seconds = {old: 0.0, new: 0.0}
    flagged: dict = {old: [], new: []}
    stepping = 0.0
    for k in range(steps):
        q0, t0 = sim.q.copy(), sim.t
        c = time.process_time()
        sim.step()
        stepping += time.process_time() - c
        q1, t1 = sim.q.copy(), sim.t
        for rep in range(2):
            for check in ((old, new) if (k + rep) % 2 == 0 else (new, old)):
                c = time.process_time()
                free = check(contact, q0, q1, t0, t1)
                seconds[check] += time.process_time() - c
                if not free and rep == 0:
                    flagged[check].append(k + 1)
    ms = 1e3 / steps
    return (f"{name}: {steps} steps, {stepping * ms:.2f} ms CPU a step; check old "
            f"{seconds[old] * ms / 2:.3f} ms, new {seconds[new] * ms / 2:.3f} ms "
            f"({100 * seconds[new] / 2 / stepping:.2f} % of the step); steps flagged: old "
            f"{len(flagged[old])} {flagged[old]}, new {len(flagged[new])} {flagged[new]}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="+", help="scene names, e.g. contact_stack")
    parser.add_argument("--old", required=True, type=Path, help="the older checkout")
    parser.add_argument("--steps", type=int, default=None, help="default: the scene's")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a scene override (VALUE as fem3d run --set reads it), repeatable")
    args = parser.parse_args(argv)
    from fem3d.app.cli import parse_assignments

    overrides = dict(parse_assignments(args.set))
    old = old_check(args.old)
    for name in args.scenes:
        print(measure(name, args.steps, old, overrides), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
