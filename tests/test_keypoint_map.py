"""The learned keypoint offsets (flowmocap.vision.keypoint_map): the shipped file loads,
the map is the closed form ``J_j + R_p o_j``, its gradient is autograd's and matches
finite differences through E_j, the tracker's terms use it only when asked, init.json
says whose joints it gives, and the learning tool recovers known offsets."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from flowmocap.body import JOINT_INDEX, load_body_model
from flowmocap.errors import InputError, ModelFileError
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.init import parse_init
from flowmocap.fit.objective import FrameData, FrameState, Scene, frame_energy, keypoint_observation
from flowmocap.geometry import PinholeCamera, look_at
from flowmocap.io import walk_poses
from flowmocap.vision.detect import SMPL_KEYPOINTS
from flowmocap.vision.keypoint_map import (KEYPOINT_OFFSETS_FILE, KEYPOINT_OFFSETS_FILES, detector_points,
                                           load_keypoint_map)

from test_learned_prior_terms import scene64  # noqa: F401  (the float64 scene fixture)
from conftest import load_script

ROOT = Path(__file__).resolve().parents[1]
ALL_OFF = dict(flow_weight=0.0, silhouette_weight=0.0, limit_weight=0.0, penetration_weight=0.0,
               temporal_weight=0.0, anchor_weight=0.0, keypoint_weight=1.0, limb_depth_weight=0.0,
               detector3d_weight=0.0, pose_prior_weight=0.0)


@pytest.mark.parametrize("model", ["full", "heavy"])
def test_the_shipped_offsets_load_and_are_small(model):
    kmap = load_keypoint_map(model=model)
    assert kmap is load_keypoint_map(model=model)  # read once
    assert kmap.offset.shape == (24, 3) and kmap.part.shape == (24,)
    moved = {j for j in range(24) if np.abs(kmap.offset[j]).max() > 0}
    assert moved <= {JOINT_INDEX[n] for n in SMPL_KEYPOINTS}  # only the detector's joints move
    assert {JOINT_INDEX["left_hip"], JOINT_INDEX["right_hip"]} <= moved  # the largest and surest offsets
    assert np.linalg.norm(kmap.offset, axis=1).max() < 0.08
    doc = json.loads(KEYPOINT_OFFSETS_FILES[model].read_text())
    assert doc["landmark_model"] == model  # learned from that network's keypoints
    for name, e in doc["keypoints"].items():  # kept only where it predicts held-out clips better
        assert e["held_out_median_px_after"] <= e["held_out_median_px_before"], name
    assert not any(f"/{s:02d}_" in f for f in doc["training_clips"] for s in (2, 8, 13, 61))  # no test subject


def test_each_landmark_network_has_its_own_offsets_and_the_tracker_uses_its_networks(scene64):
    full, heavy = load_keypoint_map(), load_keypoint_map(model="heavy")
    assert full is load_keypoint_map(model="full") and KEYPOINT_OFFSETS_FILES["full"] == KEYPOINT_OFFSETS_FILE
    assert not np.allclose(full.offset, heavy.offset)  # the networks place some keypoints differently
    out = scene64.model(betas=scene64.betas, pose=torch.tensor(walk_poses(np.array([0.3]))[0])[None])
    for model, kmap in (("full", full), ("heavy", heavy)):
        got = detector_points(out, TrackerConfig(keypoint_offsets=True, detector_model=model))
        torch.testing.assert_close(got, kmap.apply(out.joints, out.transforms))
    with pytest.raises(InputError, match="unknown detector model"):
        load_keypoint_map(model="lite")


def test_apply_is_the_closed_form_and_follows_the_body(scene64):
    kmap = load_keypoint_map()
    model = scene64.model
    pose = torch.tensor(walk_poses(np.array([0.4]))[0])
    out = model(betas=scene64.betas, pose=pose[None], trans=torch.tensor([[0.1, 0.0, 0.2]], dtype=torch.float64))
    pts = kmap.apply(out.joints, out.transforms)[0].numpy()
    J, T = out.joints[0].numpy(), out.transforms[0].numpy()
    for j in range(24):
        np.testing.assert_allclose(pts[j], J[j] + T[kmap.part[j], :3, :3] @ kmap.offset[j], atol=1e-12)
    np.testing.assert_allclose(kmap.apply(J, T), pts, atol=1e-12)  # numpy and torch agree
    # rest pose: the offsets themselves
    rest = model(betas=scene64.betas)
    np.testing.assert_allclose(kmap.apply(rest.joints, rest.transforms)[0].numpy() - rest.joints[0].numpy(),
                               kmap.offset, atol=1e-12)
    # turning the whole body turns the keypoints with it
    turned = pose.clone()
    turned[:3] = torch.tensor([0.0, 1.2, 0.0])
    from scipy.spatial.transform import Rotation

    g0 = Rotation.from_rotvec(pose[:3].numpy())
    g1 = Rotation.from_rotvec(turned[:3].numpy())
    o0 = model(betas=scene64.betas, pose=pose[None])
    o1 = model(betas=scene64.betas, pose=turned[None])
    p0 = kmap.apply(o0.joints, o0.transforms)[0].numpy() - o0.joints[0, 0].numpy()
    p1 = kmap.apply(o1.joints, o1.transforms)[0].numpy() - o1.joints[0, 0].numpy()
    np.testing.assert_allclose(p1, (g1 * g0.inv()).apply(p0), atol=1e-9)
    # the ears' middle: head + R_head o
    h = JOINT_INDEX["head"]
    np.testing.assert_allclose(kmap.ears_middle(J, T), J[h] + T[kmap.ears_part, :3, :3] @ kmap.ears_offset, atol=1e-12)


def test_detector_points_only_when_asked(scene64):
    out = scene64.model(betas=scene64.betas)
    assert detector_points(out, TrackerConfig(keypoint_offsets=False)) is out.joints
    assert detector_points(out, None) is out.joints
    moved = detector_points(out, TrackerConfig(keypoint_offsets=True))
    assert not torch.allclose(moved, out.joints)


def _keypoint_data(scene, pose, shift):
    """2D joints of ``pose`` shifted by ``shift`` px, for E_j."""
    with torch.no_grad():
        out, _, _ = scene.forward(pose, torch.zeros(3, dtype=torch.float64))
        j2d = scene.camera.project(out.joints[0]).numpy() + shift
    conf = np.zeros(24)
    conf[[JOINT_INDEX[n] for n in SMPL_KEYPOINTS]] = 1.0
    return FrameData(mask=None, silhouette=None, person_pixels=1.0, keypoints=keypoint_observation(j2d, conf))


def test_e_j_with_offsets_is_zero_at_the_keypoints_and_its_gradient_matches_finite_differences(scene64):
    pose = torch.tensor(walk_poses(np.array([0.2]))[0])
    cfg = TrackerConfig(keypoint_offsets=True, **ALL_OFF)
    # observed keypoints exactly where the map puts them: E_j = 0 with the map, > 0 without
    with torch.no_grad():
        out, _, _ = scene64.forward(pose, torch.zeros(3, dtype=torch.float64))
        kp = scene64.camera.project(detector_points(out, cfg)[0]).numpy()
    conf = np.zeros(24)
    conf[[JOINT_INDEX[n] for n in SMPL_KEYPOINTS]] = 1.0
    data = FrameData(mask=None, silhouette=None, person_pixels=1.0, keypoints=keypoint_observation(kp, conf))
    state = FrameState(pose, torch.zeros(3, dtype=torch.float64))
    on, _ = frame_energy(scene64, state, data, cfg, None, None, None)
    off, _ = frame_energy(scene64, state, data, TrackerConfig(keypoint_offsets=False, **ALL_OFF), None, None, None)
    assert float(on) < 1e-8 < 1e-3 < float(off)  # the observation is stored in float32
    # gradient with respect to the pose against central differences
    data = _keypoint_data(scene64, pose, shift=3.0)
    p = pose.clone().requires_grad_()
    e, _ = frame_energy(scene64, FrameState(p, torch.zeros(3, dtype=torch.float64)), data, cfg, None, None, None)
    (g,) = torch.autograd.grad(e, p)
    h = 1e-6
    for k in (0, 4, 3 * JOINT_INDEX["left_hip"], 3 * JOINT_INDEX["right_shoulder"] + 2, 3 * JOINT_INDEX["left_knee"]):
        d = torch.zeros(72, dtype=torch.float64)
        d[k] = h
        ep = frame_energy(scene64, FrameState(pose + d, torch.zeros(3, dtype=torch.float64)), data, cfg, None, None, None)[0]
        em = frame_energy(scene64, FrameState(pose - d, torch.zeros(3, dtype=torch.float64)), data, cfg, None, None, None)[0]
        assert float(g[k]) == pytest.approx(float(ep - em) / (2 * h), rel=1e-5, abs=1e-7)


def test_init_json_says_whose_joints_it_gives():
    base = {"joints2d": {"left_hip": [10, 10], "right_hip": [20, 10], "left_shoulder": [10, 0],
                         "right_shoulder": [20, 0]}}
    assert parse_init(base).from_detector is False
    assert parse_init({**base, "joints_from": "detector"}).from_detector is True
    with pytest.raises(InputError, match="joints_from"):
        parse_init({**base, "joints_from": "openpose"})


def test_auto_init_marks_its_joints_as_the_detectors():
    from flowmocap.vision.auto import PersonTrack, auto_init

    K = 15
    kp = np.tile(np.linspace(50, 200, K)[:, None], (1, 1, 2)).reshape(1, K, 2)
    track = PersonTrack(keypoints=kp, confidence=np.ones((1, K)), found=np.array([True]), mask_paths=[None])
    init = auto_init(track, 0)
    assert init["joints_from"] == "detector" and parse_init(init).from_detector


def test_a_bad_offset_file_gets_the_projects_error(tmp_path):
    with pytest.raises(ModelFileError, match="not found"):
        load_keypoint_map(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"keypoints": {"left_hip": {"joint": "left_hip"}}}))
    with pytest.raises(ModelFileError, match="not a keypoint-offset file"):
        load_keypoint_map(bad)
    doc = json.loads(KEYPOINT_OFFSETS_FILE.read_text())
    doc["keypoints"]["left_hip"]["offset_m"] = [0.0, 5.0, 0.0]
    big = tmp_path / "big.json"
    big.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match="below 0.2 m"):
        load_keypoint_map(big)


def _tool():
    return load_script(ROOT / "tools" / "learn_keypoint_offsets.py")


def test_the_learning_tool_recovers_a_known_offset_despite_outliers():
    tool = _tool()
    rng = np.random.default_rng(3)
    o_true = np.array([0.03, -0.02, 0.015])
    clips = []
    X, R, uv, ci = [], [], [], []
    from scipy.spatial.transform import Rotation

    for c in range(3):
        Rc, tc = look_at((3.0 * np.sin(c), 0.3, 3.0 * np.cos(c)), (0.0, 0.0, 0.0))
        cam = PinholeCamera.from_focal(640, 480, 600.0, Rc, tc)
        clips.append({"camera": cam})
        for _ in range(80):
            x = rng.normal(0, 0.3, 3)
            r = Rotation.random(random_state=rng.integers(1 << 30)).as_matrix()
            p = cam.project(torch.as_tensor((x + r @ o_true)[None]))[0].numpy()
            X.append(x)
            R.append(r)
            uv.append(p + rng.normal(0, 0.5, 2))
            ci.append(c)
    X, R, uv, ci = np.array(X), np.array(R), np.array(uv), np.array(ci)
    uv[::20] += 80.0  # 5 % gross outliers
    o = tool.fit_offset(clips, X, R, uv, ci)
    np.testing.assert_allclose(o, o_true, atol=2e-3)
    assert tool.median_error(clips, X, R, uv, ci, o) < 1.0 < tool.median_error(clips, X, R, uv, ci, np.zeros(3))


def test_the_joint_fit_reads_detector_joints_through_the_map_and_given_joints_as_the_models(scene64):
    """fit_to_joints (init steps 1-2, the refits): with ``joints_from_detector`` and
    ``keypoint_offsets`` it matches the detector's keypoints with the mapped points, so
    keypoints made from a known pose through the map are fitted back to that pose's map
    (and without the map the joints end off by about the offsets); given joints are the
    model's own either way."""
    from flowmocap.fit.init import fit_to_joints

    model = load_body_model("default")
    R, t = look_at((0.3, 0.2, 3.0), (0.0, -0.1, 0.0))
    cam = PinholeCamera.from_focal(640, 480, 1000.0, R, t)  # 1 cm is about 3 px here
    pose = torch.tensor(walk_poses(np.array([0.3]))[0], dtype=torch.float32)
    trans = torch.tensor([0.0, 0.0, 0.0])
    cfg_on = TrackerConfig(keypoint_offsets=True, init_pose_prior_weight=0.0, init_learned_prior_weight=0.0)
    with torch.no_grad():
        out = model(pose=pose[None], trans=trans[None])
        kp = cam.project(detector_points(out, cfg_on)[0]).numpy()
    conf = np.zeros(24)
    conf[[JOINT_INDEX[n] for n in SMPL_KEYPOINTS]] = 1.0
    moved = conf.astype(bool) & (np.abs(load_keypoint_map().offset).max(1) > 0)
    start = pose.clone()
    start[3:] *= 0.7

    def err(p, t, cfg):
        """Mean px distance of the moved joints' mapped points from the keypoints."""
        with torch.no_grad():
            o = model(pose=p[None], trans=t[None])
            return float(np.linalg.norm(cam.project(detector_points(o, cfg)[0]).numpy() - kp, axis=1)[moved].mean())

    p1, t1, _, _ = fit_to_joints(model, cam, kp, conf, None, cfg_on, start, trans, torch.zeros(1, 10), fit_shape=False,
                                 iterations=30, joints_from_detector=True)
    p0, t0, _, _ = fit_to_joints(model, cam, kp, conf, None, cfg_on, start, trans, torch.zeros(1, 10), fit_shape=False,
                                 iterations=30, joints_from_detector=False)
    e1, e0 = err(p1, t1, cfg_on), err(p0, t0, cfg_on)
    assert e1 < 1.5  # px: the map's points land on the keypoints (0.9 px: the joint limits hold a little)
    assert e0 > 2 * e1 + 1.0  # read as the model's joints, the body ends off by about the offsets (3.8 px)
