"""Peer: pbatoolkit's hyperelastic potential (C++ with Python bindings).

pbatoolkit 0.0.11 offers Saint-Venant-Kirchhoff and *Stable* Neo-Hookean (Smith et al. 2018),
not the classic ``C (J^(-2/3) I1 - 3) + D (J - 1)^2``; Stable Neo-Hookean is the closest and costs
about the same per element, so its numbers compare the machinery (element loop, assembly into
CSR) rather than the exact same arithmetic. Lame ``mu = 2 C``, ``lambda = 2 D`` to match the
classic model's small-strain behaviour. No SPD projection (``NoCorrection``), like the others.

``hyper_elastic_potential`` always returns the assembled global gradient / CSR Hessian; the
"hessian_elements" group has no pbatoolkit row.
"""

from __future__ import annotations

import numpy as np

from bench import BenchMesh, Skip, register

LIB = "pbatoolkit"
_NOTE = ("pbatoolkit: 0.0.11 has Stable Neo-Hookean only (not the classic model), "
         "mu = 2C, lambda = 2D; its energy, gradient and Hessian calls assemble globally.")


class PbatNeoHookean:
    """pbatoolkit FEM data for one mesh.

    Parameters
    ----------
    X : (n, 3) float64
    T : (m, 4) int64
    C, D : float
    """

    def __init__(self, X: np.ndarray, T: np.ndarray, C: float, D: float) -> None:
        try:
            import pbatoolkit as pbat
        except ImportError as err:
            raise Skip("pbatoolkit not installed (pip install pbatoolkit)") from err
        fem = pbat.pbat.fem
        self.fem = fem
        self.element = fem.Element.Tetrahedron
        V = np.asfortranarray(X.T)
        Cells = np.asfortranarray(T.T.astype(np.int64))
        self.Xn, self.E = fem.mesh(V, Cells, element=self.element, order=1)
        self.n = self.Xn.shape[1]
        wg = fem.mesh_quadrature_weights(self.E, self.Xn, self.element, order=1,
                                         quadrature_order=1)
        eg = fem.mesh_quadrature_elements(self.E, wg)
        self.wg = np.ravel(wg)
        self.eg = np.ravel(eg)
        self.GNeg = fem.shape_function_gradients(self.E, self.Xn, element=self.element, order=1,
                                                 dims=3, quadrature_order=1)
        self.mug = np.full(self.wg.shape, 2.0 * C)
        self.lambdag = np.full(self.wg.shape, 2.0 * D)
        self.flags = fem.ElementElasticityComputationFlags

    def _call(self, q: np.ndarray, flags):
        x = np.ascontiguousarray(q, dtype=np.float64).reshape(-1)  # vertex-major = order "F"
        return self.fem.hyper_elastic_potential(
            E=self.E, n_nodes=self.n, eg=self.eg, wg=self.wg, GNeg=self.GNeg, mug=self.mug,
            lambdag=self.lambdag, x=x, energy=self.fem.HyperElasticEnergy.StableNeoHookean,
            flags=flags, spd_correction=self.fem.HyperElasticSpdCorrection.NoCorrection,
            element=self.element, order=1, dims=3,
        )

    def energy(self, q: np.ndarray) -> float:
        return float(self._call(q, self.flags.Potential)[0])

    def gradient(self, q: np.ndarray) -> np.ndarray:
        return self._call(q, self.flags.Gradient)[1]

    def hessian(self, q: np.ndarray):
        return self._call(q, self.flags.Hessian)[2]


def _model(mesh: BenchMesh) -> PbatNeoHookean:
    C, D = mesh.params
    return PbatNeoHookean(mesh.X, mesh.T, float(C), float(D))


@register("energy/pbatoolkit", group="energy", library=LIB, requires=("pbatoolkit",),
          note=_NOTE)
def _energy(mesh: BenchMesh):
    p = _model(mesh)
    return lambda: p.energy(mesh.q)


@register("gradient/pbatoolkit", group="gradient", library=LIB, requires=("pbatoolkit",))
def _gradient(mesh: BenchMesh):
    p = _model(mesh)
    return lambda: p.gradient(mesh.q)


@register("hessian_csr/pbatoolkit", group="hessian_csr", library=LIB, requires=("pbatoolkit",))
def _hess_csr(mesh: BenchMesh):
    p = _model(mesh)
    return lambda: p.hessian(mesh.q)
