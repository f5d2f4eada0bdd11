"""Adjoint gradients of static and BDF2 trajectories against central finite differences
(``fem3d.diff.static``, ``fem3d.diff.bdf2``), and the refusals of what is not differentiated."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.diff import PositionLoss, simulate, trajectory_gradient
from fem3d.diff.adjoint import scene_with
from fem3d.errors import ParameterError
from fem3d.scene import apply_overrides
from tests.diff.test_backward_euler_gradients import (
    VALUES,
    apply_pin,
    box_scene,
    central,
    noisy_loss,
    two_halves,
)

STEPS = 6


def total_loss(scene, loss, steps: int = STEPS) -> float:
    qs = simulate(scene, steps)
    return sum(loss.frame(n, qs[n])[0] for n in range(1, steps + 1))


def relative_errors(scene, loss, values: dict, rel: float, steps: int = STEPS) -> dict:
    """``{key: max |adjoint - central difference| / max |difference|}``; the step: ``rel``
    of the value (vectors: of their largest entry, at least ``rel``)."""
    _, grads = trajectory_gradient(scene, loss, list(values), checkpoint_every=4)
    out = {}
    for key, value in values.items():
        v = np.atleast_1d(np.asarray(value, dtype=np.float64))
        h = rel * max(np.abs(v).max(), 1.0 if v.size > 1 else 0.0)
        fd = np.empty(v.size)
        for c in range(v.size):
            def at(s, c=c, v=v, key=key):
                w = v.copy()
                w[c] += s
                return total_loss(scene_with(scene, {key: w if v.size > 1 else w[0]}), loss,
                                  steps)
            fd[c] = central(at, h)
        g = np.atleast_1d(grads[key])
        out[key] = float(np.abs(g - fd).max() / np.abs(fd).max())
    return out


def drive(scene, integrator: str):
    """``scene`` with its pins (x = 0 face or the bottom) carried by three keyframes."""
    pin = scene.bodies[0].pins[0].select.model_dump(mode="json", exclude_none=True)
    return apply_pin(scene, {"select": pin, "motion": {
        "interpolation": "smooth", "keyframes": [
            {"t": 0.0}, {"t": 0.03, "translate": [0.02, 0.03, 0.01]},
            {"t": 0.1, "translate": [0.05, -0.02, 0.0]}]}})


# ------------------------------------------------------------------ static
def static_bar():
    """The two-halves bar (1e5 | 4e5, 24 tets) clamped at x = 0 sagging under gravity,
    ``static``, its clamp moved by keyframes (so each step's equilibrium differs)."""
    scene = apply_overrides(two_halves(1e5, 4e5), {"simulation.integrator": "static",
                                                   "bodies[0].velocity": [0.0, 0.0, 0.0],
                                                   "bodies[0].material.density": 1000.0})
    return drive(scene, "static")


def test_static_gradients_match_central_differences() -> None:
    """E (body and region), nu, density, gravity: relative steps 1e-6 (at 1e-5 the central
    difference's own truncation error is 2e-7 (E) and 1.1e-6 (density), at 1e-4 100 times
    that: it scales as h^2); the keyframes' translate: a step of 1e-5 of its size; to 1e-6."""
    scene = static_bar()
    loss = noisy_loss(simulate(scene, STEPS), np.random.default_rng(11))
    errors = relative_errors(scene, loss, {
        "bodies[0].material.E": 1e5, "bodies[0].material.regions[0].E": 4e5,
        "bodies[0].material.nu": 0.3, "bodies[0].material.density": 1000.0,
        "simulation.gravity": np.array([0.0, -9.81, 0.0])}, 1e-6)
    for k in range(1, 3):
        kf = scene.bodies[0].pins[0].motion.keyframes[k]
        errors |= relative_errors(scene, loss, {
            f"bodies[0].pins[0].motion.keyframes[{k}].translate": np.array(kf.translate)},
            1e-5 / max(np.abs(kf.translate).max(), 1e-3))
    print("static", errors)
    assert max(errors.values()) < 1e-6, errors


# ------------------------------------------------------------------ BDF2, Newmark
@pytest.mark.parametrize("integrator", ["bdf2", "newmark"])
@pytest.mark.parametrize("beta", [0.0, 0.002])
def test_bdf2_and_newmark_gradients_match_central_differences(integrator: str,
                                                              beta: float) -> None:
    """The box of tests/diff/test_backward_euler_gradients.py with BDF2 (first step backward
    Euler) and Newmark (its
    a_0 from M a_0 = f(q_0, v_0)), 6 steps: E, nu, density, alpha (and beta), initial
    velocity, gravity; relative steps 1e-5; to 1e-6."""
    scene, values = box_scene(beta)
    scene = apply_overrides(scene, {"simulation.integrator": integrator})
    loss = noisy_loss(simulate(scene, STEPS), np.random.default_rng(12))
    keys = {k: values[k] for k in VALUES if beta > 0 or "stiffness" not in k}
    errors = relative_errors(scene, loss, keys, 1e-5)
    print(integrator, beta, errors)
    assert max(errors.values()) < 1e-6, errors


@pytest.mark.parametrize("integrator", ["bdf2", "newmark"])
def test_bdf2_and_newmark_pin_keyframe_and_region_gradients(integrator: str) -> None:
    """BDF2 and Newmark on the two-halves bar with its clamp driven by keyframes: the
    region's E (relative step 1e-4; the loss is weakly sensitive to it, so smaller steps meet
    round-off: BDF2 7e-7 at 1e-5, 3.6e-6 at 1e-6) and each keyframe's translate (step 1e-5
    of its size), to 1e-6."""
    scene = drive(apply_overrides(two_halves(1e5, 4e5),
                                  {"simulation.integrator": integrator}), integrator)
    loss = noisy_loss(simulate(scene, STEPS), np.random.default_rng(13))
    errors = relative_errors(scene, loss, {"bodies[0].material.regions[0].E": 4e5}, 1e-4)
    for k in range(1, 3):
        t = np.array(scene.bodies[0].pins[0].motion.keyframes[k].translate)
        errors |= relative_errors(scene, loss, {
            f"bodies[0].pins[0].motion.keyframes[{k}].translate": t}, 1e-5 / np.abs(t).max())
    print(integrator, "pins", errors)
    assert max(errors.values()) < 1e-6, errors


def test_undifferentiated_integrators_are_refused_in_one_line() -> None:
    scene, _ = box_scene(0.0)
    with pytest.raises(ParameterError, match="'linear' is not differentiated") as info:
        trajectory_gradient(apply_overrides(scene, {"simulation.integrator": "linear"}),
                            PositionLoss({1: np.zeros((27, 3))}), ["bodies[0].material.E"])
    assert "\n" not in str(info.value)


def test_static_initial_velocity_key_is_refused() -> None:
    with pytest.raises(ParameterError, match="'static' has no velocities"):
        trajectory_gradient(static_bar(), PositionLoss({1: np.zeros((30, 3))}),
                            ["bodies[0].velocity"])


def test_contact_with_a_scheme_without_contact_is_refused_in_one_line(monkeypatch) -> None:
    """Every registered scheme differentiates contact
    (``tests/diff/test_contact_gradients_each_scheme.py``);
    one registered without (``SchemeAdjoint.contact = False``) is refused in one line."""
    from fem3d.diff.bdf2 import BDF2Adjoint
    from fem3d.diff.schemes import SCHEMES
    from tests.diff.test_contact_gradients import drop_scene

    without = BDF2Adjoint()
    without.contact = False
    monkeypatch.setitem(SCHEMES, "bdf2", without)
    scene = apply_overrides(drop_scene(), {"simulation.integrator": "bdf2"})
    with pytest.raises(ParameterError, match="contact is not differentiated with "
                       r"simulation.integrator = 'bdf2' \(differentiated with contact: "
                       "implicit, newmark, static\\)") as info:
        trajectory_gradient(scene, PositionLoss({1: np.zeros((1, 3))}, vertices=[0]),
                            ["bodies[0].material.E"])
    assert "\n" not in str(info.value)
