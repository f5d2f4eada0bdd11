"""Adjoint gradients through IPC contact and friction (fem3d.diff.contact): a box's landing
and slide against central finite differences, the exact pieces of one adjoint step, and
``fem3d fit`` through a contact landing."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.app.fit.run import scene_toml
from fem3d.app.run import run_scene
from fem3d.diff import PositionLoss, simulate, trajectory_gradient
from fem3d.diff.adjoint import _prepare, scene_with
from fem3d.errors import ParameterError, SimulationError
from fem3d.scene.load import scene_from_arrays
from fem3d.solve.state import State
from tests.physics.test_assembly import box_mesh

STEPS = 10
E_KEY = "bodies[0].material.E"
#: IPC's stiffness fixed (the adaptive one is held fixed per step: not differentiated); about
#: what the adaptive rule picks for this landing (6.2e10)
CONTACT = {"enabled": True, "dhat": 1e-3, "kappa": 5e10, "mu": 0.3}
GROUND = [{"plane": {"point": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0]}}]


def drop_scene(**overrides):
    """A 0.2 m box (2x2x2 cells, 48 tets, E = 1e4) 5 mm above the ground, thrown down at
    1 m/s and sideways at 0.5 m/s: it lands in its first step and slides, slowed by friction,
    for the rest (10 steps of 0.01 s)."""
    X, T = box_mesh(2, 2, 2, size=(0.2, 0.2, 0.2))
    X[:, 1] += 0.005
    values = {"pulls": [], "simulation.dt": 0.01, "simulation.gravity": [0.0, -9.81, 0.0],
              "bodies[0].pins": [], E_KEY: 1e4, "bodies[0].material.nu": 0.3,
              "bodies[0].material.density": 1000.0, "bodies[0].velocity": [0.5, -1.0, 0.0],
              "contact": CONTACT, "obstacles": GROUND}
    values.update(overrides)
    return scene_from_arrays(X, T, values)


def ground_mesh(folder: Path) -> str:
    """A 2 x 2 m square of two triangles at y = 0 (a mesh obstacle: ipctk's pairs)."""
    path = folder / "ground.obj"
    path.write_text("v -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nf 1 3 2\nf 1 4 3\n")
    return str(path)


#: the mesh ground's motion: 0.1 m against the box's slide and 0.05 m across it in 0.1 s
CONVEYOR = {"keyframes": [{"t": 0.0}, {"t": 0.1, "translate": [-0.1, 0.0, 0.05]}]}


def variant(name: str, tmp_path: Path):
    """``(scene, {key: value})`` of a drop variant: the ground a plane (NumPy's pairs), a
    moving mesh (ipctk's pairs, a kinematic obstacle: it drags the box back), or a plane
    with static 0.5 above kinetic 0.3 friction."""
    if name == "plane":
        return drop_scene(), {E_KEY: 1e4, "contact.mu": 0.3, "contact.kappa": 5e10}
    if name == "moving_mesh":
        scene = drop_scene(obstacles=[{"mesh": {"path": ground_mesh(tmp_path),
                                                "motion": CONVEYOR}}])
        return scene, {E_KEY: 1e4, "contact.mu": 0.3}
    contact = {**CONTACT, "mu": 0.0, "mu_s": 0.5, "mu_k": 0.3}
    return drop_scene(contact=contact), {"contact.mu_k": 0.3}  # E: as on the plane


def total_loss(scene, loss) -> float:
    qs = simulate(scene, STEPS)
    return sum(loss.frame(n, qs[n])[0] for n in range(1, STEPS + 1))


@pytest.mark.parametrize("ground", ["plane", "moving_mesh", "mu_s_mu_k"])
def test_contact_drop_gradient_matches_central_differences(ground: str, tmp_path) -> None:
    scene, values = variant(ground, tmp_path)
    qs = simulate(scene, STEPS)
    # it lands (within dhat of the ground after the first step) and slides, slowed
    dhat = 1e-3 * float(np.linalg.norm(np.ptp(np.concatenate(
        [qs[0], [[-1, 0, -1], [1, 0, 1]]] if ground == "moving_mesh" else [qs[0]]), axis=0)))
    assert all(0 < q[:, 1].min() < dhat for q in qs[1:])
    slide = np.diff([q[:, 0].mean() for q in qs])
    if ground == "moving_mesh":  # dragged back by the ground
        assert slide[0] > 0 > slide[-1]
    else:  # slowed by friction
        assert 0 < slide[-1] < 0.6 * slide[0]
    rng = np.random.default_rng(0)
    loss = PositionLoss({n: qs[n] + 0.01 * rng.normal(size=qs[n].shape)
                         for n in range(1, STEPS + 1)})
    value, grads = trajectory_gradient(scene, loss, list(values), checkpoint_every=4)
    assert value == pytest.approx(total_loss(scene, loss), rel=1e-12)
    for key, v in values.items():
        h = 1e-5 * v  # the step: 1e-5 of the value
        fd = (total_loss(scene_with(scene, {key: v + h}), loss)
              - total_loss(scene_with(scene, {key: v - h}), loss)) / (2 * h)
        # measured: 3e-9 (E), 2e-10 (mu), 6e-8 (kappa) on the plane, 3e-9 and 1e-9 on the
        # moving mesh, 1e-9 (mu_k) with mu_s > mu_k
        error = abs(grads[key] - fd) / abs(fd)
        assert error < 1e-6, f"{key}: adjoint {grads[key]}, differences {fd}, error {error:.1e}"


def test_two_bodies_gradient_matches_central_differences() -> None:
    """A second box (E = 2e4) thrown onto the first, which rests on the ground (6 steps):
    ipctk's pairs between two deformable bodies (their Hessian blocks widen the solver's
    pattern).
    This contact is stiffer, so every run converges Newton to ``rtol = 1e-14`` (at the
    default ``1e-11`` the differences' own noise is about ``1e-6``)."""
    from fem3d.scene import apply_overrides

    base = drop_scene(**{"bodies[0].velocity": [0.0, 0.0, 0.0]})
    lower = base.bodies[0].model_dump(exclude_none=True, mode="json")
    upper = {**lower, "velocity": [0.5, -1.0, 0.0], "transform": {"translate": [0.02, 0.21, 0]},
             "material": {**lower["material"], "E": 2e4}}
    scene = apply_overrides(base, {"bodies": [lower, upper]})
    rtol, steps = 1e-14, 6

    def total(sc) -> float:
        qs = simulate(sc, steps, rtol=rtol)
        return sum(loss.frame(n, qs[n])[0] for n in range(1, steps + 1))

    qs = simulate(scene, steps, rtol=rtol)
    assert qs[-1][:27, 1].max() < 0.9 * qs[0][:27, 1].max()  # the upper box squashes it
    rng = np.random.default_rng(0)
    loss = PositionLoss({n: qs[n] + 0.01 * rng.normal(size=qs[n].shape)
                         for n in range(1, steps + 1)})
    values = {E_KEY: 1e4, "contact.mu": 0.3}
    _, grads = trajectory_gradient(scene, loss, list(values), checkpoint_every=4, rtol=rtol)
    for key, v in values.items():
        h = 1e-5 * v
        fd = (total(scene_with(scene, {key: v + h})) - total(scene_with(scene, {key: v - h}))
              ) / (2 * h)
        # measured: 5.9e-8 (E), 7.1e-9 (mu); 10 steps: 4.8e-9 and 2.1e-7 (the differences'
        # truncation there: 2e-5 at h = 1e-4)
        error = abs(grads[key] - fd) / abs(fd)
        assert error < 1e-6, f"{key}: adjoint {grads[key]}, differences {fd}, error {error:.1e}"


@pytest.mark.parametrize("ground", ["plane", "mesh"])
def test_one_step_pieces_are_exact(ground: str, tmp_path) -> None:
    """The contact adjoint's Hessian (unprojected), its derivative by the lagged state and
    by the friction coefficients, against central differences of the contact gradient, at
    slips within the static-to-kinetic transition (where the friction Hessian is
    indefinite and Newton's PSD projection differs)."""
    contact = {**CONTACT, "mu": 0.0, "mu_s": 0.6, "mu_k": 0.3}
    obstacles = GROUND if ground == "plane" else [{"mesh": {"path": ground_mesh(tmp_path)}}]
    run = _prepare(drop_scene(contact=contact, obstacles=obstacles), 1e-11, 1e-16)
    ext = run.terms[0]
    cm = ext.cm
    s0 = run.step(run.step(run.state0))  # in contact
    dt = run.dt
    eps = cm.eps_v * dt
    rng = np.random.default_rng(1)
    slip = rng.normal(size=s0.q.shape) * np.array([1.0, 0.0, 1.0])
    slip *= (eps * rng.uniform(0.3, 2.5, size=(slip.shape[0], 1))
             / np.linalg.norm(slip, axis=1, keepdims=True))
    q1 = s0.q + slip + np.array([0.0, 1e-6, 0.0])
    ext.after_step(s0)  # the stiffness step s0 used: the fixed one

    def at(q0, q1_, mu=None):
        s_0 = State(q=q0, v=s0.v, t=s0.t, step=s0.step)
        s_1 = State(q=q1_, v=s0.v, t=s0.t + dt, step=s0.step + 1)
        saved = (cm.mu, cm.mu_k)
        if mu is not None:
            cm.mu, cm.mu_k = mu
        ext.set_step(s_0, s_1, dt, ["contact.mu_s", "contact.mu_k"])
        g = cm.barrier_gradient(q1_.reshape(-1)) + cm.friction_gradient(q1_.reshape(-1))
        cm.mu, cm.mu_k = saved
        return g

    g0 = at(s0.q, q1)
    assert cm.n_friction_pairs > 0
    H = ext.hessian()
    lf = rng.normal(size=g0.size)
    vjp, dmu_s, dmu_k = (ext.lagged_vjp(lf), ext.coefficient_vjp("contact.mu_s", lf),
                         ext.coefficient_vjp("contact.mu_k", lf))
    w = rng.normal(size=s0.q.shape)
    h = 1e-3 * eps
    # the Hessian by the end-of-step positions
    fd = (at(s0.q, q1 + h * w) - at(s0.q, q1 - h * w)) / (2 * h)
    Hw = H @ w.reshape(-1)
    assert np.abs(Hw - fd).max() < 1e-5 * np.abs(fd).max()
    projected = cm.hessian(q1.reshape(-1), project=True).tocsr() @ w.reshape(-1)
    assert np.abs(projected - fd).max() > 1e-3 * np.abs(fd).max()  # the test can tell
    # the lagged state, the step's unknowns held: q0 and q1 move together
    fd = (lf @ at(s0.q + h * w, q1 + h * w) - lf @ at(s0.q - h * w, q1 - h * w)) / (2 * h)
    assert vjp @ w.reshape(-1) == pytest.approx(fd, rel=1e-5)
    # the coefficients (the friction is linear in them)
    for which, d in ((0, dmu_s), (1, dmu_k)):
        mu = np.array([0.6, 0.3])
        step = np.eye(2)[which] * 1e-3
        fd = (lf @ at(s0.q, q1, mu + step) - lf @ at(s0.q, q1, mu - step)) / 2e-3
        assert d == pytest.approx(fd, rel=1e-7)


def test_substeps_allowed_until_a_step_would_take_them(monkeypatch) -> None:
    """``contact.max_substeps > 1``: every step whose straight motion is free is the whole
    step a run takes (same gradient as without substeps); where a run would take substeps
    the forward pass stops, naming the step."""
    from fem3d.physics.terms.contact import ContactTerm

    loss = PositionLoss({2: np.zeros((27, 3))})
    _, plain = trajectory_gradient(drop_scene(), loss, [E_KEY])
    _, checked = trajectory_gradient(drop_scene(contact={**CONTACT, "max_substeps": 4}),
                                     loss, [E_KEY])
    assert checked[E_KEY] == plain[E_KEY]
    monkeypatch.setattr(ContactTerm, "straight_path_is_free", lambda *a: False)
    with pytest.raises(SimulationError, match="step 0: its straight motion passes through"):
        trajectory_gradient(drop_scene(contact={**CONTACT, "max_substeps": 4}), loss,
                            [E_KEY])


def test_friction_iterations_and_contact_keys_without_their_term_are_refused() -> None:
    scene = drop_scene(contact={**CONTACT, "friction_iterations": 3})
    loss = PositionLoss({1: np.zeros((27, 3))})
    with pytest.raises(ParameterError, match="friction_iterations = 3"):
        trajectory_gradient(scene, loss, [E_KEY])
    no_contact = drop_scene(contact={"enabled": False}, obstacles=[], **{
        "bodies[0].pins": [{"select": {"lowest_y": {"tol": 0.0}}}]})
    with pytest.raises(ParameterError, match="'contact.mu' in this scene"):
        trajectory_gradient(no_contact, loss, ["contact.mu"])
    adaptive = drop_scene(contact={k: v for k, v in CONTACT.items() if k != "kappa"})
    with pytest.raises(ParameterError, match="'contact.kappa'.*a fixed kappa"):
        trajectory_gradient(adaptive, loss, ["contact.kappa"])


@pytest.mark.parametrize("integrator", ["implicit", "bdf2"])
def test_fit_recovers_E_through_a_contact_landing(tmp_path: Path, integrator: str) -> None:
    """``fem3d fit`` on a target run (``fem3d run``, its VTU frames with the ground as a
    second part) of the landing (6 steps) with E = 3e4, from E = 1e4, the fit's scene with
    the same integrator. The target is run with IPC's default stopping rule
    (``contact.tolerance = 1e-2``), a slightly different map from the fit's converged one:
    measured 29990 (3e-4) in 6 iterations with ``implicit`` (10 steps: 29986), 30024.7
    (8.2e-4) in 5 with ``bdf2``."""
    base = {"simulation.steps": 6, "output.every": 1,  # lands, then slides
            "simulation.integrator": integrator}
    summary = run_scene(drop_scene(**base, **{E_KEY: 3e4}), tmp_path / "target", quiet=True,
                        preview=False)
    assert summary.status == "ok"
    (tmp_path / "box.toml").write_text(scene_toml(drop_scene(**base)))
    fit_file = tmp_path / "fit.toml"
    fit_file.write_text(textwrap.dedent("""\
        scene = "box.toml"
        target = "target"
        [[params]]
        key = "bodies[0].material.E"
        start = 1e4
        bounds = [1e3, 1e6]
    """))
    out = tmp_path / "out"
    assert main(["fit", str(fit_file), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "fit.json").read_text())
    assert doc["params"][E_KEY] == pytest.approx(3e4, rel=1e-2)
    assert doc["result"]["success"] and doc["frames"] == list(range(1, 7))


def test_contact_bunny_drop_landing_gradient_matches_central_differences() -> None:
    """The gallery's contact_bunny_drop (1,518 tets, adaptive kappa, mu = 0.3) lowered to
    1 cm above the ground and thrown sideways: it comes within 2 mm of the ground in step 4
    and slides through steps 5-7 (the run stops there; 10 steps cost half as much again and
    prove no more). E and mu (the
    adaptive kappa is replayed: neither moves it here) against central differences, step
    1e-5 of the value; measured 1.8e-9 (E) and 1.2e-8 (mu) (10 steps: 4.6e-7, 6.4e-9)."""
    from fem3d.scene import apply_overrides, load_scene

    base = load_scene("contact_bunny_drop")
    rest = simulate(base, 0)[0]
    lift = 0.245 - float(rest[:, 1].min()) + 0.01  # the lowest vertex 1 cm up
    scene = apply_overrides(base, {"bodies[0].transform.translate": [0.0, lift, 0.0],
                                   "bodies[0].velocity": [0.4, 0.0, 0.0]})
    steps = 7
    qs = simulate(scene, steps)
    assert qs[3][:, 1].min() > 2e-3 and qs[4][:, 1].min() < 2e-3  # lands in step 4
    assert qs[steps][:, 1].min() < 2e-3  # landed (within a couple of dhat of the ground)
    rng = np.random.default_rng(3)
    loss = PositionLoss({n: qs[n] + 1e-3 * rng.normal(size=qs[n].shape)
                         for n in range(1, steps + 1)})

    def total(sc) -> float:
        run = simulate(sc, steps)
        return sum(loss.frame(n, run[n])[0] for n in range(1, steps + 1))

    values = {E_KEY: 1e5, "contact.mu": 0.3}
    _, grads = trajectory_gradient(scene, loss, list(values), checkpoint_every=5)
    for key, v in values.items():
        h = 1e-5 * v
        fd = (total(scene_with(scene, {key: v + h})) - total(scene_with(scene, {key: v - h}))
              ) / (2 * h)
        error = abs(grads[key] - fd) / abs(fd)
        assert error < 1e-6, f"{key}: adjoint {grads[key]}, differences {fd}, error {error:.1e}"
