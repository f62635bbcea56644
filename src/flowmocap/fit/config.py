"""All tracker weights and settings in one place, with defaults; ``--config`` overrides.

A config file is JSON with any subset of the fields of :class:`TrackerConfig`, e.g.

    {"flow_weight": 1.0, "levels": 3, "iterations": 25}

Energies are normalised so that the defaults need no retuning across image sizes:
``E_f`` and ``E_c`` are divided by the number of person pixels (mask or model).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from flowmocap.errors import InputError


#: Settings ``flowmocap track`` starts from when the masks come from the person detector
#: (real video; a config file still overrides them). Such a mask is the dressed person (a
#: skirt, hair) and the detector gives 2D joints on every frame. E_c from the mesh itself
#: (unbiased, where the capsules leave gaps at the joints, head and feet) at four times the
#: weight, weighing the uncovered mask more (``a`` 0.4); a second hypothesis for every frame
#: whose silhouette IoU with the mask falls below 0.8: a fit to the detections
#: (flowmocap.fit.reinit), kept when it is better; the 2D joints at weight 0.3 instead of 1
#: in the init and these fits. DAVIS dance-twirl body IoU 0.708 (the defaults) -> 0.762;
#: Sports2D walk 0.701 -> 0.784, joints 5.2 % -> 2.8 % of the height apart; about 1.5 times
#: the time per frame. On the synthetic CMU protocol (exact body masks, no per-frame detections)
#: the same E_c settings were worse on 5 of the 6 seeds run (median local error 4.69 cm
#: against 3.42), so they are not the defaults.
REAL_VIDEO = {"silhouette_model": "mesh", "silhouette_weight": 20.0, "silhouette_a": 0.4,
              "reinit_min_iou": 0.8, "reinit_patience": 1, "init_keypoint_weight": 0.3}


@dataclass
class TrackerConfig:
    # --- per-frame objective (paper Eq. 4) --------------------------------------------
    flow_weight: float = 1.0          # lambda_f: E_f, px^2 per person pixel
    silhouette_weight: float = 5.0     # lambda_c: E_c, px^2 per person pixel
    silhouette_a: float = 0.6         # a in E_c: weight of S_M * C_I (model inside the mask)
    limit_weight: float = 10.0        # lambda_b: E_b joint limits
    penetration_weight: float = 10.0  # lambda_sp: E_sp capsule interpenetration (m^2)
    temporal_weight: float = 0.5      # lambda_theta: E_theta, rad^2, to the previous pose
    occlusion_temporal_gain: float = 0.0  # E_theta of joint j times (1 + gain * hidden share of its part); 20 gave
                                          # 5.42/6.83 cm on the CMU protocol (seed 0) but 9.90/13.61 on seed 1: off
    anchor_weight: float = 0.5        # lambda_a: E_a, rad^2, every joint but the root towards its rotation in
                                      # the first frame, when the init states a rough pose (not for the
                                      # automatic init, not after a re-initialisation); an extension of the
                                      # paper against drift: CMU protocol, 8 seeds, median 6.34/8.07 cm without,
                                      # 4.62/6.75 with; DAVIS (automatic init) lost 0.014 IoU with it, hence off there
    temporal_reference: str = "prediction"  # E_theta towards the Kalman "prediction" (default) or the "previous" pose (paper)
    levels: int = 3                   # Gaussian pyramid levels of E_f
    stages: tuple = ((2,), (0, 1, 2))  # coarse to fine: which pyramid levels each stage uses
    iterations: int = 20              # optimiser iterations per stage
    optimizer: str = "lbfgs"          # "lbfgs" (torch L-BFGS, strong Wolfe) or "lm" (Levenberg-Marquardt; needs mesh E_c)
    keypoint_weight: float = 0.05     # lambda_j: detected 2D joints (real video only; an extension of the paper):
                                      # robust px^2 per confident joint, keeps the body on the person
    keypoint_sigma: float = 20.0      # Geman-McClure scale of that term, px (a left/right swap saturates)
    limb_depth_weight: float = 2.0    # lambda_d: E_d, each limb's direction in depth towards the detector's 3D
                                      # joints (MediaPipe's world landmarks; an extension of the paper), when
                                      # they are given (video input, or --joints3d auto)
    limb_depth_sigma: float = 0.3     # Geman-McClure scale of E_d (a difference of sines)
    capsule_grid_step: int = 8        # grid step (px) of the capsule distance map C_M
    silhouette_model: str = "capsules"  # S_M/C_M of E_c from "capsules" (paper) or the "mesh"
    # --- re-initialisation (real video with detections; flowmocap.fit.reinit) -----------
    reinit_min_iou: float = 0.5       # a frame is bad below this silhouette IoU with the person's mask
    reinit_max_joint_error: float = 0.15  # ... or above this median 2D joint distance, a fraction of the person's height
    reinit_patience: int = 3          # bad frames in a row before the frame is re-initialised from the detector
    reinit_iterations: int = 60       # L-BFGS iterations per step of that fit (flowmocap.fit.reinit.fit_to_detection)
    # --- observed flow -----------------------------------------------------------------
    flow_method: str = "dis-fine"     # observed flow (flowmocap.vision.FLOW_METHODS); DIS refined to full resolution
    flow_in_mask: bool = True         # E_f only on mask pixels when a mask is given
    flow_occlusion_check: bool = False  # E_f only on pixels whose flow passes a forward-backward
                                        # consistency check (costs a second, forward flow per frame);
                                        # CMU protocol, 8 seeds: median 7.43/9.11 cm vs 7.17/9.18 without: off
    # --- Kalman filters ----------------------------------------------------------------
    kalman: bool = True
    kalman_rot_accel_noise: float = 0.02  # rad/frame^2, the joint filters' white angular acceleration; with their
                                          # 0.02 rad measurement noise it sets how much the prediction smooths
    torch_threads: int = 1            # torch threads while tracking: the per-frame problem is small, so one
                                      # thread is as fast, leaves a core to the flow of the next frame, and
                                      # keeps results independent of the machine's core count
    # --- initialisation ----------------------------------------------------------------
    init_keypoint_weight: float = 1.0     # robust 2D joints (px^2 scale)
    init_keypoint_sigma: float = 50.0     # Geman-McClure scale, px
    init_pose_prior_weight: float = 200.0  # towards the start pose, per rad^2, when the init states no rough pose
                                           # (automatic init: 1000 here took DAVIS body IoU from 0.714 to 0.657)
    init_rough_pose_weight: float = 1000.0  # the same when it does (joints it leaves out count as at rest): with
                                            # 15 deg of noise (CMU protocol, 8 seeds) frame 0 is 3.53 cm off at 1000,
                                            # 4.00 at 200, 4.76 at 50; tracked: median 6.35/8.57 cm vs 7.17/9.18 at 200
    init_shape_prior_weight: float = 5.0  # towards the mean shape
    init_iterations: int = 60
    init_flow_iterations: int = 30

    @classmethod
    def load(cls, path: str | Path | None = None, base: dict | None = None, **overrides) -> "TrackerConfig":
        """Defaults, updated from ``base`` (e.g. :data:`REAL_VIDEO`), then from a JSON file,
        then from keyword overrides (None values are ignored)."""
        values = {}
        if path is not None:
            try:
                values = json.loads(Path(path).read_text())
            except FileNotFoundError:
                raise InputError(f"config file {path} does not exist.") from None
            except json.JSONDecodeError as e:
                raise InputError(f"config file {path} is not valid JSON: {e}") from None
            if not isinstance(values, dict):
                raise InputError(f"config file {path} must hold a JSON object of settings.")
        values = {**(base or {}), **values}
        values.update({k: v for k, v in overrides.items() if v is not None})
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise InputError(f"unknown config settings {unknown}; known: {sorted(names)}.")
        if "stages" in values:
            values["stages"] = tuple(tuple(int(l) for l in s) for s in values["stages"])
        cfg = cls(**values)
        if cfg.optimizer not in ("lbfgs", "lm"):
            raise InputError(f"optimizer must be 'lbfgs' or 'lm'; got {cfg.optimizer!r}.")
        if cfg.optimizer == "lm" and cfg.silhouette_model != "mesh":
            raise InputError("optimizer 'lm' needs silhouette_model 'mesh' (the capsule silhouette has no "
                             "cheap Jacobian); set both.")
        if not cfg.anchor_weight >= 0:
            raise InputError(f"anchor_weight must be >= 0; got {cfg.anchor_weight!r}.")
        if cfg.optimizer == "lm" and (cfg.anchor_weight > 0 or cfg.limb_depth_weight > 0):
            raise InputError("anchor_weight and limb_depth_weight work with optimizer 'lbfgs' only; set both 0 "
                             "for 'lm'.")
        if not cfg.kalman_rot_accel_noise > 0:
            raise InputError(f"kalman_rot_accel_noise must be > 0; got {cfg.kalman_rot_accel_noise!r}.")
        if not cfg.occlusion_temporal_gain >= 0:
            raise InputError(f"occlusion_temporal_gain must be >= 0; got {cfg.occlusion_temporal_gain!r}.")
        if not (cfg.init_pose_prior_weight >= 0 and cfg.init_rough_pose_weight >= 0):
            raise InputError(f"init_pose_prior_weight and init_rough_pose_weight must be >= 0; got "
                             f"{cfg.init_pose_prior_weight!r}, {cfg.init_rough_pose_weight!r}.")
        if not (cfg.limb_depth_weight >= 0 and cfg.limb_depth_sigma > 0):
            raise InputError(f"limb_depth_weight must be >= 0 and limb_depth_sigma > 0; got "
                             f"{cfg.limb_depth_weight!r}, {cfg.limb_depth_sigma!r}.")
        if not (cfg.keypoint_weight >= 0 and cfg.keypoint_sigma > 0):
            raise InputError(f"keypoint_weight must be >= 0 and keypoint_sigma > 0; got {cfg.keypoint_weight!r}, "
                             f"{cfg.keypoint_sigma!r}.")
        if not (0 <= cfg.reinit_min_iou <= 1 and cfg.reinit_max_joint_error > 0 and int(cfg.reinit_patience) >= 1
                and int(cfg.reinit_iterations) >= 1):
            raise InputError(f"reinit_min_iou must be in [0, 1], reinit_max_joint_error > 0, reinit_patience and "
                             f"reinit_iterations positive integers; got {cfg.reinit_min_iou!r}, "
                             f"{cfg.reinit_max_joint_error!r}, {cfg.reinit_patience!r}, {cfg.reinit_iterations!r}.")
        if int(cfg.torch_threads) != cfg.torch_threads or cfg.torch_threads < 1:
            raise InputError(f"torch_threads must be a positive integer; got {cfg.torch_threads!r}.")
        if cfg.temporal_reference not in ("previous", "prediction"):
            raise InputError(f"temporal_reference must be 'previous' or 'prediction'; got {cfg.temporal_reference!r}.")
        if cfg.silhouette_model not in ("capsules", "mesh"):
            raise InputError(f"silhouette_model must be 'capsules' or 'mesh'; got {cfg.silhouette_model!r}.")
        for s in cfg.stages:
            if not s or any(l < 0 or l >= cfg.levels for l in s):
                raise InputError(f"stages {cfg.stages} must name pyramid levels 0..{cfg.levels - 1}.")
        return cfg

    def to_dict(self) -> dict:
        d = asdict(self)
        d["stages"] = [list(s) for s in self.stages]
        return d
