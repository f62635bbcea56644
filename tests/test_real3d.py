"""The real multi-view 3D benchmark: joints, PA-MPJPE, people across views with unknown
time offsets (synthetic cameras), scoring a run against a reference with the views'
offsets, and a smoke test of the calibration on the real recording."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flowmocap.body.skeleton import EVAL_JOINTS
from flowmocap.errors import DataError, InputError
from flowmocap.eval.real3d import (DATA, EVAL_NAMES, VIEWS, associate_people, bone_lengths, consistent_joints,
                                   eval_points, joint_errors, pa_mpjpe, person_pixel, run_real3d, score_run, scored_frames,
                                   scored_runs, triangulate_person)
from flowmocap.vision.detect import KEYPOINT_NAMES

from test_triangulate import moving_person, ring_cameras


def keypoints3d(T=100, seed=0, centre=(0.0, 0.0)):
    """``(T, 15, 3)`` moving keypoints of one person (metres) around ``centre``."""
    X = moving_person(T, J=len(KEYPOINT_NAMES), seed=seed)
    X[..., :2] += centre
    return X


def test_eval_points_takes_the_head_between_the_ears():
    X = keypoints3d(3)
    j = eval_points(X)
    assert j.shape == (3, 13, 3) and len(EVAL_NAMES) == 13 and EVAL_NAMES[0] == "head"
    ears = 0.5 * (X[:, KEYPOINT_NAMES.index("left_ear")] + X[:, KEYPOINT_NAMES.index("right_ear")])
    np.testing.assert_allclose(j[:, 0], ears)
    np.testing.assert_allclose(j[:, EVAL_NAMES.index("right_knee")], X[:, KEYPOINT_NAMES.index("right_knee")])


def test_pa_mpjpe_per_frame_and_per_sequence():
    ref = eval_points(keypoints3d(20))
    # each frame turned, scaled and moved differently: per-frame 0, per-sequence not
    R = Rotation.from_euler("z", np.linspace(0, 90, 20)[:, None], degrees=True).as_matrix()
    moved = 1.3 * np.einsum("tij,tkj->tki", R, ref) + np.arange(20)[:, None, None] * 0.1
    pf, ps, curve = pa_mpjpe(moved, ref)
    assert pf < 1e-6 and ps > 50 and curve.shape == (20,)
    # one similarity for the whole sequence: both 0
    same = 0.8 * ref @ R[10].T + np.array([1.0, 2.0, 3.0])
    pf, ps, _ = pa_mpjpe(same, ref)
    assert pf < 1e-6 and ps < 1e-6
    # a 10 cm error on one of 13 joints in every frame: the alignment cannot raise the
    # summed squared error, so the mean error is at most sqrt(0.1^2 / 13) m
    bad = ref.copy()
    bad[:, 3, 0] += 0.1
    pf, _, _ = pa_mpjpe(bad, ref)
    assert 3 < pf < 1000 * np.sqrt(0.01 / 13)
    # a joint left out of the reference in some frames is left out of the fit there too
    valid = np.ones((20, 13), bool)
    valid[::2, 3] = False
    pf, ps, _ = pa_mpjpe(bad, ref, valid)
    pf_all, _, _ = pa_mpjpe(bad, ref)
    assert 0 < pf < pf_all
    holes = ref.copy()
    holes[::2, 3] = np.nan
    pf, ps, _ = pa_mpjpe(same, holes)
    assert pf < 1e-6 and ps < 1e-6
    valid[0, EVAL_NAMES.index("left_hip")] = False
    with pytest.raises(InputError, match="hips"):
        pa_mpjpe(bad, ref, valid)


def test_joint_errors_say_where_the_per_frame_error_comes_from():
    ref = eval_points(keypoints3d(20, seed=3))
    R = Rotation.from_euler("z", np.linspace(0, 60, 20)[:, None], degrees=True).as_matrix()
    moved = 0.9 * np.einsum("tij,tkj->tki", R, ref) + np.array([0.5, -1.0, 2.0])
    np.testing.assert_allclose(joint_errors(moved, ref), 0.0, atol=1e-6)  # a similarity per frame: none
    # every joint scored in every frame: the joints' mean is pa_mpjpe's per-frame error
    bad = moved.copy()
    bad[:, EVAL_NAMES.index("left_wrist")] += [0.12, 0.0, 0.05]
    per_joint = joint_errors(bad, ref)
    assert per_joint.shape == (13,)
    assert per_joint.mean() == pytest.approx(pa_mpjpe(bad, ref)[0], rel=1e-9)
    assert int(np.argmax(per_joint)) == EVAL_NAMES.index("left_wrist")  # the joint that is off leads
    # a joint scored in some frames: its mean over those; one never scored: NaN
    valid = np.ones((20, 13), bool)
    valid[:, EVAL_NAMES.index("right_ankle")] = False
    valid[::2, EVAL_NAMES.index("left_wrist")] = False
    got = joint_errors(bad, ref, valid)
    assert np.isnan(got[EVAL_NAMES.index("right_ankle")]) and np.isfinite(np.delete(got, EVAL_NAMES.index("right_ankle"))).all()
    assert got[EVAL_NAMES.index("left_wrist")] > 50
    with pytest.raises(InputError, match="13, 3"):
        joint_errors(bad[:, :12], ref[:, :12])


def skeleton13(T=10):
    """``(T, 13, 3)`` a standing person (metres, z up) turning about the vertical."""
    names = {"head": (0, 0, 1.6), "left_shoulder": (0.18, 0, 1.4), "right_shoulder": (-0.18, 0, 1.4),
             "left_elbow": (0.22, 0, 1.12), "right_elbow": (-0.22, 0, 1.12), "left_wrist": (0.24, 0.05, 0.88),
             "right_wrist": (-0.24, 0.05, 0.88), "left_hip": (0.1, 0, 0.9), "right_hip": (-0.1, 0, 0.9),
             "left_knee": (0.1, 0.02, 0.5), "right_knee": (-0.1, 0.02, 0.5), "left_ankle": (0.1, 0, 0.08),
             "right_ankle": (-0.1, 0, 0.08)}
    base = np.array([names[n] for n in EVAL_NAMES])
    R = Rotation.from_euler("z", np.linspace(0, 60, T)[:, None], degrees=True).as_matrix()
    return np.einsum("tij,kj->tki", R, base)


def test_joints_off_the_skeleton_are_left_out():
    j = skeleton13()
    lengths = bone_lengths(j)
    assert np.allclose(lengths[0], np.linalg.norm(j[0, 0] - j[0, 1]))
    bad = j.copy()
    bad[2, EVAL_NAMES.index("left_wrist")] += [0.3, 0.0, 0.2]  # a wrist two views agreed on wrongly
    lw, rw = EVAL_NAMES.index("left_wrist"), EVAL_NAMES.index("right_wrist")
    bad[5, [lw, rw]] = bad[5, [rw, lw]]  # wrists swapped
    bad[7, EVAL_NAMES.index("left_knee")] = np.nan
    ls, le = EVAL_NAMES.index("left_shoulder"), EVAL_NAMES.index("left_elbow")
    bad[8, ls] += [0.0, 0.0, 0.3]  # a wrong shoulder and wrist, and the elbow between them far off too
    bad[8, lw] += [0.0, 0.4, 0.0]
    bad[8, le] += [0.0, 1.2, 0.0]
    ok = consistent_joints(bad, lengths)
    expected = np.ones((10, 13), bool)
    expected[2, lw] = False
    expected[5, [lw, rw]] = False
    # a missing knee leaves the ankle with no bone that checks it
    expected[7, [EVAL_NAMES.index("left_knee"), EVAL_NAMES.index("left_ankle")]] = False
    expected[8, [ls, le, lw]] = False
    np.testing.assert_array_equal(ok, expected)


def views_of(cams, people3d, offsets, order, T=80, start=10, noise=1.0, seed=0):
    """Per view, the tracks of the people (in a per-view order), frames 0..T-1 of view v
    showing reference times start + offsets[v] + f."""
    rng = np.random.default_rng(seed)
    out = []
    for v, cam in enumerate(cams):
        tracks = []
        for p in order[v]:
            times = start + offsets[v] + np.arange(T)
            px = cam.project(people3d[p][times]) + rng.normal(0, noise, (T, len(KEYPOINT_NAMES), 2))
            tracks.append((px, np.full(px.shape[:2], 0.9)))
        out.append(tracks)
    return out


def test_people_are_associated_and_offsets_found():
    cams = ring_cameras()
    people3d = [keypoints3d(120, seed=1, centre=(-0.6, 0.2)), keypoints3d(120, seed=2, centre=(0.7, -0.3))]
    truth = [0, 2, -3, 1]
    order = [[0, 1], [1, 0], [0, 1], [1, 0]]  # each view lists the people in its own order
    tracks = views_of(cams, people3d, truth, order)
    tracks[2].append((tracks[2][0][0][::-1].copy(), tracks[2][0][1].copy()))  # someone moving otherwise
    a = associate_people(cams, tracks, search=range(-6, 7))
    assert a["offsets"].tolist() == truth
    assert a["people"] == [[[0], [1], [0], [1]], [[1], [0], [1], [0]]]
    assert a["pair_cost"][1].shape == (2, 2) and a["pair_cost"][1][0, 1] < 5 < a["pair_cost"][1][0, 0]
    # the reference of person 0, with and without view 1
    full = triangulate_person(cams, a["tracks"][0], a["offsets"])
    wo = triangulate_person(cams, a["tracks"][0], a["offsets"], exclude=1)
    assert full["times"][0] == -3 and len(full["times"]) == 80 + 3 + 2
    t = 40
    k = int(np.nonzero(full["times"] == t)[0][0])
    np.testing.assert_allclose(full["points"][k], people3d[0][10 + t], atol=0.01)
    assert full["views"][k].min() == 4 and wo["views"][k].max() == 3
    assert np.nanmedian(full["error_px"]) < 2.0
    with pytest.raises(InputError, match="one list of tracks per camera"):
        associate_people(cams, tracks[:3])


def test_person_pixel():
    kp = np.full((5, 15, 2), np.nan)
    conf = np.zeros((5, 15))
    kp[2] = np.linspace([10, 20], [30, 60], 15)
    conf[2, :3] = 0.9  # too few
    conf[3, :6] = 0.9
    kp[3] = kp[2] + 100
    frame, (x, y) = person_pixel(kp, conf)
    assert frame == 3 and x == pytest.approx((kp[3, 0, 0] + kp[3, 5, 0]) / 2)
    assert person_pixel(kp[:2], conf[:2]) is None


def fake_run(tmp_path, ref_points, offset, T=30, missing=()):
    """A result folder whose fit and detector world landmarks are the reference's joints
    (turned into another frame), frame f at reference time f + offset; frames in
    ``missing`` have no detection."""
    import cv2

    from flowmocap.io.results import write_motion

    res = tmp_path / "run"
    (res / "detections" / "masks").mkdir(parents=True)
    R = Rotation.from_euler("xyz", [10, 50, -20], degrees=True).as_matrix()
    j24 = np.zeros((T, 24, 3))
    world = np.full((T, 15, 3), np.nan)
    found = np.ones(T, bool)
    for f in range(T):
        kp3 = ref_points[f + offset] @ R.T
        j13 = eval_points(kp3)
        j24[f, list(EVAL_JOINTS)] = j13
        if f not in missing:
            world[f] = kp3 - kp3[:2].mean(0)
        else:
            found[f] = False
    write_motion(res, {"joints3d": j24.astype(np.float32), "frame_index": np.arange(T)})
    (res / "run.json").write_text(json.dumps({"status": "finished"}))
    np.savez(res / "detections" / "keypoints.npz", keypoints=np.zeros((T, 15, 2), np.float32),
             confidence=np.zeros((T, 15), np.float32), found=found, names=np.array(KEYPOINT_NAMES),
             box=np.zeros((T, 4)), world=world.astype(np.float32))
    (res / "detections" / "detections.json").write_text(json.dumps({"detector": "x", "frames": T, "size": [544, 960]}))
    for i in range(T):
        cv2.imwrite(str(res / "detections" / "masks" / f"{i:06d}.png"), np.zeros((4, 4), np.uint8))
    return res


def test_score_run_matches_frames_by_the_offset(tmp_path):
    cams = ring_cameras()
    j13 = skeleton13(60)  # a person turning: reference times 0..59, as the 15 detector keypoints
    X = np.zeros((60, len(KEYPOINT_NAMES), 3))
    for k, n in enumerate(KEYPOINT_NAMES):
        X[:, k] = j13[:, EVAL_NAMES.index(n)] if n in EVAL_NAMES else j13[:, 0] + (0.0, 0.08, 0.0)
    X[:, KEYPOINT_NAMES.index("left_ear")] = j13[:, 0] + (0.07, 0, 0)
    X[:, KEYPOINT_NAMES.index("right_ear")] = j13[:, 0] - (0.07, 0, 0)
    X[:, KEYPOINT_NAMES.index("left_elbow")] += np.sin(np.arange(60) / 5)[:, None] * (0.0, 0.05, 0.0)
    X[5, 0] = np.nan  # no reference at time 5
    tri = {"times": np.arange(60), "points": X}
    reference = {"people": {"p": {"without": {"cam02": tri}, "all": tri}}, "offsets": {"cam02": 4},
                 "cameras": {"cam02": cams[1]}}
    res = fake_run(tmp_path, np.nan_to_num(X), offset=4, T=30, missing={7})
    row = score_run(res, reference, "p", "cam02")
    # frame 1 is time 5 (no reference), frame 7 has no detection
    assert row["skipped"] == {"no_reference": 1, "no_detection": 1, "no_fit": 0}
    assert row["frames_scored"] == 28
    for m in ("flowmocap", "detector3d"):
        assert row[m]["per_frame_mm"] < 1e-3 and row[m]["per_sequence_mm"] < 1e-3
    # the arrays behind the scores: the run's frames, the fit and the reference at time f + 4
    d = scored_frames(res, reference, "p", "cam02")
    assert d["used"] == [f for f in range(30) if f not in (1, 7)]
    assert d["ours"].shape == d["detector"].shape == d["ref"].shape == (28, 13, 3)
    assert d["valid"].shape == (28, 13) and d["ours_kp"] is None  # the fake result has no body parameters
    np.testing.assert_allclose(d["ref"][2], eval_points(X[3 + 4]))  # frame 3 (the third used) at time 7
    # scored with the wrong offset the same run is off
    reference["offsets"]["cam02"] = 0
    assert score_run(res, reference, "p", "cam02")["flowmocap"]["per_frame_mm"] > 5


def test_scored_runs_yields_the_finished_person_views_with_scored_frames(tmp_path):
    cams = ring_cameras()
    j13 = skeleton13(40)
    X = np.zeros((40, len(KEYPOINT_NAMES), 3))
    for k, n in enumerate(KEYPOINT_NAMES):
        X[:, k] = j13[:, EVAL_NAMES.index(n)] if n in EVAL_NAMES else j13[:, 0]
    X[:, KEYPOINT_NAMES.index("left_ear")] = j13[:, 0] + (0.07, 0, 0)
    X[:, KEYPOINT_NAMES.index("right_ear")] = j13[:, 0] - (0.07, 0, 0)
    tri = {"times": np.arange(40), "points": X}
    reference = {"people": {"p": {"without": {"cam02": tri, "cam03": tri}, "all": tri}},
                 "offsets": {"cam02": 0, "cam03": 45}, "cameras": {"cam02": cams[1], "cam03": cams[2]}}
    runs = tmp_path / "bench" / "runs"
    runs.mkdir(parents=True)
    fake_run(tmp_path, X, offset=0, T=20).rename(runs / "p-cam02")
    fake_run(tmp_path, X, offset=0, T=20).rename(runs / "p-cam03")  # its offset puts every frame past the reference
    (runs / "p-cam04").mkdir()  # not run
    got = list(scored_runs(tmp_path / "bench", reference))
    assert [(r.name, p, v) for r, p, v, _ in got] == [("p-cam02", "p", "cam02")]
    assert got[0][3]["used"] == list(range(20))


def test_runner_checks_its_input(tmp_path):
    with pytest.raises(InputError, match="frames"):
        run_real3d(tmp_path, frames=1)
    with pytest.raises(DataError, match="not in"):
        run_real3d(tmp_path, data_dir=tmp_path / "nowhere")


@pytest.mark.parametrize("fast", [False, True])
def test_runner_passes_fast_to_the_tracker_and_records_it(tmp_path, monkeypatch, fast):
    import flowmocap.eval.real3d as r3
    from flowmocap.errors import OptimizationError

    calls = []
    monkeypatch.setattr(r3, "build_reference", lambda *a, **k: {"people": {"person1": {"tracks": {"cam01": (1,)}}},
                                                                 "info": {}})
    monkeypatch.setattr(r3, "person_pixel", lambda *a: (0, (10.0, 20.0)))
    monkeypatch.setattr(r3, "format_real3d_table", lambda result: "table")  # the stand-in reference has no numbers

    def track(video, res, **kw):
        calls.append(kw)
        raise OptimizationError("stand-in tracker")

    monkeypatch.setattr(r3, "track", track)
    out = run_real3d(tmp_path, person_views=["person1@cam01"], log=None, progress=False, fast=fast)
    assert [c["fast"] for c in calls] == [fast] and calls[0]["person"] == "10,20" and calls[0]["max_size"] == 640
    assert out["settings"]["fast"] is fast and out["rows"][0]["failed"].startswith("OptimizationError")


def test_bench_fast_is_for_real_video_only(tmp_path):
    from flowmocap.cli import main

    assert main(["bench", "--suite", "quick", "--fast", "--out", str(tmp_path / "o"), "--quiet"]) == 2


# ------------------------------------------------------------------ the real recording


@pytest.mark.skipif(not (DATA / "Calib.qca.txt").exists(), reason="the Pose2Sim recording (../shared/data/video/"
                    "pose2sim-multi) is not next to the repository")
def test_real_calibration_reprojects_detections_within_pixels():
    """One frame of every view through MediaPipe (static mode, the person in front of
    cam04 and cam03: the man, who faces cam03/cam04 and is the largest there; found in
    cam01 and cam02 by the lowest error): triangulated, the keypoints reproject within a
    few pixels; with the calibration matrix transposed (the wrong convention) by
    hundreds."""
    pytest.importorskip("mediapipe")
    from flowmocap.geometry.triangulate import CalibratedCamera, triangulate
    from flowmocap.io.calibration import read_qualisys_calibration
    import av
    import cv2

    from flowmocap.vision.auto import find_people
    from flowmocap.vision.detect import MediaPipePoseDetector

    cams = read_qualisys_calibration(DATA / "Calib.qca.txt")
    assert list(cams) == list(VIEWS)
    frame = 10

    class One:
        def __init__(self, img):
            self.img, self.size = img, (img.shape[1], img.shape[0])

        def __len__(self):
            return 1

        def frame(self, i):
            return self.img

    found = {}
    for v in VIEWS:
        with av.open(str(DATA / "videos" / f"{v}.mp4")) as container:  # only the frames up to the one needed
            for i, f in enumerate(container.decode(video=0)):
                if i == frame:
                    img = f.to_ndarray(format="rgb24")
                    break
        s = 960 / max(img.shape[:2])
        img = cv2.resize(img, (round(img.shape[1] * s), round(img.shape[0] * s)), interpolation=cv2.INTER_AREA)
        cands = find_people(One(img), MediaPipePoseDetector(augment=False),
                            [MediaPipePoseDetector(augment=False)], progress=False)[0]
        found[v] = [(np.asarray(c.keypoints) / s, np.asarray(c.confidence)) for c in cands]
    assert all(found[v] for v in VIEWS)
    # the combination of one person per view that triangulates best
    best = None
    for a in found["cam01"]:
        for b in found["cam02"]:
            for c in found["cam03"]:
                for d in found["cam04"]:
                    obs = [a, b, c, d]
                    tri = triangulate([cams[v] for v in VIEWS], np.stack([o[0] for o in obs]),
                                      np.stack([o[1] for o in obs]), max_error_px=None)
                    e = float(np.nanmedian(tri.error_px))
                    if best is None or e < best[0]:
                        best = (e, obs)
    err, obs = best
    assert err < 15.0, f"median reprojection error {err:.1f} px"
    wrong = [CalibratedCamera(c.name, c.K, c.dist, np.diag([1.0, -1, -1]) @ (np.diag([1.0, -1, -1]) @ c.R).T,
                              -(np.diag([1.0, -1, -1]) @ (np.diag([1.0, -1, -1]) @ c.R).T) @ c.center,
                              c.width, c.height) for c in (cams[v] for v in VIEWS)]
    tri = triangulate(wrong, np.stack([o[0] for o in obs]), np.stack([o[1] for o in obs]), max_error_px=None)
    assert not np.nanmedian(tri.error_px) < 100.0


def test_keypoint_joints_put_the_fit_at_the_detectors_keypoints():
    """The fit scored in the reference's convention: the 12 joints moved by the learned
    offsets, the head at the middle of the ears, in EVAL_NAMES order."""
    import torch

    from flowmocap.body import load_body_model
    from flowmocap.eval.real3d import keypoint_joints
    from flowmocap.io import walk_poses
    from flowmocap.vision.keypoint_map import load_keypoint_map

    class _Res:
        motion = {"gender": "neutral"}
        poses = walk_poses(np.linspace(0.0, 1.0, 3))
        trans = np.array([[0.0, 0.0, 3.0]] * 3)
        betas = np.zeros(10)

    pts = keypoint_joints(_Res())
    assert pts.shape == (3, 13, 3)
    model = load_body_model("default", dtype=torch.float64)
    out = model(betas=torch.zeros(1, 10, dtype=torch.float64), pose=torch.as_tensor(_Res.poses),
                trans=torch.as_tensor(_Res.trans))
    J, T = out.joints.numpy(), out.transforms.numpy()
    kmap = load_keypoint_map(model="full")  # the reference is triangulated from the full network's keypoints
    np.testing.assert_allclose(pts[:, 1:], kmap.apply(J, T)[:, list(EVAL_JOINTS)][:, 1:], atol=1e-5)
    heavy = load_keypoint_map(model="heavy").apply(J, T)[:, list(EVAL_JOINTS)][:, 1:]
    assert np.abs(pts[:, 1:] - heavy).max() > 0.005  # so scoring with the tracker's heavy offsets would differ
    np.testing.assert_allclose(pts[:, 0], kmap.ears_middle(J, T), atol=1e-5)
    assert EVAL_NAMES[0] == "head"
    assert np.linalg.norm(pts[:, 0] - J[:, EVAL_JOINTS[0]], axis=-1).min() > 0.01  # the ears are not the head joint


def test_offset_margins_say_how_well_the_offsets_are_determined():
    from flowmocap.eval.real3d import offset_margins

    info = {"offset_cost": {"cam02": [3.0, 2.1, 2.0, 2.5], "cam03": [None, 4.0, 2.0, None], "cam04": [None, None]}}
    m = offset_margins(info)
    assert m == pytest.approx({"cam02": 0.05, "cam03": 1.0})  # the better neighbour; cam04 has no finite cost
    assert offset_margins({}) == {}


def test_pinned_offsets_replace_the_estimate():
    from flowmocap.errors import InputError
    from flowmocap.eval.real3d import PINNED_OFFSETS, VIEWS, reference_offsets

    est = np.array([0, -1, -4, -1])
    np.testing.assert_array_equal(reference_offsets(est, None), est)
    np.testing.assert_array_equal(reference_offsets(est, {"cam01": 0, "cam02": 0, "cam03": -2, "cam04": 0}),
                                  [0, 0, -2, 0])
    assert PINNED_OFFSETS is None or (set(PINNED_OFFSETS) == set(VIEWS) and PINNED_OFFSETS["cam01"] == 0)
    with pytest.raises(InputError, match="lack cam04"):
        reference_offsets(est, {"cam01": 0, "cam02": 0, "cam03": -2})
    with pytest.raises(InputError, match="whole frames"):
        reference_offsets(est, {"cam01": 0, "cam02": 0.5, "cam03": -2, "cam04": 0})
