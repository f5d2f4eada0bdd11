"""A misspelled required key keeps its "did you mean" (issue 39): pydantic reports both the
missing required key and the unknown one; the unknown key, whose hint names the missing one,
is what the one-line error says."""

from __future__ import annotations

from pathlib import Path

import pytest

from fem3d.app.cli import main
from fem3d.errors import InputError
from fem3d.scene import apply_overrides, load_scene

DATA = Path(__file__).resolve().parents[2] / "data"

SCENE = f'''
[simulation]
steps = 2

[[bodies]]
mesh = "{DATA / "contact_block.mesh"}"
material = {{ model = "neo_hookean", E = 1e6, nu = 0.3, density = 1000.0 }}

[contact]
enabled = true

[[obstacles]]
plane = {{ point = [0.0, -1.0, 0.0], normal = [0.0, 1.0, 0.0] }}
'''

CASES = {
    "body material": (SCENE.replace("material =", "materail ="),
                      "bodies[0].materail: unknown key; did you mean 'material'?"),
    "plane normal": (SCENE.replace("normal =", "norml ="),
                     "obstacles[0].plane.norml: unknown key; did you mean 'normal'?"),
    "top-level bodies": (SCENE.replace("[[bodies]]", "[[bodeis]]"),
                         "bodeis: unknown key; did you mean 'bodies'?"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_misspelled_required_key_through_cli(case, tmp_path, capsys):
    text, needle = CASES[case]
    p = tmp_path / "scene.toml"
    p.write_text(text)
    out = tmp_path / "out"
    status = main(["run", str(p), "--out", str(out), "--quiet", "--no-preview"])
    err = capsys.readouterr().err.strip()
    assert status == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith(f"fem3d run: error: {p}: {needle}"), err
    assert "missing" not in err and "more)" not in err, err  # the missing key is explained
    assert not out.exists()


def test_unrelated_unknown_key_leaves_missing_key_reported(tmp_path):
    """An unknown key that is no misspelling of the missing one explains nothing."""
    p = tmp_path / "scene.toml"
    p.write_text(SCENE.replace("material =", "colour = 1\nstuff ="))
    with pytest.raises(InputError) as info:
        load_scene(p)
    assert "bodies[0].material: missing (required) (and 2 more)" in str(info.value)


def test_misspelled_required_key_in_override():
    s = load_scene("arma")
    d = s.to_dict()["bodies"][0]
    d["materail"] = d.pop("material")
    with pytest.raises(InputError) as info:
        apply_overrides(s, {"bodies[0]": d})
    assert str(info.value).startswith(
        "override: bodies[0].materail: unknown key; did you mean 'material'?"), info.value
