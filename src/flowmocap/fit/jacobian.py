"""Closed-form Jacobians of skinned points with respect to pose and translation.

For Gauss-Newton / Levenberg-Marquardt the tracker needs ``d x / d (pose, trans)`` for
every projected vertex ``x``: 6,890 x 2 rows by 75 columns. Forward-mode autodiff
through the body model costs about 40 forward passes; the kinematic chain gives it in
closed form instead.

A small change ``delta`` of joint j's axis-angle ``theta_j`` turns its local rotation
into ``R_j exp([J_r(theta_j) delta]_x)`` (``J_r``: the right Jacobian of SO(3)), which in
the world rotates every bone below j (j included) about the posed joint position
``p_j`` by the world vector ``omega = R^w_j J_r(theta_j) delta``. A skinned point
``v = sum_k w_k x_k`` (``x_k``: the point moved rigidly by bone k) therefore moves by

    dv = omega x (m_j - s_j p_j),   m_j = sum_{k below j} w_k x_k,  s_j = sum_{k below j} w_k,

and ``dv / dtrans = I``. Pose blend shapes (SMPL's ``posedirs``) are left out: their
derivative is small and a Gauss-Newton step does not need it exactly (the default body
has none, so there it is exact).
"""

from __future__ import annotations

import numpy as np

from flowmocap.body.skeleton import NUM_JOINTS, PARENTS


def _descendants(parents) -> np.ndarray:
    """``(J, J)`` 0/1 matrix: ``D[j, k] = 1`` if bone k is j or lies below j."""
    J = len(parents)
    D = np.eye(J)
    for k in range(J):
        p = parents[k]
        while p >= 0:
            D[p, k] = 1.0
            p = parents[p]
    return D


_DESC = _descendants(list(PARENTS))


def right_jacobian_so3(theta: np.ndarray) -> np.ndarray:
    """Right Jacobian of SO(3) at axis-angles ``theta (..., 3)``: ``(..., 3, 3)``.

    ``exp(theta + d) ~= exp(theta) exp(J_r(theta) d)`` for small ``d``.
    """
    theta = np.asarray(theta, dtype=np.float64)
    t = np.linalg.norm(theta, axis=-1)[..., None, None]
    K = np.zeros(theta.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -theta[..., 2], theta[..., 1]
    K[..., 1, 0], K[..., 1, 2] = theta[..., 2], -theta[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -theta[..., 1], theta[..., 0]
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    a = np.where(small, 0.5 - t**2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    b = np.where(small, 1.0 / 6.0 - t**2 / 120.0, (ts - np.sin(ts)) / ts**3)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye - a * K + b * (K @ K)


def skinned_point_jacobian(
    pose: np.ndarray,
    transforms: np.ndarray,
    joints: np.ndarray,
    rest_points: np.ndarray,
    weights: np.ndarray,
) -> np.ndarray:
    """``d v / d (pose, trans)`` of linearly skinned points.

    Args:
        pose: ``(72,)`` axis-angle pose in radians.
        transforms: ``(24, 4, 4)`` skinning transforms of the posed body, translation
            included (:attr:`flowmocap.body.BodyOutput.transforms` of one body).
        joints: ``(24, 3)`` posed joint positions in metres (translation included).
        rest_points: ``(N, 3)`` rest-pose points (shaped vertices, or capsule ends).
        weights: ``(N, 24)`` skinning weights (rows sum to 1; one-hot for a point
            carried by a single bone).

    Returns:
        ``(N, 3, 75)`` in metres per radian (columns ``3 j + c`` of joint j's axis-angle
        component c) and metres per metre (the last three: translation).
    """
    pose = np.asarray(pose, np.float64).reshape(NUM_JOINTS, 3)
    T = np.asarray(transforms, np.float64)
    p = np.asarray(joints, np.float64)
    X = np.asarray(rest_points, np.float64)
    W = np.asarray(weights, np.float64)
    N = X.shape[0]
    Rw, tw = T[:, :3, :3], T[:, :3, 3]
    # world rotation of each joint's frame: the skinning transform's rotation part
    A = Rw @ right_jacobian_so3(pose)  # (24, 3, 3): omega = A_j delta
    out = np.zeros((N, 3, 3 * NUM_JOINTS + 3))
    Dt = _DESC.T  # (k, j)
    s = W @ Dt  # (N, J): weight of the bones below j
    # m_j = sum_k D[j,k] w_k x_k with x_k = R_k X + t_k; split to avoid (N, 24, 3) per bone
    # sum_k D[j,k] w_k R_k X = (W D^T-weighted) ... computed per joint in a loop over J
    WX = W[:, :, None] * X[:, None, :]  # (N, K, 3)
    for j in range(NUM_JOINTS):
        below = np.flatnonzero(_DESC[j])
        active = s[:, j] > 0
        if not active.any():
            continue
        idx = np.flatnonzero(active)
        # m_j - s_j p_j for the active points: sum_k w_k (R_k X + t_k - p_j)
        m = np.einsum("nkb,kab->na", WX[idx][:, below], Rw[below])
        m += W[idx][:, below] @ (tw[below] - p[j])
        # columns: A_j[:, c] x m
        for c in range(3):
            out[idx, :, 3 * j + c] = np.cross(A[j, :, c][None, :], m)
    out[:, 0, -3], out[:, 1, -2], out[:, 2, -1] = 1.0, 1.0, 1.0
    return out


def projection_jacobian(points_world: np.ndarray, R: np.ndarray, t: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """``d px / d X`` of the pinhole projection of world points: ``(N, 2, 3)`` in px per metre.

    Args:
        points_world: ``(N, 3)`` metres.
        R, t: world-to-camera rotation ``(3, 3)`` and translation ``(3,)``.
        fx, fy: focal lengths in pixels.
    """
    Xc = np.asarray(points_world, np.float64) @ np.asarray(R, np.float64).T + np.asarray(t, np.float64)
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    P = np.zeros((len(z), 2, 3))
    P[:, 0, 0] = fx / z
    P[:, 0, 2] = -fx * x / z**2
    P[:, 1, 1] = fy / z
    P[:, 1, 2] = -fy * y / z**2
    return P @ np.asarray(R, np.float64)
