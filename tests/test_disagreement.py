"""flowmocap.fit.disagreement: how far the run's 3D sources part, per frame and joint."""

import numpy as np
import pytest

from flowmocap.body.skeleton import EVAL_JOINTS
from flowmocap.errors import InputError
from flowmocap.fit.disagreement import MIN_ALIGN_POINTS, source_disagreement, to_body_joints
from flowmocap.geometry.procrustes import similarity_procrustes


def _turned(x, seed):
    """``x (T, P, 3)`` under a random similarity per frame."""
    rng = np.random.default_rng(seed)
    out = np.empty_like(x)
    for t in range(len(x)):
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        R *= np.sign(np.linalg.det(R))
        out[t] = rng.uniform(0.5, 2.0) * x[t] @ R.T + rng.normal(size=3)
    return out


def _brute_force(first, others):
    """The definition, frame by frame and point by point."""
    T, P, _ = first.shape
    srcs = [first]
    for o in others:
        a = np.full_like(first, np.nan)
        for t in range(T):
            m = np.isfinite(o[t]).all(-1) & np.isfinite(first[t]).all(-1)
            if m.sum() >= MIN_ALIGN_POINTS:
                _, s, R, tr = similarity_procrustes(o[t][m], first[t][m])
                a[t] = s * o[t] @ R.T + tr
        srcs.append(a)
    out = np.full((T, P), np.nan)
    for t in range(T):
        for p in range(P):
            d = [np.linalg.norm(srcs[i][t, p] - srcs[j][t, p]) for i in range(len(srcs))
                 for j in range(i + 1, len(srcs))
                 if np.isfinite(srcs[i][t, p]).all() and np.isfinite(srcs[j][t, p]).all()]
            if d:
                out[t, p] = np.mean(d)
    return out


def test_sources_that_differ_by_a_similarity_agree():
    x = np.random.default_rng(0).normal(0, 0.3, (6, 13, 3)) + (0, 0, 4)
    d = source_disagreement(x, [_turned(x, 1), _turned(x, 2)])
    assert d.shape == (6, 13)
    np.testing.assert_allclose(d, 0.0, atol=1e-9)


def test_one_point_moved_in_one_source_is_the_largest_and_matches_the_definition():
    rng = np.random.default_rng(3)
    x = rng.normal(0, 0.3, (5, 13, 3)) + (0, 0, 4)
    moved = x.copy()
    moved[:, 5] += (0.0, 0.0, 0.4)  # a wrist 40 cm deeper in the lifter's shape
    lifter, detector = _turned(moved, 4), _turned(x + rng.normal(0, 0.005, x.shape), 5)
    d = source_disagreement(x, [lifter, detector])
    np.testing.assert_allclose(d, _brute_force(x, [lifter, detector]), atol=1e-9)
    assert (d.argmax(1) == 5).all()
    # two of the three pairs hold the 40 cm (less what the alignment spreads over the others)
    assert ((d[:, 5] > 0.15) & (d[:, 5] < 0.4 * 2 / 3 + 0.02)).all(), d[:, 5]
    assert (np.delete(d, 5, axis=1) < 0.1).all()


def test_missing_points_and_sources():
    rng = np.random.default_rng(6)
    x = rng.normal(0, 0.3, (4, 13, 3)) + (0, 0, 4)
    lifter = _turned(x + rng.normal(0, 0.02, x.shape), 7)
    detector = _turned(x + rng.normal(0, 0.02, x.shape), 8)
    lifter[1] = np.nan                       # no lifted pose in frame 1: the fit and the detector remain
    detector[2, 3] = np.nan                  # the detector lacks one point in frame 2
    detector[3, : 13 - MIN_ALIGN_POINTS + 1] = np.nan  # too few shared points to align: left out of frame 3
    first = x.copy()
    first[0, 0] = np.nan                     # the fit lacks a point: the other two still compare it
    d = source_disagreement(first, [lifter, detector])
    np.testing.assert_allclose(d, _brute_force(first, [lifter, detector]), atol=1e-9)
    assert np.isfinite(d).all()
    only_fit = source_disagreement(first, [np.full_like(x, np.nan)])
    assert np.isnan(only_fit).all()          # fewer than two sources: no value
    with pytest.raises(InputError, match="shape"):
        source_disagreement(x, [x[:, :12]])
    with pytest.raises(InputError, match="first"):
        source_disagreement(x[0], [])


def test_to_body_joints_puts_the_13_in_their_places():
    v = np.arange(26, dtype=float).reshape(2, 13)
    out = to_body_joints(v)
    assert out.shape == (2, 24)
    np.testing.assert_array_equal(out[:, list(EVAL_JOINTS)], v)
    assert np.isnan(np.delete(out, list(EVAL_JOINTS), axis=1)).all()
    with pytest.raises(InputError):
        to_body_joints(np.zeros((2, 12)))


def test_review_frames_marks_the_tenth_where_the_sources_part_most():
    from flowmocap.fit.disagreement import review_frames

    d = np.full((21, 24), np.nan)
    d[:20, :13] = np.arange(20)[:, None] * 0.01  # frame means 0.00 .. 0.19 m; frame 20 has none
    d[3, 0] = np.nan  # a joint without sources leaves the frame's mean to the others
    per_frame, flagged = review_frames(d)
    np.testing.assert_allclose(per_frame[:20], np.arange(20) * 0.01)
    assert np.isnan(per_frame[20]) and not flagged[20]
    np.testing.assert_array_equal(np.flatnonzero(flagged), [18, 19])  # at or above the 90th percentile
    assert review_frames(d, share=1.0)[1][:20].all()
    assert not review_frames(np.full((4, 24), np.nan))[1].any()
    with pytest.raises(InputError):
        review_frames(d, share=0.0)
    with pytest.raises(InputError):
        review_frames(d[0])
