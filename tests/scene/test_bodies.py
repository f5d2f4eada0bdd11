"""Scene bodies: transforms, initial velocities, several bodies, every selector, pulls,
gravity, damping, moving pins, USD output, surfaces tetrahedralized by fTetWild."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.app.run import run_scene
from fem3d.errors import InputError
from fem3d.mesh.formats import read_tet_mesh, write_surface_mesh
from fem3d.scene import Scene, apply_overrides, load_scene
from fem3d.scene.arrays import build_arrays as assemble
from fem3d.scene.arrays import rotation_matrix, select_vertices
from fem3d.simulation import Simulation

ROOT = Path(__file__).resolve().parents[2]
ARMA = str(ROOT / "data" / "arma_6.node")
MAT = {"model": "neo_hookean", "E": 6e5, "nu": 0.4, "density": 0.1}
PIN = [{"select": {"lowest_y": {"tol": 0.1}}}]


def body(**kw) -> dict:
    return {"mesh": ARMA, "material": dict(MAT), "pins": PIN} | kw


def scene(**kw) -> Scene:
    d = {"name": "t", "simulation": {"dt": 0.01, "steps": 3}, "bodies": [body()]} | kw
    return Scene.from_dict(d)


def test_transform_and_initial_velocity():
    X0 = read_tet_mesh(ARMA).X
    tr = {"scale": 2.0, "rotate_deg": [0.0, 90.0, 30.0], "translate": [1.0, 2.0, 3.0]}
    w, v = np.array([0.0, 0.0, 2.0]), np.array([0.5, 0.0, 0.0])
    s = scene(bodies=[body(transform=tr, velocity=list(v), angular_velocity=list(w))])
    a = assemble(s)
    R = rotation_matrix([0.0, 90.0, 30.0])
    assert np.allclose(R.T @ R, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    assert np.allclose(a.X, 2.0 * X0 @ R.T + [1.0, 2.0, 3.0])
    c = a.X.mean(axis=0)
    assert np.allclose(a.v0, v + np.cross(w, a.X - c))
    sim = Simulation(s)
    free = np.setdiff1d(np.arange(a.X.shape[0]), sim.fixed_vertices)
    assert np.allclose(sim.v[free], a.v0[free]) and not sim.v[sim.fixed_vertices].any()
    # selectors see the transformed positions: lowest_y of the rotated body
    assert np.array_equal(sim.fixed_vertices,
                          np.flatnonzero(a.X[:, 1] <= a.X[:, 1].min() + 0.1))


def test_rotation_matrix_convention():
    # Rz Ry Rx: x about 90 deg z -> y
    assert np.allclose(rotation_matrix([0, 0, 90]) @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(rotation_matrix([90, 0, 0]) @ [0, 1, 0], [0, 0, 1])
    R = rotation_matrix([10, 20, 30])
    assert np.allclose(R, rotation_matrix([0, 0, 30]) @ rotation_matrix([0, 20, 0])
                       @ rotation_matrix([10, 0, 0]))


def test_every_selector_kind(tmp_path):
    X = read_tet_mesh(ARMA).X
    s = scene()
    ids_file = tmp_path / "ids.txt"
    ids_file.write_text("# pinned\n3 1, 2\n  7 # more\n")
    cases = {
        "lowest_y": ({"lowest_y": {"tol": 0.05}}, X[:, 1] <= X[:, 1].min() + 0.05),
        "box": ({"box": [[-0.1, -1.0, -1.0], [0.1, 1.0, 1.0]]}, np.abs(X[:, 0]) <= 0.1),
        "half_space": ({"half_space": {"point": [0.0, 0.2, 0.0], "normal": [0.0, 1.0, 0.0]}},
                       X[:, 1] >= 0.2),
        "sphere": ({"sphere": {"center": list(X[61]), "radius": 0.1}},
                   np.linalg.norm(X - X[61], axis=1) <= 0.1),
        "vertices": ({"vertices": [5, 2, 5]}, np.isin(np.arange(len(X)), [2, 5])),
        "vertices_file": ({"vertices_file": str(ids_file)},
                          np.isin(np.arange(len(X)), [1, 2, 3, 7])),
        "near_vertex": ({"near_vertex": {"vertex": 61, "radius": 0.1}},
                        np.linalg.norm(X - X[61], axis=1) <= 0.1),
        "nearest_to": ({"nearest_to": {"point": list(X[61] + 0.001), "radius": 0.1}},
                       np.linalg.norm(X - X[61], axis=1) <= 0.1),
    }
    from fem3d.scene.spec import Selector

    for kind, (sel, mask) in cases.items():
        got = select_vertices(s, X, Selector.model_validate(sel), "k")
        assert np.array_equal(got, np.flatnonzero(mask)), kind
        assert got.size > 0, kind
    with pytest.raises(InputError, match=r"k\.sphere: selects no vertex"):
        select_vertices(s, X, Selector.model_validate(
            {"sphere": {"center": [9.0, 9.0, 9.0], "radius": 0.1}}), "k")
    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 x\n")
    with pytest.raises(InputError, match="vertices_file"):
        select_vertices(s, X, Selector.model_validate({"vertices_file": str(bad)}), "k")


def test_several_bodies_and_pulls():
    s = scene(bodies=[body(), body(name="right", transform={"translate": [2.0, 0.0, 0.0]})],
              pulls=[{"select": {"near_vertex": {"vertex": 61, "radius": 0.01}},
                      "offset": [0.0, 0.0, 0.2], "stiffness": 1e5},
                     {"body": 1, "select": {"near_vertex": {"vertex": 61, "radius": 0.01}},
                      "target": [2.5, 0.5, 0.0], "stiffness": 3e5, "start": 0.01}])
    a = assemble(s)
    assert a.X.shape == (518, 3) and a.T.shape == (1254, 4) and a.T[627:].min() == 259
    assert a.pulls[1].vertices.tolist() == [259 + 61]
    assert np.allclose(a.pulls[1].targets, [[2.5, 0.5, 0.0]])  # one vertex: its centroid
    sim = Simulation(s, scripted=True)
    assert sim.fixed_vertices.size == 2 * 26
    sim.step()
    assert sim.pull.vertices.tolist() == [61]
    sim.step()  # both pulls act: per-spring stiffness
    assert sim.pull.vertices.tolist() == [61, 320]
    assert np.array_equal(sim.pull.stiffness, [1e5, 3e5])
    tgt = np.array([2.5, 0.5, 0.0])
    assert np.linalg.norm(sim.q[320] - tgt) < np.linalg.norm(a.X[320] - tgt)  # toward it



def test_materials_per_body_region_params_and_cell_fields(tmp_path):
    import meshio

    two = scene(bodies=[body(), body(transform={"translate": [2.0, 0.0, 0.0]},
                                     material={"model": "stvk", "E": 1e5, "nu": 0.3,
                                               "density": 0.2})])
    sim = Simulation(two)
    m = sim.model
    assert m.material == "neo_hookean+stvk" and len(m.groups) == 2
    assert m.density is not None and np.array_equal(m.density, np.r_[np.full(627, 0.1),
                                                                      np.full(627, 0.2)])
    sim.step()
    # a region: the tets whose vertices are all above y = 0.5 get another E
    reg = scene(bodies=[body(material=dict(MAT) | {"regions": [
        {"select": {"half_space": {"point": [0.0, 0.5, 0.0], "normal": [0.0, 1.0, 0.0]}},
         "E": 6e6}]})])
    sim = Simulation(reg)
    X, T = sim.model.X, sim.model.T
    upper = (X[T][:, :, 1] >= 0.5).all(axis=1)
    assert len(sim.model.groups) == 2 and 0 < upper.sum() < len(T)
    groups = {tuple(g.elements.tolist()): g for g in sim.model.groups}
    assert set(groups) == {tuple(np.flatnonzero(upper)), tuple(np.flatnonzero(~upper))}
    # the model's own parameters instead of E, nu (stvk's mu, lam = E, nu's Lame values)
    own = scene(bodies=[body(material={"model": "stvk", "params": {"mu": 2e5, "lam": 3e5},
                                       "density": 0.1})])
    (g,) = Simulation(own).model.groups
    assert g.values == {"mu": 2e5, "lam": 3e5}
    bad = scene(bodies=[body(material={"model": "stvk", "params": {"mu": 2e5}, "density": 0.1})])
    with pytest.raises(InputError, match=r"bodies\[0\]\.material: .*missing: lam"):
        Simulation(bad)
    # a stiffness field from the mesh file's cell data
    mesh = read_tet_mesh(ARMA)
    field = np.linspace(1e5, 1e6, len(mesh.T))
    vtu = tmp_path / "graded.vtu"
    meshio.write(vtu, meshio.Mesh(mesh.X, [("tetra", mesh.T)], cell_data={"E": [field]}))
    graded = scene(bodies=[body(mesh=str(vtu), material={
        "model": "stvk", "E": 1.0, "nu": 0.3, "density": 0.1, "cell_fields": {"E": "E"}})])
    (g,) = Simulation(graded).model.groups
    from fem3d.physics.materials import parameters_from

    assert np.allclose(g.values["mu"], parameters_from("stvk", field, 0.3)["mu"])
    missing = apply_overrides(graded, {"bodies[0].material.cell_fields": {"E": "stiff"}})
    with pytest.raises(InputError, match=r"cell_fields\.E: .*no tet cell data 'stiff'"):
        Simulation(missing)


def test_gravity_and_damping():
    g = scene(simulation={"dt": 0.01, "gravity": [0.0, -9.81, 0.0]})
    sim = Simulation(g)
    y0 = sim.q[:, 1].mean()
    for _ in range(5):
        info = sim.step()
    assert sim.q[:, 1].mean() < y0  # sags
    assert info.potential < 0  # gravity's energy is part of the potential
    # Rayleigh damping reaches the System: per body (arrays) when the bodies differ
    two = scene(bodies=[body(damping={"rayleigh_mass": 2.0}),
                        body(transform={"translate": [2.0, 0.0, 0.0]},
                             damping={"rayleigh_stiffness": 0.01})])
    sys_ = Simulation(two).system
    assert np.array_equal(sys_.loads.rayleigh_alpha, np.r_[np.full(259, 2.0), np.zeros(259)])
    assert np.array_equal(sys_.loads.rayleigh_beta, np.r_[np.zeros(627), np.full(627, 0.01)])
    # and takes energy out: a body set moving with mass damping slows down faster
    kin = {}
    for alpha in (0.0, 20.0):
        soft = {"model": "neo_hookean", "E": 100.0, "nu": 0.3, "density": 1000.0}
        s = scene(bodies=[body(velocity=[0.5, 0.0, 0.0], material=soft,
                               damping={"rayleigh_mass": alpha})])
        sim = Simulation(s)
        assert sim.system.loads.rayleigh_alpha == alpha
        for _ in range(10):
            info = sim.step()
        kin[alpha] = info.kinetic + info.potential
    assert kin[20.0] < 0.5 * kin[0.0]


def test_moving_pins_follow_their_keyframes():
    from fem3d.physics.motion import Keyframes

    motion = {"keyframes": [{"t": 0.0}, {"t": 0.05, "translate": [0.0, 0.0, 0.05],
                                         "rotate_deg": [0.0, 20.0, 0.0]}],
              "interpolation": "smooth"}
    s = scene(bodies=[body(pins=[{"select": {"lowest_y": {"tol": 0.1}}, "motion": motion}])])
    sim = Simulation(s)
    fixed = sim.fixed_vertices
    X = sim.model.X[fixed]
    kf = Keyframes([0.0, 0.05], [[0, 0, 0], [0, 0, 0.05]], [[0, 0, 0], [0, 20, 0]],
                   X.mean(axis=0), "smooth")
    for _ in range(8):
        sim.step()
        assert np.allclose(sim.q[fixed], kf.apply(X, sim.t), atol=1e-12)
    assert np.allclose(sim.q[fixed], kf.apply(X, 1.0))  # held after the last keyframe
    assert np.abs(sim.q - sim.model.X).max() > 0.04
    for integrator in ("linear",):  # the linearly-implicit scheme takes them too
        sim = Simulation(apply_overrides(s, {"simulation.integrator": integrator}))
        for _ in range(3):
            sim.step()
        assert np.allclose(sim.q[fixed], kf.apply(X, sim.t), atol=1e-12)


def test_usd_output_reads_back(tmp_path):
    from pxr import Usd, UsdGeom

    s = scene(bodies=[body(), body(name="two", transform={"translate": [2.0, 0.0, 0.0]})],
              output={"format": "usd", "every": 2},
              simulation={"dt": 0.01, "steps": 6, "gravity": [0.0, -9.81, 0.0]})
    summary = run_scene(s, tmp_path / "o")
    assert summary.status == "ok"
    path = tmp_path / "o" / "frames.usdc"
    assert path.is_file() and not list((tmp_path / "o").glob("frames/*"))
    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == pytest.approx(100.0)
    meshes = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert [m.GetPrim().GetName() for m in meshes] == ["arma_6", "two"]
    sim = Simulation(s)
    for m, vs in zip(meshes, sim.assembled.body_vertices, strict=True):
        attr = m.GetPointsAttr()
        assert attr.GetTimeSamples() == [0.0, 2.0, 4.0, 6.0]
        for t in attr.GetTimeSamples():
            assert len(attr.Get(t)) == vs.stop - vs.start
        counts = np.asarray(m.GetFaceVertexCountsAttr().Get())
        idx = np.asarray(m.GetFaceVertexIndicesAttr().Get())
        assert (counts == 3).all() and idx.max() < vs.stop - vs.start
    first = np.asarray(meshes[1].GetPointsAttr().Get(0.0))
    assert np.allclose(first, sim.model.X[259:], atol=1e-6)
    last = np.asarray(meshes[0].GetPointsAttr().Get(6.0))
    assert last[:, 1].mean() < np.asarray(meshes[0].GetPointsAttr().Get(0.0))[:, 1].mean()
    for _ in range(6):
        sim.step()
    assert np.allclose(last, sim.q[:259], atol=1e-5)


def test_usd_run_resumes(tmp_path):
    from pxr import Usd, UsdGeom

    s = apply_overrides(scene(output={"format": "usd", "every": 1}), {"simulation.steps": 4})
    out = tmp_path / "o"
    assert run_scene(s, out, checkpoint_every=2).status == "ok"
    assert main(["resume", str(out), "--steps", "7", "--quiet", "--no-preview"]) == 0
    stage = Usd.Stage.Open(str(out / "frames.usdc"))
    (mesh,) = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert mesh.GetPointsAttr().GetTimeSamples() == [float(i) for i in range(8)]


def _cube(path: Path, holes: int = 0) -> Path:
    V = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * 0.1
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    write_surface_mesh(path, V, F[: len(F) - holes])
    return path


def test_sheet_fttetwild_cannot_repair_through_cli(tmp_path, capsys, monkeypatch):
    pytest.importorskip("wildmeshing")
    monkeypatch.setenv("FEM3D_CACHE", str(tmp_path / "cache"))
    sheet = tmp_path / "sheet.obj"
    write_surface_mesh(sheet, np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]]),
                       np.array([[0, 1, 2], [0, 2, 3]]))
    p = tmp_path / "s.toml"
    p.write_text(f'[[bodies]]\nmesh = "{sheet.name}"\nmaterial = {{ E = 1e5, nu = 0.3 }}\n'
                 f'pins = [{{ select = {{ lowest_y = {{ tol = 0.01 }} }} }}]\n')
    out = tmp_path / "out"
    status = main(["run", str(p), "--out", str(out), "--quiet", "--no-preview"])
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1, err
    assert err.startswith(f"fem3d run: error: {p}: bodies[0].mesh: {sheet}: "), err
    assert "not closed" in err and not out.exists()


@pytest.mark.slow
def test_surface_body_tetrahedralized_cached_and_skinned(tmp_path, capsys, monkeypatch):
    """A closed OBJ runs through fTetWild once; the second run reads the cache; its surface
    is the display mesh."""
    pytest.importorskip("wildmeshing")

    cache = tmp_path / "cache"
    monkeypatch.setenv("FEM3D_CACHE", str(cache))
    cube = _cube(tmp_path / "cube.obj")
    # a wide envelope (epsilon) and a low quality target: fTetWild in ~0.1 s instead of
    # 3-13 s (measured); the cube's tets are then its own corners, the volume still exact
    argv = ["run", str(cube), "--steps", "3", "--quiet", "--no-preview",
            "--set", "bodies[0].tetrahedralize.epsilon=0.05",
            "--set", "bodies[0].tetrahedralize.edge_length=0.3",
            "--set", "bodies[0].tetrahedralize.stop_quality=100.0"]
    assert main([*argv, "--out", str(tmp_path / "a")]) == 0
    (meta,) = list((cache / "tetwild").glob("*.json"))
    info = json.loads(meta.read_text())
    assert info["tets"] > 0 and info["edge_length"] == 0.3 and info["epsilon"] == 0.05
    import fem3d.mesh.tetrahedralize as tetrahedralize

    def no_tetwild(*args, **kwargs):  # a cache hit must not run fTetWild (not a time budget)
        raise AssertionError("fTetWild ran on a cache hit")

    monkeypatch.setattr(tetrahedralize, "tetrahedralize_arrays", no_tetwild)
    s = load_scene(cube, {"bodies[0].tetrahedralize.edge_length": 0.3,
                          "bodies[0].tetrahedralize.epsilon": 0.05,
                          "bodies[0].tetrahedralize.stop_quality": 100.0})
    sim = Simulation(s)
    assert list((cache / "tetwild").glob("*.json")) == [meta]
    assert sim.has_skin and sim.display_faces.shape == (12, 3)
    assert np.allclose(sim.skin_positions(), sim.assembled.skin_V, atol=1e-9)
    vol = float(sim.model.vol.sum())
    assert vol == pytest.approx(1e-3, rel=0.05)
    # a different size knob is another cache entry
    assert main([*argv[:-4], "--set", "bodies[0].tetrahedralize.edge_length=0.25", "--set",
                 "bodies[0].tetrahedralize.stop_quality=100.0",
                 "--out", str(tmp_path / "b")]) == 0
    assert len(list((cache / "tetwild").glob("*.json"))) == 2
    capsys.readouterr()
