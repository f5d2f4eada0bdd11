"""Contact scenes end to end: scene files with [contact] and obstacles, through Simulation and
the ``fem3d`` command line (exit status, the one-line message, the files written)."""

from __future__ import annotations

from pathlib import Path

import ipctk
import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.errors import InputError, ParameterError
from fem3d.io.checkpoint import CHECKPOINT_NAME, load_run_checkpoint
from fem3d.io.energy import read_energy_csv
from fem3d.mesh.tetmesh import boundary_faces
from fem3d.scene import apply_overrides, load_scene
from fem3d.simulation import Simulation
from tests.conftest_mesh_helpers import medit_text
from tests.physics.contact.test_potentials import box_mesh

ROOT = Path(__file__).resolve().parents[2]


def write_scene(tmp_path: Path, *, lower_y=0.004, upper_y=0.07, integrator="implicit",
                mu=0.2, obstacles_extra="") -> Path:
    """Two soft 10 cm blocks above a ground plane: the upper one falls onto the lower one."""
    X, T = box_mesh((2, 1, 2), size=(0.1, 0.05, 0.1))
    (tmp_path / "block.mesh").write_text(medit_text(X, T))
    text = f"""
[simulation]
integrator = "{integrator}"
dt = 0.01
steps = 12
gravity = [0.0, -9.81, 0.0]

[[bodies]]
name = "lower"
mesh = "block.mesh"
transform = {{ translate = [0.0, {lower_y}, 0.0] }}
material = {{ model = "neo_hookean", E = 2e5, nu = 0.3, density = 1000.0 }}

[[bodies]]
name = "upper"
mesh = "block.mesh"
transform = {{ translate = [0.03, {upper_y}, 0.02] }}
material = {{ model = "neo_hookean", E = 2e5, nu = 0.3, density = 1000.0 }}

[contact]
enabled = true
dhat = 1e-3
mu = {mu}

[[obstacles]]
plane = {{ point = [0.0, 0.0, 0.0], normal = [0.0, 1.0, 0.0] }}
{obstacles_extra}
"""
    path = tmp_path / "stack.toml"
    path.write_text(text)
    return path


def surfaces_intersect(sim: Simulation) -> bool:
    """Triangle-triangle intersections of the bodies' boundaries, by a fresh ipctk mesh."""
    F = boundary_faces(sim.model.T).astype(np.int32)
    X = np.asfortranarray(sim.model.X)
    cm = ipctk.CollisionMesh.build_from_full_mesh(X, ipctk.edges(F), F)
    return ipctk.has_intersections(cm, cm.vertices(np.asfortranarray(sim.q)))


def test_stack_scene_never_intersects_and_the_upper_block_lands(tmp_path):
    sim = Simulation(load_scene(str(write_scene(tmp_path))))
    assert sim.contact is not None and sim.fixed_vertices.size == 0
    upper = sim.assembled.body_vertices[1]
    y0 = sim.q[upper, 1].min()
    for _ in range(12):
        info = sim.step()
        assert sim.last_stats.converged
        assert sim.q[:, 1].min() > 0.0  # nothing below the ground
        assert not surfaces_intersect(sim)
    assert info.newton_iterations >= 1
    assert sim.q[upper, 1].min() < y0 - 0.01  # it fell onto the lower block


@pytest.mark.parametrize("overrides", [
    {"simulation.newton.line_search": "parabolic", "contact.newton_start": "clamped"},
    {"contact.newton_start": "q_t"},
    {"simulation.newton.line_search": "parabolic", "contact.newton_start": "q_t"},
    {"contact.newton_start": "q_t", "contact.hessian_projection": "exact",
     "simulation.newton.solver": "direct"},  # exact is refused with the scene's reuse
], ids=["parabolic", "q_t", "both", "q_t_exact_hessian"])
def test_stack_with_the_opt_in_newton_settings_stays_valid(overrides):
    """The gallery stack with the opt-in Newton settings (issue 21: the parabolic line
    search, the start at ``q_t`` when CCD cuts the free flight) through the bunny's landing
    on the bottom block (step 10) and the top block's on the bunny (18): every step
    converges, no surfaces intersect (a fresh ipctk mesh), nothing goes below the ground,
    and the line search took halvings (so the refinement had work to do; the exact contact
    Hessian, ``contact.hessian_projection = "exact"``, too: its full steps were all accepted
    only while shifted steps could pass IPC's rule,
    tests/physics/contact/test_hessian_projection.py)."""
    sim = Simulation(apply_overrides(load_scene("contact_stack"), overrides))
    assert sim.newton.line_search == overrides.get("simulation.newton.line_search",
                                                   "backtrack")
    assert sim.contact.newton_policy.restart_when_clamped == (
        overrides.get("contact.newton_start") == "q_t")
    halvings = 0
    for _ in range(22):
        sim.step()
        assert sim.last_stats.converged
        halvings += sim.last_stats.line_search_halvings
        assert sim.q[:, 1].min() > 0.0
        assert not surfaces_intersect(sim)
    assert halvings > 0


def test_newton_start_q_t_starts_an_impact_step_at_the_start_positions(monkeypatch):
    """With ``contact.newton_start = "q_t"`` a step whose free flight CCD cuts starts Newton
    at ``v = 0`` (``q_t``); one whose free flight is clear still starts at ``v_t``; the
    default starts at ``v_t`` scaled back by CCD."""
    import fem3d.solve.minimise as be

    starts = []
    real = be.newtons_method

    def spy(x0, *args, **kwargs):
        starts.append(np.array(x0))
        return real(x0, *args, **kwargs)

    monkeypatch.setattr(be, "newtons_method", spy)
    kinds = {}
    for start in ("clamped", "q_t"):
        sim = Simulation(apply_overrides(load_scene("contact_stack"),
                                         {"contact.newton_start": start}))
        free = sim.constraints.free_dofs
        kinds[start] = []
        for _ in range(12):  # the bunny lands on the bottom block at step 10
            v_t = sim.v.reshape(-1)[free].copy()
            starts.clear()
            sim.step()
            x0 = starts[0]
            kinds[start].append("v_t" if np.array_equal(x0, v_t) else
                                "q_t" if v_t.any() and not x0.any() else "clamped")
    assert "q_t" in kinds["q_t"] and "v_t" in kinds["q_t"]
    assert "clamped" not in kinds["q_t"]
    assert "q_t" not in kinds["clamped"] and "clamped" in kinds["clamped"]


def test_first_step_accept_ends_a_resting_step_after_one_factorization(tmp_path):
    """``contact.first_step = "accept"``: once the blocks rest on the ground and on each
    other, a step's first Newton direction already passes IPC's rule; it is taken and ends
    the step (one factorization) where ``"confirm"`` factorizes again to judge a second
    direction (two). Until then both runs are the same to the bit, and where they differ the
    states stay within the rule's tolerance of each other."""
    base = load_scene(str(write_scene(tmp_path, upper_y=0.056)))
    runs = {}
    for first_step in ("confirm", "accept"):
        sim = Simulation(apply_overrides(base, {"contact.first_step": first_step,
                                                "simulation.steps": 40}))
        factorizations, states = [], []
        for _ in range(40):
            sim.step()
            assert sim.last_stats.converged
            factorizations.append(sim.last_stats.factorizations)
            states.append(sim.q.copy())
        assert not surfaces_intersect(sim) and sim.q[:, 1].min() > 0.0
        runs[first_step] = np.array(factorizations), states
    (f_confirm, q_confirm), (f_accept, q_accept) = runs["confirm"], runs["accept"]
    same = next(k for k in range(40) if f_accept[k] != f_confirm[k])
    assert same > 0 and all(np.array_equal(q_accept[k], q_confirm[k]) for k in range(same))
    assert (f_confirm[-10:] == 2).all() and (f_accept[-10:] == 1).all()
    # the rule's tolerance: 1e-2 of the scene's diagonal per second, over one dt
    diagonal = float(np.linalg.norm(np.ptp(sim.model.X, axis=0)))
    assert np.abs(q_accept[-1] - q_confirm[-1]).max() < 1e-2 * diagonal * 0.01


def test_cli_runs_a_contact_scene_and_writes_every_body(tmp_path, capsys):
    scene = write_scene(tmp_path)
    out = tmp_path / "run"
    status = main(["run", str(scene), "--steps", "6", "--frame-every", "3", "--out", str(out),
                   "--quiet", "--no-preview"])
    assert status == 0, capsys.readouterr().err
    import meshio

    frames = sorted((out / "frames").glob("*.vtu"))
    assert len(frames) == 3
    m = meshio.read(frames[-1])
    X, T = box_mesh((2, 1, 2), size=(0.1, 0.05, 0.1))
    # both blocks' boundaries are in the frame
    assert m.points.shape[0] == 2 * np.unique(boundary_faces(T)).size or \
        m.points.shape[0] == 2 * X.shape[0]
    assert len(read_energy_csv(out / "energy.csv")["t"]) == 7


def test_linearly_implicit_euler_refuses_contact_scenes(tmp_path, capsys):
    scene = write_scene(tmp_path)
    status = main(["run", str(scene), "--integrator", "linear", "--out", str(tmp_path / "x"),
                   "--quiet", "--no-preview"])
    err = capsys.readouterr().err.strip()
    assert status == 2
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert "simulation.integrator" in err and "contact needs backward Euler" in err
    # and the viewer's integrator switch says the same
    sim = Simulation(load_scene(str(scene)))
    with pytest.raises(ParameterError, match="contact needs backward Euler"):
        sim.integrator = "linear"
    assert sim.integrator == "implicit"


def test_intersecting_bodies_at_the_start_are_named(tmp_path, capsys):
    scene = write_scene(tmp_path, upper_y=0.03)  # the upper block overlaps the lower one
    with pytest.raises(InputError, match=r"bodies\[0\] \(lower\) and bodies\[1\] \(upper\)"):
        Simulation(load_scene(str(scene)))
    status = main(["run", str(scene), "--out", str(tmp_path / "x"), "--quiet",
                   "--no-preview"])
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1
    assert "stack.toml" in err and "intersect" in err
    below = write_scene(tmp_path, lower_y=-0.01)  # the lower block pokes through the ground
    with pytest.raises(InputError, match=r"bodies\[0\] \(lower\) and obstacles\[0\]"):
        Simulation(load_scene(str(below)))


def test_obstacles_without_contact_are_refused(tmp_path):
    scene = write_scene(tmp_path)
    text = scene.read_text().replace("enabled = true", "enabled = false")
    scene.write_text(text)
    with pytest.raises(InputError, match="obstacles act through contact"):
        Simulation(load_scene(str(scene)))


@pytest.mark.parametrize("settings", [[], ["simulation.newton.line_search=parabolic",
                                             "contact.newton_start=q_t"]],
                         ids=["default", "issue21-opt-in"])
def test_contact_checkpoint_resume_is_bit_exact(tmp_path, capsys, settings):
    """Split while the blocks are in contact (the solver pattern has grown by the contact
    pairs and the barrier stiffness has adapted): the resumed run equals the straight one."""
    scene = write_scene(tmp_path)
    common = ["--quiet", "--no-preview", "--frame-every", "3"]
    for item in settings:
        common += ["--set", item]
    a, b = tmp_path / "straight", tmp_path / "resumed"
    assert main(["run", str(scene), "--steps", "12", "--checkpoint-every", "12", "--out",
                 str(a), *common]) == 0
    assert main(["run", str(scene), "--steps", "8", "--checkpoint-every", "8", "--out",
                 str(b), *common]) == 0
    mid = load_run_checkpoint(b / CHECKPOINT_NAME)
    assert mid.snapshot["pattern_keys"].size > 0  # contact pairs had widened the pattern
    assert mid.snapshot["contact"].shape == (5,)
    assert main(["resume", str(b), "--steps", "12", "--quiet"]) == 0
    ca, cb = load_run_checkpoint(a / CHECKPOINT_NAME), load_run_checkpoint(b / CHECKPOINT_NAME)
    for key in ("q", "v", "contact", "pattern_keys"):
        assert np.array_equal(ca.snapshot[key], cb.snapshot[key]), key
    assert (a / "energy.csv").read_bytes() == (b / "energy.csv").read_bytes()
    for name in sorted(p.name for p in (a / "frames").iterdir()):
        assert (a / "frames" / name).read_bytes() == (b / "frames" / name).read_bytes(), name


@pytest.mark.parametrize("name", sorted(p.stem for p in (ROOT / "data" / "scenes").glob(
    "contact_*.toml")))
def test_gallery_contact_scenes_load_and_step(name):
    sim = Simulation(load_scene(name))
    assert sim.contact is not None
    for _ in range(2):
        sim.step()
    gaps = sim.contact.contact.plane_gaps(sim.q)
    assert (gaps > 0).all()
    assert not sim.contact.contact.has_intersections(sim.q.reshape(-1))


#: Each gallery contact scene run until its bodies touch, measured on full runs (frames of
#: the 2026-12 code): the bunny lands at step 25 of 150, the stack's top block on the bunny
#: at step 18 (the bunny on the bottom block at 10), the bar coils onto itself at step 235
#: of 300, the incline's block touches from the start. None: the whole duration (cheap
#: enough, and the bunny must come to rest). (name, steps, kind of contact, comes to rest)
GALLERY_RUNS = [
    ("contact_bunny_drop", None, "plane", True),
    ("contact_incline", None, "plane", False),
    ("contact_stack", 22, "bodies", False),
    ("contact_twisted_bar", 250, "self", False),
]
NEAR = 3e-3  # m: "in contact" (the scenes' barrier widths are below 1 mm)


def _ipc_mesh(V: np.ndarray, F: np.ndarray) -> ipctk.CollisionMesh:
    V = np.asfortranarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int32)
    return ipctk.CollisionMesh(V, ipctk.edges(F), F)


def _near_pairs(V: np.ndarray, F: np.ndarray, between_bodies: bool) -> int:
    """Surface primitive pairs (not sharing a vertex) closer than :data:`NEAR`, by ipctk;
    with ``between_bodies`` only pairs of the last body (the one that falls last, whose
    vertices come last) and another (bodies: connected components)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    F = np.asarray(F, dtype=np.int32)
    cm = _ipc_mesh(V, F)
    c = ipctk.NormalCollisions()
    c.build(cm, np.asfortranarray(V, dtype=np.float64), NEAR)
    if not between_bodies:
        return len(c)
    ii = np.concatenate([F[:, 0], F[:, 1]])
    jj = np.concatenate([F[:, 1], F[:, 2]])
    _n, body = connected_components(coo_matrix((np.ones(ii.size), (ii, jj)),
                                               shape=(len(V), len(V))), directed=False)
    pairs = [*c.ee_collisions, *c.fv_collisions, *c.ev_collisions, *c.vv_collisions]
    last = body[len(V) - 1]
    labels = [{body[i] for i in p.vertex_ids(cm.edges, cm.faces) if i >= 0} for p in pairs]
    return sum(len(b) > 1 and last in b for b in labels)


def _states(scene, out: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """(vertices, triangles) of the simulation surface to check, read back from the run.

    The frames are the display meshes: with a skin they are not the simulation surface, so
    such a scene is checked on its final state (the checkpoint) over the model's boundary."""
    import meshio

    if any(b.skin for b in scene.bodies):
        ck = load_run_checkpoint(out / CHECKPOINT_NAME)
        T = Simulation(scene).model.T
        return [(np.asarray(ck.snapshot["q"]).reshape(-1, 3), boundary_faces(T))]
    frames = sorted((out / "frames").glob("*.vtu"))
    assert frames
    return [(m.points, m.cells_dict["triangle"]) for m in map(meshio.read, frames)]


@pytest.mark.slow
@pytest.mark.parametrize(("name", "steps", "contact", "rests"), GALLERY_RUNS)
def test_gallery_contact_scenes_make_contact_without_intersecting(tmp_path, capsys, name,
                                                                    steps, contact, rests):
    """Each contact scene run until its bodies touch; the written states checked by an
    ipctk collision mesh of their own (not the model's contact code): no intersection, no
    vertex behind a plane, the contact the scene is about made, resting bodies at rest."""
    scene = load_scene(name)
    n = steps or round(scene.simulation.duration / scene.simulation.dt)
    out = tmp_path / "run"
    args = ["run", name, "--out", str(out), "--quiet", "--no-preview",
            "--checkpoint-every", str(n)]
    if steps is not None:
        args += ["--set", f"simulation.steps={steps}"]
    assert main(args) == 0, capsys.readouterr().err
    states = _states(scene, out)
    planes = [(np.asarray(o.plane.point), np.asarray(o.plane.normal) / np.linalg.norm(
        o.plane.normal)) for o in scene.obstacles if o.plane is not None]
    near = []
    for k, (V, F) in enumerate(states):
        assert not ipctk.has_intersections(_ipc_mesh(V, F), np.asfortranarray(V, float)), (
            f"{name}: surfaces intersect in state {k}")
        gap = min((float(((V - p) @ nrm).min()) for p, nrm in planes), default=np.inf)
        assert gap > 0, f"{name}: a vertex is {-gap:.3g} m behind a plane in state {k}"
        near.append((gap, _near_pairs(V, F, contact == "bodies")))
    if contact == "plane":
        assert min(g for g, _ in near) < NEAR, f"{name}: never touched its plane"
    else:
        assert max(c for _, c in near) > 0, f"{name}: the bodies never touched ({contact})"
    kinetic = np.asarray(read_energy_csv(out / "energy.csv")["kinetic"])
    assert len(kinetic) == n + 1
    if rests:
        assert kinetic[-1] < 1e-6 * kinetic.max(), (  # issue 21: "at rest"
            f"{name}: not at rest at the end (kinetic {kinetic[-1]:.3g} J, peak "
            f"{kinetic.max():.3g} J)")


def test_keyframed_mesh_obstacle_lifts_a_block_without_intersecting(tmp_path):
    """A mesh obstacle (an OBJ floor, keyframed upward) pushes a block resting on it.

    Slowly (0.1 mm per step, below the gap): a kinematic obstacle's motion over a step is
    checked by CCD with the bodies held where they are, so it may not advance by more than
    its gap to them in one step (docs/contact.md, limits)."""
    from tests.conftest_mesh_helpers import obj_text

    X, T = box_mesh((2, 1, 2), size=(0.1, 0.05, 0.1))
    (tmp_path / "block.mesh").write_text(medit_text(X, T))
    V = np.array([[-0.2, 0.0, -0.2], [0.3, 0.0, -0.2], [0.3, 0.0, 0.3], [-0.2, 0.0, 0.3]])
    (tmp_path / "floor.obj").write_text(obj_text(V, np.array([[0, 2, 1], [0, 3, 2]])))
    (tmp_path / "lift.toml").write_text("""
[simulation]
integrator = "implicit"
dt = 0.01
steps = 10

[[bodies]]
mesh = "block.mesh"
transform = { translate = [0.0, 0.0002, 0.0] }
material = { model = "neo_hookean", E = 2e5, nu = 0.3, density = 1000.0 }

[contact]
enabled = true

[[obstacles]]
mesh = { path = "floor.obj", motion = { keyframes = [
    { t = 0.0, translate = [0.0, 0.0, 0.0] }, { t = 0.1, translate = [0.0, 0.001, 0.0] }] } }
""")
    sim = Simulation(load_scene(str(tmp_path / "lift.toml")))
    assert len(sim.obstacles()) == 1
    for _ in range(10):
        sim.step()
        name, Vt, F = sim.obstacles()[0]
        floor_y = Vt[:, 1].max()
        assert sim.q[:, 1].min() > floor_y  # never below the (moving) floor
        assert not sim.contact.contact.has_intersections(sim.q.reshape(-1))
    assert floor_y == pytest.approx(0.001)
    assert sim.q[:, 1].min() > 0.001  # carried up with it (it started 0.0002 above y = 0)
