"""Bodies of different elements in one scene (issue 41: ``element`` per body): a P1 and a P2
body run side by side, each as it runs alone; with contact between them every step is
intersection-free; resume is bit for bit; the volume frames hold ``tetra`` and ``tetra10``
cells; what is not built for mixed scenes (mpiexec runs, the adjoint) is refused in one line
naming ``bodies[i].element``, and a mixed model's ``T``/``element`` raise when used as one."""

from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.errors import InputError
from fem3d.mesh.element import ELEMENTS, MixedElementError
from fem3d.mesh.formats import write_tet_mesh
from fem3d.mesh.tetmesh import TetMesh, box_tet_mesh
from fem3d.physics.stress import element_stress
from fem3d.scene import load_scene
from fem3d.simulation import Simulation

ROOT = Path(__file__).resolve().parents[2]
P1, P2 = ELEMENTS["p1"], ELEMENTS["p2"]
CLAMP = 'pins = [{ select = { box = [[-1.0, -1.0, -1.0], [1e-6, 1.0, 1.0]] } }]'

#: three bars side by side (P1, P2, P1: three element blocks), each with its own material,
#: damping and pins; the P2 bar pulled by a scripted pull and loaded by a traction on its
#: end face (6-node faces), the last P1 bar's clamp keyframed
BODIES = [
    f'''mesh = "MESH"
material = {{ model = "stvk", E = 1e6, nu = 0.3, density = 1000.0 }}
damping = {{ rayleigh_mass = 1.0, rayleigh_stiffness = 0.002 }}
{CLAMP}
''',
    f'''mesh = "MESH"
element = "p2"
transform = {{ translate = [0.0, 0.0, 0.5] }}
material = {{ model = "neo_hookean", E = 2e6, nu = 0.35, density = 1200.0, regions = [
    {{ select = {{ box = [[0.49, -1.0, -1.0], [2.0, 1.0, 1.0]] }}, E = 4e6 }}] }}
damping = {{ rayleigh_mass = 0.5, rayleigh_stiffness = 0.001 }}
{CLAMP}

[[bodies.loads]]
select = {{ box = [[0.999, -1.0, -1.0], [2.0, 1.0, 2.0]] }}
traction = [0.0, 0.0, 300.0]
''',
    '''mesh = "MESH"
transform = { translate = [0.0, 0.0, 1.0] }
material = { model = "neo_hookean", E = 5e5, nu = 0.3, density = 800.0 }
pins = [{ select = { box = [[-1.0, -1.0, -1.0], [1e-6, 1.0, 2.0]] }, motion = { keyframes = [
    { t = 0.0, translate = [0.0, 0.0, 0.0] }, { t = 0.1, translate = [0.0, 0.02, 0.0] }] } }]
''',
]
PULL = '''[[pulls]]
body = {body}
select = {{ sphere = {{ center = [1.0, 0.1, 0.6], radius = 0.06 }} }}
offset = [0.0, 0.05, 0.0]
start = 0.02
duration = 0.04
stiffness = 200.0
'''


@pytest.fixture(scope="module")
def bar(tmp_path_factory) -> Path:
    """A 1 x 0.1 x 0.1 bar of 4 x 1 x 1 cells (24 tets, 20 vertices)."""
    path = tmp_path_factory.mktemp("mesh") / "bar.mesh"
    write_tet_mesh(path, TetMesh(*box_tet_mesh((4, 1, 1), (1.0, 0.1, 0.1))))
    return path


def _scene(tmp_path: Path, name: str, bar: Path, bodies: list[int], integrator: str,
           steps: int = 4, extra: str = "") -> Path:
    text = (f'[simulation]\nintegrator = "{integrator}"\ndt = 0.02\nsteps = {steps}\n'
            'gravity = [0.0, -9.81, 0.0]\n')
    for i in bodies:
        text += "\n[[bodies]]\n" + BODIES[i].replace("MESH", str(bar))
    if 1 in bodies:
        text += "\n" + PULL.format(body=bodies.index(1))
    path = tmp_path / f"{name}.toml"
    path.write_text(text + extra)
    return path


def _run(path: Path, steps: int = 4, backend: str | None = None) -> Simulation:
    sim = Simulation(load_scene(str(path)), backend=backend)
    for _ in range(steps):
        sim.step()
        assert sim.last_stats.converged
    return sim


@pytest.mark.parametrize("integrator,backend", [
    ("implicit", None), ("bdf2", None), ("newmark", None), ("linear", None), ("static", None),
    ("implicit", "numpy")])
def test_each_body_moves_as_it_does_alone(integrator, backend, bar, tmp_path):
    """P1, P2 and P1 bars in one scene (three element blocks: materials with a region,
    per-body damping, a pull and a traction on the P2 bar, a keyframed clamp) end where each
    ends alone."""
    mixed = _run(_scene(tmp_path, "mixed", bar, [0, 1, 2], integrator), backend=backend)
    model = mixed.model
    assert model.is_mixed and model.element_names == "p1+p2"
    assert backend is None or model.kernel_backend == backend
    assert [b.element for _, b in model.element_blocks()] == [P1, P2, P1]
    assert [(s.start, s.stop) for s in model.spans] == [(0, 24), (24, 48), (48, 72)]
    assert model.n_tets == 72 and model.n_vertices == 20 + 81 + 20
    for i, vs in enumerate(mixed.assembled.body_vertices):
        alone = _run(_scene(tmp_path, f"alone{i}", bar, [i], integrator), backend=backend)
        moved = np.abs(alone.q - alone.model.X).max()
        assert moved > 1e-3  # it moved (sagged, was pulled or lifted)
        gap = np.abs(mixed.q[vs] - alone.q).max()
        # to round-off (measured: at most 2.1e-15 m of 4-59 cm; the P1 bars often bit for
        # bit); one Newton loop for all bodies could stop an iteration apart from a body's own
        assert gap <= 1e-11 * moved, (i, gap, moved)
        assert np.abs(mixed.v[vs] - alone.v).max() <= 1e-10 * max(np.abs(alone.v).max(), 1.0)


def _contact_scene(tmp_path: Path) -> Path:
    """tests/physics/test_p2.py's stack of two P2 blocks with the upper block made P1."""
    from tests.physics.test_p2 import _p2_stack

    path = _p2_stack(tmp_path)
    bottom, top = path.read_text().split('name = "top"')
    path.write_text(bottom + 'name = "top"' + top.replace('element = "p2"\n', "", 1))
    return path


def test_a_p1_block_dropped_on_a_p2_block_stays_intersection_free(tmp_path):
    """IPC's collision mesh is each body's own surface (the P2 block's faces split through
    their edge nodes, the P1 block's faces as they are); every step converges, no triangle
    pair intersects (a fresh ipctk mesh of the surfaces) and nothing goes below the ground;
    the P1 block lands on the P2 block."""
    import ipctk

    sim = Simulation(load_scene(str(_contact_scene(tmp_path))))
    a = sim.assembled
    p2, p1 = a.blocks
    F = np.concatenate([P2.surface_triangles(p2.T), P1.surface_triangles(p1.T)])
    assert np.array_equal(sim.surface_faces, F)
    g = sim.contact.contact.geometry
    assert np.array_equal(g.surface[g.faces[:F.shape[0]]], F)
    assert np.isin(p2.T[:, 4:], g.surface).any()  # the P2 block's edge nodes collide
    cm = ipctk.CollisionMesh.build_from_full_mesh(np.asfortranarray(sim.model.X),
                                                  ipctk.edges(F.astype(np.int32)),
                                                  F.astype(np.int32))
    top, bottom = a.body_vertices[1], a.body_vertices[0]
    y0 = sim.q[top, 1].min()
    for _ in range(22):  # lands by step 8, at rest from step 17
        sim.step()
        assert sim.last_stats.converged
        assert sim.q[:, 1].min() > 0.0
        assert not ipctk.has_intersections(cm, cm.vertices(np.asfortranarray(sim.q)))
    assert sim.q[top, 1].min() < y0 - 0.02  # fell 2.8 cm
    assert abs(sim.q[top, 1].min() - sim.q[bottom, 1].max()) < 3e-3  # and rests on it


def test_resume_and_volume_frames_of_a_mixed_scene(bar, tmp_path):
    """A mixed run interrupted at step 2 and resumed to 4 ends bit for bit where the
    uninterrupted run does, its volume frames byte for byte; meshio reads each frame back as
    a ``tetra`` block (the P1 bars) and a ``tetra10`` block (the P2 bar), the nodes at the
    run's positions and the stress cell data the model's."""
    scene = _scene(tmp_path, "mixed", bar, [0, 1], "implicit",
                   extra='\n[output]\nvolume = true\n')
    common = ["--quiet", "--no-preview"]
    assert main(["run", str(scene), "--steps", "4", "--checkpoint-every", "4",
                 "--out", str(tmp_path / "a"), *common]) == 0
    assert main(["run", str(scene), "--steps", "2", "--checkpoint-every", "2",
                 "--out", str(tmp_path / "b"), *common]) == 0
    assert main(["resume", str(tmp_path / "b"), "--steps", "4", *common]) == 0
    a, b = np.load(tmp_path / "a" / "checkpoint.npz"), np.load(tmp_path / "b" / "checkpoint.npz")
    assert np.array_equal(a["state_q"], b["state_q"]) and np.array_equal(a["state_v"], b["state_v"])
    names = sorted(f.name for f in (tmp_path / "a" / "volume").iterdir())
    assert len(names) == 5
    for name in names:
        assert (tmp_path / "a" / "volume" / name).read_bytes() == \
            (tmp_path / "b" / "volume" / name).read_bytes()
    energy = [(tmp_path / d / "energy.csv").read_bytes() for d in "ab"]
    assert energy[0] == energy[1]

    sim = Simulation(load_scene(str(scene)), scripted=True)
    for _ in range(4):
        sim.step()
    mesh = meshio.read(tmp_path / "a" / "volume" / names[-1])
    blocks = [b for _, b in sim.model.element_blocks()]
    assert [(c.type, c.data.shape) for c in mesh.cells] == [("tetra", (24, 4)),
                                                            ("tetra10", (24, 10))]
    for cells, block in zip(mesh.cells, blocks, strict=True):
        assert np.array_equal(cells.data, block.T)
    assert np.array_equal(mesh.points, sim.q.reshape(-1, 3))
    stress = element_stress(sim.model, sim.q)
    np.testing.assert_array_equal(np.concatenate(mesh.cell_data["von_mises"]), stress.von_mises)
    assert np.isfinite(mesh.point_data["von_mises"]).all()


@pytest.mark.parametrize("fmt", ["obj", "vtu"])
def test_frames_and_preview_of_a_mixed_scene(fmt, bar, tmp_path):
    """The frames are both bodies' display surfaces (the P2 bar's faces as 4 triangles
    through its edge nodes), at the run's positions; the preview is written."""
    scene = _scene(tmp_path, "mixed", bar, [0, 1], "implicit", steps=2)
    out = tmp_path / "o"
    assert main(["run", str(scene), "--format", fmt, "--out", str(out), "--quiet"]) == 0
    assert (out / "preview.gif").is_file()
    frame = meshio.read(sorted((out / "frames").glob(f"*.{fmt}"))[-1])
    sim = Simulation(load_scene(str(scene)), scripted=True)  # as fem3d run: the pull acts
    sim.step()
    sim.step()
    a = sim.assembled
    faces = np.concatenate([frame.cells_dict["triangle"]])
    assert faces.shape[0] == P1.surface_triangles(a.blocks[0].T).shape[0] + \
        P2.surface_triangles(a.blocks[1].T).shape[0]
    np.testing.assert_allclose(frame.points[faces], sim.q.reshape(-1, 3)[sim.surface_faces],
                               rtol=0, atol=1e-6 if fmt == "obj" else 0)


def test_a_mixed_model_refuses_use_as_one_element(bar, tmp_path):
    """The mixed model's and scene arrays' ``T``, ``element``, ``dphi_dX``, ``mat`` raise
    a MixedElementError naming the attribute (no silent use of one block's), while a
    one-element model is its own single block."""
    sim = Simulation(load_scene(str(_scene(tmp_path, "mixed", bar, [0, 1], "implicit"))))
    for use in (lambda: sim.model.T.shape, lambda: np.asarray(sim.model.T),
                lambda: sim.model.element.n_nodes, lambda: sim.model.dphi_dX[0],
                lambda: sim.model.mat.energy, lambda: sim.model.elem_dofs,
                lambda: sim.assembled.T[0], lambda: len(sim.assembled.element)):
        with pytest.raises(MixedElementError, match=r"the bodies mix elements \(p1, p2\)"):
            use()
    single = Simulation(load_scene(str(_scene(tmp_path, "single", bar, [1], "implicit"))))
    ((span, block),) = single.model.element_blocks()
    assert block is single.model and span == slice(0, 24) and not single.model.is_mixed
    assert single.model.element is P2 and single.assembled.blocks[0].T is single.assembled.T


def test_what_mixed_scenes_do_not_run_is_refused_in_one_line(bar, tmp_path):
    """mpiexec runs and the adjoint (trajectory_gradient, fem3d fit) refuse a scene whose
    bodies mix elements, naming the first body whose element differs."""
    from fem3d.diff.adjoint import PositionLoss, trajectory_gradient
    from fem3d.parallel.run import check_distributable

    scene = load_scene(str(_scene(tmp_path, "mixed", bar, [0, 1], "implicit",
                                  extra="")), {"pulls": []})
    with pytest.raises(InputError, match=r"bodies\[1\]\.element: 'p2' beside bodies\[0\]'s "
                                         r"'p1': mpiexec -n 2 runs need every body on one "
                                         r"element") as info:
        check_distributable(scene, 2)
    assert "\n" not in str(info.value)
    loss = PositionLoss(targets={2: np.zeros((103, 3))})
    with pytest.raises(InputError, match=r"bodies\[1\]\.element: .*the adjoint"):
        trajectory_gradient(scene, loss, ["bodies[0].material.E"])


def test_fem3d_fit_refuses_a_mixed_scene_in_one_line(bar, tmp_path, capsys):
    """``fem3d fit`` of a mixed scene: exit 2, one line naming ``bodies[1].element``, before
    reading any target."""
    scene = _scene(tmp_path, "mixed", bar, [0, 1], "implicit", extra="")
    scene.write_text(scene.read_text().split("[[pulls]]")[0])
    (tmp_path / "target").mkdir()  # no frames in it: the refusal comes first
    fit = tmp_path / "fit.toml"
    fit.write_text(f'scene = "{scene}"\ntarget = "{tmp_path / "target"}"\n\n[[params]]\n'
                   'key = "bodies[0].material.E"\nstart = 2e6\nbounds = [1e5, 1e9]\n')
    assert main(["fit", str(fit), "--out", str(tmp_path / "fit_out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert "bodies[1].element: 'p2' beside bodies[0]'s 'p1': fem3d fit (the adjoint) need " \
        "every body on one element" in err


def test_a_sweep_over_the_second_bodys_element(bar, tmp_path):
    """``fem3d sweep`` runs mixed cases: a grid over ``bodies[1].element`` (P1 + P1, P1 + P2),
    each case's frames bit for bit what ``fem3d run`` gives."""
    from fem3d.io.dataset import read_run_frames
    from tests.app.test_sweep_runs import _main

    scene = _scene(tmp_path, "pair", bar, [0, 1], "implicit", steps=2)
    scene.write_text(scene.read_text().split("[[pulls]]")[0])
    spec = tmp_path / "s.toml"
    spec.write_text('scene = "pair.toml"\n[grid]\n"bodies[1].element" = ["p1", "p2"]\n'
                    '[dataset]\ndtype = "float64"\n')
    out = tmp_path / "out"
    rc, err = _main("sweep", str(spec), "--workers", "1", "--out", str(out), "--quiet")
    assert rc == 0 and "2 ok, 0 failed, 0 lost" in err, err
    for case in sorted((out / "cases").iterdir()):
        element = "p2" if read_run_frames(case)[2].shape[1] == 20 + 81 else "p1"
        alone = tmp_path / f"alone_{element}"
        rc, err = _main("run", str(scene), "--set", f'bodies[1].element="{element}"',
                        "--out", str(alone), "--no-preview", "--quiet")
        assert rc == 0, err
        for a, b in zip(read_run_frames(case), read_run_frames(alone), strict=True):
            np.testing.assert_array_equal(a, b)
    assert sorted(p.name for p in tmp_path.glob("alone_*")) == ["alone_p1", "alone_p2"]


def test_the_mixed_models_matrices_are_the_bodies_own(bar, tmp_path):
    """The mixed model's pattern, mass, Hessian, gradient and energy are each body's own
    model's, block diagonal (the union pattern holds exactly the bodies' entries)."""
    from fem3d.physics.assembly import assemble_gradient, assemble_hessian, potential_energy

    mixed = Simulation(load_scene(str(_scene(tmp_path, "m", bar, [0, 1], "implicit")))).model
    alone = [Simulation(load_scene(str(_scene(tmp_path, f"a{i}", bar, [i], "implicit")))).model
             for i in (0, 1)]
    assert mixed.nnz == alone[0].nnz + alone[1].nnz
    q = mixed.X + 0.01 * np.random.default_rng(3).standard_normal(mixed.X.shape)
    n0 = 3 * alone[0].n_vertices
    parts = [q[:n0 // 3], q[n0 // 3:]]
    H, M = assemble_hessian(mixed, q).toarray(), mixed.mass.toarray()
    for (rows, A, Q) in ((slice(0, n0), alone[0], parts[0]), (slice(n0, None), alone[1], parts[1])):
        np.testing.assert_allclose(H[rows, rows], assemble_hessian(A, Q).toarray(),
                                   rtol=1e-13, atol=1e-9)
        np.testing.assert_array_equal(M[rows, rows], A.mass.toarray())
        np.testing.assert_allclose(assemble_gradient(mixed, q)[rows], assemble_gradient(A, Q),
                                   rtol=1e-13, atol=1e-12)
    assert not H[:n0, n0:].any() and not M[:n0, n0:].any()
    assert potential_energy(mixed, q) == pytest.approx(
        potential_energy(alone[0], parts[0]) + potential_energy(alone[1], parts[1]), rel=1e-14)
