"""The volume frames of a run (``output.volume = true``): ``volume/*.vtu`` + ``volume.pvd``
hold every node and the element's own VTK cells (``tetra10`` for P2, ``tetra`` for P1), the
per-element stress as cell data and its vertex averages as point data, at the run's state;
resume keeps them; and the P2 runs' other outputs (OBJ, USD, the preview) come from the
subdivided quadratic surface."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import meshio
import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.io.checkpoint import load_run_checkpoint
from fem3d.mesh.element import ELEMENTS
from fem3d.mesh.formats import write_tet_mesh
from fem3d.mesh.tetmesh import TetMesh, box_tet_mesh
from fem3d.physics.stress import element_stress, vertex_fields
from fem3d.scene import load_scene
from fem3d.simulation import Simulation

CELLS = {"p1": ("tetra", 4), "p2": ("tetra10", 10)}


def _overrides(mesh: Path, element: str, steps: int) -> dict[str, object]:
    return {"bodies[0].mesh": str(mesh), "bodies[0].element": element,
            "bodies[0].material.E": 1e6, "simulation.steps": steps, "output.volume": True}


def _set_args(overrides: dict[str, object]) -> list[str]:
    args = []
    for k, v in overrides.items():
        value = {True: "true", False: "false"}.get(v, v) if isinstance(v, bool) else v
        args += ["--set", f"{k}={value!r}" if isinstance(value, str) and k.endswith(
            ("mesh", "element")) else f"{k}={value}"]
    return args


@pytest.fixture(scope="module")
def beam(tmp_path_factory) -> Path:
    """A 4 x 1 x 1-cell beam, 1 x 0.25 x 0.25 (24 tets, 20 vertices)."""
    path = tmp_path_factory.mktemp("mesh") / "beam.mesh"
    write_tet_mesh(path, TetMesh(*box_tet_mesh((4, 1, 1), (1.0, 0.25, 0.25))))
    return path


def _run(beam: Path, element: str, out: Path, steps: int = 2, *extra: str) -> dict:
    overrides = _overrides(beam, element, steps)
    rc = main(["run", "cantilever", *_set_args(overrides), "--checkpoint-every", str(steps),
               "--out", str(out), "--quiet", "--no-preview", *extra])
    assert rc == 0
    return overrides


@pytest.mark.parametrize("element", ["p2", "p1"])
def test_volume_frames_hold_the_elements_at_the_runs_state(element, beam, tmp_path):
    out = tmp_path / "run"
    overrides = _run(beam, element, out)
    sim = Simulation(load_scene("cantilever", overrides))
    model = sim.model
    cell, k = CELLS[element]
    assert model.T.shape[1] == k
    # P2: corners and edge nodes, the nodes of the 9 x 3 x 3 grid of half cells
    assert model.n_vertices == (81 if element == "p2" else 20)
    files = sorted((out / "volume").glob("volume_*.vtu"))
    assert [f.name for f in files] == [f"volume_0000{i}.vtu" for i in range(3)]
    pvd = (out / "volume.pvd").read_text()
    assert all(f'file="volume/{f.name}"' in pvd for f in files)

    q = np.asarray(load_run_checkpoint(out / "checkpoint.npz").snapshot["q"])
    assert np.abs(q - model.X).max() > 1e-4  # the beam sagged: the last frame is not the rest
    for f, expect in ((files[0], model.X), (files[-1], q)):
        mesh = meshio.read(f)
        assert [c.type for c in mesh.cells] == [cell]
        assert np.array_equal(mesh.cells[0].data, model.T)
        assert mesh.points.shape == (model.n_vertices, 3)
        assert np.array_equal(mesh.points, expect)  # exactly the run's state

    mesh = meshio.read(files[-1])
    e = element_stress(model, q)
    cd = {name: mesh.cell_data[name][0] for name in mesh.cell_data}
    assert cd["von_mises"].shape == (model.n_tets,)
    np.testing.assert_allclose(cd["von_mises"], e.von_mises, rtol=1e-12)
    np.testing.assert_allclose(cd["cauchy_stress"], e.cauchy.reshape(-1, 9), rtol=1e-12,
                               atol=1e-12 * np.abs(e.cauchy).max())
    np.testing.assert_allclose(cd["principal_stretches"], e.stretches, rtol=1e-12)
    assert e.von_mises.max() > 0
    for name, values in vertex_fields(model, q).items():
        np.testing.assert_allclose(mesh.point_data[name].reshape(values.shape), values,
                                   rtol=1e-12, atol=1e-12 * np.abs(values).max())
    # the surface frames stay the display surface
    frame = meshio.read(out / "frames" / "frame_00002.vtu")
    assert [c.type for c in frame.cells] == ["triangle"]
    assert len(frame.cells[0].data) == len(sim.display_faces)


def test_volume_frames_read_back_in_vtk(beam, tmp_path):
    """VTK's own reader takes the P2 volume as quadratic tetrahedra (cell type 24) in the
    element's node order: the volume VTK integrates over the rest frame's cells is the
    beam's, 1 x 0.25 x 0.25 (edge nodes in another order would bend the cells)."""
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy

    out = tmp_path / "run"
    _run(beam, "p2", out, 1)
    reader = vtk.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(out / "volume" / "volume_00000.vtu"))
    reader.Update()
    grid = reader.GetOutput()
    assert grid.GetNumberOfCells() == 24 and grid.GetNumberOfPoints() == 81
    assert {grid.GetCellType(e) for e in range(24)} == {vtk.VTK_QUADRATIC_TETRA}
    assert vtk_to_numpy(grid.GetCellData().GetArray("von_mises")).shape == (24,)
    integrate = vtk.vtkIntegrateAttributes()
    integrate.SetInputData(grid)
    integrate.Update()
    volume = integrate.GetOutput().GetCellData().GetArray("Volume").GetValue(0)
    assert volume == pytest.approx(0.0625, rel=1e-12)


def test_volume_frames_off_by_default(beam, tmp_path):
    overrides = _overrides(beam, "p2", 1)
    overrides.pop("output.volume")
    assert main(["run", "cantilever", *_set_args(overrides), "--out", str(tmp_path / "r"),
                 "--quiet", "--no-preview"]) == 0
    assert not (tmp_path / "r" / "volume").exists()
    assert not (tmp_path / "r" / "volume.pvd").exists()


def test_volume_frames_resume(beam, tmp_path):
    """A resumed run continues the volume frames: the files after the checkpoint are removed,
    the continued ones equal an uninterrupted run's byte for byte."""
    whole, part = tmp_path / "whole", tmp_path / "part"
    _run(beam, "p2", whole, 4)
    _run(beam, "p2", part, 2)
    stray = part / "volume" / "volume_00003.vtu"  # as if written after the checkpoint
    stray.write_bytes(b"not a frame")
    (part / "volume.pvd").unlink()
    assert main(["resume", str(part), "--steps", "4", "--quiet", "--no-preview"]) == 0
    names = sorted(f.name for f in (whole / "volume").iterdir())
    assert names == sorted(f.name for f in (part / "volume").iterdir())
    assert len(names) == 5
    for name in names:
        assert (whole / "volume" / name).read_bytes() == (part / "volume" / name).read_bytes()
    assert (whole / "volume.pvd").read_text() == (part / "volume.pvd").read_text()


def test_distributed_runs_refuse_the_volume(beam):
    """``mpiexec`` runs write the surface's pieces only: ``output.volume`` is refused in one
    line naming the key, not ignored."""
    from fem3d.errors import InputError
    from fem3d.parallel.run import check_distributable

    scene = load_scene("cantilever", _overrides(beam, "p1", 1))
    with pytest.raises(InputError, match=r"output\.volume: mpiexec -n 2 runs") as info:
        check_distributable(scene, 2)
    assert "\n" not in str(info.value)
    check_distributable(load_scene("cantilever", {**_overrides(beam, "p1", 1),
                                                  "output.volume": False}), 2)


# ---------------------------------------------------------------------------- other outputs
HAS_USD = importlib.util.find_spec("pxr") is not None


@pytest.mark.parametrize("fmt", [
    "obj", pytest.param("usd", marks=pytest.mark.skipif(
        not HAS_USD, reason="usd-core (pxr) is not installed: fem3d[scenes]"))])
def test_p2_frames_and_preview_are_the_subdivided_surface(fmt, beam, tmp_path):
    """OBJ and USD frames and preview.gif of a P2 run: the display surface, 4 linear triangles
    per quadratic boundary face through its corner and edge nodes, at the run's state."""
    out = tmp_path / fmt
    overrides = _overrides(beam, "p2", 2)
    overrides.pop("output.volume")
    assert main(["run", "cantilever", *_set_args(overrides), "--format", fmt, "--out",
                 str(out), "--quiet", "--checkpoint-every", "2"]) == 0
    sim = Simulation(load_scene("cantilever", overrides))
    faces = ELEMENTS["p2"].surface_triangles(sim.model.T)
    assert faces.shape[0] == 4 * ELEMENTS["p2"].boundary_faces(sim.model.T).shape[0]
    q = np.asarray(load_run_checkpoint(out / "checkpoint.npz").snapshot["q"])
    if fmt == "obj":  # positions as %.9g
        mesh = meshio.read(out / "frames" / "frame_00002.obj")
        points, tris, tol = mesh.points, mesh.cells_dict["triangle"], 1e-8
    else:
        from pxr import Usd, UsdGeom

        stage = Usd.Stage.Open(str(out / "frames.usdc"))
        prim = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
        usd = UsdGeom.Mesh(prim)
        points = np.asarray(usd.GetPointsAttr().Get(Usd.TimeCode(2)), dtype=np.float64)
        tris = np.asarray(usd.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
        assert set(np.asarray(usd.GetFaceVertexCountsAttr().Get()).tolist()) == {3}
        tol = 1e-6  # USD's points are float32
    assert points.shape == (sim.model.n_vertices, 3)  # edge nodes included
    np.testing.assert_allclose(points, q, rtol=0, atol=tol * np.abs(q).max())
    assert np.array_equal(np.sort(np.sort(tris, axis=1), axis=0),
                          np.sort(np.sort(faces, axis=1), axis=0))
    from PIL import Image

    with Image.open(out / "preview.gif") as gif:
        assert gif.n_frames == 3


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))
