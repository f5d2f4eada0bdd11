"""The frozen model: everything about a mesh and its material that does not change per step.

A :class:`Model` is built once per mesh (:func:`build_model`) and holds

* the rest shape: ``X``, ``T``, the shape-function gradients ``dphi_dX`` and volumes ``vol``
  (from the generated geometry kernels);
* the material: name, ``E``, ``nu``, ``rho`` and the kernel parameters (Neo-Hookean
  ``C = 0.5 E / (2 (1 + nu))``, ``D = 0.5 E nu / ((1 + nu)(1 - 2 nu))``);
* the exact consistent mass matrix (generated ``mass_matrix`` kernel, assembled);
* the sparsity pattern of the ``3n x 3n`` system and two precomputed scatter maps:
  ``scatter`` sends the ``(m, 12, 12)`` element blocks straight into CSR ``data`` positions
  and ``elem_dofs`` sends ``(m, 12)`` element vectors into the ``3n`` DOF vector, so that an
  assembly is one ``np.bincount`` and the pattern is never rebuilt.

The stiffness and the mass matrix share the pattern, so ``M + dt^2 H`` is arithmetic on the
``data`` arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import scipy.sparse as sp

from fem3d.errors import InputError, ParameterError

__all__ = [
    "Model",
    "build_model",
    "material_parameters",
    "validate_material",
    "validate_dt",
    "element_dofs",
    "block_pattern",
]


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
        Material name (for messages).
    E, nu : float
        Young's modulus and Poisson's ratio (validated by :func:`validate_material`).
    param_names : tuple of str
        The material kernels' ``PARAM_NAMES``.

    Returns
    -------
    (n_params,) float64
        In ``param_names`` order. Known names: ``C = 0.5 E / (2 (1 + nu))`` (half the shear
        modulus ``mu``), ``D = 0.5 E nu / ((1 + nu)(1 - 2 nu))`` (half Lame's ``lambda``),
        ``mu`` and ``lambda`` / ``lam``.
    """
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    known = {"C": 0.5 * mu, "D": 0.5 * lam, "mu": mu, "lambda": lam, "lam": lam}
    missing = [p for p in param_names if p not in known]
    if missing:
        raise ParameterError(
            f"material {material!r} has parameters {param_names}; cannot derive "
            f"{missing} from E and nu"
        )
    return np.array([known[p] for p in param_names], dtype=np.float64)


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


def block_pattern(T: np.ndarray, n_vertices: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """CSR pattern of the ``3n x 3n`` element matrices of tets ``T`` and their scatter map.

    The pattern is found over vertex pairs (16 per tet) and expanded to 3x3 blocks, which needs
    about a ninth of the memory and time of sorting all 144 DOF pairs of every tet.

    Parameters
    ----------
    T : (m, 4) int64
        Tets.
    n_vertices : int
        Number of vertices ``n``; the matrices are ``N x N`` with ``N = 3 n`` (vertex-major
        DOFs, see :func:`element_dofs`).

    Returns
    -------
    pattern : (N, N) scipy.sparse.csr_matrix
        Canonical (sorted, no duplicates), ``data`` all zeros: every ``(3 i + c, 3 j + d)`` with
        vertices ``i, j`` in a common tet.
    scatter : (m * 144,) int32
        ``scatter[e * 144 + 12 r + s]`` is the ``data`` position of the entry of element DOFs
        ``(r, s)`` of tet ``e``, so ``np.bincount(scatter, blocks.ravel(), nnz)`` assembles
        ``(m, 12, 12)`` blocks. int32 halves the memory and the bandwidth of the fused C
        assembly, which reads it on every call.

    Raises
    ------
    ValueError
        More than ``2**31 - 1`` stored entries.
    """
    T = np.asarray(T, dtype=np.int64)
    m, corners = T.shape
    n = int(n_vertices)
    keys = (T[:, :, None] * n + T[:, None, :]).reshape(-1)
    pairs, block = np.unique(keys, return_inverse=True)
    del keys
    if 9 * pairs.size > np.iinfo(np.int32).max:
        raise ValueError(f"the sparsity pattern has {9 * pairs.size} entries, more than int32 "
                         "indexes")
    block_rows, block_cols = np.divmod(pairs, n)
    block_ptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(block_rows, minlength=n), out=block_ptr[1:])
    # number the block entries 1..9 nnzb, convert to CSR: its data says where each one lands
    numbered = np.arange(1, 9 * pairs.size + 1, dtype=np.float64).reshape(-1, 3, 3)
    csr = sp.bsr_matrix((numbered, block_cols, block_ptr), shape=(3 * n, 3 * n)).tocsr()
    where = np.empty(9 * pairs.size, dtype=np.int32)
    where[csr.data.astype(np.int64) - 1] = np.arange(csr.nnz, dtype=np.int32)
    # entry (3a + c, 3b + d) of tet e lives in block (T[e, a], T[e, b]) at (c, d)
    block = block.astype(np.int32).reshape(m, corners, 1, corners, 1)
    local = 3 * np.arange(3, dtype=np.int32)[:, None] + np.arange(3, dtype=np.int32)
    scatter = where[9 * block + local.reshape(1, 1, 3, 1, 3)].reshape(-1)
    pattern = sp.csr_matrix((np.zeros(csr.nnz), csr.indices.astype(np.int32),
                             csr.indptr.astype(np.int32)), shape=(3 * n, 3 * n))
    pattern.has_sorted_indices = True
    return pattern, scatter


def _readonly(*arrays: np.ndarray) -> None:
    for a in arrays:
        a.setflags(write=False)


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
        Material name in the kernel registry (``"neo_hookean"``).
    E, nu, rho : float
        Young's modulus, Poisson's ratio, density.
    params : (n_params,) float64
        Kernel parameters in the material's ``PARAM_NAMES`` order.
    mat : object
        Material kernels (``fem3d.kernels.material_kernels``).
    geo : object
        Geometry kernels.
    mass : (3n, 3n) scipy.sparse.csr_matrix
        Consistent mass matrix, on :attr:`pattern`'s sparsity.
    pattern : (3n, 3n) scipy.sparse.csr_matrix
        Shared sparsity pattern (data zeros).
    scatter : (m * 144,) int32
        Element-block to CSR-``data`` map (see :func:`block_pattern`).
    elem_dofs : (m, 12) int64
        Element DOFs; ``elem_dofs.ravel()`` is the ``(m * 12,)`` force scatter map.
    backend : str or None
        Kernel back end requested (None: automatic).
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
    elem_dofs: np.ndarray = field(repr=False)
    backend: str | None = None

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
        return np.zeros(self.n_tets, dtype=np.int32)

    @cached_property
    def element_slots(self) -> np.ndarray:
        """``(m,) int32`` ``0, 1, ..., m - 1``: a fused kernel's map for one value per element."""
        slots = np.arange(self.n_tets, dtype=np.int32)
        slots.setflags(write=False)
        return slots

    @cached_property
    def dof_slots(self) -> np.ndarray:
        """``(m, 12) int32`` copy of :attr:`elem_dofs`: the fused gradient's scatter map."""
        slots = self.elem_dofs.astype(np.int32)
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
        self, E: float | None = None, nu: float | None = None, rho: float | None = None
    ) -> Model:
        """A copy with new material values, sharing the mesh, pattern and scatter maps.

        Parameters
        ----------
        E, nu, rho : float, optional
            New values (None keeps the current one).
        """
        E, nu, rho = validate_material(
            self.E if E is None else E,
            self.nu if nu is None else nu,
            self.rho if rho is None else rho,
        )
        params = material_parameters(self.material, E, nu, tuple(self.mat.PARAM_NAMES))
        _readonly(params)
        mass = self.mass
        if rho != self.rho:
            mass = self.csr(self.mass.data * (rho / self.rho))  # M is linear in rho
            _readonly(mass.data)
        return Model(
            X=self.X, T=self.T, dphi_dX=self.dphi_dX, vol=self.vol, material=self.material,
            E=E, nu=nu, rho=rho, params=params, mat=self.mat, geo=self.geo, mass=mass,
            pattern=self.pattern, scatter=self.scatter, elem_dofs=self.elem_dofs,
            backend=self.backend,
        )


def build_model(
    X: np.ndarray,
    T: np.ndarray,
    *,
    E: float,
    nu: float,
    rho: float,
    material: str = "neo_hookean",
    backend: str | None = None,
    path: str | None = None,
) -> Model:
    """Precompute everything about a mesh and material.

    Parameters
    ----------
    X : (n, 3) float64
        Rest positions.
    T : (m, 4) int
        Tets, 0-based, positively oriented.
    E, nu, rho : float
        Young's modulus (> 0), Poisson's ratio (-1, 0.5), density (> 0).
    material : str, optional
        Registered material name (default ``"neo_hookean"``).
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
        Bad material values.
    InputError
        Bad arrays, a vertex index out of range, or a tet with non-positive volume.
    """
    from fem3d.kernels import geometry_kernels, material_kernels

    E, nu, rho = validate_material(E, nu, rho)
    X = np.array(X, dtype=np.float64, order="C")  # own copy: it is made read-only
    T = np.array(T, order="C")
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

    mat = material_kernels(material, backend=backend)
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
    params = material_parameters(material, E, nu, tuple(mat.PARAM_NAMES))

    dofs = element_dofs(T)
    pattern, scatter = block_pattern(T, X.shape[0])
    mass_blocks = geo.mass_matrix(vol, (rho,))
    mass_data = np.bincount(scatter, weights=mass_blocks.reshape(-1), minlength=pattern.nnz)
    mass = sp.csr_matrix((mass_data, pattern.indices, pattern.indptr), shape=pattern.shape)
    mass.has_sorted_indices = True
    _readonly(X, T, dphi_dX, vol, params, mass.data, scatter, dofs,
              pattern.indices, pattern.indptr)
    return Model(
        X=X, T=T, dphi_dX=dphi_dX, vol=vol, material=material, E=E, nu=nu, rho=rho,
        params=params, mat=mat, geo=geo, mass=mass, pattern=pattern, scatter=scatter,
        elem_dofs=dofs, backend=backend,
    )
