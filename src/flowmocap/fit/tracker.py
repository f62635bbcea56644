"""Per-frame tracking (paper Sec. 3.7) and the ``track`` driver with resumable results.

For each frame i >= 1: the Kalman filters predict pose and translation; then

    min_{pose_i, trans_i}  l_f E_f + l_c E_c + l_b E_b + l_sp E_sp + l_theta E_theta [+ l_j E_j] [+ l_a E_a]

is minimised coarse to fine over the flow pyramid (stages of :class:`TrackerConfig`),
with the shape fixed after initialisation. ``E_f`` compares the observed backward flow
F_o(i, i-1) with the flow rendered from the model at frame i (the variables) to the model
at frame i-1 (the previous result, fixed). The optimised pose updates the filters.
``E_j`` (not in the paper) pulls the model's 2D joints towards a detector's where one is
given (real video): a robust term that keeps the body on the person where flow drifts.
``E_a`` (not in the paper either) pulls every joint but the root towards its rotation in
the first frame when the init states a rough pose: a limb that is hidden or seen end-on
otherwise drifts in depth with nothing observed to stop it.
"""

from __future__ import annotations

import json
import math
import platform
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from flowmocap import __version__
from flowmocap.body import BodyModel, Capsules, body_capsules
from flowmocap.body.capsules import rest_capsules
from flowmocap.errors import DataError, InputError, OptimizationError
from flowmocap.fit import energies as en
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.kalman import PoseFilter
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.io.results import read_result, write_motion, write_run
from flowmocap.io.sequence import Sequence
from flowmocap.render import flow_loss, flow_target, prepare_faces
from flowmocap.vision import FlowCache, flow_consistency

ENERGY_NAMES = ("total", "flow", "silhouette", "limits", "penetration", "temporal", "keypoints", "anchor",
                "limb_depth")


@dataclass
class FrameState:
    """Fitted parameters of one frame: ``pose (72,)`` radians, ``trans (3,)`` metres."""

    pose: torch.Tensor
    trans: torch.Tensor


@dataclass
class Scene:
    """What every energy evaluation needs: the body, its shape, the camera, the faces."""

    model: BodyModel
    betas: torch.Tensor  # (1, 10)
    camera: PinholeCamera
    faces: object = None

    def __post_init__(self):
        if self.faces is None:
            self.faces = prepare_faces(self.model.faces_np)
        with torch.no_grad():
            self.rest_capsules = rest_capsules(self.model, self.model(betas=self.betas))
        w = self.model.weights.detach().cpu().numpy()
        self.part = w.argmax(1)  # (V,) the joint that moves each vertex most
        self.part_size = np.maximum(np.bincount(self.part, minlength=w.shape[1]), 1)

    def capsules(self, out) -> Capsules:
        """Posed capsules of a forward pass with this scene's (fixed) shape."""
        return body_capsules(self.model, out, rest=self.rest_capsules)

    def forward(self, pose: torch.Tensor, trans: torch.Tensor):
        """Body output and ``(V, 2)`` projected vertices, ``(V,)`` depths."""
        out = self.model(betas=self.betas, pose=pose.reshape(1, 72), trans=trans.reshape(1, 3))
        v = out.vertices[0]
        return out, self.camera.project(v), self.camera.depth(v)


@dataclass
class FrameData:
    """Observations of frame i: image mask (optional) and its chamfer map, flow target(s)."""

    mask: np.ndarray | None
    silhouette: object  # fit.energies.SilhouetteTarget or None
    person_pixels: float
    targets: list = field(default_factory=list)  # one FlowTarget per stage
    temporal_weights: object = None  # (24,) per-joint factors of E_theta, or None (all 1)
    keypoints: tuple | None = None  # detected (j2d (24, 2) px, conf (24,)) tensors for E_j, or None
    anchor: torch.Tensor | None = None  # (72,) pose of the track's first frame for E_a (cfg.anchor_weight)
    joints3d: tuple | None = None  # detected 3D joints for E_d: (j3d (24, 3) m in camera axes, conf (24,)), or None


def keypoint_observation(j2d, conf, min_confidence: float = 0.5, min_joints: int = 4) -> tuple | None:
    """Detected joints for ``E_j``: ``(j2d (24, 2), conf (24,))`` float32 tensors with the
    confidences below ``min_confidence`` (and non-finite joints) set to 0, or None when
    fewer than ``min_joints`` joints are left (``j2d``: pixels, SMPL joint order)."""
    j = np.asarray(j2d, np.float64).reshape(-1, 2)
    c = np.asarray(conf, np.float64).reshape(-1).copy()
    if j.shape[0] != c.shape[0]:
        raise InputError(f"detected joints {j.shape} and confidences {c.shape} differ in count.")
    ok = np.isfinite(j).all(1) & np.isfinite(c) & (c >= min_confidence)
    if ok.sum() < min_joints:
        return None
    c[~ok] = 0.0
    j = np.where(ok[:, None], j, 0.0)
    return torch.as_tensor(j, dtype=torch.float32), torch.as_tensor(c, dtype=torch.float32)


def frame_data(mask: np.ndarray | None, flow: np.ndarray | None, cfg: TrackerConfig,
               fallback_pixels: float, keypoints: tuple | None = None,
               flow_valid: np.ndarray | None = None) -> FrameData:
    """Prepare the observations of one frame for repeated energy evaluations
    (``keypoints``: a :func:`keypoint_observation` or None; ``flow_valid``: ``(H, W)``
    bool, the pixels whose observed flow passed the forward-backward check, or None)."""
    target = None
    pixels = fallback_pixels
    if mask is not None:
        target = en.silhouette_target(mask)
        pixels = float(mask.sum())
    targets = []
    if flow is not None:
        # With a mask, E_f counts only person pixels: observed flow smeared across the
        # motion boundary (every dense method blurs it) would otherwise dominate E_f and
        # pull the outline; the silhouette term carries the outline instead.
        weight = mask.astype(np.float32) if (mask is not None and cfg.flow_in_mask) else None
        if flow_valid is not None:
            # (dis)occluded pixels have no true correspondence: their observed flow is
            # whatever the method smeared in from the occluder
            weight = flow_valid.astype(np.float32) * (weight if weight is not None else 1.0)
        for stage in cfg.stages:
            lw = [float(4 ** l) if l in stage else 0.0 for l in range(cfg.levels)]
            targets.append(flow_target(flow, weight=weight, levels=cfg.levels, level_weights=lw))
    return FrameData(mask=mask, silhouette=target, person_pixels=max(pixels, 1.0), targets=targets,
                     keypoints=keypoints)


def frame_energy(scene: Scene, state: FrameState, data: FrameData, cfg: TrackerConfig, stage: int | None,
                 prev_px: torch.Tensor | None, prev_pose: torch.Tensor | None) -> tuple[torch.Tensor, dict]:
    """The paper's Eq. 4 for one frame; returns ``(total, {name: value})`` (floats detached)."""
    out, px, depth = scene.forward(state.pose, state.trans)
    terms = {}
    if prev_px is not None and data.targets and cfg.flow_weight > 0:
        ef = flow_loss(px, prev_px, scene.faces, data.targets[stage], depth_cur=depth, cull_backfaces=True)
        terms["flow"] = cfg.flow_weight * ef / data.person_pixels
    caps = None
    if data.mask is not None and cfg.silhouette_weight > 0:
        if cfg.silhouette_model == "mesh":
            ec = en.mesh_silhouette_energy(px, depth, scene.faces, data.silhouette, a=cfg.silhouette_a,
                                           grid_step=cfg.capsule_grid_step)
        else:
            caps = scene.capsules(out)
            ec = en.silhouette_energy(caps, scene.camera, data.silhouette, a=cfg.silhouette_a,
                                      grid_step=cfg.capsule_grid_step)[0]
        terms["silhouette"] = cfg.silhouette_weight * ec
    if cfg.limit_weight > 0:
        terms["limits"] = cfg.limit_weight * en.joint_limit_energy(state.pose.reshape(1, 72))[0]
    if cfg.penetration_weight > 0:
        caps = caps if caps is not None else scene.capsules(out)
        terms["penetration"] = cfg.penetration_weight * en.interpenetration_energy(caps)[0]
    if prev_pose is not None and cfg.temporal_weight > 0:
        terms["temporal"] = cfg.temporal_weight * en.temporal_energy(
            state.pose.reshape(1, 72), prev_pose.reshape(1, 72), weights=data.temporal_weights)[0]
    if data.keypoints is not None and cfg.keypoint_weight > 0:
        terms["keypoints"] = cfg.keypoint_weight * keypoint_term(scene, out, data.keypoints, cfg.keypoint_sigma)
    if data.anchor is not None and cfg.anchor_weight > 0:
        terms["anchor"] = cfg.anchor_weight * en.pose_prior_energy(state.pose.reshape(1, 72),
                                                                   data.anchor.reshape(1, 72))[0]
    if data.joints3d is not None and cfg.limb_depth_weight > 0:
        terms["limb_depth"] = cfg.limb_depth_weight * en.world_limb_depth_energy(
            out.joints, scene.camera, data.joints3d, cfg.limb_depth_sigma)[0]
    total = sum(terms.values(), (state.pose * 0.0).sum())
    return total, {k: float(v.detach()) for k, v in terms.items()}


def keypoint_term(scene: Scene, out, keypoints: tuple, sigma: float) -> torch.Tensor:
    """``E_j``: robust squared pixel distance (Geman-McClure, scale ``sigma`` px) between the
    model's projected joints and detected ones, confidence-weighted, per confident joint
    (px^2; a whole-body shift of d px costs about d^2, like ``E_f`` per person pixel)."""
    j2d, conf = keypoints
    pj = scene.camera.project(out.joints[0])
    return en.keypoint_energy(pj[None], j2d, conf, sigma=sigma)[0] / float((conf > 0).sum())


def minimise(params: list[torch.Tensor], closure_energy, iterations: int) -> float:
    """L-BFGS (strong Wolfe) on ``params``; raises OptimizationError on non-finite energy.

    A trial point of the line search where the energy cannot be evaluated (an
    :class:`~flowmocap.errors.InputError`, e.g. a step so long that part of the body
    ends up behind the camera) counts as an energy above every accepted one, with zero
    gradient, so the line search backs off towards the last good point instead of giving
    up the frame.
    Only a start that cannot be evaluated raises.

    Returns the last energy L-BFGS evaluated (the parameters hold the result; callers
    that need the energy's terms at the result evaluate them themselves, so no extra
    evaluation is spent here).
    """
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-7, tolerance_change=1e-9, history_size=20)
    last = [float("nan")]
    first = [None]

    def closure():
        opt.zero_grad()
        try:
            e = closure_energy()
        except InputError as err:
            if first[0] is None:
                raise OptimizationError(f"the energy could not be evaluated at the start pose: {err}") from err
            # above every energy L-BFGS has accepted (they only decrease from the start),
            # so the Armijo test fails and the line search shrinks the step; not so high
            # that its cubic interpolation collapses the step to nothing
            wall = sum((p * 0.0).sum() for p in params) + first[0] + 1.0 + abs(first[0])
            wall.backward()  # zero gradients: nothing to follow past the wall
            return wall
        if not torch.isfinite(e):
            raise OptimizationError("the energy became non-finite (NaN or inf)")
        e.backward()
        last[0] = float(e.detach())
        if first[0] is None:
            first[0] = last[0]
        return e

    opt.step(closure)
    return last[0]


def hidden_parts(scene: Scene, state: FrameState) -> np.ndarray:
    """Hidden share of each joint's body part at ``state``: ``(24,)`` in [0, 1].

    A vertex counts as seen when a triangle holding it is visible in the rasterised
    body; a body part is the vertices a joint moves most. An unoccluded part shows
    about half its vertices (its front), so the share is ``1 - min(1, 2 seen / all)``.
    """
    from flowmocap.render import rasterize

    with torch.no_grad():
        _, px, depth = scene.forward(state.pose, state.trans)
    face_id = rasterize(px.numpy(), depth.numpy(), scene.faces, scene.camera.height, scene.camera.width,
                        cull_backfaces=True).face_id
    faces = np.asarray(scene.model.faces_np)
    seen = np.zeros(len(scene.part), bool)
    seen[faces[np.unique(face_id[face_id >= 0])].ravel()] = True
    count = np.bincount(scene.part[seen], minlength=len(scene.part_size))
    return 1.0 - np.minimum(1.0, 2.0 * count / scene.part_size)


def track_frame(scene: Scene, init: FrameState, data: FrameData, cfg: TrackerConfig,
                prev: FrameState) -> tuple[FrameState, dict]:
    """Optimise one frame from ``init`` (the prediction) against the previous frame ``prev``
    with the configured optimiser (L-BFGS here, or :func:`flowmocap.fit.lm.lm_track_frame`)."""
    if cfg.occlusion_temporal_gain > 0 and cfg.temporal_weight > 0:
        factor = 1.0 + cfg.occlusion_temporal_gain * hidden_parts(scene, init)
        factor[0] = 1.0  # the root moves the whole body; its part is the pelvis only
        data.temporal_weights = torch.as_tensor(factor, dtype=init.pose.dtype)
    if cfg.optimizer == "lm":
        from flowmocap.fit.lm import lm_track_frame

        return lm_track_frame(scene, init, data, cfg, prev)
    with torch.no_grad():
        _, prev_px, _ = scene.forward(prev.pose, prev.trans)
    pose = init.pose.detach().clone().requires_grad_()
    trans = init.trans.detach().clone().requires_grad_()
    state = FrameState(pose, trans)
    ref = init.pose.detach().clone() if cfg.temporal_reference == "prediction" else prev.pose
    for stage in range(len(cfg.stages)):
        minimise([pose, trans], lambda: frame_energy(scene, state, data, cfg, stage, prev_px, ref)[0],
                 cfg.iterations)
    with torch.no_grad():
        try:
            total, terms = frame_energy(scene, state, data, cfg, len(cfg.stages) - 1, prev_px, ref)
        except InputError as err:
            raise OptimizationError(f"the energy could not be evaluated at the result: {err}") from err
    terms["total"] = float(total)
    return FrameState(pose.detach(), trans.detach()), terms


def refine_first_pair(scene: Scene, s0: FrameState, s1: FrameState, d0: FrameData, d1: FrameData,
                      cfg: TrackerConfig, j2d: torch.Tensor, conf: torch.Tensor,
                      prior: tuple[torch.Tensor, torch.Tensor]) -> tuple[FrameState, FrameState]:
    """Initialisation step 3: the flow step on frame 1 while frame 0 may still move.

    Frame 0 keeps the terms of steps 1-2 that only it has: its 2D joints (``j2d (24, 2)``
    px, ``conf (24,)``) and the prior towards the init's pose, ``prior = (pose (72,) rad,
    per-joint weights (24,) per rad^2)`` (:func:`~flowmocap.fit.init.rough_pose_weights`
    when the init states a rough pose, zeros when its pose is only a guess). Without that
    prior the flow of frame 1 and the silhouettes, which cannot tell a limb from its
    mirror image in depth, moved frame 0 away from the rough pose the user gave.
    """
    p0, t0 = s0.pose.clone().requires_grad_(), s0.trans.clone().requires_grad_()
    p1, t1 = s1.pose.clone().requires_grad_(), s1.trans.clone().requires_grad_()
    a, b = FrameState(p0, t0), FrameState(p1, t1)
    prior_pose = torch.as_tensor(prior[0], dtype=p0.dtype).reshape(1, 72)
    prior_w = torch.as_tensor(np.asarray(prior[1], np.float64), dtype=p0.dtype)

    def energy(stage):
        out0, px0, _ = scene.forward(p0, t0)
        e1, _ = frame_energy(scene, b, d1, cfg, stage, px0, p0)
        e0, _ = frame_energy(scene, a, d0, cfg, stage, None, None)
        pj = scene.camera.project(out0.joints[0])
        ek = cfg.init_keypoint_weight * en.keypoint_energy(pj[None], j2d, conf, sigma=cfg.init_keypoint_sigma)[0]
        ep = en.pose_prior_energy(p0.reshape(1, 72), prior_pose, weights=prior_w)[0]
        return e1 + e0 + ek + ep

    for stage in range(len(cfg.stages)):
        minimise([p0, t0, p1, t1], lambda: energy(stage), cfg.init_flow_iterations)
    return FrameState(p0.detach(), t0.detach()), FrameState(p1.detach(), t1.detach())


@dataclass
class KnownStart:
    """A start that needs no initialisation: the first two frames' ``poses (2, 72)``,
    ``trans (2, 3)`` and the ``betas (10,)`` (e.g. ground truth, for ablations and tests)."""

    poses: np.ndarray
    trans: np.ndarray
    betas: np.ndarray


class ResultBuffer:
    """Per-frame results, flushed to ``motion.npz`` + ``run.json`` after every frame."""

    def __init__(self, out_dir: Path, scene: Scene, fps: float, run: dict):
        self.out_dir = Path(out_dir)
        self.scene = scene
        self.fps = fps
        self.run = run
        self.poses, self.trans, self.j3d, self.j2d, self.energies, self.index = [], [], [], [], [], []

    def add(self, frame: int, state: FrameState, terms: dict) -> None:
        with torch.no_grad():
            out, _, _ = self.scene.forward(state.pose, state.trans)
            j3 = out.joints[0]
            self.j3d.append(j3.numpy())
            self.j2d.append(self.scene.camera.project(j3).numpy())
        self.poses.append(state.pose.numpy().astype(np.float32))
        self.trans.append(state.trans.numpy().astype(np.float32))
        self.energies.append([terms.get(n, np.nan) for n in ENERGY_NAMES])
        self.index.append(frame)

    def flush(self) -> None:
        write_motion(self.out_dir, {
            "poses": np.asarray(self.poses, np.float32).reshape(-1, 72),
            "trans": np.asarray(self.trans, np.float32).reshape(-1, 3),
            "betas": self.scene.betas[0].numpy().astype(np.float32),
            "gender": np.array(self.scene.model.gender),
            "fps": np.array(float(self.fps)),
            "camera": np.array(json.dumps(self.scene.camera.to_dict())),
            "joints3d": np.asarray(self.j3d, np.float32).reshape(-1, 24, 3),
            "joints2d": np.asarray(self.j2d, np.float32).reshape(-1, 24, 2),
            "energies": np.asarray(self.energies, np.float64).reshape(-1, len(ENERGY_NAMES)),
            "energy_names": np.array(ENERGY_NAMES),
            "frame_index": np.asarray(self.index, np.int64),
        })
        write_run(self.out_dir, self.run)

    def restore(self, motion: dict) -> None:
        self.poses = list(motion["poses"])
        self.trans = list(motion["trans"])
        self.j3d = list(motion["joints3d"])
        self.j2d = list(motion["joints2d"])
        # by name: a run written by an older version may lack later terms' columns
        names = [str(n) for n in motion.get("energy_names", ENERGY_NAMES)]
        col = {n: k for k, n in enumerate(names)}
        self.energies = [[float(e[col[n]]) if n in col else float("nan") for n in ENERGY_NAMES]
                         for e in motion["energies"]]
        self.index = [int(i) for i in motion["frame_index"]]


def _frame_range(frames: str | tuple | None, n: int) -> tuple[int, int]:
    if frames is None:
        return 0, n
    if isinstance(frames, str):
        try:
            a, _, b = frames.partition(":")
            a = int(a) if a else 0
            b = int(b) if b else n
        except ValueError:
            raise InputError(f"--frames must look like A:B (e.g. 0:100); got {frames!r}.") from None
    else:
        a, b = frames
    if not (0 <= a < b <= n) or b - a < 2:
        raise InputError(f"frames {a}:{b} do not select at least 2 of the {n} frames.")
    return a, b


def track_sequence(seq: Sequence, out_dir: str | Path, model: BodyModel, camera: PinholeCamera, init,
                   cfg: TrackerConfig | None = None, frames=None, resume: bool = False,
                   progress: bool = True, monitor=None, keypoints=None, joints3d=None) -> dict:
    """Track a sequence and write ``out_dir/motion.npz`` and ``run.json`` frame by frame.

    Args:
        seq: the input frames (and masks).
        out_dir: result folder.
        model: body model; camera: the static camera.
        init: an :class:`~flowmocap.fit.init.InitSpec` for the first tracked frame, or a
            :class:`KnownStart` to skip the initialisation.
        cfg: settings (default :class:`TrackerConfig`).
        frames: ``"A:B"`` or ``(A, B)``: the frame range (default all).
        resume: continue an interrupted run in ``out_dir`` with the same input and settings.
        progress: show a progress bar.
        monitor: optional failure check, called after every tracked frame ``i`` (from the
            third frame on) as ``monitor(i, state, scene, mask)`` with the optimised
            :class:`FrameState`, the :class:`Scene` and the frame's mask (or None). It
            returns None to accept the frame, or ``(new_state, info)`` to re-initialise:
            the frame is replaced by ``new_state``, the Kalman filters restart from it,
            and ``{"frame": i, "event": "re-initialised", **info}`` is recorded in
            ``run.json``. It must not rely on state of its own that a ``--resume`` loses.
        keypoints: optional detected 2D joints for ``E_j`` (``cfg.keypoint_weight``), a
            callable ``keypoints(i) -> (j2d (24, 2) px, conf (24,))`` in SMPL joint order,
            or None for a frame without a detection.
        joints3d: optional detected 3D joints for ``E_d`` (``cfg.limb_depth_weight``), a
            callable ``joints3d(i) -> (j3d (24, 3) metres in the camera's axes, conf (24,))``
            in SMPL joint order (:meth:`~flowmocap.vision.auto.PersonTrack.smpl_joints3d`),
            or None for a frame without them.

    Returns:
        the final ``run.json`` contents.
    """
    cfg = cfg or TrackerConfig()
    threads = torch.get_num_threads()
    torch.set_num_threads(int(cfg.torch_threads))
    try:
        return _track_sequence(seq, out_dir, model, camera, init, cfg, frames, resume, progress, monitor,
                               keypoints, joints3d)
    finally:
        torch.set_num_threads(threads)


def _track_sequence(seq, out_dir, model, camera, init, cfg, frames, resume, progress, monitor, keypoints,
                    joints3d) -> dict:
    from tqdm import tqdm

    from flowmocap.fit.init import fit_frame0, rough_pose_weights

    out_dir = Path(out_dir)
    a, b = _frame_range(frames, len(seq))
    run = {
        "flowmocap": __version__, "torch": torch.__version__, "python": platform.python_version(),
        "input": str(seq.root), "frames": [a, b], "config": cfg.to_dict(), "model": model.name or model.source,
        "model_source": model.source,
        "gender": model.gender, "camera": camera.to_dict(), "status": "running", "events": [],
        "timings": {},
    }
    done_states: list[FrameState] = []
    kf = None
    if resume and (out_dir / "motion.npz").exists():
        motion, old = read_result(out_dir)
        if isinstance(old.get("config"), dict):
            # settings added in a later version count as their defaults in an older run
            defaults = TrackerConfig().to_dict()
            old["config"] = {**{k: v for k, v in json.loads(json.dumps(defaults)).items()
                                if k not in old["config"]}, **old["config"]}
        for key in ("input", "frames", "config"):
            if old.get(key) != json.loads(json.dumps(run[key])):
                raise InputError(f"cannot resume: {key} differs from the interrupted run in {out_dir} "
                                 f"({old.get(key)!r} vs {run[key]!r}); start a new result folder instead.")
        run = old
        run["status"] = "running"
        betas = torch.as_tensor(motion["betas"])[None]
        scene = Scene(model, betas, camera)
        buf = ResultBuffer(out_dir, scene, seq.meta.get("fps", 30.0), run)
        buf.restore(motion)
        done_states = [FrameState(torch.as_tensor(p), torch.as_tensor(t)) for p, t in zip(motion["poses"], motion["trans"])]
        kf = PoseFilter.from_state_dict(run["kalman"]) if cfg.kalman and run.get("kalman") else None
    else:
        if out_dir.exists() and (out_dir / "motion.npz").exists() and not resume:
            raise InputError(f"{out_dir} already holds a result; pass --resume to continue it or choose another folder.")
        out_dir.mkdir(parents=True, exist_ok=True)
    # E_a (cfg.anchor_weight) holds the track to a start someone vouched for (see _anchor_state)
    run["anchored"] = isinstance(init, KnownStart) or init.states_rough_pose
    cache = FlowCache(out_dir / "flow_cache", method=cfg.flow_method)
    forward_cache = FlowCache(out_dir / "flow_cache_forward", method=cfg.flow_method) if cfg.flow_occlusion_check else None

    def load(i: int):
        mask = seq.mask(i)
        if mask is not None and not mask.any():
            run["events"].append({"frame": i, "event": "empty mask: no silhouette term for this frame"})
            return None
        return mask

    def flow_of(i: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Observed backward flow of frame i and, with the occlusion check, its valid pixels."""
        cur, prev = seq.frame(i), seq.frame(i - 1)
        flow = cache.flow(i, cur, prev)
        if forward_cache is None:
            return flow, None
        return flow, flow_consistency(flow, forward_cache.flow(i, prev, cur))

    def detected(i: int) -> tuple | None:
        found = keypoints(i) if (keypoints is not None and cfg.keypoint_weight > 0) else None
        return keypoint_observation(*found) if found is not None else None

    def detected3d(i: int) -> tuple | None:
        return joints3d(i) if (joints3d is not None and cfg.limb_depth_weight > 0) else None

    def observe(i: int) -> tuple[np.ndarray | None, FrameData]:
        """Mask and prepared observations of frame i (run ahead in a worker thread; the
        person-size fallback for a frame without a mask is filled in by the caller)."""
        mask = seq.mask(i)
        usable = mask if (mask is not None and mask.any()) else None
        flow, valid = flow_of(i)
        data = frame_data(usable, flow, cfg, float("nan"), detected(i), valid)
        data.joints3d = detected3d(i)
        return mask, data

    t_start = time.perf_counter()
    if not done_states and isinstance(init, KnownStart):
        f = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32)  # noqa: E731
        scene = Scene(model, f(init.betas).reshape(1, -1), camera)
        buf = ResultBuffer(out_dir, scene, seq.meta.get("fps", 30.0), run)
        done_states = [FrameState(f(init.poses[k]), f(init.trans[k])) for k in (0, 1)]
        buf.add(a, done_states[0], {})
        buf.add(a + 1, done_states[1], {})
        kf = new_filter(init.poses[0], init.trans[0], cfg) if cfg.kalman else None
        if kf is not None:
            kf.update(init.poses[1].astype(np.float64), init.trans[1].astype(np.float64))
            run["kalman"] = kf.state_dict()
        buf.flush()
    if not done_states:
        t0 = time.perf_counter()
        m0 = load(a)
        d0 = frame_data(m0, None, cfg, 1.0)
        d0.joints3d = detected3d(a)
        pose0, trans0, betas, init_terms = fit_frame0(model, camera, init, d0.silhouette, cfg, d0.joints3d)
        scene = Scene(model, betas, camera)
        buf = ResultBuffer(out_dir, scene, seq.meta.get("fps", 30.0), run)
        s0 = FrameState(pose0, trans0)
        m1 = load(a + 1)
        flow1, valid1 = flow_of(a + 1)
        d1 = frame_data(m1, flow1, cfg, d0.person_pixels, detected(a + 1), valid1)
        d1.joints3d = detected3d(a + 1)
        j2d = torch.as_tensor(init.joints2d, dtype=torch.float32)
        conf = torch.as_tensor(init.confidence, dtype=torch.float32)
        # a rough pose the init states holds frame 0 through step 3 too; the automatic init's start
        # pose is a guess, and holding it there cost DAVIS 0.05 body IoU
        prior_w = rough_pose_weights(init, cfg) if init.states_rough_pose else np.zeros(24)
        s0, s1 = refine_first_pair(scene, s0, FrameState(pose0.clone(), trans0.clone()), d0, d1, cfg, j2d, conf,
                                   (init.pose, prior_w))
        _, terms1 = frame_energy(scene, s1, d1, cfg, len(cfg.stages) - 1,
                                 scene.forward(s0.pose, s0.trans)[1].detach(), s0.pose)
        buf.add(a, s0, init_terms)
        buf.add(a + 1, s1, terms1)
        done_states = [s0, s1]
        run["timings"]["init_s"] = time.perf_counter() - t0
        kf = new_filter(s0.pose.numpy(), s0.trans.numpy(), cfg) if cfg.kalman else None
        if kf is not None:
            kf.update(s1.pose.numpy().astype(np.float64), s1.trans.numpy().astype(np.float64))
            run["kalman"] = kf.state_dict()
        buf.flush()
    frame_times = run["timings"].get("frame_s", [])
    start = a + len(done_states)
    bar = tqdm(range(start, b), initial=start - a, total=b - a, disable=not progress, unit="frame",
               desc="tracking")
    # The observed flow and targets of frame i+1 are prepared while frame i is optimised
    # (OpenCV and numpy release the GIL, and the optimiser is single-threaded).
    ahead = ThreadPoolExecutor(max_workers=1, thread_name_prefix="flowmocap-observe")
    pending = ahead.submit(observe, start) if start < b else None
    try:
        for i in bar:
            t0 = time.perf_counter()
            observed = pending.result()
            pending = ahead.submit(observe, i + 1) if i + 1 < b else None
            kf = _track_one(i, t0, observed, done_states, kf, scene, cfg, run, monitor, buf, frame_times, bar)
    finally:
        ahead.shutdown(wait=True, cancel_futures=True)
    run["status"] = "finished"
    run["timings"]["total_s"] = run["timings"].get("total_s", 0.0) + time.perf_counter() - t_start
    buf.flush()
    return run


def _track_one(i, t0, observed, done_states, kf, scene, cfg, run, monitor, buf, frame_times, bar):
    """One frame of :func:`track_sequence`'s loop: predict, optimise, check, record.
    ``t0``: when the frame started; ``observed``: ``(mask, FrameData)`` of the frame.
    Returns the Kalman filter (a new one after a re-initialisation)."""
    prev = done_states[-1]
    if kf is not None:
        p, t = kf.predict()
        pred = FrameState(torch.as_tensor(p, dtype=torch.float32), torch.as_tensor(t, dtype=torch.float32))
    else:
        pred = FrameState(prev.pose.clone(), prev.trans.clone())
    mask, data = observed
    if cfg.anchor_weight > 0:
        start = _anchor_state(done_states, run)
        data.anchor = start.pose if start is not None else None
    if mask is not None and not mask.any():
        run["events"].append({"frame": i, "event": "empty mask: no silhouette term for this frame"})
        mask = None
    if mask is None:
        data.person_pixels = max(buf_pixels(done_states, scene), 1.0)
    try:
        state, terms = track_frame(scene, pred, data, cfg, prev)
    except OptimizationError as e:
        run["events"].append({"frame": i, "event": "non-finite energy; retried from the previous pose",
                              "detail": str(e)})
        try:
            state, terms = track_frame(scene, FrameState(prev.pose.clone(), prev.trans.clone()), data, cfg, prev)
        except OptimizationError as e2:
            run["events"].append({"frame": i, "event": "retry failed; kept the prediction", "detail": str(e2)})
            state, terms = pred, {"total": float("nan")}
    reinit = monitor(i, state, scene, mask) if monitor is not None else None
    if reinit is not None:
        state, info = reinit
        run["events"].append({"frame": i, "event": "re-initialised", **info})
        if kf is not None:
            kf = new_filter(state.pose.numpy(), state.trans.numpy(), cfg)
    elif kf is not None:
        kf.update(state.pose.numpy().astype(np.float64), state.trans.numpy().astype(np.float64))
    if kf is not None:
        run["kalman"] = kf.state_dict()
    done_states.append(state)
    buf.add(i, state, terms)
    frame_times.append(time.perf_counter() - t0)
    run["timings"]["frame_s"] = frame_times
    run["timings"]["s_per_frame_median"] = float(np.median(frame_times))
    buf.flush()
    bar.set_postfix({k[:4]: f"{v:.3g}" for k, v in terms.items()})
    return kf


def _anchor_state(done_states: list[FrameState], run: dict) -> FrameState | None:
    """The fitted first frame ``E_a`` pulls towards, or None for no ``E_a``.

    Only a start someone vouched for anchors the track: an init.json that states a rough
    pose, or a known start (``run["anchored"]``). The automatic init of real video (a
    guess from one frame's detections) does not, and neither does a re-initialisation:
    after one there is no anchor. ``done_states`` holds the frames from ``run["frames"][0]`` on.
    """
    if not run.get("anchored") or any(e.get("event") == "re-initialised" for e in run["events"]):
        return None
    return done_states[0]


def new_filter(pose, trans, cfg: TrackerConfig) -> PoseFilter:
    """Kalman filters started at ``pose (72,)`` radians and ``trans (3,)`` metres, with the
    configured joint-rotation process noise."""
    return PoseFilter(np.asarray(pose, np.float64), np.asarray(trans, np.float64),
                      rot_accel_noise=cfg.kalman_rot_accel_noise)


def buf_pixels(states: list[FrameState], scene: Scene) -> float:
    """Projected person size (pixels) of the last state: the E_f normaliser without a mask."""
    from flowmocap.render import rasterize

    with torch.no_grad():
        _, px, d = scene.forward(states[-1].pose, states[-1].trans)
    r = rasterize(px.numpy(), d.numpy(), scene.faces, scene.camera.height, scene.camera.width, cull_backfaces=True)
    return float((r.face_id >= 0).sum())
