"""The per-frame keypoint baseline on a tiny synthetic clip, and its keypoint noise model."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from flowmocap.body import load_body_model
from flowmocap.errors import InputError
from flowmocap.eval.baseline import (
    KEYPOINT_JOINTS,
    BaselineConfig,
    Skeleton,
    detector_keypoints,
    run_baseline,
)
from flowmocap.eval.protocol import noisy_init
from flowmocap.eval.scoring import score_result
from flowmocap.fit.init import parse_init
from flowmocap.io.results import read_result
from flowmocap.io.sequence import load_sequence
from flowmocap.synth import synthesize

FRAMES = 4


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    d = tmp_path_factory.mktemp("bl") / "seq"
    synthesize("builtin:walk", d, fps=30, frames=FRAMES, size="320x240", betas="random", seed=3, azimuth=70.0,
               distance=3.2, flow=False, supersample=1)
    return load_sequence(d)


def test_detector_keypoints_noise_and_outliers():
    gt = np.random.default_rng(0).uniform(0, 500, (400, 24, 2))
    kp, conf = detector_keypoints(gt, noise_px=3.0, outlier_rate=0.05, outlier_px=(20, 60), seed=1)
    given = conf[0] > 0
    assert given.sum() == len(KEYPOINT_JOINTS) == 14
    assert np.isnan(kp[:, ~given]).all()
    d = np.linalg.norm(kp[:, given] - gt[:, given], axis=-1)
    outliers = d > 15
    assert 0.03 < outliers.mean() < 0.07
    assert d[outliers].max() < 60 + 6 * 3
    assert 2.5 < np.sqrt((d[~outliers] ** 2).mean() / 2) < 3.5
    again, _ = detector_keypoints(gt, seed=1)
    assert np.array_equal(np.nan_to_num(kp), np.nan_to_num(again))


def test_skeleton_matches_the_model():
    model = load_body_model("default")
    betas = torch.randn(1, 10) * 0.5
    pose, trans = torch.randn(72) * 0.3, torch.randn(3)
    out = model(betas=betas, pose=pose[None], trans=trans[None])
    joints, tf = Skeleton(model, betas)(pose, trans)
    assert torch.allclose(joints, out.joints[0], atol=1e-5)
    assert torch.allclose(tf, out.transforms, atol=1e-5)


def test_baseline_fits_each_frame_and_writes_a_scorable_result(clip, tmp_path):
    model = load_body_model("default")
    init = parse_init(noisy_init(clip.gt, seed=0), *clip.size)
    kp, conf = detector_keypoints(clip.gt["joints2d"], seed=2)
    cfg = BaselineConfig(iterations=10, orient_iterations=10)
    out = tmp_path / "baseline"
    run = run_baseline(clip, out, model, clip.camera, init, kp, conf, cfg=cfg, progress=False)
    assert run["status"] == "finished"
    motion, run = read_result(out)
    assert motion["joints3d"].shape == (FRAMES, 24, 3)
    assert motion["poses"].shape == (FRAMES, 72)
    assert list(motion["frame_index"]) == list(range(FRAMES))
    assert len(run["timings"]["frame_s"]) == FRAMES
    s = score_result(out, clip)
    for k in ("local_cm", "global_cm", "mpjpe_cm", "accel_mm", "px2d", "iou", "s_per_frame"):
        assert s[k] is not None and np.isfinite(s[k]), k
    # a working fit lands near the keypoints and the body; a broken one does not
    assert s["px2d"] < 15.0
    assert s["local_cm"] < 20.0
    assert s["iou"] > 0.5
    # a finished result is not silently overwritten; resuming a finished run is a no-op
    with pytest.raises(InputError):
        run_baseline(clip, out, model, clip.camera, init, kp, conf, cfg=cfg, progress=False)
    run_baseline(clip, out, model, clip.camera, init, kp, conf, cfg=cfg, resume=True, progress=False)
    assert read_result(out)[0]["poses"].shape == (FRAMES, 72)


def test_baseline_resumes_an_interrupted_run(clip, tmp_path):
    model = load_body_model("default")
    init = parse_init(noisy_init(clip.gt, seed=0), *clip.size)
    kp, conf = detector_keypoints(clip.gt["joints2d"], seed=2)
    cfg = BaselineConfig(iterations=5, orient_iterations=5, pose_prior_weights=(100.0,))
    out = tmp_path / "b"
    run_baseline(clip, out, model, clip.camera, init, kp, conf, cfg=cfg, progress=False)
    full, _ = read_result(out)
    # cut the result back to 2 frames, as an interrupted run leaves it
    from flowmocap.io.results import write_motion, write_run

    motion, run = read_result(out)
    cut = {k: (v[:2] if k in ("poses", "trans", "joints3d", "joints2d", "energies", "frame_index") else v)
           for k, v in motion.items()}
    run["status"] = "running"
    run["timings"]["frame_s"] = run["timings"]["frame_s"][:2]
    write_motion(out, cut)
    write_run(out, run)
    run_baseline(clip, out, model, clip.camera, init, kp, conf, cfg=cfg, resume=True, progress=False)
    again, run = read_result(out)
    assert run["status"] == "finished"
    assert np.allclose(again["joints3d"], full["joints3d"], atol=1e-4)
    with pytest.raises(InputError):
        run_baseline(clip, out, model, clip.camera, init, kp, conf, cfg=BaselineConfig(), resume=True, progress=False)


def test_wrong_keypoint_shape_is_an_input_error(clip, tmp_path):
    model = load_body_model("default")
    init = parse_init(noisy_init(clip.gt, seed=0), *clip.size)
    with pytest.raises(InputError, match="keypoints must be"):
        run_baseline(clip, tmp_path / "x", model, clip.camera, init, np.zeros((2, 24, 2)), np.ones((2, 24)))


@pytest.mark.parametrize("key", ["joints3d", "joints2d"])
def test_a_ground_truth_shorter_than_the_results_frames_is_a_data_error(tmp_path, key):
    """score_result against a sequence whose gt.npz holds fewer frames than the result's
    frame numbers reach is a DataError naming gt.npz (not an IndexError), as a sequence
    with too few frames already is."""
    from flowmocap.errors import DataError
    from flowmocap.io.results import write_motion, write_run
    from flowmocap.io.sequence import Sequence

    write_motion(tmp_path / "res", {"poses": np.zeros((4, 72)), "trans": np.zeros((4, 3)), "betas": np.zeros(10),
                                    "joints3d": np.zeros((4, 24, 3)), "joints2d": np.zeros((4, 24, 2)),
                                    "frame_index": np.arange(4)})
    write_run(tmp_path / "res", {"flowmocap": "test", "status": "finished"})
    gt = {"joints3d": np.zeros((4, 24, 3)), "joints2d": np.zeros((4, 24, 2))}
    gt[key] = gt[key][:2]
    seq = Sequence(root=tmp_path / "seq", frames=[tmp_path / f"{i}.png" for i in range(4)], masks=None, camera=None,
                   gt=gt, size=(64, 48))
    with pytest.raises(DataError, match=rf"gt\.npz '{key}' has 2 frames but the result has frame 3"):
        score_result(tmp_path / "res", seq)
