"""Similarity Procrustes alignment (Umeyama 1991), batched, numpy or torch."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from flowmocap.errors import InputError

__all__ = ["similarity_procrustes"]


def similarity_procrustes(source: Any, target: Any, weights: Any = None, estimate_scale: bool = True):
    """Best similarity transform taking ``source`` onto ``target`` (weighted least squares).

    Finds ``scale > 0``, a rotation ``R`` (``det R = +1``, never a reflection, even if
    ``target`` is a mirror image of ``source``) and ``t`` minimising
    ``sum_i w_i |scale * R @ source_i + t - target_i|^2`` (Umeyama's closed form), and
    returns ``aligned = scale * source @ R^T + t``. Used for the paper's
    Procrustes-aligned joint errors ("local": per frame, batch over frames; "global":
    one alignment per sequence, flatten the frames into ``N``).

    Args:
        source: ``(..., N, 3)`` points to move, metres (numpy array or torch tensor).
        target: ``(..., N, 3)`` points to match; leading dims broadcast with ``source``.
        weights: optional ``(..., N)`` non-negative per-point weights (broadcast over
            the leading dims), e.g. joint visibility; default all ones. Only their
            ratios matter.
        estimate_scale: if False, ``scale`` is fixed to 1 (rigid alignment).

    Returns:
        ``(aligned (..., N, 3), scale (...), R (..., 3, 3), t (..., 3))``, numpy arrays if
        ``source`` is a numpy array (computed in float64, returned in its dtype), else
        torch tensors in ``source``'s dtype and device (differentiable where the SVD is,
        i.e. for distinct singular values). If all source points coincide, ``scale`` is
        0 and ``aligned`` is the weighted target centroid.

    Raises:
        InputError: on mismatched shapes, a last dimension other than 3, negative
            weights, or weights that sum to zero.
    """
    as_numpy = isinstance(source, np.ndarray)
    if as_numpy:
        out_dtype = source.dtype if source.dtype in (np.float32, np.float64) else np.float64
        src = torch.from_numpy(np.array(source, dtype=np.float64))
    elif isinstance(source, torch.Tensor):
        src = source if source.is_floating_point() else source.double()
    else:
        raise InputError(
            "source must be a numpy array or torch tensor of shape (..., N, 3), "
            f"got {type(source).__name__}"
        )
    tgt = _to_tensor(target, src, "target")
    for name, x in (("source", src), ("target", tgt)):
        if x.dim() < 2 or x.shape[-1] != 3:
            raise InputError(f"{name} must have shape (..., N, 3), got {tuple(x.shape)}")
    if src.shape[-2] != tgt.shape[-2]:
        raise InputError(
            "source and target must have the same number of points, "
            f"got {src.shape[-2]} and {tgt.shape[-2]}"
        )
    n = src.shape[-2]
    if weights is None:
        w = torch.ones(n, dtype=src.dtype, device=src.device)
    else:
        w = _to_tensor(weights, src, "weights")
        if w.dim() < 1 or w.shape[-1] != n:
            raise InputError(f"weights must have shape (..., N) with N = {n}, got {tuple(w.shape)}")
        if bool((w < 0).any()):
            raise InputError("weights must be non-negative")
    try:
        lead = torch.broadcast_shapes(src.shape[:-2], tgt.shape[:-2], w.shape[:-1])
    except RuntimeError:
        raise InputError(
            f"source {tuple(src.shape)}, target {tuple(tgt.shape)} and weights {tuple(w.shape)} "
            "have incompatible batch shapes"
        ) from None
    src, tgt, w = src.expand(lead + (n, 3)), tgt.expand(lead + (n, 3)), w.expand(lead + (n,))
    w_sum = w.sum(-1, keepdim=True)
    if bool((w_sum <= 0).any()):
        raise InputError("weights sum to zero: at least one point needs a positive weight")
    w = w / w_sum

    mu_s = (w[..., None] * src).sum(-2)
    mu_t = (w[..., None] * tgt).sum(-2)
    xs = src - mu_s[..., None, :]
    yt = tgt - mu_t[..., None, :]
    cov = (yt * w[..., None]).transpose(-1, -2) @ xs  # sum_i w_i y_i x_i^T, (..., 3, 3)
    U, D, Vh = torch.linalg.svd(cov)
    d = torch.sign(torch.linalg.det(U) * torch.linalg.det(Vh))
    d = torch.where(d == 0, torch.ones_like(d), d)
    s = torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1)
    R = U @ (s[..., None] * Vh)
    if estimate_scale:
        var_s = (w * (xs * xs).sum(-1)).sum(-1)
        positive = var_s > 0
        var_safe = torch.where(positive, var_s, torch.ones_like(var_s))
        scale = torch.where(positive, (D * s).sum(-1) / var_safe, 0.0)
    else:
        scale = torch.ones(R.shape[:-2], dtype=src.dtype, device=src.device)
    t = mu_t - scale[..., None] * (R @ mu_s[..., None])[..., 0]
    aligned = scale[..., None, None] * (src @ R.transpose(-1, -2)) + t[..., None, :]
    if as_numpy:
        return tuple(x.numpy().astype(out_dtype, copy=False) for x in (aligned, scale, R, t))
    return aligned, scale, R, t


def _to_tensor(x: Any, like: torch.Tensor, name: str) -> torch.Tensor:
    try:
        return torch.as_tensor(np.array(x) if not isinstance(x, torch.Tensor) else x,
                               dtype=like.dtype, device=like.device)
    except (TypeError, ValueError, RuntimeError):
        raise InputError(f"{name} must be a numeric array, got {type(x).__name__}") from None
