"""Adjoint gradients through IPC contact and lagged friction with ``bdf2``, ``newmark``
(``gamma = 0.55`` with contact) and ``static``, against central finite differences: the box
of ``test_diff_contact`` landing and sliding on a plane or a moving mesh, and, ``static``,
pressed onto the plane and dragged sideways by its pinned top."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.diff import PositionLoss, simulate, trajectory_gradient
from fem3d.diff.adjoint import _prepare, scene_with
from fem3d.scene import apply_overrides
from fem3d.solve.schemes.newmark import CONTACT_ALPHA
from tests.diff.test_contact_gradients import E_KEY, drop_scene, variant

STEPS = 6
V_KEY = "bodies[0].velocity"


def total_loss(scene, loss, steps: int = STEPS, rtol: float = 1e-11) -> float:
    qs = simulate(scene, steps, rtol=rtol)
    return sum(loss.frame(n, qs[n])[0] for n in range(1, steps + 1))


def noisy(qs, seed: int) -> PositionLoss:
    """Every frame against a noisy copy of the positions (so the gradient is not zero)."""
    rng = np.random.default_rng(seed)
    return PositionLoss({n: qs[n] + 0.01 * rng.normal(size=qs[n].shape)
                         for n in range(1, len(qs))})


def errors(scene, loss, steps: dict, rtol: float = 1e-11) -> dict:
    """``{key: |adjoint - central difference| / |difference|}``, the step of each key
    ``steps[key] = (value, relative step)``; a vector key along a random direction ``d``
    (``dL/dv . d`` against ``(L(v + h d) - L(v - h d)) / 2h``); Newton to ``rtol``."""
    _, grads = trajectory_gradient(scene, loss, list(steps), checkpoint_every=4, rtol=rtol)
    out = {}
    for key, (value, rel) in steps.items():
        value = np.asarray(value, dtype=np.float64)
        d = np.random.default_rng(3).normal(size=value.shape) if value.ndim else np.array(1.0)
        h = rel * float(np.abs(value).max())

        def at(s, key=key, value=value, d=d):
            w = value + s * d
            return total_loss(scene_with(scene, {key: w if w.ndim else float(w)}), loss,
                              rtol=rtol)
        fd = (at(h) - at(-h)) / (2 * h)
        adjoint = float(np.sum(np.asarray(grads[key]) * d))
        out[key] = abs(adjoint - fd) / abs(fd)
    return out


@pytest.mark.parametrize("integrator, ground", [
    ("bdf2", "plane"), ("newmark", "plane"), ("newmark", "moving_mesh")])
def test_contact_gradients_match_central_differences(integrator: str, ground: str,
                                                     tmp_path) -> None:
    """E, mu, kappa (fixed) and the initial velocity (along a random direction): relative
    steps 1e-5 (kappa: 1e-4, its small gradient's differences are round-off below), to 1e-6.
    Newmark bounces on
    the mesh (it leaves ``dhat`` in step 2): Newton to ``rtol = 1e-14`` there (at ``1e-11``
    the differences' noise is 1e-6 of mu's gradient, 2e-7 of E's; at 1e-14: 9e-9, 3e-9)."""
    scene, _ = variant(ground, tmp_path)
    scene = apply_overrides(scene, {"simulation.integrator": integrator})
    rtol = 1e-14 if ground == "moving_mesh" else 1e-11
    qs = simulate(scene, STEPS, rtol=rtol)
    dhat = _prepare(scene, 1e-11, 1e-16).terms[0].cm.dhat
    assert 0 < qs[1][:, 1].min() < dhat and 0 < qs[-1][:, 1].min() < dhat  # lands at once
    slide = np.diff([q[:, 0].mean() for q in qs])
    assert 0 < slide[-1] < 0.8 * slide[0]  # slowed by friction (the mesh: moving against)
    steps = {E_KEY: (1e4, 1e-5), "contact.mu": (0.3, 1e-5),
             "contact.kappa": (5e10, 1e-4), V_KEY: ([0.5, -1.0, 0.0], 1e-5)}
    found = errors(scene, noisy(qs, 0), steps, rtol)
    print(integrator, ground, {k: f"{e:.1e}" for k, e in found.items()})
    assert max(found.values()) < 1e-6, found


def test_newmark_contact_runs_with_the_dissipative_gamma() -> None:
    """The adjoint's Newmark step map is the forward's: ``gamma = 1/2 + CONTACT_ALPHA`` with
    contact, 1/2 without (with 1/2 in the adjoint the Newmark plane's errors are E 6.4e-2,
    mu 0.31)."""
    scene = apply_overrides(pressed_box(gap=0.005), {"simulation.integrator": "newmark"})
    assert _prepare(scene, 1e-11, 1e-16).scheme.gamma == 0.5 + CONTACT_ALPHA
    free = apply_overrides(scene, {"contact.enabled": False, "obstacles": []})
    assert _prepare(free, 1e-11, 1e-16).scheme.gamma == 0.5
    assert _prepare(scene, 1e-11, 1e-16).scheme.gamma == 0.5 + CONTACT_ALPHA  # per run


def pressed_box(gap: float = 2e-4):
    """``static``: the box 0.2 mm above the ground (within ``dhat``), its top face pinned
    and carried by keyframes 4 mm down (20 ms) then 2 cm along x and 5 mm along z (80 ms):
    friction holds the bottom while the top shears it, until the bottom starts to slide."""
    pin = {"select": {"box": [[-1, 0.19 + gap, -1], [1, 1, 1]]}, "motion": {"keyframes": [
        {"t": 0.0}, {"t": 0.02, "translate": [0.0, -0.004, 0.0]},
        {"t": 0.08, "translate": [0.02, -0.004, 0.005]}]}}
    return drop_scene(**{"simulation.integrator": "static", V_KEY: [0.0, 0.0, 0.0],
                         "bodies[0].pins": [pin],
                         "bodies[0].transform": {"translate": [0.0, gap - 0.005, 0.0]}})


def test_static_contact_gradients_match_central_differences() -> None:
    """E, mu, kappa and the pin's last keyframe (along a random direction): relative steps
    1e-5 (kappa 1e-4), to 1e-6."""
    scene = pressed_box()
    qs = simulate(scene, STEPS)
    bottom = np.array([q[q[:, 1] < 0.01, 0].mean() for q in qs])
    assert all(0 < q[:, 1].min() < 1e-3 for q in qs)  # pressed, not touching
    assert bottom[4] - bottom[0] < 1e-4 < bottom[-1] - bottom[0] < 0.02 / 4  # holds, then slips
    steps = {E_KEY: (1e4, 1e-5), "contact.mu": (0.3, 1e-5), "contact.kappa": (5e10, 1e-4),
             "bodies[0].pins[0].motion.keyframes[2].translate": ([0.02, -0.004, 0.005],
                                                                 1e-5)}
    found = errors(scene, noisy(qs, 0), steps)
    print("static", {k: f"{e:.1e}" for k, e in found.items()})
    assert max(found.values()) < 1e-6, found


def test_newmark_contact_start_within_dhat_gradients() -> None:
    """Newmark from a start within ``dhat`` (the pressed box of the static test, thrown
    along x at 0.3 m/s, ``newmark``): ``a_0`` holds the barrier's force at ``q_0`` (as
    ``fem3d run``'s), and its adjoint the barrier's part (without it, kappa's gradient is off
    by a factor 18). Relative steps 1e-5 (kappa 1e-4), along random directions, to 1e-6."""
    scene = apply_overrides(pressed_box(), {"simulation.integrator": "newmark",
                                            V_KEY: [0.3, 0.0, 0.0]})
    run = _prepare(scene, 1e-11, 1e-16)
    assert run.state0.history["a"][:, 1].max() > 100.0  # the barrier pushes at the start
    qs = simulate(scene, STEPS)
    steps = {E_KEY: (1e4, 1e-5), "contact.mu": (0.3, 1e-5), "contact.kappa": (5e10, 1e-4),
             V_KEY: ([0.3, 0.0, 0.0], 1e-5),
             "bodies[0].pins[0].motion.keyframes[2].translate": ([0.02, -0.004, 0.005],
                                                                 1e-5)}
    found = errors(scene, noisy(qs, 0), steps)
    print("newmark start in contact", {k: f"{e:.1e}" for k, e in found.items()})
    assert max(found.values()) < 1e-6, found
