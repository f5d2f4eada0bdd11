"""One vs two threads of the fused C assemblies (energy, gradient, CSR Hessian) on box meshes.

    python -m bench.assembly_threads [--sizes 1e5,1e6] [--repeats 5]

For each size and kernel, alternating in one process (the machine is shared): the serial loop
(no schedule: today's path, below ``fem3d.schedule.PARALLEL_MIN_TETS``), the scheduled loop
on one thread and on two. Prints the best wall time of ``--repeats`` calls and the CPU time
(``time.process_time``) of that call, the 2-thread speed-up over one thread and over the
serial loop, the schedule's blocks and colours, and the load average.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


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
    args = parser.parse_args(argv)

    from bench import BenchMesh
    from fem3d.kernels import c_extension
    from fem3d.model import build_model
    from fem3d.schedule import schedule_for

    ext = c_extension()
    if ext is None:
        raise SystemExit("the C extension is not built")
    print(f"OpenMP {bool(ext.OPENMP)}, max threads {ext.max_threads()}, "
          f"load {os.getloadavg()[0]:.2f}")
    print("| tets | kernel | serial ms | 1 thread ms (cpu) | 2 threads ms (cpu) | 1t/2t "
          "| serial/2t | blocks x colours |")
    print("| ---: | --- | ---: | ---: | ---: | ---: | ---: | --- |")
    for size in (float(s) for s in args.sizes.split(",")):
        mesh = BenchMesh.make(size)
        model = build_model(mesh.X, mesh.T, E=mesh.E, nu=mesh.nu, rho=mesh.rho, backend="c")
        q = mesh.q
        for kernel, index, n_out in (("energy", model.energy_slots, 1),
                                     ("gradient", model.dof_slots, model.n_dofs),
                                     ("hessian", model.scatter, model.nnz)):
            fused = getattr(ext, f"neo_hookean_{kernel}_assemble")
            schedule = schedule_for(model.T, index, n_out)
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
            for _ in range(args.repeats):  # alternate: load changes hit every variant alike
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
    print(f"\nload {os.getloadavg()}; `python -m bench.assembly_threads --sizes {args.sizes} "
          f"--repeats {args.repeats}`")


if __name__ == "__main__":
    main()
