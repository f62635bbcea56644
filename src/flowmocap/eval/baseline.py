"""The per-frame keypoint baseline: SMPLify's recipe (Bogo et al. 2016) on our body model.

Every frame is fitted on its own to 2D keypoints -- no flow, no silhouette, no Kalman
prediction, no closeness to the previous frame -- which is what the paper compares
against (its Table 1). The recipe, with the project's energy terms
(:mod:`flowmocap.fit.energies`):

1. **Shape**, once, on frame 0: the tracker's own initialisation step 1
   (:func:`flowmocap.fit.init.fit_frame0` without the silhouette: robust keypoints,
   closeness to the rough pose, shape prior, joint limits, interpenetration), from the
   same init.json the tracker gets. The shape is then fixed for all frames.
2. **Every frame t**, independently, from the same start -- frame 0's fitted pose (the
   "generic start"; SMPLify starts each image from its mean pose) with a translation
   guessed from frame t's keypoints (:func:`flowmocap.fit.init.guess_translation`):

   a. translation and global orientation on the torso keypoints (hips, shoulders);
   b. all pose components and the translation against
      ``E = E_kp(sigma) + w_pose E_prior + w_b E_b + w_sp E_sp`` over stages whose pose
      prior weight is annealed from strong to weak (SMPLify's schedule, scaled to our
      units). The pose prior pulls towards frame 0's fitted pose, a stand-in for
      SMPLify's Gaussian mixture learned from CMU mocap (we ship no learned prior);
      the root is not in it.

   Nothing of frame t-1 enters frame t, so depth ambiguities and keypoint noise show up
   as jitter and jumps -- the temporal incoherence the paper's method removes.

**Keypoints** on synthetic sequences (:func:`detector_keypoints`): the ground-truth 2D
joints of the 14 joints a DeepCut / LSP-style detector gives (head, neck, shoulders,
elbows, wrists, hips, knees, ankles) with Gaussian noise of 3 px per coordinate, and
5 % of them (seeded, independently per joint and frame) displaced as gross outliers by
20-60 px in a uniformly random direction. All confidences are 1 (a real detector
would lower some; the robust Geman-McClure data term has to cope).

The result folder has the tracker's layout (:mod:`flowmocap.io.results`), so
:func:`flowmocap.eval.scoring.score_result` scores both the same way; it is written
after every frame and resumes where an interrupted run stopped.
"""

from __future__ import annotations

import json
import platform
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from flowmocap.body import JOINT_INDEX, BodyModel
from flowmocap.body.capsules import pose_capsules, rest_capsules
from flowmocap.body.lbs import rigid_transforms
from flowmocap.errors import InputError, OptimizationError
from flowmocap.fit import energies as en
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.init import INIT_JOINTS, InitSpec, fit_frame0, guess_translation
from flowmocap.fit.lbfgs import minimise
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.geometry.rotations import axis_angle_to_matrix
from flowmocap.io.results import read_result, write_motion, write_run
from flowmocap.version import __version__

#: The joints a 2D detector gives (LSP / DeepCut's 14), as SMPL joint names.
KEYPOINT_JOINTS = INIT_JOINTS + ("neck", "head")
#: Torso joints for the orientation step.
TORSO_JOINTS = ("left_hip", "right_hip", "left_shoulder", "right_shoulder")
ENERGY_NAMES = ("total", "keypoints", "pose_prior", "limits", "penetration")


@dataclass
class BaselineConfig:
    """Settings of the baseline (all recorded in ``run.json``)."""

    keypoint_sigma: float = 50.0                   # Geman-McClure scale, px (the tracker's init)
    pose_prior_weights: tuple = (400.0, 150.0, 60.0)  # annealed per stage, px^2 per rad^2
    limit_weight: float = 10.0                     # E_b
    penetration_weight: float = 10.0               # E_sp (m^2)
    depth_weight: float = 1000.0                   # camera step: px^2 per m^2 off the size-based depth
    orient_iterations: int = 20                    # step a
    iterations: int = 20                           # per annealing stage of step b
    # detector-like keypoint noise on synthetic sequences
    noise_px: float = 3.0
    outlier_rate: float = 0.05
    outlier_px: tuple = (20.0, 60.0)
    seed: int = 0

    def to_dict(self) -> dict:
        """The settings as a JSON-ready dict (tuples as lists)."""
        d = asdict(self)
        d["pose_prior_weights"] = list(self.pose_prior_weights)
        d["outlier_px"] = list(self.outlier_px)
        return d


def detector_keypoints(joints2d, noise_px: float = 3.0, outlier_rate: float = 0.05,
                       outlier_px: tuple = (20.0, 60.0), seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Detector-like 2D keypoints from ground-truth joints.

    Args:
        joints2d: ``(T, 24, 2)`` ground-truth joints, pixels.
        noise_px: standard deviation of the Gaussian noise per coordinate, pixels.
        outlier_rate: probability that a keypoint is a gross outlier.
        outlier_px: ``(min, max)`` displacement of an outlier in pixels, uniform, in a
            uniformly random direction (added on top of the Gaussian noise).
        seed: random seed.

    Returns:
        ``keypoints (T, 24, 2)`` pixels (NaN for joints a detector does not give) and
        ``confidence (T, 24)`` (1 for :data:`KEYPOINT_JOINTS`, 0 otherwise).
    """
    j = np.asarray(joints2d, np.float64)
    if j.ndim != 3 or j.shape[1:] != (24, 2):
        raise InputError(f"joints2d must be (T, 24, 2) pixels; got {j.shape}.")
    rng = np.random.default_rng(seed)
    T = j.shape[0]
    kp = j + rng.normal(0.0, noise_px, j.shape)
    outlier = rng.random((T, 24)) < outlier_rate
    ang = rng.uniform(0, 2 * np.pi, (T, 24))
    dist = rng.uniform(outlier_px[0], outlier_px[1], (T, 24))
    kp += outlier[..., None] * dist[..., None] * np.stack([np.cos(ang), np.sin(ang)], -1)
    conf = np.zeros((T, 24))
    conf[:, [JOINT_INDEX[n] for n in KEYPOINT_JOINTS]] = 1.0
    kp[conf == 0] = np.nan
    return kp, conf


class _Writer:
    """The tracker's result layout, flushed after every frame."""

    def __init__(self, out_dir: Path, model: BodyModel, camera: PinholeCamera, betas: torch.Tensor,
                 fps: float, run: dict):
        self.out_dir, self.model, self.camera, self.betas, self.fps, self.run = out_dir, model, camera, betas, fps, run
        keys = ("poses", "trans", "joints3d", "joints2d", "energies", "frame_index")
        self.rows: dict[str, list] = {k: [] for k in keys}

    def add(self, frame: int, pose: torch.Tensor, trans: torch.Tensor, terms: dict) -> None:
        with torch.no_grad():
            j3 = self.model(betas=self.betas, pose=pose[None], trans=trans[None]).joints[0]
        self.rows["poses"].append(pose.numpy().astype(np.float32))
        self.rows["trans"].append(trans.numpy().astype(np.float32))
        self.rows["joints3d"].append(j3.numpy().astype(np.float32))
        self.rows["joints2d"].append(self.camera.project(j3).numpy().astype(np.float32))
        self.rows["energies"].append([terms.get(n, np.nan) for n in ENERGY_NAMES])
        self.rows["frame_index"].append(frame)

    def restore(self, motion: dict) -> None:
        for k in self.rows:
            self.rows[k] = list(motion[k])

    def flush(self) -> None:
        r = self.rows
        write_motion(self.out_dir, {
            "poses": np.asarray(r["poses"], np.float32).reshape(-1, 72),
            "trans": np.asarray(r["trans"], np.float32).reshape(-1, 3),
            "betas": self.betas[0].numpy().astype(np.float32),
            "gender": np.array(self.model.gender),
            "fps": np.array(float(self.fps)),
            "camera": np.array(json.dumps(self.camera.to_dict())),
            "joints3d": np.asarray(r["joints3d"], np.float32).reshape(-1, 24, 3),
            "joints2d": np.asarray(r["joints2d"], np.float32).reshape(-1, 24, 2),
            "energies": np.asarray(r["energies"], np.float64).reshape(-1, len(ENERGY_NAMES)),
            "energy_names": np.array(ENERGY_NAMES),
            "frame_index": np.asarray(r["frame_index"], np.int64),
        })
        write_run(self.out_dir, self.run)


class Skeleton:
    """Joints and bone transforms of a fixed-shape body, without the mesh.

    The baseline's energies need only the posed joints (keypoints) and the bone
    transforms (capsules), so skinning the 6890-vertex mesh every evaluation would be
    wasted: this is :func:`flowmocap.body.lbs.rigid_transforms` on the shaped rest
    joints, equal to the model's ``joints`` and ``transforms``.
    """

    def __init__(self, model: BodyModel, betas: torch.Tensor):
        with torch.no_grad():
            out = model(betas=betas)
            self.rest_joints = out.rest_joints.detach()
            self.rest_capsules = rest_capsules(model, out)
        self.parents = model.parents

    def __call__(self, pose: torch.Tensor, trans: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``pose (72,)``, ``trans (3,)`` -> ``joints (24, 3)``, ``transforms (1, 24, 4, 4)``."""
        rot = axis_angle_to_matrix(pose.reshape(1, 24, 3))
        joints, tf = rigid_transforms(rot, self.rest_joints, self.parents)
        top = torch.cat([tf[..., :3, :3], tf[..., :3, 3:] + trans.reshape(1, 1, 3, 1)], -1)
        tf = torch.cat([top, tf[..., 3:, :]], -2)
        return joints[0] + trans, tf


def fit_frame(skeleton: Skeleton, camera: PinholeCamera, start_pose: torch.Tensor, keypoints: np.ndarray,
              confidence: np.ndarray, cfg: BaselineConfig, model: BodyModel | None = None,
              betas: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Fit one frame to its keypoints from ``start_pose``; nothing else is shared between frames.

    Args:
        skeleton: :class:`Skeleton` of the fixed shape.
        camera: the static camera.
        start_pose: ``(72,)`` the start and the centre of the pose prior, radians.
        keypoints: ``(24, 2)`` pixels (NaN = missing); confidence: ``(24,)``.
        cfg: :class:`BaselineConfig`.
        model, betas: the body model and ``(1, 10)`` shape, for the translation guess.

    Returns:
        ``pose (72,)``, ``trans (3,)`` and the final weighted energy terms.
    """
    ok = np.isfinite(keypoints).all(-1) & (confidence > 0)
    if ok.sum() < 4:
        raise InputError("fewer than 4 keypoints in this frame; the baseline needs at least hips and shoulders.")
    torso_idx = [JOINT_INDEX[n] for n in TORSO_JOINTS]
    spec = InitSpec(0, np.where(ok[:, None], keypoints, 0.0), np.where(ok, confidence, 0.0),
                    start_pose.double().numpy(), None, betas[0].double().numpy())
    trans = guess_translation(model, camera, spec).clone().requires_grad_()
    depth0 = float(camera.depth(skeleton(start_pose, trans.detach())[0][0]))
    ref = start_pose.detach().clone()
    pose = ref.clone().requires_grad_()
    kp = torch.as_tensor(spec.joints2d, dtype=torch.float32)
    conf = torch.as_tensor(spec.confidence, dtype=torch.float32)
    torso = torch.zeros_like(conf)
    torso[torso_idx] = 1.0
    root_mask = torch.zeros(72)
    root_mask[:3] = 1.0

    def energy(w_pose: float, torso_only: bool, terms: dict | None = None):
        p = pose if not torso_only else ref + root_mask * (pose - ref)
        joints, tf = skeleton(p, trans)
        pj = camera.project(joints)
        t = {"keypoints": en.keypoint_energy(pj[None], kp, conf * torso if torso_only else conf,
                                             sigma=cfg.keypoint_sigma)[0]}
        if torso_only:
            # SMPLify's camera step: stay near the depth estimated from the body's 2D size
            t["depth"] = cfg.depth_weight * (camera.depth(joints[0]) - depth0) ** 2
        else:
            t["pose_prior"] = w_pose * en.pose_prior_energy(p[None], ref[None])[0]
            t["limits"] = cfg.limit_weight * en.joint_limit_energy(p[None])[0]
            caps = pose_capsules(skeleton.rest_capsules, tf)
            t["penetration"] = cfg.penetration_weight * en.interpenetration_energy(caps)[0]
        if terms is not None:
            terms.update({k: float(v) for k, v in t.items()})
        return sum(t.values())

    minimise([trans, pose], lambda: energy(0.0, True), cfg.orient_iterations)
    with torch.no_grad():  # only the root moved in step a
        pose.copy_(ref + root_mask * (pose - ref))
    for w in cfg.pose_prior_weights:
        minimise([trans, pose], lambda: energy(w, False), cfg.iterations)
    terms: dict = {}
    with torch.no_grad():
        terms["total"] = float(energy(cfg.pose_prior_weights[-1], False, terms))
    return pose.detach(), trans.detach(), terms


def run_baseline(seq, out_dir: str | Path, model: BodyModel, camera: PinholeCamera, init: InitSpec,
                 keypoints: np.ndarray, confidence: np.ndarray, cfg: BaselineConfig | None = None,
                 resume: bool = False, progress: bool = True, keypoint_note: str = "") -> dict:
    """Fit every frame of ``seq`` independently and write a result folder.

    Args:
        seq: the :class:`~flowmocap.io.sequence.Sequence` (its frames are not read: the
            baseline sees keypoints only).
        out_dir: result folder (``motion.npz``, ``run.json``).
        model, camera: body model and static camera.
        init: the frame-0 :class:`~flowmocap.fit.init.InitSpec` (2D joints and rough
            pose) for the shape fit, the same the tracker gets.
        keypoints: ``(T, 24, 2)`` per-frame keypoints, pixels (NaN = missing).
        confidence: ``(T, 24)``.
        cfg: :class:`BaselineConfig`.
        resume: continue an interrupted run in ``out_dir`` made with the same settings.
        progress: show a progress bar.
        keypoint_note: how the keypoints were made, for ``run.json``.

    Returns:
        the final ``run.json`` contents.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: one thread is 2-3x faster than two here
    try:
        return _run_baseline(seq, out_dir, model, camera, init, keypoints, confidence, cfg, resume, progress,
                             keypoint_note)
    finally:
        torch.set_num_threads(threads)


def _run_baseline(seq, out_dir, model, camera, init, keypoints, confidence, cfg, resume, progress,
                  keypoint_note) -> dict:
    cfg = cfg or BaselineConfig()
    out_dir = Path(out_dir)
    T = len(seq)
    keypoints = np.asarray(keypoints, np.float64)
    confidence = np.asarray(confidence, np.float64)
    if keypoints.shape != (T, 24, 2) or confidence.shape != (T, 24):
        raise InputError(f"keypoints must be ({T}, 24, 2) and confidence ({T}, 24) for the {T} frames; "
                         f"got {keypoints.shape} and {confidence.shape}.")
    run = {"method": "baseline (per-frame keypoint fit, SMPLify recipe)", "flowmocap": __version__,
           "torch": torch.__version__, "python": platform.python_version(), "input": str(seq.root),
           "frames": [0, T], "config": cfg.to_dict(), "keypoints": keypoint_note, "model": model.source,
           "gender": model.gender, "camera": camera.to_dict(), "status": "running", "events": [], "timings": {}}
    fps = float(seq.meta.get("fps", 30.0))
    writer = None
    if resume and (out_dir / "motion.npz").exists():
        motion, old = read_result(out_dir)
        for key in ("input", "frames", "config"):
            if old.get(key) != json.loads(json.dumps(run[key])):
                raise InputError(f"cannot resume: {key} differs from the interrupted baseline run in {out_dir}; "
                                 "start a new result folder instead.")
        run = old
        betas = torch.as_tensor(motion["betas"], dtype=torch.float32)[None]
        start_pose = torch.as_tensor(run["start_pose"], dtype=torch.float32)
        writer = _Writer(out_dir, model, camera, betas, fps, run)
        writer.restore(motion)
    else:
        if (out_dir / "motion.npz").exists():
            raise InputError(f"{out_dir} already holds a result; pass resume=True to continue it "
                             "or choose another folder.")
        out_dir.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        pose0, _, betas, _ = fit_frame0(model, camera, init, None, TrackerConfig())
        start_pose = pose0.detach()
        run["start_pose"] = start_pose.numpy().tolist()
        run["timings"]["init_s"] = time.perf_counter() - t0
        writer = _Writer(out_dir, model, camera, betas.detach(), fps, run)
    skeleton = Skeleton(model, writer.betas)
    _fit_frames(seq, keypoints, confidence, skeleton, camera, start_pose, cfg, model, writer, run, progress)
    return run


def _fit_frames(seq, keypoints, confidence, skeleton, camera, start_pose, cfg, model, writer, run, progress) -> None:
    from tqdm import tqdm

    T = len(seq)
    t_start = time.perf_counter()
    frame_times = run["timings"].get("frame_s", [])
    start = len(writer.rows["frame_index"])
    for t in tqdm(range(start, T), initial=start, total=T, disable=not progress, unit="frame", desc="baseline"):
        t0 = time.perf_counter()
        try:
            pose, trans, terms = fit_frame(skeleton, camera, start_pose, keypoints[t], confidence[t], cfg,
                                           model, writer.betas)
        except OptimizationError as e:
            run["events"].append({"frame": t, "event": "non-finite energy; kept the start pose", "detail": str(e)})
            ok = np.isfinite(keypoints[t]).all(-1) & (confidence[t] > 0)
            spec = InitSpec(t, np.where(ok[:, None], keypoints[t], 0.0), ok.astype(float),
                            start_pose.double().numpy(), None, writer.betas[0].double().numpy())
            pose, trans, terms = start_pose.clone(), guess_translation(model, camera, spec), {}
        writer.add(t, pose, trans, terms)
        frame_times.append(time.perf_counter() - t0)
        run["timings"]["frame_s"] = frame_times
        run["timings"]["s_per_frame_median"] = float(np.median(frame_times))
        writer.flush()
    run["status"] = "finished"
    run["timings"]["total_s"] = run["timings"].get("total_s", 0.0) + time.perf_counter() - t_start
    writer.flush()
