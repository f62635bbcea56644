"""The automatic start (init steps 1-2 without a stated rough pose, as ``flowmocap track``
starts a video and as the refits start again) follows the detector's 3D joints away from
the rest pose it begins at: a body far from rest (a crouch, an arm raised) is found from
its 2D joints and its 3D joints given as a detector gives them (hip-centred, in the
camera's axes)."""

from __future__ import annotations

import numpy as np
import torch

from flowmocap.body import JOINT_INDEX as J
from flowmocap.body import load_body_model
from flowmocap.eval.metrics import local_procrustes_error
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.init import InitSpec, fit_frame0
from flowmocap.geometry import PinholeCamera, look_at

#: the 12 joints a detector gives
DETECTED = [J[n] for n in ("left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
                           "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist",
                           "right_wrist")]


def _start_error(cfg: TrackerConfig) -> float:
    """Metres: the start's local (similarity-aligned) joint error against the truth."""
    model = load_body_model("default")
    R, t = look_at((1.2, 0.3, 3.2), (0.0, -0.2, 0.0))
    cam = PinholeCamera.from_focal(480, 640, 560.0, R, t)
    pose = torch.zeros(72)
    pose[:3] = torch.tensor([0.0, 0.5, 0.0])  # turned a little away from the camera
    for side in ("left", "right"):
        pose[3 * J[f"{side}_hip"]] -= 1.2  # thighs raised
        pose[3 * J[f"{side}_knee"]] += 1.7  # knees bent: a crouch
    pose[3 * J["left_shoulder"] + 2] += 1.3  # the left arm raised sideways
    pose[3 * J["right_elbow"] + 1] += 1.4  # the right elbow bent
    with torch.no_grad():
        truth = model(pose=pose[None]).joints[0].double().numpy()
    j2d = cam.project(torch.as_tensor(truth)).numpy()
    conf = np.zeros(24)
    conf[DETECTED] = 0.9
    # the detector's 3D: hip-centred, in the camera's axes
    hips = truth[[J["left_hip"], J["right_hip"]]].mean(0)
    j3d = (truth - hips) @ np.asarray(cam.R, np.float64).T
    start = np.zeros(72)
    start[:3] = pose[:3].numpy() + np.array([0.0, 0.3, 0.0])  # the facing guess, 17 degrees off
    spec = InitSpec(0, j2d, conf, start, None, np.zeros(10))
    torch.manual_seed(0)
    got, trans, betas, _ = fit_frame0(model, cam, spec, None, cfg, (j3d, conf))
    with torch.no_grad():
        fitted = model(betas=betas, pose=got[None], trans=trans[None]).joints.double().numpy()
    return float(local_procrustes_error(fitted, truth[None])[0])


def test_the_automatic_start_follows_the_detectors_3d_away_from_rest():
    """With the defaults the start lands within a few cm of a crouch with a raised arm; with
    the weight before 2026-11-28 (every joint held towards the rest pose at 200 per rad^2) it
    stayed far nearer the rest pose."""
    base = dict(keypoint_offsets=False, init_iterations=40)
    now = _start_error(TrackerConfig.load({**base}, profile="video"))
    before = _start_error(TrackerConfig.load({**base, "init_pose_prior_weight": 200.0}, profile="video"))
    assert now < 0.035
    assert now < 0.5 * before
