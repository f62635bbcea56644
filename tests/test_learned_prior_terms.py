"""The learned pose prior (flowmocap.fit.pose_prior) as a term of the per-frame objective
and of the init's and refits' joint fits: off by default, loaded once, the prior's
energy times its weight, with the gradient of that energy."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flowmocap.body import JOINT_INDEX, load_body_model
from flowmocap.fit.config import DEPTH_CUES_OFF, TrackerConfig
from flowmocap.fit.objective import FrameData, FrameState, Scene, frame_energy, learned_pose_prior
from flowmocap.geometry import PinholeCamera, look_at
from flowmocap.io import walk_poses

J = JOINT_INDEX
#: every weight of the per-frame objective off, so a test sees one term alone
ALL_OFF = dict(flow_weight=0.0, silhouette_weight=0.0, limit_weight=0.0, penetration_weight=0.0,
               temporal_weight=0.0, anchor_weight=0.0, keypoint_weight=0.0, limb_depth_weight=0.0)


@pytest.fixture(scope="module")
def scene64():
    R, t = look_at((0.3, 0.2, 3.0), (0.0, -0.1, 0.0))
    cam = PinholeCamera.from_focal(320, 240, 300.0, R, t)
    return Scene(load_body_model("default", dtype=torch.float64), torch.zeros(1, 10, dtype=torch.float64), cam)


def _data():
    return FrameData(mask=None, silhouette=None, person_pixels=1.0)


def test_the_prior_is_loaded_once():
    assert learned_pose_prior() is learned_pose_prior()


def test_off_at_weight_zero_and_weighted_when_on(scene64):
    pose = torch.tensor(walk_poses(np.array([0.3]))[0])
    state = FrameState(pose, torch.zeros(3, dtype=torch.float64))
    assert TrackerConfig().pose_prior_weight > 0  # on by default
    _, terms = frame_energy(scene64, state, _data(), TrackerConfig(**DEPTH_CUES_OFF), None, None, None)
    assert "learned_prior" not in terms
    cfg = TrackerConfig(pose_prior_weight=0.01, **ALL_OFF)
    total, terms = frame_energy(scene64, state, _data(), cfg, None, None, None)
    expected = 0.01 * float(learned_pose_prior().energy(pose[None])[0])
    assert terms == {"learned_prior": pytest.approx(expected, rel=1e-12)}
    assert float(total) == pytest.approx(expected, rel=1e-12)
    # a pose no one makes costs more than a walking one
    odd = pose.clone()
    odd[3 * J["left_knee"]] -= 1.5  # the knee bent backwards
    odd[3 * J["right_elbow"] + 1] -= 2.0
    assert frame_energy(scene64, FrameState(odd, state.trans), _data(), cfg, None, None, None)[1]["learned_prior"] > \
        terms["learned_prior"]


def test_gradient_of_the_term_matches_finite_differences(scene64):
    cfg = TrackerConfig(pose_prior_weight=0.01, **ALL_OFF)
    trans = torch.zeros(3, dtype=torch.float64)
    pose = torch.tensor(walk_poses(np.array([0.6]))[0]).requires_grad_()

    def f(p):
        return frame_energy(scene64, FrameState(p, trans), _data(), cfg, None, None, None)[0]

    # away from a tie between two mixture components the max-mixture energy is smooth
    assert torch.autograd.gradcheck(f, (pose,), eps=1e-6, atol=1e-7)


def test_the_joint_fits_take_the_prior(scene64, monkeypatch):
    """fit_to_joints (the init's steps 1-2 and the refits) adds the prior with
    ``init_learned_prior_weight`` and not otherwise; the fit with it ends at a pose the
    prior likes better."""
    import flowmocap.fit.init as init

    model = load_body_model("default")
    cam = scene64.camera
    pose = torch.tensor(walk_poses(np.array([0.3]))[0], dtype=torch.float32)
    with torch.no_grad():
        j2d = cam.project(model(pose=pose[None]).joints[0]).numpy()
    conf = np.zeros(24)
    conf[[1, 2, 4, 5, 7, 8, 16, 17, 18, 19, 20, 21]] = 1.0
    start = torch.zeros(72)
    start[:3] = pose[:3]
    out = {}
    for w in (0.0, 50.0):
        cfg = TrackerConfig(init_learned_prior_weight=w, init_pose_prior_weight=0.0)
        p, _, _, terms = init.fit_to_joints(model, cam, j2d, conf, None, cfg, start, torch.zeros(3),
                                            torch.zeros(1, 10), fit_shape=False, iterations=15)
        out[w] = (float(learned_pose_prior().energy(p[None])[0]), terms)
    assert "learned_prior" not in out[0.0][1] and out[50.0][1]["learned_prior"] == pytest.approx(50.0 * out[50.0][0],
                                                                                                  rel=1e-5)
    assert out[50.0][0] < out[0.0][0]


def test_uncovered_joints_prior_closed_form_and_gradient(scene64):
    """``uncovered_prior_weight`` adds, to ``E_p``, that weight times the squared rotations
    of the joints the learned prior does not cover (closed form), with that gradient."""
    from flowmocap.fit.objective import uncovered_joint_weights

    w = uncovered_joint_weights()
    names = {n for n, j in J.items() if w[j] > 0}
    assert names == {"spine3", "left_collar", "right_collar", "left_foot", "right_foot", "left_hand", "right_hand"}
    pose = torch.tensor(walk_poses(np.array([0.3]))[0])
    pose[3 * J["left_collar"]:3 * J["left_collar"] + 3] = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    pose[3 * J["spine3"] + 2] = 0.25
    state = FrameState(pose.clone().requires_grad_(), torch.zeros(3, dtype=torch.float64))
    expected = sum(float((pose[3 * J[n]:3 * J[n] + 3] ** 2).sum()) for n in names)
    cfg = TrackerConfig(pose_prior_weight=0.0, uncovered_prior_weight=2.0, **ALL_OFF)
    total, terms = frame_energy(scene64, state, _data(), cfg, None, None, None)
    assert terms == {"learned_prior": pytest.approx(2.0 * expected, rel=1e-12)}
    total.backward()
    grad = torch.zeros(72, dtype=torch.float64)
    for n in names:
        grad[3 * J[n]:3 * J[n] + 3] = 4.0 * pose[3 * J[n]:3 * J[n] + 3]
    torch.testing.assert_close(state.pose.grad, grad)
    both = TrackerConfig(pose_prior_weight=0.01, uncovered_prior_weight=2.0, **ALL_OFF)
    _, terms = frame_energy(scene64, FrameState(pose, state.trans), _data(), both, None, None, None)
    gmm = 0.01 * float(learned_pose_prior().energy(pose[None])[0])
    assert terms["learned_prior"] == pytest.approx(gmm + 2.0 * expected, rel=1e-12)
    assert TrackerConfig().uncovered_prior_weight == 0.0
