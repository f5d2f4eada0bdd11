"""Tests of fem3d.solve.linear (the solver seam, its registry, the direct solvers) and
fem3d.solve.linear.krylov: every back end that is installed, SuperLU always."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fem3d.errors import Fem3dError
from fem3d.solve.linear import (
    LINEAR_SOLVERS,
    DirectSolver,
    LinearSolver,
    NotPositiveDefinite,
    SolverOptions,
    available_linear_solvers,
    direct_solver_names,
    linear_solver_names,
    make_linear_solver,
    register_linear_solver,
    resolve_linear_solver,
)
from fem3d.solve.linear.krylov import PreconditionedCG
from fem3d.solve.linear.superlu import SuperLUSolver

AVAILABLE = available_linear_solvers(direct=True)
DIRECT = direct_solver_names()


# CHOLMOD runs in both of its modes: "auto" picks simplicial for small cheap factors
VARIANTS = ["cholmod:supernodal", "cholmod:simplicial", *DIRECT[1:]]


@pytest.fixture(params=VARIANTS)
def backend(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.delenv("FEM3D_SOLVER", raising=False)
    if request.param.partition(":")[0] not in AVAILABLE:
        pytest.skip(f"sparse solver back end {request.param!r} not installed")
    return request.param


def analysed(A, name: str = "auto", mode: str = "auto") -> DirectSolver:
    """The registry's direct solver ``name`` with ``A``'s pattern analysed."""
    solver = make_linear_solver(name, SolverOptions(cholmod_mode=mode), direct=True)
    assert isinstance(solver, DirectSolver)
    solver.analyse(A)
    return solver


def make_solver(A: sp.spmatrix, variant: str) -> DirectSolver:
    """A direct solver for ``"backend"`` or ``"cholmod:<mode>"``, analysed on ``A``."""
    backend, _, mode = variant.partition(":")
    solver = analysed(A, backend, mode or "auto")
    assert solver.backend == backend and (not mode or solver.cholmod_mode == mode)
    assert isinstance(solver, LinearSolver)  # the protocol's methods and attributes
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
    assert analysed(A, "auto").backend == "superlu"
    assert analysed(A, "cholmod").backend == "superlu"  # the variable wins over a direct name
    monkeypatch.setenv("FEM3D_SOLVER", "nonsense")
    with pytest.raises(ValueError, match="FEM3D_SOLVER"):
        analysed(A)
    monkeypatch.setenv("FEM3D_SOLVER", "amg")  # not a direct solver
    with pytest.raises(ValueError, match=r"'amg' \(FEM3D_SOLVER\); available: cholmod, "):
        analysed(A)
    monkeypatch.delenv("FEM3D_SOLVER")
    assert analysed(A).backend == AVAILABLE[0]
    assert "superlu" in AVAILABLE


def test_registry_names_and_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("FEM3D_SOLVER", raising=False)
    assert linear_solver_names() == ("auto", *LINEAR_SOLVERS)
    assert DIRECT == ("cholmod", "pardiso", "superlu", "petsc")
    assert "amg" in LINEAR_SOLVERS and LINEAR_SOLVERS["amg"].iterative
    with pytest.raises(ValueError, match="unknown linear solver 'mumps'; available: auto, "
                                         "cholmod, pardiso, superlu, amg, petsc"):
        resolve_linear_solver("mumps")
    # a missing library: one line naming how to install it
    monkeypatch.setattr(LINEAR_SOLVERS["pardiso"], "available", classmethod(lambda cls: False))
    with pytest.raises(ImportError, match="'pardiso' is not installed: pip install pypardiso"):
        resolve_linear_solver("pardiso")
    # an iterative choice stands for the direct default where a direct solver is needed
    assert resolve_linear_solver("amg", direct=True) == AVAILABLE[0]


def test_a_registered_solver_is_chosen_by_name_and_by_auto(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A plug-in solver: one class and one registration; ``"auto"`` takes it from its size."""
    monkeypatch.delenv("FEM3D_SOLVER", raising=False)
    monkeypatch.setattr("fem3d.solve.linear.registry.LINEAR_SOLVERS", dict(LINEAR_SOLVERS))
    from fem3d.solve.linear import registry

    class DenseSolver(SuperLUSolver):
        name = "dense"
        auto_min_free_dofs = 50

    register_linear_solver(DenseSolver)
    assert registry.linear_solver_names()[-1] == "dense"
    assert resolve_linear_solver("auto", 49) == AVAILABLE[0]
    assert resolve_linear_solver("auto", 50) == "dense"  # AMG-CG only from 1e4
    A = grid_laplacian(3)
    solver = analysed(A, "dense")
    solver.factorize(A)
    assert solver.report.backend == "dense" and solver.report.iterations == 0
    with pytest.raises(ValueError, match="name other than"):
        register_linear_solver(type("Nameless", (DenseSolver,), {"name": "auto"}))
    with pytest.raises(TypeError, match="lacks"):
        register_linear_solver(type("Half", (), {"name": "half"}))


def test_bad_pattern_input(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("FEM3D_SOLVER", raising=False)
    with pytest.raises(ValueError, match="square"):
        analysed(sp.csr_matrix(np.ones((2, 3))), "superlu")
    with pytest.raises(ValueError, match="diagonal"):
        analysed(sp.csr_matrix(np.array([[0.0, 1.0], [1.0, 0.0]])), "superlu")
    with pytest.raises(ValueError, match="symmetric"):
        analysed(sp.csr_matrix(np.array([[1.0, 1.0], [0.0, 1.0]])), "superlu")
    with pytest.raises(TypeError):
        analysed(np.eye(3), "superlu")  # type: ignore[arg-type]
    with pytest.raises(RuntimeError, match="factorize"):
        analysed(grid_laplacian(2), "superlu").solve(np.ones(24))


@pytest.mark.skipif("cholmod" not in AVAILABLE, reason="CHOLMOD not installed")
def test_cholmod_auto_mode_follows_the_factor_cost() -> None:
    from fem3d.solve.linear import cholmod

    small = grid_laplacian(4)  # 192 rows, short columns of L
    assert analysed(small, "cholmod").cholmod_mode == "simplicial"
    dense_block = sp.csr_matrix(np.eye(60) + np.ones((60, 60)))  # L is a full triangle
    assert analysed(dense_block, "cholmod").cholmod_mode == "simplicial"
    cost = analysed(dense_block, "cholmod")._factor_cost_per_entry()
    assert cost == pytest.approx((2 * 60 + 1) / 3)  # sum c^2 / sum c for c = 1..60
    # from about 80 flops per entry the supernodal code is the faster one (2.4x at 83)
    block_120 = sp.csr_matrix(np.eye(120) + np.ones((120, 120)))  # 80.3 flops per entry
    assert analysed(block_120, "cholmod").cholmod_mode == "supernodal"
    bigger = sp.csr_matrix(np.eye(400) + np.ones((400, 400)))  # ~267 flops per entry
    assert analysed(bigger, "cholmod").cholmod_mode == "supernodal"
    assert cholmod.SIMPLICIAL_MAX_N >= 400
    with pytest.raises(ValueError, match="cholmod_mode"):
        analysed(small, "cholmod", "fast")


@pytest.mark.skipif("cholmod" not in AVAILABLE, reason="CHOLMOD not installed")
def test_cholmod_runs_on_the_calling_thread_alone() -> None:
    # CHOLMOD 3's supernodal code opens a 4-thread OpenMP region per supernode whatever
    # OMP_NUM_THREADS says; fem3d runs those regions on one thread (a factorization of the
    # pile's matrix: 93 ms with the team on 2 cores, 24 ms without). A fresh process: the
    # team, once started, stays alive, and other tests start OpenMP teams of their own.
    script = """
import os, numpy as np, scipy.sparse as sp
from fem3d.solve.linear import SolverOptions, make_linear_solver
n = 24
lap = sp.diags([-1.0, 2.01, -1.0], [-1, 0, 1], shape=(n, n))
eye = sp.identity(n)
A = (sp.kron(sp.kron(lap, eye), eye) + sp.kron(sp.kron(eye, lap), eye)
     + sp.kron(sp.kron(eye, eye), lap)).tocsr()
solver = make_linear_solver("cholmod", SolverOptions(cholmod_mode="supernodal"))
solver.analyse(A)
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
