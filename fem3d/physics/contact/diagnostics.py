"""Which bodies intersect: the slow, named answer a contact error message gives."""

from __future__ import annotations

from typing import TYPE_CHECKING

import ipctk
import numpy as np

if TYPE_CHECKING:
    from fem3d.physics.contact.model import ContactModel

__all__ = ["group_chain", "intersecting_pairs"]


def intersecting_pairs(model: ContactModel, q: np.ndarray) -> list[tuple[str, str]]:
    """Names of the (body/obstacle, body/obstacle) pairs that intersect at ``q``.

    Slow (one collision mesh per pair); meant for error messages.
    """
    q3 = np.asarray(q, dtype=np.float64).reshape(-1, 3)
    out: list[tuple[str, str]] = []
    names = list(model.body_names)
    V = model.collision_vertices(q3)
    groups = model._groups.copy()
    # each mesh obstacle its own group for the names
    for i, off in enumerate(model._mesh_offsets):
        k = model.meshes[i].vertices.shape[0]
        groups[off:off + k] = len(names) + i
    names += [m.name for m in model.meshes]
    present = np.unique(groups)
    faces_group = groups[model.faces[:, 0]]
    for ia, a in enumerate(present):
        for b in present[ia:]:
            if a == b and (a >= len(model.body_names) or not model.self_contact):
                continue
            sel = np.flatnonzero((faces_group == a) | (faces_group == b))
            F = model.faces[sel]
            used = np.unique(F)
            ren = np.full(V.shape[0], -1, dtype=np.int64)
            ren[used] = np.arange(used.size)
            Fs = np.ascontiguousarray(ren[F], dtype=np.int32)
            Vs = np.asfortranarray(V[used])
            cm = ipctk.CollisionMesh(Vs, ipctk.edges(Fs), Fs)
            if a != b:
                ga = groups[used]
                cm.can_collide = ipctk.make_connected_components_filter(
                    group_chain(ga))
            if ipctk.has_intersections(cm, Vs):
                out.append((names[a], names[b]))
    for p in model.planes:
        gaps = p.signed_distance(V[: model.n_surface])
        for b in np.unique(model._groups[: model.n_surface][gaps <= 0]):
            out.append((names[b], p.name))
    return out


def group_chain(groups: np.ndarray) -> np.ndarray:
    """Synthetic triangles ``(k, 3) int32`` that connect each group's vertices (a fan; a
    degenerate triangle for a pair): one connected component per group."""
    tris = [np.zeros((0, 3), dtype=np.int64)]
    for g in np.unique(groups):
        ids = np.flatnonzero(groups == g)
        if ids.size >= 3:
            tris.append(np.stack([np.full(ids.size - 2, ids[0]), ids[1:-1], ids[2:]],
                                 axis=1))
        elif ids.size == 2:
            tris.append(np.array([[ids[0], ids[1], ids[1]]]))
    return np.ascontiguousarray(np.concatenate(tris), dtype=np.int32)
