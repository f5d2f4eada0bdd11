"""The solver pattern's widening by contact entries (fem3d.solve.system.System._extend)."""

from __future__ import annotations

import numpy as np
import pytest

from fem3d.physics.constraints import Constraints
from fem3d.physics.model import build_model
from fem3d.solve.system import System
from tests.physics.contact.test_potentials import two_boxes


def _system() -> System:
    X, T, _ = two_boxes(0.01)
    model = build_model(X, T, E=1e5, nu=0.3, rho=1000.0)
    return System(model, Constraints.from_fixed_vertices(X, np.array([0, 1])))


def test_widened_pattern_keeps_every_base_entry_where_a_search_finds_it():
    system = _system()
    nf = system.constraints.n_free
    rng = np.random.default_rng(3)
    for _ in range(3):  # each widening moves the base entries up by the keys inserted below
        keys = rng.integers(0, nf, 40) * nf + rng.integers(0, nf, 40)
        ext = system._extend(keys)
        assert np.array_equal(ext.base_pos, np.searchsorted(ext.keys, system._base_key_array()))
        assert np.array_equal(ext.keys, np.unique(ext.keys))
        r, c = np.divmod(keys, nf)
        assert np.isin(keys, ext.keys).all() and np.isin(c * nf + r, ext.keys).all()
        # structurally symmetric: the direct solver takes System's patterns unchecked
        ones = ext.pattern.copy()
        ones.data[:] = 1.0
        assert (ones != ones.T).nnz == 0
    saved = system.pattern_keys()
    fresh = _system()
    fresh.restore_pattern(saved)  # a checkpoint's pattern: the same keys and positions
    assert np.array_equal(fresh._ext.keys, saved)
    assert np.array_equal(fresh._ext.base_pos, system._ext.base_pos)


def test_locate_reuses_a_kept_answer_for_the_first_keys_exactly():
    system = _system()
    nf = system.constraints.n_free
    rng = np.random.default_rng(5)
    system._extend(rng.integers(0, nf * nf, 30))
    have = system._ext.keys
    inside = have[rng.integers(0, have.size, 50)]
    outside = np.setdiff1d(rng.integers(0, nf * nf, 50), have)[:5]
    first = system._locate(inside)
    both = system._locate(np.concatenate([inside, inside[:7]]))
    assert both[1] and np.array_equal(both[0][:50], first[0])
    assert np.array_equal(both[0], np.searchsorted(have, np.concatenate([inside, inside[:7]])))
    assert not system._locate(np.concatenate([inside, outside]))[1]


def test_contact_entries_outside_the_pattern_are_added_where_they_belong():
    system = _system()
    n = 3 * system.model.n_vertices
    rng = np.random.default_rng(7)
    for _ in range(2):  # the first widens from the mesh's pattern, the second from a wider one
        rows, cols = rng.integers(0, n, 200), rng.integers(0, n, 200)
        vals = rng.standard_normal(200)
        A = system.mass_free
        B = system.add_hessian(A, (rows, cols, vals), 0.5)
        expected = A.toarray()
        r, c = system.constraints._new_index[rows], system.constraints._new_index[cols]
        keep = (r >= 0) & (c >= 0)
        np.add.at(expected, (r[keep], c[keep]), 0.5 * vals[keep])
        assert np.array_equal(B.toarray(), expected)
        assert B.nnz == system._ext.keys.size and system.pattern_covers(rows, cols)


def test_the_c_search_finds_the_positions_numpy_finds(monkeypatch):
    """System._search: the C extension's per-row search against NumPy's search of all keys,
    on the base and on a widened pattern, keys inside, missing, and past the last one."""
    from fem3d.kernels.backend import c_extension

    if c_extension() is None:
        pytest.skip("the C extension is not built")
    import fem3d.solve.system as system_module

    system = _system()
    nf = system.constraints.n_free
    rng = np.random.default_rng(11)
    for widen in (False, True):
        if widen:
            system._extend(rng.integers(0, nf * nf, 40))
        have = system._base_key_array() if system._ext is None else system._ext.keys
        missing = np.setdiff1d(rng.integers(0, nf * nf, 60), have)
        for keys in (have[rng.integers(0, have.size, 80)],
                     np.concatenate([have[:5], missing, [nf * nf - 1, have[-1]]])):
            pos, inside = system._search(have, keys)
            expected = np.minimum(np.searchsorted(have, keys), have.size - 1)
            assert np.array_equal(pos, expected)
            assert inside == bool(np.array_equal(have[expected], keys))
            monkeypatch.setattr(system_module, "c_extension", lambda: None)
            assert np.array_equal(system._search(have, keys)[0], pos)
            assert system._search(have, keys)[1] == inside
            monkeypatch.undo()
        assert not system._search(have, missing)[1]
    with pytest.raises(ValueError, match="outside the"):
        system._search(have, np.array([nf * nf]))


def test_the_pattern_hint_holds_whole_blocks_of_every_pair_within_the_margin():
    """BarrierTerm._pattern_hint: the 3 x 3 blocks of every pair of vertices of a pair of
    primitives within the margin, a superset of ipctk's barrier Hessian there (which leaves
    out its exact zeros: the boxes' faces are axis-aligned)."""
    import ipctk

    from fem3d.physics.contact import ContactModel
    from fem3d.physics.terms.contact import ContactTerm

    X, T, ids = two_boxes(0.01)
    cm = ContactModel(X, T, body_ids=ids, dhat=0.02)
    term = ContactTerm(cm).barrier
    q = X.reshape(-1)
    rows, cols = term._pattern_hint(q)
    n = 3 * X.shape[0]
    hint = np.unique(rows.astype(np.int64) * n + cols)
    V = cm.collision_vertices(q)
    part = cm.collisions.parts[0]
    Vp = part.view(V)
    margin = term.pattern_margin * cm.dhat
    cands = ipctk.Candidates()
    cands.build(part.mesh, Vp, 0.5 * margin)
    col = ipctk.NormalCollisions()
    col.build(cands, part.mesh, Vp, margin)
    H = cm.geometry.to_full_matrix(
        [ipctk.BarrierPotential(margin, 1.0).hessian(col, part.mesh, Vp)])
    exact = np.unique(H.row.astype(np.int64) * n + H.col)
    assert np.isin(exact, hint).all()
    assert hint.size > exact.size  # the Hessian's exact zeros
    r, c = np.divmod(hint, n)
    blocks, counts = np.unique((r // 3) * n + c // 3, return_counts=True)
    assert (counts == 9).all()  # whole 3 x 3 blocks
    vi, vj = np.divmod(blocks, n)
    assert (ids[vi] != ids[vj]).any()  # it couples the two boxes
