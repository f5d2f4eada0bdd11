"""The contact pile (data/scenes/contact_pile.toml): 13 soft bodies in an open box.

The whole pile (16,464 tets) is run to rest by ``python -m bench.tools.pile_check`` (minutes; its
figures are in docs/contact.md). Here, in seconds: the scene file meets its brief, its initial
state is intersection-free and inside the box, and the pile's lower part (four blocks, an
upright bunny on each, the board across their ears: the scene's bodies 0-8, built from the
same file by overrides) falls through its impacts with every written frame checked by a test
of its own: a fresh ``ipctk.CollisionMesh`` of the frame's triangles (all bodies in one
group, so self-intersections count) and the box's bounds; neither is the solver's contact set.
"""

from __future__ import annotations

from pathlib import Path

import ipctk
import meshio
import numpy as np
import pytest

from bench.tools.pile_check import box_bounds, check_frames, rest_step
from fem3d.app.run import run_scene
from fem3d.scene import apply_overrides, load_scene
from fem3d.simulation import Simulation

ROOT = Path(__file__).resolve().parents[2]
SCENE = ROOT / "data" / "scenes" / "contact_pile.toml"
#: blocks 1-4, bunnies 1-4 (upright on them), the board (across the bunnies' ears)
COLUMNS = tuple(range(9))
#: with ``contact.self_contact = false`` the ears the board squashes pass into the bunnies'
#: heads from frame 11 on (measured: frames 11-15 intersect, ``python -m bench.tools.pile_check
#: --bodies 0,1,2,3,4,5,6,7,8 --steps 30 --set contact.self_contact=false``), so the run
#: goes past that
COLUMN_STEPS = 15


@pytest.fixture(scope="module")
def scene():
    return load_scene(str(SCENE))


def test_the_pile_is_what_its_brief_asks(scene):
    sim = Simulation(scene)
    assert len(scene.bodies) >= 12 and sim.model.n_tets >= 15_000
    assert sum("bunny" in b.mesh for b in scene.bodies) >= 4
    assert sum("block" in b.mesh for b in scene.bodies) >= 2
    c = scene.contact
    assert c.enabled and c.self_contact and c.mu > 0
    assert [o.mesh is not None for o in scene.obstacles] == [True]  # the box, a mesh obstacle
    lower, upper = box_bounds(scene)
    q = sim.q
    assert (q[:, [0, 2]] > lower[[0, 2]]).all() and (q[:, [0, 2]] < upper[[0, 2]]).all()
    assert (q[:, 1] > lower[1]).all()
    assert not sim.contact.contact.has_intersections(q.reshape(-1))


def _frames_like(tmp_path: Path, points: list[np.ndarray], cells) -> Path:
    (tmp_path / "frames").mkdir()
    for i, p in enumerate(points):
        meshio.write(tmp_path / "frames" / f"frame_{i:05d}.vtu",
                     meshio.Mesh(p, [("triangle", cells)]))
    return tmp_path


def test_the_frame_check_sees_intersections_and_vertices_outside(tmp_path):
    """The independent check itself: two tets' surfaces pushed into each other, a vertex
    moved out through a wall. (One group for all triangles: a body's own triangles that cross
    are found the same way as two bodies'.)"""
    lower, upper = np.array([-1.0, 0.0, -1.0]), np.array([1.0, 1.0, 1.0])
    tet = np.array([[0, 0, 0], [0.2, 0, 0], [0, 0.2, 0], [0, 0, 0.2]], float) + [0, 0.1, 0]
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    apart = np.vstack([tet, tet + [0.5, 0, 0]])
    cells = np.vstack([F, F + 4])
    into = np.vstack([tet, tet + [0.05, 0.02, 0.03]])
    out = apart.copy()
    out[5, 0] = 1.2  # through the wall x = 1
    rep = check_frames(_frames_like(tmp_path, [apart, into, out], cells), lower, upper)
    assert rep.frames == 3
    assert rep.intersecting == [1] and rep.outside == [2]
    assert rest_step(np.array([0.0, 1.0, 0.5, 1e-7, 1e-8]), 1e-6) == 3
    assert rest_step(np.array([0.0, 1.0, 1e-7, 0.5]), 1e-6) is None


def test_the_state_check_names_a_rest_that_ended():
    from bench.tools.contact_check import last_rest

    slipped = np.array([0.0, 1.0, 0.5, *[1e-8] * 12, 1e-3, 1e-2])
    assert last_rest(slipped, 1e-6) == (3, 14)
    assert last_rest(slipped, 1e-6, at_least=13) is None  # too short a rest
    assert last_rest(np.array([0.0, 1.0, *[1e-8] * 12]), 1e-6) is None  # at rest at the end


def test_the_state_check_sees_intersections_planes_boxes_and_obstacles():
    """``bench.tools.contact_check``'s per-state test: a body pushed into another, a vertex behind
    a plane, one out of the box, and a body crossing a mesh obstacle's triangle (the
    obstacle is in the same collision mesh), each flagged at its state only."""
    from bench.tools.contact_check import StateChecks

    tet = np.array([[0, 0, 0], [0.2, 0, 0], [0, 0.2, 0], [0, 0, 0.2]], float) + [0, 0.1, 0]
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    apart = np.vstack([tet, tet + [0.5, 0, 0]])
    wall = (np.array([[0.8, -1, -1], [0.8, 1, -1], [0.8, 0, 1]], float), np.array([[0, 1, 2]]))
    checks = StateChecks(np.vstack([F, F + 4]), [(np.zeros(3), np.array([0.0, 1.0, 0.0]))],
                         (np.array([-1.0, 0.0, -1.0]), np.array([1.0, 1.0, 1.0])))
    into = np.vstack([tet, tet + [0.05, 0.02, 0.03]])
    below = apart - [0, 0.15, 0]
    through_wall = apart + [0.25, 0, 0]  # the second tet straddles the plane x = 0.8
    outside = apart.copy()
    outside[5, 2] = 1.2
    for x in (apart, into, below, through_wall, outside):
        checks.add(x, [wall])
    assert checks.intersecting == [1, 3]
    assert checks.behind_plane == [2]
    assert checks.outside_box == [2, 4]  # below the floor y = 0 too
    assert not checks.ok


@pytest.mark.slow
def test_the_columns_and_the_board_land_without_intersecting(scene, tmp_path):
    d = scene.model_dump(mode="json")
    lower_part = apply_overrides(scene, {"bodies": [d["bodies"][i] for i in COLUMNS],
                                         "simulation.steps": COLUMN_STEPS})
    out = tmp_path / "lower_part"
    summary = run_scene(lower_part, out, quiet=True)
    assert summary.status == "ok", summary.message
    lower, upper = box_bounds(lower_part)
    rep = check_frames(out, lower, upper)
    assert rep.frames == COLUMN_STEPS + 1
    assert rep.intersecting == [], f"frames {rep.intersecting[:5]} intersect"
    assert rep.outside == []
    # the contacts the run is about were made by the end: the blocks on the floor, each
    # bunny on its block, the board on every bunny (surface pairs closer than 1 mm, by ipctk)
    sim = Simulation(lower_part)
    last = meshio.read(sorted((out / "frames").glob("*.vtu"))[-1])
    x = np.asarray(last.points, dtype=np.float64)
    assert x.shape == sim.q.shape
    touching = _touching_bodies(x, np.asarray(last.cells_dict["triangle"]),
                                sim.assembled.body_vertices)
    assert {(i, i + 4) for i in range(4)} | {(i, 8) for i in range(4, 8)} <= touching, touching
    for block in sim.assembled.body_vertices[:4]:
        assert x[block, 1].min() < 1e-3  # on the floor


def _touching_bodies(x: np.ndarray, faces: np.ndarray, bodies) -> set[tuple[int, int]]:
    """Pairs of bodies with surface primitives closer than 1 mm (ipctk's collision build)."""
    body = np.full(len(x), -1)
    for i, v in enumerate(bodies):
        body[v] = i
    F = np.asarray(faces, dtype=np.int32)
    cm = ipctk.CollisionMesh(np.asfortranarray(x), ipctk.edges(F), F)
    c = ipctk.NormalCollisions()
    c.build(cm, np.asfortranarray(x), 1e-3)
    pairs = set()
    for p in [*c.ee_collisions, *c.fv_collisions, *c.ev_collisions, *c.vv_collisions]:
        b = sorted({int(body[i]) for i in p.vertex_ids(cm.edges, cm.faces) if i >= 0})
        pairs |= {(b[0], b[-1])} if len(b) > 1 else set()
    return pairs


def test_the_newton_peer_row_says_why_it_is_skipped(monkeypatch, capsys):
    """``python -m bench.contact``'s Newton (VBD) row when Newton cannot be imported: a
    skipped row with the reason, printed and tabulated, never an exception."""
    import sys
    import types

    from bench import Skip
    from bench import contact as bench_contact
    from bench.peers import newton_vbd

    monkeypatch.setitem(sys.modules, "newton", None)  # import newton -> ImportError
    # Warp present (a stand-in where it is not installed): the row names newton itself
    monkeypatch.setitem(sys.modules, "warp", types.ModuleType("warp"))
    with pytest.raises(Skip, match="newton not installed"):
        newton_vbd.drop(np.zeros((4, 3)), np.array([[0, 1, 2, 3]]), steps=1, E=1e5, nu=0.3,
                        rho=1e3, mu=0.3, particle_radius=1e-3)
    row = bench_contact.run_newton_peer(1)
    assert row["tets"] == 1518 and "newton not installed" in row["skipped"]
    bench_contact._print_row(row)
    assert "skipped: newton not installed" in capsys.readouterr().out
    assert bench_contact._markdown_row(row).count("|") == 14  # 13 columns, like the others
