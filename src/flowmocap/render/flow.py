r"""The flow renderer (paper Sec. 3.2) and the flow objective ``E_f`` (Sec. 3.3).

Rendered flow
-------------
``F_r(i, i-1)`` is *backward* flow stored at frame ``i``'s pixels: at every pixel ``p``
of frame ``i`` covered by the mesh, the 2D displacement ``(dx, dy)`` in pixels from
``p`` to where the same surface point was in frame ``i - 1``. Background pixels get
zero flow (the paper's static camera and static background).

Let the visible triangle at ``p`` have projected vertices ``x_k`` (frame ``i``) and
``x'_k`` (frame ``i - 1``), depths ``z_k`` and ``z'_k``, and let ``lambda_k`` be the
*screen-space* barycentrics of ``p`` in the frame-``i`` triangle (``p = sum lambda_k
x_k``). The surface point seen at ``p`` has perspective-correct barycentrics ``b_k``
proportional to ``lambda_k / z_k``; in frame ``i - 1`` it is ``sum b_k X'_k`` and
projects (for any pinhole camera: the intrinsics cancel) to ``sum mu_k x'_k`` with

    mu_k = lambda_k rho_k / sum_j lambda_j rho_j,     rho_k = z'_k / z_k.

So the exact flow of the surface point is ``F = sum_k mu_k x'_k - p``. Two modes:

* **paper** (default, depths not given): ``rho = 1``, i.e. ``F = sum_k lambda_k
  (x'_k - x_k)``, the screen-space barycentric interpolation of the projected vertex
  displacements that the paper (and OpenDR) use. It is exact whenever the three
  vertices' depth ratios ``z'/z`` are equal -- any motion parallel to the image plane,
  rotation about the optical axis, pure 2D motion of the projected vertices -- and
  otherwise off by ``O(|rho_j - rho_k| * |x'_j - x'_k|)``: tiny for a fine mesh
  (measured for a 3.4 degree rotation step: 4e-4 px with 2 px triangles, as SMPL at
  640x480; 0.4 px with 50-100 px faces of a coarse box; see the tests).
  Perspective-correct barycentrics would *not* be better here: ``sum b_k x_k != p``, so
  ``sum b_k (x'_k - x_k)`` is wrong even for a pure rotation about the optical axis.
* **exact** (``depth_cur`` and ``depth_prev`` given): ``rho_k = z'_k / z_k``, the exact
  displacement of the visible surface point for a mesh moving vertex by vertex (each
  triangle moving affinely in 3D), with gradients also w.r.t. both depths.

Flow objective
--------------
With ``w(p) >= 0`` a per-pixel weight (validity of the observed flow), the level-0
residual image is ``r_0(p) = sqrt(w(p)) (F_o(p) - F_r(p))`` over *all* pixels (the
paper's sum over ``p``; with ``covered_only=True`` it is additionally multiplied by the
model's coverage mask). The pyramid is that of the **residual** image,
``r_l = pyrDown^l(r_0)`` (the same linear operator for both flows, so this equals the
difference of the two flows' pyramids after the weighting). Flow vectors are **not**
rescaled at coarser levels: every level measures residuals in level-0 pixels, so the
levels are commensurable and the sum is one consistent quantity:

    E_f = sum_l s_l sum_p || r_l(p) ||^2,        s_l = 4**l by default,

``s_l = 4**l`` compensating the 4x fewer pixels per level, so that a smooth residual
contributes about equally at every level (pass ``level_weights`` to change it;
``levels=1`` is the plain sum of the paper's equation).

Gradients (w.r.t. the projected vertices of both frames, visibility fixed):
through the displacements (``d F / d x'_k = mu_k``), through the barycentrics of ``p``
w.r.t. the frame-``i`` vertices (``d lambda / d x_k = -lambda_k grad_p lambda``), and an
OpenDR-style occlusion-boundary term: for every pair of 4-neighbour pixels ``p, q`` on
an occlusion boundary (one is background, or their faces share no vertex; the face
nearer to the camera at its pixel is the front one), moving the front face's vertices by ``delta`` along the pair's axis moves the edge by
``beta_k delta`` (``beta`` = front face barycentrics of the point between the two pixel
centres, clamped to the triangle) and changes both pixels by half the residual jump,
``d r(p) = d r(q) = (r(front) - r(back)) / 2`` per pixel of edge motion (a central
difference across the edge; for level 0 it is exactly the derivative of a
coverage-smoothed energy). The silhouette term of the paper carries the outline more
robustly; ``boundary=False`` switches this part off.

Speed: value and gradient come from one Numba call that works on the bounding box of
the covered pixels (the pyramid of ``sqrt(w) F_o`` is precomputed once per observed
frame pair by :func:`flow_target`); pass a ``FlowTarget`` and, where available, a
``Raster`` when evaluating ``E_f`` many times. ``cull_backfaces=True`` halves the
rasterisation time for closed meshes (a body) without changing what is visible.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from concurrent.futures import Executor, Future
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import scipy.sparse as sp
import torch
from numba import njit

from flowmocap.errors import InputError
from flowmocap.render._checks import (
    check_faces,
    check_points,
    check_vector,
    to_numpy,
)
from flowmocap.render.pyramid import (
    reflect_index,
    binomial_tap,
    down_region,
    pyr_down_adjoint_region,
    pyr_down_region,
    pyramid_shapes,
)
from flowmocap.render.raster import Raster, rasterize_scratch

__all__ = ["FlowTarget", "FlowResiduals", "flow_target", "render_flow", "flow_loss", "flow_loss_async",
           "PendingFlow", "flow_residuals"]


# ----------------------------------------------------------------------------- kernels


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _screen_bary(px, py, x0, y0, x1, y1, x2, y2):
    """Screen-space barycentrics of (px, py) and their gradients w.r.t. (px, py)."""
    inv = 1.0 / ((x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0))
    l0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) * inv
    l1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) * inv
    l2 = 1.0 - l0 - l1
    return (l0, l1, l2, (y1 - y2) * inv, (x2 - x1) * inv, (y2 - y0) * inv, (x0 - x2) * inv,
            (y0 - y1) * inv, (x1 - x0) * inv)


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _face_bary(faces, xc, f, px, py):
    """Vertices ``i0, i1, i2`` of face ``f`` and :func:`_screen_bary` of (px, py) in its
    frame-``i`` triangle ``xc``."""
    i0 = faces[f, 0]
    i1 = faces[f, 1]
    i2 = faces[f, 2]
    l0, l1, l2, d0x, d0y, d1x, d1y, d2x, d2y = _screen_bary(
        px, py, xc[i0, 0], xc[i0, 1], xc[i1, 0], xc[i1, 1], xc[i2, 0], xc[i2, 1])
    return i0, i1, i2, l0, l1, l2, d0x, d0y, d1x, d1y, d2x, d2y


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _prev_point(xp, rho, i0, i1, i2, l0, l1, l2):
    """Where the surface point with screen barycentrics ``l`` was at frame ``i - 1``:
    ``m_k = lambda_k rho_k``, ``s = 1 / sum_k m_k`` (so ``mu_k = m_k s``) and
    ``q = sum_k mu_k x'_k`` (module docstring); the flow is ``q - p``."""
    m0 = l0 * rho[i0]
    m1 = l1 * rho[i1]
    m2 = l2 * rho[i2]
    s = 1.0 / (m0 + m1 + m2)
    qx = (m0 * xp[i0, 0] + m1 * xp[i1, 0] + m2 * xp[i2, 0]) * s
    qy = (m0 * xp[i0, 1] + m1 * xp[i1, 1] + m2 * xp[i2, 1]) * s
    return m0, m1, m2, s, qx, qy


@njit(cache=True, nogil=True, error_model="numpy")
def _render_flow_kernel(face_id, faces, xc, xp, rho, flow):
    H, W = face_id.shape
    for v in range(H):
        py = v + 0.5
        for u in range(W):
            f = face_id[v, u]
            if f < 0:
                continue
            px = u + 0.5
            i0, i1, i2, l0, l1, l2, _a, _b, _c, _d, _e, _f = _face_bary(faces, xc, f, px, py)
            _m0, _m1, _m2, _s, qx, qy = _prev_point(xp, rho, i0, i1, i2, l0, l1, l2)
            flow[v, u, 0] = qx - px
            flow[v, u, 1] = qy - py


@njit(cache=True, nogil=True)
def _covered_bbox(face_id):
    H, W = face_id.shape
    r0, r1, c0, c1 = H, 0, W, 0
    for v in range(H):
        row_any = False
        for u in range(W):
            if face_id[v, u] >= 0:
                row_any = True
                if u < c0:
                    c0 = u
                break
        if not row_any:
            continue
        for u in range(W - 1, -1, -1):
            if face_id[v, u] >= 0:
                if u + 1 > c1:
                    c1 = u + 1
                break
        if v < r0:
            r0 = v
        r1 = v + 1
    if r1 <= r0:
        return 0, 0, 0, 0
    return r0, r1, c0, c1


@njit(cache=True, nogil=True)
def _share_vertex(faces, f, g):
    for a in range(3):
        for b in range(3):
            if faces[f, a] == faces[g, b]:
                return True
    return False


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _edge_weights(faces, xc, f, ex, ey):
    """Front face ``f``'s barycentrics at the edge point (ex, ey), clamped to the triangle."""
    _i0, _i1, _i2, l0, l1, l2, _a, _b, _c, _d, _e, _f = _face_bary(faces, xc, f, ex, ey)
    l0 = max(l0, 0.0)
    l1 = max(l1, 0.0)
    l2 = max(l2, 0.0)
    s = l0 + l1 + l2
    if s <= 0.0:
        return 1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0
    return l0 / s, l1 / s, l2 / s


@njit(cache=True, nogil=True, inline="always")
def _boundary_pair(face_id, rdepth, faces, va, ua, vb, ub):
    """(is_boundary, front_is_a, front_face) for 4-neighbour pixels a and b."""
    fa = face_id[va, ua]
    fb = face_id[vb, ub]
    if fa == fb:
        return False, True, -1
    if fa < 0:
        return True, False, fb
    if fb < 0:
        return True, True, fa
    if _share_vertex(faces, fa, fb):
        return False, True, -1
    if rdepth[va, ua] <= rdepth[vb, ub]:
        return True, True, fa
    return True, False, fb


@njit(cache=True, nogil=True, error_model="numpy")
def _boundary_pass(face_id, rdepth, faces, xc, useb, B0, C0, A0, r0, r1, c0, c1, grad_cur):
    """Occlusion-boundary gradient of all 4-neighbour pixel pairs in the region."""
    for axis in range(2):
        dv = 1 if axis == 1 else 0
        du = 1 - dv
        for v in range(r0, r1 - dv):
            vb = v + dv
            for u in range(c0, c1 - du):
                ub = u + du
                fa = face_id[v, u]
                fb = face_id[vb, ub]
                if fa == fb:
                    continue
                if fa >= 0 and fb >= 0:
                    a0 = faces[fa, 0]
                    a1 = faces[fa, 1]
                    a2 = faces[fa, 2]
                    b0 = faces[fb, 0]
                    b1 = faces[fb, 1]
                    b2 = faces[fb, 2]
                    if (a0 == b0 or a0 == b1 or a0 == b2 or a1 == b0 or a1 == b1 or a1 == b2
                            or a2 == b0 or a2 == b1 or a2 == b2):
                        continue
                    ff = fa if rdepth[v, u] <= rdepth[vb, ub] else fb
                else:
                    ff = fa if fa >= 0 else fb
                ra0 = useb * B0[v, u, 0] + C0[v, u, 0]
                ra1 = useb * B0[v, u, 1] + C0[v, u, 1]
                rb0 = useb * B0[vb, ub, 0] + C0[vb, ub, 0]
                rb1 = useb * B0[vb, ub, 1] + C0[vb, ub, 1]
                # (A_a + A_b) . (r_front - r_back) / 2 times the direction front -> back
                # (+1 if the front is pixel a): both cases give (A_a + A_b) . (r_a - r_b) / 2
                coef = 0.5 * ((A0[v, u, 0] + A0[vb, ub, 0]) * (ra0 - rb0)
                              + (A0[v, u, 1] + A0[vb, ub, 1]) * (ra1 - rb1))
                if coef == 0.0:
                    continue
                w0, w1, w2 = _edge_weights(faces, xc, ff, u + 0.5 + 0.5 * du, v + 0.5 + 0.5 * dv)
                grad_cur[faces[ff, 0], axis] += coef * w0
                grad_cur[faces[ff, 1], axis] += coef * w1
                grad_cur[faces[ff, 2], axis] += coef * w2


@njit(cache=True, nogil=True, error_model="numpy")
def _flow_objective_kernel(face_id, rdepth, faces, xc, xp, rho, sw, bbuf, shapes, offsets,
                           scales, bnorm, covered_only, boundary, bbox, cbuf, abuf, tmp,
                           grad_cur, grad_prev, grad_rho):
    """E_f and its gradient; see the module docstring. Returns E (float64).

    bbox: (4,) int64 rows [0, 1) x columns [2, 3) holding every covered pixel. cbuf /
    abuf: flat scratch buffers (any content) for the model part of the residual pyramid
    and its adjoint; bbuf: the pyramid of sqrt(w) F_o (flat, same layout); tmp: scratch.
    """
    L = shapes.shape[0]
    H = shapes[0, 0]
    W = shapes[0, 1]
    useb = 0.0 if covered_only else 1.0
    reg = np.zeros((L, 4), dtype=np.int64)
    if bbox[1] > bbox[0] and bbox[3] > bbox[2]:
        # one pixel of margin: boundary pairs reach the background pixel next to the mesh
        reg[0, 0] = max(0, bbox[0] - 1)
        reg[0, 1] = min(H, bbox[1] + 1)
        reg[0, 2] = max(0, bbox[2] - 1)
        reg[0, 3] = min(W, bbox[3] + 1)
    for l in range(1, L):
        a, b = down_region(reg[l - 1, 0], reg[l - 1, 1], shapes[l, 0])
        c, d = down_region(reg[l - 1, 2], reg[l - 1, 3], shapes[l, 1])
        if b <= a or d <= c:
            a, b, c, d = 0, 0, 0, 0
        reg[l, 0] = a
        reg[l, 1] = b
        reg[l, 2] = c
        reg[l, 3] = d
    r0 = reg[0, 0]
    r1 = reg[0, 1]
    c0 = reg[0, 2]
    c1 = reg[0, 3]
    # the scratch buffers are reused between calls: clear what the pyramid reads
    for l in range(1, L - 1 + 1):
        Cp = cbuf[offsets[l - 1]:offsets[l]].reshape((shapes[l - 1, 0], shapes[l - 1, 1], 2))
        if reg[l, 1] > reg[l, 0]:
            Cp[max(0, reg[l - 1, 0] - 4):min(shapes[l - 1, 0], reg[l - 1, 1] + 4),
               max(0, reg[l - 1, 2] - 4):min(shapes[l - 1, 1], reg[l - 1, 3] + 4), :] = 0.0

    B0 = bbuf[offsets[0]:offsets[1]].reshape((H, W, 2))
    C0 = cbuf[offsets[0]:offsets[1]].reshape((H, W, 2))
    A0 = abuf[offsets[0]:offsets[1]].reshape((H, W, 2))

    # level 0: the model's part of the residual, C0 = -sqrt(w) F_r (+ sqrt(w) F_o if
    # covered_only), the energy and the adjoint seed A0 = 2 s_0 r_0
    energy = 0.0
    acc = 0.0
    s0 = scales[0]
    for v in range(r0, r1):
        py = v + 0.5
        for u in range(c0, c1):
            f = face_id[v, u]
            b0 = useb * B0[v, u, 0]
            b1 = useb * B0[v, u, 1]
            if f < 0:
                C0[v, u, 0] = 0.0
                C0[v, u, 1] = 0.0
                A0[v, u, 0] = 2.0 * s0 * b0
                A0[v, u, 1] = 2.0 * s0 * b1
                continue
            px = u + 0.5
            i0, i1, i2, l0, l1, l2, _a, _b, _c, _d, _e, _f = _face_bary(faces, xc, f, px, py)
            _m0, _m1, _m2, _s, qx, qy = _prev_point(xp, rho, i0, i1, i2, l0, l1, l2)
            fx = qx - px
            fy = qy - py
            w = sw[v, u]
            cx = (1.0 - useb) * B0[v, u, 0] - w * fx
            cy = (1.0 - useb) * B0[v, u, 1] - w * fy
            C0[v, u, 0] = cx
            C0[v, u, 1] = cy
            q0 = b0 + cx
            q1 = b1 + cy
            acc += q0 * q0 + q1 * q1 - b0 * b0 - b1 * b1
            A0[v, u, 0] = 2.0 * s0 * q0
            A0[v, u, 1] = 2.0 * s0 * q1
    energy += s0 * (acc + useb * bnorm[0])

    # coarser levels of the model part, their energy and adjoint seeds 2 s_l r_l
    for l in range(1, L):
        hl = shapes[l, 0]
        wl = shapes[l, 1]
        Bl = bbuf[offsets[l]:offsets[l + 1]].reshape((hl, wl, 2))
        Cl = cbuf[offsets[l]:offsets[l + 1]].reshape((hl, wl, 2))
        Al = abuf[offsets[l]:offsets[l + 1]].reshape((hl, wl, 2))
        Cp = cbuf[offsets[l - 1]:offsets[l]].reshape((shapes[l - 1, 0], shapes[l - 1, 1], 2))
        pyr_down_region(Cp, Cl, tmp, reg[l, 0], reg[l, 1], reg[l, 2], reg[l, 3])
        sl = scales[l]
        acc = 0.0
        for v in range(reg[l, 0], reg[l, 1]):
            for u in range(reg[l, 2], reg[l, 3]):
                b0 = useb * Bl[v, u, 0]
                b1 = useb * Bl[v, u, 1]
                q0 = b0 + Cl[v, u, 0]
                q1 = b1 + Cl[v, u, 1]
                acc += q0 * q0 + q1 * q1 - b0 * b0 - b1 * b1
                Al[v, u, 0] = 2.0 * sl * q0
                Al[v, u, 1] = 2.0 * sl * q1
        energy += sl * (acc + useb * bnorm[l])
    for l in range(L - 1, 0, -1):
        Al = abuf[offsets[l]:offsets[l + 1]].reshape((shapes[l, 0], shapes[l, 1], 2))
        Ap = abuf[offsets[l - 1]:offsets[l]].reshape((shapes[l - 1, 0], shapes[l - 1, 1], 2))
        pyr_down_adjoint_region(Al, Ap, tmp, reg[l, 0], reg[l, 1], reg[l, 2], reg[l, 3])

    # gradient: interior (displacements and barycentrics) and occlusion boundaries
    for v in range(r0, r1):
        py = v + 0.5
        for u in range(c0, c1):
            f = face_id[v, u]
            if f < 0:
                continue
            w = sw[v, u]
            gx = -w * A0[v, u, 0]
            gy = -w * A0[v, u, 1]
            if gx == 0.0 and gy == 0.0:
                continue
            px = u + 0.5
            i0, i1, i2, l0, l1, l2, d0x, d0y, d1x, d1y, d2x, d2y = _face_bary(faces, xc, f, px, py)
            m0, m1, m2, s, qx, qy = _prev_point(xp, rho, i0, i1, i2, l0, l1, l2)
            # t_k = g . (x'_k - q) / S ; dE/drho_k = lambda_k t_k ; h_k = rho_k t_k
            t0 = (gx * (xp[i0, 0] - qx) + gy * (xp[i0, 1] - qy)) * s
            t1 = (gx * (xp[i1, 0] - qx) + gy * (xp[i1, 1] - qy)) * s
            t2 = (gx * (xp[i2, 0] - qx) + gy * (xp[i2, 1] - qy)) * s
            grad_rho[i0] += l0 * t0
            grad_rho[i1] += l1 * t1
            grad_rho[i2] += l2 * t2
            h0 = rho[i0] * t0
            h1 = rho[i1] * t1
            h2 = rho[i2] * t2
            Gx = h0 * d0x + h1 * d1x + h2 * d2x
            Gy = h0 * d0y + h1 * d1y + h2 * d2y
            grad_cur[i0, 0] -= l0 * Gx
            grad_cur[i0, 1] -= l0 * Gy
            grad_cur[i1, 0] -= l1 * Gx
            grad_cur[i1, 1] -= l1 * Gy
            grad_cur[i2, 0] -= l2 * Gx
            grad_cur[i2, 1] -= l2 * Gy
            grad_prev[i0, 0] += m0 * s * gx
            grad_prev[i0, 1] += m0 * s * gy
            grad_prev[i1, 0] += m1 * s * gx
            grad_prev[i1, 1] += m1 * s * gy
            grad_prev[i2, 0] += m2 * s * gx
            grad_prev[i2, 1] += m2 * s * gy
    if boundary:
        _boundary_pass(face_id, rdepth, faces, xc, useb, B0, C0, A0, r0, r1, c0, c1, grad_cur)
    return energy


@njit(cache=True, nogil=True, error_model="numpy")
def _jacobian_kernel(face_id, rdepth, faces, xc, xp, rho, sw, r0img, boundary,
                     rows, cols, vals, rows_p, cols_p, vals_p, rows_r, cols_r, vals_r):
    """COO entries of d r_0 / d (xc, xp, rho) at level 0. Returns (n_cur, n_prev, n_rho).

    Row of pixel (v, u), component c: 2 (v W + u) + c; column of vertex k, axis a: 2 k + a
    (rho: k)."""
    H, W = face_id.shape
    nc = 0
    npv = 0
    nr = 0
    for v in range(H):
        py = v + 0.5
        for u in range(W):
            f = face_id[v, u]
            if f < 0:
                continue
            w = sw[v, u]
            if w == 0.0:
                continue
            px = u + 0.5
            i0, i1, i2, l0, l1, l2, d0x, d0y, d1x, d1y, d2x, d2y = _face_bary(faces, xc, f, px, py)
            m0, m1, m2, s, qx, qy = _prev_point(xp, rho, i0, i1, i2, l0, l1, l2)
            row = 2 * (v * W + u)
            idx = (i0, i1, i2)
            lam = (l0, l1, l2)
            mu = (m0 * s, m1 * s, m2 * s)
            # dF/dlambda_j = rho_j (x'_j - q) / S ; M = sum_j dF/dlambda_j grad(lambda_j)^T
            e0x = rho[i0] * (xp[i0, 0] - qx) * s
            e0y = rho[i0] * (xp[i0, 1] - qy) * s
            e1x = rho[i1] * (xp[i1, 0] - qx) * s
            e1y = rho[i1] * (xp[i1, 1] - qy) * s
            e2x = rho[i2] * (xp[i2, 0] - qx) * s
            e2y = rho[i2] * (xp[i2, 1] - qy) * s
            Mxx = e0x * d0x + e1x * d1x + e2x * d2x
            Mxy = e0x * d0y + e1x * d1y + e2x * d2y
            Myx = e0y * d0x + e1y * d1x + e2y * d2x
            Myy = e0y * d0y + e1y * d1y + e2y * d2y
            for k in range(3):
                # r = -w F ; dF/dx_k = -lambda_k M  ->  dr/dx_k = w lambda_k M
                a = w * lam[k]
                col = 2 * idx[k]
                rows[nc] = row
                cols[nc] = col
                vals[nc] = a * Mxx
                rows[nc + 1] = row
                cols[nc + 1] = col + 1
                vals[nc + 1] = a * Mxy
                rows[nc + 2] = row + 1
                cols[nc + 2] = col
                vals[nc + 2] = a * Myx
                rows[nc + 3] = row + 1
                cols[nc + 3] = col + 1
                vals[nc + 3] = a * Myy
                nc += 4
                rows_p[npv] = row
                cols_p[npv] = col
                vals_p[npv] = -w * mu[k]
                rows_p[npv + 1] = row + 1
                cols_p[npv + 1] = col + 1
                vals_p[npv + 1] = -w * mu[k]
                npv += 2
                # dF/drho_k = lambda_k (x'_k - q) / S
                rows_r[nr] = row
                cols_r[nr] = idx[k]
                vals_r[nr] = -w * lam[k] * (xp[idx[k], 0] - qx) * s
                rows_r[nr + 1] = row + 1
                cols_r[nr + 1] = idx[k]
                vals_r[nr + 1] = -w * lam[k] * (xp[idx[k], 1] - qy) * s
                nr += 2
    if boundary:
        for axis in range(2):
            dv = 1 if axis == 1 else 0
            du = 1 - dv
            for v in range(H - dv):
                for u in range(W - du):
                    vb = v + dv
                    ub = u + du
                    isb, front_a, ff = _boundary_pair(face_id, rdepth, faces, v, u, vb, ub)
                    if not isb:
                        continue
                    # d r(a) = d r(b) = (r_a - r_b) / 2 per pixel of motion of the edge in +axis
                    j0 = 0.5 * (r0img[v, u, 0] - r0img[vb, ub, 0])
                    j1 = 0.5 * (r0img[v, u, 1] - r0img[vb, ub, 1])
                    if j0 == 0.0 and j1 == 0.0:
                        continue
                    ex = u + 0.5 + 0.5 * du
                    ey = v + 0.5 + 0.5 * dv
                    b0, b1, b2 = _edge_weights(faces, xc, ff, ex, ey)
                    bw = (b0, b1, b2)
                    for pix in range(2):
                        row = 2 * (v * W + u) if pix == 0 else 2 * (vb * W + ub)
                        for k in range(3):
                            col = 2 * faces[ff, k] + axis
                            rows[nc] = row
                            cols[nc] = col
                            vals[nc] = bw[k] * j0
                            rows[nc + 1] = row + 1
                            cols[nc + 1] = col
                            vals[nc + 1] = bw[k] * j1
                            nc += 2
    return nc, npv, nr


# ----------------------------------------------------------------------------- targets


@njit(cache=True, nogil=True)
def _target_level0(fo, w, has_weight, sw, b0):
    """sw = sqrt(w), b0 = sqrt(w) F_o; non-finite F_o -> weight 0. False if w is invalid."""
    H, W = sw.shape
    for v in range(H):
        for u in range(W):
            ww = np.float64(w[v, u]) if has_weight else 1.0
            if not (ww >= 0.0 and ww < np.inf):
                return False
            fx = np.float64(fo[v, u, 0])
            fy = np.float64(fo[v, u, 1])
            if not (np.isfinite(fx) and np.isfinite(fy)):
                ww = 0.0
                fx = 0.0
                fy = 0.0
            r = np.sqrt(ww)
            sw[v, u] = r
            b0[v, u, 0] = r * fx
            b0[v, u, 1] = r * fy
    return True


@dataclass(frozen=True, eq=False)
class FlowTarget:
    """An observed flow field prepared for :func:`flow_loss` (build with :func:`flow_target`).

    Holds the per-pixel weights and the Gaussian pyramid of ``sqrt(w) F_o``, which do not
    change while the model is optimised against one frame pair; building it once saves
    a full-image pyramid per evaluation.

    Attributes:
        height, width: image size ``H, W``.
        levels: number of pyramid levels ``L`` (1 = full resolution only).
        level_weights: ``(L,)`` float64 weights ``s_l`` of the levels.
        shapes: ``(L, 2)`` int64 level sizes ``(H_l, W_l)``.
        offsets: ``(L + 1,)`` int64 start of each level in the flat buffers.
        sqrt_weight: ``(H, W)`` float64 ``sqrt(w)`` (0 where ``F_o`` is not finite).
        b: flat float64 pyramid of ``sqrt(w) F_o``.
        b_norm: ``(L,)`` float64 ``||pyrDown^l(sqrt(w) F_o)||^2``.
    """

    height: int
    width: int
    levels: int
    level_weights: np.ndarray
    shapes: np.ndarray
    offsets: np.ndarray
    sqrt_weight: np.ndarray
    b: np.ndarray
    b_norm: np.ndarray

    def level(self, flat: np.ndarray, l: int) -> np.ndarray:
        """View of level ``l`` of a flat pyramid buffer as ``(H_l, W_l, 2)``."""
        h, w = self.shapes[l]
        return flat[self.offsets[l]:self.offsets[l + 1]].reshape(h, w, 2)


def flow_target(
    observed_flow: Any,
    weight: Any = None,
    levels: int = 3,
    level_weights: Sequence[float] | None = None,
) -> FlowTarget:
    """Prepare an observed flow field for repeated :func:`flow_loss` evaluations.

    Args:
        observed_flow: ``(H, W, 2)`` observed backward flow ``F_o(i, i-1)``, ``(dx, dy)``
            in pixels at frame ``i``'s pixels. Non-finite values count as weight 0.
        weight: ``(H, W)`` non-negative per-pixel weights ``w`` (e.g. a flow confidence
            or a mask); ``None`` for all ones.
        levels: number of Gaussian pyramid levels (1 = full resolution only).
        level_weights: ``(levels,)`` non-negative weights ``s_l``; default ``4**l``.

    Returns:
        :class:`FlowTarget`.

    Raises:
        InputError: wrong shapes, negative or non-finite weights, bad ``levels``.
    """
    fo = to_numpy(observed_flow, "observed_flow")
    if fo.ndim != 3 or fo.shape[2] != 2 or fo.shape[0] < 1 or fo.shape[1] < 1:
        raise InputError(f"observed_flow must have shape (H, W, 2) with H, W >= 1, got {fo.shape}")
    if not np.issubdtype(fo.dtype, np.floating):
        if not np.issubdtype(fo.dtype, np.integer):
            raise InputError(f"observed_flow must hold real numbers, got dtype {fo.dtype}")
        fo = fo.astype(np.float64)
    if fo.dtype not in (np.float32, np.float64):
        fo = fo.astype(np.float64)
    fo = np.ascontiguousarray(fo)
    H, W = fo.shape[:2]
    if int(levels) != levels or not 1 <= levels <= 16:
        raise InputError(f"levels must be an integer in 1..16, got {levels}")
    levels = int(levels)
    if weight is None:
        w = np.ones((1, 1))
    else:
        w = to_numpy(weight, "weight")
        if w.shape != (H, W):
            raise InputError(f"weight must have shape {(H, W)} (one value per pixel), got {w.shape}")
        if not np.issubdtype(w.dtype, np.number) or np.issubdtype(w.dtype, np.complexfloating):
            raise InputError(f"weight must hold real numbers, got dtype {w.dtype}")
        w = np.ascontiguousarray(w, dtype=np.float64)
    if level_weights is None:
        s = 4.0 ** np.arange(levels)
    else:
        s = np.asarray(level_weights, dtype=np.float64)
        if s.shape != (levels,) or not np.all(np.isfinite(s)) or np.any(s < 0):
            raise InputError(f"level_weights must be {levels} non-negative numbers, got {level_weights!r}")
    shapes = np.array(pyramid_shapes(H, W, levels), dtype=np.int64)
    sizes = shapes[:, 0] * shapes[:, 1] * 2
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    sw = np.empty((H, W))
    b = np.empty(int(offsets[-1]))
    if not _target_level0(fo, w, weight is not None, sw, b[: sizes[0]].reshape(H, W, 2)):
        raise InputError("weight must be finite and non-negative (0 = ignore the pixel)")
    tmp = np.empty((H, (W + 1) // 2, 2))
    for l in range(1, levels):
        src = b[offsets[l - 1]:offsets[l]].reshape(shapes[l - 1][0], shapes[l - 1][1], 2)
        dst = b[offsets[l]:offsets[l + 1]].reshape(shapes[l][0], shapes[l][1], 2)
        pyr_down_region(src, dst, tmp, 0, shapes[l][0], 0, shapes[l][1])
    b_norm = np.array([np.dot(b[offsets[l]:offsets[l + 1]], b[offsets[l]:offsets[l + 1]]) for l in range(levels)])
    for a in (s, shapes, offsets, sw, b, b_norm):
        a.setflags(write=False)
    return FlowTarget(H, W, levels, s, shapes, offsets, sw, b, b_norm)


# ----------------------------------------------------------------------------- public ops


def _check_raster(raster: Any, num_faces: int, H: int | None = None, W: int | None = None) -> Raster:
    if not isinstance(raster, Raster):
        raise InputError(f"raster must be a Raster from rasterize(), got {type(raster).__name__}")
    fid = raster.face_id
    if not isinstance(fid, np.ndarray) or fid.ndim != 2 or getattr(raster.depth, "shape", None) != fid.shape:
        raise InputError("raster.face_id and raster.depth must be (H, W) arrays; use rasterize()")
    if H is not None and fid.shape != (H, W):
        raise InputError(f"the raster is {fid.shape} but the flow image is {(H, W)}")
    if fid.size and int(fid.max()) >= num_faces:
        raise InputError("the raster refers to faces the mesh does not have; pass the rasterised faces")
    if fid.dtype != np.int32 or not fid.flags.c_contiguous or raster.depth.dtype != np.float32:
        raster = Raster(np.ascontiguousarray(fid, dtype=np.int32), raster.bary,
                        np.ascontiguousarray(raster.depth, dtype=np.float32), raster.bbox)
    return raster


def _rho(depth_cur: Any, depth_prev: Any, V: int) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    if depth_prev is None:
        return np.ones(V), None, None
    if depth_cur is None:
        raise InputError("exact flow needs depth_cur as well as depth_prev (metres, (V,))")
    zc = check_vector(depth_cur, "depth_cur", V, positive=True)
    zp = check_vector(depth_prev, "depth_prev", V, positive=True)
    return zp / zc, zc, zp


def render_flow(
    raster: Raster,
    verts_px_cur: Any,
    verts_px_prev: Any,
    faces: Any,
    depth_cur: Any = None,
    depth_prev: Any = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Render the backward flow ``F_r(i, i-1)`` of a moving mesh at frame ``i``'s pixels.

    Args:
        raster: :class:`~flowmocap.render.Raster` of the mesh at frame ``i``.
        verts_px_cur: ``(V, 2)`` projected vertices at frame ``i`` (pixels).
        verts_px_prev: ``(V, 2)`` projected vertices at frame ``i - 1`` (pixels).
        faces: ``(F, 3)`` int vertex indices (the rasterised ones), or ``Faces``.
        depth_cur, depth_prev: optional ``(V,)`` camera-space depths (metres) at frames
            ``i`` and ``i - 1``; with both, the exact displacement of the visible surface
            point is rendered, without them the paper's screen-space interpolation of
            vertex displacements (module docstring).

    Returns:
        ``flow (H, W, 2)`` float32 ``(dx, dy)`` in pixels pointing from frame ``i`` to
        ``i - 1`` (0 on background), and ``mask (H, W)`` bool of covered pixels.
    """
    xc = check_points(verts_px_cur, "verts_px_cur", 2)
    V = xc.shape[0]
    xp = check_points(verts_px_prev, "verts_px_prev", 2, V)
    f = check_faces(faces, V)
    raster = _check_raster(raster, f.shape[0])
    rho, _, _ = _rho(depth_cur, depth_prev, V)
    flow = np.zeros(raster.face_id.shape + (2,))
    _render_flow_kernel(raster.face_id, f, xc, xp, rho, flow)
    return flow.astype(np.float32), raster.face_id >= 0


@dataclass(frozen=True)
class _Evaluation:
    energy: float
    grad_cur: np.ndarray
    grad_prev: np.ndarray
    grad_depth_cur: np.ndarray | None
    grad_depth_prev: np.ndarray | None


def _prepare(verts_px_cur, verts_px_prev, faces, observed_flow, weight, levels, level_weights,
             raster, depth_cur, depth_prev, cull_backfaces):
    xc = check_points(verts_px_cur, "verts_px_cur", 2)
    V = xc.shape[0]
    xp = check_points(verts_px_prev, "verts_px_prev", 2, V)
    f = check_faces(faces, V)
    if isinstance(observed_flow, FlowTarget):
        target = observed_flow
        if weight is not None or (levels is not None and levels != target.levels) or level_weights is not None:
            raise InputError("with a FlowTarget, set weight, levels and level_weights in flow_target()")
    else:
        target = flow_target(observed_flow, weight, 3 if levels is None else levels, level_weights)
    rho, zc, zp = _rho(depth_cur, depth_prev, V)
    if raster is None:
        if depth_cur is None:
            raise InputError("pass raster= (from rasterize) or depth_cur= (metres, (V,)) to rasterise the mesh")
        zc_r = zc if zc is not None else check_vector(depth_cur, "depth_cur", V)
        raster = rasterize_scratch(xc, zc_r, f, target.height, target.width, cull_backfaces, 1e-3)
    raster = _check_raster(raster, f.shape[0], target.height, target.width)
    return xc, xp, f, target, rho, zc, zp, raster


_SCRATCH = threading.local()


def _scratch(n: int, H: int, W: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-thread scratch buffers, reused between calls of the same size (fresh
    allocations would cost a page fault per 4 KiB touched, more than the kernel)."""
    cache = getattr(_SCRATCH, "buffers", None)
    if cache is None or cache[0] != (n, H, W):
        cache = ((n, H, W), np.zeros(n), np.zeros(n), np.zeros((H, (W + 1) // 2, 2)))
        _SCRATCH.buffers = cache
    return cache[1], cache[2], cache[3]


def _bbox(raster: Raster) -> np.ndarray:
    """(4,) int64 rows [0, 1) x columns [2, 3) of the covered pixels."""
    if raster.bbox is not None:
        return np.asarray(raster.bbox, dtype=np.int64)
    return np.array(_covered_bbox(raster.face_id), dtype=np.int64)


def _evaluate(xc, xp, f, target, rho, zc, zp, raster, covered_only, boundary) -> _Evaluation:
    cbuf, abuf, tmp = _scratch(int(target.offsets[-1]), target.height, target.width)
    gc = np.zeros_like(xc)
    gp = np.zeros_like(xp)
    gr = np.zeros(xc.shape[0])
    energy = _flow_objective_kernel(
        raster.face_id, raster.depth, f, xc, xp, rho, target.sqrt_weight, target.b, target.shapes,
        target.offsets, target.level_weights, target.b_norm, bool(covered_only), bool(boundary),
        _bbox(raster), cbuf, abuf, tmp, gc, gp, gr)
    gzc = gzp = None
    if zp is not None:
        gzp = gr / zc
        gzc = -gr * rho / zc
    return _Evaluation(float(energy), gc, gp, gzc, gzp)


class _ScalarWithGradient(torch.autograd.Function):
    """A scalar whose gradients w.r.t. its inputs were computed together with its value."""

    @staticmethod
    def forward(ctx, value, grads, *inputs):  # noqa: D102
        ctx.grads = grads
        return value.clone()

    @staticmethod
    def backward(ctx, grad_out):  # noqa: D102
        return (None, None, *[None if g is None else grad_out * g for g in ctx.grads])


def flow_loss(
    verts_px_cur: Any,
    verts_px_prev: Any,
    faces: Any,
    observed_flow: Any,
    weight: Any = None,
    *,
    levels: int | None = None,
    level_weights: Sequence[float] | None = None,
    raster: Raster | None = None,
    depth_cur: Any = None,
    depth_prev: Any = None,
    covered_only: bool = False,
    boundary: bool = True,
    cull_backfaces: bool = False,
) -> torch.Tensor:
    """The flow objective ``E_f`` over a Gaussian pyramid, differentiable (module docstring).

    Value and gradient are computed together in one Numba pass; the returned scalar
    carries the gradient w.r.t. every torch input that requires it, so gradients flow on
    to whatever produced the projected vertices (pose, shape, translation, camera).

    Args:
        verts_px_cur: ``(V, 2)`` projected vertices at frame ``i`` (pixels), torch or numpy.
        verts_px_prev: ``(V, 2)`` projected vertices at frame ``i - 1`` (pixels).
        faces: ``(F, 3)`` int vertex indices, or ``Faces``.
        observed_flow: ``(H, W, 2)`` observed backward flow ``F_o(i, i-1)`` in pixels, or
            a :class:`FlowTarget` (then ``weight``/``levels``/``level_weights`` come from it).
        weight: ``(H, W)`` non-negative pixel weights, or ``None`` (all ones).
        levels: pyramid levels (default 3; 1 = full resolution only).
        level_weights: ``(levels,)`` level weights ``s_l`` (default ``4**l``).
        raster: the mesh rasterised at frame ``i`` (visibility is held fixed); if ``None``
            it is rasterised here from ``verts_px_cur`` and ``depth_cur``.
        depth_cur: ``(V,)`` depths at frame ``i`` (metres); needed without ``raster``.
        depth_prev: ``(V,)`` depths at frame ``i - 1``; with ``depth_cur`` it switches to
            the exact surface-point flow, differentiable w.r.t. both depths too.
        covered_only: multiply the residual by the model's coverage (ignore pixels the
            model does not cover) instead of comparing them with zero flow.
        boundary: include the occlusion-boundary gradient term.
        cull_backfaces: passed to :func:`rasterize` when rasterising here.

    Returns:
        0-dim torch tensor ``E_f`` (pixels^2), dtype of ``verts_px_cur`` if it is a
        floating torch tensor (else float64), on its device.
    """
    xc, xp, f, target, rho, zc, zp, raster = _prepare(
        verts_px_cur, verts_px_prev, faces, observed_flow, weight, levels, level_weights,
        raster, depth_cur, depth_prev, cull_backfaces)
    ev = _evaluate(xc, xp, f, target, rho, zc, zp, raster, covered_only, boundary)
    return _attach(ev, verts_px_cur, verts_px_prev, depth_cur, depth_prev, zp is not None)


class PendingFlow:
    """``E_f`` being computed on a worker thread (:func:`flow_loss_async`). Call it for the
    energy (a 0-dim tensor, as :func:`flow_loss` returns); :meth:`raster` gives the mesh's
    rasterisation as soon as the worker has made it (for another term that needs the
    same coverage, e.g. the mesh silhouette), while the flow kernel goes on."""

    def __init__(self, pending: Future, raster: Future, finish: Callable):
        self._pending, self._raster, self._finish = pending, raster, finish

    def raster(self) -> Raster:
        """The :class:`~flowmocap.render.Raster` of the current vertices (read it only
        until this energy is finished: the worker reuses its buffers)."""
        return self._raster.result()

    def __call__(self) -> torch.Tensor:
        """Wait for the worker; ``E_f`` as a 0-dim tensor (pixels^2) carrying its gradients,
        exactly as :func:`flow_loss` returns it (the worker's exceptions are raised here)."""
        return self._finish(self._pending.result())


def flow_loss_async(executor: Executor, verts_px_cur: torch.Tensor, verts_px_prev: torch.Tensor, faces: Any,
                    observed_flow: FlowTarget, *, depth_cur: torch.Tensor, cull_backfaces: bool = False
                    ) -> PendingFlow:
    """:func:`flow_loss` (with its rasterisation from ``depth_cur``) started on
    ``executor``, so that the compiled rasteriser and flow kernel (which release the GIL)
    run on another core while the caller builds the other terms of an objective.

    Takes what the tracker passes to :func:`flow_loss` (a prepared :class:`FlowTarget`,
    ``(V, 2)`` pixels and ``(V,)`` metres); copies the vertices before returning, so the
    caller may go on using (not modifying) its tensors. Returns a :class:`PendingFlow`;
    calling it waits and gives exactly what :func:`flow_loss` would have (the same
    arithmetic; its exceptions are raised there).

    Args:
        executor: where the work runs (e.g. a one-thread ``ThreadPoolExecutor``).
        verts_px_cur, verts_px_prev: ``(V, 2)`` projected vertices at frames ``i`` and
            ``i - 1``, pixels (CPU tensors).
        faces: ``(F, 3)`` int vertex indices, or ``Faces``.
        observed_flow: the frame's :class:`FlowTarget`.
        depth_cur: ``(V,)`` depths at frame ``i``, metres (for the rasterisation).
        cull_backfaces: passed to :func:`rasterize`.

    Raises:
        InputError: ``observed_flow`` is not a :class:`FlowTarget`.
    """
    if not isinstance(observed_flow, FlowTarget):
        raise InputError("flow_loss_async needs a FlowTarget (flow_target())")
    numeric = [t.detach().numpy().copy() if isinstance(t, torch.Tensor) else t
               for t in (verts_px_cur, verts_px_prev, depth_cur)]
    raster_ready: Future = Future()

    def work():
        try:
            xc, xp, f, target, rho, zc, zp, raster = _prepare(
                numeric[0], numeric[1], faces, observed_flow, None, None, None, None, numeric[2], None, cull_backfaces)
        except BaseException as e:
            raster_ready.set_exception(e)
            raise
        raster_ready.set_result(raster)
        return _evaluate(xc, xp, f, target, rho, zc, zp, raster, False, True)

    return PendingFlow(executor.submit(work), raster_ready,
                       lambda ev: _attach(ev, verts_px_cur, verts_px_prev, depth_cur, None, False))


def _attach(ev: _Evaluation, verts_px_cur, verts_px_prev, depth_cur, depth_prev, exact: bool) -> torch.Tensor:
    """The energy of ``ev`` as a 0-dim tensor carrying its gradients to the inputs that require them."""
    ref = verts_px_cur if isinstance(verts_px_cur, torch.Tensor) and verts_px_cur.is_floating_point() else None
    dtype = ref.dtype if ref is not None else torch.float64
    device = ref.device if ref is not None else torch.device("cpu")
    inputs, grads = [], []
    pairs = [(verts_px_cur, ev.grad_cur), (verts_px_prev, ev.grad_prev)]
    if exact:
        pairs += [(depth_cur, ev.grad_depth_cur), (depth_prev, ev.grad_depth_prev)]
    for t, g in pairs:
        if isinstance(t, torch.Tensor) and t.requires_grad:
            inputs.append(t)
            grads.append(torch.from_numpy(g).to(dtype=t.dtype, device=t.device))
    value = torch.tensor(ev.energy, dtype=dtype, device=device)
    if not inputs:
        return value
    return _ScalarWithGradient.apply(value, tuple(grads), *inputs)


@dataclass(frozen=True)
class FlowResiduals:
    """Stacked residuals of :func:`flow_loss` and their sparse Jacobians.

    ``E_f = residuals @ residuals`` and ``grad E_f = 2 J^T residuals`` for each ``J``.

    Attributes:
        residuals: ``(N,)`` float64, ``sqrt(s_l) * r_l.ravel()`` of every level, level 0
            first; level ``l`` occupies ``[row_offsets[l], row_offsets[l+1])`` and its
            pixel ``(v, u)`` component ``c`` is row ``row_offsets[l] + 2 (v W_l + u) + c``.
        jac_cur: ``(N, 2V)`` scipy CSR ``d r / d verts_px_cur.ravel()`` (column ``2k + a``
            is vertex ``k``, axis ``a``). Level 0 rows touch the 3 vertices of the
            pixel's face, plus, on occlusion boundaries, those of the neighbouring front face.
        jac_prev: ``(N, 2V)`` scipy CSR ``d r / d verts_px_prev.ravel()``.
        jac_depth_cur, jac_depth_prev: ``(N, V)`` CSR w.r.t. the depths (exact mode), else None.
        row_offsets: ``(L + 1,)`` int64.
        shapes: ``(L, 2)`` level sizes.
    """

    residuals: np.ndarray
    jac_cur: sp.csr_matrix
    jac_prev: sp.csr_matrix
    jac_depth_cur: sp.csr_matrix | None
    jac_depth_prev: sp.csr_matrix | None
    row_offsets: np.ndarray
    shapes: np.ndarray


@functools.lru_cache(maxsize=16)
def _pyr_down_matrix(h: int, w: int) -> sp.csr_matrix:
    """The pyramid step on a flattened ``(h, w, 2)`` image as a sparse matrix (cached)."""
    def one_d(n: int) -> sp.csr_matrix:
        m = (n + 1) // 2
        rows, cols, vals = [], [], []
        for i in range(m):
            for t in range(5):
                rows.append(i)
                cols.append(reflect_index(2 * i + t - 2, n))
                vals.append(binomial_tap(t))
        return sp.csr_matrix((vals, (rows, cols)), shape=(m, n))
    return sp.kron(sp.kron(one_d(h), one_d(w)), sp.identity(2), format="csr")


def flow_residuals(
    verts_px_cur: Any,
    verts_px_prev: Any,
    faces: Any,
    observed_flow: Any,
    weight: Any = None,
    *,
    levels: int | None = None,
    level_weights: Sequence[float] | None = None,
    raster: Raster | None = None,
    depth_cur: Any = None,
    depth_prev: Any = None,
    covered_only: bool = False,
    boundary: bool = True,
    cull_backfaces: bool = False,
) -> FlowResiduals:
    """Residuals of ``E_f`` and their sparse Jacobians, for Gauss-Newton / LM solvers.

    Same arguments and definitions as :func:`flow_loss`; ``E_f = r @ r`` and
    ``2 J^T r`` is :func:`flow_loss`'s gradient. Coarser pyramid levels are
    ``pyrDown`` applied to the level-0 rows as sparse matrix products, so their rows
    touch the vertices of a 5x5 (per level) neighbourhood of pixels.

    Returns:
        :class:`FlowResiduals`.
    """
    xc, xp, f, target, rho, zc, zp, raster = _prepare(
        verts_px_cur, verts_px_prev, faces, observed_flow, weight, levels, level_weights,
        raster, depth_cur, depth_prev, cull_backfaces)
    H, W = target.height, target.width
    V = xc.shape[0]
    flow = np.zeros((H, W, 2))
    _render_flow_kernel(raster.face_id, f, xc, xp, rho, flow)
    covered = raster.face_id >= 0
    r0 = target.level(target.b, 0) - target.sqrt_weight[..., None] * flow
    if covered_only:
        r0 = np.where(covered[..., None], r0, 0.0)
    n_cov = int(covered.sum())
    n_pairs = 2 * H * W if boundary else 0
    cap = 12 * n_cov + 12 * n_pairs + 1
    rows, cols, vals = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap)
    cap2 = 6 * n_cov + 1
    rp, cp, vp = np.empty(cap2, np.int64), np.empty(cap2, np.int64), np.empty(cap2)
    rr, cr, vr = np.empty(cap2, np.int64), np.empty(cap2, np.int64), np.empty(cap2)
    nc, npv, nr = _jacobian_kernel(raster.face_id, raster.depth, f, xc, xp, rho, target.sqrt_weight,
                                   np.ascontiguousarray(r0), bool(boundary), rows, cols, vals,
                                   rp, cp, vp, rr, cr, vr)
    n0 = H * W * 2
    J = {
        "cur": sp.csr_matrix((vals[:nc], (rows[:nc], cols[:nc])), shape=(n0, 2 * V)),
        "prev": sp.csr_matrix((vp[:npv], (rp[:npv], cp[:npv])), shape=(n0, 2 * V)),
    }
    if zp is not None:
        Jr = sp.csr_matrix((vr[:nr], (rr[:nr], cr[:nr])), shape=(n0, V))
        J["zc"] = Jr @ sp.diags(-rho / zc)
        J["zp"] = Jr @ sp.diags(1.0 / zc)
    res = [r0.ravel()]
    blocks: dict[str, list[sp.csr_matrix]] = {k: [m] for k, m in J.items()}
    shapes = target.shapes
    for l in range(1, target.levels):
        D = _pyr_down_matrix(int(shapes[l - 1][0]), int(shapes[l - 1][1]))
        res.append(D @ res[-1])
        for k in blocks:
            blocks[k].append(D @ blocks[k][-1])
    scale = np.sqrt(target.level_weights)
    residuals = np.concatenate([scale[l] * res[l] for l in range(target.levels)])
    stacked = {k: sp.vstack([scale[l] * m for l, m in enumerate(v)], format="csr") for k, v in blocks.items()}
    row_offsets = np.concatenate([[0], np.cumsum([len(r) for r in res])]).astype(np.int64)
    return FlowResiduals(residuals, stacked["cur"], stacked["prev"], stacked.get("zc"), stacked.get("zp"),
                         row_offsets, shapes.copy())
