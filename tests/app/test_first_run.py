"""A new user's first ten minutes: what ``fem3d view`` prints, unknown-scene messages, docs."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from fem3d.app.viewer.logic import HOTKEYS, console_help
from fem3d.errors import InputError
from fem3d.scene import load_scene

ROOT = Path(__file__).resolve().parents[2]


def test_the_console_names_the_viewer_keys_that_work():
    line = console_help()
    assert f"{HOTKEYS['mesh']} mesh" in line and HOTKEYS["mesh"] == "M"
    assert "S mesh" not in line
    for key in HOTKEYS.values():
        assert key in line


def test_unknown_scene_lists_the_scenes():
    with pytest.raises(InputError) as info:
        load_scene("bunyn")
    msg = str(info.value)
    assert "did you mean 'bunny'" in msg and "use one of bunny, arma" in msg


def test_unknown_scene_without_built_in_scenes_says_where_it_looked(tmp_path, monkeypatch):
    monkeypatch.setenv("FEM3D_SCENES", str(tmp_path))
    with pytest.raises(InputError) as info:
        load_scene("bunny")
    msg = str(info.value)
    assert "use one of ," not in msg
    assert str(tmp_path) in msg and "FEM3D_SCENES" in msg


def test_docs_do_not_say_contact_is_refused():
    text = (ROOT / "docs" / "scenes.md").read_text(encoding="utf-8")
    assert "refuses `enabled = true`" not in text


# ----------------------------------------------------------------------------- the preview


def _two_squares(near_first: bool) -> tuple[np.ndarray, np.ndarray]:
    """Two unit squares facing the camera (+z), the second in front at z = 1 and shifted."""
    sq = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    V = np.vstack([sq, sq + [0.5, 0.5, 1.0]])
    far, near = np.array([[0, 1, 2], [0, 2, 3]]), np.array([[4, 5, 6], [4, 6, 7]])
    return V, (np.vstack([near, far]) if near_first else np.vstack([far, near]))


@pytest.mark.parametrize("near_first", [True, False])
def test_the_preview_draws_the_nearest_face_whatever_the_order(near_first):
    from fem3d.io.preview import _camera, _draw_frames

    V, F = _two_squares(near_first)
    right, up, toward = _camera(0.0, 0.0)  # looking along -z
    proj = np.stack([right, up, toward], axis=1)
    base = np.zeros((4, 3))
    base[F[:, 0] >= 4] = [1.0, 0.0, 0.0]  # the near square red, the far one black
    img = np.asarray(_draw_frames([V], F, proj, toward, base, 60, (0.75, 0.75, 0.75))[0])
    # the overlap (u, v in [0.5, 1]) is the near square's: pixels 30-39 right, 20-29 down
    assert (img[22:28, 32:38, 0] == 255).all() and (img[22:28, 32:38, 1] == 0).all()
    assert (img[45:50, 10:15] == 0).all()  # the far square alone: black
    assert (img[0:5, 0:5] == 255).all()  # paper


def test_skipping_back_faces_leaves_the_preview_unchanged():
    """A closed surface's back faces are skipped (half the work); the picture is the one
    of drawing them all. The decimated bunny skin stays a closed oriented surface."""
    from fem3d.io.preview import (
        _camera,
        _cluster_decimate,
        _draw_frames,
        _outward_sign,
    )
    from fem3d.mesh.formats import read_surface_mesh

    V, F = read_surface_mesh(ROOT / "data" / "bunny_skin.obj")
    A, Fd = _cluster_decimate(V, F, 6000)
    W = A @ V
    facing = _outward_sign(W, Fd)
    assert (facing == 1.0).all()  # closed and outward: every face may be skipped
    assert (_outward_sign(W, Fd[:, [0, 2, 1]]) == -1.0).all()
    assert (_outward_sign(W, Fd[1:]) == 0.0).all()  # a hole: nothing skipped
    right, up, toward = _camera(15.0, 30.0)
    proj = np.stack([right, up, toward], axis=1)
    P = W @ proj
    c = 0.5 * (P.min(axis=0) + P.max(axis=0))
    box = (c[0], c[1], 0.6 * float(np.ptp(P[:, :2], axis=0).max()))
    light = toward
    args = ([W], Fd, proj, light, np.array([0.8, 0.7, 0.6]), 120, box)
    culled = np.asarray(_draw_frames(*args, facing=facing)[0])
    whole = np.asarray(_draw_frames(*args)[0])
    assert (culled.sum(axis=2) < 3 * 255).mean() > 0.2  # the bunny is there
    np.testing.assert_array_equal(culled, whole)


def test_run_says_when_it_wrote_the_preview(tmp_path, capsys):
    from fem3d.app.cli import main

    out = tmp_path / "bunny"
    assert main(["run", "bunny", "--steps", "4", "--quiet", "--out", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"fem3d run: wrote {out / 'preview.gif'} (5 frames) and energy.png")
    assert (out / "preview.gif").is_file() and (out / "energy.png").is_file()


# ----------------------------------------------------------------------------- messages


def test_an_intersecting_start_is_said_in_plain_words(tmp_path, capsys):
    from fem3d.app.cli import main

    out = tmp_path / "x"
    status = main(["run", "contact_stack", "--set", "bodies[1].transform.translate=[-0.02,0.01,0]",
                   "--steps", "1", "--quiet", "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1, err
    assert err.endswith("contact_stack.toml: bodies: in the initial state, bodies[0] (bottom "
                        "block) and bodies[1] (bunny) intersect (not intersection-free)")
    assert not out.exists()


def test_a_fit_file_with_a_missing_target_names_file_key_and_path(tmp_path, capsys):
    from fem3d.app.cli import main

    text = (ROOT / "examples" / "fit" / "fit.toml").read_text(encoding="utf-8")
    fit = tmp_path / "fit.toml"
    scene = repr(str(ROOT / "examples" / "fit" / "cantilever.toml"))
    fit.write_text(text.replace('"cantilever.toml"', scene)
                   .replace('"../../out/fit_target"', '"nowhere/run"'), encoding="utf-8")
    assert main(["fit", str(fit), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert err.startswith(f"fem3d fit: error: {fit}: target = 'nowhere/run': "
                          f"{tmp_path / 'nowhere' / 'run'} does not exist (")
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- make run / test


def _make(tmp_path: Path, target: str, fail_on: str = "", status: int = 0) -> list[str]:
    """``make TARGET`` in a copy of the build files, with a stand-in python that prints how it
    is called (``-c`` snippets run for real) instead of installing or running anything, and
    fails when its arguments contain ``fail_on``."""
    for rel in ("Makefile", "pyproject.toml", "setup.py", "scripts/install_cholmod.sh",
                "scripts/install_chromium.sh", *(str(p.relative_to(ROOT)) for p in
                                                   (ROOT / "generated" / "c").glob("*.c"))):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / rel, tmp_path / rel)
    fake = tmp_path / "python"
    fake.write_text('#!/bin/bash\nif [ "$1" = "-c" ]; then exec python3 "$@"; fi\n'
                    'echo "PY $*"\n'
                    + (f'case "$*" in *{fail_on}*) echo "boom" >&2; exit 1;; esac\n'
                       if fail_on else ""))
    fake.chmod(0o755)
    r = subprocess.run(["make", "--no-print-directory", target, f"PYTHON={fake}"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env={**os.environ, "CHROMIUM": "/bin/true"})
    assert (r.returncode != 0) == bool(status), r.stdout + r.stderr
    return (r.stdout + r.stderr).splitlines()


def _index(lines: list[str], needle: str) -> int:
    hits = [i for i, line in enumerate(lines) if needle in line]
    assert hits, f"{needle!r} not in:\n" + "\n".join(lines)
    return hits[0]


def test_make_run_says_what_it_does_at_each_stage(tmp_path):
    lines = _make(tmp_path, "run")
    first = _index(lines, "[1/3] installing fem3d's dependencies")
    assert "building its C kernels" in lines[first] and "minute" in lines[first]
    order = [first,
             _index(lines, "PY -m pip install -q setuptools>=68 wheel"),
             _index(lines, "[2/3] CHOLMOD"),
             _index(lines, "[3/3] simulating the bunny"),
             _index(lines, "PY -m fem3d run bunny --out runs/bunny")]
    assert order == sorted(order)
    # the dependencies and the C build, both before CHOLMOD
    assert order[1] < _index(lines, "numpy>=1.26 scipy>=1.11") < order[2]
    assert order[1] < _index(lines, "--no-deps --no-build-isolation -e .") < order[2]


def test_make_run_stops_when_the_c_build_fails(tmp_path):
    lines = _make(tmp_path, "run", fail_on="--no-build-isolation", status=2)
    assert _index(lines, "building fem3d's C kernels failed")
    assert not any("[2/3]" in line or "fem3d run bunny" in line for line in lines)
    assert not (tmp_path / ".venv-run-stamp").exists()


def test_make_test_says_up_front_that_it_installs_chromium_and_why(tmp_path):
    lines = _make(tmp_path, "test")
    first = lines[0]
    assert "Debian's chromium" in first and "browser test of the viewer" in first
    assert _index(lines, "PY -m pip install") > 0  # announced before anything is installed
    assert _index(lines, "chromium present") < _index(lines, "PY -m pytest")
