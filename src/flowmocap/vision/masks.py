"""Person masks: reading mask images and their chamfer distance maps (paper Sec. 3.5).

A mask is an ``(H, W)`` bool array, True on the person. Mask files may be binary
(0 / 255), grey, RGB or palette PNGs (DAVIS annotations are palette images whose
index 0 is the background): any non-zero value is the person.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from flowmocap.errors import DataError, InputError, NoPersonError

__all__ = ["chamfer_map", "load_mask", "mask_iou"]


def chamfer_map(mask: Any) -> np.ndarray:
    """Distance in pixels from every pixel to the nearest mask pixel (``C_I``).

    Exact Euclidean distance between pixel centres (``cv2.distanceTransform`` with
    ``DIST_L2`` and ``DIST_MASK_PRECISE``): 0 on the mask, 1 next to it, ``sqrt(2)``
    diagonally next to it, and so on. OpenCV's result differs in the last bit from call
    to call when it runs on several threads (146 of 10800 pixels of a test mask, 1e-6
    px), which made two runs of the tracker end apart; each distance is therefore taken
    back to its exact square (an integer ``dx^2 + dy^2``, recovered exactly from a value up
    to 1 ulp off for distances below 1365 px) and its square root correctly rounded: the
    same exact map every call. Farther from the mask (only in frames over 1365 px across)
    the integer may be off by one and the last bit may still vary.

    Args:
        mask: ``(H, W)`` array, True / non-zero on the person.

    Returns:
        ``(H, W)`` float32 distances in pixels.

    Raises:
        InputError: not a 2D array. NoPersonError: the mask is empty.
    """
    m = np.asarray(mask)
    if m.ndim != 2 or m.size == 0:
        raise InputError(f"mask must be a non-empty (H, W) array, got shape {m.shape}")
    outside = (m == 0).astype(np.uint8)
    if outside.all():
        raise NoPersonError(
            "the person mask is empty, so there is no silhouette to measure distances to; "
            "check the mask (or the segmentation) for this frame"
        )
    d = cv2.distanceTransform(outside, cv2.DIST_L2, cv2.DIST_MASK_PRECISE).astype(np.float64)
    return np.sqrt(np.rint(d * d)).astype(np.float32)


def load_mask(path: str | Path) -> np.ndarray:
    """Read a person mask image.

    Palette images are read as their palette indices (index 0 = background), so a
    DAVIS annotation gives every annotated object; grey images by value, colour images
    by any non-zero colour channel (an alpha channel is ignored).

    Args:
        path: an image file (PNG, ...).

    Returns:
        ``(H, W)`` bool array, True on the person.

    Raises:
        DataError: the file is missing or not a readable image. NoPersonError: the mask
            is empty.
    """
    from PIL import Image, UnidentifiedImageError

    p = Path(path)
    if not p.is_file():
        raise DataError(f"mask file not found: {p}")
    try:
        with Image.open(p) as im:
            im.load()
            if im.mode in ("P", "PA"):
                arr = np.asarray(im.getchannel(0) if im.mode == "PA" else im)
            elif im.mode in ("RGBA", "LA"):
                arr = np.asarray(im)[..., :-1]
            else:
                arr = np.asarray(im)
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise DataError(f"cannot read mask image {p}: {exc}") from None
    mask = arr != 0 if arr.ndim == 2 else (arr != 0).any(-1)
    if not mask.any():
        raise NoPersonError(f"mask {p} is empty (no non-zero pixel): no person to fit in this frame")
    return mask


def mask_iou(a: Any, b: Any) -> float | np.ndarray:
    """Intersection over union of binary masks (non-zero = person).

    Args:
        a, b: ``(H, W)`` masks, or ``(T, H, W)`` stacks of ``T`` mask pairs.

    Returns:
        A float in [0, 1] for one pair, ``(T,)`` float64 for stacks; 1 where both masks
        are empty.

    Raises:
        InputError: shapes differ or are neither ``(H, W)`` nor ``(T, H, W)``.
    """
    a, b = np.asarray(a) != 0, np.asarray(b) != 0
    if a.shape != b.shape or a.ndim not in (2, 3):
        raise InputError(f"masks must be (T, H, W) or (H, W) of equal shape; got {a.shape} and {b.shape}.")
    inter = (a & b).sum((-2, -1))
    union = (a | b).sum((-2, -1))
    iou = np.where(union > 0, inter / np.maximum(union, 1), 1.0)
    return float(iou) if a.ndim == 2 else iou
