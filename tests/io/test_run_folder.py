"""A finished run folder holds the run's outputs and no lock file, however the run ended:
normally, failed (exit 1), interrupted (exit 130); a stale lock after ``kill -9`` is taken
over; two runs racing for a folder still exclude each other (fem3d.io.rundir)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fem3d.app.cli import main
from fem3d.errors import InputError, SimulationError
from fem3d.io import rundir

ROOT = Path(__file__).resolve().parents[2]
QUICK = ["--steps", "3", "--no-preview", "--quiet"]


def _hidden(out: Path) -> list[str]:
    return sorted(p.name for p in out.rglob(".*"))


def test_a_finished_run_leaves_no_lock(tmp_path, capsys):
    out = tmp_path / "bunny"
    assert main(["run", "bunny", *QUICK, "--checkpoint-every", "3", "--out", str(out)]) == 0
    assert (out / "energy.csv").is_file() and _hidden(out) == []
    assert main(["resume", str(out), "--steps", "5", "--quiet"]) == 0
    assert _hidden(out) == []
    capsys.readouterr()


def test_a_failed_run_leaves_no_lock(tmp_path, capsys, monkeypatch):
    from fem3d.simulation import Simulation

    step = Simulation.step

    def blow_up(self):  # noqa: ANN001, ANN202
        if self.step_index == 2:
            raise SimulationError("non-finite state", step=3)
        return step(self)

    monkeypatch.setattr(Simulation, "step", blow_up)
    out = tmp_path / "bunny"
    assert main(["run", "bunny", *QUICK, "--out", str(out)]) == 1
    assert "simulation failed" in capsys.readouterr().err
    assert (out / "energy.csv").is_file() and _hidden(out) == []


def test_an_interrupted_run_leaves_no_lock(tmp_path):
    out = tmp_path / "arma"
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "fem3d", "run", "bunny", "--steps", "100000", "--no-preview",
         "--quiet", "--checkpoint-every", "2", "--out", str(out)],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while not (out / "checkpoint.npz").exists():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the run never checkpointed"
            time.sleep(0.05)
        assert (out / rundir.LOCK_NAME).exists()  # held while running
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert _hidden(out) == []


def test_a_stale_lock_is_taken_over_and_removed(tmp_path, capsys):
    out = tmp_path / "bunny"
    out.mkdir()
    (out / rundir.LOCK_NAME).write_text("pid=999999\ncommand=fem3d run bunny\n")  # kill -9
    assert main(["run", "bunny", *QUICK, "--out", str(out)]) == 0
    assert _hidden(out) == []
    capsys.readouterr()


def test_a_held_folder_is_refused_and_freed_after(tmp_path):
    out = tmp_path / "o"
    with rundir.claim(out):
        with pytest.raises(InputError, match=f"in use by process {os.getpid()}"), \
                rundir.claim(out):
            pass
        assert (out / rundir.LOCK_NAME).exists()
    assert not (out / rundir.LOCK_NAME).exists()


def test_a_run_that_opened_the_lock_before_it_was_removed_starts_over(tmp_path, monkeypatch):
    """B opens the lock file while A holds it; A ends (unlinks it); B's flock on the removed
    file succeeds, but B must notice and lock a new file, else a third run C could lock the
    new file too and two runs would write one folder."""
    out = tmp_path / "o"
    with rundir.claim(out):
        stale = os.open(out / rundir.LOCK_NAME, os.O_RDWR)  # B's open, before A ends
    real_open = os.open
    opened = []

    def open_once_stale(path, flags, mode=0o777):  # noqa: ANN001, ANN202
        if Path(path).name == rundir.LOCK_NAME and not opened:
            opened.append(path)
            return stale
        return real_open(path, flags, mode)

    monkeypatch.setattr(os, "open", open_once_stale)
    with rundir.claim(out):  # B
        monkeypatch.setattr(os, "open", real_open)
        assert (out / rundir.LOCK_NAME).exists()  # B holds a file the name leads to
        with pytest.raises(InputError, match="in use"), rundir.claim(out):  # C
            pass
    assert opened and not (out / rundir.LOCK_NAME).exists()
