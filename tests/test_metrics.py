"""Evaluation metrics on hand-made cases with known answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flowmocap.body.skeleton import EVAL_JOINTS
from flowmocap.errors import InputError
from flowmocap.eval.metrics import (
    acceleration_error,
    depth_split_error,
    global_procrustes_error,
    joint2d_error,
    local_procrustes_error,
    mpjpe,
)
from flowmocap.vision.masks import mask_iou


def _skeleton(T=5, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(0, 0.3, (T, 24, 3))


def test_similarity_transform_gives_zero_aligned_error_and_known_unaligned_error():
    gt = _skeleton()
    R = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    pred = 1.3 * gt @ R.T + np.array([0.5, -0.2, 2.0])
    assert np.allclose(local_procrustes_error(pred, gt), 0, atol=1e-9)
    assert np.allclose(global_procrustes_error(pred, gt), 0, atol=1e-9)
    # unaligned, root-relative: |1.3 R (x - r) - (x - r)| per joint
    rel = gt[:, list(EVAL_JOINTS)] - gt[:, :1]
    expected = np.linalg.norm(1.3 * rel @ R.T - rel, axis=-1).mean(-1)
    assert np.allclose(mpjpe(pred, gt), expected)
    assert mpjpe(pred, gt).mean() > 0.05


def test_per_frame_transforms_separate_local_from_global():
    gt = _skeleton(T=4)
    pred = gt.copy()
    pred[2] = gt[2] @ Rotation.from_rotvec([0, 0.8, 0]).as_matrix().T + 0.4  # one frame jumps
    assert np.allclose(local_procrustes_error(pred, gt), 0, atol=1e-9)
    assert global_procrustes_error(pred, gt).mean() > 0.02


def test_constant_acceleration_gives_the_known_error():
    T, a = 10, np.array([0.0, -0.002, 0.001])  # m / frame^2
    t = np.arange(T, dtype=float)[:, None, None]
    gt = _skeleton(T=1) + 0.01 * t  # constant velocity: zero acceleration
    pred = gt + 0.5 * a * t**2
    err = acceleration_error(pred, gt)
    assert err.shape == (T - 2,)
    assert np.allclose(err, np.linalg.norm(a))
    # a constant offset or a constant velocity difference costs nothing
    assert np.allclose(acceleration_error(gt + 0.3 + 0.05 * t, gt), 0, atol=1e-12)
    with pytest.raises(InputError):
        acceleration_error(gt[:2], gt[:2])


def test_depth_split_error_separates_image_plane_and_depth():
    """A joint moved along the camera's viewing axis shows as depth error only, one moved
    across it as image-plane error only; moving the whole body (the root too) is no error."""
    gt = _skeleton()
    R = Rotation.from_rotvec([0.2, 1.1, -0.3]).as_matrix()  # world -> camera
    view, across = R.T @ np.array([0.0, 0.0, 1.0]), R.T @ np.array([0.6, 0.8, 0.0])
    pred = gt + np.array([0.4, -1.0, 2.0])  # a global shift: no root-relative error
    pred[:, 5] += 0.07 * view  # 7 cm further from the camera
    pred[:, 9] -= 0.03 * across  # 3 cm across the view
    pred[:3, 11] -= 0.05 * view  # nearer, in 3 of the 5 frames
    plane, depth, bias = depth_split_error(pred, gt, R)
    expected = np.zeros((3, 24))
    expected[1, 5] = expected[2, 5] = 0.07
    expected[0, 9] = 0.03
    expected[1, 11], expected[2, 11] = 0.03, -0.03
    np.testing.assert_allclose(np.stack([plane, depth, bias]), expected, atol=1e-12)
    with pytest.raises(InputError):
        depth_split_error(pred, gt, np.eye(2))


def test_joint2d_error():
    gt = np.zeros((3, 24, 2))
    pred = gt + np.array([3.0, 4.0])
    assert np.allclose(joint2d_error(pred, gt), 5.0)
    with pytest.raises(InputError):
        joint2d_error(pred[:, :, :1], gt[:, :, :1])


def test_rendered_silhouette_of_ground_truth_matches_synthetic_masks(tmp_path):
    from flowmocap.body import load_body_model
    from flowmocap.eval.metrics import render_silhouettes
    from flowmocap.io.sequence import load_sequence
    from flowmocap.synth import synthesize

    synthesize("builtin:walk", tmp_path / "s", fps=30, frames=3, size="96x72", betas="random", seed=1, flow=False,
               supersample=1)
    seq = load_sequence(tmp_path / "s")
    model = load_body_model("default")
    sil = render_silhouettes(model, seq.gt["poses"], seq.gt["trans"], seq.gt["betas"], seq.camera)
    masks = np.stack([seq.mask(i) for i in range(3)])
    assert mask_iou(sil, masks).min() > 0.98


def test_metrics_agree_on_nan_empty_and_joint_indices():
    """A NaN crashed the Procrustes metrics inside torch's SVD where mpjpe gave NaN; no frames
    gave [] in one and a message about weights in another; a 13-joint array or a joint index
    past J was an IndexError."""
    import numpy as np
    import pytest

    from flowmocap.errors import InputError
    from flowmocap.eval.metrics import (acceleration_error, global_procrustes_error, joint2d_error,
                                        local_procrustes_error, mpjpe)

    rng = np.random.default_rng(3)
    gt = rng.normal(0, 0.3, (6, 24, 3))
    pred = gt + rng.normal(0, 0.01, gt.shape)
    holed = pred.copy()
    holed[2, 5] = np.nan
    for metric in (local_procrustes_error, global_procrustes_error, mpjpe):
        whole, with_hole = metric(pred, gt), metric(holed, gt)
        assert np.isnan(with_hole[2]) and np.isfinite(np.delete(with_hole, 2)).all(), metric.__name__
    np.testing.assert_allclose(np.delete(local_procrustes_error(holed, gt), 2), np.delete(local_procrustes_error(pred, gt), 2))
    np.testing.assert_allclose(global_procrustes_error(holed[[0, 1, 3, 4, 5]], gt[[0, 1, 3, 4, 5]]),
                               np.delete(global_procrustes_error(holed, gt), 2))
    for metric in (local_procrustes_error, global_procrustes_error, mpjpe, acceleration_error):
        with pytest.raises(InputError, match="no frames"):
            metric(np.zeros((0, 24, 3)), np.zeros((0, 24, 3)))
        with pytest.raises(InputError, match="joint index .* outside the 13 joints"):
            metric(gt[:, :13], gt[:, :13])
    assert np.allclose(mpjpe(gt[:, :13], gt[:, :13], joints=range(13)), 0)
    with pytest.raises(InputError, match="joint index 99"):
        mpjpe(gt, gt, root=99)
    with pytest.raises(InputError, match="joint index 30"):
        joint2d_error(gt[..., :2], gt[..., :2], joints=[0, 30])
