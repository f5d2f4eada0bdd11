"""Backward-Euler steps: Newton iteration cost, factorization reuse vs refactorization, memory.

    python -m bench.newton_step --mesh arma --refine 0,1,2 --steps 80   # armadillo-class drag
    python -m bench.newton_step --mesh box --tets 2e4 --steps 6         # swinging box
    python -m bench.newton_step --mesh box --tets 1e6 --steps 1 --modes direct   # the 1e6 step
    python -m bench.newton_step --mesh box --tets 1e5 --steps 1 --swing 4 --modes direct,reuse,amg
    python -m bench.newton_step --mesh box --tets 1e5 --steps 1 --modes direct,amg,petsc --repeats 1

``--mesh arma``: the armadillo scene (``arma_6``, 627 tets) and its 1:8 refinements
(``bench.meshes.refine_tets``: 5,016 and 40,128 tets, same shape, feet fixed as in the scene).
The scene's picked hand vertices are dragged like a viewer user would: out by 20 % of the
height over 0.3 s, then round a circle, then released for the last 20 steps.
``--mesh box``: the box (``bench.meshes.box_mesh``) clamped at its lowest z, starting at rest
with a swinging velocity ``v = (a z^2, -b x z, 0)``.

On a machine shared with other work the CPU time per step (``time.process_time``, one thread:
``OMP_NUM_THREADS=1``) estimates the unloaded wall time better than the wall time does; both
are printed.

Each mode runs every step's Newton iteration to the same gradient tolerance (no iteration
cap: equal accuracy; a few steps of either mode stop earlier, where the line search meets the
energy's round-off, and are counted), from a fresh :class:`fem3d.solve.integrators.System`; the
best of
``--repeats`` runs is reported (the machine is shared). Printed per mode: time per step,
Newton iterations, factorizations, CG iterations, the largest final gradient norm, the
largest deviation of the trajectory from the first mode's (relative to the mesh size), the
speed-up over the first mode, and peak RSS, then where the time went (matrix assembly,
factorizations, AMG setups, CG iterations, energies and gradients) and how many Newton
iterations solved with the previous iterate's matrix (``reuse``); first, the pieces of one
Newton iteration (assembly into the reduced pattern, factorization, solve; with ``amg``: one
hierarchy setup and one V-cycle). Modes: ``direct`` and ``reuse`` on the default direct back
end (CHOLMOD), ``amg`` on AMG-preconditioned CG (pyamg), ``petsc`` Newton's direct direction
on PETSc's KSP in one process (CG + GAMG, the rigid-body near-null space: what
``linear_solver = "petsc"`` and the ranks of ``mpiexec`` solve with), each forced whatever
``"auto"`` would pick. ``--warm-start extrapolate`` starts each step's Newton iteration at the
lower-energy of ``v_t`` and ``2 v_t - v_t-1`` (:data:`fem3d.solve.settings.
WARM_STARTS`; the interactive drag of docs/benchmarks.md, on one core:
``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1``)::

    python -m bench.newton_step --mesh arma --refine 1 --modes reuse --warm-start extrapolate
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.meshes import box_mesh, refine_tets
from fem3d.kernels.threads import report as thread_report
from fem3d.physics.constraints import Constraints, pick_nearest_vertices
from fem3d.physics.model import Model, build_model
from fem3d.physics.springs import Pull
from fem3d.solve import integrators as integ
from fem3d.solve.linear import resolve_linear_solver
from fem3d.solve.settings import WARM_STARTS


@dataclass
class Workload:
    """A mesh, its constraint set and the per-step pulls of one benchmark run."""

    name: str
    model: Model
    constraints: Constraints
    start: integ.State
    dt: float
    pulls: list[Pull | None]

    @property
    def size(self) -> float:
        return float(np.ptp(self.model.X, axis=0).max())


def armadillo(level: int, steps: int) -> Workload:
    """The armadillo scene refined ``level`` times, its hand dragged for ``steps - 20`` steps."""
    from fem3d.physics.constraints import fixed_vertices_lowest_y
    from fem3d.scene import load_scene
    from fem3d.scene.arrays import build_arrays

    scene = load_scene("arma")
    a = build_arrays(scene)
    body, pull = scene.bodies[0], scene.pulls[0]
    X, T = a.X, a.T
    for _ in range(level):
        X, T = refine_tets(X, T)  # old vertices keep their indices: same feet, same hand
    mat = body.material
    model = build_model(X, T, E=mat.E, nu=mat.nu, rho=mat.density)
    fixed_tol = body.pins[0].select.lowest_y.tol
    constraints = Constraints.from_fixed_vertices(X, fixed_vertices_lowest_y(X, fixed_tol))
    hand = X[pull.select.near_vertex.vertex]
    picked = pick_nearest_vertices(X, hand, pull.select.near_vertex.radius,
                                   nearest_if_empty=True)
    h = float(np.ptp(X[:, 1]))
    pulls: list[Pull | None] = []
    for i in range(steps):
        out, angle = min(1.0, i / 30), 0.1 * max(0, i - 30)
        target = hand + h * np.array([0.1 * np.sin(angle), 0.05 * (1 - np.cos(angle)), 0.2 * out])
        pulls.append(Pull.make(picked, target, pull.stiffness, model.n_vertices)
                     if i < steps - 20 else None)
    return Workload(f"armadillo x{8 ** level} ({len(T)} tets)", model, constraints,
                    integ.State.at_rest(model), scene.simulation.dt, pulls)


def swinging_box(n_tets: float, steps: int, swing: float) -> Workload:
    """The clamped box with the swinging initial velocity, no pull."""
    X, T = box_mesh(n_tets)
    model = build_model(X, T, E=6e5, nu=0.4, rho=0.1)
    fixed = np.flatnonzero(X[:, 2] <= X[:, 2].min() + 1e-12)
    v0 = np.zeros_like(X)
    v0[:, 0] = swing * X[:, 2] ** 2
    v0[:, 1] = -0.75 * swing * X[:, 2] * X[:, 0]
    v0[fixed] = 0.0
    return Workload(f"box ({len(T)} tets)", model, Constraints.from_fixed_vertices(X, fixed),
                    integ.State(q=X.copy(), v=v0), 0.01, [None] * steps)


def _best_seconds(call, repeats: int) -> float:
    seconds = []
    for _ in range(repeats):
        t = time.perf_counter()
        call()
        seconds.append(time.perf_counter() - t)
    return min(seconds)


def _backend(mode: str) -> str:
    if mode in ("amg", "petsc"):
        return mode
    return resolve_linear_solver(direct=True)


def _direction(mode: str) -> str:
    """Newton's direction of a mode (``petsc``: the direct direction on PETSc's solver,
    CG + GAMG above ``GAMG_MIN_FREE_DOFS`` free DOFs)."""
    return "direct" if mode == "petsc" else mode


def iteration_pieces(work: Workload, modes: list[str]) -> dict:
    """Seconds of the pieces of one Newton iteration at a deformed state (best of a few after
    a warm-up; one of each on large meshes): the direct ones when a direct mode runs, the AMG
    ones (hierarchy setup, one V-cycle) when ``amg`` runs."""
    q = work.start.q + work.dt * work.start.v
    out: dict = {}
    direct = [m for m in modes if m not in ("amg", "petsc")]
    system = integ.System(work.model, work.constraints, _backend(direct[0] if direct else "amg"))
    A = system.newton_matrix(q, work.dt)
    b = np.ones(A.shape[0])
    repeats = 5 if A.shape[0] < 1e5 else 1
    out["assembly"] = _best_seconds(lambda: system.newton_matrix(q, work.dt), repeats)
    out["matvec"] = _best_seconds(lambda: A @ b, repeats)
    if direct:
        if repeats > 1:  # warm caches; a large factorization is its own warm-up
            system.factorize(A)
            system.solve(b)
        out["factorize"] = _best_seconds(lambda: system.factorize(A), repeats)
        out["solve"] = _best_seconds(lambda: system.solve(b), repeats)
        out["cholmod_mode"] = getattr(system.solver, "cholmod_mode", None)
    if "amg" in modes:
        amg = system if system.linear_backend == "amg" else \
            integ.System(work.model, work.constraints, "amg")
        out["amg_setup"] = _best_seconds(lambda: amg.amg_setup(A), repeats)
        out["vcycle"] = _best_seconds(lambda: amg.amg.hierarchy.apply(b), repeats)
        out["amg_levels"] = amg.amg.hierarchy.level_sizes
    return out


def run_mode(work: Workload, mode: str, cg_maxiter: int = 16, cg_rtol: float = 1e-6,
             warm_start: str = "previous") -> dict:
    """All steps of ``work`` with one linear-solver mode (and Newton start, ``warm_start``:
    :data:`fem3d.solve.settings.WARM_STARTS`); totals and the trajectory."""
    t_system = time.perf_counter()
    system = integ.System(work.model, work.constraints, _backend(mode))
    t_system = time.perf_counter() - t_system  # the solver's analysis (ordering; aggregation)
    state = work.start
    seconds, trajectory = 0.0, []
    totals = dict(newton=0, factorizations=0, cg=0, psd_fallbacks=0, final_gradient=0.0,
                  stopped_at_round_off=0, amg_setups=0, halvings=0, lagged=0)
    parts: dict[str, float] = {}
    cpu = 0.0
    for pull in work.pulls:
        t, c = time.perf_counter(), time.process_time()
        state, stats = integ.implicit_euler(system, state, work.dt, pull, max_iterations=None,
                                            linear_solver=_direction(mode),
                                            cg_maxiter=cg_maxiter,
                                            cg_rtol=cg_rtol, warm_start=warm_start)
        seconds += time.perf_counter() - t
        cpu += time.process_time() - c
        totals["newton"] += stats.newton_iterations
        totals["factorizations"] += stats.factorizations
        totals["cg"] += stats.cg_iterations
        totals["psd_fallbacks"] += stats.psd_fallbacks
        totals["amg_setups"] += stats.amg_setups
        totals["halvings"] += stats.line_search_halvings
        totals["lagged"] += stats.lagged_matrices
        for part, sec in stats.seconds.items():
            parts[part] = parts.get(part, 0.0) + sec
        norms = stats.gradient_norms
        totals["final_gradient"] = max(totals["final_gradient"], norms[-1])
        # Newton also stops where the line search finds no decrease left (energy round-off)
        totals["stopped_at_round_off"] += norms[-1] > stats.gradient_tolerance
        trajectory.append(state.q)
    steps = len(work.pulls)
    return dict(totals, seconds_per_step=seconds / steps, cpu_seconds_per_step=cpu / steps,
                system_seconds=t_system,
                trajectory=trajectory,
                parts_per_step={k: v / steps for k, v in parts.items()})


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", choices=("arma", "box"), default="arma")
    parser.add_argument("--refine", default="0,1", help="armadillo refinement levels")
    parser.add_argument("--tets", type=float, default=2e4, help="box size")
    parser.add_argument("--steps", type=int, default=80)
    parser.add_argument("--swing", type=float, default=40.0, help="box velocity scale a")
    parser.add_argument("--modes", default="direct,reuse,amg",
                        help="comma-separated: direct, reuse, amg, petsc (PETSc's KSP in "
                             "one process: CG + GAMG on these sizes)")
    parser.add_argument("--cg-maxiter", type=int, default=16, help="reuse: CG budget per solve")
    parser.add_argument("--cg-rtol", type=float, default=1e-6, help="reuse: CG relative residual")
    parser.add_argument("--warm-start", default="previous", choices=WARM_STARTS,
                        help="Newton's start: previous (v_t), extrapolate (also 2 v_t - v_t-1)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per mode (best shown)")
    parser.add_argument("--jsonl", type=Path, help="append one JSON record per mode here")
    args = parser.parse_args(argv)
    modes = args.modes.split(",")
    if args.mesh == "arma":
        workloads = (lambda level=int(lv): armadillo(level, args.steps)
                     for lv in args.refine.split(","))
    else:
        workloads = (lambda: swinging_box(args.tets, args.steps, args.swing),)
    for make in workloads:
        start = time.perf_counter()
        work = make()
        print(f"{work.name}: {work.constraints.n_free} free DOFs, {len(work.pulls)} steps, "
              f"setup {time.perf_counter() - start:.1f} s", flush=True)
        p = iteration_pieces(work, modes)
        if "factorize" in p:
            total = p["assembly"] + p["factorize"] + p["solve"]
            print(f"  one Newton iteration: assembly {p['assembly'] * 1e3:.2f} ms, factorize "
                  f"{p['factorize'] * 1e3:.2f} ms (CHOLMOD {p['cholmod_mode']}), solve "
                  f"{p['solve'] * 1e3:.2f} ms = {total / p['factorize']:.2f}x the "
                  f"factorization; a factorization costs "
                  f"{p['factorize'] / (p['solve'] + p['matvec']):.0f} CG iterations", flush=True)
        if "amg_setup" in p:
            print(f"  AMG: assembly {p['assembly'] * 1e3:.2f} ms, hierarchy setup "
                  f"{p['amg_setup'] * 1e3:.2f} ms (levels {p['amg_levels']}), one V-cycle "
                  f"{p['vcycle'] * 1e3:.2f} ms, one mat-vec {p['matvec'] * 1e3:.2f} ms; a setup "
                  f"costs {p['amg_setup'] / (p['vcycle'] + p['matvec']):.0f} CG iterations"
                  + (f", a factorization {p['factorize'] / p['amg_setup']:.1f} setups"
                     if "factorize" in p else ""), flush=True)
        reference = None
        for mode in modes:
            best = min((run_mode(work, mode, args.cg_maxiter, args.cg_rtol, args.warm_start)
                        for _ in range(args.repeats)),
                       key=lambda r: r["seconds_per_step"])
            if reference is None:
                reference = best
            deviation = max(float(np.abs(a - b).max()) for a, b in
                            zip(best["trajectory"], reference["trajectory"], strict=True))
            speedup = reference["seconds_per_step"] / best["seconds_per_step"]
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
            print(f"  {mode:6s}: {best['seconds_per_step'] * 1e3:9.2f} ms/step (CPU "
                  f"{best['cpu_seconds_per_step'] * 1e3:.2f} ms), Newton "
                  f"{best['newton']}, factorizations {best['factorizations']}, CG "
                  f"{best['cg']}, PSD fallbacks {best['psd_fallbacks']}, max final |g| "
                  f"{best['final_gradient']:.1e} ({best['stopped_at_round_off']} steps "
                  f"stopped at round-off), max |q - q_{modes[0]}| / size "
                  f"{deviation / work.size:.1e}, {speedup:.2f}x {modes[0]}, peak RSS "
                  f"{rss:.2f} GiB", flush=True)
            parts = best["parts_per_step"]
            other = best["seconds_per_step"] - sum(parts.values())
            print("          per step: " + ", ".join(
                f"{k} {v * 1e3:.1f} ms" for k, v in sorted(parts.items()))
                + f", other {other * 1e3:.1f} ms; AMG setups {best['amg_setups']}, line-search "
                f"halvings {best['halvings']}, lagged Newton matrices {best['lagged']}; before "
                f"the steps: System (the solver's analysis) {best['system_seconds']:.2f} s",
                flush=True)
            if args.jsonl:
                record = {k: v for k, v in best.items() if k != "trajectory"}
                record |= dict(workload=work.name, mode=mode, cg_maxiter=args.cg_maxiter,
                               cg_rtol=args.cg_rtol, warm_start=args.warm_start,
                               speedup=speedup, deviation=deviation / work.size,
                               free_dofs=work.constraints.n_free, pieces=p)
                with args.jsonl.open("a") as f:
                    f.write(json.dumps(record) + "\n")
    if thread_report():
        print(thread_report(), flush=True)


if __name__ == "__main__":
    main()
