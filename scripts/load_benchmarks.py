"""The load benchmarks of docs/loads.md: Cook's membrane on a mesh sequence and Lame's
thick-walled sphere (octant and whole), from the scenes in data/scenes/.

    python scripts/load_benchmarks.py            # prints the tables, writes the figure
    python scripts/load_benchmarks.py --quick    # without the two largest meshes
    python scripts/load_benchmarks.py --plane-stress   # Cook's membrane in 2-D plane stress,
                                                       # P2 triangles (scikit-fem): a check

Writes docs/figures/cook_convergence.png (the corner's vertical displacement against the
mesh size, with the published 23.96).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from fem3d.scene import load_scene
from fem3d.simulation import Simulation

ROOT = Path(__file__).resolve().parent.parent
COOK_REFERENCE = 23.96
A, B, E, NU, P = 1.0, 2.0, 1000.0, 0.3, 1.0


def lame_u(r: np.ndarray) -> np.ndarray:
    """Lame's radial displacement of the sphere ``A <= r <= B`` under internal pressure."""
    return P * A**3 * r / (E * (B**3 - A**3)) * ((1 - 2 * NU) + (1 + NU) * B**3 / (2 * r**3))


def solve(name: str, mesh: str | None = None) -> tuple[Simulation, float]:
    """One static step of scene ``name`` (on ``mesh``); the simulation and its seconds."""
    sim = Simulation(load_scene(name, {"bodies[0].mesh": mesh} if mesh else None))
    t0 = time.perf_counter()
    sim.step()
    return sim, time.perf_counter() - t0


def cook(sizes) -> list[tuple[int, int, float, float]]:
    """``(n, tets, corner v, seconds)`` per mesh ``cook_<n>``."""
    rows = []
    for n in sizes:
        sim, sec = solve("cook_membrane", f"meshes/cook_{n}.mesh")
        X = sim.model.X
        corner = np.flatnonzero((np.abs(X[:, 0] - 48) < 1e-9) & (np.abs(X[:, 1] - 60) < 1e-9))
        rows.append((n, sim.model.n_tets, float((sim.q - X)[corner, 1].mean()), sec))
    return rows


def lame(sim: Simulation) -> tuple[float, float, float]:
    """Relative errors of the radial displacement: mean over the inner surface, mean over
    the outer surface, and the worst vertex."""
    X = sim.model.X
    r = np.linalg.norm(X, axis=1)
    ur = np.einsum("ij,ij->i", sim.q - X, X) / r
    rel = ur / lame_u(r) - 1.0
    inner, outer = np.abs(r - A) < 1e-6, np.abs(r - B) < 1e-6
    return float(rel[inner].mean()), float(rel[outer].mean()), float(rel[np.abs(rel).argmax()])


def cook_plane_stress_p2(n: int) -> float:
    """The corner's vertical displacement of Cook's membrane in 2-D plane stress on ``n x n``
    quadratic triangles by scikit-fem (independent of fem3d: an optional check)."""
    import skfem
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    lam, mu = lame_parameters(1.0, 1.0 / 3.0)
    m = skfem.MeshTri.init_tensor(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
    xi, eta = m.p
    m = skfem.MeshTri(np.vstack([48 * xi, (1 - eta) * 44 * xi + eta * (44 + 16 * xi)]), m.t)
    element = skfem.ElementVector(skfem.ElementTriP2())
    basis = skfem.Basis(m, element)
    K = skfem.asm(linear_elasticity(2 * lam * mu / (lam + 2 * mu), mu), basis)
    right = skfem.FacetBasis(m, element, facets=m.facets_satisfying(
        lambda x: np.abs(x[0] - 48) < 1e-9))
    f = skfem.asm(skfem.LinearForm(lambda v, w: v.value[1] / 16.0), right)
    u = skfem.solve(*skfem.condense(K, f, D=basis.get_dofs(lambda x: np.abs(x[0]) < 1e-9)))
    corner = np.flatnonzero((np.abs(m.p[0] - 48) < 1e-9) & (np.abs(m.p[1] - 60) < 1e-9))[0]
    return float(u[basis.nodal_dofs[1, corner]])


def plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = np.array([r[0] for r in rows])
    v = np.array([r[2] for r in rows])
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    ax.semilogx(48.0 / n, v, "o-", label="fem3d, P1 tets (n x n x 1 cells)")
    ax.axhline(COOK_REFERENCE, color="k", ls="--", lw=1, label="published 23.96")
    ax.invert_xaxis()
    ax.set_xlabel("cell width along x, 48 / n")
    ax.set_ylabel("vertical displacement at (48, 60)")
    ax.set_title("Cook's membrane")
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="skip cook_64 and lame_eighth_24")
    parser.add_argument("--plane-stress", action="store_true",
                        help="only Cook's membrane in 2-D plane stress, P2 (scikit-fem)")
    args = parser.parse_args()
    if args.plane_stress:
        for n in (16, 32, 64):
            print(f"plane stress, P2 triangles, {n} x {n}: {cook_plane_stress_p2(n):.4f}")
        return
    sizes = (2, 4, 8, 16, 32) if args.quick else (2, 4, 8, 16, 32, 64)
    rows = cook(sizes)
    print("| mesh | tets | v at (48, 60) | / 23.96 | solve (s) |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for n, tets, v, sec in rows:
        print(f"| cook_{n} | {tets:,} | {v:.4f} | {v / COOK_REFERENCE:.4f} | {sec:.2f} |")
    plot(rows, ROOT / "docs" / "figures" / "cook_convergence.png")
    print("\n| scene, mesh | tets | inner surface | outer surface | worst vertex | solve (s) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    meshes = [("lame_sphere_eighth", f"meshes/lame_eighth_{n}.mesh")
              for n in ((8, 16) if args.quick else (8, 16, 24))]
    sims = {}
    for name, mesh in [*meshes, ("lame_sphere", None)]:
        sim, sec = solve(name, mesh)
        sims[(name, mesh)] = sim
        inner, outer, worst = lame(sim)
        label = f"{name}, {Path(mesh).stem if mesh else 'lame_sphere_8'}"
        print(f"| {label} | {sim.model.n_tets:,} | {100 * inner:+.2f} % | {100 * outer:+.2f} % "
              f"| {100 * worst:+.2f} % | {sec:.2f} |")
    eighth = sims[meshes[0]]
    whole = sims[("lame_sphere", None)]
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(whole.model.X).query(eighth.model.X)
    assert dist.max() < 1e-12
    diff = np.abs(eighth.q - whole.q[idx]).max() / np.abs(eighth.q - eighth.model.X).max()
    print(f"\noctant vs whole sphere (lame_eighth_8 in lame_sphere_8): max |q| difference "
          f"{diff:.1e} of the largest displacement")


if __name__ == "__main__":
    main()
