"""Steps per second of the classic scenes, each integrator, Python overhead included.

    python -m bench.scenes [--steps 100] [--repeats 3] [--markdown FILE]

Each row runs ``Simulation.step()`` (``scripted=True``: the scene's pull attaches at t = 0 and
is released after 0.3 s) for ``--steps`` steps from rest, exactly as ``fem3d run`` does
without writing frames, and reports the best of ``--repeats`` runs (the machine is shared),
with that run's CPU time per step (``time.process_time``).
A run that blows up (the linearly-implicit armadillo) is reported with its step. Real time
at dt = 0.01 s is 100 steps per second.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from fem3d.errors import SimulationError
from fem3d.scene import load_scene
from fem3d.simulation import Simulation

#: (scene, integrator, Newton's linear solver); the scenes' own integrators come first.
ROWS = (
    ("bunny", "linear", "direct"),
    ("arma", "implicit", "direct"),
    ("arma", "implicit", "reuse"),
    ("bunny", "implicit", "direct"),
    ("bunny", "implicit", "reuse"),
    ("arma", "linear", "direct"),
)


def run(sim: Simulation, steps: int) -> tuple[float, float, int, str]:
    """Wall and CPU seconds per step, Newton iterations and outcome of ``steps`` scripted
    steps (on a shared machine the CPU time estimates the unloaded wall time better)."""
    sim.reset()
    newton = 0
    start, cpu = time.perf_counter(), time.process_time()
    for i in range(steps):
        try:
            newton += sim.step().newton_iterations
        except SimulationError:
            n = max(i, 1)
            return ((time.perf_counter() - start) / n, (time.process_time() - cpu) / n, newton,
                    f"exploded at step {i}")
    return ((time.perf_counter() - start) / steps, (time.process_time() - cpu) / steps, newton,
            "ok")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--markdown", type=Path, help="also write the table here")
    args = parser.parse_args(argv)
    lines = ["| scene | integrator | Newton solves | ms / step | steps / s | CPU ms / step "
             "| Newton iterations | outcome |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: | --- |"]
    print(lines[0], lines[1], sep="\n", flush=True)
    for name, integrator, solver in ROWS:
        scene = load_scene(name, {"simulation.integrator": integrator,
                                  "simulation.newton.solver": solver})
        sim = Simulation(scene, scripted=True)
        runs = [run(sim, args.steps) for _ in range(args.repeats)]
        seconds, cpu, newton, outcome = min(runs)
        solves = "factorize" if integrator == "linear" else solver
        mode = sim.system.solver.cholmod_mode
        backend = sim.system.solver.backend + (f" {mode}" if mode else "")
        lines.append(f"| {name} ({sim.model.n_tets} tets) | {integrator} | {solves} "
                     f"({backend}) | {seconds * 1e3:.2f} | {1 / seconds:.0f} | {cpu * 1e3:.2f} "
                     f"| {newton} "
                     f"| {outcome} |")
        print(lines[-1], flush=True)
    note = (f"\n{args.steps} scripted steps, best of {args.repeats}; "
            f"`python -m bench.scenes --steps {args.steps} --repeats {args.repeats}`.\n")
    print(note)
    if args.markdown:
        args.markdown.write_text("\n".join(lines) + "\n" + note)


if __name__ == "__main__":
    main()
