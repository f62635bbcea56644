"""Where the 3D is least sure: how far the run's 3D sources disagree, per frame and joint.

A monocular 3D pose has errors no one source reveals, but the run holds three estimates of
each frame's 13 scored points that err in different ways: the tracked fit (flow,
silhouette, keypoints, priors), the keypoint lifter (:mod:`flowmocap.vision.lifter`) and
the detector's own 3D (MediaPipe's world landmarks). Each other source is aligned onto
the first by a similarity per frame (so only its shape counts, at the fit's place and
size), and each point gets the mean of its pairwise distances between the sources.

None of them says *which* source is right (docs/experiments.md, "Choosing the 3D source
joint by joint"), but where they part the finished motion is often wrong: on the three
suites of issue 18 the value ranks the worst tenth of joint-frames with an area under the
ROC curve of about 0.8 (``benchmarks/disagreement.py``). It is a flag for review and
clean-up, not a calibrated error bar.
"""

from __future__ import annotations

import numpy as np

from flowmocap.body.skeleton import EVAL_JOINTS
from flowmocap.errors import InputError

__all__ = ["MIN_ALIGN_POINTS", "REVIEW_SHARE", "review_frames", "source_disagreement", "to_body_joints"]

#: A source is aligned onto the first in a frame only where both give at least this many points.
MIN_ALIGN_POINTS = 4
#: The share of a run's frames :func:`review_frames` marks: those where the sources part most.
REVIEW_SHARE = 0.1


def source_disagreement(first: np.ndarray, others: list[np.ndarray]) -> np.ndarray:
    """Per frame and point, the mean pairwise distance between 3D sources.

    Args:
        first: ``(T, P, 3)`` metres, the source the others are aligned onto (the tracked
            fit's points); NaN where it gives none.
        others: each ``(T, P, 3)``, any units and axes (NaN where it gives none): aligned
            onto ``first`` per frame by a similarity Procrustes over the points both give
            (:func:`~flowmocap.geometry.procrustes.similarity_procrustes`), in frames where
            they share at least :data:`MIN_ALIGN_POINTS`; left out of that frame otherwise.

    Returns:
        ``(T, P)`` metres: the mean over the pairs of sources that give the point of the
        distance between them; NaN where fewer than two give it.

    Raises:
        InputError: shapes that do not match.
    """
    from flowmocap.geometry.procrustes import similarity_procrustes

    first = np.asarray(first, np.float64)
    if first.ndim != 3 or first.shape[-1] != 3:
        raise InputError(f"first must be (T, P, 3); got {first.shape}.")
    sources = [first]
    for o in others:
        o = np.asarray(o, np.float64)
        if o.shape != first.shape:
            raise InputError(f"every source must have the shape of the first, {first.shape}; got {o.shape}.")
        have = np.isfinite(o).all(-1) & np.isfinite(first).all(-1)
        aligned = np.full_like(first, np.nan)
        use = np.flatnonzero(have.sum(1) >= MIN_ALIGN_POINTS)
        if use.size:  # the similarity from the shared points, then applied to every point the source gives
            _, s, R, tr = similarity_procrustes(np.nan_to_num(o[use]), np.nan_to_num(first[use]),
                                                weights=have[use].astype(np.float64))
            aligned[use] = s[:, None, None] * np.einsum("tpj,tij->tpi", o[use], R) + tr[:, None]
        sources.append(aligned)
    total = np.zeros(first.shape[:2])
    pairs = np.zeros(first.shape[:2])
    for i in range(len(sources)):
        for j in range(i + 1, len(sources)):
            d = np.linalg.norm(sources[i] - sources[j], axis=-1)
            ok = np.isfinite(d)
            total[ok] += d[ok]
            pairs[ok] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(pairs > 0, total / np.maximum(pairs, 1), np.nan)


def to_body_joints(points13: np.ndarray, joints: int = 24) -> np.ndarray:
    """``(T, 13)`` values in the order of :data:`~flowmocap.body.skeleton.EVAL_JOINTS` as
    ``(T, joints)`` in the body's joint order, NaN for the joints not among the 13.

    Args:
        points13: ``(T, 13)`` one value per scored joint and frame (any unit, kept).
        joints: how many joints the body has (24 for SMPL's skeleton).
    """
    points13 = np.asarray(points13, np.float64)
    if points13.ndim != 2 or points13.shape[1] != len(EVAL_JOINTS):
        raise InputError(f"points13 must be (T, {len(EVAL_JOINTS)}); got {points13.shape}.")
    out = np.full((len(points13), joints), np.nan)
    out[:, list(EVAL_JOINTS)] = points13
    return out


def review_frames(disagreement: np.ndarray, share: float = REVIEW_SHARE) -> tuple[np.ndarray, np.ndarray]:
    """The frames to review: ``(per_frame (T,) metres, flagged (T,) bool)``.

    Args:
        disagreement: ``(T, J)`` metres, a result's ``disagreement`` (NaN where none).
        share: the share of the frames that have a value to flag: those whose mean over the
            joints is at or above the run's ``1 - share`` quantile of it.

    Returns:
        Each frame's mean over its joints (NaN where it has none), and the flag (False there).
    """
    d = np.asarray(disagreement, np.float64)
    if d.ndim != 2:
        raise InputError(f"disagreement must be (T, J); got {d.shape}.")
    if not 0.0 < share <= 1.0:
        raise InputError(f"share must lie in (0, 1]; got {share!r}.")
    have = np.isfinite(d).any(1)
    per_frame = np.full(len(d), np.nan)
    flagged = np.zeros(len(d), bool)
    if have.any():
        per_frame[have] = np.nanmean(d[have], 1)
        flagged[have] = per_frame[have] >= np.quantile(per_frame[have], 1.0 - share)
    return per_frame, flagged
