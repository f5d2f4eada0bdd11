"""A new user's first ten minutes: what ``fem3d view`` prints, unknown-scene messages, docs."""

from __future__ import annotations

from pathlib import Path

import pytest

from fem3d.app.viewer.logic import HOTKEYS, console_help
from fem3d.errors import InputError
from fem3d.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]


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
