"""The shape fitted on frame 0 moved towards the proportions the whole video shows before
tracking (``TrackerConfig.init_shape_share``; fit.init.shape_towards_seen, initialise)."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from flowmocap.body import load_body_model
from flowmocap.fit import init as init_mod
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.lift_refit import body_girth, posed_proportions
from flowmocap.fit.objective import FrameState
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.vision.keypoint_map import load_keypoint_map

BETAS = np.array([1.0, -1.2, 0.6, 0.0, 0.8, 0.0, -0.5, 0.0, 0.0, 0.3])


def _pose():
    p = np.zeros(72)
    p[3 * 4] = 0.6  # a bent left knee
    p[3 * 19 + 1] = -0.5  # a turned right elbow
    return p


def _props(model, betas, pose):
    with torch.no_grad():
        return posed_proportions(model, load_keypoint_map(), torch.as_tensor(np.asarray(betas, np.float64)).reshape(1, -1),
                                 torch.as_tensor(np.asarray(pose, np.float64)).reshape(1, 72)).numpy()


@pytest.mark.parametrize("girth", [None, 0.005])
def test_shape_towards_seen_moves_the_proportions_in_the_frames_pose(girth):
    model = load_body_model("default")
    m64 = load_body_model("default", dtype=torch.float64)
    pose = torch.as_tensor(_pose(), dtype=torch.float32)
    seen = _props(m64, BETAS, pose)
    start = torch.zeros(1, 10)
    betas, info = init_mod.shape_towards_seen(model, start, pose, seen, 0.5, girth)
    assert betas.dtype == torch.float32 and betas.shape == (1, 10)
    own, got = _props(m64, start, pose), _props(m64, betas, pose)
    goal = own + 0.5 * (seen - own)
    assert np.abs(got - goal).max() < 0.6 * np.abs(own - goal).max(), (own, goal, got)
    np.testing.assert_allclose(info["proportions_before"], own, atol=1e-4)
    np.testing.assert_allclose(info["proportions_seen"], seen, atol=1e-4)
    np.testing.assert_allclose(info["proportions_after"], got, atol=1e-4)
    assert info["betas_frame0"] == [0.0] * 10 and info["share"] == 0.5 and info["girth_sigma"] == girth
    if girth:  # the width held: the body's girth moves less than without the hold
        free, _ = init_mod.shape_towards_seen(model, start, pose, seen, 0.5, None)
        moved = lambda b: float((body_girth(m64, b.double()) - body_girth(m64, start.double())).pow(2).mean().sqrt())  # noqa: E731
        assert moved(betas) < 0.7 * moved(free), (moved(betas), moved(free))


@pytest.mark.parametrize("share, given", [(0.5, True), (0.0, True), (0.5, False)])
def test_initialise_tracks_with_the_moved_shape_only_when_asked(monkeypatch, share, given):
    """initialise's wiring: frame 0's fitted betas are replaced by shape_towards_seen's before
    step 3 (refine_first_pair), and the Start says so; the fits themselves are stubbed."""
    model = load_body_model("default")
    cam = PinholeCamera.from_fov(640, 480, 60.0)
    fitted = torch.full((1, 10), 0.1)
    monkeypatch.setattr(init_mod, "fit_frame0", lambda *a, **k: (torch.as_tensor(_pose(), dtype=torch.float32),
                                                                  torch.tensor([0.0, 0.0, 4.0]), fitted, {}))
    used = {}

    def refine(scene, s0, s1, *a, **k):
        used["betas"] = scene.betas.clone()
        return s0, FrameState(s0.pose.clone(), s0.trans.clone())

    monkeypatch.setattr(init_mod, "refine_first_pair", refine)
    monkeypatch.setattr(init_mod, "frame_energy", lambda *a, **k: (None, {}))
    spec = init_mod.InitSpec(frame=0, joints2d=np.zeros((24, 2)), confidence=np.zeros(24), pose=np.zeros(72),
                             trans=None, betas=np.zeros(10))
    seen = _props(load_body_model("default", dtype=torch.float64), BETAS, _pose())
    cfg = TrackerConfig(init_shape_share=share, init_shape_girth=0.005)
    frame = SimpleNamespace(silhouette=None, joints3d=None)
    start = init_mod.initialise(model, cam, spec, frame, frame, cfg, seen if given else None)
    if share > 0 and given:
        want, _ = init_mod.shape_towards_seen(model, fitted, torch.as_tensor(_pose()), seen, share, 0.005)
        torch.testing.assert_close(used["betas"], want)
        assert start.shape is not None and start.shape["share"] == share
        assert (used["betas"] - fitted).abs().max() > 0.05
    else:
        torch.testing.assert_close(used["betas"], fitted)
        assert start.shape is None


def _walker_track(frames=16, shin_stretch=1.0):
    """A PersonTrack of a body walking in place, seen 4 m away; ``shin_stretch``: each
    ankle's 2D moved away from its knee by this factor."""
    from flowmocap.fit.lift_refit import keypoints13
    from flowmocap.vision.auto import PersonTrack
    from flowmocap.vision.detect import KEYPOINT_NAMES
    from flowmocap.vision.lifter import POINTS

    cam = PinholeCamera(fx=600.0, fy=600.0, cx=320.0, cy=240.0, width=640, height=480,
                        R=np.diag([1.0, -1.0, -1.0]), t=np.array([0.1, 0.9, 4.0]))
    poses = np.zeros((frames, 72))
    swing = 0.4 * np.sin(np.linspace(0, 2 * np.pi, frames))
    poses[:, 3 * 1], poses[:, 3 * 2] = swing, -swing  # hips
    poses[:, 3 * 4], poses[:, 3 * 5] = 0.3 + 0.3 * np.cos(swing), 0.3 - 0.3 * np.cos(swing)  # knees
    m64 = load_body_model("default", dtype=torch.float64)
    with torch.no_grad():
        kp, _ = keypoints13(m64, load_keypoint_map(), torch.as_tensor(poses), torch.zeros(1, 10, dtype=torch.float64),
                            torch.zeros(frames, 3, dtype=torch.float64))
    px = np.asarray(cam.project(kp.numpy().reshape(-1, 3))).reshape(frames, 13, 2)
    for knee, ankle in ((POINTS.index("left_knee"), POINTS.index("left_ankle")),
                        (POINTS.index("right_knee"), POINTS.index("right_ankle"))):
        px[:, ankle] = px[:, knee] + shin_stretch * (px[:, ankle] - px[:, knee])
    out = np.zeros((frames, len(KEYPOINT_NAMES), 2))
    for k, name in enumerate(POINTS):
        for n in (("left_ear", "right_ear", "nose") if name == "head" else (name,)):
            out[:, KEYPOINT_NAMES.index(n)] = px[:, k]
    return PersonTrack(out, np.ones((frames, len(KEYPOINT_NAMES))), np.ones(frames, bool), [None] * frames, {})


def test_the_pipeline_reads_the_videos_proportions_from_the_lifter_only_when_asked():
    from flowmocap.fit.lift_refit import PROPORTION_BONES
    from flowmocap.pipeline import _seen_proportions

    on = TrackerConfig(init_shape_share=0.5)
    assert _seen_proportions(None, on, 30.0) is None
    assert _seen_proportions(_walker_track(), TrackerConfig(), 30.0) is None  # the setting off
    assert _seen_proportions(_walker_track(frames=5), on, 30.0) is None  # too few frames
    plain = _seen_proportions(_walker_track(), on, 30.0)
    long = _seen_proportions(_walker_track(shin_stretch=1.25), on, 30.0)
    assert plain.shape == (7,) and abs(plain.sum() - 1) < 0.01  # medians of shares, one per bone
    shin = PROPORTION_BONES.index(((9, 11), (10, 12)))
    # what the images show, the lifter reads (a part of it: it leans on its training bodies)
    assert long[shin] > plain[shin] + 0.003, (plain, long)
