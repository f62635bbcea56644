"""Re-initialisation monitor: good frames pass, a run of bad frames is re-fitted from the
detector, earlier verdicts survive a resume (re-judged from the stored 2D joints)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flowmocap.errors import InputError
from flowmocap.fit.config import DEPTH_CUES_OFF, TrackerConfig
from flowmocap.fit.reinit import ReinitMonitor, _better, joint_disagreement
from flowmocap.vision.auto import detect_sequence

from test_auto import GroundTruthDetector


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    from flowmocap.body import load_body_model
    from flowmocap.fit.objective import Scene
    from flowmocap.io.sequence import load_sequence
    from flowmocap.synth import synthesize

    d = tmp_path_factory.mktemp("reinit") / "seq"
    synthesize("builtin:walk", d, fps=30, frames=6, size="160x120", seed=2, azimuth=60.0, distance=3.0, flow=False)
    seq = load_sequence(d)
    track = detect_sequence(seq, tmp_path_factory.mktemp("det"), GroundTruthDetector(seq), progress=False)
    model = load_body_model("default")
    scene = Scene(model, torch.as_tensor(seq.gt["betas"])[None], seq.camera)
    return seq, track, scene


def _state(seq, i, shift=(0.0, 0.0, 0.0)):
    from flowmocap.fit.objective import FrameState

    return FrameState(torch.as_tensor(seq.gt["poses"][i]), torch.as_tensor(seq.gt["trans"][i]) + torch.tensor(shift))


def test_good_frames_pass(setup):
    seq, track, scene = setup
    mon = ReinitMonitor(track, TrackerConfig())
    for i in range(2, 6):
        assert mon(i, _state(seq, i), scene, seq.mask(i)) is None
        assert mon.scores[i]["iou"] > 0.9 and mon.scores[i]["joint_error"] < 0.05


def test_a_run_of_bad_frames_is_reinitialised(setup):
    seq, track, scene = setup
    cfg = TrackerConfig(reinit_iterations=15)
    mon = ReinitMonitor(track, cfg, patience=3)
    off = (0.5, 0.0, 0.0)  # half a metre to the side: the body misses the person
    assert mon(2, _state(seq, 2, off), scene, seq.mask(2)) is None
    assert mon(3, _state(seq, 3, off), scene, seq.mask(3)) is None
    res = mon(4, _state(seq, 4, off), scene, seq.mask(4))
    assert res is not None
    state, info = res
    assert info["after"]["iou"] > 0.6 > info["before"]["iou"]
    assert info["criterion"] == "image"  # the steps after tracking ease only the 3D seams
    with torch.no_grad():
        out, _, _ = scene.forward(state.pose, state.trans)
        pj = scene.camera.project(out.joints[0]).numpy()
    j2d, conf = track.smpl_joints(4)
    assert joint_disagreement(pj, j2d, conf) < 0.1


def test_verdicts_survive_a_resume(setup, tmp_path):
    """A fresh monitor (as after --resume) re-judges the earlier frames from their stored
    2D joints (``motion.npz`` ``joints2d`` by ``frame_index``, as the pipeline passes them)."""
    seq, track, scene = setup
    with torch.no_grad():
        j2d = []
        for i in range(4):
            out, _, _ = scene.forward(*(lambda s: (s.pose, s.trans))(_state(seq, i, (0.5, 0.0, 0.0))))
            j2d.append(scene.camera.project(out.joints[0]).numpy())
    np.savez(tmp_path / "motion.npz", joints2d=np.array(j2d), frame_index=np.arange(4))
    with np.load(tmp_path / "motion.npz") as motion:
        stored = {int(f): j for f, j in zip(motion["frame_index"], motion["joints2d"])}
    mon = ReinitMonitor(track, TrackerConfig(reinit_iterations=15), stored_joints2d=stored, patience=3)
    assert mon(4, _state(seq, 4, (0.5, 0.0, 0.0)), scene, seq.mask(4)) is not None
    fresh = ReinitMonitor(track, TrackerConfig(reinit_iterations=15), patience=3)  # no stored result
    assert fresh(4, _state(seq, 4, (0.5, 0.0, 0.0)), scene, seq.mask(4)) is None


def test_thresholds_come_from_the_config(setup, monkeypatch):
    import flowmocap.fit.reinit as reinit

    seq, track, scene = setup
    cfg = TrackerConfig(reinit_min_iou=0.7, reinit_max_joint_error=0.05, reinit_patience=1, reinit_iterations=15)
    calls = []
    fit = reinit.fit_to_detection
    monkeypatch.setattr(reinit, "fit_to_detection", lambda *a, **k: calls.append(k["iterations"]) or fit(*a, **k))
    mon = ReinitMonitor(track, cfg)
    assert (mon.min_iou, mon.max_joint_error, mon.patience) == (0.7, 0.05, 1)
    # patience 1: a single bad frame is re-fitted at once
    res = mon(2, _state(seq, 2, (0.5, 0.0, 0.0)), scene, seq.mask(2))
    assert res is not None and res[1]["after"]["iou"] > res[1]["before"]["iou"]
    assert calls == [15, 15]  # lost (half a metre off): from the tracked pose and from an upright body
    calls.clear()
    mild = ReinitMonitor(track, TrackerConfig(reinit_min_iou=0.999, reinit_patience=1, reinit_iterations=15))
    mild(3, _state(seq, 3, (0.01, 0.0, 0.0)), scene, seq.mask(3))
    assert calls == [15]  # drifted, not lost: from the tracked pose only
    assert ReinitMonitor(track, cfg, min_iou=0.3).min_iou == 0.3  # an argument overrides the config
    for bad in ({"reinit_min_iou": 1.5}, {"reinit_max_joint_error": 0.0}, {"reinit_patience": 0},
                {"reinit_iterations": 0}):
        with pytest.raises(InputError):
            TrackerConfig.load(None, **bad)


def test_refits_turned_down_back_off(setup, monkeypatch):
    """Each refit turned down doubles the wait before the next attempt (from the patience,
    up to reinit_max_wait); a kept refit or a good frame ends the wait; the wait survives
    a resume."""
    import json

    seq, track, scene = setup
    mon = ReinitMonitor(track, TrackerConfig(reinit_patience=1, reinit_max_wait=4))
    kept = {"now": False}
    attempts = []

    def refit(i, state, scene_, mask, before, in3d=False):
        attempts.append(i)
        return (state, {}) if kept["now"] else None

    monkeypatch.setattr(ReinitMonitor, "_confident", lambda self, i: True)  # the clip has 6 frames
    monkeypatch.setattr(mon, "_reinitialise", refit)
    monkeypatch.setattr(mon, "judge", lambda i, *a: {"iou": 0.3, "joint_error": 0.5, "bad": True})
    for i in range(2, 14):  # every frame bad, every refit turned down: waits 1, 2, 4, 4, ...
        mon(i, _state(seq, 0), scene, None)
    assert attempts == [2, 3, 5, 9, 13]
    state = json.loads(json.dumps(mon.state_dict()))
    fresh = ReinitMonitor(track, TrackerConfig(reinit_patience=1, reinit_max_wait=4))
    fresh.load_state_dict(state)
    assert [fresh._due(i, 1) for i in (14, 16, 17)] == [mon._due(i, 1) for i in (14, 16, 17)] == [False, False, True]
    monkeypatch.setattr(mon, "judge", lambda i, *a: {"iou": 0.9, "joint_error": 0.01, "bad": False})
    mon(14, _state(seq, 0), scene, None)  # a good frame ends the wait
    monkeypatch.setattr(mon, "judge", lambda i, *a: {"iou": 0.3, "joint_error": 0.5, "bad": True})
    attempts.clear()
    kept["now"] = True
    for i in range(15, 19):  # kept refits: no wait beyond the patience
        mon(i, _state(seq, 0), scene, None)
    assert attempts == [15, 16, 17, 18]
    # without the back-off (the default, 1), every bad frame is tried
    plain = ReinitMonitor(track, TrackerConfig(reinit_patience=1))
    monkeypatch.setattr(plain, "_reinitialise", refit)
    monkeypatch.setattr(plain, "judge", lambda i, *a: {"iou": 0.3, "joint_error": 0.5, "bad": True})
    kept["now"], attempts[:] = False, []
    for i in range(2, 8):
        plain(i, _state(seq, 0), scene, None)
    assert attempts == [2, 3, 4, 5, 6, 7]
    with pytest.raises(InputError):
        TrackerConfig.load(None, reinit_max_wait=0)


def test_a_refit_must_not_lose_the_silhouette_for_the_joints():
    """Closer joints at a much lower IoU (a detector glitch) are refused; a small IoU loss
    or an IoU gain is accepted; without masks the joints decide."""
    before = {"iou": 0.78, "joint_error": 0.29}
    assert not _better(before, {"iou": 0.58, "joint_error": 0.01})
    assert _better(before, {"iou": 0.77, "joint_error": 0.01})
    assert _better(before, {"iou": 0.80, "joint_error": 0.35})
    assert not _better(before, {"iou": 0.77, "joint_error": 0.30})
    assert _better({"iou": None, "joint_error": 0.2}, {"iou": None, "joint_error": 0.1})
    assert not _better({"iou": None, "joint_error": 0.1}, {"iou": None, "joint_error": 0.2})


def test_a_refit_may_cost_more_iou_the_closer_its_joints_come():
    """``reinit_iou_per_joint_error``: the IoU a refit may lose grows by that much per unit
    of 2D joint error gained, on top of the 0.02 tolerance; off (0) it is today's rule."""
    from flowmocap.fit.reinit import IOU_TOLERANCE, _iou_allowance, _refused

    before = {"iou": 0.79, "joint_error": 0.12}
    after = {"iou": 0.72, "joint_error": 0.02}  # 0.07 IoU lost for joints 0.10 of the height closer
    assert not _better(before, after)
    assert not _better(before, after, 0.4)  # may lose 0.02 + 0.04
    assert _better(before, after, 1.0)  # may lose 0.02 + 0.10
    assert _iou_allowance(before, after, 1.0) == pytest.approx(IOU_TOLERANCE + 0.10)
    # a small 2D gain buys little: 0.05 -> 0.04 allows 0.03 at 1.0
    assert not _better({"iou": 0.79, "joint_error": 0.05}, {"iou": 0.75, "joint_error": 0.04}, 1.0)
    # joints further away buy nothing (and are no reason to keep a lower IoU at all)
    assert _iou_allowance({"iou": 0.8, "joint_error": 0.02}, {"iou": 0.8, "joint_error": 0.05}, 1.0) == IOU_TOLERANCE
    assert not _better({"iou": 0.8, "joint_error": 0.02}, {"iou": 0.79, "joint_error": 0.05}, 1.0)
    assert _iou_allowance({"iou": 0.8, "joint_error": None}, after, 1.0) == IOU_TOLERANCE
    assert "at most 0.12 lower" in _refused(before, {"iou": 0.6, "joint_error": 0.02}, 1.0)
    assert "at most 0.02 lower" in _refused(before, after)
    with pytest.raises(InputError):
        TrackerConfig.load(None, reinit_iou_per_joint_error=-1.0)


def test_the_monitor_keeps_a_refit_by_the_configured_allowance(setup, monkeypatch):
    """The monitor judges an image refit with ``reinit_iou_per_joint_error`` from its
    config: the same scores are turned down at 0 and kept at 1."""
    from flowmocap.fit import reinit

    seq, track, scene = setup
    monkeypatch.setattr(reinit, "fit_to_detection", lambda scene_, cfg, j2d, conf, mask, pose0, trans0, **kw:
                        (pose0, trans0, 1.0))
    scores = {"tracked": {"iou": 0.79, "joint_error": 0.12, "bad": True},
              "refit": {"iou": 0.72, "joint_error": 0.02, "bad": True}}
    kept = {}
    for k in (0.0, 1.0):
        mon = ReinitMonitor(track, TrackerConfig(reinit_patience=1, reinit_min_iou=0.8,
                                                 reinit_max_joint3d_error=0.0, reinit_iou_per_joint_error=k))
        calls = iter(["tracked", "refit"])
        monkeypatch.setattr(mon, "judge", lambda *a, **kw: dict(scores[next(calls)]))
        kept[k] = mon(3, _state(seq, 3, (0.01, 0.0, 0.0)), scene, seq.mask(3))
        if kept[k] is None:
            assert "at most 0.02 lower" in mon.take_events()[0]["why"]
    assert kept[0.0] is None
    assert kept[1.0] is not None and kept[1.0][1]["after"]["joint_error"] == 0.02


# ------------------------------------------------------------- the 3D criterion


def test_joint3d_disagreement_closed_form():
    """Zero for any similarity image of the model's joints; one joint moved by d among n
    confident ones gives a mean between d / n and a few d / n (the alignment, fitted with
    it, spreads its error over the others); too few confident joints give None."""
    from scipy.spatial.transform import Rotation

    from flowmocap.fit.reinit import joint3d_disagreement

    rng = np.random.default_rng(3)
    x = rng.normal(size=(24, 3)) * 0.3
    conf = np.zeros(24)
    conf[[1, 2, 4, 5, 7, 8, 16, 17, 18, 19, 20, 21]] = 0.9  # the 12 joints a detector gives
    obs = 0.6 * x @ Rotation.from_rotvec([0.3, -1.0, 0.4]).as_matrix().T + [1.0, 2.0, 3.0]
    assert joint3d_disagreement(x, obs, conf) < 1e-9
    moved = obs.copy()
    moved[7] += [0.0, 0.0, 0.6 * 0.5]  # the ankle half a metre (model scale) out in depth
    err = joint3d_disagreement(x, moved, conf)
    assert 0.5 / 12 < err < 0.5 / 12 * 2.5
    low = conf.copy()
    low[7] = 0.2  # below the confidence threshold: not compared
    assert joint3d_disagreement(x, moved, low) < err
    few = np.zeros(24)
    few[[1, 2, 4]] = 1.0
    assert joint3d_disagreement(x, obs, few) is None


def test_the_3d_criterion_can_be_turned_off(setup):
    seq, track, scene = setup
    assert ReinitMonitor(track, TrackerConfig()).max_joint3d_error == 0.1  # on by default
    mon = ReinitMonitor(track, TrackerConfig(**DEPTH_CUES_OFF))
    assert mon.max_joint3d_error == 0.0
    mon(2, _state(seq, 2), scene, seq.mask(2))
    assert "joint3d_error" not in mon.scores[2] and mon.verdicts3d[2] is None


def _crouched(seq, i):
    """Frame ``i``'s truth with both thighs raised and both knees bent (a crouch), the body
    lowered to keep the feet where they were roughly."""
    from flowmocap.body import JOINT_INDEX as J
    from flowmocap.fit.objective import FrameState

    pose = torch.as_tensor(seq.gt["poses"][i]).clone()
    for side in ("left", "right"):
        pose[3 * J[f"{side}_hip"]] -= 1.3
        pose[3 * J[f"{side}_knee"]] += 1.6
    return FrameState(pose, torch.as_tensor(seq.gt["trans"][i]) + torch.tensor([0.0, -0.25, 0.0]))


def test_a_run_of_3d_bad_frames_is_reinitialised(setup, monkeypatch):
    """The detector's 3D joints are the truth; the tracked frames are crouched. With the
    3D criterion on, ``patience3d`` such frames in a row are refitted (the 2D criteria's
    patience is out of reach here), and the refit's 3D joints are closer."""
    seq, track, scene = setup
    truth = {i: (np.asarray(seq.gt["joints3d"][i]) @ np.asarray(seq.camera.R).T, np.full(24, 0.9))
             for i in range(len(seq))}
    monkeypatch.setattr(track, "smpl_joints3d", lambda i, camera=None, ray_share=1.0: truth[i])
    cfg = TrackerConfig(reinit_max_joint3d_error=0.08, reinit_3d_patience=2, reinit_patience=10,
                        reinit_iterations=10, init_detector3d_weight=1e5)
    mon = ReinitMonitor(track, cfg)
    assert mon(2, _state(seq, 2), scene, seq.mask(2)) is None
    assert mon.scores[2]["joint3d_error"] < 0.02 and mon.verdicts3d[2] is False
    assert mon(3, _crouched(seq, 3), scene, seq.mask(3)) is None  # one 3D-bad frame: patience 2
    assert mon.verdicts3d[3] is True  # (the 2D criteria's patience, 10, is not reached)
    res = mon(4, _crouched(seq, 4), scene, seq.mask(4))
    assert res is not None
    state, info = res
    assert "3D joints" in info["why"] and info["criterion"] == "3d"
    assert info["after"]["joint3d_error"] < 0.5 * info["before"]["joint3d_error"]
    assert "bad3d" not in info["after"]


def test_a_3d_refit_must_still_fit_the_image():
    from flowmocap.fit.reinit import _better_3d

    before = {"iou": 0.8, "joint_error": 0.05, "joint3d_error": 0.15}
    assert _better_3d(before, {"iou": 0.79, "joint_error": 0.06, "joint3d_error": 0.05}, 0.15)
    assert not _better_3d(before, {"iou": 0.79, "joint_error": 0.06, "joint3d_error": 0.16}, 0.15)  # no closer
    assert not _better_3d(before, {"iou": 0.70, "joint_error": 0.04, "joint3d_error": 0.05}, 0.15)  # lost IoU
    assert not _better_3d(before, {"iou": 0.85, "joint_error": 0.20, "joint3d_error": 0.05}, 0.15)  # 2D off
    assert _better_3d({"iou": None, "joint_error": None, "joint3d_error": 0.2},
                      {"iou": None, "joint_error": None, "joint3d_error": 0.1}, 0.15)
    assert not _better_3d({"iou": 0.8, "joint_error": 0.05, "joint3d_error": None},
                          {"iou": 0.8, "joint_error": 0.05, "joint3d_error": 0.1}, 0.15)


def test_why_a_3d_refit_is_turned_down():
    """Each condition of ``_better_3d`` that fails is named, with the numbers."""
    from flowmocap.fit.reinit import _refused, _refused_3d

    before = {"iou": 0.8, "joint_error": 0.05, "joint3d_error": 0.15}
    assert _refused_3d(before, {"iou": 0.79, "joint_error": 0.06, "joint3d_error": 0.05}, 0.15) is None
    assert "no closer" in _refused_3d(before, {"iou": 0.8, "joint_error": 0.05, "joint3d_error": 0.16}, 0.15)
    why = _refused_3d(before, {"iou": 0.70, "joint_error": 0.04, "joint3d_error": 0.05}, 0.15)
    assert "IoU drops" in why and "0.800 -> 0.700" in why
    assert "2D joints" in _refused_3d(before, {"iou": 0.85, "joint_error": 0.20, "joint3d_error": 0.05}, 0.15)
    assert "no 3D joints" in _refused_3d({**before, "joint3d_error": None}, before, 0.15)
    why = _refused({"iou": 0.78, "joint_error": 0.29}, {"iou": 0.58, "joint_error": None})
    assert "0.780 -> 0.580" in why and "0.290 -> none" in why


def test_a_3d_refit_kept_above_the_iou_floor():
    """``reinit_3d_keep_iou``: a 3D refit whose IoU drops by more than the tolerance is
    kept when its IoU stays at or above the floor, turned down below it or when off."""
    from flowmocap.fit.reinit import _better_3d, _refused_3d

    before = {"iou": 0.88, "joint_error": 0.05, "joint3d_error": 0.08}
    after = {"iou": 0.81, "joint_error": 0.05, "joint3d_error": 0.04}
    assert not _better_3d(before, after, 0.15)  # off: 0.07 lower than the tracked frame
    assert _better_3d(before, after, 0.15, keep_iou=0.8)
    why = _refused_3d(before, {**after, "iou": 0.79}, 0.15, keep_iou=0.8)
    assert "below 0.8" in why and "0.880 -> 0.790" in why
    # the floor does not excuse a refit that is no closer in 3D or leaves the 2D joints
    assert "no closer" in _refused_3d(before, {**after, "joint3d_error": 0.09}, 0.15, keep_iou=0.8)
    assert "2D joints" in _refused_3d(before, {**after, "joint_error": 0.2}, 0.15, keep_iou=0.8)


def test_a_refit_turned_down_is_recorded_once(setup, monkeypatch):
    """A 3D refit that does not come closer to the detector's 3D is not kept, and the
    monitor hands the tracker one event that says why (then none until the next)."""
    from flowmocap.fit import reinit
    from flowmocap.fit.reinit import TURNED_DOWN_EVENT

    seq, track, scene = setup
    truth = {i: (np.asarray(seq.gt["joints3d"][i]) @ np.asarray(seq.camera.R).T, np.full(24, 0.9))
             for i in range(len(seq))}
    monkeypatch.setattr(track, "smpl_joints3d", lambda i, camera=None, ray_share=1.0: truth[i])
    # every fit gives the tracked pose back: the refit's 3D is no closer than the tracked frame's
    monkeypatch.setattr(reinit, "fit_to_detection", lambda scene_, cfg, j2d, conf, mask, pose0, trans0, **kw:
                        (pose0, trans0, 1.0))
    cfg = TrackerConfig(reinit_max_joint3d_error=0.08, reinit_3d_patience=2, reinit_patience=10)
    mon = ReinitMonitor(track, cfg)
    assert mon(3, _crouched(seq, 3), scene, seq.mask(3)) is None
    assert mon.take_events() == []  # one 3D-bad frame: no attempt yet
    assert mon(4, _crouched(seq, 4), scene, seq.mask(4)) is None  # attempted and turned down
    events = mon.take_events()
    assert len(events) == 1 and mon.take_events() == []
    e = events[0]
    assert e["event"] == TURNED_DOWN_EVENT and e["frame"] == 4 and e["criterion"] == "3d"
    assert "no closer" in e["why"] and e["before"]["joint3d_error"] > 0.08
    assert e["after"]["joint3d_error"] == e["before"]["joint3d_error"]  # the tracked pose won (first, same energy)


def test_the_tracker_records_the_refits_turned_down(setup):
    """SequenceTracker adds what a monitor's ``take_events`` hands it to the frame's events."""
    from flowmocap.fit.tracker import SequenceTracker

    seq, track, scene = setup

    class Monitor:
        def __call__(self, i, state, scene_, mask):
            return None

        def take_events(self):
            return [{"event": "re-initialisation turned down", "why": "test"}]

    from flowmocap.fit.objective import frame_data

    cfg = TrackerConfig(iterations=2, **DEPTH_CUES_OFF)
    tr = SequenceTracker(scene, cfg, monitor=Monitor())
    tr.start(_state(seq, 0), _state(seq, 1), anchored=False)
    res = tr.step(2, seq.mask(2), frame_data(seq.mask(2), None, cfg, 1.0))
    assert {"event": "re-initialisation turned down", "why": "test"} in res.events


def test_collapsed_detections_are_not_refitted_to():
    import numpy as np

    from flowmocap.fit.reinit import collapsed_detection

    rng = np.random.default_rng(0)
    j2d = np.stack([rng.uniform(100, 140, 24), np.linspace(100, 400, 24)], 1)  # 300 px tall
    conf = np.ones(24)
    assert not collapsed_detection(j2d, conf, 480)
    folded = j2d.copy()
    folded[:, 1] = 200 + (folded[:, 1] - 100) / 30  # 10 px tall: knees and ankles at the hips
    assert collapsed_detection(folded, conf, 480)
    few = np.zeros(24)
    few[:5] = 1.0
    assert collapsed_detection(j2d, few, 480)


def test_minimise_refuses_to_leave_non_finite_parameters():
    import torch

    from flowmocap.errors import OptimizationError
    from flowmocap.fit.lbfgs import minimise

    x = torch.tensor([1.0, 2.0], dtype=torch.float64, requires_grad=True)

    class FiniteValueNanGradient(torch.autograd.Function):
        @staticmethod
        def forward(ctx, v):
            return torch.nan_to_num((v ** 2).sum(), nan=1.0)  # finite even at NaN parameters

        @staticmethod
        def backward(ctx, g):
            return torch.full((2,), float("nan"), dtype=torch.float64)

    def energy():
        return FiniteValueNanGradient.apply(x)

    with pytest.raises(OptimizationError, match="non-finite"):
        minimise([x], energy, iterations=5)
    assert not torch.isfinite(x).all()  # what the check caught


def test_pixels_where_someone_else_is_seen_are_left_out_of_the_iou(setup):
    """A body half hidden behind someone else: its mask is cut where they stand, so
    the IoU drops; with those pixels given as the others' (unknown), the body may cover
    them and the IoU is the visible part's."""
    seq, track, scene = setup
    from flowmocap.fit.reinit import body_silhouette

    i = 3
    st = _state(seq, i)
    body = body_silhouette(scene, st.pose, st.trans)
    cols = np.nonzero(body.any(0))[0]
    front = np.zeros_like(body)
    front[:, (cols[0] + cols[-1]) // 2:] = True  # someone in front of the body's right half
    cut = seq.mask(i) & ~front
    plain = ReinitMonitor(track, TrackerConfig()).judge(i, scene, st.pose, st.trans, cut)["iou"]
    aware = ReinitMonitor(track, TrackerConfig(), others=lambda j: front & ~cut).judge(i, scene, st.pose, st.trans,
                                                                                        cut)["iou"]
    assert plain < 0.7 < 0.9 < aware


def test_a_lasting_3d_disagreement_is_refitted_after_n_refusals(setup, monkeypatch):
    """``reinit_3d_insist`` N: after N 3D refits in a row turned down for the silhouette
    alone, the next is kept at an IoU of at least ``reinit_min_iou``; the count starts
    again when the 3D agrees, and off (0) every such refit is turned down."""
    import torch

    from flowmocap.fit import reinit

    seq, track, scene = setup
    refit = torch.full((72,), 0.01)
    monkeypatch.setattr(reinit, "fit_to_detection", lambda scene_, cfg, j2d, conf, mask, pose0, trans0, **kw:
                        (refit, trans0, 1.0))
    monkeypatch.setattr(reinit, "collapsed_detection", lambda *a, **k: False)
    tracked = {"iou": 0.88, "joint_error": 0.05, "joint3d_error": 0.09, "bad": False, "bad3d": True}
    refitted = {"iou": 0.83, "joint_error": 0.04, "joint3d_error": 0.04, "bad": False, "bad3d": False}
    agreeing = {**tracked, "joint3d_error": 0.03, "bad3d": False}

    def run(insist, frames):
        """Frames ``(i, agrees)``; returns the frames whose refit was kept."""
        cfg = TrackerConfig(reinit_max_joint3d_error=0.07, reinit_3d_patience=1, reinit_patience=10,
                            reinit_min_iou=0.8, reinit_3d_insist=insist)
        mon = ReinitMonitor(track, cfg)
        monkeypatch.setattr(mon, "_confident", lambda i: True)
        kept = []
        for i, agrees in frames:
            def judge(i_, scene_, pose, trans, mask, agrees=agrees):
                return dict(refitted if torch.equal(pose, refit) else (agreeing if agrees else tracked))
            monkeypatch.setattr(mon, "judge", judge)
            out = mon(i, _state(seq, i % len(seq)), scene, None)
            if out is not None:
                kept.append(i)
                assert "after 2 such refits in a row were turned down" in out[1]["why"]
        return kept, mon

    assert run(0, [(i, False) for i in range(6)])[0] == []
    kept, mon = run(2, [(i, False) for i in range(6)])
    assert kept == [2, 5]  # two turned down (0, 1), the third kept; the count starts again after it
    assert mon.state_dict()["refused3d"] == 0  # reset by the refit kept at frame 5
    assert run(2, [(i, False) for i in range(5)])[1].state_dict()["refused3d"] == 2  # resumes insisting
    # a frame whose 3D agrees ends the run: the count starts again
    assert run(2, [(0, False), (1, True), (2, False), (3, False), (4, False)])[0] == [4]
    # below reinit_min_iou it is turned down all the same
    refitted["iou"] = 0.79
    assert run(2, [(i, False) for i in range(5)])[0] == []
