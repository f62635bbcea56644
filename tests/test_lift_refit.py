"""flowmocap.fit.lift_refit: the refit of a finished motion towards the lifter's depths."""

import json

import numpy as np
import pytest
import torch

from flowmocap.body import load_body_model
from flowmocap.body.skeleton import JOINT_INDEX
from flowmocap.errors import InputError
from flowmocap.fit.lift_refit import blend_targets, keypoints13, lifter_refit_motion, posed_joints_only, refit_energy
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.vision.auto import PersonTrack
from flowmocap.vision.detect import KEYPOINT_NAMES
from flowmocap.vision.keypoint_map import load_keypoint_map
from flowmocap.vision.lifter import HIPS, POINTS

T = 4
CAM = PinholeCamera(fx=600.0, fy=600.0, cx=320.0, cy=240.0, width=640, height=480,
                    R=np.diag([1.0, -1.0, -1.0]), t=np.array([0.1, 0.9, 4.0]))


def _pose(**joints_deg):
    p = np.zeros(72)
    for name, rv in joints_deg.items():
        p[3 * JOINT_INDEX[name]:3 * JOINT_INDEX[name] + 3] = np.radians(rv)
    return p


#: the truth: the right forearm reaching towards the camera and the left one sideways
TRUTH = _pose(left_shoulder=(0, 0, -70), right_shoulder=(0, 0, 70), right_elbow=(0, 80, 0),
              left_hip=(-20, 0, 0), left_knee=(30, 0, 0))


def _bodies(poses):
    model, kmap = load_body_model("default", dtype=torch.float64), load_keypoint_map()
    with torch.no_grad():
        kp, joints = keypoints13(model, kmap, torch.as_tensor(np.asarray(poses)), torch.zeros(1, 10),
                                 torch.zeros(len(poses), 3))
    return kp.numpy(), joints.numpy()


class TruthLifter:
    """A stand-in lifter that returns the true keypoints (ray axes, as the real one)."""

    def __init__(self, truth_world):
        self.truth_cam = truth_world @ CAM.R.T + CAM.t

    def lift_points(self, points, mask, fps=None):
        assert fps is not None and fps > 0  # the refit passes the result's frame rate (a temporal lifter needs it)
        assert points.shape == (len(self.truth_cam), len(POINTS), 2) and mask.shape == points.shape[:2]
        self.seen = np.asarray(points, np.float64).copy()
        self.mask = np.asarray(mask, bool).copy()
        out = np.full((len(points), len(POINTS), 3), np.nan)
        for f in range(len(points)):
            hip = points[f, list(HIPS)].mean(0)
            ray = CAM.ray_rotation(float(hip[0]), float(hip[1]))
            out[f] = self.truth_cam[f] @ ray  # camera axes -> the ray's (x_cam = x_ray @ ray.T)
        return out


def _setup(tmp_path, fit_pose, truth=TRUTH, image=None, frames=T):
    """``image``: the pose whose keypoints the detection's 2D are (default ``truth``);
    ``fit_pose``: one pose for every frame, or ``(frames, 72)``. With the default 4 frames
    the last has no person."""
    fit_poses = np.asarray(fit_pose, np.float64)
    fit_poses = np.tile(fit_poses, (frames, 1)) if fit_poses.ndim == 1 else fit_poses.copy()
    truth_kp, _ = _bodies([truth] * frames)
    fit_kp, fit_joints = _bodies(fit_poses)
    image_kp = truth_kp if image is None else _bodies([image] * frames)[0]
    px = np.asarray(CAM.project(image_kp.reshape(-1, 3))).reshape(frames, 13, 2)
    kp = np.zeros((frames, len(KEYPOINT_NAMES), 2))
    for k, name in enumerate(POINTS):
        for n in (("left_ear", "right_ear", "nose") if name == "head" else (name,)):
            kp[:, KEYPOINT_NAMES.index(n)] = px[:, k]
    found = np.ones(frames, bool)
    found[3] = frames != T  # no person in the last of 4 frames: its body stays
    track = PersonTrack(kp, np.ones((frames, len(KEYPOINT_NAMES))), found, [tmp_path / "m.png"] * frames, {})
    motion = {"poses": fit_poses.astype(np.float32), "trans": np.zeros((frames, 3), np.float32),
              "betas": np.zeros(10, np.float32), "joints3d": fit_joints.astype(np.float32),
              "joints2d": np.asarray(CAM.project(fit_joints.reshape(-1, 3))).reshape(frames, 24, 2).astype(np.float32),
              "camera": json.dumps(CAM.to_dict()), "frame_index": np.arange(frames), "fps": 30.0}
    return motion, track, truth_kp, fit_kp


def test_blend_targets_keep_each_pixel_and_blend_depth():
    rng = np.random.default_rng(0)
    fit = rng.normal(0, 0.3, (2, 13, 3)) + (0, 0, 4)
    lifted = fit * 1.7 + (1, 2, 3)  # the same shape elsewhere and larger: aligned, it is the fit
    np.testing.assert_allclose(blend_targets(fit, lifted, 0.5), fit, atol=1e-9)
    other = fit.copy()
    other[:, 5, 2] += 0.4  # one point deeper in the lifter's shape
    tg = blend_targets(fit, other, 1.0)
    np.testing.assert_allclose(tg[..., :2] / tg[..., 2:], fit[..., :2] / fit[..., 2:], atol=1e-12)  # same pixels
    assert (tg[:, 5, 2] > fit[:, 5, 2] + 0.2).all()
    half = blend_targets(fit, other, 0.5)
    np.testing.assert_allclose(half[..., 2], 0.5 * (fit[..., 2] + tg[..., 2]), atol=1e-12)


def test_full_blend_targets_are_the_fit_and_the_aligned_lifter_mixed_point_by_point():
    rng = np.random.default_rng(1)
    fit = rng.normal(0, 0.3, (3, 13, 3)) + (0, 0, 4)
    shape = fit + rng.normal(0, 0.05, fit.shape)  # another shape ...
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    lifted = 1.3 * shape @ R.T + (0.5, -1, 2)  # ... elsewhere, turned and larger
    from flowmocap.geometry.procrustes import similarity_procrustes

    aligned = similarity_procrustes(lifted, fit)[0]
    np.testing.assert_allclose(blend_targets(fit, lifted, 0.0, "full"), fit, atol=1e-12)
    np.testing.assert_allclose(blend_targets(fit, lifted, 1.0, "full"), aligned, atol=1e-12)
    np.testing.assert_allclose(blend_targets(fit, lifted, 0.25, "full"), 0.75 * fit + 0.25 * aligned, atol=1e-12)
    # the depth blend is the full one's depth, on the fit's rays
    d, f = blend_targets(fit, lifted, 0.25, "depth"), blend_targets(fit, lifted, 0.25, "full")
    np.testing.assert_allclose(d[..., 2], f[..., 2], atol=1e-12)
    np.testing.assert_allclose(d[..., :2] / d[..., 2:], fit[..., :2] / fit[..., 2:], atol=1e-12)
    with pytest.raises(InputError, match="blend"):
        blend_targets(fit, lifted, 0.5, "both")


@pytest.mark.parametrize("blend", ["depth", "full"])
def test_refit_moves_a_wrong_forearm_towards_the_lifted_depth_and_keeps_the_image(tmp_path, blend):
    wrong = TRUTH.copy()
    wrong[3 * JOINT_INDEX["right_elbow"] + 1] = np.radians(-80)  # the forearm reaching away instead
    motion, track, truth_kp, fit_kp = _setup(tmp_path, wrong)
    model = load_body_model("default")
    # converged (60 iterations; the default 20 stops earlier: the same direction, a little more image motion)
    out, info = lifter_refit_motion(motion, track, model, weight=1.0, lifter=TruthLifter(truth_kp), iterations=60,
                                    blend=blend)
    assert info["blend"] == blend
    assert info["frames_refit"] == 3
    kp_after, joints_after = _bodies(out["poses"].astype(np.float64))
    wrist = POINTS.index("right_wrist")
    before = np.linalg.norm(fit_kp[:3, wrist] - truth_kp[:3, wrist], axis=-1)
    after = np.linalg.norm(kp_after[:3, wrist] - truth_kp[:3, wrist], axis=-1)
    assert (before > 0.2).all() and (after < 0.3 * before).all(), (before, after)
    # the image barely moves (targets lie on the fit's rays), joints3d/2d are the new body's
    np.testing.assert_allclose(out["joints3d"], joints_after + out["trans"][:, None], atol=1e-4)
    assert info["mean_move_px"] < 3.0 and info["mean_move_mm"] > 10
    # the frame without a person, and everything else, is kept; the tracked poses too
    np.testing.assert_array_equal(out["poses"][3], motion["poses"][3])
    np.testing.assert_array_equal(out["poses_tracked"], motion["poses"])
    assert out["fps"] == motion["fps"] and out["camera"] == motion["camera"]


def test_the_image_term_holds_the_tracked_image(tmp_path):
    """With ``pixel_sigma`` the refit still turns the wrong forearm towards the truth, and
    the 24 joints' image moves less than without it."""
    wrong = TRUTH.copy()
    wrong[3 * JOINT_INDEX["right_elbow"] + 1] = np.radians(-80)
    wrong[3 * JOINT_INDEX["spine2"]] = np.radians(15)  # and a bent spine the lifter disagrees with
    motion, track, truth_kp, fit_kp = _setup(tmp_path, wrong)
    model, lifter = load_body_model("default"), TruthLifter(truth_kp)
    # converged (60 iterations); a tighter hold (2 px) keeps the forearm from turning at all
    free, info_free = lifter_refit_motion(motion, track, model, weight=1.0, lifter=lifter, iterations=60)
    held, info_held = lifter_refit_motion(motion, track, model, weight=1.0, lifter=lifter, iterations=60,
                                          pixel_sigma=5.0)
    assert info_held["mean_move_px"] < 0.7 * info_free["mean_move_px"], (info_held, info_free)
    wrist = POINTS.index("right_wrist")
    kp_held, _ = _bodies(held["poses"][:3].astype(np.float64))
    before = np.linalg.norm(fit_kp[:3, wrist] - truth_kp[:3, wrist], axis=-1)
    after = np.linalg.norm(kp_held[:, wrist] - truth_kp[:3, wrist], axis=-1)
    assert (after < 0.5 * before).all(), (before, after)


@pytest.mark.parametrize("blend,sigma,turns", [("full", 4.0, True), ("depth", 6.0, True), ("full", 2.0, False)])
def test_the_hold_lets_a_wrong_forearm_turn(tmp_path, blend, sigma, turns):
    """The pipeline's defaults (``lifter_refit_blend`` "full" with a 4 px hold; before,
    "depth" with 6 px) still turn a forearm reaching the wrong way in depth to the lifter's
    side, while a 2 px hold keeps it from turning: the turn passes through poses whose
    image is further off (docs/experiments.md, "The full blend with a 4 px hold")."""
    wrong = TRUTH.copy()
    wrong[3 * JOINT_INDEX["right_elbow"] + 1] = np.radians(-80)
    wrong[3 * JOINT_INDEX["spine2"]] = np.radians(15)
    motion, track, truth_kp, fit_kp = _setup(tmp_path, wrong)
    out, _ = lifter_refit_motion(motion, track, load_body_model("default"), weight=1.0, lifter=TruthLifter(truth_kp),
                                 iterations=60, pixel_sigma=sigma, blend=blend)
    wrist = POINTS.index("right_wrist")
    kp, _ = _bodies(out["poses"][:3].astype(np.float64))
    before = np.linalg.norm(fit_kp[:3, wrist] - truth_kp[:3, wrist], axis=-1)
    after = np.linalg.norm(kp[:, wrist] - truth_kp[:3, wrist], axis=-1)
    assert ((after < 0.35 * before).all() if turns else (after > 0.5 * before).all()), (before, after)


def test_a_seam_is_eased_before_the_refit_and_the_tracked_image_still_holds(tmp_path):
    """A 3D re-initialisation at frame 6: before it the forearm reaches away from the camera
    (the image nearly the truth's), from it on as the truth. Eased over 0.2 s (6 frames), the
    refit starts the frames before the seam part of the way to the restarted pose: their
    forearm comes nearer the truth than without the easing, their image stays where the
    tracker put it, and the frames from the seam on are as without it."""
    wrong = TRUTH.copy()
    wrong[3 * JOINT_INDEX["right_elbow"] + 1] = np.radians(-80)
    frames = 10
    poses = np.array([wrong] * 6 + [TRUTH] * 4)
    motion, track, truth_kp, _ = _setup(tmp_path, poses, frames=frames)
    model, lifter = load_body_model("default"), TruthLifter(truth_kp)
    kw = dict(weight=0.5, lifter=lifter, pixel_sigma=4.0, seams=[6])
    plain, info0 = lifter_refit_motion(motion, track, model, **kw)
    eased, info = lifter_refit_motion(motion, track, model, seam_s=0.2, **kw)
    assert info0["seams_eased"] == [] and info["seams_eased"] == [6] and info["seam_s"] == 0.2
    wrist = POINTS.index("right_wrist")
    err = {name: np.linalg.norm(_bodies(m["poses"].astype(np.float64))[0][:, wrist] - truth_kp[:, wrist], axis=-1)
           for name, m in (("plain", plain), ("eased", eased))}
    assert (err["eased"][3:6] < err["plain"][3:6] - 0.02).all(), err  # the last frames before the seam
    np.testing.assert_allclose(eased["joints3d"][6:], plain["joints3d"][6:], atol=2e-3)
    np.testing.assert_array_equal(eased["poses_tracked"], motion["poses"])  # the tracker's own poses are kept
    move = np.linalg.norm(eased["joints2d"][:6] - motion["joints2d"][:6], axis=-1)  # the image hold
    assert move.mean() < 3.0, move.mean()
    with pytest.raises(InputError, match="seconds"):
        lifter_refit_motion(motion, track, model, seam_s=float("inf"), **kw)


def test_weight_zero_and_bad_input(tmp_path):
    motion, track, truth_kp, _ = _setup(tmp_path, TRUTH)
    model = load_body_model("default")
    same, info = lifter_refit_motion(motion, track, model, weight=0.0)
    assert info["frames_refit"] == 0 and same["poses"] is motion["poses"] and "poses_tracked" not in same
    with pytest.raises(InputError, match="weight"):
        lifter_refit_motion(motion, track, model, weight=1.5)
    with pytest.raises(InputError, match="pixel_sigma"):
        lifter_refit_motion(motion, track, model, weight=0.5, pixel_sigma=-2.0)
    short = PersonTrack(track.keypoints[:2], track.confidence[:2], track.found[:2], track.mask_paths[:2], {})
    with pytest.raises(InputError, match="detections have 2 frames"):
        lifter_refit_motion(motion, short, model, weight=0.5, lifter=TruthLifter(truth_kp))
    # the truth refitted towards itself stays where it is
    out, _ = lifter_refit_motion(motion, track, model, weight=1.0, lifter=TruthLifter(truth_kp))
    np.testing.assert_allclose(out["joints3d"], motion["joints3d"], atol=2e-3)


@pytest.mark.parametrize("pixel_sigma,some_let_go", [(None, False), (3.0, False), (3.0, True)],
                         ids=["3d-only", "with-image-term", "image-term-weighted"])
def test_refit_energy_gradient_matches_finite_differences(pixel_sigma, some_let_go):
    model, kmap = load_body_model("default", dtype=torch.float64), load_keypoint_map()
    rng = np.random.default_rng(1)
    poses0 = torch.as_tensor(np.stack([TRUTH, TRUTH]) + rng.normal(0, 0.05, (2, 72)))
    targets = torch.as_tensor(rng.normal(0, 0.5, (2, 13, 3)))
    use = torch.tensor([1.0, 0.0])
    with torch.no_grad():
        pixels = CAM.project(keypoints13(model, kmap, poses0, torch.zeros(1, 10), torch.zeros(2, 3))[1])
    pixels = pixels + torch.as_tensor(rng.normal(0, 5.0, (2, 24, 2)))

    pixel_use = torch.as_tensor(rng.uniform(0, 1, (2, 24)) > 0.5, dtype=torch.float64) if some_let_go else None

    def energy(pose, trans):
        return refit_energy(model, kmap, pose, trans, torch.zeros(1, 10), targets, use, poses0, 0.02, 0.3,
                            CAM, pixels, pixel_sigma, pixel_use)

    pose = (poses0 + torch.as_tensor(rng.normal(0, 0.1, (2, 72)))).requires_grad_(True)
    trans = torch.as_tensor(rng.normal(0, 0.1, (2, 3))).requires_grad_(True)
    e = energy(pose, trans)
    gp, gt = torch.autograd.grad(e, (pose, trans))
    h = 1e-6
    for (which, i, j) in [("pose", 0, 3 * JOINT_INDEX["right_elbow"] + 1), ("pose", 0, 1), ("pose", 1, 10),
                          ("trans", 0, 2), ("trans", 1, 0)]:
        p, t = pose.detach().clone(), trans.detach().clone()
        x = p if which == "pose" else t
        x[i, j] += h
        up = energy(p, t).item()
        x[i, j] -= 2 * h
        down = energy(p, t).item()
        fd = (up - down) / (2 * h)
        an = (gp if which == "pose" else gt)[i, j].item()
        assert an == pytest.approx(fd, rel=1e-5, abs=1e-4), (which, i, j)
    # frame 1 has no target: only the pose term pulls it
    assert float(gt[1].abs().max()) == 0.0


def test_one_shape_for_every_frame_is_shaped_once_and_gives_the_same_joints_and_gradients():
    """A long motion's refit must not hold a shaped rest mesh per frame (3 GB for a
    10-minute video): one row of betas is shaped once and shared as a view, with the same
    joints, transforms and gradients as shaping every frame."""
    model = load_body_model("default", dtype=torch.float64)
    rng = np.random.default_rng(3)
    T = 40
    poses = torch.as_tensor(rng.normal(0, 0.3, (T, 72)))
    trans = torch.as_tensor(rng.normal(0, 0.5, (T, 3)))
    betas = torch.as_tensor(rng.normal(0, 1.0, (1, 10))).requires_grad_(True)
    shared = posed_joints_only(model, betas, poses, trans)
    assert shared.vertices is None
    assert shared.rest_vertices.shape[0] == T and shared.rest_vertices.stride(0) == 0  # one mesh, not T
    per_frame = model(betas=betas.expand(T, -1), pose=poses, trans=trans, with_vertices=False)
    assert per_frame.rest_vertices.stride(0) != 0
    np.testing.assert_allclose(shared.joints.detach().numpy(), per_frame.joints.detach().numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(shared.transforms.detach().numpy(), per_frame.transforms.detach().numpy(), rtol=0,
                               atol=1e-12)
    w = torch.as_tensor(rng.normal(0, 1.0, (T, 24, 3)))
    g_shared = torch.autograd.grad((shared.joints * w).sum(), betas)[0]
    g_per_frame = torch.autograd.grad((per_frame.joints * w).sum(), betas)[0]
    np.testing.assert_allclose(g_shared.numpy(), g_per_frame.numpy(), rtol=1e-10, atol=1e-12)
    # different shapes per row are still shaped row by row
    several = torch.as_tensor(rng.normal(0, 1.0, (T, 10)))
    rows = posed_joints_only(model, several, poses, trans)
    one = model(betas=several[5:6], pose=poses[5:6], trans=trans[5:6], with_vertices=False)
    np.testing.assert_allclose(rows.joints[5].numpy(), one.joints[0].numpy(), rtol=0, atol=1e-12)


def test_pipeline_keeps_the_tracked_motion_when_the_refit_cannot_run(tmp_path):
    from flowmocap import pipeline
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.io.results import read_result, write_motion, write_run

    motion, track, _, _ = _setup(tmp_path, TRUTH)
    out = tmp_path / "result"
    out.mkdir()
    write_motion(out, motion)
    write_run(out, {"status": "finished", "events": []})
    short = PersonTrack(track.keypoints[:2], track.confidence[:2], track.found[:2], track.mask_paths[:2], {})
    said = []
    run = pipeline._lifter_refit(out, short, load_body_model("default"), TrackerConfig(), {"status": "finished"},
                                 said.append)
    assert "skipped" in run["lifter_refit"] and "skipped" in said[0]
    kept, info = read_result(out)
    np.testing.assert_array_equal(kept["poses"], motion["poses"])
    assert "poses_tracked" not in kept and "skipped" in info["lifter_refit"]


@pytest.mark.parametrize("smooth", [True, False])
def test_pipeline_smooths_the_refitted_depth_and_keeps_the_tracked_translation(tmp_path, smooth):
    from flowmocap import pipeline
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.fit.smooth import depth_smoothed_motion
    from flowmocap.io.results import read_result, write_motion, write_run

    wrong = TRUTH.copy()
    wrong[3 * JOINT_INDEX["right_elbow"] + 1] = np.radians(-80)
    motion, track, _, _ = _setup(tmp_path, wrong)
    motion["trans"] = motion["trans"] + np.array([[0, 0, 0], [0, 0, 0.2], [0, 0, -0.1], [0, 0, 0.1]], np.float32)
    motion["joints3d"] = motion["joints3d"] + (motion["trans"])[:, None]
    motion["trans_tracked"] = motion["trans"] - 0.01
    out = tmp_path / "result"
    out.mkdir()
    write_motion(out, motion)
    write_run(out, {"status": "finished", "events": []})
    model = load_body_model("default")
    cfg = TrackerConfig(lifter_refit_smooth_depth=smooth)
    run = pipeline._lifter_refit(out, track, model, cfg, {"status": "finished", "events": []}, lambda s: None)
    got, _ = read_result(out)
    refit, _ = lifter_refit_motion(motion, track, model, weight=cfg.lifter_refit_weight,
                                   pixel_sigma=cfg.lifter_refit_pixel_sigma, blend=cfg.lifter_refit_blend,
                                   detector_model=cfg.detector_model)
    want = depth_smoothed_motion(refit, cfg.depth_smoothing_s) if smooth else refit
    np.testing.assert_allclose(got["trans"], want["trans"], atol=1e-5)
    np.testing.assert_allclose(got["joints3d"], want["joints3d"], atol=1e-5)
    assert smooth == (np.abs(got["trans"] - refit["trans"]).max() > 1e-3)  # the smoothing moved the frames
    np.testing.assert_array_equal(got["trans_tracked"], motion["trans_tracked"])  # the tracker's own, kept
    assert ("depth_smoothed_s" in run["lifter_refit"]) == smooth
    # the sources' disagreement is written with the motion and read back by the API
    np.testing.assert_array_equal(got["disagreement"], refit["disagreement"])
    assert run["lifter_refit"]["disagreement_median_mm"] > 0 and run["lifter_refit"]["review_frames"]
    assert pipeline.Result(out, got, run).disagreement.shape == (T, 24)


def test_reinit_frames_say_which_seams_the_smoothing_steps_still_start_again_at():
    from flowmocap import pipeline

    events = [{"event": "re-initialised", "frame": 5, "criterion": "image", "why": "1 bad frames in a row"},
              {"event": "re-initialised", "frame": 9, "criterion": "3d", "why": "..."},
              {"event": "limb flipped in depth", "frame": 10},
              # a run written before the field: its reason tells
              {"event": "re-initialised", "frame": 14, "why": "3 frames in a row with the 3D joints more than ..."}]
    run = {"events": events}
    assert pipeline._reinit_frames_3d(run) == [9, 14]
    assert pipeline._reinit_frames(run) == [5, 9, 14]
    eased = {**run, "lifter_refit": {"seams_eased": [9]}}
    assert pipeline._reinit_frames(eased) == [5, 14]
    assert pipeline._reinit_frames(eased, include_eased=True) == [5, 9, 14]


@pytest.mark.parametrize("seam_s", [0.2, 0.0])
def test_pipeline_eases_a_3d_seam_and_smooths_the_depth_across_it(tmp_path, seam_s):
    from flowmocap import pipeline
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.fit.smooth import depth_smoothed_motion
    from flowmocap.io.results import read_result, write_motion, write_run

    wrong = TRUTH.copy()
    wrong[3 * JOINT_INDEX["right_elbow"] + 1] = np.radians(-80)
    motion, track, truth_kp, _ = _setup(tmp_path, np.array([wrong] * 6 + [TRUTH] * 4), frames=10)
    motion["trans"][6:] += np.float32([0, 0, 0.3])  # the refit restarted deeper too
    motion["joints3d"] = motion["joints3d"] + motion["trans"][:, None]
    out = tmp_path / "result"
    out.mkdir()
    write_motion(out, motion)
    run = {"status": "finished", "events": [{"event": "re-initialised", "frame": 6, "criterion": "3d"}]}
    write_run(out, run)
    model, cfg = load_body_model("default"), TrackerConfig(lifter_refit_seam_s=seam_s)
    said = []
    run = pipeline._lifter_refit(out, track, model, cfg, run, said.append)
    got, _ = read_result(out)
    refit, _ = lifter_refit_motion(motion, track, model, weight=cfg.lifter_refit_weight,
                                   pixel_sigma=cfg.lifter_refit_pixel_sigma, blend=cfg.lifter_refit_blend,
                                   seams=[6], seam_s=seam_s, detector_model=cfg.detector_model)
    # an eased seam has no jump left: the depth is smoothed across it; otherwise it starts again there
    want = depth_smoothed_motion(refit, cfg.depth_smoothing_s, breaks=[] if seam_s else [6])
    np.testing.assert_allclose(got["trans"], want["trans"], atol=1e-5)
    assert run["lifter_refit"]["seams_eased"] == ([6] if seam_s else [])
    assert ("eased" in said[0]) == bool(seam_s)
    jump = np.abs(np.diff(got["trans"][:, 2]))[5]
    assert (jump < 0.1) if seam_s else (jump > 0.25), got["trans"][:, 2]
    assert pipeline._reinit_frames(run) == ([] if seam_s else [6])  # what the later steps start again at


def test_the_lifter_can_read_the_fits_own_keypoints(tmp_path):
    wrong = TRUTH.copy()
    wrong[3 * JOINT_INDEX["right_elbow"] + 1] = np.radians(-80)
    motion, track, truth_kp, fit_kp = _setup(tmp_path, wrong)
    model = load_body_model("default")
    lifter = TruthLifter(truth_kp)
    out, info = lifter_refit_motion(motion, track, model, weight=1.0, lifter=lifter, iterations=60,
                                    lifter_input="fit")
    assert info["lifter_input"] == "fit" and info["frames_refit"] == 3  # still only where the person was found
    # it read the fit's 13 keypoints projected, not the detection (which is the truth's image here)
    fit_px = np.asarray(CAM.project(fit_kp.reshape(-1, 3))).reshape(T, 13, 2)
    np.testing.assert_allclose(lifter.seen, fit_px, atol=1e-6)
    kp_after, _ = _bodies(out["poses"].astype(np.float64))
    wrist = POINTS.index("right_wrist")
    before = np.linalg.norm(fit_kp[:3, wrist] - truth_kp[:3, wrist], axis=-1)
    after = np.linalg.norm(kp_after[:3, wrist] - truth_kp[:3, wrist], axis=-1)
    assert (after < 0.3 * before).all(), (before, after)
    with pytest.raises(InputError, match="lifter_input"):
        lifter_refit_motion(motion, track, model, lifter=lifter, lifter_input="mediapipe")


def test_agree_and_unswap_inputs_correct_the_detection_against_the_fit(tmp_path):
    motion, track, truth_kp, fit_kp = _setup(tmp_path, TRUTH)  # the fit is the truth; the detection its image
    model = load_body_model("default")
    px = np.asarray(CAM.project(truth_kp.reshape(-1, 3))).reshape(T, 13, 2)
    # a whole-body left/right exchange in frames 0 and 2: "unswap" reads them exchanged back
    mirror = [0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11]
    assert all(POINTS[m].replace("left", "x").replace("right", "left").replace("x", "right") == POINTS[k]
               for k, m in enumerate(mirror) if k)
    swapped = track.keypoints.copy()
    for k, name in enumerate(POINTS[1:], start=1):
        swapped[[0, 2], KEYPOINT_NAMES.index(name)] = px[[0, 2], mirror[k]]
    track_sw = PersonTrack(swapped, track.confidence, track.found, track.mask_paths, {})
    for mode, expect_frames_0_2 in (("detector", px[[0, 2]][:, mirror]), ("unswap", px[[0, 2]])):
        lifter = TruthLifter(truth_kp)
        lifter_refit_motion(motion, track_sw, model, weight=0.5, lifter=lifter, iterations=2, lifter_input=mode)
        np.testing.assert_allclose(lifter.seen[[0, 2]], expect_frames_0_2, atol=1e-4)
        np.testing.assert_allclose(lifter.seen[1], px[1], atol=1e-4)
    # one point 100 px off: "agree" reads the fit's own there and the detection elsewhere
    off = track.keypoints.copy()
    off[:, KEYPOINT_NAMES.index("left_wrist")] += (100.0, 0.0)
    off[:, KEYPOINT_NAMES.index("left_knee")] += (5.0, 0.0)
    lifter = TruthLifter(truth_kp)
    lifter_refit_motion(motion, PersonTrack(off, track.confidence, track.found, track.mask_paths, {}), model,
                        weight=0.5, lifter=lifter, iterations=2, lifter_input="agree")
    wrist, knee = POINTS.index("left_wrist"), POINTS.index("left_knee")
    np.testing.assert_allclose(lifter.seen[:, wrist], px[:, wrist], atol=1e-3)  # the fit's (= the truth's) point
    np.testing.assert_allclose(lifter.seen[:, knee], px[:, knee] + (5.0, 0.0), atol=1e-3)  # the detection's


def test_the_lifter_reads_the_frames_the_tracker_exchanged_back(tmp_path, monkeypatch):
    from flowmocap import pipeline
    from flowmocap.fit import lift_refit
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.fit.swap import EXCHANGED_EVENT
    from flowmocap.io.results import write_motion, write_run

    motion, track, truth_kp, _ = _setup(tmp_path, TRUTH)
    model = load_body_model("default")
    px = np.asarray(CAM.project(truth_kp.reshape(-1, 3))).reshape(T, 13, 2)
    mirror = [0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11]
    swapped = track.keypoints.copy()  # the detector turned the body about in frames 1 and 2
    for k, name in enumerate(POINTS[1:], start=1):
        swapped[[1, 2], KEYPOINT_NAMES.index(name)] = px[[1, 2], mirror[k]]
    track_sw = PersonTrack(swapped, track.confidence, track.found, track.mask_paths, {})
    # the tracker exchanged frame 2 back (named twice), not frame 1; frame 99 is not in the track
    lifter = TruthLifter(truth_kp)
    _, info = lifter_refit_motion(motion, track_sw, model, weight=0.5, lifter=lifter, iterations=2,
                                  exchanged=[2, 99, 2])
    np.testing.assert_allclose(lifter.seen[[0, 2]], px[[0, 2]], atol=1e-4)  # as the tracker used them
    np.testing.assert_allclose(lifter.seen[1], px[1][mirror], atol=1e-4)  # as the detector gave it
    assert info["frames_exchanged"] == 1  # frame 2 (named twice); frame 99 is not in the track
    # the pipeline passes the run's exchange events on
    out = tmp_path / "result"
    out.mkdir()
    write_motion(out, motion)
    events = [{"frame": 2, "event": EXCHANGED_EVENT}, {"frame": 1, "event": "re-initialised"}]
    write_run(out, {"status": "finished", "events": events})
    seen = {}
    real = lift_refit.lifter_refit_motion

    def spy(*a, **k):
        seen.update(k)
        return real(*a, **{**k, "lifter": TruthLifter(truth_kp), "iterations": 2})

    monkeypatch.setattr(lift_refit, "lifter_refit_motion", spy)
    cfg = TrackerConfig(lifter_refit_hidden_share=0.25, lifter_refit_bridge_s=0.2, detector_model="full",
                        lifter_refit_min_confidence=0.3)
    pipeline._lifter_refit(out, track_sw, model, cfg, {"status": "finished", "events": events}, lambda s: None)
    assert seen["exchanged"] == [2]
    assert seen["hidden_share"] == 0.25 and seen["bridge_s"] == 0.2  # the settings reach the refit
    assert seen["min_confidence"] == 0.3
    assert seen["detector_model"] == "full"  # the body's keypoints placed with that network's offsets
    with pytest.raises(InputError, match="unknown detector model"):
        lifter_refit_motion(motion, track_sw, model, weight=0.5, lifter=lifter, iterations=2, detector_model="lite")


def test_the_lifter_reads_points_at_its_minimum_confidence_as_given(tmp_path):
    motion, track, truth_kp, _ = _setup(tmp_path, TRUTH)
    model = load_body_model("default")
    conf = track.confidence.copy()
    wrist = KEYPOINT_NAMES.index("left_wrist")
    conf[:, wrist] = 0.2  # a point the detector calls hidden
    conf[:, KEYPOINT_NAMES.index("left_knee")] = 0.0  # and one it did not give
    low = PersonTrack(track.keypoints, conf, track.found, track.mask_paths, {})
    masks = {}
    for m in (0.5, 0.1, 0.0):
        lifter = TruthLifter(truth_kp)
        lifter_refit_motion(motion, low, model, weight=0.5, lifter=lifter, iterations=2, min_confidence=m)
        masks[m] = lifter.mask
    w, k = POINTS.index("left_wrist"), POINTS.index("left_knee")
    found = np.asarray(track.found, bool)
    assert not masks[0.5][:, w].any() and masks[0.1][found, w].all() and masks[0.0][found, w].all()
    assert not any(masks[m][:, k].any() for m in masks)  # confidence 0 is never given
    others = [i for i in range(len(POINTS)) if i not in (w, k)]
    assert (masks[0.5][:, others] == masks[0.0][:, others]).all()


@pytest.mark.parametrize("bridge_s", [0.0, 0.1, 0.05])
def test_a_point_the_detector_lost_for_a_moment_is_bridged_before_lifting(tmp_path, bridge_s):
    motion, track, truth_kp, _ = _setup(tmp_path, TRUTH, frames=8)
    model = load_body_model("default")
    px = np.asarray(CAM.project(truth_kp.reshape(-1, 3))).reshape(8, 13, 2)
    kp, conf, found = track.keypoints.copy(), track.confidence.copy(), track.found.copy()
    w = KEYPOINT_NAMES.index("left_wrist")
    kp[:, w] += np.arange(8)[:, None] * (2.0, -1.0)  # the wrist moves along a line in the image
    kp[[3, 4, 5], w] = (0.0, 0.0)  # lost for 3 frames (at 30 fps, 0.1 s) ...
    conf[[3, 4, 5], w] = 0.1
    found[4] = False  # ... one of them without the person: never filled
    lifter = TruthLifter(truth_kp)
    lifter_refit_motion(motion, PersonTrack(kp, conf, found, track.mask_paths, {}), model, weight=0.5,
                        lifter=lifter, iterations=2, bridge_s=bridge_s)
    k = POINTS.index("left_wrist")
    filled = bridge_s >= 0.1
    np.testing.assert_array_equal(lifter.mask[[3, 4, 5], k], [filled, False, filled])
    others = np.ones((8, 13), bool)
    others[[3, 4, 5], k] = False
    assert lifter.mask[others].all()  # every other point as the detection gave it
    if filled:  # the line between frames 2 and 6
        np.testing.assert_allclose(lifter.seen[[3, 5], k], px[[3, 5], k] + np.array([[6.0, -3.0], [10.0, -5.0]]))
    with pytest.raises(InputError, match="bridge_s"):
        lifter_refit_motion(motion, track, model, weight=0.5, lifter=lifter, bridge_s=-1.0)


def test_vote_flip_frames_finds_runs_where_every_source_reaches_the_other_way():
    from flowmocap.body.skeleton import EVAL_JOINTS
    from flowmocap.fit.lift_refit import vote_flip_frames

    limb = (JOINT_INDEX["right_elbow"], JOINT_INDEX["right_wrist"])
    a, b = EVAL_JOINTS.index(limb[0]), EVAL_JOINTS.index(limb[1])
    n = 12
    fit = np.zeros((n, 13, 3)) + (0, 0, 4.0)
    fit[:, b, 2] += 0.15                          # the fit's forearm reaches away from the camera
    src = fit.copy()
    src[2:9, b, 2] = 4.0 - 0.15                   # frames 2-8: this source says towards
    other = src.copy()
    other[5, b, 2] = 4.0 + 0.15                   # the other source agrees with the fit in frame 5
    got = vote_flip_frames(fit, [src], limb, min_reach=0.08, min_frames=3)
    np.testing.assert_array_equal(np.flatnonzero(got), np.arange(2, 9))
    assert not vote_flip_frames(fit, [src], limb, 0.08, 8).any()        # a run of 7 is too short for 8
    both = vote_flip_frames(fit, [src, other], limb, 0.08, 3)            # every source must agree: 2-4 and 6-8
    np.testing.assert_array_equal(np.flatnonzero(both), [2, 3, 4, 6, 7, 8])
    assert not vote_flip_frames(fit, [src, other], limb, 0.08, 4).any()
    assert not vote_flip_frames(fit, [src], limb, 0.2, 1).any()          # reaching 15 cm is not more than 20
    shallow = src.copy()
    shallow[:, b, 2] = 4.0 - 0.05
    assert not vote_flip_frames(fit, [shallow], limb, 0.08, 1).any()     # the source must reach far enough too
    missing = src.copy()
    missing[4] = np.nan                                                  # no source in frame 4 ends the run
    np.testing.assert_array_equal(np.flatnonzero(vote_flip_frames(fit, [missing], limb, 0.08, 3)), [5, 6, 7, 8])


def _give_world(track, kp13):
    """The detector's 3D (``track.world``): ``kp13 (T, 13, 3)`` world points in the axes of the
    ray through the hips, hip-centred, as MediaPipe gives its world landmarks."""
    world = np.full((T, len(KEYPOINT_NAMES), 3), np.nan)
    truth_cam = kp13 @ CAM.R.T + CAM.t
    px = np.asarray(CAM.project(kp13.reshape(-1, 3))).reshape(T, 13, 2)
    for f in range(T):  # the detector's 3D: the truth in the axes of the ray through the hips, hip-centred
        ray = CAM.ray_rotation(*map(float, px[f, list(HIPS)].mean(0)))
        x = (truth_cam[f] - truth_cam[f, list(HIPS)].mean(0)) @ ray
        for k, name in enumerate(POINTS):
            for n in (("left_ear", "right_ear") if name == "head" else (name,)):
                world[f, KEYPOINT_NAMES.index(n)] = x[k]
    track.world = world


@pytest.mark.parametrize("share", [0.0, 1.0])
def test_a_limb_the_detector_cannot_see_moves_towards_its_3d_and_leaves_the_tracked_image(tmp_path, share):
    wrong = TRUTH.copy()
    wrong[3 * JOINT_INDEX["right_elbow"] + 1] = np.radians(-40)  # the tracked forearm elsewhere, in the image too
    motion, track, truth_kp, fit_kp = _setup(tmp_path, wrong)
    _give_world(track, truth_kp)  # the detector's own 3D: the truth
    conf = track.confidence.copy()
    hidden = [KEYPOINT_NAMES.index("right_wrist")]
    conf[:3, hidden] = 0.2  # it cannot see the wrist (its 2D: the truth's, unused)
    track = PersonTrack(track.keypoints, conf, track.found, track.mask_paths, {}, world=track.world)
    model = load_body_model("default")
    fit_lifter = TruthLifter(fit_kp)  # a lifter that agrees with the fit: only the new step moves the wrist
    out, info = lifter_refit_motion(motion, track, model, weight=0.5, lifter=fit_lifter, iterations=60,
                                    blend="full", pixel_sigma=4.0, hidden_share=share)
    kp_after, _ = _bodies(out["poses"].astype(np.float64))
    wrist = POINTS.index("right_wrist")
    before = np.linalg.norm(fit_kp[:3, wrist] - truth_kp[:3, wrist], axis=-1)
    after = np.linalg.norm(kp_after[:3, wrist] - truth_kp[:3, wrist], axis=-1)
    px = lambda x: np.asarray(CAM.project(x.reshape(-1, 3))).reshape(x.shape[:-1] + (2,))  # noqa: E731
    moved_px = np.linalg.norm(px(kp_after[:3, wrist]) - px(fit_kp[:3, wrist]), axis=-1)
    off_px = lambda k: np.linalg.norm(px(k[:3, wrist]) - px(truth_kp[:3, wrist]), axis=-1)  # noqa: E731
    assert info["hidden_share"] == share and info["hidden_points"] == (3 if share else 0)
    assert (before > 0.1).all() and (off_px(fit_kp) > 5).all()
    if share:  # towards the detector's 3D, in the image too: the tracked image is let go of
        assert (after < 0.3 * before).all(), (before, after)
        assert (off_px(kp_after) < 0.6 * off_px(fit_kp)).all(), (off_px(fit_kp), off_px(kp_after))
    else:  # nothing pulls it: it stays where it was tracked
        assert (after > 0.9 * before).all() and (moved_px < 3).all()
    # the other points keep their image
    others = [k for k in range(13) if k not in (wrist, POINTS.index("right_elbow"))]
    assert np.abs(px(kp_after[:3, others]) - px(fit_kp[:3, others])).max() < 3.0
    with pytest.raises(InputError, match="hidden_share"):
        lifter_refit_motion(motion, track, model, weight=0.5, lifter=fit_lifter, hidden_share=1.5)


@pytest.mark.parametrize("min_frames, flips", [(3, True), (4, False), (0, False)])
def test_a_forearm_the_detector_sees_the_other_way_for_a_run_of_frames_is_mirrored(tmp_path, min_frames, flips):
    wrong = TRUTH.copy()
    wrong[3 * JOINT_INDEX["right_elbow"] + 1] = np.radians(-80)  # reaching away instead of towards
    motion, track, truth_kp, fit_kp = _setup(tmp_path, wrong)
    _give_world(track, truth_kp)
    # a lifter that agrees with the fit: the refit alone keeps the forearm where it is
    out, info = lifter_refit_motion(motion, track, load_body_model("default"), weight=0.5,
                                    lifter=TruthLifter(fit_kp), iterations=30, pixel_sigma=6.0,
                                    vote_min_frames=min_frames, vote_sources="detector")
    kp_after, _ = _bodies(out["poses"].astype(np.float64))
    wrist = POINTS.index("right_wrist")
    err = np.linalg.norm(kp_after[:3, wrist] - truth_kp[:3, wrist], axis=-1)
    before = np.linalg.norm(fit_kp[:3, wrist] - truth_kp[:3, wrist], axis=-1)
    assert info["limb_frames_voted"] == (3 if flips else 0)
    assert info["limb_runs_voted"] == ([{"limb": "right_elbow->right_wrist", "frames": [0, 2]}] if flips else [])
    if flips:
        # the mirror image of the wrong forearm, not the truth itself, and the refit then pulls
        # half-way towards the lifter's (the wrong) depths: much nearer, and reaching the right way
        assert (before > 0.2).all() and (err < 0.25 * before).all(), (before, err)
        elbow = POINTS.index("right_elbow")
        cam = lambda x: x @ CAM.R.T + CAM.t  # noqa: E731
        reach = cam(kp_after[:3])[:, wrist, 2] - cam(kp_after[:3])[:, elbow, 2]
        true_reach = cam(truth_kp[:3])[:, wrist, 2] - cam(truth_kp[:3])[:, elbow, 2]
        assert (true_reach < -0.1).all() and (reach < -0.1).all(), (true_reach, reach)
        assert info["mean_move_px"] < 3.0  # the mirror image keeps the wrist's pixel
    else:
        assert (err > 0.8 * before).all(), (before, err)
    np.testing.assert_array_equal(out["poses"][3], motion["poses"][3])  # no person: kept
    np.testing.assert_array_equal(out["poses_tracked"], motion["poses"])


@pytest.mark.parametrize("with_detector", [True, False])
def test_the_refit_flags_the_joint_where_its_sources_part(tmp_path, with_detector):
    from flowmocap.body.skeleton import EVAL_JOINTS

    wrong = TRUTH.copy()
    wrong[3 * JOINT_INDEX["right_elbow"] + 1] = np.radians(-80)  # the fit's forearm reaching away
    motion, track, truth_kp, fit_kp = _setup(tmp_path, wrong)
    if with_detector:
        _give_world(track, truth_kp)  # the detector's 3D agrees with the lifter (the truth)
    out, info = lifter_refit_motion(motion, track, load_body_model("default"), weight=0.5,
                                    lifter=TruthLifter(truth_kp), iterations=5)
    d = out["disagreement"]
    assert d.shape == (T, 24) and d.dtype == np.float32
    others = [j for j in range(24) if j not in EVAL_JOINTS]
    assert np.isnan(d[:, others]).all() and np.isnan(d[3]).all()  # not scored; no person in frame 3
    wrist = JOINT_INDEX["right_wrist"]
    gap = np.linalg.norm(fit_kp[:3, POINTS.index("right_wrist")] - truth_kp[:3, POINTS.index("right_wrist")], axis=-1)
    assert (gap > 0.2).all()
    # the fit parts from both other sources at the wrist (2 of 3 pairs), from the lifter alone without the detector
    share = 2 / 3 if with_detector else 1.0
    assert (d[:3, wrist] > 0.5 * share * gap).all() and (d[:3, wrist] < 1.05 * share * gap).all(), (d[:3, wrist], gap)
    rest = [j for j in EVAL_JOINTS if j not in (wrist, JOINT_INDEX["right_elbow"])]
    assert (d[:3, rest] < 0.35 * d[:3, wrist, None]).all()
    assert info["disagreement_p90_mm"] >= info["disagreement_median_mm"] > 0
    assert info["review_frames"] and all(a <= b <= 2 for a, b in info["review_frames"])  # frames with sources


def test_the_vote_reads_no_detector_3d_where_there_is_none(tmp_path):
    wrong = TRUTH.copy()
    wrong[3 * JOINT_INDEX["right_elbow"] + 1] = np.radians(-80)
    motion, track, truth_kp, fit_kp = _setup(tmp_path, wrong)
    assert track.world is None
    out, info = lifter_refit_motion(motion, track, load_body_model("default"), weight=0.5,
                                    lifter=TruthLifter(fit_kp), iterations=5, vote_min_frames=1)
    assert info["limb_frames_voted"] == 0
    with pytest.raises(InputError, match="vote"):
        lifter_refit_motion(motion, track, load_body_model("default"), weight=0.5, lifter=TruthLifter(fit_kp),
                            vote_min_frames=1, vote_sources="everyone")


@pytest.mark.parametrize("image_of, check, flips", [("truth", True, True), ("fit", True, False), ("fit", False, True)])
def test_an_upper_arm_is_mirrored_only_where_the_detected_wrist_agrees(tmp_path, image_of, check, flips):
    from flowmocap.fit.flip import mirrored_rotvec

    truth = _pose(right_shoulder=(0, 50, 30), right_elbow=(0, 70, 0))  # upper arm and forearm reach in depth
    _, joints = _bodies([truth])
    out = load_body_model("default", dtype=torch.float64)(betas=torch.zeros(1, 10), pose=torch.as_tensor(truth[None]),
                                                           trans=torch.zeros(1, 3), with_vertices=False)
    limb = (JOINT_INDEX["right_shoulder"], JOINT_INDEX["right_elbow"])
    wrong = truth.copy()  # the upper arm mirrored in depth: the elbow on its pixel, the wrist elsewhere
    wrong[3 * limb[0]:3 * limb[0] + 3] = mirrored_rotvec(truth, joints[0], out.transforms[0, :, :3, :3].numpy(),
                                                        CAM.R, CAM.t, limb)
    motion, track, truth_kp, fit_kp = _setup(tmp_path, wrong, truth=truth, image=truth if image_of == "truth" else wrong)
    _give_world(track, truth_kp)
    cam = lambda x: x[:3] @ CAM.R.T + CAM.t  # noqa: E731
    e, w = POINTS.index("right_elbow"), POINTS.index("right_wrist")
    s = POINTS.index("right_shoulder")
    assert (np.abs(cam(truth_kp)[:, e, 2] - cam(truth_kp)[:, s, 2]) > 0.1).all()  # a vote can be cast
    px = lambda kp: np.asarray(CAM.project(kp[:3, w]))  # noqa: E731
    assert (np.linalg.norm(px(truth_kp) - px(fit_kp), axis=-1) > 10).all()  # the mirror moves the wrist's pixel
    res, info = lifter_refit_motion(motion, track, load_body_model("default"), weight=0.5, lifter=TruthLifter(fit_kp),
                                    iterations=1, vote_min_frames=3, vote_sources="detector", vote_check_2d=check)
    assert info["limb_frames_voted"] == (3 if flips else 0), info


# ---------------------------------------------- the body's proportions towards the lifter's (twenty-ninth session)

def test_bone_proportions_closed_form_scale_free_and_alike_in_numpy_and_torch():
    from flowmocap.fit.lift_refit import PROPORTION_BONES, bone_proportions

    rng = np.random.default_rng(3)
    pts = rng.normal(0, 0.4, (5, 13, 3))
    got = bone_proportions(pts)
    lengths = np.stack([np.mean([np.linalg.norm(pts[:, a] - pts[:, b], axis=-1) for a, b in pairs], 0)
                        for pairs in PROPORTION_BONES], -1)
    np.testing.assert_allclose(got, lengths / lengths.sum(-1, keepdims=True), atol=1e-12)
    np.testing.assert_allclose(got.sum(-1), 1.0, atol=1e-12)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    np.testing.assert_allclose(bone_proportions(2.5 * pts @ R.T + (1, 2, 3)), got, atol=1e-12)  # size, turn, place
    np.testing.assert_allclose(bone_proportions(torch.as_tensor(pts)).numpy(), got, atol=1e-12)


def _proportions(model, kmap, betas, poses=None):
    from flowmocap.fit.lift_refit import posed_proportions

    poses = np.zeros((1, 72)) if poses is None else np.asarray(poses, np.float64)
    with torch.no_grad():
        return posed_proportions(model, kmap, torch.as_tensor(np.asarray(betas, np.float64)).reshape(1, -1),
                                 torch.as_tensor(poses)).numpy()


TRUTH_BETAS = np.array([1.0, -1.2, 0.6, 0.0, 0.8, 0.0, -0.5, 0.0, 0.0, 0.3])


def test_posed_proportions_are_the_mean_of_each_poses_and_turn_with_the_pose():
    from flowmocap.fit.lift_refit import bone_proportions

    model, kmap = load_body_model("default", dtype=torch.float64), load_keypoint_map()
    poses = np.stack([np.zeros(72), TRUTH])
    with torch.no_grad():
        kp, _ = keypoints13(model, kmap, torch.as_tensor(poses), torch.zeros(1, 10, dtype=torch.float64),
                            torch.zeros(2, 3, dtype=torch.float64))
    each = bone_proportions(kp.numpy())
    np.testing.assert_allclose(_proportions(model, kmap, np.zeros(10), poses), each.mean(0), atol=1e-12)
    assert np.abs(each[0] - each[1]).max() > 1e-3  # the keypoints' offsets turn with the joints


def _proportion_energy(model, kmap, b, b0, goal, at):
    import flowmocap.fit.lift_refit as lr

    poses = torch.zeros(1, 72, dtype=torch.float64) if at is None else torch.as_tensor(at)
    return ((lr.posed_proportions(model, kmap, b, poses) - torch.as_tensor(goal)) ** 2).sum() / lr.PROPORTION_SIGMA ** 2 \
        + ((b - b0) ** 2).sum() / lr.SHAPE_SIGMA ** 2


@pytest.mark.parametrize("poses", [None, "posed"])
def test_fit_proportions_minimises_its_energy_and_keeps_a_shape_that_has_them(poses, monkeypatch):
    import flowmocap.fit.lift_refit as lr

    model, kmap = load_body_model("default", dtype=torch.float64), load_keypoint_map()
    at = None if poses is None else np.stack([TRUTH, _pose(left_knee=(60, 0, 0), right_elbow=(0, -40, 0))])
    at_t = None if at is None else torch.as_tensor(at)
    goal = _proportions(model, kmap, TRUTH_BETAS, at)
    start = torch.zeros(1, 10, dtype=torch.float64)
    before = np.abs(_proportions(model, kmap, start, at) - goal).max()
    got = lr.fit_proportions(model, kmap, start, goal, poses=at_t)
    after = np.abs(_proportions(model, kmap, got, at) - goal).max()
    assert before > 0.005 and after < 0.6 * before, (before, after)
    # a minimum of the documented energy: its gradient vanishes there, not at the start
    grads = []
    for b in (start, got):
        b = b.clone().requires_grad_(True)
        _proportion_energy(model, kmap, b, start, goal, at).backward()
        grads.append(b.grad.norm().item())
    assert grads[1] < 1e-3 * grads[0], grads
    # the shape's term only settles what the proportions leave free: with a tight scale they are met
    monkeypatch.setattr(lr, "PROPORTION_SIGMA", 1e-4)
    tight = np.abs(_proportions(model, kmap, lr.fit_proportions(model, kmap, start, goal, poses=at_t), at) - goal).max()
    assert tight < 0.1 * before, (before, tight)
    kept = lr.fit_proportions(model, kmap, torch.as_tensor(TRUTH_BETAS).reshape(1, -1), goal, poses=at_t)  # already there
    np.testing.assert_allclose(kept.numpy().ravel(), TRUTH_BETAS, atol=1e-6)


@pytest.mark.parametrize("share", [1.0, 0.5, 0.0])
def test_the_refit_moves_the_bodys_proportions_towards_the_lifters(tmp_path, share):
    frames = 12
    model64, kmap = load_body_model("default", dtype=torch.float64), load_keypoint_map()
    motion, track, _, _ = _setup(tmp_path, TRUTH, frames=frames)
    with torch.no_grad():  # the lifter sees a body of other proportions in the same pose
        truth_kp, _ = keypoints13(model64, kmap, torch.as_tensor(np.tile(TRUTH, (frames, 1))),
                                  torch.as_tensor(TRUTH_BETAS).reshape(1, -1), torch.zeros(frames, 3, dtype=torch.float64))
    out, info = lifter_refit_motion(motion, track, load_body_model("default"), weight=0.5,
                                    lifter=TruthLifter(truth_kp.numpy()), iterations=20, shape_share=share)
    own, seen = _proportions(model64, kmap, np.zeros(10), [TRUTH]), _proportions(model64, kmap, TRUTH_BETAS, [TRUTH])
    if share == 0:
        assert info["shape"] is None and "betas_tracked" not in out
        np.testing.assert_array_equal(out["betas"], motion["betas"])
        return
    np.testing.assert_array_equal(out["betas_tracked"], motion["betas"])
    after = _proportions(model64, kmap, out["betas"], [TRUTH])
    np.testing.assert_allclose(info["shape"]["proportions_before"], own, atol=1e-4)
    np.testing.assert_allclose(info["shape"]["proportions_lifter"], seen, atol=1e-4)  # the median of the lifted frames
    np.testing.assert_allclose(info["shape"]["proportions_after"], after, atol=1e-4)
    goal = own + share * (seen - own)
    assert np.abs(after - goal).max() < 0.6 * np.abs(own - goal).max(), (own, goal, after)
    # joints3d are the new body's
    with torch.no_grad():
        j = model64(betas=torch.as_tensor(out["betas"], dtype=torch.float64).reshape(1, -1).expand(frames, -1),
                    pose=torch.as_tensor(out["poses"], dtype=torch.float64),
                    trans=torch.as_tensor(out["trans"], dtype=torch.float64), with_vertices=False).joints.numpy()
    np.testing.assert_allclose(out["joints3d"], j, atol=1e-4)


def test_a_stated_height_holds_through_the_shape_step(tmp_path):
    from flowmocap.body.stature import stature

    frames = 12
    model64, kmap = load_body_model("default", dtype=torch.float64), load_keypoint_map()
    motion, track, _, _ = _setup(tmp_path, TRUTH, frames=frames)
    with torch.no_grad():
        truth_kp, _ = keypoints13(model64, kmap, torch.as_tensor(np.tile(TRUTH, (frames, 1))),
                                  torch.as_tensor(TRUTH_BETAS).reshape(1, -1), torch.zeros(frames, 3, dtype=torch.float64))
    kw = dict(weight=0.5, lifter=TruthLifter(truth_kp.numpy()), iterations=20, shape_share=1.0)
    free, _ = lifter_refit_motion(motion, track, load_body_model("default"), **kw)
    out, info = lifter_refit_motion(motion, track, load_body_model("default"), height=1.62, **kw)
    assert abs(stature(model64, free["betas"]) - 1.62) > 0.01  # the shape step alone moves the stature
    assert stature(model64, out["betas"]) == pytest.approx(1.62, abs=1e-4)  # float32 betas
    np.testing.assert_allclose(info["shape"]["proportions_after"], _proportions(model64, kmap, out["betas"], [TRUTH]),
                               atol=1e-4)


def test_too_few_lifted_frames_keep_the_shape(tmp_path):
    motion, track, truth_kp, _ = _setup(tmp_path, TRUTH)  # 3 frames with a person
    out, info = lifter_refit_motion(motion, track, load_body_model("default"), weight=0.5,
                                    lifter=TruthLifter(truth_kp), iterations=5, shape_share=1.0)
    assert info["shape"] is None and "betas_tracked" not in out


def test_the_proportions_gradient_matches_finite_differences():
    from flowmocap.fit.lift_refit import posed_proportions

    model, kmap = load_body_model("default", dtype=torch.float64), load_keypoint_map()
    poses = torch.as_tensor(np.stack([TRUTH, np.zeros(72)]))
    w = torch.as_tensor(np.random.default_rng(5).normal(size=7))
    _check_betas_gradient(lambda b: (posed_proportions(model, kmap, b, poses) * w).sum(), 0.5 * TRUTH_BETAS,
                          rtol=1e-5, atol=1e-8)


def _check_betas_gradient(f, at, rtol, atol):
    """Autograd's gradient of the scalar ``f(betas (1, 10))`` at ``at`` against central differences."""
    b = torch.as_tensor(at).reshape(1, -1).requires_grad_(True)
    f(b).backward()
    h, num = 1e-6, np.zeros(10)
    for i in range(10):
        d = torch.zeros(1, 10, dtype=torch.float64)
        d[0, i] = h
        with torch.no_grad():
            num[i] = (f(b + d) - f(b - d)).item() / (2 * h)
    np.testing.assert_allclose(b.grad.numpy().ravel(), num, rtol=rtol, atol=atol)


@pytest.mark.parametrize("share", [-0.1, 1.5])
def test_a_shape_share_outside_zero_to_one_is_refused(tmp_path, share):
    motion, track, truth_kp, _ = _setup(tmp_path, TRUTH)
    with pytest.raises(InputError, match="shape_share"):
        lifter_refit_motion(motion, track, load_body_model("default"), lifter=TruthLifter(truth_kp), shape_share=share)


def test_body_girth_is_each_vertexs_distance_from_its_main_bone():
    from flowmocap.body.skeleton import PARENTS
    from flowmocap.fit.lift_refit import body_girth

    model = load_body_model("default", dtype=torch.float64)
    betas = torch.as_tensor(0.5 * TRUTH_BETAS).reshape(1, -1)
    got = body_girth(model, betas).numpy()
    verts, joints = (x[0].numpy() for x in model.shaped(betas))
    weights = model.weights.numpy()
    for v in np.random.default_rng(0).choice(len(verts), 200, replace=False):
        j = int(weights[v].argmax())
        c = next((k for k, p in enumerate(PARENTS) if p == j), j)
        a, b = joints[j], joints[c]
        u = 0.0 if c == j else np.clip(np.dot(verts[v] - a, b - a) / np.dot(b - a, b - a), 0, 1)
        assert abs(got[v] - np.linalg.norm(verts[v] - (a + u * (b - a)))) < 1e-9
    assert got.shape == (len(verts),) and (got >= 0).all() and 0.03 < got.mean() < 0.15  # metres


def test_the_girth_energy_gradient_matches_finite_differences():
    from flowmocap.fit.lift_refit import body_girth

    model = load_body_model("default", dtype=torch.float64)
    g0 = body_girth(model, torch.zeros(1, 10, dtype=torch.float64)).detach()
    _check_betas_gradient(lambda b: ((body_girth(model, b) - g0) ** 2).mean(), 0.3 * TRUTH_BETAS,
                          rtol=1e-4, atol=1e-10)


def test_holding_the_girth_keeps_the_body_as_wide_while_its_proportions_move():
    from flowmocap.fit.lift_refit import body_girth, fit_proportions

    model, kmap = load_body_model("default", dtype=torch.float64), load_keypoint_map()
    start = torch.zeros(1, 10, dtype=torch.float64)
    own = _proportions(model, kmap, start)
    goal = own + np.array([0, 0, 0, -0.01, 0.01, 0, 0])  # shorter shins, a longer torso
    g0 = body_girth(model, start)
    moved = {}
    for sigma in (None, 0.002):
        b = fit_proportions(model, kmap, start, goal, girth_sigma=sigma)
        moved[sigma] = (float((body_girth(model, b) - g0).pow(2).mean().sqrt()),
                        float(np.abs(_proportions(model, kmap, b) - goal).max()))
    assert moved[0.002][0] < 0.5 * moved[None][0], moved  # the width held
    assert moved[0.002][1] < 0.6 * np.abs(own - goal).max(), moved  # the proportions still move


# ------------------------------------------ the same step before tracking: init_shape_share (thirtieth session)

def test_median_proportions_skip_frames_without_3d_and_need_enough_frames():
    from flowmocap.fit.lift_refit import PROPORTION_MIN_FRAMES, bone_proportions, median_proportions

    rng = np.random.default_rng(7)
    pts = rng.normal(0, 0.4, (PROPORTION_MIN_FRAMES + 3, 13, 3))
    pts[2, 5] = np.nan  # a frame without all 13 points is left out
    keep = np.ones(len(pts), bool)
    keep[2] = False
    np.testing.assert_allclose(median_proportions(pts), np.median(bone_proportions(pts[keep]), 0), atol=1e-12)
    assert median_proportions(pts[:PROPORTION_MIN_FRAMES]) is None  # one frame short of enough
    assert median_proportions(np.full((30, 13, 3), np.nan)) is None


@pytest.mark.parametrize("share", [0.0, 0.5, 1.0])
def test_proportions_towards_moves_the_share_asked(share):
    from flowmocap.fit.lift_refit import proportions_towards

    model, kmap = load_body_model("default", dtype=torch.float64), load_keypoint_map()
    at = torch.as_tensor(np.stack([TRUTH]))
    start = torch.zeros(1, 10, dtype=torch.float64)
    seen = _proportions(model, kmap, TRUTH_BETAS, at)
    new, own, got = proportions_towards(model, kmap, start, at, seen, share)
    np.testing.assert_allclose(own, _proportions(model, kmap, start, at), atol=1e-12)
    np.testing.assert_allclose(got, _proportions(model, kmap, new, at), atol=1e-12)
    goal = own + share * (seen - own)
    if share == 0:
        np.testing.assert_allclose(new.numpy(), start.numpy(), atol=1e-6)
    else:
        assert np.abs(got - goal).max() < 0.6 * np.abs(own - goal).max(), (own, goal, got)


@pytest.mark.parametrize("pixel_sigma,weighted", [(None, False), (3.0, False), (3.0, True)])
def test_refit_energy_value_closed_form(pixel_sigma, weighted):
    from flowmocap.vision.keypoint_map import load_keypoint_map

    model, kmap = load_body_model("default", dtype=torch.float64), load_keypoint_map()
    R = np.diag([1.0, -1.0, -1.0])
    t = np.array([0.1, 0.9, 4.0])
    cam = PinholeCamera(fx=600.0, fy=610.0, cx=320.0, cy=240.0, width=640, height=480, R=R, t=t)
    rng = np.random.default_rng(2)
    B = 3
    poses = torch.tensor(rng.normal(0, 0.2, (B, 72)))
    tracked = poses + torch.tensor(rng.normal(0, 0.05, (B, 72)))
    trans = torch.tensor(rng.normal(0, 0.1, (B, 3)))
    betas = torch.tensor(rng.normal(0, 0.5, (1, 10)))
    targets = torch.tensor(rng.normal(0, 0.5, (B, 13, 3)))
    use = torch.tensor([1.0, 0.0, 1.0])
    pixels = torch.tensor(rng.uniform(200, 400, (B, 24, 2)))
    pixel_use = torch.tensor((rng.random((B, 24)) > 0.4).astype(float)) if weighted else None
    sigma, reg = 0.02, 0.3
    e = refit_energy(model, kmap, poses, trans, betas, targets, use, tracked, sigma, reg,
                     cam, pixels, pixel_sigma, pixel_use)
    with torch.no_grad():
        kp, joints = keypoints13(model, kmap, poses, betas, trans)
    kp, joints = kp.numpy(), joints.numpy()
    u = use.numpy()
    want = (u * ((kp - targets.numpy()) ** 2).sum((1, 2))).sum() / sigma ** 2
    if pixel_sigma:
        pc = joints @ R.T + t
        px = np.stack([600.0 * pc[..., 0] / pc[..., 2] + 320.0, 610.0 * pc[..., 1] / pc[..., 2] + 240.0], -1)
        d2 = ((px - pixels.numpy()) ** 2).sum(-1)
        if weighted:
            d2 = d2 * pixel_use.numpy()
        want += (u * d2.sum(1)).sum() / pixel_sigma ** 2
    want += ((poses[:, 3:] - tracked[:, 3:]).numpy() ** 2).sum() / reg ** 2
    assert float(e) == pytest.approx(want, rel=1e-12)




def test_body_girth_is_each_vertex_distance_to_its_bone():
    from flowmocap.body import load_body_model
    from flowmocap.body.skeleton import PARENTS, children
    from flowmocap.fit.lift_refit import body_girth

    model = load_body_model("default", dtype=torch.float64)
    betas = torch.tensor(np.random.default_rng(3).normal(0, 0.8, (1, 10)))
    g = body_girth(model, betas).numpy()
    with torch.no_grad():
        v, jt = (x[0].numpy() for x in model.shaped(betas))
    W = model.weights.numpy()
    want = np.empty(len(v))
    for n in range(len(v)):
        j = int(np.argmax(W[n]))
        kids = children(j)
        a, b = jt[j], jt[kids[0] if kids else j]
        ab = b - a
        s = 0.0 if ab @ ab == 0 else min(max((v[n] - a) @ ab / (ab @ ab), 0.0), 1.0)
        want[n] = np.linalg.norm(v[n] - (a + s * ab))
    assert len(PARENTS) == jt.shape[0]
    np.testing.assert_allclose(g, want, rtol=1e-10, atol=1e-12)


def test_the_steps_after_tracking_run_on_the_settings_threads_whatever_the_process_has(tmp_path, monkeypatch):
    """A ``--workers`` process has fewer torch threads than a run alone; the steps after
    tracking run on ``torch_threads`` as the tracker does, so the two give the same result
    to the last bit (torch's reductions split their work by the thread count)."""
    import torch

    from flowmocap import pipeline
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.io.results import write_motion, write_run

    motion, track, _, _ = _setup(tmp_path, TRUTH)
    out = tmp_path / "result"
    out.mkdir()
    write_motion(out, motion)
    write_run(out, {"status": "finished", "events": []})
    seen = []

    def spy(name):
        def step(out, *args):
            seen.append((name, torch.get_num_threads()))
            return args[-2]  # the run info, as each step returns it
        return step

    monkeypatch.setattr(pipeline, "_lifter_refit", spy("lifter_refit"))
    monkeypatch.setattr(pipeline, "_stance_pending", lambda *a: True)
    monkeypatch.setattr(pipeline, "_stance_depth", spy("stance"))
    monkeypatch.setattr(pipeline, "_smooth_poses", spy("smooth"))
    before = torch.get_num_threads()
    try:
        for pool in (1, 2, 3):
            torch.set_num_threads(pool)
            seen.clear()
            pipeline._post_steps(out, track, load_body_model("default"), TrackerConfig(torch_threads=2),
                                 {"status": "finished"}, "auto", lambda s: None)
            assert seen == [("lifter_refit", 2), ("stance", 2), ("smooth", 2)]
            assert torch.get_num_threads() == pool  # the process's own pool back afterwards
    finally:
        torch.set_num_threads(before)


def test_the_detectors_3d_takes_its_share_of_the_rays_turn():
    """``_detector_cam``: MediaPipe's 3D of each frame turned from the axes of the ray through the
    detected hips into the camera's; with ``share`` that turn's angle times the share, so 0 leaves
    it in its own axes and 1 takes the whole turn (the default)."""
    from flowmocap.fit.lift_refit import _detector_cam

    rng = np.random.default_rng(0)
    idx = np.arange(2)
    world = rng.normal(size=(2, len(KEYPOINT_NAMES), 3))
    conf = np.ones((2, len(KEYPOINT_NAMES)))
    px = np.tile(np.array([[500.0, 100.0]]), (2, 13, 1))  # the hips far off the image's middle
    track = PersonTrack(np.zeros((2, len(KEYPOINT_NAMES), 2)), conf, np.ones(2, bool), [None, None], {}, world=world)
    full = _detector_cam(track, idx, CAM, px, None)
    none = _detector_cam(track, idx, CAM, px, None, share=0.0)
    half = _detector_cam(track, idx, CAM, px, None, share=0.5)
    R = CAM.ray_rotation(500.0, 100.0)
    np.testing.assert_allclose(full, none @ R.T, atol=1e-9)
    np.testing.assert_allclose(half, none @ CAM.ray_rotation(500.0, 100.0, 0.5).T, atol=1e-9)
    assert np.abs(half - full).max() > 0.01
