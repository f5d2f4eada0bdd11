"""The ghost exchange of rank-local vectors (:class:`fem3d.parallel.ghosts.Ghosts`) and the
rank-local DOF layout (:func:`fem3d.parallel.partition.local_layout`): on 3 ranks under
``mpiexec`` (tests/parallel/ghost_checks.py) and in one process."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fem3d.parallel.ghosts import Ghosts
from fem3d.parallel.partition import local_layout
from fem3d.solve.linear.petsc import DofLayout
from tests.parallel.helpers import mpi_env, mpiexec_or_skip

CHECKS = Path(__file__).with_name("ghost_checks.py")


@pytest.mark.alone
def test_ghosts_and_local_layout_on_three_ranks(tmp_path):
    """A 384-tet box cut by METIS on 3 ranks: assembled partial sums equal one process's
    ``np.add.at`` to 1e-14, summed in rank order with the same bits on every holder (an
    entry held alone unchanged); ghosts complete to their owner's values; the local layout
    numbers every free DOF once; PETSc's solve with local vectors (MUMPS, CG + GAMG) equals
    scipy's, ghosts included."""
    out = tmp_path / "ghosts.json"
    cmd = [*mpiexec_or_skip(), "3", sys.executable, str(CHECKS), str(out)]
    proc = subprocess.run(cmd, env=mpi_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads(out.read_text())
    assert r["ranks"] == 3 and min(r["tets_per_rank"]) > 0
    assert r["owner_ok"] and r["shared_entries"] > 0
    assert r["assemble_error_rows"] < 1e-14 and r["assemble_error_flat"] < 1e-14
    assert r["rows_equal_flat_bits"] and r["alone_unchanged"] and r["assemble_is_copy"]
    assert r["rank_order_bits"] and r["holders_same_bits"]
    assert r["complete_ok"]
    assert r["n"] == r["n_expected"] == sum(r["counts"]) and min(r["counts"]) > 0
    assert r["owned_rows_once"] and r["start_ok"] and r["order_same_on_holders"]
    assert r["layout_ghosts"]
    for name, pc in (("mumps", "cholesky"), ("gamg", "gamg")):
        assert r[f"solve_pc_{name}"] == pc
        assert r[f"solve_error_{name}"] < 1e-8, name
        assert r[f"solve_ghosts_same_bits_{name}"], name


#: a communicator of one rank with nothing but its size and rank: any exchange would fail
ONE_RANK = SimpleNamespace(Get_size=lambda: 1, Get_rank=lambda: 0)


def test_one_rank_copies_without_exchanging():
    """On one rank every entry is owned, and ``assemble`` and ``complete`` return copies of
    their input, bit for bit, rows too, without a call to the communicator."""
    ids = np.array([0, 3, 4, 9], dtype=np.uint32)
    g = Ghosts.build(ONE_RANK, ids)
    assert g.ids is ids and g.owner.tolist() == [0] * 4 and g.owned.all()
    for values in (np.array([-0.0, 1.5, np.nan, 1e-300]), np.arange(12.0).reshape(4, 3)):
        for out in (g.assemble(values), g.complete(values)):
            assert out.tobytes() == values.tobytes() and not np.shares_memory(out, values)
    layout, ghosts = local_layout(ONE_RANK, ids.astype(np.int64))
    assert layout.ghosts is ghosts and layout.n == 4 and layout.start == 0
    assert layout.order.tolist() == layout.owned.tolist() == [0, 1, 2, 3]
    assert layout.counts.tolist() == [4]
    # a whole-vector layout (no ghosts) keeps its fields; n is its rows' count
    whole = DofLayout(comm=ONE_RANK, order=np.arange(6), owned=np.arange(6), start=0,
                      counts=np.array([6]))
    assert whole.n == 6 and whole.ghosts is None


@pytest.mark.parametrize("ids, message", [
    (np.array([0, 2, 1]), "sorted and unique"), (np.array([1, 1]), "sorted and unique"),
    (np.array([0.0, 1.0]), "1-D integer array")])
def test_bad_ids_are_one_line(ids, message):
    with pytest.raises(ValueError, match=message):
        Ghosts.build(ONE_RANK, ids)


def test_values_of_another_length_are_one_line():
    g = Ghosts.build(ONE_RANK, np.arange(3))
    with pytest.raises(ValueError, match=r"values of shape \(4,\), expected \(3,\)"):
        g.assemble(np.zeros(4))


def test_petsc_solve_with_a_local_layout_on_one_rank():
    """PETSc with a one-rank local layout (the ghost path: local pattern, rows counted by
    ``assemble``, solution by ``complete``) solves as scipy does."""
    pytest.importorskip("petsc4py")
    from mpi4py import MPI

    from fem3d.solve.linear.base import SolverOptions
    from fem3d.solve.linear.petsc import PetscSolver

    n = 30
    rng = np.random.default_rng(3)
    B = sp.random(n, n, density=0.1, random_state=4)
    A = (B @ B.T + sp.eye(n) * n).tocsr()
    b = rng.standard_normal(n)
    layout, _ = local_layout(MPI.COMM_SELF, np.arange(n, dtype=np.int64) * 2)
    for options in ("", "-ksp_type cg -pc_type gamg -ksp_rtol 1e-12"):
        points = rng.standard_normal((n // 3, 3))
        solver = PetscSolver(SolverOptions(points=points, petsc_options=options),
                             layout=layout)
        solver.analyse(A)
        solver.factorize(A)
        x = solver.solve(b)
        assert np.linalg.norm(x - spla.spsolve(A.tocsc(), b)) < 1e-8 * np.linalg.norm(x)
