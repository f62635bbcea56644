"""After tracking: each frame's body refitted towards a depth blend with the lifter (issue 18).

The tracker's fit and a 3D estimate from the 2D keypoints err in different ways: on the
real multi-view recording, half of each (the fit's keypoints aligned onto the lifter's
:mod:`flowmocap.vision.lifter` output, blended) scores about 13 % better than either
(``benchmarks/fusion_bound.py``). Inside the tracker such a cue is one voice among flow,
silhouette and priors, and the chaos of tracking moves single runs by more than it gains;
after tracking it can be applied to every frame alike. For each frame with a lifted pose:

1. ``F``: the fit's 13 keypoints (the detector's convention: the body's joints moved by
   :mod:`flowmocap.vision.keypoint_map`'s offsets, the head at the middle of the ears) in
   the camera's axes; ``A``: the lifter's 3D of the frame's detection, turned from the
   axes of the ray through the detected hips into the camera's
   (:meth:`~flowmocap.geometry.camera.PinholeCamera.ray_rotation`) and aligned onto
   ``F`` by a similarity (so only its shape counts, at the fit's place and size). The
   lifter reads the detection's 2D keypoints by default; ``lifter_input="fit"`` gives it
   the fit's own keypoints projected instead, ``"agree"`` the detected ones within
   :data:`AGREE_PX` of the fit's and the fit's elsewhere (both measured against the
   default in docs/experiments.md, "Where the real3d error comes from"; not the default).
2. The target of keypoint ``j``, with ``blend="full"`` (the pipeline's default,
   ``TrackerConfig.lifter_refit_blend``): ``(1 - w) F_j + w A_j`` (``w`` = ``weight``),
   all three coordinates blended; with ``blend="depth"`` (the pipeline's default until
   2026-11-28): ``F_j`` moved along its own camera ray to the depth ``(1 - w) z(F_j) + w
   z(A_j)``, the same pixel with a blended depth. Either way the image is also held by
   the third term of step 3 when ``pixel_sigma`` is given; the full blend with a 4 px
   hold moves the image a little more than the depth blend with 6 px did (real3d 1.7
   against 1.3 px) and is better in 3D on the real recording, level or better on the
   renders (docs/experiments.md, "The full blend with a 4 px hold").
3. The body's pose and translation are refitted to those targets by L-BFGS: ``sum_j |k_j -
   target_j|^2 / sigma^2 + sum |theta - theta_tracked|^2 / reg^2`` over the 23 joint
   rotations (m^2 / m^2 and rad^2 / rad^2); the shape stays. With ``pixel_sigma`` a third
   term holds the image: each of the 24 joints' squared pixel distance from where the
   tracked body put it, over ``pixel_sigma^2`` (the pipeline's default 4 px,
   ``TrackerConfig.lifter_refit_pixel_sigma``: the overlay moves less, the 3D gain stays
   nearly whole; docs/experiments.md).

Before step 1, with ``vote_min_frames`` > 0 (the pipeline's default 3,
``TrackerConfig.lifter_refit_vote_frames``), a limb the tracker left mirrored in depth is
turned back where the detector says so for a run of frames (:func:`vote_flip_frames`):
for each upper arm, forearm, thigh and shin in turn, where the detector's own 3D joints
(``vote_sources="detector"``, the default; turned into the camera's axes about the ray
through the detected hips and aligned onto ``F`` by a similarity per frame) and the fit
both reach more than ``vote_min_reach`` (0.08 m) from the limb's parent to its child along
the camera's axis, but opposite ways, in at least ``vote_min_frames`` frames in a row, the
tracked pose's limb is mirrored in those frames (:func:`~flowmocap.fit.flip.mirrored_rotvec`:
its child joint keeps its pixel and its distance from the parent). An upper arm's or
thigh's mirror also moves the wrist or ankle in the image; with ``vote_check_2d`` (default)
such a run is mirrored only if those land no further from the detected ones, summed over
the run. The refit then starts from, and is held to, the mirrored poses; its image term
(``pixel_sigma``) still holds the tracked body's image. Why: the tracker's per-frame flip
test decides by one frame's energy, in which flow and silhouette hardly tell a limb from
its mirror image, and a limb once flipped stays so (docs/experiments.md, eighteenth
session).

With ``shape_share`` > 0 (``TrackerConfig.lifter_refit_shape_share``), the body's shape is
refitted first, once for the whole motion: the tracker fits the betas on the first frame
alone, and on real people the fitted legs came out long against the torso (the real
multi-view recording: shin 0.79 of the torso at the keypoints against the reference's 0.68,
docs/experiments.md, twenty-ninth session). The lifter reads every frame's 2D, so the
median of its :func:`bone_proportions` over the lifted frames says what the images show;
:func:`fit_proportions` moves the betas until the body's proportions, in the tracked poses of
up to :data:`PROPORTION_FRAMES` of those frames, have moved ``shape_share`` of the way from
its own towards the lifter's. Steps 1-3 then run with that body (its image term still holds
the tracked body's image), and the tracker's betas are kept as ``betas_tracked``.

With ``hidden_share`` > 0 (``TrackerConfig.lifter_refit_hidden_share``; the ``video``
profile's 0.5), a keypoint the detector gives below confidence 0.5 in a frame, a limb it
cannot see, gets a different target in step 2: the blended one moved ``hidden_share`` of the
way to the detector's own 3D point (turned into the camera's axes like the vote's, aligned
onto ``F`` by a similarity fitted on the frame's confident points). And step 3's image term
lets go of that joint, and of the hand or foot below a wrist or ankle. The tracker had no 2D
for such a limb and the lifter leaves it out, so the tracked image there is no evidence; on
the real recording MediaPipe's guess for a hidden arm was the better one (docs/experiments.md,
thirty-third session). With ``bridge_s`` > 0, a keypoint missing for at most that long is first
filled by a straight line between the frames that have it (tried, off).

Frames without a lifted pose (no person, too few confident keypoints) keep the tracked
body. ``joints3d`` and ``joints2d`` are recomputed; the tracked poses are kept as
``poses_tracked``. The three 3D sources' disagreement per frame and joint
(:mod:`flowmocap.fit.disagreement`) is added as ``disagreement``: the refit does not use
it; it tells the user where the 3D is least sure.
"""

from __future__ import annotations

import copy
import json
from typing import Any

import numpy as np
import torch

from flowmocap.body.skeleton import EVAL_JOINTS, JOINT_INDEX
from flowmocap.errors import InputError
from flowmocap.fit.energies import DEPTH_LIMBS
from flowmocap.vision.lifter import MIRROR

__all__ = ["BLENDS", "LIFTER_INPUTS", "blend_targets", "body_girth", "bone_proportions", "fit_proportions", "keypoints13",
           "posed_joints_only",
           "lifter_refit_motion", "median_proportions", "posed_proportions", "proportions_towards", "refit_energy"]


#: the 2D the refit's lifter reads (:func:`lifter_refit_motion`'s ``lifter_input``)
LIFTER_INPUTS = ("detector", "fit", "agree", "unswap")
#: ``"agree"``: a detected point farther than this from the fit's (pixels) is replaced by the fit's
AGREE_PX = 20.0


#: frames posed at a time by the refit's passes over a whole motion without gradients
NO_GRAD_CHUNK = 1024


def posed_joints_only(model, betas: torch.Tensor, poses: torch.Tensor, trans: torch.Tensor):
    """The body's :class:`~flowmocap.body.model.BodyOutput` without vertices for ``poses
    (B, 72)`` radians and ``trans (B, 3)`` metres. ``betas`` ``(1, num_betas)`` (one shape for
    every frame) is shaped once and shared, so the memory does not grow by a shaped rest
    mesh per frame (about 0.17 MB a frame in float64: 3 GB for a 10-minute video);
    ``(B, num_betas)`` is shaped per row."""
    if betas.shape[0] == 1:
        return model(betas=betas, pose=poses, trans=trans, shaped=model.shaped(betas), with_vertices=False)
    return model(betas=betas, pose=poses, trans=trans, with_vertices=False)


def keypoints13(model, kmap, poses: torch.Tensor, betas: torch.Tensor, trans: torch.Tensor):
    """``(keypoints (B, 13, 3), joints (B, 24, 3))`` of posed bodies, world axes, metres:
    the 13 points in the order of :data:`~flowmocap.body.skeleton.EVAL_JOINTS` where the
    detector puts them (the head at the middle of the ears). Without gradients, a long
    motion is posed :data:`NO_GRAD_CHUNK` frames at a time (the same values, less memory).
    ``poses (B, 72)`` radians, ``betas (1, num_betas)`` or ``(B, num_betas)``, ``trans (B,
    3)`` metres, as for :func:`posed_joints_only`."""
    if not torch.is_grad_enabled() and len(poses) > NO_GRAD_CHUNK:
        parts = [keypoints13(model, kmap, poses[a:a + NO_GRAD_CHUNK], betas, trans[a:a + NO_GRAD_CHUNK])
                 for a in range(0, len(poses), NO_GRAD_CHUNK)]
        return torch.cat([k for k, _ in parts]), torch.cat([j for _, j in parts])
    out = posed_joints_only(model, betas, poses, trans)
    return _keypoints_of(kmap, out), out.joints


def _keypoints_of(kmap, out) -> torch.Tensor:
    """``(B, 13, 3)`` :func:`keypoints13`'s points of a posed body ``out`` (its joints and transforms)."""
    kp = kmap.apply(out.joints, out.transforms)[:, list(EVAL_JOINTS)]
    rot = out.transforms[:, kmap.ears_part, :3, :3]
    ears = torch.as_tensor(np.asarray(kmap.ears_offset), dtype=out.joints.dtype)
    head = out.joints[:, JOINT_INDEX["head"]] + (rot @ ears[:, None])[..., 0]
    return torch.cat([head[:, None], kp[:, 1:]], 1)


#: How the targets blend the fit with the lifter (:func:`blend_targets`).
BLENDS = ("full", "depth")


def blend_targets(fit_cam: np.ndarray, lifted_cam: np.ndarray, weight: float, blend: str = "depth") -> np.ndarray:
    """``(T, 13, 3)`` targets in the camera's axes (step 2 of the module docstring).

    Args:
        fit_cam: ``(T, 13, 3)`` the fit's keypoints, camera axes, metres (z > 0).
        lifted_cam: ``(T, 13, 3)`` the lifter's, camera axes (any origin and scale).
        weight: the lifter's share, in [0, 1].
        blend: ``"full"``: the three coordinates of each keypoint blended with the
            lifter's (aligned onto the fit by a similarity per frame); ``"depth"``: only
            the depth, each keypoint kept on its camera ray (its pixel unchanged).
    """
    from flowmocap.geometry.procrustes import similarity_procrustes

    if blend not in BLENDS:
        raise InputError(f"blend must be one of {BLENDS}; got {blend!r}.")
    fit_cam = np.asarray(fit_cam, np.float64)
    aligned = similarity_procrustes(np.asarray(lifted_cam, np.float64), fit_cam)[0]
    if blend == "full":
        return (1.0 - weight) * fit_cam + weight * aligned
    z = (1.0 - weight) * fit_cam[..., 2] + weight * aligned[..., 2]
    return fit_cam * (z / fit_cam[..., 2])[..., None]


#: The limbs a run of frames may be mirrored in depth by (:func:`vote_flip_frames`):
#: SMPL's (parent, child) bones, parents before children (:data:`~flowmocap.fit.energies.DEPTH_LIMBS`).
VOTE_LIMBS = DEPTH_LIMBS
#: Who votes (``vote_sources``): the lifter's 3D, the detector's own, or both together.
VOTE_SOURCES = ("detector", "lifter", "both")


#: the bones whose lengths :func:`bone_proportions` compares, as pairs of the 13 keypoints
#: (order of :data:`~flowmocap.body.skeleton.EVAL_JOINTS`), each side's pair averaged with the
#: other's: upper arm, forearm, thigh, shin, shoulder to hip, and the shoulders' and hips' width
PROPORTION_BONES = (((1, 3), (2, 4)), ((3, 5), (4, 6)), ((7, 9), (8, 10)), ((9, 11), (10, 12)),
                    ((1, 7), (2, 8)), ((1, 2),), ((7, 8),))


def bone_proportions(points):
    """``(..., 7)`` each bone of :data:`PROPORTION_BONES` (left and right averaged) as a share
    of their sum, so a body's size drops out: ``points (..., 13, 3)`` keypoints in the order of
    :data:`~flowmocap.body.skeleton.EVAL_JOINTS`, metres (numpy or torch)."""
    lib = torch if isinstance(points, torch.Tensor) else np
    lengths = [sum(((points[..., a, :] - points[..., b, :]) ** 2).sum(-1) ** 0.5 for a, b in pairs) / len(pairs)
               for pairs in PROPORTION_BONES]
    total = sum(lengths)
    return lib.stack([length / total for length in lengths], -1)


#: :func:`fit_proportions`: the proportions' scale (a share of the bones' sum) and the shape's
#: (betas, unit variance) in its energy: the proportions are met closely where the shape space
#: can reach them, the shape's term only settles what they leave free
PROPORTION_SIGMA = 0.005
SHAPE_SIGMA = 1.0
#: the fewest frames with a lifted pose for the shape to be refitted, and the most frames the
#: body's own proportions are measured at
PROPORTION_MIN_FRAMES = 10
PROPORTION_FRAMES = 32


def posed_proportions(model, kmap, betas: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
    """``(7,)`` the mean over ``poses (B, 72)`` of the body's :func:`bone_proportions` at its
    13 keypoints (the keypoints' offsets turn with the pose, so a body's proportions are
    measured in the poses it is compared in); ``betas (1, 10)``."""
    kp, _ = keypoints13(model, kmap, poses, betas, torch.zeros(len(poses), 3, dtype=poses.dtype))
    return bone_proportions(kp).mean(0)


def body_girth(model, betas: torch.Tensor) -> torch.Tensor:
    """``(V,)`` metres: each rest vertex's distance from the bone it mostly follows (the
    segment from its most-weighted joint to that joint's first child; the joint itself for
    a joint without children), for ``betas (1, 10)``: the body's girth along its bones,
    apart from their lengths."""
    from flowmocap.body.skeleton import PARENTS, children

    verts, joints = model.shaped(betas)
    verts, joints = verts[0], joints[0]
    main = model.weights.argmax(1)
    child = torch.as_tensor([(children(j) or [j])[0] for j in range(len(PARENTS))])
    a, b = joints[main], joints[child[main]]
    ab = b - a
    u = ((verts - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-12)
    return torch.linalg.norm(verts - (a + u.clamp(0, 1)[:, None] * ab), dim=-1)


def fit_proportions(model, kmap, betas: torch.Tensor, target: np.ndarray, poses: torch.Tensor | None = None,
                    iterations: int = 100, girth_sigma: float | None = None) -> torch.Tensor:
    """``(1, 10)`` betas whose body has the bone proportions ``target (7,)`` (:func:`posed_proportions`
    over ``poses (B, 72)``, radians; None: the rest pose), starting from and held to ``betas (1, 10)``:
    L-BFGS on ``sum |p(beta) - target|^2 / PROPORTION_SIGMA^2 + |beta - betas|^2 / SHAPE_SIGMA^2``;
    with ``girth_sigma`` (metres) also ``mean_v (g_v(beta) - g_v(betas))^2 / girth_sigma^2``, the
    body's :func:`body_girth` held."""
    poses = torch.zeros(1, 72, dtype=betas.dtype) if poses is None else poses.to(betas.dtype)
    goal = torch.as_tensor(np.asarray(target, np.float64), dtype=betas.dtype)
    b = betas.detach().clone().requires_grad_(True)
    girth0 = body_girth(model, betas).detach() if girth_sigma else None
    opt = torch.optim.LBFGS([b], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        e = ((posed_proportions(model, kmap, b, poses) - goal) ** 2).sum() / PROPORTION_SIGMA ** 2 \
            + ((b - betas) ** 2).sum() / SHAPE_SIGMA ** 2
        if girth_sigma:
            e = e + ((body_girth(model, b) - girth0) ** 2).mean() / girth_sigma ** 2
        e.backward()
        return e

    opt.step(closure)
    return b.detach()


def median_proportions(points: np.ndarray) -> np.ndarray | None:
    """``(7,)`` the median over frames of :func:`bone_proportions` of ``points (T, 13, 3)``
    (metres, :data:`~flowmocap.body.skeleton.EVAL_JOINTS`' order; NaN where a frame has no
    3D), over the frames with all 13 points; None with fewer than :data:`PROPORTION_MIN_FRAMES`
    such frames."""
    pts = np.asarray(points, np.float64)
    ok = np.isfinite(pts).all((1, 2)) if pts.ndim == 3 else np.zeros(0, bool)
    if ok.sum() < PROPORTION_MIN_FRAMES:
        return None
    return np.median(bone_proportions(pts[ok]), axis=0)


def proportions_towards(model, kmap, betas: torch.Tensor, poses: torch.Tensor, seen: np.ndarray, share: float,
                        girth_sigma: float | None = None) -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
    """``(betas_new (1, 10), own (7,), got (7,))``: the body's :func:`posed_proportions` over
    ``poses (B, 72)`` (radians) moved ``share`` (in [0, 1]) of the way from its own, ``own``,
    towards ``seen (7,)`` by :func:`fit_proportions` (``girth_sigma``, metres: the body's girth
    held), and those it reached, ``got``; ``betas (1, 10)`` and ``model`` of one dtype."""
    with torch.no_grad():
        own = posed_proportions(model, kmap, betas, poses).numpy()
    new = fit_proportions(model, kmap, betas, own + share * (np.asarray(seen, np.float64) - own), poses=poses,
                          girth_sigma=girth_sigma)
    with torch.no_grad():
        got = posed_proportions(model, kmap, new, poses).numpy()
    return new, own, got


def vote_flip_frames(fit_cam: np.ndarray, sources: list[np.ndarray], limb: tuple[int, int],
                     min_reach: float, min_frames: int) -> np.ndarray:
    """``(T,)`` bool: the frames of runs, at least ``min_frames`` long, in which every
    source reaches along the camera's axis with the limb the other way from the fit.

    Args:
        fit_cam: ``(T, 13, 3)`` the fit's keypoints (:data:`~flowmocap.body.skeleton.EVAL_JOINTS`'s
            order), camera axes, metres.
        sources: each ``(T, 13, 3)`` another 3D estimate of the same keypoints aligned
            onto ``fit_cam`` (camera axes, metres), NaN where it has none.
        limb: ``(parent, child)`` SMPL joint indices, both among the 13 keypoints.
        min_reach: metres: a frame counts only where the fit and every source reach
            further than this from the limb's parent to its child along the axis.
        min_frames: the shortest run of such frames that counts (frames that follow
            one another in the arrays' first axis).
    """
    a, b = EVAL_JOINTS.index(limb[0]), EVAL_JOINTS.index(limb[1])
    reach = lambda x: np.asarray(x, np.float64)[:, b, 2] - np.asarray(x, np.float64)[:, a, 2]  # noqa: E731
    rf = reach(fit_cam)
    against = np.abs(rf) > min_reach
    for src in sources:
        rs = reach(src)
        against &= np.isfinite(rs) & (np.abs(np.nan_to_num(rs)) > min_reach) & (np.sign(np.nan_to_num(rs)) != np.sign(rf))
    out = np.zeros(len(rf), bool)
    for run in _runs(against):
        if run.size >= min_frames:
            out[run] = True
    return out


def refit_energy(model, kmap, poses, trans, betas, targets, use, poses_tracked, sigma: float, reg: float,
                 camera=None, pixels=None, pixel_sigma: float | None = None, pixel_use=None):
    """The refit's energy (step 3 of the module docstring), a scalar: ``targets (B, 13, 3)``
    in world axes, ``use (B,)`` the frames that have one (0 / 1). With ``pixel_sigma``
    (pixels) it adds ``sum_j w_j |camera.project(J_j) - pixels_j|^2 / pixel_sigma^2`` over the
    24 joints of the frames used, ``pixels (B, 24, 2)``: the tracked body's image held;
    ``pixel_use (B, 24)`` the weights ``w_j`` (default 1: every joint held).

    Args:
        poses: ``(B, 72)`` radians; trans: ``(B, 3)`` metres; betas: ``(1, num_betas)``
            (tensors, the variables).
        poses_tracked: ``(B, 72)`` radians, the tracked poses the joints 1..23 are held
            near (``sum (poses - poses_tracked)^2 / reg^2``).
        sigma: metres, the scale of the keypoints' distance to ``targets``.
        reg: radians, the scale of the poses' change.

    Returns:
        A 0-d tensor (unitless).
    """
    kp, joints = keypoints13(model, kmap, poses, betas, trans)
    fit = (((kp - targets) ** 2).sum(-1).sum(-1) * use).sum() / sigma ** 2
    if pixel_sigma:
        d2 = ((camera.project(joints) - pixels) ** 2).sum(-1)
        if pixel_use is not None:
            d2 = d2 * pixel_use
        fit = fit + (d2.sum(-1) * use).sum() / pixel_sigma ** 2
    return fit + ((poses[:, 3:] - poses_tracked[:, 3:]) ** 2).sum() / reg ** 2


def lifter_refit_motion(motion: dict, track, model, weight: float = 0.5, sigma: float = 0.02, reg: float = 0.3,
                        iterations: int = 60, chunk: int = 256, lifter=None, progress=None,
                        pixel_sigma: float | None = None, blend: str = "depth",
                        lifter_input: str = "detector", exchanged=None, vote_min_frames: int = 0,
                        vote_min_reach: float = 0.08, vote_sources: str = "detector",
                        vote_check_2d: bool = True, seams=(), seam_s: float = 0.0,
                        ease=None, shape_share: float = 0.0, shape_girth_sigma: float | None = None,
                        bridge_s: float = 0.0, hidden_share: float = 0.0,
                        height: float | None = None, detector_model: str = "full",
                        min_confidence: float = 0.5, detector_ray_share: float = 1.0) -> tuple[dict, dict]:
    """A result's ``motion.npz`` arrays with each frame refitted (module docstring).

    Args:
        motion: ``poses (T, 72)``, ``trans (T, 3)``, ``betas``, ``joints3d (T, 24, 3)``,
            ``joints2d (T, 24, 2)``, ``camera`` (JSON of ``PinholeCamera.to_dict()``),
            ``frame_index (T,)`` and anything else (kept).
        track: the :class:`~flowmocap.vision.auto.PersonTrack` of the run (its 2D
            keypoints and confidences, by input frame number).
        model: the run's :class:`~flowmocap.body.model.BodyModel` (copied in float64).
        weight: the lifter's share of each keypoint's target, in [0, 1]; 0 returns the
            arrays unchanged.
        blend: ``"depth"`` or ``"full"`` (:func:`blend_targets`).
        lifter_input: the 2D the lifter reads: ``"detector"``, the detection's keypoints
            (confidence at least 0.5); ``"fit"``, the tracked body's own 13 keypoints
            projected (frames where the detector found the person either way).
        exchanged: input frame numbers whose detection the tracker exchanged left for
            right (``TrackerConfig.detector_swap_check``; :func:`~flowmocap.fit.swap.exchanged_frames`):
            the lifter reads those frames' keypoints exchanged back, as the tracker used
            them. None or empty: the detection as it came.
        sigma: metres, reg: radians: the energy's scales.
        vote_min_frames: the shortest run of frames in which the sources see a limb the
            other way that mirrors it before the refit (module docstring); 0: none.
        vote_min_reach: metres: how far along the camera's axis the fit and every source
            must reach with the limb for a frame to count.
        vote_sources: who votes: ``"detector"`` (its own 3D joints, ``track.world``;
            frames without all 13 at confidence 0.5 do not count), ``"lifter"`` or ``"both"``.
        vote_check_2d: an upper arm or thigh is mirrored over a run only if its wrist or
            ankle then lies no further from the detected one, summed over the run.
        seams: input frame numbers where the tracker re-initialised. With ``seam_s`` > 0
            the tracked frames before each (of those in ``ease``, None: all) are first
            eased into the pose it restarts from over ``seam_s`` seconds
            (:func:`~flowmocap.fit.smooth.seam_blend`; never past an earlier seam); the
            refit starts from, and is held to, the eased poses, while its image term
            (``pixel_sigma``) still holds the tracked body's image.
        iterations: L-BFGS iterations per chunk of ``chunk`` frames (60: about converged;
            ``TrackerConfig.lifter_refit_iterations``).
        pixel_sigma: pixels, or None: the scale of a term that holds the 24 joints' image
            where the tracker put it (:func:`refit_energy`); None leaves it out.
        lifter: a :class:`~flowmocap.vision.lifter.Lifter` (default the packaged one).
        progress: optional callable ``(done_frames, total)``.
        shape_share: in [0, 1]: how far the body's bone proportions move towards the lifter's
            before the refit (module docstring); 0: the tracked shape stays.
        shape_girth_sigma: metres or None: with ``shape_share``, the body's girth along its
            bones (:func:`body_girth`) held at this scale (:func:`fit_proportions`).
        height: metres or None: with ``shape_share``, the refitted shape is given this
            stature afterwards (:func:`flowmocap.body.stature.with_stature`: the person's
            stated height, which the tracked body already had).
        detector_model: the landmark network the detections came from
            (:data:`flowmocap.vision.detect.MODELS`; the pipeline passes its run's
            ``TrackerConfig.detector_model``): the body's keypoints are placed with its
            learned offsets (:func:`flowmocap.vision.keypoint_map.load_keypoint_map`).
        min_confidence: with ``lifter_input`` ``"detector"`` or ``"unswap"``, the lifter reads
            a detected point at this confidence or more (and above 0) as given, the others as
            missing (``TrackerConfig.lifter_refit_min_confidence``).
        bridge_s: seconds: with ``lifter_input`` ``"detector"`` or ``"unswap"``, a detected
            point missing (confidence below ``min_confidence``) for at most this long between two frames
            that have it is filled by a straight line between them before lifting
            (:func:`~flowmocap.vision.lifter.bridge_gaps`); 0: the lifter guesses it.
        hidden_share: in [0, 1]: for a keypoint the detector gives below confidence 0.5 (a
            limb it cannot see), the target moves this share of the way towards the
            detector's own 3D point (aligned onto the fit by a similarity per frame on the
            confident points), and the image term (``pixel_sigma``) lets go of its joint
            (and of the hand or foot below a wrist or ankle); 0: off.
        detector_ray_share: in [0, 1]: the share of the turn from the ray through the person
            into the camera's axes the detector's own 3D is given
            (:attr:`~flowmocap.fit.config.TrackerConfig.detector3d_ray_share`).

    Returns:
        ``(motion, info)``: the new arrays, and ``frames_refit``, ``seams_eased`` (the input
        frame numbers of the seams eased), ``limb_frames_voted``
        (limbs mirrored before the refit, counted once per frame), ``limb_runs_voted``
        (``[{"limb": "left_elbow->left_wrist", "frames": [first, last]}]``, input frame
        numbers, both ends included), ``mean_move_mm`` (mean
        distance the 24 joints moved), ``mean_move_px`` (in the image),
        ``disagreement_median_mm`` and ``disagreement_p90_mm`` (the median and 90th
        percentile of ``disagreement`` over the joint-frames that have one; None if none),
        ``shape`` (None, or with ``shape_share``: ``share``, ``proportions_before``,
        ``proportions_lifter``, ``proportions_after`` (each ``(7,)``, :func:`bone_proportions`)
        and ``betas_tracked``), ``review_frames`` (``[[first, last], ...]`` input frame numbers, both ends included:
        the stretches of the tenth of frames where the sources part most,
        :func:`~flowmocap.fit.disagreement.review_frames`).
        The arrays gain ``disagreement (T, 24)`` float32, metres: per frame and joint, how far
        the fit (after the vote), the lifter and the detector's own 3D part
        (:func:`~flowmocap.fit.disagreement.source_disagreement`), for the 13 scored joints
        (:data:`~flowmocap.body.skeleton.EVAL_JOINTS`), NaN for the rest and where fewer than
        two sources give the joint.
    """
    from flowmocap.geometry.camera import PinholeCamera
    from flowmocap.vision.keypoint_map import load_keypoint_map
    from flowmocap.vision.lifter import HIPS, bridge_gaps, eval_points_2d, load_lifter

    if not 0.0 <= weight <= 1.0:
        raise InputError(f"weight must lie in [0, 1]; got {weight!r}.")
    if not 0.0 <= shape_share <= 1.0:
        raise InputError(f"shape_share must lie in [0, 1]; got {shape_share!r}.")
    if pixel_sigma is not None and not pixel_sigma > 0:
        raise InputError(f"pixel_sigma must be a positive number of pixels or None; got {pixel_sigma!r}.")
    if blend not in BLENDS:
        raise InputError(f"blend must be one of {BLENDS}; got {blend!r}.")
    if lifter_input not in LIFTER_INPUTS:
        raise InputError(f"lifter_input must be one of {LIFTER_INPUTS}; got {lifter_input!r}.")
    if vote_sources not in VOTE_SOURCES:
        raise InputError(f"vote_sources must be one of {VOTE_SOURCES}; got {vote_sources!r}.")
    if not 0.0 <= hidden_share <= 1.0:
        raise InputError(f"hidden_share must lie in [0, 1]; got {hidden_share!r}.")
    if not bridge_s >= 0:
        raise InputError(f"bridge_s must be >= 0 seconds; got {bridge_s!r}.")
    if not (int(vote_min_frames) == vote_min_frames and vote_min_frames >= 0 and vote_min_reach >= 0):
        raise InputError(f"vote_min_frames must be a whole number >= 0 and vote_min_reach >= 0 metres; got "
                         f"{vote_min_frames!r} and {vote_min_reach!r}.")
    if weight == 0:
        return dict(motion), {"frames_refit": 0, "limb_frames_voted": 0, "limb_runs_voted": [], "seams_eased": [],
                              "mean_move_mm": 0.0, "mean_move_px": 0.0, "shape": None}
    lifter = load_lifter() if lifter is None else lifter
    camera = PinholeCamera.from_dict(json.loads(str(np.asarray(motion["camera"]))))
    R, t = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
    idx = np.asarray(motion["frame_index"], int)
    if idx.size and (idx.min() < 0 or idx.max() >= len(track)):
        raise InputError(f"the result's frames reach {idx.max()} but the detections have {len(track)} frames.")
    body = copy.deepcopy(model).double()
    kmap = load_keypoint_map(model=detector_model)
    poses0 = torch.as_tensor(np.asarray(motion["poses"], np.float64))
    trans0 = torch.as_tensor(np.asarray(motion["trans"], np.float64))
    betas = torch.as_tensor(np.asarray(motion["betas"], np.float64)).reshape(1, -1)

    with torch.no_grad():
        fit_world, joints_before = keypoints13(body, kmap, poses0, betas, trans0)
    seams_eased: list[int] = []
    if seam_s > 0 and len(seams):  # the jumps at re-initialisations eased into the frames before them
        from flowmocap.fit.smooth import seam_blend

        p_eased, t_eased, seams_eased = seam_blend(poses0.numpy(), trans0.numpy(), idx, seams,
                                                   float(np.asarray(motion.get("fps", 30.0))), seam_s, ease=ease)
        poses0, trans0 = torch.as_tensor(p_eased), torch.as_tensor(t_eased)
        with torch.no_grad():
            fit_world, _ = keypoints13(body, kmap, poses0, betas, trans0)
    trans_new = trans0.clone()
    fit_cam = fit_world.numpy() @ R.T + t
    fps = float(motion.get("fps", 30.0))
    n_exchanged = 0
    if lifter_input in ("detector", "unswap"):  # every frame of the track (a temporal lifter reads neighbours)
        pts_all, conf_all = eval_points_2d(track.keypoints, track.confidence)
        given_all = (conf_all >= min_confidence) & (conf_all > 0)
        back = np.asarray(sorted({int(f) for f in (exchanged or ()) if 0 <= int(f) < len(pts_all)}), int)
        n_exchanged = int(back.size)
        if back.size:  # the tracker's own decision, frame by frame
            pts_all[back] = pts_all[back][:, list(MIRROR)]
            given_all[back] = given_all[back][:, list(MIRROR)]
        if lifter_input == "unswap":  # frames whose detection fits the fit's keypoints better left/right swapped
            fit2 = np.asarray(camera.project(fit_world.reshape(-1, 3)), np.float64).reshape(len(idx), -1, 2)
            both = given_all[idx] & given_all[idx][:, list(MIRROR)]
            det2 = np.nan_to_num(pts_all[idx])
            d0 = np.where(both, np.linalg.norm(det2 - fit2, axis=-1), 0).sum(1)
            d1 = np.where(both, np.linalg.norm(det2[:, list(MIRROR)] - fit2, axis=-1), 0).sum(1)
            swap = np.zeros(len(pts_all), bool)
            swap[idx[d1 < 0.5 * d0]] = True
            pts_all[swap] = pts_all[swap][:, list(MIRROR)]
            given_all[swap] = given_all[swap][:, list(MIRROR)]
        if bridge_s > 0:  # a point lost for a moment: the line between where it was seen (frames with the person)
            found = np.asarray(track.found, bool)[:, None]
            pts_b, given_b = bridge_gaps(pts_all, given_all & found, int(round(bridge_s * fps)))
            fill = given_b & ~given_all & found
            pts_all, given_all = np.where(fill[..., None], pts_b, pts_all), given_all | fill
        lifted = lifter.lift_points(pts_all, given_all, fps=fps)[idx]
        pts2 = pts_all[idx]
    else:  # the fit's own keypoints in the image (or where the detection is far from them)
        pts2 = np.asarray(camera.project(fit_world.reshape(-1, 3)), np.float64).reshape(len(idx), -1, 2)
        if lifter_input == "agree":
            det2, conf2 = eval_points_2d(track.keypoints[idx], track.confidence[idx])
            near = (conf2 >= 0.5) & (np.linalg.norm(np.nan_to_num(det2, nan=1e9) - pts2, axis=-1) <= AGREE_PX)
            pts2 = np.where(near[..., None], det2, pts2)
        lifted = lifter.lift_points(pts2, np.ones(pts2.shape[:2], bool), fps=fps)
    lifted[~np.asarray(track.found, bool)[idx]] = np.nan
    ok = np.isfinite(lifted).all((1, 2))
    for k in np.flatnonzero(ok):
        u, v = pts2[k, list(HIPS)].mean(0)
        lifted[k] = lifted[k] @ camera.ray_rotation(float(u), float(v)).T
    shape_info = None
    seen = median_proportions(lifted) if shape_share > 0 else None
    if seen is not None:  # the body's proportions towards the lifter's
        some = np.flatnonzero(ok)[np.linspace(0, ok.sum() - 1, min(PROPORTION_FRAMES, int(ok.sum()))).round().astype(int)]
        at = poses0[torch.as_tensor(some)]
        betas, own, got = proportions_towards(body, kmap, betas, at, seen, shape_share, shape_girth_sigma)
        if height:  # the stated stature again; the proportions reached are the body's with it
            from flowmocap.body.stature import with_stature

            betas = with_stature(body, betas, height)
            with torch.no_grad():
                got = posed_proportions(body, kmap, betas, at).numpy()
        with torch.no_grad():
            fit_world, _ = keypoints13(body, kmap, poses0, betas, trans0)
        fit_cam = fit_world.numpy() @ R.T + t
        shape_info = {"share": shape_share, "girth_sigma": shape_girth_sigma, "proportions_before": np.round(own, 4).tolist(),
                      "proportions_lifter": np.round(seen, 4).tolist(), "proportions_after": np.round(got, 4).tolist(),
                      "betas_tracked": np.asarray(motion["betas"], np.float64).reshape(-1).round(4).tolist()}
    n_voted, voted_runs = 0, []
    if vote_min_frames > 0 and ok.any():
        from flowmocap.fit.flip import limb_name

        srcs = []
        if vote_sources in ("lifter", "both"):
            srcs.append(lifted)
        if vote_sources in ("detector", "both"):
            srcs.append(_detector_cam(track, idx, camera, pts2, exchanged, share=detector_ray_share))
        det2 = None
        if vote_check_2d:
            d2, c2 = _detected_as_used(track, idx, exchanged)
            det2 = np.where((c2 >= 0.5)[..., None], d2, np.nan)
        poses0, fit_cam, runs = _vote_flips(body, kmap, poses0, trans0, betas, camera, srcs,
                                            vote_min_reach, vote_min_frames, det2)
        n_voted = sum(b - a + 1 for _, a, b in runs)
        voted_runs = [{"limb": limb_name(limb), "frames": [int(idx[a]), int(idx[b])]} for limb, a, b in runs]
    # where the three 3D sources part (the fit as voted, the lifter, the detector's own 3D):
    # a per-joint flag for the user (flowmocap.fit.disagreement), not used by the refit
    from flowmocap.fit.disagreement import review_frames, source_disagreement, to_body_joints
    from flowmocap.vision.auto import frame_runs

    det_all = _detector_cam(track, idx, camera, pts2, exchanged, gate=False, share=detector_ray_share)  # every point
    disagreement = source_disagreement(fit_cam, [lifted, det_all])
    poses_new = poses0.clone()
    targets_cam = fit_cam.copy()
    if ok.any():
        targets_cam[ok] = blend_targets(fit_cam[ok], lifted[ok], weight, blend)
    pixel_use = None
    n_hidden = 0
    if hidden_share > 0:  # limbs the detector cannot see: towards its own 3D, the tracked image let go
        targets_cam, pixel_use, n_hidden = _hidden_towards_detector(
            targets_cam, fit_cam, det_all, track, idx, exchanged, hidden_share, joints_before.shape[1])
    targets = torch.as_tensor((targets_cam - t) @ R)
    with torch.no_grad():
        pixels0 = camera.project(joints_before) if pixel_sigma else None
    use = torch.as_tensor(ok, dtype=torch.float64)
    for a in range(0, len(idx), chunk):
        b = min(a + chunk, len(idx))
        if not ok[a:b].any():
            continue
        pose = poses0[a:b].clone().requires_grad_(True)
        tr = trans0[a:b].clone().requires_grad_(True)
        opt = torch.optim.LBFGS([pose, tr], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe")

        def closure(pose=pose, tr=tr, a=a, b=b):
            opt.zero_grad()
            e = refit_energy(body, kmap, pose, tr, betas, targets[a:b], use[a:b], poses0[a:b], sigma, reg,
                             camera, None if pixels0 is None else pixels0[a:b], pixel_sigma,
                             None if pixel_use is None else pixel_use[a:b])
            e.backward()
            return e

        opt.step(closure)
        keep = torch.as_tensor(ok[a:b])[:, None]
        poses_new[a:b] = torch.where(keep, pose.detach(), poses0[a:b])
        trans_new[a:b] = torch.where(keep, tr.detach(), trans0[a:b])
        if progress is not None:
            progress(b, len(idx))
    if not (torch.isfinite(poses_new).all() and torch.isfinite(trans_new).all()):
        raise InputError("the refit towards the lifter gave non-finite values; run without it "
                         "(\"lifter_refit_weight\": 0) and report the input.")
    with torch.no_grad():
        joints = keypoints13(body, kmap, poses_new, betas, trans_new)[1].numpy()
    j2d = np.asarray(camera.project(joints.reshape(-1, 3)), np.float64).reshape(len(idx), -1, 2)  # world points
    out = dict(motion)
    out["poses_tracked"] = np.asarray(motion["poses"]).copy()
    if shape_info is not None:  # the refitted shape; the tracker's kept as betas_tracked
        out["betas_tracked"] = np.asarray(motion["betas"]).copy()
        out["betas"] = betas.numpy().reshape(np.shape(motion["betas"])).astype(np.asarray(motion["betas"]).dtype)
    out["poses"] = poses_new.numpy().astype(np.asarray(motion["poses"]).dtype)
    out["trans"] = trans_new.numpy().astype(np.asarray(motion["trans"]).dtype)
    out["joints3d"] = joints.astype(np.asarray(motion["joints3d"]).dtype)
    out["joints2d"] = j2d.astype(np.asarray(motion["joints2d"]).dtype)
    out["disagreement"] = to_body_joints(disagreement, joints.shape[1]).astype(np.float32)
    before2d = np.asarray(motion["joints2d"], np.float64)
    known = disagreement[np.isfinite(disagreement)]
    info = {"frames_refit": int(ok.sum()), "limb_frames_voted": n_voted, "limb_runs_voted": voted_runs,
            "seams_eased": seams_eased, "seam_s": seam_s, "shape": shape_info,
            "weight": weight, "pixel_sigma": pixel_sigma, "blend": blend,
            "lifter_input": lifter_input, "frames_exchanged": n_exchanged, "hidden_share": hidden_share,
            "hidden_points": n_hidden,
            "mean_move_mm": float(1000 * np.linalg.norm(joints - joints_before.numpy(), axis=-1).mean()),
            "mean_move_px": float(np.linalg.norm(j2d - before2d, axis=-1).mean()),
            "disagreement_median_mm": float(1000 * np.median(known)) if known.size else None,
            "disagreement_p90_mm": float(1000 * np.quantile(known, 0.9)) if known.size else None,
            "review_frames": frame_runs(idx[review_frames(disagreement)[1]])}
    return out, info


def _aligned(src: np.ndarray, fit_cam: np.ndarray) -> np.ndarray:
    """``src (T, 13, 3)`` aligned onto ``fit_cam`` by a similarity per frame; NaN frames stay NaN."""
    from flowmocap.geometry.procrustes import similarity_procrustes

    out = np.full_like(fit_cam, np.nan)
    have = np.isfinite(src).all((1, 2))
    if have.any():
        out[have] = similarity_procrustes(src[have], fit_cam[have])[0]
    return out


def _detector_cam(track, idx: np.ndarray, camera, pts2: np.ndarray, exchanged, gate: bool = True,
                  share: float = 1.0) -> np.ndarray:
    """``(T, 13, 3)`` the detector's own 3D keypoints of the result's frames turned into the
    camera's axes (as the lifter's: about the ray through the detected hips), exchanged left
    for right where the tracker did; NaN for frames without all 13 at confidence 0.5
    (``gate=False``: every frame where the person was found and the detected hips' pixels
    are known, NaN only for points the detector gives none); ``share``: of the turn from the
    ray's axes (:attr:`~flowmocap.fit.config.TrackerConfig.detector3d_ray_share`)."""
    from flowmocap.vision.lifter import HIPS, eval_points_2d

    out = np.full((len(idx), 13, 3), np.nan)
    if getattr(track, "world", None) is None:
        return out
    w, wc = eval_points_2d(np.asarray(track.world)[idx], np.asarray(track.confidence)[idx])
    back = {int(f) for f in (exchanged or ())}
    for k, f in enumerate(idx):
        if not (track.found[f] and np.isfinite(pts2[k, list(HIPS)]).all()
                and (not gate or ((wc[k] >= 0.5).all() and np.isfinite(w[k]).all()))):
            continue
        x = w[k][list(MIRROR)] if int(f) in back else w[k]
        u, v = pts2[k, list(HIPS)].mean(0)
        out[k] = x @ camera.ray_rotation(float(u), float(v), share).T
    return out


#: the body joints below a keypoint that its image hold lets go of with it (a wrist's hand, an ankle's foot)
_BELOW = {"left_wrist": ("left_hand",), "right_wrist": ("right_hand",), "left_ankle": ("left_foot",),
          "right_ankle": ("right_foot",)}


def _detected_as_used(track, idx: np.ndarray, exchanged) -> tuple[np.ndarray, np.ndarray]:
    """``(points (T, 13, 2) pixels, confidence (T, 13))``: the detection's 13 points of the
    result's frames ``idx``, exchanged left for right where the tracker did (``exchanged``)."""
    from flowmocap.vision.lifter import eval_points_2d

    pts, conf = eval_points_2d(np.asarray(track.keypoints)[idx], np.asarray(track.confidence)[idx])
    back = np.isin(idx, [int(f) for f in (exchanged or ())])
    pts[back], conf[back] = pts[back][:, list(MIRROR)], conf[back][:, list(MIRROR)]
    return pts, conf


def _hidden_towards_detector(targets_cam, fit_cam, det, track, idx, exchanged, share: float, n_joints: int):
    """``(targets_cam, pixel_use, n)``: :func:`lifter_refit_motion`'s ``hidden_share`` step.
    ``targets_cam``, ``fit_cam`` ``(T, 13, 3)`` camera axes, ``det`` the detector's own 3D
    points there (:func:`_detector_cam` without its gate); returns the targets with each
    hidden point (detected below confidence 0.5, the person found) moved ``share`` of the
    way to the detector's own 3D point, aligned onto ``fit_cam`` by a similarity per frame
    fitted on the frame's confident points (at least 4, both hips among them); ``pixel_use
    (T, n_joints)`` float64 tensor, 0 for the body joints of those points (and the hand or
    foot below them), 1 elsewhere; ``n`` the number of points moved."""
    from flowmocap.geometry.procrustes import similarity_procrustes
    from flowmocap.vision.lifter import HIPS, POINTS

    seen = _detected_as_used(track, idx, exchanged)[1] >= 0.5
    hidden = ~seen & np.isfinite(det).all(-1) & np.asarray(track.found, bool)[idx][:, None]
    frames = hidden.any(1) & (seen.sum(1) >= 4) & seen[:, list(HIPS)].all(1) & np.isfinite(det).all((1, 2))
    out = targets_cam.copy()
    use = np.ones((len(idx), n_joints))
    if not frames.any():
        return out, torch.as_tensor(use), 0
    rows = np.flatnonzero(frames)
    aligned = similarity_procrustes(det[rows], fit_cam[rows], weights=seen[rows].astype(np.float64))[0]
    hid = hidden[rows]
    out[rows] = np.where(hid[..., None], (1.0 - share) * targets_cam[rows] + share * aligned, targets_cam[rows])
    for k, name in enumerate(POINTS):
        joints = [JOINT_INDEX[name]] + [JOINT_INDEX[n] for n in _BELOW.get(name, ())]
        for j in joints:
            if j < n_joints:
                use[rows, j] = np.where(hid[:, k], 0.0, use[rows, j])
    return out, torch.as_tensor(use), int(hid.sum())


def _runs(frames: np.ndarray) -> list[np.ndarray]:
    """The runs of consecutive True entries of ``frames (T,)`` bool, as index arrays."""
    idx = np.flatnonzero(frames)
    return [r for r in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if r.size] if idx.size else []


def _vote_flips(body, kmap, poses, trans, betas, camera, sources, min_reach, min_frames, det2=None):
    """Each limb of :data:`VOTE_LIMBS` mirrored in depth (:func:`~flowmocap.fit.flip.mirrored_rotvec`)
    over the runs of frames :func:`vote_flip_frames` finds, limb after limb (each vote on
    the body as the earlier limbs left it). The mirror keeps the limb's child joint on its
    pixel but moves the joints below it: with ``det2 (T, 13, 2)`` (the detection's 2D
    keypoints, NaN where not confident), a run of an upper arm or thigh is mirrored only
    if its wrist or ankle does not end further from the detected one, summed over the
    run. Returns ``(poses, fit_cam, runs)``: ``runs`` the mirrored runs as ``(limb, first row,
    last row)``."""
    from flowmocap.body.skeleton import PARENTS
    from flowmocap.fit.flip import mirrored_rotvec

    R, t = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
    poses = poses.clone()
    done = []

    def posed(p):
        joints, rots, kps = [], [], []
        with torch.no_grad():
            for a in range(0, len(p), NO_GRAD_CHUNK):
                b = a + NO_GRAD_CHUNK
                out = posed_joints_only(body, betas, p[a:b], trans[a:b])  # posed once for all three
                joints.append(out.joints.numpy())
                rots.append(out.transforms[:, :, :3, :3].numpy())
                kps.append(_keypoints_of(kmap, out).numpy())
        return np.concatenate(joints), np.concatenate(rots), np.concatenate(kps)

    def pixels(kp, j):
        return np.asarray(camera.project(kp[:, j]), np.float64)

    joints, rots, kp = posed(poses)
    for limb in VOTE_LIMBS:
        fit_cam = kp @ R.T + t
        frames = vote_flip_frames(fit_cam, [_aligned(s, fit_cam) for s in sources], limb, min_reach, min_frames)
        cand = {}
        for k in np.flatnonzero(frames):
            rv = mirrored_rotvec(poses[k].numpy(), joints[k], rots[k], R, t, limb)
            if rv is not None:
                cand[int(k)] = torch.as_tensor(rv, dtype=poses.dtype)
        if not cand:
            continue
        below = [c for c in range(len(PARENTS)) if PARENTS[c] == limb[1] and c in EVAL_JOINTS]
        if below and det2 is not None:  # the joint below the child moves in the image: the detection decides
            g = EVAL_JOINTS.index(below[0])
            ks = np.array(sorted(cand))
            trial = poses[ks].clone()
            trial[:, 3 * limb[0]:3 * limb[0] + 3] = torch.stack([cand[int(k)] for k in ks])
            with torch.no_grad():
                kp_new = keypoints13(body, kmap, trial, betas, trans[ks])[0].numpy()
            d_old = np.linalg.norm(pixels(kp[ks], g) - det2[ks, g], axis=-1)
            d_new = np.linalg.norm(pixels(kp_new, g) - det2[ks, g], axis=-1)
            at = {int(k): i for i, k in enumerate(ks)}
            mask = np.zeros(len(poses), bool)
            mask[ks] = True
            for run in _runs(mask):
                i = [at[int(k)] for k in run]
                have = np.isfinite(d_old[i]) & np.isfinite(d_new[i])
                if have.any() and d_new[i][have].sum() > d_old[i][have].sum():
                    for k in run:
                        cand.pop(int(k))
        for k, rv in cand.items():
            poses[k, 3 * limb[0]:3 * limb[0] + 3] = rv
        mask = np.zeros(len(poses), bool)
        mask[list(cand)] = True
        done += [(limb, int(run[0]), int(run[-1])) for run in _runs(mask)]
        if cand:
            joints, rots, kp = posed(poses)
    return poses, kp @ R.T + t, done
