"""``E_j`` (detected 2D joints) and ``E_d`` (the depth of each limb's direction against the
detector's 3D joints) as compiled passes with their gradients written out.

The torch definitions stay in :mod:`flowmocap.fit.energies` (``keypoint_residuals``,
``limb_depth_residuals``) as the reference the tests compare with
(``tests/test_joint_terms.py``); the tracker evaluates these terms dozens of times a frame
on 24 points, where autograd's small operations cost more than the arithmetic.

Both take world joints ``P (B, N, 3)`` and a camera ``(R, t, f, c)`` and return ``(B,)``
energies with the gradient to ``P``:

- :func:`keypoint_energy_world`: ``sum_j c_j sum_a rho(p_ja - o_ja)`` with the projection
  ``p = f (R P + t)_xy / (R P + t)_z + c`` and Geman-McClure's ``rho(x) = s^2 x^2 / (s^2 +
  x^2)``, ``rho'(x) = 2 s^4 x / (s^2 + x^2)^2``.
- :func:`limb_depth_energy_world`: ``sum_l c_l rho(u_z - o_z)`` for each limb ``l`` from
  joint ``a`` to ``b``, ``v = R (P_b - P_a)``, ``u_z = v_z / |v|`` (``du_z/dv = e_z / |v| -
  v_z v / |v|^3``) and the detector's ``o_z`` (precomputed).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

from flowmocap.fit.with_gradient import energy_with_gradient

__all__ = ["keypoint_energy_world", "limb_depth_energy_world"]


@njit(cache=True, nogil=True, error_model="numpy")
def _keypoint_kernel(P, R, t, f, c, obs, conf, sigma, energy, grad):  # pragma: no cover - compiled
    B, N = P.shape[0], P.shape[1]
    for b in range(B):
        e = 0.0
        for j in range(N):
            for a in range(3):
                grad[b, j, a] = 0.0
            if conf[j] <= 0.0:
                continue
            s2 = sigma[j] * sigma[j]
            pc = np.zeros(3)
            for a in range(3):
                pc[a] = R[a, 0] * P[b, j, 0] + R[a, 1] * P[b, j, 1] + R[a, 2] * P[b, j, 2] + t[a]
            z = pc[2]
            gpc = np.zeros(3)
            for a in range(2):
                x = f[a] * pc[a] / z + c[a] - obs[j, a]
                den = s2 + x * x
                e += conf[j] * s2 * x * x / den
                gx = conf[j] * 2.0 * s2 * s2 * x / (den * den)
                gpc[a] += gx * f[a] / z
                gpc[2] -= gx * f[a] * pc[a] / (z * z)
            for a in range(3):
                grad[b, j, a] = R[0, a] * gpc[0] + R[1, a] * gpc[1] + R[2, a] * gpc[2]
        energy[b] = e


@njit(cache=True, nogil=True, error_model="numpy")
def _limb_depth_kernel(P, R, limbs, oz, conf, sigma, energy, grad):  # pragma: no cover - compiled
    B, N = P.shape[0], P.shape[1]
    s2 = sigma * sigma
    for b in range(B):
        for j in range(N):
            for a in range(3):
                grad[b, j, a] = 0.0
        e = 0.0
        for k in range(limbs.shape[0]):
            if conf[k] <= 0.0:
                continue
            pa, ch = limbs[k, 0], limbs[k, 1]
            v = np.zeros(3)
            for a in range(3):
                for m in range(3):
                    v[a] += R[a, m] * (P[b, ch, m] - P[b, pa, m])
            norm = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
            n = norm if norm > 1e-9 else 1e-9
            x = v[2] / n - oz[k]
            den = s2 + x * x
            e += conf[k] * s2 * x * x / den
            gx = conf[k] * 2.0 * s2 * s2 * x / (den * den)
            gv = np.zeros(3)
            for a in range(3):
                gv[a] = gx * ((1.0 / n if a == 2 else 0.0) - (v[2] * v[a] / (n * n * n) if norm > 1e-9 else 0.0))
            for a in range(3):
                gp = R[0, a] * gv[0] + R[1, a] * gv[1] + R[2, a] * gv[2]
                grad[b, ch, a] += gp
                grad[b, pa, a] -= gp
        energy[b] = e


def _compiled(P: torch.Tensor, kernel, args: tuple, factor: float) -> torch.Tensor:
    """``factor`` times the ``(B,)`` energy ``kernel(P, *args, energy, grad)`` fills, with its gradient."""
    def compute(p):
        energy = np.empty(p.shape[0])
        grad = np.empty_like(p)
        kernel(p, *args, energy, grad)
        return energy * factor, [grad * factor]

    return energy_with_gradient(compute, P)


def _camera_arrays(camera) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return (np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64),
            np.array([camera.fx, camera.fy], np.float64), np.array([camera.cx, camera.cy], np.float64))


def keypoint_energy_world(points: torch.Tensor, camera, obs: np.ndarray, conf: np.ndarray, sigma,
                          factor: float = 1.0) -> torch.Tensor:
    """``factor * sum_j conf_j sum_a rho(p_ja - obs_ja)``, ``(B,)`` px^2 in ``points``' dtype.

    Args:
        points: ``(B, N, 3)`` world points, metres (in front of the camera).
        camera: a :class:`~flowmocap.geometry.camera.PinholeCamera` (its ``R``, ``t``,
            ``fx``, ``fy``, ``cx``, ``cy``).
        obs: ``(N, 2)`` detected pixels, finite where ``conf > 0``.
        conf: ``(N,)`` non-negative weights (0: missing).
        sigma: Geman-McClure scale, pixels (> 0): one for every point, or ``(N,)`` one each.
        factor: multiplies the energy.
    """
    R, t, f, c = _camera_arrays(camera)
    n = np.shape(obs)[0]
    s = np.full(n, float(sigma)) if np.ndim(sigma) == 0 else np.ascontiguousarray(sigma, np.float64).reshape(-1)
    if s.shape != (n,):
        raise ValueError(f"sigma must be a number or one per point ({n}); got shape {np.shape(sigma)}")
    return _compiled(points, _keypoint_kernel,
                           (R, t, f, c, np.ascontiguousarray(obs, np.float64), np.ascontiguousarray(conf, np.float64),
                            s), float(factor))


def limb_depth_energy_world(points: torch.Tensor, rotation: np.ndarray, limbs: np.ndarray, oz: np.ndarray,
                            conf: np.ndarray, sigma: float) -> torch.Tensor:
    """``sum_l conf_l rho(u_z - oz_l)``, ``(B,)`` in ``points``' dtype.

    Args:
        points: ``(B, N, 3)`` world points, metres.
        rotation: ``(3, 3)`` world to camera axes.
        limbs: ``(L, 2)`` int64 ``(parent, child)`` joint indices.
        oz: ``(L,)`` the detector's limb directions' depth components (sines).
        conf: ``(L,)`` non-negative weights (0: no detection of the limb).
        sigma: Geman-McClure scale (> 0).
    """
    return _compiled(points, _limb_depth_kernel,
                           (np.asarray(rotation, np.float64), np.ascontiguousarray(limbs, np.int64),
                            np.ascontiguousarray(oz, np.float64), np.ascontiguousarray(conf, np.float64),
                            float(sigma)), 1.0)
