"""Levenberg-Marquardt on the stacked residuals of the per-frame objective (issue 5, item 5).

The tracker's energy (:func:`flowmocap.fit.tracker.frame_energy`) is a sum of squares,

    E(x) = sum_b ||r_b(x)||^2,   x = (pose (72), trans (3)),

with one residual block per term, each scaled by the square root of its weight (and
normalisation) so that ``sum ||r_b||^2`` is exactly ``frame_energy``'s total:

=============  ==============================================  ==========================
block          residuals                                       scale
=============  ==============================================  ==========================
flow           rows of :func:`flowmocap.render.flow_residuals`  sqrt(flow_weight / pixels)
               that depend on x, plus one constant row
silhouette     :func:`~flowmocap.fit.energies.mesh_silhouette_  sqrt(silhouette_weight)
               residuals` (mesh model only)
limits         :func:`~flowmocap.fit.energies.joint_limit_      sqrt(limit_weight)
               residuals`
penetration    :func:`~flowmocap.fit.energies.interpenetration_ sqrt(penetration_weight)
               residuals`
temporal       :func:`~flowmocap.fit.energies.temporal_         sqrt(temporal_weight)
               residuals`
keypoints      :func:`~flowmocap.fit.energies.keypoint_         sqrt(keypoint_weight /
               residuals` (detected joints, when given)       confident joints)
=============  ==============================================  ==========================

Jacobians ``J_b = d r_b / d x`` come in closed form where the residuals depend on
projected vertices or capsule ends (the kinematic chain, :func:`skinning_jacobian`, times
the pinhole projection) and from reverse-mode autodiff (batched over the few non-zero
rows) for the small pose-only blocks. The flow block's Jacobian is the sparse
``d r / d px`` of the flow renderer (occlusion-boundary rows included) times the dense
``d px / d x``; only the rows that depend on x are kept, pushed through the pyramid
level by level as sparse products on the compressed rows.

:func:`lm_track_frame` then runs Levenberg-Marquardt with Marquardt's diagonal
scaling: solve ``(J^T J + lambda diag(J^T J)) delta = -J^T r`` (75 x 75), accept the step
only if ``frame_energy`` decreases, adapt ``lambda`` with Nielsen's gain-ratio rule
(starting each stage at 0.1: a nearly undamped first Gauss-Newton step from a start
several centimetres off can jump into another basin of the flow term), and stop a
stage after ``cfg.iterations`` trial steps, when an accepted step (or the linear model's
prediction) lowers the energy by less than ``rtol`` relatively, or after a few rejected
steps in a row (the rasterised energy is piecewise constant at the scale of a pixel, so
close to its minimum more damping does not help). Only ``cfg.silhouette_model == "mesh"`` is supported:
the capsule silhouette term has one residual per image pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
import torch
from numba import njit

from flowmocap.body.capsules import _BONES, Capsules
from flowmocap.body.skeleton import PARENTS
from flowmocap.errors import InputError, OptimizationError
from flowmocap.fit import energies as en
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.jacobian import _DESC, right_jacobian_so3

if TYPE_CHECKING:  # the tracker imports this module to dispatch to it: no import cycle at load time
    from flowmocap.fit.tracker import FrameData, FrameState, Scene


def _state(pose, trans) -> "FrameState":
    from flowmocap.fit.tracker import FrameState

    return FrameState(pose, trans)

__all__ = ["Block", "skinning_jacobian", "pixel_jacobian", "flow_block", "residual_blocks", "stacked_residuals",
           "lm_stage", "lm_track_frame", "LM_RTOL", "LM_LAMBDA0", "LM_MAX_REJECTS", "LM_REJECT_FACTOR"]

NUM_PARAMS = 75
#: Default relative energy decrease below which an accepted LM step ends a stage.
LM_RTOL = 5e-3
#: Initial damping of each stage (relative to the diagonal of J^T J); 1e-3 (nearly pure
#: Gauss-Newton) lost the pose on 3 of 7 frames started 5 cm off, 0.1 on none.
LM_LAMBDA0 = 0.1
#: Rejected steps in a row that end a stage.
LM_MAX_REJECTS = 5
#: Damping growth after a rejected step.
LM_REJECT_FACTOR = 10.0


@dataclass
class Block:
    """One term's residuals ``r (m,)`` and Jacobian ``J (m, 75)`` (float64)."""

    name: str
    r: np.ndarray
    J: np.ndarray


# ------------------------------------------------------------------------ kinematics


def _moved_offsets(pose, transforms, joints, rest_points, weights):
    """``A (J, 3, 3)`` and ``rel (J, N, 3)``: ``dv/dtheta_jc = (A_j e_c) x rel_j`` (see
    :func:`skinning_jacobian`)."""
    pose = np.asarray(pose, np.float64).reshape(-1, 3)
    T = np.asarray(transforms, np.float64)
    p = np.asarray(joints, np.float64)
    X = np.asarray(rest_points, np.float64)
    Wt = np.ascontiguousarray(np.asarray(weights, np.float64).T)  # (J, N)
    nj, N = Wt.shape
    Rw, tw = T[:, :3, :3], T[:, :3, 3]
    A = Rw @ right_jacobian_so3(pose)  # (J, 3, 3): omega = A_j delta
    Y = np.matmul(X[None], Rw.transpose(0, 2, 1)) + tw[:, None, :]  # (J, N, 3): x_k of every bone
    Y *= Wt[:, :, None]
    M = (_DESC @ Y.reshape(nj, -1)).reshape(nj, N, 3)  # sum over the bones below j of w_k x_k
    M -= (_DESC @ Wt)[:, :, None] * p[:, None, :]  # ... - s_j p_j
    return A, M


def skinning_jacobian(pose: np.ndarray, transforms: np.ndarray, joints: np.ndarray, rest_points: np.ndarray,
                      weights: np.ndarray) -> np.ndarray:
    """``d v / d (pose, trans)`` of linearly skinned points, ``(N, 3, 75)``.

    The same quantity as :func:`flowmocap.fit.jacobian.skinned_point_jacobian` (see its
    docstring for the derivation; pose blend shapes are left out), vectorised over the
    joints: ``dv/dtheta_jc = (A_j e_c) x (sum_{k below j} w_k x_k - s_j p_j)`` with
    ``A_j = R^w_j J_r(theta_j)``.
    """
    A, rel = _moved_offsets(pose, transforms, joints, rest_points, weights)
    nj, N = rel.shape[:2]
    out = np.zeros((N, 3, 3 * nj + 3))
    rx, ry, rz = rel[..., 0].T, rel[..., 1].T, rel[..., 2].T  # (N, J)
    for c in range(3):
        ax, ay, az = A[:, 0, c], A[:, 1, c], A[:, 2, c]
        out[:, 0, c:3 * nj:3] = ay * rz - az * ry
        out[:, 1, c:3 * nj:3] = az * rx - ax * rz
        out[:, 2, c:3 * nj:3] = ax * ry - ay * rx
    out[:, 0, -3], out[:, 1, -2], out[:, 2, -1] = 1.0, 1.0, 1.0
    return out


@njit(cache=True, nogil=True)
def _pixel_jacobian_kernel(X, W, Rw, tw, p, A, parents, Rc, tc, fx, fy, out):
    """Fused skinning and projection Jacobian; see :func:`pixel_jacobian`."""
    N = X.shape[0]
    nj = W.shape[1]
    m = np.zeros((nj, 3))
    s = np.zeros(nj)
    for n in range(N):
        vx = 0.0
        vy = 0.0
        vz = 0.0
        for k in range(nj):
            w = W[n, k]
            if w == 0.0:
                m[k, 0] = 0.0
                m[k, 1] = 0.0
                m[k, 2] = 0.0
                s[k] = 0.0
                continue
            xk0 = Rw[k, 0, 0] * X[n, 0] + Rw[k, 0, 1] * X[n, 1] + Rw[k, 0, 2] * X[n, 2] + tw[k, 0]
            xk1 = Rw[k, 1, 0] * X[n, 0] + Rw[k, 1, 1] * X[n, 1] + Rw[k, 1, 2] * X[n, 2] + tw[k, 1]
            xk2 = Rw[k, 2, 0] * X[n, 0] + Rw[k, 2, 1] * X[n, 1] + Rw[k, 2, 2] * X[n, 2] + tw[k, 2]
            m[k, 0] = w * xk0
            m[k, 1] = w * xk1
            m[k, 2] = w * xk2
            s[k] = w
            vx += w * xk0
            vy += w * xk1
            vz += w * xk2
        # sums over the bones below each joint (parents precede children)
        for k in range(nj - 1, 0, -1):
            q = parents[k]
            m[q, 0] += m[k, 0]
            m[q, 1] += m[k, 1]
            m[q, 2] += m[k, 2]
            s[q] += s[k]
        # projection rows d px / d v
        cx = Rc[0, 0] * vx + Rc[0, 1] * vy + Rc[0, 2] * vz + tc[0]
        cy = Rc[1, 0] * vx + Rc[1, 1] * vy + Rc[1, 2] * vz + tc[1]
        cz = Rc[2, 0] * vx + Rc[2, 1] * vy + Rc[2, 2] * vz + tc[2]
        iz = 1.0 / cz
        P = np.empty((2, 3))
        for a in range(3):
            P[0, a] = fx * iz * (Rc[0, a] - cx * iz * Rc[2, a])
            P[1, a] = fy * iz * (Rc[1, a] - cy * iz * Rc[2, a])
        for i in range(2):
            out[n, i, 3 * nj] = P[i, 0]
            out[n, i, 3 * nj + 1] = P[i, 1]
            out[n, i, 3 * nj + 2] = P[i, 2]
        for j in range(nj):
            if s[j] == 0.0:
                for i in range(2):
                    for c in range(3):
                        out[n, i, 3 * j + c] = 0.0
                continue
            r0 = m[j, 0] - s[j] * p[j, 0]
            r1 = m[j, 1] - s[j] * p[j, 1]
            r2 = m[j, 2] - s[j] * p[j, 2]
            for i in range(2):
                # P_i . (a x r) = a . (r x P_i)
                q0 = r1 * P[i, 2] - r2 * P[i, 1]
                q1 = r2 * P[i, 0] - r0 * P[i, 2]
                q2 = r0 * P[i, 1] - r1 * P[i, 0]
                for c in range(3):
                    out[n, i, 3 * j + c] = q0 * A[j, 0, c] + q1 * A[j, 1, c] + q2 * A[j, 2, c]


def pixel_jacobian(scene: Scene, out, pose: torch.Tensor) -> np.ndarray:
    """``d px / d (pose, trans)`` of every projected vertex, ``(V, 2, 75)`` in px per rad / m.

    :func:`skinning_jacobian` chained with the pinhole projection
    (:func:`~flowmocap.fit.jacobian.projection_jacobian`), fused in one compiled loop
    over the vertices (each joint's sums over the bones below it accumulated from the
    leaves up).
    """
    cam = scene.camera
    np64 = lambda t: np.ascontiguousarray(t.detach().double().cpu().numpy())  # noqa: E731
    T = np64(out.transforms[0])
    key = id(scene.model)
    cache = _MODEL_CACHE.get(key)
    if cache is None or cache[0] is not scene.model:
        cache = (scene.model, np64(scene.model.weights), np.asarray(PARENTS, np.int64))
        _MODEL_CACHE[key] = cache
    _, W, parents = cache
    pose64 = np64(pose).reshape(-1, 3)
    A = np.ascontiguousarray(T[:, :3, :3] @ right_jacobian_so3(pose64))
    res = np.empty((W.shape[0], 2, 3 * W.shape[1] + 3))
    _pixel_jacobian_kernel(np64(out.rest_vertices[0]), W, np.ascontiguousarray(T[:, :3, :3]),
                           np.ascontiguousarray(T[:, :3, 3]), np64(out.joints[0]), A, parents,
                           np.ascontiguousarray(cam.R, dtype=np.float64), np.ascontiguousarray(cam.t, dtype=np.float64),
                           float(cam.fx), float(cam.fy), res)
    return res


_MODEL_CACHE: dict = {}


def _capsule_end_jacobian(scene: Scene, out, pose: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``d start / d x`` and ``d end / d x`` of the posed capsules, ``(K, 3, 75)`` each."""
    rest = scene.rest_capsules
    K = rest.start.shape[1]
    bones = _BONES.numpy()
    W = np.zeros((2 * K, 24))
    W[np.arange(2 * K), np.concatenate([bones, bones])] = 1.0
    X = torch.cat([rest.start[0], rest.end[0]]).detach().double().cpu().numpy()
    J = skinning_jacobian(pose.detach().double().cpu().numpy(), out.transforms[0].detach().double().cpu().numpy(),
                          out.joints[0].detach().double().cpu().numpy(), X, W)
    return J[:K], J[K:]


# ------------------------------------------------------------------------ small blocks


def _rows_jacobian(r: torch.Tensor, inputs: list[torch.Tensor]) -> np.ndarray:
    """Dense ``d r / d inputs`` by reverse mode over the non-zero rows only, ``(m, sum sizes)``."""
    m = r.numel()
    n = sum(x.numel() for x in inputs)
    J = np.zeros((m, n))
    flat = r.reshape(-1)
    rows = torch.nonzero(flat.detach() != 0).reshape(-1).tolist()
    if not rows or not r.requires_grad:
        return J
    if len(rows) <= 8:  # a few single backward passes beat vmap's overhead
        for k, i in enumerate(rows):
            grads = torch.autograd.grad(flat[i], inputs, retain_graph=k < len(rows) - 1, allow_unused=True)
            J[i] = np.concatenate([np.zeros(x.numel()) if g is None else g.detach().double().reshape(-1).numpy()
                                   for g, x in zip(grads, inputs)])
        return J
    eye = torch.zeros(len(rows), m, dtype=r.dtype)
    eye[torch.arange(len(rows)), torch.as_tensor(rows)] = 1.0
    grads = torch.autograd.grad(flat, inputs, grad_outputs=eye, is_grads_batched=True, allow_unused=True)
    parts = [torch.zeros(len(rows), x.numel(), dtype=r.dtype) if g is None else g.reshape(len(rows), -1)
             for g, x in zip(grads, inputs)]
    J[rows] = torch.cat(parts, 1).double().numpy()
    return J


# ------------------------------------------------------------------------ flow block


_CSC_CACHE: dict = {}


def _pyr_down_csc(h: int, w: int) -> sp.csc_matrix:
    from flowmocap.render.flow import _pyr_down_matrix

    key = (h, w)
    if key not in _CSC_CACHE:
        _CSC_CACHE[key] = _pyr_down_matrix(h, w).tocsc()
    return _CSC_CACHE[key]


@njit(cache=True, nogil=True)
def _accumulate_rows(rows, cols, vals, dpx, G):
    """``G[rows[e]] += vals[e] * dpx[cols[e]]`` for every entry e (a sparse-dense product)."""
    P = dpx.shape[1]
    for e in range(rows.shape[0]):
        r = rows[e]
        c = cols[e]
        v = vals[e]
        for k in range(P):
            G[r, k] += v * dpx[c, k]


def flow_block(px: np.ndarray, prev_px: np.ndarray, depth: np.ndarray, faces, target, dpx: np.ndarray,
               boundary: bool = True) -> tuple[np.ndarray, np.ndarray, float]:
    """The x-dependent rows of :func:`flowmocap.render.flow_residuals` and their Jacobian.

    Equivalent to ``res = flow_residuals(px, prev_px, faces, target, depth_cur=depth,
    cull_backfaces=True)`` followed by ``res.jac_cur @ dpx.reshape(2V, 75)`` restricted to
    the rows with a non-zero Jacobian, but without building the ``(N, 2V)`` matrices of
    the full image: the level-0 Jacobian is built for the covered (and boundary) pixels,
    multiplied by ``dpx`` and pushed through the pyramid on the compressed rows. Levels of
    weight 0 contribute no rows.

    Args:
        px, prev_px: ``(V, 2)`` projected vertices at frames i and i - 1.
        depth: ``(V,)`` depths at frame i (the rasteriser's).
        faces: the scene's faces; target: a :class:`~flowmocap.render.FlowTarget`.
        dpx: ``(V, 2, P)`` ``d px / d x``.
        boundary: include the occlusion-boundary rows (as :func:`flow_loss` does).

    Returns:
        ``r (m,)``, ``J (m, P)`` and ``rest``: the energy of the remaining rows (constant
        under small changes of x), so that ``E_f = r @ r + rest``.
    """
    from flowmocap.render import flow as fl
    from flowmocap.render.pyramid import pyr_down_region

    xc, xp, f, tgt, rho, _zc, _zp, raster = fl._prepare(px, prev_px, faces, target, None, None, None, None,
                                                         depth, None, True)
    H, W = tgt.height, tgt.width
    V = xc.shape[0]
    P = dpx.shape[-1]
    flow = np.zeros((H, W, 2))
    fl._render_flow_kernel(raster.face_id, f, xc, xp, rho, flow)
    r0 = tgt.level(tgt.b, 0) - tgt.sqrt_weight[..., None] * flow
    # the Jacobian on the covered pixels' bounding box plus one pixel (boundary pairs reach
    # the background pixel next to the mesh); the flow and its derivatives are unchanged
    # when both frames' vertices and the pixel grid move by the same offset
    b = fl._bbox(raster)
    if b[1] > b[0] and b[3] > b[2]:
        y0, y1, x0, x1 = max(0, b[0] - 1), min(H, b[1] + 1), max(0, b[2] - 1), min(W, b[3] + 1)
        hc, wc = y1 - y0, x1 - x0
        crop = lambda a: np.ascontiguousarray(a[y0:y1, x0:x1])  # noqa: E731
        fid = crop(raster.face_id)
        off = np.array([x0, y0], np.float64)
        n_cov = int((fid >= 0).sum())
        cap = 12 * n_cov + (12 * 2 * hc * wc if boundary else 0) + 1
        rows, cols, vals = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap)
        cap2 = 6 * n_cov + 1
        rp, cp, vp = np.empty(cap2, np.int64), np.empty(cap2, np.int64), np.empty(cap2)
        rr, cr, vr = np.empty(cap2, np.int64), np.empty(cap2, np.int64), np.empty(cap2)
        nc, _, _ = fl._jacobian_kernel(fid, crop(raster.depth), f, xc - off, xp - off, rho, crop(tgt.sqrt_weight),
                                       crop(r0), bool(boundary), rows, cols, vals, rp, cp, vp, rr, cr, vr)
        rows, cols, vals = rows[:nc], cols[:nc], vals[:nc]
        used = np.bincount(rows, minlength=2 * hc * wc) > 0
        local = np.flatnonzero(used)
        pos = np.full(2 * hc * wc, -1, np.int64)
        pos[local] = np.arange(len(local))
        G = np.zeros((len(local), P))
        _accumulate_rows(pos[rows], cols, vals, np.ascontiguousarray(dpx.reshape(2 * V, P)), G)
        pix = local // 2
        keep = 2 * ((pix // wc + y0) * W + pix % wc + x0) + local % 2  # rows of the full image, sorted
    else:
        keep, G = np.zeros(0, np.int64), np.zeros((0, P))
    s = tgt.level_weights
    res = r0.reshape(-1)
    out_r, out_J = [], []
    total = 0.0
    if s[0] > 0:
        out_r.append(math.sqrt(s[0]) * res[keep])
        out_J.append(math.sqrt(s[0]) * G)
    total += s[0] * float(res @ res)
    last = max([l for l in range(tgt.levels) if s[l] > 0], default=-1)
    img = r0
    for l in range(1, last + 1):
        h, w = (int(v) for v in tgt.shapes[l - 1])
        Dc = _pyr_down_csc(h, w)
        nxt = np.empty((int(tgt.shapes[l][0]), int(tgt.shapes[l][1]), 2))
        pyr_down_region(img, nxt, np.empty((h, (w + 1) // 2, 2)), 0, nxt.shape[0], 0, nxt.shape[1])  # == Dc @ img
        img = nxt
        res = img.reshape(-1)
        if len(keep):
            sub = Dc[:, keep].tocsr()
            nz = np.flatnonzero(np.diff(sub.indptr))
            G = np.asarray(sub[nz] @ G)
            keep = nz
        if s[l] > 0:
            out_r.append(math.sqrt(s[l]) * res[keep])
            out_J.append(math.sqrt(s[l]) * G)
            total += s[l] * float(res @ res)
    r = np.concatenate(out_r) if out_r else np.zeros(0)
    J = np.concatenate(out_J) if out_J else np.zeros((0, P))
    return r, J, max(total - float(r @ r), 0.0)


# ------------------------------------------------------------------------ silhouette


def _silhouette_block(px: torch.Tensor, depth: torch.Tensor, faces, target, a: float, grid_step: int,
                      dpx: np.ndarray, margin: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Residuals of :func:`~flowmocap.fit.energies.mesh_silhouette_residuals` and ``d r / d x``.

    The inside part's residual ``v`` depends only on vertex v's pixel position, so one
    backward pass of their sum gives every row's (2,) derivative; the uncovered part's
    row ``p`` is ``c |p - x_nn(p)|`` with the nearest vertex found here exactly as the
    energy finds it.
    """
    from scipy.spatial import cKDTree

    from flowmocap.render.raster import rasterize

    V = px.shape[0]
    leaf = px.detach().clone().requires_grad_()
    r = en.mesh_silhouette_residuals(leaf, depth.detach(), faces, target, a=a, grid_step=grid_step, margin=margin)
    inside = r[:V]
    dr = torch.zeros_like(leaf)
    if inside.requires_grad and bool((inside != 0).any()):
        (dr,) = torch.autograd.grad(inside.sum(), leaf)
    dr = dr.double().numpy()
    J_in = np.einsum("na,nak->nk", dr, dpx, optimize=True)
    n_out = r.shape[0] - V
    if n_out == 0:
        return r.detach().double().numpy(), J_in
    step = int(grid_step)
    grid = en._mask_grid(target, step)
    n = max(len(grid), 1)
    xy = px.detach().cpu().numpy().astype(np.float64)
    z = depth.detach().cpu().numpy()
    face_id = rasterize(xy, z, faces, target.height, target.width, cull_backfaces=True).face_id
    uncovered = grid[face_id[grid[:, 1], grid[:, 0]] < 0]
    if len(uncovered) != n_out:
        raise OptimizationError("internal: the silhouette's uncovered samples differ from the energy's")
    p = uncovered + 0.5
    _, nn = cKDTree(xy).query(p)
    d = p - xy[nn]
    dist = np.sqrt((d * d).sum(1) + 1e-12)
    c = math.sqrt((1.0 - a) / n)
    g = -c * d / dist[:, None]  # d r_p / d x_nn
    J_out = np.einsum("na,nak->nk", g, dpx[nn], optimize=True)
    return r.detach().double().numpy(), np.concatenate([J_in, J_out])


# ------------------------------------------------------------------------ all blocks


def _check_config(cfg: TrackerConfig, data: FrameData) -> None:
    if data.mask is not None and cfg.silhouette_weight > 0 and cfg.silhouette_model != "mesh":
        raise InputError(
            f"the Levenberg-Marquardt solver needs silhouette_model='mesh' (got {cfg.silhouette_model!r}): the "
            "capsule silhouette term has one residual per image pixel; set silhouette_model to 'mesh' or use "
            "optimizer 'lbfgs'.")


def residual_blocks(scene: Scene, state: FrameState, data: FrameData, cfg: TrackerConfig, stage: int | None,
                    prev_px: torch.Tensor | None, ref_pose: torch.Tensor | None, boundary: bool = True) -> list[Block]:
    """The weighted residual blocks of :func:`~flowmocap.fit.tracker.frame_energy` and their Jacobians.

    ``sum(b.r @ b.r for b in blocks)`` equals ``frame_energy(...)[0]`` (same arguments);
    ``J`` columns are ``(pose (72), trans (3))``. The flow block ends with one constant row
    (the pixels whose residual does not depend on x). ``boundary=False`` drops the flow
    renderer's occlusion-boundary rows from the Jacobian (for finite-difference checks).

    Raises:
        InputError: ``cfg.silhouette_model`` is not ``"mesh"`` while a mask is given.
    """
    _check_config(cfg, data)
    pose = state.pose.detach().reshape(72)
    trans = state.trans.detach().reshape(3)
    with torch.no_grad():
        out, px, depth = scene.forward(pose, trans)
    blocks: list[Block] = []
    need_px = (prev_px is not None and data.targets and cfg.flow_weight > 0) or \
              (data.mask is not None and cfg.silhouette_weight > 0)
    dpx = pixel_jacobian(scene, out, pose) if need_px else None
    if prev_px is not None and data.targets and cfg.flow_weight > 0:
        r, J, rest = flow_block(px.numpy(), prev_px.detach().numpy(), depth.numpy(), scene.faces,
                                data.targets[stage], dpx, boundary=boundary)
        w = math.sqrt(cfg.flow_weight / data.person_pixels)
        blocks.append(Block("flow", w * np.append(r, math.sqrt(rest)), w * np.vstack([J, np.zeros((1, NUM_PARAMS))])))
    if data.mask is not None and cfg.silhouette_weight > 0:
        r, J = _silhouette_block(px, depth, scene.faces, data.silhouette, cfg.silhouette_a, cfg.capsule_grid_step, dpx)
        w = math.sqrt(cfg.silhouette_weight)
        blocks.append(Block("silhouette", w * r, w * J))
    if cfg.limit_weight > 0:
        r, Jp = en.joint_limit_jacobian(pose.numpy())
        J = np.zeros((r.size, NUM_PARAMS))
        J[:, :72] = Jp
        w = math.sqrt(cfg.limit_weight)
        blocks.append(Block("limits", w * r, w * J))
    if cfg.penetration_weight > 0:
        caps = scene.capsules(out)
        s = caps.start.detach().clone().requires_grad_()
        e = caps.end.detach().clone().requires_grad_()
        r = en.interpenetration_residuals(Capsules(s, e, caps.radius.detach()))[0]
        J = np.zeros((r.numel(), NUM_PARAMS))
        if bool((r != 0).any()):
            Jse = _rows_jacobian(r, [s, e])  # (m, 2 K 3)
            K = s.shape[1]
            Js, Je = _capsule_end_jacobian(scene, out, pose)
            J = Jse[:, : 3 * K] @ Js.reshape(3 * K, NUM_PARAMS) + Jse[:, 3 * K:] @ Je.reshape(3 * K, NUM_PARAMS)
        w = math.sqrt(cfg.penetration_weight)
        blocks.append(Block("penetration", w * r.detach().double().numpy(), w * J))
    if ref_pose is not None and cfg.temporal_weight > 0:
        p = pose.clone().requires_grad_()
        r = en.temporal_residuals(p.reshape(1, 72), ref_pose.detach().reshape(1, 72), weights=data.temporal_weights)[0]
        J = np.zeros((r.numel(), NUM_PARAMS))
        # joints 1..23: r = sqrt(w) (theta - theta_ref) (diagonal); the root: the geodesic difference
        sw = np.ones(72) if data.temporal_weights is None else np.sqrt(
            np.repeat(np.asarray(data.temporal_weights, np.float64), 3))
        J[3:, 3:72] = np.diag(sw[3:])
        J[:3, :72] = _rows_jacobian(r[:3], [p])
        w = math.sqrt(cfg.temporal_weight)
        blocks.append(Block("temporal", w * r.detach().double().numpy(), w * J))
    if data.keypoints is not None and cfg.keypoint_weight > 0:
        j2d, conf = data.keypoints
        p = pose.clone().requires_grad_()
        t = trans.clone().requires_grad_()
        o = scene.model(betas=scene.betas, pose=p.reshape(1, 72), trans=t.reshape(1, 3))
        r = en.keypoint_residuals(scene.camera.project(o.joints[0])[None], j2d, conf, sigma=cfg.keypoint_sigma)[0]
        w = math.sqrt(cfg.keypoint_weight / float((conf > 0).sum()))
        blocks.append(Block("keypoints", w * r.detach().double().numpy(), w * _rows_jacobian(r, [p, t])))
    return blocks


def stacked_residuals(scene: Scene, state: FrameState, data: FrameData, cfg: TrackerConfig, stage: int | None,
                      prev_px: torch.Tensor | None, ref_pose: torch.Tensor | None,
                      boundary: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """All blocks of :func:`residual_blocks` stacked: ``r (M,)``, ``J (M, 75)``."""
    blocks = residual_blocks(scene, state, data, cfg, stage, prev_px, ref_pose, boundary)
    if not blocks:
        return np.zeros(0), np.zeros((0, NUM_PARAMS))
    return np.concatenate([b.r for b in blocks]), np.concatenate([b.J for b in blocks])


# ------------------------------------------------------------------------ the solver


def _normal_equations(blocks: list[Block]) -> tuple[np.ndarray, np.ndarray, float]:
    """``J^T J``, ``J^T r`` and ``r @ r`` summed over the blocks."""
    A = np.zeros((NUM_PARAMS, NUM_PARAMS))
    g = np.zeros(NUM_PARAMS)
    e = 0.0
    for b in blocks:
        A += b.J.T @ b.J
        g += b.J.T @ b.r
        e += float(b.r @ b.r)
    return A, g, e


def _energy(scene, x: np.ndarray, data, cfg, stage, prev_px, ref, dtype) -> tuple[float, dict]:
    if not np.all(np.isfinite(x)):
        raise OptimizationError("the Levenberg-Marquardt step became non-finite (NaN or inf)")
    from flowmocap.fit.tracker import frame_energy

    st = _state(torch.as_tensor(x[:72], dtype=dtype), torch.as_tensor(x[72:], dtype=dtype))
    with torch.no_grad():
        try:
            total, terms = frame_energy(scene, st, data, cfg, stage, prev_px, ref)
        except InputError as e:  # e.g. non-finite projected vertices
            raise OptimizationError(f"the energy could not be evaluated: {e}") from e
    total = float(total)
    if not math.isfinite(total):
        raise OptimizationError("the energy became non-finite (NaN or inf)")
    return total, terms


def lm_stage(scene: Scene, x: np.ndarray, data: FrameData, cfg: TrackerConfig, stage: int, prev_px, ref,
             dtype, rtol: float = LM_RTOL, lam0: float = LM_LAMBDA0, max_rejects: int = LM_MAX_REJECTS,
             stats: dict | None = None) -> tuple[np.ndarray, float]:
    """One coarse-to-fine stage of Levenberg-Marquardt from ``x (75,)``; returns ``(x, energy)``.

    At most ``cfg.iterations`` trial steps. A step is accepted only if ``frame_energy``
    decreases; ``lambda`` then shrinks by Nielsen's rule ``max(1/3, 1 - (2 rho - 1)^3)``
    (``rho``: actual over predicted decrease), else grows tenfold. The stage ends
    when an accepted step lowers the energy by less than ``rtol`` relatively, when the
    linear model predicts a decrease below ``rtol`` relatively, or after
    ``max_rejects`` rejected steps in a row (the rasterised energy is piecewise constant
    at the scale of a pixel, so close to its minimum the linear model stops predicting it
    and more damping only shrinks the step).
    """
    E, _ = _energy(scene, x, data, cfg, stage, prev_px, ref, dtype)
    lam = lam0
    need_lin = True
    rejected = 0
    A = g = d = None
    for _ in range(cfg.iterations):
        if need_lin:
            st = _state(torch.as_tensor(x[:72], dtype=dtype), torch.as_tensor(x[72:], dtype=dtype))
            A, g, _ = _normal_equations(residual_blocks(scene, st, data, cfg, stage, prev_px, ref))
            if not (np.all(np.isfinite(A)) and np.all(np.isfinite(g))):
                raise OptimizationError("the residual Jacobian became non-finite (NaN or inf)")
            d = np.diag(A).copy()
            d = np.maximum(d, 1e-9 * max(float(d.max()), 1e-30))
            need_lin = False
            if stats is not None:
                stats["jacobians"] = stats.get("jacobians", 0) + 1
        try:
            delta = np.linalg.solve(A + lam * np.diag(d), -g)
            predicted = -2.0 * float(g @ delta) - float(delta @ A @ delta)  # E - model(x + delta)
        except np.linalg.LinAlgError:
            predicted = float("nan")
        if math.isfinite(predicted) and 0.0 <= predicted < rtol * E:
            break  # even the linear model promises less than rtol: converged
        accepted = False
        if math.isfinite(predicted) and predicted > 0.0:
            E_new, _ = _energy(scene, x + delta, data, cfg, stage, prev_px, ref, dtype)
            if stats is not None:
                stats["evaluations"] = stats.get("evaluations", 0) + 1
                if stats.get("trace") is not None:
                    stats["trace"].append((stage, lam, E, E_new, predicted))
            accepted = E_new < E
        if accepted:
            rho = (E - E_new) / predicted
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            x = x + delta
            decrease = (E - E_new) / max(E, 1e-30)
            E = E_new
            need_lin = True
            rejected = 0
            if decrease < rtol:
                break
        else:
            lam *= LM_REJECT_FACTOR
            rejected += 1
            if rejected >= max_rejects:
                break
    return x, E


def lm_track_frame(scene: Scene, init: FrameState, data: FrameData, cfg: TrackerConfig, prev: FrameState,
                   ref_pose: torch.Tensor | None = None, *, rtol: float = LM_RTOL,
                   lam0: float = LM_LAMBDA0, max_rejects: int = LM_MAX_REJECTS,
                   stats: dict | None = None) -> tuple[FrameState, dict]:
    """Optimise one frame with Levenberg-Marquardt; the counterpart of
    :func:`flowmocap.fit.tracker.track_frame` (same arguments, same result).

    Coarse to fine over ``cfg.stages``, at most ``cfg.iterations`` trial steps per stage.

    Args:
        scene, init, data, cfg, prev: as for ``track_frame``.
        ref_pose: the pose ``E_theta`` pulls towards; default as ``track_frame`` chooses
            it (``init``'s pose for ``temporal_reference == "prediction"``, else ``prev``'s).
        rtol: an accepted step that lowers the energy by less than this fraction ends the stage.
        lam0: the initial damping of each stage (relative to the diagonal of ``J^T J``).
        max_rejects: this many rejected steps in a row end the stage.
        stats: optional dict that receives counts of Jacobians and energy evaluations.

    Returns:
        ``(FrameState, terms)`` with the final energies by name and ``"total"``.

    Raises:
        InputError: ``cfg.silhouette_model`` is not ``"mesh"`` while the frame has a mask.
        OptimizationError: the energy, a step or the Jacobian became non-finite.
    """
    _check_config(cfg, data)
    dtype = init.pose.dtype
    with torch.no_grad():
        _, prev_px, _ = scene.forward(prev.pose, prev.trans)
    if ref_pose is None:
        ref_pose = init.pose.detach().clone() if cfg.temporal_reference == "prediction" else prev.pose
    x = np.concatenate([init.pose.detach().double().numpy().reshape(72), init.trans.detach().double().numpy().reshape(3)])
    for stage in range(len(cfg.stages)):
        x, _ = lm_stage(scene, x, data, cfg, stage, prev_px, ref_pose, dtype, rtol=rtol, lam0=lam0, max_rejects=max_rejects,
                        stats=stats)
    state = _state(torch.as_tensor(x[:72], dtype=dtype), torch.as_tensor(x[72:], dtype=dtype))
    total, terms = _energy(scene, x, data, cfg, len(cfg.stages) - 1, prev_px, ref_pose, dtype)
    terms["total"] = total
    return state, terms
