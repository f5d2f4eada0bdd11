"""Scenes, the Simulation facade, the `fem3d run` command line and the examples."""

from __future__ import annotations

import csv
import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fem3d.app.cli import SUBCOMMANDS, build_parser, main
from fem3d.errors import InputError
from fem3d.scene.arrays import build_arrays as assemble
from fem3d.scene.arrays import hand_vertex, top_vertex
from fem3d.scene.load import SCENES, load_scene
from fem3d.simulation import Simulation, StepInfo

ROOT = Path(__file__).resolve().parents[2]


def test_scene_table():
    bunny, arma = load_scene("bunny"), load_scene("arma")
    a_b, a_a = assemble(bunny), assemble(arma)
    assert (a_b.X.shape, a_b.T.shape) == ((500, 3), (1518, 4))
    m = bunny.bodies[0].material
    assert (m.model, m.E, m.nu, m.density) == ("neo_hookean", 6e6, 0.4, 0.1)
    assert (a_b.spring_k, a_b.pick_radius) == (1e8, 1.0)
    assert bunny.bodies[0].pins[0].select.lowest_y.tol == 3.0
    assert bunny.simulation.integrator == "linear"
    assert (a_a.X.shape, a_a.T.shape) == ((259, 3), (627, 4))
    m = arma.bodies[0].material
    assert (m.E, a_a.spring_k, a_a.pick_radius) == (6e5, 1e5, 0.01)
    assert arma.bodies[0].pins[0].select.lowest_y.tol == 0.1
    assert arma.simulation.integrator == "implicit"
    assert a_a.skin_V.shape == (26002, 3) and a_a.skin_F.shape == (52000, 3)
    for s, a in ((bunny, a_b), (arma, a_a)):
        assert s.simulation.dt == 0.01 and s.n_steps == 100
        (pull,) = a.pulls
        assert pull.duration == pytest.approx(0.3) and pull.start == 0
        off = pull.targets - a.X[pull.vertices]
        assert 0.14 * a.height <= np.linalg.norm(off[0]) <= 0.21 * a.height
        assert a.skin_V is not None
    assert a_b.pulls[0].vertices.tolist() == [top_vertex(a_b.X)]
    assert a_a.pulls[0].vertices.tolist() == [hand_vertex(a_a.X)] == [61]
    assert list(SCENES)[:2] == ["bunny", "arma"]


def test_scene_errors():
    with pytest.raises(InputError, match="unknown scene"):
        load_scene("teapot")
    with pytest.raises(InputError):
        load_scene("does/not/exist.mesh")
    with pytest.raises(InputError, match=r"simulation\.dt"):
        load_scene("arma", {"simulation.dt": -0.01})
    with pytest.raises(InputError, match=r"simulation\.integrator"):
        load_scene("arma", {"simulation.integrator": "rk4"})
    with pytest.raises(InputError, match="unknown key"):
        load_scene("arma", {"colour": "red"})


def test_scene_from_path_and_simulation_api(tmp_path):
    scene = load_scene(ROOT / "data" / "arma_6.node", {"bodies[0].material.E": 1e5})
    assert scene.name == "arma_6" and scene.bodies[0].material.E == 1e5
    assert scene.simulation.integrator == "implicit"
    sim = Simulation(scene)
    assert sim.surface_faces.shape[1] == 3 and sim.skin_positions().shape == sim.model.X.shape
    h = float(np.ptp(sim.model.X[:, 1]))
    assert sim.spring_k == pytest.approx(0.15 * 1e5 * h) and sim.pick_radius == 0.01 * h
    info = sim.step()
    assert isinstance(info, StepInfo) and info.t == pytest.approx(scene.simulation.dt)
    assert info.total == pytest.approx(info.kinetic + info.potential)
    ids = sim.pick(sim.q[10])
    assert 10 in ids
    sim.set_pull(ids, sim.q[10] + [0.0, 0.0, 0.05])
    sim.integrator = "implicit"
    assert sim.step().pull > 0
    with pytest.raises(InputError):
        sim.integrator = "verlet"
    with pytest.raises(InputError):
        sim.set_pull(ids, [1.0, 2.0])
    sim.reset()
    assert sim.t == 0 and sim.pull is None


def test_arma_skin_follows_simulation():
    sim = Simulation(load_scene("arma"), scripted=True)
    rest = sim.skin_positions()
    assert np.allclose(rest, sim.assembled.skin_V, atol=1e-9)
    for _ in range(3):
        sim.step()
    moved = sim.skin_positions()
    assert np.abs(moved - rest).max() > 0.01


def _read_energy(path: Path) -> list[dict[str, float]]:
    with open(path, newline="") as fh:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(fh)]


def test_cli_run_arma_writes_outputs(tmp_path, capsys):
    out = tmp_path / "arma"
    status = main(["run", "arma", "--steps", "20", "--frame-every", "5", "--out", str(out),
                   "--quiet"])
    err = capsys.readouterr().err
    assert status == 0, err
    assert "ms/step" in err
    frames = sorted((out / "frames").glob("*.vtu"))
    assert [f.name for f in frames] == [f"frame_{i:05d}.vtu" for i in (0, 5, 10, 15, 20)]
    pvd = (out / "frames.pvd").read_text()
    assert pvd.count("<DataSet") == 5
    rows = _read_energy(out / "energy.csv")
    assert len(rows) == 21 and rows[-1]["t"] == pytest.approx(0.2)
    assert max(r["total"] for r in rows) > 0
    for name in ("energy.png", "preview.gif"):
        assert (out / name).stat().st_size > 1000
    import meshio

    m = meshio.read(frames[-1])
    assert m.points.shape == (26002, 3)  # the skinned display mesh, not the 259-vertex mesh


def test_cli_linear_solver_amg_runs_and_resumes_bit_exact(tmp_path, capsys):
    whole, part = tmp_path / "whole", tmp_path / "part"
    common = ["--linear-solver", "amg", "--no-preview", "--quiet", "--frame-every", "100"]
    assert main(["run", "arma", "--steps", "4", "--out", str(whole), *common]) == 0
    assert main(["run", "arma", "--steps", "2", "--checkpoint-every", "2", "--out", str(part),
                 *common]) == 0
    assert main(["resume", str(part), "--steps", "4", "--quiet"]) == 0
    capsys.readouterr()
    # the resumed run rebuilt the same AMG hierarchy: every energy row is the same bytes
    assert (whole / "energy.csv").read_bytes() == (part / "energy.csv").read_bytes()


def test_cli_linear_on_arma_fails_with_message(tmp_path, capsys):
    out = tmp_path / "boom"
    status = main(["run", "arma", "--integrator", "linear", "--steps", "80", "--frame-every",
                   "1000", "--no-preview", "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert status == 1
    assert "exploded" in err and "step" in err
    rows = _read_energy(out / "energy.csv")
    assert 30 < len(rows) < 81  # every good step up to the failure was logged
    assert all(np.isfinite([r["total"] for r in rows]))
    assert (out / "energy.png").exists() and (out / "frames" / "frame_00000.vtu").exists()


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["run", "teapot"], "unknown scene"),
        (["run", "nosuch.mesh"], "nosuch.mesh"),
        (["run", "arma", "--dt", "-1"], "--dt: simulation.dt"),
        (["run", "arma", "--steps", "-3"], "--steps"),
    ],
)
def test_cli_bad_input_exits_2_with_one_line(argv, needle, capsys, tmp_path):
    status = main([*argv, "--out", str(tmp_path / "x"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert status == 2
    assert needle in err
    assert len(err.splitlines()) == 1 and "Traceback" not in err


def test_cli_subcommand_registry():
    assert SUBCOMMANDS[0] == "fem3d.app.cli:add_run_subcommand"
    parser = build_parser()
    args = parser.parse_args(["run", "bunny", "--steps", "3", "--debug"])
    assert args.steps == 3 and args.debug and args.func is not None


def test_python_dash_m_entry_point(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "fem3d", "run", "teapot"], capture_output=True, text=True,
        cwd=ROOT, timeout=120,
    )
    assert proc.returncode == 2 and "unknown scene" in proc.stderr


def test_example_pull_bunny():
    spec = importlib.util.spec_from_file_location("pull_bunny", ROOT / "examples" / "pull_bunny.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    d = mod.max_ear_displacement(40)
    print("max ear displacement:", d)
    assert d == pytest.approx(24.169835, rel=1e-5)


def test_cli_unwritable_output_exits_2(tmp_path, capsys):
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a folder")
    status = main(["run", "arma", "--steps", "1", "--out", str(blocker / "out"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert status == 2 and "Traceback" not in err and len(err.splitlines()) == 1
