"""Offline smoothing on SO(3) (flowmocap.fit.smooth) against closed forms and scipy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import savgol_filter
from scipy.spatial.transform import Rotation

from flowmocap.errors import InputError
from flowmocap.fit.smooth import (DEPTH_ORDER, DEPTH_WINDOW_S, depth_smoothed_motion, savgol_weights,
                                  seam_blend, smooth_motion, smooth_root_depth, smooth_rotations,
                                  smooth_translations, window_frames)
from flowmocap.geometry.camera import PinholeCamera


@pytest.mark.parametrize("window,order", [(5, 2), (9, 2), (7, 1), (11, 3), (9, 0)])
def test_weights_are_scipys_savgol_filter_ends_included(window, order):
    x = np.random.default_rng(window).normal(size=(31, 4))
    np.testing.assert_allclose(smooth_translations(x, window, order),
                               savgol_filter(x, window, order, axis=0, mode="interp"), atol=1e-12)
    _, w = savgol_weights(31, window, order)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-12)


def test_rotations_about_one_axis_are_filtered_like_their_angle():
    """About a fixed axis, rotations compose like their angles: the SO(3) filter must give
    exactly scipy's filter of the angle."""
    rng = np.random.default_rng(1)
    axis = np.array([0.3, -0.8, 0.5])
    axis /= np.linalg.norm(axis)
    angle = np.cumsum(rng.normal(0, 0.15, 40)) + 0.5
    out = smooth_rotations(angle[:, None] * axis, 9, 2)
    expect = Rotation.from_rotvec(savgol_filter(angle, 9, 2, mode="interp")[:, None] * axis)
    assert (Rotation.from_rotvec(out).inv() * expect).magnitude().max() < 1e-9


def test_constant_angular_velocity_is_kept_and_the_frame_does_not_matter():
    rng = np.random.default_rng(2)
    R0 = Rotation.random(3, random_state=3)
    omega = rng.normal(0, 0.08, (3, 3))
    t = np.arange(30)
    R = [R0[j] * Rotation.from_rotvec(t[:, None] * omega[j]) for j in range(3)]
    rv = np.stack([r.as_rotvec() for r in R], 1)  # (T, 3, 3)
    out = smooth_rotations(rv, 7, 2)
    for j in range(3):
        assert (Rotation.from_rotvec(out[:, j]).inv() * R[j]).magnitude().max() < 1e-9
    noisy = (Rotation.from_rotvec(rv.reshape(-1, 3)) * Rotation.from_rotvec(rng.normal(0, 0.05, (90, 3))))
    noisy = noisy.as_rotvec().reshape(30, 3, 3)
    W = Rotation.random(random_state=9)
    a = Rotation.from_rotvec(smooth_rotations(noisy, 7, 2).reshape(-1, 3))
    b = Rotation.from_rotvec(smooth_rotations((W * Rotation.from_rotvec(noisy.reshape(-1, 3))).as_rotvec()
                                              .reshape(30, 3, 3), 7, 2).reshape(-1, 3))
    assert ((W * a).inv() * b).magnitude().max() < 1e-9


def test_jitter_shrinks_as_the_savgol_variance_ratio_predicts():
    """White rotation noise of std s per axis around a fixed rotation: in the interior the
    filter leaves std s * sqrt(sum w^2) (the linear filter's noise gain; exact to first order)."""
    rng = np.random.default_rng(4)
    T, window, order, s = 4000, 9, 2, 0.02
    base = Rotation.from_rotvec([0.4, -1.0, 0.2])
    noise = rng.normal(0, s, (T, 3))
    out = Rotation.from_rotvec(smooth_rotations((base * Rotation.from_rotvec(noise)).as_rotvec(), window, order))
    resid = (base.inv() * out).as_rotvec()[window:-window]
    _, w = savgol_weights(T, window, order)
    gain = np.sqrt((w[T // 2] ** 2).sum())
    assert resid.std() == pytest.approx(s * gain, rel=0.05)
    assert gain < 0.65


def test_smooth_motion_shapes_windows_and_errors():
    rng = np.random.default_rng(5)
    poses = rng.normal(0, 0.3, (20, 72))
    trans = rng.normal(0, 0.1, (20, 3))
    p, t = smooth_motion(poses, trans, fps=30.0, window_s=0.2)
    assert p.shape == (20, 72) and t.shape == (20, 3)
    np.testing.assert_allclose(t, savgol_filter(trans, 7, 2, axis=0, mode="interp"), atol=1e-12)
    assert window_frames(0.2, 30.0) == 7 and window_frames(0.2, 60.0) == 13 and window_frames(0.01, 30.0) == 5
    # shorter than the window: the window shrinks; at most `order` frames: unchanged
    p3, _ = smooth_motion(poses[:2], trans[:2], fps=30.0)
    np.testing.assert_allclose(p3, poses[:2])
    p5, _ = smooth_motion(poses[:5], trans[:5], fps=30.0, window_s=1.0)
    assert np.abs(p5 - poses[:5]).max() > 1e-3
    with pytest.raises(InputError, match="seconds"):
        smooth_motion(poses, trans, 30.0, window_s=0.0)
    # a window of 1e308 s (export --smooth 1e308) overflowed seconds x fps to infinity: now the whole clip
    huge, _ = smooth_motion(poses, trans, 30.0, window_s=1e308)
    np.testing.assert_allclose(huge, smooth_motion(poses, trans, 30.0, window_s=1e6)[0])
    with pytest.raises(InputError, match=r"\(T, 72\)"):
        smooth_motion(poses[:, :70], trans, 30.0)
    with pytest.raises(InputError, match="NaN"):
        smooth_rotations(np.full((10, 3), np.nan), 5)


def test_runs_of_consecutive_frames_are_smoothed_apart():
    rng = np.random.default_rng(6)
    poses = rng.normal(0, 0.3, (30, 72))
    trans = rng.normal(0, 0.1, (30, 3))
    index = np.r_[np.arange(0, 18), np.arange(40, 52)]  # a gap after row 17
    p, t = smooth_motion(poses, trans, 30.0, frame_index=index)
    for a, b in ((0, 18), (18, 30)):
        pa, ta = smooth_motion(poses[a:b], trans[a:b], 30.0)
        np.testing.assert_allclose(p[a:b], pa, atol=1e-12)
        np.testing.assert_allclose(t[a:b], ta, atol=1e-12)
    whole, _ = smooth_motion(poses, trans, 30.0)
    assert np.abs(whole[15:21] - p[15:21]).max() > 1e-3  # without the index it reaches across
    with pytest.raises(InputError, match="frame_index"):
        smooth_motion(poses, trans, 30.0, frame_index=index[:5])


def test_rotations_of_a_long_motion_are_smoothed_a_few_joints_at_a_time_alike(monkeypatch):
    import flowmocap.fit.smooth as S

    rng = np.random.default_rng(11)
    r = rng.normal(0, 0.4, (40, 24, 3))
    whole = smooth_rotations(r, 9)
    monkeypatch.setattr(S, "MAX_ROTATIONS", 40 * 9 * 5)  # blocks of 5 joints (the last of 4)
    np.testing.assert_allclose(smooth_rotations(r, 9), whole, atol=1e-12)
    monkeypatch.setattr(S, "MAX_ROTATIONS", 1)  # one joint at a time
    np.testing.assert_allclose(smooth_rotations(r, 9), whole, atol=1e-12)
    np.testing.assert_allclose(smooth_rotations(r[:, 0], 9), whole[:, 0], atol=1e-12)


def test_breaks_start_a_new_run():
    rng = np.random.default_rng(8)
    poses = rng.normal(0, 0.3, (30, 72))
    trans = rng.normal(0, 0.1, (30, 3))
    index = np.arange(100, 130)
    p, t = smooth_motion(poses, trans, 30.0, frame_index=index, breaks=[112])  # row 12 starts a run
    for a, b in ((0, 12), (12, 30)):
        pa, ta = smooth_motion(poses[a:b], trans[a:b], 30.0)
        np.testing.assert_allclose(p[a:b], pa, atol=1e-12)
        np.testing.assert_allclose(t[a:b], ta, atol=1e-12)
    same, _ = smooth_motion(poses, trans, 30.0, frame_index=index, breaks=[5, 500])  # frames not in the motion
    np.testing.assert_allclose(same, smooth_motion(poses, trans, 30.0)[0], atol=1e-12)
    with pytest.raises(InputError, match="NaN"):
        smooth_motion(np.where(np.arange(30)[:, None] == 3, np.nan, poses), trans, 30.0)


def _stepped_motion(T=30, seam=20, seed=11):
    """Every joint turning and the body moving at constant velocity, and from row ``seam`` on
    a jump: each joint's rotation turned by one fixed rotation ``D`` more, the translation
    moved by ``d`` more. Returns ``poses (T, 72)``, ``trans (T, 3)``, ``D (24, 3)``, ``d (3,)``."""
    rng = np.random.default_rng(seed)
    base = Rotation.from_rotvec(rng.normal(0, 0.4, (24, 3)))
    omega = rng.normal(0, 0.03, (24, 3))
    D, d = rng.normal(0, 0.3, (24, 3)), np.array([0.1, -0.05, 0.4])
    poses, trans = np.empty((T, 72)), np.empty((T, 3))
    for t in range(T):
        R = Rotation.from_rotvec(t * omega) * base
        if t >= seam:
            R = Rotation.from_rotvec(D) * R
        poses[t] = R.as_rotvec().reshape(72)
        trans[t] = (0.2, 0.9, 4.0) + t * np.array([0.01, 0.0, -0.02]) + (d if t >= seam else 0)
    return poses, trans, D, d


def test_seam_blend_spreads_the_jump_over_the_frames_before_the_seam():
    """Closed form: at constant velocity the jump is exactly ``D`` and ``d``, and frame ``t``
    of the ``k`` before the seam takes the smoothstep share ``w_t`` of it; the frames before
    them and from the seam on stay as they were, and the step becomes a ramp."""
    poses, trans, D, d = _stepped_motion()
    p, t, eased = seam_blend(poses, trans, np.arange(100, 130), [120], 30.0, 0.2)  # k = 6 frames, rows 14-19
    assert eased == [120]
    np.testing.assert_array_equal(p[:14], poses[:14])
    np.testing.assert_array_equal(p[20:], poses[20:])
    np.testing.assert_array_equal(t[:14], trans[:14])
    np.testing.assert_array_equal(t[20:], trans[20:])
    for row in range(14, 20):
        x = (row - 14 + 1) / 7
        w = x * x * (3 - 2 * x)
        want = Rotation.from_rotvec(w * D) * Rotation.from_rotvec(poses[row].reshape(24, 3))
        got = Rotation.from_rotvec(p[row].reshape(24, 3))
        assert (got.inv() * want).magnitude().max() < 1e-9
        np.testing.assert_allclose(t[row], trans[row] + w * d, atol=1e-12)
    # the step of |d| between rows 19 and 20 is gone; no second difference is larger than the step's share
    acc = np.linalg.norm(t[2:] - 2 * t[1:-1] + t[:-2], axis=1)
    acc0 = np.linalg.norm(trans[2:] - 2 * trans[1:-1] + trans[:-2], axis=1)
    assert acc0.max() > 0.99 * np.linalg.norm(d) and acc.max() < 0.35 * np.linalg.norm(d)
    assert np.linalg.norm(t[20] - t[19]) < 0.25 * np.linalg.norm(d)


def test_seam_blend_stops_at_earlier_seams_and_gaps_and_eases_only_what_it_is_asked():
    poses, trans, _, _ = _stepped_motion()
    # an earlier seam 3 rows before: only rows 17-19 eased
    p, _, eased = seam_blend(poses, trans, None, [17, 20], 30.0, 0.2, ease=[20])
    assert eased == [20]
    np.testing.assert_array_equal(p[:17], poses[:17])
    assert np.abs(p[17:20] - poses[17:20]).max() > 1e-3
    # a gap in the frame numbers before row 17: the same rows
    index = np.r_[np.arange(17), np.arange(30, 43)]
    q, _, _ = seam_blend(poses, trans, index, [index[20]], 30.0, 0.2)
    np.testing.assert_allclose(q, p, atol=1e-12)
    # a seam with fewer than two frames before it, a seam not in the motion, one not asked for: untouched
    r, u, eased = seam_blend(poses, trans, None, [1, 500, 20], 30.0, 0.2, ease=[1, 500])
    assert eased == []
    np.testing.assert_array_equal(r, poses)
    np.testing.assert_array_equal(u, trans)
    with pytest.raises(InputError, match="seconds"):
        seam_blend(poses, trans, None, [20], 30.0, 0.0)
    with pytest.raises(InputError, match="shape"):
        seam_blend(poses[:, :71], trans, None, [20], 30.0, 0.2)
    with pytest.raises(InputError, match="frame_index"):
        seam_blend(poses, trans, np.arange(5), [20], 30.0, 0.2)


def _body_motion(body, cam, poses, trans):
    """A result's motion arrays for ``poses (T, 72)`` and ``trans (T, 3)`` at 30 fps."""
    import json

    import torch

    T = len(poses)
    dt = body.v_template.dtype
    with torch.no_grad():
        j = body(betas=torch.zeros(1, 10, dtype=dt), pose=torch.as_tensor(poses, dtype=dt),
                 trans=torch.as_tensor(trans, dtype=dt)).joints.double().numpy()
    return {"poses": poses.astype(np.float32), "trans": trans.astype(np.float32), "betas": np.zeros(10, np.float32),
            "joints3d": j.astype(np.float32), "joints2d": cam.project(j.reshape(-1, 3)).reshape(T, 24, 2).astype(np.float32),
            "fps": np.array(30.0), "camera": np.array(json.dumps(cam.to_dict())), "frame_index": np.arange(T),
            "energies": np.zeros((T, 2))}


def test_pipeline_smooths_the_finished_motion_once_restarting_at_reinitialisations(tmp_path):
    from flowmocap import pipeline
    from flowmocap.body import load_body_model
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.fit.smooth import pose_smoothed_motion
    from flowmocap.io.results import read_result, write_motion, write_run

    body = load_body_model("default")
    rng = np.random.default_rng(10)
    T = 20
    motion = _body_motion(body, _camera(), rng.normal(0, 0.1, (T, 72)), rng.normal(0, 0.05, (T, 3)) + (0, 0, 1))
    out = tmp_path / "result"
    out.mkdir()
    write_motion(out, motion)
    run = {"status": "finished", "events": [{"event": "re-initialised", "frame": 8}]}
    write_run(out, run)
    said = []
    cfg = TrackerConfig()
    run = pipeline._smooth_poses(out, body, cfg, run, said.append)
    got, info = read_result(out)
    want, _ = pose_smoothed_motion(motion, body, cfg.pose_smoothing_s, breaks=[8])
    np.testing.assert_allclose(got["poses"], want["poses"], atol=1e-6)
    np.testing.assert_allclose(got["trans"], want["trans"], atol=1e-6)
    whole, _ = pose_smoothed_motion(motion, body, cfg.pose_smoothing_s)
    assert np.abs(got["trans"] - whole["trans"]).max() > 1e-4  # the re-initialisation was read from run.json
    np.testing.assert_allclose(got["joints3d"], want["joints3d"], atol=1e-5)
    np.testing.assert_array_equal(got["poses_unsmoothed"], motion["poses"])
    assert info["pose_smoothing"]["window_s"] == cfg.pose_smoothing_s and run["pose_smoothing"]["mean_move_mm"] > 0
    assert "smoothed the motion" in said[0]
    again = pipeline._smooth_poses(out, body, cfg, run, said.append)  # a resumed, finished run: not twice
    np.testing.assert_array_equal(read_result(out)[0]["poses"], got["poses"])
    assert again is run and len(said) == 1


def test_pose_smoothed_motion_recomputes_joints_and_keeps_the_motion_before():
    """The poses and translation are :func:`smooth_motion`'s, the joints the body model's
    of them and their projections; a motion that is a quadratic in time on SO(3) about one
    axis per joint (which degree 2 keeps) barely moves, jitter on it is taken out."""
    from flowmocap.body import load_body_model
    from flowmocap.fit.smooth import pose_smoothed_motion

    body = load_body_model("default")
    cam = _camera()
    rng = np.random.default_rng(9)
    T = 24
    axes = rng.normal(0, 1, (24, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    s = np.arange(T) / 30.0
    angle = 0.2 + 0.8 * s[:, None] - 0.5 * s[:, None] ** 2  # (T, 1) radians, the same curve for each joint
    clean = (angle[:, :, None] * axes[None]).reshape(T, 72)
    trans = np.stack([0.3 * s, 0.1 + 0 * s, 0.2 * s ** 2], 1)

    def motion_of(poses, tr=trans):
        return _body_motion(body, cam, poses, tr)

    kept, info = pose_smoothed_motion(motion_of(clean), body)
    np.testing.assert_allclose(kept["poses"], clean, atol=1e-4)
    assert info["mean_move_mm"] < 0.1 and info["window_s"] == 0.3 and info["order"] == 2

    noisy = motion_of(clean + rng.normal(0, 0.05, clean.shape), trans + rng.normal(0, 0.01, trans.shape))
    out, info = pose_smoothed_motion(noisy, body)
    p, t = smooth_motion(noisy["poses"], noisy["trans"], 30.0)
    np.testing.assert_allclose(out["poses"], p, atol=1e-6)
    np.testing.assert_allclose(out["trans"], t, atol=1e-6)
    np.testing.assert_array_equal(out["poses_unsmoothed"], noisy["poses"])
    np.testing.assert_array_equal(out["trans_unsmoothed"], noisy["trans"])
    want = motion_of(p, t)
    np.testing.assert_allclose(out["joints3d"], want["joints3d"], atol=1e-5)
    np.testing.assert_allclose(out["joints2d"], cam.project(out["joints3d"].reshape(-1, 3)).reshape(T, 24, 2),
                               atol=1e-3)
    assert np.abs(out["poses"] - clean).mean() < 0.6 * np.abs(noisy["poses"] - clean).mean()
    assert info["mean_move_mm"] > 1 and info["mean_move_px"] > 0.1
    assert out["poses"].dtype == np.float32 and out["energies"] is noisy["energies"]
    split, _ = pose_smoothed_motion(noisy, body, breaks=[10])  # a re-initialisation: both start again
    before = smooth_motion(noisy["poses"][:10], noisy["trans"][:10], 30.0)
    np.testing.assert_allclose(split["poses"][:10], before[0], atol=1e-6)
    np.testing.assert_allclose(split["trans"][:10], before[1], atol=1e-6)


def _camera():
    R = Rotation.from_euler("xyz", [0.2, -0.7, 0.1]).as_matrix()
    return PinholeCamera(fx=500.0, fy=500.0, cx=160.0, cy=120.0, width=320, height=240, R=R, t=[0.1, -0.2, 4.0])


def _roots(cam, dist, pixels):
    """World points at camera distances ``dist (T,)`` on the rays through ``pixels (T, 2)``."""
    ray = np.stack([(pixels[:, 0] - cam.cx) / cam.fx, (pixels[:, 1] - cam.cy) / cam.fy, np.ones(len(dist))], 1)
    c = ray / np.linalg.norm(ray, axis=1, keepdims=True) * dist[:, None]
    R, t = np.asarray(cam.R, np.float64), np.asarray(cam.t, np.float64)
    return (c - t) @ R  # camera -> world


def test_root_depth_follows_the_savgol_filter_of_its_distance_and_keeps_its_pixel():
    """The root moves along its own camera ray (same pixel) to the Savitzky-Golay filter of
    its distance from the camera; a distance quadratic in time is kept exactly by degree 2,
    a straight line by the default degree."""
    cam = _camera()
    rng = np.random.default_rng(3)
    T, fps = 150, 60.0
    pixels = np.stack([100 + 0.5 * np.arange(T), 120 + 10 * np.sin(np.arange(T) / 9)], 1)
    tt = np.arange(T) / fps
    smooth_dist = 4.0 - 0.4 * tt + 0.05 * tt ** 2
    noisy = smooth_dist + rng.normal(0, 0.08, T)
    root = _roots(cam, noisy, pixels)
    shift = smooth_root_depth(root, cam.R, cam.t, fps, window_s=2.0, order=2)
    moved = root + shift
    R, t = np.asarray(cam.R, np.float64), np.asarray(cam.t, np.float64)
    dist = np.linalg.norm(moved @ R.T + t, axis=1)
    np.testing.assert_allclose(dist, savgol_filter(noisy, window_frames(2.0, fps, 2), 2, mode="interp"), atol=1e-9)
    np.testing.assert_allclose(cam.project(moved), cam.project(root), atol=1e-3)  # float32 projection
    assert np.abs(dist - smooth_dist).std() < 0.4 * np.abs(noisy - smooth_dist).std()
    exact = _roots(cam, smooth_dist, pixels)
    np.testing.assert_allclose(smooth_root_depth(exact, cam.R, cam.t, fps, window_s=2.0, order=2), 0.0, atol=1e-9)
    line = _roots(cam, 4.0 - 0.4 * tt, pixels)
    np.testing.assert_allclose(smooth_root_depth(line, cam.R, cam.t, fps), 0.0, atol=1e-9)
    d = np.linalg.norm((root + smooth_root_depth(root, cam.R, cam.t, fps)) @ R.T + t, axis=1)
    window = window_frames(DEPTH_WINDOW_S, fps, DEPTH_ORDER)
    np.testing.assert_allclose(d, savgol_filter(noisy, window, DEPTH_ORDER, mode="interp"), atol=1e-9)


def test_root_depth_runs_gaps_non_finite_frames_and_errors():
    cam = _camera()
    rng = np.random.default_rng(4)
    T = 40
    pixels = np.full((T, 2), 150.0)
    noisy = 4.0 + rng.normal(0, 0.05, T)
    root = _roots(cam, noisy, pixels)
    index = np.r_[np.arange(20), np.arange(30, 50)]  # a gap of 10 input frames after the 20th row
    whole = smooth_root_depth(root, cam.R, cam.t, 30.0, window_s=0.5, frame_index=index)
    parts = [smooth_root_depth(root[a:b], cam.R, cam.t, 30.0, window_s=0.5) for a, b in ((0, 20), (20, 40))]
    np.testing.assert_allclose(whole, np.concatenate(parts), atol=1e-12)
    jumped = smooth_root_depth(root, cam.R, cam.t, 30.0, window_s=0.5, breaks=[15])  # a refit at row 15
    parts = [smooth_root_depth(root[a:b], cam.R, cam.t, 30.0, window_s=0.5) for a, b in ((0, 15), (15, 40))]
    np.testing.assert_allclose(jumped, np.concatenate(parts), atol=1e-12)
    bad = root.copy()
    bad[10] = np.nan
    shift = smooth_root_depth(bad, cam.R, cam.t, 30.0, window_s=0.5)
    assert np.all(shift[10] == 0) and np.isfinite(shift).all()
    np.testing.assert_allclose(shift[11:], smooth_root_depth(root[11:], cam.R, cam.t, 30.0, window_s=0.5),
                               atol=1e-12)
    np.testing.assert_allclose(smooth_root_depth(root[:2], cam.R, cam.t, 30.0), 0.0)  # too short: unchanged
    with pytest.raises(InputError):
        smooth_root_depth(root[:, :2], cam.R, cam.t, 30.0)
    with pytest.raises(InputError):
        smooth_root_depth(root, cam.R, cam.t, 30.0, window_s=-1.0)
    with pytest.raises(InputError):
        smooth_root_depth(root, cam.R, cam.t, 30.0, frame_index=np.arange(3))


def test_depth_smoothed_motion_moves_trans_and_joints_together_and_projects_again():
    import json

    cam = _camera()
    rng = np.random.default_rng(5)
    T = 30
    root = _roots(cam, 4.0 + rng.normal(0, 0.05, T), np.full((T, 2), 140.0) + rng.normal(0, 3, (T, 2)))
    joints = root[:, None, :] + rng.normal(0, 0.3, (1, 24, 3))
    joints[:, 0] = root
    motion = {"poses": rng.normal(0, 0.2, (T, 72)).astype(np.float32),
              "trans": (root + 0.1).astype(np.float32), "joints3d": joints.astype(np.float32),
              "joints2d": cam.project(joints.reshape(-1, 3)).reshape(T, 24, 2).astype(np.float32),
              "fps": np.array(30.0), "camera": np.array(json.dumps(cam.to_dict())),
              "frame_index": np.arange(T), "energies": np.zeros((T, 2))}
    out = depth_smoothed_motion(motion)
    shift = smooth_root_depth(joints[:, 0], cam.R, cam.t, 30.0)
    np.testing.assert_allclose(out["trans"] - out["trans_tracked"], shift, atol=1e-6)
    np.testing.assert_array_equal(out["trans_tracked"], motion["trans"])
    np.testing.assert_allclose(out["joints3d"] - motion["joints3d"], np.repeat(shift[:, None], 24, 1), atol=1e-6)
    np.testing.assert_allclose(out["joints2d"], cam.project(out["joints3d"].reshape(-1, 3)).reshape(T, 24, 2),
                               atol=1e-3)
    assert np.abs(shift).max() > 1e-3 and out["poses"] is motion["poses"] and out["energies"] is motion["energies"]
    assert out["trans"].dtype == np.float32 and out["joints2d"].dtype == np.float32
    same = depth_smoothed_motion(motion, window_s=0)
    assert "trans_tracked" not in same and same["trans"] is motion["trans"]


def test_post_pending_says_which_steps_after_tracking_a_finished_run_lacks(tmp_path):
    from flowmocap import pipeline
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.io.results import write_motion, write_run

    out = tmp_path / "r"
    out.mkdir()
    motion = {"poses": np.zeros((3, 72), np.float32), "trans": np.zeros((3, 3), np.float32)}
    write_motion(out, motion)
    write_run(out, {"status": "finished", "events": []})
    cfg, off = TrackerConfig(), TrackerConfig(pose_smoothing_s=0.0, stance_depth_share=0.0)
    stance = TrackerConfig(pose_smoothing_s=0.0)  # the stance step alone
    ended = {"status": "finished", "body": {"stature_m": 1.7}}  # what a run whose steps all ended records
    assert pipeline._post_pending(out, stance, "auto", ended)  # not done
    assert not pipeline._post_pending(out, stance, "auto", {**ended, "stance_depth": {"frames_in_stance": 0}})
    assert pipeline._post_pending(out, cfg, "auto", ended)  # not smoothed
    assert not pipeline._post_pending(out, off, "auto", ended)  # no detections: no refit to do either
    (out / "detections").mkdir()
    (out / "detections" / "keypoints.npz").write_bytes(b"")
    assert pipeline._post_pending(out, off, "auto", ended)  # detections and no refit yet
    assert not pipeline._post_pending(out, off, "off", ended)  # the refit needs the 3D cues on
    assert not pipeline._post_pending(out, off, "auto", {**ended, "lifter_refit": {"skipped": "too few frames"}})
    write_motion(out, {**motion, "poses_tracked": motion["poses"], "poses_unsmoothed": motion["poses"]})
    assert not pipeline._post_pending(out, cfg, "auto", ended)  # both done
    # a run stopped before the end of its steps: its status, its body, or a record motion.npz
    # holds and run.json lost (a stop between the two files)
    assert pipeline._post_pending(out, cfg, "auto", {**ended, "status": "finishing"})
    assert pipeline._post_pending(out, cfg, "auto", {"status": "finished"})
    write_motion(out, {**motion, "poses_tracked": motion["poses"], "poses_unsmoothed": motion["poses"],
                       "post_steps": np.array('{"pose_smoothing": {"seconds": 0.1}}')})
    assert pipeline._post_pending(out, cfg, "auto", ended)
    assert not pipeline._post_pending(out, cfg, "auto", {**ended, "pose_smoothing": {"seconds": 0.1}})


def _finishing_result(out):
    from flowmocap.io.results import write_motion, write_run

    out.mkdir()
    motion = {"poses": np.zeros((3, 72), np.float32), "trans": np.tile(np.float32([0, 0, 3]), (3, 1))}
    write_motion(out, motion)
    run = {"status": "finishing", "tracked": True, "events": []}
    write_run(out, run)
    return run


def test_a_step_after_tracking_stopped_between_its_two_files_is_not_done_twice(tmp_path, monkeypatch):
    """A kill after a step's motion.npz and before its run.json used to leave the step
    unrecorded: --resume applied the stance step a second time (22 mm off the uninterrupted
    run), and the refit's and smoothing's records were lost for good."""
    from flowmocap import pipeline
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.io.results import read_result

    out = tmp_path / "r"
    run = _finishing_result(out)

    def killed(*a, **k):
        raise KeyboardInterrupt

    step = lambda m: ({**m, "trans": m["trans"] + np.float32([0, 0, 0.02])}, {"frames_in_stance": 3})  # noqa: E731
    monkeypatch.setattr(pipeline, "write_run", killed)
    with pytest.raises(KeyboardInterrupt):
        pipeline._post_step(out, run, "stance_depth", step, lambda _m: None, lambda _i: "")
    monkeypatch.undo()
    motion, on_disk = read_result(out)
    assert "stance_depth" not in on_disk  # run.json never heard of it ...
    assert pipeline._steps_done(motion)["stance_depth"]["frames_in_stance"] == 3  # ... motion.npz did
    assert on_disk["status"] == "interrupted"  # "finishing" and no process holds the folder
    assert not pipeline._stance_pending(out, TrackerConfig(pose_smoothing_s=0.0), on_disk)  # not applied again
    synced = pipeline._synced_steps(out, on_disk)
    assert synced["stance_depth"]["frames_in_stance"] == 3 and read_result(out)[1]["stance_depth"] == synced["stance_depth"]
    np.testing.assert_allclose(read_result(out)[0]["trans"][:, 2], 3.02, atol=1e-6)  # moved once


def test_a_stop_during_the_steps_after_tracking_is_recorded(tmp_path, monkeypatch):
    """run.json used to say "finished" before the steps after tracking ran, so a stop there
    left an unfinished motion that export used without a word, and a batch skipped it."""
    from flowmocap import pipeline
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.io.results import read_result

    out = tmp_path / "r"
    run = _finishing_result(out)

    def stopped(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "_smooth_poses", stopped)
    with pytest.raises(KeyboardInterrupt):
        pipeline._post_steps(out, None, None, TrackerConfig(stance_depth_share=0.0), run, "auto", lambda _m: None)
    _, on_disk = read_result(out)
    assert on_disk["status"] == "interrupted" and "in the steps after tracking" in on_disk["error"]
    assert pipeline._post_pending(out, TrackerConfig(stance_depth_share=0.0), "auto", on_disk)  # --resume does them
