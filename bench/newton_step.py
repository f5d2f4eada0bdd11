"""One backward-Euler step of a clamped box: Newton iteration cost, factorization reuse, memory.

    python -m bench.newton_step --tets 2e4 --steps 6            # direct vs reuse, per-step medians
    python -m bench.newton_step --tets 1e6 --steps 1 --modes direct   # the 1e6-tet step

The box (``bench.meshes.box_mesh``) is clamped at its lowest z and starts at rest with a
swinging velocity ``v = (a z^2, -b x z, 0)``. Prints the pieces of one Newton iteration
(assembly + reduction, factorization, solve), then per mode the median step time, Newton
iterations, factorizations, CG iterations, final gradient norm and peak RSS.
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from bench.meshes import box_mesh
from fem3d import integrators as integ
from fem3d.assembly import hessian_data
from fem3d.constraints import Constraints
from fem3d.model import build_model


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=float, default=2e4)
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--swing", type=float, default=40.0, help="velocity scale a (b = 0.75 a)")
    parser.add_argument("--modes", default="direct,reuse")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    X, T = box_mesh(args.tets)
    model = build_model(X, T, E=6e5, nu=0.4, rho=0.1)
    fixed = np.flatnonzero(X[:, 2] <= X[:, 2].min() + 1e-12)
    constraints = Constraints.from_fixed_vertices(X, fixed)
    system = integ.System(model, constraints)
    print(f"{len(T)} tets, {constraints.free_dofs.size} free DOFs, "
          f"setup {time.perf_counter() - start:.1f} s", flush=True)
    v0 = np.zeros_like(X)
    v0[:, 0] = args.swing * X[:, 2] ** 2
    v0[:, 1] = -0.75 * args.swing * X[:, 2] * X[:, 0]
    v0[fixed] = 0.0

    q = X + 0.01 * v0
    system.reduced(model.mass.data + hessian_data(model, q))  # warm-up: one-time scatter order
    t = time.perf_counter()
    A_free = system.reduced(model.mass.data + 1e-4 * hessian_data(model, q))
    t_assembly = time.perf_counter() - t
    t = time.perf_counter()
    system.factorize(A_free)
    t_factor = time.perf_counter() - t
    t = time.perf_counter()
    system.solve(np.ones(A_free.shape[0]))
    t_solve = time.perf_counter() - t
    total = t_assembly + t_factor + t_solve
    print(f"one Newton iteration: assembly+reduce {t_assembly:.3f} s, factorize {t_factor:.3f} s,"
          f" solve {t_solve:.3f} s = {total / t_factor:.2f}x the factorization", flush=True)

    for mode in args.modes.split(","):
        state = integ.State(q=X.copy(), v=v0.copy())
        fresh = integ.System(model, constraints)
        times, iterations, factorizations, cg = [], 0, 0, 0
        for _ in range(args.steps):
            t = time.perf_counter()
            state, stats = integ.implicit_euler(fresh, state, 0.01, linear_solver=mode)
            times.append(time.perf_counter() - t)
            iterations += stats.newton_iterations
            factorizations += stats.factorizations
            cg += stats.cg_iterations
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
        print(f"{mode:6s}: median step {np.median(times):.3f} s over {args.steps}, Newton "
              f"iterations {iterations}, factorizations {factorizations}, CG iterations {cg}, "
              f"final |g| {stats.gradient_norms[-1]:.2e}, peak RSS {rss:.2f} GiB", flush=True)


if __name__ == "__main__":
    main()
