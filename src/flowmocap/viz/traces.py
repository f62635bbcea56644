"""Joint traces (the paper's Fig. 3): the history of the evaluated joints drawn over frames."""

from __future__ import annotations

import numpy as np

from flowmocap.body.skeleton import EVAL_JOINTS
from flowmocap.errors import InputError

__all__ = ["TRACE_RGB", "GT_TRACE_RGB", "draw_traces", "trace_box"]

#: Trace colour of the fitted joints (the paper's green) and of ground truth, RGB 0..255.
TRACE_RGB = (40, 220, 60)
GT_TRACE_RGB = (255, 90, 40)


def _check_joints(joints2d, name: str) -> np.ndarray:
    j = np.asarray(joints2d, np.float64)
    if j.ndim != 3 or j.shape[2] != 2:
        raise InputError(f"{name} must be (T, J, 2) pixels, got {j.shape}.")
    return j


def draw_traces(image: np.ndarray, joints2d: np.ndarray, upto: int, history: int | None = None,
                joints=EVAL_JOINTS, colour=TRACE_RGB, thickness: int = 2, fade: bool = True,
                dots: bool = True) -> np.ndarray:
    """Draw the path of each joint from frame ``upto - history`` to ``upto`` over an image.

    Args:
        image: ``(H, W, 3)`` uint8 RGB.
        joints2d: ``(T, J, 2)`` joint positions in pixels (pixel centres at +0.5), one row
            per frame of the trace.
        upto: the last frame of the trace (an index into ``joints2d``).
        history: how many frames back to draw (default: from frame 0).
        joints: the joint indices to draw (default: the paper's 13 evaluated joints).
        colour: RGB 0..255.
        thickness: line width in pixels.
        fade: older segments drawn fainter.
        dots: mark each joint's current position.

    Returns:
        ``(H, W, 3)`` uint8 RGB (a new image).
    """
    import cv2

    j = _check_joints(joints2d, "joints2d")
    if not 0 <= upto < j.shape[0]:
        raise InputError(f"upto must index one of the {j.shape[0]} frames, got {upto}.")
    start = 0 if history is None else max(0, upto - int(history))
    out = np.ascontiguousarray(image, dtype=np.uint8).copy()
    shift = 4  # sub-pixel precision of cv2's fixed-point coordinates
    n = upto - start
    for k in range(start, upto):
        w = (k + 1 - start) / max(n, 1) if fade else 1.0
        layer = out.copy()
        for joint in joints:
            a, b = j[k, joint], j[k + 1, joint]
            if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
                continue
            p = tuple(int(round(v * (1 << shift))) for v in a - 0.5)
            q = tuple(int(round(v * (1 << shift))) for v in b - 0.5)
            cv2.line(layer, p, q, colour, thickness, cv2.LINE_AA, shift)
        a_ = 0.35 + 0.65 * w
        out = np.clip(np.round(a_ * layer.astype(np.float32) + (1 - a_) * out.astype(np.float32)), 0, 255
                      ).astype(np.uint8)
    if dots:
        for joint in joints:
            c = j[upto, joint]
            if np.all(np.isfinite(c)):
                p = tuple(int(round(v * (1 << shift))) for v in c - 0.5)
                cv2.circle(out, p, (thickness + 1) << shift, colour, -1, cv2.LINE_AA, shift)
    return out


def trace_box(joints2d: np.ndarray, size: tuple[int, int], masks=None, margin: int = 12,
              joints=EVAL_JOINTS) -> tuple[int, int, int, int]:
    """``(r0, r1, c0, c1)``: a crop holding every drawn joint (and mask pixels), plus a margin.

    Args:
        joints2d: ``(T, J, 2)`` pixels.
        size: ``(width, height)`` of the image.
        masks: optional iterable of ``(H, W)`` bool masks to include (e.g. the body).
        margin: pixels added on each side.
        joints: the joint indices included (default: the paper's 13 evaluated joints).

    Returns:
        Row and column bounds in pixels (end-exclusive), clipped to the image.
    """
    W, H = size
    pts = _check_joints(joints2d, "joints2d")[:, list(joints)].reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    lo = pts.min(0) if len(pts) else np.array([0.0, 0.0])
    hi = pts.max(0) if len(pts) else np.array([W, H], float)
    for m in masks or []:
        rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
        if rows.size:
            lo = np.minimum(lo, [cols[0], rows[0]])
            hi = np.maximum(hi, [cols[-1] + 1, rows[-1] + 1])
    c0, r0 = (int(np.floor(v)) - margin for v in lo)
    c1, r1 = (int(np.ceil(v)) + margin for v in hi)
    return max(0, r0), min(H, r1), max(0, c0), min(W, c1)
