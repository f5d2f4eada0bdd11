"""The frozen model: everything about a mesh and its material that does not change per step.

A :class:`Model` is built once per mesh (:func:`build_model`) and holds

* the element (:mod:`fem3d.mesh.element`: ``"p1"``, ``"p2"``), which says how many nodes an
  element has, which kernels give its rest shape and mass, and what its faces are;
* the rest shape: ``X``, ``T`` (one row of nodes per element), the shape-function gradients
  ``dphi_dX`` and volumes ``vol`` (from the element's generated geometry kernels);
* the material: one or several :class:`MaterialGroup` (a registered material on a subset of
  the elements, its parameters per group or per element, see :mod:`fem3d.physics.groups`), a
  density per mesh or per element, and the summary values ``E``, ``nu``, ``rho``;
* the exact consistent mass matrix (generated ``mass_matrix`` kernel, assembled);
* the element blocks of a scene whose bodies mix elements (P1 and P2): one :class:`Model`
  per run of consecutive bodies on one element (:attr:`Model.blocks`,
  :func:`mixed_model`), all on the whole mesh's nodes, sparsity pattern and DOF vector;
* the sparsity pattern of the ``3n x 3n`` system and two precomputed scatter maps:
  ``scatter`` sends the ``(m, d, d)`` element blocks (``d = 3 x`` nodes per element) straight
  into CSR ``data`` positions and ``elem_dofs`` sends ``(m, d)`` element vectors into the
  ``3n`` DOF vector, so that an
  assembly is one ``np.bincount`` and the pattern is never rebuilt.

The stiffness and the mass matrix share the pattern, so ``M + dt^2 H`` is arithmetic on the
``data`` arrays.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property, partial
from typing import Any

import numpy as np
import scipy.sparse as sp

from fem3d.errors import InputError, ParameterError
from fem3d.mesh import element as elements
from fem3d.mesh.element import Element, MixedElements
from fem3d.physics.groups import (
    GROUP_PARAMS,
    GroupData,
    GroupedKernels,
    MaterialGroup,
    kernels_of,
    resolve_groups,
    summary_E_nu,
    with_E_nu,
)
from fem3d.physics.materials import parameters_from
from fem3d.physics.pattern import assemble_mass, block_pattern, merge_patterns

__all__ = [
    "GROUP_PARAMS",
    "GroupData",
    "GroupedKernels",
    "MaterialGroup",
    "Model",
    "build_model",
    "mixed_model",
    "with_psd_projection",
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
    """Global DOF indices of each element's node-major DOFs.

    Parameters
    ----------
    T : (m, k) int64
        Elements of ``k`` nodes.

    Returns
    -------
    (m, 3 k) int64
        ``[3 T[e,0], 3 T[e,0]+1, 3 T[e,0]+2, 3 T[e,1], ...]``.
    """
    T = np.asarray(T, dtype=np.int64)
    return (3 * T[:, :, None] + np.arange(3)).reshape(T.shape[0], -1)


def _readonly(*arrays: np.ndarray) -> None:
    for a in arrays:
        a.setflags(write=False)


@dataclass(frozen=True, eq=False)
class Model:
    """Mesh + material + precomputed sparsity (immutable; see the module docstring).

    Attributes
    ----------
    X : (n, 3) float64
        Rest positions of the nodes.
    T : (m, k) int64
        Elements: ``k`` nodes each (:attr:`element`), corners first, positively oriented.
    dphi_dX : float64
        Shape-function gradients, the element's ``rest_shape`` output (P1: ``(m, 4, 3)``,
        constant per tet).
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
    scatter : (m * d^2,) int32
        Element-block to CSR-``data`` map (see :func:`block_pattern`; ``d = 3 k``, 12 for P1).
    elem_dofs : (m, d) int64
        Element DOFs; ``elem_dofs.ravel()`` is the ``(m * d,)`` force scatter map (made when
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
    element : Element
        The finite element of every cell (:func:`fem3d.mesh.element.element`).
    blocks : tuple of Model
        Empty for a model of one element. A model whose bodies mix elements
        (:func:`mixed_model`) holds one model per element block (its elements ``T`` in the
        whole mesh's node numbering, its own rest shape, materials, kernels and mass, its
        ``scatter`` into this model's :attr:`pattern`); its own ``T``, ``dphi_dX``,
        ``element``, ``mat``, ``geo``, ``params`` and ``groups`` are
        :class:`~fem3d.mesh.element.MixedElements`, which raise on any use. Its ``vol`` and
        ``scatter`` are the blocks' flattened and concatenated in element order (what an
        integrator scales and gathers; :meth:`split` cuts them back into the blocks').
        Iterate :meth:`element_blocks` to handle both kinds of model.
    spans : tuple of slice
        Each block's range of elements in the scene's element order (empty: one element).
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
    element: Element = field(default=elements.ELEMENTS["p1"], repr=False)
    blocks: tuple[Model, ...] = field(default=(), repr=False)
    spans: tuple[slice, ...] = field(default=(), repr=False)

    @property
    def is_mixed(self) -> bool:
        """Whether the bodies mix elements (the model holds :attr:`blocks`)."""
        return bool(self.blocks)

    def element_blocks(self) -> tuple[tuple[slice, Model], ...]:
        """``((span, block), ...)``: each element block and its range of elements; a model of
        one element is its own single block (``slice(0, m)``, itself)."""
        if self.blocks:
            return tuple(zip(self.spans, self.blocks, strict=True))
        return ((slice(0, int(self.T.shape[0])), self),)

    def split(self, flat: np.ndarray, like: str = "vol") -> list[np.ndarray]:
        """Cut a mixed model's flat per-element array (:attr:`vol` or :attr:`scatter`, or one
        made from them: ``vol * dt^2``, a reduced scatter map) into the blocks' arrays,
        shaped like each block's ``like`` attribute (views)."""
        refs = [getattr(b, like) for b in self.blocks]
        total = sum(r.size for r in refs)
        if flat.size != total:
            raise ValueError(f"an array of {flat.size} values is not the blocks' {like} "
                             f"({total} values)")
        bounds = np.cumsum([0] + [r.size for r in refs])
        return [flat[a:b].reshape(r.shape) for a, b, r in zip(bounds[:-1], bounds[1:], refs,
                                                                 strict=True)]

    def element_volumes(self) -> np.ndarray:
        """``(m,) float64`` rest volume of each element (:meth:`Element.volumes`)."""
        if self.blocks:
            return np.concatenate([b.element_volumes() for b in self.blocks])
        return self.element.volumes(self.vol)

    def scaled_volumes(self, per_element: np.ndarray) -> np.ndarray:
        """:attr:`vol` times a per-element ``(m,)`` factor (on every quadrature point of an
        element whose ``vol`` is per point): a Rayleigh ``beta`` per element."""
        per_element = np.asarray(per_element, dtype=np.float64)
        if self.blocks:
            return np.concatenate([b.scaled_volumes(per_element[s]).reshape(-1)
                                   for s, b in self.element_blocks()])
        return self.vol * per_element.reshape(per_element.shape + (1,) * (self.vol.ndim - 1))

    @property
    def kernel_backend(self) -> str:
        """The back end of the material kernels (``"c"``, ``"numpy"``)."""
        return self.blocks[0].mat.backend if self.blocks else self.mat.backend

    @property
    def element_names(self) -> str:
        """The element of every block, ``"p1"`` or ``"p1+p2"``."""
        return "+".join(dict.fromkeys(b.element.name for _, b in self.element_blocks()))

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
        if self.blocks:
            return all(b.allows_inversion for b in self.blocks)
        return bool(self.groups) and all(g.allows_inversion for g in self.groups)

    @property
    def n_vertices(self) -> int:
        """Number of vertices ``n``."""
        return int(self.X.shape[0])

    @property
    def n_tets(self) -> int:
        """Number of tets ``m``."""
        if self.blocks:
            return sum(b.n_tets for b in self.blocks)
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
        blocks : (m, d, d) float64
            ``d`` = :attr:`Element.n_dofs`.

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
        """``(m, d) int64`` element DOFs (:meth:`Element.element_dofs`), read-only."""
        dofs = self.element.element_dofs(self.T)
        dofs.setflags(write=False)
        return dofs

    @cached_property
    def dof_slots(self) -> np.ndarray:
        """``(m, d) int32`` :attr:`elem_dofs`: the fused gradient's scatter map."""
        if 3 * self.n_vertices > np.iinfo(np.int32).max:
            raise ValueError("more DOFs than int32 indexes")
        slots = (3 * self.T.astype(np.int32)[:, :, None]
                 + np.arange(3, dtype=np.int32)).reshape(-1, self.element.n_dofs)
        slots.setflags(write=False)
        return slots

    def assemble_vectors(self, vecs: np.ndarray) -> np.ndarray:
        """Sum of element vectors into the DOF vector.

        Parameters
        ----------
        vecs : (m, d) float64

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
        if self.blocks:  # every block alike; densities scaled by one factor
            stiff = material is not None or (E, nu) != (self.E, self.nu)
            blocks = tuple(b.with_material(E if stiff else None, nu if stiff else None,
                                           None if rho == self.rho else b.rho * (rho / self.rho),
                                           material=material) for b in self.blocks)
            return _mixed(blocks, self.spans, self.pattern, self.backend, self.psd_projection,
                          E=E if stiff else None, nu=nu if stiff else None)
        groups, mat, params = self.groups, self.mat, self.params
        if material is not None:
            groups = resolve_groups([MaterialGroup(material, None, {"E": E, "nu": nu})],
                                     self.n_tets, self.backend, None, self.element)
            mat, params = kernels_of(groups)
        elif (E, nu) != (self.E, self.nu):
            groups = tuple(with_E_nu(g, E, nu) for g in self.groups)
            mat, params = kernels_of(groups)
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


def with_psd_projection(model: Model, psd_projection: str) -> Model:
    """``model`` (and each of its element blocks) with another PSD projection."""
    blocks = tuple(replace(b, psd_projection=psd_projection) for b in model.blocks)
    return replace(model, psd_projection=psd_projection, blocks=blocks)


def mixed_model(blocks: Sequence[Model], spans: Sequence[slice]) -> Model:
    """The model of a mesh whose bodies mix elements, from one model per element block.

    Parameters
    ----------
    blocks : sequence of Model
        Each block's model (:func:`build_model` of the same ``X``, the block's elements in
        the whole mesh's node numbering), at least two.
    spans : sequence of slice
        Each block's range of elements in the scene's element order (consecutive, from 0).

    Returns
    -------
    Model
        :attr:`Model.blocks` these blocks, each moved onto the union of their sparsity
        patterns (its ``scatter`` remapped, its ``mass`` the block's own on the union); the
        mass is the sum of the blocks' and the summary ``E``, ``nu``, ``rho`` their
        volume-weighted means.
    """
    pattern, positions = merge_patterns([b.pattern for b in blocks])
    moved = []
    for b, pos in zip(blocks, positions, strict=True):
        scatter = pos[b.scatter]
        data = np.zeros(pattern.nnz)
        data[pos] = b.mass.data
        mass = sp.csr_matrix((data, pattern.indices, pattern.indptr), shape=pattern.shape)
        mass.has_sorted_indices = True
        _readonly(scatter, data)
        moved.append(replace(b, pattern=pattern, scatter=scatter, mass=mass))
    _readonly(pattern.indices, pattern.indptr)
    return _mixed(tuple(moved), tuple(spans), pattern, blocks[0].backend,
                  blocks[0].psd_projection)


def _mixed(blocks: tuple[Model, ...], spans: tuple[slice, ...], pattern: sp.csr_matrix,
           backend: str | None, psd_projection: str, *, E: float | None = None,
           nu: float | None = None) -> Model:
    """The mixed model of blocks already on ``pattern`` (``E, nu``: the summary when every
    block was given them, else the blocks' volume-weighted means)."""
    volumes = np.array([b.total_volume for b in blocks])

    def mean(values: list[float]) -> float:  # one value stays bit for bit itself
        if all(v == values[0] for v in values):
            return float(values[0])
        return float(np.dot(values, volumes) / volumes.sum())

    mass_data = blocks[0].mass.data.copy()
    for b in blocks[1:]:
        mass_data += b.mass.data
    mass = sp.csr_matrix((mass_data, pattern.indices, pattern.indptr), shape=pattern.shape)
    mass.has_sorted_indices = True
    vol = np.concatenate([b.vol.reshape(-1) for b in blocks])
    scatter = np.concatenate([b.scatter for b in blocks])
    density = None
    if any(b.density is not None for b in blocks):
        density = np.concatenate([b.density if b.density is not None
                                  else np.full(b.n_tets, b.rho) for b in blocks])
        _readonly(density)
    _readonly(mass.data, vol, scatter)
    names = [b.element.name for b in blocks]
    stand_in = {k: MixedElements(f"model.{k}", dict.fromkeys(names))
                for k in ("T", "dphi_dX", "params", "mat", "geo", "groups", "element")}
    return Model(
        X=blocks[0].X, vol=vol, material="+".join(dict.fromkeys(b.material for b in blocks)),
        E=mean([b.E for b in blocks]) if E is None else float(E),
        nu=mean([b.nu for b in blocks]) if nu is None else float(nu),
        rho=mean([b.rho for b in blocks]), mass=mass, pattern=pattern, scatter=scatter,
        backend=backend, density=density, psd_projection=psd_projection, blocks=blocks,
        spans=spans, **stand_in)


def _own_copy(a, dtype) -> np.ndarray:
    """``a`` as a C-ordered array of ``dtype`` the caller may make read-only: ``a`` itself
    when it is one already and read-only (a validated mesh's arrays), else a copy."""
    if isinstance(a, np.ndarray) and not a.flags.writeable and a.flags.c_contiguous and \
            (dtype is None or a.dtype == dtype) and a.base is None:
        return a
    return np.array(a, dtype=dtype, order="C")


def _mesh_arrays(X, T, el: Element, path: str | None) -> tuple[np.ndarray, np.ndarray]:
    """Own C-ordered copies of the rest positions ``(n, 3)`` and elements ``(m, k) int64``,
    checked (InputError names the vertex or element)."""
    X = _own_copy(X, np.float64)  # made read-only
    T = _own_copy(T, None)
    if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] < 4:
        raise InputError(f"X must have shape (n >= 4, 3), got {X.shape}", path=path)
    if not np.isfinite(X).all():
        bad = int(np.flatnonzero(~np.isfinite(X).all(axis=1))[0])
        raise InputError("vertex has a non-finite coordinate", path=path, element=bad)
    if T.ndim != 2 or T.shape[1] != el.n_nodes or T.shape[0] < 1:
        raise InputError(f"T must have shape (m >= 1, {el.n_nodes}), got {T.shape}", path=path)
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
    element: str | Element = "p1",
) -> Model:
    """Precompute everything about a mesh and its materials.

    Parameters
    ----------
    X : (n, 3) float64
        Rest positions.
    T : (m, k) int
        Elements of ``element`` (``k`` nodes, corners first), 0-based, positively oriented.
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
    element : str or Element, optional
        The finite element (:data:`fem3d.mesh.element.ELEMENTS`; default ``"p1"``): ``T`` has
        its number of nodes per row.

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
    el = _element_of(element)
    X, T = _mesh_arrays(X, T, el, path)
    geo, dphi_dX, vol = _rest_shape(el, X, T, backend, path)
    volumes = el.volumes(vol)
    resolved = resolve_groups(groups, T.shape[0], backend, path, el)
    mat, params = kernels_of(resolved)
    rho_e = None
    if per_element_density:
        rho_e = _element_density(density, volumes)
        rho = float((rho_e * volumes).sum() / volumes.sum())
    if given_E_nu is None:
        E, nu = summary_E_nu(resolved, volumes)

    _stages.debug("model: rest shape, materials")
    pattern, scatter = block_pattern(T, X.shape[0])
    _stages.debug("model: sparsity pattern")
    mass_data = assemble_mass(partial(el.mass_matrices, geo, X, T, volumes, rho, rho_e),
                              scatter, T, pattern.indptr)
    mass = sp.csr_matrix((mass_data, pattern.indices, pattern.indptr), shape=pattern.shape)
    mass.has_sorted_indices = True
    _readonly(X, T, dphi_dX, vol, mass.data, scatter, pattern.indices, pattern.indptr)
    material_name = "+".join(dict.fromkeys(g.material for g in resolved))
    _stages.debug("model: mass matrix")
    return Model(
        X=X, T=T, dphi_dX=dphi_dX, vol=vol, material=material_name, E=float(E), nu=float(nu),
        rho=float(rho), params=params, mat=mat, geo=geo, mass=mass, pattern=pattern,
        scatter=scatter, backend=backend, groups=resolved, density=rho_e, element=el,
    )


def _element_of(name: str | Element) -> Element:
    try:
        return elements.element(name)
    except ValueError as error:
        raise ParameterError(str(error)) from None


def _rest_shape(el: Element, X: np.ndarray, T: np.ndarray, backend: str | None,
                path: str | None) -> tuple[Any, np.ndarray, np.ndarray]:
    """The element's geometry kernels and their rest shape ``(dphi_dX, vol)`` of ``X[T]``;
    refuses an element whose volume (P1) or Jacobian at a quadrature point (P2) is not
    positive."""
    geo = el.geometry(backend)
    try:
        dphi_dX, vol = el.rest_shape(geo, X[T])
    except ValueError as error:  # a generated rest shape that refuses det J <= 0 itself
        hit = re.search(r"element (\d+)", str(error))
        raise InputError(f"{el.name} element has a non-positive Jacobian at a quadrature "
                         f"point: {error}", path=path,
                         element=int(hit.group(1)) if hit else None) from None
    dphi_dX = np.ascontiguousarray(dphi_dX, dtype=np.float64)
    vol = np.ascontiguousarray(vol, dtype=np.float64)
    bad = ~(vol > 0) if vol.ndim == 1 else ~(vol > 0).reshape(vol.shape[0], -1).all(axis=1)
    if bad.any():
        e = int(np.flatnonzero(bad)[0])
        what, which = (f"tet has non-positive volume {vol[e]:.3g}", "tets") if vol.ndim == 1 \
            else (f"{el.name} element has a non-positive Jacobian at a quadrature point (min "
                  f"{vol[e].min():.3g})", "elements")
        raise InputError(f"{what} (degenerate or inverted; {int(bad.sum())} such {which})",
                         path=path, element=e)
    return geo, dphi_dX, vol
