"""Which bodies intersect: the slow, named answer a contact error message gives."""

from __future__ import annotations

from collections.abc import Sequence

import ipctk
import numpy as np

from fem3d.physics.contact.geometry import CollisionGeometry, group_chain
from fem3d.physics.contact.obstacles import PlaneObstacle

__all__ = ["intersecting_pairs"]


def intersecting_pairs(geometry: CollisionGeometry, planes: Sequence[PlaneObstacle],
                       q: np.ndarray) -> list[tuple[str, str]]:
    """Names of the (body/obstacle, body/obstacle) pairs that intersect at ``q``.

    Slow (one collision mesh per pair); meant for error messages.
    """
    g = geometry
    q3 = np.asarray(q, dtype=np.float64).reshape(-1, 3)
    out: list[tuple[str, str]] = []
    names = list(g.body_names)
    V = g.collision_vertices(q3)
    groups = g.groups.copy()
    # each mesh obstacle its own group for the names
    for i, off in enumerate(g.mesh_offsets):
        k = g.meshes[i].vertices.shape[0]
        groups[off:off + k] = len(names) + i
    names += [m.name for m in g.meshes]
    present = np.unique(groups)
    faces_group = groups[g.faces[:, 0]]
    for ia, a in enumerate(present):
        for b in present[ia:]:
            if a == b and (a >= len(g.body_names) or not g.self_contact):
                continue
            sel = np.flatnonzero((faces_group == a) | (faces_group == b))
            F = g.faces[sel]
            used = np.unique(F)
            ren = np.full(V.shape[0], -1, dtype=np.int64)
            ren[used] = np.arange(used.size)
            Fs = np.ascontiguousarray(ren[F], dtype=np.int32)
            Vs = np.asfortranarray(V[used])
            cm = ipctk.CollisionMesh(Vs, ipctk.edges(Fs), Fs)
            if a != b:
                cm.can_collide = ipctk.make_connected_components_filter(
                    group_chain(groups[used]))
            if ipctk.has_intersections(cm, Vs):
                out.append((names[a], names[b]))
    for p in planes:
        gaps = p.signed_distance(V[: g.n_surface])
        for b in np.unique(g.groups[: g.n_surface][gaps <= 0]):
            out.append((names[b], p.name))
    return out
