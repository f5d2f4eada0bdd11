"""`fem3d sweep` on a 2-worker LocalCluster: results, resuming, a killed worker, datasets.

Small fast cases: the armadillo's simulation mesh (no skin), a few backward-Euler steps.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.io.dataset import load_case, load_sweep, read_run_frames

ROOT = Path(__file__).resolve().parents[2]
MESH = ROOT / "data" / "arma_6.node"
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}


def _sweep_file(folder: Path, body: str, name: str = "s.toml") -> Path:
    p = folder / name
    p.write_text(f'scene = "{MESH}"\n' + textwrap.dedent(body), encoding="utf-8")
    return p


def _results(out: Path) -> list[dict[str, str]]:
    with open(out / "results.csv", newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


SWEEP = """
[set]
"simulation.steps" = 4
[grid]
"bodies[0].material.E" = [2e5, 6e5]
[[cases]]
"bodies[0].material.nu" = 0.35
[[cases]]                               # rejected by the scene
"bodies[0].material.nu" = 0.7
[[cases]]                               # explodes at step 1
"simulation.integrator" = "linear"
"pulls[0].offset" = [0.0, 0.0, 50.0]
"pulls[0].stiffness" = 1e8
[dataset]
dtype = "float32"
"""
NU, INTEGRATOR = "bodies[0].material.nu", "simulation.integrator"
STATUSES = ["ok", "failed", "failed"] * 2


def _main(*args: str) -> tuple[int, str]:
    """``fem3d ARGS`` in this process: exit status and stderr."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = main(list(args))
    return rc, err.getvalue()


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    """A 6-case sweep run once with 2 workers: 2 ok, 2 rejected (nu = 0.7), 2 exploding."""
    folder = tmp_path_factory.mktemp("sweep")
    spec = _sweep_file(folder, SWEEP)
    out = folder / "out"
    rc, err = _main("sweep", str(spec), "--workers", "2", "--out", str(out), "--quiet")
    return spec, out, rc, err


def test_results_table_and_failed_cases(swept):
    spec, out, rc, err = swept
    assert rc == 1, err  # some cases failed
    assert "2 ok, 4 failed, 0 lost" in err
    rows = _results(out)
    assert [r["case"] for r in rows] == [str(i) for i in range(6)]
    assert [r["status"] for r in rows] == STATUSES
    assert [float(r["bodies[0].material.E"]) for r in rows] == [2e5] * 3 + [6e5] * 3
    assert [r[NU] for r in rows] == ["0.35", "0.7", ""] * 2
    assert [r[INTEGRATOR] for r in rows] == ["", "", "linear"] * 2
    for r in rows:
        if r[NU] == "0.7":  # rejected before running: no folder
            assert r["message"].startswith(f"invalid: {spec} case {r['case']}: ")
            assert "bodies[0].material.nu: Input should be less than 0.5" in r["message"]
            assert not (out / "cases" / r["id"]).exists()
            continue
        if r[INTEGRATOR] == "linear":  # ran, exploded, recorded; the sweep went on
            assert "step 1: linearly-implicit Euler exploded" in r["message"], r["message"]
            summary = json.loads((out / "cases" / r["id"] / "summary.json").read_text())
            assert summary["status"] == "failed" and int(r["steps"]) == 1
            assert not (out / "cases" / r["id"] / "trajectory.npz").exists()
            continue
        assert int(r["steps"]) == 4 and float(r["wall_seconds"]) > 0
        for col in ("kinetic_final", "potential_final", "total_final", "total_max",
                    "max_displacement", "newton_iterations"):
            assert np.isfinite(float(r[col])), col
        assert r["worker"].startswith("tcp://") and r["attempt"] == "1"
        case = out / "cases" / r["id"]
        started = json.loads((case / "started.json").read_text())
        assert started["threads"] == {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
        summary = json.loads((case / "summary.json").read_text())
        assert summary["status"] == "ok" and summary["id"] == r["id"]
        assert summary["digest"].startswith(r["id"]) and len(summary["digest"]) == 64
        assert json.loads((case / "scene.json").read_text())  # the resolved scene
    assert (out / "results.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the stiffer armadillo moves less under the same pull
    ok = [r for r in rows if r["status"] == "ok"]
    assert float(ok[1]["max_displacement"]) < float(ok[0]["max_displacement"])


def test_cases_equal_fem3d_run_one_by_one(swept, tmp_path):
    """Each case of the sweep is bit for bit what `fem3d run` gives with the same overrides."""
    _, out, _, _ = swept
    for r in (r for r in _results(out) if r["status"] == "ok"):
        alone = tmp_path / r["id"]
        sets = ["simulation.steps=4", f"bodies[0].material.E={r['bodies[0].material.E']}",
                f"bodies[0].material.nu={r[NU]}"]
        rc, err = _main("run", str(MESH), *(a for s in sets for a in ("--set", s)),
                        "--out", str(alone), "--no-preview", "--quiet")
        assert rc == 0, err
        case = out / "cases" / r["id"]
        for a, b in zip(read_run_frames(case), read_run_frames(alone), strict=True):
            np.testing.assert_array_equal(a, b)
        assert (case / "energy.csv").read_bytes() == (alone / "energy.csv").read_bytes()


def test_dataset_matches_frames(swept):
    _, out, _, _ = swept
    data = load_sweep(out)
    assert data.keys == ["bodies[0].material.E", NU, INTEGRATOR, "pulls[0].offset",
                         "pulls[0].stiffness"]
    assert len(data) == 2  # the ok cases
    np.testing.assert_array_equal(data.params(["bodies[0].material.E", NU]),
                                  [[2e5, 0.35], [6e5, 0.35]])
    assert np.isnan(data.params(["pulls[0].stiffness"])).all()
    Y = data.positions()
    assert Y.dtype == np.float32 and Y.shape[:2] == (2, 5) and Y.shape[3] == 3
    for case in data:
        steps, times, P, faces = read_run_frames(case.path.parent)
        np.testing.assert_array_equal(case.positions, P.astype(np.float32))
        np.testing.assert_array_equal(case.rest, P[0])
        np.testing.assert_array_equal(case.steps, np.arange(5))
        np.testing.assert_array_equal(case.times, times)
        np.testing.assert_array_equal(case.faces, faces)
        assert case.summary["status"] == "ok"
        again = load_case(case.path)
        assert again.id == case.id and again.params == case.params


def test_second_invocation_runs_nothing_then_redoes_a_partial_case(swept, tmp_path):
    # on a copy: the module's sweep stays as run for the other tests, in any order
    spec, out = swept[0], tmp_path / "out"
    shutil.copytree(swept[1], out)
    rows = _results(out)
    ok = [r["id"] for r in rows if r["status"] == "ok"]
    stamps = {i: (out / "cases" / i / "summary.json").stat().st_mtime_ns for i in ok}
    start = time.perf_counter()
    rc, err = _main("sweep", str(spec), "--workers", "2", "--out", str(out), "--quiet")
    assert rc == 1, err
    assert "(0 to run, 4 complete before, 2 rejected)" in err
    assert "ran 0, skipped 4" in err
    assert stamps == {i: (out / "cases" / i / "summary.json").stat().st_mtime_ns for i in ok}
    assert _results(out) == rows
    print(f"no-op sweep: {time.perf_counter() - start:.2f} s")
    # a case interrupted half-way: no summary.json, a stale frame; the next run redoes it,
    # and --retry-failed runs the exploding cases again
    partial = out / "cases" / ok[0]
    (partial / "summary.json").unlink()
    (partial / "frames" / "frame_00004.vtu").write_bytes(b"garbage")
    rc, err = _main("sweep", str(spec), "--workers", "1", "--out", str(out), "--quiet",
                    "--retry-failed")
    assert "(3 to run, 1 complete before, 2 rejected)" in err, err
    again = _results(out)
    assert [r["status"] for r in again] == STATUSES
    assert again[0]["attempt"] == "2"
    assert (out / "cases" / ok[1] / "summary.json").stat().st_mtime_ns == stamps[ok[1]]
    for col in ("steps", "total_final", "max_displacement", "kinetic_final"):
        assert again[0][col] == rows[0][col]
    steps, _, P, _ = read_run_frames(partial)
    assert list(steps) == [0, 1, 2, 3, 4] and np.isfinite(P).all()


@pytest.mark.slow  # a sweep process of its own, and a worker started again
def test_killed_worker_loses_no_case(tmp_path):
    spec = _sweep_file(tmp_path, """
        [set]
        "simulation.steps" = 20
        [grid]
        "bodies[0].material.E" = [2e5, 3e5, 4e5, 5e5]
    """)
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "fem3d", "sweep", str(spec), "--workers", "2", "--out",
         str(out), "--quiet"], cwd=ROOT, env=ENV, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True,
    )
    try:
        deadline = time.monotonic() + 120
        victim = None
        while victim is None and time.monotonic() < deadline and proc.poll() is None:
            for f in sorted((out / "cases").glob("*/started.json")):
                if (f.parent / "summary.json").exists():
                    continue  # finished already: find one that is running
                try:
                    victim = (f.parent, json.loads(f.read_text())["pid"])
                    break
                except (OSError, ValueError):
                    pass
            time.sleep(0.02)
        assert victim is not None, "no case started"
        folder, pid = victim
        assert not (folder / "summary.json").exists()  # mid-case
        os.kill(pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "4 ok, 0 failed, 0 lost" in err
    rows = _results(out)
    assert [r["status"] for r in rows] == ["ok"] * 4
    killed = next(r for r in rows if r["id"] == folder.name)
    assert killed["attempt"] == "2" and int(killed["steps"]) == 20
    assert json.loads((folder / "started.json").read_text())["pid"] != pid


def test_bad_key_path_is_one_line_exit_2(tmp_path, capsys):
    for key, message in (
        ("bodies[0].materal.E", "bodies[0] has no field 'materal'"),
        ("bodies[3].material.E", "index 3 out of range: bodies has 1 entries"),
    ):
        spec = _sweep_file(tmp_path, f'[grid]\n"{key}" = [1.0, 2.0]\n')
        assert main(["sweep", str(spec), "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"{spec}: {key}: {message}" in err, err
        assert not (tmp_path / "out").exists()


#: loaded by every worker process of the external cluster below (via PYTHONPATH): the case
#: whose E is 3e5 kills its worker each time it starts, as a segfaulting kernel would
@pytest.mark.slow  # an external cluster of two worker processes
def test_sweep_on_an_external_scheduler(tmp_path, monkeypatch):
    """``--scheduler ADDRESS`` on an external ``LocalCluster``: every case runs there (in its
    workers' processes, not in this one) and ends ok with its steps."""
    dask = pytest.importorskip("dask")
    distributed = pytest.importorskip("distributed")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    spec = _sweep_file(tmp_path, """
        [set]
        "simulation.steps" = 2
        [grid]
        "bodies[0].material.E" = [2e5, 3e5, 4e5]
    """)
    out = tmp_path / "out"
    with dask.config.set({"distributed.scheduler.allowed-failures": 3}), \
            distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                     dashboard_address=None) as cluster:
        rc, err = _main("sweep", str(spec), "--scheduler", cluster.scheduler_address,
                        "--out", str(out), "--quiet")
    assert rc == 0, err
    assert "3 ok, 0 failed, 0 lost" in err, err
    rows = _results(out)
    assert [r["status"] for r in rows] == ["ok", "ok", "ok"]
    assert all(int(r["steps"]) == 2 for r in rows)


_KILL_EVERY_WORKER = '''
import os
if os.environ.get("FEM3D_TEST_SABOTAGE"):
    import fem3d.app.sweep.run as _run

    def run_case(task):
        os._exit(1)  # the worker process dies with the case, every time

    _run.run_case = run_case
'''


@pytest.mark.slow  # an external cluster whose worker is restarted three times
def test_a_case_that_kills_its_worker_is_lost_after_three_deaths(tmp_path, monkeypatch):
    """A case whose run kills the worker process every time is given up after Dask's allowed
    failures (3) and recorded ``lost`` with the ``KilledWorker`` reason; the sweep exits 1. One
    case and one worker: no other case can be taken down with it (Dask also counts the tasks a
    dying worker held), so the count is exact."""
    dask = pytest.importorskip("dask")
    distributed = pytest.importorskip("distributed")
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(_KILL_EVERY_WORKER, encoding="utf-8")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(site), str(ROOT)]))
    monkeypatch.setenv("FEM3D_TEST_SABOTAGE", "1")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    spec = _sweep_file(tmp_path, """
        [set]
        "simulation.steps" = 2
        [grid]
        "bodies[0].material.E" = [3e5]
    """)
    out = tmp_path / "out"
    with dask.config.set({"distributed.scheduler.allowed-failures": 3}), \
            distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                     dashboard_address=None) as cluster:
        rc, err = _main("sweep", str(spec), "--scheduler", cluster.scheduler_address,
                        "--out", str(out), "--quiet")
    assert rc == 1, err
    assert "0 ok, 0 failed, 1 lost" in err, err
    (row,) = _results(out)
    assert row["status"] == "lost" and "KilledWorker" in row["message"], row
