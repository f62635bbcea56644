"""Automatic masks, joints and initialisation through the detector interface (a fake
detector, so the logic is tested apart from MediaPipe): frames without the person, the
person leaving the frame, another person, stored detections reused, the facing guess,
and ``flowmocap track video.mp4`` end to end with no other input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import flowmocap.vision.auto as auto
from flowmocap.body.skeleton import JOINT_INDEX
from flowmocap.errors import NoPersonError
from flowmocap.vision.auto import (auto_init, detect_sequence, facing_rotvec, first_person_frame, frame_runs,
                                   load_detections)
from flowmocap.vision.detect import KEYPOINT_NAMES, Detection

from test_detect import FakeDetector, stick_keypoints


class Frames:
    """A sequence-like object of blank frames."""

    def __init__(self, n, size=(96, 128)):
        self.n, self.size = n, size
        self.root = "frames"

    def __len__(self):
        return self.n

    def frame(self, i):
        return np.zeros((self.size[1], self.size[0], 3), np.uint8)


class Nobody:
    name = "nobody"

    def reset(self):
        pass

    def detect(self, image):
        return None


def test_gaps_and_partial_exit_are_recorded(tmp_path):
    boxes = {i: (30 + 2 * i, 20, 60 + 2 * i, 110) for i in range(2, 10) if i != 5}
    boxes[9] = (80, 20, 110, 110)  # partly out of the 96-wide frame
    track = detect_sequence(Frames(10), tmp_path, FakeDetector(boxes), progress=False)
    assert track.found.tolist() == [i in boxes for i in range(10)]
    assert track.info["no_person"] == [[0, 1], [5, 5]]
    assert not track.mask(0).any() and track.mask(3).any()
    assert not track.mask(3)[0:2, 0:2].any()  # the speck was cleaned away
    assert (track.confidence[9] == 0).any() and (track.confidence[9] > 0).any()  # joints outside: unknown
    assert first_person_frame(track) == 2
    assert (tmp_path / "detections" / "masks" / "000009.png").exists()


def test_stored_detections_are_reused(tmp_path):
    boxes = {i: (30, 20, 60, 110) for i in range(4)}
    first = detect_sequence(Frames(4), tmp_path, FakeDetector(boxes), progress=False)
    again = detect_sequence(Frames(4), tmp_path, FakeDetector({}), progress=False)  # would find nobody
    assert again.found.all() and np.allclose(again.keypoints, first.keypoints)
    assert load_detections(tmp_path, "another detector") is None
    assert load_detections(tmp_path, "fake", num_frames=5) is None


def _truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


@pytest.mark.parametrize("damage", [
    lambda d: _truncate(d / "keypoints.npz"),
    lambda d: (d / "keypoints.npz").write_bytes(b""),
    lambda d: (d / "detections.json").write_text("{half"),
    lambda d: (d / "detections.json").write_text("[]"),
    lambda d: np.savez(d / "keypoints.npz", found=np.ones(4, bool), keypoints=np.zeros(3), confidence=np.zeros(3)),
], ids=["truncated-npz", "empty-npz", "bad-json", "json-list", "wrong-shapes"])
def test_a_damaged_detection_cache_is_computed_anew(tmp_path, damage):
    """An unreadable detections/ cache (a truncated or empty keypoints.npz, bad JSON,
    arrays of the wrong shape) counts as absent: the detector runs again instead of every
    rerun failing with a traceback until the folder is deleted by hand."""
    boxes = {i: (30, 20, 60, 110) for i in range(4)}
    first = detect_sequence(Frames(4), tmp_path, FakeDetector(boxes), progress=False)
    damage(tmp_path / "detections")
    assert load_detections(tmp_path) is None
    again = detect_sequence(Frames(4), tmp_path, FakeDetector(boxes), progress=False)
    np.testing.assert_array_equal(again.keypoints, first.keypoints)
    assert load_detections(tmp_path, "fake", 4) is not None


def test_the_detection_cache_is_written_atomically(tmp_path, monkeypatch):
    """A pass stopped while it writes the cache (a kill, a full disk) leaves no half-written
    keypoints.npz and no detections.json of the earlier pass to pair with new masks: the
    next run detects again."""
    boxes = {i: (30, 20, 60, 110) for i in range(4)}
    first = detect_sequence(Frames(4), tmp_path, FakeDetector(boxes), progress=False)
    d = tmp_path / "detections"
    before = (d / "keypoints.npz").read_bytes()

    def full_disk(f, **arrays):
        f.write(b"PK\x03\x04 half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(auto.np, "savez", full_disk)
    with pytest.raises(OSError, match="No space left"):
        detect_sequence(Frames(4), tmp_path, FakeDetector(boxes), progress=False, reuse=False)
    monkeypatch.undo()
    assert (d / "keypoints.npz").read_bytes() == before and not list(d.glob("*.tmp"))
    assert load_detections(tmp_path) is None  # the earlier pass's detections.json is gone: detected again
    again = detect_sequence(Frames(4), tmp_path, FakeDetector(boxes), progress=False)
    np.testing.assert_array_equal(again.keypoints, first.keypoints)
    assert not list(d.rglob("*.tmp"))


def test_no_person_anywhere(tmp_path):
    with pytest.raises(NoPersonError, match="no person found"):
        detect_sequence(Frames(3), tmp_path, Nobody(), progress=False)


def test_frame_runs():
    assert frame_runs([2, 3, 4, 7, 9, 10]) == [[2, 4], [7, 7], [9, 10]]
    assert frame_runs(np.array([5])) == [[5, 5]]
    assert frame_runs([]) == []


def test_the_main_person_is_kept(tmp_path):
    """The tracking detector follows a small person in the background; the searcher finds
    the big one who walks through: the big one is kept, the small one ignored."""
    small = {i: (5, 5, 20, 40) for i in range(12)}
    big = {i: (30 + 3 * i, 30, 70 + 3 * i, 126) for i in range(3, 12)}
    track = detect_sequence(Frames(12, (128, 128)), tmp_path, FakeDetector(small), progress=False,
                            searcher=FakeDetector(big))
    assert track.found.tolist() == [i >= 3 for i in range(12)]
    assert track.keypoints[5, 0, 1] > 40  # the big person's hip, not the small one's
    assert track.info["ignored_people"] and track.info["ignored_people"][0]["frames"] == [0, 11]


def _facing(kp, conf):
    R = Rotation.from_rotvec(facing_rotvec(kp, conf)).as_matrix()
    return R @ np.array([0.0, 1.0, 0.0]), R @ np.array([0.0, 0.0, 1.0])  # body up, body front (camera frame)


def test_facing_guess():
    kp = stick_keypoints(40, 20, 80, 120)
    conf = np.full(len(kp), 0.9)
    up, front = _facing(kp, conf)
    assert up[1] < -0.99 and front[2] < -0.99  # upright (image y down), facing the camera
    back = kp.copy()
    for n in ("left", "right"):  # seen from behind: left and right swap sides
        for j in ("hip", "knee", "ankle", "shoulder", "elbow", "wrist", "ear"):
            back[KEYPOINT_NAMES.index(f"{n}_{j}"), 0] = kp[KEYPOINT_NAMES.index(f"{'right' if n == 'left' else 'left'}_{j}"), 0]
    conf_back = conf.copy()
    conf_back[KEYPOINT_NAMES.index("nose")] = 0.0
    up, front = _facing(back, conf_back)
    assert up[1] < -0.99 and front[2] > 0.99
    side = kp.copy()  # side-on, nose to the image right: walking to the right
    for k, n in enumerate(KEYPOINT_NAMES):
        side[k, 0] = 60.0
    side[KEYPOINT_NAMES.index("nose"), 0] = 66.0
    up, front = _facing(side, conf)
    assert front[0] > 0.9


def test_facing_guess_in_the_world_of_a_turned_camera(tmp_path):
    """With a camera of rotation R the orientation is the world's: seen through the camera
    (R times it) it is the guess for an unturned camera, upright and facing it."""
    kp = stick_keypoints(40, 20, 80, 120)
    conf = np.full(len(kp), 0.9)
    R = Rotation.from_euler("xyz", [170.0, 40.0, -5.0], degrees=True).as_matrix()  # world y up, tilted, turned
    G = Rotation.from_rotvec(facing_rotvec(kp, conf, camera_R=R)).as_matrix()
    assert np.allclose(R @ G, Rotation.from_rotvec(facing_rotvec(kp, conf)).as_matrix(), atol=1e-9)
    assert (R @ G @ [0.0, 1.0, 0.0])[1] < -0.99  # the body's up is the image's up
    assert np.allclose(facing_rotvec(kp, conf, camera_R=np.eye(3)), facing_rotvec(kp, conf))
    track = detect_sequence(Frames(3), tmp_path, FakeDetector({i: (30, 20, 60, 110) for i in range(3)}),
                            progress=False)
    init = auto_init(track, 1, camera_R=R)
    assert np.allclose(init["pose"]["pelvis"], facing_rotvec(track.keypoints[1], track.confidence[1], camera_R=R))


def test_auto_init_schema(tmp_path):
    from flowmocap.fit.init import parse_init

    track = detect_sequence(Frames(3), tmp_path, FakeDetector({i: (30, 20, 60, 110) for i in range(3)}),
                            progress=False)
    init = auto_init(track, 1)
    spec = parse_init(init, 96, 128)
    assert spec.frame == 1 and (spec.confidence > 0).sum() == 12
    assert np.allclose(spec.joints2d[JOINT_INDEX["left_hip"]], track.keypoints[1, 0])
    json.dumps(init)


# ------------------------------------------------------------------ end to end (CLI)


class GroundTruthDetector:
    """Keypoints and masks of a synthetic sequence, absent in some frames."""

    name = "gt"

    def __init__(self, seq, absent=()):
        self.seq, self.absent, self.i = seq, set(absent), 0

    def reset(self):
        self.i = 0

    def detect(self, image):
        i = self.i
        self.i += 1
        if i in self.absent:
            return None
        j2d = self.seq.gt["joints2d"][i]
        kp = np.zeros((len(KEYPOINT_NAMES), 2))
        conf = np.zeros(len(KEYPOINT_NAMES))
        for k, n in enumerate(KEYPOINT_NAMES):
            if n in JOINT_INDEX:
                kp[k], conf[k] = j2d[JOINT_INDEX[n]], 0.95
        return Detection(kp, conf, self.seq.mask(i))


@pytest.fixture(scope="module")
def small_clip(tmp_path_factory):
    from flowmocap.synth import synthesize

    d = tmp_path_factory.mktemp("auto") / "seq"
    synthesize("builtin:walk", d, fps=30, frames=6, size="160x120", seed=1, azimuth=80.0, distance=3.0, flow=False)
    return d


def test_track_video_without_any_other_input(small_clip, tmp_path, monkeypatch):
    import flowmocap.vision.detect as detect
    from flowmocap.cli import main
    from flowmocap.io.results import read_result
    from flowmocap.io.sequence import load_sequence

    from test_video import write_video

    seq = load_sequence(small_clip)
    video = write_video(tmp_path / "walk.mp4", [seq.frame(i) for i in range(len(seq))])
    fake = GroundTruthDetector(seq, absent={0, 4})
    monkeypatch.setattr(auto, "DETECT_IN_CHILD", False)  # the stand-in detectors live in this process
    monkeypatch.setattr(detect, "MediaPipePoseDetector", lambda augment=True, model="full": fake if augment else Nobody())
    cfg = tmp_path / "fast.json"
    cfg.write_text(json.dumps({"init_iterations": 8, "init_flow_iterations": 4, "iterations": 4}))
    out = tmp_path / "out"
    assert main(["track", str(video), "--out", str(out), "--config", str(cfg), "--quiet"]) == 0
    motion, run = read_result(out)
    assert run["status"] == "finished"
    assert motion["frame_index"].tolist() == [1, 2, 3, 4, 5]  # frame 0 has nobody: started at 1
    assert "started at frame 1" in run["frame_range"]
    assert run["gaps"] == [{"frames": [4, 4], "why": "no person found: tracked by flow alone, no silhouette term"}]
    assert run["masks"] == "automatic" and run["init"] == "automatic"
    assert run["camera_motion"]["moving"] is False and "rotvecs" not in run["camera_motion"]  # a still camera
    assert "default focal length" in run["camera_source"]
    assert len(run["video"]["timestamps"]) == 6 and run["video"]["fps"] == pytest.approx(30, rel=0.02)
    assert any(e.get("frame") == 4 and "empty mask" in e["event"] for e in run["events"])
    assert (out / "init_auto.json").exists() and (out / "detections" / "masks" / "000004.png").exists()
    assert np.isfinite(motion["poses"]).all()
    # automatic masks: the video profile, under the config file's
    from flowmocap.fit.config import PROFILES

    assert run["profile"] == "video" and {k: run["config"][k] for k in PROFILES["video"]} == PROFILES["video"]
    assert run["config"]["iterations"] == 4


@pytest.mark.parametrize("fast, model, made", [(False, "full", [True, False]), (True, "full", [False, False]),
                                               (False, "heavy", [True, False])])
def test_fast_runs_the_detector_without_its_mask_augmentation(small_clip, tmp_path, monkeypatch, fast, model, made):
    """--fast: the detector without the mask augmentation (augment=False); the searcher
    for other people (also augment=False) stays either way. Both are made with the
    config's ``detector_model``."""
    import flowmocap
    import flowmocap.vision.detect as detect
    from flowmocap.io.sequence import load_sequence

    built = []
    monkeypatch.setattr(auto, "DETECT_IN_CHILD", False)  # the stand-in detectors live in this process
    monkeypatch.setattr(detect, "MediaPipePoseDetector",
                        lambda augment=True, model="full": built.append((augment, model))
                        or GroundTruthDetector(load_sequence(small_clip)))
    res = flowmocap.track(small_clip, tmp_path / "out", masks="auto", frames="0:3", log=None, progress=False,
                          config={"init_iterations": 4, "init_flow_iterations": 2, "iterations": 2,
                                  "detector_model": model}, fast=fast)
    assert len(res) == 3 and np.isfinite(res.poses).all()
    assert built == [(a, model) for a in made]


def test_an_unknown_detector_model_is_refused_before_any_work(small_clip, tmp_path):
    import flowmocap
    from flowmocap.errors import InputError
    from flowmocap.fit.config import TrackerConfig

    with pytest.raises(InputError, match="unknown detector model 'huge'; choose one of full, heavy"):
        flowmocap.track(small_clip, tmp_path / "out", masks="auto", detector="huge", log=None, progress=False)
    assert not (tmp_path / "out" / "detections").exists()
    with pytest.raises(InputError, match="'detector_model' must be one of 'full', 'heavy'"):
        TrackerConfig.load(None, detector_model="huge")
    assert TrackerConfig.load(None, detector_model="full").detector_model == "full"


def test_unknown_detector_name_is_refused(tmp_path):
    from flowmocap.errors import InputError

    with pytest.raises(InputError, match="'plain', 'unaugmented'"):
        detect_sequence(Frames(3), tmp_path, detector="quick", progress=False)


class WorldDetector(GroundTruthDetector):
    """Ground-truth keypoints plus their 3D positions in the camera's axes about the hips."""

    def detect(self, image):
        i = self.i
        det = super().detect(image)
        if det is None:
            return None
        j3d = np.asarray(self.seq.gt["joints3d"][i], np.float64) @ np.asarray(self.seq.camera.R).T
        j3d -= 0.5 * (j3d[JOINT_INDEX["left_hip"]] + j3d[JOINT_INDEX["right_hip"]])
        det.world = np.array([j3d[JOINT_INDEX[n]] if n in JOINT_INDEX else np.zeros(3) for n in KEYPOINT_NAMES])
        return det


def test_3d_joints_are_stored_and_given_in_smpl_order(small_clip, tmp_path, monkeypatch):
    import flowmocap.vision.detect as detect
    from flowmocap.io.sequence import load_sequence
    from flowmocap.vision.auto import detect_joints3d

    seq = load_sequence(small_clip)
    track = detect_sequence(seq, tmp_path / "a", detector=WorldDetector(seq, absent={3}), searcher=None,
                            progress=False)
    j3d, conf = track.smpl_joints3d(2)
    truth = np.asarray(seq.gt["joints3d"][2], np.float64) @ np.asarray(seq.camera.R).T
    ok = conf > 0
    assert ok.sum() == 12
    rel = truth[ok] - truth[ok][0]
    np.testing.assert_allclose(j3d[ok] - j3d[ok][0], rel, atol=1e-5)
    assert track.smpl_joints3d(3) is None  # nobody found there
    # with the camera: turned from the axes of the ray through the hips into the camera's
    hips = track.keypoints[2, [KEYPOINT_NAMES.index("left_hip"), KEYPOINT_NAMES.index("right_hip")]].mean(0)
    turned, _ = track.smpl_joints3d(2, seq.camera)
    np.testing.assert_allclose(turned, j3d @ seq.camera.ray_rotation(*hips).T, atol=1e-9)
    part, _ = track.smpl_joints3d(2, seq.camera, ray_share=0.3)  # a share of that turn
    np.testing.assert_allclose(part, j3d @ seq.camera.ray_rotation(*hips, 0.3).T, atol=1e-9)
    stored = load_detections(tmp_path / "a")
    np.testing.assert_allclose(stored.smpl_joints3d(2)[0], j3d)
    # detections stored before the 3D joints existed load without them
    with np.load(tmp_path / "a" / "detections" / "keypoints.npz") as z:
        arrays = {k: z[k] for k in z.files if k != "world"}
    np.savez(tmp_path / "a" / "detections" / "keypoints.npz", **arrays)
    old = load_detections(tmp_path / "a")
    assert old.world is None and old.smpl_joints3d(2) is None
    # the tracker's source of them for an input with its own masks and init.json
    monkeypatch.setattr(auto, "DETECT_IN_CHILD", False)  # the stand-in detectors live in this process
    monkeypatch.setattr(detect, "MediaPipePoseDetector", lambda augment=True, model="full": WorldDetector(seq))
    joints3d, note = detect_joints3d(seq, tmp_path / "b", progress=False)
    assert joints3d is not None and joints3d(2) is not None and "3D joints" in note
    # the same from flowmocap's lifter of the 2D keypoints (detector3d_source "lifter"): other
    # numbers, the same body up to a similarity (the stand-in's 2D is the truth's projection)
    from flowmocap.geometry.procrustes import similarity_procrustes

    lifted, _ = detect_joints3d(seq, tmp_path / "b", progress=False, lift=True)
    (a, ca), (b, cb) = joints3d(2), lifted(2)
    ok = ca > 0
    assert (cb == ca).all() and not np.allclose(a[ok], b[ok])
    assert np.linalg.norm(similarity_procrustes(b[ok], a[ok])[0] - a[ok], axis=-1).mean() < 0.04  # 1.7 cm
    monkeypatch.setattr(detect, "MediaPipePoseDetector", lambda augment=True, model="full": Nobody())
    joints3d, note = detect_joints3d(seq, tmp_path / "c", progress=False)
    assert joints3d is None and "no 3D joints" in note


def test_packed_masks_round_trip_and_are_small():
    """find_people keeps one mask per person per frame of a whole video: packed to the bits
    of the mask's box, and unpacked exactly."""
    from flowmocap.vision.auto import PackedMask, _mask_array

    rng = np.random.default_rng(0)
    m = np.zeros((480, 640), bool)
    m[100:400, 250:400] = rng.random((300, 150)) > 0.3
    p = PackedMask.pack(m)
    np.testing.assert_array_equal(p.unpack(), m)
    np.testing.assert_array_equal(_mask_array(p), m)
    np.testing.assert_array_equal(_mask_array(m), m)
    assert p.bits.nbytes <= 300 * 150 / 8 + 1 and p.bits.nbytes < m.nbytes / 40
    empty = PackedMask.pack(np.zeros((4, 5), bool))
    assert empty.unpack().shape == (4, 5) and not empty.unpack().any()


def test_own_masks_and_init_can_use_the_detectors_joints_in_every_frame(small_clip, tmp_path, monkeypatch):
    """detector_keypoints: an input with its own masks and init.json runs the detector once
    and uses its 2D joints in every frame (E_j) and for refits; off, the 3D joints only."""
    import flowmocap
    import flowmocap.pipeline as pipeline
    import flowmocap.vision.detect as detect
    from flowmocap.eval.protocol import noisy_init
    from flowmocap.fit.reinit import ReinitMonitor
    from flowmocap.io.sequence import load_sequence

    seq = load_sequence(small_clip)
    monkeypatch.setattr(auto, "DETECT_IN_CHILD", False)  # the stand-in detectors live in this process
    monkeypatch.setattr(detect, "MediaPipePoseDetector", lambda augment=True, model="full": WorldDetector(seq))
    judged = []

    class Spy(ReinitMonitor):
        def __call__(self, i, state, scene, mask):
            judged.append(i)
            return super().__call__(i, state, scene, mask)

    monkeypatch.setattr(pipeline, "ReinitMonitor", Spy)
    init = noisy_init(seq.gt, frame=0, seed=1)
    quick = {"iterations": 3, "init_iterations": 5, "init_flow_iterations": 3}
    on = flowmocap.track(small_clip, tmp_path / "on", init=init, config=quick, progress=False)  # the default
    assert on.run["status"] == "finished" and on.run["profile"] == "synthetic"
    assert np.all(on.energies["keypoints"][2:] > 0)  # E_j on every tracked frame (0 and 1: the init)
    assert judged == list(range(2, len(seq)))  # every frame after the init is judged for a refit
    assert "detector joints" in on.run["joints3d"] and (tmp_path / "on" / "detections" / "keypoints.npz").exists()
    judged.clear()
    off = flowmocap.track(small_clip, tmp_path / "off", init=init, config={**quick, "detector_keypoints": False},
                          progress=False)
    assert np.isnan(off.energies["keypoints"][2:]).all()  # no E_j after the init
    assert judged == [] and "3D joints for E_d" in off.run["joints3d"]


def test_a_long_run_without_the_person_is_held_at_the_last_seen_pose(small_clip, tmp_path, monkeypatch):
    """Frames 2-3 without the person, a run longer than hold_unseen_frames (1 here): the body
    is not tracked there by flow alone but held at frame 1's pose and place, run.json says so,
    and frame 4 (seen again) is tracked."""
    import flowmocap.vision.detect as detect
    from flowmocap.cli import main
    from flowmocap.io.results import read_result
    from flowmocap.io.sequence import load_sequence

    from test_video import write_video

    seq = load_sequence(small_clip)
    video = write_video(tmp_path / "walk.mp4", [seq.frame(i) for i in range(len(seq))])
    fake = GroundTruthDetector(seq, absent={2, 3})
    monkeypatch.setattr(auto, "DETECT_IN_CHILD", False)
    monkeypatch.setattr(detect, "MediaPipePoseDetector", lambda augment=True, model="full": fake if augment else Nobody())
    cfg = tmp_path / "hold.json"
    cfg.write_text(json.dumps({"init_iterations": 8, "init_flow_iterations": 4, "iterations": 4,
                               "hold_unseen_frames": 1}))
    out = tmp_path / "out"
    assert main(["track", str(video), "--out", str(out), "--config", str(cfg), "--quiet"]) == 0
    motion, run = read_result(out)
    assert run["gaps"] == [{"frames": [2, 3], "why": "no person found: held at the last seen pose"}]
    held = [e for e in run["events"] if e["event"].startswith("held: the person is not seen")]
    assert [e["frame"] for e in held] == [2, 3] and held[0]["frames"] == [2, 3]
    rows = {int(f): k for k, f in enumerate(motion["frame_index"])}
    for key in ("poses_tracked", "trans_tracked"):
        x = motion[key]
        np.testing.assert_array_equal(x[rows[2]], x[rows[1]])
        np.testing.assert_array_equal(x[rows[3]], x[rows[1]])
        assert np.abs(x[rows[4]] - x[rows[1]]).max() > 1e-4  # seen again: tracked
    # after tracking the held frames are filled in between frames 1 and 4 (before the smoothing)
    assert run["unseen_inbetween"]["runs"] == [[2, 3]] and run["unseen_inbetween"]["frames"] == 2
    t = motion["trans_unsmoothed"]
    np.testing.assert_allclose(t[rows[2]], t[rows[1]] + (t[rows[4]] - t[rows[1]]) / 3, atol=1e-5)
    np.testing.assert_allclose(t[rows[3]], t[rows[1]] + 2 * (t[rows[4]] - t[rows[1]]) / 3, atol=1e-5)
    # at the default (15 frames) the same two frames are tracked by flow alone
    out2 = tmp_path / "out2"
    cfg.write_text(json.dumps({"init_iterations": 8, "init_flow_iterations": 4, "iterations": 4}))
    assert main(["track", str(video), "--out", str(out2), "--config", str(cfg), "--quiet"]) == 0
    motion2, run2 = read_result(out2)
    assert "flow alone" in run2["gaps"][0]["why"] and not any("held" in e["event"] for e in run2["events"])
    assert np.abs(motion2["poses_tracked"][2] - motion2["poses_tracked"][1]).max() > 1e-4
