"""The model's differentiable distance map ``C_M`` from a capsule body (paper Sec. 3.5).

``C_M(p)`` is the distance in pixels from pixel centre ``p`` to the model's silhouette
(0 inside), approximated by the union of the projected capsules ("stadiums": all
points within ``radius`` of a 2D segment):

    C_M(p) = max(0, min_k (dist(p, segment_k) - radius_k)).

To keep it cheap it is evaluated exactly on a coarse grid of pixel centres, every
``grid_step`` pixels starting at pixel (0, 0), and bilinearly interpolated in between
(exact at grid pixels ``(u, v)`` with ``u % grid_step == 0`` and ``v % grid_step == 0``;
between them the interpolation error is at most ``grid_step / 2`` px near a
capsule's rim, 0 inside the capsules and far from them it is tiny). Everything is
torch, differentiable w.r.t. the segment end points and radii.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional  # noqa: F401  (interpolate)

from flowmocap.errors import InputError
from flowmocap.render._checks import check_size

__all__ = ["capsule_distance_map", "project_capsules"]


def _as_tensor(x: Any, name: str, shape_tail: tuple[int, ...], ref: torch.Tensor | None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        t = x
    else:
        try:
            t = torch.as_tensor(np.asarray(x, dtype=np.float64))
        except (TypeError, ValueError):
            raise InputError(f"{name} must be an array of numbers") from None
    if t.ndim != 1 + len(shape_tail) or tuple(t.shape[1:]) != shape_tail:
        want = "(K" + "".join(f", {d}" for d in shape_tail) + ")"
        raise InputError(f"{name} must have shape {want}, got {tuple(t.shape)}")
    if not torch.is_floating_point(t):
        t = t.to(torch.float64)
    if ref is not None:
        t = t.to(dtype=ref.dtype, device=ref.device)
    if not torch.isfinite(t.detach()).all():
        raise InputError(f"{name} holds NaN or infinite values")
    return t


def _reference(*xs: Any) -> torch.Tensor | None:
    for x in xs:
        if isinstance(x, torch.Tensor) and torch.is_floating_point(x):
            return x
    return None


class _GridDistance(torch.autograd.Function):
    """``max(0, min_k (dist(p, segment_k) - r_k))`` at fixed points ``p (N, 2)``.

    The forward pass keeps only the nearest capsule of each point, so the backward pass
    costs O(N) instead of O(N K): by the envelope theorem the gradient of the distance
    to a segment w.r.t. its end points is that of the distance to the (fixed) closest
    point ``c = a + t (b - a)``: ``-n (1 - t)`` and ``-n t`` with ``n`` the unit vector
    from ``c`` to ``p``; w.r.t. the radius it is -1 (0 where clamped to 0 or at ``p = c``).
    """

    @staticmethod
    def forward(ctx, pts, a, b, r):  # noqa: D102
        d = b - a
        inv = 1.0 / (d * d).sum(-1).clamp_min(1e-12)
        best = torch.full((pts.shape[0],), float("inf"), dtype=a.dtype, device=a.device)
        arg = torch.zeros(pts.shape[0], dtype=torch.long, device=a.device)
        for k in range(a.shape[0]):
            px = pts[:, 0] - a[k, 0]
            py = pts[:, 1] - a[k, 1]
            t = ((px * d[k, 0] + py * d[k, 1]) * inv[k]).clamp(0.0, 1.0)
            ex = px - t * d[k, 0]
            ey = py - t * d[k, 1]
            dist = torch.sqrt(ex * ex + ey * ey) - r[k]
            closer = dist < best
            best = torch.where(closer, dist, best)
            arg = torch.where(closer, torch.full_like(arg, k), arg)
        ctx.save_for_backward(pts, a, b, r, arg, best)
        return best.clamp_min(0.0)

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        pts, a, b, r, arg, best = ctx.saved_tensors
        g = grad * (best > 0)
        ak, bk = a[arg], b[arg]
        d = bk - ak
        t = (((pts - ak) * d).sum(-1) / (d * d).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
        e = pts - ak - t[:, None] * d
        dist = torch.sqrt((e * e).sum(-1))
        n = torch.where(dist[:, None] > 1e-12, e / dist.clamp_min(1e-12)[:, None], torch.zeros_like(e))
        ga = torch.zeros_like(a).index_add_(0, arg, -n * ((1.0 - t) * g)[:, None])
        gb = torch.zeros_like(b).index_add_(0, arg, -n * (t * g)[:, None])
        gr = torch.zeros_like(r).index_add_(0, arg, -g)
        return None, ga, gb, gr


def capsule_distance_map(
    starts_px: Any,
    ends_px: Any,
    radii_px: Any,
    height: int,
    width: int,
    grid_step: int = 4,
) -> torch.Tensor:
    """Distance (pixels) of every pixel centre to the union of 2D capsules, 0 inside.

    Args:
        starts_px, ends_px: ``(K, 2)`` segment end points in pixels (pixel centres at
            +0.5), torch (differentiable) or numpy.
        radii_px: ``(K,)`` capsule radii in pixels.
        height, width: image size ``H, W``.
        grid_step: spacing in pixels of the grid of exact evaluations (1 = exact
            everywhere); see the module docstring.

    Returns:
        ``(H, W)`` torch tensor (dtype/device of the first floating torch input, else
        float64), differentiable w.r.t. the inputs.

    Raises:
        InputError: wrong shapes, NaNs, negative radii, an empty image, a bad step.
    """
    h, w = check_size(height, width)
    if int(grid_step) != grid_step or grid_step < 1:
        raise InputError(f"grid_step must be a positive integer (pixels), got {grid_step}")
    step = int(grid_step)
    ref = _reference(starts_px, ends_px, radii_px)
    a = _as_tensor(starts_px, "starts_px", (2,), ref)
    b = _as_tensor(ends_px, "ends_px", (2,), a)
    if a.shape[0] == 0:
        raise InputError("capsule_distance_map needs at least one capsule")
    if b.shape[0] != a.shape[0]:
        raise InputError(f"starts_px and ends_px must have the same length, got {a.shape[0]} and {b.shape[0]}")
    r = _as_tensor(radii_px, "radii_px", (), a)
    if r.shape[0] != a.shape[0]:
        raise InputError(f"radii_px must have one radius per capsule ({a.shape[0]}), got {r.shape[0]}")
    if (r.detach() < 0).any():
        raise InputError("radii_px must be non-negative")
    gh, gw = (h - 1) // step + 2, (w - 1) // step + 2
    gy = torch.arange(gh, dtype=a.dtype, device=a.device) * step + 0.5
    gx = torch.arange(gw, dtype=a.dtype, device=a.device) * step + 0.5
    pts = torch.stack(torch.meshgrid(gy, gx, indexing="ij")[::-1], dim=-1).reshape(-1, 2)
    grid = _GridDistance.apply(pts, a, b, r).reshape(gh, gw)
    if step == 1:
        return grid[:h, :w]
    # pixel u sits at grid coordinate u / step: align_corners interpolation onto
    # (gh - 1) * step + 1 samples puts output sample o exactly there
    up = torch.nn.functional.interpolate(
        grid[None, None], size=((gh - 1) * step + 1, (gw - 1) * step + 1), mode="bilinear", align_corners=True)
    return up[0, 0, :h, :w]


def project_capsules(
    starts3d: Any, ends3d: Any, radii: Any, fx: float, fy: float, cx: float, cy: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Project 3D capsules (camera coordinates, OpenCV axes) to 2D stadiums.

    The end points are projected exactly; the radius becomes
    ``radius * sqrt(fx * fy) / z_mid`` with ``z_mid`` the mean depth of the two end
    points. This is the first-order approximation: it ignores the perspective
    widening of a sphere's outline (relative error about ``(r / z)^2 / 2``, 0.1 % for a
    10 cm limb 2 m away), off-axis elongation, and it gives the stadium one width even
    when the capsule recedes in depth (then the near end is drawn too thin and the far
    end too thick, by the ratio of their depths to ``z_mid``).

    Args:
        starts3d, ends3d: ``(K, 3)`` segment end points in camera coordinates (metres).
        radii: ``(K,)`` radii in metres.
        fx, fy, cx, cy: pinhole intrinsics in pixels (pixel centres at +0.5).

    Returns:
        ``starts_px (K, 2)``, ``ends_px (K, 2)``, ``radii_px (K,)`` torch tensors,
        differentiable w.r.t. the inputs.

    Raises:
        InputError: wrong shapes, NaNs, or an end point closer than its radius to the
            camera plane (capsule not in front of the camera).
    """
    ref = _reference(starts3d, ends3d, radii)
    a = _as_tensor(starts3d, "starts3d", (3,), ref)
    b = _as_tensor(ends3d, "ends3d", (3,), a)
    r = _as_tensor(radii, "radii", (), a)
    if not (a.shape[0] == b.shape[0] == r.shape[0]):
        raise InputError("starts3d, ends3d and radii must have the same length K")
    if (torch.minimum(a[:, 2], b[:, 2]).detach() <= r.detach()).any():
        raise InputError("a capsule is not in front of the camera (end point depth <= radius)")

    def proj(p: torch.Tensor) -> torch.Tensor:
        return torch.stack([fx * p[:, 0] / p[:, 2] + cx, fy * p[:, 1] / p[:, 2] + cy], dim=1)

    z_mid = 0.5 * (a[:, 2] + b[:, 2])
    return proj(a), proj(b), r * float(np.sqrt(fx * fy)) / z_mid
