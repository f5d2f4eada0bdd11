"""``fem3d`` command lines one after another in one process: under ``mpiexec``, on every rank.

Each launch of ranks costs about 1.5 s of start-up on this project's 2-core machine (Python,
fem3d, MPI and PETSc imported on every rank) against well under a second for a run of the
tests' box, so the tests whose runs only make outputs to compare launch them together
(:func:`tests.parallel.helpers.run_mpi_batch`). What a run does when it fails (exit statuses,
``MPI_Abort``, signals) stays tested by runs launched one by one.

    python batch_runs.py PLAN.json

``PLAN.json`` maps a name to a command line (``["run", "box.toml", "--out", "out"]``); rank 0
writes ``PLAN.results.json``: each name's exit status and what the run wrote to stderr.
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
from pathlib import Path

from fem3d.app.cli import main
from fem3d.parallel.comm import launched_rank


def run_plan(plan: Path) -> dict[str, dict[str, object]]:
    """Each command line of ``plan`` through :func:`fem3d.app.cli.main`, in order."""
    results: dict[str, dict[str, object]] = {}
    for name, argv in json.loads(plan.read_text()).items():
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            status = main(argv)
        results[name] = {"status": status, "stderr": err.getvalue()}
    return results


if __name__ == "__main__":
    plan = Path(sys.argv[1])
    results = run_plan(plan)
    if launched_rank() == 0:
        plan.with_suffix(".results.json").write_text(json.dumps(results))
