"""Throughput of the generated element kernels of every material, NumPy vs C, elements/s.

    python -m bench.kernel_throughput [--elements 100000] [--repeats 7] [--material NAME ...]
                                      [--backend numpy c] [--kernel energy gradient ...]

Random well-shaped tets deformed by random gradients (fibre directions random); parameters
from ``E = 1e5, nu = 0.3`` through each material's mapping; median of repeats after one
warm-up, the materials timed in interleaved rounds. The last column is the ratio to
``neo_hookean`` (the assignment's material) measured in the same rounds, which is what to
compare on a shared machine. Not a test: figures depend on
the machine (print them, never assert them).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from fem3d.kernels.backend import c_extension
from fem3d.kernels.dispatch import geometry_kernels, material_kernels
from fem3d.physics import materials

KERNELS = ("energy", "gradient", "hessian", "hessian_psd")
REFERENCE = "neo_hookean"


def random_elements(m: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x_e, dphi_dX, vol)`` for ``m`` random tets, moderately deformed."""
    rng = np.random.default_rng(seed)
    X = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    X_e = X + 0.1 * rng.normal(size=(m, 4, 3))
    dphi, vol = geometry_kernels("numpy").rest_shape(X_e)
    keep = vol > 1e-3
    F = np.eye(3) + 0.1 * rng.normal(size=(m, 3, 3))
    x_e = np.einsum("mij,mvj->mvi", F, X_e)
    return x_e[keep], dphi[keep], vol[keep]


def material_arguments(name: str, m: int, seed: int = 1) -> tuple[list[np.ndarray], np.ndarray]:
    """The material's per-element inputs (random) and its parameters of ``E = 1e5, nu = 0.3``."""
    info = materials.info(name)
    rng = np.random.default_rng(seed)
    inputs = [rng.normal(size=(m, *shape)) for shape in info.per_element_inputs.values()]
    values = materials.parameters_from(name, E=1e5, nu=0.3)
    return inputs, np.array([values[p] for p in info.param_names])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--elements", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--material", nargs="+", default=None,
                        help="materials to measure (default: every registered one)")
    parser.add_argument("--backend", nargs="+", default=None, choices=("numpy", "c"))
    parser.add_argument("--kernel", nargs="+", default=list(KERNELS), choices=KERNELS)
    args = parser.parse_args(argv)
    # the reference first: every other row's ratio is against it
    names = [REFERENCE, *(n for n in args.material or materials.names() if n != REFERENCE)]
    x_e, dphi, vol = random_elements(args.elements)
    m = len(vol)
    backends = args.backend or (["numpy"] + (["c"] if c_extension() is not None else []))
    threads = c_extension().max_threads() if c_extension() is not None else 1
    print(f"{m} elements, median of {args.repeats}; C threads {threads} "
          f"(OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')})")
    print(f"{'material':<20} {'kernel':<12} {'backend':<6} {'ops':>6} {'seconds':>9} "
          f"{'elements/s':>12} {'vs ' + REFERENCE:>15}")
    arguments = {}
    for name in names:
        inputs, params = material_arguments(name, m)
        arguments[name] = (x_e, dphi, vol, *inputs, params)
    rows = {}
    for kernel in args.kernel:
        for backend in backends:
            functions = {n: getattr(material_kernels(n, backend), kernel) for n in names}
            times: dict[str, list[float]] = {n: [] for n in names}
            for n in names:  # warm-up
                functions[n](*arguments[n])
            # interleaved: each round times every material once, so that the load of a shared
            # machine changes the ratios less than it changes the figures
            for _ in range(args.repeats):
                for n in names:
                    start = time.perf_counter()
                    functions[n](*arguments[n])
                    times[n].append(time.perf_counter() - start)
            for n in names:
                rows[(n, kernel, backend)] = float(np.median(times[n]))
    for name in names:
        for kernel in args.kernel:
            for backend in backends:
                t = rows[(name, kernel, backend)]
                ratio = rows[(REFERENCE, kernel, backend)] / t
                ops = material_kernels(name, backend).SIGNATURES[kernel]["op_count"]
                print(f"{name:<20} {kernel:<12} {backend:<6} {ops:>6} {t:9.4f} {m / t:12.3e} "
                      f"{ratio:14.2f}x")


if __name__ == "__main__":
    main()
