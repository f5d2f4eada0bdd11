"""Peer: NVIDIA Warp kernels on the CPU (float64), hand-derived Neo-Hookean.

Same energy as the other rows, ``psi = C (J^(-2/3) tr(F^T F) - 3) + D (J - 1)^2``. The Hessian
is written in 3x3 blocks, never forming the 9x9 ``d2psi/dF2``: with ``g = cof(F)``,
``f_a = F dphi_a``, ``g_a = g dphi_a``, ``a = J^(-2/3)``, ``b = J^(-5/3)``, ``c = J^(-8/3)``,

    H_ab / vol = 2 C a (dphi_a . dphi_b) I - (4/3) C b (f_a g_b^T + g_a f_b^T)
                 + ((10/9) C I1 c + 2 D) g_a g_b^T + s E(F (dphi_a x dphi_b)),

``s = 2 D (J - 1) - (2/3) C I1 b`` and ``E(w)[k, l] = eps_klq w_q`` (the contraction of
``d2 det/dF2`` with the two shape gradients).

Kernels: per-element energy (summed on the host), gradient with ``atomic_add`` into the vertex
array, element Hessians ``(m, 12, 12)``, and the CSR Hessian by ``atomic_add`` into the
``data`` array through a precomputed element-entry -> CSR-slot map.
Warp compiles the kernels on first use (cached in ~/.cache/warp); the worker's warm-up call
keeps that out of the timings.
"""

# No "from __future__ import annotations": Warp evaluates kernel annotations itself.

import numpy as np
import scipy.sparse as sp

from bench import BenchMesh, Skip, register

LIB = "warp-cpu"
_K: dict | None = None


def _kernels() -> dict:
    """Define the Warp kernels (once, on first use: importing warp is slow)."""
    global _K
    if _K is not None:
        return _K
    try:
        import warp as wp
    except ImportError as err:
        raise Skip("warp-lang not installed (pip install warp-lang)") from err
    wp.config.quiet = True
    wp.init()
    f64 = wp.float64

    @wp.func
    def def_grad(q: wp.array(dtype=wp.vec3d), T: wp.array2d(dtype=wp.int32),
                 dphi: wp.array2d(dtype=wp.vec3d), e: int):
        F = wp.mat33d()
        for a in range(4):
            F += wp.outer(q[T[e, a]], dphi[e, a])
        return F

    @wp.func
    def cofactor(F: wp.mat33d):
        f0 = wp.vec3d(F[0, 0], F[1, 0], F[2, 0])
        f1 = wp.vec3d(F[0, 1], F[1, 1], F[2, 1])
        f2 = wp.vec3d(F[0, 2], F[1, 2], F[2, 2])
        c0 = wp.cross(f1, f2)
        c1 = wp.cross(f2, f0)
        c2 = wp.cross(f0, f1)
        return wp.mat33d(c0[0], c1[0], c2[0], c0[1], c1[1], c2[1], c0[2], c1[2], c2[2])

    @wp.func
    def eps_w(w: wp.vec3d):
        z = f64(0.0)
        return wp.mat33d(z, w[2], -w[1], -w[2], z, w[0], w[1], -w[0], z)

    @wp.kernel
    def energy_k(q: wp.array(dtype=wp.vec3d), T: wp.array2d(dtype=wp.int32),
                 dphi: wp.array2d(dtype=wp.vec3d), vol: wp.array(dtype=f64), C: f64, D: f64,
                 out: wp.array(dtype=f64)):
        e = wp.tid()
        F = def_grad(q, T, dphi, e)
        J = wp.determinant(F)
        I1 = wp.ddot(F, F)
        a = wp.pow(J, f64(-2.0) / f64(3.0))
        out[e] = vol[e] * (C * (a * I1 - f64(3.0)) + D * (J - f64(1.0)) * (J - f64(1.0)))

    @wp.kernel
    def gradient_k(q: wp.array(dtype=wp.vec3d), T: wp.array2d(dtype=wp.int32),
                   dphi: wp.array2d(dtype=wp.vec3d), vol: wp.array(dtype=f64), C: f64, D: f64,
                   grad: wp.array(dtype=wp.vec3d)):
        e = wp.tid()
        F = def_grad(q, T, dphi, e)
        g = cofactor(F)
        J = wp.determinant(F)
        I1 = wp.ddot(F, F)
        a = wp.pow(J, f64(-2.0) / f64(3.0))
        b = a / J
        P = (f64(2.0) * C * a) * F + (
            f64(-2.0) / f64(3.0) * C * I1 * b + f64(2.0) * D * (J - f64(1.0))) * g
        for v in range(4):
            wp.atomic_add(grad, T[e, v], vol[e] * (P * dphi[e, v]))

    @wp.func
    def hess_block(F: wp.mat33d, g: wp.mat33d, da: wp.vec3d, db: wp.vec3d, k0: f64, k1: f64,
                   k2: f64, s: f64):
        fa = F * da
        fb = F * db
        ga = g * da
        gb = g * db
        eye3 = wp.identity(n=3, dtype=f64)
        H = (k0 * wp.dot(da, db)) * eye3 - k1 * (wp.outer(fa, gb) + wp.outer(ga, fb))
        H += k2 * wp.outer(ga, gb) + s * eps_w(F * wp.cross(da, db))
        return H

    @wp.func
    def hess_coeffs(F: wp.mat33d, C: f64, D: f64):
        J = wp.determinant(F)
        I1 = wp.ddot(F, F)
        a = wp.pow(J, f64(-2.0) / f64(3.0))
        b = a / J
        c = b / J
        k0 = f64(2.0) * C * a
        k1 = f64(4.0) / f64(3.0) * C * b
        k2 = f64(10.0) / f64(9.0) * C * I1 * c + f64(2.0) * D
        s = f64(2.0) * D * (J - f64(1.0)) - f64(2.0) / f64(3.0) * C * I1 * b
        return wp.vec4d(k0, k1, k2, s)

    @wp.kernel
    def hessian_k(q: wp.array(dtype=wp.vec3d), T: wp.array2d(dtype=wp.int32),
                  dphi: wp.array2d(dtype=wp.vec3d), vol: wp.array(dtype=f64), C: f64, D: f64,
                  He: wp.array3d(dtype=f64)):
        e = wp.tid()
        F = def_grad(q, T, dphi, e)
        g = cofactor(F)
        k = hess_coeffs(F, C, D)
        for A in range(4):
            for B in range(4):
                H = vol[e] * hess_block(F, g, dphi[e, A], dphi[e, B], k[0], k[1], k[2], k[3])
                for i in range(3):
                    for j in range(3):
                        He[e, 3 * A + i, 3 * B + j] = H[i, j]

    @wp.kernel
    def hessian_csr_k(q: wp.array(dtype=wp.vec3d), T: wp.array2d(dtype=wp.int32),
                      dphi: wp.array2d(dtype=wp.vec3d), vol: wp.array(dtype=f64), C: f64,
                      D: f64, slot: wp.array3d(dtype=wp.int32), data: wp.array(dtype=f64)):
        e = wp.tid()
        F = def_grad(q, T, dphi, e)
        g = cofactor(F)
        k = hess_coeffs(F, C, D)
        for A in range(4):
            for B in range(4):
                H = vol[e] * hess_block(F, g, dphi[e, A], dphi[e, B], k[0], k[1], k[2], k[3])
                for i in range(3):
                    for j in range(3):
                        wp.atomic_add(data, slot[e, 3 * A + i, 3 * B + j], H[i, j])

    _K = dict(wp=wp, energy=energy_k, gradient=gradient_k, hessian=hessian_k,
              hessian_csr=hessian_csr_k)
    return _K


class WarpNeoHookean:
    """Warp arrays of one mesh and the four operations (device ``"cpu"``).

    Parameters
    ----------
    X : (n, 3) float64
    T : (m, 4) int64
    C, D : float
    """

    def __init__(self, X: np.ndarray, T: np.ndarray, C: float, D: float) -> None:
        from bench.meshes import rest_shape

        self.k = _kernels()
        wp = self.k["wp"]
        self.wp = wp
        dev = "cpu"
        dphi, vol = rest_shape(X, T)
        self.m, self.n = len(T), len(X)
        self.C, self.D = float(C), float(D)
        self.T = wp.array(T.astype(np.int32), dtype=wp.int32, device=dev)
        self.dphi = wp.array(dphi, dtype=wp.vec3d, device=dev)
        self.vol = wp.array(vol, dtype=wp.float64, device=dev)
        self.q = wp.zeros(self.n, dtype=wp.vec3d, device=dev)
        self.e_out = wp.zeros(self.m, dtype=wp.float64, device=dev)
        self.grad = wp.zeros(self.n, dtype=wp.vec3d, device=dev)
        self._He = None
        self._csr = None
        self.dev = dev

    def _set_q(self, q: np.ndarray) -> None:
        self.q.numpy()[:] = q  # zero-copy view on the CPU

    def _args(self):
        return [self.q, self.T, self.dphi, self.vol, self.C, self.D]

    def energy(self, q: np.ndarray) -> float:
        self._set_q(q)
        self.wp.launch(self.k["energy"], dim=self.m, inputs=[*self._args(), self.e_out],
                       device=self.dev)
        return float(self.e_out.numpy().sum())

    def gradient(self, q: np.ndarray) -> np.ndarray:
        self._set_q(q)
        self.grad.zero_()
        self.wp.launch(self.k["gradient"], dim=self.m, inputs=[*self._args(), self.grad],
                       device=self.dev)
        return self.grad.numpy().reshape(-1)

    def element_hessians(self, q: np.ndarray) -> np.ndarray:
        if self._He is None:
            self._He = self.wp.zeros((self.m, 12, 12), dtype=self.wp.float64, device=self.dev)
        self._set_q(q)
        self.wp.launch(self.k["hessian"], dim=self.m, inputs=[*self._args(), self._He],
                       device=self.dev)
        return self._He.numpy()

    def _prepare_csr(self, T: np.ndarray) -> None:
        from bench.meshes import element_dofs

        wp = self.wp
        dofs = element_dofs(T)
        N = 3 * self.n
        rows = np.broadcast_to(dofs[:, :, None], (self.m, 12, 12)).ravel()
        cols = np.broadcast_to(dofs[:, None, :], (self.m, 12, 12)).ravel()
        keys = rows.astype(np.int64) * N + cols
        uniq, slot = np.unique(keys, return_inverse=True)
        r, c = np.divmod(uniq, N)
        indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=N))])
        self._indices, self._indptr = c.astype(np.int32), indptr.astype(np.int32)
        self._slot = wp.array(slot.reshape(self.m, 12, 12).astype(np.int32), dtype=wp.int32,
                              device=self.dev)
        self._data = wp.zeros(len(uniq), dtype=wp.float64, device=self.dev)
        self._csr = True

    def hessian(self, q: np.ndarray, T: np.ndarray) -> sp.csr_matrix:
        if self._csr is None:
            self._prepare_csr(T)
        self._set_q(q)
        self._data.zero_()
        self.wp.launch(self.k["hessian_csr"], dim=self.m,
                       inputs=[*self._args(), self._slot, self._data], device=self.dev)
        N = 3 * self.n
        return sp.csr_matrix((self._data.numpy(), self._indices, self._indptr), shape=(N, N))


def _model(mesh: BenchMesh) -> WarpNeoHookean:
    C, D = mesh.params
    return WarpNeoHookean(mesh.X, mesh.T, C, D)


# the first launch compiles (or loads from ~/.cache/warp) the kernels: never a sample
_KW = dict(library=LIB, requires=("warp",), warmup_required=True)
_NOTE = "warp-cpu: NVIDIA Warp kernels (float64) on the CPU device, hand-derived Hessian blocks."


@register("energy/warp-cpu", group="energy", note=_NOTE, **_KW)
def _energy(mesh: BenchMesh):
    w = _model(mesh)
    return lambda: w.energy(mesh.q)


@register("gradient/warp-cpu", group="gradient", **_KW)
def _gradient(mesh: BenchMesh):
    w = _model(mesh)
    return lambda: w.gradient(mesh.q)


@register("hessian_elements/warp-cpu", group="hessian_elements", **_KW)
def _hess_e(mesh: BenchMesh):
    w = _model(mesh)
    return lambda: w.element_hessians(mesh.q)


@register("hessian_csr/warp-cpu", group="hessian_csr", **_KW)
def _hess_csr(mesh: BenchMesh):
    w = _model(mesh)
    w._prepare_csr(mesh.T)
    return lambda: w.hessian(mesh.q, mesh.T)
