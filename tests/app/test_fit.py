"""``fem3d fit``: recovering parameters from a run's frames, its files, bad fit files."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.app.fit import load_fit_file
from fem3d.app.fit.run import scene_toml
from fem3d.app.run import run_scene
from fem3d.errors import InputError
from fem3d.scene import apply_overrides, load_scene
from fem3d.scene.load import scene_from_arrays
from tests.physics.test_assembly import box_mesh

E_TRUE, NU_TRUE = 3e5, 0.3
E_KEY, NU_KEY = "bodies[0].material.E", "bodies[0].material.nu"


def bar_scene(**values):
    """A 1.5 x 0.5 x 0.5 cantilever (3x2x2 boxes, 72 tets) pinned at x = 0, sagging under
    gravity for 20 steps of 0.01 s; every second step is a frame."""
    X, T = box_mesh(3, 2, 2, size=(1.5, 0.5, 0.5))
    return scene_from_arrays(X, T, {
        "pulls": [], "simulation.dt": 0.01, "simulation.steps": 20,
        "simulation.gravity": [0.0, -9.81, 0.0], "output.every": 2,
        "bodies[0].pins": [{"select": {"box": [[-1, -1, -1], [1e-6, 2, 2]]}}],
        "bodies[0].material.density": 1000.0, NU_KEY: NU_TRUE, **values})


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """A folder with the base scene (bar.toml, E = 1e5) and the target run (E = 3e5)."""
    d = tmp_path_factory.mktemp("fit")
    target = bar_scene(**{E_KEY: E_TRUE, "simulation.newton.max_iterations": None})
    summary = run_scene(target, d / "target", quiet=True, preview=False)
    assert summary.status == "ok"
    (d / "bar.toml").write_text(scene_toml(bar_scene(**{E_KEY: 1e5})))
    return d


def write_fit(work: Path, name: str, body: str) -> Path:
    p = work / f"{name}.toml"
    p.write_text(textwrap.dedent(body))
    return p


E_FIT = """\
    scene = "bar.toml"
    target = "target"
    [[params]]
    key = "bodies[0].material.E"
    start = 1e5
    bounds = [1e3, 1e8]
    [optimizer]
    max_iterations = 30
"""


def test_fit_recovers_E_and_writes_its_files(work: Path, capsys) -> None:
    fit_file = write_fit(work, "e", E_FIT)
    out = work / "out_e"
    assert main(["fit", str(fit_file), "--out", str(out)]) == 0
    err = capsys.readouterr().err.splitlines()
    doc = json.loads((out / "fit.json").read_text())
    E = doc["params"][E_KEY]
    assert abs(E / E_TRUE - 1) < 1e-3
    assert doc["result"]["success"] and doc["result"]["iterations"] <= 30
    history = doc["history"]
    assert history[0]["params"][E_KEY] == 1e5 and history[0]["iteration"] == 0
    assert len(history) == doc["result"]["iterations"] + 1
    for rec in history:
        assert set(rec) >= {"iteration", "params", "loss", "gradient_norm"}
    assert history[-1]["loss"] < 1e-8 * history[0]["loss"]
    assert doc["frames"] == list(range(2, 21, 2))
    # one progress line per iteration, then the summary
    progress = [line for line in err if line.startswith("fem3d fit: iter")]
    assert len(progress) == len(history)
    assert "loss" in progress[0] and "|grad|" in progress[0] and E_KEY in progress[0]
    assert "converged" in err[-1]
    fitted = load_scene(out / "fitted.toml")
    assert fitted.bodies[0].material.E == pytest.approx(E, rel=1e-12)
    assert (out / "fit.png").read_bytes()[:4] == b"\x89PNG"


def test_fit_recovers_E_and_nu_together(work: Path) -> None:
    fit_file = write_fit(work, "enu", E_FIT.replace("[optimizer]", """\
    [[params]]
    key = "bodies[0].material.nu"
    start = 0.4
    bounds = [0.0, 0.49]
    [optimizer]"""))
    out = work / "out_enu"
    assert main(["fit", str(fit_file), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "fit.json").read_text())
    # measured: 10 iterations, both to about 1e-9
    assert doc["params"][E_KEY] == pytest.approx(E_TRUE, rel=1e-3)
    assert doc["params"][NU_KEY] == pytest.approx(NU_TRUE, rel=1e-3)


def test_fit_of_a_vector_parameter(work: Path) -> None:
    fit_file = write_fit(work, "gravity", """\
        scene = "bar.toml"
        target = "target"
        [set]
        "bodies[0].material.E" = 3e5    # the target's
        [[params]]
        key = "simulation.gravity"
        start = [1.0, -5.0, 0.0]
        bounds = [-20.0, 20.0]
    """)
    out = work / "out_gravity"
    assert main(["fit", str(fit_file), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "fit.json").read_text())
    assert doc["params"]["simulation.gravity"] == pytest.approx([0.0, -9.81, 0.0], abs=1e-4)
    assert load_scene(out / "fitted.toml").simulation.gravity[1] == pytest.approx(-9.81,
                                                                                  abs=1e-4)


def test_fit_of_selected_frames_and_vertices(work: Path) -> None:
    fit_file = write_fit(work, "sel", E_FIT.replace("[[params]]", """\
    [loss]
    frames = [10, 20]
    select = {box = [[1.4, -1, -1], [2, 2, 2]]}
    [[params]]"""))
    out = work / "out_sel"
    assert main(["fit", str(fit_file), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "fit.json").read_text())
    assert doc["frames"] == [10, 20] and doc["vertices_per_frame"] == 9
    assert doc["params"][E_KEY] == pytest.approx(E_TRUE, rel=1e-3)


def test_iteration_limit_exits_1_and_still_writes(work: Path, capsys) -> None:
    fit_file = write_fit(work, "short", E_FIT)
    out = work / "out_short"
    assert main(["fit", str(fit_file), "--out", str(out), "--max-iterations", "1"]) == 1
    doc = json.loads((out / "fit.json").read_text())
    assert not doc["result"]["success"] and "ITERATIONS" in doc["result"]["message"]
    assert "did not converge" in capsys.readouterr().err.splitlines()[-1]


@pytest.mark.parametrize("change, key", [
    (("key = ", "kye = "), "params[0].kye: unknown key"),
    (('"bodies[0].material.E"', '"bodies[0].pins"'), "params[0].key: cannot fit"),
    (("[1e3, 1e8]", "[1e8, 1e3]"), "params[0].bounds: need low < high"),
    (("[1e3, 1e8]", "[-1.0, 1e8]\n    log = true"), "params[0].bounds: log = true needs"),
    (("start = 1e5", "start = 1e9"), "params[0].bounds: start"),
    (('target = "target"\n', ""), "target: missing"),
    (('target = "target"', 'target = "nowhere"'), "target = 'nowhere': "),
    (("max_iterations = 30", "max_iterations = 0"), "optimizer.max_iterations:"),
])
def test_bad_fit_file_exits_2_naming_the_key(work: Path, capsys, change, key) -> None:
    fit_file = write_fit(work, "bad", E_FIT.replace(*change))
    out = work / "out_bad"
    assert main(["fit", str(fit_file), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(fit_file) in err[0] and key in err[0], err
    assert not out.exists()


def test_frame_not_in_target_is_refused(work: Path) -> None:
    fit_file = write_fit(work, "frames", E_FIT.replace("[[params]]",
                                                       "[loss]\nframes = [3]\n[[params]]"))
    with pytest.raises(InputError, match="loss.frames: step 3"):
        from fem3d.app.fit import fit
        fit(load_fit_file(fit_file), where=str(fit_file))


def test_refuses_to_overwrite_its_inputs(work: Path, capsys) -> None:
    out = work / "out_self"
    out.mkdir()
    (out / "fitted.toml").write_text((work / "bar.toml").read_text())
    fit_file = write_fit(work, "self", E_FIT.replace('"bar.toml"', '"out_self/fitted.toml"'))
    assert main(["fit", str(fit_file), "--out", str(out)]) == 2
    assert "overwrite its own scene file" in capsys.readouterr().err


def test_target_without_frames_and_unsupported_scene_name_the_key(work: Path, capsys) -> None:
    (work / "empty").mkdir(exist_ok=True)
    fit_file = write_fit(work, "empty", E_FIT.replace('"target"', '"empty"'))
    assert main(["fit", str(fit_file), "--out", str(work / "out_empty")]) == 2
    assert "empty.toml: target: " in capsys.readouterr().err
    fit_file = write_fit(work, "linear", E_FIT.replace("[[params]]", """\
    [set]
    "simulation.integrator" = "linear"
    [[params]]"""))
    assert main(["fit", str(fit_file), "--out", str(work / "out_linear")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "linear.toml: scene: " in err[0] and "implicit" in err[0]
    assert "'linear' is not differentiated" in err[0]


@pytest.mark.parametrize(("integrator", "steps"),
                         [("static", 2), ("bdf2", 10), ("newmark", 10)])
def test_fit_recovers_E_with_static_bdf2_and_newmark(tmp_path: Path, integrator: str,
                                                     steps: int) -> None:
    """The cantilever of ``bar_scene`` run with ``simulation.integrator = static`` (its sag
    under gravity, 2 load steps), ``bdf2`` and ``newmark`` (10 steps) with E = 3e5 as the
    target; the fit file's scene has the same integrator and E = 1e5: E is recovered within
    1e-3 (measured: 8e-11, 5e-14, 4e-13)."""
    settings = {"simulation.integrator": integrator, "simulation.steps": steps,
                "output.every": 1 if integrator == "static" else 2}
    target = bar_scene(**{E_KEY: E_TRUE, "simulation.newton.max_iterations": None},
                       **settings)
    assert run_scene(target, tmp_path / "target", quiet=True, preview=False).status == "ok"
    (tmp_path / "bar.toml").write_text(scene_toml(bar_scene(**{E_KEY: 1e5}, **settings)))
    fit_file = write_fit(tmp_path, "fit", E_FIT)
    out = tmp_path / "out"
    assert main(["fit", str(fit_file), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "fit.json").read_text())
    assert doc["result"]["success"]
    print(integrator, "E relative error", doc["params"][E_KEY] / E_TRUE - 1, "iterations",
          doc["result"]["iterations"])
    assert doc["params"][E_KEY] == pytest.approx(E_TRUE, rel=1e-3)
    assert load_scene(out / "fitted.toml").simulation.integrator == integrator


def test_a_failed_simulation_exits_1_with_the_iterations_before(work: Path, monkeypatch,
                                                                 capsys) -> None:
    import fem3d.app.fit.run as fit_run
    from fem3d.errors import SimulationError

    calls = []
    real = fit_run.trajectory_gradient

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise SimulationError("Newton did not converge", step=4)
        return real(*args, **kwargs)

    monkeypatch.setattr(fit_run, "trajectory_gradient", failing)
    fit_file = write_fit(work, "fails", E_FIT)
    out = work / "out_fails"
    assert main(["fit", str(fit_file), "--out", str(out), "--quiet"]) == 1
    doc = json.loads((out / "fit.json").read_text())
    assert not doc["result"]["success"]
    assert "simulation failed: step 4" in doc["result"]["message"]
    assert len(doc["history"]) >= 1 and (out / "fitted.toml").is_file()
    assert "did not converge" in capsys.readouterr().err


def test_fit_to_a_dataset_trajectory(work: Path) -> None:
    from fem3d.io.dataset import read_run_frames, write_trajectory

    steps, times, positions, faces = read_run_frames(work / "target")
    write_trajectory(work / "trajectory.npz", positions=positions, times=times, steps=steps,
                     faces=faces, dtype="float64")
    fit_file = write_fit(work, "npz", E_FIT.replace('"target"', '"trajectory.npz"'))
    out = work / "out_npz"
    assert main(["fit", str(fit_file), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "fit.json").read_text())
    assert doc["params"][E_KEY] == pytest.approx(E_TRUE, rel=1e-3)


def test_a_target_run_with_another_dt_is_refused(work: Path, capsys) -> None:
    fit_file = write_fit(work, "dt", E_FIT.replace("[[params]]", """\
    [set]
    "simulation.dt" = 0.005
    [[params]]"""))
    assert main(["fit", str(fit_file), "--out", str(work / "out_dt")]) == 2
    assert "target: its frame of step 2 is at t = 0.02" in capsys.readouterr().err


def halves_scene(X, T, E1: float, E2: float):
    """A bar clamped at x = 0, sagging for 20 steps (a frame every 2nd): ``E1`` on x < 0.5
    (the body's E), ``E2`` on x > 0.5 (``regions[0].E``)."""
    return scene_from_arrays(X, T, {
        "pulls": [], "simulation.dt": 0.01, "simulation.steps": 20,
        "simulation.gravity": [0.0, -9.81, 0.0], "output.every": 2,
        "simulation.newton.max_iterations": None,
        "bodies[0].pins": [{"select": {"box": [[-1, -1, -1], [1e-6, 2, 2]]}}],
        "bodies[0].material.E": E1, "bodies[0].material.nu": 0.3,
        "bodies[0].material.regions": [
            {"select": {"box": [[0.5 - 1e-6, -1, -1], [2, 2, 2]]}, "E": E2}]})


def test_fit_recovers_the_stiffness_of_two_halves_of_a_bar(tmp_path: Path) -> None:
    """Per-region keys: a 1 x 0.25 x 0.25 bar (8x2x2 boxes, 192 tets) clamped at x = 0 whose
    halves have E1 = 1e5 (x < 0.5: the body's E) and E2 = 4e5 (x > 0.5: regions[0].E),
    sagging for 20 steps; both fitted from 2e5 to within 1 % (docs/differentiable.md)."""
    X, T = box_mesh(8, 2, 2, size=(1.0, 0.25, 0.25))

    def halves(E1: float, E2: float):
        return halves_scene(X, T, E1, E2)
    assert run_scene(halves(1e5, 4e5), tmp_path / "target", quiet=True,
                     preview=False).status == "ok"
    (tmp_path / "halves.toml").write_text(scene_toml(halves(2e5, 2e5)))
    fit_file = write_fit(tmp_path, "fit_halves", """\
        scene = "halves.toml"
        target = "target"
        [[params]]
        key = "bodies[0].material.E"
        bounds = [1e3, 1e8]
        [[params]]
        key = "bodies[0].material.regions[0].E"
        bounds = [1e3, 1e8]
        [optimizer]
        max_iterations = 40
    """)
    out = tmp_path / "out"
    assert main(["fit", str(fit_file), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "fit.json").read_text())
    assert doc["start"] == {"bodies[0].material.E": 2e5, "bodies[0].material.regions[0].E": 2e5}
    assert doc["params"]["bodies[0].material.E"] == pytest.approx(1e5, rel=1e-2)
    assert doc["params"]["bodies[0].material.regions[0].E"] == pytest.approx(4e5, rel=1e-2)
    fitted = load_scene(out / "fitted.toml")
    assert fitted.bodies[0].material.regions[0].E == pytest.approx(
        doc["params"]["bodies[0].material.regions[0].E"], rel=1e-12)


def test_fit_of_a_per_tet_field_writes_its_mesh(tmp_path: Path, capsys) -> None:
    """A per-tet field key (``bodies[0].material.cell_fields.E``): the bar of two halves
    from a ``.vtu`` with a per-tet ``youngs`` array; the fit starts every tet at 2e5, writes
    the fitted field into ``fitted_body0.vtu`` beside ``fitted.toml`` and lowers the loss by
    orders of magnitude (per-tet E is not determined by a sag alone: not asserted per tet)."""
    import meshio

    X, T = box_mesh(8, 2, 2, size=(1.0, 0.25, 0.25))
    E = np.where(X[T].mean(axis=1)[:, 0] > 0.5, 4e5, 1e5)
    meshio.write(tmp_path / "bar.vtu", meshio.Mesh(X, [("tetra", T)],
                                                    cell_data={"youngs": [E]}))
    scene = apply_overrides(halves_scene(X, T, 2e5, 2e5), {
        "bodies[0].mesh": str(tmp_path / "bar.vtu"), "bodies[0].material.regions": [],
        "bodies[0].material.cell_fields": {"E": "youngs"}})
    assert run_scene(scene, tmp_path / "target", quiet=True, preview=False).status == "ok"
    (tmp_path / "field.toml").write_text(scene_toml(scene))
    fit_file = write_fit(tmp_path, "fit_field", """\
        scene = "field.toml"
        target = "target"
        [[params]]
        key = "bodies[0].material.cell_fields.E"
        start = 2e5
        bounds = [1e3, 1e8]
        [optimizer]
        max_iterations = 8
    """)
    out = tmp_path / "out"
    assert main(["fit", str(fit_file), "--out", str(out)]) in (0, 1)
    err = capsys.readouterr().err.splitlines()
    assert "192 tets]" in next(line for line in err if "iter   0" in line)
    doc = json.loads((out / "fit.json").read_text())
    key = "bodies[0].material.cell_fields.E"
    assert doc["start"][key] == [2e5] * 192 and len(doc["params"][key]) == 192
    assert doc["loss"] < 1e-3 * doc["history"][0]["loss"]
    fitted = load_scene(out / "fitted.toml")
    assert Path(fitted.bodies[0].mesh) == (out / "fitted_body0.vtu").resolve()
    written = meshio.read(out / "fitted_body0.vtu").cell_data["youngs"][0]
    np.testing.assert_array_equal(written, doc["params"][key])
    assert meshio.read(tmp_path / "bar.vtu").cell_data["youngs"][0][0] == 1e5  # untouched


def test_a_per_tet_field_start_must_be_one_number(work: Path, capsys) -> None:
    fit_file = write_fit(work, "field", E_FIT.replace('"bodies[0].material.E"',
                                                      '"bodies[0].material.cell_fields.E"')
                         .replace("start = 1e5", "start = [1e5, 2e5, 3e5]"))
    assert main(["fit", str(fit_file), "--out", str(work / "out_field")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "params[0].start" in err[0] and "one number" in err[0], err
