"""Stress and strain for output: each element's Cauchy stress, von Mises stress and principal
stretches, and their volume-weighted averages at the vertices (what the VTU frames carry).

Per element (constant in a linear tet; over a quadratic one's quadrature points, averaged by
their weights): ``F`` from the element's generated geometry kernel, the first Piola-Kirchhoff
stress ``P = dpsi/dF`` from the material's generated per-F kernel, the Cauchy stress
``sigma = P F^T / J``, von Mises ``sqrt(3/2 s : s)`` with ``s`` the deviator of ``sigma``, and
the principal stretches ``sqrt(eig(F^T F))`` (ascending).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fem3d.mesh.element import ELEMENTS
from fem3d.physics.model import Model

__all__ = ["ElementStress", "element_fields", "element_stress", "node_weights",
           "vertex_fields"]


@dataclass(frozen=True)
class ElementStress:
    """Stress and stretch per element.

    Attributes
    ----------
    cauchy : (m, 3, 3) float64
    von_mises : (m,) float64
    stretches : (m, 3) float64
        Principal stretches, ascending.
    """

    cauchy: np.ndarray
    von_mises: np.ndarray
    stretches: np.ndarray


def element_stress(model: Model, q: np.ndarray) -> ElementStress:
    """The stress and stretches of every element at positions ``q`` (``(n, 3)`` or ``(3n,)``):
    per quadrature point of the element (one for P1), averaged with the points' weights;
    a model of several elements block by block, in element order."""
    if model.blocks:
        parts = [element_stress(b, q) for b in model.blocks]
        return ElementStress(*(np.concatenate([getattr(p, f) for p in parts])
                               for f in ("cauchy", "von_mises", "stretches")))
    m = model.T.shape[0]
    x = np.asarray(q, dtype=np.float64).reshape(-1, 3)[model.T]
    geo = model.element.geometry(model.backend)
    F = np.asarray(geo.deformation_gradient(x, model.dphi_dX)).reshape(m, -1, 3, 3)
    nq = F.shape[1]
    w = np.asarray(model.vol, dtype=np.float64).reshape(m, nq)
    P = np.empty_like(F)
    for g in model.groups:
        els = slice(None) if g.elements is None else np.asarray(g.elements)
        Fg = F[els].reshape(-1, 3, 3)
        per_point = [np.repeat(a, nq, axis=0) if np.ndim(a) == 2 else a
                     for a in (*g.inputs, g.params)]
        per_f = ELEMENTS["p1"].material_kernels(g.material, model.backend)  # psi's P(F)
        P[els] = np.asarray(per_f.dpsi_dF(Fg, *per_point)).reshape(-1, nq, 3, 3)
    F, P = F.reshape(-1, 3, 3), P.reshape(-1, 3, 3)
    J = np.linalg.det(F)
    sigma = np.einsum("mij,mkj->mik", P, F) / J[:, None, None]
    s = sigma - np.trace(sigma, axis1=1, axis2=2)[:, None, None] / 3.0 * np.eye(3)
    von_mises = np.sqrt(1.5 * np.einsum("mij,mij->m", s, s))
    C = np.einsum("mki,mkj->mij", F, F)
    stretches = np.sqrt(np.clip(np.linalg.eigvalsh(C), 0.0, None))
    share = (w / w.sum(axis=1, keepdims=True)).reshape(-1)

    def mean(a: np.ndarray) -> np.ndarray:  # over each element's points, by weight
        return (a * share.reshape((-1,) + (1,) * (a.ndim - 1))).reshape(
            (m, nq) + a.shape[1:]).sum(axis=1)

    return ElementStress(mean(sigma), mean(von_mises), mean(stretches))


def element_fields(e: ElementStress) -> dict[str, np.ndarray]:
    """:func:`element_stress` as cell data: ``von_mises`` ``(m,)``, ``cauchy_stress``
    ``(m, 9)`` (row-major), ``principal_stretches`` ``(m, 3)``."""
    return {"von_mises": e.von_mises, "cauchy_stress": e.cauchy.reshape(-1, 9),
            "principal_stretches": e.stretches}


def node_weights(model: Model) -> tuple[int | np.ndarray, np.ndarray, np.ndarray]:
    """What a volume-weighted vertex average of per-element values needs: ``k`` (nodes per
    element: an int, or ``(m,)`` for a model of several elements; ``np.repeat(values, k)``
    gives each element node its element's value), each element node's weight (its element's
    rest volume) and its node."""
    if model.blocks:
        blocks = model.blocks
        k = np.repeat([b.T.shape[1] for b in blocks], [b.n_tets for b in blocks])
        return (k, np.repeat(model.element_volumes(), k),
                np.concatenate([b.T.reshape(-1) for b in blocks]))
    k = model.T.shape[1]
    return k, np.repeat(model.element.volumes(model.vol), k), model.T.reshape(-1)


def vertex_fields(model: Model, q: np.ndarray, e: ElementStress | None = None,
                  assemble: Callable[[np.ndarray], np.ndarray] | None = None
                  ) -> dict[str, np.ndarray]:
    """Volume-weighted vertex averages of :func:`element_stress` for point data: ``von_mises``
    ``(n,)``, ``cauchy_stress`` ``(n, 9)`` (row-major), ``principal_stretches`` ``(n, 3)``
    (``e``: the elements' stress at ``q`` if already computed).

    ``assemble``: for an MPI rank's share of the elements, the sum over the ranks of the
    weighted sums and weights at each of its vertices (``(n, c) -> (n, c)``,
    :meth:`fem3d.parallel.ghosts.Ghosts.assemble`), so that a vertex on the cut gets the
    average over all its elements, the one-process value.
    """
    e = element_stress(model, q) if e is None else e
    k, w, idx = node_weights(model)
    n = model.n_vertices
    values = {"von_mises": e.von_mises, "cauchy_stress": e.cauchy,
              "principal_stretches": e.stretches}
    sums = [np.bincount(idx, weights=w, minlength=n)]
    for v in values.values():
        v = v.reshape(v.shape[0], -1)
        sums += [np.bincount(idx, weights=w * np.repeat(v[:, c], k), minlength=n)
                 for c in range(v.shape[1])]
    if assemble is not None:
        sums = list(assemble(np.stack(sums, axis=1)).T)
    total = sums[0]
    total[total == 0] = 1.0
    out, column = {}, 1
    for name, v in values.items():
        width = int(np.prod(v.shape[1:], dtype=int))
        average = np.stack(sums[column:column + width], axis=1) / total[:, None]
        out[name] = average[:, 0] if v.ndim == 1 else average
        column += width
    return out
