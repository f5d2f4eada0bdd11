"""Race-free schedules that let the fused C assembly loops (``<kernel>_assemble``) use threads.

A fused loop adds every element's output into ``out[index[e, :]]``. Two threads may work at
once only on elements that write disjoint entries of ``out``. A :class:`Schedule` splits the
elements into blocks of consecutive elements and colours the blocks (greedily, in C: one pass
over ``index``) so that no two blocks of one colour write one entry; the C loop then runs the
colours one after the other and the blocks of a colour in parallel, each block's elements in
order. Every entry of ``out`` therefore receives its terms in the same order whatever the
number of threads: results are identical on 1, 2 or 16 threads (they differ from the serial
element order only by round-off). Outputs of at most ``PRIVATE_MAX_OUT`` entries (the
energy's one) are summed per block instead, and the block sums added in block order.

A schedule is built once per ``(T, index)`` pair (read-only arrays, such as a model's maps)
and reused (:func:`schedule_for`); meshes below :data:`PARALLEL_MIN_TETS` tets keep the serial
loop, so small scenes are bit-identical to the serial path. When the mesh's element order
needs too many colours (elements in random order), the blocks are taken along a reverse
Cuthill-McKee order of the vertices instead (the schedule's order only; the mesh is unchanged).

Threads: each fused kernel runs on the count :func:`fem3d.kernels.threads.adaptive` chose for
it from the times of its first calls (one thread or OpenMP's count, ``OMP_NUM_THREADS``; the
environment variable ``FEM3D_THREADS`` forces one), passed to the C loop.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from fem3d.kernels.backend import c_extension

__all__ = ["PARALLEL_MIN_TETS", "Schedule", "build_schedule", "schedule_for"]

#: Meshes with fewer tets use the serial loop (today's element order, bit for bit, so the
#: classic scenes are unchanged). Measured on the shared 2-core machine
#: (``python -m bench.assembly_threads --below-threshold``): two threads gain 1.8-1.9x from
#: 4e4 tets, only 1.4x on the gradient at 1e4, and fall to 0.05-0.5x below 1e4 whenever other
#: processes hold the cores (each barrier then waits for a descheduled thread).
PARALLEL_MIN_TETS = 32768
#: Blocks per mesh at most, and elements per block at least (fixed: not the thread count, so
#: that the summation order does not depend on it).
MAX_BLOCKS = 256
MIN_BLOCK = 1024
#: A colouring with more colours than this tries the reverse Cuthill-McKee order.
GOOD_COLOURS = 8


@dataclass(frozen=True, eq=False)
class Schedule:
    """Blocks of elements in colour order, for the fused C loops.

    Attributes
    ----------
    order : (m,) int64
        A permutation of the elements: block ``b`` is ``order[blocks[b]:blocks[b + 1]]``.
    blocks : (n_blocks + 1,) int64
        Offsets into ``order``, rising from 0 to ``m``.
    colours : (n_colours + 1,) int64
        Offsets into the blocks, rising from 0 to ``n_blocks``: colour ``c`` is blocks
        ``colours[c] ... colours[c + 1] - 1``, no two of which write one entry of ``out``
        (one colour: a small output summed per block).
    """

    order: np.ndarray
    blocks: np.ndarray
    colours: np.ndarray

    @property
    def n_blocks(self) -> int:
        """Number of blocks."""
        return int(self.blocks.size - 1)

    @property
    def n_colours(self) -> int:
        """Number of colours (passes over the mesh)."""
        return int(self.colours.size - 1)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(order, blocks, colours)``: the trailing arguments of a fused C kernel."""
        return self.order, self.blocks, self.colours

    def element_colours(self) -> np.ndarray:
        """``(m,) int64`` colour of every element (for checks)."""
        per_block = np.repeat(np.arange(self.n_colours), np.diff(self.colours))
        colour = np.empty(self.order.size, dtype=np.int64)
        colour[self.order] = np.repeat(per_block, np.diff(self.blocks))
        return colour

    def element_blocks(self) -> np.ndarray:
        """``(m,) int64`` block of every element (for checks)."""
        block = np.empty(self.order.size, dtype=np.int64)
        block[self.order] = np.repeat(np.arange(self.n_blocks), np.diff(self.blocks))
        return block


def _block_starts(m: int) -> np.ndarray:
    size = max(MIN_BLOCK, -(-m // MAX_BLOCKS))
    return np.append(np.arange(0, m, size, dtype=np.int64), np.int64(m))


def _rcm_order(T: np.ndarray) -> np.ndarray:
    """Elements sorted by their first vertex in reverse Cuthill-McKee order (a banded sweep
    through the mesh whatever its numbering)."""
    n, k = int(T.max()) + 1, T.shape[1]  # k nodes per element
    rows = np.repeat(T, k, axis=1).reshape(-1)
    cols = np.tile(T, (1, k)).reshape(-1)
    graph = sp.csr_matrix((np.ones(rows.size, dtype=np.int8), (rows, cols)), shape=(n, n))
    perm = reverse_cuthill_mckee(graph, symmetric_mode=True)
    rank = np.empty(n, dtype=np.int64)
    rank[perm] = np.arange(n)
    return np.argsort(rank[T].min(axis=1), kind="stable").astype(np.int64)


def build_schedule(T: np.ndarray, index: np.ndarray, n_out: int, *,
                   min_tets: int = PARALLEL_MIN_TETS) -> Schedule | None:
    """A race-free schedule of the fused loop over ``T`` writing ``out[index]``.

    Parameters
    ----------
    T : (m, k) int64
        The elements' nodes (only their number, and the vertex graph when the element order
        colours badly, are used).
    index : (m, k) int
        Destination of every element output entry, in ``[0, n_out)``.
    n_out : int
        Length of ``out``.
    min_tets : int, optional
        Smaller meshes get no schedule (the serial loop).

    Returns
    -------
    Schedule or None
        None below ``min_tets`` tets, without the C extension, for an ``index`` with an entry
        outside ``[0, n_out)`` (the serial loop reports it), or when no colouring with at most
        32 colours is found (every block writes one shared entry).
    """
    ext = c_extension()
    T = np.asarray(T)
    m = int(T.shape[0])
    if ext is None or m < max(min_tets, 1):
        return None
    index = np.ascontiguousarray(index, dtype=np.int32).reshape(-1)
    if index.size % m:
        raise ValueError(f"index has {index.size} entries, not a multiple of m = {m}")
    starts = _block_starts(m)
    n_blocks = starts.size - 1
    if n_out <= ext.PRIVATE_MAX_OUT:  # summed per block: any blocks will do
        return _frozen(np.arange(m, dtype=np.int64), starts, np.array([0, n_blocks]))
    best: tuple[int, np.ndarray, np.ndarray] | None = None
    for make_order in (lambda: np.arange(m, dtype=np.int64), lambda: _rcm_order(T)):
        order = make_order()
        colour = np.empty(n_blocks, dtype=np.int32)
        try:
            n_colours = ext.colour_blocks(index, order, starts, int(n_out), colour)
        except ValueError:
            return None  # an entry outside [0, n_out): the serial loop names the element
        if n_colours > 0 and (best is None or n_colours < best[0]):
            best = (n_colours, order, colour)
        if best is not None and best[0] <= GOOD_COLOURS:
            break
    if best is None:
        return None
    n_colours, order, colour = best
    # blocks colour by colour (stable: block order within a colour), order rearranged to match
    perm = np.argsort(colour, kind="stable")
    sizes = np.diff(starts)[perm]
    new_starts = np.concatenate(([0], np.cumsum(sizes))).astype(np.int64)
    shift = np.empty(n_blocks, dtype=np.int64)
    shift[perm] = new_starts[:-1] - starts[perm]
    position = np.arange(m, dtype=np.int64) + np.repeat(shift, np.diff(starts))
    new_order = np.empty(m, dtype=np.int64)
    new_order[position] = order
    counts = np.bincount(colour, minlength=n_colours)
    colours = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
    return _frozen(new_order, new_starts, colours)


def _frozen(order: np.ndarray, blocks: np.ndarray, colours: np.ndarray) -> Schedule:
    arrays = [np.ascontiguousarray(a, dtype=np.int64) for a in (order, blocks, colours)]
    for a in arrays:
        a.setflags(write=False)
    return Schedule(*arrays)


_CACHE: dict[tuple[int, int, int], tuple[weakref.ref, weakref.ref, Schedule | None]] = {}


def schedule_for(T: np.ndarray, index: np.ndarray, n_out: int) -> Schedule | None:
    """:func:`build_schedule`, cached per ``(T, index, n_out)``.

    Only read-only arrays (a model's ``T`` and scatter maps) are cached and scheduled: their
    contents cannot change between calls. Writable ones get None (the serial loop).
    """
    if T.shape[0] < PARALLEL_MIN_TETS or T.flags.writeable or index.flags.writeable:
        return None
    key = (id(T), id(index), int(n_out))
    hit = _CACHE.get(key)
    if hit is not None and hit[0]() is T and hit[1]() is index:
        return hit[2]
    schedule = build_schedule(T, index, n_out)
    for k in [k for k, (t, i, _) in _CACHE.items() if t() is None or i() is None]:
        del _CACHE[k]
    _CACHE[key] = (weakref.ref(T), weakref.ref(index), schedule)
    return schedule
