"""A missing optional extra is one line naming the extra to install, exit status 2, and nothing
written (no output folder, no lock file). Every extra is installed here, so each test hides
one module from a fresh interpreter (``sys.modules[name] = None`` in a sitecustomize)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from fem3d.io import extras

ROOT = Path(__file__).resolve().parents[2]


def _fem3d(tmp_path: Path, hidden: str, *argv: str, **env: str) -> subprocess.CompletedProcess:
    site = tmp_path / "site"
    site.mkdir(exist_ok=True)
    (site / "sitecustomize.py").write_text(
        f"import sys\nfor m in {hidden.split(',')!r}:\n    sys.modules[m] = None\n")
    full = {k: v for k, v in os.environ.items() if k != "FEM3D_SOLVER"}
    full.update(PYTHONPATH=f"{site}{os.pathsep}{ROOT}", OMP_NUM_THREADS="1",
                FEM3D_CACHE=str(tmp_path / "cache"), **env)  # an empty tet cache
    return subprocess.run([sys.executable, "-m", "fem3d", *argv], cwd=tmp_path, env=full,
                          capture_output=True, text=True, timeout=300)


def _one_line(r: subprocess.CompletedProcess, extra: str) -> str:
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert f"pip install 'fem3d[{extra}]'" in lines[0] and "Traceback" not in r.stderr
    return lines[0]


def test_sweep_without_dask_distributed(tmp_path):
    out = tmp_path / "sweep"
    r = _fem3d(tmp_path, "distributed", "sweep", str(ROOT / "data/sweeps/arma_stiffness.toml"),
               "--out", str(out))
    line = _one_line(r, "sweep")
    assert line.startswith("fem3d sweep: error: fem3d sweep (Dask) needs dask.distributed")
    assert "cases" not in r.stdout + r.stderr  # refused before announcing the cases
    assert not out.exists()


def test_usd_frames_without_usd_core(tmp_path):
    out = tmp_path / "usd"
    r = _fem3d(tmp_path, "pxr", "run", "cantilever", "--format", "usd", "--out", str(out))
    line = _one_line(r, "scenes")
    assert "--format usd (output.format) needs usd-core (module pxr)" in line
    assert not out.exists()  # no folder holding only .fem3d.lock


def test_surface_body_without_wildmeshing(tmp_path):
    out = tmp_path / "surf"
    r = _fem3d(tmp_path, "wildmeshing", "run", str(ROOT / "data/scenes/bunny_surface.toml"),
               "--out", str(out))
    line = _one_line(r, "scenes")
    assert "coarser_bunny.obj" in line and "fTetWild (module wildmeshing)" in line
    assert not out.exists()


def test_cholmod_asked_for_without_scikit_sparse(tmp_path):
    out = tmp_path / "chol"
    r = _fem3d(tmp_path, "sksparse", "run", "cantilever", "--steps", "1", "--out", str(out),
               FEM3D_SOLVER="cholmod")
    line = _one_line(r, "cholmod")
    assert "'cholmod' (FEM3D_SOLVER) is not installed" in line
    assert not out.exists()


def test_viewer_without_viser(tmp_path):
    r = _fem3d(tmp_path, "viser", "view", "bunny")
    assert "fem3d view: error: the viewer needs viser" in _one_line(r, "view")


def test_require_names_what_needs_it_and_passes_when_installed(monkeypatch):
    extras.require("pxr", "x")  # installed here: no error
    monkeypatch.setitem(sys.modules, "pxr", None)
    assert not extras.has_module("pxr")
    with pytest.raises(extras.MissingExtra, match=r"^USD needs usd-core \(module pxr\): pip "):
        extras.require("pxr", "USD")
    assert set(extras.EXTRAS) >= {"distributed", "pxr", "wildmeshing", "sksparse", "viser"}
