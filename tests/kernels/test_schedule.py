"""Threaded fused assembly (fem3d.kernels.schedule): race-free, deterministic, equal to the
serial loop."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.kernels.backend import c_extension
from fem3d.kernels.schedule import PARALLEL_MIN_TETS, Schedule, build_schedule, schedule_for
from fem3d.mesh.tetmesh import box_tet_mesh
from fem3d.physics import assembly
from fem3d.physics.model import build_model

pytestmark = pytest.mark.skipif(c_extension() is None, reason="C extension not built")


def _threads(n: int) -> None:
    c_extension().set_max_threads(n)


@pytest.fixture(autouse=True)
def _restore_threads():
    ext = c_extension()
    before = ext.max_threads() if ext is not None else 1
    yield
    if ext is not None:
        ext.set_max_threads(before)


def _deformed(X: np.ndarray, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return X @ np.array([[1.1, 0.05, 0.0], [0.0, 0.95, 0.1], [0.02, 0.0, 1.05]]).T \
        + 0.01 * rng.standard_normal(X.shape)


@pytest.fixture(scope="module")
def big():
    """A box above the threshold and a deformed state."""
    X, T = box_tet_mesh((24, 16, 15))  # 34,560 tets
    assert len(T) >= PARALLEL_MIN_TETS
    model = build_model(X, T, E=1e5, nu=0.4, rho=1000.0, backend="c")
    return model, _deformed(X)


def _serial(model, kernel: str, q: np.ndarray, index: np.ndarray, n_out: int) -> np.ndarray:
    """The serial loop: writable copies of T and index get no schedule."""
    out = np.zeros(n_out)
    getattr(model.mat, f"{kernel}_assemble")(q, model.T.copy(), model.dphi_dX, model.vol,
                                             model.params, index.copy(), out)
    return out


def _race_free(schedule, index: np.ndarray) -> bool:
    """No entry of out is written by two blocks of one colour."""
    k = index.size // schedule.order.size
    colour = np.repeat(schedule.element_colours().astype(np.int64), k)
    block = np.repeat(schedule.element_blocks().astype(np.int64), k)
    slot = index.reshape(-1).astype(np.int64)
    # (colour, slot, block) as one integer key: far faster than np.unique(axis=1)
    n_slots, n_blocks = int(slot.max()) + 1, int(block.max()) + 1
    pairs = _distinct((colour * n_slots + slot) * n_blocks + block)
    writers = _distinct(pairs // n_blocks)  # (colour, slot) with one or more blocks
    return writers.size == pairs.size


def _distinct(keys: np.ndarray) -> np.ndarray:
    """The sorted distinct values (``np.unique``'s hash path is ~10x slower on 5M keys)."""
    keys = np.sort(keys)
    return keys[np.r_[True, keys[1:] != keys[:-1]]]


def test_threaded_equals_serial_and_is_independent_of_thread_count(big) -> None:
    model, q = big
    cases = [("energy", model.energy_slots, 1), ("gradient", model.dof_slots, model.n_dofs),
             ("hessian", model.scatter, model.nnz)]
    for kernel, index, n_out in cases:
        schedule = schedule_for(model.T, index, n_out)
        assert schedule is not None and schedule.n_blocks > 1, kernel
        results = []
        for n in (1, 2, 1):
            _threads(n)
            out = np.zeros(n_out)
            getattr(model.mat, f"{kernel}_assemble")(q, model.T, model.dphi_dX, model.vol,
                                                     model.params, index, out)
            results.append(out)
        np.testing.assert_array_equal(results[0], results[1])  # bit for bit
        np.testing.assert_array_equal(results[0], results[2])
        serial = _serial(model, kernel, q, index, n_out)
        scale = np.abs(serial).max()
        np.testing.assert_allclose(results[1], serial, rtol=1e-12, atol=1e-12 * scale)
    # the public entry points take the same path
    _threads(2)
    h = assembly.hessian_data(model, q)
    np.testing.assert_allclose(h, _serial(model, "hessian", q, model.scatter, model.nnz),
                               rtol=1e-12, atol=1e-12 * np.abs(h).max())
    e = assembly.potential_energy(model, q)
    assert e == pytest.approx(float(_serial(model, "energy", q, model.energy_slots, 1)[0]),
                              rel=1e-12)


def test_schedules_are_race_free_and_cover_every_element(big) -> None:
    model, _ = big
    for index, n_out in ((model.dof_slots, model.n_dofs), (model.scatter, model.nnz)):
        s = build_schedule(model.T, index, n_out)
        assert np.array_equal(np.sort(s.order), np.arange(model.n_tets))
        assert s.n_colours <= 8 and s.n_blocks >= 2 * s.n_colours
        assert _race_free(s, index)
        assert not _race_free(Schedule(s.order, s.blocks, np.array([0, s.n_blocks])), index)
    # the CSR map's schedule also keeps blocks of one colour vertex-disjoint
    s = build_schedule(model.T, model.scatter, model.nnz)
    colour, block = s.element_colours(), s.element_blocks()
    for c in range(s.n_colours):
        e = np.flatnonzero(colour == c)
        n_vertices = len(model.X)
        pairs = _distinct(np.repeat(block[e].astype(np.int64), 4) * n_vertices
                          + model.T[e].reshape(-1))  # (block, vertex) as one key
        assert _distinct(pairs % n_vertices).size == pairs.size


def test_a_shuffled_element_order_is_still_scheduled_and_correct(big) -> None:
    model, q = big
    rng = np.random.default_rng(0)
    perm = rng.permutation(model.n_tets)
    shuffled = build_model(model.X, model.T[perm], E=1e5, nu=0.4, rho=1000.0, backend="c")
    s = schedule_for(shuffled.T, shuffled.scatter, shuffled.nnz)
    assert s is not None and _race_free(s, shuffled.scatter)
    _threads(2)
    g = assembly.assemble_gradient(shuffled, q)
    np.testing.assert_allclose(g, assembly.assemble_gradient(model, q), rtol=1e-10,
                               atol=1e-12 * np.abs(g).max())
    h = assembly.assemble_hessian(shuffled, q)
    h0 = assembly.assemble_hessian(model, q)
    assert abs(h - h0).max() <= 1e-12 * abs(h0).max()
    assert assembly.potential_energy(shuffled, q) == pytest.approx(
        assembly.potential_energy(model, q), rel=1e-12)


def test_small_meshes_writable_maps_and_shared_sinks_stay_serial(big) -> None:
    model, _ = big
    X, T = box_tet_mesh((4, 4, 4))
    small = build_model(X, T, E=1e5, nu=0.4, rho=1000.0, backend="c")
    assert schedule_for(small.T, small.scatter, small.nnz) is None
    assert schedule_for(model.T.copy(), model.scatter, model.nnz) is None  # writable
    # every element writing one shared (sink) entry among others: no colouring exists
    sink = model.scatter.copy()
    sink[::144] = model.nnz
    assert build_schedule(model.T, sink, model.nnz + 1) is None
    # an entry outside out: no schedule, the serial loop reports it
    assert build_schedule(model.T, model.scatter, model.nnz - 1) is None


def test_bad_indices_are_reported_from_the_threads(big) -> None:
    model, q = big
    ext = c_extension()
    s = build_schedule(model.T, model.dof_slots, model.n_dofs)
    block = s.element_blocks()
    colour = s.element_colours()
    # two bad elements in different blocks of colour 0: the lower one is named
    e0 = np.flatnonzero(colour == 0)
    first, second = int(e0[block[e0] == block[e0].max()][0]), int(e0[0])
    assert block[first] != block[second]
    args = (q, model.dphi_dX, model.vol, model.params)
    for n in (1, 2):
        _threads(n)
        T = model.T.copy()
        T[[first, second], 2] = model.n_vertices
        with pytest.raises(ValueError, match=f"vertex index .* element {min(first, second)} "):
            ext.neo_hookean_gradient_assemble(args[0], T, *args[1:], model.dof_slots,
                                              np.zeros(model.n_dofs), *s.arrays())
        index = model.dof_slots.copy()
        index[[first, second], 5] = model.n_dofs
        with pytest.raises(ValueError, match=f"index .* element {min(first, second)} "):
            ext.neo_hookean_gradient_assemble(args[0], model.T, *args[1:], index,
                                              np.zeros(model.n_dofs), *s.arrays())
        # the energy (summed per block) reports the same way
        es = build_schedule(model.T, model.energy_slots, 1)
        with pytest.raises(ValueError, match=f"vertex index .* element {min(first, second)} "):
            ext.neo_hookean_energy_assemble(args[0], T, *args[1:], model.energy_slots,
                                            np.zeros(1), *es.arrays())
    order = s.order.copy()
    order[7] = model.n_tets
    with pytest.raises(ValueError, match="order has an element outside"):
        ext.neo_hookean_gradient_assemble(*args[:1], model.T, *args[1:], model.dof_slots,
                                          np.zeros(model.n_dofs), order, s.blocks, s.colours)
    bad_blocks = s.blocks.copy()
    bad_blocks[-1] -= 1
    with pytest.raises(ValueError, match="schedule does not fit"):
        ext.neo_hookean_gradient_assemble(*args[:1], model.T, *args[1:], model.dof_slots,
                                          np.zeros(model.n_dofs), s.order, bad_blocks, s.colours)
    with pytest.raises(ValueError, match="int64"):
        ext.neo_hookean_gradient_assemble(*args[:1], model.T, *args[1:], model.dof_slots,
                                          np.zeros(model.n_dofs), s.order.astype(np.int32),
                                          s.blocks, s.colours)
