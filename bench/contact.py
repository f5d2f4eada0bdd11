"""Backward Euler with IPC contact: steps per second and where the time goes.

    python -m bench.contact [--steps 150] [--refine 0 1] [--narrow-phase additive]
                            [--cases bunny_drop bunny_stack contact_stack contact_pile]
                            [--scene-steps 100] [--no-newton] [--markdown FILE]
                            [--line-search backtrack parabolic] [--newton-start clamped q_t]
                            [--cholmod auto|simplicial|supernodal]

``--line-search`` and ``--newton-start`` run each contact case once per value (issue 21's
opt-in Newton settings, ``simulation.newton.line_search`` and ``contact.newton_start``).

Cases: the coarse bunny (``data/coarser_bunny.mesh``, 1,518 tets) dropped on a ground plane,
bouncing and coming to rest, and a stack of two bunnies dropped onto each other and the
ground (3,036 tets); ``--refine k`` also runs each case on the mesh red-refined ``k`` times
(x8 tets per level: about 1.2e4 and 1e5 tets). Scene cases (``contact_*``, a name of
``data/scenes``) run the gallery scene as ``fem3d run`` steps it (``Simulation.step``) for its
first ``--scene-steps`` steps: ``contact_stack`` (three bodies, 1,902 tets) and
``contact_pile`` (13 bodies in an open box, 16,464 tets; ``python -m bench.tools.pile_check`` runs
it to rest and checks every frame). Every step is a full backward-Euler step as ``fem3d run``
takes it (Newton to IPC's velocity tolerance, CCD-clamped line search), one thread
(``OMP_NUM_THREADS=1`` is set here before NumPy loads).

Peer (unless ``--no-newton``): the same bunny drop in NVIDIA Newton's VBD solver on Warp's CPU
device (``bench/peers/newton_vbd.py``: 10 substeps x 10 iterations per 0.01 s frame, one frame
per fem3d step, vertex contact radius = fem3d's ``dhat``), its frames per second and lowest
vertex beside fem3d's; skipped with the reason when Newton is not installed or cannot run.

Time split (wall seconds summed over the run, from wrappers around the integrator's calls):
``ccd`` (continuous collision detection), ``contact`` (collision-set builds + barrier and
friction energy/gradient/Hessian), ``elastic`` (strain energy, gradient, Newton matrix
assembly incl. mass and inversion checks), ``pattern`` (adding the contact Hessian into the
solver pattern, re-analysis when new pairs appear), ``solve`` (factorizations + triangular
solves); ``other`` is the rest (Python, line search bookkeeping).
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def refine_red(X: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One level of red refinement (8 tets per tet; interior octahedron split along a
    diagonal); keeps orientation."""
    edges = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    e = np.sort(T[:, edges].reshape(-1, 2), axis=1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    mid = X.shape[0] + inv.reshape(-1, 6)
    Xn = np.vstack([X, 0.5 * (X[uniq[:, 0]] + X[uniq[:, 1]])])
    v0, v1, v2, v3 = T.T
    m01, m02, m03, m12, m13, m23 = mid.T
    tets = [
        [v0, m01, m02, m03], [m01, v1, m12, m13], [m02, m12, v2, m23], [m03, m13, m23, v3],
        [m01, m02, m03, m13], [m01, m02, m13, m12], [m02, m03, m13, m23],
        [m02, m12, m13, m23],
    ]
    Tn = np.concatenate([np.stack(t, axis=1) for t in tets])
    # fix orientation where the split made a tet negative
    d = Xn[Tn[:, 1:]] - Xn[Tn[:, :1]]
    neg = np.linalg.det(d) < 0
    Tn[neg, 2], Tn[neg, 3] = Tn[neg, 3].copy(), Tn[neg, 2].copy()
    return Xn, Tn


class Timers:
    """Wall time per category, from wrappers installed on module attributes."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self._undo: list = []

    def wrap(self, owner, name: str, category: str) -> None:
        fn = getattr(owner, name)

        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                self.seconds[category] += time.perf_counter() - t0

        setattr(owner, name, timed)
        self._undo.append((owner, name, fn))

    def restore(self) -> None:
        for owner, name, fn in reversed(self._undo):
            setattr(owner, name, fn)
        self._undo.clear()


def build_case(name: str, refine: int, narrow_phase: str, newton_start: str = "clamped",
               cholmod: str | None = None):
    """(model, system, contact term, initial state, dt) of a case (``cholmod``: CHOLMOD's
    factorization, None: its own rule)."""
    from fem3d.mesh.formats import read_tet_mesh
    from fem3d.physics.constraints import Constraints
    from fem3d.physics.contact import ContactModel, PlaneObstacle
    from fem3d.physics.model import build_model
    from fem3d.physics.terms.contact import ContactTerm
    from fem3d.scene.build import build_loads
    from fem3d.solve.integrators import State, System

    m = read_tet_mesh(ROOT / "data" / "coarser_bunny.mesh")
    X0, T0 = m.X, m.T
    for _ in range(refine):
        X0, T0 = refine_red(X0, T0)
    # 165 units tall -> 0.33 m; lowest point 0.05 m above the ground
    X0 = (X0 - X0.mean(axis=0)) * 0.002
    X0[:, 1] += 0.05 - X0[:, 1].min()
    if name == "bunny_drop":
        X, T, ids = X0, T0, np.zeros(len(X0), dtype=np.int64)
    elif name == "bunny_stack":
        top = X0 + np.array([0.05, X0[:, 1].max() - X0[:, 1].min() + 0.02, 0.02])
        X = np.vstack([X0, top])
        T = np.vstack([T0, T0 + len(X0)])
        ids = np.r_[np.zeros(len(X0), np.int64), np.ones(len(X0), np.int64)]
    else:
        raise ValueError(name)
    model = build_model(X, T, E=2e5, nu=0.4, rho=1000.0)
    system = System(model, Constraints.from_fixed_vertices(X, np.zeros(0, np.int64)),
                    loads=build_loads(model, [0.0, -9.81, 0.0]), cholmod_mode=cholmod or "auto")
    L = float(np.linalg.norm(np.ptp(X, axis=0)))
    cm = ContactModel(X, T, body_ids=ids, planes=[PlaneObstacle([0, 0, 0], [0, 1, 0])],
                      dhat=1e-3 * L, mu=0.3, eps_v=1e-3 * L, narrow_phase=narrow_phase)
    term = ContactTerm(cm, tolerance=1e-2, newton_start=newton_start)
    return model, system, term, State.at_rest(model), 0.01


def _install_timers() -> Timers:
    import fem3d.physics.terms.elasticity as elasticity
    import fem3d.solve.integrators as integ
    from fem3d.physics.contact import ContactModel
    from fem3d.solve.linear.krylov import PreconditionedCG
    from fem3d.solve.newton_matrix import NewtonMatrixBuilder

    timers = Timers()
    timers.wrap(elasticity, "assemble_gradient", "elastic")
    timers.wrap(elasticity, "potential_energy", "elastic")
    timers.wrap(elasticity, "count_inverted", "elastic")
    timers.wrap(NewtonMatrixBuilder, "add_elements", "elastic")
    timers.wrap(integ.System, "add_hessian", "pattern")
    timers.wrap(integ.System, "factorize", "solve")
    timers.wrap(integ.System, "solve", "solve")
    timers.wrap(PreconditionedCG, "solve", "solve")
    timers.wrap(ContactModel, "max_step", "ccd")
    timers.wrap(ContactModel, "obstacle_step", "ccd")
    for fn in ("barrier_energy", "barrier_gradient", "barrier_hessian", "friction_energy",
               "friction_gradient", "friction_hessian", "lag_friction", "n_active",
               "minimum_distance", "initialize_stiffness"):
        timers.wrap(ContactModel, fn, "contact")
    return timers


def _label(newton_solver: str, line_search: str, newton_start: str = "clamped",
           cholmod: str | None = None) -> str:
    tags = [t for t, default in ((newton_solver, "direct"), (line_search, "backtrack"),
                                 (newton_start, "clamped"), (cholmod, None)) if t != default]
    return f" [{', '.join(tags)}]" if tags else ""


def run_case(name: str, refine: int, steps: int, narrow_phase: str,
             newton_solver: str = "direct", contact: bool = True,
             line_search: str = "backtrack", newton_start: str = "clamped",
             cholmod: str | None = None) -> dict:
    import fem3d.solve.integrators as integ

    model, system, term, state, dt = build_case(name, refine, narrow_phase, newton_start,
                                                cholmod)
    timers = _install_timers()
    newton = factorizations = halvings = 0
    terms = [term] if contact else []
    generations0 = getattr(system, "pattern_generation", 0)
    lowest = np.inf
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        for _ in range(steps):
            state, stats = integ.implicit_euler(system, state, dt, terms=terms,
                                                linear_solver=newton_solver,
                                                line_search=line_search)
            newton += stats.newton_iterations
            factorizations += stats.factorizations
            halvings += stats.line_search_halvings
            lowest = min(lowest, float(state.q[:, 1].min()))
    finally:
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        timers.restore()
    sec = dict(timers.seconds)
    # nested calls: CCD inside contact wrappers never happens; elastic includes none of these
    sec["other"] = wall - sum(sec.values())
    return {
        "case": name + ("" if contact else " (no contact)") + _label(
            newton_solver, line_search, newton_start, cholmod),
        "tets": model.n_tets, "factorizations_per_step": factorizations / steps,
        "halvings_per_step": halvings / steps, "cpu": cpu,
        "steps": steps, "wall": wall,
        "steps_per_s": steps / wall, "newton_per_step": newton / steps,
        "pattern_reanalyses": getattr(system, "pattern_generation", 0) - generations0,
        "lowest_gap": lowest, "seconds": sec,
    }


def run_scene_case(name: str, steps: int, newton_solver: str = "direct",
                   line_search: str = "backtrack", newton_start: str = "clamped",
                   cholmod: str | None = None) -> dict:
    """A gallery scene (``data/scenes/<name>.toml``) stepped as ``fem3d run`` steps it
    (``cholmod``: overrides the scene's ``simulation.cholmod``)."""
    from fem3d.scene import load_scene
    from fem3d.simulation import Simulation

    overrides = {} if newton_solver == "direct" else {"simulation.newton.solver": newton_solver}
    if line_search != "backtrack":
        overrides["simulation.newton.line_search"] = line_search
    if newton_start != "clamped":
        overrides["contact.newton_start"] = newton_start
    if cholmod is not None:
        overrides["simulation.cholmod"] = cholmod
    sim = Simulation(load_scene(name, overrides))
    timers = _install_timers()
    newton = factorizations = cg = halvings = 0
    generations0 = sim.system.pattern_generation
    analyses0 = getattr(sim.system, "analyses", 0)
    lowest = np.inf
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        for _ in range(steps):
            sim.step()
            newton += sim.last_stats.newton_iterations
            factorizations += sim.last_stats.factorizations
            cg += sim.last_stats.cg_iterations
            halvings += sim.last_stats.line_search_halvings
            lowest = min(lowest, float(sim.q[:, 1].min()))
    finally:
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        timers.restore()
    sec = dict(timers.seconds)
    sec["other"] = wall - sum(sec.values())
    return {
        "case": name + _label(newton_solver, line_search, newton_start, cholmod),
        "tets": sim.model.n_tets, "factorizations_per_step": factorizations / steps,
        "halvings_per_step": halvings / steps, "cpu": cpu,
        "steps": steps, "wall": wall, "steps_per_s": steps / wall,
        "newton_per_step": newton / steps,
        "pattern_reanalyses": sim.system.pattern_generation - generations0,
        "analyses": getattr(sim.system, "analyses", 0) - analyses0,
        "cg_per_step": cg / steps,
        "lowest_gap": lowest, "seconds": sec,
    }


def run_newton_peer(steps: int) -> dict:
    """The bunny drop of :func:`build_case` in Newton's VBD (CPU), or a skipped row."""
    from bench import Skip
    from bench.peers import newton_vbd

    model, _system, term, state, dt = build_case("bunny_drop", 0, "additive")
    try:
        return newton_vbd.drop(model.X, model.T, steps=steps, dt=dt, E=2e5, nu=0.4,
                               rho=1000.0, mu=0.3, particle_radius=term.contact.dhat)
    except Skip as why:
        return {"case": f"bunny_drop [{newton_vbd.LIB}]", "tets": model.n_tets,
                "skipped": str(why)}


def _print_row(r: dict) -> None:
    if "skipped" in r:
        print(f"{r['case']:28s} {r['tets']:7d} tets  skipped: {r['skipped']}", flush=True)
        return
    s = r.get("seconds")
    split = "  ".join(f"{k} {v / r['wall']:.0%}" for k, v in sorted(s.items())) if s else (
        f"Warp kernels compiled in the warm-up frame ({r['compile_s']:.1f} s, untimed); "
        f"vertex contact radius {r['particle_radius']:.2e} m")
    fem = "" if s is None else (
        f"{r['newton_per_step']:.2f} Newton/step {r['factorizations_per_step']:.2f} fact/step  "
        f"{r['halvings_per_step']:.2f} halvings/step  {r['steps'] / r['cpu']:.2f} steps/s CPU  "
        f"re-analyses {r['pattern_reanalyses']}  ")
    if "analyses" in r:  # the scene cases: CHOLMOD analyses, CG iterations, CPU time
        fem += f"(analyses {r['analyses']}, CG/step {r['cg_per_step']:.1f})  "
    print(f"{r['case']:28s} {r['tets']:7d} tets {r['steps']:4d} steps "
          f"{r['steps_per_s']:7.2f} steps/s  {fem}min y {r['lowest_gap']:.2e} | {split}",
          flush=True)


def _markdown_row(r: dict) -> str:
    if "skipped" in r:
        return f"| {r['case']} | {r['tets']:,} | skipped: {r['skipped']} |" + " |" * 10
    s = r.get("seconds")
    if s is None:  # the peer: no fem3d breakdown
        return (f"| {r['case']} | {r['tets']:,} | {r['steps_per_s']:.2f} | "
                f"{r['lowest_gap'] * 1e3:.3f} |" + " |" * 9)
    pct = [f"{s.get(k, 0.0) / r['wall']:.0%}" for k in
           ("ccd", "contact", "elastic", "pattern", "solve", "other")]
    return (f"| {r['case']} | {r['tets']:,} | {r['steps_per_s']:.2f} | "
            f"{r['lowest_gap'] * 1e3:.3f} | {r['newton_per_step']:.2f} | "
            f"{r['factorizations_per_step']:.2f} | {r['pattern_reanalyses']} | "
            + " | ".join(pct) + " |")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--refine", type=int, nargs="*", default=[0])
    ap.add_argument("--cases", nargs="*",
                    default=["bunny_drop", "bunny_stack", "contact_stack", "contact_pile"])
    ap.add_argument("--scene-steps", type=int, default=100,
                    help="steps of the scene cases (contact_*)")
    ap.add_argument("--no-newton", action="store_true",
                    help="skip the Newton (VBD, CPU) peer of the bunny drop")
    ap.add_argument("--narrow-phase", default="additive")
    ap.add_argument("--newton-solver", nargs="*", default=["direct", "reuse"])
    ap.add_argument("--line-search", nargs="*", default=["backtrack"],
                    help="Newton's line searches to run (backtrack, parabolic), one row each")
    ap.add_argument("--newton-start", nargs="*", default=["clamped"],
                    help="contact.newton_start values to run (clamped, q_t), one row each")
    ap.add_argument("--cholmod", choices=["auto", "simplicial", "supernodal"],
                    help="CHOLMOD's factorization in every case (default: the case's own, "
                         "simulation.cholmod of a scene)")
    ap.add_argument("--no-peer", action="store_true",
                    help="skip the contact-free peer row (same mesh, free fall)")
    ap.add_argument("--markdown", type=Path)
    args = ap.parse_args(argv)
    rows = []
    for case in (c for c in args.cases if c.startswith("contact_")):
        for solver in args.newton_solver:
            for search in args.line_search:
                for start in args.newton_start:
                    rows.append(run_scene_case(case, args.scene_steps, solver, search, start,
                                               args.cholmod))
                    _print_row(rows[-1])
    for refine in args.refine:
        for case in (c for c in args.cases if not c.startswith("contact_")):
            steps = args.steps if refine == 0 else max(3, args.steps // (8 ** refine))
            runs = [(s, True) for s in args.newton_solver]
            if not args.no_peer and case == "bunny_drop":
                runs.append(("direct", False))
            for solver, contact in runs:
                for search in (args.line_search if contact else ["backtrack"]):
                    for start in (args.newton_start if contact else ["clamped"]):
                        rows.append(run_case(case, refine, steps, args.narrow_phase, solver,
                                             contact, search, start, args.cholmod))
                        _print_row(rows[-1])
            if case == "bunny_drop" and refine == 0 and not args.no_newton:
                rows.append(run_newton_peer(steps))
                _print_row(rows[-1])
    if args.markdown:
        lines = ["| case | tets | steps/s | lowest vertex (mm) | Newton/step | "
                 "factorizations/step | re-analyses | ccd | contact | elastic | pattern | solve "
                 "| other |",
                 "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: "
                 "| ---: | ---: |"]
        lines += [_markdown_row(r) for r in rows]
        args.markdown.write_text("\n".join(lines) + "\n")

if __name__ == "__main__":
    main()
