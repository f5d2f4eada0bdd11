"""P1 against P2 tetrahedra: the figures of docs/elements.md.

``python -m bench.elements`` prints the cantilever of docs/scenes.md ("Check against theory":
1 x 0.1 x 0.1, StVK, nu = 0, E = 1e9, static under gravity) against Euler-Bernoulli for P1 and
P2 meshes, with DOFs and wall time of the static solve; ``--cells 10x1x1,20x2x2`` chooses the
meshes and ``--elements p2`` the elements. Nothing here is run by CI
(tests/physics/test_p2.py checks the bounds).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parent.parent
E, RHO, G, L, H = 1e9, 1000.0, 9.81, 1.0, 0.1
#: Euler-Bernoulli tip deflection of the beam under its own weight, ``q L^4 / (8 E I)``.
EULER_BERNOULLI = 1.5 * RHO * G * L ** 4 / (E * H ** 2)


def _box_mesh():
    spec = importlib.util.spec_from_file_location("make_gallery",
                                                  ROOT / "examples" / "make_gallery.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.box_mesh


def cantilever(cells: tuple[int, int, int], element: str, folder: Path,
               nu: float = 0.0) -> dict:
    """The static tip deflection of the cantilever on a ``cells`` mesh of ``element``: the
    mean y displacement of the nodes at x = L, its ratio to Euler-Bernoulli, DOFs and the
    seconds of the model build and of the static step (``nu`` > 0: the clamp's Poisson
    stiffening and, near 0.5, volume locking)."""
    from fem3d.mesh.formats import write_tet_mesh
    from fem3d.mesh.tetmesh import TetMesh
    from fem3d.scene import load_scene
    from fem3d.simulation import Simulation

    X, T = _box_mesh()(cells, (L, H, H))
    mesh = folder / f"beam_{'x'.join(map(str, cells))}.mesh"
    write_tet_mesh(mesh, TetMesh(X, T))
    scene = load_scene("cantilever", {
        "bodies[0].mesh": str(mesh), "bodies[0].material.E": E, "bodies[0].material.nu": nu,
        "bodies[0].damping.rayleigh_stiffness": 0.0, "simulation.integrator": "static",
        "simulation.steps": 1, "bodies[0].element": element})
    t0 = time.perf_counter()
    sim = Simulation(scene)
    t1 = time.perf_counter()
    sim.step()
    t2 = time.perf_counter()
    Xn = sim.model.X
    tip = np.flatnonzero(np.isclose(Xn[:, 0], L))
    delta = float(-(sim.q[tip, 1] - Xn[tip, 1]).mean())
    return {"cells": "x".join(map(str, cells)), "element": element, "tets": sim.model.n_tets,
            "dofs": sim.model.n_dofs, "delta": delta, "ratio": delta / EULER_BERNOULLI,
            "build_s": t1 - t0, "step_s": t2 - t1}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cells", default="10x1x1,20x2x2,40x4x4,60x6x6")
    parser.add_argument("--elements", default="p1,p2")
    parser.add_argument("--nu", type=float, default=0.0, help="Poisson's ratio (default 0)")
    args = parser.parse_args(argv)
    print(f"Euler-Bernoulli tip deflection {EULER_BERNOULLI:.5e} m (nu = {args.nu:g})")
    print("| element | cells | tets | DOFs | tip / EB | build (ms) | static step (ms) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        for element in args.elements.split(","):
            for c in args.cells.split(","):
                cells = tuple(int(k) for k in c.split("x"))
                r = cantilever(cells, element, Path(tmp), args.nu)
                print(f"| {r['element']} | {r['cells']} | {r['tets']} | {r['dofs']} | "
                      f"{r['ratio']:.4f} | {1e3 * r['build_s']:.0f} | {1e3 * r['step_s']:.0f} |",
                      flush=True)


if __name__ == "__main__":
    main()
