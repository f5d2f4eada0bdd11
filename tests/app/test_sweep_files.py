"""Sweep files: validation (one line naming the key, exit 2), case expansion, key paths."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest
from pydantic import BaseModel, ConfigDict

from fem3d.app.cli import main
from fem3d.app.sweep.plan import check_key_path, expand_cases
from fem3d.app.sweep.spec import load_sweep_file
from fem3d.errors import InputError

ROOT = Path(__file__).resolve().parents[2]


def _write(tmp_path: Path, text: str, name: str = "s.toml") -> Path:
    p = tmp_path / name
    p.write_text(textwrap.dedent(text), encoding="utf-8")
    return p


def test_example_sweep_file_loads():
    spec = load_sweep_file(ROOT / "data" / "sweeps" / "arma_stiffness.toml")
    cases = expand_cases(spec)
    assert len(cases) == 3 * 2 * 2
    assert spec.swept_keys == ["bodies[0].material.E", "pulls[0].stiffness",
                               "bodies[0].material.nu"]
    assert {c["bodies[0].material.E"] for c in cases} == {2e5, 6e5, 1.8e6}


def test_grid_zip_cases_product_and_bare_dotted_keys(tmp_path):
    p = _write(tmp_path, """
        scene = "arma"
        [set]
        simulation.steps = 3            # bare dotted key: nested tables, flattened
        [grid]
        "bodies[0].material.E" = [1.0, 2.0]
        simulation.dt = [0.01, 0.005, 0.0025]
        [zip]
        "pulls[0].stiffness" = [10.0, 20.0]
        "pulls[0].duration" = [0.1, 0.2]
        [[cases]]
        "simulation.integrator" = "implicit"
        [[cases]]
        "simulation.integrator" = "linear"
    """)
    spec = load_sweep_file(p)
    assert spec.set == {"simulation.steps": 3}
    assert spec.name == "s"
    cases = expand_cases(spec)
    assert len(cases) == 2 * 3 * 2 * 2
    assert cases[0] == {"bodies[0].material.E": 1.0, "simulation.dt": 0.01,
                        "pulls[0].stiffness": 10.0, "pulls[0].duration": 0.1,
                        "simulation.integrator": "implicit"}
    # the last grid key varies fastest (after zip and cases)
    assert [c["simulation.dt"] for c in cases[:8:4]] == [0.01, 0.005]
    zipped = {(c["pulls[0].stiffness"], c["pulls[0].duration"]) for c in cases}
    assert zipped == {(10.0, 0.1), (20.0, 0.2)}
    assert len({tuple(sorted(c.items())) for c in cases}) == len(cases)


@pytest.mark.parametrize("method", ["latin_hypercube", "random", "sobol", "halton"])
def test_samples_seeded_in_range(tmp_path, method):
    p = _write(tmp_path, f"""
        scene = "arma"
        [sample]
        method = "{method}"
        n = 16
        seed = 3
        [sample.ranges]
        "bodies[0].material.E" = {{ low = 1e4, high = 1e6, log = true }}
        "bodies[0].material.nu" = {{ low = 0.2, high = 0.45 }}
        "simulation.steps" = {{ low = 2, high = 5, integer = true }}
    """)
    a, b = expand_cases(load_sweep_file(p)), expand_cases(load_sweep_file(p))
    assert a == b and len(a) == 16
    E = np.array([c["bodies[0].material.E"] for c in a])
    nu = np.array([c["bodies[0].material.nu"] for c in a])
    steps = [c["simulation.steps"] for c in a]
    assert (E >= 1e4).all() and (E <= 1e6).all() and (nu >= 0.2).all() and (nu <= 0.45).all()
    assert all(isinstance(s, int) and 2 <= s <= 5 for s in steps)
    if method == "latin_hypercube":  # one sample in each of the n strata of every axis
        strata = np.floor((np.log(E) - np.log(1e4)) / (np.log(1e6) - np.log(1e4)) * 16)
        assert sorted(strata.astype(int)) == list(range(16))
        strata = np.floor((nu - 0.2) / 0.25 * 16)
        assert sorted(strata.astype(int)) == list(range(16))
    other = _write(tmp_path, p.read_text().replace("seed = 3", "seed = 4"), "t.toml")
    assert expand_cases(load_sweep_file(other)) != a


BAD = [
    ("scene = \n", "not valid TOML"),
    ("[grid]\n'simulation.dt' = [0.1]\n", "scene: Field required"),
    ("scene = 'arma'\ncolour = 'red'\n", "colour: unknown key"),
    # a misspelled required key: the unknown key and its right name, not "scene: missing"
    ("scnee = 'arma'\n", "scnee: unknown key; did you mean 'scene'?"),
    ("scene = 'arma'\n[dataset]\ndtipe = 'float32'\n",
     "dataset.dtipe: unknown key; did you mean 'dtype'?"),
    ("scene = 'arma'\n[grid]\n'simulation.dt' = 0.01\n",
     'grid."simulation.dt": Input should be a valid list'),
    ("scene = 'arma'\n[grid]\n'simulation.dt' = []\n", "grid: simulation.dt: an empty list"),
    ("scene = 'arma'\n[zip]\na = [1, 2]\nb = [1]\n", "zip: the lists must have one length"),
    ("scene = 'arma'\n[set]\na = 1\n[grid]\na = [1, 2]\n", "a: given in both set and grid"),
    ("scene = 'arma'\n[sample]\nn = 0\n[sample.ranges]\na = {low = 1, high = 2}\n",
     "sample.n: Input should be greater than or equal to 1"),
    ("scene = 'arma'\n[sample]\nn = 2\n[sample.ranges]\na = {low = 2, high = 1}\n",
     'sample.ranges.a: high (1) is below low (2)'),
    ("scene = 'arma'\n[sample]\nn = 2\n[sample.ranges]\na = {low = 0, high = 1, log = true}\n",
     "log = true needs low > 0"),
    ("scene = 'arma'\n[sample]\nn = 2\nmethod = 'grid'\n[sample.ranges]\na = {low=0, high=1}\n",
     "sample.method: Input should be 'latin_hypercube', 'random', 'sobol' or 'halton'"),
    ("scene = 'arma'\n[results]\nmetric = 'speed'\n", "results.metric: Input should be"),
    ("scene = 'arma'\n[dataset]\ndtype = 'float16'\n", "dataset.dtype: Input should be"),
    ("scene = 'arma'\n[grid]\na = [1, 2]\nb = [1, 2]\nc = [1, 2]\nd = [1, 2]\n"
     "e = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20]\n"
     "f = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20]\n"
     "g = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20]\n",
     "more than the limit of 100000"),
]


@pytest.mark.parametrize(("text", "message"), BAD)
def test_bad_sweep_file_is_one_line_exit_2(tmp_path, capsys, text, message):
    p = _write(tmp_path, text)
    assert main(["sweep", str(p), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.startswith(f"fem3d sweep: error: {p}: ")
    assert message in err
    assert not (tmp_path / "out").exists()


def test_missing_sweep_file_and_bad_options(tmp_path, capsys):
    assert main(["sweep", str(tmp_path / "nope.toml")]) == 2
    assert "no such sweep file" in capsys.readouterr().err
    p = _write(tmp_path, "scene = 'arma'\n")
    assert main(["sweep", str(p), "--workers", "0"]) == 2
    assert "--workers must be >= 1" in capsys.readouterr().err
    with pytest.raises(InputError, match="not valid TOML"):
        load_sweep_file(_write(tmp_path, "[grid\n"))


class _Inner(BaseModel):
    model_config = ConfigDict(extra="forbid")
    E: float = 1.0
    params: dict[str, float] = {}


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid")
    material: _Inner = _Inner()
    skin: str | None = None
    translate: tuple[float, float, float] = (0.0, 0.0, 0.0)


class _Root(BaseModel):
    model_config = ConfigDict(extra="forbid")
    bodies: list[_Body]
    gravity: list[float] = [0.0, 0.0, 0.0]
    extra: _Inner | None = None


def test_check_key_path_against_a_schema():
    schema = _Root.model_json_schema()
    data = _Root(bodies=[_Body()]).model_dump(mode="json")
    ok = ["bodies[0].material.E", "bodies[0].material.params.mu", "gravity[1]",
          "bodies[0].translate[2]", "extra.E", "bodies[0].skin", "bodies[0].material"]
    for key in ok:
        assert check_key_path(key, schema, data) is None, key
    assert "index 1 out of range: bodies has 1 entries" in check_key_path(
        "bodies[1].material.E", schema, data)
    assert "bodies[0].material has no field 'Young'" in check_key_path(
        "bodies[0].material.Young", schema, data)
    assert "the scene has no field 'body'" in check_key_path("body[0].E", schema, data)
    assert "is not a list" in check_key_path("extra[0]", schema, data)
    assert "bad key path segment" in check_key_path("bodies[x].E", schema, data)
    assert "out of range" in check_key_path("bodies[0].translate[3]", schema, data)
