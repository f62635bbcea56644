"""``E_3d`` (the detector's 3D joints after a per-frame similarity alignment) as one
compiled pass with its gradient written out.

:func:`flowmocap.fit.energies.detector_joints_residuals` defines the term in torch: the
detected joints ``o_j`` are aligned onto the model's ``x_j`` by the confidence-weighted
similarity of Umeyama's closed form (an SVD of the 3x3 cross-covariance), and each joint's
error ``d_j = x_j - (s R o_j + t)`` costs ``c_j rho(|d_j|^2)`` with the pseudo-Huber
``rho(r2) = 2 k^2 (sqrt(1 + r2 / k^2) - 1)``. Differentiating through the SVD takes
autograd some forty small operations per evaluation; here value and gradient come from
one Numba kernel in float64 (:func:`aligned_joints_energy`), tested against the torch
definition and finite differences (``tests/test_aligned_joints.py``).

The gradient, for ``W = sum_j c_j``, centred ``X_j = x_j - mu_x``, ``O_j = o_j - mu_o``,
``Sigma = sum_j c_j X_j O_j^T / W = U D V^T``, ``S = diag(1, 1, sign(det U det V))``,
``R = U S V^T``, ``s = tr(D S) / var_o`` and ``g_j = dE/dd_j = 2 c_j d_j / sqrt(1 + |d_j|^2 / k^2)``:

    dE/dx_j = g_j - c_j / W sum_k g_k + c_j / W Gamma O_j,
    Gamma = -<A, R> / var_o R - s U S beta V^T,   A = sum_j g_j O_j^T,

with ``B = V^T R^T A V`` and ``beta_ij = (B_ij - B_ji) / (l_i + l_j)`` (``l = diag(S D)``,
``beta_ii = 0``): ``s`` moves with ``<R, dSigma> / var_o`` (the rotation's own change is
orthogonal to ``Sigma`` at the optimum) and ``R`` with ``R Omega``, ``Omega`` the skew
solution of ``Omega M + M Omega = R^T dSigma - dSigma^T R`` for ``M = R^T Sigma``; the mean
``mu_x`` drops out of ``dSigma`` because the ``O_j`` are centred with the same weights.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

from flowmocap.fit.with_gradient import energy_with_gradient

__all__ = ["aligned_joints_energy", "MIN_ALIGNED_JOINTS"]

#: Fewest joints with ``c > 0`` the alignment needs (fewer: energy and gradient 0), as
#: :data:`flowmocap.fit.energies.MIN_DETECTOR_JOINTS`.
MIN_ALIGNED_JOINTS = 4
#: Variance (m^2) of the detected joints at or below which they count as one point: the
#: alignment's scale is 0 (the torch definition tests ``> 0``, which rounding makes a
#: ratio of two tiny numbers there, with a gradient autograd gives as NaN).
_POINT_VAR = 1e-18
#: Smallest ``|l_i + l_j|`` divided by in the rotation's derivative (two singular values
#: summing to 0 make the rotation undefined; torch's SVD gradient is infinite there).
_TINY = 1e-12


@njit(cache=True, nogil=True, inline="always")
def _mm(a, b):  # pragma: no cover - compiled
    """``a @ b`` of two 3x3 arrays."""
    out = np.zeros((3, 3))
    for p in range(3):
        for q in range(3):
            for m in range(3):
                out[p, q] += a[p, m] * b[m, q]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _aligned_kernel(x, obs, c, k, energy, grad):  # pragma: no cover - compiled
    """Per batch ``b``: ``energy[b]`` and ``grad[b] = dE/dx[b]`` for ``x (B, N, 3)``,
    ``obs (N, 3)``, ``c (N,)`` (0 for a missing joint, finite ``obs`` where ``c > 0``)."""
    B, N = x.shape[0], x.shape[1]
    W = 0.0
    n_ok = 0
    for j in range(N):
        W += c[j]
        if c[j] > 0.0:
            n_ok += 1
    for b in range(B):
        energy[b] = 0.0
        for j in range(N):
            for a in range(3):
                grad[b, j, a] = 0.0
    if n_ok < 4 or W <= 0.0:
        return
    mu_o = np.zeros(3)
    for j in range(N):
        if c[j] > 0.0:  # a missing joint's obs may be anything, NaN included
            for a in range(3):
                mu_o[a] += c[j] * obs[j, a] / W
    O = np.zeros((N, 3))
    var_o = 0.0
    for j in range(N):
        for a in range(3):
            O[j, a] = obs[j, a] - mu_o[a] if c[j] > 0.0 else 0.0
            var_o += c[j] * O[j, a] * O[j, a] / W
    k2 = k * k
    X = np.zeros((N, 3))
    d = np.zeros((N, 3))
    g = np.zeros((N, 3))
    for b in range(B):
        mu_x = np.zeros(3)
        for j in range(N):
            for a in range(3):
                mu_x[a] += c[j] * x[b, j, a] / W
        cov = np.zeros((3, 3))
        for j in range(N):
            for a in range(3):
                X[j, a] = x[b, j, a] - mu_x[a]
            for p in range(3):
                for q in range(3):
                    cov[p, q] += c[j] * X[j, p] * O[j, q] / W
        U, D, Vh = np.linalg.svd(cov)
        sgn = np.sign(np.linalg.det(U) * np.linalg.det(Vh))
        if sgn == 0.0:
            sgn = 1.0
        S = np.array([1.0, 1.0, sgn])
        R = np.zeros((3, 3))
        for p in range(3):
            for q in range(3):
                for m in range(3):
                    R[p, q] += U[p, m] * S[m] * Vh[m, q]
        s = (D[0] * S[0] + D[1] * S[1] + D[2] * S[2]) / var_o if var_o > _POINT_VAR else 0.0
        e = 0.0
        G = np.zeros(3)
        A = np.zeros((3, 3))
        for j in range(N):
            r2 = 0.0
            for a in range(3):
                ro = R[a, 0] * O[j, 0] + R[a, 1] * O[j, 1] + R[a, 2] * O[j, 2]
                d[j, a] = X[j, a] - s * ro
                r2 += d[j, a] * d[j, a]
            q_ = np.sqrt(1.0 + r2 / k2)
            e += c[j] * 2.0 * k2 * (q_ - 1.0)
            for a in range(3):
                g[j, a] = 2.0 * c[j] * d[j, a] / q_
                G[a] += g[j, a]
                for m in range(3):
                    A[a, m] += g[j, a] * O[j, m]
        energy[b] = e
        Gamma = np.zeros((3, 3))
        if var_o > _POINT_VAR:
            AR = 0.0
            for p in range(3):
                for q in range(3):
                    AR += A[p, q] * R[p, q]
            # B = V^T R^T A V = Vh (R^T A) Vh^T
            Bm = _mm(_mm(Vh, _mm(R.T.copy(), A)), Vh.T.copy())
            lam = D * S
            beta = np.zeros((3, 3))
            for p in range(3):
                for q in range(3):
                    if p != q:
                        den = lam[p] + lam[q]
                        if abs(den) < _TINY:
                            den = _TINY if den >= 0.0 else -_TINY
                        beta[p, q] = (Bm[p, q] - Bm[q, p]) / den
            SB = np.zeros((3, 3))
            for p in range(3):
                for q in range(3):
                    SB[p, q] = S[p] * beta[p, q]
            H = _mm(_mm(U, SB), Vh)
            for p in range(3):
                for q in range(3):
                    Gamma[p, q] = -AR / var_o * R[p, q] - s * H[p, q]
        for j in range(N):
            w = c[j] / W
            for a in range(3):
                go = Gamma[a, 0] * O[j, 0] + Gamma[a, 1] * O[j, 1] + Gamma[a, 2] * O[j, 2]
                grad[b, j, a] = g[j, a] - w * G[a] + w * go


def aligned_joints_energy(joints: torch.Tensor, obs: np.ndarray, conf: np.ndarray, scale: float,
                          rotation: np.ndarray | None = None, factor: float = 1.0) -> torch.Tensor:
    """``factor * sum_j c_j rho(|d_j|^2)`` per batch, ``(B,)`` m^2 in ``joints``' dtype, with
    the gradient to ``joints`` (the module docstring has the formulas).

    Args:
        joints: ``(B, N, 3)`` model joints, metres (any origin: the alignment's
            translation absorbs it), in the detector's axes or, with ``rotation``, in
            axes it turns into them (``x = joints @ rotation.T``, e.g. world joints and
            the camera's rotation).
        obs: ``(N, 3)`` float64 detected joints, finite wherever ``conf > 0`` (any
            origin and scale).
        conf: ``(N,)`` float64 weights in ``[0, 1]``, 0 for a missing joint; fewer than
            :data:`MIN_ALIGNED_JOINTS` positive: energy and gradient 0.
        scale: pseudo-Huber scale ``k`` in metres (> 0).
        rotation: optional ``(3, 3)`` rotation (see ``joints``).
        factor: multiplies the energy (e.g. one over the number of joints).

    The caller checks the inputs (:func:`flowmocap.fit.energies.detector_joints_energy`
    does).
    """
    rot = None if rotation is None else np.ascontiguousarray(rotation, np.float64)
    obs = np.ascontiguousarray(obs, np.float64)
    conf = np.ascontiguousarray(conf, np.float64)

    def compute(x):
        if rot is not None:
            x = np.ascontiguousarray(x @ rot.T)
        energy = np.empty(x.shape[0])
        grad = np.empty_like(x)
        _aligned_kernel(x, obs, conf, float(scale), energy, grad)
        if rot is not None:
            grad = grad @ rot
        return energy * factor, [grad * factor]

    return energy_with_gradient(compute, joints)
