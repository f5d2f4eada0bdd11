"""The frozen model: everything about a mesh and its material that does not change per step.

A :class:`Model` is built once per mesh (:func:`build_model`) and holds

* the rest shape: ``X``, ``T``, the shape-function gradients ``dphi_dX`` and volumes ``vol``
  (from the generated geometry kernels);
* the material: one or several :class:`MaterialGroup` (a registered material on a subset of
  the elements, its parameters per group or per element, see :mod:`fem3d.physics.materials`), a
  density per mesh or per element, and the summary values ``E``, ``nu``, ``rho``;
* the exact consistent mass matrix (generated ``mass_matrix`` kernel, assembled);
* the sparsity pattern of the ``3n x 3n`` system and two precomputed scatter maps:
  ``scatter`` sends the ``(m, 12, 12)`` element blocks straight into CSR ``data`` positions
  and ``elem_dofs`` sends ``(m, 12)`` element vectors into the ``3n`` DOF vector, so that an
  assembly is one ``np.bincount`` and the pattern is never rebuilt.

The stiffness and the mass matrix share the pattern, so ``M + dt^2 H`` is arithmetic on the
``data`` arrays.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
import scipy.sparse as sp

from fem3d.errors import InputError, ParameterError
from fem3d.kernels.dispatch import geometry_kernels, material_kernels
from fem3d.physics.materials import info, lame_to_E_nu, parameters_from, small_strain_lame
from fem3d.physics.pattern import assemble_mass, block_pattern

__all__ = [
    "GroupData",
    "MaterialGroup",
    "Model",
    "build_model",
    "material_parameters",
    "validate_material",
    "validate_dt",
    "element_dofs",
    "block_pattern",
]

_stages = logging.getLogger("fem3d.stages")  # stage marks (fem3d run --profile)


def validate_material(E: float, nu: float, rho: float) -> tuple[float, float, float]:
    """Check the elastic and inertial parameters.

    Parameters
    ----------
    E : float
        Young's modulus, ``> 0``.
    nu : float
        Poisson's ratio, ``-1 < nu < 0.5``.
    rho : float
        Density, ``> 0``.

    Returns
    -------
    (E, nu, rho) as floats.

    Raises
    ------
    ParameterError
        A value is not finite or out of range.
    """
    E, nu, rho = float(E), float(nu), float(rho)
    if not math.isfinite(E) or E <= 0:
        raise ParameterError(f"Young's modulus E must be a finite number > 0, got {E}")
    if not math.isfinite(nu) or not -1.0 < nu < 0.5:
        raise ParameterError(f"Poisson's ratio nu must satisfy -1 < nu < 0.5, got {nu}")
    if not math.isfinite(rho) or rho <= 0:
        raise ParameterError(f"density rho must be a finite number > 0, got {rho}")
    return E, nu, rho


def validate_dt(dt: float) -> float:
    """Check a time step: finite and ``> 0``; returns it as a float."""
    dt = float(dt)
    if not math.isfinite(dt) or dt <= 0:
        raise ParameterError(f"time step dt must be a finite number > 0, got {dt}")
    return dt


def material_parameters(material: str, E: float, nu: float, param_names: tuple[str, ...]):
    """Kernel parameters of a material from Young's modulus and Poisson's ratio.

    Parameters
    ----------
    material : str
        Registered material name.
    E, nu : float
        Young's modulus and Poisson's ratio.
    param_names : tuple of str
        The material kernels' ``PARAM_NAMES`` (the order of the result).

    Returns
    -------
    (n_params,) float64
        ``fem3d.physics.materials.parameters_from(material, E, nu)`` in ``param_names`` order (for
        ``neo_hookean``: ``C = 0.5 E / (2 (1 + nu))``, ``D = 0.5 E nu / ((1 + nu)(1 - 2 nu))``).
    """
    values = parameters_from(material, E=E, nu=nu)
    return np.array([values[p] for p in param_names], dtype=np.float64)


def element_dofs(T: np.ndarray) -> np.ndarray:
    """Global DOF indices of each element's 12 vertex-major DOFs.

    Parameters
    ----------
    T : (m, 4) int64

    Returns
    -------
    (m, 12) int64
        ``[3 T[e,0], 3 T[e,0]+1, 3 T[e,0]+2, 3 T[e,1], ...]``.
    """
    return (3 * np.asarray(T, dtype=np.int64)[:, :, None] + np.arange(3)).reshape(-1, 12)


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


def _resolve_groups(groups: Sequence[MaterialGroup], m: int, backend: str | None,
                    path: str | None) -> tuple[GroupData, ...]:
    """Check the groups against a mesh of ``m`` tets and resolve their parameters."""
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
        resolved.append(_resolve_group(i, g, el, m, backend))
    return tuple(resolved)


def _resolve_group(i: int, g: MaterialGroup, el: np.ndarray | None, m: int,
                   backend: str | None) -> GroupData:
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
                     inputs=tuple(inputs), kernels=material_kernels(g.material, backend),
                     n_tets=m, span=span)


def _summary_E_nu(groups: Sequence[GroupData], vol: np.ndarray) -> tuple[float, float]:
    """Volume-weighted mean small-strain ``E`` and ``nu`` of the groups (for scales, such as
    the Newton tolerance, and the viewer's sliders)."""
    total_E = total_nu = total_vol = 0.0
    for g in groups:
        w = vol if g.elements is None else vol[g.elements]
        names = [n for n, _ in g.kernels.SIGNATURES["psi"]["inputs"][1:]]
        mu, lam = small_strain_lame(g.material, g.values,
                                    dict(zip(names, g.inputs, strict=True)))
        E, nu = lame_to_E_nu(np.asarray(mu), np.asarray(lam))
        total_E += float(np.sum(np.broadcast_to(E, w.shape) * w))
        total_nu += float(np.sum(np.broadcast_to(nu, w.shape) * w))
        total_vol += float(w.sum())
    return total_E / total_vol, total_nu / total_vol


@dataclass(frozen=True, eq=False)
class Model:
    """Mesh + material + precomputed sparsity (immutable; see the module docstring).

    Attributes
    ----------
    X : (n, 3) float64
        Rest positions.
    T : (m, 4) int64
        Positively oriented tets.
    dphi_dX : (m, 4, 3) float64
        Gradients of the linear shape functions (constant per tet).
    vol : (m,) float64
        Rest volumes (all ``> 0``).
    material : str
        Material name in the kernel registry (``"neo_hookean"``); ``"a+b"`` for groups of
        several materials.
    E, nu, rho : float
        Young's modulus, Poisson's ratio, density: as given, or (material groups with their
        own parameters, per-element densities) the volume-weighted means of the effective
        small-strain values.
    params : (n_params,) float64 or GROUP_PARAMS
        Kernel parameters in the material's ``PARAM_NAMES`` order (one group with shared
        parameters), else the token :data:`GROUP_PARAMS` that :class:`GroupedKernels` takes.
    mat : object
        Material kernels: ``fem3d.kernels.dispatch.material_kernels`` (one group with shared
        parameters) or :class:`GroupedKernels`; both take ``(..., model.params)``.
    geo : object
        Geometry kernels.
    mass : (3n, 3n) scipy.sparse.csr_matrix
        Consistent mass matrix, on :attr:`pattern`'s sparsity.
    pattern : (3n, 3n) scipy.sparse.csr_matrix
        Shared sparsity pattern (data zeros).
    scatter : (m * 144,) int32
        Element-block to CSR-``data`` map (see :func:`block_pattern`).
    elem_dofs : (m, 12) int64
        Element DOFs; ``elem_dofs.ravel()`` is the ``(m * 12,)`` force scatter map (made when
        first asked for: the C kernels use :attr:`dof_slots`).
    backend : str or None
        Kernel back end requested (None: automatic).
    groups : tuple of GroupData
        The material groups, resolved (:class:`MaterialGroup` as given to
        :func:`build_model`).
    density : (m,) float64 or None
        Per-element density when one was given, else None (``rho`` everywhere).
    psd_projection : {"svd", "ql", "jacobi"}
        Eigen-solver of the per-element PSD projection (:attr:`psd_hessian`).
    """

    X: np.ndarray
    T: np.ndarray
    dphi_dX: np.ndarray
    vol: np.ndarray
    material: str
    E: float
    nu: float
    rho: float
    params: np.ndarray
    mat: Any = field(repr=False)
    geo: Any = field(repr=False)
    mass: sp.csr_matrix = field(repr=False)
    pattern: sp.csr_matrix = field(repr=False)
    scatter: np.ndarray = field(repr=False)
    backend: str | None = None
    groups: tuple[GroupData, ...] = field(default=(), repr=False)
    density: np.ndarray | None = field(default=None, repr=False)
    psd_projection: str = "svd"

    @property
    def psd_hessian(self) -> str:
        """Name of the element-Hessian kernel with ``dP/dF`` projected to positive
        semi-definite by :attr:`psd_projection`'s eigen-solver."""
        suffix = "" if self.psd_projection == "ql" else f"_{self.psd_projection}"
        return f"hessian_psd{suffix}"

    @property
    def allows_inversion(self) -> bool:
        """True when every group's material is defined for ``J <= 0`` (declared by its material
        file): the line search need not refuse inverted tets."""
        return bool(self.groups) and all(g.allows_inversion for g in self.groups)

    @property
    def n_vertices(self) -> int:
        """Number of vertices ``n``."""
        return int(self.X.shape[0])

    @property
    def n_tets(self) -> int:
        """Number of tets ``m``."""
        return int(self.T.shape[0])

    @property
    def n_dofs(self) -> int:
        """``3 n``."""
        return 3 * self.n_vertices

    @property
    def nnz(self) -> int:
        """Stored entries of the ``3n x 3n`` pattern."""
        return int(self.pattern.nnz)

    @property
    def total_volume(self) -> float:
        """Sum of rest volumes."""
        return float(self.vol.sum())

    def assemble_blocks(self, blocks: np.ndarray) -> np.ndarray:
        """CSR ``data`` of the sum of element blocks on the shared pattern.

        Parameters
        ----------
        blocks : (m, 12, 12) float64

        Returns
        -------
        (nnz,) float64
        """
        return np.bincount(self.scatter, weights=blocks.reshape(-1), minlength=self.nnz)

    @cached_property
    def energy_slots(self) -> np.ndarray:
        """``(m,) int32`` zeros: the fused energy kernel sums every element into slot 0."""
        slots = np.zeros(self.n_tets, dtype=np.int32)
        slots.setflags(write=False)
        return slots

    @cached_property
    def element_slots(self) -> np.ndarray:
        """``(m,) int32`` ``0, 1, ..., m - 1``: a fused kernel's map for one value per element."""
        slots = np.arange(self.n_tets, dtype=np.int32)
        slots.setflags(write=False)
        return slots

    @cached_property
    def elem_dofs(self) -> np.ndarray:
        """``(m, 12) int64`` element DOFs (:func:`element_dofs`), read-only."""
        dofs = element_dofs(self.T)
        dofs.setflags(write=False)
        return dofs

    @cached_property
    def dof_slots(self) -> np.ndarray:
        """``(m, 12) int32`` :attr:`elem_dofs`: the fused gradient's scatter map."""
        if 3 * self.n_vertices > np.iinfo(np.int32).max:
            raise ValueError("more DOFs than int32 indexes")
        slots = (3 * self.T.astype(np.int32)[:, :, None]
                 + np.arange(3, dtype=np.int32)).reshape(-1, 12)
        slots.setflags(write=False)
        return slots

    def assemble_vectors(self, vecs: np.ndarray) -> np.ndarray:
        """Sum of element vectors into the DOF vector.

        Parameters
        ----------
        vecs : (m, 12) float64

        Returns
        -------
        (3n,) float64
        """
        return np.bincount(
            self.elem_dofs.reshape(-1), weights=vecs.reshape(-1), minlength=self.n_dofs
        )

    def csr(self, data: np.ndarray) -> sp.csr_matrix:
        """A CSR matrix on the shared pattern with the given ``(nnz,)`` data."""
        A = sp.csr_matrix(
            (data, self.pattern.indices, self.pattern.indptr),
            shape=self.pattern.shape,
            copy=False,
        )
        A.has_sorted_indices = True
        return A

    def with_material(
        self, E: float | None = None, nu: float | None = None, rho: float | None = None,
        *, material: str | None = None,
    ) -> Model:
        """A copy with new material values, sharing the mesh, pattern and scatter maps.

        Parameters
        ----------
        material : str, optional
            Another registered material for every tet (one group, parameters of ``E, nu``:
            the viewer's material menu). Its per-element inputs take their defaults.
        E, nu : float, optional
            New Young's modulus / Poisson's ratio (None keeps the current one). When either
            is given, every group gets its material's parameters of ``E, nu`` (per-element
            stiffness fields become uniform; shape parameters such as Fung's ``b`` and the
            per-element inputs such as fibre directions are kept).
        rho : float, optional
            New density; a per-element density is scaled so that its mean becomes ``rho``.
        """
        E, nu, rho = validate_material(
            self.E if E is None else E,
            self.nu if nu is None else nu,
            self.rho if rho is None else rho,
        )
        groups, mat, params = self.groups, self.mat, self.params
        if material is not None:
            groups = _resolve_groups([MaterialGroup(material, None, {"E": E, "nu": nu})],
                                     self.n_tets, self.backend, None)
            mat, params = _kernels_of(groups)
        elif (E, nu) != (self.E, self.nu):
            groups = tuple(_with_E_nu(g, E, nu) for g in self.groups)
            mat, params = _kernels_of(groups)
        mass, density = self.mass, self.density
        if rho != self.rho:
            mass = self.csr(self.mass.data * (rho / self.rho))  # M is linear in rho
            _readonly(mass.data)
            if density is not None:
                density = density * (rho / self.rho)
                _readonly(density)
        name = "+".join(dict.fromkeys(g.material for g in groups))
        return replace(self, material=name, E=E, nu=nu, rho=rho, params=params, mat=mat,
                       mass=mass, groups=groups, density=density)


def _with_E_nu(g: GroupData, E: float, nu: float) -> GroupData:
    """Group ``g`` with the parameters of ``E, nu`` (scalar shape parameters kept)."""
    material = info(g.material)
    shape = {p: g.values[p] for p in material.shape_params if np.ndim(g.values[p]) == 0}
    values = parameters_from(g.material, E=E, nu=nu, params=shape)
    params = np.array([values[p] for p in material.param_names], dtype=np.float64)
    _readonly(params)
    return replace(g, values=values, params=params, _cache={})


def _kernels_of(groups: Sequence[GroupData]) -> tuple[Any, Any]:
    """``(model.mat, model.params)`` of a model with ``groups``."""
    if len(groups) == 1 and groups[0].elements is None and not groups[0].inputs \
            and groups[0].params.ndim == 1:
        return groups[0].kernels, groups[0].params
    return GroupedKernels(groups), GROUP_PARAMS


def _own_copy(a, dtype) -> np.ndarray:
    """``a`` as a C-ordered array of ``dtype`` the caller may make read-only: ``a`` itself
    when it is one already and read-only (a validated mesh's arrays), else a copy."""
    if isinstance(a, np.ndarray) and not a.flags.writeable and a.flags.c_contiguous and \
            (dtype is None or a.dtype == dtype) and a.base is None:
        return a
    return np.array(a, dtype=dtype, order="C")


def _mesh_arrays(X, T, path: str | None) -> tuple[np.ndarray, np.ndarray]:
    """Own C-ordered copies of the rest positions ``(n, 3)`` and tets ``(m, 4) int64``,
    checked (InputError names the vertex or tet)."""
    X = _own_copy(X, np.float64)  # made read-only
    T = _own_copy(T, None)
    if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] < 4:
        raise InputError(f"X must have shape (n >= 4, 3), got {X.shape}", path=path)
    if not np.isfinite(X).all():
        bad = int(np.flatnonzero(~np.isfinite(X).all(axis=1))[0])
        raise InputError("vertex has a non-finite coordinate", path=path, element=bad)
    if T.ndim != 2 or T.shape[1] != 4 or T.shape[0] < 1:
        raise InputError(f"T must have shape (m >= 1, 4), got {T.shape}", path=path)
    if not np.issubdtype(T.dtype, np.integer):
        raise InputError(f"T must hold integers, got {T.dtype}", path=path)
    T = T.astype(np.int64, copy=False)
    out = (T < 0) | (T >= X.shape[0])
    if out.any():
        e = int(np.flatnonzero(out.any(axis=1))[0])
        raise InputError(
            f"tet refers to vertex {int(T[e][out[e]][0])}, outside [0, {X.shape[0]})",
            path=path, element=e,
        )
    return X, T


def _element_density(density, vol: np.ndarray) -> np.ndarray:
    """A per-tet density ``(m,)``, checked and read-only."""
    rho_e = np.array(density, dtype=np.float64)
    if rho_e.shape != vol.shape:
        raise ParameterError(f"density must be a number or one value per tet "
                             f"({vol.shape[0]}), got shape {rho_e.shape}")
    bad = ~(np.isfinite(rho_e) & (rho_e > 0))
    if bad.any():
        raise ParameterError(f"density of tet {int(bad.argmax())} must be a finite number "
                             f"> 0, got {rho_e[bad.argmax()]}")
    _readonly(rho_e)
    return rho_e


def build_model(
    X: np.ndarray,
    T: np.ndarray,
    *,
    E: float | None = None,
    nu: float | None = None,
    rho: float | None = None,
    material: str = "neo_hookean",
    groups: Sequence[MaterialGroup] | None = None,
    density: float | np.ndarray | None = None,
    backend: str | None = None,
    path: str | None = None,
) -> Model:
    """Precompute everything about a mesh and its materials.

    Parameters
    ----------
    X : (n, 3) float64
        Rest positions.
    T : (m, 4) int
        Tets, 0-based, positively oriented.
    E, nu : float, optional
        Young's modulus (> 0), Poisson's ratio (-1, 0.5) of ``material`` on every tet (the
        one-material form; not together with ``groups``).
    rho : float, optional
        Density (> 0); the same as ``density`` given as a number.
    material : str, optional
        Registered material name (default ``"neo_hookean"``) of the one-material form.
    groups : sequence of MaterialGroup, optional
        Materials per set of tets, each with its parameters (per group or per element); every
        tet in exactly one group (one group may have ``elements=None``: the rest).
    density : float or (m,) float64, optional
        Density per mesh or per tet (> 0).
    backend : {None, "numpy", "c"}, optional
        Kernel back end (None: C if built, else NumPy; ``FEM3D_KERNELS`` overrides).
    path : str, optional
        Mesh file, for error messages.

    Returns
    -------
    Model

    Raises
    ------
    ParameterError
        Bad material values or groups (the message names the group and parameter).
    InputError
        Bad arrays, a vertex index out of range, or a tet with non-positive volume.
    """
    if rho is not None and density is not None:
        raise ParameterError("give the density once: rho= or density=, not both")
    density = rho if density is None else density
    if density is None:
        raise ParameterError("build_model needs a density (rho= or density=)")
    per_element_density = np.ndim(density) > 0
    if groups is None:
        E, nu, rho = validate_material(E if E is not None else math.nan,
                                       nu if nu is not None else math.nan,
                                       1.0 if per_element_density else density)
        groups = [MaterialGroup(material, None, {"E": E, "nu": nu})]
        given_E_nu = (E, nu)
    else:
        if E is not None or nu is not None:
            raise ParameterError("with groups=, give E and nu in each MaterialGroup's params")
        given_E_nu = None
        rho = 1.0 if per_element_density else float(density)
        if not per_element_density:
            validate_material(1.0, 0.0, rho)
    X, T = _mesh_arrays(X, T, path)

    geo = geometry_kernels(backend=backend)
    dphi_dX, vol = geo.rest_shape(X[T])
    dphi_dX = np.ascontiguousarray(dphi_dX, dtype=np.float64)
    vol = np.ascontiguousarray(vol, dtype=np.float64)
    bad = ~(vol > 0)
    if bad.any():
        e = int(np.flatnonzero(bad)[0])
        raise InputError(
            f"tet has non-positive volume {vol[e]:.3g} (degenerate or inverted; "
            f"{int(bad.sum())} such tets)", path=path, element=e,
        )
    resolved = _resolve_groups(groups, T.shape[0], backend, path)
    mat, params = _kernels_of(resolved)
    rho_e = None
    if per_element_density:
        rho_e = _element_density(density, vol)
        rho = float((rho_e * vol).sum() / vol.sum())
    if given_E_nu is None:
        E, nu = _summary_E_nu(resolved, vol)

    _stages.debug("model: rest shape, materials")
    pattern, scatter = block_pattern(T, X.shape[0])
    _stages.debug("model: sparsity pattern")
    mass_data = assemble_mass(geo, vol, rho, rho_e, scatter, T, pattern.indptr)
    mass = sp.csr_matrix((mass_data, pattern.indices, pattern.indptr), shape=pattern.shape)
    mass.has_sorted_indices = True
    _readonly(X, T, dphi_dX, vol, mass.data, scatter, pattern.indices, pattern.indptr)
    material_name = "+".join(dict.fromkeys(g.material for g in resolved))
    _stages.debug("model: mass matrix")
    return Model(
        X=X, T=T, dphi_dX=dphi_dX, vol=vol, material=material_name, E=float(E), nu=float(nu),
        rho=float(rho), params=params, mat=mat, geo=geo, mass=mass, pattern=pattern,
        scatter=scatter, backend=backend, groups=resolved, density=rho_e,
    )
