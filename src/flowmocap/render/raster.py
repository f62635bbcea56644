"""Z-buffered triangle rasterisation of projected vertices (CPU, Numba).

Pixel convention (the project's, see :mod:`flowmocap.geometry.camera`): pixel ``(u, v)``
(column ``u``, row ``v``) covers ``[u, u+1) x [v, v+1)`` and is sampled at its centre
``(u + 0.5, v + 0.5)``; the image spans ``[0, W] x [0, H]``.

Coverage rule: a pixel centre belongs to a triangle if it is strictly inside, or on an
edge whose inward normal points to +x (or, for a horizontal edge, to +y) -- a
"top-left" style tie rule. Edge functions of a shared edge are evaluated from the two
endpoints in one canonical order, so two triangles sharing an edge agree bit for bit and
a pixel centre on the edge goes to exactly one of them: no gaps, no double coverage.

Near plane: triangles with any vertex at ``depth < near`` are skipped whole (no
clipping). For a body in front of the camera this never happens; a body partly behind
the camera loses the triangles that cross the near plane.

Orientation: a triangle is *front-facing* when its vertices run counter-clockwise as
seen by the camera (outward normals by the right-hand rule, OpenCV camera looking
along +z), which is a *negative* signed area ``(x1-x0)(y2-y0) - (x2-x0)(y1-y0)`` in pixel
coordinates (y down). ``cull_backfaces=True`` drops the others.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from flowmocap.errors import InputError
from flowmocap.render._checks import check_faces, check_points, check_size, check_vector

__all__ = ["Raster", "rasterize", "silhouette", "body_mask"]


@dataclass(frozen=True)
class Raster:
    """What the rasteriser saw at each pixel centre.

    Attributes:
        face_id: ``(H, W)`` int32, index of the visible triangle, ``-1`` for background.
        bary: ``(H, W, 3)`` float32, perspective-correct barycentric coordinates of the
            pixel centre's surface point w.r.t. the visible face's three vertices (in the
            order of ``faces[face_id]``); they sum to 1; zero on background. Use
            :func:`flowmocap.render.interpolate` to interpolate vertex attributes.
        depth: ``(H, W)`` float32, camera-space Z of the visible surface point in metres
            (perspective-correct), ``inf`` on background.
        bbox: ``(row0, row1, col0, col1)``, half-open pixel ranges that hold every
            covered pixel (all zero if none), or ``None`` if unknown.
    """

    face_id: np.ndarray
    bary: np.ndarray
    depth: np.ndarray
    bbox: tuple[int, int, int, int] | None = None

    @property
    def height(self) -> int:
        """Image height H in pixels."""
        return int(self.face_id.shape[0])

    @property
    def width(self) -> int:
        """Image width W in pixels."""
        return int(self.face_id.shape[1])

    @property
    def mask(self) -> np.ndarray:
        """``(H, W)`` bool, True where the mesh covers the pixel centre."""
        return self.face_id >= 0


@njit(cache=True, nogil=True, inline="always")
def _edge_setup(ax, ay, bx, by):
    """Canonical endpoints (lexicographic) of edge a->b, the sign that maps the canonical
    edge function back to a->b, and the tie flag (include centres lying on the edge)."""
    sign = 1.0
    if ax > bx or (ax == bx and ay > by):
        ax, ay, bx, by = bx, by, ax, ay
        sign = -1.0
    # inward normal of the edge a->b for a triangle with positive signed area
    nx = -(by - ay) * sign
    ny = (bx - ax) * sign
    tie = nx > 0.0 or (nx == 0.0 and ny > 0.0)
    return ax, ay, bx - ax, by - ay, sign, tie


@njit(cache=True, nogil=True, error_model="numpy")
def _rasterize_kernel(xy, z, faces, cull, near, face_id, depth, bary):
    """Returns the bounding box (row0, row1, col0, col1) of the triangles drawn."""
    H, W = face_id.shape
    inv_z = 1.0 / z
    br0, br1, bc0, bc1 = H, 0, W, 0
    for f in range(faces.shape[0]):
        i0 = faces[f, 0]
        i1 = faces[f, 1]
        i2 = faces[f, 2]
        z0 = z[i0]
        z1 = z[i1]
        z2 = z[i2]
        if z0 < near or z1 < near or z2 < near:
            continue
        x0 = xy[i0, 0]
        y0 = xy[i0, 1]
        x1 = xy[i1, 0]
        y1 = xy[i1, 1]
        x2 = xy[i2, 0]
        y2 = xy[i2, 1]
        # bounding box of pixel centres u + 0.5 in [xmin, xmax]; most triangles of a
        # fine mesh contain no pixel centre and leave here
        xmin = min(x0, min(x1, x2))
        xmax = max(x0, max(x1, x2))
        ymin = min(y0, min(y1, y2))
        ymax = max(y0, max(y1, y2))
        if xmax < 0.5 or ymax < 0.5 or xmin > W - 0.5 or ymin > H - 0.5:
            continue
        u0 = max(0, int(np.ceil(xmin - 0.5)))
        u1 = min(W - 1, int(np.floor(xmax - 0.5)))
        if u0 > u1:
            continue
        v0 = max(0, int(np.ceil(ymin - 0.5)))
        v1 = min(H - 1, int(np.floor(ymax - 0.5)))
        if v0 > v1:
            continue
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0.0:
            continue
        if cull and area > 0.0:
            continue
        # orient to positive area: slots (a, b, c) hold original corners (0, s1, s2)
        if area > 0.0:
            s1 = 1
            s2 = 2
            bx_ = x1
            by_ = y1
            cx_ = x2
            cy_ = y2
            izb = inv_z[i1]
            izc = inv_z[i2]
        else:
            s1 = 2
            s2 = 1
            bx_ = x2
            by_ = y2
            cx_ = x1
            cy_ = y1
            izb = inv_z[i2]
            izc = inv_z[i1]
        iza = inv_z[i0]
        drawn = False
        ax_ = x0
        ay_ = y0
        # edge k is opposite slot k: e0 = b->c, e1 = c->a, e2 = a->b
        e0x, e0y, e0dx, e0dy, e0s, e0t = _edge_setup(bx_, by_, cx_, cy_)
        e1x, e1y, e1dx, e1dy, e1s, e1t = _edge_setup(cx_, cy_, ax_, ay_)
        e2x, e2y, e2dx, e2dy, e2s, e2t = _edge_setup(ax_, ay_, bx_, by_)
        for v in range(v0, v1 + 1):
            py = v + 0.5
            r0 = e0dx * (py - e0y)
            r1 = e1dx * (py - e1y)
            r2 = e2dx * (py - e2y)
            for u in range(u0, u1 + 1):
                px = u + 0.5
                w0 = (r0 - e0dy * (px - e0x)) * e0s
                if w0 < 0.0 or (w0 == 0.0 and not e0t):
                    continue
                w1 = (r1 - e1dy * (px - e1x)) * e1s
                if w1 < 0.0 or (w1 == 0.0 and not e1t):
                    continue
                w2 = (r2 - e2dy * (px - e2x)) * e2s
                if w2 < 0.0 or (w2 == 0.0 and not e2t):
                    continue
                s = w0 + w1 + w2
                if s <= 0.0:
                    continue
                p0 = w0 * iza
                p1 = w1 * izb
                p2 = w2 * izc
                iz = p0 + p1 + p2
                zz = np.float32(s / iz)
                if zz < depth[v, u]:
                    depth[v, u] = zz
                    face_id[v, u] = f
                    bary[v, u, 0] = p0 / iz
                    bary[v, u, s1] = p1 / iz
                    bary[v, u, s2] = p2 / iz
                    drawn = True
        if drawn:
            br0 = min(br0, v0)
            br1 = max(br1, v1 + 1)
            bc0 = min(bc0, u0)
            bc1 = max(bc1, u1 + 1)
    if br1 <= br0:
        return 0, 0, 0, 0
    return br0, br1, bc0, bc1


def rasterize(
    verts_px: Any,
    depth: Any,
    faces: Any,
    height: int,
    width: int,
    cull_backfaces: bool = False,
    near: float = 1e-3,
) -> Raster:
    """Rasterise a triangle mesh whose vertices are already projected to pixels.

    Args:
        verts_px: ``(V, 2)`` projected vertex positions ``(x, y)`` in pixels (pixel
            centres at integer + 0.5), numpy or torch (detached; no gradient flows
            through the rasteriser -- visibility is piecewise constant).
        depth: ``(V,)`` camera-space Z of the vertices in metres (positive in front of
            the camera); used for the z-buffer and perspective-correct barycentrics.
        faces: ``(F, 3)`` int vertex indices, or a :class:`~flowmocap.render.Faces`.
        height, width: image size in pixels (``H``, ``W``).
        cull_backfaces: drop triangles that face away from the camera (clockwise as
            seen by the camera; see the module docstring).
        near: near plane in metres; a triangle with any vertex at ``depth < near`` is
            skipped whole (no clipping).

    Returns:
        :class:`Raster` with ``face_id (H, W) int32`` (-1 background),
        ``bary (H, W, 3) float32`` (perspective-correct) and ``depth (H, W) float32``
        (metres, inf background). The nearest surface wins; exact depth ties keep the
        lower face index.

    Raises:
        InputError: wrong shapes, NaN/inf vertices or depths, indices out of range, an
            empty image, or a non-positive ``near``.
    """
    h, w = check_size(height, width)
    xy = check_points(verts_px, "verts_px", 2)
    z = check_vector(depth, "depth", xy.shape[0])
    f = check_faces(faces, xy.shape[0])
    near = float(near)
    if not np.isfinite(near) or near <= 0.0:
        raise InputError(f"near must be a positive distance in metres, got {near}")
    face_id = np.full((h, w), -1, dtype=np.int32)
    zbuf = np.full((h, w), np.inf, dtype=np.float32)
    bary = np.zeros((h, w, 3), dtype=np.float32)
    bbox = _rasterize_kernel(xy, z, f, bool(cull_backfaces), near, face_id, zbuf, bary)
    return Raster(face_id, bary, zbuf, tuple(int(b) for b in bbox))


_SCRATCH = threading.local()


def rasterize_scratch(xy: np.ndarray, z: np.ndarray, faces: np.ndarray, height: int, width: int,
                      cull_backfaces: bool, near: float) -> Raster:
    """:func:`rasterize` into per-thread buffers reused between calls (already checked
    inputs). Only the previous call's bounding box is cleared, which saves the page
    faults of fresh full-image buffers. The result is overwritten by the next call in
    the same thread, and ``bary`` is stale (not zero) on background pixels: for internal,
    transient use only (e.g. inside ``flow_loss``).

    Args:
        xy: ``(V, 2)`` float64 projected vertices, pixels (as :func:`check_points
            <flowmocap.render._checks.check_points>` returns them).
        z: ``(V,)`` float64 camera-space depths, metres.
        faces: ``(F, 3)`` int32 checked vertex indices.
        height, width: image size in pixels.
        cull_backfaces, near: as for :func:`rasterize` (``near`` in metres).
    """
    key = (height, width)
    buf = getattr(_SCRATCH, "buffers", None)
    if buf is None or buf[0] != key:
        buf = [key, np.full((height, width), -1, np.int32), np.full((height, width), np.inf, np.float32),
               np.zeros((height, width, 3), np.float32), (0, 0, 0, 0)]
        _SCRATCH.buffers = buf
    _, face_id, zbuf, bary, (r0, r1, c0, c1) = buf
    face_id[r0:r1, c0:c1] = -1
    zbuf[r0:r1, c0:c1] = np.inf
    box = _rasterize_kernel(xy, z, faces, bool(cull_backfaces), float(near), face_id, zbuf, bary)
    bbox = tuple(int(b) for b in box)
    buf[4] = bbox
    return Raster(face_id, bary, zbuf, bbox)


def body_mask(verts_px: Any, depth: Any, faces: Any, height: int, width: int) -> np.ndarray:
    """The pixels a closed mesh (a posed body) covers: :func:`rasterize` with back faces
    culled (the same outline as without, from half the triangles), then :func:`silhouette`.

    Args:
        verts_px: ``(V, 2)`` projected vertices in pixels (pixel centres at integer + 0.5).
        depth: ``(V,)`` camera-space Z in metres.
        faces: ``(F, 3)`` int vertex indices, or a :class:`~flowmocap.render.Faces`.
        height, width: image size in pixels.

    Returns:
        ``(H, W)`` bool, True where a triangle covers the pixel centre.
    """
    return rasterize(verts_px, depth, faces, height, width, cull_backfaces=True).face_id >= 0


def silhouette(raster: Raster, dtype: Any = bool) -> np.ndarray:
    """The model's binary silhouette.

    Args:
        raster: a :class:`Raster`.
        dtype: ``bool`` (default) or a numeric dtype (1.0 inside, 0.0 outside).

    Returns:
        ``(H, W)`` array, True / 1 where a triangle covers the pixel centre.
    """
    if not isinstance(raster, Raster):
        raise InputError(f"silhouette needs a Raster from rasterize(), got {type(raster).__name__}")
    m = raster.face_id >= 0
    return m if np.dtype(dtype) == np.bool_ else m.astype(dtype)
