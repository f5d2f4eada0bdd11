"""Tests of fem3d.solve.linear and fem3d.solve.krylov: every back end that is installed, SuperLU
always."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fem3d.errors import Fem3dError
from fem3d.solve.krylov import PreconditionedCG
from fem3d.solve.linear import (
    BACKENDS,
    NotPositiveDefinite,
    SparseSPDSolver,
    available_backends,
)

AVAILABLE = available_backends()


# CHOLMOD runs in both of its modes: "auto" picks simplicial for small cheap factors
VARIANTS = ["cholmod:supernodal", "cholmod:simplicial", *BACKENDS[1:]]


@pytest.fixture(params=VARIANTS)
def backend(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.delenv("FEM3D_SOLVER", raising=False)
    if request.param.partition(":")[0] not in AVAILABLE:
        pytest.skip(f"sparse solver back end {request.param!r} not installed")
    return request.param


def make_solver(A: sp.spmatrix, variant: str) -> SparseSPDSolver:
    """``SparseSPDSolver`` for ``"backend"`` or ``"cholmod:<mode>"``."""
    backend, _, mode = variant.partition(":")
    solver = SparseSPDSolver(A, backend, cholmod_mode=mode or "auto")
    assert solver.backend == backend and (not mode or solver.cholmod_mode == mode)
    return solver


def grid_laplacian(n: int = 7) -> sp.csr_matrix:
    """(3 n^3, 3 n^3) SPD: 3-D 7-point Laplacian (Dirichlet) kron a 3x3 SPD block."""
    d = sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    eye = sp.identity(n)
    lap = sp.kron(sp.kron(d, eye), eye) + sp.kron(sp.kron(eye, d), eye)
    lap = lap + sp.kron(sp.kron(eye, eye), d)
    block = np.array([[2.0, 0.5, 0.1], [0.5, 1.5, 0.2], [0.1, 0.2, 1.0]])
    A = sp.kron(lap, block, format="csr")
    A.sort_indices()
    return A


def test_matches_spsolve(backend: str) -> None:
    A = grid_laplacian()
    rng = np.random.default_rng(1)
    b = rng.standard_normal((A.shape[0], 2))
    solver = make_solver(A, backend)
    solver.factorize(A)
    ref = spla.spsolve(A.tocsc(), b)
    np.testing.assert_allclose(solver.solve(b), ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(solver.solve(b[:, 0]), ref[:, 0], rtol=1e-9, atol=1e-12)
    # a second matrix of the same pattern: numeric refactorization only
    A2 = (A + sp.diags(rng.uniform(0.1, 1.0, A.shape[0]))).tocsr()
    solver.factorize(A2)
    np.testing.assert_allclose(
        solver.solve(b[:, 0]), spla.spsolve(A2.tocsc(), b[:, 0]), rtol=1e-9, atol=1e-12
    )


def test_subset_pattern_and_bad_pattern(backend: str) -> None:
    A = grid_laplacian(4)
    solver = make_solver(A, backend)
    # a matrix whose pattern is a subset (the diagonal only) is embedded into the analysed one
    D = sp.diags(A.diagonal()).tocsr()
    solver.factorize(D)
    b = np.arange(A.shape[0], dtype=float)
    np.testing.assert_allclose(solver.solve(b), b / A.diagonal(), rtol=1e-12)
    # an entry outside the pattern is refused
    bad = A.tolil()
    bad[0, A.shape[0] - 1] = bad[A.shape[0] - 1, 0] = 1e-3
    with pytest.raises(ValueError, match="outside the sparsity pattern"):
        solver.factorize(bad.tocsr())


def test_indefinite_raises_and_shift_recovers(backend: str) -> None:
    A = grid_laplacian(5)
    lam_min = spla.eigsh(A, k=1, sigma=0, which="LM", return_eigenvectors=False)[0]
    # shift just past the smallest eigenvalue: one slightly negative direction
    Aind = (A - 1.5 * lam_min * sp.identity(A.shape[0])).tocsr()
    solver = make_solver(A, backend)
    with pytest.raises(NotPositiveDefinite) as info:
        solver.factorize(Aind)
    assert isinstance(info.value, Fem3dError)
    assert isinstance(info.value, np.linalg.LinAlgError)
    with pytest.raises(RuntimeError):
        solver.solve(np.ones(A.shape[0]))  # the failed factorization is not used

    mu = solver.factorize_shifted(Aind)
    assert mu > 0.0 and solver.shift == mu
    shifted = Aind + mu * sp.diags(np.abs(Aind.diagonal()))
    assert np.linalg.eigvalsh(shifted.toarray()).min() > 0.0
    b = np.ones(A.shape[0])
    np.testing.assert_allclose(solver.solve(b), spla.spsolve(shifted.tocsc(), b), rtol=1e-8)

    # a mass-like SPD shift matrix inside the pattern
    mu_m = solver.factorize_shifted(Aind, A)
    assert mu_m > 0.0
    # SPD input needs no shift
    assert solver.factorize_shifted(A) == 0.0
    # known indefinite: the ladder starts shifted
    assert solver.factorize_shifted(Aind, mu0=mu, try_unshifted=False) == mu


@pytest.mark.parametrize("needed", [0, 3, 7, 12])
def test_ladder_from_the_bottom_bisects_to_the_lowest_rung(backend: str, needed: int) -> None:
    """An indefinite matrix whose lowest positive-definite rung is ``mu0 10^needed``: the
    ladder started at ``A`` itself finds that rung (what climbing it finds) in about
    ``log2(13)`` attempts, and the factorization left in place is that rung's."""
    A = grid_laplacian(4)
    lam_min = float(np.linalg.eigvalsh(A.toarray()).min())
    mu0, growth, tries = 1e-4, 10.0, 13
    target = mu0 * growth**needed
    # S = I, A - c I with c between the rung below and the rung needed (geometric middle)
    c = lam_min + target / np.sqrt(growth)
    Aind = (A - c * sp.identity(A.shape[0])).tocsr()
    solver = make_solver(A, backend)
    attempts: list[np.ndarray] = []  # the matrices factorized (their data)
    factorize_data = solver._factorize_data

    def counted(data: np.ndarray) -> None:
        attempts.append(data)
        factorize_data(data)

    solver._factorize_data = counted
    eye = np.ones(A.shape[0])
    mu = solver.factorize_shifted(Aind, eye, mu0=mu0, growth=growth, max_tries=tries)
    assert mu == pytest.approx(target, rel=1e-12) and solver.shift == mu
    assert len(attempts) <= 1 + 4 + 1  # A itself, bisection over 13 rungs, one redo
    b = np.arange(1.0, A.shape[0] + 1)
    expected = spla.spsolve((Aind + mu * sp.identity(A.shape[0])).tocsc(), b)
    np.testing.assert_allclose(solver.solve(b), expected, rtol=1e-8)
    # the climb from a hint (no unshifted attempt) finds the same rung
    attempts.clear()
    assert solver.factorize_shifted(Aind, eye, mu0=mu0, growth=growth, max_tries=tries,
                                    try_unshifted=False) == mu
    assert len(attempts) == needed + 1


def test_shift_gives_up(backend: str) -> None:
    A = grid_laplacian(3)
    solver = make_solver(A, backend)
    with pytest.raises(NotPositiveDefinite, match="still not positive definite"):
        solver.factorize_shifted(-A, max_tries=2)


def test_nonfinite_matrix_is_not_positive_definite(backend: str) -> None:
    A = grid_laplacian(3)
    solver = make_solver(A, backend)
    B = A.copy()
    B.data[0] = np.nan
    with pytest.raises(NotPositiveDefinite, match="non-finite"):
        solver.factorize(B)


def test_cg_with_old_factorization(backend: str) -> None:
    A = grid_laplacian()
    rng = np.random.default_rng(2)
    solver = make_solver(A, backend)
    solver.factorize(A)
    # a nearby matrix of the same pattern (values perturbed symmetrically by ~5 %)
    P = A.copy()
    P.data *= 1.0 + 0.05 * rng.uniform(-1, 1, P.nnz)
    A2 = ((P + P.T) * 0.5).tocsr()
    b = rng.standard_normal(A.shape[0])
    cg = PreconditionedCG(solver, rtol=1e-10, maxiter=60, refactorize_on_stall=False)
    res = cg.solve(A2, b)
    assert res.converged and not res.stalled and not res.refactorized
    assert 0 < res.iterations < 30
    np.testing.assert_allclose(res.x, spla.spsolve(A2.tocsc(), b), rtol=1e-7, atol=1e-9)
    assert cg.n_refactorizations == 0


def test_cg_stalls_and_refactorizes(backend: str) -> None:
    A = grid_laplacian()
    solver = make_solver(A, backend)
    solver.factorize(A)
    A_far = (A + 50.0 * sp.diags(np.linspace(0.0, 1.0, A.shape[0]) ** 4)).tocsr()
    b = np.ones(A.shape[0])
    ref = spla.spsolve(A_far.tocsc(), b)
    stalled = PreconditionedCG(solver, maxiter=3, refactorize_on_stall=False).solve(A_far, b)
    assert stalled.stalled and not stalled.converged
    cg = PreconditionedCG(solver, maxiter=3)
    res = cg.solve(A_far, b)
    assert res.refactorized and res.converged and cg.n_refactorizations == 1
    np.testing.assert_allclose(res.x, ref, rtol=1e-9)
    # the new factorization now preconditions exactly: no iteration needed
    res2 = cg.solve(A_far, b)
    assert res2.iterations == 0 and not res2.refactorized


def test_cg_detects_indefinite(backend: str) -> None:
    A = grid_laplacian(4)
    solver = make_solver(A, backend)
    solver.factorize(A)
    b = np.ones(A.shape[0])
    res = PreconditionedCG(solver, refactorize_on_stall=False).solve(-A, b)
    assert res.stalled and res.negative_curvature
    slow = PreconditionedCG(solver, maxiter=1, refactorize_on_stall=False).solve(
        (A + 50.0 * sp.diags(np.linspace(0.0, 1.0, A.shape[0]) ** 4)).tocsr(), b)
    assert slow.stalled and not slow.negative_curvature


def test_env_override(monkeypatch: pytest.MonkeyPatch) -> None:
    A = grid_laplacian(3)
    monkeypatch.setenv("FEM3D_SOLVER", "superlu")
    assert SparseSPDSolver(A, "auto").backend == "superlu"
    monkeypatch.setenv("FEM3D_SOLVER", "nonsense")
    with pytest.raises(ValueError, match="FEM3D_SOLVER"):
        SparseSPDSolver(A)
    monkeypatch.delenv("FEM3D_SOLVER")
    assert SparseSPDSolver(A).backend == AVAILABLE[0]
    assert "superlu" in AVAILABLE


def test_bad_pattern_input() -> None:
    with pytest.raises(ValueError, match="square"):
        SparseSPDSolver(sp.csr_matrix(np.ones((2, 3))), "superlu")
    with pytest.raises(ValueError, match="diagonal"):
        SparseSPDSolver(sp.csr_matrix(np.array([[0.0, 1.0], [1.0, 0.0]])), "superlu")
    with pytest.raises(ValueError, match="symmetric"):
        SparseSPDSolver(sp.csr_matrix(np.array([[1.0, 1.0], [0.0, 1.0]])), "superlu")
    with pytest.raises(TypeError):
        SparseSPDSolver(np.eye(3), "superlu")  # type: ignore[arg-type]


@pytest.mark.skipif("cholmod" not in AVAILABLE, reason="CHOLMOD not installed")
def test_cholmod_auto_mode_follows_the_factor_cost() -> None:
    from fem3d.solve import linear as linsolve

    small = grid_laplacian(4)  # 192 rows, short columns of L
    assert SparseSPDSolver(small, "cholmod").cholmod_mode == "simplicial"
    dense_block = sp.csr_matrix(np.eye(60) + np.ones((60, 60)))  # L is a full triangle
    assert SparseSPDSolver(dense_block, "cholmod").cholmod_mode == "simplicial"
    cost = SparseSPDSolver(dense_block, "cholmod")._factor_cost_per_entry()
    assert cost == pytest.approx((2 * 60 + 1) / 3)  # sum c^2 / sum c for c = 1..60
    # from about 80 flops per entry the supernodal code is the faster one (2.4x at 83)
    block_120 = sp.csr_matrix(np.eye(120) + np.ones((120, 120)))  # 80.3 flops per entry
    assert SparseSPDSolver(block_120, "cholmod").cholmod_mode == "supernodal"
    bigger = sp.csr_matrix(np.eye(400) + np.ones((400, 400)))  # ~267 flops per entry
    assert SparseSPDSolver(bigger, "cholmod").cholmod_mode == "supernodal"
    assert linsolve.SIMPLICIAL_MAX_N >= 400
    with pytest.raises(ValueError, match="cholmod_mode"):
        SparseSPDSolver(small, "cholmod", cholmod_mode="fast")


@pytest.mark.skipif("cholmod" not in AVAILABLE, reason="CHOLMOD not installed")
def test_cholmod_runs_on_the_calling_thread_alone() -> None:
    # CHOLMOD 3's supernodal code opens a 4-thread OpenMP region per supernode whatever
    # OMP_NUM_THREADS says; fem3d runs those regions on one thread (a factorization of the
    # pile's matrix: 93 ms with the team on 2 cores, 24 ms without). A fresh process: the
    # team, once started, stays alive, and other tests start OpenMP teams of their own.
    script = """
import os, numpy as np, scipy.sparse as sp
from fem3d.solve.linear import SparseSPDSolver
n = 24
lap = sp.diags([-1.0, 2.01, -1.0], [-1, 0, 1], shape=(n, n))
eye = sp.identity(n)
A = (sp.kron(sp.kron(lap, eye), eye) + sp.kron(sp.kron(eye, lap), eye)
     + sp.kron(sp.kron(eye, eye), lap)).tocsr()
solver = SparseSPDSolver(A, "cholmod", cholmod_mode="supernodal")
solver.factorize(A)
x = solver.solve(np.ones(A.shape[0]))
assert np.allclose(A @ x, 1.0)
print(len(os.listdir("/proc/self/task")))
"""
    if not os.path.isdir("/proc/self/task"):
        pytest.skip("needs Linux's /proc to count threads")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                         text=True, check=True, timeout=120)
    assert int(out.stdout.split()[-1]) == 1
