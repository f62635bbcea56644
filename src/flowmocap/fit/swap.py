"""A detection that labels the whole body left for right, told and undone (issue 18).

A 2D detector sometimes takes a person who faces the camera to face away (or the other
way round) and labels every left keypoint as the right one: the image of the body turned
about in depth. Its 3D keypoints then describe that turned-about body. On the real
multi-view recording MediaPipe does so in 26 of person1-cam02's 69 scored frames, and the
re-initialisation followed it (docs/experiments.md, "Where the real3d error comes from").

:func:`detection_swapped` tells such a frame from the tracker's own body: the detection
is much nearer the body's keypoints with left and right exchanged (mean distance below
:data:`SWAP_RATIO` of the unexchanged one) and is far from them as labelled (more than
``min_px``). :func:`exchanged_2d` and :func:`exchanged_3d` undo it: the labels exchanged
and, in 3D, the body turned back about the plane through the hips across the ray (each
point's component along the viewing ray negated), which keeps its image.

Which of the two -- the detector or the tracked body -- has it right cannot be known from
one frame; this trusts the body (the tracker's prediction, made from the frames before).
"""

from __future__ import annotations

import numpy as np

from flowmocap.fit.pose_prior import MIRROR_JOINTS

__all__ = ["EXCHANGED_EVENT", "SWAP_RATIO", "MIN_SIDED", "detection_swapped", "exchanged_2d", "exchanged_3d",
           "exchanged_frames", "exchanged_keypoints"]

#: the exchanged detection's mean distance from the body, as a share of the unexchanged one, below which it is swapped
SWAP_RATIO = 0.5
#: fewer left/right joints detected on both sides than this and nothing is decided
MIN_SIDED = 6
#: the tracker's event for a frame whose detection it exchanged back (``run.json``'s events)
EXCHANGED_EVENT = "detection's left and right exchanged back"


def _np(x) -> np.ndarray:
    return np.asarray(x.detach().numpy() if hasattr(x, "detach") else x, np.float64)


def detection_swapped(body_2d, j2d, conf, min_px: float) -> bool:
    """Whether a frame's detection labels the body left for right.

    Args:
        body_2d: ``(24, 2)`` pixels, the body's joints where the detector puts them
            (:func:`~flowmocap.vision.keypoint_map.detector_points`, projected).
        j2d: ``(24, 2)`` pixels and ``conf``: ``(24,)`` the detection in SMPL joint order
            (0: not detected).
        min_px: the detection must be at least this far from the body as labelled (mean
            over the joints compared), so a side view, whose left and right joints
            overlap, is never exchanged.

    Returns:
        True when the exchanged detection's mean distance is below :data:`SWAP_RATIO` of
        the unexchanged one over the left/right joints detected on both sides (at least
        :data:`MIN_SIDED` of them).
    """
    p, j, c = _np(body_2d), _np(j2d), _np(conf)
    m = np.asarray(MIRROR_JOINTS)
    use = (c > 0) & (c[m] > 0) & (m != np.arange(len(m))) & np.isfinite(j).all(1)
    if use.sum() < MIN_SIDED:
        return False
    d0 = float(np.linalg.norm(j[use] - p[use], axis=1).mean())
    d1 = float(np.linalg.norm(j[m][use] - p[use], axis=1).mean())
    return d0 > min_px and d1 < SWAP_RATIO * d0


def exchanged_2d(j2d, conf) -> tuple:
    """``(j2d, conf)`` in SMPL joint order with left and right exchanged (same types).

    Args:
        j2d: ``(24, 2)`` pixels, numpy or torch.
        conf: ``(24,)`` confidences in [0, 1], the same type.
    """
    m = list(MIRROR_JOINTS)
    return j2d[m], conf[m]


def exchanged_3d(j3d, conf, ray) -> tuple:
    """The detector's 3D joints of a swapped detection turned back.

    Args:
        j3d: ``(24, 3)`` metres relative to the middle of the hips, camera axes
            (:meth:`~flowmocap.vision.auto.PersonTrack.smpl_joints3d`); conf: ``(24,)``.
        ray: ``(3,)`` the viewing ray through the person (any length), camera axes.

    Returns:
        ``(j3d, conf)``: left and right exchanged and each point's component along the
        ray negated (the body turned about in depth, its image kept to first order).
    """
    r = _np(ray)
    r = r / np.linalg.norm(r)
    m = list(MIRROR_JOINTS)
    x = _np(j3d)[m]
    x = x - 2.0 * (x @ r)[:, None] * r
    out = x.astype(np.asarray(j3d).dtype) if not hasattr(j3d, "detach") else j3d.new_tensor(x)
    return out, conf[m]


def exchanged_keypoints(keypoints, confidence) -> tuple:
    """``(keypoints (K, d), confidence (K,))`` of :data:`~flowmocap.vision.detect.KEYPOINT_NAMES`
    with left and right exchanged (the nose stays)."""
    from flowmocap.vision.detect import KEYPOINT_NAMES

    def other(n: str) -> str:
        return ("right_" + n[5:]) if n.startswith("left_") else ("left_" + n[6:]) if n.startswith("right_") else n

    m = [KEYPOINT_NAMES.index(other(n)) for n in KEYPOINT_NAMES]
    return keypoints[m], confidence[m]


def exchanged_frames(events: list[dict]) -> list[int]:
    """The input frame numbers whose detection the tracker exchanged back, from a run's
    ``events`` (``run.json``; :data:`EXCHANGED_EVENT`), sorted and without repeats."""
    return sorted({int(e["frame"]) for e in events if e.get("event") == EXCHANGED_EVENT and "frame" in e})
