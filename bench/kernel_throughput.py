"""Throughput of the generated element kernels of every material, NumPy vs C, elements/s.

    python -m bench.kernel_throughput [--elements 100000] [--repeats 7] [--material NAME ...]
                                      [--backend numpy c] [--kernel energy gradient ...]
                                      [--element p1 p2]

Random well-shaped tets deformed by random gradients (fibre directions random); parameters
from ``E = 1e5, nu = 0.3`` through each material's mapping; median of repeats after one
warm-up, the materials timed in interleaved rounds. The last column is the ratio to
``neo_hookean`` (the assignment's material) measured in the same rounds, which is what to
compare on a shared machine. ``--element p2`` adds the quadratic tets' rows: the same tets
lifted to 10 nodes (edge midpoints, then moved by the same gradients plus node noise), each
P2 kernel timed in the same rounds as its P1 kernel; the last column there is the P2 time
per element over P1's. Not a test: figures depend on the machine (print them, never assert
them).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from fem3d.kernels.backend import c_extension
from fem3d.kernels.dispatch import geometry_kernels, kernel_module, material_kernels
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


def p2_elements(m: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x_e, dN_dX, w_detJ)`` for ``m`` random P2 tets: the tets of :func:`random_elements`
    with their edge midpoints, deformed the same way, plus node noise (curved edges)."""
    rng = np.random.default_rng(seed)
    X = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    X_e = X + 0.1 * rng.normal(size=(m, 4, 3))
    _, vol = geometry_kernels("numpy").rest_shape(X_e)
    keep = vol > 1e-3
    F = np.eye(3) + 0.1 * rng.normal(size=(m, 3, 3))
    edges = kernel_module("p2_tet", "numpy")._numpy.EDGES
    X10 = np.concatenate([X_e, np.stack([(X_e[:, a] + X_e[:, b]) / 2 for a, b in edges], 1)], 1)
    dN, _, w = kernel_module("p2_tet", "numpy").rest_shape(X10[keep])
    x10 = np.einsum("mij,mvj->mvi", F, X10) + 0.003 * rng.normal(size=X10.shape)
    return x10[keep], dN, w


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
    parser.add_argument("--element", nargs="+", default=["p1"], choices=("p1", "p2"),
                        help="p2: also time the quadratic tets' kernels against P1's")
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
    if "p2" in args.element:
        p2_rows(names, args.kernel, backends, args.elements, args.repeats, arguments)


def p2_rows(names: list[str], kernels: list[str], backends: list[str], elements: int,
            repeats: int, p1_arguments: dict) -> None:
    """Time each P2 kernel and its P1 kernel in interleaved rounds; print per-element rates
    and the P2 / P1 time per element."""
    x10, dN, w = p2_elements(elements)
    m2 = len(w)
    m1 = len(p1_arguments[names[0]][2])
    print(f"\nP2: {m2} elements ({dN.shape[1]} quadrature points), against P1 on {m1}; "
          f"median of {repeats}")
    print(f"{'material':<20} {'kernel':<12} {'backend':<6} {'ops':>7} {'P2 s':>8} "
          f"{'P2 el/s':>10} {'P1 el/s':>10} {'P2/P1 per element':>18}")
    for name in names:
        inputs, params = material_arguments(name, m2)
        p2_args = (x10, dN, w, *inputs, params)
        for kernel in kernels:
            for backend in backends:
                p2 = getattr(kernel_module(f"p2_{name}", backend), kernel)
                p1 = getattr(material_kernels(name, backend), kernel)
                calls = {"p1": (p1, p1_arguments[name]), "p2": (p2, p2_args)}
                times: dict[str, list[float]] = {"p1": [], "p2": []}
                for fn, a in calls.values():
                    fn(*a)  # warm-up
                for _ in range(repeats):
                    for key, (fn, a) in calls.items():
                        start = time.perf_counter()
                        fn(*a)
                        times[key].append(time.perf_counter() - start)
                t1, t2 = float(np.median(times["p1"])), float(np.median(times["p2"]))
                ops = kernel_module(f"p2_{name}", backend).SIGNATURES[kernel]["op_count"]
                ratio = (t2 / m2) / (t1 / m1)
                print(f"{name:<20} {kernel:<12} {backend:<6} {ops:>7} {t2:8.4f} {m2 / t2:10.3e} "
                      f"{m1 / t1:10.3e} {ratio:17.1f}x")


if __name__ == "__main__":
    main()
