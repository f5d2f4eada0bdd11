"""Scene files: the schema, its error messages, overrides, serialisation, and `fem3d run` on
scene files (good and bad input through the command line)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.app.run import RunSummary, run_scene
from fem3d.errors import InputError
from fem3d.io.checkpoint import CHECKPOINT_NAME, load_run_checkpoint
from fem3d.scene import Scene, apply_overrides, load_scene, scene_names, scene_schema
from fem3d.simulation import Simulation

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "data"
ARMA_MESH = DATA / "arma_6.node"

SMALL = f'''
name = "small"
[simulation]
integrator = "implicit"
dt = 0.01
steps = 4

[[bodies]]
mesh = "{ARMA_MESH}"
material = {{ model = "neo_hookean", E = 6e5, nu = 0.4, density = 0.1 }}
pins = [{{ select = {{ lowest_y = {{ tol = 0.1 }} }} }}]

[[pulls]]
select = {{ near_vertex = {{ vertex = 61, radius = 0.05 }} }}
offset = [0.1, 0.0, 0.0]
duration = 0.02
stiffness = 1e4
'''


def write(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_named_scenes_are_files():
    names = scene_names()
    assert names[:2] == ["bunny", "arma"]
    for n in names:
        assert (DATA / "scenes" / f"{n}.toml").is_file()


def test_to_dict_from_dict_and_digest(tmp_path):
    s = load_scene("arma")
    d = s.to_dict()
    json.dumps(d)  # JSON-safe
    assert Path(d["bodies"][0]["mesh"]).is_absolute() and Path(d["bodies"][0]["mesh"]).is_file()
    again = Scene.from_dict(d)
    assert again.to_dict() == d and again.digest() == s.digest()
    assert apply_overrides(s, {"bodies[0].material.E": 1e5}).digest() != s.digest()
    # the digest sees the mesh's contents, not only its path
    for f in ("arma_6.node", "arma_6.ele"):
        shutil.copy(DATA / f, tmp_path / f)
    p = write(tmp_path, SMALL.replace(str(ARMA_MESH), "arma_6.node"))
    a = load_scene(p)
    before = a.digest()
    text = (tmp_path / "arma_6.node").read_text().splitlines()
    text[1] = text[1][:-1] + ("1" if text[1][-1] != "1" else "2")
    (tmp_path / "arma_6.node").write_text("\n".join(text) + "\n")
    assert load_scene(p).digest() != before


def test_paths_are_relative_to_the_file(tmp_path, monkeypatch):
    sub = tmp_path / "a" / "b"
    sub.mkdir(parents=True)
    for f in ("arma_6.node", "arma_6.ele"):
        shutil.copy(DATA / f, tmp_path / "a" / f)
    p = write(sub, SMALL.replace(str(ARMA_MESH), "../arma_6.node"))
    monkeypatch.chdir(tmp_path)
    s = load_scene(p)
    assert s.path(s.bodies[0].mesh).resolve() == (tmp_path / "a" / "arma_6.node").resolve()
    assert Simulation(s).model.n_vertices == 259


def test_apply_overrides():
    s = load_scene("arma")
    t = apply_overrides(s, {"bodies[0].material.E": 1e5, "simulation.dt": 0.005,
                            "simulation.gravity": (0, -1, 0), "pulls": []})
    assert t.bodies[0].material.E == 1e5 and t.simulation.dt == 0.005 and t.pulls == []
    assert t.simulation.gravity == (0.0, -1.0, 0.0)
    assert s.bodies[0].material.E == 6e5  # frozen original untouched
    u = apply_overrides(apply_overrides(s, {"simulation.duration": 0.5}), {"simulation.steps": 7})
    assert (u.simulation.steps, u.simulation.duration, u.n_steps) == (7, None, 7)
    assert apply_overrides(s, {"simulation.duration": 0.5}).n_steps == 50
    cases = {
        "bodies[0].material.nu": (0.7, "bodies[0].material.nu: Input should be less than 0.5"),
        "bodies[3].material.E": (1.0, "bodies[3].material.E: index 3 out of range"),
        "simulation.dtt": (0.1, "simulation.dtt: unknown key; did you mean 'dt'?"),
        "bodies[0].material.model": ("neo_hooke", "did you mean 'neo_hookean'?"),
        "simulation..dt": (0.1, "not a key path"),
    }
    for key, (value, needle) in cases.items():
        with pytest.raises(InputError) as info:
            apply_overrides(s, {key: value})
        assert str(info.value).startswith("override: ") and needle in str(info.value), info.value
    with pytest.raises(InputError, match="^--dt: simulation.dt"):
        apply_overrides(s, {"simulation.dt": -1.0}, source="--dt")


def test_material_by_name_no_special_case():
    from fem3d.kernels.dispatch import available_materials

    for name in available_materials():
        s = load_scene("arma", {"bodies[0].material.model": name})
        sim = Simulation(s)
        assert sim.model.material == name
        sim.step()
        assert np.isfinite(sim.q).all()


def test_schema():
    import tomllib

    import jsonschema

    schema = scene_schema()
    assert {"simulation", "bodies", "pulls", "contact", "obstacles", "output",
            "interaction"} <= set(schema["properties"])
    assert "base_dir" not in schema["properties"] and "source" not in schema["properties"]
    for name in scene_names():
        data = tomllib.loads((DATA / "scenes" / f"{name}.toml").read_text())
        jsonschema.validate(data, schema)  # every shipped scene passes the printed schema
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"bodies": [{"mesh": "x.mesh", "material": {"E": 1, "nu": 0.3}}],
                             "simulaton": {}}, schema)


def test_schema_command(capsys):
    assert main(["schema"]) == 0
    out = capsys.readouterr().out
    assert json.loads(out) == json.loads(json.dumps(scene_schema()))


# ------------------------------------------------------------------------------ bad input
BAD = {
    "typo key": (SMALL.replace("[simulation]", "[simulaton]"),
                 "simulaton: unknown key; did you mean 'simulation'?"),
    "nested typo": (SMALL.replace("density = 0.1", "densty = 0.1"),
                    "bodies[0].material.densty: unknown key; did you mean 'density'?"),
    "wrong type": (SMALL.replace("dt = 0.01", 'dt = "fast"'),
                   "simulation.dt: Input should be a valid number, got 'fast'"),
    "out of range": (SMALL.replace("nu = 0.4", "nu = 0.6"),
                     "bodies[0].material.nu: Input should be less than 0.5, got 0.6"),
    "missing mesh": (SMALL.replace(str(ARMA_MESH), "no/such.mesh"),
                     "bodies[0].mesh: no such file"),
    "empty selector": (SMALL.replace("lowest_y = { tol = 0.1 }",
                                     "box = [[5, 5, 5], [6, 6, 6]]"),
                       "bodies[0].pins[0].select.box: selects no vertex"),
    "two selectors": (SMALL.replace("lowest_y = { tol = 0.1 }",
                                    "lowest_y = { tol = 0.1 }, vertices = [1]"),
                      "bodies[0].pins[0].select: give exactly one of"),
    "keyframes out of order": (
        SMALL.replace("pins = [{ select = { lowest_y = { tol = 0.1 } } }]",
                      "pins = [{ select = { lowest_y = { tol = 0.1 } }, motion = { keyframes = "
                      "[{ t = 0.0 }, { t = 0.5 }, { t = 0.2 }] } }]"),
        "bodies[0].pins[0].motion.keyframes: keyframes[2].t = 0.2 must be after"),
    "unknown material": (SMALL.replace('model = "neo_hookean"', 'model = "stvkk"'),
                         "bodies[0].material.model: unknown material 'stvkk'"),
    "bad TOML": (SMALL.replace("dt = 0.01", "dt = = 0.01"), "not valid TOML"),
    "no bodies": ("[simulation]\ndt = 0.01\n", "bodies: missing"),
    "vertex id out of range": (SMALL.replace("lowest_y = { tol = 0.1 }", "vertices = [0, 999]"),
                               "bodies[0].pins[0].select.vertices: vertex id 999 out of range"),
    "pull body": (SMALL.replace("[[pulls]]", "[[pulls]]\nbody = 2"), "pulls[0].body = 2"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_scene_file_through_cli(case, tmp_path, capsys):
    text, needle = BAD[case]
    p = write(tmp_path, text)
    out = tmp_path / "out"
    status = main(["run", str(p), "--out", str(out), "--quiet", "--no-preview"])
    err = capsys.readouterr().err.strip()
    assert status == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith(f"fem3d run: error: {p}: "), err
    assert needle in err, err
    assert not out.exists()  # nothing written


@pytest.mark.parametrize("argv, needle", [
    (["--set", "bodies[0].material.E=-1"], "--set: bodies[0].material.E: Input should be "
                                           "greater than 0"),
    (["--set", "simulation.dtt=1"], "--set: simulation.dtt: unknown key; did you mean 'dt'?"),
    (["--set", "nokey"], "expected KEY=VALUE"),
    (["--material", "stvkk"], "--material: bodies[0].material.model: unknown material"),
    (["--dt", "nan"], "--dt: simulation.dt: Input should be a finite number"),
])
def test_bad_flag_through_cli(argv, needle, tmp_path, capsys):
    out = tmp_path / "out"
    status = main(["run", "arma", *argv, "--out", str(out), "--quiet", "--no-preview"])
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1 and needle in err, err
    assert not out.exists()


def test_run_scene_file_with_material_flag_and_resume(tmp_path, capsys):
    p = write(tmp_path, SMALL)
    out = tmp_path / "run"
    status = main(["run", str(p), "--material", "stvk", "--set", "simulation.steps=6",
                   "--checkpoint-every", "3", "--out", str(out), "--quiet", "--no-preview"])
    err = capsys.readouterr().err
    assert status == 0, err
    assert "material stvk" in err and "steps 0 -> 6" in err
    ckpt = load_run_checkpoint(out / CHECKPOINT_NAME)
    scene = Scene.from_dict(ckpt.settings["scene"])
    assert scene.bodies[0].material.model == "stvk" and scene.n_steps == 6
    assert len(list((out / "frames").glob("*.vtu"))) == 7
    # resume needs nothing but the folder, even with the scene file gone
    p.unlink()
    assert main(["resume", str(out), "--steps", "9", "--quiet", "--no-preview"]) == 0
    err = capsys.readouterr().err
    assert "material stvk" in err and "steps 6 -> 9" in err
    assert len(list((out / "frames").glob("*.vtu"))) == 10


def test_run_scene_summary(tmp_path):
    s = load_scene(write(tmp_path, SMALL))
    summary = run_scene(s, tmp_path / "o")
    assert isinstance(summary, RunSummary) and summary.status == "ok" and summary.exit_status == 0
    assert summary.steps == 4 and summary.newton_iterations >= 4
    assert summary.max_displacement > 0 and summary.max_total >= summary.total > 0
    assert summary.wall_seconds > 0
    assert not (tmp_path / "o" / "preview.gif").exists()  # preview=False by default
    assert (tmp_path / "o" / "energy.csv").read_text().count("\n") == 6
    s = load_scene("arma", {"simulation.integrator": "linear", "simulation.steps": 80,
                            "output.every": 1000})
    failed = run_scene(s, tmp_path / "f")
    assert failed.status == "failed" and failed.exit_status == 1 and "exploded" in failed.message


def test_psd_projection_picks_the_models_kernel():
    from dataclasses import replace

    from fem3d.physics.assembly import hessian_data

    scene = load_scene("cantilever")
    assert Simulation(scene).model.psd_hessian == "hessian_psd_svd"
    model = Simulation(apply_overrides(scene, {"simulation.psd_projection": "jacobi"})).model
    assert model.psd_hessian == "hessian_psd_jacobi"
    # squashed: compressed elements have an indefinite dP/dF, which all three project
    q = model.X * np.array([1.0, 0.6, 1.0]) + 1e-3 * np.random.default_rng(3).normal(
        size=model.X.shape)
    jacobi = hessian_data(model, q, psd=True)
    ql = hessian_data(replace(model, psd_projection="ql"), q, psd=True)
    svd = hessian_data(replace(model, psd_projection="svd"), q, psd=True)
    for other in (jacobi, svd):
        assert not np.array_equal(other, ql)  # another eigen-solver, another round-off
        np.testing.assert_allclose(other, ql, rtol=1e-9, atol=1e-12 * np.abs(ql).max())
    assert not np.allclose(ql, hessian_data(model, q), rtol=1e-6)  # something was projected
