"""Colour images of a mesh for synthesising test videos: Lambertian shading,
supersampled anti-aliasing, compositing over a background, and a procedural
high-frequency surface pattern that optical flow can lock on to."""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
from numba import njit

from flowmocap.errors import InputError
from flowmocap.render._checks import check_faces, check_points, check_size, to_numpy
from flowmocap.render.interpolate import interpolate_covered
from flowmocap.render.raster import rasterize

__all__ = ["shade", "vertex_normals", "face_normals", "procedural_pattern", "value_noise"]


def face_normals(verts: Any, faces: Any) -> np.ndarray:
    """Unit normals of the triangles by the right-hand rule.

    Args:
        verts: ``(V, 3)`` positions (metres). faces: ``(F, 3)`` int.

    Returns:
        ``(F, 3)`` float64 unit normals ``(v1 - v0) x (v2 - v0)`` (zero for degenerate faces).
    """
    v = check_points(verts, "verts", 3)
    f = check_faces(faces, v.shape[0])
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def vertex_normals(verts: Any, faces: Any) -> np.ndarray:
    """Smooth vertex normals: the area-weighted mean of the adjacent face normals.

    Args:
        verts: ``(V, 3)`` positions (metres). faces: ``(F, 3)`` int.

    Returns:
        ``(V, 3)`` float64 unit normals (zero for vertices in no face).
    """
    v = check_points(verts, "verts", 3)
    f = check_faces(faces, v.shape[0])
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # length = 2 * area
    out = np.zeros_like(v)
    idx = f.ravel()
    for c in range(3):
        out[:, c] = np.bincount(idx, weights=np.repeat(n[:, c], 3), minlength=v.shape[0])
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, norm, out=np.zeros_like(out), where=norm > 0)


def _lattice_tables(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.permutation(256).astype(np.int64), rng.random(256)


@njit(cache=True, nogil=True)
def _value_noise_kernel(p, perm, vals, out):
    for n in range(p.shape[0]):
        fx = np.floor(p[n, 0])
        fy = np.floor(p[n, 1])
        fz = np.floor(p[n, 2])
        ix = np.int64(fx)
        iy = np.int64(fy)
        iz = np.int64(fz)
        tx = p[n, 0] - fx
        ty = p[n, 1] - fy
        tz = p[n, 2] - fz
        sx = tx * tx * (3.0 - 2.0 * tx)
        sy = ty * ty * (3.0 - 2.0 * ty)
        sz = tz * tz * (3.0 - 2.0 * tz)
        acc = 0.0
        for dx in range(2):
            wx = sx if dx else 1.0 - sx
            hx = perm[(ix + dx) & 255]
            for dy in range(2):
                wy = sy if dy else 1.0 - sy
                hy = perm[(hx + iy + dy) & 255]
                for dz in range(2):
                    wz = sz if dz else 1.0 - sz
                    acc += wx * wy * wz * vals[perm[(hy + iz + dz) & 255]]
        out[n] = acc


def value_noise(points: Any, seed: int = 0) -> np.ndarray:
    """Smooth 3D value noise with unit lattice spacing.

    Random values in ``[0, 1]`` on the integer lattice, interpolated with a smoothstep
    (C1) trilinear blend; periodic with period 256 along each axis.

    Args:
        points: ``(N, 3)`` positions in lattice units.
        seed: selects the random lattice.

    Returns:
        ``(N,)`` float64 values in ``[0, 1]``.
    """
    p = check_points(points, "points", 3)
    if np.abs(p).max(initial=0.0) > 2.0**52:
        raise InputError("value_noise: points too far from the origin for the lattice")
    perm, vals = _lattice_tables(seed)
    out = np.empty(p.shape[0])
    _value_noise_kernel(p, perm, vals, out)
    return out


def procedural_pattern(points: Any, cell: float = 0.04, octaves: int = 4, seed: int = 0) -> np.ndarray:
    """A colourful, clothing-like pattern with detail at several scales, for flow to lock on.

    Evaluate it at *rest-pose* surface coordinates (e.g. the output of
    :func:`~flowmocap.render.interpolate` of the rest-pose vertices) so that it moves
    with the surface; evaluated at vertex positions it gives per-vertex colours.

    Args:
        points: ``(N, 3)`` surface positions in metres.
        cell: size of the coarsest pattern features in metres; each further octave
            halves it (default 4 cm down to 5 mm).
        octaves: number of noise octaves.
        seed: selects the pattern.

    Returns:
        ``(N, 3)`` float64 RGB colours in ``[0, 1]``.
    """
    p = check_points(points, "points", 3) / float(cell)
    if octaves < 1:
        raise InputError(f"octaves must be >= 1, got {octaves}")
    chans = []
    for c in range(3):
        acc = np.zeros(p.shape[0])
        amp, total = 1.0, 0.0
        for o in range(octaves):
            acc += amp * value_noise(p * 2.0**o + 17.0 * c, seed=seed * 7 + c * 101 + o)
            total += amp
            amp *= 0.6
        chans.append(acc / total)
    rgb = np.stack(chans, axis=1)
    # stretch contrast around the mean (fbm concentrates near 0.5)
    rgb = 0.5 + 2.2 * (rgb - 0.5)
    return np.clip(rgb, 0.03, 0.97)


def _sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup (clamped at the border) of ``(Ht, Wt, 3)`` at ``uv (N, 2)``."""
    ht, wt = texture.shape[:2]
    x = np.clip(uv[:, 0] * wt - 0.5, 0.0, wt - 1.0)
    y = np.clip(uv[:, 1] * ht - 0.5, 0.0, ht - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), wt - 2 if wt > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(np.int64), ht - 2 if ht > 1 else 0)
    x1 = np.minimum(x0 + 1, wt - 1)
    y1 = np.minimum(y0 + 1, ht - 1)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    return ((1 - fy) * ((1 - fx) * texture[y0, x0] + fx * texture[y0, x1])
            + fy * ((1 - fx) * texture[y1, x0] + fx * texture[y1, x1]))


def shade(
    verts_px: Any,
    depth: Any,
    faces: Any,
    verts_cam: Any,
    colors: Any = None,
    *,
    uv: Any = None,
    texture: Any = None,
    surface_coords: Any = None,
    pattern: Callable[[np.ndarray], np.ndarray] | None = None,
    background: Any = None,
    height: int | None = None,
    width: int | None = None,
    light_dir: tuple[float, float, float] = (-0.3, -0.5, -1.0),
    ambient: float = 0.35,
    smooth: bool = True,
    supersample: int = 2,
    cull_backfaces: bool = False,
) -> np.ndarray:
    """Render a Lambertian-shaded, anti-aliased colour image of a mesh over a background.

    The surface colour (albedo) comes from exactly one of: per-vertex ``colors``; a
    ``texture`` image looked up at interpolated ``uv``; or ``pattern`` (default
    :func:`procedural_pattern`) evaluated per pixel at the interpolated
    ``surface_coords`` (e.g. rest-pose vertex positions, so the pattern sticks to the
    moving surface -- the best choice for optical flow). Shading is
    ``albedo * (ambient + (1 - ambient) * max(0, n . l))`` with ``n`` the (smooth or
    per-face) normal turned towards the camera (two-sided lighting). The image is
    rendered at ``supersample`` x ``supersample`` samples per pixel and box-filtered, so
    edge pixels mix surface and background colour (premultiplied compositing).

    Args:
        verts_px: ``(V, 2)`` projected vertices in pixels (pixel centres at +0.5).
        depth: ``(V,)`` camera-space Z in metres (positive in front of the camera).
        faces: ``(F, 3)`` int vertex indices (counter-clockwise seen from outside).
        verts_cam: ``(V, 3)`` camera-space vertex positions in metres (for normals).
        colors: ``(V, 3)`` per-vertex RGB in ``[0, 1]``.
        uv: ``(V, 2)`` texture coordinates in ``[0, 1]``: ``u`` along texture columns,
            ``v`` along rows, ``(0, 0)`` the top-left corner of the texture image.
        texture: ``(Ht, Wt, 3)`` uint8 (0..255) or float (0..1) texture image.
        surface_coords: ``(V, 3)`` coordinates (metres) at which ``pattern`` is evaluated.
        pattern: callable ``(N, 3) -> (N, 3)`` RGB in ``[0, 1]``; default
            :func:`procedural_pattern`.
        background: ``(H, W, 3)`` uint8 image to composite over; ``None`` for black
            (then ``height`` and ``width`` are required).
        height, width: image size in pixels (taken from ``background`` if omitted).
        light_dir: direction *towards* the light in camera coordinates (x right,
            y down, z forward); default from the upper left, behind the camera.
        ambient: ambient fraction in ``[0, 1]``.
        smooth: interpolate smooth vertex normals (True) or use flat face normals.
        supersample: samples per pixel along each axis (>= 1; 2 means 2x2).
        cull_backfaces: skip back-facing triangles.

    Returns:
        ``(H, W, 3)`` uint8 RGB image.

    Raises:
        InputError: wrong shapes, NaNs, not exactly one colour source, bad sizes.
    """
    xy = check_points(verts_px, "verts_px", 2)
    nv = xy.shape[0]
    f = check_faces(faces, nv)
    vc = check_points(verts_cam, "verts_cam", 3, nv)
    if background is not None:
        bg = to_numpy(background, "background")
        if bg.ndim != 3 or bg.shape[2] != 3:
            raise InputError(f"background must be an (H, W, 3) uint8 image, got shape {bg.shape}")
        if height is None:
            height = bg.shape[0]
        if width is None:
            width = bg.shape[1]
        if bg.shape[:2] != (height, width):
            raise InputError(f"background has size {bg.shape[:2]} but the image is {(height, width)}")
    elif height is None or width is None:
        raise InputError("shade needs height and width when no background image is given")
    h, w = check_size(height, width)
    s = int(supersample)
    if s != supersample or s < 1 or s > 8:
        raise InputError(f"supersample must be an integer in 1..8, got {supersample}")
    if not 0.0 <= float(ambient) <= 1.0:
        raise InputError(f"ambient must be in [0, 1], got {ambient}")
    sources = sum(x is not None for x in (colors, texture, surface_coords))
    if sources != 1:
        raise InputError("shade needs exactly one colour source: colors, texture (with uv) or surface_coords")
    light = np.asarray(light_dir, dtype=np.float64)
    if light.shape != (3,) or not np.all(np.isfinite(light)) or np.linalg.norm(light) == 0:
        raise InputError(f"light_dir must be a non-zero 3-vector, got {light_dir!r}")
    light = light / np.linalg.norm(light)

    if colors is not None:
        attr = check_points(colors, "colors", 3, nv)
    elif texture is not None:
        if uv is None:
            raise InputError("a texture needs per-vertex uv coordinates (V, 2)")
        attr = check_points(uv, "uv", 2, nv)
        tex = to_numpy(texture, "texture")
        if tex.ndim != 3 or tex.shape[2] != 3 or tex.shape[0] < 1 or tex.shape[1] < 1:
            raise InputError(f"texture must be an (Ht, Wt, 3) image, got shape {tex.shape}")
        tex = tex.astype(np.float64) / (255.0 if tex.dtype == np.uint8 else 1.0)
    else:
        attr = check_points(surface_coords, "surface_coords", 3, nv)

    hs, ws = h * s, w * s
    raster = rasterize(xy * s, depth, f, hs, ws, cull_backfaces=cull_backfaces)
    covered = raster.face_id >= 0

    point = interpolate_covered(raster, vc, f)
    if smooth:
        n = interpolate_covered(raster, vertex_normals(vc, f), f)
    else:
        n = face_normals(vc, f)[raster.face_id[covered]]
    norm = np.sqrt((n * n).sum(axis=1, keepdims=True))
    n = np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)
    n = np.where(((n * point).sum(axis=1) > 0)[:, None], -n, n)

    a = interpolate_covered(raster, attr, f)
    if colors is not None:
        albedo = a
    elif texture is not None:
        albedo = _sample_texture(tex, a)
    else:
        albedo = np.asarray((pattern or procedural_pattern)(a), dtype=np.float64)
        if albedo.shape != (a.shape[0], 3):
            raise InputError(f"pattern must map (N, 3) points to (N, 3) colours, got {albedo.shape}")
    intensity = float(ambient) + (1.0 - float(ambient)) * np.maximum(0.0, n @ light)
    rgb = np.clip(albedo, 0.0, 1.0) * intensity[:, None]

    full = np.zeros((hs, ws, 3), dtype=np.float32)
    full[covered] = rgb
    cov = covered.astype(np.float32)
    img = np.zeros((h, w, 3), dtype=np.float32)
    alpha = np.zeros((h, w), dtype=np.float32)
    for i in range(s):
        for j in range(s):
            img += full[i::s, j::s]
            alpha += cov[i::s, j::s]
    img = img.astype(np.float64) / (s * s)
    alpha = alpha.astype(np.float64) / (s * s)
    if background is not None:
        img = img + (1.0 - alpha)[..., None] * (bg.astype(np.float64) / 255.0)
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
