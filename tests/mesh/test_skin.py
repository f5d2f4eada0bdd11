"""Tests of fem3d.mesh.skin.build_skinning_matrix."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from fem3d.errors import InputError
from fem3d.mesh.skin import build_skinning_matrix

ROOT = Path(__file__).resolve().parents[2]
DATA_DIRS = [ROOT / "data", ROOT.parent / "shared" / "reference-meshes"]


def _data(name: str) -> Path:
    for d in DATA_DIRS:
        if (d / name).exists():
            return d / name
    pytest.skip(f"{name} not found in {DATA_DIRS}")


def cube_mesh(n: int = 3, size: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Unit cube split into n^3 cells of 6 Kuhn tets each (conforming, positive volume)."""
    g = np.arange(n + 1)
    X = np.array(list(itertools.product(g, g, g)), dtype=np.float64) * (size / n)

    def vid(i, j, k):
        return (i * (n + 1) + j) * (n + 1) + k

    tets = []
    for i, j, k in itertools.product(range(n), repeat=3):
        for perm in itertools.permutations(range(3)):
            c = [i, j, k]
            path = [tuple(c)]
            for axis in perm:
                c = list(c)
                c[axis] += 1
                path.append(tuple(c))
            tets.append([vid(*p) for p in path])
    T = np.array(tets, dtype=np.int64)
    e = X[T[:, 1:]] - X[T[:, :1]]
    neg = np.linalg.det(e) < 0
    T[neg] = T[neg][:, [0, 2, 1, 3]]
    return X, T


def _brute_barycentrics(X, T, p):
    """(k, m, 4) barycentric coordinates of every point in every tet (reference)."""
    D = np.transpose(X[T[:, 1:]] - X[T[:, :1]], (0, 2, 1))
    lam = np.einsum("mij,kmj->kmi", np.linalg.inv(D), p[:, None, :] - X[T[:, 0]][None])
    return np.concatenate([1 - lam.sum(-1, keepdims=True), lam], axis=-1)


def _read_node_ele(node: Path, ele: Path) -> tuple[np.ndarray, np.ndarray]:
    X = np.loadtxt(node, skiprows=1, comments="#")[:, 1:4]
    T = np.loadtxt(ele, skiprows=1, comments="#", dtype=np.int64)[:, 1:5]
    return X, T


def _read_obj_vertices(path: Path) -> np.ndarray:
    with open(path) as fh:
        return np.array([ln.split()[1:4] for ln in fh if ln.startswith("v ")], dtype=np.float64)


def test_identity_when_skin_is_the_sim_mesh():
    X, T = cube_mesh(3)
    W = build_skinning_matrix(X, T, X)
    assert isinstance(W, sp.csr_matrix)
    assert W.shape == (X.shape[0], X.shape[0])
    D = W.toarray()
    np.testing.assert_allclose(D, np.eye(X.shape[0]), atol=1e-12, rtol=0)
    np.testing.assert_allclose(W @ X, X, atol=1e-12, rtol=0)


def test_random_affine_maps_are_reproduced_exactly():
    rng = np.random.default_rng(1)
    X, T = cube_mesh(3)
    inside = rng.uniform(0.0, 1.0, (500, 3))
    outside = rng.uniform(-0.3, 1.3, (200, 3))
    skin = np.vstack([inside, outside])
    W = build_skinning_matrix(X, T, skin)
    for _ in range(3):
        A = rng.normal(size=(3, 3))
        b = rng.normal(size=3)
        np.testing.assert_allclose(W @ (X @ A.T + b), skin @ A.T + b, atol=1e-12, rtol=0)
    np.testing.assert_allclose(np.asarray(W.sum(axis=1)).ravel(), 1.0, atol=1e-13, rtol=0)
    assert np.all(np.diff(W.indptr) == 4)


def test_inside_vertices_get_their_containing_tet():
    rng = np.random.default_rng(2)
    X, T = cube_mesh(4)
    skin = rng.uniform(0.0, 1.0, (400, 3))
    W = build_skinning_matrix(X, T, skin)
    coords = W.data.reshape(-1, 4)
    assert coords.min() >= -1e-9
    # the four columns are the corners of some tet that contains the point
    ref = _brute_barycentrics(X, T, skin)
    contains = ref.min(axis=2) >= -1e-9
    tets_as_sets = {frozenset(t) for t in T.tolist()}
    for r in range(skin.shape[0]):
        cols = frozenset(W.indices[W.indptr[r] : W.indptr[r + 1]].tolist())
        assert cols in tets_as_sets
        assert contains[r].any()


def test_outside_vertices_extrapolate_from_best_tet():
    rng = np.random.default_rng(3)
    X, T = cube_mesh(5)  # 750 tets: more than the largest candidate round
    # points just outside the faces of the cube
    skin = rng.uniform(0.05, 0.95, (300, 3))
    axis = rng.integers(0, 3, 300)
    side = rng.integers(0, 2, 300)
    skin[np.arange(300), axis] = np.where(side == 1, 1.0 + 0.02, -0.02)
    W = build_skinning_matrix(X, T, skin)
    coords = W.data.reshape(-1, 4)
    assert (coords.min(axis=1) < 0).all()  # really extrapolated
    np.testing.assert_allclose(W @ X, skin, atol=1e-12, rtol=0)
    np.testing.assert_allclose(coords.sum(axis=1), 1.0, atol=1e-13, rtol=0)
    # nearest in the barycentric sense among all tets (brute force)
    best = _brute_barycentrics(X, T, skin).min(axis=2).max(axis=1)
    np.testing.assert_allclose(coords.min(axis=1), best, atol=1e-12, rtol=0)


def test_degenerate_tets_are_skipped():
    X, T = cube_mesh(2)
    flat = np.array([[0, 1, 2, 0]])  # repeated vertex: zero volume
    skin = np.random.default_rng(4).uniform(0, 1, (50, 3))
    W = build_skinning_matrix(X, np.vstack([flat, T]), skin)
    np.testing.assert_allclose(W @ X, skin, atol=1e-12, rtol=0)
    assert np.isfinite(W.data).all()


@pytest.mark.parametrize(
    "X, T, V",
    [
        (np.zeros((4, 2)), np.array([[0, 1, 2, 3]]), np.zeros((1, 3))),
        (np.eye(4, 3), np.array([[0, 1, 2, 4]]), np.zeros((1, 3))),
        (np.eye(4, 3), np.array([[0, 1, 2, 3]]), np.array([[np.nan, 0, 0]])),
        (np.eye(4, 3), np.array([[0.0, 1, 2, 3]]), np.zeros((1, 3))),
        (np.eye(4, 3), np.zeros((0, 4), dtype=int), np.zeros((1, 3))),
        (np.zeros((4, 3)), np.array([[0, 1, 2, 3]]), np.zeros((1, 3))),
    ],
    ids=["X-shape", "index-range", "nan-skin", "float-tets", "no-tets", "all-degenerate"],
)
def test_bad_input_raises(X, T, V):
    with pytest.raises(InputError):
        build_skinning_matrix(X, T, V)


def test_empty_skin():
    X, T = cube_mesh(1)
    W = build_skinning_matrix(X, T, np.zeros((0, 3)))
    assert W.shape == (0, X.shape[0])


def test_armadillo_skin():
    X, T = _read_node_ele(_data("arma_6.node"), _data("arma_6.ele"))
    V = _read_obj_vertices(_data("armadillo.obj"))
    assert X.shape == (259, 3) and T.shape == (627, 4) and V.shape == (26002, 3)
    W = build_skinning_matrix(X, T, V)
    assert W.shape == (26002, 259)
    coords = W.data.reshape(-1, 4)
    inside = coords.min(axis=1) >= -1e-9
    assert inside.mean() > 0.99
    err = np.abs(W @ X - V).max(axis=1)
    assert err[inside].max() < 1e-12
    np.testing.assert_allclose(coords.sum(axis=1), 1.0, atol=1e-12, rtol=0)
    # follows a rigid motion of the sim mesh
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    np.testing.assert_allclose(W @ (X @ R.T + 2.0), V @ R.T + 2.0, atol=1e-12, rtol=0)
