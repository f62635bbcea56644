"""Optical flow as colour: the Middlebury colour coding (Baker et al., "A Database and
Evaluation Methodology for Optical Flow", IJCV 2011).

The direction of a flow vector picks a hue on a colour wheel, its length the saturation:
zero flow is white, a vector of length ``max_magnitude`` the fully saturated wheel
colour; longer vectors keep their hue and are darkened to 75 %. The wheel has 55 colours
in six ramps chosen so that perceptually similar steps are about equally long:
red -> yellow (15 steps), yellow -> green (6), green -> cyan (4), cyan -> blue (11),
blue -> magenta (13), magenta -> red (6); colours between the 55 are linearly
interpolated; the 55 colours span the full circle (colour ``k`` at angle ``2 pi k / 55``).
Flow ``(dx, dy)`` is in image axes (x right, y down): flow to the right is red,
downwards (``dy > 0``) yellow, to the left light blue, upwards violet.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from flowmocap.errors import InputError

__all__ = ["WHEEL_RAMPS", "color_wheel", "flow_to_color", "color_wheel_legend"]

#: ``(start colour, end colour, steps)`` of the six ramps of the wheel, RGB 0..255.
WHEEL_RAMPS: tuple[tuple[tuple[int, int, int], tuple[int, int, int], int], ...] = (
    ((255, 0, 0), (255, 255, 0), 15),  # red -> yellow
    ((255, 255, 0), (0, 255, 0), 6),  # yellow -> green
    ((0, 255, 0), (0, 255, 255), 4),  # green -> cyan
    ((0, 255, 255), (0, 0, 255), 11),  # cyan -> blue
    ((0, 0, 255), (255, 0, 255), 13),  # blue -> magenta
    ((255, 0, 255), (255, 0, 0), 6),  # magenta -> red
)


def color_wheel() -> np.ndarray:
    """The ``(55, 3)`` float64 wheel colours (0..255), starting at red.

    Within a ramp of ``n`` steps from colour ``A`` to ``B``, step ``k`` (``0 <= k < n``)
    is ``A + floor(255 k / n) / 255 (B - A)``: the channel that changes moves in whole
    units, as in the original Middlebury code, and the ramp's end is the next ramp's
    first colour.
    """
    rows = []
    for a, b, n in WHEEL_RAMPS:
        a_, b_ = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        frac = np.floor(255.0 * np.arange(n) / n)[:, None] / 255.0
        rows.append(a_ + frac * (b_ - a_))
    return np.concatenate(rows)


_WHEEL = color_wheel()
_WHEEL.setflags(write=False)


def flow_to_color(flow: Any, max_magnitude: float | None = None) -> np.ndarray:
    """Colour-code a flow field (Middlebury colour wheel, see the module docstring).

    Args:
        flow: ``(H, W, 2)`` flow ``(dx, dy)`` in pixels (x right, y down), numpy or torch.
        max_magnitude: flow length (pixels) drawn fully saturated; ``None`` for the
            largest finite length in ``flow`` (1 if all are zero). Give the same value
            to several fields to compare them.

    Returns:
        ``(H, W, 3)`` uint8 RGB image. Non-finite flow vectors are drawn black.

    Raises:
        InputError: wrong shape, or a non-positive / non-finite ``max_magnitude``.
    """
    if hasattr(flow, "detach"):
        flow = flow.detach().cpu().numpy()
    f = np.asarray(flow, dtype=np.float64)
    if f.ndim != 3 or f.shape[2] != 2:
        raise InputError(f"flow must have shape (H, W, 2), got {f.shape}")
    valid = np.isfinite(f).all(axis=2)
    u = np.where(valid, f[..., 0], 0.0)
    v = np.where(valid, f[..., 1], 0.0)
    mag = np.hypot(u, v)
    if max_magnitude is None:
        top = float(mag.max()) if mag.size else 0.0
        max_magnitude = top if top > 0 else 1.0
    else:
        max_magnitude = float(max_magnitude)
        if not np.isfinite(max_magnitude) or max_magnitude <= 0:
            raise InputError(f"max_magnitude must be a positive number of pixels, got {max_magnitude}")
    rad = mag / max_magnitude
    # angle from the +x axis measured so that right = 0 (red), down -> yellow/green,
    # left = half-way round (cyan), up -> blue/magenta
    n = len(_WHEEL)
    pos = (np.arctan2(v, u) % (2.0 * np.pi)) / (2.0 * np.pi) * n
    k0 = np.floor(pos).astype(np.int64) % n
    k1 = (k0 + 1) % n
    t = (pos - np.floor(pos))[..., None]
    hue = ((1.0 - t) * _WHEEL[k0] + t * _WHEEL[k1]) / 255.0
    r = rad[..., None]
    inside = r <= 1.0
    col = np.where(inside, 1.0 - np.minimum(r, 1.0) * (1.0 - hue), 0.75 * hue)
    col[~valid] = 0.0
    return np.clip(np.round(255.0 * col), 0, 255).astype(np.uint8)


def color_wheel_legend(size: int = 128, background: tuple[int, int, int] = (255, 255, 255)) -> np.ndarray:
    """A colour key: the disc of flows up to ``max_magnitude``, the centre being zero.

    The pixel at offset ``(dx, dy)`` from the centre shows the colour of the flow
    ``(dx, dy)`` scaled so the disc's rim is ``max_magnitude`` (image axes: right is
    red, down yellow, left light blue, up violet). Outside the disc: ``background``.

    Args:
        size: side of the square image in pixels (>= 3).
        background: RGB colour outside the disc.

    Returns:
        ``(size, size, 3)`` uint8 RGB image.
    """
    if int(size) != size or size < 3:
        raise InputError(f"size must be a whole number of pixels >= 3, got {size!r}")
    size = int(size)
    radius = 0.5 * size - 1.0
    c = 0.5 * size
    y, x = np.mgrid[0:size, 0:size] + 0.5
    flow = np.stack([x - c, y - c], axis=-1) / radius
    img = flow_to_color(flow, max_magnitude=1.0)
    dist = np.hypot(flow[..., 0], flow[..., 1]) * radius
    # anti-aliased rim: coverage of a pixel by the disc, approximately
    alpha = np.clip(radius + 0.5 - dist, 0.0, 1.0)[..., None]
    bg = np.asarray(background, dtype=np.float64)
    out = alpha * img.astype(np.float64) + (1.0 - alpha) * bg
    return np.clip(np.round(out), 0, 255).astype(np.uint8)
