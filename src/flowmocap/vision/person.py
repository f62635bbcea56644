"""One person's mask and identity over time: mask cleaning, frame-to-frame continuity,
and choosing one person among several (``person="largest" | N | "x,y"``).

Masks are ``(H, W)`` bool arrays; keypoints ``(K, 2)`` pixels with ``(K,)`` confidences
(see :mod:`flowmocap.vision.detect`); boxes ``(x0, y0, x1, y1)`` pixels.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from flowmocap.errors import InputError

__all__ = ["person_box", "clean_mask", "box_iou", "same_person", "parse_person", "describe_person",
           "choose_person", "box_distance"]


def person_box(keypoints: np.ndarray, confidence: np.ndarray, mask: np.ndarray | None = None,
               min_confidence: float = 0.3) -> tuple[float, float, float, float] | None:
    """``(x0, y0, x1, y1)`` pixels around the confident keypoints (and the mask, if given).

    Args:
        keypoints: ``(K, 2)`` pixels; confidence: ``(K,)``.
        mask: optional ``(H, W)`` bool.
        min_confidence: the confidence a keypoint needs to count.

    Returns None when fewer than two keypoints are confident and the mask is empty.
    """
    xs, ys = [], []
    ok = np.asarray(confidence) >= min_confidence
    if ok.sum() >= 2:
        p = np.asarray(keypoints)[ok]
        xs += [p[:, 0].min(), p[:, 0].max()]
        ys += [p[:, 1].min(), p[:, 1].max()]
    if mask is not None and mask.any():
        rows = np.nonzero(mask.any(1))[0]
        cols = np.nonzero(mask.any(0))[0]
        xs += [cols[0], cols[-1] + 1]
        ys += [rows[0], rows[-1] + 1]
    if not xs:
        return None
    return float(min(xs)), float(min(ys)), float(max(xs)), float(max(ys))


def clean_mask(mask: np.ndarray, keypoints: np.ndarray, confidence: np.ndarray, min_fraction: float = 0.02,
               max_hole_fraction: float = 0.01, min_confidence: float = 0.3) -> np.ndarray:
    """The person's part of a segmentation: components touching the person, holes filled.

    Keeps the largest connected component that overlaps the box around the confident
    keypoints (enlarged by 15% of its size on each side), and every other overlapping
    component of at least ``min_fraction`` of its area (a hand or a foot the
    segmentation cut off); drops the rest (specks, other people). Fills holes smaller
    than ``max_hole_fraction`` of the person's area (larger holes, e.g. between an arm and
    the body, are real).

    Args:
        mask: ``(H, W)`` bool segmentation.
        keypoints: ``(K, 2)`` pixels; confidence: ``(K,)``.

    Returns:
        ``(H, W)`` bool; empty when no component overlaps the person.
    """
    m = np.asarray(mask, bool)
    if not m.any():
        return m.copy()
    H, W = m.shape
    box = person_box(keypoints, confidence, None, min_confidence)
    lab, n = ndi.label(m)
    sizes = ndi.sum(m, lab, np.arange(1, n + 1))
    if box is None:
        region = np.ones_like(m)
    else:
        x0, y0, x1, y1 = box
        px, py = 0.15 * (x1 - x0) + 4, 0.15 * (y1 - y0) + 4
        region = np.zeros_like(m)
        region[max(0, int(y0 - py)):min(H, int(np.ceil(y1 + py))), max(0, int(x0 - px)):min(W, int(np.ceil(x1 + px)))] = True
    touching = np.unique(lab[region & m])
    touching = touching[touching > 0]
    if len(touching) == 0:
        return np.zeros_like(m)
    largest = sizes[touching - 1].max()
    keep = touching[sizes[touching - 1] >= min_fraction * largest]
    out = np.isin(lab, keep)
    # holes: the background's 4-connected pieces that do not reach the image's border (what
    # ndi.binary_fill_holes fills; one labelling instead of its ~10x slower iterated dilation)
    hl, hn = ndi.label(~out)
    if hn:
        edge = np.unique(np.r_[hl[0], hl[-1], hl[:, 0], hl[:, -1]])
        hs = np.bincount(hl.ravel(), minlength=hn + 1)
        small = np.nonzero(hs <= max_hole_fraction * out.sum())[0]
        small = np.setdiff1d(small[small > 0], edge)
        if len(small):
            out |= np.isin(hl, small)
    return out


def box_iou(a, b) -> float:
    """Intersection over union of two ``(x0, y0, x1, y1)`` boxes (0 if either is None)."""
    if a is None or b is None:
        return 0.0
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def same_person(prev_box, cur_box, frames_apart: int = 1) -> bool:
    """Whether a detection continues the person of an earlier one.

    True when the boxes overlap (IoU > 0.1) or their centres lie within 0.5 of the
    earlier box's height per frame apart (at most 2 heights): a person moves less than
    half their height between neighbouring frames. ``prev_box``, ``cur_box``: ``(x0, y0,
    x1, y1)`` pixels, or None (then True).
    """
    if prev_box is None or cur_box is None:
        return True
    if box_iou(prev_box, cur_box) > 0.1:
        return True
    h = max(prev_box[3] - prev_box[1], prev_box[2] - prev_box[0], 1.0)
    c0 = np.array([(prev_box[0] + prev_box[2]) / 2, (prev_box[1] + prev_box[3]) / 2])
    c1 = np.array([(cur_box[0] + cur_box[2]) / 2, (cur_box[1] + cur_box[3]) / 2])
    return float(np.linalg.norm(c1 - c0)) < min(0.5 * frames_apart, 2.0) * h


def parse_person(person) -> tuple[str, object]:
    """Which person to track, from ``--person`` or ``track(person=...)``.

    Args:
        person: ``"largest"`` (the person seen biggest, nearest and longest: the main
            track of :func:`flowmocap.vision.auto.detect_sequence`), an int ``N >= 0`` or
            ``"N"`` (the N-th person by that same score; 0 = the largest), or ``"x,y"`` /
            ``(x, y)`` pixels (the person whose box contains, or lies nearest to, that
            point in the first frame they appear in).

    Returns:
        ``("largest", None)``, ``("index", N)`` or ``("point", (x, y))``.

    Raises:
        InputError: anything else (the message lists the accepted forms).
    """
    forms = "'largest', a rank N >= 0 (0 = the largest person) or a pixel 'x,y' inside the person's box"
    if person is None or (isinstance(person, str) and person.strip().lower() == "largest"):
        return "largest", None
    if isinstance(person, (bool, np.bool_)):
        raise InputError(f"person must be {forms}; got {person!r}.")
    if isinstance(person, (int, np.integer)):
        if person < 0:
            raise InputError(f"person rank must be >= 0 (0 = the largest person); got {person}.")
        return "index", int(person)
    if isinstance(person, (tuple, list, np.ndarray)) and len(person) == 2:
        try:
            x, y = (float(v) for v in person)
        except (TypeError, ValueError):
            raise InputError(f"person must be {forms}; got {person!r}.") from None
        if not (np.isfinite(x) and np.isfinite(y)):
            raise InputError(f"the person's pixel must be finite; got {person!r}.")
        return "point", (x, y)
    if isinstance(person, str):
        text = person.strip()
        if text.lower() == "all":
            raise InputError("person='all' tracks every person, each into a result folder of their own: use "
                             "flowmocap.batch.track_people (the command line's --person all); a single run takes "
                             f"{forms}.")
        if "," in text:
            parts = text.split(",")
            try:
                xy = tuple(float(v) for v in parts)
            except ValueError:
                xy = ()
            if len(xy) == 2:
                return parse_person(xy)
            raise InputError(f"person {person!r}: a pixel must be two numbers 'x,y' (e.g. 540,900); or use {forms}.")
        try:
            return parse_person(int(text))
        except ValueError:
            pass
    raise InputError(f"person must be {forms}; got {person!r}.")


def describe_person(choice: tuple[str, object]) -> str:
    """The canonical text of a :func:`parse_person` result (``largest``, ``2``, ``540,900``)."""
    kind, value = choice
    if kind == "largest":
        return "largest"
    if kind == "index":
        return str(value)
    return f"{value[0]:g},{value[1]:g}"


def box_distance(box, point) -> float:
    """Distance in pixels from ``point (x, y)`` to the box (0 inside it)."""
    x0, y0, x1, y1 = box
    dx = max(x0 - point[0], 0.0, point[0] - x1)
    dy = max(y0 - point[1], 0.0, point[1] - y1)
    return float(np.hypot(dx, dy))


def choose_person(first_boxes: list, scores, choice: tuple[str, object]) -> int:
    """The index of the chosen person among candidate tracks.

    Args:
        first_boxes: per track, its box ``(x0, y0, x1, y1)`` pixels in the first frame it
            appears in.
        scores: per track, the main-person score (larger = seen bigger, nearer, longer).
        choice: a :func:`parse_person` result. ``largest``: the highest score (the first
            of equal ones); ``("index", N)``: the N-th by decreasing score; ``("point",
            (x, y))``: the track whose first box contains the point or lies nearest to it
            (:func:`box_distance`), ties broken by the distance to the box's centre.

    Raises:
        InputError: no tracks, or a rank beyond the number of people found.
    """
    n = len(first_boxes)
    if n == 0 or len(scores) != n:
        raise InputError(f"choose_person needs one score per track; got {n} tracks and {len(scores)} scores.")
    kind, value = choice
    order = sorted(range(n), key=lambda k: -float(scores[k]))  # stable: equal scores keep their order
    if kind == "largest":
        return order[0]
    if kind == "index":
        if value >= n:
            raise InputError(f"person {value} was asked for but only {n} "
                             f"{'person was' if n == 1 else 'people were'} found (ranks 0..{n - 1}, 0 = the "
                             "largest); give a smaller rank or a pixel 'x,y' on the person.")
        return order[value]
    if kind == "point":
        def key(k):
            b = first_boxes[k]
            centre = ((b[0] + b[2]) / 2, (b[1] + b[3]) / 2)
            return (box_distance(b, value), float(np.hypot(centre[0] - value[0], centre[1] - value[1])))

        return min(range(n), key=key)
    raise InputError(f"unknown person choice {choice!r}; use parse_person.")
