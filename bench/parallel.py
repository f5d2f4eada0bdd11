"""Strong and weak scaling of ``mpiexec -n N fem3d run``: the same box on 1, 2, ... ranks,
or (``--weak``) a box of ``--tets`` tets per rank.

    python -m bench.parallel --tets 1e5 --steps 3 --ranks 1,2
    python -m bench.parallel --tets 1e5 --steps 3 --ranks 1,2 --petsc-options "-pc_type gamg"
    python -m bench.parallel --weak --tets 5e5 --steps 2 --ranks 1,2

A box (``bench.meshes.box_mesh``) clamped at its lowest z, swinging under gravity
(backward Euler, Neo-Hookean, ``dt = 0.01``), written to a temporary folder; each rank count
runs ``mpiexec -n N python -m fem3d run`` (one thread per rank) and the run's own summary
line is parsed: wall time of the steps, set-up time, Newton iterations, the peak RSS of
each rank (and after set-up) and the CPU time of each rank's steps. 1 rank is the one-process
``fem3d run`` (the same PETSc solver, no MPI layer; its RSS from the operating system; the
first rank count, so that the children's peak is its). Every row also gives the CPU time of
all the processes it ran (set-up included) and the 1-minute load average before and after
(the machine may be shared: wall-time speed-ups are only as good as the load lets them be).
Prints one row per rank count, the speed-up (weak: the efficiency, the first's time per step
over this one's) and the peak memory per rank over the first.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.meshes import box_mesh
from fem3d.mesh.formats import write_tet_mesh
from fem3d.mesh.tetmesh import TetMesh

SUMMARY = re.compile(r"(\d+) steps on (\d+) ranks in ([\d.]+) s \(([\d.]+) s set-up\), "
                     r"(\d+) Newton iterations.*peak RSS per rank ([\d., ]+) MiB "
                     r"\(after set-up ([\d., ]+)\), CPU of the steps per rank ([\d., ]+) s")
ONE = re.compile(r"(\d+) steps in ([\d.]+) s; [\d.]+ ms/step \(([\d.]+) Newton iterations/step\)")


def scene_text(mesh: Path, steps: int, petsc_options: str) -> str:
    extra = f'petsc_options = "{petsc_options}"' if petsc_options else ""
    return f"""
[simulation]
integrator = "implicit"
dt = 0.01
steps = {steps}
gravity = [0.0, -9.81, 0.0]
linear_solver = "petsc"
{extra}

[[bodies]]
mesh = "{mesh}"
velocity = [0.5, 0.0, 0.0]
material = {{ model = "neo_hookean", E = 1e6, nu = 0.3, density = 1000.0 }}
pins = [{{ select = {{ box = [[-1.0, -1.0, -1.0], [2.0, 2.0, 1e-6]] }} }}]

[output]
every = 1000000
"""


def run(ranks: int, scene: Path, out: Path) -> dict:
    """One run; 1 rank: the one-process ``fem3d run`` (the same PETSc solver, no MPI
    layer), its peak RSS from the operating system."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OMPI_ALLOW_RUN_AS_ROOT": "1",
           "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}
    fem3d = [sys.executable, "-m", "fem3d", "run", str(scene), "--out", str(out), "--no-preview"]
    cmd = fem3d if ranks == 1 else ["mpiexec", "--oversubscribe", "-n", str(ranks), *fem3d]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    # every process's CPU (ranks and mpiexec, set-up included)
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    if ranks == 1:
        match = ONE.search(proc.stderr + proc.stdout)
        rss = after.ru_maxrss / 1024.0
    else:
        match = SUMMARY.search(proc.stdout)
    if proc.returncode or match is None:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}")
    if ranks == 1:
        steps, wall, newton = match.groups()
        return {"ranks": 1, "steps": int(steps), "wall": float(wall), "setup": float("nan"),
                "newton": round(float(newton) * int(steps)), "rss": [rss], "cpu": cpu,
                "setup_rss": [float("nan")], "step_cpu": [float("nan")]}
    steps, _, wall, setup, newton, rss, setup_rss, step_cpu = match.groups()
    return {"ranks": ranks, "steps": int(steps), "wall": float(wall), "setup": float(setup),
            "newton": int(newton), "rss": _floats(rss), "cpu": cpu,
            "setup_rss": _floats(setup_rss), "step_cpu": _floats(step_cpu)}


def _floats(text: str) -> list[float]:
    return [float(r) for r in text.split(",")]


def write_box(folder: Path, tets: float, steps: int, petsc_options: str) -> tuple[Path, str]:
    """The box scene of about ``tets`` tets in ``folder``; its path and a one-line summary."""
    X, T = box_mesh(tets)
    folder.mkdir(parents=True, exist_ok=True)
    mesh = folder / "box.mesh"
    write_tet_mesh(mesh, TetMesh(X, T))
    scene = folder / "box.toml"
    scene.write_text(scene_text(mesh, steps, petsc_options))
    return scene, f"box: {T.shape[0]:,} tets, {X.shape[0]:,} vertices"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tets", type=float, default=1e5, help="tets (--weak: per rank)")
    p.add_argument("--steps", type=int, default=3)
    p.add_argument("--ranks", default="1,2")
    p.add_argument("--petsc-options", default="")
    p.add_argument("--weak", action="store_true",
                   help="weak scaling: a box of --tets tets per rank for each rank count")
    args = p.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="fem3d_parallel_"))
    counts = [int(r) for r in args.ranks.split(",")]
    try:
        scenes = {}
        for n in counts if args.weak else counts[:1]:
            scenes[n], line = write_box(tmp / f"box{n}", args.tets * (n if args.weak else 1),
                                        args.steps, args.petsc_options)
            print(f"{line}{f' for {n} rank(s)' if args.weak else ''}, {args.steps} "
                  f"backward-Euler steps, linear_solver = petsc "
                  f"{args.petsc_options or '(default)'}")
        rows = []
        for n in counts:
            load = os.getloadavg()[0]
            rows.append(run(n, scenes[n if args.weak else counts[0]], tmp / f"out{n}"))
            r = rows[-1]
            ratio = (rows[0]['wall'] / rows[0]['steps']) / (r['wall'] / r['steps'])
            print(f"  {n} rank(s): {r['wall'] / r['steps']:.2f} s/step "
                  f"({'efficiency ' if args.weak else 'x'}{ratio:.2f}), set-up "
                  f"{r['setup']:.2f} s, "
                  f"{r['newton']} Newton iterations, peak RSS per rank "
                  f"{', '.join(f'{m:.0f}' for m in r['rss'])} MiB (after set-up "
                  f"{', '.join(f'{m:.0f}' for m in r['setup_rss'])}; "
                  f"x{max(r['rss']) / rows[0]['rss'][0]:.2f} of the first), CPU of the steps "
                  f"per rank {', '.join(f'{c:.1f}' for c in r['step_cpu'])} s, CPU of every "
                  f"process {r['cpu']:.1f} s, load average {load:.1f} -> "
                  f"{os.getloadavg()[0]:.1f}", flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
