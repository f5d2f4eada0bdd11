"""fem3d benchmark suite (run by hand: ``python -m bench`` or ``make bench``; never in CI).

Layout
------
``bench/__init__.py``      the case registry (:func:`register`, :data:`CASES`), :class:`BenchMesh`
``bench/meshes.py``        box tet meshes of a given size, the linear-elastic test system
``bench/cases_fem3d.py``   fem3d's own rows (kernels, assembly, linear solvers, integrators)
``bench/peers/*.py``       peers: plain NumPy/SciPy, NVIDIA Warp (CPU), pbatoolkit
``bench/worker.py``        runs ONE case at ONE size in its own process (peak RSS is per process)
``bench/report.py``        JSON lines -> Markdown table with ratios + log-log plot
``bench/__main__.py``      the command line

A *case* is ``(name, group, library, setup)``: ``setup(mesh) -> fn`` builds everything that is
not timed and returns a zero-argument callable that does the timed work. Cases in the same
*group* do the same work and are compared in one table; rows whose library starts with
``fem3d`` are the reference of the ratios. Optional dependencies are imported inside ``setup``;
a missing one raises :class:`Skip`, printed as a note.

Adding a row: in any module listed in :data:`CASE_MODULES`::

    @register("energy/mylib", group="energy", library="mylib", requires=("mylib",))
    def _setup(mesh: BenchMesh):
        model = mylib.build(mesh.X, mesh.T)
        return lambda: model.energy(mesh.q)
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

#: Commands whose figures are per core (``python -m bench.tools.contact_check`` ...): one thread
#: unless the caller says otherwise. Set here, before this package imports NumPy and with it
#: the BLAS that reads the variables once (a module's own ``__main__`` block comes too late).
ONE_CORE_COMMANDS = frozenset({"bench.adjoint", "bench.contact", "bench.tools.contact_check",
                               "bench.tools.path_check", "bench.tools.pile_check"})
_argv = getattr(sys, "orig_argv", [])
if "-m" in _argv[:-1] and _argv[_argv.index("-m") + 1] in ONE_CORE_COMMANDS:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

#: What each group measures (the tables' captions), in report order.
GROUPS: dict[str, str] = {
    "energy": "total strain energy V(q) = sum_e vol_e psi(F_e) (scalar)",
    "gradient": "assembled gradient dV/dq, (3n,)",
    "hessian_elements": "element Hessians d2(vol psi)/dx_e2, (m, 12, 12)",
    "hessian_csr": "assembled Hessian as a (3n, 3n) CSR matrix (element kernels included)",
    "analyze": "symbolic analysis (fill-reducing ordering) of A = M + dt^2 K, free DOFs",
    "factor": "numeric factorization of A = M + dt^2 K on the free DOFs (box clamped at z=0)",
    "solve": "one solve with that factorization",
    "step": "one backward-Euler time step (Newton iterations included)",
}

#: Modules that register cases, imported by :func:`load_cases`.
CASE_MODULES: tuple[str, ...] = (
    "bench.cases_fem3d",
    "bench.peers.baseline_numpy",
    "bench.peers.warp_nh",
    "bench.peers.pbatoolkit_nh",
)


class Skip(Exception):
    """Raised by a case's setup when it cannot run here (missing package, size limit)."""


@dataclass(frozen=True)
class Case:
    """One benchmark row.

    Attributes
    ----------
    name : str
        Unique, ``"group/library"`` by convention.
    group : str
        Key of :data:`GROUPS`.
    library : str
        Row label; ``fem3d...`` rows are the ratio reference.
    setup : callable
        ``setup(mesh: BenchMesh) -> fn``; ``fn()`` is timed. ``setup`` raises :class:`Skip`.
    requires : tuple of str
        Importable modules needed (checked before starting a worker).
    max_tets : float
        Larger sizes are skipped (too slow or too much memory on 2 cores / 24 GiB).
    note : str
        Shown under the table.
    warmup_required : bool
        The first call does extra one-off work (JIT, ordering), so it is never used as a
        sample, even when it is slower than the time budget.
    """

    name: str
    group: str
    library: str
    setup: Callable[[BenchMesh], Callable[[], object]]
    requires: tuple[str, ...] = ()
    max_tets: float = float("inf")
    note: str = ""
    warmup_required: bool = False

    @property
    def is_fem3d(self) -> bool:
        return self.library.startswith("fem3d")

    def missing(self) -> list[str]:
        """Required modules that are not importable."""
        return [m for m in self.requires if importlib.util.find_spec(m) is None]


CASES: dict[str, Case] = {}


def register(
    name: str,
    *,
    group: str,
    library: str,
    requires: tuple[str, ...] = (),
    max_tets: float = float("inf"),
    note: str = "",
    warmup_required: bool = False,
) -> Callable[[Callable[[BenchMesh], Callable[[], object]]], Callable]:
    """Decorator registering ``setup`` as a :class:`Case`."""
    if group not in GROUPS:
        raise ValueError(f"unknown benchmark group {group!r}; add it to bench.GROUPS")

    def deco(setup: Callable[[BenchMesh], Callable[[], object]]) -> Callable:
        if name in CASES:
            raise ValueError(f"benchmark case {name!r} registered twice")
        CASES[name] = Case(name, group, library, setup, requires, max_tets, note,
                           warmup_required)
        return setup

    return deco


def load_cases() -> dict[str, Case]:
    """Import every module of :data:`CASE_MODULES` (they register their cases)."""
    for mod in CASE_MODULES:
        importlib.import_module(mod)
    return CASES


# ---------------------------------------------------------------------------------- problem
#: Material and time step of the armadillo scene (shared/README.md).
E_YOUNG, NU, RHO, DT = 6e5, 0.4, 0.1, 0.01


def nh_params(E: float = E_YOUNG, nu: float = NU) -> tuple[float, float]:
    """Neo-Hookean ``(C, D)`` as the classic assignment defines them."""
    C = 0.5 * E / (2.0 * (1.0 + nu))
    D = 0.5 * E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return C, D


@dataclass
class BenchMesh:
    """A box mesh of about ``size`` tets, a deformed state, and the solver test system.

    Attributes
    ----------
    size : float
        Requested tet count.
    X : (n, 3) float64
        Rest positions (unit cube).
    T : (m, 4) int64
        Positively oriented tets.
    q : (n, 3) float64
        Deformed positions: a homogeneous stretch/shear plus a small smooth perturbation
        (every ``J > 0``), so that nothing is evaluated at the trivial rest state.
    params : (2,) float64
        Neo-Hookean ``(C, D)``.
    """

    size: float
    X: np.ndarray
    T: np.ndarray
    q: np.ndarray
    params: np.ndarray
    E: float = E_YOUNG
    nu: float = NU
    rho: float = RHO
    dt: float = DT
    _cache: dict = field(default_factory=dict, repr=False)

    @classmethod
    def make(cls, size: float) -> BenchMesh:
        from bench.meshes import box_mesh

        X, T = box_mesh(size)
        F0 = np.array([[1.10, 0.05, 0.00], [0.00, 0.95, 0.02], [0.01, 0.00, 1.03]])
        q = X @ F0.T + 0.01 * np.sin(6.0 * X[:, [1, 2, 0]])
        return cls(size=size, X=X, T=T, q=q, params=np.array(nh_params()))

    @property
    def n_tets(self) -> int:
        return int(self.T.shape[0])

    @property
    def n_vertices(self) -> int:
        return int(self.X.shape[0])

    @cached_property
    def rest(self) -> tuple[np.ndarray, np.ndarray]:
        """``(dphi_dX (m, 4, 3), vol (m,))``."""
        from bench.meshes import rest_shape

        return rest_shape(self.X, self.T)

    @cached_property
    def system(self):
        """:class:`bench.meshes.LinearSystem` (A = M + dt^2 K on the free DOFs, SPD)."""
        from bench.meshes import linear_elastic_system

        return linear_elastic_system(self.X, self.T, E=self.E, nu=self.nu, rho=self.rho,
                                     dt=self.dt)
