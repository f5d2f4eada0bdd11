"""Time to first step of a big scene file: ``fem3d run`` stage by stage, old code beside new.

    python -m bench.startup [--tets 1e6] [--old /path/to/old/checkout] [--dir DIR]
                            [--steps 2] [--markdown FILE]

Writes a scene file (``DIR/big.toml``) around a box of about ``--tets`` tets
(:func:`bench.meshes.box_mesh`, 2 x 1 x 1, written as MEDIT ``DIR/box.mesh``): Neo-Hookean,
gravity, the x = 0 face pinned, backward Euler with the AMG solver, ``--steps`` steps, VTU
frames. Then runs ``fem3d run DIR/big.toml --no-preview --quiet`` once per checkout, each in a
process of its own, one after the other (only one such process at a time: a 1e6-tet run
holds gigabytes), ``--old`` first when given, this checkout second.

Each child times the same stages in both checkouts by wrapping functions both have (they
mark where a stage ends, in call order): reading the mesh (until validation starts),
validating it, the scene's arrays, the model's rest shape (until ``block_pattern``), the
sparsity pattern, the mass matrix (the rest of ``build_model``), pins/motions/contact (until
``System``), the reduced pattern (until the AMG analysis), the AMG analysis, the rest of the
simulation's set-up, the outputs' set-up (until the first step), the first step and the rest.
A stage's wall and CPU seconds (user + system) are those since the previous mark; memory is
the resident size at its end and the process's peak so far. The parent adds each child's
peak RSS and total user / system time (``os.wait4``). Wall times on a shared machine swing
with its load (printed); compare CPU times and ratios.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

SCENE = """# written by python -m bench.startup: a box of {tets} tets sagging under gravity
[simulation]
integrator = "implicit"
dt = 0.01
steps = {steps}
gravity = [0.0, -9.81, 0.0]
linear_solver = "amg"

[[bodies]]
name = "box"
mesh = "box.mesh"
material = {{ model = "neo_hookean", E = 1e6, nu = 0.3, density = 1000.0 }}
pins = [{{ select = {{ box = [[-1.0, -1.0, -1.0], [1e-6, 2.0, 2.0]] }} }}]

[output]
format = "vtu"
every = 1
"""


def write_scene(folder: Path, tets: float, steps: int) -> Path:
    """``folder/big.toml`` and ``folder/box.mesh`` (kept when the mesh is there already)."""
    from bench.meshes import box_mesh
    from fem3d.mesh.formats import write_tet_mesh
    from fem3d.mesh.tetmesh import TetMesh

    folder.mkdir(parents=True, exist_ok=True)
    mesh = folder / "box.mesh"
    stamp = folder / "box.tets"
    if not (mesh.exists() and stamp.exists() and stamp.read_text() == repr(float(tets))):
        X, T = box_mesh(tets, size=(2.0, 1.0, 1.0))
        write_tet_mesh(mesh, TetMesh(X, T))
        stamp.write_text(repr(float(tets)))
    scene = folder / "big.toml"
    scene.write_text(SCENE.format(tets=f"{tets:g}", steps=steps))
    return scene


# ------------------------------------------------------------------------------ child
class _Marks:
    """Stage ends in call order: wall, CPU and memory since the previous one."""

    def __init__(self) -> None:
        self.rows: list[dict] = []
        self.last = (time.perf_counter() - _process_age(), 0.0, 0.0)

    def mark(self, name: str) -> None:
        now, t = time.perf_counter(), os.times()
        rss, peak = _memory_mib()
        wall0, user0, sys0 = self.last
        self.rows.append({"stage": name, "wall": now - wall0, "user": t.user - user0,
                          "sys": t.system - sys0, "rss": rss, "peak": peak})
        self.last = (now, t.user, t.system)


def _process_age() -> float:
    with open("/proc/self/stat") as f:
        start = float(f.read().rsplit(")", 1)[1].split()[19])
    with open("/proc/uptime") as f:
        return float(f.read().split()[0]) - start / os.sysconf("SC_CLK_TCK")


def _memory_mib() -> tuple[float, float]:
    rss = peak = float("nan")
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) / 1024
            elif line.startswith("VmHWM:"):
                peak = int(line.split()[1]) / 1024
    return rss, peak


def _wrap(owner, name: str, marks: _Marks, before: str | None, after: str | None,
          once: bool = False) -> None:
    """Replace ``owner.name`` by a wrapper marking ``before`` at entry, ``after`` at exit."""
    inner = getattr(owner, name)
    done = []

    @functools.wraps(inner)
    def wrapper(*args, **kwargs):
        if once and done:
            return inner(*args, **kwargs)
        done.append(True)
        if before:
            marks.mark(before)
        result = inner(*args, **kwargs)
        if after:
            marks.mark(after)
        return result

    setattr(owner, name, wrapper)


def _mesh_readers(formats) -> list:
    """The modules of a checkout's mesh readers that call ``validate_tet_mesh``."""
    import importlib
    import importlib.util

    names = ("fem3d.mesh.medit", "fem3d.mesh.tetgen", "fem3d.mesh.meshio_formats")
    modules = [formats] + [importlib.import_module(n) for n in names
                           if importlib.util.find_spec(n) is not None]
    return [m for m in modules if hasattr(m, "validate_tet_mesh")]


def child(scene: str, out: str, result: str) -> int:
    """One ``fem3d run`` with the stage wrappers (run with the checkout on PYTHONPATH)."""
    import warnings

    warnings.simplefilter("ignore")
    marks = _Marks()
    import fem3d.mesh.formats as formats
    import fem3d.physics.model as model
    import fem3d.scene.build as build
    import fem3d.simulation as simulation
    import fem3d.solve.linear.amg as amg
    from fem3d.app.cli import main

    marks.mark("start-up (Python, imports)")
    # the readers call validate_tet_mesh: from formats (before the reader modules), or from
    # the module of each reader family (medit, tetgen, meshio_formats)
    for reader in _mesh_readers(formats):
        _wrap(reader, "validate_tet_mesh", marks, "scene file, read mesh", "validate mesh")
    _wrap(build, "build_arrays", marks, None, "scene arrays (transforms, selections)")
    _wrap(model, "block_pattern", marks, "model: rest shape, materials",
          "model: sparsity pattern")
    _wrap(build, "build_model", marks, None, "model: mass matrix")
    _wrap(simulation, "System", marks, "pins, motions, damping, contact", None)
    _wrap(amg.AMGPreconditioner, "analyze", marks, "system: reduced pattern",
          "system: amg analysis", once=True)
    _wrap(simulation.Simulation, "__init__", marks, None, "simulation set-up")
    _wrap(simulation.Simulation, "step", marks, "output set-up, initial frame", "first step",
          once=True)
    status = main(["run", scene, "--out", out, "--quiet", "--no-preview"])
    marks.mark("rest of the run (later steps, outputs)")
    Path(result).write_text(json.dumps({"status": status, "rows": marks.rows,
                                        "fem3d": str(Path(formats.__file__).parents[2])}))
    return status


# ------------------------------------------------------------------------------ parent
def run_checkout(checkout: Path, scene: Path, out: Path) -> dict:
    """Run the child under ``checkout``; its stages plus wall, CPU and peak RSS."""
    result = out.with_suffix(".json")
    env = dict(os.environ, PYTHONPATH=str(checkout))
    start = time.perf_counter()
    # this file as a script, run in the scene's folder: nothing but the checkout on the path
    # (``python -m`` would put the working directory first)
    proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--child",
                             str(scene), str(out), str(result)], env=env, cwd=scene.parent)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    data = json.loads(result.read_text()) if result.exists() else {"rows": []}
    data.update(wall=time.perf_counter() - start, user=usage.ru_utime, sys=usage.ru_stime,
                peak_mib=usage.ru_maxrss / 1024, returncode=proc.returncode)
    return data


def _first_step(rows: list[dict], key: str) -> float:
    total = 0.0
    for r in rows:
        if r["stage"] == "first step":
            return total
        total += r[key] if key == "wall" else r["user"] + r["sys"]
    return total


def table(runs: dict[str, dict]) -> list[str]:
    """Markdown: per stage, wall and CPU seconds and peak so far of each checkout."""
    names = list(runs)
    head = "| stage | " + " | ".join(f"{n} wall s | {n} CPU s | {n} peak MiB" for n in names)
    lines = [head + (" | CPU new/old |" if len(names) == 2 else " |"),
             "| --- |" + " ---: | ---: | ---: |" * len(names) + (" ---: |" if len(names) == 2
                                                                 else "")]
    stages = list(dict.fromkeys(r["stage"] for run in runs.values() for r in run["rows"]))
    for stage in stages:
        cells, cpus = [], []
        for n in names:
            row = next((r for r in runs[n]["rows"] if r["stage"] == stage), None)
            if row is None:
                cells.append("| | ")
                cpus.append(float("nan"))
                continue
            cpu = row["user"] + row["sys"]
            cpus.append(cpu)
            cells.append(f"{row['wall']:.2f} | {cpu:.2f} | {row['peak']:.0f}")
        ratio = f" | {cpus[1] / cpus[0]:.2f}" if len(names) == 2 and cpus[0] > 0 else \
            (" | " if len(names) == 2 else "")
        lines.append(f"| {stage} | " + " | ".join(cells) + ratio + " |")
    ttfs = [(_first_step(runs[n]["rows"], "wall"), _first_step(runs[n]["rows"], "cpu"))
            for n in names]
    cells = " | ".join(f"**{w:.2f}** | **{c:.2f}** | " for w, c in ttfs)
    ratio = f" | {ttfs[1][1] / ttfs[0][1]:.2f}" if len(names) == 2 else ""
    lines.append(f"| **time to first step** | {cells}{ratio} |")
    cells = " | ".join(f"{runs[n]['wall']:.2f} | {runs[n]['user'] + runs[n]['sys']:.2f} | "
                       f"**{runs[n]['peak_mib']:.0f}**" for n in names)
    ratio = ""
    if len(names) == 2:
        a, b = (runs[n]["user"] + runs[n]["sys"] for n in names)
        ratio = f" | {b / a:.2f}"
    lines.append(f"| whole run (peak RSS) | {cells}{ratio} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tets", type=float, default=1e6)
    ap.add_argument("--steps", type=int, default=2)
    ap.add_argument("--old", type=Path, help="an older checkout (its fem3d/ is imported)")
    ap.add_argument("--dir", type=Path, default=Path("/tmp/fem3d-bench-startup"))
    ap.add_argument("--markdown", type=Path, help="also write the table here")
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return child(*args.child)
    scene = write_scene(args.dir, args.tets, args.steps)
    checkouts = {"old": args.old, "new": ROOT} if args.old else {"new": ROOT}
    runs = {}
    for name, checkout in checkouts.items():
        load = os.getloadavg()[0]
        runs[name] = run_checkout(Path(checkout).resolve(), scene, args.dir / f"out_{name}")
        runs[name]["load"] = load
        print(f"{name} (fem3d of {runs[name].get('fem3d')}): exit {runs[name]['returncode']}, "
              f"{runs[name]['wall']:.1f} s wall, load {load:.1f} at its start", flush=True)
    lines = table(runs)
    loads = ", ".join(f"{n} {r['load']:.1f}" for n, r in runs.items())
    note = (f"\n`python -m bench.startup --tets {args.tets:g} --steps {args.steps}"
            f"{' --old ' + str(args.old) if args.old else ''}`; 1-minute load average at "
            f"each run's start: {loads} (2 cores).")
    print("\n".join(lines) + "\n" + note)
    if args.markdown:
        args.markdown.write_text("\n".join(lines) + "\n" + note + "\n")
    return 0 if all(r["returncode"] == 0 for r in runs.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
