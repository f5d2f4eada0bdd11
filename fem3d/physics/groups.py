"""Materials on groups of elements: a :class:`MaterialGroup` as given to
:func:`fem3d.physics.model.build_model`, resolved for a mesh into :class:`GroupData`
(parameters per group or per element, per-element inputs), and :class:`GroupedKernels`, the
material kernels of a model with several groups evaluated group by group.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from fem3d.errors import ParameterError
from fem3d.mesh.element import ELEMENTS, Element
from fem3d.physics.materials import info, lame_to_E_nu, parameters_from, small_strain_lame

__all__ = ["GROUP_PARAMS", "GroupData", "GroupedKernels", "MaterialGroup", "kernels_of",
           "resolve_groups", "summary_E_nu", "with_E_nu"]


def _readonly(*arrays: np.ndarray) -> None:
    for a in arrays:
        a.setflags(write=False)


@dataclass(frozen=True)
class MaterialGroup:
    """A material on a set of elements, as given to :func:`build_model`.

    Parameters
    ----------
    material : str
        Registered material name (:func:`fem3d.physics.materials.names`).
    elements : (k,) int64, optional
        The tets of this group; None: every tet no other group lists (at most one group).
    params : mapping, optional
        ``E`` and ``nu`` (mapped by :func:`fem3d.physics.materials.parameters_from`) and/or the
        material's own parameters, each a number or a per-element ``(k,)`` array (a
        stiffness field), plus the material's per-element inputs (e.g. a fibre direction
        ``a``: one ``(3,)`` value or ``(k, 3)``; a missing one defaults to the first unit
        vector, the x axis).
    """

    material: str
    elements: np.ndarray | None = None
    params: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class GroupData:
    """A :class:`MaterialGroup` resolved for one mesh (built by :func:`build_model`).

    Attributes
    ----------
    material : str
    elements : (k,) int64 or None
        None: every tet of the mesh (the arrays of the model are used as they are).
    values : dict of str -> float or (k,) float64
        The material's parameters (resolved from ``E, nu`` where given).
    params : (n_params,) or (k, n_params) float64
        Kernel parameters, shared by the group or per element.
    inputs : tuple of (k, ...) float64
        The material's per-element inputs, in kernel order.
    kernels : KernelModule
    """

    material: str
    elements: np.ndarray | None
    values: dict
    params: np.ndarray
    inputs: tuple[np.ndarray, ...]
    kernels: Any = field(repr=False)
    n_tets: int = 0
    _cache: dict = field(default_factory=dict, repr=False)
    #: ``slice(first, last + 1)`` when the elements are consecutive tets (a body's): its
    #: subsets are views, not copies (a copy of the scatter map is 576 bytes per tet).
    span: slice | None = field(default=None, repr=False)

    @property
    def allows_inversion(self) -> bool:
        """Whether this group's material is defined for ``J <= 0``."""
        return info(self.material).allows_inversion

    def subset(self, array: np.ndarray) -> np.ndarray:
        """``array``'s rows of this group's elements. ``array`` has a leading tet axis, or is
        flat with a fixed number of entries per tet (a scatter map). Subsets of read-only
        arrays (the model's maps, the integrator's scaled volumes) are cached, so repeated
        fused-kernel calls copy nothing."""
        if self.elements is None:
            return array
        a = np.asarray(array)
        if self.span is not None and a.flags.c_contiguous:
            rows = a.reshape(self.n_tets, -1)[self.span] if a.ndim == 1 else a[self.span]
            return rows.reshape(-1) if a.ndim == 1 else rows
        cached = self._cache.get(id(a))
        if cached is not None and cached[0] is a:
            return cached[1]
        if a.ndim == 1:
            if a.size % self.n_tets:
                raise ValueError(f"an array of {a.size} values does not hold one row per tet "
                                 f"({self.n_tets} tets)")
            picked = np.ascontiguousarray(a.reshape(self.n_tets, -1)[self.elements]).reshape(-1)
        else:
            picked = np.ascontiguousarray(a[self.elements])
        if not a.flags.writeable:
            picked.setflags(write=False)
            if len(self._cache) >= 16:
                self._cache.pop(next(iter(self._cache)))
            self._cache[id(a)] = (a, picked)
        return picked


class _GroupToken:
    """``model.params`` of a model whose material is not one set of shared parameters: the
    kernels of :class:`GroupedKernels` take it in place of a parameter array."""

    def __repr__(self) -> str:
        return "<per-group material parameters>"


GROUP_PARAMS = _GroupToken()


class GroupedKernels:
    """``model.mat`` of a model with several material groups, per-element parameters or
    per-element inputs: the kernels of :class:`fem3d.kernels.dispatch.KernelModule` with the same
    arguments over the whole mesh, evaluated group by group.

    Element arrays (``x_e``, ``dphi_dX``, ``vol``, the fused kernels' ``T`` and ``index``) are
    split by the groups' elements; each group adds its own inputs and parameters. The
    parameter argument must be ``model.params`` (:data:`GROUP_PARAMS`).
    """

    def __init__(self, groups: Sequence[GroupData]) -> None:
        self.groups = tuple(groups)
        first = self.groups[0].kernels
        self.backend = first.backend
        self.name = "+".join(dict.fromkeys(g.material for g in self.groups))
        self.SIGNATURES = first.SIGNATURES
        for kernel, signature in first.SIGNATURES.items():
            setattr(self, kernel, self._kernel(kernel, signature))
            if all(g.kernels.has_assemble(kernel) for g in self.groups):
                setattr(self, f"{kernel}_assemble", self._assemble(kernel))

    def has_assemble(self, kernel: str) -> bool:
        """Whether the fused ``<kernel>_assemble`` exists for every group (C back end)."""
        return hasattr(self, f"{kernel}_assemble")

    def __repr__(self) -> str:
        return f"GroupedKernels({self.name!r}, {len(self.groups)} groups, backend={self.backend!r})"

    @staticmethod
    def _check(params: object, kernel: str) -> None:
        if params is not GROUP_PARAMS:
            raise TypeError(f"{kernel}: this model's material parameters are per group; pass "
                            "model.params")

    def _base_inputs(self, kernel: str, group: GroupData) -> int:
        own = len(group.inputs)
        return len(group.kernels.SIGNATURES[kernel]["inputs"]) - own

    def _kernel(self, kernel: str, signature: dict):
        def call(*args, out=None):
            *arrays, params = args
            self._check(params, kernel)
            m = len(arrays[0])
            shapes = [(m, *shape) for _, shape in signature["outputs"]]
            results = [np.empty(s) for s in shapes] if out is None else \
                list(out) if isinstance(out, tuple | list) else [out]
            for g in self.groups:
                n_base = self._base_inputs(kernel, g)
                base = [np.asarray(a) if g.elements is None else
                        np.asarray(a)[g.span if g.span is not None else g.elements]
                        for a in arrays[:n_base]]
                values = getattr(g.kernels, kernel)(*base, *g.inputs, g.params)
                values = values if isinstance(values, tuple) else (values,)
                for r, v in zip(results, values, strict=True):
                    if g.elements is None:
                        r[...] = v
                    else:
                        r[g.elements] = v
            return results[0] if len(results) == 1 else tuple(results)

        call.__name__ = kernel
        return call

    def _assemble(self, kernel: str):
        def call(q, T, *rest):
            *arrays, params, index, out = rest
            self._check(params, kernel)
            for g in self.groups:
                fused = getattr(g.kernels, f"{kernel}_assemble")
                fused(q, g.subset(T), *(g.subset(a) for a in arrays), *g.inputs, g.params,
                      g.subset(index), out)
            return out

        call.__name__ = f"{kernel}_assemble"
        return call


def resolve_groups(groups: Sequence[MaterialGroup], m: int, backend: str | None,
                   path: str | None, element: Element = ELEMENTS["p1"]) -> tuple[GroupData, ...]:
    """Check the groups against a mesh of ``m`` elements and resolve their parameters (and
    the material kernels on ``element``)."""
    if not groups:
        raise ParameterError("build_model needs at least one material group")
    owner = np.full(m, -1, dtype=np.int64)
    rest = [i for i, g in enumerate(groups) if g.elements is None]
    if len(rest) > 1:
        raise ParameterError(f"material groups {rest[0]} and {rest[1]} both have elements=None "
                             "(at most one group takes the remaining tets)")
    element_sets: list[np.ndarray | None] = []
    for i, g in enumerate(groups):
        if not isinstance(g, MaterialGroup):
            raise ParameterError(f"material group {i} must be a MaterialGroup, got "
                                 f"{type(g).__name__}")
        info(g.material)  # unknown names: ParameterError
        if g.elements is None:
            element_sets.append(None)
            continue
        el = np.asarray(g.elements)
        if el.ndim != 1 or not (el.size == 0 or np.issubdtype(el.dtype, np.integer)):
            raise ParameterError(f"material group {i} ({g.material}): elements must be a 1-d "
                                 f"array of tet indices, got shape {el.shape} {el.dtype}")
        el = el.astype(np.int64)
        bad = (el < 0) | (el >= m)
        if bad.any():
            raise ParameterError(f"material group {i} ({g.material}): element "
                                 f"{int(el[bad][0])} is outside [0, {m})")
        taken = owner[el] >= 0
        if taken.any() or np.unique(el).size != el.size:
            e = int(el[taken][0]) if taken.any() else int(el[np.argmax(np.bincount(el))])
            other = int(owner[e]) if taken.any() else i
            raise ParameterError(f"material group {i} ({g.material}): element {e} is already "
                                 f"in material group {other}")
        owner[el] = i
        element_sets.append(el)
    if rest:
        remaining = np.flatnonzero(owner < 0)
        element_sets[rest[0]] = None if remaining.size == m else remaining
        owner[remaining] = rest[0]
    elif (owner < 0).any():
        e = int(np.flatnonzero(owner < 0)[0])
        raise ParameterError(f"tet {e} is in no material group ({int((owner < 0).sum())} such "
                             "tets); give one group elements=None for the rest")
    resolved = []
    for i, (g, el) in enumerate(zip(groups, element_sets, strict=True)):
        resolved.append(_resolve_group(i, g, el, m, backend, element))
    return tuple(resolved)


def _resolve_group(i: int, g: MaterialGroup, el: np.ndarray | None, m: int,
                   backend: str | None, element: Element) -> GroupData:
    material = info(g.material)
    k = m if el is None else el.size
    where = f"material group {i} ({g.material})"
    given = dict(g.params)
    inputs = []
    for name, shape in material.per_element_inputs.items():
        value = given.pop(name, None)
        if value is None:
            a = np.zeros((k, *shape))
            a.reshape(k, -1)[:, 0] = 1.0
        else:
            a = np.asarray(value, dtype=np.float64)
            if a.shape == shape:
                a = np.broadcast_to(a, (k, *shape))
            if a.shape != (k, *shape):
                raise ParameterError(f"{where}: input {name!r} must have shape {shape} or "
                                     f"({k}, {', '.join(map(str, shape))}), got {a.shape}")
            flat = a.reshape(k, -1)
            bad = ~(np.isfinite(flat).all(axis=1) & (np.abs(flat).sum(axis=1) > 0))
            if bad.any():
                raise ParameterError(f"{where}: input {name!r} of element "
                                     f"{int(bad.argmax()) if el is None else int(el[bad.argmax()])}"
                                     " is zero or not finite")
        inputs.append(np.ascontiguousarray(a, dtype=np.float64))
    for key, value in given.items():
        size = np.asarray(value).size
        if np.ndim(value) > 0 and size != k:
            raise ParameterError(f"{where}: parameter {key!r} has {size} values for {k} "
                                 "elements")
    E, nu = given.pop("E", None), given.pop("nu", None)
    try:
        values = parameters_from(g.material, E=E, nu=nu, params=given)
    except ParameterError as error:
        raise ParameterError(f"{where}: {error}") from None
    names = material.param_names
    if all(np.ndim(values[p]) == 0 for p in names):
        params = np.array([values[p] for p in names], dtype=np.float64)
    else:
        params = np.ascontiguousarray(np.stack(
            [np.broadcast_to(np.asarray(values[p], dtype=np.float64), (k,)) for p in names],
            axis=1))
    _readonly(params, *inputs)
    span = None
    if el is not None and el.size and int(el[-1]) - int(el[0]) + 1 == el.size and \
            (np.diff(el) == 1).all():
        span = slice(int(el[0]), int(el[-1]) + 1)
    return GroupData(material=g.material, elements=el, values=values, params=params,
                     inputs=tuple(inputs), kernels=element.material_kernels(g.material, backend),
                     n_tets=m, span=span)


def summary_E_nu(groups: Sequence[GroupData], vol: np.ndarray) -> tuple[float, float]:
    """Volume-weighted mean small-strain ``E`` and ``nu`` of the groups (for scales, such as
    the Newton tolerance, and the viewer's sliders)."""
    total_E = total_nu = total_vol = 0.0
    for g in groups:
        w = vol if g.elements is None else vol[g.elements]
        names = list(info(g.material).per_element_inputs)  # the order of g.inputs
        mu, lam = small_strain_lame(g.material, g.values,
                                    dict(zip(names, g.inputs, strict=True)))
        E, nu = lame_to_E_nu(np.asarray(mu), np.asarray(lam))
        total_E += float(np.sum(np.broadcast_to(E, w.shape) * w))
        total_nu += float(np.sum(np.broadcast_to(nu, w.shape) * w))
        total_vol += float(w.sum())
    return total_E / total_vol, total_nu / total_vol


def with_E_nu(g: GroupData, E: float, nu: float) -> GroupData:
    """Group ``g`` with the parameters of ``E, nu`` (scalar shape parameters kept)."""
    material = info(g.material)
    shape = {p: g.values[p] for p in material.shape_params if np.ndim(g.values[p]) == 0}
    values = parameters_from(g.material, E=E, nu=nu, params=shape)
    params = np.array([values[p] for p in material.param_names], dtype=np.float64)
    _readonly(params)
    return replace(g, values=values, params=params, _cache={})


def kernels_of(groups: Sequence[GroupData]) -> tuple[Any, Any]:
    """``(model.mat, model.params)`` of a model with ``groups``."""
    if len(groups) == 1 and groups[0].elements is None and not groups[0].inputs \
            and groups[0].params.ndim == 1:
        return groups[0].kernels, groups[0].params
    return GroupedKernels(groups), GROUP_PARAMS
