"""The tracker end to end on short synthetic clips (through :func:`flowmocap.pipeline.track`,
or :class:`~flowmocap.fit.tracker.SequenceTracker` where a test injects observations):
accuracy with and without the flow term, resuming an interrupted run, init.json checks
and bad input."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from flowmocap.body import load_body_model
from flowmocap.errors import DataError, InputError, NoPersonError, OptimizationError
from flowmocap.eval.protocol import evaluate, noisy_init
from flowmocap.fit.config import DEPTH_CUES_OFF, TrackerConfig
from flowmocap.fit.init import parse_init
from flowmocap.fit.objective import FrameState, Scene, configured_keypoints, frame_data, keypoint_observation
from flowmocap.fit.tracker import KnownStart, SequenceTracker, track_frames
from flowmocap.io.results import read_result
from flowmocap.io.sequence import load_sequence
from flowmocap.pipeline import parse_frame_range, track
from flowmocap.synth import synthesize

FRAMES = 8


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A short 320x240 built-in walk seen close up, with a non-mean body shape."""
    d = tmp_path_factory.mktemp("clip") / "seq"
    synthesize("builtin:walk", d, fps=30, frames=FRAMES, size="320x240", betas="random", seed=3,
               azimuth=70.0, distance=3.2, flow=False)
    return d


@pytest.fixture(scope="module")
def model():
    return load_body_model("default")


def _known_start(seq):
    gt = seq.gt
    return KnownStart(poses=gt["poses"][:2], trans=gt["trans"][:2], betas=gt["betas"])


def _track(seq, out, model, cfg=None, init=None, **kw):
    """:func:`track` on the sequence folder ``seq.root`` (its masks and camera), from the
    known start unless ``init`` (an init.json dict) is given, without the detector's 3D joints."""
    track(seq.root, out, init=init or _known_start(seq), config=(cfg or TrackerConfig()).to_dict(), model=model,
          progress=False, joints3d="off", log=None, **kw)
    motion, run = read_result(out)
    return motion, run


def _f32(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x), dtype=torch.float32)


def _track_direct(seq, out, model, cfg, frames, keypoints=None, joints3d=None, events=None):
    """:class:`SequenceTracker` + :func:`track_frames` from the known start, with per-frame
    detections :func:`track` does not take: ``keypoints(i) -> (j2d (24, 2), conf (24,))``
    for ``E_j`` and ``joints3d(i) -> (j3d (24, 3), conf (24,))`` for ``E_d``; ``events``: a
    list the frames' events are added to.

    Returns ``(joints2d (T, 24, 2), terms)`` of the tracked frames (from the third on),
    ``terms`` one dict of energies per frame."""
    from flowmocap.vision import FlowCache

    a, b = parse_frame_range(frames, len(seq))
    gt = seq.gt
    scene = Scene(model, _f32(gt["betas"])[None], seq.camera)
    tracker = SequenceTracker(scene, cfg)
    tracker.start(*(FrameState(_f32(gt["poses"][k]), _f32(gt["trans"][k])) for k in (a, a + 1)), anchored=True)
    cache = FlowCache(out / "flow_cache", method=cfg.flow_method)

    def observe(i):
        mask = seq.mask(i)
        kp = configured_keypoints(*keypoints(i), cfg) if keypoints is not None else None
        data = frame_data(mask, cache.flow(i, seq.frame(i), seq.frame(i - 1)), cfg, float("nan"), kp)
        data.joints3d = joints3d(i) if joints3d is not None else None
        return mask, data

    results = []
    threads = torch.get_num_threads()
    torch.set_num_threads(cfg.torch_threads)
    try:
        track_frames(tracker, range(a + 2, b), observe, results.append, progress=False)
    finally:
        torch.set_num_threads(threads)
    with torch.no_grad():
        j2d = np.stack([scene.camera.project(scene.forward(r.state.pose, r.state.trans)[0].joints[0]).numpy()
                        for r in results])
    if events is not None:
        events += [e for r in results for e in r.events]
    return j2d, [r.terms for r in results]


def test_flow_term_keeps_the_error_small(clip, model, tmp_path):
    seq = load_sequence(clip)
    with_flow, _ = _track(seq, tmp_path / "flow", model)
    # without flow: only silhouette, limits and temporal terms remain
    without, _ = _track(seq, tmp_path / "noflow", model, TrackerConfig(flow_weight=0.0))
    e_flow = evaluate(with_flow, seq.gt)
    e_none = evaluate(without, seq.gt)
    print("local cm with flow", e_flow["local_cm"], "without", e_none["local_cm"])
    assert with_flow["poses"].shape == (FRAMES, 72)
    assert np.isnan(with_flow["energies"][:2]).all()  # the known start is not optimised: no energies
    assert e_flow["local_cm"] < 4.0
    assert e_flow["local_cm"] < 0.8 * e_none["local_cm"]


def test_interrupted_run_resumes_to_the_same_result(clip, model, tmp_path, monkeypatch):
    import flowmocap.fit.tracker as tracker

    seq = load_sequence(clip)
    ref, _ = _track(seq, tmp_path / "ref", model, frames="0:6")
    original = tracker.track_frame
    calls = {"n": 0}

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(tracker, "track_frame", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _track(seq, tmp_path / "run", model, frames="0:6")
    partial, run = read_result(tmp_path / "run")
    assert len(partial["poses"]) == 4 and run["status"] == "interrupted" and run["error"] == "KeyboardInterrupt"
    monkeypatch.setattr(tracker, "track_frame", original)
    with pytest.raises(InputError, match="already holds a result"):
        _track(seq, tmp_path / "run", model, frames="0:6")
    resumed, run = _track(seq, tmp_path / "run", model, frames="0:6", resume=True)
    assert run["status"] == "finished" and "error" not in run
    assert run["model"] == "default" and "anny" in run["model_source"]  # loadable again, and described
    for key in ("poses", "trans", "joints3d", "joints2d", "frame_index"):
        np.testing.assert_array_equal(resumed[key], ref[key], err_msg=key)
    np.testing.assert_array_equal(resumed["energies"], ref["energies"])
    assert not (tmp_path / "run" / "progress.json").exists()  # a finished run keeps motion.npz alone
    with pytest.raises(InputError, match="cannot resume.*options"):
        _track(seq, tmp_path / "run", model, frames="0:5", resume=True)
    with pytest.raises(InputError, match="the config differs"):
        _track(seq, tmp_path / "run", model, TrackerConfig(flow_weight=2.0), frames="0:6", resume=True)


def test_a_run_written_by_an_older_flowmocap_is_not_resumed(clip, model, tmp_path):
    """Before the frame log, an interrupted run was motion.npz + run.json with the tracker's
    state in it, written one after the other: nothing to continue exactly from."""
    from flowmocap.io.results import write_run

    seq = load_sequence(clip)
    out = tmp_path / "old"
    _track(seq, out, model, frames="0:4")
    _, old = read_result(out)
    old["status"] = "running"
    old.pop("tracked")  # an older flowmocap did not say that every frame was tracked
    write_run(out, old)
    with pytest.raises(InputError, match="older flowmocap"):
        _track(seq, out, model, frames="0:4", resume=True)


def test_non_finite_energy_is_rolled_back_and_recorded(clip, model, tmp_path, monkeypatch):
    import flowmocap.fit.tracker as tracker

    seq = load_sequence(clip)
    original = tracker.track_frame
    calls = {"n": 0}

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 1:
            raise OptimizationError("the energy became non-finite (NaN or inf)")
        return original(*args, **kwargs)

    monkeypatch.setattr(tracker, "track_frame", flaky)
    motion, run = _track(seq, tmp_path / "nan", model, frames="0:4")
    assert len(motion["poses"]) == 4 and np.isfinite(motion["poses"]).all()
    assert run["events"] and run["events"][0]["frame"] == 2
    assert "non-finite" in run["events"][0]["event"]


def test_a_trial_pose_that_cannot_be_evaluated_makes_the_line_search_back_off():
    """A line-search trial outside where the energy can be evaluated (a capsule behind the
    camera) counts as a wall: the minimiser stops inside it, lower than it started;
    a start that cannot be evaluated rolls the frame back (OptimizationError)."""
    from flowmocap.fit.lbfgs import minimise

    x = torch.zeros(3, requires_grad=True)

    def energy():
        if float(x.detach().abs().sum()) > 0.5:
            raise InputError("a capsule is not in front of the camera")
        return ((x - 2.0) ** 2).sum()

    minimise([x], energy, 30)
    assert float(x.detach().abs().sum()) <= 0.5
    assert float(energy().detach()) < 10.2  # 12 at the start, 10.08 at the best point inside
    x.data[:] = 1.0
    with pytest.raises(OptimizationError, match="start pose"):
        minimise([x], energy, 10)


def test_the_minimiser_stops_once_the_energy_stalls_at_its_best_point():
    """With rel_tolerance, L-BFGS ends once STALL_WINDOW evaluations improve the lowest
    energy by less than that fraction, and leaves the parameters at the lowest energy it
    evaluated (possibly before the line search it stopped in); without, it runs as torch's."""
    from flowmocap.fit.lbfgs import STALL_WINDOW, minimise

    scales = torch.logspace(0, 3, 12)  # an ill-conditioned quadratic: slow, steady progress

    def run(rel):
        x = torch.ones(12, requires_grad=True)
        seen = []

        def energy():
            e = (scales * (x - 0.3) ** 2).sum() + 1.0  # minimum 1 at x = 0.3
            seen.append((float(e.detach()), x.detach().clone()))
            return e

        value = minimise([x], energy, 100, rel_tolerance=rel)
        return x.detach(), value, seen

    x0, v0, seen0 = run(0.0)
    x1, v1, seen1 = run(1e-3)
    assert len(seen1) < len(seen0)  # stopped early
    lowest = min(e for e, _ in seen1)
    assert v1 == lowest
    assert float((scales * (x1 - 0.3) ** 2).sum() + 1.0) == pytest.approx(lowest, rel=1e-6)
    # it stopped because the lowest energy stalled: over the last window it moved < 0.1 %
    best = np.minimum.accumulate([e for e, _ in seen1])
    assert best[-1 - STALL_WINDOW] - best[-1] <= 1e-3 * best[-1]
    assert all(best[k - STALL_WINDOW] - best[k] > 1e-3 * best[k] for k in range(STALL_WINDOW, len(best) - 1))
    assert v0 <= v1 and v1 - 1.0 < 0.05  # close to the minimum all the same


def test_initialisation_from_noisy_joints(clip, model, tmp_path):
    seq = load_sequence(clip)
    cfg = TrackerConfig(init_iterations=40, init_flow_iterations=10)
    motion, run = _track(seq, tmp_path / "init", model, cfg, init=noisy_init(seq.gt, frame=0, seed=1), frames="0:3")
    scores = evaluate(motion, seq.gt)
    assert scores["local_cm_per_frame"][0] < 9.0
    assert run["timings"]["init_s"] > 0


def test_init_json_checks(tmp_path):
    with pytest.raises(InputError, match="joints2d"):
        parse_init({"pose": {}})
    with pytest.raises(InputError, match="unknown joint"):
        parse_init({"joints2d": {"left_hipp": [1, 2]}})
    with pytest.raises(InputError, match="outside"):
        parse_init({"joints2d": {"left_hip": [500, 20], "right_hip": [1, 1], "left_shoulder": [2, 2],
                                 "right_shoulder": [3, 3]}}, 320, 240)
    with pytest.raises(NoPersonError):
        parse_init({"joints2d": {"left_hip": [5, 5], "right_hip": None}})
    p = tmp_path / "init.json"
    p.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        parse_init(p)


def test_bad_sequences(clip, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(clip, bad)
    (bad / "masks" / "000003.png").unlink()
    with pytest.raises(DataError, match="masks"):
        load_sequence(bad)
    import cv2

    shutil.copy(clip / "masks" / "000000.png", bad / "masks" / "000003.png")
    cv2.imwrite(str(bad / "frames" / "000002.png"), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(DataError, match="one size"):  # found when the folder is opened, before any work
        load_sequence(bad)
    with pytest.raises(DataError, match="no images"):
        load_sequence(tmp_path)


def test_empty_mask_is_recorded(clip, model, tmp_path):
    import cv2

    d = tmp_path / "seq"
    shutil.copytree(clip, d)
    cv2.imwrite(str(d / "masks" / "000002.png"), np.zeros((240, 320), np.uint8))
    seq = load_sequence(d)
    motion, run = _track(seq, tmp_path / "out", model, frames="0:3")
    assert len(motion["poses"]) == 3
    assert any(e["frame"] == 2 and "empty mask" in e["event"] for e in run["events"])


def test_config_file(tmp_path):
    p = tmp_path / "cfg.json"
    p.write_text(json.dumps({"flow_weight": 2.0, "stages": [[0]]}))
    cfg = TrackerConfig.load(p)
    assert cfg.flow_weight == 2.0 and cfg.stages == ((0,),)
    p.write_text(json.dumps({"flow_wieght": 2.0}))
    with pytest.raises(InputError, match="unknown config"):
        TrackerConfig.load(p)
    for bad in ({"silhouette_model": "voxels"}, {"flow_method": "magic"}):
        p.write_text(json.dumps(bad))
        with pytest.raises(InputError, match=next(iter(bad))):
            TrackerConfig.load(p)
    # a base (the real-video settings) goes under the file, keyword overrides over both
    p.write_text(json.dumps({"silhouette_weight": 7.0}))
    base = {"silhouette_weight": 20.0, "silhouette_a": 0.4}
    cfg = TrackerConfig.load(p, base=base, flow_weight=3.0, levels=None)
    assert (cfg.silhouette_weight, cfg.silhouette_a, cfg.flow_weight, cfg.levels) == (7.0, 0.4, 3.0, 3)
    assert TrackerConfig.load(None, base=base).silhouette_weight == 20.0


def test_all_weights_zero_keeps_the_prediction(clip, model):
    """With every term switched off the energy is an exact 0-d zero, not a Python int."""
    from flowmocap.fit.objective import frame_energy

    seq = load_sequence(clip)
    cfg = TrackerConfig(flow_weight=0.0, silhouette_weight=0.0, temporal_weight=0.0, limit_weight=0.0,
                        penetration_weight=0.0, **DEPTH_CUES_OFF)
    scene = Scene(model, torch.as_tensor(seq.gt["betas"])[None], seq.camera)
    state = FrameState(torch.as_tensor(seq.gt["poses"][2]).requires_grad_(), torch.as_tensor(seq.gt["trans"][2]))
    total, terms = frame_energy(scene, state, frame_data(seq.mask(2), None, cfg, 1.0), cfg, 0, None, None)
    assert isinstance(total, torch.Tensor) and total.dim() == 0 and float(total.detach()) == 0.0 and terms == {}


def _write_video(frames_dir, path):
    import imageio.v3 as iio

    from flowmocap.io.sequence import list_images, read_image

    frames = np.stack([read_image(p) for p in list_images(frames_dir)])
    iio.imwrite(path, frames, plugin="pyav", codec="mpeg4", fps=30)
    return frames


def test_video_input_tracks(clip, model, tmp_path):
    from flowmocap.io.video import load_video

    video = tmp_path / "clip.mp4"
    frames = _write_video(clip / "frames", video)
    seq = load_video(video, masks=clip / "masks")
    assert len(seq) == len(frames) and seq.size == (320, 240)
    assert seq.meta["fps"] == pytest.approx(30.0)
    assert np.abs(seq.frame(3).astype(int) - frames[3]).mean() < 8  # lossy codec
    gt = load_sequence(clip).gt
    start = KnownStart(poses=gt["poses"][:2], trans=gt["trans"][:2], betas=gt["betas"])
    track(video, tmp_path / "out", init=start, masks=clip / "masks", camera=clip / "camera.json",
          config=TrackerConfig().to_dict(), frames="0:4", model=model, progress=False, joints3d="off", log=None)
    motion, run = read_result(tmp_path / "out")
    assert len(motion["poses"]) == 4 and run["status"] == "finished"


def test_bad_videos(clip, tmp_path):
    from flowmocap.io.video import load_video

    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"\x00\x00\x00\x18ftypmp42 this is not a video")
    with pytest.raises(DataError, match="cannot decode"):
        load_video(broken)
    with pytest.raises(DataError, match="does not exist"):
        load_video(tmp_path / "missing.mp4")
    video = tmp_path / "clip.mp4"
    _write_video(clip / "frames", video)
    few = tmp_path / "few"
    few.mkdir()
    shutil.copy(clip / "masks" / "000000.png", few / "000000.png")
    with pytest.raises(DataError, match="one mask per frame"):
        load_video(video, masks=few)


def _true_joints2d(seq, model):
    scene = Scene(model, torch.as_tensor(seq.gt["betas"], dtype=torch.float32)[None], seq.camera)
    with torch.no_grad():
        return [scene.camera.project(scene.forward(torch.as_tensor(p, dtype=torch.float32),
                                                   torch.as_tensor(t, dtype=torch.float32))[0].joints[0]).numpy()
                for p, t in zip(seq.gt["poses"], seq.gt["trans"])]


def test_detected_joints_pull_the_body(clip, model, tmp_path):
    """E_j (detected 2D joints) on its own keeps tracking close where nothing else observes the body."""
    seq = load_sequence(clip)
    truth = _true_joints2d(seq, model)
    rng = np.random.default_rng(0)
    noisy = [j + rng.normal(scale=1.0, size=j.shape) for j in truth]
    conf = np.full(24, 0.9)
    conf[[10, 11, 22, 23]] = 0.0  # joints a detector does not give
    # the other terms off, and a prediction that drifts: without E_j the body drifts
    cfg = TrackerConfig(flow_weight=0.0, silhouette_weight=0.0, keypoint_weight=0.05, kalman=False, temporal_weight=0.0)
    seen = _track_direct(seq, tmp_path / "kp", model, cfg, "0:6", keypoints=lambda i: (noisy[i], conf))
    blind = _track_direct(seq, tmp_path / "none", model, cfg, "0:6")
    err = lambda m: float(np.median(np.linalg.norm(m[0] - np.stack(truth[2:6]), axis=-1)))  # noqa: E731
    assert all(np.isfinite(t["keypoints"]) for t in seen[1])
    assert not any("keypoints" in t for t in blind[1])
    print("median 2D joint error px with E_j", err(seen), "without", err(blind))
    assert err(seen) < 3.0 and err(seen) < 0.5 * err(blind), (err(seen), err(blind))


def _detector_joints2d(seq, model, frame):
    """The true body's joints of ``frame`` where the detector puts them (pixels, (24, 2))."""
    from flowmocap.vision.keypoint_map import detector_points

    scene = Scene(model, _f32(seq.gt["betas"])[None], seq.camera)
    with torch.no_grad():
        out, _, _ = scene.forward(_f32(seq.gt["poses"][frame]), _f32(seq.gt["trans"][frame]))
        return scene, scene.camera.project(detector_points(out, TrackerConfig())[0]).double().numpy()


def test_a_joint_is_lost_when_a_confident_detection_is_far_and_not_swapped(clip, model):
    from flowmocap.body.skeleton import JOINT_NAMES
    from flowmocap.fit.tracker import lost_joints

    seq = load_sequence(clip)
    scene, pts = _detector_joints2d(seq, model, 3)
    state = FrameState(_f32(seq.gt["poses"][3]), _f32(seq.gt["trans"][3]))
    cfg = TrackerConfig()  # keypoint_sigma 20 px: far is beyond 25 px
    rw, lw = JOINT_NAMES.index("right_wrist"), JOINT_NAMES.index("left_wrist")
    conf = np.ones(24)
    assert not lost_joints(scene, state, (pts, conf), cfg).any()
    moved = pts.copy()
    moved[rw] += [30.0, -10.0]
    assert np.flatnonzero(lost_joints(scene, state, (moved, conf), cfg)).tolist() == [rw]
    assert not lost_joints(scene, state, (moved, np.where(np.arange(24) == rw, 0.8, 1.0)), cfg).any()  # not confident
    near = pts.copy()
    near[rw] += [20.0, 10.0]  # 22 px: within 1.25 sigma
    assert not lost_joints(scene, state, (near, conf), cfg).any()
    swapped = pts.copy()
    swapped[[rw, lw]] = pts[[lw, rw]]  # a detector's left/right swap is not a lost joint
    assert np.linalg.norm(pts[rw] - pts[lw]) > 30.0
    assert not lost_joints(scene, state, (swapped, conf), cfg).any()
    assert not lost_joints(scene, state, None, cfg).any()


def test_a_held_joint_has_the_hold_scale_and_weight_in_e_j(clip, model):
    from flowmocap.fit.joint_terms import keypoint_energy_world
    from flowmocap.fit.objective import keypoint_term
    from flowmocap.vision.keypoint_map import detector_points

    seq = load_sequence(clip)
    scene, pts = _detector_joints2d(seq, model, 3)
    rng = np.random.default_rng(5)
    obs = pts + rng.normal(scale=30.0, size=pts.shape)
    conf = rng.uniform(0.5, 1.0, 24)
    conf[[10, 11]] = 0.0
    cfg = TrackerConfig(keypoint_hold_sigma=70.0, keypoint_hold_weight=3.0)
    hold = np.zeros(24, bool)
    hold[[5, 21]] = True
    with torch.no_grad():
        out, _, _ = scene.forward(_f32(seq.gt["poses"][3]), _f32(seq.gt["trans"][3]))
        points = detector_points(out, cfg)
        got = keypoint_term(scene, out, (obs, conf), 20.0, cfg, hold=hold)
        want = keypoint_energy_world(points, scene.camera, obs, np.where(hold, 3.0 * conf, conf),
                                     np.where(hold, 70.0, 20.0), factor=1.0 / 22)[0]
        plain = keypoint_term(scene, out, (obs, conf), 20.0, cfg)
    assert float(got) == float(want) and float(got) != float(plain)
    assert float(keypoint_term(scene, out, (obs, conf), 20.0, cfg, hold=np.zeros(24, bool))) == float(plain)


def test_a_joint_lost_for_several_frames_is_held_to_its_detection(clip, model, tmp_path):
    """A confident detection that the fit stays far from (here a detector 40 px off on the
    right wrist, the only cue on it besides flow and silhouette) gets a wider E_j scale
    after ``keypoint_hold_frames`` frames, which pulls the wrist towards it; the counts
    are part of the tracker's state (resume)."""
    from flowmocap.body.skeleton import JOINT_NAMES

    seq = load_sequence(clip)
    rw = JOINT_NAMES.index("right_wrist")
    det = []
    for i in range(FRAMES):
        pts = _detector_joints2d(seq, model, i)[1]
        pts[rw] += [-40.0, 0.0]  # away from the left wrist (+40 would land on it here: a swap)
        det.append(pts)
    conf = np.ones(24)
    conf[[10, 11, 22, 23]] = 0.0
    runs = {}
    for K in (0, 2):
        cfg = TrackerConfig(keypoint_hold_frames=K)
        events = []
        j2d, terms = _track_direct(seq, tmp_path / f"k{K}", model, cfg, "0:8", keypoints=lambda i: (det[i], conf),
                                   events=events)
        runs[K] = (j2d, [e for e in events if e["event"] == "held lost joints to the detector"])
    assert runs[0][1] == []
    held = runs[2][1]
    assert [e["frame"] for e in held] == [4, 5, 6, 7] and all(e["joints"] == [rw] for e in held)
    assert held[0]["frames_lost"] == [2]
    truth = np.stack(_true_joints2d(seq, model)[2:8])
    gap = {K: np.linalg.norm(runs[K][0][:, rw] - truth[:, rw], axis=-1) for K in runs}  # towards -40 px in x
    print("right wrist px from the truth, no hold / hold:", gap[0].round(1), gap[2].round(1))
    assert gap[2][-1] > gap[0][-1] + 2.0 and gap[2][-1] > gap[2][1] + 2.0  # (flow and silhouette hold it too)
    np.testing.assert_allclose(runs[2][0][:2], runs[0][0][:2], atol=1e-4)  # the same until the hold

    scene = Scene(model, _f32(seq.gt["betas"])[None], seq.camera)
    tracker = SequenceTracker(scene, TrackerConfig())
    tracker.start(*(FrameState(_f32(seq.gt["poses"][k]), _f32(seq.gt["trans"][k])) for k in (0, 1)), anchored=True)
    tracker.lost[rw] = 7
    again = SequenceTracker(scene, TrackerConfig())
    again.load_state_dict(json.loads(json.dumps(tracker.state_dict())))
    assert again.lost[rw] == 7 and again.lost.sum() == 7
    data = frame_data(seq.mask(2), None, TrackerConfig(), float("nan"), keypoint_observation(det[2], conf))
    assert np.flatnonzero(again.keypoint_hold(data)).tolist() == [rw]
    assert SequenceTracker(scene, TrackerConfig(keypoint_hold_frames=0)).keypoint_hold(data) is None
    assert SequenceTracker(scene, TrackerConfig()).keypoint_hold(data) is None  # nothing lost yet


def test_keypoint_observation_checks():
    j = np.arange(48, dtype=float).reshape(24, 2)
    c = np.full(24, 0.9)
    c[:3] = 0.2
    j[5] = np.nan
    kp, conf = keypoint_observation(j, c)
    assert kp.shape == (24, 2) and conf.shape == (24,)
    assert (conf[:3] == 0).all() and conf[5] == 0 and torch.isfinite(kp).all() and (conf[6:] > 0).all()
    c[:] = 0.1
    c[:3] = 0.9
    assert keypoint_observation(j, c) is None  # fewer than 4 confident joints: no term
    with pytest.raises(InputError, match="differ"):
        keypoint_observation(j, c[:12])


def test_keypoint_observation_minimum_confidence_and_floor():
    j = np.arange(48, dtype=float).reshape(24, 2)
    c = np.linspace(0.0, 0.96, 24)  # 0, 0.04, ..., 0.96
    _, conf = keypoint_observation(j, c)
    assert (conf[c < 0.5] == 0).all() and np.allclose(conf[c >= 0.5], c[c >= 0.5])  # the default: as before
    _, conf = keypoint_observation(j, c, min_confidence=0.0, floor=0.5)
    assert conf[0] == 0  # a joint at confidence 0 is not detected, whatever the floor
    assert np.allclose(conf[1:], np.maximum(c[1:], 0.5))  # the others weigh at least the floor
    _, conf = keypoint_observation(j, c, min_confidence=0.2, floor=0.3)
    assert (conf[c < 0.2] == 0).all() and np.allclose(conf[c >= 0.2], np.maximum(c[c >= 0.2], 0.3))


def test_the_tracker_reads_e_j_confidence_settings_from_the_config(clip, model, tmp_path):
    """(:func:`configured_keypoints`, as the pipeline reads the detections) Joints detected at
    confidence 0.2 enter E_j at the defaults (every detected joint, weighed alike), not at
    ``keypoint_min_confidence`` 0.5 (``--fast``'s), and a floor gives them more weight."""
    cfg = TrackerConfig()
    assert (cfg.keypoint_min_confidence, cfg.keypoint_confidence_floor) == (0.0, 1.0)
    seq = load_sequence(clip)
    truth = _true_joints2d(seq, model)
    conf = np.full(24, 0.2)
    conf[[10, 11, 22, 23]] = 0.0
    base = dict(flow_weight=0.0, silhouette_weight=0.0, keypoint_weight=0.05, kalman=False, temporal_weight=0.0)
    shifted = [j + 4.0 for j in truth]
    settings = {"default": {}, "fast": {"keypoint_min_confidence": 0.5, "keypoint_confidence_floor": 0.0},
                "low": {"keypoint_min_confidence": 0.1, "keypoint_confidence_floor": 0.0},
                "floor": {"keypoint_min_confidence": 0.1, "keypoint_confidence_floor": 0.8}}
    runs = {name: _track_direct(seq, tmp_path / name, model, TrackerConfig(**base, **kw), "0:3",
                                keypoints=lambda i: (shifted[i], conf))
            for name, kw in settings.items()}
    assert not any("keypoints" in t for t in runs["fast"][1])
    first = {k: [t["keypoints"] for t in runs[k][1] if "keypoints" in t] for k in ("default", "low", "floor")}
    assert all(v and np.isfinite(v).all() for v in first.values())
    low, floor, default = first["low"][0], first["floor"][0], first["default"][0]
    assert floor > 2.0 * low  # the same residuals at four times the weight (0.8 against 0.2)
    assert default > floor  # weight 1


def test_rough_pose_weights_follow_the_joints_the_init_states(clip, model):
    """An init.json with a rough pose pulls every joint but the root towards it with
    ``init_rough_pose_weight``, one without (or with the root's alone, as the automatic
    init) with ``init_pose_prior_weight``; a prior weight far above the other terms keeps
    a joint at its rough rotation through the fit, a zero one lets the 2D joints move it."""
    from flowmocap.body.skeleton import JOINT_INDEX
    from flowmocap.fit import energies as en
    from flowmocap.fit.init import fit_frame0, rough_pose_weights

    seq = load_sequence(clip)
    data = noisy_init(seq.gt, frame=0, seed=2)
    spec = parse_init(data, *seq.size)
    named = set(data["pose"])

    assert spec.pose_given.sum() == len(named)
    assert all(spec.pose_given[JOINT_INDEX[n]] for n in named)
    cfg = TrackerConfig(init_pose_prior_weight=7.0, init_rough_pose_weight=70.0)
    w = rough_pose_weights(spec, cfg)
    assert w.shape == (24,) and w[0] == 0.0
    assert (w[1:] == 70.0).all()
    assert parse_init({**data, "pose": {}, "pose72": np.zeros(72).tolist()}, *seq.size).pose_given.all()
    bare = parse_init({"joints2d": data["joints2d"]}, *seq.size)
    assert not bare.pose_given.any() and (rough_pose_weights(bare, cfg)[1:] == 7.0).all()
    root_only = parse_init({"joints2d": data["joints2d"], "pose": {"pelvis": [0.0, 3.0, 0.0]}}, *seq.size)
    assert (rough_pose_weights(root_only, cfg) == np.r_[0.0, np.full(23, 7.0)]).all()
    with pytest.raises(InputError):
        TrackerConfig.load(init_rough_pose_weight=-1.0)

    knee = JOINT_INDEX["left_knee"]
    sil = en.silhouette_target(seq.mask(0))
    stiff = TrackerConfig(init_rough_pose_weight=1e7, init_iterations=15)
    pose, _, _, _ = fit_frame0(model, seq.camera, spec, sil, stiff)
    assert np.allclose(pose.numpy()[3 * knee:3 * knee + 3], spec.pose[3 * knee:3 * knee + 3], atol=1e-3)
    free = TrackerConfig(init_rough_pose_weight=0.0, init_iterations=15)
    pose, _, _, _ = fit_frame0(model, seq.camera, spec, sil, free)
    assert not np.allclose(pose.numpy()[3 * knee:3 * knee + 3], spec.pose[3 * knee:3 * knee + 3], atol=1e-2)


def test_kalman_process_noise_comes_from_the_config():
    """``kalman_rot_accel_noise`` reaches every joint filter (and survives a resume's state
    round trip); a non-positive value is refused."""
    from flowmocap.fit.kalman import PoseFilter
    from flowmocap.fit.tracker import new_filter

    kf = new_filter(np.zeros(72), np.zeros(3), TrackerConfig(kalman_rot_accel_noise=0.005))
    assert all(j.accel_noise == pytest.approx(0.005) for j in kf.joints)
    again = PoseFilter.from_state_dict(json.loads(json.dumps(kf.state_dict())))
    assert all(j.accel_noise == pytest.approx(0.005) for j in again.joints)
    for bad in (0.0, -0.01):
        with pytest.raises(InputError):
            TrackerConfig.load(kalman_rot_accel_noise=bad)


def test_anchor_term_pulls_towards_the_first_frame_of_the_track(clip, model, tmp_path):
    """``E_a`` is ``anchor_weight`` times the squared distance of every joint's rotation but
    the root's from the track's first frame (closed form); the first frame is the start
    of a track someone vouched for, and there is none after an automatic init or a
    re-initialisation; tracking with it stays accurate."""
    from flowmocap.fit.objective import FrameData, frame_energy

    seq = load_sequence(clip)
    gt = seq.gt
    scene = Scene(model, torch.as_tensor(gt["betas"], dtype=torch.float32)[None], seq.camera)
    anchor = torch.as_tensor(gt["poses"][0], dtype=torch.float32)
    delta = torch.zeros(72)
    delta[:3] = 0.7  # the root is free
    delta[3 * 4:3 * 4 + 3] = torch.tensor([0.2, -0.1, 0.05])
    state = FrameState(anchor + delta, torch.as_tensor(gt["trans"][0], dtype=torch.float32))
    cfg = TrackerConfig(anchor_weight=3.0, flow_weight=0.0, silhouette_weight=0.0, limit_weight=0.0,
                        penetration_weight=0.0, temporal_weight=0.0, **DEPTH_CUES_OFF)
    _, terms = frame_energy(scene, state, FrameData(None, None, 1.0, anchor=anchor), cfg, None, None, None)
    assert terms["anchor"] == pytest.approx(3.0 * (0.04 + 0.01 + 0.0025), rel=1e-5)

    # SequenceTracker: the anchor is the first frame of an anchored start, kept through
    # the frames and a state round trip, dropped for good when the monitor re-initialises
    gts = [FrameState(_f32(p), _f32(t)) for p, t in zip(gt["poses"], gt["trans"])]
    cfg = TrackerConfig(anchor_weight=0.5, iterations=3, **DEPTH_CUES_OFF)
    data = lambda i: frame_data(seq.mask(i), None, cfg, 1.0)  # noqa: E731
    asked = []

    def monitor(i, state, scene, mask):
        asked.append(i)
        return (gts[i].clone(), {"why": "test"}) if i == 3 else None

    tr = SequenceTracker(scene, cfg, monitor)
    tr.start(gts[0], gts[1], anchored=True)
    assert torch.equal(tr.anchor.pose, gts[0].pose)
    restored = SequenceTracker(scene, cfg)
    restored.load_state_dict(json.loads(json.dumps(tr.state_dict())))
    assert torch.equal(restored.anchor.pose, gts[0].pose)
    res = tr.step(2, seq.mask(2), data(2))
    assert "anchor" in res.terms and torch.equal(tr.anchor.pose, gts[0].pose)
    res = tr.step(3, seq.mask(3), data(3))
    assert [e["event"] for e in res.events] == ["re-initialised"] and res.events[0]["why"] == "test"
    assert tr.anchor is None and tr.state_dict()["anchor"] is None
    assert torch.equal(res.state.pose, gts[3].pose) and torch.equal(tr.prev.pose, gts[3].pose)
    res = tr.step(4, seq.mask(4), data(4))
    assert "anchor" not in res.terms and tr.anchor is None and asked == [2, 3, 4]
    restored.load_state_dict(json.loads(json.dumps(tr.state_dict())))
    assert restored.anchor is None
    guess = SequenceTracker(scene, cfg)  # an automatic init's start is a guess: no anchor
    guess.start(gts[0], gts[1], anchored=False)
    assert guess.anchor is None and "anchor" not in guess.step(2, seq.mask(2), data(2)).terms

    motion, run = _track(seq, tmp_path / "anchor", model, TrackerConfig(anchor_weight=0.5))  # a known start
    tracked = motion.get("poses_unsmoothed", motion["poses"])  # the tracker's frames, before the smoothing
    np.testing.assert_array_equal(np.asarray(run["tracker"]["anchor"], np.float32), tracked[0])
    col = list(motion["energy_names"]).index("anchor")
    assert np.isfinite(motion["energies"][2:, col]).all()
    assert evaluate(motion, seq.gt)["local_cm"] < 4.0
    bare = {"joints2d": noisy_init(gt, frame=0, seed=1)["joints2d"]}  # no rough pose
    motion, run = _track(seq, tmp_path / "bare", model, TrackerConfig(anchor_weight=0.5, init_iterations=10,
                                                                      init_flow_iterations=5), frames="0:4",
                         init=bare)
    assert run["tracker"]["anchor"] is None
    assert np.isnan(motion["energies"][:, col]).all()
    with pytest.raises(InputError):
        TrackerConfig.load(anchor_weight=-1.0)


def test_anchor_any_start_anchors_a_guessed_start_and_each_refit(clip, model, tmp_path):
    """With ``anchor_any_start`` the automatic init's start is anchored too (the pipeline
    passes it as ``anchored``), and a re-initialisation moves the anchor to the refit's
    pose instead of dropping it; the state round trip keeps it."""
    seq = load_sequence(clip)
    gt = seq.gt
    scene = Scene(model, torch.as_tensor(gt["betas"], dtype=torch.float32)[None], seq.camera)
    gts = [FrameState(_f32(p), _f32(t)) for p, t in zip(gt["poses"], gt["trans"])]
    cfg = TrackerConfig(anchor_weight=0.5, anchor_any_start=True, iterations=3, **DEPTH_CUES_OFF)
    data = lambda i: frame_data(seq.mask(i), None, cfg, 1.0)  # noqa: E731
    tr = SequenceTracker(scene, cfg, lambda i, state, scene, mask: (gts[i].clone(), {"why": "test"}) if i == 3
                         else None)
    tr.start(gts[0], gts[1], anchored=True)
    tr.step(2, seq.mask(2), data(2))
    res = tr.step(3, seq.mask(3), data(3))
    assert [e["event"] for e in res.events] == ["re-initialised"]
    assert torch.equal(tr.anchor.pose, gts[3].pose)
    assert "anchor" in tr.step(4, seq.mask(4), data(4)).terms
    restored = SequenceTracker(scene, cfg)
    restored.load_state_dict(json.loads(json.dumps(tr.state_dict())))
    assert torch.equal(restored.anchor.pose, gts[3].pose)

    bare = {"joints2d": noisy_init(gt, frame=0, seed=1)["joints2d"]}  # no rough pose: a guessed start
    motion, run = _track(seq, tmp_path / "bare", model, TrackerConfig(anchor_weight=0.5, anchor_any_start=True,
                                                                      init_iterations=10, init_flow_iterations=5),
                         frames="0:4", init=bare)
    tracked = motion.get("poses_unsmoothed", motion["poses"])  # the tracker's frames, before the smoothing
    np.testing.assert_array_equal(np.asarray(run["tracker"]["anchor"], np.float32), tracked[0])
    col = list(motion["energy_names"]).index("anchor")
    assert np.isfinite(motion["energies"][2:, col]).all()
    with pytest.raises(InputError, match="anchor_any_start"):
        TrackerConfig.load(anchor_any_start=1)


def test_the_flow_step_of_the_init_keeps_frame_0_to_its_rough_pose(clip, model, tmp_path):
    """Init step 3 (the flow step on frame 1 while frame 0 may still move) keeps frame 0's
    prior towards the init's rough pose: with that prior far above the other terms, frame
    0 leaves the tracker at the rough pose; with it off, the flow and silhouettes move it."""
    seq = load_sequence(clip)
    spec = parse_init(noisy_init(seq.gt, frame=0, seed=4), *seq.size)
    stated = np.repeat(spec.pose_given, 3)
    stated[:3] = False  # the root has no prior: the 2D joints place it
    moved = {}
    for name, weight in (("stiff", 1e7), ("free", 0.0)):
        cfg = TrackerConfig(init_rough_pose_weight=weight, init_iterations=15, init_flow_iterations=10,
                            anchor_weight=0.0)
        motion, _ = _track(seq, tmp_path / name, model, cfg, init=noisy_init(seq.gt, frame=0, seed=4), frames="0:2")
        moved[name] = np.abs(motion["poses"][0][stated] - spec.pose[stated]).max()
    assert moved["stiff"] < 2e-3
    assert moved["free"] > 0.05


def _camera_joints3d(seq, i):
    """Ground-truth joints of frame ``i`` in the camera's axes (as a 3D detector gives them)."""
    return np.asarray(seq.gt["joints3d"][i], np.float64) @ np.asarray(seq.camera.R).T, np.full(24, 0.9)


def test_limb_depth_term_in_the_frame_energy(clip, model, tmp_path):
    """E_d in the per-frame objective: zero at the true pose when the detector's 3D joints
    are the truth in the camera's axes, positive with a shin bent out of place; the tracker
    takes them per frame and records the term."""
    from flowmocap.body.skeleton import JOINT_INDEX
    from flowmocap.fit.objective import FrameData, frame_energy

    seq = load_sequence(clip)
    gt = seq.gt
    scene = Scene(model, torch.as_tensor(gt["betas"], dtype=torch.float32)[None], seq.camera)
    # the "detector's" 3D joints are the model's own: no keypoint offsets
    cfg = TrackerConfig(limb_depth_weight=2.0, silhouette_weight=0.0, limit_weight=0.0, penetration_weight=0.0,
                        keypoint_offsets=False)
    data = FrameData(mask=None, silhouette=None, person_pixels=1.0, joints3d=_camera_joints3d(seq, 2))
    pose = torch.as_tensor(gt["poses"][2], dtype=torch.float32)
    trans = torch.as_tensor(gt["trans"][2], dtype=torch.float32)
    _, terms = frame_energy(scene, FrameState(pose, trans), data, cfg, None, None, None)
    assert terms["limb_depth"] < 1e-6
    bent = pose.clone()
    bent[3 * JOINT_INDEX["left_knee"]] += 0.8
    _, terms = frame_energy(scene, FrameState(bent, trans), data, cfg, None, None, None)
    assert terms["limb_depth"] > 1e-3

    asked = []

    def joints3d(i):
        asked.append(i)
        return _camera_joints3d(seq, i)

    _, terms = _track_direct(seq, tmp_path / "ed", model, TrackerConfig(limb_depth_weight=2.0), "0:4",
                             joints3d=joints3d)
    assert sorted(asked) == [2, 3]
    assert len(terms) == 2 and all(np.isfinite(t["limb_depth"]) for t in terms)  # frames 2 and 3 have the term


def test_the_tracker_flips_a_limb_back_when_asked(clip, model):
    """``flip_test``: a track whose previous frame has the left shin mirrored in depth (as
    after a depth flip; same 2D points) gets it flipped back on the next frame where the
    detector's 3D joints (E_3d) say so, and records the flip; without ``flip_test`` the
    step is that of before (no flip events)."""
    from flowmocap.body.skeleton import JOINT_INDEX
    from flowmocap.fit.flip import flipped_pose, limb_name

    seq = load_sequence(clip)
    gt = seq.gt
    scene = Scene(model, _f32(gt["betas"])[None], seq.camera)
    shin = (JOINT_INDEX["left_knee"], JOINT_INDEX["left_ankle"])
    first = FrameState(_f32(gt["poses"][0]), _f32(gt["trans"][0]))
    second = FrameState(_f32(gt["poses"][1]), _f32(gt["trans"][1]))
    second.pose = flipped_pose(scene, second.pose, second.trans, shin)
    found = {}
    for flip in (False, True):
        cfg = TrackerConfig(kalman=False, flip_test=flip, detector3d_weight=50.0, iterations=5, limb_depth_weight=0.0)
        tracker = SequenceTracker(scene, cfg)
        tracker.start(first, second, anchored=False)
        data = frame_data(seq.mask(2), None, cfg, float("nan"))
        data.joints3d = _camera_joints3d(seq, 2)
        res = tracker.step(2, seq.mask(2), data)
        found[flip] = [e for e in res.events if e["event"] == "limb flipped in depth"]
        with torch.no_grad():
            j = scene.camera.to_camera(scene.forward(res.state.pose, res.state.trans)[0].joints[0]).numpy()
        true = np.asarray(gt["joints3d"][2]) @ np.asarray(seq.camera.R).T
        d, t = j[shin[1]] - j[shin[0]], true[shin[1]] - true[shin[0]]
        found[flip, "cos"] = float(d @ t / np.linalg.norm(d) / np.linalg.norm(t))
    assert found[False] == []
    assert [e["limb"] for e in found[True]] == [limb_name(shin)] and found[True][0]["frame"] == 2
    assert found[True, "cos"] > 0.95 and found[True, "cos"] > found[False, "cos"]
