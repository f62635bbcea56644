"""Closed-form checks of the measures in issue 18's check scripts:
benchmarks/real3d_torso.py (the torso's yaw), benchmarks/detector_runs_2d.py (the
detector runs' keypoints combined), benchmarks/source_selection.py and
benchmarks/disagreement.py (the sources' disagreement as a flag),
benchmarks/error_over_time.py (a clip's error by time), benchmarks/prior_flip.py (the
pose prior against a limb mirrored in depth), benchmarks/mediapipe_image_depth.py
(MediaPipe's image-landmark depth), benchmarks/camera_motion_cost.py (the camera's
motion timed pass by pass), and benchmarks/virtual_pan.py (a turning camera made from a
still one)."""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import load_script

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def _load(name):
    return load_script(BENCH / f"{name}.py")


@pytest.fixture(scope="module")
def torso():
    return _load("real3d_torso")


NAMES = ("head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
         "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle")


def _body(rotvec: np.ndarray) -> np.ndarray:
    """A torso in SMPL's body axes (x the person's left, y up, z forward), turned by
    ``rotvec`` into the camera's axes and put 3 m in front of it: ``(1, 13, 3)``."""
    p = np.zeros((13, 3))
    i = {n: k for k, n in enumerate(NAMES)}
    p[i["left_shoulder"]], p[i["right_shoulder"]] = (0.18, 0.5, 0.0), (-0.18, 0.5, 0.0)
    p[i["left_hip"]], p[i["right_hip"]] = (0.1, 0.0, 0.02), (-0.1, 0.0, 0.02)
    return (Rotation.from_rotvec(rotvec).apply(p) + (0.0, 0.0, 3.0))[None]


@pytest.mark.parametrize("yaw", [0.0, 30.0, -75.0, 150.0, -170.0])
def test_torso_yaw_follows_the_facing_convention_of_the_automatic_init(torso, yaw):
    # facing_rotvec's global orientation for an upright body turned by `yaw`
    rotvec = (Rotation.from_euler("y", np.radians(yaw)) * Rotation.from_euler("x", np.pi)).as_rotvec()
    got = torso.torso_yaw(_body(rotvec), NAMES)[0]
    assert torso.angle_gap(np.array([got]), np.array([yaw]))[0] == pytest.approx(0.0, abs=1e-6)


def test_angle_gap_wraps(torso):
    got = torso.angle_gap(np.array([179.0, -170.0, 10.0]), np.array([-179.0, 170.0, 10.0]))
    assert got == pytest.approx([2, 20, 0])


def test_the_mirror_run_comes_back_with_left_and_right_exchanged():
    mod = _load("detector_runs_2d")

    class Landmark:
        def __init__(self, x, y):
            self.x, self.y, self.visibility = x, y, 1.0

    # a result whose every landmark sits at x = 0.25 of a 200-px-wide mirrored image, but
    # the left shoulder at 0.75: mirrored back, the person's left shoulder is at 50 px
    # and the right shoulder takes the other value
    lms = [Landmark(0.25, 0.5) for _ in range(33)]
    lms[mod.MEDIAPIPE_LANDMARKS["left_shoulder"]] = Landmark(0.75, 0.5)

    class Result:
        pose_landmarks = type("L", (), {"landmark": lms})

    kp = mod.landmarks(Result(), 200, 100, mirrored=True)
    names = list(mod.KEYPOINT_NAMES)
    assert kp[names.index("right_shoulder")] == pytest.approx([50.0, 50.0])
    assert kp[names.index("left_shoulder")] == pytest.approx([150.0, 50.0])


def test_hypotheses_combine_the_runs_given():
    mod = _load("detector_runs_2d")
    base = np.stack([np.arange(15.0), np.arange(15.0) * 2], 1) * 10.0  # a body about 220 px tall
    others = {"mirror": base + 2.0, "border": None, "single": base + 100.0}  # one run far off, one missing
    h = mod.hypotheses(base, others)
    K = mod.K
    assert h["border"] is None
    assert h["mean"] == pytest.approx((3 * base[:K] + 102.0) / 3)
    assert h["median"] == pytest.approx(base[:K] + 2.0)
    assert h["main_and_mirror"] == pytest.approx(base[:K] + 1.0)
    assert h["mean_of_agreeing"] == pytest.approx(base[:K] + 1.0)  # the run 100 px off is left out


@pytest.fixture(scope="module")
def selection():
    return _load("source_selection")


def _poses(rng, T=6, P=13):
    return rng.normal(size=(T, P, 3)) * 0.3 + (0.0, 0.0, 4.0)


def test_frame_errors_ignore_a_similarity_and_count_only_valid_points(selection):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    ref = _poses(rng)
    moved = 1.7 * Rotation.from_rotvec([0.3, -0.2, 1.0]).apply(ref.reshape(-1, 3)).reshape(ref.shape) + 5.0
    valid = np.ones(ref.shape[:2], bool)
    assert selection.frame_errors(moved, ref, valid) == pytest.approx(np.zeros(len(ref)), abs=1e-9)
    bad = moved.copy()
    bad[:, 0] += 10.0  # a wild point, left out of the scored points
    valid[:, 0] = False
    assert selection.frame_errors(bad, ref, valid) == pytest.approx(np.zeros(len(ref)), abs=1e-9)
    valid[2, :10] = False  # fewer than 4 points: no score
    assert np.isnan(selection.frame_errors(bad, ref, valid)[2])


def test_the_oracle_takes_the_exact_source_point_by_point(selection):
    rng = np.random.default_rng(1)
    ref = _poses(rng)
    # each source exact but for one point, a different one, 0.5 m off
    fit, lift = ref.copy(), ref.copy()
    fit[:, 5] += (0.5, 0.0, 0.0)
    lift[:, 3] += (0.0, -0.5, 0.0)
    valid = np.ones(ref.shape[:2], bool)
    out = selection.oracle_blend(fit, lift, ref, valid)
    assert np.allclose(out, ref, atol=1e-9)
    assert selection.frame_errors(out, ref, valid) == pytest.approx(np.zeros(len(ref)), abs=1e-9)
    # a point not valid keeps the middle share
    valid[:, 3] = False
    out = selection.oracle_blend(fit, lift, ref, valid)
    assert np.allclose(out[:, 3], 0.5 * (fit[:, 3] + lift[:, 3]))


def test_point_errors_favour_no_source_and_blend3_mixes_per_point(selection):
    rng = np.random.default_rng(2)
    ref = _poses(rng)
    valid = np.ones(ref.shape[:2], bool)
    a, b = ref + 0.02, ref - 0.02  # the same offset either way from the truth
    ea, eb = selection.point_errors([a, b], ref, valid)
    assert ea == pytest.approx(eb, abs=1e-9)
    assert ea == pytest.approx(np.full(ref.shape[:2], 0.02 * np.sqrt(3)), rel=1e-6)
    share = np.zeros(ref.shape[:2])
    share[:, 3] = 1.0
    mixed = selection.blend3(ref, a, b, share, 0.0)
    assert np.allclose(mixed[:, 3], a[:, 3]) and np.allclose(np.delete(mixed, 3, 1), np.delete(ref, 3, 1))
    assert np.allclose(selection.blend3(ref, a, b, 0.25, 0.25), 0.5 * ref + 0.25 * (a + b))


def _body_points(rng, T=5, noise=0.03):
    """(T, 13, 3) rough people: shoulders above hips, limbs hanging, a little noise."""
    base = np.array([[0, 1.7, 0], [0.2, 1.45, 0], [-0.2, 1.45, 0], [0.25, 1.15, 0], [-0.25, 1.15, 0],
                     [0.27, 0.9, 0.05], [-0.27, 0.9, 0.05], [0.1, 0.95, 0], [-0.1, 0.95, 0], [0.1, 0.5, 0.02],
                     [-0.1, 0.5, 0.02], [0.1, 0.08, 0], [-0.1, 0.08, 0]], float)
    return base + rng.normal(scale=noise, size=(T, 13, 3))


def test_the_torso_frame_ignores_a_similarity_and_puts_the_torso_on_its_axes(selection):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(4)
    x = _body_points(rng)
    moved = 2.3 * Rotation.from_rotvec([0.4, 1.1, -0.3]).apply(x.reshape(-1, 3)).reshape(x.shape) + (1.0, -2.0, 5.0)
    a, b = selection.torso_frame(x), selection.torso_frame(moved)
    assert np.allclose(a, b, atol=1e-9)
    mid_hips, mid_shoulders = 0.5 * (a[:, 7] + a[:, 8]), 0.5 * (a[:, 1] + a[:, 2])
    assert np.allclose(mid_hips, 0.0, atol=1e-12)
    assert np.allclose(mid_shoulders, [[0.0, 1.0, 0.0]] * len(x), atol=1e-12)
    assert (a[:, 7, 0] > a[:, 8, 0]).all() and (a[:, 1, 0] > a[:, 2, 0]).all()  # left on +x
    feats = selection.limb_features(x)
    r, m, e = selection.LIMBS["left arm"]
    assert np.allclose(feats["left arm"], np.concatenate([a[:, m] - a[:, r], a[:, e] - a[:, r]], -1))


def test_limb_plausibility_finds_the_limb_unlike_the_examples(selection):
    rng = np.random.default_rng(5)
    db = selection.LimbPlausibility(_body_points(rng, T=200))
    people = _body_points(rng, T=3)
    odd = people.copy()
    odd[1, 5] = odd[1, 1] + (0.0, 0.6, 0.0)  # a left wrist above the shoulder: no example has that
    d_ok, d_odd = db.distance(people), db.distance(odd)
    assert d_odd["left arm"][1] > 5 * d_ok["left arm"][1]
    for limb in ("right arm", "left leg", "right leg"):
        assert d_odd[limb] == pytest.approx(d_ok[limb])
    # the rule takes, limb by limb, the candidate nearest an example where it is 2x nearer than the share 0.5's
    r = {"fit": people, "lift": odd, "mp": odd}
    out = selection.plausibility_rule(db, 2.0)(r)
    half = 0.5 * (people + odd)
    assert np.allclose(out[1, [3, 5]], people[1, [3, 5]])  # the odd arm's frame: the fit's arm
    assert np.allclose(np.delete(out, 1, 0), np.delete(half, 1, 0))  # elsewhere the share 0.5


def test_bone_deviation_and_the_bone_rule(selection):
    rng = np.random.default_rng(6)
    x = _body_points(rng, T=7, noise=0.003)
    x[:, 5] = x[:, 3] + (0.0, -0.25, 0.0)  # left forearm 0.25 m in every frame
    x[2, 5] = x[2, 3] + (0.0, -0.35, 0.0)  # ... but 0.35 m in frame 2: 40 % too long
    dev = selection.bone_deviation(x)
    assert dev["left arm"][2] == pytest.approx(0.4)
    assert dev["left arm"][0] < 0.2
    fit = x + 0.01
    r = {"fit": fit, "lift": x, "mp": x}
    out = selection.bone_rule(0.2)(r)
    half = 0.5 * (fit + x)
    assert np.allclose(out[2, [3, 5]], fit[2, [3, 5]])
    out[2, [3, 5]] = half[2, [3, 5]]
    assert np.allclose(out, half)
    # limb_composite leaves a limb alone where the pick names no candidate
    same = selection.limb_composite(half, {"fit": fit}, {k: np.full(7, "") for k in selection.LIMBS})
    assert np.allclose(same, half)


def test_the_mean_lifter_of_benchmarks_lifter_refit_averages_its_lifters():
    from flowmocap.vision.lifter import load_lifter

    mod = _load("lifter_refit")
    one = load_lifter()
    rng = np.random.default_rng(3)
    pts = rng.uniform(100, 400, size=(4, 13, 2))
    mask = np.ones((4, 13), bool)
    mask[1, 5] = False
    same = mod.MeanLifter([None, None])
    assert not same.temporal
    assert np.allclose(same.lift_points(pts, mask), one.lift_points(pts, mask), equal_nan=True)

    class Shifted:  # a second lifter that answers 1 m to the right
        temporal = False

        def lift_points(self, p, m, fps=None):
            return one.lift_points(p, m) + (1.0, 0.0, 0.0)

    mixed = mod.MeanLifter([None])
    mixed.lifters.append(Shifted())
    assert np.allclose(mixed.lift_points(pts, mask), one.lift_points(pts, mask) + (0.5, 0.0, 0.0))
    with pytest.raises(ValueError):
        mod.MeanLifter([])


def test_disagreement_scripts_measures():
    dis = _load("disagreement")
    score = np.arange(100.0)
    worst = score >= 90
    assert dis.auroc(score, worst) == 1.0 and dis.auroc(-score, worst) == 0.0
    assert dis.auroc(np.zeros(100), worst) == 0.5  # ties count half
    assert np.isnan(dis.auroc(score, np.zeros(100, bool)))
    f = dis.flag_scores(score / 1000, score / 1000)  # a perfect flag
    assert f["auroc_top10"] == 1.0 and f["precision_top10"] == 1.0 and f["spearman"] == pytest.approx(1.0)
    assert f["error_flagged_mm"] == pytest.approx(94.5) and f["error_rest_mm"] == pytest.approx(44.5)
    # the per-joint error after a similarity per frame: none for a turned, scaled copy, one moved point's otherwise
    rng = np.random.default_rng(0)
    ref = rng.normal(0, 0.3, (3, 13, 3))
    pred = 1.5 * Rotation.from_rotvec([0.2, -0.4, 0.1]).apply(ref.reshape(-1, 3)).reshape(ref.shape) + 2.0
    valid = np.ones((3, 13), bool)
    valid[1, 4] = False
    err = dis.per_joint_error(pred, ref, valid)
    assert np.isnan(err[1, 4]) and np.nanmax(err) < 1e-9
    valid[2, 4:] = False  # 4 valid points is enough, 3 is not
    valid[0, 3:] = False
    err = dis.per_joint_error(pred, ref, valid)
    assert np.isfinite(err[2, :4]).all() and np.isnan(err[0]).all()


def test_error_over_time_cuts_the_start_and_thirds():
    mod = _load("error_over_time")
    e = np.arange(10, dtype=float)  # frames 0..9
    # the first 2 frames, then thirds of 4, 3 and 3 frames (array_split gives the first the extra one)
    assert mod.parts(e, head=2) == pytest.approx([0.5, 1.5, 5.0, 8.0])
    assert mod.parts(np.full(7, 4.0), head=10) == pytest.approx([4.0] * 4)  # a start longer than the clip: all of it
    with pytest.raises(ValueError, match="cannot be cut"):
        mod.parts(np.ones(2), head=1)


def test_prior_flip_mirrors_keep_the_childs_pixel_and_the_measure_counts_preferences():
    import torch

    from flowmocap.body import load_body_model
    from flowmocap.fit.energies import DEPTH_LIMBS

    mod = _load("prior_flip")
    # the camera looks at its target, x right and y down (image y grows downwards)
    R, t = mod.look_at(np.array([0.0, 1.0, 4.0]), np.array([0.0, 1.0, 0.0]))
    assert R @ R.T == pytest.approx(np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    assert R @ np.array([0.0, 1.0, 0.0]) + t == pytest.approx([0.0, 0.0, 4.0])
    assert (R @ np.array([0.0, 2.0, 0.0]) + t)[1] < 0  # above the target: up in the image

    model = load_body_model("default", dtype=torch.float64)
    poses = np.random.default_rng(3).normal(0, 0.3, (3, 72))
    with torch.no_grad():
        out = model(pose=torch.as_tensor(poses), with_vertices=False)
    J, G = out.joints.numpy(), out.transforms[:, :, :3, :3].numpy()
    index, which, flipped, cams = mod.flip_pairs(J, G, poses, DEPTH_LIMBS, np.random.default_rng(0))
    assert len(which) > 10 and len(cams) == 3
    with torch.no_grad():
        Jf = model(pose=torch.as_tensor(flipped), with_vertices=False).joints.numpy()
    for m in range(len(which)):
        (R, t), (p, c) = cams[index[m]], DEPTH_LIMBS[which[m]]
        a, b = J[index[m]] @ R.T + t, Jf[m] @ R.T + t
        assert b[c, :2] / b[c, 2] == pytest.approx(a[c, :2] / a[c, 2], abs=1e-9)  # the same pixel
        assert b[p] == pytest.approx(a[p], abs=1e-9)  # the parent stays
        assert np.linalg.norm(b[c] - b[p]) == pytest.approx(np.linalg.norm(a[c] - a[p]), abs=1e-9)

    # the measure: real poses at 0, mirrors at +1 (preferred real), -1 or 0 (a tie counts half)
    e_real = np.zeros(2)
    e_flip = np.array([1.0, -1.0, 1.0, 0.0, 5.0])
    idx, limb = np.array([0, 0, 1, 1, 1]), np.array([0, 1, 0, 1, 1])
    moved = np.array([0.2, 0.2, 0.2, 0.2, 0.05])  # the last is too small a move to count
    r = mod.discrimination(e_real, e_flip, idx, limb, moved, n_limbs=3)
    assert r["mirrors"] == 4 and r["accuracy"] == pytest.approx((1 + 0 + 1 + 0.5) / 4)
    assert r["median_margin"] == pytest.approx(0.5)
    assert r["per_limb"][0]["accuracy"] == 1.0 and r["per_limb"][1]["accuracy"] == pytest.approx(0.25)
    assert r["per_limb"][2] == {"accuracy": None, "median_margin": None, "mirrors": 0}


def test_mediapipe_image_depth_crop_and_points():
    """The crop is the keypoints' box grown about its centre and kept inside the image;
    image landmarks become pixels with z on the width's scale (times ``z_scale``)."""
    mod = _load("mediapipe_image_depth")
    kp = np.array([[100.0, 200.0], [140.0, 300.0], [5000.0, 5000.0], [np.nan, 0.0]])
    conf = np.array([0.9, 0.8, 0.1, 0.9])  # the far point is not confident, the NaN one is not finite
    # box 40 x 100 centred at (120, 250): side 1.4 * 100 + 40 = 180
    assert mod.crop_box(kp, conf, (1000, 1000)) == (30, 160, 210, 340)
    assert mod.crop_box(kp, conf, (150, 1000))[2] == 150  # clipped to the image's width
    assert mod.crop_box(kp, conf, (1000, 1000), margin=1.0, pad=0.0) == (70, 200, 170, 300)
    assert mod.crop_box(kp, np.array([0.9, 0.1, 0.1, 0.9]), (1000, 1000)) is None  # one confident point
    lm = np.array([[0.5, 0.25, -0.1], [0.0, 1.0, 0.2]])
    assert mod.image_landmarks_3d(lm, 200, 400) == pytest.approx(np.array([[100.0, 100.0, -20.0], [0.0, 400.0, 40.0]]))
    assert mod.image_landmarks_3d(lm, 200, 400, z_scale=0.5)[:, 2] == pytest.approx([-10.0, 20.0])


def _real3d_result(ours, det):
    """A real3d.json with one row per person-view: ``ours``, ``det`` per-frame mm lists."""
    names = [("person1", "cam01"), ("person1", "cam02"), ("person2", "cam01")][:len(ours)]
    return {"rows": [{"person": p, "view": v, "flowmocap": {"per_frame_mm": o}, "flowmocap_kp": {"per_frame_mm": o - 3},
                      "detector3d": {"per_frame_mm": d}} for (p, v), o, d in zip(names, ours, det)]
            + [{"person": "person2", "view": "cam04", "skipped_run": "not detected"}]}


def test_real3d_draws_config_and_summary(tmp_path):
    dr = _load("real3d_draws")
    assert dr.draw_config(None, 0) == {} and dr.draw_config({"keypoint_weight": 0.1}, 0) == {"keypoint_weight": 0.1}
    assert dr.draw_config(None, 1)["flow_weight"] == pytest.approx(1.000001, abs=1e-12)
    assert dr.draw_config({"flow_weight": 2.0}, 2)["flow_weight"] == pytest.approx(2.0 * 0.999998, abs=1e-12)
    s = dr.summarise([_real3d_result([60.0, 80.0], [80.0, 80.0]), _real3d_result([70.0, 70.0], [80.0, 80.0])])
    assert [d["flowmocap"] for d in s["draws"]] == [70.0, 70.0]
    assert s["draws"][0]["at_or_above"] == ["person1@cam02"] and s["draws"][1]["at_or_above"] == []
    assert s["mean"]["flowmocap"] == 70.0 and s["mean"]["ratio"] == pytest.approx(70.0 / 80.0)
    assert s["mean"]["flowmocap_kp"] == 67.0
    v = s["views"]["person1@cam01"]
    assert (v["mean"], v["low"], v["high"], v["draws_at_or_above"]) == (65.0, 60.0, 70.0, 0)
    assert s["views"]["person1@cam02"]["draws_at_or_above"] == 1 and "person2@cam04" not in s["views"]
    text = dr.format_summary(s)
    assert "| **mean** | 70.00 | 67.00 | 80.00 | 0.88 |" in text and "person1@cam02" in text
    # a later draw reuses draw 0's reference and detections, and keeps what it has
    src, dst = tmp_path / "draw0", tmp_path / "draw1"
    (src / "reference").mkdir(parents=True)
    (src / "reference" / "ref.json").write_text("{}")
    (src / "runs" / "person1-cam01" / "detections").mkdir(parents=True)
    (src / "runs" / "person1-cam01" / "detections" / "keypoints.npz").write_bytes(b"x")
    (src / "runs" / "person1-cam01" / "motion.npz").write_bytes(b"m")
    dr._reuse(src, dst)
    assert (dst / "reference" / "ref.json").exists()
    assert (dst / "runs" / "person1-cam01" / "detections" / "keypoints.npz").exists()
    assert not (dst / "runs" / "person1-cam01" / "motion.npz").exists()  # the tracking is the draw's own
    dr._reuse(src, dst)  # again: nothing to do, no error


def test_people_floor_measures_are_zero_at_the_reference_and_see_a_wrong_depth():
    """benchmarks/people_floor.py: the depth-ratio and gap errors are 0 for the reference at any
    overall scale, and for the other person at 1.2 times the depth log(1.2) and the gap's change."""
    floor = _load("people_floor")
    rng = np.random.default_rng(0)
    ref_f = rng.uniform(-0.5, 0.5, (20, 3)) + (0.0, 0.0, 3.0)
    ref_o = rng.uniform(-0.5, 0.5, (20, 3)) + (1.0, 0.0, 4.0)
    m = floor.pair_measures(2.0 * ref_f, 2.0 * ref_o, ref_f, ref_o)  # the same scene, twice as large
    assert m["depth_ratio"] == pytest.approx(0.0, abs=1e-12) and m["gap"] == pytest.approx(0.0, abs=1e-12)
    m = floor.pair_measures(ref_f, 1.2 * ref_o, ref_f, ref_o)  # the other 1.2 times as far along its ray
    assert m["depth_ratio"] == pytest.approx(np.log(1.2))
    gap = np.abs(np.linalg.norm(1.2 * ref_o - ref_f, axis=1) - np.linalg.norm(ref_o - ref_f, axis=1)) / ref_f[:, 2]
    assert m["gap"] == pytest.approx(np.median(gap))


def test_camera_motion_cost_times_each_pass_and_writes_its_table(tmp_path, monkeypatch):
    """benchmarks/camera_motion_cost.py: every synthetic floor timed ``--repeat`` times, the
    median in the table, what was found summarised (the fit itself replaced by a stand-in here:
    the real one is timed by the script, not by the tests)."""
    from types import SimpleNamespace

    import flowmocap.vision.camera_motion as cm

    cost = _load("camera_motion_cost")
    calls = []

    def fake(seq, camera, **kw):
        calls.append(len(seq))
        return SimpleNamespace(turn_deg=np.array([0.0, 2.5]), moving_sideways=True, move_share=0.02,
                               sideways=0.9, focal=None)

    monkeypatch.setattr(cm, "camera_motion", fake)
    monkeypatch.setattr("sys.argv", ["camera_motion_cost.py", "--synthetic", "--repeat", "2",
                                     "--out", str(tmp_path / "cost")])
    cost.main()
    assert calls == [30] * 4  # two scenes of 30 frames, twice each
    doc = json.loads((tmp_path / "cost.json").read_text())
    assert [len(r["seconds"]) for r in doc["rows"]] == [2, 2]
    assert all(r["median_s"] == pytest.approx(np.median(r["seconds"])) for r in doc["rows"])
    assert doc["rows"][0]["found"] == {"turn_deg_max": 2.5, "moving_sideways": True, "move_share": 0.02,
                                       "sideways_h": 0.9, "focal_px": None}
    table = (tmp_path / "cost.md").read_text()
    assert "| synthetic | dolly sideways 5 cm a frame | 30 |" in table and "2.50, yes (0.9), 0.02, None" in table
    with pytest.raises(SystemExit):  # nothing to time
        monkeypatch.setattr("sys.argv", ["camera_motion_cost.py"])
        cost.main()


def test_virtual_pan_turns_and_sees_a_pixel_where_its_warp_puts_it(tmp_path):
    """benchmarks/virtual_pan.py: the turns pan from -pan to +pan about the camera's y axis and
    tilt up and back; a still frame with one bright dot, written through a turned and zoomed
    virtual camera (undistorted first), shows the dot where :func:`virtual_pixel` says, the
    truth of the pixel mapping the script carries the person's pixel with; a camera that turns
    beyond the still view's edge says how much of a frame fell outside."""
    import cv2
    from types import SimpleNamespace

    vp = _load("virtual_pan")
    V = vp.turns(11, 4.0, 2.0)
    rv = np.degrees(Rotation.from_matrix(V).as_rotvec())
    np.testing.assert_allclose(rv[[0, -1], 1], [-4.0, 4.0], atol=1e-9)
    np.testing.assert_allclose(rv[[0, 5, -1], 0], [0.0, 2.0, 0.0], atol=0.01)  # the tilt, up and back
    K = np.array([[400.0, 0.0, 161.0], [0.0, 400.0, 118.0], [0.0, 0.0, 1.0]])
    Kv = vp.virtual_intrinsics(K, (320, 240), (160, 120), 1.5)
    np.testing.assert_allclose(Kv, [[300.0, 0.0, 80.0], [0.0, 300.0, 60.0], [0.0, 0.0, 1.0]])  # 400 px at half size, 1.5x
    cam = SimpleNamespace(K=K, dist=np.array([-0.05, 0.1, 0.0, 0.0, 0.0]))
    img = np.zeros((240, 320, 3), np.uint8)
    cv2.circle(img, (175, 130), 3, (255, 255, 255), -1)

    class Still:
        def __len__(self):
            return 1

        def frame(self, i):
            return img

    turn, zoom = Rotation.from_euler("yx", [3.0, -2.0], degrees=True).as_matrix(), vp.zoomed(Kv, 0.9)
    import flowmocap.io.video as video

    real = video.load_video
    video.load_video = lambda *a, **k: Still()
    try:
        info = vp.write_virtual(Path("still.mp4"), cam, turn[None], [zoom], (160, 120), tmp_path / "v.mp4", 30.0)
        wide = vp.write_virtual(Path("still.mp4"), cam, Rotation.from_euler("y", 30.0, degrees=True).as_matrix()[None],
                                [Kv], (160, 120), tmp_path / "w.mp4", 30.0)
    finally:
        video.load_video = real
    import imageio.v3 as iio

    out = iio.imread(tmp_path / "v.mp4", plugin="pyav")[0].astype(float).sum(-1)
    seen = np.array(np.unravel_index(np.argmax(cv2.GaussianBlur(out, (5, 5), 0)), out.shape))[::-1] + 0.0
    want = vp.virtual_pixel(cam, (175.0, 130.0), turn, zoom)
    assert np.linalg.norm(seen - want) < 1.5
    assert info == {"outside_share": 0.0, "frames": 1} and wide["outside_share"] > 0.1
