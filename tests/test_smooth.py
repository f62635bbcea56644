"""Offline smoothing on SO(3) (flowmocap.fit.smooth) against closed forms and scipy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import savgol_filter
from scipy.spatial.transform import Rotation

from flowmocap.errors import InputError
from flowmocap.fit.smooth import (savgol_weights, smooth_motion, smooth_rotations, smooth_translations,
                                  window_frames)


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
