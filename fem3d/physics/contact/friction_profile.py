"""Smoothed Coulomb friction of point-plane contacts, with static and kinetic coefficients.

IPC's lagged friction (Li et al. 2020) is ``sum_k lambda_k F(|u_k|)`` over the contact pairs,
``u_k`` the tangential slip over the step and ``lambda_k`` the lagged normal force. With one
coefficient ``mu``, ``F = mu f0`` and ``f0`` is IPC's mollifier (``f1 = f0'`` rises from 0 to 1
over the slip ``eps = eps_v dt``: static friction below it).

With ``mu_s > mu_k`` the friction force per unit normal force is

* ``g(y) = mu_s f1(y)`` for ``y < eps`` (static: up to ``mu_s`` at ``eps``, so a load below
  ``mu_s lambda`` holds);
* ``g(y) = mu_k + (mu_s - mu_k) (1 - 3 t^2 + 2 t^3)``, ``t = (y - eps) / eps``, for
  ``eps <= y < 2 eps`` (a C1 fall from ``mu_s`` to ``mu_k``);
* ``g(y) = mu_k`` beyond (kinetic).

``F`` is the integral of ``g``, so the friction stays a potential (the Hessian's part along the
slip, ``g'``, is negative in the transition; the per-pair PSD projection clamps it). ipctk 1.6.1
has its own static-to-kinetic blend (``ipctk.smooth_mu``), from ``mu_s`` at zero slip to
``mu_k`` at ``eps``: multiplied by ``f1``, its largest force is well below ``mu_s`` (``0.34``
for ``mu_s = 0.6, mu_k = 0.3``), so it holds a block only up to about that; the mesh-mesh pairs
use it (``ipctk.TangentialCollisions.build(..., mu_s, mu_k)``), the planes use ``g`` above.

With ``mu_s == mu_k`` every function here computes what fem3d computed before the two
coefficients existed, operation for operation.
"""

from __future__ import annotations

import numpy as np

__all__ = ["friction_profile", "point_plane_friction"]


def friction_profile(y: np.ndarray, eps: float, mu_s: float, mu_k: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``F(y)``, ``g(y) / y`` and ``g'(y) - g(y) / y`` of the smoothed friction (see the
    module), elementwise over slips ``y >= 0``.

    Returns
    -------
    F, g_over_y, c2 : ndarray
        ``g_over_y`` at ``y = 0`` is its limit ``2 mu_s / eps``; ``c2`` is what multiplies
        ``uh uh^T`` in the Hessian ``lambda (g / y P + c2 uh uh^T)``.
    """
    small = y < eps
    f0 = np.where(small, -y ** 3 / (3 * eps * eps) + y * y / eps + eps / 3, y)
    f1_y = np.where(small, -y / (eps * eps) + 2.0 / eps, 1.0 / np.maximum(y, eps))
    yy = np.where(y > 0, y, 1.0)
    c2 = np.where(small, -y / (eps * eps), -1.0 / yy)
    if mu_s == mu_k:
        return mu_s * f0, mu_s * f1_y, mu_s * c2
    t = np.clip((y - eps) / eps, 0.0, 1.0)
    blend = t - t ** 3 + 0.5 * t ** 4  # integral of 1 - 3 t^2 + 2 t^3
    F = np.where(small, mu_s * f0,
                 mu_s * eps + mu_k * (y - eps) + (mu_s - mu_k) * eps * blend)
    g = mu_k + (mu_s - mu_k) * (1.0 - 3.0 * t * t + 2.0 * t ** 3)
    dg = (mu_s - mu_k) * (-6.0 * t + 6.0 * t * t) / eps
    g_y = np.where(small, mu_s * f1_y, g / yy)
    c2 = np.where(small, mu_s * c2, dg - g / yy)
    return F, g_y, c2


def point_plane_friction(n: np.ndarray, w: np.ndarray, lam: np.ndarray, eps: float,
                         mu_s: float, mu_k: float, order: int, *,
                         project: bool | str = True):
    """Lagged point-plane friction ``sum lambda F(|P w|)`` of points displaced by ``w``
    (``(k, 3)``) from their lagged positions, against planes of unit normals ``n``
    (``(k, 3)``; ``P = I - n n^T``), normal forces ``lam`` (``(k,)``).

    Returns
    -------
    float, (k, 3) or (k, 3, 3)
        The energy (``order`` 0), each point's gradient (1) or Hessian block (2,
        PSD-projected when ``project``: negative eigenvalues clamped at zero, or mirrored to
        their absolute value when ``project == "abs"``).
    """
    u = w - (w * n).sum(axis=1, keepdims=True) * n
    y = np.sqrt((u * u).sum(axis=1))
    if mu_s == mu_k:  # the one-coefficient friction, as before mu_s and mu_k
        return _single(n, u, y, lam, eps, mu_s, order, project)
    F, g_y, c2 = friction_profile(y, eps, mu_s, mu_k)
    if order == 0:
        return float((lam * F).sum())
    if order == 1:
        return (lam * g_y)[:, None] * u
    pos = y > 0
    uh = np.where(pos[:, None], u / np.where(pos, y, 1.0)[:, None], 0.0)
    Pm = np.eye(3) - n[:, :, None] * n[:, None, :]
    blocks = lam[:, None, None] * (g_y[:, None, None] * Pm
                                   + c2[:, None, None] * uh[:, :, None] * uh[:, None, :])
    return _project(blocks, project == "abs") if project else blocks


def _single(n, u, y, lam, eps, mu, order, project):
    """``mu_s == mu_k``: IPC's friction with one coefficient."""
    small = y < eps
    ml = mu * lam
    if order == 0:
        f0 = np.where(small, -y ** 3 / (3 * eps * eps) + y * y / eps + eps / 3, y)
        return float((ml * f0).sum())
    f1_y = np.where(small, -y / (eps * eps) + 2.0 / eps, 1.0 / np.maximum(y, eps))
    if order == 1:
        return (ml * f1_y)[:, None] * u
    # (f2 - f1 / y) u u^T / y^2 = c2 uh uh^T, uh = u / y: c2 = -y / eps^2 when slipping
    # slowly, -1 / y when sliding
    pos = y > 0
    yy = np.where(pos, y, 1.0)
    uh = np.where(pos[:, None], u / yy[:, None], 0.0)
    c2 = np.where(small, -y / (eps * eps), -1.0 / yy)
    Pm = np.eye(3) - n[:, :, None] * n[:, None, :]
    blocks = ml[:, None, None] * (f1_y[:, None, None] * Pm
                                  + c2[:, None, None] * uh[:, :, None] * uh[:, None, :])
    return _project(blocks, project == "abs") if project else blocks


def _project(blocks: np.ndarray, mirror: bool = False) -> np.ndarray:
    """Eigenvalues of each symmetric block clamped at zero (``mirror``: made absolute)."""
    w_, V_ = np.linalg.eigh(blocks)
    w_ = np.abs(w_) if mirror else np.maximum(w_, 0.0)
    return (V_ * w_[:, None, :]) @ V_.transpose(0, 2, 1)
