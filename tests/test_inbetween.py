"""The frames where the person was not seen, filled in between the poses before and after
(flowmocap.fit.smooth.inbetween_unseen), in closed form, and a gait's cycle carried through
them (flowmocap.fit.smooth.motion_period)."""

from __future__ import annotations

import json

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from flowmocap.body import load_body_model
from flowmocap.fit.smooth import inbetween_unseen, motion_period
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.io.results import UNSEEN_WORDS, unseen_frames


def test_a_held_run_is_filled_by_slerp_and_a_line_and_one_at_the_end_is_left():
    model = load_body_model("default")
    rng = np.random.default_rng(4)
    T = 8
    poses = np.repeat(rng.normal(0, 0.4, (1, 72)), T, 0)
    poses[5:] = rng.normal(0, 0.4, 72)  # held at frame 1's pose in 2-4, another pose from 5
    poses[:2] = rng.normal(0, 0.4, 72)
    poses[2:5] = poses[1]
    trans = np.zeros((T, 3))
    trans[:2], trans[2:5], trans[5:] = [0, 0, 3], [0, 0, 3], [1.0, 0.5, 4.0]
    cam = PinholeCamera.from_focal(320, 240, 300.0)
    motion = {"poses": poses.astype(np.float32), "trans": trans.astype(np.float32), "betas": np.zeros(10, np.float32),
              "joints3d": np.zeros((T, 24, 3), np.float32), "joints2d": np.zeros((T, 24, 2), np.float32),
              "camera": np.array(json.dumps(cam.to_dict())), "frame_index": np.arange(10, 10 + T), "fps": np.array(30.0)}
    out, info = inbetween_unseen(motion, model, [(12, 14), (17, 17)])  # the second: the last frame, no after
    assert info == {"runs": [[12, 14]], "frames": 3, "cycles": [], "stops": []}
    p = np.asarray(out["poses"], np.float64)
    for k, u in ((2, 0.25), (3, 0.5), (4, 0.75)):
        for j in (0, 5, 17):
            ends = Rotation.from_rotvec(np.stack([poses[1, 3 * j:3 * j + 3], poses[5, 3 * j:3 * j + 3]]))
            want = Slerp([0, 1], ends)([u])[0]
            assert (Rotation.from_rotvec(p[k, 3 * j:3 * j + 3]) * want.inv()).magnitude() < 1e-5
        np.testing.assert_allclose(out["trans"][k], (1 - u) * trans[1] + u * trans[5], atol=1e-6)
    np.testing.assert_array_equal(out["poses"][[0, 1, 5, 6, 7]], motion["poses"][[0, 1, 5, 6, 7]])
    # the joints follow the new poses, and project with the camera
    assert np.abs(out["joints3d"][3]).max() > 0.1
    np.testing.assert_allclose(out["joints2d"][3], cam.project(np.asarray(out["joints3d"][3], np.float64)), atol=1e-3)
    # nothing to fill: the same arrays
    same, none = inbetween_unseen(motion, model, [])
    assert none == {"runs": [], "frames": 0, "cycles": [], "stops": []} and same["poses"] is motion["poses"]


def test_unseen_frames_say_how_each_frame_was_filled():
    run = {"gaps": [{"frames": [3, 4], "why": "no person found: tracked by flow alone, no silhouette term"},
                    {"frames": [10, 30], "why": "no person found: held at the last seen pose"},
                    {"frames": [40, 60], "why": "no person found: held at the last seen pose"}],
           "unseen_inbetween": {"runs": [[10, 30]], "frames": 21}}
    how = unseen_frames(run)
    assert how[3] == how[4] == "flow" and how[10] == how[30] == "between" and how[50] == "held" and 5 not in how
    assert set(UNSEEN_WORDS) == {"flow", "held", "between"} and unseen_frames({}) == {}


def _walk_motion(model, T=150, fps=30.0):
    import torch

    from flowmocap.io.builtin_walk import builtin_walk

    walk = builtin_walk(model, fps=fps, frames=T)
    cam = PinholeCamera.from_focal(320, 240, 300.0)
    with torch.no_grad():
        joints = model(pose=torch.as_tensor(walk.poses, dtype=torch.float32),
                       trans=torch.as_tensor(walk.trans, dtype=torch.float32)).joints.double().numpy()
    motion = {"poses": walk.poses.astype(np.float32), "trans": walk.trans.astype(np.float32),
              "betas": np.zeros(10, np.float32), "joints3d": np.zeros((T, 24, 3), np.float32),
              "joints2d": np.zeros((T, 24, 2), np.float32), "camera": np.array(json.dumps(cam.to_dict())),
              "frame_index": np.arange(T), "fps": np.array(fps)}
    return walk, motion, joints


def test_a_gaits_period_is_found_and_a_motion_that_does_not_alternate_is_not_a_gait():
    model = load_body_model("default")
    walk, _, _ = _walk_motion(model)
    period_frames = walk.info["period_s"] * 30.0  # the walk's own gait cycle
    lag, r = motion_period(walk.poses[:90], 30.0)
    assert abs(lag - period_frames) <= 1 and r > 0.9
    # the same legs moving together (a two-footed hop): repeats, does not alternate
    hop = walk.poses[:90].copy()
    hop[:, 6:9], hop[:, 15:18] = hop[:, 3:6], hop[:, 12:15]  # right hip and knee = the left's
    assert motion_period(hop, 30.0, min_correlation=0.5) is None
    # a pose held still, and too few frames for a period
    assert motion_period(np.repeat(walk.poses[:1], 90, 0), 30.0) is None
    assert motion_period(walk.poses[:15], 30.0) is None


def _held(motion, first: int, last: int) -> dict:
    """``motion`` with frames ``first``-``last`` held at frame ``first - 1`` (as the tracker holds them)."""
    held = dict(motion)
    poses, trans = np.array(motion["poses"]), np.array(motion["trans"])
    poses[first:last + 1], trans[first:last + 1] = poses[first - 1], trans[first - 1]
    held["poses"], held["trans"] = poses, trans
    return held


def _check_carried(model, motion, truth, first: int, last: int, side: str) -> None:
    """Frames ``first``-``last`` held, then filled: the cycle seen on ``side`` carried through
    comes within 5 mm of the walk (root-relative; the plain in-between misses it by centimetres),
    the seams do not jump, and the frames outside the run are untouched."""
    held = _held(motion, first, last)
    cycled, info = inbetween_unseen(held, model, [(first, last)])
    plain, plain_info = inbetween_unseen(held, model, [(first, last)], cycles=False)
    assert info["runs"] == plain_info["runs"] == [[first, last]] and plain_info["cycles"] == []
    assert len(info["cycles"]) == 1 and info["cycles"][0][:2] == [first, last] and info["cycles"][0][3] == side
    assert info["stops"] == []  # a walk that goes on does not stop in the run

    def local_cm(j):
        j, t = np.asarray(j[first:last + 1], np.float64), truth[first:last + 1]
        return np.linalg.norm((j - j[:, :1]) - (t - t[:, :1]), axis=-1).mean() * 100

    assert local_cm(cycled["joints3d"]) < 0.5 < 3.0 < local_cm(plain["joints3d"])
    near = slice(first - 5, last + 6)
    step = np.linalg.norm(np.diff(np.asarray(cycled["joints3d"], np.float64)[near], axis=0), axis=-1).max(1)
    assert step.max() < 1.5 * np.linalg.norm(np.diff(truth[near], axis=0), axis=-1).max()
    np.testing.assert_array_equal(cycled["poses"][:first], held["poses"][:first])
    np.testing.assert_array_equal(cycled["poses"][last + 1:], held["poses"][last + 1:])


def test_a_walk_unseen_for_a_second_is_carried_through_by_its_cycle():
    """The built-in walk, frames 80-109 held at frame 79: carried on by its cycle the filled
    frames are the walk's own within 5 mm (the plain in-between misses them by centimetres), the
    seams do not jump, and the run says which period it carried."""
    model = load_body_model("default")
    _, motion, truth = _walk_motion(model)
    _check_carried(model, motion, truth, 80, 109, "before")


def test_a_walk_unseen_early_is_carried_back_from_the_cycle_seen_after():
    """The built-in walk, frames 20-49 held at frame 19: 0.67 s seen before the run is too
    little for a period, so the cycle seen after it is carried back through the run. The
    filled frames are the walk's own within 5 mm (the plain in-between misses them by
    centimetres), the seams do not jump, and the run says the cycle was seen after it."""
    model = load_body_model("default")
    _, motion, truth = _walk_motion(model)
    assert motion_period(np.asarray(motion["poses"])[:20], 30.0) is None  # too few frames before the run
    _check_carried(model, motion, truth, 20, 49, "after")


def _walk_then_stand(model, stop: int, settle: int = 15, T: int = 150, fps: float = 30.0):
    """The built-in walk up to frame ``stop``, then ``settle`` frames easing into a standing
    pose (the body's joints at rest, the walk's root orientation there), then standing, the
    root still from ``stop`` on. Returns ``(motion, joints)`` as :func:`_walk_motion`."""
    import torch

    _, motion, _ = _walk_motion(model, T, fps)
    poses, trans = np.array(motion["poses"], np.float64), np.array(motion["trans"], np.float64)
    stand = poses[stop].copy()
    stand[3:] = 0.0
    a, b = Rotation.from_rotvec(poses[stop].reshape(24, 3)), Rotation.from_rotvec(stand.reshape(24, 3))
    for f in range(stop + 1, T):
        w = min(1.0, (f - stop) / settle)
        poses[f] = (a * Rotation.from_rotvec(w * (a.inv() * b).as_rotvec())).as_rotvec().reshape(-1)
        trans[f] = trans[stop]
    with torch.no_grad():
        joints = model(pose=torch.as_tensor(poses, dtype=torch.float32),
                       trans=torch.as_tensor(trans, dtype=torch.float32)).joints.double().numpy()
    return {**motion, "poses": poses.astype(np.float32), "trans": trans.astype(np.float32)}, joints


def _reversed(motion: dict, joints: np.ndarray):
    """The motion played backwards (the frame numbers kept)."""
    return {**motion, "poses": motion["poses"][::-1].copy(), "trans": motion["trans"][::-1].copy()}, joints[::-1].copy()


def test_a_walker_who_stops_behind_the_occluder_walks_only_as_far_as_they_got(monkeypatch):
    """The built-in walk stops at frame 90 (half a second's ease into standing), hidden in frames
    75-119: the root moves across the run a third of what the walk's speed covers in its 1.5 s,
    and the frames after it stand. The walk is carried for the frames that speed needs (16), then
    settles into the standing pose: the root path within 3 cm of the truth and the body nearer it
    than the cycle carried through the whole run, which walks on the spot with the root creeping
    at a third of the pace. Played backwards (standing, then walking off), the same from the
    cycle seen after the run."""
    import flowmocap.fit.smooth as smooth
    from flowmocap.pipeline import inbetween_words

    model = load_body_model("default")
    first, last = 75, 119
    for side, (motion, truth), (f0, f1) in (
            ("before", _walk_then_stand(model, 90), (first, last)),
            ("after", _reversed(*_walk_then_stand(model, 90)), (149 - last, 149 - first))):
        held = _held(motion, f0, f1)
        stopped, info = inbetween_unseen(held, model, [(f0, f1)])
        assert info["cycles"][0][3] == side and len(info["stops"]) == 1
        f, l, walked, sd = info["stops"][0]
        assert (f, l, sd) == (f0, f1, side) and abs(walked - 16) <= 3
        with monkeypatch.context() as m:
            m.setattr(smooth, "STOP_MAX_SHARE", 0.0)  # the cycle through the whole run, as before
            on, on_info = inbetween_unseen(held, model, [(f0, f1)])
        assert on_info["stops"] == [] and on_info["cycles"] == info["cycles"]
        run = slice(f0, f1 + 1)

        def root_cm(mo):
            return np.linalg.norm(np.asarray(mo["joints3d"], np.float64)[run, 0] - truth[run, 0], axis=-1).mean() * 100

        def local_cm(mo):
            j, t = np.asarray(mo["joints3d"], np.float64)[run], truth[run]
            return np.linalg.norm((j - j[:, :1]) - (t - t[:, :1]), axis=-1).mean() * 100

        said = inbetween_words(info)  # and the log says so
        assert (f"in frames {f0}-{f1} the person moved too little to walk all the way" in said
                and ("the walk stops after" if side == "before" else "into the walk of the last") in said)
        assert root_cm(stopped) < 3.0 < 8.0 < root_cm(on), (root_cm(stopped), root_cm(on))  # 2.2 and 24.5
        assert local_cm(stopped) < 1.5 < 5.0 < local_cm(on), (local_cm(stopped), local_cm(on))  # 0.8 and 9.2
        near = slice(f0 - 5, f1 + 6)  # no jump at the seams or at the stop
        step = np.linalg.norm(np.diff(np.asarray(stopped["joints3d"], np.float64)[near], axis=0), axis=-1).max(1)
        assert step.max() < 1.5 * np.linalg.norm(np.diff(truth[near], axis=0), axis=-1).max()
