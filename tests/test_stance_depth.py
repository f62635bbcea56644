"""flowmocap.fit.smooth.stance_depth_shift / stance_depth_motion: a planted foot keeps its depth."""

import json

import numpy as np
import pytest

from flowmocap.errors import InputError
from flowmocap.fit import smooth as SD
from flowmocap.geometry.camera import PinholeCamera


def _planted(T=40, fps=60.0, wobble=None, seed=0):
    """A body whose left foot stands still in the world while its root moves sideways,
    seen by a camera at the origin looking down +z (world = camera axes), with each
    frame moved along the ray through its root by ``wobble (T,)`` metres of depth."""
    FOOT_JOINTS = SD.FOOT_JOINTS

    rng = np.random.default_rng(seed)
    cam = PinholeCamera(fx=600.0, fy=600.0, cx=320.0, cy=240.0, width=640, height=480, R=np.eye(3), t=np.zeros(3))
    J = np.zeros((T, 24, 3))
    J[:, :, 1] = np.linspace(-0.9, 0.8, 24)  # a 1.7 m column of joints
    J[:, :, 2] = 4.0
    J[:, :, 0] = np.linspace(-0.2, 0.2, T)[:, None]  # the body sways sideways ...
    left, right = FOOT_JOINTS
    J[:, left] = (0.1, 0.85, 4.1)  # ... over a planted left foot
    J[:, right] = np.c_[np.linspace(-0.5, 0.5, T), np.full(T, 0.7), np.full(T, 3.9)]  # the right foot swings
    true = J.copy()
    w = 0.05 * np.sin(np.arange(T) * 2 * np.pi / 17 + rng.uniform(0, 6)) if wobble is None else np.asarray(wobble, float)
    root = J[:, 0]
    J = J + (root * (w / root[:, 2])[:, None])[:, None, :]  # along the root's ray: depth + w, same root pixel
    j2d = np.asarray(cam.project(J.reshape(-1, 3))).reshape(T, 24, 2)
    return cam, J, j2d, true, w


def test_stance_depth_shift_makes_a_planted_foot_keep_its_depth():
    FOOT_JOINTS, stance_depth_shift = SD.FOOT_JOINTS, SD.stance_depth_shift

    cam, J, j2d, true, w = _planted()
    shift, stance = stance_depth_shift(J, j2d, cam.R, cam.t, 60.0, speed=0.3, min_s=0.1, window_s=0.0, share=1.0)
    left = FOOT_JOINTS[0]
    fixed = J + shift[:, None, :]
    assert stance.all()  # the left foot stands in every frame; the right one never does
    # the planted foot's depth is now constant: the wobble's median, as the correction says
    np.testing.assert_allclose(fixed[:, left, 2], true[:, left, 2] + np.median(w), atol=1e-9)
    # the whole body moved along the ray through its root: the root keeps its pixel
    np.testing.assert_allclose(cam.project(fixed[:, 0]), cam.project(J[:, 0]), atol=1e-9)
    np.testing.assert_allclose(fixed[:, 0, 2] - J[:, 0, 2], np.median(w) - w, atol=1e-9)
    # half the share moves half as far; smoothing averages the correction over the window
    half, _ = stance_depth_shift(J, j2d, cam.R, cam.t, 60.0, speed=0.3, min_s=0.1, window_s=0.0, share=0.5)
    np.testing.assert_allclose(half, 0.5 * shift, atol=1e-12)
    smooth, _ = stance_depth_shift(J, j2d, cam.R, cam.t, 60.0, speed=0.3, min_s=0.1, window_s=5 / 60, share=1.0)
    dz = np.median(w) - w
    want = np.convolve(np.pad(dz, 2, mode="edge"), np.ones(5) / 5, mode="valid")
    np.testing.assert_allclose(smooth[:, 2], want, atol=1e-9)  # world = camera axes: z is the depth


def test_a_planted_foot_seen_by_a_zooming_camera_keeps_the_worlds_depth():
    """The planted foot of a still body seen by a camera zooming out from 1 to 0.9 of its focal
    length: a tracker that keeps the first focal length puts every frame at its depth / zoom, so
    the foot's tracked depth grows. With the zooms the correction keeps the foot's depth times
    the zoom (the world's, flowmocap.export.motion.zoomed_depth) where it is; without them it
    would hold the tracked depth and move the foot 11 % in the world."""
    FOOT_JOINTS, stance_depth_shift = SD.FOOT_JOINTS, SD.stance_depth_shift

    cam, _, _, true, _ = _planted(wobble=np.zeros(40))
    left = FOOT_JOINTS[0]
    zooms = np.linspace(1.0, 0.9, 40)
    J = true.copy()
    J[:, :, 2] /= zooms[:, None]  # where the tracker puts it
    j2d = np.asarray(cam.project(J.reshape(-1, 3))).reshape(40, 24, 2)
    shift, stance = stance_depth_shift(J, j2d, cam.R, cam.t, 60.0, speed=0.3, min_s=0.1, window_s=0.0, share=1.0,
                                       zooms=zooms)
    assert stance.all()
    world = (J[:, left, 2] + shift[:, 2]) * zooms
    np.testing.assert_allclose(world, np.median(true[:, left, 2]), atol=0.02)  # the foot's depth, 4.1 m: kept
    assert np.ptp(world) < 0.01
    blind, _ = stance_depth_shift(J, j2d, cam.R, cam.t, 60.0, speed=0.3, min_s=0.1, window_s=0.0, share=1.0)
    assert np.ptp((J[:, left, 2] + blind[:, 2]) * zooms) > 0.4  # the tracked depth held: 11 % of it in the world
    with pytest.raises(InputError, match="zooms must be"):
        stance_depth_shift(J, j2d, cam.R, cam.t, 60.0, zooms=zooms[:-1])


def test_stance_depth_shift_leaves_moving_feet_short_stances_and_other_runs_alone():
    FOOT_JOINTS, stance_depth_shift = SD.FOOT_JOINTS, SD.stance_depth_shift

    cam, J, j2d, _, _ = _planted()
    left = FOOT_JOINTS[0]
    moving = J.copy()
    moving[:, left, 0] += np.linspace(0, 1.5, len(J))  # the left foot walks too: no stance anywhere
    m2d = np.asarray(cam.project(moving.reshape(-1, 3))).reshape(j2d.shape)
    shift, stance = stance_depth_shift(moving, m2d, cam.R, cam.t, 60.0, speed=0.3, min_s=0.1)
    assert not stance.any() and not shift.any()
    # a stance shorter than min_s does not count
    shift, stance = stance_depth_shift(J, j2d, cam.R, cam.t, 60.0, speed=0.3, min_s=1.0)
    assert not stance.any() and not shift.any()
    # a break at frame 20 starts a new run: each half is corrected to its own median
    shift, _ = stance_depth_shift(J, j2d, cam.R, cam.t, 60.0, speed=0.3, min_s=0.1, window_s=0.0, share=1.0,
                                  breaks=[20])
    fixed = J[:, left, 2] + shift[:, 2]
    assert np.ptp(fixed[:20]) < 1e-9 and np.ptp(fixed[20:]) < 1e-9
    with pytest.raises(InputError, match="joints"):
        stance_depth_shift(J[:, :5], j2d[:, :5], cam.R, cam.t, 60.0)
    with pytest.raises(InputError, match="share"):
        stance_depth_shift(J, j2d, cam.R, cam.t, 60.0, share=2.0)


def test_stance_depth_motion_moves_trans_and_joints_together_and_projects_again():
    cam, J, j2d, _, _ = _planted()
    T = len(J)
    motion = {"poses": np.zeros((T, 72), np.float32), "trans": J[:, 0].astype(np.float32),
              "joints3d": J.astype(np.float32), "joints2d": j2d.astype(np.float32), "fps": 60.0,
              "camera": json.dumps(cam.to_dict()), "frame_index": np.arange(T), "betas": np.zeros(10)}
    same, info = SD.stance_depth_motion(motion, 0.0)
    assert info["frames_in_stance"] == 0 and all(same[k] is motion[k] for k in motion)
    out, info = SD.stance_depth_motion(motion, 0.5, speed=0.3, min_s=0.1, window_s=0.0)
    shift, stance = SD.stance_depth_shift(J, j2d, cam.R, cam.t, 60.0, speed=0.3, min_s=0.1, window_s=0.0, share=0.5)
    assert info["frames_in_stance"] == int(stance.sum()) == T and info["mean_shift_mm"] > 1.0
    np.testing.assert_allclose(out["trans"], motion["trans"] + shift, atol=1e-5)
    np.testing.assert_allclose(out["joints3d"], motion["joints3d"] + shift[:, None], atol=1e-5)
    np.testing.assert_allclose(out["joints2d"], np.asarray(cam.project(out["joints3d"].reshape(-1, 3))).reshape(T, 24, 2),
                               atol=1e-3)
    np.testing.assert_array_equal(out["poses"], motion["poses"])


def test_pipeline_applies_the_stance_step_once_before_the_pose_smoothing(tmp_path):
    from flowmocap import pipeline
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.io.results import read_result, write_motion, write_run

    cam, J, j2d, _, _ = _planted()
    T = len(J)
    motion = {"poses": np.zeros((T, 72), np.float32), "trans": J[:, 0].astype(np.float32),
              "joints3d": J.astype(np.float32), "joints2d": j2d.astype(np.float32), "fps": np.float64(60.0),
              "camera": json.dumps(cam.to_dict()), "frame_index": np.arange(T), "betas": np.zeros(10, np.float32)}
    out = tmp_path / "result"
    out.mkdir()
    write_motion(out, motion)
    events = [{"frame": 20, "event": "re-initialised"}]
    write_run(out, {"status": "finished", "events": events})
    cfg = TrackerConfig(stance_speed=0.3, stance_min_s=0.1)
    run = {"status": "finished", "events": events}
    assert pipeline._stance_pending(out, cfg, run)
    assert not pipeline._stance_pending(out, TrackerConfig(stance_depth_share=0.0), run)
    said = []
    run = pipeline._stance_depth(out, cfg, run, said.append)
    got, info = read_result(out)
    want, _ = SD.stance_depth_motion(motion, cfg.stance_depth_share, speed=0.3, min_s=0.1,
                                     window_s=cfg.stance_window_s, breaks=[20])
    np.testing.assert_allclose(got["trans"], want["trans"], atol=1e-6)
    np.testing.assert_allclose(got["joints3d"], want["joints3d"], atol=1e-6)
    assert info["stance_depth"]["frames_in_stance"] == T and "kept its depth" in said[0]
    assert not pipeline._stance_pending(out, cfg, run)  # done once
    # a run whose motion was already smoothed last (finished before the step existed) is left alone
    write_motion(out, {**motion, "poses_unsmoothed": motion["poses"]})
    assert not pipeline._stance_pending(out, cfg, {"status": "finished", "events": []})
