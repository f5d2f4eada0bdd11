"""Throughput of the generated element kernels, NumPy vs C, in elements per second.

    python -m bench.kernel_throughput [--elements 100000] [--repeats 7] [--material neo_hookean]

Random well-shaped tets deformed by random gradients; median of repeats after one warm-up.
Not a test: figures depend on the machine (print them, never assert them).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from fem3d.kernels import c_extension, geometry_kernels, material_kernels

KERNELS = ("energy", "gradient", "hessian", "hessian_psd")


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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--elements", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--material", default="neo_hookean")
    args = parser.parse_args(argv)
    x_e, dphi, vol = random_elements(args.elements)
    m = len(vol)
    params = {"neo_hookean": (1.0e5, 5.0e5), "stvk": (2.0e5, 1.0e6)}.get(args.material, (1.0, 1.0))
    backends = ["numpy"] + (["c"] if c_extension() is not None else [])
    threads = c_extension().max_threads() if c_extension() is not None else 1
    print(f"{args.material}, {m} elements, median of {args.repeats}; "
          f"C threads {threads} (OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')})")
    print(f"{'kernel':<12} {'backend':<6} {'seconds':>9} {'elements/s':>12}")
    for kernel in KERNELS:
        for backend in backends:
            function = getattr(material_kernels(args.material, backend), kernel)
            function(x_e, dphi, vol, params)
            times = []
            for _ in range(args.repeats):
                start = time.perf_counter()
                function(x_e, dphi, vol, params)
                times.append(time.perf_counter() - start)
            t = float(np.median(times))
            print(f"{kernel:<12} {backend:<6} {t:9.4f} {m / t:12.3e}")


if __name__ == "__main__":
    main()
