"""The per-frame objective (paper Eq. 4 plus our extensions) and what it is evaluated on.

    E = l_f E_f + l_c E_c + l_b E_b + l_sp E_sp + l_theta E_theta [+ l_j E_j] [+ l_a E_a] [+ l_d E_d]
        [+ l_3d E_3d] [+ l_p E_p] [+ l_z E_z]

``E_f`` compares the observed backward flow F_o(i, i-1) with the flow rendered from the
model at frame i (the variables) to the model at frame i-1 (fixed); ``E_c`` the body's
silhouette with the person's mask; ``E_b`` joint limits; ``E_sp`` capsule
interpenetration; ``E_theta`` closeness to a reference pose (the Kalman prediction while
tracking). Not in the paper: ``E_j`` pulls the projected joints towards a detector's 2D
joints (real video), ``E_a`` every joint but the root towards its rotation in the
track's first frame, ``E_d`` each limb's direction in depth towards a detector's 3D
joints, ``E_3d`` the model's joints towards a detector's 3D joints after a per-frame
similarity alignment, with a cost that keeps pulling a limb that has flipped in depth
(where ``E_d`` saturates), ``E_p`` a pose prior learned from motion capture
(:mod:`flowmocap.fit.pose_prior`, loaded once by :func:`learned_pose_prior`), ``E_z`` the
root's motion along the camera ray away from the previous frame's (or the Kalman
prediction's) root (the depth a single camera barely sees).
:class:`Scene` holds what stays fixed over a sequence (body, shape, camera,
faces), :class:`FrameState` the variables, :class:`FrameData` one frame's observations.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import cache

import numpy as np
import torch

from flowmocap.body import BodyModel, Capsules, body_capsules
from flowmocap.body.capsules import rest_capsules
from flowmocap.body.fused import make_rig, posed_body
from flowmocap.errors import InputError
from flowmocap.fit import energies as en
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.joint_terms import keypoint_energy_world
from flowmocap.fit.pose_prior import PosePrior
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.render import flow_loss_async, flow_target, prepare_faces
from flowmocap.vision.keypoint_map import detector_points

#: The columns of the per-frame energies a result stores (``motion.npz`` ``energies``).
ENERGY_NAMES = ("total", "flow", "silhouette", "limits", "penetration", "temporal", "keypoints", "anchor",
                "limb_depth", "detector3d", "learned_prior", "depth_temporal")


@cache
def learned_pose_prior() -> PosePrior:
    """The packaged learned pose prior (:meth:`PosePrior.load`), read once per process.

    Raises:
        DataError: the packaged prior is missing or unreadable (its message says how to
            get one); only when a ``*learned_prior*``/``pose_prior_weight`` setting is on.
    """
    return PosePrior.load()


@cache
def uncovered_joint_weights() -> torch.Tensor:
    """``(24,)``: 1 for each joint but the root that the packaged learned prior does not
    cover (its training skeletons lack them: ``spine3``, the collars, feet and hands), else 0.
    Made once per process (the energy reads it at every evaluation); do not modify it."""
    w = torch.ones(24)
    w[0] = 0.0
    w[list(learned_pose_prior().joints)] = 0.0
    return w


@dataclass
class FrameState:
    """Fitted parameters of one frame: ``pose (72,)`` radians, ``trans (3,)`` metres."""

    pose: torch.Tensor
    trans: torch.Tensor

    def clone(self) -> "FrameState":
        """A detached copy."""
        return FrameState(self.pose.detach().clone(), self.trans.detach().clone())


@dataclass
class Scene:
    """What every energy evaluation needs: the body, its shape ``betas (1, 10)``, the
    camera and the prepared faces."""

    model: BodyModel
    betas: torch.Tensor  # (1, 10)
    camera: PinholeCamera
    faces: object = None

    def __post_init__(self):
        if self.faces is None:
            self.faces = prepare_faces(self.model.faces_np)
        with torch.no_grad():
            self.rest_capsules = rest_capsules(self.model, self.model(betas=self.betas))
            self.shaped = self.model.shaped(self.betas)  # the shape is fixed: shape it once
        self.rig = make_rig(self.model, self.shaped)  # and pose it in one compiled pass (flowmocap.body.fused)

    def capsules(self, out) -> Capsules:
        """Posed capsules of a forward pass ``out`` with this scene's (fixed) shape:
        :class:`~flowmocap.body.capsules.Capsules` with ``(B, K, 3)`` end points and
        ``(B, K)`` radii, metres, in the frame of ``out``'s joints."""
        return body_capsules(self.model, out, rest=self.rest_capsules)

    def forward(self, pose: torch.Tensor, trans: torch.Tensor):
        """Body output, ``(V, 2)`` projected vertices (pixels) and ``(V,)`` depths (metres).

        ``pose`` ``(72,)`` axis-angle radians and ``trans`` ``(3,)`` metres (world frame),
        as for :func:`~flowmocap.body.fused.posed_body` (batch 1).
        """
        out = posed_body(self.rig, pose, trans)
        return (out, *self.camera.project_with_depth(out.vertices[0]))


@dataclass
class FrameData:
    """Observations of one frame: the person's mask (optional) and its chamfer target,
    the flow target per optimisation stage, and the detections the extensions use."""

    mask: np.ndarray | None  # (H, W) bool
    silhouette: object  # fit.energies.SilhouetteTarget or None
    person_pixels: float  # E_f's and E_c's normaliser
    targets: list = field(default_factory=list)  # one FlowTarget per stage
    keypoints: tuple | None = None  # detected (j2d (24, 2) px, conf (24,)) tensors for E_j, or None
    anchor: torch.Tensor | None = None  # (72,) pose of the track's first frame for E_a, or None
    joints3d: tuple | None = None  # detected (j3d (24, 3) m in camera axes, conf (24,)) for E_d and E_3d, or None
    depth_ref: tuple | None = None  # (ref_trans (3,) m, unit viewing ray (3,)) for E_z, or None
    keypoint_hold: np.ndarray | None = None  # (24,) bool: joints E_j holds (SequenceTracker.keypoint_hold), or None
    unseen: tuple | None = None  # (first, last) frame of a run of frames without the person longer than
    #                              TrackerConfig.hold_unseen_frames that holds this frame, or None


def keypoint_observation(j2d, conf, min_confidence: float = 0.5, min_joints: int = 4,
                         floor: float = 0.0) -> tuple | None:
    """Detected joints for ``E_j``: ``(j2d (24, 2), conf (24,))`` float32 tensors with the
    confidences below ``min_confidence`` (and zero or non-finite ones) set to 0 and the others
    raised to at least ``floor`` (``E_j`` weighs each joint by it), or None when fewer than
    ``min_joints`` joints are left (``j2d``: pixels, SMPL joint order)."""
    j = np.asarray(j2d, np.float64).reshape(-1, 2)
    c = np.asarray(conf, np.float64).reshape(-1).copy()
    if j.shape[0] != c.shape[0]:
        raise InputError(f"detected joints {j.shape} and confidences {c.shape} differ in count.")
    ok = np.isfinite(j).all(1) & np.isfinite(c) & (c >= min_confidence) & (c > 0)
    if ok.sum() < min_joints:
        return None
    c = np.where(ok, np.maximum(c, floor), 0.0)
    j = np.where(ok[:, None], j, 0.0)
    return torch.as_tensor(j, dtype=torch.float32), torch.as_tensor(c, dtype=torch.float32)


def configured_keypoints(j2d, conf, cfg: TrackerConfig) -> tuple | None:
    """:func:`keypoint_observation` with ``cfg.keypoint_min_confidence`` and
    ``cfg.keypoint_confidence_floor``: the detected joints as the tracker's ``E_j`` uses them."""
    return keypoint_observation(j2d, conf, min_confidence=cfg.keypoint_min_confidence,
                                floor=cfg.keypoint_confidence_floor)


def frame_data(mask: np.ndarray | None, flow: np.ndarray | None, cfg: TrackerConfig,
               fallback_pixels: float, keypoints: tuple | None = None,
               unknown: np.ndarray | None = None) -> FrameData:
    """Prepare the observations of one frame for repeated energy evaluations.

    Args:
        mask: ``(H, W)`` bool person mask, or None.
        flow: ``(H, W, 2)`` observed backward flow in pixels, or None (no ``E_f``).
        fallback_pixels: the person's size in pixels when there is no mask.
        keypoints: a :func:`keypoint_observation`, or None.
        unknown: ``(H, W)`` bool pixels where someone else may hide the person, or None
            (:func:`~flowmocap.fit.energies.silhouette_target`; used when
            ``cfg.occluders_unknown``).

    Returns:
        :class:`FrameData`: the silhouette target, the flow targets (pixels), the keypoints
        and the person's size in pixels, ready for :func:`frame_energy`.
    """
    target = None
    pixels = fallback_pixels
    if mask is not None:
        target = en.silhouette_target(mask, unknown=unknown if cfg.occluders_unknown else None)
        pixels = float(mask.sum())
    targets = []
    if flow is not None:
        # with a mask, E_f counts only person pixels: flow smeared across the motion
        # boundary would otherwise pull the outline, which E_c carries instead
        weight = mask.astype(np.float32) if (mask is not None and cfg.flow_in_mask) else None
        for stage in cfg.stages:
            lw = [float(4 ** l) if l in stage else 0.0 for l in range(cfg.levels)]
            targets.append(flow_target(flow, weight=weight, levels=cfg.levels, level_weights=lw))
    return FrameData(mask=mask, silhouette=target, person_pixels=max(pixels, 1.0), targets=targets,
                     keypoints=keypoints)


_FLOW_THREAD: list = []


def _flow_thread() -> ThreadPoolExecutor:
    """The one worker thread :func:`frame_energy` computes ``E_f`` on (made on first use;
    a forked child makes its own)."""
    if not _FLOW_THREAD or _FLOW_THREAD[0][0] != os.getpid():
        _FLOW_THREAD[:] = [(os.getpid(), ThreadPoolExecutor(max_workers=1, thread_name_prefix="flowmocap-flow"))]
    return _FLOW_THREAD[0][1]


def frame_energy(scene: Scene, state: FrameState, data: FrameData, cfg: TrackerConfig, stage: int | None,
                 prev_px: torch.Tensor | None, ref_pose: torch.Tensor | None) -> tuple[torch.Tensor, dict]:
    """The objective of one frame.

    Args:
        state: the variables; data: the frame's observations.
        stage: index into ``data.targets`` (the pyramid levels ``E_f`` uses).
        prev_px: ``(V, 2)`` projected vertices of the previous frame (fixed), or None (no ``E_f``).
        ref_pose: ``(72,)`` reference of ``E_theta``, or None (no ``E_theta``).

    Returns:
        ``(total, {name: value})``: the differentiable total and each weighted term as a float.
    """
    out, px, depth = scene.forward(state.pose, state.trans)
    terms = {}
    flow = None
    if prev_px is not None and data.targets and cfg.flow_weight > 0:
        # rasterised and compared on the flow thread while the other terms are built here
        flow = flow_loss_async(_flow_thread(), px, prev_px, scene.faces, data.targets[stage], depth_cur=depth,
                               cull_backfaces=True)
        terms["flow"] = None  # keeps E_f first in the sum, as it always was
    caps = None
    mesh_silhouette = data.mask is not None and cfg.silhouette_weight > 0 and cfg.silhouette_model == "mesh"
    if mesh_silhouette:
        # made after the other terms, so that the flow thread's rasterisation (whose coverage
        # it reads) is ready by then; its place here keeps the order of the sum
        terms["silhouette"] = None
    elif data.mask is not None and cfg.silhouette_weight > 0:
        caps = scene.capsules(out)
        terms["silhouette"] = cfg.silhouette_weight * en.silhouette_energy(
            caps, scene.camera, data.silhouette, a=cfg.silhouette_a, grid_step=cfg.capsule_grid_step)[0]
    if cfg.limit_weight > 0:
        terms["limits"] = cfg.limit_weight * en.joint_limit_energy(state.pose.reshape(1, 72))[0]
    if cfg.penetration_weight > 0:
        caps = caps if caps is not None else scene.capsules(out)
        terms["penetration"] = cfg.penetration_weight * en.interpenetration_energy(caps)[0]
    if ref_pose is not None and cfg.temporal_weight > 0:
        terms["temporal"] = cfg.temporal_weight * en.temporal_energy(state.pose.reshape(1, 72),
                                                                     ref_pose.reshape(1, 72))[0]
    points = None  # where the detector would put the model's joints (E_j, E_d, E_3d), made once
    if data.keypoints is not None and cfg.keypoint_weight > 0:
        points = detector_points(out, cfg)
        terms["keypoints"] = cfg.keypoint_weight * keypoint_term(scene, out, data.keypoints, cfg.keypoint_sigma, cfg,
                                                                 points=points, hold=data.keypoint_hold)
    if data.anchor is not None and cfg.anchor_weight > 0:
        terms["anchor"] = cfg.anchor_weight * en.pose_prior_energy(state.pose.reshape(1, 72),
                                                                   data.anchor.reshape(1, 72))[0]
    if data.joints3d is not None and (cfg.limb_depth_weight > 0 or cfg.detector3d_weight > 0):
        points = detector_points(out, cfg) if points is None else points
        if cfg.limb_depth_weight > 0:
            terms["limb_depth"] = cfg.limb_depth_weight * en.world_limb_depth_energy(
                points, scene.camera, data.joints3d, cfg.limb_depth_sigma)[0]
        if cfg.detector3d_weight > 0:
            terms["detector3d"] = cfg.detector3d_weight * en.world_detector_joints_energy(
                points, scene.camera, data.joints3d, cfg.detector3d_scale)[0]
    if cfg.pose_prior_weight > 0:
        terms["learned_prior"] = cfg.pose_prior_weight * learned_pose_prior().energy(state.pose.reshape(1, 72))[0]
    if cfg.uncovered_prior_weight > 0:  # the joints the learned prior says nothing about, towards rest
        rest = cfg.uncovered_prior_weight * en.pose_prior_energy(state.pose.reshape(1, 72), torch.zeros(72),
                                                                 uncovered_joint_weights())[0]
        terms["learned_prior"] = terms["learned_prior"] + rest if "learned_prior" in terms else rest
    if data.depth_ref is not None and cfg.depth_temporal_weight > 0:
        terms["depth_temporal"] = cfg.depth_temporal_weight * en.depth_temporal_energy(
            state.trans.reshape(1, 3), *data.depth_ref)[0]
    if mesh_silhouette:
        terms["silhouette"] = cfg.silhouette_weight * en.mesh_silhouette_energy(
            px, depth, scene.faces, data.silhouette, a=cfg.silhouette_a, grid_step=cfg.capsule_grid_step,
            raster=flow.raster() if flow is not None else None)
    if flow is not None:
        terms["flow"] = cfg.flow_weight * flow() / data.person_pixels
    total = sum(terms.values(), (state.pose * 0.0).sum())
    return total, {k: float(v.detach()) for k, v in terms.items()}


def keypoint_term(scene: Scene, out, keypoints: tuple, sigma: float, cfg: TrackerConfig | None = None,
                  points: torch.Tensor | None = None, hold: np.ndarray | None = None) -> torch.Tensor:
    """``E_j``: robust squared pixel distance (Geman-McClure, scale ``sigma`` px) between the
    model's projected joints and detected ones, confidence-weighted, per confident joint
    (px^2; a whole-body shift of d px costs about d^2, like ``E_f`` per person pixel).
    The model's joints are moved to where the detector puts them
    (:func:`~flowmocap.vision.keypoint_map.detector_points`) when ``cfg.keypoint_offsets``;
    ``points`` ``(1, 24, 3)`` gives those points when they are already made. ``hold``
    ``(24,)`` bool: joints the tracker holds (:meth:`~flowmocap.fit.tracker.SequenceTracker.keypoint_hold`):
    scale ``cfg.keypoint_hold_sigma`` and weight times ``cfg.keypoint_hold_weight``."""
    j2d, conf = keypoints
    c = conf.detach().to(torch.float64).numpy() if isinstance(conf, torch.Tensor) else np.asarray(conf, np.float64)
    obs = j2d.detach().to(torch.float64).numpy() if isinstance(j2d, torch.Tensor) else np.asarray(j2d, np.float64)
    n = float((c > 0).sum())
    missing = ~np.isfinite(obs).all(-1)  # counts as not detected, as in keypoint_residuals
    c, obs = np.where(missing, 0.0, c), np.where(missing[:, None], 0.0, obs)
    if hold is not None and np.any(hold):
        cfg = cfg if cfg is not None else TrackerConfig()
        hold = np.asarray(hold, bool)
        sigma = np.where(hold, cfg.keypoint_hold_sigma, sigma)
        c = np.where(hold, c * cfg.keypoint_hold_weight, c)
    # keypoint_energy of the projected points, in one compiled pass with its gradient
    points = detector_points(out, cfg) if points is None else points
    return keypoint_energy_world(points, scene.camera, obs, c, sigma, factor=1.0 / n)[0]
