"""One vs two threads of the fused C assemblies (energy, gradient, CSR Hessian) on box meshes.

    python -m bench.assembly_threads [--sizes 1e5,1e6] [--repeats 5] [--below-threshold]
                                     [--wait-idle 20]

For each size and kernel, alternating in one process (the machine is shared): the serial loop
(no schedule: today's path, below ``fem3d.kernels.schedule.PARALLEL_MIN_TETS``), the scheduled loop
on one thread and on two (``--below-threshold``: scheduled below the threshold too, to see
where it should lie). Prints the best wall time of ``--repeats`` calls and the CPU time
(``time.process_time``) of that call, the 2-thread speed-up over one thread and over the
serial loop, the schedule's blocks and colours, and the load average. ``--wait-idle PCT``
starts each round of calls only once the machine's CPUs were busy less than PCT percent over
half a second (other work paused; at most a minute's wait), and counts the rounds that waited
in vain.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def _busy_percent(seconds: float = 0.5) -> float:
    """Percentage of the machine's CPU time spent busy over ``seconds`` (Linux /proc/stat)."""

    def sample() -> tuple[int, int]:
        with open("/proc/stat") as f:
            values = [int(v) for v in f.readline().split()[1:]]
        return sum(values), values[3] + values[4]  # total, idle + iowait

    total0, idle0 = sample()
    time.sleep(seconds)
    total1, idle1 = sample()
    return 100.0 * (1.0 - (idle1 - idle0) / max(total1 - total0, 1))


def _wait_idle(percent: float | None, limit_s: float = 60.0) -> bool:
    """Wait until the CPUs are less than ``percent`` busy; False when ``limit_s`` passed."""
    if percent is None:
        return True
    start = time.perf_counter()
    while time.perf_counter() - start < limit_s:
        if _busy_percent() < percent:
            return True
    return False


def _best(fn, repeats: int) -> tuple[float, float]:
    best = (float("inf"), 0.0)
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        fn()
        w, c = time.perf_counter() - w, time.process_time() - c
        best = min(best, (w, c))
    return best


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1e5,1e6")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--below-threshold", action="store_true",
                        help="build schedules below fem3d.kernels.schedule.PARALLEL_MIN_TETS too")
    parser.add_argument("--wait-idle", type=float, default=None, metavar="PCT",
                        help="start each round once the CPUs are less than PCT%% busy")
    args = parser.parse_args(argv)

    from bench import BenchMesh
    from fem3d.kernels.backend import c_extension
    from fem3d.kernels.schedule import build_schedule, schedule_for
    from fem3d.physics.model import build_model

    ext = c_extension()
    if ext is None:
        raise SystemExit("the C extension is not built")
    print(f"OpenMP {bool(ext.OPENMP)}, max threads {ext.max_threads()}, "
          f"load {os.getloadavg()[0]:.2f}")
    print("| tets | kernel | serial ms | 1 thread ms (cpu) | 2 threads ms (cpu) | 1t/2t "
          "| serial/2t | blocks x colours |")
    print("| ---: | --- | ---: | ---: | ---: | ---: | ---: | --- |")
    busy_rounds = 0
    for size in (float(s) for s in args.sizes.split(",")):
        mesh = BenchMesh.make(size)
        model = build_model(mesh.X, mesh.T, E=mesh.E, nu=mesh.nu, rho=mesh.rho, backend="c")
        q = mesh.q
        for kernel, index, n_out in (("energy", model.energy_slots, 1),
                                     ("gradient", model.dof_slots, model.n_dofs),
                                     ("hessian", model.scatter, model.nnz)):
            fused = getattr(ext, f"neo_hookean_{kernel}_assemble")
            schedule = build_schedule(model.T, index, n_out, min_tets=0) \
                if args.below_threshold else schedule_for(model.T, index, n_out)
            out = np.zeros(n_out)
            base = (q, model.T, model.dphi_dX, model.vol, model.params, index, out)
            sched = schedule.arrays() if schedule is not None else ()

            def serial(base=base, fused=fused, out=out):
                out[:] = 0.0
                fused(*base)

            def threaded(base=base, fused=fused, out=out, sched=sched):
                out[:] = 0.0
                fused(*base, *sched)

            times = {"serial": [], 1: [], 2: []}
            serial()  # warm up (page faults of out)
            threaded()
            for _ in range(args.repeats):  # alternate: load changes hit every variant alike
                if not _wait_idle(args.wait_idle):
                    busy_rounds += 1
                ext.set_max_threads(1)
                times["serial"].append(_best(serial, 1))
                times[1].append(_best(threaded, 1))
                ext.set_max_threads(2)
                times[2].append(_best(threaded, 1))
            s, one, two = (min(times[k]) for k in ("serial", 1, 2))
            shape = f"{schedule.n_blocks} x {schedule.n_colours}" if schedule else "serial"
            print(f"| {model.n_tets} | {kernel} | {s[0] * 1e3:.2f} | {one[0] * 1e3:.2f} "
                  f"({one[1] * 1e3:.1f}) | {two[0] * 1e3:.2f} ({two[1] * 1e3:.1f}) | "
                  f"{one[0] / two[0]:.2f} | {s[0] / two[0]:.2f} | {shape} |", flush=True)
        ext.set_max_threads(2)
        del model, mesh
    waited = f", {busy_rounds} round(s) found no idle moment" if args.wait_idle else ""
    print(f"\nload {os.getloadavg()}{waited}; `python -m bench.assembly_threads "
          f"--sizes {args.sizes} --repeats {args.repeats}"
          f"{' --below-threshold' if args.below_threshold else ''}"
          f"{f' --wait-idle {args.wait_idle:g}' if args.wait_idle else ''}`")


if __name__ == "__main__":
    main()
