"""AMG-preconditioned CG for backward Euler's Newton systems (the ``"amg"`` linear solver)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.sparse as sp

pytest.importorskip("pyamg")

from fem3d.physics.constraints import Constraints  # noqa: E402
from fem3d.physics.model import build_model  # noqa: E402
from fem3d.solve.integrators import State, System, implicit_euler, linearly_implicit_euler  # noqa: E402
from fem3d.solve.linear import amg as solve_amg  # noqa: E402
from fem3d.solve.linear import resolve_linear_solver  # noqa: E402
from fem3d.solve.linear.amg_cg import AMGCGSolver  # noqa: E402
from tests.physics.test_assembly import box_mesh  # noqa: E402


def clamped_box(n=(6, 6, 6), E=6e5, rho=100.0):
    X, T = box_mesh(*n, size=(1.0, 1.0, 1.0))
    model = build_model(X, T, E=E, nu=0.4, rho=rho)
    fixed = np.flatnonzero(X[:, 2] <= 1e-12)
    return model, Constraints.from_fixed_vertices(X, fixed)


def swinging(model, constraints, a=4.0):
    X = model.X
    v = np.zeros_like(X)
    v[:, 0] = a * X[:, 2] ** 2
    v[:, 1] = -0.75 * a * X[:, 2] * X[:, 0]
    v[constraints.fixed_vertices] = 0.0
    return State(q=X.copy(), v=v)


def run(system, state, steps, dt=0.01, **kw):
    out, all_stats = [], []
    for _ in range(steps):
        state, stats = implicit_euler(system, state, dt, max_iterations=None, **kw)
        assert stats.converged
        out.append(state.q)
        all_stats.append(stats)
    return out, all_stats


def test_amg_trajectory_agrees_with_the_direct_solve():
    """Both Newton runs stop at the same gradient tolerance ``|g| <= tol`` (rtol 1e-10 of the
    first gradient), so their end points differ by at most ``2 tol |A^-1|``: here 1e-8 of the
    mesh size over 6 steps (measured about 1e-10); the inexact Newton needs more iterations
    but no factorization."""
    model, c = clamped_box()
    start = swinging(model, c)
    direct, dstats = run(System(model, c, resolve_linear_solver(direct=True)), start, 6)
    amg_system = System(model, c, "amg")
    assert amg_system.linear_backend == "amg"
    amg, astats = run(amg_system, start, 6)
    size = np.ptp(model.X, axis=0).max()
    motion = max(np.abs(q - model.X).max() for q in direct)
    assert motion > 0.02 * size
    deviation = max(np.abs(a - b).max() for a, b in zip(amg, direct, strict=True))
    print("max deviation / size", deviation / size)
    assert deviation < 1e-8 * size
    assert sum(s.factorizations for s in astats) == 0
    assert sum(s.cg_iterations for s in astats) > 0
    setups = sum(s.amg_setups for s in astats)
    assert 1 <= setups < sum(s.newton_iterations for s in astats)  # the hierarchy is reused
    for s in astats:  # every step reached the tolerance it aimed for (not a round-off stop)
        assert s.converged and s.newton_iterations >= 1
        assert len(s.gradient_norms) == s.newton_iterations + 1
        assert s.gradient_norms[-1] <= s.gradient_tolerance
        assert s.gradient_norms[0] > s.gradient_tolerance  # the step had work to do
    assert {"matrix", "cg", "objective"} <= set(astats[0].seconds)


def test_amg_falls_back_to_the_psd_hessian_on_an_indefinite_system():
    """A half-height sheared box at dt = 0.1: ``M + dt^2 H`` is indefinite; CG meets negative
    curvature, the step switches to the PSD-projected Hessian and ends where direct does."""
    model, c = clamped_box((4, 4, 4), E=1e5, rho=1.0)
    X = model.X
    q = X.copy()
    q[:, 2] *= 0.5
    q[:, 0] += 0.3 * np.sin(3.0 * X[:, 2])
    q[c.fixed_vertices] = X[c.fixed_vertices]
    state = State(q=q, v=np.zeros_like(X))
    ref, rstats = implicit_euler(System(model, c, resolve_linear_solver(direct=True)), state, 0.1,
                                 max_iterations=None)
    assert rstats.shifted_factorizations >= 1  # the exact Hessian is indefinite here
    new, stats = implicit_euler(System(model, c, "amg"), state, 0.1, max_iterations=None)
    print("psd fallbacks", stats.psd_fallbacks, "cg", stats.cg_iterations)
    assert stats.psd_fallbacks == 1 and stats.converged
    assert np.abs(new.q - ref.q).max() < 1e-6 * np.abs(ref.q - state.q).max()


def test_rigid_body_modes_are_the_null_space_of_the_rest_stiffness():
    from fem3d.physics.assembly import hessian_data

    model, _ = clamped_box((3, 3, 3))
    B = solve_amg.rigid_body_modes(model.X)
    H = model.csr(hessian_data(model, model.X))
    assert B.shape == (model.n_dofs, 6)
    assert np.abs(H @ B).max() < 1e-9 * np.abs(H.data).max()
    assert np.linalg.matrix_rank(B) == 6


def test_auto_picks_amg_by_size_and_env_and_missing_pyamg(monkeypatch):
    model, c = clamped_box((3, 3, 3))
    monkeypatch.delenv("FEM3D_SOLVER", raising=False)
    assert System(model, c).linear_backend == resolve_linear_solver(direct=True)
    monkeypatch.setattr(AMGCGSolver, "auto_min_free_dofs", c.n_free)
    assert System(model, c).linear_backend == "amg"
    monkeypatch.setenv("FEM3D_SOLVER", "superlu")  # a forced direct back end wins over auto
    assert System(model, c).linear_backend == "superlu"
    monkeypatch.delenv("FEM3D_SOLVER")
    monkeypatch.setattr(AMGCGSolver, "available", classmethod(lambda cls: False))
    assert System(model, c).linear_backend == resolve_linear_solver(direct=True)
    with pytest.raises(ImportError, match="'amg' is not installed: pip install pyamg"):
        System(model, c, "amg")


def test_a_saved_hierarchy_resumes_bit_for_bit():
    """``factorized_data`` records the matrix the hierarchy was built from; a fresh System
    rebuilds the same hierarchy from it and continues exactly (checkpoint/resume)."""
    model, c = clamped_box((4, 4, 4))
    start = swinging(model, c)
    first = System(model, c, "amg")
    mid, _ = implicit_euler(first, start, 0.01, max_iterations=None)
    saved = first.factorized_data.copy()
    a, _ = implicit_euler(first, mid, 0.01, max_iterations=None)
    fresh = System(model, c, "amg")
    fresh.refactorize_saved(saved)
    b, _ = implicit_euler(fresh, mid, 0.01, max_iterations=None)
    assert np.array_equal(a.q, b.q) and np.array_equal(a.v, b.v)


def test_linear_scheme_and_objective_terms_with_the_amg_back_end():
    from tests.solve.test_integrators import PairSprings

    model, c = clamped_box((3, 3, 3))
    system = System(model, c, "amg")
    start = swinging(model, c)
    lin, _ = linearly_implicit_euler(system, start, 0.01)  # factorizes (direct solver made lazily)
    direct = System(model, c, resolve_linear_solver(direct=True))
    ref, _ = linearly_implicit_euler(direct, start, 0.01)
    np.testing.assert_allclose(lin.q, ref.q, rtol=0, atol=1e-12)
    far = [int(np.argmax(model.X.sum(axis=1))), int(np.argmax(model.X[:, 2] - model.X[:, 0]))]
    term = PairSprings([far], 1e4)
    new, stats = implicit_euler(system, start, 0.01, terms=[term], max_iterations=None)
    assert stats.converged and system.pattern_generation == 1 and stats.amg_setups >= 1
    assert system.amg_current


def _newton_matrix(n=(5, 5, 5)):
    model, c = clamped_box(n)
    start = swinging(model, c)
    system = System(model, c, "amg")
    q = start.q.reshape(-1) + 0.01 * start.v.reshape(-1)
    return system, system.newton_matrix(q, 0.01)


def _textbook_v_cycle(amg, A, b):
    """Forward block Gauss-Seidel, residual, restriction, recursion, exact coarsest solve,
    prolongation, backward block Gauss-Seidel, on the full level matrices R A P."""
    from pyamg.relaxation.relaxation import block_gauss_seidel

    mats = [A.tobsr(blocksize=(3, 3))]
    for lvl in amg._levels:
        mats.append((lvl.R @ mats[-1] @ lvl.P).tobsr(blocksize=lvl.P.blocksize[::-1]))

    def cycle(i, b):
        if i == len(amg._levels):
            return np.linalg.lstsq(mats[i].toarray(), b, rcond=None)[0]
        Ai, k = mats[i], mats[i].blocksize[0]
        x = np.zeros_like(b)
        block_gauss_seidel(Ai, x, b, sweep="forward", blocksize=k)
        x += amg._levels[i].P @ cycle(i + 1, amg._levels[i].R @ (b - Ai @ x))
        block_gauss_seidel(Ai, x, b, sweep="backward", blocksize=k)
        return x

    return cycle(0, b)


def test_v_cycle_is_the_textbook_symmetric_v_cycle():
    """The V-cycle's half-triangle sweeps (and the reversed upper triangle) compute the plain
    V-cycle of forward and backward block Gauss-Seidel, and the result is symmetric."""
    system, A = _newton_matrix((8, 8, 8))
    amg = solve_amg.AMGPreconditioner(system.amg.hierarchy.B, {"max_coarse": 10})
    amg.setup(A)
    assert len(amg.level_sizes) >= 3  # two coarse levels: 3x3 and 6x6 blocks both covered
    rng = np.random.default_rng(3)
    b1, b2 = rng.standard_normal((2, A.shape[0]))
    z1 = amg.apply(b1)
    ref = _textbook_v_cycle(amg, A, b1)
    assert np.abs(z1 - ref).max() < 1e-10 * np.abs(ref).max()
    assert abs(b2 @ z1 - b1 @ amg.apply(b2)) < 1e-12 * abs(b2 @ z1)
    assert b1 @ z1 > 0


def test_hierarchy_has_pyamg_smoothed_aggregation_structure():
    """The structural aggregation (computed once per pattern) is pyamg's own: the same level
    sizes and coarse block patterns as ``pyamg.smoothed_aggregation_solver`` with a zero
    strength threshold."""
    import pyamg

    system, A = _newton_matrix((6, 6, 6))
    amg = solve_amg.AMGPreconditioner(system.amg.hierarchy.B, {"max_coarse": 10})
    amg.setup(A)
    ml = pyamg.smoothed_aggregation_solver(
        A.tobsr(blocksize=(3, 3)), B=system.amg.hierarchy.B, strength=("symmetric", {"theta": 0.0}),
        improve_candidates=None, max_coarse=10, smooth=("jacobi", {"weighting": "block"}))
    assert amg.level_sizes == [lvl.A.shape[0] for lvl in ml.levels]
    for ours, theirs in zip(amg._levels, ml.levels[:-1], strict=True):
        assert ours.P.nnz == theirs.P.nnz
        # same smoothed prolongator up to pyamg's randomly started spectral estimate
        assert abs(ours.P - theirs.P).max() < 0.05 * abs(theirs.P).max()


def test_setup_analyzes_once_per_pattern_and_maps_partial_blocks():
    """``analyze`` runs when a pattern is new (System does it at construction); a pattern
    of partial 3x3 blocks (an objective term's per-axis springs) maps into BSR exactly."""
    system, A = _newton_matrix((3, 3, 3))
    amg = system.amg.hierarchy
    plan = amg._plan
    amg.setup(A)
    assert amg._plan is plan  # the pattern analysed by System(...)
    n = A.shape[0]
    rng = np.random.default_rng(0)
    extra = sp.coo_matrix((rng.random(40), (rng.integers(0, n, 40), rng.integers(0, n, 40))),
                          shape=(n, n))
    B = (A + extra + extra.T).tocsr()
    B.sort_indices()
    indptr, indices, slot = solve_amg._block_pattern(B.indptr, B.indices, n)
    data = np.zeros(indices.size * 9)
    data[slot] = B.data
    bsr = sp.bsr_matrix((data.reshape(-1, 3, 3), indices, indptr), shape=(n, n))
    assert abs(bsr - B).max() == 0.0
    amg.setup(B)
    assert amg._plan is not plan and amg.ready


def test_block_inverses_pseudo_invert_singular_blocks():
    rng = np.random.default_rng(1)
    blocks = rng.standard_normal((6, 3, 3))
    blocks[2] = 0.0
    blocks[4] = np.outer([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])
    D = sp.bsr_matrix((blocks, np.arange(6), np.arange(7)), shape=(18, 18))
    inv = solve_amg._block_inverses(D)
    for i in range(6):
        np.testing.assert_allclose(inv[i], np.linalg.pinv(blocks[i]), atol=1e-9)


def test_forcing_term_tightens_with_convergence_but_not_past_the_tolerance():
    from fem3d.solve.directions import forcing_term as _forcing_term

    assert _forcing_term(5.0, 0.0, 0.1, 1e-8, 0.1) == 0.1  # first iteration
    assert _forcing_term(0.5, 5.0, 0.1, 1e-8, 0.1) == pytest.approx(0.9 * 0.01)
    assert _forcing_term(4.0, 5.0, 0.1, 1e-8, 0.1) == 0.1  # slow progress: capped
    assert _forcing_term(1e-6, 1e-2, 1e-3, 1e-8, 0.1) == pytest.approx(0.5e-2)  # tol floor
    assert _forcing_term(1e-3, 1e-2, 0.5, 1e-8, 0.1) == 0.1  # safeguard 0.9 eta^2 > 0.1


def test_amg_steps_save_assemblies_and_keep_the_gradient_tolerance(monkeypatch):
    """The chord step (the last iteration reuses the previous Newton matrix) saves assemblies;
    every step still ends below the unchanged gradient tolerance."""
    model, c = clamped_box((6, 6, 6))
    system = System(model, c, "amg")
    calls = [0]
    newton_matrix = system.newton_matrix

    def counted(*args, **kwargs):
        calls[0] += 1
        return newton_matrix(*args, **kwargs)

    monkeypatch.setattr(system, "newton_matrix", counted)
    _, stats = run(system, swinging(model, c), 4)
    newton = sum(s.newton_iterations for s in stats)
    assert calls[0] < newton
    for s in stats:
        assert s.gradient_norms[-1] <= s.gradient_tolerance


def test_end_game_judges_noisy_energies_by_the_gradient():
    """Near the tolerance an objective's round-off scales with its terms, not with |E|: a
    step the energy cannot resolve is accepted when it shrinks the gradient (with
    ``roundoff_rtol``), where plain backtracking halves through the noise and stalls above
    the tolerance."""
    from fem3d.solve.newton import newtons_method

    rng = np.random.default_rng(1)
    Q = rng.standard_normal((8, 8))
    H = Q @ Q.T + 8.0 * np.eye(8)
    x_star = rng.standard_normal(8)

    def energy(x):  # tiny at the minimum, with round-off-like noise of 1e-15
        e = x - x_star
        return 1e-6 + 0.5 * float(e @ H @ e) + 1e-15 * math.sin(1e9 * float(x.sum()))

    def gradient(x):
        return H @ (x - x_star)

    def direction(x, g):  # an inexact Newton direction (1e-3 relative residual)
        return -np.linalg.solve(H, g) * (1.0 + 1e-3)

    x0 = x_star + 1e-3 * rng.standard_normal(8)
    kw = dict(max_iterations=20, rtol=0.0, atol=1e-10)
    noisy = newtons_method(x0, energy, gradient, direction, roundoff_rtol=1e-10, **kw)
    assert noisy.converged and noisy.gradient_norms[-1] <= 1e-10
    assert noisy.line_search_halvings == 0 and noisy.iterations <= 4
    plain = newtons_method(x0, energy, gradient, direction, **kw)
    assert plain.gradient_norms[-1] > 1e-10 and plain.line_search_halvings > 20


# --- the threaded kernels of the large systems (fem3d.solve.sparse_threads) -----------------

def _threaded_setup(n=(14, 14, 14), **options):
    """A swinging box's Newton matrix and a hierarchy on the threaded kernels."""
    from fem3d.solve import sparse_threads

    if sparse_threads.c_kernels() is None:
        pytest.skip("the C extension is not built")
    model, c = clamped_box(n)
    system = System(model, c, "amg")
    state = swinging(model, c)
    A = system.newton_matrix(state.q + 0.01 * state.v, 0.01)
    amg = solve_amg.AMGPreconditioner(system.amg.hierarchy.B, {"threads_min_rows": 0} | options)
    amg.setup(A)
    assert amg._threads is not None
    return A, amg, system


def test_threaded_kernels_equal_the_numpy_reference():
    """Sweeps (forward from zero, backward), the V-cycle's BSR mat-vecs (3x3, 6x6, 3x6, 6x3
    blocks), the CSR mat-vec and the dot product against NumPy/SciPy to round-off; the
    schedule's blocks of one colour share no entry."""
    from fem3d.solve import sparse_threads

    A, amg, _ = _threaded_setup((8, 8, 8), max_coarse=10)
    ext = sparse_threads.c_kernels()
    rng = np.random.default_rng(0)
    assert len(amg._levels) == 2  # 3x3 and 6x6 levels
    for lvl in amg._levels:
        L, U, s, k = lvl.L, lvl.U, lvl.sweep, lvl.Dinv.shape[1]
        # a finer schedule than the level's own: several blocks and colours even here
        Afull = (L + U).tobsr(blocksize=(k, k))
        s = sparse_threads.sweep_schedule(Afull.indptr, Afull.indices, min_block_rows=8)
        if k == 3:  # (the 6x6 level is dense: one block)
            assert s.n_colours >= 2 and s.n_blocks > s.n_colours
        colour = np.repeat(np.arange(s.n_colours), np.diff(s.colours))
        block_colour = colour
        row_block = np.empty(L.shape[0] // k, dtype=np.int64)
        row_block[s.sequence()] = np.repeat(np.arange(s.n_blocks), np.diff(s.blocks))
        rows = np.repeat(np.arange(row_block.size), np.diff(Afull.indptr))
        bi, bj = row_block[rows], row_block[Afull.indices]
        assert not np.any((bi != bj) & (block_colour[bi] == block_colour[bj]))
        L, U = sparse_threads.split_triangles(Afull, s.rank)
        assert np.allclose((L + U).toarray(), Afull.toarray(), rtol=0, atol=0)
        b = rng.standard_normal(L.shape[0])
        x = np.zeros_like(b)
        ext.block_sweep(L.indptr, L.indices, L.data, None, None, None, lvl.Dinv, s.order,
                        s.blocks, s.colours, x, b)
        ref = sparse_threads.reference_sweep(L, U, lvl.Dinv, s, np.zeros_like(b), b)
        assert np.abs(x - ref).max() <= 1e-13 * np.abs(ref).max()
        x2 = x.copy()
        ext.block_sweep(L.indptr, L.indices, L.data, U.indptr, U.indices, U.data, lvl.Dinv,
                        s.order, s.blocks, s.colours, x2, b)
        ref = sparse_threads.reference_sweep(L, U, lvl.Dinv, s, x, b, backward=True)
        assert np.abs(x2 - ref).max() <= 1e-13 * np.abs(ref).max()
        for M in (U, lvl.P, lvl.R):
            v = rng.standard_normal(M.shape[1])
            y0 = rng.standard_normal(M.shape[0])
            y = y0.copy()
            ext.bsr_matvec(M.indptr, M.indices, M.data, *M.blocksize, v, y, -1.0, y)
            ref = y0 - M @ v
            assert np.abs(y - ref).max() <= 1e-13 * np.abs(ref).max()
    lvl = amg._levels[0]
    Abar = (lvl.L + lvl.U).tobsr(blocksize=(3, 3))
    for left, right in ((Abar, lvl.P), (lvl.R, Abar), (lvl.R, lvl.P)):  # 3x3x6, 6x3x3, 6x3x6
        ours = sparse_threads.bsr_product(ext, left, right)
        theirs = (left @ right).toarray()
        assert ours.has_sorted_indices and np.all(np.diff(ours.indices[:ours.indptr[1]]) > 0)
        assert np.abs(ours.toarray() - theirs).max() <= 1e-13 * np.abs(theirs).max()
    p = rng.standard_normal(A.shape[0])
    y = np.empty_like(p)
    ext.csr_matvec(A.indptr, A.indices, A.data, p, y)
    assert np.abs(y - A @ p).max() <= 1e-13 * np.abs(A @ p).max()
    big = rng.standard_normal(200_001)
    assert ext.dot(big, big[::-1].copy()) == pytest.approx(big @ big[::-1], rel=1e-12)
    with pytest.raises(ValueError, match="bsr_matvec: indptr must rise"):
        P = amg._levels[0].P
        bad = P.indices.copy()
        bad[0] = P.shape[1] // P.blocksize[1]  # one block column past the end
        ext.bsr_matvec(P.indptr, bad, P.data, *P.blocksize, np.ones(P.shape[1]), None, 1.0,
                       np.empty(P.shape[0]))


def test_threaded_amg_is_bit_identical_on_one_and_two_threads():
    """Setup, V-cycle and CG on 1 and 2 OpenMP threads: the same bits (the sweeps' colours
    run one after the other, every row's sum in storage order, dot products in fixed
    chunks)."""
    from fem3d.solve import sparse_threads

    A, amg, _ = _threaded_setup()
    ext = sparse_threads.c_kernels()
    level0 = amg._levels[0].sweep
    assert level0.n_colours >= 2 and level0.n_blocks >= 4  # the sweeps do run in parallel
    assert A.shape[0] // 3 >= 2048  # above FEM3D_AMG_PARALLEL_ROWS
    b = np.random.default_rng(1).standard_normal(A.shape[0])
    big = np.random.default_rng(2).standard_normal(1_000_003)
    before = ext.max_threads()
    results = []
    try:
        for threads in (1, 2):
            ext.set_max_threads(threads)
            amg.setup(A)
            res = amg.solve(A, b, rtol=1e-8, maxiter=100)
            results.append((amg.apply(b), res.x, res.iterations, ext.dot(big, big)))
    finally:
        ext.set_max_threads(before)
    (z1, x1, it1, d1), (z2, x2, it2, d2) = results
    assert np.array_equal(z1, z2) and np.array_equal(x1, x2) and it1 == it2 and d1 == d2


def test_threaded_amg_converges_like_the_classic_smoother(monkeypatch):
    """The sweeps in colour/block order precondition as well as pyamg's sweeps in row order
    (CG iterations to 1e-8 within one), and the threaded back end keeps the trajectory of
    the direct solve."""
    A, amg, system = _threaded_setup()
    classic = solve_amg.AMGPreconditioner(system.amg.hierarchy.B)
    classic.setup(A)
    assert classic._threads is None  # below threads_min_rows
    b = np.random.default_rng(3).standard_normal(A.shape[0])
    new = amg.solve(A, b, rtol=1e-8, maxiter=100)
    old = classic.solve(A, b, rtol=1e-8, maxiter=100)
    print("CG iterations threaded", new.iterations, "classic", old.iterations)
    assert new.converged and new.iterations <= old.iterations + 1
    assert np.linalg.norm(A @ new.x - b) <= 1e-8 * np.linalg.norm(b) * 1.01

    monkeypatch.setitem(solve_amg.AMG_OPTIONS, "threads_min_rows", 0)
    model, c = clamped_box()
    start = swinging(model, c)
    direct, _ = run(System(model, c, resolve_linear_solver(direct=True)), start, 2)
    amg_system = System(model, c, "amg")
    threaded, _ = run(amg_system, start, 2)
    assert amg_system.amg.hierarchy._threads is not None
    size = np.ptp(model.X, axis=0).max()
    assert max(np.abs(a - d).max() for a, d in zip(threaded, direct, strict=True)) < 1e-8 * size


def test_without_the_c_extension_large_systems_keep_the_classic_path(monkeypatch):
    """No C extension (or one without the AMG kernels): every size runs pyamg's sweeps and
    SciPy's products, as below ``threads_min_rows`` (the NumPy/SciPy fallback)."""
    from fem3d.solve import sparse_threads

    model, c = clamped_box((4, 4, 4))
    system = System(model, c, "amg")
    state = swinging(model, c)
    A = system.newton_matrix(state.q + 0.01 * state.v, 0.01)
    b = np.random.default_rng(4).standard_normal(A.shape[0])
    classic = solve_amg.AMGPreconditioner(system.amg.hierarchy.B)
    classic.setup(A)
    monkeypatch.setattr(sparse_threads, "c_extension", lambda: None)
    assert sparse_threads.c_kernels() is None
    fallback = solve_amg.AMGPreconditioner(system.amg.hierarchy.B, {"threads_min_rows": 0})
    fallback.setup(A)
    assert fallback._threads is None
    assert np.array_equal(fallback.solve(A, b, rtol=1e-8, maxiter=50).x,
                          classic.solve(A, b, rtol=1e-8, maxiter=50).x)
