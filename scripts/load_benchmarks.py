"""The load benchmarks of docs/loads.md: Cook's membrane on a mesh sequence with linear (P1)
and quadratic (P2) tets, and Lame's thick-walled sphere (octant and whole; P1 on the
``.mesh`` files, P2 on the isoparametric ``*_p2.vtu`` ones), from the scenes in data/scenes/.

    python scripts/load_benchmarks.py            # prints the tables, writes the figure
    python scripts/load_benchmarks.py --quick    # without the largest meshes
    python scripts/load_benchmarks.py --plane-stress   # Cook's membrane in 2-D plane stress,
                                                       # P2 triangles (scikit-fem): a check

Writes docs/figures/cook_convergence.png (the corner's vertical displacement against the
mesh size, P1 and P2, with the published 23.96 and, when scikit-fem is installed, the 2-D
quadratic-triangle value on 64 x 64 squares).
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


def solve(name: str, mesh: str | None = None, element: str = "p1") -> tuple[Simulation, float]:
    """One static step of scene ``name`` (on ``mesh``, with ``element``); the simulation and
    its seconds."""
    overrides = {"bodies[0].element": element} | ({"bodies[0].mesh": mesh} if mesh else {})
    sim = Simulation(load_scene(name, overrides))
    t0 = time.perf_counter()
    sim.step()
    return sim, time.perf_counter() - t0


def cook(sizes, element: str = "p1") -> list[tuple[int, int, int, float, float]]:
    """``(n, tets, nodes, corner v, seconds)`` per mesh ``cook_<n>`` (the corner's nodes
    through the thickness averaged)."""
    rows = []
    for n in sizes:
        sim, sec = solve("cook_membrane", f"meshes/cook_{n}.mesh", element)
        X = sim.model.X
        corner = np.flatnonzero((np.abs(X[:, 0] - 48) < 1e-9) & (np.abs(X[:, 1] - 60) < 1e-9))
        rows.append((n, sim.model.n_tets, sim.model.n_vertices,
                     float((sim.q - X)[corner, 1].mean()), sec))
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


def plot(curves: dict[str, list], path: Path, plane_stress: float | None = None) -> None:
    """The corner's displacement against the cell width, one curve per element."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for (element, rows), marker in zip(curves.items(), ("o-", "s-"), strict=False):
        n = np.array([r[0] for r in rows])
        v = np.array([r[3] for r in rows])
        ax.semilogx(48.0 / n, v, marker, label=f"fem3d, {element.upper()} tets (n x n x 1 cells)")
    ax.axhline(COOK_REFERENCE, color="k", ls="--", lw=1, label="published 23.96")
    if plane_stress is not None:
        ax.axhline(plane_stress, color="gray", ls=":", lw=1.5,
                   label=f"2-D plane stress, P2 triangles 64 x 64: {plane_stress:.2f}")
    ax.invert_xaxis()
    ax.set_xlabel("cell width along x, 48 / n")
    ax.set_ylabel("vertical displacement at (48, 60)")
    ax.set_title("Cook's membrane")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def cook_tables(quick: bool) -> None:
    """Cook's membrane with P1 and P2 tets: the tables and the figure."""
    curves = {}
    for element in ("p1", "p2"):
        rows = curves[element] = cook((2, 4, 8, 16, 32) if quick else (2, 4, 8, 16, 32, 64),
                                      element)
        print(f"\n| mesh, {element.upper()} | tets | nodes | v at (48, 60) | / 23.96 | solve (s) |")
        print("| --- | ---: | ---: | ---: | ---: | ---: |")
        for n, tets, nodes, v, sec in rows:
            print(f"| cook_{n} | {tets:,} | {nodes:,} | {v:.4f} | {v / COOK_REFERENCE:.4f} "
                  f"| {sec:.2f} |")
    try:
        plane_stress = cook_plane_stress_p2(64)
    except ImportError:  # scikit-fem is optional
        plane_stress = None
    plot(curves, ROOT / "docs" / "figures" / "cook_convergence.png", plane_stress)


def octant_vs_whole(eighth: Simulation, whole: Simulation) -> float:
    """Largest difference of the octant's displacements from the whole sphere's at the same
    nodes, relative to the largest displacement."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(whole.model.X).query(eighth.model.X)
    assert dist.max() < 1e-12
    return float(np.abs(eighth.q - whole.q[idx]).max() / np.abs(eighth.q - eighth.model.X).max())


def lame_tables(quick: bool) -> None:
    """Lame's sphere: P1 on the octant's sequence and the whole sphere, P2 (curved) likewise;
    the octant against the whole sphere for each element."""
    print("\n| scene, mesh, element | tets | nodes | inner surface | outer surface | worst vertex "
          "| solve (s) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    runs = [("lame_sphere_eighth", f"meshes/lame_eighth_{n}.mesh", "p1")
            for n in ((8, 16) if quick else (8, 16, 24))]
    runs += [("lame_sphere", None, "p1")]
    runs += [("lame_sphere_eighth", f"meshes/lame_eighth_{n}_p2.vtu", "p2") for n in (4, 8)]
    runs += [("lame_sphere", "meshes/lame_sphere_4_p2.vtu", "p2")]
    sims = {}
    for name, mesh, element in runs:
        sim, sec = solve(name, mesh, element)
        sims[(name, mesh)] = sim
        inner, outer, worst = lame(sim)
        label = f"{name}, {Path(mesh).stem if mesh else 'lame_sphere_8'}, {element.upper()}"
        print(f"| {label} | {sim.model.n_tets:,} | {sim.model.n_vertices:,} "
              f"| {100 * inner:+.2f} % | {100 * outer:+.2f} % | {100 * worst:+.2f} % "
              f"| {sec:.2f} |")
    for eighth, whole, what in (
            (runs[0][:2], ("lame_sphere", None), "P1: lame_eighth_8 in lame_sphere_8"),
            (("lame_sphere_eighth", "meshes/lame_eighth_4_p2.vtu"),
             ("lame_sphere", "meshes/lame_sphere_4_p2.vtu"),
             "P2: lame_eighth_4_p2 in lame_sphere_4_p2")):
        diff = octant_vs_whole(sims[eighth], sims[whole])
        print(f"\noctant vs whole sphere ({what}): max |q| difference {diff:.1e} of the "
              "largest displacement")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="skip cook_64 (P1 and P2) and lame_eighth_24")
    parser.add_argument("--plane-stress", action="store_true",
                        help="only Cook's membrane in 2-D plane stress, P2 (scikit-fem)")
    args = parser.parse_args()
    if args.plane_stress:
        for n in (16, 32, 64):
            print(f"plane stress, P2 triangles, {n} x {n}: {cook_plane_stress_p2(n):.4f}")
        return
    cook_tables(args.quick)
    lame_tables(args.quick)


if __name__ == "__main__":
    main()
