"""Substeps of contact steps (fem3d.solve.substeps): a step whose own straight motion passes
through a surface is redone as 2, 4, ... substeps of dt/n.

Checked here: a substepped step equals two steps of dt/2 (up to the solver's round-off); a
step that needs no substeps is bit for bit the step without the check; the step counter and
time; pins at the substep times; a resume across a substepped step is bit-exact; the cap
fails with one line naming the setting; a pair pressed closer than Tight-Inclusion's default
tolerance catches is not a crossing, one pushed into or through the other is. The fast body
itself is ``tests/solve/test_contact_steps.py::test_a_fast_body_hits_a_free_body_...[20.0]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.errors import InputError, SimulationError
from fem3d.io.checkpoint import CHECKPOINT_NAME, load_run_checkpoint
from fem3d.physics.contact import ContactModel
from fem3d.physics.contact import path as contact_path
from fem3d.physics.terms.contact import ContactTerm
from fem3d.scene import apply_overrides, load_scene
from fem3d.simulation import Simulation
from fem3d.solve.integrators import State, implicit_euler
from fem3d.solve.substeps import check_max_substeps
from tests.conftest_mesh_helpers import medit_text
from tests.physics.contact.test_potentials import box_mesh
from tests.solve.test_contact_steps import DT, free_system, independent_intersections


def two_boxes(speed: float, gap: float = 0.03, mu: float = 0.0):
    """Box b (0.1 m) flies at ``speed`` toward box a, ``gap`` away, no gravity."""
    Xa, Ta = box_mesh((1, 1, 1), size=(0.1, 0.1, 0.1), origin=(0.0, 0.0, 0.0))
    Xb, Tb = box_mesh((1, 1, 1), size=(0.1, 0.1, 0.1), origin=(0.1 + gap, 0.02, 0.01))
    X, T = np.vstack([Xa, Xb]), np.vstack([Ta, Tb + len(Xa)])
    ids = np.r_[np.zeros(len(Xa), int), np.ones(len(Xb), int)]
    model, system = free_system(X, T, E=1e6, gravity=None)
    term = ContactTerm(ContactModel(X, T, body_ids=ids, dhat=1e-3, mu=mu), tolerance=1e-2)
    v = np.zeros_like(X)
    v[ids == 1, 0] = -speed
    return X, T, system, term, State(q=X.copy(), v=v)


def fail_first_check(term: ContactTerm) -> list:
    """Make the term's first straight-motion check fail (the rest as they are)."""
    calls, check = [], term.straight_path_is_free

    def first_fails(*args):
        calls.append(args)
        return len(calls) > 1 and check(*args)

    term.straight_path_is_free = first_fails
    return calls


def test_a_substepped_step_is_two_steps_of_half_dt():
    """At 1 m/s, sideways too, into the struck box (in contact within the step, friction
    lagged at each substep's start), a step whose check is made to fail is redone as two
    substeps: the same state as two steps of dt/2 from the same start (measured: bit for
    bit; the tolerance allows the solver's round-off), with the step's time and index."""
    X, T, system, term, state = two_boxes(1.0, gap=0.005, mu=0.5)
    state = State(q=state.q, v=state.v + [0.0, 0.0, 0.3])
    calls = fail_first_check(term)
    sub, stats = implicit_euler(system, state, DT, terms=[term], max_substeps=4)
    assert stats.substeps == 2 and stats.converged and len(calls) == 3
    assert sub.t == DT and sub.step == 1 and "q_prev" not in sub.history
    X, T, system, term, half = two_boxes(1.0, gap=0.005, mu=0.5)
    half = State(q=half.q, v=half.v + [0.0, 0.0, 0.3])
    for _ in range(2):
        half, _ = implicit_euler(system, half, DT / 2, terms=[term])
    assert term.contact.n_active(half.q.reshape(-1)) > 0  # the boxes touch
    assert term.contact.n_friction_pairs > 0  # and friction acts
    np.testing.assert_allclose(sub.q, half.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sub.v, half.v, rtol=0, atol=1e-10)
    assert not independent_intersections(X, T, sub.q)


def test_a_step_that_needs_no_substeps_is_bit_identical_to_the_step_without_the_check():
    *_, system, term, plain = two_boxes(5.0)
    *_, system2, term2, checked = two_boxes(5.0)
    for _ in range(4):
        plain, _ = implicit_euler(system, plain, DT, terms=[term])
        checked, stats = implicit_euler(system2, checked, DT, terms=[term2], max_substeps=8)
        assert stats.substeps == 1
        assert np.array_equal(plain.q, checked.q) and np.array_equal(plain.v, checked.v)


def test_the_cap_fails_with_one_line_naming_the_setting():
    *_, system, term, state = two_boxes(20.0)
    with pytest.raises(SimulationError, match=r"even in 2 substeps .*contact.max_substeps"):
        implicit_euler(system, state, DT, terms=[term], max_substeps=2)
    with pytest.raises(Exception, match="power of two"):
        check_max_substeps(3)


def write_scene(tmp_path: Path, *, max_substeps: int, integrator: str = "implicit",
                gap: float = 0.03) -> Path:
    """The two boxes of :func:`two_boxes` at 20 m/s as a scene file (``dhat`` 1 mm as
    there); with ``gap`` 0.23 m, b reaches a in the second step."""
    X, T = box_mesh((1, 1, 1), size=(0.1, 0.1, 0.1))
    (tmp_path / "box.mesh").write_text(medit_text(X, T))
    diagonal = float(np.linalg.norm([0.2 + gap, 0.12, 0.11]))  # the scene's, at rest
    text = f"""
[simulation]
integrator = "{integrator}"
dt = 0.01
steps = 4

[[bodies]]
name = "a"
mesh = "box.mesh"
material = {{ model = "neo_hookean", E = 1e6, nu = 0.3, density = 1000.0 }}

[[bodies]]
name = "b"
mesh = "box.mesh"
transform = {{ translate = [{0.1 + gap}, 0.02, 0.01] }}
velocity = [-20.0, 0.0, 0.0]
material = {{ model = "neo_hookean", E = 1e6, nu = 0.3, density = 1000.0 }}

[contact]
enabled = true
dhat = {1e-3 / diagonal!r}
tolerance = 1e-2
max_substeps = {max_substeps}
"""
    path = tmp_path / "fast.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("integrator", ["implicit", "bdf2", "newmark"])
def test_simulation_substeps_keep_the_bodies_apart_and_the_history_one_dt_back(
        tmp_path, integrator):
    sim = Simulation(load_scene(str(write_scene(tmp_path, max_substeps=8,
                                                integrator=integrator))))
    substeps = []
    for _ in range(4):
        start = sim.state
        sim.step()
        substeps.append(sim.last_stats.substeps)
        assert sim.step_index == start.step + 1 and sim.t == start.t + 0.01
        if "q_prev" in sim.state.history:  # BDF2: the history is the step's start
            assert sim.state.history["q_prev"] is start.q
            assert sim.state.history["v_prev"] is start.v
        b = sim.assembled.body_vertices[1]
        a = sim.assembled.body_vertices[0]
        assert sim.q[b, 0].mean() - sim.q[a, 0].mean() > 0.05  # b never gets past a
        assert not sim.contact.contact.has_intersections(sim.q.reshape(-1))
    assert max(substeps) > 1


def test_moving_pins_are_at_their_substep_positions(tmp_path):
    """A pinned box whose pin moves on a keyframed (smooth) path: with a forced substep the
    pins end the first substep where the keyframes put them at t + dt/2."""
    path = write_scene(tmp_path, max_substeps=2, gap=0.23)  # no contact in step 1
    text = path.read_text().replace(
        'name = "a"\n', 'name = "a"\npins = [ { select = { box = [[-1, -1, -1], [0.001, 1, 1]] }, '
        'motion = { keyframes = [ { t = 0.0, translate = [0.0, 0.0, 0.0] }, '
        '{ t = 0.04, translate = [0.0, 0.04, 0.0] } ], interpolation = "smooth" } } ]\n')
    path.write_text(text)
    sim = Simulation(load_scene(str(path)))
    seen = []
    check = sim.contact.straight_path_is_free

    def record(q0, q1, t0, t1):
        seen.append((t1, np.array(q1).reshape(-1, 3)[sim.fixed_vertices]))
        return len(seen) > 1 and check(q0, q1, t0, t1)

    sim.contact.straight_path_is_free = record
    sim.step()
    assert sim.last_stats.substeps == 2
    (t_full, _), (t_half, p_half), (t_end, p_end) = seen
    assert t_half == 0.005 and t_full == t_end == 0.01
    np.testing.assert_array_equal(p_half, sim.fixed_positions(0.005))
    np.testing.assert_array_equal(p_end, sim.fixed_positions(0.01))
    np.testing.assert_array_equal(sim.q[sim.fixed_vertices], sim.fixed_positions(0.01))


def test_resume_across_a_substepped_step_is_bit_exact(tmp_path):
    scene = write_scene(tmp_path, max_substeps=8, gap=0.23)
    common = ["--quiet", "--no-preview", "--frame-every", "1"]
    a, b = tmp_path / "straight", tmp_path / "resumed"
    assert main(["run", str(scene), "--steps", "4", "--checkpoint-every", "4", "--out",
                 str(a), *common]) == 0
    assert main(["run", str(scene), "--steps", "1", "--checkpoint-every", "1", "--out",
                 str(b), *common]) == 0
    assert main(["resume", str(b), "--steps", "4", "--quiet"]) == 0
    ca, cb = load_run_checkpoint(a / CHECKPOINT_NAME), load_run_checkpoint(b / CHECKPOINT_NAME)
    for key in ("q", "v", "contact", "pattern_keys"):
        assert np.array_equal(ca.snapshot[key], cb.snapshot[key]), key
    assert (a / "energy.csv").read_bytes() == (b / "energy.csv").read_bytes()
    # and the second step was substepped
    sim = Simulation(load_scene(str(scene)))
    sim.step()
    assert sim.last_stats.substeps == 1
    sim.step()
    assert sim.last_stats.substeps > 1


def test_a_scene_over_the_cap_fails_with_one_line(tmp_path, capsys):
    scene = write_scene(tmp_path, max_substeps=2)
    status = main(["run", str(scene), "--out", str(tmp_path / "x"), "--quiet",
                   "--no-preview"])
    err = capsys.readouterr().err
    assert status != 0
    assert "passes through a surface even in 2 substeps" in err
    assert "contact.max_substeps" in err
    with pytest.raises(InputError, match="max_substeps: must be a power of two"):
        apply_overrides(load_scene(str(scene)), {"contact.max_substeps": 6})


#: A rotation taking the boxes off the axes (Tight-Inclusion's boxes are axis-aligned: faces
#: along the axes make its test exact).
TILT = np.linalg.qr(np.array([[1.0, 0.3, -0.2], [0.1, 1.0, 0.4], [-0.3, 0.2, 1.0]]))[0]


def resting_boxes(gap: float):
    """Box b (0.1 m) resting ``gap`` above box a, offset sideways, both tilted by
    :data:`TILT`: a ContactModel with ``dhat`` 1 mm, the rest positions ``(n, 3)``, b's
    vertices, and ``move(d)``: the positions with b moved by ``d`` (in the boxes' frame)."""
    Xa, Ta = box_mesh((1, 1, 1), size=(0.1, 0.1, 0.1))
    Xb, Tb = box_mesh((1, 1, 1), size=(0.1, 0.1, 0.1), origin=(0.02, 0.1 + gap, 0.01))
    X, T = np.vstack([Xa, Xb]), np.vstack([Ta, Tb + len(Xa)])
    b = np.r_[np.zeros(len(Xa), bool), np.ones(len(Xb), bool)]

    def move(d):
        Y = X.copy()
        Y[b] += d
        return Y @ TILT.T

    return ContactModel(X @ TILT.T, T, body_ids=b.astype(int), dhat=1e-3), move


def test_a_resting_pair_closer_than_the_ccd_tolerance_is_not_a_crossing():
    """Box b settles from 20 um to 0.1 um above box a while sliding 5 mm: its straight
    motion comes closer than Tight-Inclusion's default tolerance (1e-6 m, which flags it)
    but never meets a; the check passes it. The same box pushed 1 mm into a, or moved
    through a to below it (ending intersection-free), is a crossing."""
    import ipctk

    contact, move = resting_boxes(2e-5)
    q0, q1 = move([0.0, 0.0, 0.0]), move([0.005, 1e-7 - 2e-5, 0.0])
    assert not contact.has_intersections(q1.reshape(-1))
    # the old check (Tight-Inclusion at its default tolerance alone) reports a hit
    part = contact.collisions.parts[0]
    V0, V1 = (np.asfortranarray(contact.collision_vertices(q)) for q in (q0, q1))
    cands = contact.collisions.candidates_along(part, V0, V1)
    assert not cands.is_step_collision_free(
        part.mesh, V0, V1, min_distance=0.0,
        narrow_phase_ccd=ipctk.TightInclusionCCD(1e-6, 10_000_000, 1.0))
    assert contact_path.straight_path_is_free(contact.collisions, q0, q1, 0.0, DT)
    pressed = move([0.005, -1e-3 - 2e-5, 0.0])
    assert not contact_path.straight_path_is_free(contact.collisions, q0, pressed, 0.0, DT)
    through = move([0.005, -0.2 - 2e-5 - 1e-3, 0.0])
    assert not contact.has_intersections(through.reshape(-1))
    assert not contact_path.straight_path_is_free(contact.collisions, q0, through, 0.0, DT)
