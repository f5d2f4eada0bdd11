"""Tests of fem3d.physics.constraints."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial import cKDTree

from fem3d.errors import InputError, ParameterError
from fem3d.physics.constraints import (
    Constraints,
    fixed_point_constraints,
    fixed_vertices_lowest_y,
    pick_nearest_vertices,
)


def _random_spd(N: int, rng: np.random.Generator, density: float = 0.05) -> sp.csr_matrix:
    B = sp.random(N, N, density=density, random_state=rng, format="csr")
    return (B @ B.T + sp.identity(N)).tocsr()


def test_selection_matrix_properties():
    P = fixed_point_constraints(5, np.array([3, 0, 3]))
    assert P.shape == (9, 15)
    np.testing.assert_array_equal((P @ P.T).toarray(), np.eye(9))
    cols = P.indices
    np.testing.assert_array_equal(cols, [3, 4, 5, 6, 7, 8, 12, 13, 14])


def test_constraints_expand_restrict_round_trip():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(20, 3))
    fixed = np.array([2, 5, 5, 17])
    C = Constraints.from_fixed_vertices(X, fixed)
    np.testing.assert_array_equal(C.fixed_vertices, [2, 5, 17])
    assert C.n_free == 3 * 17 and C.n_dofs == 60
    np.testing.assert_array_equal((C.P @ C.P.T).toarray(), np.eye(C.n_free))
    q_free = rng.normal(size=C.n_free)
    q = C.expand(q_free)
    np.testing.assert_array_equal(q, C.P.T @ q_free + C.x0)
    np.testing.assert_array_equal(q.reshape(-1, 3)[C.fixed_vertices], X[C.fixed_vertices])
    np.testing.assert_array_equal(C.restrict(q), q_free)
    np.testing.assert_array_equal(C.restrict(q.reshape(-1, 3)), q_free)
    np.testing.assert_array_equal(C.expand_zero(q_free), C.P.T @ q_free)
    # x0 is zero on free DOFs
    np.testing.assert_array_equal(C.x0[C.free_dofs], 0.0)
    with pytest.raises(ValueError):
        C.expand(q_free[:-1])
    with pytest.raises(ValueError):
        C.restrict(q[:-1])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reduce_matrix_matches_PAPt(seed):
    rng = np.random.default_rng(seed)
    n = 40
    X = rng.normal(size=(n, 3))
    C = Constraints.from_fixed_vertices(X, rng.choice(n, 7, replace=False))
    A = _random_spd(3 * n, rng)
    ref = (C.P @ A @ C.P.T).toarray()
    R = C.reduce_matrix(A)
    assert R.shape == (C.n_free, C.n_free)
    np.testing.assert_array_equal(R.toarray(), ref)
    assert R.has_sorted_indices == A.has_sorted_indices
    A.sort_indices()
    R = C.reduce_matrix(A)
    assert R.has_sorted_indices
    for r in range(R.shape[0]):  # the flag we set is true
        assert np.all(np.diff(R.indices[R.indptr[r] : R.indptr[r + 1]]) > 0)
    np.testing.assert_array_equal(R.toarray(), ref)
    # same pattern, new values: cached path
    A2 = A.copy()
    A2.data = rng.normal(size=A2.data.size)
    np.testing.assert_array_equal(C.reduce_matrix(A2).toarray(), (C.P @ A2 @ C.P.T).toarray())
    # different pattern: cache must be refreshed
    A3 = _random_spd(3 * n, rng)
    np.testing.assert_array_equal(C.reduce_matrix(A3).toarray(), (C.P @ A3 @ C.P.T).toarray())
    # other formats and non-canonical CSR (duplicates)
    np.testing.assert_array_equal(C.reduce_matrix(A.tocoo()).toarray(), ref)
    coo = A.tocoo()
    dup = sp.csr_matrix(
        (
            np.concatenate([coo.data, coo.data]) * 0.5,
            (np.concatenate([coo.row, coo.row]), np.concatenate([coo.col, coo.col])),
        ),
        shape=A.shape,
    )
    np.testing.assert_allclose(C.reduce_matrix(dup).toarray(), ref, rtol=1e-15, atol=1e-15)


def test_reduce_matrix_result_does_not_alias_cache():
    rng = np.random.default_rng(5)
    X = rng.normal(size=(10, 3))
    C = Constraints.from_fixed_vertices(X, [0])
    A = _random_spd(30, rng, density=0.3)
    R1 = C.reduce_matrix(A)
    R1.indices[:] = 0  # caller mangles its result
    R2 = C.reduce_matrix(A)
    np.testing.assert_array_equal(R2.toarray(), (C.P @ A @ C.P.T).toarray())


def test_reduce_matrix_shape_check():
    C = Constraints.from_fixed_vertices(np.zeros((4, 3)), [0])
    with pytest.raises(ValueError):
        C.reduce_matrix(sp.identity(9, format="csr"))


def test_fixed_vertices_lowest_y():
    X = np.array([[0, 0.0, 0], [1, 0.05, 0], [2, 0.2, 0], [3, -0.01, 5], [4, 1.0, 1]])
    np.testing.assert_array_equal(fixed_vertices_lowest_y(X, 0.1), [0, 1, 3])
    np.testing.assert_array_equal(fixed_vertices_lowest_y(X, 0.0), [3])
    assert fixed_vertices_lowest_y(X, 0.1).dtype == np.int64
    np.testing.assert_array_equal(fixed_vertices_lowest_y(X, 10.0), np.arange(5))


@pytest.mark.parametrize("tol", [-1e-3, np.nan, np.inf])
def test_fixed_vertices_bad_tolerance(tol):
    with pytest.raises(ParameterError):
        fixed_vertices_lowest_y(np.zeros((3, 3)), tol)


def test_fixed_vertices_empty_selection():
    with pytest.raises(ParameterError):
        fixed_vertices_lowest_y(np.zeros((0, 3)), 0.1)
    with pytest.raises(ParameterError):
        fixed_vertices_lowest_y(np.array([[0.0, np.nan, 0.0]]), 0.1)


def test_bad_fixed_indices():
    with pytest.raises(ParameterError):
        Constraints.from_fixed_vertices(np.zeros((4, 3)), [4])
    with pytest.raises(ParameterError):
        Constraints.from_fixed_vertices(np.zeros((4, 3)), [-1])
    with pytest.raises(ParameterError):
        fixed_point_constraints(4, np.array([0.5]))
    with pytest.raises(InputError):
        Constraints.from_fixed_vertices(np.zeros((4, 2)), [0])


def test_pick_nearest_vertices():
    rng = np.random.default_rng(7)
    X = rng.uniform(-1, 1, (2000, 3))
    p = np.array([0.1, -0.2, 0.3])
    r = 0.25
    ref = np.flatnonzero(np.linalg.norm(X - p, axis=1) <= r)
    got = pick_nearest_vertices(X, p, r)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, ref)
    tree = cKDTree(X)
    np.testing.assert_array_equal(pick_nearest_vertices(X, p, r, tree=tree), ref)
    # nothing within radius
    far = np.array([10.0, 10.0, 10.0])
    assert pick_nearest_vertices(X, far, 0.1).size == 0
    assert pick_nearest_vertices(X, far, 0.1, tree=tree).size == 0
    nearest = np.argmin(np.linalg.norm(X - far, axis=1))
    np.testing.assert_array_equal(
        pick_nearest_vertices(X, far, 0.1, nearest_if_empty=True), [nearest]
    )
    np.testing.assert_array_equal(
        pick_nearest_vertices(X, far, 0.1, tree=tree, nearest_if_empty=True), [nearest]
    )


@pytest.mark.parametrize("radius, point", [(-1.0, [0, 0, 0]), (0.1, [0, 0]), (0.1, [0, np.nan, 0])])
def test_pick_bad_parameters(radius, point):
    with pytest.raises(ParameterError):
        pick_nearest_vertices(np.zeros((3, 3)), np.array(point, dtype=float), radius)


def test_reduce_matrix_alternating_patterns_stay_cached():
    rng = np.random.default_rng(11)
    n = 30
    C = Constraints.from_fixed_vertices(rng.normal(size=(n, 3)), [0, 1])
    mats = [_random_spd(3 * n, rng, density=d) for d in (0.02, 0.05, 0.1)]
    for _ in range(3):
        for A in mats:
            np.testing.assert_array_equal(C.reduce_matrix(A).toarray(), (C.P @ A @ C.P.T).toarray())
    assert len(C._cache) == 3  # every pattern computed once and kept
