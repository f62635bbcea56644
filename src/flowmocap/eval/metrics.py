"""3D joint error metrics of the paper (Sec. 4): Procrustes-aligned mean joint error."""

from __future__ import annotations

import numpy as np

from flowmocap.body.skeleton import EVAL_JOINTS
from flowmocap.errors import InputError
from flowmocap.geometry.procrustes import similarity_procrustes


def _check(pred, gt):
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[2] != 3:
        raise InputError(f"joints must be (T, J, 3) of equal shape; got {pred.shape} and {gt.shape}.")
    return pred, gt


def local_procrustes_error(pred, gt, joints=EVAL_JOINTS) -> np.ndarray:
    """Per-frame similarity Procrustes, then mean joint distance.

    Args:
        pred, gt: ``(T, 24, 3)`` joints in metres.
        joints: the joints evaluated (default: the paper's 13).

    Returns:
        ``(T,)`` mean error per frame in metres.
    """
    pred, gt = _check(pred, gt)
    p, g = pred[:, list(joints)], gt[:, list(joints)]
    aligned = similarity_procrustes(p, g)[0]
    return np.linalg.norm(aligned - g, axis=-1).mean(-1)


def global_procrustes_error(pred, gt, joints=EVAL_JOINTS) -> np.ndarray:
    """One similarity Procrustes over all frames' joints, then mean distance per frame.

    Returns:
        ``(T,)`` metres.
    """
    pred, gt = _check(pred, gt)
    T = pred.shape[0]
    p, g = pred[:, list(joints)].reshape(-1, 3), gt[:, list(joints)].reshape(-1, 3)
    aligned = similarity_procrustes(p, g)[0]
    return np.linalg.norm(aligned - g, axis=-1).reshape(T, -1).mean(-1)


def mpjpe(pred, gt, joints=EVAL_JOINTS, root: int = 0) -> np.ndarray:
    """Root-relative mean per-joint position error without alignment, ``(T,)`` metres."""
    pred, gt = _check(pred, gt)
    p = pred[:, list(joints)] - pred[:, root : root + 1]
    g = gt[:, list(joints)] - gt[:, root : root + 1]
    return np.linalg.norm(p - g, axis=-1).mean(-1)
