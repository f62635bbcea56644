"""All tracker weights and settings in one place, with defaults, named profiles and checks.

A config file is JSON with any subset of the fields of :class:`TrackerConfig`, e.g.

    {"flow_weight": 1.0, "levels": 3, "iterations": 25}

:meth:`TrackerConfig.load` layers, lowest first: the defaults, a named profile from
:data:`PROFILES` (``"synthetic"``: the defaults; ``"video"``: real video with automatic
masks), ``base``, the config file, keyword overrides. Every value is checked when a
:class:`TrackerConfig` is constructed, however it was made; a mistake is an
:class:`~flowmocap.errors.InputError` that names the setting, the value and what is
expected. What each setting does, its unit and how its value was measured:
``docs/settings.md``.

Energies are normalised so that the defaults need no retuning across image sizes:
``E_f`` and ``E_c`` are divided by the number of person pixels (mask or model).
"""

from __future__ import annotations

import json
import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from flowmocap.errors import InputError
from flowmocap.vision import FLOW_METHODS

#: Named settings profiles, each a partial config over the defaults (``docs/settings.md``
#: says what each changes and how that was measured).
PROFILES: dict[str, dict[str, Any]] = {
    # exact body masks, no per-frame detections: the defaults
    "synthetic": {},
    # a segmenter's mask of a dressed person and 2D joints on every frame: E_c from the mesh,
    # stronger, and a refit from the detections wherever the silhouette IoU drops or the 3D
    # joints stay 7 cm from the detector's (kept after three refits in a row turned down for the
    # silhouette alone, at an IoU of at least 0.8); after tracking, the body's proportions half-way
    # towards the lifter's, its girth held (the shape was fitted on one frame's automatic mask),
    # and the limbs the detector cannot see half-way towards its own 3D in the refit
    "video": {"silhouette_model": "mesh", "silhouette_weight": 20.0, "silhouette_a": 0.4,
              "reinit_min_iou": 0.8, "reinit_patience": 1, "init_keypoint_weight": 0.3,
              "reinit_max_joint3d_error": 0.07, "lifter_refit_shape_share": 0.5, "lifter_refit_shape_girth": 0.005,
              "lifter_refit_hidden_share": 0.5, "reinit_3d_insist": 3},
}

#: ``track(fast=True)`` / ``flowmocap track --fast``: settings over the profile's, faster
#: at some cost in the 2D fit on real video (docs/settings.md, "Speed and --fast", has the
#: measurements): every L-BFGS run stops at a stall ten times larger than the default's, a
#: refit's steps get two thirds of the default's iterations, and a refit that is turned
#: down doubles the wait before the next attempt, up to 8 frames, and the detector runs
#: MediaPipe's "full" landmark model (the wheel's own, faster than the default heavy one)
#: with its :data:`NETWORK_SETTINGS`.
#: ``track(fast=True)`` also runs the detector without its mask augmentation
#: (flowmocap.pipeline); together, on the real clips, 0.74x the defaults' time before the
#: heavy model became the default (docs/settings.md).
#: Settings tied to the landmark network that gives the detections (each network's confidence
#: means something else): ``track(detector=...)`` / ``--detector`` lays the named network's
#: under the config file, and ``--fast`` carries full's. Heavy's are the defaults: it places the
#: joints it calls hidden within 6-9 px, so ``E_j`` and the lifter use every joint it gives;
#: full's low-confidence joints are 11-13 px off, so they are left out below 0.5
#: (docs/experiments.md, "Every keypoint the heavy network gives, weighed alike").
NETWORK_SETTINGS: dict[str, dict[str, Any]] = {
    "heavy": {"keypoint_min_confidence": 0.0, "keypoint_confidence_floor": 1.0, "lifter_refit_min_confidence": 0.0},
    "full": {"keypoint_min_confidence": 0.5, "keypoint_confidence_floor": 0.0, "lifter_refit_min_confidence": 0.5},
}

FAST_SETTINGS: dict[str, Any] = {"rel_tolerance": 1e-3, "reinit_iterations": 20, "reinit_max_wait": 8,
                                 "detector_model": "full", **NETWORK_SETTINGS["full"]}

#: Settings that no longer exist, with what happens now; a config naming one is refused.
REMOVED_SETTINGS: dict[str, str] = {
    "occlusion_temporal_gain": "E_theta weighs every joint alike (temporal_weight), hidden or not",
    "flow_occlusion_check": "E_f uses every person pixel (flow_in_mask) without a forward-backward "
                            "flow consistency check",
    "temporal_reference": "E_theta always pulls towards the Kalman prediction, never the previous pose",
    "optimizer": "every frame is optimised with L-BFGS (the Levenberg-Marquardt solver is gone); "
                 "'iterations' sets its iterations per stage",
}


def profile_names() -> list[str]:
    """The names :meth:`TrackerConfig.load` accepts as ``profile``."""
    return list(PROFILES)


# What each number setting must satisfy (checked in TrackerConfig.__post_init__).
_AT_LEAST_0, _ABOVE_0, _UNIT, _AT_LEAST_1 = ">= 0", "> 0", "in [0, 1]", ">= 1"
_HEIGHT = "0 (not known) or a height in metres in [0.5, 2.5]"
_SECONDS = "in [0, 86400] (seconds; a day at most)"
_LEVELS = "in [1, 16] (the flow's pyramid levels)"
_THREADS = "in [1, 1024]"
_RANGE_OK = {
    _AT_LEAST_0: lambda v: v >= 0,
    _ABOVE_0: lambda v: v > 0,
    _UNIT: lambda v: 0 <= v <= 1,
    _AT_LEAST_1: lambda v: v >= 1,
    _HEIGHT: lambda v: v == 0 or 0.5 <= v <= 2.5,  # flowmocap.body.stature.STATURE_RANGE_M
    _SECONDS: lambda v: 0 <= v <= 86400,  # beyond, frames = seconds x fps overflows to infinity
    _LEVELS: lambda v: 1 <= v <= 16,  # flowmocap.render.flow's pyramid
    _THREADS: lambda v: 1 <= v <= 1024,
}
_RANGES: dict[str, str] = {
    "flow_weight": _AT_LEAST_0, "silhouette_weight": _AT_LEAST_0, "silhouette_a": _UNIT,
    "limit_weight": _AT_LEAST_0, "penetration_weight": _AT_LEAST_0, "temporal_weight": _AT_LEAST_0,
    "anchor_weight": _AT_LEAST_0, "levels": _LEVELS, "iterations": _AT_LEAST_1, "rel_tolerance": _AT_LEAST_0,
    "uncovered_prior_weight": _AT_LEAST_0,
    "keypoint_weight": _AT_LEAST_0, "keypoint_sigma": _ABOVE_0, "keypoint_min_confidence": _UNIT,
    "keypoint_confidence_floor": _UNIT,
    "keypoint_hold_sigma": _ABOVE_0, "keypoint_hold_weight": _AT_LEAST_0,
    "keypoint_hold_frames": _AT_LEAST_0, "hold_unseen_frames": _AT_LEAST_0,
    "limb_depth_weight": _AT_LEAST_0, "limb_depth_sigma": _ABOVE_0, "capsule_grid_step": _AT_LEAST_1,
    "detector3d_weight": _AT_LEAST_0, "detector3d_scale": _ABOVE_0, "flip_iterations": _AT_LEAST_0,
    "flip_vote_frames": _AT_LEAST_0, "flip_vote_reach": _AT_LEAST_0,
    "reinit_max_joint3d_error": _AT_LEAST_0, "reinit_3d_patience": _AT_LEAST_1, "reinit_3d_keep_iou": _UNIT,
    "reinit_3d_insist": _AT_LEAST_0,
    "reinit_max_wait": _AT_LEAST_1, "reinit_iou_per_joint_error": _AT_LEAST_0,
    "pose_prior_weight": _AT_LEAST_0, "init_learned_prior_weight": _AT_LEAST_0,
    "depth_temporal_weight": _AT_LEAST_0, "depth_smoothing_s": _SECONDS, "lifter_refit_weight": _UNIT,
    "lifter_refit_pixel_sigma": _AT_LEAST_0, "pose_smoothing_s": _SECONDS, "lifter_refit_iterations": _AT_LEAST_1,
    "lifter_refit_vote_frames": _AT_LEAST_0, "lifter_refit_vote_reach": _AT_LEAST_0, "lifter_refit_seam_s": _SECONDS,
    "lifter_refit_shape_share": _UNIT, "lifter_refit_shape_girth": _AT_LEAST_0, "lifter_refit_bridge_s": _SECONDS,
    "lifter_refit_min_confidence": _UNIT,
    "lifter_refit_hidden_share": _UNIT, "detector3d_ray_share": _UNIT,
    "stance_depth_share": _UNIT, "stance_speed": _ABOVE_0, "stance_min_s": _SECONDS, "stance_window_s": _SECONDS,
    "reinit_min_iou": _UNIT, "reinit_max_joint_error": _ABOVE_0, "reinit_patience": _AT_LEAST_1,
    "reinit_iterations": _AT_LEAST_1, "reinit_depth_weight": _AT_LEAST_0,
    "kalman_rot_accel_noise": _ABOVE_0, "torch_threads": _THREADS,
    "init_keypoint_weight": _AT_LEAST_0, "init_keypoint_sigma": _ABOVE_0,
    "init_pose_prior_weight": _AT_LEAST_0, "init_rough_pose_weight": _AT_LEAST_0,
    "init_shape_share": _UNIT, "init_shape_girth": _AT_LEAST_0, "body_height_m": _HEIGHT,
    "init_shape_prior_weight": _AT_LEAST_0, "init_detector3d_weight": _AT_LEAST_0, "init_iterations": _AT_LEAST_1,
    "init_flow_iterations": _AT_LEAST_1,
}
_CHOICES: dict[str, tuple[str, ...]] = {
    "silhouette_model": ("capsules", "mesh"),
    "flow_method": tuple(FLOW_METHODS),
    "depth_temporal_reference": ("previous", "prediction"),
    "detector3d_source": ("mediapipe", "lifter", "both"),
    "lifter_refit_blend": ("full", "depth"),
    "lifter_refit_vote_sources": ("detector", "lifter", "both"),
    "detector_model": ("full", "heavy"),
}


def _bad(name: str, value: Any, expected: str) -> InputError:
    return InputError(f"config setting {name!r} must be {expected}; got {value!r}"
                      f"{'' if value is None else f' ({type(value).__name__})'}.")


#: Settings that turn off the depth cues added for generalisation (issue 18: ``E_3d`` in
#: the frames and the joint fits, the per-limb flip test, the learned prior ``E_p``, the
#: 3D re-initialisation criterion, the root-depth term ``E_z``), leaving the tracker of before them; e.g.
#: ``TrackerConfig.load(None, **DEPTH_CUES_OFF)`` or the same as a config file.
DEPTH_CUES_OFF: dict = {"detector3d_weight": 0.0, "init_detector3d_weight": 0.0, "flip_test": False,
                        "pose_prior_weight": 0.0, "init_learned_prior_weight": 0.0,
                        "reinit_max_joint3d_error": 0.0, "depth_temporal_weight": 0.0, "lifter_refit_weight": 0.0}


@dataclass
class TrackerConfig:
    """Every setting of the tracker, its initialisation, re-initialisation and the steps after
    tracking, with the defaults of the ``synthetic`` profile (:data:`PROFILES` holds the
    ``video`` profile's overrides). Units are in each field's comment (weights are
    dimensionless, distances in metres unless marked px, times in seconds); each field is
    described with its measurements in ``docs/settings.md``. Every value is checked on
    construction (``__post_init__``: ranges, choices; a bad one raises ``InputError``), and
    :meth:`from_dict` refuses unknown names.
    """

    # --- per-frame objective (paper Eq. 4) --------------------------------------------
    flow_weight: float = 1.0           # lambda_f, E_f: the rendered flow must match the observed flow
    silhouette_weight: float = 5.0     # lambda_c, E_c: keeps the body inside the person's mask
    silhouette_a: float = 0.6          # a in E_c: > 0.5 tolerates masks wider than the body (clothes)
    occluders_unknown: bool = True     # E_c and the refits' IoU: pixels where other people are seen
    #                                    (PersonTrack.others) may hide the person: the body may cover them
    limit_weight: float = 10.0         # lambda_b, E_b: soft joint limits rule out impossible poses
    penetration_weight: float = 10.0   # lambda_sp, E_sp: limbs must not pass through each other
    temporal_weight: float = 0.5       # lambda_theta, E_theta: towards the Kalman prediction, smooths
    anchor_weight: float = 0.5         # lambda_a, E_a: towards the stated first pose, against drift
    anchor_any_start: bool = False     # E_a also from a start nobody stated (the automatic init), and
    #                                    from each re-initialisation's pose (else E_a ends there)
    levels: int = 3                    # Gaussian pyramid levels of E_f, for motions beyond a few px
    stages: tuple[tuple[int, ...], ...] = ((2,), (0, 1, 2))  # coarse to fine: levels used per stage
    iterations: int = 20               # L-BFGS iterations per stage
    rel_tolerance: float = 1e-4        # an L-BFGS run (frame stage, init or refit step) stops once 5
    #                                    evaluations improve its energy by less than this fraction; 0: never
    #                                    (1e-4, once --fast, on all three suites: docs/settings.md "Speed")
    keypoint_weight: float = 0.05      # lambda_j: detected 2D joints keep the body on the person
    keypoint_sigma: float = 20.0       # its Geman-McClure scale, px: a left/right swap saturates
    keypoint_min_confidence: float = 0.0  # E_j uses a detected joint at this confidence or more (0: every
    #                                       joint detected), weighed by its confidence raised to at least ...
    keypoint_confidence_floor: float = 1.0  # ... this (1: all alike); the lost-joint hold and the swap check
    #                                       read the same weights. The heavy network places the joints it
    #                                       calls hidden within 6-9 px; the full network's: NETWORK_SETTINGS
    keypoint_hold_frames: int = 5      # a joint whose confident detection the fit has been far from (and
    #                                    not swapped) for this many frames in a row gets ...; 0: off
    keypoint_hold_sigma: float = 80.0  # ... this E_j scale, px, and ...
    keypoint_hold_weight: float = 4.0  # ... its weight times this until it is back (fit.tracker.lost_joints)
    hold_unseen_frames: int = 15       # in a run of more than this many frames without the person (an
    #                                    occluder, a cut, out of view: the detector's tracks joined across
    #                                    it, vision.auto.link_tracks), the body is held at the last seen pose
    #                                    instead of tracked by flow alone; 0: never held
    detector_swap_check: bool = True   # per frame, a detection that labels the whole body left for right
    #                                    against the prediction is exchanged back, 2D and 3D, for the frame's
    #                                    terms and its re-initialisation check (fit.swap); False: as it comes
    detector_model: str = "heavy"      # MediaPipe's landmark model for the 2D and 3D joints (vision.detect.MODELS):
    #                                    "heavy" (shipped with flowmocap; its visibility put on full's scale) or "full"
    #                                    (in mediapipe's wheel; faster)
    detector_keypoints: bool = True    # input with its own masks and init: the detector's 2D joints of
    #                                    every frame too (E_j, and refits where tracking fails)
    keypoint_offsets: bool = True      # compare the body with the detector's joints where the detector
    #                                    puts them on a body (learned offsets, vision.keypoint_map)
    limb_depth_weight: float = 2.0     # lambda_d, E_d: the detector's 3D joints resolve depth flips
    limb_depth_sigma: float = 0.3      # its Geman-McClure scale (a difference of sines)
    capsule_grid_step: int = 8         # px between exact samples of the capsule distance map C_M
    silhouette_model: str = "capsules"  # S_M/C_M of E_c: "capsules" (paper) or the "mesh" itself
    detector3d_weight: float = 100.0   # lambda_3d, E_3d: detector's 3D joints after a similarity; 0: off
    detector3d_scale: float = 0.1      # its pseudo-Huber scale, m: quadratic below, linear above
    detector3d_source: str = "mediapipe"  # the 3D keypoints of E_d, E_3d and the 3D refit criterion: the
    #                                    detector's own ("mediapipe"), flowmocap.vision.lifter's ("lifter")
    #                                    or the mean of the two ("both")
    detector3d_ray_share: float = 1.0  # share, in [0, 1], of the turn from the ray through the person into the
    #                                    camera's axes given to the detector's own 3D (MediaPipe's world
    #                                    landmarks) where it is used: 1 takes them to be in the ray's axes;
    #                                    under a camera's turn they turn by about half of it themselves
    #                                    (docs/experiments.md, "A turning camera made from a still one").
    #                                    The lifter's 3D, trained in the ray's axes, always takes the whole turn
    flip_test: bool = True             # per frame, try each limb mirrored in depth; keep it if E is lower
    flip_iterations: int = 0           # L-BFGS iterations on each mirrored pose before comparing
    flip_vote_frames: int = 0          # in the tracker: a limb the detector's 3D sees reaching the other way in
    #                                    depth for this many frames in a row is mirrored (SequenceTracker.
    #                                    vote_flips; the refit's lifter_refit_vote_frames after tracking); 0: off
    flip_vote_reach: float = 0.08      # m: ... where both reach further than this along the camera's axis
    flip_without_temporal: bool = False  # judge a flip by the energy without E_theta (whose Kalman
                                       # prediction carries a flipped limb on to the next frames)
    pose_prior_weight: float = 0.01    # lambda_p, E_p: the learned pose prior (GMM, nats); 0: off
    uncovered_prior_weight: float = 0.0  # per rad^2, added to E_p: the joints the learned prior does not
    #                                    cover (spine3, collars, feet, hands) towards rest; 0: off
    depth_temporal_weight: float = 0.0  # lambda_z, E_z: root depth along the camera ray towards a
    #                                    reference (m^2); 0: off (measured, not better: docs/experiments.md)
    depth_temporal_reference: str = "prediction"  # E_z's reference: the Kalman "prediction" or the "previous" frame
    depth_smoothing_s: float = 0.5     # s: the finished motion's root distance from the camera smoothed over
    #                                    this window (Savitzky-Golay, degree 1; fit.smooth.smooth_root_depth)
    #                                    between re-initialisations; 0: off (the tracker's own frames)
    lifter_refit_weight: float = 0.5   # after tracking (and the depth smoothing): each frame's body refitted
    #                                    towards its keypoints blended with this share of the lifter's
    #                                    (fit.lift_refit; lifter_refit_blend says how); 0: off
    lifter_refit_blend: str = "full"  # the refit's targets: the fit's keypoints blended with the lifter's in all
    #                                    three coordinates ("full") or only in depth along each ray ("depth", the
    #                                    default until 2026-11-28; docs/experiments.md, "The full blend with a 4 px hold")
    lifter_refit_iterations: int = 60  # L-BFGS iterations of the lifter refit (each chunk of frames)
    lifter_refit_pixel_sigma: float = 4.0  # px: the refit also holds the tracked 24 joints' image at this
    #                                    scale (fit.lift_refit.refit_energy), for the overlay; 0: off (6 px with
    #                                    the "depth" blend until 2026-11-28)
    lifter_refit_vote_frames: int = 3  # before the refit: a limb mirrored in depth over each run of at least
    #                                    this many frames in which the detector's own 3D reaches with it the
    #                                    other way (fit.lift_refit.vote_flip_frames; docs/experiments.md); 0: off
    lifter_refit_vote_reach: float = 0.08  # m: ... where both reach further than this along the camera's axis
    lifter_refit_vote_sources: str = "detector"  # who votes: the "detector"'s 3D, the "lifter"'s, or "both"
    lifter_refit_seam_s: float = 0.3  # s: before the refit, the tracked frames before each re-initialisation on
    #                                    3D disagreement eased into the pose it restarted from over this long
    #                                    (fit.smooth.seam_blend; the refit still holds the tracked image); the
    #                                    smoothing steps after it then run across that seam instead of starting
    #                                    again there (docs/experiments.md, twenty-fifth session); 0: off
    lifter_refit_shape_share: float = 0.0  # before the refit: the body's bone proportions moved this share of the
    #                                    way towards the lifter's (median over the frames; fit.lift_refit.fit_proportions),
    #                                    the refit then runs with that shape; 0: the tracked shape stays (the video
    #                                    profile: 0.5; docs/experiments.md, twenty-ninth session)
    lifter_refit_shape_girth: float = 0.0  # m: with lifter_refit_shape_share, the body's girth along its bones
    #                                    (fit.lift_refit.body_girth) held at this scale while its proportions move; 0: not held
    #                                    (the video profile: 0.005)
    lifter_refit_min_confidence: float = 0.0  # the lifter reads a detected point at this confidence or more
    #                                          as given (> 0), the others as missing (full's: NETWORK_SETTINGS)
    lifter_refit_bridge_s: float = 0.0  # s: a detected point missing for at most this long between two frames that
    #                                    have it is filled by a straight line before the refit's lifter reads the
    #                                    2D (vision.lifter.bridge_gaps); 0: the lifter guesses it
    lifter_refit_hidden_share: float = 0.0  # share, in [0, 1]: a keypoint the detector gives below confidence 0.5 (a
    #                                    limb it cannot see) has its refit target moved this share of the way to the
    #                                    detector's own 3D point, and the refit's image hold lets go of it; 0: off
    #                                    (the video profile: 0.5; docs/experiments.md, thirty-third session)
    lifter_refit_smooth_depth: bool = True  # the refitted motion's root depth smoothed again (the window of
    #                                    depth_smoothing_s; the refit moves each frame's depth on its own)
    stance_depth_share: float = 0.5    # after the refit: each frame moved along the ray through its root by
    #                                    this share of what keeps a foot that stands still in the image at its
    #                                    median depth over the stance (fit.smooth.stance_depth_shift; chosen on
    #                                    the tune suite, docs/experiments.md); 0: off
    stance_speed: float = 0.12         # body heights per second: a foot slower than this in the image stands
    stance_min_s: float = 0.2          # s: ... for at least this long
    stance_window_s: float = 0.25      # s: the depth correction's moving average
    pose_smoothing_s: float = 0.3      # s: last, the finished motion's joint rotations (on SO(3)) and translation
    #                                    smoothed over this window (Savitzky-Golay, degree 2: fit.smooth.
    #                                    pose_smoothed_motion; the export's --smooth filter) between
    #                                    re-initialisations; 0: off
    # --- re-initialisation (real video with detections; flowmocap.fit.reinit) -----------
    reinit_min_iou: float = 0.5        # a frame is bad below this silhouette IoU with the mask
    reinit_max_joint_error: float = 0.15  # ... or above this median 2D joint distance / height
    reinit_patience: int = 3           # bad frames in a row before a refit, so noise triggers none
    reinit_iterations: int = 30        # L-BFGS iterations per step of that refit (60 before 2026-11-26)
    reinit_depth_weight: float = 0.0   # px^2 per (relative change)^2: a refit's root stays near the tracked
    #                                    frame's distance from the camera (1e5: a 10 % jump costs 1e3); 0: off
    #                                    (1e5 made real3d worse on all 6 person-views with refits: experiments.md)
    reinit_max_joint3d_error: float = 0.1  # m: a frame is 3D-bad above this aligned joint error; 0: off
    reinit_3d_patience: int = 3        # 3D-bad frames in a row before a refit
    reinit_3d_keep_iou: float = 0.0    # a refit on 3D disagreement whose silhouette IoU drops by more than
    #                                    reinit.IOU_TOLERANCE is kept all the same at an IoU of at least this;
    #                                    0: off (0.8 tried: docs/settings.md)
    reinit_3d_insist: int = 0          # after this many 3D refits in a row turned down for the silhouette (the
    #                                    disagreement lasting), the next are kept at an IoU of at least
    #                                    reinit_min_iou, until one is kept or the frames agree again; 0: off
    #                                    (the video profile's 3: docs/settings.md)
    reinit_iou_per_joint_error: float = 0.0  # a refit on the image criterion may cost this much more silhouette
    #                                    IoU per unit (of the person's height) its median 2D joint error comes
    #                                    closer, on top of reinit.IOU_TOLERANCE; 0: off
    reinit_max_wait: int = 1           # frames: each refit turned down doubles the wait before the next
    #                                    attempt (from the patience) up to this; 1: no back-off
    # --- observed flow -----------------------------------------------------------------
    flow_method: str = "dis-fine"      # flowmocap.vision.FLOW_METHODS; DIS refined to full resolution
    flow_in_mask: bool = True          # E_f only on mask pixels: the background's flow is not the body's
    flow_region: bool = False          # with flow_in_mask: compute the observed flow only around the person
    #                                    (both frames' masks plus a margin, vision.flow_region), 0 elsewhere
    # --- Kalman filters ----------------------------------------------------------------
    kalman: bool = True                # predict each frame's start and E_theta's target
    kalman_rot_accel_noise: float = 0.02  # rad/frame^2: how much the joint filters' prediction smooths
    torch_threads: int = 1             # the per-frame problem is small; keeps a core for the next flow
    # --- initialisation ----------------------------------------------------------------
    init_keypoint_weight: float = 1.0     # robust 2D joints of frame 0 (px^2 scale)
    init_keypoint_sigma: float = 50.0     # their Geman-McClure scale, px
    init_pose_prior_weight: float = 20.0  # towards the start pose when the init states no pose (200 before
    #                                    2026-11-28: it held the automatic start near the rest pose)
    init_rough_pose_weight: float = 1000.0  # towards the stated rough pose: trusts a noisy one
    init_shape_prior_weight: float = 5.0  # towards the mean shape: 2D joints barely constrain it
    init_shape_share: float = 0.0      # after frame 0's shape fit, before tracking: the body's bone proportions
    #                                    (in frame 0's pose) moved this share of the way towards the median of the
    #                                    lifter's (of the detector's 2D keypoints) over the video's frames
    #                                    (fit.init.shape_towards_seen); 0: frame 0's shape stays. Tried at 0.5
    #                                    on video, off (docs/experiments.md, thirtieth session)
    init_shape_girth: float = 0.0      # m: with init_shape_share, the body's girth along its bones held at this
    #                                    scale (fit.lift_refit.body_girth); 0: not held
    body_height_m: float = 0.0         # m: the person's stated standing height (track --height); the body is given
    #                                    that stature after frame 0's shape fit and after the refit's shape step
    #                                    (flowmocap.body.stature.with_stature); 0: not known, the fit's own size
    init_detector3d_weight: float = 3e4   # E_3d in the init's and the refits' joint fits (px^2 scale); 0: off
    init_learned_prior_weight: float = 5.0  # E_p in the init's and the refits' joint fits (px^2 scale); 0: off
    init_iterations: int = 60          # L-BFGS iterations per init step
    init_flow_iterations: int = 30     # L-BFGS iterations of the init's flow step (frames 0 and 1)

    def __post_init__(self) -> None:
        for f in fields(self):
            name, value, kind = f.name, getattr(self, f.name), f.type
            if name == "stages":
                value = self._check_stages(value)
            elif kind == "bool":
                if not isinstance(value, (bool, np.bool_)):
                    raise _bad(name, value, "true or false")
                value = bool(value)  # numpy's (arr.any()) as Python's: JSON, equality
            elif kind == "int":
                if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                    raise _bad(name, value, f"an integer {_RANGES[name]}")
                value = int(value)
            elif kind == "float":
                if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
                    raise _bad(name, value, f"a finite number {_RANGES[name]}")
                value = float(value)
            elif kind == "str":
                if not isinstance(value, str) or value not in _CHOICES[name]:
                    raise _bad(name, value, "one of " + ", ".join(repr(c) for c in _CHOICES[name]))
            else:  # a new field needs a check here
                raise AssertionError(f"no check for setting {name!r} of type {kind}")
            if name in _RANGES and not _RANGE_OK[_RANGES[name]](value):
                raise _bad(name, value, f"{'an integer' if kind == 'int' else 'a number'} {_RANGES[name]}")
            setattr(self, name, value)
        for stage in self.stages:
            if any(level >= self.levels for level in stage):
                raise _bad("stages", self.to_dict()["stages"],
                           f"lists of pyramid levels 0..{self.levels - 1} (levels is {self.levels})")

    @staticmethod
    def _check_stages(value: Any) -> tuple[tuple[int, ...], ...]:
        expected = "a non-empty list of non-empty lists of pyramid levels (integers >= 0), e.g. [[2], [0, 1, 2]]"
        seq = lambda x: isinstance(x, Sequence) and not isinstance(x, (str, bytes))  # noqa: E731
        if not seq(value) or not value or not all(seq(s) and s for s in value):
            raise _bad("stages", value, expected)
        if not all(not isinstance(l, bool) and isinstance(l, numbers.Integral) and l >= 0 for s in value for l in s):
            raise _bad("stages", value, expected)
        return tuple(tuple(int(l) for l in s) for s in value)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any], source: str = "config") -> "TrackerConfig":
        """A config from a dict of settings over the defaults; a removed or unknown setting
        is an :class:`InputError` (``source`` says where the dict came from)."""
        check_setting_names(values, source)
        return cls(**values)

    @classmethod
    def load(cls, path: str | Path | Mapping[str, Any] | None = None, profile: str | None = "synthetic",
             base: Mapping[str, Any] | None = None, **overrides: Any) -> "TrackerConfig":
        """The defaults, updated from the named ``profile`` (a key of :data:`PROFILES`; None
        counts as ``"synthetic"``), then from ``base``, then from the JSON file at ``path``
        (or a dict in its place), then from keyword overrides (None values are ignored)."""
        profile = "synthetic" if profile is None else profile
        if not isinstance(profile, str) or profile not in PROFILES:
            raise InputError(f"unknown settings profile {profile!r}; known: {', '.join(PROFILES)}.")
        if isinstance(path, Mapping):
            values, where = dict(path), "config"
        elif path is None:
            values, where = {}, "config"
        elif isinstance(path, (str, Path)):
            where = f"config file {path}"
            try:
                values = json.loads(Path(path).read_text())
            except FileNotFoundError:
                raise InputError(f"config file {path} does not exist.") from None
            except IsADirectoryError:
                raise InputError(f"config file {path} is a folder, not a JSON file.") from None
            except (json.JSONDecodeError, UnicodeDecodeError) as e:
                raise InputError(f"config file {path} is not valid JSON: {e}") from None
            if not isinstance(values, dict):
                raise InputError(f"config file {path} must hold a JSON object of settings.")
        else:
            raise InputError(f"a config is a JSON file's path or a dict of settings; got {type(path).__name__}.")
        if base is not None and not isinstance(base, Mapping):
            raise InputError(f"base must be a dict of settings; got {type(base).__name__}.")
        given = {k: v for k, v in overrides.items() if v is not None}
        check_setting_names(base or {}, "base settings")
        check_setting_names(values, where)
        check_setting_names(given, "config overrides")
        return cls(**{**PROFILES[profile], **(base or {}), **values, **given})

    @property
    def uses_detector3d(self) -> bool:
        """Whether any setting reads the detector's 3D joints (``E_d``, ``E_3d`` in the
        frames or the joint fits, the 3D re-initialisation criterion)."""
        return (self.limb_depth_weight > 0 or self.detector3d_weight > 0 or self.init_detector3d_weight > 0
                or self.reinit_max_joint3d_error > 0)

    def to_dict(self) -> dict:
        """All settings as a JSON-ready dict (``stages`` as lists), as ``run.json`` records them."""
        d = asdict(self)
        d["stages"] = [list(s) for s in self.stages]
        return d


def check_setting_names(values: Mapping[str, Any], source: str = "config") -> None:
    """Refuse a removed setting (saying what happens now) or an unknown one, or ``values``
    that are not a mapping of names to values."""
    if not isinstance(values, Mapping):
        raise InputError(f"{source}: the settings must be a dict of names to values (a JSON object); got "
                         f"{type(values).__name__}.")
    for name in values:
        if name in REMOVED_SETTINGS:
            raise InputError(f"{source}: setting {name!r} was removed: {REMOVED_SETTINGS[name]}. "
                             f"Delete it from the config.")
    names = {f.name for f in fields(TrackerConfig)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise InputError(f"{source}: unknown config settings {unknown}; known: {sorted(names)}.")


__all__ = ["TrackerConfig", "PROFILES", "FAST_SETTINGS", "REMOVED_SETTINGS", "profile_names", "check_setting_names"]
