"""Initialisation on frame 0 (paper Sec. 3.6) from an ``init.json``.

Schema of ``init.json`` (every key optional except ``joints2d``)::

    {
      "frame": 0,                       # the frame the joints belong to (default 0)
      "joints2d": {                     # pixels (x right, y down; pixel centres at +0.5)
        "left_hip": [x, y], "right_hip": [x, y], "left_knee": [x, y], ...
      },                                # any of hips, knees, ankles, shoulders, elbows,
                                        # wrists (SMPL joint names); missing or null = unknown
      "confidence": {"left_hip": 0.9},  # optional per joint, default 1
      "pose": {"left_knee": [ax, ay, az], ...},  # optional rough pose: axis-angle (rad)
                                        # per SMPL joint; "pelvis" is the global orientation
      "pose72": [...],                  # alternative: the whole (72,) rough pose
      "trans": [x, y, z],               # optional rough translation (metres, camera frame)
      "betas": [...],                   # optional starting shape
      "joints_from": "detector"         # optional: the joints are the detector's keypoints
    }                                   # (with TrackerConfig.keypoint_offsets they are compared
                                        # with the body where the detector puts them,
                                        # flowmocap.vision.keypoint_map); default: the body
                                        # model's own joints

Three steps, as in the paper: (1) fit translation, pose and shape to the 2D joints, with
priors towards the rough pose and the mean shape, joint limits and interpenetration;
(2) the same plus the silhouette term (:func:`fit_frame0`); (3) the flow step on frame 1
while frame 0's pose and translation may still move (:func:`refine_first_pair`).
:func:`initialise` runs the three.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from flowmocap.body import JOINT_INDEX, BodyModel, body_capsules
from flowmocap.body.capsules import rest_capsules
from flowmocap.body.fused import make_rig, posed_body
from flowmocap.errors import InputError, NoPersonError
from flowmocap.fit import energies as en
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.lbfgs import minimise
from flowmocap.fit.objective import FrameData, FrameState, Scene, frame_energy, learned_pose_prior
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.render import prepare_faces
from flowmocap.vision.keypoint_map import detector_points

INIT_JOINTS = (
    "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)


@dataclass
class InitSpec:
    """Parsed init.json: ``joints2d (24, 2)`` pixels, ``confidence (24,)`` (0 = unknown),
    ``pose (72,)`` rough pose, ``trans (3,)`` or None, ``betas (10,)``, ``pose_given
    (24,)`` bool: the joints whose rough rotation the file states (None: none), and
    ``from_detector``: the joints are the detector's keypoints (``"joints_from":
    "detector"``), not the body model's own joints."""

    frame: int
    joints2d: np.ndarray
    confidence: np.ndarray
    pose: np.ndarray
    trans: np.ndarray | None
    betas: np.ndarray
    pose_given: np.ndarray | None = None
    from_detector: bool = False

    @property
    def states_rough_pose(self) -> bool:
        """Whether the init states a rough rotation for any joint but the root (the
        automatic init guesses the root alone)."""
        return self.pose_given is not None and bool(np.asarray(self.pose_given, bool)[1:].any())


def parse_init(data: dict | str | Path, width: int | None = None, height: int | None = None) -> InitSpec:
    """Read and check an init.json (path or dict); see the module docstring for the schema.

    Raises:
        InputError: malformed file, unknown joint names, fewer than 4 joints, a joint
            outside the image.
    """
    if not isinstance(data, dict):
        path = Path(data)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise InputError(f"init file {path} does not exist.") from None
        except json.JSONDecodeError as e:
            raise InputError(f"init file {path} is not valid JSON: {e}") from None
    if "joints2d" not in data or not isinstance(data["joints2d"], dict):
        raise InputError("init.json needs a 'joints2d' object mapping joint names to [x, y] pixels.")
    j2d = np.zeros((24, 2))
    conf = np.zeros(24)
    confidences = data.get("confidence", {}) or {}
    for name, xy in data["joints2d"].items():
        if name not in JOINT_INDEX:
            raise InputError(f"init.json: unknown joint {name!r}; use SMPL joint names such as {', '.join(INIT_JOINTS)}.")
        if xy is None:
            continue
        xy = np.asarray(xy, dtype=np.float64)
        if xy.shape != (2,) or not np.isfinite(xy).all():
            raise InputError(f"init.json: joint {name!r} must be [x, y] pixels; got {data['joints2d'][name]!r}.")
        if width is not None and not (0 <= xy[0] <= width and 0 <= xy[1] <= height):
            raise InputError(f"init.json: joint {name!r} at {xy.tolist()} lies outside the {width}x{height} image.")
        j = JOINT_INDEX[name]
        j2d[j] = xy
        conf[j] = float(confidences.get(name, 1.0))
    if (conf > 0).sum() < 4:
        raise NoPersonError("init.json gives fewer than 4 joints; mark at least hips and shoulders.")
    pose = np.zeros(72)
    given = np.zeros(24, bool)
    if "pose72" in data:
        pose = np.asarray(data["pose72"], dtype=np.float64)
        if pose.shape != (72,):
            raise InputError("init.json: 'pose72' must have 72 numbers.")
        given[:] = True
    for name, aa in (data.get("pose") or {}).items():
        if name not in JOINT_INDEX:
            raise InputError(f"init.json: unknown joint {name!r} in 'pose'.")
        pose[3 * JOINT_INDEX[name] : 3 * JOINT_INDEX[name] + 3] = np.asarray(aa, dtype=np.float64)
        given[JOINT_INDEX[name]] = True
    trans = np.asarray(data["trans"], dtype=np.float64) if data.get("trans") is not None else None
    betas = np.zeros(10)
    if data.get("betas") is not None:
        b = np.asarray(data["betas"], dtype=np.float64)
        betas[: min(10, b.size)] = b[:10]
    source = data.get("joints_from", "model")
    if source not in ("model", "detector"):
        raise InputError(f"init.json: 'joints_from' must be 'model' or 'detector'; got {source!r}.")
    return InitSpec(int(data.get("frame", 0)), j2d, conf, pose, trans, betas, given, from_detector=source == "detector")


def guess_translation(model: BodyModel, camera: PinholeCamera, spec: InitSpec) -> torch.Tensor:
    """Translation that puts the rough-posed body's joints over the 2D joints (least squares).

    The depth comes from the ratio of 3D to 2D spread of the given joints; x and y from
    back-projecting their centroid. Returns ``(3,)`` float32 metres: the body model's
    translation in the camera's world frame (the camera frame when ``R = I``, ``t = 0``).
    """
    with torch.no_grad():
        out = model(betas=torch.as_tensor(spec.betas, dtype=torch.float32)[None],
                    pose=torch.as_tensor(spec.pose, dtype=torch.float32)[None])
    j3 = out.joints[0].numpy().astype(np.float64)
    ok = spec.confidence > 0
    p2, p3 = spec.joints2d[ok], j3[ok]
    # spread in the camera's view: rotate the body into the camera frame first
    R = np.asarray(camera.R)
    p3c = p3 @ R.T
    s2 = np.sqrt(((p2 - p2.mean(0)) ** 2).sum(1).mean())
    s3 = np.sqrt(((p3c[:, :2] - p3c[:, :2].mean(0)) ** 2).sum(1).mean())
    f = math.sqrt(camera.fx * camera.fy)
    z = f * s3 / max(s2, 1e-6)
    c2 = p2.mean(0)
    ray = np.array([(c2[0] - camera.cx) / camera.fx, (c2[1] - camera.cy) / camera.fy, 1.0])
    centre_cam = ray * z  # where the joints' centroid should be, camera frame
    centre_world = R.T @ (centre_cam - np.asarray(camera.t))
    return torch.as_tensor(centre_world - p3.mean(0), dtype=torch.float32)


def fit_frame0(model: BodyModel, camera: PinholeCamera, spec: InitSpec, silhouette, cfg: TrackerConfig,
               joints3d: tuple | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict]:
    """Steps 1 and 2 of the initialisation (``joints3d``: the frame's detected 3D joints
    for ``E_d``, as :func:`fit_to_joints` takes them, or None).

    Args:
        spec: the parsed init (``joints2d (24, 2)`` pixels, ``pose (72,)`` radians, ...).
        silhouette: a :class:`~flowmocap.fit.energies.SilhouetteTarget` or None.

    Returns:
        ``pose (72,)`` radians, ``trans (3,)`` metres, ``betas (1, 10)`` and a dict of
        final energies.
    """
    trans = (torch.as_tensor(spec.trans, dtype=torch.float32) if spec.trans is not None
             else guess_translation(model, camera, spec))
    return fit_to_joints(model, camera, spec.joints2d, spec.confidence, silhouette, cfg,
                         torch.as_tensor(spec.pose, dtype=torch.float32), trans,
                         torch.as_tensor(spec.betas, dtype=torch.float32)[None], fit_shape=True,
                         prior_weights=rough_pose_weights(spec, cfg), joints3d=joints3d,
                         joints_from_detector=spec.from_detector)


def rough_pose_weights(spec: InitSpec, cfg: TrackerConfig) -> np.ndarray:
    """Per-joint weights of the initialisation's pose prior, ``(24,)`` per rad^2.

    An init that states a rough pose (a rotation for any joint but the root) describes
    the whole body, the joints it leaves out being at rest: every joint is then pulled
    towards it with ``cfg.init_rough_pose_weight``. Without one (2D joints only, or the
    automatic init, which guesses the root alone) the start pose is only a guess and the
    weight is ``cfg.init_pose_prior_weight``. The root gets 0: the 2D joints decide it.
    """
    weight = cfg.init_rough_pose_weight if spec.states_rough_pose else cfg.init_pose_prior_weight
    w = np.full(24, float(weight))
    w[0] = 0.0
    return w


def fit_to_joints(model: BodyModel, camera: PinholeCamera, joints2d, confidence, silhouette, cfg: TrackerConfig,
                  pose0: torch.Tensor, trans0: torch.Tensor, betas: torch.Tensor, *, fit_shape: bool,
                  iterations: int | None = None, prior_weights=None,
                  joints3d: tuple | None = None,
                  joints_from_detector: bool = False,
                  root_distance: float | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict]:
    """Fit the body to one frame's 2D joints, then also to its silhouette (init steps 1-2).

    Translation alone first, then pose and translation (and the shape when ``fit_shape``)
    against the robust 2D-joint term with joint limits, interpenetration and a prior
    towards ``pose0`` (and the mean shape), then the same plus E_c. With
    ``cfg.init_learned_prior_weight`` the learned pose prior
    (:func:`~flowmocap.fit.objective.learned_pose_prior`) joins the prior towards
    ``pose0``.

    Args:
        joints2d: ``(24, 2)`` pixels; confidence: ``(24,)`` (0 = missing).
        silhouette: a :class:`~flowmocap.fit.energies.SilhouetteTarget` or None.
        pose0: ``(72,)`` start and prior, radians; trans0: ``(3,)`` metres; betas: ``(1, 10)``.
        fit_shape: optimise the betas (with ``cfg.init_shape_prior_weight``) or keep them.
        iterations: L-BFGS iterations per step (default ``cfg.init_iterations``).
        prior_weights: ``(24,)`` per-joint weights of the prior towards ``pose0``, per
            rad^2 (see :func:`rough_pose_weights`); default ``cfg.init_pose_prior_weight``
            for every joint but the root.
        joints3d: the detector's 3D joints of the frame, ``(j3d (24, 3) metres in the
            camera's axes, conf (24,))``, for ``E_d`` (``cfg.limb_depth_weight``) and
            ``E_3d`` (``cfg.init_detector3d_weight``: this fit's 2D-joint term is in px^2
            summed over the joints, hundreds of times the per-frame objective's scale,
            so ``E_3d`` has its own weight here) in every step; None for none.
        joints_from_detector: ``joints2d`` are the detector's keypoints: with
            ``cfg.keypoint_offsets`` they are compared with the body where the detector
            puts them (:func:`~flowmocap.vision.keypoint_map.detector_points`), as the
            3D joints always are; otherwise with the body model's joints.
        root_distance: metres: keep the root's distance from the camera near this one
            (:func:`~flowmocap.fit.energies.root_distance_energy`, weight
            ``cfg.reinit_depth_weight``; the re-initialisation passes the tracked
            frame's), or None for no such term.

    Returns:
        ``pose (72,)``, ``trans (3,)``, ``betas (1, 10)`` and a dict of the final energies.
    """
    iterations = iterations or cfg.init_iterations
    ref_pose = torch.as_tensor(pose0, dtype=torch.float32).detach().clone()
    pose = ref_pose.clone().requires_grad_()
    trans = torch.as_tensor(trans0, dtype=torch.float32).detach().clone().requires_grad_()
    betas = torch.as_tensor(betas, dtype=torch.float32).detach().clone().requires_grad_(fit_shape)
    j2d = torch.as_tensor(np.asarray(joints2d), dtype=torch.float32)
    conf = torch.as_tensor(np.asarray(confidence), dtype=torch.float32)
    faces = prepare_faces(model.faces_np) if cfg.silhouette_model == "mesh" else None
    if prior_weights is None:
        prior_weights = np.r_[0.0, np.full(23, float(cfg.init_pose_prior_weight))]
    prior_w = torch.as_tensor(np.asarray(prior_weights, np.float64), dtype=torch.float32)
    if prior_w.shape != (24,):
        raise InputError(f"prior_weights must have shape (24,); got {tuple(prior_w.shape)}.")

    rest = rig = None  # the shaped body and its capsules depend on the shape only: made once when it is fixed
    if not fit_shape:
        with torch.no_grad():
            rest = rest_capsules(model, model(betas=betas))
            rig = make_rig(model, model.shaped(betas))  # posed in one compiled pass (flowmocap.body.fused)

    def energy(with_silhouette: bool, terms: dict | None = None):
        mesh = with_silhouette and silhouette is not None and cfg.silhouette_model == "mesh"
        # only the mesh silhouette needs the vertices: the other terms are the joints' and the capsules'
        out = (posed_body(rig, pose, trans, with_vertices=mesh) if rig is not None
               else model(betas=betas, pose=pose[None], trans=trans[None], with_vertices=mesh))
        dp = detector_points(out, cfg)
        pj = camera.project((dp if joints_from_detector else out.joints)[0])
        t = {
            "keypoints": cfg.init_keypoint_weight * en.keypoint_energy(pj[None], j2d, conf, sigma=cfg.init_keypoint_sigma)[0],
            "pose_prior": en.pose_prior_energy(pose[None], ref_pose[None], weights=prior_w)[0],
        }
        if fit_shape:
            t["shape_prior"] = cfg.init_shape_prior_weight * en.shape_prior_energy(betas)[0]
        t["limits"] = cfg.limit_weight * en.joint_limit_energy(pose[None])[0]
        if joints3d is not None and cfg.limb_depth_weight > 0:
            t["limb_depth"] = cfg.limb_depth_weight * en.world_limb_depth_energy(dp, camera, joints3d,
                                                                                 cfg.limb_depth_sigma)[0]
        if joints3d is not None and cfg.init_detector3d_weight > 0:
            t["detector3d"] = cfg.init_detector3d_weight * en.world_detector_joints_energy(
                dp, camera, joints3d, cfg.detector3d_scale)[0]
        if cfg.init_learned_prior_weight > 0:
            t["learned_prior"] = cfg.init_learned_prior_weight * learned_pose_prior().energy(pose[None])[0]
        if root_distance is not None and cfg.reinit_depth_weight > 0:
            t["root_distance"] = cfg.reinit_depth_weight * en.root_distance_energy(
                camera.to_camera(out.joints[0, :1]), root_distance)[0]
        caps = body_capsules(model, out, rest=rest)
        t["penetration"] = cfg.penetration_weight * en.interpenetration_energy(caps)[0]
        if with_silhouette and silhouette is not None:
            if mesh:
                ec = en.mesh_silhouette_energy(*camera.project_with_depth(out.vertices[0]), faces, silhouette,
                                               a=cfg.silhouette_a, grid_step=cfg.capsule_grid_step)
            else:
                ec = en.silhouette_energy(caps, camera, silhouette, a=cfg.silhouette_a,
                                          grid_step=cfg.capsule_grid_step)[0]
            t["silhouette"] = cfg.silhouette_weight * ec
        if terms is not None:
            terms.update({k: float(v) for k, v in t.items()})
        return sum(t.values())

    params = [trans, pose] + ([betas] if fit_shape else [])
    # 1a: translation only, 1b: everything, 2: everything with the silhouette
    minimise([trans], lambda: energy(False), max(iterations // 3, 1), cfg.rel_tolerance)
    minimise(params, lambda: energy(False), iterations, cfg.rel_tolerance)
    if silhouette is not None and cfg.silhouette_weight > 0:
        minimise(params, lambda: energy(True), iterations, cfg.rel_tolerance)
    terms: dict = {}
    with torch.no_grad():
        energy(silhouette is not None, terms)
    return pose.detach(), trans.detach(), betas.detach(), terms


def refine_first_pair(scene: Scene, s0: FrameState, s1: FrameState, d0: FrameData, d1: FrameData,
                      cfg: TrackerConfig, j2d: torch.Tensor, conf: torch.Tensor,
                      prior: tuple, joints_from_detector: bool = False) -> tuple[FrameState, FrameState]:
    """Initialisation step 3: the flow step on frame 1 while frame 0 may still move.

    Frame 0 keeps the terms of steps 1-2 that only it has: its 2D joints (``j2d (24, 2)``
    px, ``conf (24,)``) and the prior towards the init's pose, ``prior = (pose (72,) rad,
    per-joint weights (24,) per rad^2)`` (:func:`rough_pose_weights` when the init states
    a rough pose, zeros when its pose is only a guess). Without that prior the flow of
    frame 1 and the silhouettes, which cannot tell a limb from its mirror image in depth,
    moved frame 0 away from the rough pose the user gave. ``joints_from_detector``: as
    in :func:`fit_to_joints`.

    Returns:
        ``(s0, s1)``: the refined :class:`FrameState` of frames 0 and 1 (``pose`` ``(72,)``
        axis-angle radians, ``trans`` ``(3,)`` metres), detached.
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
        pj = scene.camera.project((detector_points(out0, cfg) if joints_from_detector else out0.joints)[0])
        ek = cfg.init_keypoint_weight * en.keypoint_energy(pj[None], j2d, conf, sigma=cfg.init_keypoint_sigma)[0]
        ep = en.pose_prior_energy(p0.reshape(1, 72), prior_pose, weights=prior_w)[0]
        return e1 + e0 + ek + ep

    for stage in range(len(cfg.stages)):
        minimise([p0, t0, p1, t1], lambda: energy(stage), cfg.init_flow_iterations, cfg.rel_tolerance)
    return FrameState(p0.detach(), t0.detach()), FrameState(p1.detach(), t1.detach())


@dataclass
class Start:
    """The result of the initialisation: the scene (with the fitted shape), the first two
    frames' states and their energies."""

    scene: Scene
    first: FrameState
    second: FrameState
    first_terms: dict
    second_terms: dict
    shape: dict | None = None  # with TrackerConfig.init_shape_share: the proportions before, seen and after
    #: where frame 0's fit gave a stature outside FITTED_STATURE_M (no height stated):
    #: ``{"fitted_m", "held_m"}``, else None
    stature_held: dict | None = None


def shape_towards_seen(model: BodyModel, betas: torch.Tensor, pose: torch.Tensor, seen: np.ndarray, share: float,
                       girth_sigma: float | None = None) -> tuple[torch.Tensor, dict]:
    """``(betas (1, 10) in betas' dtype, info)``: ``betas (1, 10)`` refitted so that the body's
    bone proportions in ``pose (72,)`` (radians) move ``share`` (in [0, 1]) of the way towards
    ``seen (7,)`` (:func:`~flowmocap.fit.lift_refit.bone_proportions` of what the images
    show, e.g. the median of the lifter's over a video), the body's girth held at
    ``girth_sigma`` metres (None: not held); ``info``: the proportions before, seen and
    after (:func:`~flowmocap.fit.lift_refit.proportions_towards`)."""
    import copy

    from flowmocap.fit.lift_refit import proportions_towards
    from flowmocap.vision.keypoint_map import load_keypoint_map

    body = copy.deepcopy(model).double()
    b64 = torch.as_tensor(betas, dtype=torch.float64).detach().reshape(1, -1)
    p64 = torch.as_tensor(pose, dtype=torch.float64).detach().reshape(1, 72)
    new, own, got = proportions_towards(body, load_keypoint_map(), b64, p64, seen, share, girth_sigma)
    info = {"share": share, "girth_sigma": girth_sigma, "proportions_before": np.round(own, 4).tolist(),
            "proportions_seen": np.round(np.asarray(seen, np.float64), 4).tolist(),
            "proportions_after": np.round(got, 4).tolist(),
            "betas_frame0": b64.reshape(-1).numpy().round(4).tolist()}
    return new.to(torch.as_tensor(betas).dtype), info


def given_stature(model: BodyModel, camera: PinholeCamera, betas: torch.Tensor, trans: torch.Tensor,
                  height: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The body given a stated stature, kept where it was in the image.

    ``betas`` become the nearest shape of stature ``height`` metres
    (:func:`flowmocap.body.stature.with_stature`) and the body's root joint moves along its
    camera ray to the distance scaled by the same factor as the stature (a body ``s`` times
    taller is ``s`` times further away for the same image), so the fit's next steps start
    where the image puts it.

    Args:
        betas: ``(1, n)`` shape; trans: ``(3,)`` metres, world frame; height: metres.

    Returns:
        ``(betas (1, n), trans (3,))`` in the inputs' dtypes.
    """
    from flowmocap.body.stature import stature, with_stature

    new = with_stature(model, betas, height)
    scale = float(height) / stature(model, betas)
    with torch.no_grad():
        root_old = model(betas=betas, with_vertices=False).joints[0, 0].double().numpy()
        root_new = model(betas=new, with_vertices=False).joints[0, 0].double().numpy()
    R, t = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
    cam = R @ (root_old + np.asarray(torch.as_tensor(trans).detach().double())) + t
    moved = R.T @ (scale * cam - t) - root_new
    return new, torch.as_tensor(moved, dtype=torch.as_tensor(trans).dtype)


def initialise(model: BodyModel, camera: PinholeCamera, spec: InitSpec, d0: FrameData, d1: FrameData,
               cfg: TrackerConfig, proportions: np.ndarray | None = None) -> Start:
    """The paper's three initialisation steps on the first two frames.

    Args:
        spec: the parsed init (2D joints of the first frame, optional rough pose).
        d0, d1: the first two frames' observations (:func:`~flowmocap.fit.objective.frame_data`;
            ``d1`` with the observed flow to the first frame; ``joints3d`` set for ``E_d``).
        proportions: ``(7,)`` or None: the body's bone proportions the whole video shows
            (:func:`~flowmocap.fit.lift_refit.median_proportions` of the lifter's 3D of every frame); with
            ``cfg.init_shape_share`` > 0, the shape fitted on frame 0 moves that share of
            the way towards them (:func:`shape_towards_seen`, girth held at
            ``cfg.init_shape_girth``) before step 3. With ``cfg.body_height_m`` the body is
            then given that stature (:func:`given_stature`), before step 3 too; without it, a
            stature outside :data:`~flowmocap.body.stature.FITTED_STATURE_M` is held at the
            nearer bound the same way (``Start.stature_held``).

    Returns:
        a :class:`Start`; ``second_terms`` are the energies of frame 1 against frame 0.
    """
    pose0, trans0, betas, first_terms = fit_frame0(model, camera, spec, d0.silhouette, cfg, d0.joints3d)
    shape = None
    if proportions is not None and cfg.init_shape_share > 0:
        betas, shape = shape_towards_seen(model, betas, pose0, proportions, cfg.init_shape_share,
                                          cfg.init_shape_girth or None)
    held = None
    if cfg.body_height_m:
        betas, trans0 = given_stature(model, camera, betas, trans0, cfg.body_height_m)
    else:  # a body no person has (a mask that holds more than the person): held at the nearer bound
        from flowmocap.body.stature import held_stature, stature

        bound = held_stature(model, betas)
        if bound is not None:
            held = {"fitted_m": round(stature(model, betas), 4), "held_m": bound}
            betas, trans0 = given_stature(model, camera, betas, trans0, bound)
    scene = Scene(model, betas, camera)
    s0 = FrameState(pose0, trans0)
    j2d = torch.as_tensor(spec.joints2d, dtype=torch.float32)
    conf = torch.as_tensor(spec.confidence, dtype=torch.float32)
    # a rough pose the init states holds frame 0 through step 3 too; the automatic init's
    # start pose is a guess, and holding it there cost DAVIS body IoU (docs/experiments.md)
    prior_w = rough_pose_weights(spec, cfg) if spec.states_rough_pose else np.zeros(24)
    s0, s1 = refine_first_pair(scene, s0, s0.clone(), d0, d1, cfg, j2d, conf, (spec.pose, prior_w),
                               joints_from_detector=spec.from_detector)
    _, second_terms = frame_energy(scene, s1, d1, cfg, len(cfg.stages) - 1,
                                   scene.forward(s0.pose, s0.trans)[1].detach(), s0.pose)
    return Start(scene, s0, s1, first_terms, second_terms, shape, held)
