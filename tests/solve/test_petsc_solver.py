"""The ``"petsc"`` linear solver in one process (``linear_solver = "petsc"``): PETSc's MUMPS
Cholesky and CG + GAMG against SciPy and CHOLMOD, the options passed through, and the
one-line errors without the ``fem3d[mpi]`` extra."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fem3d.scene import load_scene
from fem3d.scene.spec import SimulationSpec
from fem3d.simulation import Simulation
from fem3d.solve.linear import LINEAR_SOLVERS, NotPositiveDefinite, SolverOptions
from fem3d.solve.linear.petsc import PetscSolver, parse_options
from tests.parallel.helpers import relative_difference, write_scene

needs_petsc = pytest.mark.skipif(not PetscSolver.available(),
                                 reason="petsc4py is not installed (fem3d[mpi])")


def test_parse_options():
    assert parse_options("-ksp_type cg -pc_type gamg -ksp_rtol 1e-12 -log_view") == {
        "ksp_type": "cg", "pc_type": "gamg", "ksp_rtol": "1e-12", "log_view": ""}
    assert parse_options("-ksp_atol -1e-3") == {"ksp_atol": "-1e-3"}
    with pytest.raises(ValueError, match="'gamg' follows no option"):
        parse_options("-pc_type hypre gamg")
    with pytest.raises(ValueError, match="'cg' follows no option"):
        parse_options("cg")


def _newton_matrix() -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """A backward-Euler Newton matrix of the box scene's first step, its free vertices'
    rest positions and a right-hand side."""
    with tempfile.TemporaryDirectory() as tmp:
        sim = Simulation(load_scene(str(write_scene(Path(tmp)))))
    system = sim.system
    A = system.newton_matrix(sim.q.reshape(-1) + 0.01, 0.01)
    points = sim.model.X[system.free[0::3] // 3]
    b = np.random.default_rng(0).standard_normal(A.shape[0])
    return A, points, b


@needs_petsc
@pytest.mark.parametrize("options", ["", "-ksp_type cg -pc_type gamg -ksp_rtol 1e-12",
                                     "-ksp_type cg -pc_type jacobi -ksp_rtol 1e-12 "
                                     "-ksp_max_it 5000"])
def test_solves_like_scipy(options):
    A, points, b = _newton_matrix()
    solver = PetscSolver(SolverOptions(points=points, petsc_options=options))
    solver.analyse(A)
    solver.factorize(A)
    x = solver.solve(b)
    expected = spla.spsolve(A.tocsc(), b)
    assert np.linalg.norm(x - expected) <= 1e-9 * np.linalg.norm(expected)
    ksp = solver._ksp
    wanted = parse_options(options).get("ksp_type", "preonly")
    assert ksp.getType() == wanted
    assert ksp.getPC().getType() == parse_options(options).get("pc_type", "cholesky")
    report = solver.report
    assert report.backend == "petsc" and report.converged
    if wanted == "cg":
        assert report.iterations > 1 and report.residual <= 1e-12


@needs_petsc
def test_environment_options_win(monkeypatch):
    A, points, b = _newton_matrix()
    monkeypatch.setenv("FEM3D_PETSC_OPTIONS", "-pc_type jacobi -ksp_type cg -ksp_rtol 1e-11")
    solver = PetscSolver(SolverOptions(points=points, petsc_options="-pc_type gamg"))
    solver.analyse(A)
    solver.factorize(A)
    solver.solve(b)
    assert solver._ksp.getPC().getType() == "jacobi"


@needs_petsc
def test_product_options_reach_gamg_set_up():
    """``-matptap_via`` in the scene's options reaches GAMG's products (PETSc reads it from
    its global database, not the KSP's prefix): a bad value fails the set-up, a good one
    solves, and the global database is left as it was."""
    from fem3d.solve.linear.petsc import petsc_module

    A, points, b = _newton_matrix()
    gamg = "-ksp_type cg -pc_type gamg -ksp_rtol 1e-12"
    bad = PetscSolver(SolverOptions(points=points, petsc_options=f"{gamg} -matptap_via nope"))
    bad.analyse(A)
    with pytest.raises(NotPositiveDefinite, match="could not set up the solver"):
        bad.factorize(A)
    solver = PetscSolver(SolverOptions(points=points,
                                       petsc_options=f"{gamg} -matptap_via scalable"))
    solver.analyse(A)
    solver.factorize(A)
    x = solver.solve(b)
    expected = spla.spsolve(A.tocsc(), b)
    assert np.linalg.norm(x - expected) <= 1e-9 * np.linalg.norm(expected)
    assert not petsc_module().Options().hasName("matptap_via")


@needs_petsc
def test_indefinite_matrix_is_refused_and_shifted():
    """MUMPS' LDL^T counts negative pivots: an indefinite matrix raises, and the shift ladder
    lands on the first positive-definite rung, as with CHOLMOD."""
    n = 30
    A = sp.diags([np.r_[np.ones(n - 1), -0.5]], [0], format="csr") + \
        sp.diags([0.1 * np.ones(n - 1), 0.1 * np.ones(n - 1)], [-1, 1], format="csr")
    solver = PetscSolver()
    solver.analyse(A)
    with pytest.raises(NotPositiveDefinite, match="negative pivots"):
        solver.factorize(A)
    mu = solver.factorize_shifted(A, np.ones(n), mu0=0.1, growth=10.0, max_tries=4)
    assert mu == 1.0  # -0.5 + 0.1 and the off-diagonals: indefinite; -0.5 + 1: definite
    x = solver.solve(np.ones(n))
    assert np.allclose((A + sp.identity(n)) @ x, 1.0)


@needs_petsc
def test_a_krylov_solve_that_breaks_down_is_nan_and_one_out_of_iterations_its_iterate():
    """CG that breaks down on an indefinite matrix (``b^T A b = 0``) gives NaN, for Newton
    to fall back on the gradient; CG that runs out of iterations
    (``DIVERGED_MAX_IT``) gives its last iterate, not converged (until now the first raised
    an AttributeError: petsc4py has no ``DIVERGED_ITS``)."""
    n = 40
    indefinite = sp.diags([np.r_[np.ones(n // 2), -np.ones(n // 2)]], [0], format="csr")
    solver = PetscSolver(SolverOptions(petsc_options="-ksp_type cg -pc_type none"))
    solver.analyse(indefinite)
    solver.factorize(indefinite)
    assert np.isnan(solver.solve(np.ones(n))).all()
    assert not solver.report.converged
    spd = sp.diags([2.0 * np.ones(n), -np.ones(n - 1), -np.ones(n - 1)], [0, -1, 1],
                   format="csr")
    solver = PetscSolver(SolverOptions(petsc_options="-ksp_type cg -pc_type none "
                                                     "-ksp_max_it 3"))
    solver.analyse(spd)
    solver.factorize(spd)
    x = solver.solve(np.ones(n))
    assert np.isfinite(x).all() and np.abs(x).max() > 0 and not solver.report.converged
    assert solver.report.iterations == 3


@needs_petsc
@pytest.mark.parametrize("integrator", ["implicit", "bdf2"])
@pytest.mark.parametrize("options", ["", "-ksp_type cg -pc_type gamg"])
def test_simulation_equals_the_default_solver(tmp_path, integrator, options):
    """20 steps of the two-material box with linear_solver = "petsc" (MUMPS, and GAMG-CG)
    equal the default direct solver's to Newton's tolerance (1e-8 of the motion)."""
    extra = f'petsc_options = "{options}"' if options else ""
    runs = {}
    for name in ("auto", "petsc"):
        scene = load_scene(str(write_scene(tmp_path, integrator=integrator, linear_solver=name,
                                           extra=extra if name == "petsc" else "")))
        sim = Simulation(scene)
        assert sim.system.linear_backend == name if name == "petsc" else True
        for _ in range(20):
            sim.step()
        runs[name] = sim.q.copy()
    rest = sim.model.X
    diff = relative_difference(runs["petsc"], runs["auto"], rest)
    print(f"{integrator} {options or 'mumps'}: relative difference {diff:.2e}")
    assert diff <= 1e-8


def test_registered_and_in_the_schema():
    assert LINEAR_SOLVERS["petsc"] is PetscSolver
    assert "petsc" in SimulationSpec.model_json_schema()["properties"]["linear_solver"]["enum"]


def _fem3d(*args, cwd):
    return subprocess.run([sys.executable, "-m", "fem3d", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=120)


def test_missing_extra_is_one_line(tmp_path):
    """Without petsc4py, linear_solver = "petsc" fails in one line naming the extra, exit 2,
    nothing written."""
    scene = write_scene(tmp_path, linear_solver="petsc", steps=1)
    blocker = tmp_path / "block" / "petsc4py"
    blocker.mkdir(parents=True)
    (blocker / "__init__.py").write_text("raise ImportError('blocked by the test')\n")
    env = {**os.environ, "PYTHONPATH": f"{tmp_path / 'block'}:{os.environ.get('PYTHONPATH', '')}"}
    proc = subprocess.run([sys.executable, "-m", "fem3d", "run", str(scene), "--out",
                           str(tmp_path / "out")], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120, env=env)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "simulation.linear_solver" in lines[0] and "fem3d[mpi]" in lines[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("extra, message", [
    ('petsc_options = "-ksp_type cg"', "petsc_options applies to linear_solver = 'petsc'"),
])
def test_petsc_options_need_the_petsc_solver(tmp_path, extra, message):
    scene = write_scene(tmp_path, steps=1, extra=extra)
    proc = _fem3d("run", str(scene), "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert proc.returncode == 2
    assert message in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_stray_word_in_petsc_options_is_one_line(tmp_path):
    scene = write_scene(tmp_path, steps=1, linear_solver="petsc",
                        extra='petsc_options = "-pc_type hypre boomeramg"')
    proc = _fem3d("run", str(scene), "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert proc.returncode == 2
    assert "'boomeramg' follows no option" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


@needs_petsc
@pytest.mark.parametrize("options", ["-ksp_type cg -pc_type gamg -ksp_rtol 1e-12", ""])
def test_release_lets_go_of_gamg_and_a_solve_after_it_raises(options):
    """``release`` destroys a GAMG KSP at once (made anew for each matrix anyway) and keeps
    MUMPS' (its analysis serves the next matrix); a solve after it raises one clear line,
    and the next factorization solves to the same bits as before."""
    A, points, b = _newton_matrix()
    solver = PetscSolver(SolverOptions(points=points, petsc_options=options))
    solver.analyse(A)
    solver.factorize(A)
    first = solver.solve(b)
    ksp = solver._ksp
    solver.release()
    gamg = "gamg" in options
    assert (solver._ksp is None) == gamg
    if not gamg:
        assert solver._ksp is ksp
    with pytest.raises(RuntimeError, match="petsc: no factorization to solve with"):
        solver.solve(b)
    solver.factorize(A)
    assert np.array_equal(solver.solve(b), first)


def test_release_of_a_direct_solver_then_refactorize():
    """Any direct solver: a solve after ``release`` raises, a factorization after it
    solves as before (SciPy's SuperLU: no optional library)."""
    A, _, b = _newton_matrix()
    solver = LINEAR_SOLVERS["superlu"]()
    solver.analyse(A)
    solver.factorize(A)
    first = solver.solve(b)
    solver.release()
    with pytest.raises(RuntimeError, match="superlu: no factorization to solve with"):
        solver.solve(b)
    solver.factorize(A)  # SuperLU's second factorization takes another path: not the bits
    assert np.linalg.norm(solver.solve(b) - first) <= 1e-12 * np.linalg.norm(first)


@needs_petsc
def test_newton_releases_the_gamg_hierarchy_after_each_direction(tmp_path, monkeypatch):
    """Newton's ``direct`` direction releases the factorization once its direction is
    solved: with GAMG no KSP is alive while the next Newton matrix is assembled, one is
    still made per Newton matrix, and the run is the one it was without the release (the
    same bits)."""
    from fem3d.solve.directions import NewtonDirection

    extra = 'petsc_options = "-ksp_type cg -pc_type gamg"'
    scene = load_scene(str(write_scene(tmp_path, linear_solver="petsc", extra=extra)))
    alive_at_assembly: list[bool] = []
    made: list[int] = []
    new_ksp, matrix = PetscSolver._new_ksp, NewtonDirection.matrix

    def counting_new_ksp(self):
        made.append(1)
        return new_ksp(self)

    def watched_matrix(self, x, psd):
        solver = self.system._solver
        alive_at_assembly.append(solver is not None and solver._ksp is not None)
        return matrix(self, x, psd)

    monkeypatch.setattr(PetscSolver, "_new_ksp", counting_new_ksp)
    monkeypatch.setattr(NewtonDirection, "matrix", watched_matrix)
    runs = {}
    for release in (True, False):
        if not release:
            monkeypatch.setattr(PetscSolver, "_release", lambda self: None)
        sim = Simulation(scene)
        made.clear()
        alive_at_assembly.clear()
        for _ in range(3):
            sim.step()
        runs[release] = (sim.q.copy(), list(alive_at_assembly), len(made))
    q, alive, n_made = runs[True]
    assert len(alive) > 3 and not any(alive)
    assert all(runs[False][1][1:])  # kept until the next factorization: alive at assembly
    assert n_made == runs[False][2] == len(alive)
    assert np.array_equal(q, runs[False][0])
