"""The tracker's energy terms (paper Sec. 3.3-3.7) as differentiable torch functions.

Every term comes in two forms: ``*_residuals(...) -> (B, M)`` and
``*_energy(...) -> (B,)`` with ``energy == (residuals ** 2).sum(-1)``, so the
optimiser can stack residuals for Gauss-Newton / Levenberg-Marquardt or sum weighted
energies for L-BFGS. B is the batch of body hypotheses (usually 1). The flow term E_f
lives in :mod:`flowmocap.render` (``flow_loss``, ``flow_residuals``).

==========================  =============================================  ===========
term                         energy                                         unit
==========================  =============================================  ===========
E_b  joint limits            sum (max(e^(lo-th)-1,0) + max(e^(th-hi)-1,0))^2  --
E_sp interpenetration        sum_pairs max(r_a + r_b - d_ab - tol, 0)^2      m^2 (tol 2 cm)
E_c  silhouette coverage     sum_p (a S_M C_I + (1-a) S_I C_M)^2 / |S_I|     px^2
E_c  (mesh form)             a mean_v C_I(x_v)^2 + (1-a) mean_p C_M(p)^2     px^2
keypoints (init)             sum_j c_j GM_sigma(x_j - x_obs_j)                px^2
E_d  limb depth              sum_l c_l GM_sigma(u_z,l - o_z,l)                --
E_3d detector 3D joints      sum_j c_j PH_s(|x_j - (s R o_j + t)|)          m^2
pose prior (init)            sum_i w_i (theta_i - theta_ref_i)^2             rad^2
shape prior (init)           ||beta||^2                                      --
E_theta                      sum_i w_i (theta_i - theta_prev_i)^2            rad^2 (root:
                                                                             geodesic)
E_z  root depth              ((sigma - sigma_ref) . u)^2                     m^2
==========================  =============================================  ===========

E_sp and E_c take the capsules of :func:`flowmocap.body.body_capsules`; compute them
once per evaluation and pass them to both.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from numba import njit

from flowmocap.body.capsules import CAPSULE_BONES, CAPSULE_NAMES, Capsules, body_capsules
from flowmocap.body.files import load_body_model
from flowmocap.body.skeleton import NUM_JOINTS, PARENTS
from flowmocap.errors import InputError, NoPersonError
from flowmocap.fit import rotation_terms as rt
from flowmocap.fit.aligned_joints import aligned_joints_energy
from flowmocap.fit.joint_terms import limb_depth_energy_world
from flowmocap.fit.with_gradient import energy_with_gradient
from flowmocap.fit.joint_limits import JointLimits, default_joint_limits, joint_angles
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.geometry.procrustes import similarity_procrustes
from flowmocap.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from flowmocap.render.capsules import (capsule_distance_grid, capsule_signed_distance, grid_signed_distance_grad_kernel,
                                       grid_signed_distance_kernel, project_capsules)
from flowmocap.vision.masks import chamfer_map

__all__ = [
    "joint_limit_residuals",
    "joint_limit_energy",
    "interpenetration_pairs",
    "segment_segment_distance",
    "interpenetration_residuals",
    "interpenetration_energy",
    "SilhouetteTarget",
    "silhouette_target",
    "camera_ray",
    "depth_temporal_residuals",
    "depth_temporal_energy",
    "root_distance_residuals",
    "root_distance_energy",
    "capsule_signed_distance",
    "silhouette_residuals",
    "silhouette_energy",
    "mesh_silhouette_residuals",
    "mesh_silhouette_energy",
    "keypoint_residuals",
    "keypoint_energy",
    "DEPTH_LIMBS",
    "limb_depth_residuals",
    "limb_depth_energy",
    "world_limb_depth_energy",
    "MIN_DETECTOR_JOINTS",
    "pseudo_huber",
    "detector_joints_residuals",
    "detector_joints_energy",
    "world_detector_joints_energy",
    "pose_prior_residuals",
    "pose_prior_energy",
    "shape_prior_residuals",
    "shape_prior_energy",
    "temporal_residuals",
    "temporal_energy",
]

NUM_POSE = 3 * NUM_JOINTS


def _pose(pose: Any, name: str = "pose") -> torch.Tensor:
    """``(B, 72)`` floating tensor from ``(B, 72)``, ``(B, 24, 3)`` or ``(72,)``."""
    if not isinstance(pose, torch.Tensor):
        raise InputError(f"{name} must be a torch.Tensor of shape (B, 72), got {type(pose).__name__}")
    if not pose.is_floating_point():
        raise InputError(f"{name} must be floating point, got {pose.dtype}")
    if pose.dim() == 3 and pose.shape[1:] == (NUM_JOINTS, 3):
        pose = pose.reshape(pose.shape[0], NUM_POSE)
    if pose.dim() == 1:
        pose = pose[None]
    if pose.dim() != 2 or pose.shape[1] != NUM_POSE:
        raise InputError(f"{name} must have shape (B, 72), got {tuple(pose.shape)}")
    return pose


#: Use the compiled kernels of :mod:`flowmocap.fit.rotation_terms` for E_b and E_theta's
#: root on CPU tensors (False: the torch-op definitions, e.g. to compare the two).
_COMPILED = True


def _like(x: Any, ref: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(x, dtype=ref.dtype, device=ref.device)


def _sum_sq(r: torch.Tensor) -> torch.Tensor:
    return (r * r).sum(-1)


# ------------------------------------------------------------------------------- E_b


_DEFAULT_LIMITS: JointLimits | None = None


def _limits(limits: JointLimits | None) -> JointLimits:
    global _DEFAULT_LIMITS
    if limits is not None:
        if not isinstance(limits, JointLimits):
            raise InputError(f"limits must be a JointLimits, got {type(limits).__name__}")
        return limits
    if _DEFAULT_LIMITS is None:
        _DEFAULT_LIMITS = default_joint_limits()
    return _DEFAULT_LIMITS


def joint_limit_residuals(pose: torch.Tensor, limits: JointLimits | None = None) -> torch.Tensor:
    """Residuals of the soft joint limits E_b (paper Eq. 2), one per limited angle.

    ``r = max(exp(lo - th) - 1, 0) + max(exp(th - hi) - 1, 0)`` for every non-root
    joint and axis, with ``th`` the joint's angles in its chart (Euler angles in a
    per-joint order, the raw axis-angle components for the shoulders; see
    :mod:`flowmocap.fit.joint_limits`). Zero inside the limits, ``~ excess`` just
    outside, growing exponentially; ``r^2`` is continuously differentiable.

    Args:
        pose: ``(B, 72)`` (or ``(B, 24, 3)``) SMPL axis-angle pose, radians.
        limits: :class:`~flowmocap.fit.joint_limits.JointLimits` (default: the table in
            :mod:`flowmocap.fit.joint_limits`).

    Returns:
        ``(B, 69)``: 23 joints (SMPL order without the root) x (x, y, z), unitless.
    """
    pose = _pose(pose)
    lim = _limits(limits)
    lock_eps = 100.0 * torch.finfo(pose.dtype).eps
    if _COMPILED and pose.device.type == "cpu":  # compiled kernel with a closed-form Jacobian; same values
        return rt.limit_residuals(pose, rt.limit_charts(lim), lock_eps)
    joints = torch.as_tensor(lim.limited, device=pose.device)
    th = joint_angles(pose, lim.charts)[:, joints]  # (B, 23, 3)
    lo = _like(lim.lower[lim.limited], th)
    hi = _like(lim.upper[lim.limited], th)
    # max(exp(x) - 1, 0) == expm1(max(x, 0)); exact and overflow-free inside the limits
    r = torch.expm1(torch.relu(lo - th)) + torch.expm1(torch.relu(th - hi))
    return r.reshape(pose.shape[0], -1)


def joint_limit_jacobian(pose: Any, limits: JointLimits | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`joint_limit_residuals` of one pose and their Jacobian, float64.

    Args:
        pose: ``(72,)`` axis-angle, radians.
        limits: as for :func:`joint_limit_residuals`.

    Returns:
        ``r (69,)`` and ``J (69, 72)`` = ``d r / d pose``.
    """
    p = np.asarray(pose, np.float64).reshape(1, NUM_POSE)
    charts = rt.limit_charts(_limits(limits))
    r, blocks = rt.limit_residuals_jacobian(p, charts, 100.0 * torch.finfo(torch.float64).eps)
    J = np.zeros((r.shape[1], NUM_POSE))
    for q, j in enumerate(charts.joints):
        J[3 * q:3 * q + 3, 3 * j:3 * j + 3] = blocks[0, q]
    return r[0], J


def joint_limit_energy(pose: torch.Tensor, limits: JointLimits | None = None) -> torch.Tensor:
    """E_b: sum of squared :func:`joint_limit_residuals`, ``(B,)`` (unitless)."""
    return _sum_sq(joint_limit_residuals(pose, limits))


# ------------------------------------------------------------------------------ E_sp

#: Pairs of capsules closer than this (metres, surface to surface) in the rest pose
#: count as touching and are never penalised.
REST_CONTACT_TOLERANCE = 0.01
#: Capsules whose bones are this many steps apart or fewer in the kinematic tree
#: (parent: 1; grandparent or sibling: 2) are not penalised, unless they belong to
#: two different limbs.
TREE_NEIGHBOURS = 2
#: The limbs, as capsule names; every other capsule is part of the trunk.
LIMBS: tuple[tuple[str, ...], ...] = tuple(
    tuple(f"{side}_{part}" for part in parts)
    for side in ("left", "right")
    for parts in (("upper_arm", "forearm", "hand"), ("thigh", "shin", "foot"))
)
#: Default overlap (metres) E_sp tolerates: a capsule's radius is the mean distance
#: of its vertices to the axis, so the capsules of surfaces that merely touch (a
#: swinging hand brushing the thigh) overlap by up to about 2 cm.
DEFAULT_TOLERANCE = 0.02

_DEFAULT_PAIRS: tuple[tuple[int, int], ...] | None = None


def _tree_distance(a: int, b: int) -> int:
    """Number of bones on the tree path between joints a and b."""
    def ancestors(j):
        out = []
        while j != -1:
            out.append(j)
            j = PARENTS[j]
        return out

    pa, pb = ancestors(a), ancestors(b)
    common = next(j for j in pa if j in pb)
    return pa.index(common) + pb.index(common)


def interpenetration_pairs(model=None) -> tuple[tuple[int, int], ...]:
    """The capsule pairs E_sp penalises (indices into ``Capsules.names``).

    All pairs except

    (a) those whose bones are at most :data:`TREE_NEIGHBOURS` steps apart in the
        kinematic tree (bone and parent, grandparent or sibling: forearm -- upper arm
        -- chest, thigh -- foot, thigh -- lower belly), unless they belong to two
        different limbs (the two thighs stay in): bending the joints between them
        presses such capsules together as it presses real flesh (sitting, a full
        elbow flexion);
    (b) those that touch or overlap in the rest pose (surface gap below
        :data:`REST_CONTACT_TOLERANCE`) of ``model``'s mean shape. For the default
        body these are the torso pieces, pelvis -- thighs and neck -- head, all of
        them already in (a).

    For the default body's 20 capsules that leaves 150 of the 190 pairs: arms against
    the trunk below the chest, the head, the other arm and the legs; legs against each
    other and the trunk above the lower belly; trunk pieces three or more bones apart.
    The upper arm against the chest is not among them (the arm hanging at the side
    touches it), so an arm swung through the chest is penalised through its forearm
    and hand only.

    Args:
        model: the body model whose rest pose decides (b); default: the bundled
            default body (computed once and cached).

    Returns:
        sorted tuple of ``(i, j)`` with ``i < j``.
    """
    global _DEFAULT_PAIRS
    if model is None and _DEFAULT_PAIRS is not None:
        return _DEFAULT_PAIRS
    m = load_body_model("default", dtype=torch.float64) if model is None else model
    with torch.no_grad():
        caps = body_capsules(m, m())
        K = len(CAPSULE_NAMES)
        i, j = zip(*itertools.combinations(range(K), 2))
        i, j = torch.tensor(i), torch.tensor(j)
        d = segment_segment_distance(caps.start[:, i], caps.end[:, i], caps.start[:, j], caps.end[:, j])
        gap = (d - caps.radius[:, i] - caps.radius[:, j])[0].double().cpu().numpy()
    limb_of = {name: n for n, limb in enumerate(LIMBS) for name in limb}
    pairs = []
    for p, (a, b) in enumerate(zip(i.tolist(), j.tolist())):
        la, lb = limb_of.get(CAPSULE_NAMES[a]), limb_of.get(CAPSULE_NAMES[b])
        two_limbs = la is not None and lb is not None and la != lb
        if _tree_distance(CAPSULE_BONES[a], CAPSULE_BONES[b]) <= TREE_NEIGHBOURS and not two_limbs:
            continue
        if gap[p] < REST_CONTACT_TOLERANCE:
            continue
        pairs.append((a, b))
    out = tuple(pairs)
    if model is None:
        _DEFAULT_PAIRS = out
    return out


def segment_segment_distance(p1: torch.Tensor, q1: torch.Tensor, p2: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Distance between 3D segments ``[p1, q1]`` and ``[p2, q2]``, batched.

    Closest points by Ericson (*Real-Time Collision Detection*, 5.1.9), robust to
    parallel and zero-length segments. The closest-point parameters are treated as
    constants in the backward pass: by the envelope theorem the gradient of a minimum
    over a fixed parameter box is the partial derivative at the minimiser, so this is
    the exact gradient wherever the closest pair is unique. The distance is
    ``sqrt(|c1 - c2|^2 + 1e-12)``, finite with zero gradient where the segments cross.

    Args:
        p1, q1, p2, q2: ``(..., 3)`` end points (metres), broadcastable.

    Returns:
        ``(...)`` distances (metres).
    """
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    with torch.no_grad():
        eps = 1e-12
        a = (d1 * d1).sum(-1)
        e = (d2 * d2).sum(-1)
        b = (d1 * d2).sum(-1)
        c = (d1 * r).sum(-1)
        f = (d2 * r).sum(-1)
        a_s, e_s = a.clamp_min(eps), e.clamp_min(eps)
        denom = a * e - b * b
        s = torch.where(denom > eps * (a * e).clamp_min(eps), ((b * f - c * e) / denom.clamp_min(eps)).clamp(0, 1),
                        torch.zeros_like(a))
        t = (b * s + f) / e_s
        s = torch.where(t < 0, (-c / a_s).clamp(0, 1), torch.where(t > 1, ((b - c) / a_s).clamp(0, 1), s))
        t = t.clamp(0, 1)
        point2 = e <= eps  # second segment is a point: t = 0, s from the projection
        s = torch.where(point2, (-c / a_s).clamp(0, 1), s)
        t = torch.where(point2, torch.zeros_like(t), t)
        point1 = a <= eps
        s = torch.where(point1, torch.zeros_like(s), s)
        t = torch.where(point1 & ~point2, (f / e_s).clamp(0, 1), t)
    diff = r + s[..., None] * d1 - t[..., None] * d2
    return torch.sqrt((diff * diff).sum(-1) + 1e-12)


def _pair_index(pairs, K: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    pairs = interpenetration_pairs() if pairs is None else pairs
    arr = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if arr.size and (arr.min() < 0 or arr.max() >= K or (arr[:, 0] == arr[:, 1]).any()):
        raise InputError(f"pairs must be (i, j) capsule indices in [0, {K}) with i != j")
    return torch.as_tensor(arr[:, 0], device=device), torch.as_tensor(arr[:, 1], device=device)


def interpenetration_residuals(
    capsules: Capsules, pairs: Sequence[tuple[int, int]] | None = None, tolerance: float = DEFAULT_TOLERANCE
) -> torch.Tensor:
    """Residuals of E_sp: the overlap depth of each penalised capsule pair.

    A simpler stand-in for SMPLify's Gaussian-sphere term (Bogo et al. 2016):
    ``r = max(r_a + r_b - d(segment_a, segment_b) - tolerance, 0)``, the depth by which
    two capsules interpenetrate (metres), zero when they are apart; ``r^2`` is
    continuously differentiable.

    Args:
        capsules: :class:`~flowmocap.body.capsules.Capsules` of a batch of bodies
            (from :func:`flowmocap.body.body_capsules`).
        pairs: ``(P, 2)`` capsule index pairs (default: :func:`interpenetration_pairs`).
        tolerance: overlap in metres that is not penalised (default
            :data:`DEFAULT_TOLERANCE`, 2 cm).

    Returns:
        ``(B, P)`` overlap depths in metres.
    """
    K = capsules.start.shape[1]
    i, j = _pair_index(pairs, K, capsules.start.device)
    d = segment_segment_distance(capsules.start[:, i], capsules.end[:, i], capsules.start[:, j], capsules.end[:, j])
    return torch.relu(capsules.radius[:, i] + capsules.radius[:, j] - d - tolerance)


def interpenetration_energy(
    capsules: Capsules, pairs: Sequence[tuple[int, int]] | None = None, tolerance: float = DEFAULT_TOLERANCE
) -> torch.Tensor:
    """E_sp: sum of squared :func:`interpenetration_residuals`, ``(B,)`` in m^2, with its
    gradient in one compiled float64 pass (:func:`_penetration_kernel`: the same closest
    points, held fixed in the gradient as there) on the CPU."""
    K = capsules.start.shape[1]
    if capsules.start.device.type != "cpu":
        return _sum_sq(interpenetration_residuals(capsules, pairs, tolerance))
    i, j = _pair_index(pairs, K, capsules.start.device)
    index = np.ascontiguousarray(np.stack([i.numpy(), j.numpy()], axis=1), np.int64)

    def compute(P, Q, rad):
        energy = np.zeros(P.shape[0])
        gp, gq, gr = np.zeros_like(P), np.zeros_like(Q), np.zeros_like(rad)
        _penetration_kernel(P, Q, rad, index, float(tolerance), energy, gp, gq, gr)
        return energy, [gp, gq, gr]

    return energy_with_gradient(compute, capsules.start, capsules.end, capsules.radius)


@njit(cache=True, nogil=True, error_model="numpy")
def _penetration_kernel(P, Q, rad, pairs, tol, energy, gp, gq, gr):  # pragma: no cover - compiled
    """E_sp ``energy (B,)`` and its gradient (``gp, gq (B, K, 3)``, ``gr (B, K)``, zeroed by
    the caller) for capsules ``P, Q (B, K, 3)`` (segment ends), ``rad (B, K)`` and
    ``pairs (P, 2)``: :func:`segment_segment_distance`'s closest points, then ``r =
    max(r_a + r_b - d - tol, 0)`` and the sum of ``r^2``. float64."""
    eps = 1e-12
    for b in range(P.shape[0]):
        e_total = 0.0
        for n in range(pairs.shape[0]):
            i, j = pairs[n, 0], pairs[n, 1]
            d1 = Q[b, i] - P[b, i]
            d2 = Q[b, j] - P[b, j]
            r = P[b, i] - P[b, j]
            a = d1[0] * d1[0] + d1[1] * d1[1] + d1[2] * d1[2]
            e = d2[0] * d2[0] + d2[1] * d2[1] + d2[2] * d2[2]
            bb = d1[0] * d2[0] + d1[1] * d2[1] + d1[2] * d2[2]
            c = d1[0] * r[0] + d1[1] * r[1] + d1[2] * r[2]
            f = d2[0] * r[0] + d2[1] * r[1] + d2[2] * r[2]
            a_s = max(a, eps)
            e_s = max(e, eps)
            denom = a * e - bb * bb
            if denom > eps * max(a * e, eps):
                s = min(max((bb * f - c * e) / max(denom, eps), 0.0), 1.0)
            else:
                s = 0.0
            t = (bb * s + f) / e_s
            if t < 0.0:
                s = min(max(-c / a_s, 0.0), 1.0)
            elif t > 1.0:
                s = min(max((bb - c) / a_s, 0.0), 1.0)
            t = min(max(t, 0.0), 1.0)
            point2 = e <= eps
            if point2:
                s = min(max(-c / a_s, 0.0), 1.0)
                t = 0.0
            if a <= eps:
                s = 0.0
                if not point2:
                    t = min(max(f / e_s, 0.0), 1.0)
            diff = r + s * d1 - t * d2
            dist = np.sqrt(diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2] + 1e-12)
            res = rad[b, i] + rad[b, j] - dist - tol
            if res <= 0.0:
                continue
            e_total += res * res
            g = 2.0 * res  # dE/dres; dres/ddist = -1, ddist/ddiff = diff / dist
            gr[b, i] += g
            gr[b, j] += g
            for k in range(3):
                gd = -g * diff[k] / dist
                gp[b, i, k] += gd * (1.0 - s)
                gq[b, i, k] += gd * s
                gp[b, j, k] -= gd * (1.0 - t)
                gq[b, j, k] -= gd * t
        energy[b] = e_total


# ------------------------------------------------------------------------------- E_c


@dataclass
class SilhouetteTarget:
    """The image side of E_c, built once per frame by :func:`silhouette_target`.

    Attributes:
        mask: ``(H, W)`` float tensor, 1 on the person (``S_I``), else 0.
        chamfer: ``(H, W)`` float tensor, distance in pixels to the nearest person
            pixel (``C_I``; 0 on the person).
        count: number of person pixels (the normaliser of E_c).
        box: the mask's bounding box ``(y0, x0, y1, x1)`` in pixels, end exclusive.
    """

    mask: torch.Tensor
    chamfer: torch.Tensor
    count: int
    box: tuple[int, int, int, int] = (0, 0, 0, 0)

    @property
    def height(self) -> int:
        """Image height H in pixels."""
        return int(self.mask.shape[0])

    @property
    def width(self) -> int:
        """Image width W in pixels."""
        return int(self.mask.shape[1])


def silhouette_target(mask: Any, dtype: torch.dtype = torch.float32, device: Any = None,
                      unknown: Any = None) -> SilhouetteTarget:
    """Prepare an image mask for :func:`silhouette_energy`.

    Args:
        mask: ``(H, W)`` person mask (bool, or numbers: non-zero = person), numpy or torch.
        dtype, device: of the returned tensors.
        unknown: optional ``(H, W)`` bool, pixels where the person may be hidden (another
            person in front, :meth:`~flowmocap.vision.auto.PersonTrack.others`): the
            chamfer map ``C_I`` is the distance to the nearest pixel of ``mask`` or
            ``unknown``, so the body may cover them at no cost; ``S_I`` (the mask the
            body must cover) stays ``mask``.

    Returns:
        :class:`SilhouetteTarget` with the mask and its chamfer map
        (:func:`flowmocap.vision.chamfer_map`).

    Raises:
        InputError: not a 2D array, or ``unknown`` of another shape. NoPersonError: the mask is empty.
    """
    m = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
    if m.ndim != 2 or m.size == 0:
        raise InputError(f"mask must be a non-empty (H, W) array, got shape {m.shape}")
    m = m != 0
    count = int(m.sum())
    if count == 0:
        raise NoPersonError(
            "the person mask is empty: nothing to fit the silhouette to; check the mask "
            "file or drop the silhouette term for this frame"
        )
    if unknown is not None:
        u = np.asarray(unknown) != 0
        if u.shape != m.shape:
            raise InputError(f"unknown must have the mask's shape {m.shape}, got {u.shape}")
        cham = chamfer_map(m | u)
    else:
        cham = chamfer_map(m)
    rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
    return SilhouetteTarget(
        mask=torch.as_tensor(m, dtype=dtype, device=device),
        chamfer=torch.as_tensor(cham, dtype=dtype, device=device),
        count=count,
        box=(int(rows[0]), int(cols[0]), int(rows[-1]) + 1, int(cols[-1]) + 1),
    )


def _as_target(target: Any, chamfer: Any, dtype: torch.dtype) -> SilhouetteTarget:
    """A :class:`SilhouetteTarget` from itself or from a mask and (optionally) its chamfer map."""
    if isinstance(target, SilhouetteTarget):
        return target
    if chamfer is None:
        return silhouette_target(target, dtype=dtype)
    m = target.detach().cpu().numpy() if isinstance(target, torch.Tensor) else np.asarray(target)
    if m.ndim != 2:
        raise InputError(f"mask must be an (H, W) array, got shape {m.shape}")
    m = m != 0
    if not m.any():
        raise NoPersonError("the person mask is empty: nothing to fit the silhouette to")
    c = chamfer if isinstance(chamfer, torch.Tensor) else torch.as_tensor(np.asarray(chamfer))
    if tuple(c.shape) != m.shape:
        raise InputError(f"chamfer must have the mask's shape {m.shape}, got {tuple(c.shape)}")
    rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
    return SilhouetteTarget(
        mask=torch.as_tensor(m, dtype=dtype, device=c.device), chamfer=c.to(dtype), count=int(m.sum()),
        box=(int(rows[0]), int(cols[0]), int(rows[-1]) + 1, int(cols[-1]) + 1))


#: The soft silhouette is evaluated up to this many ``softness`` outside the capsules.
_SOFT_REACH = 12.0


def _project(capsules: Capsules, camera: PinholeCamera) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    starts = camera.to_camera(capsules.start)
    ends = camera.to_camera(capsules.end)
    out = [project_capsules(starts[b], ends[b], capsules.radius[b], camera.fx, camera.fy, camera.cx, camera.cy)
           for b in range(starts.shape[0])]
    return tuple(torch.stack(x) for x in zip(*out))  # type: ignore[return-value]


def silhouette_residuals(
    capsules: Capsules,
    camera: PinholeCamera,
    target: SilhouetteTarget | Any,
    chamfer: Any = None,
    *,
    a: float = 0.6,
    grid_step: int = 4,
    softness: float = 1.0,
) -> torch.Tensor:
    """Per-pixel residuals of the silhouette coverage term E_c (paper Eq. 3).

    ``r(p) = (a S_M(p) C_I(p) + (1 - a) S_I(p) C_M(p)) / sqrt(|S_I|)`` where

    * ``S_I``, ``C_I``: the image mask and its chamfer map (``target``);
    * ``C_M = max(sd, 0)``: the distance to the model silhouette, from the signed
      distance ``sd`` of each pixel to the projected capsules
      (:func:`capsule_signed_distance`, exact on a grid every ``grid_step`` pixels
      and bilinear in between; the paper's "grid of values");
    * ``S_M = sigmoid(-sd / softness)``: a soft model silhouette made from the same
      capsules, so the ``S_M C_I`` part has a gradient that moves the outline (a hard
      rasterised silhouette would have none); it is 1/2 on the capsules' outline and
      within 1 % of 0 or 1 at ``4.6 * softness`` pixels from it.

    ``a > 0.5`` weighs the model leaving the mask more than the mask being left
    uncovered (person masks are wider than the body); the paper suggests such a
    weighting and gives no value, 0.6 is the default. Dividing by the number of
    mask pixels makes E_c a mean over the person, in px^2, comparable across image
    sizes and people. The capsules must lie in front of the camera.

    Only the window holding the mask and the projected capsules, widened by
    ``12 * softness + 2 * grid_step`` pixels, is evaluated; outside it ``S_M`` is below
    ``6e-6`` and ``S_I`` is 0, and the residuals there are returned as 0.

    Both ``S_M`` and ``C_M`` come from the capsules, so the term is smooth and its
    gradient exact; the price is the capsule body's fit to the mesh: on the default
    body the capsules' outline covers the mesh silhouette with an IoU of about 0.8
    (gaps at the joints, the top of the head, the feet), so against a mask of the
    mesh itself the minimum of E_c lies about 2 cm higher and 3 cm closer to the
    camera than the true translation (a = 0.6).

    Args:
        capsules: :class:`~flowmocap.body.capsules.Capsules`, batch B, world frame.
        camera: the camera (world-to-camera pose and intrinsics).
        target: from :func:`silhouette_target` (build it once per frame), or the
            ``(H, W)`` person mask itself; its size must be the camera's.
        chamfer: with a bare mask, its ``(H, W)`` chamfer map in pixels if already
            computed (:func:`flowmocap.vision.chamfer_map`); ignored for a target.
        a: weight of the ``S_M C_I`` part in ``[0, 1]``.
        grid_step: pixels between exact distance evaluations.
        softness: width of the soft silhouette's edge in pixels (> 0).

    Returns:
        ``(B, H * W)`` residuals in pixels / sqrt(pixel count).

    Raises:
        InputError: size mismatch, bad ``a``, ``grid_step`` or ``softness``, a capsule
            behind the camera.
    """
    B = capsules.start.shape[0]
    target = _as_target(target, chamfer, capsules.start.dtype)
    res, (y0, x0) = _silhouette_window(capsules, camera, target, a, grid_step, softness)
    H, W = target.height, target.width
    full = F.pad(res, (x0, W - x0 - res.shape[2], y0, H - y0 - res.shape[1]))
    return full.reshape(B, H * W)


def _silhouette_checks(camera, target, a, grid_step, softness) -> None:
    """E_c's checks of its settings and of the mask against the camera (InputError)."""
    if (target.height, target.width) != (camera.height, camera.width):
        raise InputError(
            f"the mask is {target.width}x{target.height} but the camera is "
            f"{camera.width}x{camera.height}; give masks of the video's size"
        )
    if not 0.0 <= a <= 1.0:
        raise InputError(f"a must be in [0, 1], got {a}")
    if not softness > 0:
        raise InputError(f"softness must be positive (pixels), got {softness}")
    if int(grid_step) != grid_step or grid_step < 1:
        raise InputError(f"grid_step must be a positive integer (pixels), got {grid_step}")


def _silhouette_setup(capsules, camera, target, a, grid_step, softness):
    """Checks, the projected capsules ``(s, e, r)`` and the window of E_c (the mask's box
    and the capsules' box, plus the soft edge and a grid cell): ``(s, e, r), (y0, x0, y1, x1)``
    with ``y0, x0`` on the grid."""
    _silhouette_checks(camera, target, a, grid_step, softness)
    step = int(grid_step)
    s, e, r = _project(capsules, camera)
    with torch.no_grad():
        lo = torch.minimum(s, e) - r[..., None]
        hi = torch.maximum(s, e) + r[..., None]
        box = (float(lo[..., 0].min()), float(lo[..., 1].min()), float(hi[..., 0].max()), float(hi[..., 1].max()))
    return (s, e, r), _window(box, target, step, softness)


def _window(box: tuple, target, step: int, softness: float) -> tuple[int, int, int, int]:
    """E_c's window ``(y0, x0, y1, x1)`` (``y0, x0`` on the grid): the capsules' pixel box
    ``box = (x_lo, y_lo, x_hi, y_hi)`` and the mask's, plus the soft edge and two cells,
    inside the image."""
    H, W = target.height, target.width
    margin = _SOFT_REACH * softness + 2 * step
    x_lo = min(box[0] - margin, target.box[1])
    y_lo = min(box[1] - margin, target.box[0])
    x_hi = max(box[2] + margin, target.box[3])
    y_hi = max(box[3] + margin, target.box[2])
    x0 = max(0, int(math.floor(max(x_lo, 0.0) / step)) * step)
    y0 = max(0, int(math.floor(max(y_lo, 0.0) / step)) * step)
    x1 = min(W, max(x0 + 1, int(math.ceil(min(x_hi, W)))))
    y1 = min(H, max(y0 + 1, int(math.ceil(min(y_hi, H)))))
    return y0, x0, y1, x1


def _silhouette_window(capsules, camera, target, a, grid_step, softness):
    """Residuals of E_c on the window that holds the mask and the model (see
    :func:`silhouette_residuals`): ``(B, h, w)`` and the window's corner ``(y0, x0)``."""
    (s, e, r), (y0, x0, y1, x1) = _silhouette_setup(capsules, camera, target, a, grid_step, softness)
    sd = capsule_signed_distance(s, e, r, y1 - y0, x1 - x0, int(grid_step), origin=(y0, x0))  # (B, h, w)
    mask = target.mask[y0:y1, x0:x1].to(sd.dtype)
    cham = target.chamfer[y0:y1, x0:x1].to(sd.dtype)
    soft = torch.sigmoid(-sd / softness)
    res = (a * soft * cham + (1.0 - a) * mask * torch.relu(sd)) / math.sqrt(target.count)
    return res, (y0, x0)


@njit(cache=True, nogil=True, error_model="numpy")
def _coverage_energy_kernel(grid, step, mask, cham, a, softness, scale, energy, grad):
    """E_c of :func:`silhouette_energy` and its gradient w.r.t. the exact distance samples
    in one pass: for each pixel ``(v, u)`` of the ``mask``/``cham`` window, ``sd`` is the
    bilinear interpolation of ``grid (B, gh, gw)`` at ``(v / step, u / step)`` (what
    :func:`~flowmocap.render.capsules.capsule_signed_distance` gives), the residual is
    ``scale (a sigmoid(-sd / softness) cham + (1 - a) mask max(sd, 0))`` and ``energy[b]``
    its sum of squares; ``grad (B, gh, gw)`` (zeroed by the caller) receives
    ``d energy[b] / d grid[b]``. float64 throughout."""
    B = grid.shape[0]
    h, w = mask.shape
    inv_step = 1.0 / step
    inv_soft = 1.0 / softness
    for b in range(B):
        total = 0.0
        for i in range((h + step - 1) // step):  # one grid cell at a time: its 4 samples
            for j in range((w + step - 1) // step):
                g00 = grid[b, i, j]
                g01 = grid[b, i, j + 1]
                g10 = grid[b, i + 1, j]
                g11 = grid[b, i + 1, j + 1]
                d00 = d01 = d10 = d11 = 0.0
                for v in range(i * step, min(i * step + step, h)):
                    fy = (v - i * step) * inv_step
                    for u in range(j * step, min(j * step + step, w)):
                        fx = (u - j * step) * inv_step
                        w00 = (1.0 - fy) * (1.0 - fx)
                        w01 = (1.0 - fy) * fx
                        w10 = fy * (1.0 - fx)
                        w11 = fy * fx
                        sd = w00 * g00 + w01 * g01 + w10 * g10 + w11 * g11
                        c = cham[v, u]
                        m = mask[v, u]
                        res = 0.0
                        dres = 0.0
                        x = -sd * inv_soft
                        if c != 0.0 and x > -40.0:  # S_M C_I: C_I is 0 in the mask, S_M < 5e-18 past 40 softness
                            if x >= 0.0:
                                soft = 1.0 / (1.0 + math.exp(-x))
                            else:
                                z = math.exp(x)
                                soft = z / (1.0 + z)
                            res = a * soft * c
                            dres = -a * c * soft * (1.0 - soft) * inv_soft
                        if sd > 0.0:  # C_M = max(sd, 0); no gradient at 0, as torch's relu
                            res += (1.0 - a) * m * sd
                            dres += (1.0 - a) * m
                        res *= scale
                        total += res * res
                        g = 2.0 * res * scale * dres
                        d00 += g * w00
                        d01 += g * w01
                        d10 += g * w10
                        d11 += g * w11
                grad[b, i, j] += d00
                grad[b, i, j + 1] += d01
                grad[b, i + 1, j] += d10
                grad[b, i + 1, j + 1] += d11
        energy[b] = total


class _CoverageEnergy(torch.autograd.Function):
    """E_c ``(B,)`` from the exact distance samples ``grid (B, gh, gw)``, value and gradient
    in one compiled pass (:func:`_coverage_energy_kernel`): the interpolated distance map
    and the per-pixel residuals are never made as tensors."""

    @staticmethod
    def forward(ctx, grid, mask, cham, step, a, softness, scale):  # noqa: D102
        g64 = grid.detach().to(torch.float64).numpy()
        energy = np.zeros(g64.shape[0])
        grad = np.zeros_like(g64)
        _coverage_energy_kernel(g64, step, mask, cham, a, softness, scale, energy, grad)
        ctx.save_for_backward(torch.from_numpy(grad).to(dtype=grid.dtype, device=grid.device))
        return torch.from_numpy(energy).to(dtype=grid.dtype, device=grid.device)

    @staticmethod
    def backward(ctx, grad_out):  # noqa: D102
        (grad,) = ctx.saved_tensors
        return grad_out[:, None, None] * grad, None, None, None, None, None, None


def silhouette_energy(
    capsules: Capsules,
    camera: PinholeCamera,
    target: SilhouetteTarget | Any,
    chamfer: Any = None,
    *,
    a: float = 0.6,
    grid_step: int = 4,
    softness: float = 1.0,
) -> torch.Tensor:
    """E_c: sum of squared :func:`silhouette_residuals`, ``(B,)`` in px^2 per mask pixel.

    The same arithmetic as the residuals (in float64, returned in the capsules' dtype),
    computed with its gradient in one compiled pass over the window from the exact
    distance samples (:func:`~flowmocap.render.capsules.capsule_distance_grid`), without
    making the interpolated map or the residuals as tensors: what the tracker evaluates.

    Raises:
        InputError: the capsules are not on the CPU (the distance samples and the coverage
            pass are compiled CPU code).
    """
    if capsules.start.device.type != "cpu":
        raise InputError(f"silhouette_energy runs on the CPU; the capsules are on {capsules.start.device}: "
                         "move the body's tensors there with .cpu() first.")
    target = _as_target(target, chamfer, capsules.start.dtype)
    _silhouette_checks(camera, target, a, grid_step, softness)
    return energy_with_gradient(lambda s, e, r: _capsule_silhouette(s, e, r, camera, target, int(grid_step), float(a),
                                                                    float(softness)),
                                capsules.start, capsules.end, capsules.radius)


def _silhouette_energy_composed(capsules, camera, target, a, grid_step, softness) -> torch.Tensor:
    """:func:`silhouette_energy` from its torch pieces (projection, window, exact samples)
    and the compiled coverage pass: the definition :class:`_CapsuleSilhouette` follows."""
    (s, e, r), (y0, x0, y1, x1) = _silhouette_setup(capsules, camera, target, a, grid_step, softness)
    grid = capsule_distance_grid(s, e, r, y1 - y0, x1 - x0, int(grid_step), origin=(y0, x0))
    mask = target.mask[y0:y1, x0:x1].detach().cpu().numpy()
    cham = target.chamfer[y0:y1, x0:x1].detach().cpu().numpy()
    return _CoverageEnergy.apply(grid, mask, cham, int(grid_step), float(a), float(softness),
                                 1.0 / math.sqrt(target.count))


def _capsule_silhouette(start, end, r3, camera, target, step, a, softness):
    """E_c ``(B,)`` and its gradients from world capsules ``start, end (B, K, 3)`` and
    ``r3 (B, K)`` (float64 arrays): the steps of :func:`_silhouette_energy_composed` (to the
    camera, projection, window, exact distance samples, coverage) in NumPy and the compiled
    passes, and the gradient by the chain rule back through each, so that
    :func:`silhouette_energy` is one autograd node instead of some forty."""
    R = np.asarray(camera.R, np.float64)
    t = np.asarray(camera.t, np.float64)
    ps = start @ R.T + t  # (B, K, 3) camera axes
    pe = end @ R.T + t
    if not (np.isfinite(ps).all() and np.isfinite(pe).all() and np.isfinite(r3).all()):
        raise InputError("the capsules hold NaN or infinite values")
    if (np.minimum(ps[..., 2], pe[..., 2]) <= r3).any():
        raise InputError("a capsule is not in front of the camera (end point depth <= radius)")
    f = np.array([camera.fx, camera.fy])
    c = np.array([camera.cx, camera.cy])
    sq = math.sqrt(camera.fx * camera.fy)
    a_px = f * ps[..., :2] / ps[..., 2:3] + c
    b_px = f * pe[..., :2] / pe[..., 2:3] + c
    zmid = 0.5 * (ps[..., 2] + pe[..., 2])
    r_px = r3 * sq / zmid
    lo = np.minimum(a_px, b_px) - r_px[..., None]
    hi = np.maximum(a_px, b_px) + r_px[..., None]
    y0, x0, y1, x1 = _window((float(lo[..., 0].min()), float(lo[..., 1].min()), float(hi[..., 0].max()),
                              float(hi[..., 1].max())), target, step, softness)
    h, w = y1 - y0, x1 - x0
    gh, gw = (h - 1) // step + 2, (w - 1) // step + 2
    gy = np.arange(gh) * step + (y0 + 0.5)
    gx = np.arange(gw) * step + (x0 + 0.5)
    pts = np.stack(np.meshgrid(gx, gy, indexing="xy"), axis=-1).reshape(-1, 2)
    d = b_px - a_px
    inv = 1.0 / np.maximum((d * d).sum(-1), 1e-12)
    B = ps.shape[0]
    best = np.empty((B, pts.shape[0]))
    arg = np.empty((B, pts.shape[0]), dtype=np.int64)
    grid_signed_distance_kernel(pts, np.ascontiguousarray(a_px), np.ascontiguousarray(d), inv,
                                np.ascontiguousarray(r_px), best, arg)
    grid = best.reshape(B, gh, gw)
    mask = target.mask[y0:y1, x0:x1].detach().cpu().numpy()
    cham = target.chamfer[y0:y1, x0:x1].detach().cpu().numpy()
    energy = np.zeros(B)
    g_grid = np.zeros_like(grid)
    _coverage_energy_kernel(grid, step, mask, cham, a, softness, 1.0 / math.sqrt(target.count), energy, g_grid)
    # back through the exact samples, the projection and the camera
    ga, gb, gr = np.zeros(a_px.shape), np.zeros(b_px.shape), np.zeros(r_px.shape)
    grid_signed_distance_grad_kernel(pts, np.ascontiguousarray(a_px), np.ascontiguousarray(b_px), arg,
                                     g_grid.reshape(B, -1), ga, gb, gr)
    dz = -gr * r_px / zmid * 0.5  # r_px = r sq / zmid: d/dz of either end
    grads = []
    for g2, pc in ((ga, ps), (gb, pe)):  # p_px = f p_xy / p_z + c
        g3 = np.empty_like(pc)
        g3[..., :2] = g2 * f / pc[..., 2:3]
        g3[..., 2] = -(g2 * f * pc[..., :2]).sum(-1) / pc[..., 2] ** 2 + dz
        grads.append(g3 @ R)  # p = R x + t
    grads.append(gr * sq / zmid)
    return energy, grads


def _bilinear(image: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of ``image (H, W)`` at points ``xy (N, 2)`` in pixels (pixel centres
    at integer + 0.5). Points outside the image take the border value plus their distance
    to the image, so the result keeps growing (with a gradient) away from the image."""
    H, W = image.shape
    x = xy[:, 0] - 0.5
    y = xy[:, 1] - 0.5
    xc = x.clamp(0.0, W - 1.0)
    yc = y.clamp(0.0, H - 1.0)
    outside = torch.sqrt((x - xc) ** 2 + (y - yc) ** 2 + 1e-12) - 1e-6
    with torch.no_grad():
        x0 = xc.floor().clamp(max=W - 2).long() if W > 1 else torch.zeros_like(xc, dtype=torch.long)
        y0 = yc.floor().clamp(max=H - 2).long() if H > 1 else torch.zeros_like(yc, dtype=torch.long)
        x1 = (x0 + 1).clamp(max=W - 1)
        y1 = (y0 + 1).clamp(max=H - 1)
    fx = xc - x0.to(xc.dtype)
    fy = yc - y0.to(yc.dtype)
    img = image.to(xy.dtype)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bottom * fy + outside.clamp(min=0.0)


def mesh_silhouette_residuals(
    verts_px: torch.Tensor,
    depth: Any,
    faces: Any,
    target: SilhouetteTarget | Any,
    *,
    a: float = 0.6,
    grid_step: int = 4,
    margin: float = 0.5,
    cull_backfaces: bool = True,
    raster: Any = None,
) -> torch.Tensor:
    """Residuals of E_c with the model silhouette taken from the mesh itself.

    Two parts, each a mean in px^2 (so their weights ``a`` and ``1 - a`` mean what the
    paper's do):

    * model outside the mask (the paper's ``S_M C_I``): every vertex of the body, seen
      or hidden, projects inside the person's silhouette, so each vertex ``v`` gets
      ``sqrt(a / V) * max(C_I(x_v) - margin, 0)`` with ``C_I`` the image chamfer map
      sampled bilinearly (``margin`` = 0.5 px: a vertex on the true outline lies half a
      pixel from the centre of the nearest mask pixel);
    * mask not covered by the model (``S_I C_M``): every mask pixel ``p`` on a grid of
      ``grid_step`` pixels whose centre no triangle covers gets
      ``sqrt((1 - a) / n) * |p - x_nn(p)|``, the distance to the nearest projected vertex
      (``n``: mask pixels on the grid). The rasterised coverage and the nearest vertex
      are piecewise constant in the vertices (no gradient flows through them).

    Unlike the capsule form (:func:`silhouette_residuals`) this is zero at the true
    pose for a mask of the body itself up to half a pixel, so it does not bias the fit.

    Args:
        verts_px: ``(V, 2)`` projected vertices in pixels (torch; the gradient flows here).
        depth: ``(V,)`` camera-space depths in metres (for the rasteriser; no gradient).
        faces: ``(F, 3)`` faces or a :class:`~flowmocap.render.Faces`.
        target: from :func:`silhouette_target` (or an ``(H, W)`` mask).
        a: weight of the model-outside-the-mask part, in ``[0, 1]``.
        grid_step: pixels between the mask samples of the second part.
        margin: pixels of chamfer distance tolerated (see above).
        cull_backfaces: rasterise front faces only (same coverage, faster).
        raster: the mesh already rasterised at these vertices and depths with these
            ``cull_backfaces`` (e.g. by the flow term, :class:`~flowmocap.render.flow.PendingFlow`),
            or None to rasterise here.

    Returns:
        ``(V + n_uncovered,)`` residuals in px (scaled as above).

    Raises:
        InputError: wrong shapes, bad ``a`` or ``grid_step``.
    """
    target, V, uncovered, nn, n = _mesh_silhouette_setup(verts_px, depth, faces, target, a, grid_step,
                                                         cull_backfaces, raster)
    inside = torch.relu(_bilinear(target.chamfer, verts_px) - margin) * math.sqrt(a / V)
    if len(uncovered) == 0 or a == 1.0:
        return inside
    p = torch.as_tensor(uncovered + 0.5, dtype=verts_px.dtype)
    d = torch.sqrt(((p - verts_px[torch.as_tensor(nn)]) ** 2).sum(-1) + 1e-12)
    return torch.cat([inside, d * math.sqrt((1.0 - a) / n)])


def _mesh_silhouette_setup(verts_px, depth, faces, target, a, grid_step, cull_backfaces, raster):
    """What both forms of the mesh E_c need: the checked target, ``V``, the uncovered mask
    samples ``(m, 2)`` int (x, y), the index of each one's nearest vertex ``(m,)`` and ``n``
    (mask samples on the grid). Without ``raster`` the mesh is rasterised into this
    thread's scratch buffers (only its coverage is read, at once)."""
    from scipy.spatial import cKDTree

    from flowmocap.render._checks import check_faces, check_points, check_vector
    from flowmocap.render.raster import rasterize_scratch

    target = _as_target(target, None, verts_px.dtype)
    if verts_px.ndim != 2 or verts_px.shape[1] != 2:
        raise InputError(f"verts_px must be (V, 2), got {tuple(verts_px.shape)}")
    if not 0.0 <= a <= 1.0:
        raise InputError(f"a must be in [0, 1], got {a}")
    if int(grid_step) != grid_step or grid_step < 1:
        raise InputError(f"grid_step must be a positive integer (pixels), got {grid_step}")
    V = verts_px.shape[0]
    H, W = target.height, target.width
    step = int(grid_step)
    grid = _mask_grid(target, step)
    n = max(len(grid), 1)
    with torch.no_grad():
        xy = check_points(verts_px.detach().cpu().numpy().astype(np.float64), "verts_px", 2)
        if raster is None:
            z = depth.detach().cpu().numpy() if isinstance(depth, torch.Tensor) else np.asarray(depth)
            raster = rasterize_scratch(xy, check_vector(z, "depth", V), check_faces(faces, V), H, W,
                                       bool(cull_backfaces), 1e-3)
        face_id = raster.face_id
        uncovered = grid[face_id[grid[:, 1], grid[:, 0]] < 0]
    nn = np.empty(len(uncovered), dtype=np.int64)
    if len(uncovered) and a < 1.0:
        queries = uncovered + 0.5
        if len(queries) <= _BRUTE_FORCE_QUERIES:  # a k-d tree of the body costs more than a few scans
            _nearest_points(queries, xy, nn)
        else:
            nn = cKDTree(xy).query(queries)[1].astype(np.int64)
    return target, V, uncovered, nn, n


@njit(cache=True, nogil=True, error_model="numpy")
def _mesh_silhouette_kernel(chamfer, xy, margin, wa, queries, nn, wb, grad):
    """The mesh E_c and its gradient w.r.t. ``xy`` (added to ``grad (V, 2)``): ``wa`` times
    the sum over vertices of ``max(C(x_v) - margin, 0)^2`` (``C``: :func:`_bilinear` of the
    chamfer map, its clamping and its growth outside the image included) plus ``wb`` times
    the sum over the uncovered samples ``queries (m, 2)`` (pixel centres) of the squared
    distance to their nearest vertex ``nn`` (plus 1e-12, as the residual form's)."""
    H, W = chamfer.shape
    energy = 0.0
    for v in range(xy.shape[0]):
        x = xy[v, 0] - 0.5
        y = xy[v, 1] - 0.5
        xc = min(max(x, 0.0), W - 1.0)
        yc = min(max(y, 0.0), H - 1.0)
        ox = x - xc
        oy = y - yc
        root = math.sqrt(ox * ox + oy * oy + 1e-12)
        out = root - 1e-6
        x0 = min(int(math.floor(xc)), W - 2) if W > 1 else 0
        y0 = min(int(math.floor(yc)), H - 2) if H > 1 else 0
        x1 = min(x0 + 1, W - 1)
        y1 = min(y0 + 1, H - 1)
        fx = xc - x0
        fy = yc - y0
        c00 = chamfer[y0, x0]
        c01 = chamfer[y0, x1]
        c10 = chamfer[y1, x0]
        c11 = chamfer[y1, x1]
        top = c00 * (1.0 - fx) + c01 * fx
        bottom = c10 * (1.0 - fx) + c11 * fx
        r = top * (1.0 - fy) + bottom * fy + max(out, 0.0) - margin
        if r <= 0.0:
            continue
        energy += wa * r * r
        g = 2.0 * wa * r
        gx = 0.0
        gy = 0.0
        if 0.0 <= x <= W - 1.0:  # torch's clamp passes the gradient at its bounds too
            gx += (c01 - c00) * (1.0 - fy) + (c11 - c10) * fy
        if 0.0 <= y <= H - 1.0:
            gy += bottom - top
        if out >= 0.0:
            gx += ox / root
            gy += oy / root
        grad[v, 0] += g * gx
        grad[v, 1] += g * gy
    for q in range(queries.shape[0]):
        k = nn[q]
        dx = xy[k, 0] - queries[q, 0]
        dy = xy[k, 1] - queries[q, 1]
        energy += wb * (dx * dx + dy * dy + 1e-12)
        grad[k, 0] += 2.0 * wb * dx
        grad[k, 1] += 2.0 * wb * dy
    return energy


#: Up to this many uncovered mask samples, :func:`mesh_silhouette_residuals` finds their
#: nearest vertices by scanning all of them (about 1.4 ms for a k-d tree of the body's
#: 6890 vertices, against about 6 us per sample scanned).
_BRUTE_FORCE_QUERIES = 150


@njit(cache=True, nogil=True)
def _nearest_points(queries, points, out):
    """``out[q]``: the index of the point of ``points (N, 2)`` nearest to ``queries[q]``
    (the first on ties), by scanning them all."""
    for q in range(queries.shape[0]):
        best = np.inf
        arg = 0
        for n in range(points.shape[0]):
            dx = points[n, 0] - queries[q, 0]
            dy = points[n, 1] - queries[q, 1]
            d = dx * dx + dy * dy
            if d < best:
                best = d
                arg = n
        out[q] = arg


def _mask_grid(target: SilhouetteTarget, step: int) -> np.ndarray:
    """``(n, 2)`` integer ``(x, y)`` of the mask pixels on a ``step``-pixel grid (cached)."""
    cache = getattr(target, "_grid_cache", None)
    if cache is not None and cache[0] == step:
        return cache[1]
    m = target.mask.detach().cpu().numpy() > 0
    ys, xs = np.nonzero(m[::step, ::step])
    grid = np.stack([xs * step, ys * step], axis=1).astype(np.int64)
    object.__setattr__(target, "_grid_cache", (step, grid))
    return grid


def mesh_silhouette_energy(verts_px: torch.Tensor, depth: Any, faces: Any, target: SilhouetteTarget | Any, *,
                           a: float = 0.6, grid_step: int = 4, margin: float = 0.5, cull_backfaces: bool = True,
                           raster: Any = None) -> torch.Tensor:
    """E_c from the mesh: the sum of squared :func:`mesh_silhouette_residuals` (same
    arguments), a 0-d tensor in px^2 of ``verts_px``'s dtype, computed with its gradient
    w.r.t. ``verts_px`` in one compiled float64 pass (one autograd node)."""
    target, V, uncovered, nn, n = _mesh_silhouette_setup(verts_px, depth, faces, target, a, grid_step,
                                                         cull_backfaces, raster)
    chamfer = getattr(target, "_chamfer64", None)
    if chamfer is None:
        chamfer = np.ascontiguousarray(target.chamfer.detach().cpu().numpy(), dtype=np.float64)
        object.__setattr__(target, "_chamfer64", chamfer)
    queries = (uncovered + 0.5).astype(np.float64) if a < 1.0 else np.zeros((0, 2))
    wb = (1.0 - a) / n

    def compute(xy):
        grad = np.zeros_like(xy)
        e = _mesh_silhouette_kernel(chamfer, xy[0], float(margin), a / V, queries, nn, wb, grad[0])
        return np.array([e]), [grad]

    return energy_with_gradient(compute, verts_px.unsqueeze(0))[0]


# ---------------------------------------------------------------------- 2D keypoints


def keypoint_residuals(
    joints2d_pred: torch.Tensor,
    joints2d_obs: Any,
    confidence: Any = None,
    sigma: float = 100.0,
) -> torch.Tensor:
    """Robust 2D joint residuals (SMPLify's Geman-McClure data term), per coordinate.

    The cost of a residual ``x`` (pixels, per coordinate) is
    ``c * sigma^2 x^2 / (sigma^2 + x^2)`` (quadratic for ``|x| << sigma``, saturating at
    ``c sigma^2`` for outliers); the returned residual is its signed square root
    ``sqrt(c) * sigma * x / sqrt(sigma^2 + x^2)``, smooth through 0.

    Args:
        joints2d_pred: ``(B, J, 2)`` projected model joints, pixels.
        joints2d_obs: ``(J, 2)`` or ``(B, J, 2)`` observed joints, pixels; NaN marks a
            missing joint (its confidence becomes 0).
        confidence: ``(J,)`` or ``(B, J)`` non-negative weights (default 1).
        sigma: Geman-McClure scale in pixels (SMPLify uses 100).

    Returns:
        ``(B, 2 J)`` residuals in pixels, ``[x0, y0, x1, y1, ...]``.
    """
    if not isinstance(joints2d_pred, torch.Tensor) or joints2d_pred.dim() != 3 or joints2d_pred.shape[-1] != 2:
        raise InputError(f"joints2d_pred must be a (B, J, 2) tensor, got {getattr(joints2d_pred, 'shape', None)}")
    B, J, _ = joints2d_pred.shape
    obs = _like(joints2d_obs, joints2d_pred)
    if obs.shape not in ((J, 2), (B, J, 2)):
        raise InputError(f"joints2d_obs must have shape ({J}, 2) or ({B}, {J}, 2), got {tuple(obs.shape)}")
    obs = obs.expand(B, J, 2)
    conf = torch.ones(B, J, dtype=obs.dtype, device=obs.device) if confidence is None else _like(confidence, obs)
    if conf.shape not in ((J,), (B, J)):
        raise InputError(f"confidence must have shape ({J},) or ({B}, {J}), got {tuple(conf.shape)}")
    conf = conf.expand(B, J)
    if (conf < 0).any() or not torch.isfinite(conf).all():
        raise InputError("confidence must be finite and non-negative")
    if not sigma > 0:
        raise InputError(f"sigma must be positive (pixels), got {sigma}")
    missing = ~torch.isfinite(obs).all(-1)
    conf = torch.where(missing, torch.zeros_like(conf), conf)
    x = joints2d_pred - torch.where(missing[..., None], joints2d_pred.detach(), obs)
    res = torch.sqrt(conf)[..., None] * sigma * x / torch.sqrt(sigma * sigma + x * x)
    return res.reshape(B, 2 * J)


def keypoint_energy(
    joints2d_pred: torch.Tensor, joints2d_obs: Any, confidence: Any = None, sigma: float = 100.0
) -> torch.Tensor:
    """Robust 2D joint energy, ``(B,)`` in px^2: sum of squared :func:`keypoint_residuals`."""
    return _sum_sq(keypoint_residuals(joints2d_pred, joints2d_obs, confidence, sigma))


# ------------------------------------------------------------- 3D limb directions

#: ``(parent, child)`` SMPL joint indices of the limbs whose direction in depth a
#: detector's 3D joints inform: upper arms, forearms, thighs, shins (left, right).
DEPTH_LIMBS: tuple[tuple[int, int], ...] = ((16, 18), (17, 19), (18, 20), (19, 21), (1, 4), (2, 5), (4, 7), (5, 8))
_DEPTH_LIMBS = np.array(DEPTH_LIMBS, np.int64)


def _detected_joints(joints_cam: Any, joints3d_obs: Any, confidence: Any,
                     dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """The checked inputs of the terms on a detector's 3D joints: ``joints_cam`` must be a
    ``(B, 24, 3)`` tensor; returns ``joints3d_obs (24, 3)`` and ``confidence (24,)`` as
    tensors of ``dtype``. InputError for wrong shapes."""
    if not isinstance(joints_cam, torch.Tensor) or joints_cam.dim() != 3 or joints_cam.shape[1:] != (NUM_JOINTS, 3):
        raise InputError(f"joints_cam must be a (B, 24, 3) tensor, got {getattr(joints_cam, 'shape', None)}")
    obs = torch.as_tensor(np.asarray(joints3d_obs, np.float64) if not isinstance(joints3d_obs, torch.Tensor)
                          else joints3d_obs, dtype=dtype)
    conf = torch.as_tensor(np.asarray(confidence, np.float64) if not isinstance(confidence, torch.Tensor)
                           else confidence, dtype=dtype)
    if obs.shape != (NUM_JOINTS, 3) or conf.shape != (NUM_JOINTS,):
        raise InputError(f"joints3d_obs must be (24, 3) and confidence (24,); got {tuple(obs.shape)}, "
                         f"{tuple(conf.shape)}")
    return obs, conf


def limb_depth_residuals(joints_cam: torch.Tensor, joints3d_obs: Any, confidence: Any, sigma: float = 0.3) -> torch.Tensor:
    """Robust residuals between the depth components of the model's and a detector's
    limb directions (``E_d``, an extension of the paper).

    For each limb of :data:`DEPTH_LIMBS`, ``x = u_z - o_z`` with ``u`` and ``o`` the unit
    vectors from the limb's parent joint to its child joint, of the model
    (``joints_cam``) and of the detector (``joints3d_obs``), both in the camera's axes
    (z away from the camera). ``u_z`` is the sine of the limb's angle out of the image
    plane, so ``x`` is free of the detector's scale and body proportions and says only
    whether the limb points nearer or further, the one thing flow and silhouettes cannot
    tell. The cost of ``x`` is Geman-McClure's, ``c sigma^2 x^2 / (sigma^2 + x^2)``
    (``c``: the lower confidence of the limb's two joints); the returned residual is its
    signed square root.

    Args:
        joints_cam: ``(B, 24, 3)`` model joints in camera coordinates (metres; any
            translation, only differences are used).
        joints3d_obs: ``(24, 3)`` detected joints in the camera's axes (any origin and scale).
        confidence: ``(24,)`` per joint in ``[0, 1]`` (0: not detected).
        sigma: scale of the robust cost (unitless, a sine; a limb the detector sees
            mirrored in depth, ``|x|`` up to 2, saturates).

    Returns:
        ``(B, L)`` residuals, ``L = len(DEPTH_LIMBS)``.
    """
    obs, conf = _detected_joints(joints_cam, joints3d_obs, confidence, joints_cam.dtype)
    if not sigma > 0:
        raise InputError(f"sigma must be > 0; got {sigma!r}")
    pa = [p for p, _ in DEPTH_LIMBS]
    ch = [c for _, c in DEPTH_LIMBS]
    o = obs[ch] - obs[pa]
    on = o.norm(dim=-1)
    ok = (on > 1e-6) & torch.isfinite(on)
    c = torch.where(ok, torch.minimum(conf[ch], conf[pa]).clamp(0.0, 1.0), torch.zeros_like(on))
    oz = torch.where(ok, o[:, 2] / on.clamp_min(1e-6), torch.zeros_like(on))
    v = joints_cam[:, ch] - joints_cam[:, pa]
    uz = v[..., 2] / v.norm(dim=-1).clamp_min(1e-9)
    x = uz - oz
    return torch.sqrt(c) * sigma * x / torch.sqrt(sigma * sigma + x * x)


def limb_depth_energy(joints_cam: torch.Tensor, joints3d_obs: Any, confidence: Any, sigma: float = 0.3) -> torch.Tensor:
    """``E_d``: sum of squared :func:`limb_depth_residuals`, ``(B,)`` (unitless)."""
    return _sum_sq(limb_depth_residuals(joints_cam, joints3d_obs, confidence, sigma))


def world_limb_depth_energy(joints_world: torch.Tensor, camera: PinholeCamera, joints3d: tuple,
                            sigma: float = 0.3) -> torch.Tensor:
    """:func:`limb_depth_energy` of world joints ``(B, 24, 3)`` turned into the camera's
    axes (its rotation; directions need no translation), against ``joints3d = (j3d (24,
    3), conf (24,))`` in the camera's axes; ``(B,)``."""
    if not isinstance(joints_world, torch.Tensor) or joints_world.dim() != 3 or \
            joints_world.shape[1:] != (NUM_JOINTS, 3):
        raise InputError(f"joints_world must be a (B, 24, 3) tensor, got {getattr(joints_world, 'shape', None)}")
    obs, conf = _float64(joints3d[0]), _float64(joints3d[1])
    if obs.shape != (NUM_JOINTS, 3) or conf.shape != (NUM_JOINTS,):
        raise InputError(f"joints3d_obs must be (24, 3) and confidence (24,); got {obs.shape}, {conf.shape}")
    if not sigma > 0:
        raise InputError(f"sigma must be > 0; got {sigma!r}")
    pa, ch = _DEPTH_LIMBS[:, 0], _DEPTH_LIMBS[:, 1]
    o = obs[ch] - obs[pa]
    with np.errstate(invalid="ignore"):
        on = np.linalg.norm(o, axis=-1)
        ok = (on > 1e-6) & np.isfinite(on)
    c = np.where(ok, np.clip(np.minimum(conf[ch], conf[pa]), 0.0, 1.0), 0.0)
    oz = np.where(ok, o[:, 2] / np.maximum(np.where(ok, on, 1.0), 1e-6), 0.0)
    # the torch definition (limb_depth_residuals of the joints turned into the camera's axes)
    # in one compiled pass with its gradient (flowmocap.fit.joint_terms)
    return limb_depth_energy_world(joints_world, camera.R, _DEPTH_LIMBS, oz, c, sigma)


# ------------------------------------------------------- 3D joints of a detector

#: Fewest confident detected joints :func:`detector_joints_residuals` aligns and compares
#: (a similarity in 3D needs 3 points off one line; 4 keep it from a near-degenerate fit).
MIN_DETECTOR_JOINTS = 4


def pseudo_huber(r2: torch.Tensor, scale: float) -> torch.Tensor:
    """The pseudo-Huber (Charbonnier) cost of squared distances ``r2``:
    ``rho = 2 s^2 (sqrt(1 + r2 / s^2) - 1)``, ``~ r2`` for ``r << s``, ``~ 2 s r`` for
    ``r >> s`` (unit of ``r2``; ``scale`` s in the unit of ``r``). Unlike Geman-McClure it
    never saturates: its slope tends to ``2 s`` per unit of distance, so a large error
    keeps a pull. ``r2`` may have any shape; the result has the same shape and dtype."""
    return r2 * (2.0 / (1.0 + torch.sqrt(1.0 + r2 / (scale * scale))))


def detector_joints_residuals(joints_cam: torch.Tensor, joints3d_obs: Any, confidence: Any,
                              scale: float = 0.1) -> torch.Tensor:
    """Residuals between the model's joints and a detector's 3D joints after a per-frame
    similarity alignment, with a robust cost that keeps pulling when the error is large
    (an extension of the paper, against the monocular depth ambiguity).

    The detected joints ``o_j`` are aligned onto the model's ``x_j`` by the
    confidence-weighted similarity (scale, rotation, translation; Umeyama's closed form,
    :func:`flowmocap.geometry.procrustes.similarity_procrustes`) that minimises
    ``sum_j c_j |x_j - (s R o_j + t)|^2``: the comparison is root-relative (translation
    free: centred on the confident joints' weighted mean rather than on one joint),
    free of the detector's scale and of its global orientation, so it says only how
    the body is bent, e.g. a knee or elbow bent towards the camera instead of away. The
    alignment is part of the function and is differentiated through (exact gradient;
    the 3x3 SVD is taken in float64). The cost of each joint's error ``d_j = x_j - (s R
    o_j + t)`` is ``c_j rho(|d_j|)`` with ``rho`` the pseudo-Huber cost
    :func:`pseudo_huber` at ``scale`` (quadratic below ``scale``, linear above, never
    saturating: unlike ``E_d`` it still pulls a limb that has flipped). The residual of
    a joint is the 3-vector ``sqrt(c_j) d_j sqrt(rho / |d_j|^2)``, smooth through 0,
    whose squared norm is ``c_j rho(|d_j|)``.

    Args:
        joints_cam: ``(B, 24, 3)`` model joints in the camera's axes (metres; any origin:
            the alignment's translation absorbs it; world joints work alike when the
            detector's joints are in world axes).
        joints3d_obs: ``(24, 3)`` detected joints in the camera's axes (any origin, any
            scale); non-finite joints count as missing.
        confidence: ``(24,)`` per joint, clipped to ``[0, 1]`` (0: not detected).
        scale: pseudo-Huber scale in metres: errors below it cost their square, errors
            above it about ``2 scale |d|``.

    Returns:
        ``(B, 72)`` residuals in metres, ``[x0, y0, z0, x1, ...]``; all zero when fewer
        than :data:`MIN_DETECTOR_JOINTS` joints are confident (nothing to align).

    Raises:
        InputError: wrong shapes, negative or non-finite confidences, ``scale <= 0``.
    """
    obs, conf = _detected_joints(joints_cam, joints3d_obs, confidence, torch.float64)
    if not torch.isfinite(conf).all() or (conf < 0).any():
        raise InputError("confidence must be finite and non-negative (0: joint not detected)")
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise InputError(f"scale must be a positive number of metres; got {scale!r}")
    B = joints_cam.shape[0]
    ok = torch.isfinite(obs).all(-1)
    c = torch.where(ok, conf.clamp(0.0, 1.0), torch.zeros_like(conf))
    if int((c > 0).sum()) < MIN_DETECTOR_JOINTS:
        return joints_cam.new_zeros(B, 3 * NUM_JOINTS) * joints_cam.reshape(B, -1)
    obs = torch.where(ok[:, None], obs, torch.zeros_like(obs))
    x = joints_cam.to(torch.float64)
    aligned = similarity_procrustes(obs.expand(B, NUM_JOINTS, 3), x, weights=c)[0]
    d = x - aligned
    r2 = (d * d).sum(-1, keepdim=True)
    res = torch.sqrt(c)[:, None] * d * torch.sqrt(2.0 / (1.0 + torch.sqrt(1.0 + r2 / (scale * scale))))
    return res.reshape(B, 3 * NUM_JOINTS).to(joints_cam.dtype)


def detector_joints_energy(joints_cam: torch.Tensor, joints3d_obs: Any, confidence: Any,
                           scale: float = 0.1) -> torch.Tensor:
    """Sum of squared :func:`detector_joints_residuals`, ``(B,)`` in m^2:
    ``sum_j c_j rho(|d_j|)``, in one compiled pass with its gradient
    (:func:`flowmocap.fit.aligned_joints.aligned_joints_energy`; the residuals are its
    torch definition and the reference its tests compare with)."""
    obs, c = _aligned_inputs(joints_cam, joints3d_obs, confidence, scale)
    return aligned_joints_energy(joints_cam, obs, c, scale)


def _aligned_inputs(joints_cam, joints3d_obs, confidence, scale) -> tuple[np.ndarray, np.ndarray]:
    """``E_3d``'s checked detections as float64 arrays: ``obs (24, 3)`` (0 where missing)
    and ``c (24,)`` (clipped to ``[0, 1]``, 0 where the joint is missing or not finite)."""
    if not isinstance(joints_cam, torch.Tensor) or joints_cam.dim() != 3 or joints_cam.shape[1:] != (NUM_JOINTS, 3):
        raise InputError(f"joints_cam must be a (B, 24, 3) tensor, got {getattr(joints_cam, 'shape', None)}")
    obs, conf = _float64(joints3d_obs), _float64(confidence)
    if obs.shape != (NUM_JOINTS, 3) or conf.shape != (NUM_JOINTS,):
        raise InputError(f"joints3d_obs must be (24, 3) and confidence (24,); got {obs.shape}, {conf.shape}")
    if not np.isfinite(conf).all() or (conf < 0).any():
        raise InputError("confidence must be finite and non-negative (0: joint not detected)")
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise InputError(f"scale must be a positive number of metres; got {scale!r}")
    ok = np.isfinite(obs).all(-1)
    return np.where(ok[:, None], obs, 0.0), np.where(ok, np.clip(conf, 0.0, 1.0), 0.0)


def world_detector_joints_energy(joints_world: torch.Tensor, camera: PinholeCamera, joints3d: tuple,
                                 scale: float = 0.1) -> torch.Tensor:
    """The per-frame term ``E_3d``: :func:`detector_joints_energy` of world joints ``(B, 24,
    3)`` turned into the camera's axes (its rotation; the alignment absorbs any
    translation) against ``joints3d = (j3d (24, 3), conf (24,))`` in the camera's axes,
    divided by the number of joints with ``conf > 0`` (m^2 per detected joint); ``(B,)``."""
    j3d, conf = joints3d
    obs, c = _aligned_inputs(joints_world, j3d, conf, scale)
    n = max(int((_float64(conf) > 0).sum()), 1)
    return aligned_joints_energy(joints_world, obs, c, scale, rotation=np.asarray(camera.R, np.float64), factor=1.0 / n)


def _float64(v) -> np.ndarray:
    """A tensor or anything array-like as a float64 array."""
    return v.detach().to(torch.float64).numpy() if isinstance(v, torch.Tensor) else np.asarray(v, np.float64)


# ---------------------------------------------------------------------------- priors


def _pose_weights(weights: Any, ref: torch.Tensor, default_root: float, width: int = NUM_POSE) -> torch.Tensor:
    """``(width,)`` weights from None, a scalar, per joint or per component.

    ``width`` is 72 (all joints; None gives 1 and ``default_root`` for the root) or 69
    (joints 1..23; None gives 1).
    """
    joints = width // 3
    if weights is None:
        w = torch.ones(width, dtype=ref.dtype, device=ref.device)
        if width == NUM_POSE:
            w[:3] = default_root
        return w
    w = _like(weights, ref)
    if w.dim() == 0:
        w = w.expand(width)
    elif w.shape == (joints,):
        w = w.repeat_interleave(3)
    elif w.shape != (width,):
        raise InputError(f"weights must be a scalar, ({joints},) per joint or ({width},) per component, "
                         f"got {tuple(w.shape)}")
    if (w < 0).any() or not torch.isfinite(w).all():
        raise InputError("weights must be finite and non-negative")
    return w


def _pose_or_body_pose(x: Any, name: str) -> torch.Tensor:
    """``(B, 72)`` or ``(B, 69)`` (no root) floating tensor; ``(72,)``/``(69,)`` get a batch."""
    if isinstance(x, torch.Tensor) and x.dim() in (1, 2) and x.shape[-1] == NUM_POSE - 3:
        if not x.is_floating_point():
            raise InputError(f"{name} must be floating point, got {x.dtype}")
        return x if x.dim() == 2 else x[None]
    return _pose(x, name)


def pose_prior_residuals(pose: torch.Tensor, ref_pose: Any, weights: Any = None) -> torch.Tensor:
    """Residuals pulling the pose towards a rough reference pose (initialisation).

    ``r_i = sqrt(w_i) (theta_i - theta_ref_i)`` on the raw axis-angle components, a
    quadratic prior as SMPLify's, suited to the small differences a rough manual or
    detected pose leaves.

    Args:
        pose: ``(B, 72)`` axis-angle, radians, or ``(B, 69)``: joints 1..23 only.
        ref_pose: ``(D,)`` or ``(B, D)`` reference pose of the same width D, radians.
        weights: scalar, per joint (``(24,)`` / ``(23,)``) or per component
            (``(72,)`` / ``(69,)``); default: 1 for every joint, 0 for the root
            (whose orientation the 2D joints decide).

    Returns:
        ``(B, D)`` residuals in radians.
    """
    pose = _pose_or_body_pose(pose, "pose")
    ref = _pose_or_body_pose(_like(ref_pose, pose), "ref_pose")
    if ref.shape[1] != pose.shape[1] or ref.shape[0] not in (1, pose.shape[0]):
        raise InputError(f"ref_pose has shape {tuple(ref.shape)}, pose has {tuple(pose.shape)}")
    return torch.sqrt(_pose_weights(weights, pose, 0.0, pose.shape[1])) * (pose - ref)


def pose_prior_energy(pose: torch.Tensor, ref_pose: Any, weights: Any = None) -> torch.Tensor:
    """Sum of squared :func:`pose_prior_residuals`, ``(B,)`` in rad^2."""
    return _sum_sq(pose_prior_residuals(pose, ref_pose, weights))


def shape_prior_residuals(betas: torch.Tensor) -> torch.Tensor:
    """Residuals towards the mean shape: the shape coefficients themselves.

    Args:
        betas: ``(B, S)`` shape coefficients (unit: standard deviations of the model's
            shape space for SMPL-format models).

    Returns:
        ``(B, S)``.
    """
    if not isinstance(betas, torch.Tensor) or betas.dim() not in (1, 2):
        raise InputError(f"betas must be a (B, S) tensor, got {getattr(betas, 'shape', None)}")
    return betas if betas.dim() == 2 else betas[None]


def shape_prior_energy(betas: torch.Tensor) -> torch.Tensor:
    """``||betas||^2`` per body, ``(B,)``."""
    return _sum_sq(shape_prior_residuals(betas))


def temporal_residuals(
    pose: torch.Tensor, prev_pose: Any, weights: Any = None, include_root: bool = True
) -> torch.Tensor:
    """Residuals of E_theta, the closeness of the pose to the previous frame's.

    Joints 1..23: ``r = sqrt(w) (theta_i - theta_{i-1})``, the raw axis-angle
    difference of the paper (their rotations stay well below pi, where the difference
    is well defined). The root (global orientation) is included by default but as the
    geodesic difference ``log(R_{i-1}^T R_i)``: a person facing an OpenCV camera has a
    global rotation close to pi, where the raw axis-angle vector wraps and its
    difference would jump. Both agree to first order for small rotations.

    Args:
        pose: ``(B, 72)`` current pose, radians.
        prev_pose: ``(72,)`` or ``(B, 72)`` previous pose, radians (a constant).
        weights: scalar, ``(24,)`` or ``(72,)`` weights (default 1 everywhere).
        include_root: if False the root's three residuals are 0.

    Returns:
        ``(B, 72)`` residuals in radians.
    """
    pose = _pose(pose)
    prev = _pose(_like(prev_pose, pose), "prev_pose").expand_as(pose)
    w = torch.sqrt(_pose_weights(weights, pose, 1.0))
    joints = pose[:, 3:] - prev[:, 3:]
    if include_root and _COMPILED and pose.device.type == "cpu":  # compiled, closed-form Jacobian; same values
        root = rt.root_difference(pose[:, :3], prev[:, :3].contiguous())
    elif include_root:
        rel = axis_angle_to_matrix(prev[:, :3]).transpose(-1, -2) @ axis_angle_to_matrix(pose[:, :3])
        root = matrix_to_axis_angle(rel)
    else:
        root = torch.zeros_like(pose[:, :3])
    return w * torch.cat([root, joints], dim=1)


def temporal_energy(pose: torch.Tensor, prev_pose: Any, weights: Any = None, include_root: bool = True) -> torch.Tensor:
    """E_theta: sum of squared :func:`temporal_residuals`, ``(B,)`` in rad^2."""
    return _sum_sq(temporal_residuals(pose, prev_pose, weights, include_root))


def camera_ray(camera: PinholeCamera, point: Any) -> torch.Tensor:
    """Unit direction ``(3,)`` (world axes) from the camera's centre to ``point`` ``(3,)``
    metres (world): the direction in which a monocular camera cannot see a point move.

    Raises:
        InputError: ``point`` is not 3 finite numbers or lies at the camera's centre.
    """
    p = torch.as_tensor(np.asarray(point, np.float64)).reshape(-1)
    if p.numel() != 3 or not torch.isfinite(p).all():
        raise InputError(f"point must be 3 finite numbers (metres); got {tuple(p.shape)}.")
    R = torch.tensor(np.array(camera.R, np.float64))
    centre = -R.T @ torch.tensor(np.array(camera.t, np.float64))
    d = p - centre
    n = torch.linalg.norm(d)
    if not n > 1e-9:
        raise InputError("the point lies at the camera's centre; it has no viewing ray.")
    return (d / n).to(torch.float32)


def depth_temporal_residuals(trans: torch.Tensor, ref_trans: Any, ray: Any) -> torch.Tensor:
    """Residual of ``E_z``, the root's motion along the camera ray away from a reference:
    ``r = (sigma - sigma_ref) . u`` (metres), with ``u`` the unit viewing ray through the
    reference root (:func:`camera_ray`). Motion across the ray (which the image sees) is
    free; only the component along it (which flow and silhouette barely see) costs.

    Args:
        trans: ``(3,)`` or ``(B, 3)`` translations, metres (the variables).
        ref_trans: ``(3,)`` reference translation, metres (a constant, e.g. the Kalman
            prediction).
        ray: ``(3,)`` unit viewing direction, world axes.

    Returns:
        ``(B, 1)`` residuals in metres.
    """
    if not isinstance(trans, torch.Tensor) or trans.shape[-1:] != (3,) or trans.dim() not in (1, 2):
        raise InputError(f"trans must be a (3,) or (B, 3) tensor, got {getattr(trans, 'shape', None)}")
    t = trans if trans.dim() == 2 else trans[None]
    ref = _like(ref_trans, t).reshape(-1)
    u = _like(ray, t).reshape(-1)
    if ref.numel() != 3 or u.numel() != 3:
        raise InputError(f"ref_trans and ray must have 3 values each; got {ref.numel()} and {u.numel()}.")
    return ((t - ref) * u).sum(-1, keepdim=True)


def depth_temporal_energy(trans: torch.Tensor, ref_trans: Any, ray: Any) -> torch.Tensor:
    """``E_z``: squared :func:`depth_temporal_residuals`, ``(B,)`` in m^2."""
    return _sum_sq(depth_temporal_residuals(trans, ref_trans, ray))


def root_distance_residuals(root_cam: torch.Tensor, ref_distance: float) -> torch.Tensor:
    """The root's relative change of distance from the camera: ``|root| / ref - 1``.

    A re-initialisation's fit explains the person's image by pose and depth together; a
    lost body refitted to a bent-over person can put it twice as far away as the frame
    before, which no person does between two frames. This residual keeps the refit near
    the tracked depth (``TrackerConfig.reinit_depth_weight``).

    Args:
        root_cam: ``(B, 3)`` the root joint in camera coordinates, metres (camera at 0).
        ref_distance: the reference distance from the camera, metres (> 0).

    Returns:
        ``(B, 1)`` unitless.
    """
    if not (np.isfinite(ref_distance) and ref_distance > 0):
        raise InputError(f"the reference distance must be a positive number of metres, got {ref_distance!r}.")
    return (torch.linalg.vector_norm(root_cam, dim=-1, keepdim=True) / float(ref_distance)) - 1.0


def root_distance_energy(root_cam: torch.Tensor, ref_distance: float) -> torch.Tensor:
    """Squared :func:`root_distance_residuals`, ``(B,)`` unitless."""
    return _sum_sq(root_distance_residuals(root_cam, ref_distance))
