"""The model's differentiable distance map ``C_M`` from a capsule body (paper Sec. 3.5).

The model's silhouette is approximated by the union of the projected capsules
("stadiums": all points within ``radius`` of a 2D segment). Its signed distance in
pixels from pixel centre ``p`` is

    sd(p) = min_k (dist(p, segment_k) - radius_k),    C_M(p) = max(0, sd(p)).

To keep it cheap it is evaluated exactly on a coarse grid of pixel centres, every
``grid_step`` pixels starting at pixel (0, 0), and bilinearly interpolated in between
(exact at grid pixels ``(u, v)`` with ``u % grid_step == 0`` and ``v % grid_step == 0``).
Differentiable w.r.t. the segment end points and radii: the minimum over the capsules and
its gradient are compiled (Numba) passes, the interpolation is torch (the tracker's E_c
interpolates inside its own compiled pass: ``flowmocap.fit.energies.silhouette_energy``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
import torch.nn.functional  # noqa: F401  (interpolate)
from numba import njit

from flowmocap.errors import InputError
from flowmocap.render._checks import check_size

__all__ = ["capsule_distance_grid", "capsule_signed_distance", "project_capsules", "grid_signed_distance_kernel",
           "grid_signed_distance_grad_kernel"]


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


@njit(cache=True, nogil=True)
def _grid_signed_distance_kernel(pts, a, d, inv, r, best, arg):
    """``best[b, n] = min_k (|p_n - closest point of segment k| - r[b, k])`` and its arg-min
    (the first on ties), for points ``pts (N, 2)``, segments ``a (B, K, 2)`` + ``t d``
    with ``inv = 1 / |d|^2`` ``(B, K)``; float64 throughout."""
    B, K = r.shape
    for bi in range(B):
        for n in range(pts.shape[0]):
            x = pts[n, 0]
            y = pts[n, 1]
            low = np.inf
            which = 0
            for k in range(K):
                px = x - a[bi, k, 0]
                py = y - a[bi, k, 1]
                dx = d[bi, k, 0]
                dy = d[bi, k, 1]
                t = (px * dx + py * dy) * inv[bi, k]
                if t < 0.0:
                    t = 0.0
                elif t > 1.0:
                    t = 1.0
                ex = px - t * dx
                ey = py - t * dy
                dist = math.sqrt(ex * ex + ey * ey) - r[bi, k]
                if dist < low:
                    low = dist
                    which = k
            best[bi, n] = low
            arg[bi, n] = which


class _GridSignedDistance(torch.autograd.Function):
    """``min_k (dist(p, segment_k) - r_k)`` at fixed points ``p (N, 2)`` for a batch.

    Inputs ``a, b (B, K, 2)``, ``r (B, K)``; output ``(B, N)``. The forward pass keeps the
    nearest capsule of each point, so the backward pass costs O(B N) (the gradient of
    a minimum flows to its arg-min; for the distance to a segment it is that of the
    distance to the fixed closest point ``c = a + t (b - a)``); both passes are compiled.
    """

    @staticmethod
    def forward(ctx, pts, a, b, r):  # noqa: D102
        # the minimum over the capsules in one compiled pass (in float64), not K rounds of
        # whole-grid torch operations: about 10 times faster for a body's 20 capsules
        a64 = a.detach().to(torch.float64)
        d64 = b.detach().to(torch.float64) - a64
        inv = 1.0 / (d64 * d64).sum(-1).clamp_min(1e-12)
        B, K = r.shape
        best = np.empty((B, pts.shape[0]))
        arg = np.empty((B, pts.shape[0]), dtype=np.int64)
        _grid_signed_distance_kernel(pts.detach().to(torch.float64).numpy(), a64.numpy(), d64.numpy(), inv.numpy(),
                                     r.detach().to(torch.float64).numpy(), best, arg)
        arg_t = torch.from_numpy(arg).to(a.device)
        ctx.save_for_backward(pts, a, b, arg_t)
        return torch.from_numpy(best).to(dtype=a.dtype, device=a.device)

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        pts, a, b, arg = ctx.saved_tensors
        f64 = lambda x: x.detach().to(torch.float64).contiguous().numpy()  # noqa: E731
        ga, gb, gr = np.zeros(a.shape), np.zeros(b.shape), np.zeros(a.shape[:2])
        _grid_signed_distance_grad_kernel(f64(pts), f64(a), f64(b), arg.numpy(), f64(grad), ga, gb, gr)
        as_a = lambda x: torch.from_numpy(x).to(dtype=a.dtype, device=a.device)  # noqa: E731
        return None, as_a(ga), as_a(gb), as_a(gr)


@njit(cache=True, nogil=True)
def _grid_signed_distance_grad_kernel(pts, a, b, arg, grad, ga, gb, gr):
    """The gradient of :class:`_GridSignedDistance`: each point's ``grad[b, n]`` goes to
    its nearest capsule ``arg[b, n]`` as that of the distance to the fixed closest point
    ``c = a + t (b - a)`` of its segment (``ga, gb (B, K, 2)``, ``gr (B, K)``, zeroed by the
    caller, accumulate). float64."""
    B, N = arg.shape
    for bi in range(B):
        for n in range(N):
            g = grad[bi, n]
            if g == 0.0:
                continue
            k = arg[bi, n]
            dx = b[bi, k, 0] - a[bi, k, 0]
            dy = b[bi, k, 1] - a[bi, k, 1]
            px = pts[n, 0] - a[bi, k, 0]
            py = pts[n, 1] - a[bi, k, 1]
            t = (px * dx + py * dy) / max(dx * dx + dy * dy, 1e-12)
            t = min(max(t, 0.0), 1.0)
            ex = px - t * dx
            ey = py - t * dy
            dist = math.sqrt(ex * ex + ey * ey)
            if dist > 1e-12:
                nx = ex / dist
                ny = ey / dist
                ga[bi, k, 0] -= nx * (1.0 - t) * g
                ga[bi, k, 1] -= ny * (1.0 - t) * g
                gb[bi, k, 0] -= nx * t * g
                gb[bi, k, 1] -= ny * t * g
            gr[bi, k] -= g


def capsule_distance_grid(
    starts_px: torch.Tensor,
    ends_px: torch.Tensor,
    radii_px: torch.Tensor,
    height: int,
    width: int,
    grid_step: int = 4,
    origin: tuple[int, int] = (0, 0),
) -> torch.Tensor:
    """The exact samples behind :func:`capsule_signed_distance`: the signed distance
    (pixels) to the union of 2D capsules at the pixel centres ``(x0 + j grid_step + 0.5,
    y0 + i grid_step + 0.5)`` of a ``height x width`` window at ``origin = (y0, x0)``.

    Args: as :func:`capsule_signed_distance`: ``starts_px``, ``ends_px`` ``(B, K, 2)``
    and ``radii_px`` ``(B, K)`` tensors in pixels; ``height``, ``width`` and ``grid_step``
    in pixels; ``origin`` ``(y0, x0)`` pixels, multiples of ``grid_step``.

    Returns:
        ``(B, gh, gw)`` tensor of the inputs' dtype with ``gh = (height - 1) // grid_step + 2``
        and ``gw = (width - 1) // grid_step + 2`` (one sample past the window's last pixel,
        so that every pixel lies in a grid cell), differentiable w.r.t. the end points
        and radii. Pixel ``(v, u)`` of the window lies at grid coordinate
        ``(v / grid_step, u / grid_step)``.

    Raises:
        InputError: wrong shapes, a bad step, or an origin off the grid.
    """
    if int(grid_step) != grid_step or grid_step < 1:
        raise InputError(f"grid_step must be a positive integer (pixels), got {grid_step}")
    step = int(grid_step)
    a, b, r = starts_px, ends_px, radii_px
    if a.dim() != 3 or a.shape[-1] != 2 or b.shape != a.shape:
        raise InputError(f"starts_px and ends_px must have shape (B, K, 2), got {tuple(a.shape)} and {tuple(b.shape)}")
    if r.shape != a.shape[:2]:
        raise InputError(f"radii_px must have shape (B, K) = {tuple(a.shape[:2])}, got {tuple(r.shape)}")
    h, w = check_size(height, width)
    y0, x0 = (int(o) for o in origin)
    if y0 % step or x0 % step:
        raise InputError(f"origin {origin} must be a multiple of grid_step ({step})")
    gh, gw = (h - 1) // step + 2, (w - 1) // step + 2
    gy = torch.arange(gh, dtype=a.dtype, device=a.device) * step + (y0 + 0.5)
    gx = torch.arange(gw, dtype=a.dtype, device=a.device) * step + (x0 + 0.5)
    pts = torch.stack(torch.meshgrid(gy, gx, indexing="ij")[::-1], dim=-1).reshape(-1, 2)
    return _GridSignedDistance.apply(pts, a, b, r).reshape(-1, gh, gw)


def capsule_signed_distance(
    starts_px: torch.Tensor,
    ends_px: torch.Tensor,
    radii_px: torch.Tensor,
    height: int,
    width: int,
    grid_step: int = 4,
    origin: tuple[int, int] = (0, 0),
) -> torch.Tensor:
    """Signed distance (pixels) of every pixel centre to the union of 2D capsules.

    ``sd(p) = min_k (dist(p, segment_k) - radius_k)``: negative inside the union,
    positive outside; the model's distance map is ``C_M = max(0, sd)``. Evaluated
    exactly on the pixel centres ``(u + 0.5, v + 0.5)`` with ``u, v`` multiples of
    ``grid_step`` and bilinearly interpolated in between (see the module docstring).

    Args:
        starts_px, ends_px: ``(B, K, 2)`` segment end points in pixels (pixel centres at
            +0.5), for a batch of B capsule sets.
        radii_px: ``(B, K)`` radii in pixels.
        height, width: size in pixels of the window evaluated (the whole image by default).
        grid_step: spacing in pixels of the exact evaluations (1 = exact everywhere).
        origin: ``(y0, x0)`` top-left pixel of the window, multiples of ``grid_step`` so
            that the grid is the whole image's.

    Returns:
        ``(B, height, width)`` tensor of the inputs' dtype, differentiable w.r.t. the end
        points and radii.

    Raises:
        InputError: wrong shapes, a bad step, or an origin off the grid.
    """
    grid = capsule_distance_grid(starts_px, ends_px, radii_px, height, width, grid_step, origin)
    step, (h, w), (gh, gw) = int(grid_step), check_size(height, width), grid.shape[1:]
    grid = grid[:, None]
    if step == 1:
        return grid[:, 0, :h, :w]
    # pixel u sits at grid coordinate u / step: align_corners interpolation onto
    # (gh - 1) * step + 1 samples puts output sample o exactly there
    up = torch.nn.functional.interpolate(
        grid, size=((gh - 1) * step + 1, (gw - 1) * step + 1), mode="bilinear", align_corners=True)
    return up[:, 0, :h, :w]


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


#: The compiled passes behind :func:`capsule_distance_grid`, for callers that chain them
#: with their own in one autograd node (``flowmocap.fit.energies.silhouette_energy``):
#: ``(pts (N, 2), a (B, K, 2), d = b - a, inv = 1 / |d|^2 (B, K), r (B, K), best (B, N),
#: arg (B, N) int64)`` and ``(pts, a, b, arg, grad (B, N), ga, gb (B, K, 2), gr (B, K))``,
#: float64, outputs filled (the gradients accumulate into zeroed arrays).
grid_signed_distance_kernel = _grid_signed_distance_kernel
grid_signed_distance_grad_kernel = _grid_signed_distance_grad_kernel
