"""A share of a scene in its own numbering: the vertices of its tets alone.

One MPI rank's share of a distributed run (:mod:`fem3d.parallel`) holds the vertices of its
own tets (the ones it owns and the ghosts it shares with other ranks), numbered in increasing
scene order, and every vector it steps is that long. :class:`LocalNumbering` carries what
:func:`fem3d.scene.build.build` selects on the whole scene (pins, motions, pulls, loads,
initial velocities) into that numbering; selections are made on the whole scene first, so a
rank selects what one process selects.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from fem3d.physics.springs import Pull
from fem3d.scene.arrays import ElementBlock, SceneArrays, ScriptedPull

__all__ = ["LocalNumbering", "split_tets"]


@dataclass(frozen=True, eq=False)
class LocalNumbering:
    """The vertices ``vertices`` (sorted scene ids) of the tets ``tets`` as ``0, 1, ...``.

    Attributes
    ----------
    tets : (m,) int64
        The share's tets (sorted scene ids).
    vertices : (k,) int64
        Their vertices (sorted scene ids).
    """

    tets: np.ndarray
    vertices: np.ndarray

    @classmethod
    def of_tets(cls, T: np.ndarray, tets: np.ndarray) -> LocalNumbering:
        """The numbering of the vertices of ``T[tets]``."""
        return cls(tets, np.unique(T[tets]))

    def local(self, ids: np.ndarray) -> np.ndarray:
        """Local numbers of the scene vertex ids ``ids`` (any shape), -1 where not held."""
        ids = np.asarray(ids, dtype=np.int64)
        pos = np.searchsorted(self.vertices, ids)
        pos = np.minimum(pos, max(self.vertices.size - 1, 0))
        held = self.vertices.size > 0
        hit = (self.vertices[pos] == ids) if held else np.zeros(ids.shape, dtype=bool)
        return np.where(hit, pos, -1)

    def dofs(self, full: np.ndarray) -> np.ndarray:
        """``(3k,)`` the local DOFs' entries of a scene-long DOF vector ``(3 n_scene,)``."""
        return np.asarray(full).reshape(-1, 3)[self.vertices].reshape(-1)

    def dof_ids(self, dofs: np.ndarray) -> np.ndarray:
        """Local numbers of scene DOF ids (``3 vertex + axis``) held here (others dropped),
        in the order given."""
        dofs = np.asarray(dofs, dtype=np.int64)
        v = self.local(dofs // 3)
        keep = v >= 0
        return 3 * v[keep] + dofs[keep] % 3

    def fixed_slots(self, whole_fixed: np.ndarray, local_fixed: np.ndarray) -> np.ndarray:
        """``(len(whole_fixed),) int64``: each of the scene's pinned vertices' slot among the
        local pinned vertices ``local_fixed``, -1 where not held."""
        v = self.local(whole_fixed)
        out = np.full(v.shape, -1, dtype=np.int64)
        held = v >= 0
        out[held] = np.searchsorted(local_fixed, v[held])
        return out

    def pull(self, pull: Pull, owned: np.ndarray) -> Pull:
        """The springs of ``pull`` whose vertex this share holds and owns (``owned``: per
        local vertex), in local numbers (possibly none)."""
        v = self.local(pull.vertices)
        keep = v >= 0
        keep[keep] = owned[v[keep]]
        k = pull.k if np.ndim(pull.k) == 0 else np.asarray(pull.k)[keep]
        return Pull(v[keep], pull.targets[keep], k)

    def arrays(self, a: SceneArrays, owned: np.ndarray) -> SceneArrays:
        """``a`` on the share: its rest positions, tets, initial velocities, pins and the
        scripted pulls of the vertices it owns (``owned``: per local vertex); no skin (a
        distributed run writes the surface of its tets).

        ``a`` must be of one element block (mixed elements are refused on ranks)."""
        X = a.X[self.vertices]
        T = self.local(a.T[self.tets])
        bodies_v = [slice(*np.searchsorted(self.vertices, [s.start, s.stop]).tolist())
                    for s in a.body_vertices]
        bodies_t = [slice(*np.searchsorted(self.tets, [s.start, s.stop]).tolist())
                    for s in a.body_tets]
        fixed = self.local(a.fixed)
        fixed = fixed[fixed >= 0]
        fixed_dofs = None if a.fixed_dofs is None else self.dof_ids(a.fixed_dofs)
        pulls = [ScriptedPull(self.pull(p.pull, owned), p.start, p.duration) for p in a.pulls]
        block = a.blocks[0]
        blocks = (ElementBlock(block.element, T, slice(0, T.shape[0]), block.bodies),)
        return replace(a, X=X, T=T, v0=a.v0[self.vertices], fixed=fixed, pulls=pulls,
                       body_vertices=bodies_v, body_tets=bodies_t, skin_V=None, skin_F=None,
                       skin_bodies=[], skin_identity=[], fixed_dofs=fixed_dofs, blocks=blocks)


def split_tets(T: np.ndarray, tet_rank: np.ndarray, n_parts: int
               ) -> tuple[list[np.ndarray], np.ndarray]:
    """Each part's tets (sorted) of a partition ``tet_rank`` ``(m,)`` into ``n_parts``, and
    each vertex's owner: the lowest part among its tets (``n_parts`` for a vertex of none).
    """
    order = np.argsort(tet_rank, kind="stable")  # within a part: increasing tet
    bounds = np.r_[0, np.cumsum(np.bincount(tet_rank, minlength=n_parts))]
    n = int(T.max(initial=-1)) + 1
    owner = np.full(n, n_parts, dtype=np.int64)
    np.minimum.at(owner, T.reshape(-1), np.repeat(tet_rank, T.shape[1]))
    return [order[bounds[r]:bounds[r + 1]] for r in range(n_parts)], owner
