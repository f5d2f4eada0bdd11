"""Steps per second of the classic scenes, each integrator, Python overhead included.

    python -m bench.scenes [--steps 100] [--repeats 3] [--markdown FILE]

Each row runs ``Simulation.step()`` (``scripted=True``: the scene's pull attaches at t = 0 and
is released after 0.3 s) for ``--steps`` steps from rest, exactly as ``fem3d run`` does
without writing frames, and reports the best of ``--repeats`` runs (the machine is shared),
with that run's CPU time per step (``time.process_time``).
A run that blows up (the linearly-implicit armadillo) is reported with its step. Real time
at dt = 0.01 s is 100 steps per second.

A second block times the frame writers on the armadillo's skin (26,002 vertices, 52,000
triangles): milliseconds per frame of each output format's writer (``--frames`` frames of
changing positions, written atomically into a temporary folder, best of ``--repeats``; the
USD writer's chunks written as they fill and flushed at the end), and meshio's zlib VTU
writer, what ``vtu`` was before fem3d 0.2. ``fem3d run`` writes frames in a thread of its
own, so this is the time per frame the writer thread needs, not what the steps wait.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from fem3d.errors import SimulationError
from fem3d.io.frames import VtuWriter, make_frame_writer
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


def frame_writing(frames: int, repeats: int) -> list[str]:
    """Markdown rows: ms per frame of each writer on the armadillo's skin."""
    sim = Simulation(load_scene("arma"), scripted=True)
    V0, F = sim.skin_positions(), sim.display_faces
    rng = np.random.default_rng(0)
    Vs = [V0 + rng.normal(scale=1e-3, size=V0.shape) for _ in range(frames)]
    writers = {
        "vtu (appended raw binary)": lambda d: make_frame_writer(d, F, "vtu"),
        "obj": lambda d: make_frame_writer(d, F, "obj"),
        "usd (value clips)": lambda d: make_frame_writer(d, F, "usd", dt=sim.dt),
        "vtu before 0.2 (meshio, zlib)": lambda d: VtuWriter(d, F, compression="zlib"),
    }
    rows = ["| writer | ms / frame | MB / frame |", "| --- | ---: | ---: |"]
    for name, make in writers.items():
        best, size = float("inf"), 0.0
        for _ in range(repeats):
            with tempfile.TemporaryDirectory() as d:
                w = make(Path(d))
                start = time.perf_counter()
                for k, V in enumerate(Vs):
                    w.write(k, k * sim.dt, V)
                w.flush()
                best = min(best, (time.perf_counter() - start) / frames)
                size = sum(f.stat().st_size for f in Path(d).rglob("*") if f.is_file()) / frames
        rows.append(f"| {name} | {best * 1e3:.1f} | {size / 1e6:.2f} |")
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--markdown", type=Path, help="also write the table here")
    parser.add_argument("--frames", type=int, default=30,
                        help="frames per writer in the frame-writing block (0: skip it)")
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
        mode = getattr(sim.system.solver, "cholmod_mode", None)
        backend = sim.system.solver.backend + (f" {mode}" if mode else "")
        lines.append(f"| {name} ({sim.model.n_tets} tets) | {integrator} | {solves} "
                     f"({backend}) | {seconds * 1e3:.2f} | {1 / seconds:.0f} | {cpu * 1e3:.2f} "
                     f"| {newton} "
                     f"| {outcome} |")
        print(lines[-1], flush=True)
    note = (f"\n{args.steps} scripted steps, best of {args.repeats}; "
            f"`python -m bench.scenes --steps {args.steps} --repeats {args.repeats}`.\n")
    print(note)
    if args.frames > 0:
        rows = frame_writing(args.frames, args.repeats)
        print("\n".join(rows), flush=True)
        note += ("\nFrame writing, armadillo skin (26,002 vertices), " + f"{args.frames} "
                 f"frames, best of {args.repeats}:\n\n" + "\n".join(rows) + "\n")
    if args.markdown:
        args.markdown.write_text("\n".join(lines) + "\n" + note)


if __name__ == "__main__":
    main()
