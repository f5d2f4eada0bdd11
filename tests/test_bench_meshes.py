"""The benchmark's mesh refinement: the armadillo-class meshes of ``bench.newton_step``."""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.meshes import refine_tets  # noqa: E402
from fem3d.mesh.formats import read_tet_mesh  # noqa: E402
from fem3d.scene.load import data_dir  # noqa: E402


def signed_volumes(X: np.ndarray, T: np.ndarray) -> np.ndarray:
    e = X[T[:, 1:]] - X[T[:, :1]]
    return np.linalg.det(e) / 6.0


def face_counts(T: np.ndarray) -> Counter:
    """How many tets share each (sorted) triangle."""
    faces = np.sort(T[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), axis=1)
    return Counter(map(tuple, faces.tolist()))


def test_red_refinement_keeps_the_shape_and_conforms():
    mesh = read_tet_mesh(data_dir() / "arma_6.node")
    X, T = refine_tets(mesh.X, mesh.T)
    assert T.shape == (8 * len(mesh.T), 4)
    np.testing.assert_array_equal(X[: len(mesh.X)], mesh.X)  # old vertices keep their ids
    vol = signed_volumes(X, T)
    assert vol.min() > 0
    np.testing.assert_allclose(vol.sum(), signed_volumes(mesh.X, mesh.T).sum(), rtol=1e-12)
    # conforming: every face is shared by at most two tets, and the boundary is 4x the old one
    faces, old = face_counts(T), face_counts(mesh.T)
    assert max(faces.values()) == 2
    boundary = sum(1 for c in faces.values() if c == 1)
    assert boundary == 4 * sum(1 for c in old.values() if c == 1)
    # each child lies inside its parent: children of tet e are rows e + k m, k = 0..7
    m = len(mesh.T)
    centroids = X[T].mean(axis=1).reshape(8, m, 3)
    parent = mesh.X[mesh.T]
    for k in range(8):
        # barycentric coordinates of the child centroid in the parent are all positive
        D = np.swapaxes(parent[:, 1:] - parent[:, :1], 1, 2)
        lam = np.linalg.solve(D, (centroids[k] - parent[:, 0])[..., None])[..., 0]
        assert (lam > 0).all() and (lam.sum(axis=1) < 1).all()
