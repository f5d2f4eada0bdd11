"""Surface and point loads and scripted pulls under ``mpiexec -n 2``: each loaded face is
added by the rank of the tet it bounds, each point force and pull spring by the rank that
owns its vertex, so that 2 ranks equal the one-process run (P1 and P2 faces; backward Euler
and the linearly-implicit scheme); the pins' reactions.csv too, each held DOF counted on the
rank that owns it."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.io.checkpoint import CHECKPOINT_NAME, load_run_checkpoint
from fem3d.io.energy import read_energy_csv
from fem3d.io.reactions import read_reactions_csv
from fem3d.physics.stress import vertex_fields
from fem3d.physics.terms.surface import faces_among
from fem3d.scene import load_scene
from fem3d.simulation import Simulation
from tests.parallel.helpers import relative_difference, run_mpi, write_scene
from tests.parallel.helpers import two_rank_runs as launch_two_rank_runs
from tests.parallel.test_mpi_checkpoint import GAMG
from tests.parallel.test_mpi_run import _p2_bar

# mpiexec's ranks poll while they wait: with another test on the cores they crawl
pytestmark = pytest.mark.alone

#: a traction on the tip, a pressure on the whole (closed) surface ramped in over 0.1 s,
#: a point force on a few vertices: the loads of one body
LOADS = """
[[bodies.loads]]
select = { box = [[0.999, -1, -1], [2, 1, 1]] }
traction = [0.0, 2000.0, 500.0]

[[bodies.loads]]
select = { box = [[-1, -1, -1], [2, 1, 2]] }
pressure = 300.0
keyframes = [{ t = 0.0, scale = 0.0 }, { t = 0.1, scale = 1.0 }]

[[bodies.loads]]
select = { box = [[0.99, -1, -1], [2, 1, 1]] }
force = [0.0, 30.0, 0.0]
"""

PULLS = """
[[pulls]]
body = 0
select = { box = [[0.9, -1, -1], [2, 1, 1]] }
start = 0.0
duration = 0.05
offset = [0.0, 0.1, 0.0]

[[pulls]]
body = 1
select = { box = [[0.95, -1, -1], [2, 1, 1]] }
start = 0.02
duration = 0.05
target = [1.0, 0.2, 0.6]
"""


def _loaded_box(folder, integrator):
    scene = write_scene(folder, integrator=integrator, steps=10)
    first, second = scene.read_text().rsplit("\n[[bodies]]\n", 1)  # the second bar
    scene.write_text(first + LOADS + "\n[[bodies]]\n" + second + LOADS)
    return scene


def _loaded_p2_bar(folder):
    scene = _p2_bar(folder, steps=5)
    scene.write_text(scene.read_text() + LOADS)
    return scene


def _pulled_box(folder, integrator):
    scene = write_scene(folder, integrator=integrator, steps=10)
    scene.write_text(scene.read_text() + PULLS)
    return scene


def _side_pinned_bar(folder):
    """One bar held along its whole y = 0 face, loaded: the cut between the ranks runs
    through the pin (vertices both ranks hold), so each DOF must count once."""
    scene = write_scene(folder, integrator="implicit", steps=10)
    text = scene.read_text().split("\n[[bodies]]\n")
    text[1] = text[1].replace("[[-1.0, -1.0, -1.0], [1e-6, 1.0, 1.0]]",
                              "[[-1.0, -1.0, -1.0], [2.0, 1e-6, 1.0]]")
    scene.write_text("\n[[bodies]]\n".join(text[:2]) + LOADS)
    return scene


#: the 2-rank runs compared with one process: name -> how its scene is made in a folder
SCENES = {**{f"loads {i}": lambda f, i=i: _loaded_box(f, i)
             for i in ("implicit", "bdf2", "linear")},
          "p2 loads": _loaded_p2_bar, "side pins": _side_pinned_bar,
          **{f"pulls {i}": lambda f, i=i: _pulled_box(f, i) for i in ("implicit", "linear")}}


@pytest.fixture(scope="module")
def two_rank_runs(tmp_path_factory):
    """The runs of :data:`SCENES` on 2 ranks, in one launch (``helpers.two_rank_runs``)."""
    return launch_two_rank_runs(tmp_path_factory, "loads_on_two_ranks", SCENES)


def _compare(run, steps: int, what: str) -> Simulation:
    """A 2-rank run of :func:`two_rank_runs` against its scene run in one process (the
    scripted pulls applied, as ``fem3d run`` does): the positions to 1e-8 of the motion,
    and the reactions.csv of the 2 ranks (each pin's DOFs counted on their owners, the
    forces summed over the ranks) the one-process reactions of every step, to 1e-7 of the
    largest. Returns the one-process simulation."""
    scene, proc = run
    assert proc.returncode == 0, proc.stderr[-3000:]
    state = np.load(scene.parent / "out" / "state.npz")
    sim = Simulation(load_scene(str(scene)), scripted=True)
    reactions = [sim.reactions()]
    for _ in range(steps):
        sim.step()
        reactions.append(sim.reactions())
    diff = relative_difference(state["q"], sim.q, sim.model.X)
    print(f"{what}: 2 ranks vs one process: relative difference {diff:.2e}")
    assert int(state["step"]) == steps and diff <= 1e-8
    assert relative_difference(state["v"], sim.v, 0.0 * sim.v) <= 1e-6
    rows = read_reactions_csv(scene.parent / "out" / "reactions.csv")
    expected = np.array(reactions).reshape(steps + 1, -1)
    assert sim.pin_groups and rows.shape == (steps + 1, 2 + 3 * len(sim.pin_groups))
    assert np.array_equal(rows[:, 0], np.arange(steps + 1))
    assert np.abs(rows[:, 2:] - expected).max() <= 1e-7 * np.abs(expected).max()
    return sim


@pytest.mark.parametrize("integrator", ["implicit", "bdf2", "linear"])
def test_loads_on_two_ranks_equal_one_process(two_rank_runs, integrator):
    """10 steps of the two-material box, each bar with a traction, a ramped follower
    pressure and a point force, on 2 ranks: the one-process run to 1e-8 of the motion (a
    load counted on both ranks would be off by its whole size)."""
    _compare(two_rank_runs[f"loads {integrator}"], 10, f"loads, {integrator}")


def test_reactions_of_a_pin_both_ranks_hold(two_rank_runs):
    """A pin along the whole bar, cut by the partition: the 2-rank reactions.csv is the
    one-process one (a DOF counted by both of its holders would double its share), and so
    are the pieces' stress fields at the vertices both ranks hold."""
    import meshio

    scene, _ = two_rank_runs["side pins"]
    sim = _compare(two_rank_runs["side pins"], 10, "a pin on both ranks")
    frames = scene.parent / "out" / "frames"
    for rank in (0, 1):  # each rank's piece has pinned points (at rest in frame 0)
        points = meshio.read(frames / f"frame_00000_{rank}.vtu").points
        assert (points[:, 1] == 0.0).sum() >= 4
    # the last frame's stress fields are the one-process ones, on the cut too (a vertex
    # both pieces have: its average over both ranks' elements)
    expected = vertex_fields(sim.model, sim.q)
    seen = []
    for rank in (0, 1):
        piece = meshio.read(frames / f"frame_00010_{rank}.vtu")
        d = np.linalg.norm(piece.points[:, None, :] - sim.q[None, :, :], axis=2)
        vertex = d.argmin(axis=1)
        assert d.min(axis=1).max() <= 1e-8
        for name, values in expected.items():
            got = piece.point_data[name].reshape(len(vertex), -1)
            want = values.reshape(len(sim.q), -1)[vertex]
            assert np.abs(got - want).max() <= 1e-6 * np.abs(want).max(), name
        seen.append(vertex)
    assert np.intersect1d(*seen).size > 0


def test_p2_loads_on_two_ranks_equal_one_process(two_rank_runs):
    """The P2 bar's 6-node faces: a traction, a ramped pressure and a point force, 5 steps
    on 2 ranks equal the one-process run to 1e-8 of the motion."""
    _compare(two_rank_runs["p2 loads"], 5, "P2 loads")


@pytest.mark.parametrize("integrator", ["implicit", "linear"])
def test_pulls_on_two_ranks_equal_one_process(two_rank_runs, integrator):
    """Two scripted pulls (an offset on one bar, a target on the other, overlapping in
    time) over 10 steps on 2 ranks: the one-process run to 1e-8 of the motion, and
    energy.csv's pull column the whole pull's energy."""
    run = two_rank_runs[f"pulls {integrator}"]
    _compare(run, 10, f"pulls, {integrator}")
    scene = run[0]
    energy = read_energy_csv(scene.parent / "out" / "energy.csv")
    sim = Simulation(load_scene(str(scene)), scripted=True)
    sim.step()
    assert energy["pull"][1] == pytest.approx(sim.energies()["pull"], rel=1e-8)
    assert energy["pull"][1] > 0 and energy["pull"][-1] == 0.0  # released by step 10


def test_faces_among_picks_a_share_of_the_faces():
    """A loaded face belongs to the share whose tets' boundary holds it, whatever the
    order of its corners (P1 and 6-node faces)."""
    faces = np.array([[0, 1, 2], [2, 3, 4], [5, 6, 7]])
    assert faces_among(faces, np.array([[4, 2, 3], [0, 1, 9]])).tolist() == [[2, 3, 4]]
    six = np.array([[0, 1, 2, 10, 11, 12], [2, 3, 4, 13, 14, 15]])
    assert faces_among(six, np.array([[1, 2, 0, 11, 12, 10]])).tolist() == \
        [[0, 1, 2, 10, 11, 12]]
    assert faces_among(six, np.zeros((0, 6), np.int64)).shape == (0, 6)


def test_pulls_and_loads_resume_on_two_ranks_bit_exact(tmp_path):
    """A 2-rank run with the loads and the pulls, checkpointed at step 5 (a pull attached)
    and resumed on 2 ranks to 10: bit for bit the straight 10-step run (CG + GAMG), its
    energy.csv and reactions.csv included (the resume keeps the rows up to step 5)."""
    scene = write_scene(tmp_path, integrator="bdf2", steps=10)
    first, second = scene.read_text().rsplit("\n[[bodies]]\n", 1)
    scene.write_text(first + LOADS + "\n[[bodies]]\n" + second + PULLS)
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    for out, steps in ((straight, "10"), (resumed, "5")):
        proc = run_mpi(2, "run", str(scene), "--steps", steps, "--checkpoint-every", "5",
                       "--out", str(out), *GAMG, cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-3000:]
    half = load_run_checkpoint(resumed / CHECKPOINT_NAME)
    assert half.step == 5 and half.snapshot["pull_vertices"].size  # a pull attached
    proc = run_mpi(2, "resume", str(resumed), "--steps", "10", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    a, b = np.load(straight / "state.npz"), np.load(resumed / "state.npz")
    assert np.array_equal(a["q"], b["q"]) and np.array_equal(a["v"], b["v"])
    for name in ("energy.csv", "reactions.csv"):
        assert (straight / name).read_bytes() == (resumed / name).read_bytes(), name
