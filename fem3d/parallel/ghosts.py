"""The entries of a rank-local vector that other ranks hold too, and their exchange.

A rank of a distributed run holds the entries of its own tets' vertices (owned and ghosts),
numbered locally in increasing global id. :class:`Ghosts` finds, from this rank's ids alone,
which other ranks hold each of them (a rendezvous: each id goes to a directory rank,
``id % size``, which tells every holder the others), then sums the ranks' partial values of
the shared entries (:meth:`Ghosts.assemble`) or gives the ghosts their owner's values
(:meth:`Ghosts.complete`), one exchange each. Memory and traffic are O(local entries) per
rank: no array of the global length.

Deterministic: a shared entry's total is summed in increasing rank order, so every holder
gets the same bits, in every run.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["Ghosts"]


class Ghosts:
    """The entries of a rank-local vector that other ranks hold too.

    Made by :meth:`build` (collective).

    Attributes
    ----------
    ids : (k,) int
        The global ids of this rank's local entries, as given (sorted, unique).
    owner : (k,) int64
        The lowest rank holding each id.
    owned : (k,) bool
        ``owner == rank``.
    """

    def __init__(self, comm: Any, ids: np.ndarray, owner: np.ndarray,
                 neighbours: dict[int, np.ndarray]) -> None:
        self.comm = comm
        self.ids = ids
        self.rank = comm.Get_rank()
        self.size = comm.Get_size()
        self.owner = owner
        self.owned = owner == self.rank
        for a in (self.owner, self.owned):
            a.setflags(write=False)
        # per neighbour rank (increasing): the local positions of the ids it holds too, in
        # increasing global id (the order the neighbour uses for the same ids)
        self._neighbours = neighbours
        shared = np.zeros(ids.size, dtype=bool)
        for pos in neighbours.values():
            shared[pos] = True
        self._shared = np.flatnonzero(shared)
        # complete: to each neighbour the shared entries this rank owns; from each, those it
        # owns
        self._send = {r: pos[self.owned[pos]] for r, pos in neighbours.items()}
        self._recv = {r: pos[owner[pos] == r] for r, pos in neighbours.items()}

    @classmethod
    def build(cls, comm: Any, ids: np.ndarray) -> Ghosts:
        """Collective: which other ranks hold each of this rank's ids.

        Parameters
        ----------
        comm : mpi4py.MPI.Comm
        ids : (k,) int
            The global ids of this rank's local entries (e.g. global DOF ids ``3 * v + c``),
            sorted and unique.

        Returns
        -------
        Ghosts

        Raises
        ------
        ValueError
            ``ids`` not a 1-D integer array, sorted and unique.
        """
        ids = np.asarray(ids)
        if ids.ndim != 1 or not np.issubdtype(ids.dtype, np.integer):
            raise ValueError(f"Ghosts ids must be a 1-D integer array, got {ids.dtype} of "
                             f"shape {ids.shape}")
        if ids.size > 1 and not (np.diff(ids) > 0).all():
            raise ValueError("Ghosts ids must be sorted and unique")
        size, rank = comm.Get_size(), comm.Get_rank()
        owner = np.full(ids.size, rank, dtype=np.int64)
        if size == 1:
            return cls(comm, ids, owner, {})
        gid = ids.astype(np.int64)
        # 1. each id to its directory rank
        directory = gid % size
        by_dir = np.argsort(directory, kind="stable")  # within a directory: increasing id
        got_from, got_ids = _exchange_by_rank(comm, directory[by_dir], gid[by_dir])
        # 2. the directory: for each id held by several ranks, each holder gets a pair
        # (id, other holder) per other holder
        by_id = np.lexsort((got_from, got_ids))
        got_ids, got_from = got_ids[by_id], got_from[by_id]
        first = np.r_[True, got_ids[1:] != got_ids[:-1]] if got_ids.size else \
            np.zeros(0, dtype=bool)
        starts = np.flatnonzero(first)
        sizes = np.diff(np.r_[starts, got_ids.size])
        group = np.cumsum(first) - 1  # each received id's group
        g = sizes[group]
        multi = g > 1
        i = np.flatnonzero(multi)  # each entry of a shared id, paired with its group's
        gi = g[i]
        total = int(gi.sum())
        offset = np.arange(total) - np.repeat(np.cumsum(gi) - gi, gi)
        j = np.repeat(starts[group[i]], gi) + offset
        i = np.repeat(i, gi)
        keep = i != j
        i, j = i[keep], j[keep]
        to = got_from[i]
        by_to = np.argsort(to, kind="stable")
        _, pairs_id, pairs_other = _exchange_by_rank(comm, to[by_to], got_ids[i][by_to],
                                                     got_from[j][by_to])
        # 3. each holder: the owner and, per other holder, the shared positions
        pos = np.searchsorted(gid, pairs_id)
        np.minimum.at(owner, pos, pairs_other)
        by_rank = np.lexsort((pos, pairs_other))
        pos, other = pos[by_rank], pairs_other[by_rank]
        cut = np.flatnonzero(np.r_[True, other[1:] != other[:-1]]) if other.size else \
            np.zeros(0, dtype=np.int64)
        bounds = np.r_[cut, other.size]
        neighbours = {int(other[a]): pos[a:b]
                      for a, b in zip(bounds[:-1], bounds[1:], strict=True)}
        return cls(comm, ids, owner, neighbours)

    # -- the exchanges ----------------------------------------------------------------------
    def _check(self, values: np.ndarray) -> np.ndarray:
        values = np.asarray(values)
        if values.ndim not in (1, 2) or values.shape[0] != self.ids.size:
            raise ValueError(f"Ghosts: values of shape {values.shape}, expected "
                             f"({self.ids.size},) or ({self.ids.size}, c)")
        return values

    def assemble(self, partial: np.ndarray) -> np.ndarray:
        """Collective: each entry's total over every rank holding it.

        Parameters
        ----------
        partial : (k,) or (k, c) float64
            This rank's contributions (rows for 2-D).

        Returns
        -------
        (k,) or (k, c) float64
            A new array: a shared entry's total ``v_r0 + v_r1 + ...`` summed left to right in
            increasing rank order ``r0 < r1 < ...`` of its holders (the same bits on every
            holder); an entry this rank alone holds as given, bit for bit.
        """
        partial = self._check(partial)
        out = partial.copy()
        if self.size == 1:
            return out
        received = self._swap(partial, self._neighbours, self._neighbours)
        # the holders' values rank by rank, this rank's in its place; an entry's first
        # holder's value starts its sum (no 0.0 + v: -0.0 stays -0.0)
        started = np.zeros(out.shape[0], dtype=bool)
        mine = self._shared
        sources = [(r, self._neighbours[r], received[r]) for r in received]
        sources.append((self.rank, mine, partial[mine]))
        for _, pos, vals in sorted(sources, key=lambda s: s[0]):
            new = ~started[pos]
            out[pos[new]] = vals[new]
            out[pos[~new]] += vals[~new]
            started[pos] = True
        return out

    def complete(self, values: np.ndarray) -> np.ndarray:
        """Collective: each entry takes its owner's value.

        Parameters
        ----------
        values : (k,) or (k, c)
            Any dtype; only the owned entries' values are read.

        Returns
        -------
        (k,) or (k, c)
            A new array: owned entries unchanged, ghosts with their owner's bits.
        """
        values = self._check(values)
        out = values.copy()
        if self.size == 1:
            return out
        received = self._swap(values, self._send, self._recv)
        for r, vals in received.items():
            out[self._recv[r]] = vals
        return out

    def _swap(self, values: np.ndarray, send: dict[int, np.ndarray],
              recv: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """One ``Alltoallv``: ``values[send[r]]`` to each rank ``r``; from each rank ``r``,
        ``recv[r].size`` rows (in the sender's order: increasing global id)."""
        width = int(np.prod(values.shape[1:], dtype=np.int64))
        ranks = sorted(send)
        buf = np.ascontiguousarray(
            np.concatenate([values[send[r]] for r in ranks]) if ranks else values[:0])
        send_counts = np.zeros(self.size, dtype=np.int64)
        recv_counts = np.zeros(self.size, dtype=np.int64)
        for r in ranks:
            send_counts[r] = send[r].size * width
            recv_counts[r] = recv[r].size * width
        out = np.empty((int(recv_counts.sum()) // max(width, 1), *values.shape[1:]),
                       dtype=values.dtype)
        # the buffers' datatype is their dtype's (mpi4py reads it from the buffer)
        self.comm.Alltoallv([buf, (send_counts, _displacements(send_counts))],
                            [out, (recv_counts, _displacements(recv_counts))])
        bounds = np.r_[0, np.cumsum(recv_counts[ranks]) // max(width, 1)]
        return {r: out[bounds[n]:bounds[n + 1]] for n, r in enumerate(ranks)}


def _displacements(counts: np.ndarray) -> np.ndarray:
    return np.r_[0, np.cumsum(counts)[:-1]].astype(np.int64)


def _exchange_by_rank(comm: Any, dest: np.ndarray, *columns: np.ndarray
                      ) -> tuple[np.ndarray, ...]:
    """Rows of the int64 ``columns`` to the ranks ``dest`` (sorted by ``dest``), one
    ``Alltoallv``. Returns the rows this rank got, by source rank: ``(source, *columns)``."""
    size = comm.Get_size()
    counts = np.bincount(dest, minlength=size).astype(np.int64)
    got = np.empty(size, dtype=np.int64)
    comm.Alltoall(counts, got)
    width = len(columns)
    payload = np.ascontiguousarray(np.stack(columns, axis=1), dtype=np.int64)
    out = np.empty((int(got.sum()), width), dtype=np.int64)
    comm.Alltoallv([payload, (counts * width, _displacements(counts * width))],
                   [out, (got * width, _displacements(got * width))])
    return (np.repeat(np.arange(size, dtype=np.int64), got),
            *(out[:, c] for c in range(width)))
