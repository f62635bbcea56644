"""Synthetic sequences: folder layout, exact masks, determinism, DIS flow vs true flow."""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from flowmocap.body import load_body_model
from flowmocap.errors import InputError
from flowmocap.geometry import PinholeCamera
from flowmocap.render import rasterize
from flowmocap.synth import synthesize

DEFAULT_MODEL = resources.files("flowmocap.body") / "data" / "default_neutral.npz"


@pytest.fixture(scope="module")
def model_path(toy_files):
    """The default body when it is there (what users render), else the toy body."""
    return "default" if Path(str(DEFAULT_MODEL)).exists() else toy_files["npz"]


@pytest.fixture(scope="module")
def walk_seq(tmp_path_factory, model_path):
    out = tmp_path_factory.mktemp("synth") / "walk"
    res = synthesize("builtin:walk", out, fps=60, start=10, frames=6, size="320x240",
                     betas="random", seed=7, model=model_path)
    return out, res


def test_sequence_folder(walk_seq, model_path):
    out, res = walk_seq
    T = 6
    for sub, ext, n in (("frames", "png", T), ("masks", "png", T), ("flow", "npz", T - 1)):
        files = sorted((out / sub).glob(f"*.{ext}"))
        assert len(files) == n, sub
    assert (out / "frames" / "000000.png").exists() and (out / "flow" / "000001.npz").exists()
    img = cv2.imread(str(out / "frames" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (240, 320, 3) and img.dtype == np.uint8
    cam = PinholeCamera.from_dict(json.loads((out / "camera.json").read_text()))
    assert (cam.width, cam.height) == (320, 240)
    gt = np.load(out / "gt.npz")
    assert gt["poses"].shape == (T, 72) and gt["trans"].shape == (T, 3) and gt["betas"].shape == (10,)
    assert gt["joints3d"].shape == (T, 24, 3) and gt["joints2d"].shape == (T, 24, 2)
    assert np.abs(gt["betas"]).max() > 0  # "random" shape
    np.testing.assert_array_equal(gt["source_frames"], np.arange(10, 16))
    np.testing.assert_allclose(gt["joints2d"], cam.project(gt["joints3d"].astype(np.float64)), atol=1e-3)
    # Every joint is in the picture.
    j2 = gt["joints2d"]
    assert (j2[..., 0] > 0).all() and (j2[..., 0] < 320).all() and (j2[..., 1] > 0).all() and (j2[..., 1] < 240).all()
    meta = json.loads((out / "meta.json").read_text())
    assert meta["num_frames"] == T and meta["fps"] == 60 and meta["seed"] == 7
    assert meta["source"] == "builtin:walk"


def test_masks_equal_rasterised_silhouette(walk_seq, model_path):
    out, _ = walk_seq
    gt = np.load(out / "gt.npz")
    cam = PinholeCamera.from_dict(json.loads((out / "camera.json").read_text()))
    model = load_body_model(model_path, dtype=torch.float64)
    with torch.no_grad():
        verts = model(betas=torch.as_tensor(gt["betas"][None], dtype=torch.float64),
                      pose=torch.as_tensor(gt["poses"], dtype=torch.float64),
                      trans=torch.as_tensor(gt["trans"], dtype=torch.float64)).vertices.numpy()
    for i in range(gt["poses"].shape[0]):
        mask = cv2.imread(str(out / "masks" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
        r = rasterize(cam.project(verts[i]), cam.depth(verts[i]), model.faces_np, cam.height, cam.width)
        np.testing.assert_array_equal(mask > 0, r.mask)
        assert r.mask.sum() > 500
        # Background flow is zero, body flow non-zero where the body moves.
        if i:
            flow = np.load(out / "flow" / f"{i:06d}.npz")["flow"]
            assert flow.shape == (240, 320, 2) and flow.dtype == np.float32
            assert not flow[~r.mask].any() and np.abs(flow[r.mask]).mean() > 0.5


def test_deterministic_per_seed(walk_seq, model_path, tmp_path):
    out, _ = walk_seq
    # Same seed and frames, camera from the first run's camera.json: the same bytes.
    again = synthesize("builtin:walk", tmp_path / "again", fps=60, start=10, frames=6, size=None,
                       camera=out / "camera.json", betas="random", seed=7, model=model_path)
    for name in ("frames/000000.png", "frames/000005.png", "masks/000005.png", "flow/000005.npz", "camera.json"):
        assert (out / name).read_bytes() == (again.out_dir / name).read_bytes(), name
    other = synthesize("builtin:walk", tmp_path / "other", fps=60, start=10, frames=1, size=None,
                       camera=out / "camera.json", betas="random", seed=8, model=model_path)
    assert (out / "frames/000000.png").read_bytes() != (other.out_dir / "frames/000000.png").read_bytes()
    with pytest.raises(InputError, match="already holds a sequence"):
        synthesize("builtin:walk", tmp_path / "other", frames=1, size="320x240", model=model_path)
    from flowmocap.io import builtin_walk

    short = builtin_walk(load_body_model(model_path), fps=30, frames=3)
    with pytest.raises(InputError, match="frames 0..4 requested but the motion has 3 frames"):
        synthesize(short, tmp_path / "short", frames=5, size="320x240", model=model_path)


def test_dis_flow_matches_true_flow(walk_seq):
    """OpenCV DIS (PRESET_MEDIUM) on two rendered frames vs the true flow, on the body.

    At 60 fps (HumanEva's rate, the paper's benchmark); at 30 fps the swinging foot
    moves 15-25 px per frame and DIS's mean error on the body is 0.4-1.3 px.
    """
    out, _ = walk_seq
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    errs, mags = [], []
    for i in range(1, 6):
        prev = cv2.imread(str(out / "frames" / f"{i - 1:06d}.png"), cv2.IMREAD_GRAYSCALE)
        cur = cv2.imread(str(out / "frames" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
        mask = cv2.imread(str(out / "masks" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
        true = np.load(out / "flow" / f"{i:06d}.npz")["flow"]
        observed = dis.calc(cur, prev, None)  # backward: frame i -> i-1, at frame i's pixels
        errs.append(np.linalg.norm(observed - true, axis=-1)[mask])
        mags.append(np.linalg.norm(true, axis=-1)[mask])
    epe = float(np.concatenate(errs).mean())
    print(f"\nDIS medium vs true flow on the body: mean EPE {epe:.3f} px "
          f"(true flow mean {np.concatenate(mags).mean():.2f} px)")
    assert np.concatenate(mags).mean() > 1.5  # the body does move
    assert epe < 1.0
