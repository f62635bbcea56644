"""Compiled residuals and closed-form Jacobians of the per-joint rotation terms.

The soft joint limits ``E_b`` (Euler angles of every joint's rotation in its chart)
and the root part of ``E_theta`` (the geodesic difference of two global orientations)
take a few hundred tiny tensor operations when written with torch ops, and the
tracker evaluates them some fifty times per frame. Here they are numba kernels over
float64 with closed-form Jacobians, wrapped as :class:`torch.autograd.Function` s; the
torch implementations in :mod:`flowmocap.fit.energies` define the same functions (and
remain the path for anything but CPU tensors) and the tests check both against each
other and the Jacobians against finite differences.

Closed forms used (``K = [w]_x``, ``theta = |w|``):

* Rodrigues: ``R(w) = I + A K + B K^2``, ``A = sin(theta)/theta``, ``B = (1 - cos theta)/theta^2``.
* Right Jacobian: ``R(w + d) = R(w) Exp(J_r(w) d)``, ``J_r = I - B K + C K^2``,
  ``C = (theta - sin theta)/theta^3``; hence ``dR/dw_m = R [J_r e_m]_x``.
* Inverse right Jacobian: ``J_r^{-1}(phi) = I + K/2 + D K^2``,
  ``D = 1/theta^2 - (1 + cos theta)/(2 theta sin theta)``; so for
  ``phi = log(R_ref^T R(w))``, ``dphi/dw = J_r^{-1}(phi) J_r(w)`` and
  ``dphi/dref = -J_r^{-1}(phi)^T J_r(ref)`` (a left perturbation, ``J_l^{-1} = J_r^{-T}``).
* Tait-Bryan angles of an intrinsic order (i, j, k), as
  :func:`flowmocap.geometry.matrix_to_euler`: ``first = atan2(-s R_jk, R_kk)``,
  ``middle = atan2(s R_ik, sqrt(R_ii^2 + R_ij^2))``, ``third = atan2(-s R_ij, R_ii)``
  (``s = +1`` for cyclic orders), differentiated through ``atan2``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit

from flowmocap.errors import InputError

__all__ = ["LimitCharts", "limit_charts", "limit_residuals_jacobian", "limit_residuals",
           "root_difference_jacobian", "root_difference"]

_SMALL = 1e-6  # theta^2 below which the series are used
#: float64 machine epsilon: the cosine of the middle Euler angle is floored at it, its derivative
#: then 0, as :func:`~flowmocap.geometry.rotations.matrix_to_euler` clamps it (at an exact gimbal
#: lock the cosine is rounding noise, and dividing by it gave gradients of that noise).
_EPS = 2.220446049250313e-16


@njit(cache=True, nogil=True, inline="always")
def _coeffs(t2):
    """A, B, C of the module docstring for ``theta^2 = t2``."""
    if t2 < _SMALL:
        a = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
        c = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
    else:
        t = math.sqrt(t2)
        s = math.sin(t)
        h = math.sin(0.5 * t)
        a = s / t
        b = 2.0 * h * h / t2
        c = (t - s) / (t2 * t)
    return a, b, c


@njit(cache=True, nogil=True)
def _skew(w):
    k = np.zeros((3, 3))
    k[0, 1] = -w[2]
    k[0, 2] = w[1]
    k[1, 0] = w[2]
    k[1, 2] = -w[0]
    k[2, 0] = -w[1]
    k[2, 1] = w[0]
    return k


@njit(cache=True, nogil=True)
def _rot_and_jr(w):
    """``R(w)`` and ``J_r(w)``, each ``(3, 3)``."""
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    a, b, c = _coeffs(t2)
    k = _skew(w)
    k2 = k @ k
    eye = np.eye(3)
    return eye + a * k + b * k2, eye - b * k + c * k2


@njit(cache=True, nogil=True)
def _log(m):
    """``log`` of a rotation matrix, ``(3,)`` with angle in [0, pi] (via the quaternion)."""
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    q = np.zeros(4)
    if tr > max(m[0, 0], m[1, 1], m[2, 2]):
        s = math.sqrt(max(1.0 + tr, 0.0)) * 2.0
        q[0] = 0.25 * s
        q[1] = (m[2, 1] - m[1, 2]) / s
        q[2] = (m[0, 2] - m[2, 0]) / s
        q[3] = (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = math.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0)) * 2.0
        q[0] = (m[2, 1] - m[1, 2]) / s
        q[1] = 0.25 * s
        q[2] = (m[0, 1] + m[1, 0]) / s
        q[3] = (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] >= m[2, 2]:
        s = math.sqrt(max(1.0 - m[0, 0] + m[1, 1] - m[2, 2], 0.0)) * 2.0
        q[0] = (m[0, 2] - m[2, 0]) / s
        q[1] = (m[0, 1] + m[1, 0]) / s
        q[2] = 0.25 * s
        q[3] = (m[1, 2] + m[2, 1]) / s
    else:
        s = math.sqrt(max(1.0 - m[0, 0] - m[1, 1] + m[2, 2], 0.0)) * 2.0
        q[0] = (m[1, 0] - m[0, 1]) / s
        q[1] = (m[0, 2] + m[2, 0]) / s
        q[2] = (m[1, 2] + m[2, 1]) / s
        q[3] = 0.25 * s
    if q[0] < 0.0:
        q = -q
    n = math.sqrt(q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    angle = 2.0 * math.atan2(n, q[0])
    f = 2.0 / q[0] * (1.0 - n * n / (3.0 * q[0] * q[0])) if n < 1e-8 else angle / n
    return f * q[1:]


@njit(cache=True, nogil=True)
def _jr_inv(phi):
    t2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    if t2 < _SMALL:
        d = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    else:
        t = math.sqrt(t2)
        d = 1.0 / t2 - (1.0 + math.cos(t)) / (2.0 * t * math.sin(t))
    k = _skew(phi)
    return np.eye(3) + 0.5 * k + d * (k @ k)


@njit(cache=True, nogil=True)
def _root_kernel(w, ref, out_r, out_j, out_jref):
    """Batched ``phi = log(R(ref_b)^T R(w_b))``, ``dphi/dw`` and ``dphi/dref``; w, ref ``(B, 3)``."""
    for bi in range(w.shape[0]):
        r, jr = _rot_and_jr(w[bi])
        rref, jref = _rot_and_jr(ref[bi])
        phi = _log(rref.T @ r)
        inv = _jr_inv(phi)
        out_r[bi] = phi
        out_j[bi] = inv @ jr
        out_jref[bi] = -(inv.T @ jref)


@njit(cache=True, nogil=True, inline="always")
def _datan2(y, x, dy, dx):
    return (x * dy - y * dx) / (x * x + y * y)


@njit(cache=True, nogil=True)
def _limit_kernel(pose, lo, hi, joints, kinds, axes, lock_eps, out_r, out_j):
    """Residuals ``(B, n, 3)`` and per-joint Jacobians ``(B, n, 3, 3)`` of the soft limits.

    pose ``(B, 24, 3)``; lo, hi ``(n, 3)`` of the limited ``joints (n,)``; ``kinds (n,)``:
    0 raw axis-angle, 1 intrinsic Euler of order ``axes[q] = (i, j, k)``.
    """
    for bi in range(pose.shape[0]):
        for q in range(joints.shape[0]):
            w = pose[bi, joints[q]]
            th = np.zeros(3)
            dth = np.zeros((3, 3))  # dth[a, m] = d angle about axis a / d w_m
            if kinds[q] == 0:
                for a in range(3):
                    th[a] = w[a]
                    dth[a, a] = 1.0
            else:
                i, j, k = axes[q, 0], axes[q, 1], axes[q, 2]
                s = 1.0 if (j - i) % 3 == 1 else -1.0
                rot, jr = _rot_and_jr(w)
                cb2 = rot[i, i] * rot[i, i] + rot[i, j] * rot[i, j]
                locked = cb2 < lock_eps
                floored = cb2 < _EPS * _EPS
                cb = _EPS if floored else math.sqrt(cb2)
                th[j] = math.atan2(s * rot[i, k], cb)
                if locked:
                    th[i] = math.atan2(s * rot[k, j], rot[j, j])
                    th[k] = 0.0
                else:
                    th[i] = math.atan2(-s * rot[j, k], rot[k, k])
                    th[k] = math.atan2(-s * rot[i, j], rot[i, i])
                for m in range(3):
                    dr = rot @ _skew(jr[:, m])
                    dcb = 0.0 if floored else (rot[i, i] * dr[i, i] + rot[i, j] * dr[i, j]) / cb
                    dth[j, m] = _datan2(s * rot[i, k], cb, s * dr[i, k], dcb)
                    if locked:
                        dth[i, m] = _datan2(s * rot[k, j], rot[j, j], s * dr[k, j], dr[j, j])
                    else:
                        dth[i, m] = _datan2(-s * rot[j, k], rot[k, k], -s * dr[j, k], dr[k, k])
                        dth[k, m] = _datan2(-s * rot[i, j], rot[i, i], -s * dr[i, j], dr[i, i])
            for a in range(3):
                r = 0.0
                g = 0.0
                if th[a] < lo[q, a]:
                    e = math.exp(lo[q, a] - th[a])
                    r = e - 1.0
                    g = -e
                elif th[a] > hi[q, a]:
                    e = math.exp(th[a] - hi[q, a])
                    r = e - 1.0
                    g = e
                out_r[bi, q, a] = r
                for m in range(3):
                    out_j[bi, q, a, m] = g * dth[a, m]


class LimitCharts:
    """The limits table in the kernel's form: ``joints (n,)`` limited joints, ``kinds``,
    ``axes (n, 3)``, ``lo``/``hi (n, 3)`` radians (see :class:`~flowmocap.fit.joint_limits.JointLimits`),
    built from a ``JointLimits``.

    Raises:
        InputError: a chart is neither ``"axis_angle"`` nor an intrinsic Tait-Bryan order.
    """

    def __init__(self, limits):
        self.joints = np.asarray(limits.limited, np.int64)
        self.lo = np.ascontiguousarray(limits.lower[self.joints], np.float64)
        self.hi = np.ascontiguousarray(limits.upper[self.joints], np.float64)
        self.kinds = np.zeros(len(self.joints), np.int64)
        self.axes = np.zeros((len(self.joints), 3), np.int64)
        for q, j in enumerate(self.joints):
            chart = limits.charts[j]
            if chart == "axis_angle":
                continue
            if not (isinstance(chart, str) and len(chart) == 3 and set(chart) <= set("XYZ") and len(set(chart)) == 3):
                raise InputError(f"joint {j}'s limits chart {chart!r} is not 'axis_angle' or an intrinsic "
                                 "Tait-Bryan order such as 'XZY'.")
            self.kinds[q] = 1
            self.axes[q] = ["XYZ".index(c) for c in chart]


_CHARTS: dict[int, LimitCharts] = {}


def limit_charts(limits) -> LimitCharts:
    """Cached :class:`LimitCharts` of a :class:`~flowmocap.fit.joint_limits.JointLimits`."""
    key = id(limits)
    if key not in _CHARTS or _CHARTS[key][0] is not limits:
        _CHARTS[key] = (limits, LimitCharts(limits))
    return _CHARTS[key][1]


def limit_residuals_jacobian(pose: np.ndarray, charts: LimitCharts, lock_eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Soft-limit residuals and their Jacobian, float64.

    Args:
        pose: ``(B, 72)`` axis-angle, radians.
        charts: from :func:`limit_charts`.
        lock_eps: ``cos^2`` of the middle angle below which a joint counts as gimbal-locked.

    Returns:
        ``r (B, 3 n)`` (n limited joints, x/y/z each) and ``J (B, n, 3, 3)``, the block
        ``d r[q, a] / d pose[joint q, m]`` of each limited joint.
    """
    p = np.ascontiguousarray(pose, np.float64).reshape(-1, 24, 3)
    n = len(charts.joints)
    r = np.zeros((p.shape[0], n, 3))
    J = np.zeros((p.shape[0], n, 3, 3))
    _limit_kernel(p, charts.lo, charts.hi, charts.joints, charts.kinds, charts.axes, lock_eps, r, J)
    return r.reshape(p.shape[0], 3 * n), J


class _Limits(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pose, charts, lock_eps):
        r, J = limit_residuals_jacobian(pose.detach().cpu().numpy(), charts, lock_eps)
        ctx.charts = charts
        ctx.save_for_backward(torch.from_numpy(J))
        return torch.from_numpy(r).to(pose.dtype)

    @staticmethod
    def backward(ctx, grad):
        (J,) = ctx.saved_tensors
        B, n = J.shape[:2]
        g = torch.einsum("bqa,bqam->bqm", grad.double().reshape(B, n, 3), J)
        out = torch.zeros(B, 24, 3, dtype=torch.float64)
        out[:, torch.from_numpy(ctx.charts.joints)] = g
        return out.reshape(B, 72).to(grad.dtype), None, None


def limit_residuals(pose: torch.Tensor, charts: LimitCharts, lock_eps: float) -> torch.Tensor:
    """:func:`limit_residuals_jacobian` as a differentiable op on a CPU ``(B, 72)`` tensor
    (axis-angle, radians); returns ``(B, 3 n)`` unitless residuals of ``pose``'s dtype."""
    return _Limits.apply(pose, charts, lock_eps)


def root_difference_jacobian(w: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``phi = log(R(ref)^T R(w))`` ``(B, 3)``, ``dphi/dw`` and ``dphi/dref`` ``(B, 3, 3)``
    (float64); w, ref: ``(B, 3)`` axis-angle, radians."""
    w = np.ascontiguousarray(w, np.float64).reshape(-1, 3)
    ref = np.ascontiguousarray(np.asarray(ref, np.float64).reshape(-1, 3))
    r = np.zeros_like(w)
    J = np.zeros((w.shape[0], 3, 3))
    Jref = np.zeros((w.shape[0], 3, 3))
    _root_kernel(w, ref, r, J, Jref)
    return r, J, Jref


class _Root(torch.autograd.Function):
    @staticmethod
    def forward(ctx, w, ref):
        r, J, Jref = root_difference_jacobian(w.detach().cpu().numpy(), ref.detach().cpu().numpy())
        ctx.save_for_backward(torch.from_numpy(J), torch.from_numpy(Jref))
        return torch.from_numpy(r).to(w.dtype)

    @staticmethod
    def backward(ctx, grad):
        J, Jref = ctx.saved_tensors
        g = grad.double()
        gw = torch.einsum("ba,bam->bm", g, J).to(grad.dtype) if ctx.needs_input_grad[0] else None
        gref = torch.einsum("ba,bam->bm", g, Jref).to(grad.dtype) if ctx.needs_input_grad[1] else None
        return gw, gref


def root_difference(w: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """``log(R(ref)^T R(w))``, ``(B, 3)``, differentiable in ``w`` and ``ref`` (CPU tensors
    of the same shape, axis-angle in radians)."""
    return _Root.apply(w, ref)
