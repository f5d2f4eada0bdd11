"""Adjoint gradients of backward-Euler trajectories against central finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.diff import PositionLoss, simulate, trajectory_gradient
from fem3d.diff.adjoint import Stats, scene_with
from fem3d.diff.damping import DEFAULT_CACHE_BYTES
from fem3d.errors import ParameterError
from fem3d.scene.load import scene_from_arrays
from tests.physics.test_assembly import box_mesh

STEPS = 10
VALUES = {
    "bodies[0].material.E": 1e5,
    "bodies[0].material.nu": 0.3,
    "bodies[0].material.density": 1000.0,
    "bodies[0].damping.rayleigh_mass": 0.5,
    "bodies[0].damping.rayleigh_stiffness": 0.002,
    "bodies[0].velocity": np.array([0.3, 0.0, -0.2]),
    "simulation.gravity": np.array([0.0, -9.81, 0.0]),
}


def box_scene(beta: float):
    X, T = box_mesh(2, 2, 2)
    values = {**VALUES, "bodies[0].damping.rayleigh_stiffness": beta}
    return scene_with(scene_from_arrays(X, T, {
        "simulation.dt": 0.01, "bodies[0].pins": [{"select": {"lowest_y": {"tol": 0.0}}}],
        "pulls": []}),  # the mesh scene's default pull: not differentiated (refused)
        values), values


def total_loss(scene, loss) -> float:
    qs = simulate(scene, STEPS)
    return sum(loss.frame(n, qs[n])[0] for n in range(1, STEPS + 1))


# beta > 0: the damping's dependence on q_n and on E, nu goes through the generated
# d3psi_contract and the PSD projection's derivative (see fem3d.diff.terms).
@pytest.mark.parametrize("beta", [0.0, 0.002])
def test_adjoint_gradient_matches_central_differences(beta: float) -> None:
    scene, values = box_scene(beta)
    rng = np.random.default_rng(0)
    qs = simulate(scene, STEPS)
    loss = PositionLoss({n: qs[n] + 0.01 * rng.normal(size=qs[n].shape)
                         for n in range(1, STEPS + 1)})
    keys = [k for k in VALUES if beta > 0 or "stiffness" not in k]
    value, grads = trajectory_gradient(scene, loss, keys, checkpoint_every=3)
    assert value == pytest.approx(total_loss(scene, loss), rel=1e-12)
    for key in keys:
        v = np.atleast_1d(np.asarray(values[key], dtype=np.float64))
        fd = np.empty(v.size)
        for c in range(v.size):
            # the step: 1e-5 of the value (vectors: of their largest entry, at least 1e-5)
            h = 1e-5 * max(abs(v).max(), 1.0 if v.size > 1 else 0.0)
            plus, minus = v.copy(), v.copy()
            plus[c] += h
            minus[c] -= h
            as_value = (lambda a: a) if v.size > 1 else (lambda a: a[0])
            fd[c] = (total_loss(scene_with(scene, {key: as_value(plus)}), loss)
                     - total_loss(scene_with(scene, {key: as_value(minus)}), loss)) / (2 * h)
        g = np.atleast_1d(grads[key])
        error = np.abs(g - fd).max() / np.abs(fd).max()
        assert error < 1e-6, f"{key}: adjoint {g}, differences {fd}, relative error {error:.2e}"


@pytest.mark.parametrize("beta", [0.0, 0.002])
def test_checkpointing_does_not_change_the_gradient(beta: float) -> None:
    """Every state kept (k = 1), segments recomputed (k = 3: with stiffness damping the
    recomputed steps keep their damping linearizations for the backward steps, or not when
    the byte budget is 0), one segment kept whole (k = 100): the same gradient."""
    scene, _ = box_scene(beta)
    qs = simulate(scene, STEPS)
    loss = PositionLoss({STEPS: qs[STEPS][[5, 7]] + 0.01, 4: qs[4][[5, 7]] - 0.01},
                        vertices=[5, 7])
    keys = ["bodies[0].material.E", "bodies[0].velocity",
            *(["bodies[0].damping.rayleigh_stiffness"] if beta else [])]
    _, every = trajectory_gradient(scene, loss, keys, checkpoint_every=1)
    stats = Stats()
    for k, budget in ((3, DEFAULT_CACHE_BYTES), (3, 0), (100, DEFAULT_CACHE_BYTES)):
        _, other = trajectory_gradient(scene, loss, keys, checkpoint_every=k,
                                       cache_bytes=budget, stats=stats)
        for key in keys:
            np.testing.assert_allclose(every[key], other[key], rtol=1e-12, err_msg=f"k={k}")
    assert stats.recomputed_steps == 2 * 6  # steps 1, 2, 4, 5, 7, 8 (9, 10: the last segment)
    assert (stats.peak_damping_bytes > 0) == (beta > 0)


def test_unknown_parameter_is_refused() -> None:
    scene, _ = box_scene(0.0)
    with pytest.raises(ParameterError, match="bodies\\[0\\].pins"):
        trajectory_gradient(scene, PositionLoss({1: np.zeros((27, 3))}), ["bodies[0].pins"])


def test_scripted_pulls_are_refused_not_ignored() -> None:
    """A run applies the scene's scripted pulls; a gradient without them would be of another
    trajectory, so the adjoint refuses them by name."""
    from fem3d.scene import apply_overrides

    scene, _ = box_scene(0.0)
    pulled = apply_overrides(scene, {"pulls": [{"select": {"vertices": [26]},
                                                "target": [1.5, 1.5, 1.5],
                                                "duration": 0.05}]})
    with pytest.raises(ParameterError, match="scripted pulls"):
        trajectory_gradient(pulled, PositionLoss({1: np.zeros((27, 3))}),
                            ["bodies[0].material.E"])


@pytest.mark.slow  # seven 30-step runs of the bunny: about 10 s
def test_bunny_backward_euler_E_nu_and_velocity_gradients() -> None:
    """The bunny scene (coarser_bunny.mesh: 500 vertices, 1518 tets; no pull) with backward
    Euler over 30 steps, set moving by an initial velocity: dL/dE, dL/dnu (relative steps of
    1e-5) and dL/d(initial velocity) along a random direction (a step of 1e-5 of its size)
    against central differences, to 1e-6."""
    from fem3d.scene import load_scene

    steps = 30
    v0 = np.array([200.0, 0.0, 100.0])
    scene = load_scene("bunny", {"simulation.integrator": "implicit", "pulls": [],
                                 "bodies[0].velocity": list(v0)})
    rng = np.random.default_rng(1)
    qs = simulate(scene, steps)
    loss = PositionLoss({n: qs[n] + rng.normal(size=qs[n].shape) for n in range(3, 31, 3)})

    def total(s):
        q = simulate(s, steps)
        return sum(loss.frame(n, q[n])[0] for n in loss.targets)
    keys = {"bodies[0].material.E": 6e6, "bodies[0].material.nu": 0.4}
    _, grads = trajectory_gradient(scene, loss, [*keys, "bodies[0].velocity"])
    for key, v in keys.items():
        fd = central(lambda h, key=key, v=v: total(scene_with(scene, {key: v + h})), 1e-5 * v)
        assert abs(grads[key] - fd) < 1e-6 * abs(fd), (key, grads[key], fd)
    d = rng.normal(size=3)
    fd = central(lambda h: total(scene_with(scene, {"bodies[0].velocity": v0 + h * d})),
                 1e-5 * np.linalg.norm(v0))
    adjoint = float(grads["bodies[0].velocity"] @ d)
    assert abs(adjoint - fd) < 1e-6 * abs(fd), (adjoint, fd)


# ------------------------------------------------------------------ regions, per-tet fields
def central(f, h: float) -> float:
    """``(f(h) - f(-h)) / 2h``."""
    return (f(h) - f(-h)) / (2 * h)


def noisy_loss(qs, rng, every: int = 1, scale: float = 0.01) -> PositionLoss:
    """Frames of ``qs`` moved by noise: a loss away from its minimum."""
    return PositionLoss({n: qs[n] + scale * rng.normal(size=qs[n].shape)
                         for n in range(every, len(qs), every)})


def field_scene(base, folder, E_field, tag: str):
    """``base`` on the same box mesh written as ``.vtu`` with a per-tet ``youngs`` array, the
    material's ``E`` taken from it (``cell_fields``)."""
    import meshio

    from fem3d.scene import apply_overrides
    from fem3d.scene.arrays import build_arrays
    a = build_arrays(base)
    path = folder / f"field_{tag}.vtu"
    meshio.write(path, meshio.Mesh(a.X, [("tetra", a.T)], cell_data={"youngs": [E_field]}))
    return apply_overrides(base, {"bodies[0].mesh": str(path),
                                  "bodies[0].material.cell_fields": {"E": "youngs"}})


def test_per_tet_E_field_gradient_matches_differences_along_random_directions(
        tmp_path) -> None:
    """dL/dE per tet (a cell field) against central differences of the loss along random
    directions ``d``: ``E_e (1 +- eps d_e)``, eps = 1e-4 (relative), to 1e-6."""
    scene, _ = box_scene(0.0)
    rng = np.random.default_rng(3)
    E = 1e5 * (1 + 0.5 * rng.random(48))
    base = field_scene(scene, tmp_path, E, "base")
    loss = noisy_loss(simulate(base, STEPS), rng)
    key = "bodies[0].material.cell_fields.E"
    _, grads = trajectory_gradient(base, loss, [key], checkpoint_every=4)
    g = grads[key]
    assert g.shape == (48,)

    def total_at(d):
        return lambda eps: total_loss(field_scene(scene, tmp_path, E * (1 + eps * d),
                                                  f"{eps:+g}"), loss)
    for _ in range(2):
        d = rng.normal(size=48)
        fd = central(total_at(d), 1e-4)
        adjoint = float(g @ (E * d))
        assert abs(adjoint - fd) < 1e-6 * abs(fd), (adjoint, fd)


def two_halves(E1: float, E2: float, *, nx: int = 4, steps: int | None = None):
    """A 2 x 0.5 x 0.5 bar pinned at x = 0 whose half x > 1 is region 0: ``E1`` on the pinned
    half (the body's ``E``), ``E2`` on the free half (``regions[0].E``)."""
    X, T = box_mesh(nx, 1, 1, size=(2.0, 0.5, 0.5))
    return scene_from_arrays(X, T, {
        "pulls": [], "simulation.dt": 0.01, "simulation.gravity": [0.0, -9.81, 0.0],
        **({"simulation.steps": steps} if steps else {}),
        "bodies[0].pins": [{"select": {"box": [[-1, -1, -1], [1e-6, 2, 2]]}}],
        "bodies[0].velocity": [0.0, 0.0, 0.5],
        "bodies[0].material.E": E1, "bodies[0].material.nu": 0.3,
        "bodies[0].material.regions": [{"select": {"box": [[1 - 1e-6, -1, -1], [3, 2, 2]]},
                                        "E": E2}]})


@pytest.mark.parametrize("beta", [0.0, 0.002])
def test_region_gradients_match_central_differences(beta: float) -> None:
    """The body's E (the tets outside the region), the region's own E and the shared nu
    (relative steps of 1e-4) to 1e-6; with stiffness damping too (its derivatives by q_n and
    by E, nu from the generated d3psi_contract and the projection's derivative)."""
    scene = scene_with(two_halves(1e5, 4e5), {"bodies[0].damping.rayleigh_stiffness": beta})
    rng = np.random.default_rng(4)
    loss = noisy_loss(simulate(scene, STEPS), rng)
    keys = {"bodies[0].material.E": 1e5, "bodies[0].material.regions[0].E": 4e5,
            "bodies[0].material.nu": 0.3}
    _, grads = trajectory_gradient(scene, loss, list(keys), checkpoint_every=4)
    for key, v in keys.items():
        h = 1e-4 * v
        fd = central(lambda s, key=key, v=v: total_loss(scene_with(scene, {key: v + s}), loss),
                     h)
        assert abs(grads[key] - fd) < 1e-6 * abs(fd), (key, grads[key], fd)


def test_region_key_without_its_own_value_is_refused() -> None:
    scene = two_halves(1e5, 4e5)
    with pytest.raises(ParameterError, match="regions\\[0\\].nu: the region gives no nu"):
        trajectory_gradient(scene, PositionLoss({1: np.zeros((30, 3))}),
                            ["bodies[0].material.regions[0].nu"])
    with pytest.raises(ParameterError, match="has 1 regions"):
        trajectory_gradient(scene, PositionLoss({1: np.zeros((30, 3))}),
                            ["bodies[0].material.regions[1].E"])


# ------------------------------------------------------------------ moving pins
def pinned_drive(interpolation: str):
    """The box's bottom face driven sideways by a keyframed pin (three keyframes, the last
    after the run ends, so every keyframe moves the trajectory)."""
    scene, _ = box_scene(0.0)
    return apply_pin(scene, {
        "select": {"lowest_y": {"tol": 0.0}},
        "motion": {"interpolation": interpolation, "keyframes": [
            {"t": 0.0}, {"t": 0.04, "translate": [0.05, 0.0, 0.02]},
            {"t": 0.2, "translate": [0.1, 0.03, 0.0]}]}})


def apply_pin(scene, pin: dict):
    from fem3d.scene import apply_overrides
    return apply_overrides(scene, {"bodies[0].pins": [pin]})


@pytest.mark.parametrize("interpolation", ["linear", "smooth"])
def test_pin_keyframe_translation_gradient_matches_central_differences(
        interpolation: str) -> None:
    """dL/d(translate) of each keyframe of a moving pin, per component, against central
    differences with a step of 1e-5 (the box is 1 wide), to 1e-6 of the largest component."""
    from fem3d.scene import apply_overrides

    scene = pinned_drive(interpolation)
    rng = np.random.default_rng(5)
    loss = noisy_loss(simulate(scene, STEPS), rng)
    keys = [f"bodies[0].pins[0].motion.keyframes[{k}].translate" for k in range(3)]
    _, grads = trajectory_gradient(scene, loss, keys, checkpoint_every=3)
    frames = scene.bodies[0].pins[0].motion.keyframes
    for k, key in enumerate(keys):
        fd = np.empty(3)
        for c in range(3):
            def moved(s, k=k, c=c):
                kfs = [f.model_dump(mode="json") for f in frames]
                kfs[k]["translate"][c] += s
                pin = {"select": {"lowest_y": {"tol": 0.0}},
                       "motion": {"interpolation": interpolation, "keyframes": kfs}}
                return total_loss(apply_overrides(scene, {"bodies[0].pins": [pin]}), loss)
            fd[c] = central(moved, 1e-5)
        error = np.abs(grads[key] - fd).max() / np.abs(fd).max()
        assert error < 1e-6, (key, grads[key], fd, error)


@pytest.mark.parametrize("material", ["stvk", "neo_hookean"])
def test_projected_bilinear_derivative_matches_differences_where_indefinite(
        material: str) -> None:
    """``d/dF`` and ``d/dparams`` of ``a^T A_psd(F) b`` (the damping's adjoint) against central
    differences (step 1e-7) of the same projection, on compressed and stretched F where
    ``dP/dF`` is indefinite (the Daleckii-Krein branch) and where it is not."""
    from fem3d.diff.terms import psd_bilinear_vjp
    from fem3d.kernels.dispatch import material_kernels

    k = material_kernels(material, "numpy")
    rng = np.random.default_rng(8)
    m = 40
    F = np.eye(3) + 0.4 * rng.normal(size=(m, 3, 3))
    F[: m // 2] *= rng.uniform(0.4, 0.7, size=(m // 2, 1, 1))  # compressed: indefinite
    F[np.linalg.det(F) < 0, :, 0] *= -1
    a, b = rng.normal(size=(m, 9)), rng.normal(size=(m, 9))
    params = np.tile([3.0, 5.0], (m, 1))
    _, dF, dp = psd_bilinear_vjp(k, F, a, b, (), params)
    indefinite = (np.linalg.eigvalsh(k.d2psi_dF2(F, params).reshape(m, 9, 9)) < 0).any(axis=1)
    assert 0 < indefinite.sum() < m

    def s_at(F_, p_):
        A = k.d2psi_dF2(F_, p_).reshape(m, 9, 9)
        w, V = np.linalg.eigh(A)
        A_psd = np.einsum("eik,ek,ejk->eij", V, np.maximum(w, 0.0), V)
        A_psd[~(w < 0).any(axis=1)] = A[~(w < 0).any(axis=1)]
        return np.einsum("ei,eij,ej->e", a, A_psd, b)
    h = 1e-7
    fd = np.empty((m, 9))
    for i in range(9):
        E = np.zeros(9)
        E[i] = h
        fd[:, i] = (s_at(F + E.reshape(3, 3), params)
                    - s_at(F - E.reshape(3, 3), params)) / (2 * h)
    fd_p = np.stack([(s_at(F, params + h * np.eye(2)[j]) - s_at(F, params - h * np.eye(2)[j]))
                     / (2 * h) for j in range(2)], axis=1)
    for got, ref in ((dF.reshape(m, 9), fd), (dp, fd_p)):
        # per element, relative to its largest entry (a zero row: to the batch's)
        scale = np.maximum(np.abs(ref).max(axis=1), 1e-3 * np.abs(ref).max())[:, None]
        assert (np.abs(got - ref) / scale).max() < 1e-6


def test_damping_linearization_matches_the_kernels_damping_matrix(monkeypatch) -> None:
    """``D(q)`` built from one eigendecomposition per indefinite element (what the backward
    pass keeps) is the C/NumPy kernels' ``matrix_data`` to round-off on a deformed box where
    every element is projected, and the adjoint's products from its eigendecompositions are
    those from ``eigh`` of their own."""
    from fem3d.diff import damping
    from fem3d.diff.adjoint import _prepare
    from fem3d.diff.damping import linearize_damping, psd_elements
    from fem3d.diff.terms import psd_bilinear_vjp

    scene, _ = box_scene(0.002)
    run = _prepare(scene, 1e-11, 1e-16)
    model, term = run.system.model, run.system.loads.damping
    rng = np.random.default_rng(3)
    q = (model.X * [1.0, 0.6, 1.0] + 0.05 * rng.normal(size=model.X.shape)).reshape(-1)
    lin = linearize_damping(term, run.groups, q)
    ref = term.matrix_data(q)
    assert np.abs(lin.data - ref).max() < 1e-12 * np.abs(ref).max()
    (g, els, params, inputs), = run.groups
    bad, values, V = lin.eig[0]
    assert bad.size > els.size // 2
    x = q.reshape(-1, 3)
    F = np.einsum("evc,evj->ecj", x[model.T[els]], model.dphi_dX[els])
    a, b = rng.normal(size=(els.size, 9)), rng.normal(size=(els.size, 9))
    own = psd_bilinear_vjp(g.kernels, F, a, b, inputs, params)
    kept = psd_bilinear_vjp(g.kernels, F, a, b, inputs, params, lin.eig[0])
    for x1, x2 in zip(own, kept, strict=True):
        np.testing.assert_allclose(x1, x2, rtol=1e-10, atol=1e-12 * np.abs(x1).max())
    A = g.kernels.d2psi_dF2(F, *inputs, params).reshape(-1, 9, 9)
    assert not psd_elements(A[bad]).any() and psd_elements(A[:1] * 0 + np.eye(9)).all()
    monkeypatch.setattr(damping, "CHUNK", 7)  # by chunks: the same matrix and elements
    chunked = linearize_damping(term, run.groups, q)
    np.testing.assert_allclose(chunked.data, lin.data, rtol=0, atol=1e-13 * np.abs(ref).max())
    for x1, x2 in zip(chunked.eig[0], lin.eig[0], strict=True):
        np.testing.assert_allclose(x1, x2, rtol=1e-12, atol=1e-12 * np.abs(x2).max())


def test_psd_eigen_decomposes_the_indefinite_blocks(monkeypatch) -> None:
    """The C extension's ``psd_eigen`` (LDL^T test, else tridiagonal QL) against LAPACK on
    indefinite, positive semi-definite, zero and repeated-eigenvalue blocks, n = 1 .. 12; the
    NumPy fallback of :func:`projected_eigen` picks the same blocks."""
    from fem3d.diff import damping
    from fem3d.kernels.backend import c_extension

    ext = c_extension()
    if ext is None or not hasattr(ext, "psd_eigen"):
        pytest.skip("the C extension is not built (or is older than psd_eigen)")
    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 9, 12):
        m = 300
        G = rng.normal(size=(m, n, n))
        A = G + G.transpose(0, 2, 1)
        A[:60] = G[:60] @ G[:60].transpose(0, 2, 1)  # PSD
        A[60:65] = 0.0
        Q = np.linalg.qr(rng.normal(size=(10, n, n)))[0]
        A[65:75] = (Q * np.r_[-1.0, np.ones(n - 1)]) @ Q.transpose(0, 2, 1)  # repeated
        values, V = np.empty((m, n)), np.empty((m, n, n))
        flags = np.empty(m, dtype=np.int32)
        ext.psd_eigen(A, values, V, flags)
        ref = np.linalg.eigvalsh(A)
        np.testing.assert_array_equal(flags == 1, (ref < 0).any(axis=1))
        done = flags > 0
        scale = np.abs(A).max()
        np.testing.assert_allclose(values[done], ref[done], atol=1e-13 * scale)
        back = (V[done] * values[done][:, None, :]) @ V[done].transpose(0, 2, 1)
        np.testing.assert_allclose(back, A[done], atol=1e-13 * scale)
        np.testing.assert_allclose(V[done].transpose(0, 2, 1) @ V[done],
                                   np.broadcast_to(np.eye(n), back.shape), atol=1e-13)
        with monkeypatch.context() as mp:  # the NumPy fallback
            mp.setattr(damping, "c_extension", lambda: None)
            bad, lapack_values, _ = damping.projected_eigen(A)
        np.testing.assert_array_equal(bad, np.flatnonzero(flags == 1))
        np.testing.assert_allclose(lapack_values, values[bad], atol=1e-13 * scale)
        assert np.array_equal(damping.psd_elements(A)[:65], np.ones(65, dtype=bool))
    with pytest.raises(ValueError, match="psd_eigen"):
        ext.psd_eigen(np.zeros(10), np.empty(6), np.empty(18), np.empty(2, dtype=np.int32))
