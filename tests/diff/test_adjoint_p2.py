"""The adjoint (``fem3d.diff``) and ``fem3d fit`` on quadratic (P2) tetrahedra.

The scenes are the P1 tests' (``tests/diff/test_backward_euler_gradients.py``,
``test_static_bdf2_gradients.py``, ``test_contact_gradients.py``) with ``element = "p2"``:
the same meshes lifted to 10-node elements (edge nodes added), every element's energy, its
parameter derivatives (``dgradient_dparams``, 30 x n_params) and stiffness damping's
``K_psd`` summed over the element's 4 quadrature points.

Tolerance: 1e-6 of the largest central difference, as the P1 tests. Converged runs
(``rtol = 1e-11``) make the loss smooth in every parameter, so a central difference with a
relative step ``h`` carries a truncation error ``O(h^2)`` and a round-off error
``O(eps_loss / h)``; the steps below were chosen where both are below 1e-7 (measured: the
adjoint agrees with the differences to 3e-11 .. 7e-8, see docs/elements.md).
"""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import meshio
import numpy as np
import pytest

from fem3d.app.cli import main
from fem3d.app.fit.run import scene_toml
from fem3d.app.run import run_scene
from fem3d.diff import simulate, trajectory_gradient
from fem3d.diff.adjoint import _prepare
from fem3d.diff.damping import linearize_damping, point_kernels, quadrature_points
from fem3d.scene import apply_overrides, load_scene
from tests.app.test_fit import bar_scene
from tests.diff.test_backward_euler_gradients import (
    VALUES,
    box_scene,
    central,
    field_scene,
    noisy_loss,
    pinned_drive,
)
from tests.diff.test_contact_gradients import variant
from tests.diff.test_static_bdf2_gradients import relative_errors, static_bar, total_loss

STEPS = 6
P2 = {"bodies[0].element": "p2"}


def on_p2(scene, **overrides):
    """``scene`` with body 0 on quadratic tets (and ``overrides``)."""
    return apply_overrides(scene, {**P2, **overrides})


def test_the_scenes_are_p2() -> None:
    """The lifted box: 48 elements of 10 nodes (125 nodes, 4 quadrature points each)."""
    run = _prepare(on_p2(box_scene(0.002)[0]), 1e-11, 1e-16)
    model = run.system.model
    assert model.element.name == "p2" and model.T.shape == (48, 10)
    assert model.n_vertices == 125 and model.vol.shape == (48, 4)
    assert run.damping is not None  # the exact damping adjoint (not differences)


@pytest.mark.parametrize("integrator", ["implicit", "bdf2", "newmark"])
def test_p2_dynamic_gradients_match_central_differences(integrator: str) -> None:
    """The damped box (alpha = 0.5, beta = 0.002: most of its 192 quadrature points have an
    indefinite dP/dF, so the PSD projection's derivative is exercised) on P2, 6 steps: E, nu,
    density, alpha, beta, the initial velocity, gravity; relative steps 1e-5; measured errors
    4e-11 .. 7e-8."""
    scene, values = box_scene(0.002)
    scene = on_p2(scene, **{"simulation.integrator": integrator})
    loss = noisy_loss(simulate(scene, STEPS), np.random.default_rng(12))
    errors = relative_errors(scene, loss, {k: values[k] for k in VALUES}, 1e-5)
    print(integrator, {k: f"{e:.1e}" for k, e in errors.items()})
    assert max(errors.values()) < 1e-6, errors


def test_p2_static_gradients_with_a_region_and_moving_pins() -> None:
    """``static`` on the two-halves bar (24 elements, 4e5 on the free half as a region) on
    P2, its clamp (edge nodes included) driven by keyframes: E of the body and of the
    region, nu, density, gravity (relative steps 1e-6) and each keyframe's translate
    (absolute step 1e-5 on a bar 2 m long)."""
    scene = on_p2(static_bar())
    loss = noisy_loss(simulate(scene, STEPS), np.random.default_rng(11))
    errors = relative_errors(scene, loss, {
        "bodies[0].material.E": 1e5, "bodies[0].material.regions[0].E": 4e5,
        "bodies[0].material.nu": 0.3, "bodies[0].material.density": 1000.0,
        "simulation.gravity": np.array([0.0, -9.81, 0.0])}, 1e-6)
    for k in range(1, 3):
        t = np.array(scene.bodies[0].pins[0].motion.keyframes[k].translate)
        errors |= relative_errors(scene, loss, {
            f"bodies[0].pins[0].motion.keyframes[{k}].translate": t}, 1e-5)
    print("static", {k: f"{e:.1e}" for k, e in errors.items()})
    assert max(errors.values()) < 1e-6, errors


def test_p2_moving_pin_gradient_matches_central_differences() -> None:
    """Backward Euler, the box's bottom (corner and edge nodes) driven sideways: each
    keyframe's translate, absolute step 1e-5 (at 2e-4 the difference's own truncation error
    is 2e-6; at 1e-5, 2e-8)."""
    scene = on_p2(pinned_drive("smooth"))
    loss = noisy_loss(simulate(scene, STEPS), np.random.default_rng(5))
    errors = {}
    for k in range(1, 3):
        t = np.array(scene.bodies[0].pins[0].motion.keyframes[k].translate)
        errors |= relative_errors(scene, loss, {
            f"bodies[0].pins[0].motion.keyframes[{k}].translate": t}, 1e-5)
    print("pin", {k: f"{e:.1e}" for k, e in errors.items()})
    assert max(errors.values()) < 1e-6, errors


def test_p2_per_tet_field_gradient_matches_differences_along_random_directions(
        tmp_path) -> None:
    """dL/dE per element (a cell field of the P1 ``.vtu``, the body lifted to P2) against
    central differences along random directions, relative step 1e-5 (the truncation error
    falls as h^2: 2e-4 at 1e-3, 2e-6 at 1e-4, 4e-8 at 1e-5), to 1e-6."""
    scene, _ = box_scene(0.0)
    rng = np.random.default_rng(3)
    E = 1e5 * (1 + 0.5 * rng.random(48))

    def at(E_field, tag):
        return on_p2(field_scene(scene, tmp_path, E_field, tag))
    base = at(E, "base")
    loss = noisy_loss(simulate(base, STEPS), rng)
    key = "bodies[0].material.cell_fields.E"
    _, grads = trajectory_gradient(base, loss, [key], checkpoint_every=4)
    g = grads[key]
    assert g.shape == (48,)
    for _ in range(2):
        d = rng.normal(size=48)
        fd = central(lambda eps, d=d: total_loss(at(E * (1 + eps * d), f"{eps:+g}"), loss),
                     1e-5)
        print("field", f"{abs(float(g @ (E * d)) - fd) / abs(fd):.1e}")
        assert abs(float(g @ (E * d)) - fd) < 1e-6 * abs(fd)


def test_p2_contact_drop_gradient_matches_central_differences(tmp_path) -> None:
    """The box dropped on the ground plane with friction (IPC on the subdivided quadratic
    surface), 10 steps: E, mu, kappa; relative steps 1e-5; measured 3e-9 .. 4e-8."""
    scene, values = variant("plane", tmp_path)
    scene = on_p2(scene)
    qs = simulate(scene, 10)
    assert all(q[:, 1].min() > 0 for q in qs) and qs[-1][:, 1].min() < 1e-3  # it landed
    loss = noisy_loss(qs, np.random.default_rng(0))
    errors = relative_errors(scene, loss, values, 1e-5, steps=10)
    print("contact", {k: f"{e:.1e}" for k, e in errors.items()})
    assert max(errors.values()) < 1e-6, errors


def test_p2_damping_linearization_matches_the_p2_kernels(monkeypatch) -> None:
    """``D(q)`` of the adjoint (per quadrature point: the material's per-F ``d2psi_dF2``,
    projected by one eigendecomposition per indefinite point) is the P2 kernels'
    ``hessian_psd`` damping matrix to round-off on a squashed box, by chunks too; its
    eigendecompositions index the quadrature points and are those of the points' ``A``."""
    from fem3d.diff import damping

    scene, _ = box_scene(0.002)
    run = _prepare(on_p2(scene), 1e-11, 1e-16)
    model, term = run.system.model, run.system.loads.damping
    rng = np.random.default_rng(3)
    q = (model.X * [1.0, 0.6, 1.0] + 0.03 * rng.normal(size=model.X.shape)).reshape(-1)
    lin = linearize_damping(term, run.groups, q)
    ref = term.matrix_data(q)
    assert np.abs(lin.data - ref).max() < 1e-12 * np.abs(ref).max()
    (g, els, params, inputs), = run.groups
    bad, values, V = lin.eig[0]
    assert 4 * els.size // 2 < bad.size <= 4 * els.size
    D, _ = quadrature_points(model, els)
    F = np.einsum("evc,evj->ecj", np.repeat(q.reshape(-1, 3)[model.T[els]], 4, axis=0), D)
    A = point_kernels(g).d2psi_dF2(F, *inputs, np.repeat(params, 4, axis=0)).reshape(-1, 9, 9)
    np.testing.assert_allclose(values, np.linalg.eigvalsh(A[bad]), rtol=0,
                               atol=1e-10 * np.abs(A).max())
    monkeypatch.setattr(damping, "CHUNK", 175)  # chunks of 7 elements (28 points)
    assert damping.chunk_elements(model) == 7
    chunked = linearize_damping(term, run.groups, q)
    np.testing.assert_allclose(chunked.data, lin.data, rtol=0, atol=1e-13 * np.abs(ref).max())
    np.testing.assert_array_equal(chunked.eig[0][0], bad)


# ------------------------------------------------------------------ fem3d fit on P2
E_TRUE = 3e5


def write_fit(folder: Path, name: str, body: str) -> Path:
    p = folder / f"{name}.toml"
    p.write_text(textwrap.dedent(body))
    return p


def test_fit_recovers_E_on_p2_through_the_cli(tmp_path: Path, capsys) -> None:
    """``fem3d fit`` on the bar of tests/app/test_fit.py lifted to P2 (72 elements, 175
    nodes; the target run's frames hold every node): E from 1e5 to 3e5 within 1e-3 (the P1
    test's tolerance); exit 0, one progress line per iteration and the one-line summary,
    fit.json, fit.png and fitted.toml (still P2) written."""
    target = bar_scene(**{"bodies[0].material.E": E_TRUE, "simulation.newton.max_iterations":
                          None, **P2})
    assert run_scene(target, tmp_path / "target", quiet=True, preview=False).status == "ok"
    (tmp_path / "bar.toml").write_text(scene_toml(bar_scene(**{"bodies[0].material.E": 1e5,
                                                                **P2})))
    fit_file = write_fit(tmp_path, "e", """\
        scene = "bar.toml"
        target = "target"
        [[params]]
        key = "bodies[0].material.E"
        start = 1e5
        bounds = [1e3, 1e8]
        [optimizer]
        max_iterations = 30
    """)
    out = tmp_path / "out"
    assert main(["fit", str(fit_file), "--out", str(out)]) == 0
    err = capsys.readouterr().err.splitlines()
    doc = json.loads((out / "fit.json").read_text())
    E = doc["params"]["bodies[0].material.E"]
    assert abs(E / E_TRUE - 1) < 1e-3
    assert doc["result"]["success"] and doc["vertices_per_frame"] == 175
    assert doc["history"][-1]["loss"] < 1e-8 * doc["history"][0]["loss"]
    progress = [line for line in err if line.startswith("fem3d fit: iter")]
    assert len(progress) == len(doc["history"])
    assert err[-1].startswith("fem3d fit e: converged") and str(out / "fit.json") in err[-1]
    fitted = load_scene(out / "fitted.toml")
    assert fitted.bodies[0].element == "p2"
    assert fitted.bodies[0].material.E == pytest.approx(E, rel=1e-12)
    assert (out / "fit.png").read_bytes()[:4] == b"\x89PNG"


def test_fit_of_a_per_tet_field_on_a_tetra10_mesh(tmp_path: Path) -> None:
    """A per-tet E field read from a 10-node ``.vtu`` (``tetra10`` cells): the fit writes
    the fitted field back on the same quadratic cells (``fitted_body0.vtu``) and lowers the
    loss below 1e-3 of its start in 12 iterations (measured: 7e-4; 2e-4 after 20)."""
    from fem3d.scene.arrays import build_arrays

    base = on_p2(bar_scene(**{"bodies[0].material.E": 2e5}))
    a = build_arrays(base)
    E = np.where(a.X[a.T[:, :4]].mean(axis=1)[:, 0] > 0.75, 4e5, 1e5)
    meshio.write(tmp_path / "bar10.vtu", meshio.Mesh(a.X, [("tetra10", a.T)],
                                                      cell_data={"youngs": [E]}))
    scene = apply_overrides(base, {"bodies[0].mesh": str(tmp_path / "bar10.vtu"),
                                   "bodies[0].material.cell_fields": {"E": "youngs"},
                                   "simulation.newton.max_iterations": None})
    assert run_scene(scene, tmp_path / "target", quiet=True, preview=False).status == "ok"
    (tmp_path / "field.toml").write_text(scene_toml(scene))
    fit_file = write_fit(tmp_path, "fit_field", """\
        scene = "field.toml"
        target = "target"
        [[params]]
        key = "bodies[0].material.cell_fields.E"
        start = 2e5
        bounds = [1e3, 1e8]
        [optimizer]
        max_iterations = 12
    """)
    out = tmp_path / "out"
    assert main(["fit", str(fit_file), "--out", str(out), "--quiet"]) in (0, 1)
    doc = json.loads((out / "fit.json").read_text())
    key = "bodies[0].material.cell_fields.E"
    assert len(doc["params"][key]) == 72
    assert doc["loss"] < 1e-3 * doc["history"][0]["loss"]
    written = meshio.read(out / "fitted_body0.vtu")
    assert [c.type for c in written.cells] == ["tetra10"]
    np.testing.assert_array_equal(written.cells[0].data, a.T)
    np.testing.assert_array_equal(written.cell_data["youngs"][0], doc["params"][key])
