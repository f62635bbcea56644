"""The per-frame depth-flip test of each limb (an extension of the paper, against the
monocular depth ambiguity).

A limb seen by one camera has a mirror image in depth that projects to the same 2D
points: keep its parent joint ``P`` where it is and move its child joint ``C`` to the
other point ``C'`` of the camera ray through ``C`` at the same distance from ``P``. With
the camera centre at the origin of the camera's axes, ``c = C / |C|`` and ``|C| = t1``,
the ray ``t c`` meets the sphere ``|X - P| = |C - P|`` at ``t1`` and ``t2 = 2 c . P - t1``,
so ``C' = t2 c``. (The other common definition, negating the depth component of the
limb's direction, is the same only under weak perspective; this one projects exactly
to the same pixels.) The mirrored limb is realised as a change of the parent joint's
local rotation: the smallest rotation ``D`` (in the camera's axes) taking ``C - P`` to
``C' - P`` is applied to the parent joint's global rotation, ``G_p' = D_w G_p`` with
``D_w = R^T D R`` in the world's axes, i.e. its local rotation becomes ``R_p' = G_pp^T D_w
G_pp R_p`` (``G_pp``: the global rotation of the parent joint's own parent). The limb's
descendants turn with it rigidly: mirroring a thigh also moves the shin and foot (their
2D points move; the energy decides), mirroring a shin moves the foot.

:func:`flip_limbs` tries the limbs of :data:`~flowmocap.fit.energies.DEPTH_LIMBS` one
after the other (upper arms, forearms, thighs, shins: parents before children) on a
frame's optimised state: each mirrored pose is optionally optimised for a few L-BFGS
iterations (``cfg.flip_iterations``) and kept when the frame's total energy
(:func:`~flowmocap.fit.objective.frame_energy` at the last stage) is lower than the
best so far by more than :data:`MIN_RELATIVE_GAIN` (with ``flip_iterations``, the
unflipped state gets the same polish first, so that a flip wins by the flip, not by
the extra iterations; this assumes the state was optimised to convergence, as the
tracker's is). Flow and silhouettes barely tell a limb from its mirror image; what
decides are the detector's 3D joints (``E_d``, ``E_3d``), the joint limits, the
interpenetration and the closeness to the Kalman prediction. Cost: one energy
evaluation per limb with ``flip_iterations`` 0; otherwise about ``1.5 flip_iterations``
energy and gradient evaluations more per limb, and as many for the unflipped state.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from flowmocap.body.fused import posed_body
from flowmocap.body.skeleton import JOINT_NAMES, PARENTS
from flowmocap.errors import InputError, OptimizationError
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.energies import DEPTH_LIMBS
from flowmocap.fit.lbfgs import minimise
from flowmocap.fit.objective import FrameData, FrameState, Scene, frame_energy

__all__ = ["mirror_child", "limb_rotation", "flipped_pose", "mirrored_rotvec", "flip_limbs", "limb_name"]

#: A flip is kept only when it lowers the frame's energy by more than this fraction: a
#: flip that merely ties (float noise, or a polish that only continues an unconverged
#: optimisation) is no evidence.
MIN_RELATIVE_GAIN = 1e-3
#: A mirrored child joint closer to its original than this (metres) is no flip: the limb
#: is nearly perpendicular to the ray through its child, so its mirror image is itself.
MIN_FLIP_DISTANCE = 0.01


def limb_name(limb: tuple[int, int]) -> str:
    """``"left_knee->left_ankle"``: a limb by its parent and child joint names."""
    return f"{JOINT_NAMES[limb[0]]}->{JOINT_NAMES[limb[1]]}"


def mirror_child(parent: np.ndarray, child: np.ndarray) -> np.ndarray | None:
    """The child joint of a limb mirrored in depth about the camera ray through it.

    Args:
        parent: ``(3,)`` parent joint in camera coordinates (metres; camera centre at 0).
        child: ``(3,)`` child joint in camera coordinates, in front of the camera.

    Returns:
        ``(3,)`` the other point of the ray through ``child`` at the same distance from
        ``parent`` (it projects to the same pixel), or None where there is none in front
        of the camera or it lies within :data:`MIN_FLIP_DISTANCE` of ``child``.
    """
    p = np.asarray(parent, np.float64)
    c = np.asarray(child, np.float64)
    t1 = float(np.linalg.norm(c))
    if not (np.isfinite(t1) and t1 > 0 and c[2] > 0):
        return None
    ray = c / t1
    t2 = 2.0 * float(ray @ p) - t1
    if t2 <= 0 or abs(t2 - t1) < MIN_FLIP_DISTANCE:
        return None
    return t2 * ray


def limb_rotation(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``(3, 3)`` the smallest rotation taking direction ``u`` to direction ``v`` (about
    ``u x v``; about an axis perpendicular to ``u`` by pi when they are opposite)."""
    u = np.asarray(u, np.float64) / np.linalg.norm(u)
    v = np.asarray(v, np.float64) / np.linalg.norm(v)
    axis = np.cross(u, v)
    s, c = float(np.linalg.norm(axis)), float(u @ v)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        helper = np.eye(3)[int(np.argmin(np.abs(u)))]
        axis = np.cross(u, helper)
        return Rotation.from_rotvec(math.pi * axis / np.linalg.norm(axis)).as_matrix()
    return Rotation.from_rotvec(axis / s * math.atan2(s, c)).as_matrix()


def flipped_pose(scene: Scene, pose: torch.Tensor, trans: torch.Tensor, limb: tuple[int, int]) -> torch.Tensor | None:
    """The pose with one limb mirrored in depth (see the module docstring).

    Args:
        scene: the body, shape and camera.
        pose: ``(72,)`` axis-angle, radians; trans: ``(3,)`` metres.
        limb: ``(parent, child)`` SMPL joint indices of a bone (e.g. from
            :data:`~flowmocap.fit.energies.DEPTH_LIMBS`); the parent is not the root.

    Returns:
        ``(72,)`` a new pose (``pose``'s dtype) that differs only in the parent joint's
        rotation, or None where the limb has no distinct mirror image (:func:`mirror_child`).
    """
    p, c = limb
    if not (0 < p < len(PARENTS) and 0 < c < len(PARENTS) and PARENTS[c] == p):
        raise InputError(f"a limb is (parent, child) joint indices of one bone, not the root's; got {limb!r}.")
    with torch.no_grad():
        out = posed_body(scene.rig, pose, trans, with_vertices=False)
    rotvec = mirrored_rotvec(pose.detach().double().numpy(), out.joints[0].double().numpy(),
                             out.transforms[0, :, :3, :3].double().numpy(), scene.camera.R, scene.camera.t, limb)
    if rotvec is None:
        return None
    out_pose = pose.detach().clone()
    out_pose[3 * p:3 * p + 3] = torch.as_tensor(rotvec, dtype=pose.dtype)
    return out_pose


def mirrored_rotvec(pose: np.ndarray, joints: np.ndarray, rotations: np.ndarray, R, t,
                    limb: tuple[int, int]) -> np.ndarray | None:
    """The parent joint's new local rotation that mirrors one limb in depth (the module
    docstring), from an already posed body.

    Args:
        pose: ``(72,)`` axis-angle, radians; joints: ``(24, 3)`` its posed joints, world
            axes, metres; rotations: ``(24, 3, 3)`` the joints' global rotations.
        R, t: ``(3, 3)`` and ``(3,)`` the camera's extrinsics (``x_cam = R x + t``).
        limb: ``(parent, child)`` SMPL joint indices of one bone, not the root's.

    Returns:
        ``(3,)`` axis-angle of the parent joint, or None where the limb has no distinct
        mirror image (:func:`mirror_child`).
    """
    p, c = limb
    R = np.asarray(R, np.float64)
    jc = np.asarray(joints, np.float64) @ R.T + np.asarray(t, np.float64).reshape(3)
    c2 = mirror_child(jc[p], jc[c])
    if c2 is None:
        return None
    d_world = R.T @ limb_rotation(jc[c] - jc[p], c2 - jc[p]) @ R
    g_pp = np.asarray(rotations, np.float64)[PARENTS[p]]
    local = Rotation.from_rotvec(np.asarray(pose, np.float64)[3 * p:3 * p + 3]).as_matrix()
    return Rotation.from_matrix(g_pp.T @ d_world @ g_pp @ local).as_rotvec()


def flip_limbs(scene: Scene, state: FrameState, data: FrameData, cfg: TrackerConfig, prev: FrameState,
               ref_pose: torch.Tensor | None, frame: int | None = None,
               limbs: tuple[tuple[int, int], ...] = DEPTH_LIMBS,
               terms: dict | None = None) -> tuple[FrameState, dict, list]:
    """The depth-flip test of each limb on one frame's optimised state.

    Args:
        state: the frame's optimised state; data: its observations.
        prev: the previous frame's state (``E_f``'s other end).
        ref_pose: ``(72,)`` ``E_theta``'s reference (the Kalman prediction), or None.
        frame: the frame number, for the events.
        limbs: the ``(parent, child)`` bones to try, in order.
        terms: the energies of ``state`` itself as :func:`~flowmocap.fit.tracker.track_frame`
            returns them (``frame_energy``'s terms plus a finite ``"total"``, at the last
            stage, with the same ``prev`` and ``ref_pose``), to save evaluating them again;
            None: evaluated here.

    Returns:
        ``(state, terms, events)``: the best state found (``state`` itself when no flip
        lowers the energy), its energies (``frame_energy``'s terms plus ``"total"``) and
        one event per kept flip (``{"event": "limb flipped in depth", "limb", "energy_before",
        "energy_after"}``).

    Raises:
        OptimizationError: the energy of ``state`` itself cannot be evaluated.
    """
    stage = len(cfg.stages) - 1
    with torch.no_grad():
        _, prev_px, _ = scene.forward(prev.pose, prev.trans)

    def judged(terms: dict) -> float:
        """What a flip is judged by: the total, less E_theta with ``cfg.flip_without_temporal``."""
        return terms["total"] - (terms.get("temporal", 0.0) if cfg.flip_without_temporal else 0.0)

    def evaluate(s: FrameState) -> tuple[float, dict]:
        with torch.no_grad():
            total, terms = frame_energy(scene, s, data, cfg, stage, prev_px, ref_pose)
        terms["total"] = float(total)
        return judged(terms), terms

    def polish(pose: torch.Tensor, trans: torch.Tensor) -> FrameState:
        s = FrameState(pose.detach().clone().requires_grad_(), trans.detach().clone().requires_grad_())
        minimise([s.pose, s.trans], lambda: frame_energy(scene, s, data, cfg, stage, prev_px, ref_pose)[0],
                 cfg.flip_iterations)
        return s.clone()

    if terms is not None and math.isfinite(terms.get("total", math.nan)):
        best_e, best_terms = judged(terms), dict(terms)
    else:
        try:
            best_e, best_terms = evaluate(state)
        except InputError as err:
            raise OptimizationError(f"the energy could not be evaluated at the tracked pose: {err}") from err
    best = state
    if cfg.flip_iterations > 0:  # the same polish for the state itself, so a flip wins by the flip alone
        try:
            polished = polish(state.pose, state.trans)
            e, terms = evaluate(polished)
            if math.isfinite(e) and e < best_e:
                best, best_e, best_terms = polished, e, terms
        except (InputError, OptimizationError):
            pass
    events = []
    for limb in limbs:
        pose = flipped_pose(scene, best.pose, best.trans, limb)
        if pose is None:
            continue
        try:
            cand = polish(pose, best.trans) if cfg.flip_iterations > 0 else FrameState(pose, best.trans.clone())
            e, terms = evaluate(cand)
        except (InputError, OptimizationError):
            continue  # the mirrored pose cannot be evaluated (e.g. part of the body behind the camera)
        if math.isfinite(e) and e < best_e - MIN_RELATIVE_GAIN * abs(best_e):
            ev = {"event": "limb flipped in depth", "limb": limb_name(limb), "energy_before": round(best_e, 6),
                  "energy_after": round(e, 6)}
            events.append(ev if frame is None else {"frame": frame, **ev})
            best, best_e, best_terms = cand, e, terms
    return best, best_terms, events
