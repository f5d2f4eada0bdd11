"""The guard on additive CCD: a crossing that starts with two edges 2.5e-11 m apart (the
pile, step 184) is caught, though ipctk 1.6.1's additive CCD alone calls the step free."""

from __future__ import annotations

from pathlib import Path

import ipctk
import numpy as np
import pytest

from fem3d.physics.contact import ContactModel
from fem3d.physics.contact import collisions as contact

MISS = Path(__file__).resolve().parents[3] / "bench" / "results" / \
    "accd_miss_pile_step184.npz"


def crossing_tets():
    """Two tets, each holding one of the recorded edges, at the step's start and end: rest
    positions, end positions, tets, body ids."""
    with np.load(MISS) as z:
        start, end = z["start"], z["end"]
    normal = np.cross(start[1] - start[0], start[3] - start[2])
    normal /= np.linalg.norm(normal)
    side = np.sign((start[2] - start[0]) @ normal)  # the second edge's side of the first

    def tet(p0, p1, away):  # the edge and two vertices 0.1 m off it, away from the other
        mid = 0.5 * (p0 + p1)
        w = np.cross(p1 - p0, away)
        w /= np.linalg.norm(w)
        return [p0, p1, mid + 0.1 * away + 0.05 * w, mid + 0.1 * away - 0.05 * w]

    X = np.array(tet(start[0], start[1], -side * normal) + tet(start[2], start[3], side * normal))
    T = np.array([[0, 1, 2, 3], [4, 5, 6, 7]])
    for t in T:  # positively oriented
        if np.linalg.det(X[t[1:]] - X[t[0]]) < 0:
            t[[2, 3]] = t[[3, 2]]
    X1 = X.copy()
    X1[:4] += end[0] - start[0]  # each tet moves with its edge
    X1[4:] += end[2] - start[2]
    X1[[0, 1, 4, 5]] = end
    return X, X1, T, np.repeat([0, 1], 4)


def test_the_recorded_step_crosses_two_edges() -> None:
    X, X1, T, ids = crossing_tets()
    cm = ContactModel(X, T, body_ids=ids, dhat=1e-3)
    assert not cm.has_intersections(X.reshape(-1))
    assert cm.has_intersections(X1.reshape(-1))
    assert cm.minimum_distance(X.reshape(-1)) < contact.CCD_GUARD_DISTANCE * cm.bbox_diagonal


def test_ccd_stops_the_step_before_the_crossing() -> None:
    X, X1, T, ids = crossing_tets()
    cm = ContactModel(X, T, body_ids=ids, dhat=1e-3)
    a = cm.max_step(X.reshape(-1), X1.reshape(-1))
    assert 0.0 < a < 0.67  # the edges meet at about 0.67 of the step (guard: 0.11)
    assert not cm.has_intersections((X + a * (X1 - X)).reshape(-1))


def test_without_the_guard_additive_ccd_misses_it(monkeypatch: pytest.MonkeyPatch) -> None:
    X, X1, T, ids = crossing_tets()
    with np.load(MISS) as z:
        hit, _ = ipctk.AdditiveCCD().edge_edge_ccd(*z["start"], *z["end"])
    if hit:
        pytest.skip("ipctk's additive CCD catches this crossing itself now: the guard can go")
    monkeypatch.setattr(contact, "CCD_GUARD_DISTANCE", 0.0)
    cm = ContactModel(X, T, body_ids=ids, dhat=1e-3)
    assert cm.max_step(X.reshape(-1), X1.reshape(-1)) == 1.0
