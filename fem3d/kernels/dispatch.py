"""Dispatch to the generated kernels: the C extension when built, NumPy otherwise.

Both back ends are rendered from the same kernel specs (see ``codegen``); this module only
validates arguments, allocates outputs and calls the back end :mod:`fem3d.kernels.backend`
chooses. Choose explicitly with the ``backend`` argument or the ``FEM3D_KERNELS``
environment variable (``numpy`` or ``c``).

Examples
--------
>>> nh = material_kernels("neo_hookean")
>>> H = nh.hessian(q[T], model.dphi_dX, model.vol, (C, D))    # (m, 12, 12)
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from functools import cache

import numpy as np

from fem3d._generated import MATERIALS, MODULES
from fem3d.errors import InputError
from fem3d.kernels.backend import c_extension, resolve_backend
from fem3d.kernels.schedule import schedule_for
from fem3d.kernels.threads import adaptive


class KernelModule:
    """The kernels of one generated module (a material, ``tet`` or ``spring``) on one back end.

    Every kernel is an attribute taking the per-element inputs, then (if the kernel has any)
    the parameters (``(n_params,)`` shared, or ``(m, n_params)`` per element), and returning
    its outputs with a leading element axis. The keyword
    ``out`` (an array, or a tuple of arrays for several outputs, of the result's shapes and
    float64) receives the results instead of new arrays: repeated calls on large meshes then
    skip the allocation and its page faults (the C back end writes straight into ``out``).
    """

    def __init__(self, name: str, backend: str) -> None:
        if name not in MODULES:
            raise ValueError(f"unknown kernel module {name!r}; available: {MODULES}")
        self.name = name
        self.backend = backend
        self._numpy = importlib.import_module(f"fem3d._generated.{name}")
        self.PARAM_NAMES: tuple[str, ...] = self._numpy.PARAM_NAMES
        self.SIGNATURES: dict = self._numpy.SIGNATURES
        for kernel in self.SIGNATURES:
            if backend == "numpy":
                function = _numpy_wrapper(getattr(self._numpy, kernel), name, kernel)
            else:
                function = _c_wrapper(name, kernel, self.SIGNATURES[kernel])
                fused = getattr(c_extension(), f"{name}_{kernel}_assemble", None)
                if fused is not None:
                    setattr(self, f"{kernel}_assemble",
                            _assemble_wrapper(fused, f"{name}.{kernel}"))
            setattr(self, kernel, function)

    def has_assemble(self, kernel: str) -> bool:
        """Whether ``<kernel>_assemble`` (fused gather-compute-scatter, C only) exists."""
        return hasattr(self, f"{kernel}_assemble")

    def __repr__(self) -> str:
        return f"KernelModule({self.name!r}, backend={self.backend!r})"


def _c_wrapper(module: str, kernel: str, signature: dict) -> Callable[..., object]:
    """Wrap one C kernel: validate and lay out inputs, allocate outputs, call, reshape."""
    ext = c_extension()
    function = getattr(ext, f"{module}_{kernel}", None)
    if function is None:  # an extension built before generated/ last changed
        raise InputError(
            f"the built C kernels (fem3d._ckernels) have no {module}.{kernel}: they are "
            "older than generated/; rebuild them (pip install -e . or make install), or run "
            "with FEM3D_KERNELS=numpy")
    inputs = signature["inputs"]
    outputs = signature["outputs"]
    n_params = len(signature["params"])
    qualified = f"{module}.{kernel}"

    def call(*args: object, out=None) -> np.ndarray | tuple[np.ndarray, ...]:
        expected = len(inputs) + (1 if n_params else 0)
        if len(args) != expected:
            raise TypeError(f"{qualified} takes {expected} arguments, got {len(args)}")
        arrays = []
        m = None
        for value, (name, shape) in zip(args, inputs, strict=False):
            a = np.ascontiguousarray(value, dtype=np.float64)
            size = int(np.prod(shape, dtype=np.int64))
            if a.ndim < 1 or a.ndim > 1 + len(shape) or (len(a) and a[0].size != size):
                raise ValueError(f"{qualified}: {name} must have shape (m, "
                                 f"{', '.join(map(str, shape))}), got {a.shape}")
            if m is None:
                m = a.shape[0]
            elif a.shape[0] != m:
                raise ValueError(f"{qualified}: {name} has {a.shape[0]} elements, expected {m}")
            arrays.append(a)
        params = np.asarray(args[len(inputs)] if n_params else (), dtype=np.float64)
        if params.ndim == 2 and params.shape == (m, n_params):  # per element
            params = np.ascontiguousarray(params)
        else:
            params = np.atleast_1d(params)
            if params.shape != (n_params,):
                raise ValueError(f"{qualified}: expected {n_params} parameters "
                                 f"{signature['params']} (or ({m}, {n_params}) per element), "
                                 f"got shape {params.shape}")
        shapes = [(m, *shape) for _, shape in outputs]
        if out is None:
            results = [np.empty(shape) for shape in shapes]
        else:
            results = _check_out(qualified, out, shapes)
        function(*arrays, params, *results)
        return results[0] if len(results) == 1 else tuple(results)

    call.__name__ = kernel
    call.__qualname__ = qualified
    call.__doc__ = f"C kernel {qualified}; same arguments and results as the NumPy kernel."
    return call


def _check_out(qualified: str, out, shapes: list[tuple[int, ...]]) -> list[np.ndarray]:
    """The ``out=`` arrays of a kernel call, checked against the result ``shapes``."""
    arrays = list(out) if isinstance(out, tuple | list) else [out]
    if len(arrays) != len(shapes):
        raise ValueError(f"{qualified}: out must hold {len(shapes)} arrays, got {len(arrays)}")
    for a, shape in zip(arrays, shapes, strict=True):
        if not (isinstance(a, np.ndarray) and a.dtype == np.float64 and a.shape == shape
                and a.flags.c_contiguous and a.flags.writeable):
            got = f"{a.dtype} {a.shape}" if isinstance(a, np.ndarray) else type(a).__name__
            raise ValueError(f"{qualified}: out must be a writable C-contiguous float64 array "
                             f"of shape {shape}, got {got}")
    return arrays


def _numpy_wrapper(function: Callable[..., object], module: str, kernel: str):
    """A generated NumPy kernel with the ``out=`` keyword of the C wrappers."""
    qualified = f"{module}.{kernel}"

    def call(*args: object, out=None):
        results = function(*args)
        if out is None:
            return results
        many = isinstance(results, tuple)
        values = list(results) if many else [results]
        arrays = _check_out(qualified, out, [v.shape for v in values])
        for a, v in zip(arrays, values, strict=True):
            a[...] = v
        return tuple(arrays) if many else arrays[0]

    call.__name__ = kernel
    call.__qualname__ = qualified
    call.__doc__ = function.__doc__
    return call


def _assemble_wrapper(fused: Callable[..., None], name: str) -> Callable[..., np.ndarray]:
    """``kernel_assemble(q, T, *inputs, params, index, out)``: adds every element's output into
    ``out[index[e]]``, gathering ``x_e = q[T[e]]`` itself (one pass, no temporaries).

    Meshes of at least :data:`fem3d.kernels.schedule.PARALLEL_MIN_TETS` tets whose ``T`` and
    ``index`` are read-only (a model's) run on OpenMP's threads along a race-free schedule
    built on the first call (:func:`fem3d.kernels.schedule.schedule_for`): the result does not
    depend on the thread count, which :func:`fem3d.kernels.threads.adaptive` chooses per kernel
    (``name``, e.g. ``neo_hookean.hessian``) from the times of its first calls (family
    ``"assembly"``; ``FEM3D_THREADS`` forces it). Other calls run serially in element order.

    Parameters
    ----------
    q : (n, 3) float64
    T : (m, k) int64
        The elements' ``k`` nodes (P1: 4, P2: 10).
    *inputs : the kernel's other per-element inputs (P1: ``dphi_dX (m, 4, 3)``, ``vol (m,)``;
        P2: per quadrature point), then the material's own, e.g. a fibre direction ``(m, 3)``
    params : (n_params,) or (m, n_params) float64
        Shared by every element, or per element.
    index : (m, size) int32
        Destination of each output entry in ``out`` (e.g. the CSR scatter map); other integer
        types are converted (ValueError when a value does not fit in int32).
    out : (N,) float64
        Accumulated into (not cleared) and returned.
    """
    key = f"assembly {name}"  # its thread count's key (fem3d.kernels.threads)

    def call(q, T, *rest):
        *inputs, params, index, out = rest
        T = np.ascontiguousarray(T, dtype=np.int64)
        index = _as_index32(index)
        schedule = schedule_for(T, index, out.size) if isinstance(out, np.ndarray) else None
        args = (
            np.ascontiguousarray(q, dtype=np.float64),
            T,
            *(np.ascontiguousarray(a, dtype=np.float64) for a in inputs),
            np.ascontiguousarray(np.atleast_1d(np.asarray(params, dtype=np.float64))),
            index,
            out,
        )
        if schedule is None:
            fused(*args)
        else:
            adaptive(key, "assembly", lambda n: fused(*args, *schedule.arrays(), n))
        return out

    call.__doc__ = _assemble_wrapper.__doc__
    return call


def _as_index32(index: np.ndarray) -> np.ndarray:
    """``index`` as C-contiguous int32 (the fused kernels' index type), range-checked."""
    index = np.asarray(index)
    if index.dtype == np.int32:
        return np.ascontiguousarray(index)
    if not np.issubdtype(index.dtype, np.integer):
        raise ValueError(f"index must hold integers, got dtype {index.dtype}")
    if index.size and (index.min() < 0 or index.max() > np.iinfo(np.int32).max):
        raise ValueError("index has an entry outside [0, 2**31)")
    return np.ascontiguousarray(index, dtype=np.int32)


@cache
def kernel_module(name: str, backend: str | None = None) -> KernelModule:
    """Kernels of generated module ``name`` on ``backend`` (see :func:`resolve_backend`)."""
    return KernelModule(name, resolve_backend(backend))


def material_kernels(name: str = "neo_hookean", backend: str | None = None) -> KernelModule:
    """Kernels of a material: ``psi``, ``dpsi_dF``, ``d2psi_dF2``, ``energy``, ``gradient``,
    ``hessian``. ``name`` is one of :data:`MATERIALS`."""
    if name not in MATERIALS:
        raise ValueError(f"unknown material {name!r}; available: {', '.join(MATERIALS)}")
    return kernel_module(name, resolve_backend(backend))


def geometry_kernels(backend: str | None = None) -> KernelModule:
    """Linear-tet kernels: ``rest_shape``, ``phi``, ``mass_matrix``, ``deformation_gradient``."""
    return kernel_module("tet", resolve_backend(backend))


def spring_kernels(backend: str | None = None) -> KernelModule:
    """Zero-rest-length spring kernels: ``energy``, ``gradient``, ``hessian``."""
    return kernel_module("spring", resolve_backend(backend))


def available_materials() -> Sequence[str]:
    """Names of the generated materials."""
    return MATERIALS


__all__ = [
    "MATERIALS",
    "KernelModule",
    "available_materials",
    "geometry_kernels",
    "kernel_module",
    "material_kernels",
    "spring_kernels",
]
