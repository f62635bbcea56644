"""Gaussian image pyramid, bit-compatible in definition with ``cv2.pyrDown``.

One level down: filter with the separable 5-tap kernel ``[1, 4, 6, 4, 1] / 16`` along
rows and columns (borders ``BORDER_REFLECT_101``: ``-1 -> 1``, ``W -> W - 2``) and keep
every second sample, ``(H, W) -> ((H + 1) // 2, (W + 1) // 2)``: output pixel
``(i, j)`` is ``sum_{a,b=-2..2} k[a] k[b] src[refl(2i + a), refl(2j + b)]``.

The Numba kernels work on a rectangular *region* (rows ``[r0, r1)``, columns
``[c0, c1)``) outside which the input is known to be zero, so that pyramids of residual
images that are non-zero only around the person cost only that area; the adjoint
(transpose) kernel backpropagates through a level in the same way.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

from flowmocap.errors import InputError
from flowmocap.render._checks import to_numpy

__all__ = ["pyr_down", "pyramid_shapes"]

_K0 = 1.0 / 16.0
_K1 = 4.0 / 16.0
_K2 = 6.0 / 16.0


@njit(cache=True, nogil=True, inline="always")
def reflect_index(i, n):
    """Index ``i`` reflected into ``[0, n)`` about the borders (OpenCV's BORDER_REFLECT_101)."""
    if n == 1:
        return 0
    if i < 0:
        i = -i
    if i >= n:
        i = 2 * n - 2 - i
    return i


@njit(cache=True, nogil=True, inline="always")
def binomial_tap(t):
    """Weight ``t`` in 0..4 of the 5-tap binomial kernel (1, 4, 6, 4, 1) / 16."""
    if t == 0 or t == 4:
        return _K0
    if t == 1 or t == 3:
        return _K1
    return _K2


@njit(cache=True, nogil=True)
def down_region(lo, hi, n_out):
    """Rows (or columns) of the next level that read any of rows ``[lo, hi)``, as a
    range ``[a, b)``; an empty input range gives ``(0, 0)``."""
    if hi <= lo:
        return 0, 0
    a = max(0, (lo - 1) // 2)
    b = min(n_out, (hi + 1) // 2 + 1)
    return a, b


@njit(cache=True, nogil=True, inline="always")
def _source_rows(r0, r1, n):
    """Rows ``[a, b)`` of a level of ``n`` rows that the 5 taps of the next level's rows
    ``[r0, r1)`` reach (before reflection at the borders): ``[2 r0 - 2, 2 r1 + 1)``, clipped."""
    return max(0, 2 * r0 - 2), min(n, 2 * (r1 - 1) + 3)


@njit(cache=True, nogil=True, error_model="numpy")
def pyr_down_region(src, dst, tmp, r0, r1, c0, c1):
    """``dst[r0:r1, c0:c1] = pyrDown(src)[r0:r1, c0:c1]``.

    src ``(H, W, C)``, dst ``((H+1)//2, (W+1)//2, C)``, tmp ``(H, (W+1)//2, C)`` scratch.
    """
    H, W, C = src.shape
    if r1 <= r0 or c1 <= c0:
        return
    ra, rb = _source_rows(r0, r1, H)
    for r in range(ra, rb):
        for j in range(c0, c1):
            x = 2 * j
            if x >= 2 and x + 2 < W:
                for c in range(C):
                    tmp[r, j, c] = (_K0 * (src[r, x - 2, c] + src[r, x + 2, c])
                                    + _K1 * (src[r, x - 1, c] + src[r, x + 1, c])
                                    + _K2 * src[r, x, c])
            else:
                for c in range(C):
                    acc = 0.0
                    for t in range(5):
                        acc += binomial_tap(t) * src[r, reflect_index(x + t - 2, W), c]
                    tmp[r, j, c] = acc
    for i in range(r0, r1):
        y = 2 * i
        if y >= 2 and y + 2 < H:
            for j in range(c0, c1):
                for c in range(C):
                    dst[i, j, c] = (_K0 * (tmp[y - 2, j, c] + tmp[y + 2, j, c])
                                    + _K1 * (tmp[y - 1, j, c] + tmp[y + 1, j, c])
                                    + _K2 * tmp[y, j, c])
        else:
            for j in range(c0, c1):
                for c in range(C):
                    acc = 0.0
                    for t in range(5):
                        acc += binomial_tap(t) * tmp[reflect_index(y + t - 2, H), j, c]
                    dst[i, j, c] = acc


@njit(cache=True, nogil=True, error_model="numpy")
def pyr_down_adjoint_region(adst, asrc, tmp, r0, r1, c0, c1):
    """``asrc += pyrDown^T(adst)`` for ``adst`` non-zero only on ``[r0, r1) x [c0, c1)``.

    Writes ``asrc`` rows ``[2 r0 - 2, 2 r1 + 1)`` and columns ``[2 c0 - 2, 2 c1 + 1)``
    (clipped); shapes as in :func:`pyr_down_region`.
    """
    H, W, C = asrc.shape
    if r1 <= r0 or c1 <= c0:
        return
    ra, rb = _source_rows(r0, r1, H)
    for r in range(ra, rb):
        for j in range(c0, c1):
            for c in range(C):
                tmp[r, j, c] = 0.0
    for i in range(r0, r1):
        y = 2 * i
        for t in range(5):
            r = reflect_index(y + t - 2, H)
            k = binomial_tap(t)
            for j in range(c0, c1):
                for c in range(C):
                    tmp[r, j, c] += k * adst[i, j, c]
    for r in range(ra, rb):
        for j in range(c0, c1):
            x = 2 * j
            if x >= 2 and x + 2 < W:
                for c in range(C):
                    a = tmp[r, j, c]
                    asrc[r, x - 2, c] += _K0 * a
                    asrc[r, x - 1, c] += _K1 * a
                    asrc[r, x, c] += _K2 * a
                    asrc[r, x + 1, c] += _K1 * a
                    asrc[r, x + 2, c] += _K0 * a
            else:
                for c in range(C):
                    a = tmp[r, j, c]
                    for t in range(5):
                        asrc[r, reflect_index(x + t - 2, W), c] += binomial_tap(t) * a


def pyramid_shapes(height: int, width: int, levels: int) -> list[tuple[int, int]]:
    """``[(H_0, W_0), ..., (H_{L-1}, W_{L-1})]`` with ``H_{l+1} = (H_l + 1) // 2``."""
    shapes = [(int(height), int(width))]
    for _ in range(levels - 1):
        h, w = shapes[-1]
        shapes.append(((h + 1) // 2, (w + 1) // 2))
    return shapes


def pyr_down(image: Any) -> np.ndarray:
    """One Gaussian pyramid level down, as ``cv2.pyrDown`` (module docstring).

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` real array (numpy or torch).

    Returns:
        ``((H + 1) // 2, (W + 1) // 2[, C])``, float32 for float32 input, else float64.
    """
    a = to_numpy(image, "image")
    if a.ndim not in (2, 3) or a.shape[0] < 1 or a.shape[1] < 1:
        raise InputError(f"image must have shape (H, W) or (H, W, C) with H, W >= 1, got {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise InputError(f"image must hold real numbers, got dtype {a.dtype}")
    out_dtype = np.float32 if a.dtype == np.float32 else np.float64
    src = np.ascontiguousarray(a if a.ndim == 3 else a[:, :, None], dtype=np.float64)
    H, W, C = src.shape
    Ho, Wo = (H + 1) // 2, (W + 1) // 2
    dst = np.zeros((Ho, Wo, C))
    tmp = np.empty((H, Wo, C))
    pyr_down_region(src, dst, tmp, 0, Ho, 0, Wo)
    if a.ndim == 2:
        dst = dst[:, :, 0]
    return dst.astype(out_dtype, copy=False)
