"""Interpolation of per-vertex attributes at the visible surface point of every pixel."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from numba import njit

from flowmocap.errors import InputError
from flowmocap.render._checks import check_faces, to_numpy
from flowmocap.render.raster import Raster

__all__ = ["interpolate"]


@njit(cache=True, nogil=True)
def _interpolate_kernel(face_id, bary, faces, attr, out):
    H, W = face_id.shape
    C = attr.shape[1]
    for v in range(H):
        for u in range(W):
            f = face_id[v, u]
            if f < 0:
                continue
            b0 = bary[v, u, 0]
            b1 = bary[v, u, 1]
            b2 = bary[v, u, 2]
            i0 = faces[f, 0]
            i1 = faces[f, 1]
            i2 = faces[f, 2]
            for c in range(C):
                out[v, u, c] = b0 * attr[i0, c] + b1 * attr[i1, c] + b2 * attr[i2, c]


@njit(cache=True, nogil=True)
def _interpolate_covered_kernel(face_id, bary, faces, attr, out):
    H, W = face_id.shape
    C = attr.shape[1]
    n = 0
    for v in range(H):
        for u in range(W):
            f = face_id[v, u]
            if f < 0:
                continue
            i0 = faces[f, 0]
            i1 = faces[f, 1]
            i2 = faces[f, 2]
            for c in range(C):
                out[n, c] = bary[v, u, 0] * attr[i0, c] + bary[v, u, 1] * attr[i1, c] + bary[v, u, 2] * attr[i2, c]
            n += 1


def interpolate_covered(raster: Raster, attr: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``interpolate(raster, attr, faces)[raster.mask]`` without the full image:
    ``(N, C)`` float64 for the covered pixels in row-major order (checked inputs).

    Args:
        raster: :class:`~flowmocap.render.Raster` of the mesh.
        attr: ``(V, C)`` per-vertex attributes (any unit, kept), numpy.
        faces: ``(F, 3)`` int32 vertex indices, already checked (``Faces.array``).
    """
    n = int(np.count_nonzero(raster.face_id >= 0))
    out = np.empty((n, attr.shape[1]))
    _interpolate_covered_kernel(raster.face_id, raster.bary, faces, np.ascontiguousarray(attr, dtype=np.float64), out)
    return out


def interpolate(raster: Raster, attr: Any, faces: Any, background: float = 0.0) -> Any:
    """Interpolate vertex attributes at each pixel's visible surface point.

    Uses the raster's perspective-correct barycentrics, so the result is the attribute
    of the 3D surface point seen at the pixel centre (e.g. interpolating rest-pose
    vertex positions gives the rest-pose coordinates of that surface point).

    Args:
        raster: :class:`~flowmocap.render.Raster` from :func:`~flowmocap.render.rasterize`.
        attr: ``(V, C)`` per-vertex attributes (any unit). A numpy array gives a numpy
            result (float32 if ``attr`` is float32, else float64); a torch tensor gives
            a torch tensor of its dtype and device, differentiable w.r.t. ``attr``
            (the barycentrics are constants).
        faces: ``(F, 3)`` int vertex indices (the ones rasterised), or a ``Faces``.
        background: value written at uncovered pixels.

    Returns:
        ``(H, W, C)`` interpolated attributes.

    Raises:
        InputError: wrong shapes, a raster of another mesh (face index out of range).
    """
    if not isinstance(raster, Raster):
        raise InputError(f"interpolate needs a Raster from rasterize(), got {type(raster).__name__}")
    is_torch = isinstance(attr, torch.Tensor)
    a_np = to_numpy(attr, "attr") if not is_torch else None
    shape = tuple(attr.shape)
    if len(shape) != 2:
        raise InputError(f"attr must have shape (V, C), got {shape}")
    f = check_faces(faces, shape[0])
    H, W = raster.face_id.shape
    fmax = int(raster.face_id.max()) if raster.face_id.size else -1
    if fmax >= f.shape[0]:
        raise InputError(
            f"the raster refers to face {fmax} but the mesh has {f.shape[0]} faces; "
            "pass the faces that were rasterised"
        )
    if is_torch:
        fid = torch.from_numpy(raster.face_id.astype(np.int64)).to(attr.device)
        covered = fid >= 0
        idx = torch.from_numpy(f.astype(np.int64)).to(attr.device)[fid.clamp_min(0)]  # (H, W, 3)
        b = torch.from_numpy(raster.bary).to(device=attr.device, dtype=attr.dtype)
        out = (attr[idx] * b[..., None]).sum(dim=2)
        return torch.where(covered[..., None], out, torch.full_like(out, float(background)))
    if not np.issubdtype(a_np.dtype, np.number) or np.issubdtype(a_np.dtype, np.complexfloating):
        raise InputError(f"attr must hold real numbers, got dtype {a_np.dtype}")
    dtype = np.float32 if a_np.dtype == np.float32 else np.float64
    a = np.ascontiguousarray(a_np, dtype=np.float64)
    out = np.full((H, W, shape[1]), float(background), dtype=np.float64)
    _interpolate_kernel(raster.face_id, raster.bary, f, a, out)
    return out.astype(dtype, copy=False)
