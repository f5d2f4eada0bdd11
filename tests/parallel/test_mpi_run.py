"""One simulation on several ranks: ``mpiexec -n 2 fem3d run`` equals the one-process run,
writes its pieces, and refuses what it cannot do in one line; the parts it is made of
(face graph, DOF layout, local models) checked in one process."""

from __future__ import annotations

import subprocess
import sys
import xml.etree.ElementTree as ET
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from fem3d.io.energy import read_energy_csv
from fem3d.parallel.partition import dual_graph, partition_tets
from fem3d.physics.stress import vertex_fields
from fem3d.physics.terms.base import StepMap
from fem3d.scene import load_scene
from fem3d.scene.local import split_tets
from fem3d.simulation import Simulation
from fem3d.solve.integrators import model_terms
from fem3d.solve.system import System
from tests.parallel.helpers import (
    MESH,
    mpi_env,
    mpiexec_or_skip,
    relative_difference,
    run_mpi,
    write_scene,
)
from tests.parallel.helpers import two_rank_runs as launch_two_rank_runs

# mpiexec's ranks poll while they wait: with another test on the cores they crawl
pytestmark = pytest.mark.alone


def _one_process(scene_path, steps=20) -> Simulation:
    sim = Simulation(load_scene(str(scene_path)))
    for _ in range(steps):
        sim.step()
    return sim


#: the box's integrator and PETSc options on 2 ranks (none: the default, MUMPS)
BOX_CASES = [("implicit", ""), ("bdf2", ""), ("implicit", "-ksp_type cg -pc_type gamg"),
             ("newmark", ""), ("linear", "")]


def _box(folder, integrator, options=""):
    scene = write_scene(folder, integrator=integrator)
    if options:
        scene.write_text(scene.read_text().replace(
            'linear_solver = "auto"', f'linear_solver = "petsc"\npetsc_options = "{options}"'))
    return scene


def _static_box(folder):
    scene = write_scene(folder, integrator="static", steps=3)
    scene.write_text(scene.read_text().replace("velocity = [0.0, 0.0, 0.3]", ""))
    return scene


@pytest.fixture(scope="module")
def two_rank_runs(tmp_path_factory):
    """The 2-rank runs the tests below compare, in one launch (``helpers.two_rank_runs``)."""
    scenes = {f"{integrator} {options}": lambda f, i=integrator, o=options: _box(f, i, o)
              for integrator, options in BOX_CASES}
    scenes |= {"static": _static_box, "pieces": lambda f: write_scene(f, steps=3),
               "p2": lambda f: _p2_bar(f, steps=5)}
    return launch_two_rank_runs(tmp_path_factory, "two_ranks", scenes)


@pytest.mark.parametrize("integrator, options", BOX_CASES)
def test_two_ranks_equal_one_process(tmp_path, two_rank_runs, integrator, options):
    """20 steps of the two-material box (Neo-Hookean, damped StVK) on 2 ranks (MUMPS, and
    CG + GAMG) equal the one-process run (the default direct solver) to 1e-8 of the
    motion; the linearly-implicit scheme's one solve per step too (its forces and
    right-hand side summed over the ranks)."""
    scene, proc = two_rank_runs[f"{integrator} {options}"]
    folder = scene.parent
    assert proc.returncode == 0, proc.stderr[-3000:]
    state = np.load(folder / "out" / "state.npz")
    assert int(state["step"]) == 20
    sim = _one_process(write_scene(tmp_path / "one", integrator=integrator))
    diff = relative_difference(state["q"], sim.q, sim.model.X)
    print(f"{integrator} {options or 'mumps'}: 2 ranks vs one process: relative difference "
          f"{diff:.2e}")
    assert diff <= 1e-8
    assert relative_difference(state["v"], sim.v, 0.0 * sim.v) <= 1e-6
    energy = read_energy_csv(folder / "out" / "energy.csv")
    assert len(energy["t"]) == 21
    assert abs(energy["kinetic"][-1] - sim.energies()["kinetic"]) <= \
        1e-6 * sim.energies()["kinetic"]


def test_static_on_two_ranks_equals_one_process(two_rank_runs):
    """3 static steps (equilibria under gravity, load increments where Newton needs them) of
    the two-material box at rest on 2 ranks equal the one-process run to 1e-8 of the
    displacement."""
    scene, proc = two_rank_runs["static"]
    folder = scene.parent
    assert proc.returncode == 0, proc.stderr[-3000:]
    state = np.load(folder / "out" / "state.npz")
    sim = _one_process(scene, steps=3)
    diff = relative_difference(state["q"], sim.q, sim.model.X)
    print(f"static: 2 ranks vs one process: relative difference {diff:.2e}")
    assert int(state["step"]) == 3 and diff <= 1e-8
    assert not state["v"].any()


def test_two_ranks_write_pieces(two_rank_runs):
    """Each frame: one .vtu piece per rank (the surface of its tets), a .pvtu naming both,
    frames.pvd listing the frames; the pieces' points are the run's positions; the run's
    energy.png."""
    import meshio

    scene, proc = two_rank_runs["pieces"]
    folder = scene.parent
    assert proc.returncode == 0, proc.stderr[-3000:]
    frames = folder / "out" / "frames"
    pvd = ET.parse(folder / "out" / "frames.pvd").getroot()
    files = [d.get("file") for d in pvd.iter("DataSet")]
    assert files == [f"frames/frame_{i:05d}.pvtu" for i in range(4)]
    pvtu = ET.parse(frames / "frame_00003.pvtu").getroot()
    sources = [p.get("Source") for p in pvtu.iter("Piece")]
    assert sources == ["frame_00003_0.vtu", "frame_00003_1.vtu"]
    state = np.load(folder / "out" / "state.npz")
    seen = []
    for rank, src in enumerate(sources):
        piece = meshio.read(frames / src)
        assert piece.cells[0].data.shape[1] == 3 and len(piece.points) > 0
        assert (piece.point_data["rank"] == rank).all()
        # every piece point is a vertex of the run, where the run left it
        d = np.linalg.norm(piece.points[:, None, :] - state["q"][None, :, :], axis=2)
        assert d.min(axis=1).max() == 0.0
        seen.append(d.argmin(axis=1))
    surface = Simulation(load_scene(str(scene))).surface_faces
    assert set(np.unique(surface)) <= set(np.concatenate(seen))  # the pieces cover it
    # and energy.png, as a one-process run ends
    assert (folder / "out" / "energy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_two_ranks_pieces_read_in_vtk(two_rank_runs):
    """VTK's own parallel reader (ParaView's) opens a frame's .pvtu: both pieces, together
    the body's surface triangles once each, every point where the run left its vertex, each
    rank's points tagged with it, and the one-process frame's stress fields."""
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy

    scene, proc = two_rank_runs["pieces"]
    out = scene.parent / "out"
    assert proc.returncode == 0, proc.stderr[-3000:]
    reader = vtk.vtkXMLPUnstructuredGridReader()
    reader.SetFileName(str(out / "frames" / "frame_00003.pvtu"))
    reader.Update()
    grid = reader.GetOutput()
    assert reader.GetNumberOfPieces() == 2
    n_cells = grid.GetNumberOfCells()
    assert {grid.GetCellType(e) for e in range(n_cells)} == {vtk.VTK_TRIANGLE}
    points = vtk_to_numpy(grid.GetPoints().GetData())
    q = np.load(out / "state.npz")["q"]
    d = np.linalg.norm(points[:, None, :] - q[None, :, :], axis=2)
    assert d.min(axis=1).max() == 0.0  # each point is a vertex, where the run left it
    vertex = d.argmin(axis=1)
    cells = vtk_to_numpy(grid.GetCells().GetConnectivityArray()).reshape(n_cells, 3)
    surface = Simulation(load_scene(str(scene))).surface_faces
    assert n_cells == len(surface)
    assert set(map(frozenset, vertex[cells].tolist())) == set(map(frozenset, surface.tolist()))
    ranks = vtk_to_numpy(grid.GetPointData().GetArray("rank"))
    assert set(ranks.tolist()) == {0, 1}
    # the stress fields of the one-process frame, to 1e-6 of the largest
    sim = _one_process(scene, steps=3)
    expected = vertex_fields(sim.model, sim.q)
    for name, values in expected.items():
        got = vtk_to_numpy(grid.GetPointData().GetArray(name)).reshape(len(points), -1)
        want = values.reshape(len(q), -1)[vertex]
        assert np.abs(got - want).max() <= 1e-6 * np.abs(want).max(), name


def test_a_skinned_scene_on_two_ranks_writes_the_display_mesh(tmp_path):
    """The bunny (a display mesh skinned to its tets) on 2 ranks: the one-process frames,
    ``frames/frame_NNNNN.vtu`` of the display mesh (rank 0 skins the gathered positions),
    its points and stress fields those of one process (to 1e-8 of the size and 1e-6 of the
    largest), no pieces."""
    import meshio

    out = tmp_path / "out"
    proc = run_mpi(2, "run", "bunny", "--steps", "3", "--out", str(out), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert sorted(p.name for p in (out / "frames").iterdir()) == \
        [f"frame_{i:05d}.vtu" for i in range(4)]
    sim = Simulation(load_scene("bunny"), scripted=True)  # (its pull, as fem3d run has it)
    for _ in range(3):
        sim.step()
    frame = meshio.read(out / "frames" / "frame_00003.vtu")
    V = sim.skin_positions()
    assert np.array_equal(frame.cells[0].data, sim.display_faces)
    assert np.abs(frame.points - V).max() <= 1e-8 * np.ptp(V, axis=0).max()
    W = sim.skinning_matrix
    for name, values in vertex_fields(sim.model, sim.q).items():
        want = np.asarray(W @ values)
        assert np.abs(frame.point_data[name] - want).max() <= 1e-6 * np.abs(want).max(), name


def test_without_pymetis_petscs_partitioner_cuts(tmp_path):
    """Without pymetis (its import fails), PETSc's graph partitioner cuts the mesh: 5 steps
    of the box on 2 ranks still equal the one-process run to 1e-8 of the motion."""
    scene = write_scene(tmp_path, steps=5)
    out = tmp_path / "out"
    script = ("import sys\n"
              "sys.modules['pymetis'] = None  # `import pymetis` raises ImportError\n"
              "from fem3d.app.cli import main\n"
              f"sys.exit(main(['run', {str(scene)!r}, '--out', {str(out)!r}]))\n")
    cmd = [*mpiexec_or_skip(), "2", sys.executable, "-c", script]
    proc = subprocess.run(cmd, cwd=tmp_path, env=mpi_env(), capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    state = np.load(out / "state.npz")
    sim = _one_process(scene, steps=5)
    assert int(state["step"]) == 5
    assert relative_difference(state["q"], sim.q, sim.model.X) <= 1e-8


@pytest.mark.parametrize("extra, key", [
    ('[contact]\nenabled = true\n[[obstacles]]\nplane = { point = [0, -1, 0], normal = '
     '[0, 1, 0] }', "contact.enabled"),
])
def test_refused_in_one_line(tmp_path, extra, key):
    scene = write_scene(tmp_path, steps=1)
    scene.write_text(scene.read_text() + "\n" + extra + "\n")
    proc = run_mpi(2, "run", str(scene), "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and key in lines[0] and "mpiexec -n 2" in lines[0], proc.stderr
    assert not (tmp_path / "out").exists()


def test_a_scheme_not_marked_distributed_is_refused_in_one_line(tmp_path, monkeypatch):
    """A scheme without ``distributed`` (a plug-in's; every built-in scheme runs on ranks)
    is refused naming the key and the schemes that run."""
    from fem3d.errors import InputError
    from fem3d.parallel.run import check_distributable
    from fem3d.solve.schemes.registry import get_scheme

    monkeypatch.setattr(type(get_scheme("newmark")), "distributed", False)
    scene = load_scene(str(write_scene(tmp_path, integrator="newmark", steps=1)))
    with pytest.raises(InputError) as err:
        check_distributable(scene, 2)
    message = str(err.value)
    assert "simulation.integrator" in message and "'newmark'" in message
    assert "linear, implicit, bdf2, static" in message and "\n" not in message


def test_missing_extra_is_one_line(tmp_path, monkeypatch):
    """petsc4py that does not import: one line naming the extra, exit 2, nothing written."""
    blocker = tmp_path / "block" / "petsc4py"
    blocker.mkdir(parents=True)
    (blocker / "__init__.py").write_text("raise ImportError('blocked by the test')\n")
    monkeypatch.setenv("PYTHONPATH", str(tmp_path / "block"))
    scene = write_scene(tmp_path, steps=1)
    proc = run_mpi(2, "run", str(scene), "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "fem3d[mpi]" in lines[0] and "mpiexec -n 2" in lines[0], \
        proc.stderr
    assert not (tmp_path / "out").exists()


def test_viewer_refused_in_one_line(tmp_path):
    proc = run_mpi(2, "view", "bunny", cwd=tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "runs in one process, not under mpiexec -n 2" in lines[0]


def test_a_slow_rank_0_still_says_the_failure(tmp_path):
    """Rank 1 fails at once, rank 0 takes 2 s to say why: Open MPI's mpiexec ends every rank
    as soon as one exits non-zero, so without :func:`leave_together` rank 0's line was lost
    (seen under load: exit 2 and nothing on stderr)."""
    script = ("import sys, time\n"
              "from fem3d.parallel.comm import launched_rank, leave_together\n"
              "if launched_rank() == 0:\n"
              "    time.sleep(2.0)\n"
              "    print('rank 0: the one line', file=sys.stderr)\n"
              "leave_together()\n"
              "sys.exit(2)\n")
    cmd = [*mpiexec_or_skip(), "2", sys.executable, "-c", script]
    proc = subprocess.run(cmd, cwd=tmp_path, env=mpi_env(), capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == ["rank 0: the one line"]


# -- the parts, in one process ------------------------------------------------------------
def test_dual_graph_of_two_tets():
    T = np.array([[0, 1, 2, 3], [1, 2, 3, 4], [5, 6, 7, 8]])
    indptr, indices = dual_graph(T)
    assert indptr.tolist() == [0, 1, 2, 2]
    assert indices.tolist() == [1, 0]


def test_metis_cuts_the_same_way_every_time():
    """``partition_tets`` with pymetis: rank 0's METIS cut (fixed seed) of a 20,000-tet box
    into 3 parts is the same in every call, balanced, and the parts' faces between them are
    few (PT-Scotch cut a 1e5-tet box differently in every run: docs/parallel.md)."""
    pytest.importorskip("pymetis")
    from bench.meshes import box_mesh

    _, T = box_mesh(2e4)
    cuts = [partition_tets(T, 3) for _ in range(3)]
    assert all(np.array_equal(cuts[0], c) for c in cuts[1:])
    sizes = np.bincount(cuts[0])
    assert sizes.size == 3 and sizes.min() >= 0.95 * len(T) / 3
    indptr, indices = dual_graph(T)
    rows = np.repeat(np.arange(len(T)), np.diff(indptr))
    between = int((cuts[0][rows] != cuts[0][indices]).sum()) // 2
    assert between < 0.05 * indices.size / 2  # of the faces two tets share


class _Comm:
    """Rank ``rank`` of ``size`` without MPI: what rank 0 sends is recorded; a receive
    returns ``incoming``; ``allgather`` returns this rank's row alone, ``bcast`` its
    value."""

    def __init__(self, size, rank, incoming=None):
        self.size, self.rank, self.incoming, self.sent = size, rank, incoming, []

    def Get_size(self):
        return self.size

    def Get_rank(self):
        return self.rank

    def send(self, message, dest):
        self.sent.append((dest, message))

    def recv(self, source):
        return self.incoming

    def allgather(self, row):
        return [row]

    def bcast(self, value, root):
        return value


def test_a_resume_on_as_many_ranks_keeps_the_checkpoints_partition(monkeypatch):
    """``RankShare.part`` given a partition (a resume's, written on as many ranks) takes it
    rather than partitioning anew (PT-Scotch's partition differs from run to run: a new one
    would sum in another order, docs/parallel.md); one of another mesh or rank count is
    partitioned anew. Rank 0 keeps the partition it used (the checkpoints write it) and
    sends rank 1 its tets; rank 1 keeps none."""
    from fem3d.parallel import run as parallel_run

    T = np.array([[0, 1, 2, 3], [1, 2, 3, 4], [2, 3, 4, 5]])
    whole = SimpleNamespace(arrays=SimpleNamespace(X=np.zeros((6, 3)), T=T,
                                                   skinning_matrix=lambda: None))
    made = []
    monkeypatch.setattr(parallel_run, "partition_tets",
                        lambda T, n: made.append(len(T)) or np.array([0, 0, 1]))

    def cut(whole, tets, owner, rank):
        return tets.tolist(), owner.tolist()

    comm = _Comm(2, 0)
    share = parallel_run.RankShare(comm, partition=np.array([1, 0, 1], dtype=np.int32))
    assert share.part(lambda: whole, cut) == ([1], [1, 0, 0, 0, 0, 1]) and not made
    assert comm.sent[0][0] == 1 and comm.sent[0][1][1] == ([0, 2], [1, 0, 0, 0, 0, 1])
    assert share.partition.tolist() == [1, 0, 1] and share.n_vertices == 6
    for other in ([0, 1], [0, 0, 0], [0, 1, 2]):  # another mesh; one rank; three ranks
        share = parallel_run.RankShare(_Comm(2, 0), partition=np.array(other))
        assert share.part(lambda: whole, cut)[0] == [0, 1]
        assert share.partition.tolist() == [0, 0, 1] and share.partition.dtype == np.int32
    assert made == [3, 3, 3]
    rank1 = _Comm(2, 1, incoming=("part", "rank 1's part", "digest", 6))
    share = parallel_run.RankShare(rank1, partition=np.array([1, 0, 1], dtype=np.int32))
    assert share.part(lambda: pytest.fail("rank 1 read the scene"), cut) == "rank 1's part"
    assert share.partition is None and share.digest == "digest" and share.n_vertices == 6


def test_a_failure_rank_0_meets_reading_is_every_ranks(tmp_path):
    """An :class:`InputError` rank 0 meets reading or cutting the scene goes to the ranks
    it has not sent a part to, and every rank raises it (``RankShare.agree``)."""
    from fem3d.errors import InputError
    from fem3d.parallel.run import RankShare

    def read():
        raise InputError("box.toml: bodies[0].mesh: no such file")

    comm = _Comm(3, 0)
    with pytest.raises(InputError, match="no such file"):
        RankShare(comm).part(read, None)
    assert [d for d, m in comm.sent] == [1, 2] and all(m[0] == "failure" for _, m in comm.sent)
    failed = _Comm(3, 2, incoming=("failure", "box.toml: bodies[0].mesh: no such file"))
    failed.allgather = lambda row: ["box.toml: bodies[0].mesh: no such file", "", row]
    with pytest.raises(InputError, match="no such file"):
        RankShare(failed).part(read, None)


class _Unsolved(System):
    """A System that never solves (a local model's rows of other ranks' vertices are empty:
    no solver of its own could factorize them)."""

    def _new_direct_solver(self, pattern):
        return None


class _Share:
    """One process's stand-in for rank ``rank`` of a split of the tets ``parts`` (the
    :class:`~fem3d.scene.build.Share` protocol without MPI): the part is cut as rank 0
    cuts it (a vertex owned by the lowest part holding it)."""

    def __init__(self, parts, rank, summary=None):
        self.parts, self.rank, self._summary = parts, rank, summary

    def part(self, read, cut):
        whole = read()
        tet_rank = np.zeros(whole.arrays.T.shape[0], dtype=np.int64)
        for r, p in enumerate(self.parts):
            tet_rank[p] = r
        tets, owner = split_tets(whole.arrays.T, tet_rank, len(self.parts))
        return cut(whole, tets[self.rank], owner, self.rank)

    def hold(self, numbering, constraints):
        pass

    def agree(self, failure):
        assert failure == ""

    def summary(self, model):
        return model if self._summary is None else self._summary(model)


def _halves(n_tets, seed=1):
    rng = np.random.default_rng(seed)
    first = np.sort(rng.permutation(n_tets)[:n_tets // 2])
    return [first, np.setdiff1d(np.arange(n_tets), first)]


def test_local_models_sum_to_the_whole(tmp_path):
    """The shares ``build_share`` makes of a split of the tets (two materials, damping,
    gravity, each over its own vertices): their energies, gradients and Newton matrices,
    carried to the scene's numbering, sum to the whole model's."""
    from fem3d.scene.share import build_share

    scene = load_scene(str(write_scene(tmp_path)))
    sim = Simulation(scene)
    model, system, c = sim.model, sim.system, sim.constraints
    parts = _halves(model.n_tets)
    rng = np.random.default_rng(1)
    q = sim.q.reshape(-1) + 1e-3 * rng.standard_normal(model.n_dofs)
    v = 0.1 * rng.standard_normal(model.n_dofs)

    def evaluate(s, dofs):
        """Energies, gradients (scene-long) and the Newton matrix (whole free numbering) of
        system ``s`` over the scene DOFs ``dofs``."""
        sc = s.constraints
        qs, vs = q[dofs], v[dofs]
        step = StepMap(constraints=sc, h=0.01, dt=0.01, t=0.0, step=0, q_t=qs, v_t=vs,
                       q_base=qs, v_hat_free=vs[sc.free_dofs])
        terms = [t for t in model_terms(s) if t.active]
        for t in terms:
            t.begin_step(step)
        e, g = [], []
        for t in terms:
            position = t.variable == "position"
            e.append(t.energy(qs if position else vs[sc.free_dofs]))
            full = np.zeros(model.n_dofs)
            local = t.gradient(qs if position else vs[sc.free_dofs])
            full[dofs if position else dofs[sc.free_dofs]] = local
            g.append(full)
        H = s.newton_matrix(qs, 0.01, damping=s.loads.damping_data(qs)).tocoo()
        free_of = np.full(model.n_dofs, -1)
        free_of[c.free_dofs] = np.arange(c.n_free)
        rows, cols = (free_of[dofs[sc.free_dofs][i]] for i in (H.row, H.col))
        import scipy.sparse as sp

        return e, g, sp.csr_matrix((H.data, (rows, cols)), shape=(c.n_free, c.n_free))

    whole = evaluate(system, np.arange(model.n_dofs))
    shares = []
    for rank in (0, 1):
        built = build_share(scene, None, _Share(parts, rank))
        verts = np.unique(model.T[parts[rank]])
        assert np.array_equal(built.model.X, model.X[verts])
        s = _Unsolved(built.model, built.constraints, "superlu", loads=built.loads)
        shares.append(evaluate(s, (3 * verts[:, None] + np.arange(3)).reshape(-1)))
    (e, g, H), (e0, g0, H0), (e1, g1, H1) = whole, *shares
    assert len(e) == len(e0) == 4  # inertia, elasticity, gravity, damping
    for k in range(len(e)):
        assert e0[k] + e1[k] == pytest.approx(e[k], rel=1e-12, abs=1e-12)
        assert np.allclose(g0[k] + g1[k], g[k], rtol=1e-12, atol=1e-9)
    assert abs(H0 + H1 - H).max() <= 1e-9 * abs(H).max()


def test_launched_ranks_from_the_launcher(monkeypatch):
    from fem3d.parallel.comm import RANK_VARIABLES, launched_rank, launched_ranks

    for name in (*RANK_VARIABLES, "OMPI_COMM_WORLD_RANK", "PMI_RANK", "PMIX_RANK",
                 "MPI_LOCALRANKID"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("SLURM_NTASKS", "8")  # a batch script without a launcher
    assert launched_ranks() == 1 and launched_rank() == 0
    monkeypatch.setenv("PMI_SIZE", "4")
    monkeypatch.setenv("PMI_RANK", "3")
    assert launched_ranks() == 4 and launched_rank() == 3


def test_build_restricted_to_a_share_never_builds_the_whole_model(tmp_path, monkeypatch):
    """``build_share`` (a rank's share): the model is built from the share's
    tets over their vertices alone (``build_model`` never sees the whole mesh) and equals
    the whole model restricted (rest shapes, the groups of two materials: their energies
    are checked by ``test_local_models_sum_to_the_whole``); pins,
    initial velocities and the loads are the share's (a per-tet damping coefficient
    restricted); the summary values are the share's ``summary``."""
    import fem3d.scene.build as scene_build
    from fem3d.scene.share import build_share

    scene = load_scene(str(write_scene(tmp_path)))  # two bodies: per-tet Rayleigh beta
    whole = scene_build.build(scene)
    tets = np.arange(0, whole.model.n_tets, 3)
    verts = np.unique(whole.model.T[tets])
    seen = []

    def spy(X, T, **kwargs):
        seen.append((X.shape[0], T.shape[0]))
        return build_model(X, T, **kwargs)

    build_model = scene_build.build_model
    monkeypatch.setattr(scene_build, "build_model", spy)
    rest = np.setdiff1d(np.arange(whole.model.n_tets), tets)
    share = build_share(scene, None, _Share([tets, rest], 0, lambda m: replace(
        m, E=whole.model.E, nu=whole.model.nu, rho=whole.model.rho)))
    assert seen == [(verts.size, tets.size)]  # the whole model is never built
    m = share.model
    assert m.n_tets == tets.size and m.n_vertices == verts.size
    assert np.array_equal(verts[m.T], whole.model.T[tets])
    assert np.array_equal(m.vol, whole.model.vol[tets])
    assert np.array_equal(m.dphi_dX, whole.model.dphi_dX[tets])
    assert [g.material for g in m.groups] == [g.material for g in whole.model.groups]
    assert np.array_equal(verts[share.constraints.fixed_vertices],
                          np.intersect1d(whole.constraints.fixed_vertices, verts))
    assert np.array_equal(share.arrays.v0, whole.arrays.v0[verts])
    assert np.array_equal(share.loads.rayleigh_beta, whole.loads.rayleigh_beta[tets])
    assert np.array_equal(share.loads.rayleigh_alpha, whole.loads.rayleigh_alpha[verts])
    assert (m.E, m.nu, m.rho) == (whole.model.E, whole.model.nu, whole.model.rho)


def test_rank_share_summary_is_the_whole_models(tmp_path):
    """``RankShare.summary``: the ranks' models of a two-material box (built by
    ``model_from_scene(share=)``, halves of unequal materials) get the whole model's
    ``E, nu, rho`` (the volume-weighted means over the ranks), the same on every rank."""
    from fem3d.parallel.run import RankShare
    from fem3d.scene.arrays import build_arrays
    from fem3d.scene.build import model_from_scene
    from fem3d.scene.local import LocalNumbering

    scene = load_scene(str(write_scene(tmp_path)))
    a = build_arrays(scene)
    whole = model_from_scene(scene, a)
    halves = np.array_split(np.arange(whole.n_tets), [whole.n_tets // 3])
    models = [model_from_scene(scene, a, share=LocalNumbering.of_tets(a.T, t)) for t in halves]
    assert models[0].E != models[1].E  # the halves' own summaries differ

    class Comm:  # rank r of two: allgather returns both ranks' rows
        def __init__(self, rows):
            self.rows = rows

        def allgather(self, row):
            return self.rows

    rows = [(m.E, m.nu, m.rho, m.total_volume) for m in models]
    for m in models:
        got = RankShare(Comm(rows)).summary(m)
        assert got.E == pytest.approx(whole.E, rel=1e-13)
        assert got.nu == pytest.approx(whole.nu, rel=1e-13)
        assert got.rho == pytest.approx(whole.rho, rel=1e-13)
        assert got.n_tets == m.n_tets


def _p2_bar(folder, bad_tet: int | None = None, steps: int = 1):
    """The box's first bar lifted to P2 (``bar_p2.vtu``), clamped at x = 0, sagging; with
    ``bad_tet``, that tet's edge node pushed far beyond its edge's far corner (det J < 0)."""
    import meshio

    from fem3d.mesh.quadratic import lift_to_p2

    mesh = meshio.read(MESH)
    X2, T2 = lift_to_p2(mesh.points, mesh.cells_dict["tetra"])
    if bad_tet is not None:
        tet = bad_tet % len(T2)
        X2[T2[tet, 4]] = X2[T2[tet, 0]] + 3.0 * (X2[T2[tet, 1]] - X2[T2[tet, 0]])
    folder.mkdir(parents=True, exist_ok=True)
    meshio.write(folder / "bar_p2.vtu", meshio.Mesh(X2, [("tetra10", T2)]))
    scene = folder / "bar.toml"
    scene.write_text(f"""
[simulation]
integrator = "implicit"
dt = 0.01
steps = {steps}
gravity = [0.0, -9.81, 0.0]

[[bodies]]
mesh = "{folder / 'bar_p2.vtu'}"
element = "p2"
material = {{ model = "neo_hookean", E = 2e5, nu = 0.35, density = 1000.0 }}
pins = [{{ select = {{ box = [[-1.0, -1.0, -1.0], [1e-6, 1.0, 1.0]] }} }}]
""")
    return scene


def test_p2_on_two_ranks_equals_one_process(two_rank_runs):
    """5 implicit steps of a P2 bar (edge nodes owned, numbered and written like corners) on
    2 ranks equal the one-process run to 1e-8 of the motion; the pieces hold the P2
    display surface (4 triangles per quadratic face)."""
    import meshio

    scene, proc = two_rank_runs["p2"]
    folder = scene.parent
    assert proc.returncode == 0, proc.stderr[-3000:]
    state = np.load(folder / "out" / "state.npz")
    sim = _one_process(scene, steps=5)
    diff = relative_difference(state["q"], sim.q, sim.model.X)
    print(f"P2 bar: 2 ranks vs one process: relative difference {diff:.2e}")
    assert int(state["step"]) == 5 and diff <= 1e-8
    pieces = sorted((folder / "out" / "frames").glob("frame_00005_*.vtu"))
    triangles = sum(len(meshio.read(p).cells_dict["triangle"]) for p in pieces)
    faces = sim.model.element.boundary_faces(sim.model.T)
    assert len(pieces) == 2 and triangles >= 4 * len(faces)  # plus the faces between ranks


@pytest.mark.parametrize("bad_tet", ["first", "last"])
def test_an_element_one_rank_refuses_is_one_line_on_every_rank(tmp_path, bad_tet):
    """A P2 element with a non-positive Jacobian is found by the rank that owns it alone (each
    rank checks only its own elements): every rank stops with exit status 2, no rank waits
    for the others, and one line names the element, whichever rank owns it (the first and
    the last tet of the bar lie in different ranks' parts)."""
    scene = _p2_bar(tmp_path, bad_tet=0 if bad_tet == "first" else -1)
    proc = run_mpi(2, "run", str(scene), "--out", str(tmp_path / "out"), cwd=tmp_path,
                   timeout=60)
    assert proc.returncode == 2, proc.stderr[-3000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Jacobian" in lines[0] and "bar_p2.vtu" in lines[0], proc.stderr


#: rank 1 fails alone when it writes its piece of frame 3 (a sitecustomize on PYTHONPATH)
_FAIL_ON_RANK_1 = """
import os

if os.environ.get("OMPI_COMM_WORLD_RANK", os.environ.get("PMI_RANK")) == "1":
    import fem3d.parallel.pieces as pieces
    write = pieces.PieceWriter.write
    def failing(self, step, t, q, fields=None):
        if step == 3:
            raise {error}
        write(self, step, t, q, fields)
    pieces.PieceWriter.write = failing
"""


@pytest.mark.parametrize("error, status, says", [
    ("PermissionError(13, 'Permission denied', 'frame_00003_1.vtu')", 2,
     "fem3d run: error: [Errno 13] Permission denied: 'frame_00003_1.vtu'"),
    ("RuntimeError('a bug on rank 1')", 1, "RuntimeError: a bug on rank 1"),
])
def test_an_error_on_one_rank_stops_every_rank(tmp_path, monkeypatch, error, status, says):
    """An OSError or an unexpected exception that one rank meets alone (here rank 1, writing
    its piece of frame 3) stops every rank (MPI_Abort) with the error said, instead of
    leaving rank 0 waiting in the next step's collective calls."""
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(_FAIL_ON_RANK_1.format(error=error))
    monkeypatch.setenv("PYTHONPATH", str(hook))
    scene = write_scene(tmp_path, steps=20)
    proc = run_mpi(2, "run", str(scene), "--out", str(tmp_path / "out"), cwd=tmp_path,
                   timeout=90)
    assert proc.returncode == status, proc.stderr[-3000:]
    assert says in proc.stderr
    assert not (tmp_path / "out" / "frames" / "frame_00005.pvtu").exists()
