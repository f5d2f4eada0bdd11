"""Pull springs: zero-rest-length springs ``1/2 k |x_i - target_i|^2`` on vertices.

The interactive drag, the scenes' scripted pulls and the assignment's pull spring are all
one :class:`Pull`; its energy, gradient and Hessian blocks come from the generated
``spring_kernels``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fem3d.errors import ParameterError

__all__ = ["Pull"]


@dataclass(frozen=True, eq=False)
class Pull:
    """Zero-rest-length springs pulling vertices toward targets.

    Attributes
    ----------
    vertices : (k,) int64
        Pulled vertex of each spring, sorted (a vertex may carry several springs when pulls
        are combined, :meth:`combine`).
    targets : (k, 3) float64
        Target point of each spring.
    k : float or (k,) float64
        Spring stiffness (> 0): one value shared by every spring (a float, as given to
        :meth:`make`), or one per spring.
    """

    vertices: np.ndarray
    targets: np.ndarray
    k: float | np.ndarray

    @classmethod
    def make(cls, vertices, targets, k, n_vertices: int) -> Pull:
        """Validated pull; ``targets`` may be one point ``(3,)`` shared by all vertices.

        Parameters
        ----------
        vertices : (k,) int
            Pulled vertices. With one shared target and one stiffness, duplicates are merged
            (one spring per vertex); otherwise each entry is its own spring.
        targets : (3,) or (k, 3) float64
            One target for all springs, or one per entry of ``vertices``.
        k : float or (k,) float64
            Stiffness (> 0), shared or per spring.
        n_vertices : int

        Raises
        ------
        ParameterError
            Bad vertex ids, target shape or stiffness.
        """
        raw = np.asarray(vertices, dtype=np.int64).reshape(-1)
        if raw.size and (raw.min() < 0 or raw.max() >= n_vertices):
            raise ParameterError(f"pulled vertex out of range [0, {n_vertices})")
        tgt = np.asarray(targets, dtype=np.float64)
        k_arr = np.asarray(k, dtype=np.float64)
        shared = tgt.shape == (3,) and k_arr.ndim == 0
        if shared:
            idx, order = np.unique(raw), None
        else:
            order = np.argsort(raw, kind="stable")
            idx = raw[order]
        if tgt.shape == (3,):
            tgt = np.broadcast_to(tgt, (idx.size, 3)).copy()
        elif tgt.shape == (raw.size, 3):
            tgt = tgt[order]
        else:
            raise ParameterError(f"pull target must be (3,) or ({raw.size}, 3), got {tgt.shape}")
        if not np.isfinite(tgt).all():
            raise ParameterError("pull target is not finite")
        if k_arr.ndim == 0:
            k_val: float | np.ndarray = float(k_arr)
            bad = not math.isfinite(k_val) or k_val <= 0
        elif k_arr.shape == (raw.size,):
            k_val = k_arr[order].copy()
            bad = not (np.isfinite(k_val).all() and (k_val > 0).all())
        else:
            raise ParameterError(f"spring stiffness must be a number or ({raw.size},) array, "
                                 f"got shape {k_arr.shape}")
        if bad:
            raise ParameterError(f"spring stiffness must be a finite number > 0, got {k}")
        for a in (idx, tgt) + ((k_val,) if isinstance(k_val, np.ndarray) else ()):
            a.setflags(write=False)
        return cls(vertices=idx, targets=tgt, k=k_val)

    @classmethod
    def combine(cls, pulls, n_vertices: int) -> Pull | None:
        """All springs of several pulls as one (``None`` entries and empty pulls skipped).

        Parameters
        ----------
        pulls : iterable of Pull or None
        n_vertices : int

        Returns
        -------
        Pull or None
            None when no spring is left; the pull itself when only one has springs.
        """
        live = [p for p in pulls if p is not None and p.vertices.size]
        if not live:
            return None
        if len(live) == 1:
            return live[0]
        return cls.make(np.concatenate([p.vertices for p in live]),
                        np.concatenate([p.targets for p in live]),
                        np.concatenate([p.stiffness for p in live]), n_vertices)

    @property
    def stiffness(self) -> np.ndarray:
        """``(k,)`` stiffness of each spring."""
        if isinstance(self.k, np.ndarray):
            return self.k
        return np.full(self.vertices.size, self.k)

    def _kernel_k(self) -> tuple[tuple[float], np.ndarray | None]:
        """The kernels' scalar parameter and the per-spring factor (linear in ``k``)."""
        if isinstance(self.k, np.ndarray):
            return (1.0,), self.k
        return (self.k,), None

    def energy(self, spring, q: np.ndarray) -> float:
        """Spring energy at positions ``q (n, 3)``."""
        if self.vertices.size == 0:
            return 0.0
        kk, scale = self._kernel_k()
        e = spring.energy(q[self.vertices], self.targets, kk)
        return float((e if scale is None else e * scale).sum())

    def gradient(self, spring, q: np.ndarray) -> np.ndarray:
        """``d V_pull / d q`` as a full ``(3n,)`` vector."""
        g = np.zeros(q.size)
        if self.vertices.size:
            kk, scale = self._kernel_k()
            ge = spring.gradient(q[self.vertices], self.targets, kk)[:, :3]
            if scale is not None:
                ge = ge * scale[:, None]
            if self.vertices.size < 2 or bool((np.diff(self.vertices) > 0).all()):
                g.reshape(-1, 3)[self.vertices] += ge
            else:  # several springs on one vertex
                np.add.at(g.reshape(-1, 3), self.vertices, ge)
        return g

    def hessian_blocks(self, spring, q: np.ndarray) -> np.ndarray:
        """``(k, 3, 3)`` Hessian blocks of each pulled vertex (the target is not a DOF)."""
        kk, scale = self._kernel_k()
        h = spring.hessian(q[self.vertices], self.targets, kk)[:, :3, :3]
        return h if scale is None else h * scale[:, None, None]
