"""The posed body of a fixed shape as one compiled pass with a hand-written gradient.

The tracker evaluates the body about 55 times a frame with the shape fixed. Through
:func:`~flowmocap.body.lbs.lbs` that is about 60 small torch operations forward and as
many autograd nodes backward (Rodrigues' formula, the kinematic chain one tree level at
a time, the dense ``(V, 24)`` skinning product), which cost more than their arithmetic.
:func:`posed_body` computes the same function -- Rodrigues' formula with the same Taylor
branch, the chain, the pose blend shapes when the model has them, linear blend skinning
over each vertex's few non-zero weights -- in float64 Numba kernels, and its gradient
with respect to the pose and the translation by the chain rule written out
(``_chain_backward``, ``_skin_backward``; tested against :func:`~flowmocap.body.lbs.lbs`
and against finite differences).

Maths (Loper et al. 2015, Eqs. 1-4): joint ``k`` with parent ``p`` has the local
rotation ``R_k = I + a K + b K^2`` (``K = skew(r_k)``, ``a = sin t / t``,
``b = (1 - cos t) / t^2``, ``t = |r_k|``) and offset ``t_k = J_k - J_p`` (rest joints
``J``); its world rotation and origin are ``G_k = G_p R_k`` and ``o_k = G_p t_k + o_p``;
skinning blends ``A_k = [G_k | o_k - G_k J_k]`` with the weights ``w_vk``:
``v = sum_k w_vk A_k [v_p; 1]`` where ``v_p`` is the rest vertex plus the pose blend
shapes of ``(R_k - I)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from numba import njit

from flowmocap.errors import InputError
from flowmocap.geometry.rotations import SINC_SERIES, SMALL_ANGLE_SQ, VERSINE_SERIES

#: Taylor coefficients of a(t^2) = sin t / t and b(t^2) = (1 - cos t) / t^2 (those of
#: :func:`flowmocap.geometry.rotations.axis_angle_to_matrix`).
_CA = np.array(SINC_SERIES)
_CB = np.array(VERSINE_SERIES)


@njit(cache=True, nogil=True)
def _rodrigues(r, small_sq, ca, cb, R, coef):
    """``R (3, 3)`` of the rotation vector ``r (3,)``; ``coef`` gets ``a, b`` and their
    derivatives with respect to ``t^2``."""
    x, y, z = r[0], r[1], r[2]
    t2 = x * x + y * y + z * z
    if t2 < small_sq:
        a = ca[4]
        b = cb[4]
        da = 4.0 * ca[4]
        db = 4.0 * cb[4]
        for n in range(3, -1, -1):
            a = a * t2 + ca[n]
            b = b * t2 + cb[n]
            if n > 0:
                da = da * t2 + n * ca[n]
                db = db * t2 + n * cb[n]
    else:
        t = math.sqrt(t2)
        s, c = math.sin(t), math.cos(t)
        a = s / t
        da = (t * c - s) / (t2 * 2.0 * t)
        h = math.sin(0.5 * t) / t
        b = 2.0 * h * h
        dh = (0.5 * math.cos(0.5 * t) * t - math.sin(0.5 * t)) / t2
        db = 4.0 * h * dh / (2.0 * t)
    coef[0], coef[1], coef[2], coef[3] = a, b, da, db
    # K = skew(r); K^2 = r r^T - t^2 I
    R[0, 0] = 1.0 + b * (x * x - t2)
    R[1, 1] = 1.0 + b * (y * y - t2)
    R[2, 2] = 1.0 + b * (z * z - t2)
    R[0, 1] = -a * z + b * x * y
    R[1, 0] = a * z + b * x * y
    R[0, 2] = a * y + b * x * z
    R[2, 0] = -a * y + b * x * z
    R[1, 2] = -a * x + b * y * z
    R[2, 1] = a * x + b * y * z


@njit(cache=True, nogil=True)
def _chain_forward(pose, rest_joints, parents, small_sq, ca, cb, R, G, o, A, coef):
    """Local rotations ``R``, world rotations ``G`` and origins ``o`` (the posed joints)
    of the 24 joints, the skinning transforms ``A (24, 3, 4)`` and Rodrigues'
    coefficients; parents come before their children."""
    for k in range(pose.shape[0]):
        _rodrigues(pose[k], small_sq, ca, cb, R[k], coef[k])
        p = parents[k]
        if p < 0:
            for i in range(3):
                o[k, i] = rest_joints[k, i]
                for j in range(3):
                    G[k, i, j] = R[k, i, j]
        else:
            for i in range(3):
                acc = o[p, i]
                for j in range(3):
                    acc += G[p, i, j] * (rest_joints[k, j] - rest_joints[p, j])
                    g = 0.0
                    for m in range(3):
                        g += G[p, i, m] * R[k, m, j]
                    G[k, i, j] = g
                o[k, i] = acc
        for i in range(3):
            acc = o[k, i]
            for j in range(3):
                A[k, i, j] = G[k, i, j]
                acc -= G[k, i, j] * rest_joints[k, j]
            A[k, i, 3] = acc


@njit(cache=True, nogil=True)
def _skin_forward(vp, idx, w, A, trans, out):
    """``out (V, 3) = sum_k w_vk A_k [vp_v; 1] + trans``."""
    for v in range(vp.shape[0]):
        x, y, z = vp[v, 0], vp[v, 1], vp[v, 2]
        for i in range(3):
            acc = 0.0
            for n in range(idx.shape[1]):
                wk = w[v, n]
                if wk != 0.0:
                    k = idx[v, n]
                    acc += wk * (A[k, i, 0] * x + A[k, i, 1] * y + A[k, i, 2] * z + A[k, i, 3])
            out[v, i] = acc + trans[i]


@njit(cache=True, nogil=True)
def _skin_backward(vp, idx, w, A, dv, dA, dvp, want_dvp):
    """Adds to ``dA (24, 3, 4)`` the gradient of the skinned vertices given theirs,
    ``dv (V, 3)``; with ``want_dvp`` also writes ``dvp (V, 3)`` (the rest vertices')."""
    for v in range(vp.shape[0]):
        x, y, z = vp[v, 0], vp[v, 1], vp[v, 2]
        g0, g1, g2 = dv[v, 0], dv[v, 1], dv[v, 2]
        if want_dvp:
            dvp[v, 0] = 0.0
            dvp[v, 1] = 0.0
            dvp[v, 2] = 0.0
        for n in range(idx.shape[1]):
            wk = w[v, n]
            if wk == 0.0:
                continue
            k = idx[v, n]
            for i in range(3):
                gi = wk * (g0 if i == 0 else g1 if i == 1 else g2)
                dA[k, i, 0] += gi * x
                dA[k, i, 1] += gi * y
                dA[k, i, 2] += gi * z
                dA[k, i, 3] += gi
            if want_dvp:
                for j in range(3):
                    dvp[v, j] += wk * (A[k, 0, j] * g0 + A[k, 1, j] * g1 + A[k, 2, j] * g2)


@njit(cache=True, nogil=True)
def _chain_backward(pose, rest_joints, parents, R, G, coef, dA, dO, dR, dpose):
    """``dpose (24, 3)``, the gradient of the pose, from those of the skinning transforms
    ``dA (24, 3, 4)``, the posed joints ``dO (24, 3)`` and (pose blend shapes) the local
    rotations ``dR (24, 3, 3)``; ``dA``, ``dO`` and ``dR`` are used as scratch."""
    J = pose.shape[0]
    dG = np.zeros((J, 3, 3))
    for k in range(J):
        # A_k = [G_k | o_k - G_k J_k]
        for i in range(3):
            dO[k, i] += dA[k, i, 3]
            for j in range(3):
                dG[k, i, j] += dA[k, i, j] - dA[k, i, 3] * rest_joints[k, j]
    for k in range(J - 1, -1, -1):
        p = parents[k]
        if p < 0:
            for i in range(3):
                for j in range(3):
                    dR[k, i, j] += dG[k, i, j]
            continue
        for i in range(3):
            for j in range(3):
                # G_k = G_p R_k
                s_r = 0.0  # (G_p^T dG_k)_ij
                s_g = 0.0  # (dG_k R_k^T)_ij
                for m in range(3):
                    s_r += G[p, m, i] * dG[k, m, j]
                    s_g += dG[k, i, m] * R[k, j, m]
                dR[k, i, j] += s_r
                # o_k = G_p (J_k - J_p) + o_p
                dG[p, i, j] += s_g + dO[k, i] * (rest_joints[k, j] - rest_joints[p, j])
            dO[p, i] += dO[k, i]
    for k in range(J):
        # R = I + a K + b (r r^T - t^2 I), a and b functions of t^2
        x, y, z = pose[k, 0], pose[k, 1], pose[k, 2]
        a, b, da, db = coef[k, 0], coef[k, 1], coef[k, 2], coef[k, 3]
        g = dR[k]
        tr = g[0, 0] + g[1, 1] + g[2, 2]
        t2 = x * x + y * y + z * z
        gk = (g[1, 0] - g[0, 1]) * z + (g[0, 2] - g[2, 0]) * y + (g[2, 1] - g[1, 2]) * x  # <g, K>
        grr = 0.0
        for i in range(3):
            for j in range(3):
                grr += g[i, j] * pose[k, i] * pose[k, j]
        gk2 = grr - t2 * tr  # <g, K^2>
        skew_part = (g[2, 1] - g[1, 2], g[0, 2] - g[2, 0], g[1, 0] - g[0, 1])  # <g, skew(e_i)>
        for i in range(3):
            gr = g[i, 0] * x + g[i, 1] * y + g[i, 2] * z  # (g r)_i
            gtr = g[0, i] * x + g[1, i] * y + g[2, i] * z  # (g^T r)_i
            ri = pose[k, i]
            dpose[k, i] = (2.0 * ri * (da * gk + db * gk2) + a * skew_part[i]
                           + b * (gr + gtr - 2.0 * ri * tr))


@dataclass
class Rig:
    """What :func:`posed_body` needs of a body model with a fixed shape, as float64
    arrays: the shaped rest vertices ``(V, 3)`` and joints ``(24, 3)`` (metres), the
    parents, each vertex's non-zero skinning weights ``w (V, K)`` and their joints
    ``idx (V, K)`` (zero-padded), and the pose blend shapes ``(207, V * 3)`` or None."""

    v_shaped: np.ndarray
    rest_joints: np.ndarray
    parents: np.ndarray
    idx: np.ndarray
    w: np.ndarray
    posedirs: np.ndarray | None
    shaped: tuple  # the torch tensors (v_shaped (1, V, 3), rest_joints (1, 24, 3)) for BodyOutput


def make_rig(model, shaped: tuple[torch.Tensor, torch.Tensor]) -> Rig:
    """The :class:`Rig` of ``model`` (a :class:`~flowmocap.body.BodyModel`) with the
    shape of ``shaped = model.shaped(betas)`` (batch 1)."""
    v_shaped, rest_joints = shaped
    if v_shaped.shape[0] != 1 or rest_joints.shape[0] != 1:
        raise InputError(f"make_rig takes one shape (batch 1); got a batch of {v_shaped.shape[0]}.")
    W = model.weights.detach().cpu().numpy().astype(np.float64)
    nz = W != 0.0
    K = max(1, int(nz.sum(1).max()))
    order = np.argsort(~nz, axis=1, kind="stable")[:, :K]  # each row's non-zero weights first
    w = np.take_along_axis(W, order, axis=1) * np.take_along_axis(nz, order, axis=1)
    posedirs = None if model.posedirs is None else model.posedirs.detach().cpu().numpy().astype(np.float64)
    return Rig(v_shaped[0].detach().cpu().numpy().astype(np.float64),
               rest_joints[0].detach().cpu().numpy().astype(np.float64),
               model.parents.cpu().numpy().astype(np.int64), order.astype(np.int32), np.ascontiguousarray(w),
               posedirs, tuple(x.detach() for x in shaped))


class _PosedBody(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pose, trans, rig, with_vertices):  # noqa: D102
        p = pose.detach().cpu().numpy().astype(np.float64).reshape(-1, 3)
        tr = trans.detach().cpu().numpy().astype(np.float64).reshape(3)
        if not (np.isfinite(p).all() and np.isfinite(tr).all()):
            raise InputError("pose contains NaN or infinite values." if not np.isfinite(p).all()
                             else "trans contains NaN or infinite values.")
        J = p.shape[0]
        R, G = np.empty((J, 3, 3)), np.empty((J, 3, 3))
        o, A, coef = np.empty((J, 3)), np.empty((J, 3, 4)), np.empty((J, 4))
        _chain_forward(p, rig.rest_joints, rig.parents, SMALL_ANGLE_SQ, _CA, _CB, R, G, o, A, coef)
        vp = rig.v_shaped
        if with_vertices and rig.posedirs is not None:
            feature = (R[1:] - np.eye(3)).reshape(-1)
            vp = vp + (feature @ rig.posedirs).reshape(-1, 3)
        dt, dev = pose.dtype, pose.device
        T = np.zeros((J, 4, 4))
        T[:, :3, :] = A
        T[:, :3, 3] += tr
        T[:, 3, 3] = 1.0
        if with_vertices:
            verts = np.empty_like(vp)
            _skin_forward(vp, rig.idx, rig.w, A, tr, verts)
        else:
            verts = np.zeros((0, 3))
        ctx.saved = (p, R, G, A, coef, vp, rig, with_vertices, dt, dev)
        ctx.set_materialize_grads(False)
        as_t = lambda x: torch.as_tensor(x, dtype=dt, device=dev)  # noqa: E731
        return as_t(verts), as_t(o + tr), as_t(T)

    @staticmethod
    def backward(ctx, d_verts, d_joints, d_transforms):  # noqa: D102
        p, R, G, A, coef, vp, rig, with_vertices, dt, dev = ctx.saved
        if d_verts is None and d_joints is None and d_transforms is None:
            return None, None, None, None
        J = p.shape[0]
        dA, dO, dR = np.zeros((J, 3, 4)), np.zeros((J, 3)), np.zeros((J, 3, 3))
        dtrans = np.zeros(3)
        if d_transforms is not None:
            dT = d_transforms.detach().cpu().numpy().astype(np.float64).reshape(J, 4, 4)
            dA += dT[:, :3, :]
            dtrans += dT[:, :3, 3].sum(0)
        if d_joints is not None:
            dj = d_joints.detach().cpu().numpy().astype(np.float64).reshape(J, 3)
            dO += dj
            dtrans += dj.sum(0)
        if with_vertices and d_verts is not None:
            dv = np.ascontiguousarray(d_verts.detach().cpu().numpy().astype(np.float64).reshape(-1, 3))
            dtrans += dv.sum(0)
            want = rig.posedirs is not None
            dvp = np.empty_like(vp) if want else np.empty((0, 3))
            _skin_backward(vp, rig.idx, rig.w, A, dv, dA, dvp, want)
            if want:
                dR[1:] += (rig.posedirs @ dvp.reshape(-1)).reshape(J - 1, 3, 3)
        dpose = np.empty((J, 3))
        _chain_backward(p, rig.rest_joints, rig.parents, R, G, coef, dA, dO, dR, dpose)
        as_t = lambda x: torch.as_tensor(x, dtype=dt, device=dev)  # noqa: E731
        return as_t(dpose.reshape(-1)), as_t(dtrans), None, None


def posed_body(rig: Rig, pose: torch.Tensor, trans: torch.Tensor, with_vertices: bool = True):
    """The body of ``rig``'s shape in ``pose (72,)`` (axis-angle, radians) moved by
    ``trans (3,)`` (metres), with gradients to both: the same
    :class:`~flowmocap.body.BodyOutput` as ``model(betas, pose, trans, shaped=rig.shaped,
    with_vertices=...)`` (batch 1, float64 arithmetic, returned in ``pose``'s dtype).

    Raises:
        InputError: a non-finite pose or translation (as :meth:`BodyModel.forward`).
    """
    from flowmocap.body.model import BodyOutput

    verts, joints, transforms = _PosedBody.apply(pose.reshape(-1), trans.reshape(-1), rig, bool(with_vertices))
    return BodyOutput(vertices=verts[None] if with_vertices else None, joints=joints[None],
                      rest_vertices=rig.shaped[0], rest_joints=rig.shaped[1], transforms=transforms[None])
