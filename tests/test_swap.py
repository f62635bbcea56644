"""A detection that labels the whole body left for right: told against the body, undone
in 2D and 3D (closed forms), and used so by the tracker and the re-initialisation check."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from flowmocap.body.skeleton import JOINT_NAMES
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.objective import FrameState, Scene, frame_data, keypoint_observation
from flowmocap.fit.pose_prior import MIRROR_JOINTS
from flowmocap.fit.swap import detection_swapped, exchanged_2d, exchanged_3d, exchanged_keypoints
from flowmocap.fit.tracker import SequenceTracker
from flowmocap.vision.detect import KEYPOINT_NAMES
from flowmocap.vision.keypoint_map import detector_points

M = list(MIRROR_JOINTS)
DETECTED = [JOINT_NAMES.index(n) for n in ("left_hip", "right_hip", "left_knee", "right_knee", "left_ankle",
                                           "right_ankle", "left_shoulder", "right_shoulder", "left_elbow",
                                           "right_elbow", "left_wrist", "right_wrist")]


def _conf():
    c = np.zeros(24)
    c[DETECTED] = 0.9
    return c


def _front_points(width=60.0):
    """``(24, 2)`` pixels of a body seen from the front: each left joint ``width`` px right of its right one."""
    rng = np.random.default_rng(0)
    p = rng.uniform(100, 200, (24, 2))
    for j in range(24):
        if M[j] > j:  # a left/right pair: the same height, apart in x
            p[M[j]] = p[j] - (width, 0.0)
    return p


def test_a_swapped_detection_is_told_from_the_body():
    p = _front_points()
    rng = np.random.default_rng(1)
    conf = _conf()
    assert detection_swapped(p, p[M] + rng.normal(0, 3, p.shape), conf, 20.0)
    assert not detection_swapped(p, p + rng.normal(0, 3, p.shape), conf, 20.0)
    # a side view (left and right nearly on top of each other) is never exchanged
    side = _front_points(width=8.0)
    assert not detection_swapped(side, side[M], conf, 20.0)
    # too few joints on both sides: nothing decided
    few = conf.copy()
    few[DETECTED[:8]] = 0.0
    assert not detection_swapped(p, p[M], few, 20.0)
    # one limb swapped is not the whole body
    one = p.copy()
    w, ww = JOINT_NAMES.index("left_wrist"), JOINT_NAMES.index("right_wrist")
    one[[w, ww]] = p[[ww, w]]
    assert not detection_swapped(p, one, conf, 20.0)


def test_exchanges_are_their_own_inverse_and_turn_the_3d_back_in_closed_form():
    rng = np.random.default_rng(2)
    j2d, conf = rng.normal(size=(24, 2)), rng.uniform(size=24)
    a, b = exchanged_2d(*exchanged_2d(j2d, conf))
    np.testing.assert_array_equal(a, j2d)
    np.testing.assert_array_equal(b, conf)
    t2, c2 = exchanged_2d(torch.as_tensor(j2d), torch.as_tensor(conf))  # tensors too
    np.testing.assert_array_equal(t2.numpy(), j2d[M])
    # the true body X (hip-relative, camera axes); the detector's turned-about reading of it:
    # labels exchanged and mirrored through the plane across the ray through the hips
    X = rng.normal(0, 0.3, (24, 3))
    ray = np.array([0.3, -0.2, 1.0])
    r = ray / np.linalg.norm(ray)
    turned = X[M] - 2 * (X[M] @ r)[:, None] * r
    back, c3 = exchanged_3d(turned, conf, 5 * ray)  # any length of ray
    np.testing.assert_allclose(back, X, atol=1e-12)
    np.testing.assert_array_equal(c3, conf[M])
    # its image is kept to first order: the gap shrinks with the distance along the ray
    def gap(dist):
        proj = lambda Y: (Y + dist * r)[:, :2] / (Y + dist * r)[:, 2:]  # noqa: E731
        return np.abs(proj(turned) - proj(X[M])).max() / np.abs(proj(X) - proj(X).mean(0)).max()

    assert gap(10.0) < 0.1 and gap(10.0) < 0.5 * gap(4.0)
    kp = np.arange(len(KEYPOINT_NAMES) * 2, dtype=float).reshape(-1, 2)
    k2, _ = exchanged_keypoints(kp, np.ones(len(KEYPOINT_NAMES)))
    le, re, nose = (KEYPOINT_NAMES.index(n) for n in ("left_ear", "right_ear", "nose"))
    np.testing.assert_array_equal(k2[le], kp[re])
    np.testing.assert_array_equal(k2[nose], kp[nose])


@pytest.fixture(scope="module")
def front(tmp_path_factory):
    """A short walk seen from the front, and the true body's detector points and camera-axes joints."""
    from flowmocap.body import load_body_model
    from flowmocap.io.sequence import load_sequence
    from flowmocap.synth import synthesize

    d = tmp_path_factory.mktemp("swap") / "seq"
    synthesize("builtin:walk", d, fps=30, frames=6, size="320x240", seed=4, azimuth=0.0, distance=3.0, flow=False)
    seq = load_sequence(d)
    scene = Scene(load_body_model("default"), torch.as_tensor(seq.gt["betas"], dtype=torch.float32)[None],
                  seq.camera)
    pts, j3d = [], []
    for i in range(len(seq)):
        st = FrameState(torch.as_tensor(seq.gt["poses"][i], dtype=torch.float32),
                        torch.as_tensor(seq.gt["trans"][i], dtype=torch.float32))
        with torch.no_grad():
            out, _, _ = scene.forward(st.pose, st.trans)
            pts.append(scene.camera.project(detector_points(out, TrackerConfig())[0]).double().numpy())
            cam = scene.camera.to_camera(out.joints[0]).double().numpy()
        j3d.append(cam - cam[[1, 2]].mean(0))
    return seq, scene, pts, j3d


def _state(seq, i):
    return FrameState(torch.as_tensor(seq.gt["poses"][i], dtype=torch.float32),
                      torch.as_tensor(seq.gt["trans"][i], dtype=torch.float32))


def test_the_tracker_exchanges_a_swapped_detection_back_for_its_terms(front):
    seq, scene, pts, j3d = front
    i = 3
    root = scene.camera.to_camera(scene.forward(_state(seq, i).pose, _state(seq, i).trans)[0].joints[0, 0])
    r = root.double().numpy()
    r /= np.linalg.norm(r)
    truth3d = j3d[i]
    turned = truth3d[M] - 2 * (truth3d[M] @ r)[:, None] * r  # what a detector turned about gives
    for check in (True, False):
        tracker = SequenceTracker(scene, TrackerConfig(detector_swap_check=check))
        data = frame_data(seq.mask(i), None, TrackerConfig(), float("nan"),
                          keypoint_observation(pts[i][M], _conf()))
        data.joints3d = (turned, _conf())
        swapped = check and tracker.exchange_if_swapped(_state(seq, i), data)
        assert swapped is check
        if check:  # the frame's terms see the body as it is
            np.testing.assert_allclose(data.keypoints[0].numpy()[DETECTED], pts[i][DETECTED], atol=1e-3)
            np.testing.assert_allclose(data.joints3d[0], truth3d, atol=1e-6)
    # an unswapped detection is left as it is
    data = frame_data(seq.mask(i), None, TrackerConfig(), float("nan"), keypoint_observation(pts[i], _conf()))
    before = copy.deepcopy(data.keypoints)
    assert not SequenceTracker(scene, TrackerConfig(detector_swap_check=True)).exchange_if_swapped(_state(seq, i), data)
    assert torch.equal(data.keypoints[0], before[0])


def test_a_tracked_run_records_the_exchanges_and_the_reinit_check_sees_them(front, tmp_path):
    from flowmocap.fit.reinit import ReinitMonitor
    from flowmocap.fit.tracker import track_frames
    from flowmocap.vision.auto import detect_sequence

    from test_auto import GroundTruthDetector

    seq, scene, pts, j3d = front
    swapped_frames = {3, 4}

    def observe(i):
        kp = pts[i][M] if i in swapped_frames else pts[i]
        data = frame_data(seq.mask(i), None, TrackerConfig(), float("nan"), keypoint_observation(kp, _conf()))
        return seq.mask(i), data

    events = {}
    for check in (True, False):
        tracker = SequenceTracker(scene, TrackerConfig(detector_swap_check=check, flow_weight=0.0))
        tracker.start(_state(seq, 0), _state(seq, 1), anchored=True)
        res = []
        track_frames(tracker, range(2, 6), observe, res.append, progress=False)
        events[check] = sorted(e["frame"] for r in res for e in r.events
                               if e["event"] == "detection's left and right exchanged back")
    assert events == {True: [3, 4], False: []}

    # the re-initialisation check judges a frame against the detection as the tracker used it
    track = detect_sequence(seq, tmp_path / "det", GroundTruthDetector(seq), progress=False)
    track_sw = copy.copy(track)
    track_sw.keypoints = track.keypoints.copy()
    track_sw.keypoints[3], track_sw.confidence = exchanged_keypoints(track.keypoints[3], track.confidence[3])[0], \
        track.confidence.copy()
    mon = ReinitMonitor(track_sw, TrackerConfig())
    as_given = mon.judge(3, scene, _state(seq, 3).pose, _state(seq, 3).trans, None)["joint_error"]
    mon.exchanged = {3}
    exchanged = mon.judge(3, scene, _state(seq, 3).pose, _state(seq, 3).trans, None)["joint_error"]
    assert exchanged < 0.05 < as_given, (exchanged, as_given)


def test_exchanged_frames_reads_the_trackers_events():
    from flowmocap.fit.swap import EXCHANGED_EVENT, exchanged_frames

    events = [{"frame": 7, "event": EXCHANGED_EVENT}, {"frame": 3, "event": "re-initialised"},
              {"frame": 2, "event": EXCHANGED_EVENT}, {"frame": 7, "event": EXCHANGED_EVENT}, {"event": EXCHANGED_EVENT}]
    assert exchanged_frames(events) == [2, 7]
    assert exchanged_frames([]) == []
