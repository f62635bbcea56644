"""Evaluation metrics (paper Sec. 4 and the usual additions), as pure array functions.

==========================  ======================================  ================
metric                       definition                              unit
==========================  ======================================  ================
local_procrustes_error       similarity Procrustes per frame          m (per frame)
global_procrustes_error      one similarity Procrustes per sequence   m (per frame)
mpjpe                        root-relative, no alignment              m (per frame)
depth_split_error            root-relative, split into the image      m (per joint)
                             plane and the camera's depth axis
acceleration_error           |second difference pred - gt|, world     m/frame^2
joint2d_error                Euclidean 2D distance                    px (per frame)
mask_iou (vision.masks)      intersection / union of masks            -- (per frame)
==========================  ======================================  ================

3D metrics use the paper's 13 joints (:data:`~flowmocap.body.skeleton.EVAL_JOINTS`) by
default. :func:`render_silhouettes` rasterises a fitted body for the IoU;
:mod:`flowmocap.eval.scoring` applies all of these to a result folder.
"""

from __future__ import annotations

import numpy as np

from flowmocap.body.skeleton import EVAL_JOINTS
from flowmocap.errors import InputError
from flowmocap.geometry.procrustes import similarity_procrustes


def _check(pred, gt, joints=(), root: int | None = None, dim: int = 3):
    """``pred``, ``gt`` as float64 arrays, checked: equal shapes ``(T, J, dim)`` with
    ``T >= 1``, and ``joints`` (and ``root``) indices below J. NaN are allowed: a frame
    with one among its joints scores NaN in every metric (a detector's missing frame).

    Raises:
        InputError: what is wrong, in words (a joint index past J used to be an IndexError).
    """
    pred, gt = np.asarray(pred, np.float64), np.asarray(gt, np.float64)
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[2] != dim:
        raise InputError(f"joints must be (T, J, {dim}) of equal shape; got {pred.shape} and {gt.shape}.")
    if pred.shape[0] == 0:
        raise InputError("the joints hold no frames (T = 0); give at least one frame.")
    J = pred.shape[1]
    bad = [j for j in [*joints, *([] if root is None else [root])] if not -J <= int(j) < J]
    if bad:
        raise InputError(f"joint index {bad[0]} is outside the {J} joints given (the default joints are the paper's "
                         "13 of the 24 SMPL joints: give (T, 24, 3) arrays, or joints=range(J)).")
    return pred, gt


def local_procrustes_error(pred, gt, joints=EVAL_JOINTS) -> np.ndarray:
    """Per-frame similarity Procrustes, then mean joint distance.

    Args:
        pred, gt: ``(T, 24, 3)`` joints in metres.
        joints: the joints evaluated (default: the paper's 13).

    Returns:
        ``(T,)`` mean error per frame in metres (NaN for a frame with a NaN among its joints).
    """
    pred, gt = _check(pred, gt, joints)
    p, g = pred[:, list(joints)], gt[:, list(joints)]
    ok = np.isfinite(p).all((1, 2)) & np.isfinite(g).all((1, 2))  # a frame with a NaN scores NaN
    out = np.full(len(p), np.nan)
    if ok.any():
        aligned = similarity_procrustes(p[ok], g[ok])[0]
        out[ok] = np.linalg.norm(aligned - g[ok], axis=-1).mean(-1)
    return out


def global_procrustes_error(pred, gt, joints=EVAL_JOINTS) -> np.ndarray:
    """One similarity Procrustes over all frames' joints, then mean distance per frame.

    Args:
        pred, gt: ``(T, 24, 3)`` joints in metres.
        joints: the joints evaluated (default: the paper's 13).

    Returns:
        ``(T,)`` metres (NaN for a frame with a NaN among its joints; the alignment is over
        the others).
    """
    pred, gt = _check(pred, gt, joints)
    p, g = pred[:, list(joints)], gt[:, list(joints)]
    ok = np.isfinite(p).all((1, 2)) & np.isfinite(g).all((1, 2))  # one alignment over the frames with values
    out = np.full(len(p), np.nan)
    if ok.any():
        aligned = similarity_procrustes(p[ok].reshape(-1, 3), g[ok].reshape(-1, 3))[0]
        out[ok] = np.linalg.norm(aligned - g[ok].reshape(-1, 3), axis=-1).reshape(int(ok.sum()), -1).mean(-1)
    return out


def mpjpe(pred, gt, joints=EVAL_JOINTS, root: int = 0) -> np.ndarray:
    """Root-relative mean per-joint position error without alignment, ``(T,)`` metres.

    Args:
        pred, gt: ``(T, 24, 3)`` joints in metres.
        joints: the joints evaluated (default: the paper's 13).
        root: the joint both are made relative to (default the pelvis).
    """
    pred, gt = _check(pred, gt, joints, root)
    p = pred[:, list(joints)] - pred[:, root : root + 1]
    g = gt[:, list(joints)] - gt[:, root : root + 1]
    return np.linalg.norm(p - g, axis=-1).mean(-1)


def depth_split_error(pred, gt, camera_rotation, root: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where a monocular error lies: root-relative joint error in camera coordinates,
    split into its image-plane part (camera x, y) and its depth part (camera z).

    A single camera sees the image-plane part directly and the depth part worst (a
    limb swung towards or away from the camera projects alike).

    Args:
        pred, gt: ``(T, J, 3)`` joints in metres, world frame.
        camera_rotation: ``(3, 3)`` world-to-camera rotation (camera z = viewing direction).
        root: the joint both are made relative to (default the pelvis).

    Returns:
        ``(J,)`` arrays in metres, means over frames: ``plane``, the image-plane error;
        ``depth``, the absolute depth error; ``bias``, the signed depth error (< 0: the
        joint sits nearer the camera than the truth).
    """
    pred, gt = _check(pred, gt, root=root)
    R = np.asarray(camera_rotation, np.float64)
    if R.shape != (3, 3):
        raise InputError(f"camera_rotation must be a (3, 3) matrix; got {R.shape}.")
    d = ((pred - pred[:, root : root + 1]) - (gt - gt[:, root : root + 1])) @ R.T
    return np.linalg.norm(d[..., :2], axis=-1).mean(0), np.abs(d[..., 2]).mean(0), d[..., 2].mean(0)


def acceleration_error(pred, gt, joints=EVAL_JOINTS) -> np.ndarray:
    """Acceleration error: second finite difference of the joint positions, pred vs gt.

    ``a_t = x_{t+1} - 2 x_t + x_{t-1}`` per joint, without any alignment (world / camera
    frame, so jitter of the whole body counts too), then the mean over joints of
    ``|a_pred - a_gt|``. The unit is metres per frame^2 at the sequence's frame rate
    (multiply by 1000 for mm/frame^2); the frames must be consecutive.

    Args:
        pred, gt: ``(T, 24, 3)`` joints in metres, ``T >= 3``.
        joints: the joints evaluated (default: the paper's 13).

    Returns:
        ``(T - 2,)`` metres / frame^2, one value per inner frame.
    """
    pred, gt = _check(pred, gt, joints)
    if pred.shape[0] < 3:
        raise InputError(f"the acceleration error needs at least 3 frames; got {pred.shape[0]}.")
    p, g = pred[:, list(joints)], gt[:, list(joints)]
    acc = lambda x: x[2:] - 2 * x[1:-1] + x[:-2]  # noqa: E731
    return np.linalg.norm(acc(p) - acc(g), axis=-1).mean(-1)


def joint2d_error(pred, gt, joints=EVAL_JOINTS) -> np.ndarray:
    """Mean Euclidean 2D joint distance per frame.

    Args:
        pred, gt: ``(T, 24, 2)`` joints in pixels.
        joints: the joints evaluated (default: the paper's 13).

    Returns:
        ``(T,)`` pixels.
    """
    pred, gt = _check(pred, gt, joints, dim=2)
    return np.linalg.norm(pred[:, list(joints)] - gt[:, list(joints)], axis=-1).mean(-1)


def render_silhouettes(model, poses, trans, betas, camera) -> np.ndarray:
    """The fitted body's silhouettes, rasterised with :func:`flowmocap.render.body_mask`.

    Args:
        model: the :class:`~flowmocap.body.BodyModel` of the result.
        poses: ``(T, 72)`` radians; trans: ``(T, 3)`` metres; betas: ``(10,)``.
        camera: the :class:`~flowmocap.geometry.camera.PinholeCamera` of the result.

    Returns:
        ``(T, H, W)`` bool, True where the body covers the pixel centre.
    """
    import torch

    from flowmocap.render import body_mask, prepare_faces

    poses = np.asarray(poses, np.float32).reshape(-1, 72)
    trans = np.asarray(trans, np.float32).reshape(-1, 3)
    faces = prepare_faces(model.faces_np)
    b = torch.as_tensor(np.asarray(betas, np.float32).reshape(1, -1))
    out = np.zeros((len(poses), camera.height, camera.width), bool)
    with torch.no_grad():
        for s in range(0, len(poses), 32):
            v = model(betas=b.expand(len(poses[s:s + 32]), -1), pose=torch.as_tensor(poses[s:s + 32]),
                      trans=torch.as_tensor(trans[s:s + 32])).vertices
            for k in range(v.shape[0]):
                out[s + k] = body_mask(camera.project(v[k]).numpy(), camera.depth(v[k]).numpy(), faces,
                                       camera.height, camera.width)
    return out
