"""Obstacles in what a user sees: the preview GIF draws the ground, the VTU/PVD and USD frames
hold every obstacle's mesh (static ones once, moving ones per frame)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path
from xml.etree import ElementTree

import meshio
import numpy as np
import pytest
from PIL import Image

from fem3d.io.frames import UsdWriter, VtuWriter
from fem3d.io.obstacles import ObstacleMesh, plane_square
from fem3d.io.preview import render_preview

needs_usd = pytest.mark.skipif(importlib.util.find_spec("pxr") is None,
                               reason="usd-core not installed")


def _box(lo: float = 0.1, hi: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """A closed cube's corners and 12 outward triangles."""
    V = np.array([[x, y, z] for x in (lo, hi) for y in (lo, hi) for z in (lo, hi)], float)
    V[:, 0] -= 0.2
    V[:, 2] -= 0.2
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return V, F


def _ground() -> ObstacleMesh:
    point, normal = np.zeros(3), np.array([0.0, 1.0, 0.0])
    V, F = plane_square(point, normal, np.zeros(3), 1.0, cells=4)
    return ObstacleMesh("obstacles[0] (plane)", V, F, plane=(point, normal))


def _ramp(moving: bool) -> ObstacleMesh:
    V = np.array([[0.5, 0.0, 0.0], [0.7, 0.0, 0.0], [0.5, 0.1, 0.0]])
    motion = (lambda t: V + [0.0, t, 0.0]) if moving else None
    return ObstacleMesh("obstacles[1] (ramp.obj)", V, np.array([[0, 1, 2]]), motion=motion)


def test_plane_square_is_a_grid_in_the_plane() -> None:
    n = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    V, F = plane_square(np.array([0.0, 1.0, 0.0]), n, np.array([3.0, 0.0, 1.0]), 2.0, cells=3)
    assert V.shape == (16, 3) and F.shape == (18, 3)
    np.testing.assert_allclose((V - [0.0, 1.0, 0.0]) @ n, 0.0, atol=1e-12)
    tri = V[F]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (normals @ n > 0).all()  # facing the free side
    area = 0.5 * np.linalg.norm(normals, axis=1).sum()
    np.testing.assert_allclose(area, 16.0, rtol=1e-12)  # (2 half)^2


def test_the_preview_draws_the_ground_below_the_body(tmp_path) -> None:  # noqa: ANN001
    V, F = _box()
    frames = [V, V]
    kw = dict(size=120)
    render_preview(frames, F, tmp_path / "bare.gif", **kw, first_frame_png=tmp_path / "a.png")
    render_preview(frames, F, tmp_path / "ground.gif", **kw, first_frame_png=tmp_path / "b.png",
                   obstacles=[_ground()])
    bare = np.asarray(Image.open(tmp_path / "a.png").convert("RGB"), dtype=float)
    ground = np.asarray(Image.open(tmp_path / "b.png").convert("RGB"), dtype=float)
    below = slice(115, 120)  # the bottom rows: margin under the body, or the floor
    assert (bare[below] > 250).all()  # white space without the plane
    floor = ground[below]
    assert (floor < 240).mean() > 0.9  # drawn
    # a checkerboard: two grey levels a user can read
    levels = np.unique(floor[..., 0].round(-1))
    assert levels.size >= 2 and np.ptp(floor[..., 0]) > 20
    # the body is still drawn over the ground, in its own colour
    centre = ground[55:65, 55:65]
    assert np.abs(centre[..., 0] - centre[..., 2]).mean() > 10  # tan, not grey


def test_the_preview_draws_a_moving_mesh_obstacle_where_it_is(tmp_path) -> None:  # noqa: ANN001
    V, F = _box()
    ramp = _ramp(moving=True)
    render_preview([V, V], F, tmp_path / "m.gif", size=100, obstacles=[ramp], times=[0.0, 0.2])
    gif = Image.open(tmp_path / "m.gif")
    assert gif.n_frames == 2  # the obstacle moved between the frames


@pytest.mark.parametrize("compression", [None, "zlib"])
def test_vtu_frames_hold_the_obstacles(tmp_path, compression) -> None:  # noqa: ANN001
    V, F = _box()
    w = VtuWriter(tmp_path, F, compression=compression,
                    obstacles=[_ground(), _ramp(moving=True)])
    for k in range(3):
        w.write(k, 0.1 * k, V + [0.0, -0.01 * k, 0.0])
    w.flush()
    files = sorted(p.name for p in (tmp_path / "frames").iterdir())
    assert files == ["frame_00000.vtu", "frame_00001.vtu", "frame_00002.vtu"]
    files = sorted(p.name for p in (tmp_path / "obstacles").iterdir())
    assert files == ["obstacle_0.vtu", "obstacle_1_00000.vtu", "obstacle_1_00001.vtu",
                     "obstacle_1_00002.vtu"]
    g = meshio.read(tmp_path / "obstacles" / "obstacle_0.vtu")
    np.testing.assert_allclose(g.points[:, 1], 0.0)
    assert g.cells_dict["triangle"].shape == (32, 3)
    r = meshio.read(tmp_path / "obstacles" / "obstacle_1_00002.vtu")
    np.testing.assert_allclose(r.points, _ramp(True).positions(0.2))
    parts = [(d.get("timestep"), d.get("part"), d.get("file"))
             for d in ElementTree.parse(tmp_path / "frames.pvd").iter("DataSet")]
    assert ("0.1", "1", "obstacles/obstacle_0.vtu") in parts
    assert ("0.1", "2", "obstacles/obstacle_1_00001.vtu") in parts
    assert len(parts) == 9
    # a resume from step 1 drops the later moving frames
    w.restore({0: (0.0, "frames/frame_00000.vtu"), 1: (0.1, "frames/frame_00001.vtu")}, 1)
    assert not (tmp_path / "obstacles" / "obstacle_1_00002.vtu").exists()
    assert (tmp_path / "obstacles" / "obstacle_0.vtu").exists()


def test_frames_without_obstacles_are_unchanged(tmp_path) -> None:  # noqa: ANN001
    V, F = _box()
    w = VtuWriter(tmp_path, F)
    w.write(0, 0.0, V)
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == ["frame_00000.vtu"]
    assert w.pvd_text().count("<DataSet") == 1


@needs_usd
def test_usd_stage_has_a_prim_per_obstacle(tmp_path) -> None:  # noqa: ANN001
    from pxr import Usd, UsdGeom

    V, F = _box()
    w = UsdWriter(tmp_path, F, [("box", slice(0, 8), slice(0, 12))], 0.1,
                  obstacles=[_ground(), _ramp(moving=True)])
    for k in range(3):
        w.write(k, 0.1 * k, V)
    w.close()
    stage = Usd.Stage.Open(str(tmp_path / "frames.usdc"))
    ground = UsdGeom.Mesh(stage.GetPrimAtPath("/World/obstacle_0"))
    ramp = UsdGeom.Mesh(stage.GetPrimAtPath("/World/obstacle_1"))
    assert ground and ramp
    P = np.asarray(ground.GetPointsAttr().Get(Usd.TimeCode(2)))
    np.testing.assert_allclose(P[:, 1], 0.0)
    assert len(ground.GetFaceVertexIndicesAttr().Get()) == 3 * 32
    for k in range(3):
        R = np.asarray(ramp.GetPointsAttr().Get(Usd.TimeCode(k)))
        np.testing.assert_allclose(R, _ramp(True).positions(0.1 * k), atol=1e-6)
    box = UsdGeom.Mesh(stage.GetPrimAtPath("/World/box"))
    np.testing.assert_allclose(np.asarray(box.GetPointsAttr().Get(Usd.TimeCode(1))), V,
                               atol=1e-6)


def test_a_contact_run_writes_the_ground(tmp_path) -> None:  # noqa: ANN001
    out = tmp_path / "drop"
    env_path = str(Path(__file__).resolve().parents[2])
    cmd = [sys.executable, "-m", "fem3d.app.cli", "run", "contact_bunny_drop", "--steps", "2",
           "--out", str(out), "--quiet"]
    import os

    env = dict(os.environ, PYTHONPATH=env_path)
    subprocess.run(cmd, check=True, capture_output=True, env=env, timeout=120)
    g = meshio.read(out / "obstacles" / "obstacle_0.vtu")
    np.testing.assert_allclose(g.points[:, 1], 0.0, atol=1e-12)
    bunny = meshio.read(out / "frames" / "frame_00000.vtu").points
    # the square spans the bunny's footprint
    assert g.points[:, 0].min() < bunny[:, 0].min() and g.points[:, 0].max() > bunny[:, 0].max()
    assert 'file="obstacles/obstacle_0.vtu"' in (out / "frames.pvd").read_text()
    assert (out / "preview.gif").is_file()


def _open_box(half: float = 0.5, height: float = 0.6) -> ObstacleMesh:
    """An open box around the origin (floor at y = 0, four walls, no lid), 2 triangles a side."""
    a, h = half, height
    c = np.array([[-a, 0, -a], [a, 0, -a], [a, 0, a], [-a, 0, a]], float)
    V = np.vstack([c, c + [0.0, h, 0.0]])
    F = [[0, 2, 1], [0, 3, 2]]  # the floor
    for i in range(4):
        j = (i + 1) % 4
        F += [[i, j, j + 4], [i, j + 4, i + 4]]
    return ObstacleMesh("obstacles[0] (box.obj)", V, np.array(F))


def _tan_pixels(png: Path) -> int:
    """Pixels of the bodies' colour (tan: red well above blue) in a preview PNG."""
    rgb = np.asarray(Image.open(png).convert("RGB"), dtype=float)
    return int(((rgb[..., 0] - rgb[..., 2]) > 25).sum())


def test_the_preview_cuts_an_open_box_away_to_show_what_is_inside(tmp_path) -> None:  # noqa: ANN001
    """A body inside an open box, seen from the side: the walls on the camera's side are not
    drawn, so the body shows; the picture is the one of the floor and the far walls alone. A
    box that does not hold the body, or one seen from straight above, is drawn whole."""
    from fem3d.io.preview import _camera, _cut_away

    V, F = _box(0.05, 0.25)  # a cube inside the box, below its rim
    box = _open_box()
    kw = dict(size=120, elev=20.0, azim=30.0)
    render_preview([V], F, tmp_path / "in.gif", **kw, first_frame_png=tmp_path / "in.png",
                   obstacles=[box])
    # the camera looks from +x, +z: the walls x = +0.5 and z = +0.5 are the near ones
    far = ObstacleMesh(box.name, box.vertices, box.faces[[0, 1, 2, 3, 8, 9]])
    render_preview([V], F, tmp_path / "far.gif", **kw, first_frame_png=tmp_path / "far.png",
                   obstacles=[far])
    seen = np.asarray(Image.open(tmp_path / "in.png").convert("RGB"))
    np.testing.assert_array_equal(seen, np.asarray(Image.open(tmp_path / "far.png").convert("RGB")))
    assert _tan_pixels(tmp_path / "in.png") > 150  # the cube, about 17 px wide
    grey = seen.astype(float)
    assert ((np.abs(grey[..., 0] - grey[..., 2]) < 60) & (grey[..., 0] < 235)).mean() > 0.2
    toward = _camera(20.0, 30.0)[2]
    kept, holds = _cut_away(box.faces, box.vertices, V, toward)
    assert holds and len(kept) == 6
    kept, holds = _cut_away(box.faces, box.vertices + [5.0, 0.0, 0.0], V, toward)
    assert not holds and len(kept) == 10
    assert len(_cut_away(box.faces, box.vertices, V, _camera(90.0, 30.0)[2])[0]) == 10


def test_a_body_on_the_floor_of_an_open_box_is_drawn_whole(tmp_path) -> None:  # noqa: ANN001
    """The box's floor is two large triangles, each with its centre nearer the camera than
    the cube standing on it: sorted by its farthest vertex (the box is a backdrop), the floor
    hides none of the cube (as many cube pixels as without the floor)."""
    V, F = _box(0.0, 0.2)  # on the floor y = 0
    box = _open_box()
    walls = ObstacleMesh(box.name, box.vertices, box.faces[2:])
    kw = dict(size=160, elev=25.0, azim=30.0)
    counts = []
    for ob in (box, walls):
        png = tmp_path / f"{len(ob.faces)}.png"
        render_preview([V], F, tmp_path / "x.gif", **kw, first_frame_png=png, obstacles=[ob])
        counts.append(_tan_pixels(png))
    assert counts[1] > 300
    assert counts[0] == counts[1]
