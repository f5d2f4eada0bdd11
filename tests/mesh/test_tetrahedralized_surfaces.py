"""Reproducible surface scenes (issue 39): a run of a surface body keeps the tets it ran on
(``meshes/body0.mesh`` + SHA-256 in ``meshes/meshes.json``); ``fem3d tetrahedralize`` writes
them; a scene naming that file runs the same first step bit for bit, without fTetWild."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.mesh.formats import read_tet_mesh, write_surface_mesh
from fem3d.scene import load_scene
from fem3d.simulation import Simulation

pytest.importorskip("wildmeshing")

OPTIONS = ["--edge-length", "0.3", "--stop-quality", "100"]


def _scene(folder: Path, mesh: str, name: str) -> Path:
    p = folder / name
    p.write_text(f'''[simulation]
steps = 2
gravity = [0.0, -9.81, 0.0]
[[bodies]]
mesh = "{mesh}"
tetrahedralize = {{ edge_length = 0.3, stop_quality = 100.0 }}
material = {{ E = 1e5, nu = 0.3 }}
pins = [{{ select = {{ lowest_y = {{ tol = 0.01 }} }} }}]
''')
    return p


@pytest.fixture
def cube_scene(tmp_path, monkeypatch) -> Path:
    monkeypatch.setenv("FEM3D_CACHE", str(tmp_path / "cache"))
    V = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * 0.1
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    write_surface_mesh(tmp_path / "cube.obj", V, F)
    return _scene(tmp_path, "cube.obj", "surface.toml")


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def test_surface_run_records_tets_and_mesh_scene_reproduces_it(cube_scene, tmp_path, capsys,
                                                               monkeypatch):
    a = tmp_path / "a"
    assert main(["run", str(cube_scene), "--out", str(a), "--quiet", "--no-preview"]) == 0
    mesh = a / "meshes" / "body0.mesh"
    record = json.loads((a / "meshes" / "meshes.json").read_text())["bodies"]
    tets = read_tet_mesh(mesh)
    assert [r["body"] for r in record] == [0] and record[0]["mesh"] == "meshes/body0.mesh"
    assert record[0]["sha256"] == _sha(mesh)
    assert record[0]["surface_sha256"] == _sha(tmp_path / "cube.obj")
    assert (record[0]["vertices"], record[0]["tets"]) == (tets.X.shape[0], tets.T.shape[0])
    assert record[0]["tetrahedralize"]["edge_length"] == 0.3

    # fem3d tetrahedralize writes the same tets (the cached mesh the run used)
    t = tmp_path / "t" / "cube.mesh"
    capsys.readouterr()
    assert main(["tetrahedralize", str(tmp_path / "cube.obj"), "--out", str(t), *OPTIONS]) == 0
    out = capsys.readouterr().out.strip()
    assert len(out.splitlines()) == 1 and out.startswith(f"{t}: {tets.X.shape[0]} vertices")
    assert _sha(t) == record[0]["sha256"]

    # another machine: an empty cache, no fTetWild; a scene naming the recorded mesh
    import fem3d.mesh.tetrahedralize as tetrahedralize

    surface_sim = Simulation(load_scene(cube_scene))
    surface_sim.step()
    monkeypatch.setenv("FEM3D_CACHE", str(tmp_path / "other_cache"))

    def no_tetwild(*args, **kwargs):
        raise AssertionError("fTetWild ran for a tet mesh scene")

    monkeypatch.setattr(tetrahedralize, "tetrahedralize_arrays", no_tetwild)
    again = _scene(tmp_path, str(mesh), "again.toml")
    mesh_sim = Simulation(load_scene(again))
    mesh_sim.step()
    assert np.array_equal(mesh_sim.q, surface_sim.q) and np.array_equal(mesh_sim.v,
                                                                        surface_sim.v)
    b = tmp_path / "b"
    assert main(["run", str(again), "--out", str(b), "--quiet", "--no-preview"]) == 0
    rows_a = (a / "energy.csv").read_text().splitlines()
    rows_b = (b / "energy.csv").read_text().splitlines()
    assert rows_a[:3] == rows_b[:3]  # header, rest, first step: the same bits
    assert not (b / "meshes").exists()  # a tet mesh body needs no record


def test_tet_mesh_run_writes_no_record(tmp_path):
    block = Path(__file__).resolve().parents[2] / "data" / "contact_block.mesh"
    scene = _scene(tmp_path, str(block), "block.toml")
    assert main(["run", str(scene), "--out", str(tmp_path / "o"), "--quiet",
                 "--no-preview"]) == 0
    assert not (tmp_path / "o" / "meshes").exists()


@pytest.mark.parametrize("argv, needle", [
    (["{block}"], "{block}: not a surface file (expected .obj, .stl, .ply, .off)"),
    (["{cube}", "--edge-length", "2"], "--edge-length: Input should be less than or equal to 1"),
    (["{cube}", "--out", "{tmp}/x.vtu"], "{tmp}/x.vtu: --out must name a .mesh file"),
    (["{tmp}/none.obj"], "{tmp}/none.obj: file not found"),
])
def test_tetrahedralize_bad_input(argv, needle, cube_scene, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    names = {"block": str(Path(__file__).resolve().parents[2] / "data" / "contact_block.mesh"),
             "cube": str(tmp_path / "cube.obj"), "tmp": str(tmp_path)}
    before = sorted(p.name for p in tmp_path.iterdir())
    status = main(["tetrahedralize", *[a.format(**names) for a in argv]])
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1, err
    assert err.startswith("fem3d tetrahedralize: error: " + needle.format(**names)), err
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written
