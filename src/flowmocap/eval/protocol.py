"""The evaluation protocol of the paper on synthetic sequences: a noisy initialisation
from ground truth, tracking, and the 3D joint errors."""

from __future__ import annotations

import json

import numpy as np

from flowmocap.body.skeleton import JOINT_INDEX, JOINT_NAMES
from flowmocap.fit.init import INIT_JOINTS

#: Joints whose rough pose the user sets (paper Sec. 3.6: "shoulder, elbow, hip and
#: knee"), plus the global orientation.
ROUGH_POSE_JOINTS = ("pelvis", "left_hip", "right_hip", "left_knee", "right_knee",
                     "left_shoulder", "right_shoulder", "left_elbow", "right_elbow")


def noisy_init(gt: dict, frame: int = 0, seed: int = 0, joint_noise_px: float = 3.0,
               pose_noise_deg: float = 15.0) -> dict:
    """An init.json dict made from ground truth, as a user would click it.

    Args:
        gt: a sequence's gt.npz arrays (``joints2d (T, 24, 2)``, ``poses (T, 72)``).
        frame: the frame to initialise.
        seed: random seed.
        joint_noise_px: standard deviation of Gaussian noise on each 2D joint, pixels.
        pose_noise_deg: size of a random rotation (uniform random axis, this angle)
            applied to each main joint's ground-truth rotation; other joints start at 0.

    Returns:
        dict in the init.json schema (:mod:`flowmocap.fit.init`).
    """
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    j2d = np.asarray(gt["joints2d"][frame], np.float64)
    joints = {n: (j2d[JOINT_INDEX[n]] + rng.normal(0, joint_noise_px, 2)).tolist() for n in INIT_JOINTS}
    pose = np.asarray(gt["poses"][frame], np.float64).reshape(24, 3)
    rough = {}
    for n in ROUGH_POSE_JOINTS:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        noise = Rotation.from_rotvec(np.deg2rad(pose_noise_deg) * axis)
        rough[n] = (Rotation.from_rotvec(pose[JOINT_INDEX[n]]) * noise).as_rotvec().tolist()
    return {"frame": frame, "joints2d": joints, "pose": rough,
            "note": f"from ground truth: {joint_noise_px} px joint noise, {pose_noise_deg} deg pose noise, seed {seed}"}


def evaluate(motion: dict, gt: dict) -> dict:
    """Paper metrics of a result against ground truth (frames matched by ``frame_index``).

    Returns:
        dict with ``local_cm``, ``global_cm``, ``mpjpe_cm`` (means over frames), the
        per-frame ``local_cm_per_frame`` and, when ``motion`` holds its ``camera``,
        ``joints``: for each of the paper's 13 joints, ``plane_cm`` / ``depth_cm`` /
        ``depth_bias_cm``, its root-relative error across and along the camera's view
        (:func:`~flowmocap.eval.metrics.depth_split_error`).
    """
    from flowmocap.body.skeleton import EVAL_JOINTS
    from flowmocap.eval.metrics import depth_split_error, global_procrustes_error, local_procrustes_error, mpjpe

    idx = np.asarray(motion["frame_index"], int)
    pred = np.asarray(motion["joints3d"], np.float64)
    ref = np.asarray(gt["joints3d"], np.float64)[idx]
    local = local_procrustes_error(pred, ref)
    scores = {
        "frames": int(len(idx)),
        "local_cm": float(100 * local.mean()),
        "global_cm": float(100 * global_procrustes_error(pred, ref).mean()),
        "mpjpe_cm": float(100 * mpjpe(pred, ref).mean()),
        "local_cm_per_frame": (100 * local).round(2).tolist(),
    }
    if "camera" in motion:
        rotation = json.loads(str(motion["camera"]))["R"]
        plane, depth, bias = depth_split_error(pred, ref, rotation)
        scores["joints"] = {JOINT_NAMES[j]: {"plane_cm": round(100 * float(plane[j]), 2),
                                             "depth_cm": round(100 * float(depth[j]), 2),
                                             "depth_bias_cm": round(100 * float(bias[j]), 2)}
                            for j in EVAL_JOINTS}
    return scores
