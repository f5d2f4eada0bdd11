"""The output formats as a registry (:mod:`fem3d.io.frames`): the scene's ``output.format``
choices, ``--format``, the sweeps' check and the extras come from it, and a format registered
from outside fem3d (``tests/io/frame_format_plugin.py``) is written by ``fem3d run --format``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import meshio
import numpy as np
import pytest

from fem3d.app.cli import build_parser, main
from fem3d.app.sweep.plan import plan_sweep
from fem3d.app.sweep.spec import load_sweep_file
from fem3d.errors import InputError
from fem3d.io.extras import MissingExtra
from fem3d.io.frames import FRAME_FORMATS, frame_format, frame_format_names, make_frame_writer
from fem3d.scene import scene_schema

ROOT = Path(__file__).resolve().parents[2]


def test_the_schema_and_the_cli_list_the_registered_formats() -> None:
    assert frame_format_names() == ("vtu", "obj", "usd")
    enum = scene_schema()["$defs"]["OutputSpec"]["properties"]["format"]["enum"]
    assert tuple(enum) == frame_format_names()
    run = build_parser()._subparsers._group_actions[0].choices["run"]
    action = next(a for a in run._actions if "--format" in a.option_strings)
    assert tuple(action.choices) == frame_format_names()
    assert all(f"{f.name}: {f.summary}" in action.help for f in FRAME_FORMATS.values())


def test_unknown_format_and_missing_extra(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(InputError, match="unknown output format 'stl'; available: vtu, obj, usd"):
        make_frame_writer(tmp_path, np.array([[0, 1, 2]]), "stl")
    assert [f.extra for f in FRAME_FORMATS.values()] == [None, None, "pxr"]
    monkeypatch.setitem(sys.modules, "pxr", None)  # usd-core hidden
    with pytest.raises(MissingExtra, match=r"--format usd \(output.format\) needs usd-core"):
        frame_format("usd").require()
    frame_format("vtu").require()  # needs nothing


def test_a_sweep_dataset_needs_a_format_read_back(tmp_path: Path) -> None:
    sweep = tmp_path / "s.toml"
    sweep.write_text("scene = 'arma'\n[set]\n'output.format' = 'usd'\n'simulation.steps' = 2\n"
                     "[grid]\n'simulation.dt' = [0.01]\n[dataset]\n")
    plan = plan_sweep(load_sweep_file(sweep), tmp_path / "out")
    assert [c.error for c in plan.cases] == [
        "invalid: dataset mode reads the run's frames: output.format must be 'vtu' or 'obj', "
        "got 'usd'"]


def test_a_registered_format_is_written_by_fem3d_run(tmp_path: Path) -> None:
    """The toy ``npz`` format: registered before the scene schema is built (a plug-in's
    order), ``fem3d run --format npz`` writes a frame per step with the positions a VTU
    run writes."""
    script = ("import sys, tests.io.frame_format_plugin; from fem3d.app.cli import main; "
              "sys.exit(main(sys.argv[1:]))")
    args = ["run", str(ROOT / "data" / "arma_6.node"), "--steps", "3", "--no-preview",
            "--quiet"]
    proc = subprocess.run([sys.executable, "-c", script, *args, "--format", "npz",
                           "--out", str(tmp_path / "npz")], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert main([*args, "--format", "vtu", "--out", str(tmp_path / "vtu")]) == 0
    files = sorted(p.name for p in (tmp_path / "npz" / "frames").iterdir())
    assert files == [f"frame_{k:05d}.npz" for k in range(4)]
    for k in range(4):
        with np.load(tmp_path / "npz" / "frames" / f"frame_{k:05d}.npz") as data:
            vtu = meshio.read(tmp_path / "vtu" / "frames" / f"frame_{k:05d}.vtu")
            np.testing.assert_array_equal(data["positions"], vtu.points)
            np.testing.assert_array_equal(data["faces"], vtu.cells_dict["triangle"])
    # without the plug-in the name is refused in one line, exit 2
    assert main([*args, "--set", "output.format='npz'", "--out", str(tmp_path / "no")]) == 2
