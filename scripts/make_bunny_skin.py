"""Build the bunny display (skin) mesh ``data/bunny_skin.obj``, deterministically.

The original CSC417 bunny skin is not available, so we make one from the finer bunny tet
mesh ``data/coarse_bunny.mesh`` (699 vertices):

1. take its outward boundary surface (``fem3d.mesh.tetmesh.boundary_faces``) and drop the interior
   vertices;
2. apply ``--levels`` (default 2) steps of Loop subdivision (own vectorized implementation,
   closed manifold surfaces only), which smooths the faceted surface;
3. optionally pull it inward along the area-weighted vertex normals by ``--shrink`` times
   the bounding-box diagonal (default 0: a uniform shrink pushes thin parts such as the
   ears out through the other side of the coarser simulation mesh), then pull the vertices
   that lie outside the simulation mesh ``data/coarser_bunny.mesh`` (about 100, at most
   1.3 % of the diagonal out) inward along their normals until they are inside it; each
   push is spread to the neighbours (a few smoothing sweeps) so it makes a smooth dimple,
   not a spike. Skinning then interpolates rather than extrapolates.

Usage::

    python scripts/make_bunny_skin.py [--levels 2] [--out data/bunny_skin.obj] [--png skin.png]

With ``--png`` it also renders the result with matplotlib (for a visual check).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run from a checkout without installing fem3d
    sys.path.insert(0, str(ROOT))

from fem3d.mesh.formats import read_tet_mesh, write_surface_mesh  # noqa: E402
from fem3d.mesh.skin import skin_outside_distance  # noqa: E402
from fem3d.mesh.tetmesh import boundary_faces  # noqa: E402


def compact(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices no face uses.

    Parameters
    ----------
    V : (n, 3) float64
    F : (f, 3) int64

    Returns
    -------
    V : (k, 3) float64
    F : (f, 3) int64, renumbered
    """
    used = np.unique(F)
    new = np.full(V.shape[0], -1, dtype=np.int64)
    new[used] = np.arange(used.size)
    return V[used], new[F]


def loop_subdivide(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One step of Loop subdivision of a closed, oriented, manifold triangle mesh.

    Parameters
    ----------
    V : (n, 3) float64
    F : (f, 3) int64

    Returns
    -------
    V : (n + n_edges, 3) float64
        Old vertices moved with Loop's (Warren's original) weights, then one vertex per edge.
    F : (4 f, 3) int64
        Same orientation as the input.
    """
    n = V.shape[0]
    he = np.stack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]], axis=1).reshape(-1, 2)
    opp = F[:, [2, 0, 1]].reshape(-1)  # vertex opposite each half-edge
    key = np.sort(he, axis=1)
    edges, e_of_he, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    e_of_he = e_of_he.reshape(-1)
    if not (counts == 2).all():
        raise ValueError("loop_subdivide needs a closed manifold mesh (each edge in 2 faces)")
    ne = edges.shape[0]
    # edge points: 3/8 (a + b) + 1/8 (c + d)
    opp_sum = np.zeros((ne, 3))
    np.add.at(opp_sum, e_of_he, V[opp])
    Ve = 0.375 * (V[edges[:, 0]] + V[edges[:, 1]]) + 0.125 * opp_sum
    # vertex points: (1 - k beta) v + beta * sum(neighbours)
    nb_sum = np.zeros((n, 3))
    np.add.at(nb_sum, edges[:, 0], V[edges[:, 1]])
    np.add.at(nb_sum, edges[:, 1], V[edges[:, 0]])
    valence = np.bincount(edges.reshape(-1), minlength=n).astype(np.float64)
    beta = (0.625 - (0.375 + 0.25 * np.cos(2 * np.pi / valence)) ** 2) / valence
    Vv = (1 - valence * beta)[:, None] * V + beta[:, None] * nb_sum
    # faces: corners + middle
    e = (e_of_he.reshape(-1, 3) + n)  # edge vertex of (v0v1, v1v2, v2v0)
    a, b, c = F[:, 0], F[:, 1], F[:, 2]
    ab, bc, ca = e[:, 0], e[:, 1], e[:, 2]
    F2 = np.concatenate([
        np.stack([a, ab, ca], 1),
        np.stack([b, bc, ab], 1),
        np.stack([c, ca, bc], 1),
        np.stack([ab, bc, ca], 1),
    ])
    return np.vstack([Vv, Ve]), F2


def vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, ``(n, 3) float64``."""
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N = np.zeros_like(V)
    for k in range(3):
        np.add.at(N, F[:, k], fn)
    return N / np.linalg.norm(N, axis=1, keepdims=True)


def make_skin(
    source: Path, sim: Path, levels: int = 2, shrink: float = 0.0, max_iter: int = 20,
    smooth_steps: int = 8,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Build the skin.

    Returns
    -------
    V : (k, 3) float64
    F : (f, 3) int64
    outside : (k,) float64
        Final distance of each skin vertex outside the simulation mesh (0 inside).
    """
    src = read_tet_mesh(source)
    V, F = compact(np.asarray(src.X), boundary_faces(src.T))
    for _ in range(levels):
        V, F = loop_subdivide(V, F)
    sim_mesh = read_tet_mesh(sim)
    X, T = np.asarray(sim_mesh.X), np.asarray(sim_mesh.T)
    diag = float(np.linalg.norm(np.ptp(X, axis=0)))
    N = vertex_normals(V, F)
    V = V - shrink * diag * N
    d = skin_outside_distance(V, X, T)
    A = _adjacency(F, V.shape[0])
    for _ in range(max_iter):
        if not (d > 0).any():
            break
        need = np.where(d > 0, d + 1e-3 * diag, 0.0)
        push = need.copy()
        for _ in range(smooth_steps):  # spread the push: a smooth dimple, not a spike
            push = np.maximum(need, 0.5 * push + 0.5 * (A @ push))
        V -= push[:, None] * N
        d = skin_outside_distance(V, X, T)
    return V, F, d


def _adjacency(F: np.ndarray, n: int):
    """Row-normalised vertex adjacency (neighbour averaging), ``(n, n)`` sparse."""
    from scipy.sparse import coo_matrix

    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    A = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    A.data[:] = 1.0  # each edge appears twice (once per face): count it once
    return (A.multiply(1.0 / A.sum(axis=1))).tocsr()


def render(V: np.ndarray, F: np.ndarray, png: Path) -> None:
    """Render the mesh from two views to a PNG with matplotlib (flat-shaded)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(12, 6))
    tri = V[F]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    light = np.array([0.3, 0.8, 0.6]) / np.linalg.norm([0.3, 0.8, 0.6])
    shade = 0.25 + 0.75 * np.clip(n @ light, 0, 1)
    colors = np.column_stack([shade * 0.9, shade * 0.75, shade * 0.6, np.ones_like(shade)])
    for k, (elev, azim) in enumerate([(15, -60), (15, 120)]):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        # the bunny's up axis is y: show (x, z, y)
        pc = Poly3DCollection(tri[:, :, [0, 2, 1]], facecolors=colors, edgecolors="none")
        ax.add_collection3d(pc)
        lo, hi = V.min(0)[[0, 2, 1]], V.max(0)[[0, 2, 1]]
        c, r = (lo + hi) / 2, (hi - lo).max() / 2
        ax.set_xlim(c[0] - r, c[0] + r)
        ax.set_ylim(c[1] - r, c[1] + r)
        ax.set_zlim(c[2] - r, c[2] + r)
        ax.view_init(elev=elev, azim=azim)
        ax.set_title(f"bunny skin: {len(V)} vertices, {len(F)} faces")
    fig.tight_layout()
    fig.savefig(png, dpi=80)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", type=Path, default=ROOT / "data" / "coarse_bunny.mesh")
    ap.add_argument("--sim", type=Path, default=ROOT / "data" / "coarser_bunny.mesh")
    ap.add_argument("--out", type=Path, default=ROOT / "data" / "bunny_skin.obj")
    ap.add_argument("--levels", type=int, default=2)
    ap.add_argument("--shrink", type=float, default=0.0)
    ap.add_argument("--png", type=Path, default=None)
    args = ap.parse_args(argv)
    V, F, d = make_skin(args.source, args.sim, args.levels, args.shrink)
    header = (
        "bunny display (skin) mesh for fem3d, generated by scripts/make_bunny_skin.py\n"
        f"from {args.source.name}: boundary surface, {args.levels} Loop subdivision steps, "
        f"shrunk {args.shrink:g} x diagonal,\n"
        "pulled inside the simulation mesh " + args.sim.name + ". Do not edit; regenerate."
    )
    write_surface_mesh(args.out, V, F, header=header)
    print(f"wrote {args.out}: {len(V)} vertices, {len(F)} faces; "
          f"{int((d > 0).sum())} vertices outside {args.sim.name} (max {d.max():.3g})")
    if args.png:
        render(V, F, args.png)
        print(f"rendered {args.png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
