"""Re-initialisation when tracking fails (the paper's future work), for the tracker's
``monitor`` hook (:class:`flowmocap.fit.tracker.SequenceTracker`).

A tracked frame is *bad* when the rendered body covers the person's mask poorly
(silhouette IoU below ``min_iou``) or its 2D joints disagree with the detector's
(median distance over the confident joints above ``max_joint_error`` times the person's
height in the image). After ``patience`` bad frames in a row, the frame is fitted afresh
to the detector's 2D joints and the mask, with the body shape fixed (the scene's betas),
from the tracked pose and, when the body has lost the person (IoU below 0.5, joints too
far, or no mask), also from an upright body facing the way the keypoints say (the fit
with the lower energy wins; a drifted frame needs only the first, at about half the
time). The fit replaces the tracked one if it agrees better with the detections: a
higher silhouette IoU, or closer 2D joints at an IoU no more than 0.02 lower (joints
alone are misled by a detector's glitch). The thresholds are the config's ``reinit_*``
settings. Frames without the person (no mask, too few confident joints) are neither good
nor bad: they end a run of bad frames.

A second, 3D criterion (off by default; ``reinit_max_joint3d_error`` > 0 turns it on): a
frame is *3D-bad* when the model's joints and the detector's 3D joints, the detector's
aligned onto the model by a confidence-weighted similarity, are further apart than that
many metres (mean over the confident joints, :func:`joint3d_disagreement`: the fit
has slid into a pose the detector does not see, e.g. a crouch whose 2D overlay still
matches). After ``reinit_3d_patience`` 3D-bad frames in a row the frame is refitted the
same way, always also from the upright body (the tracked pose is the one in doubt),
with ``E_d`` and ``E_3d`` (when their weights are on) pulling towards the detector's 3D;
the refit is kept when its 3D joints are closer to the detector's, at a silhouette IoU
no more than 0.02 lower and 2D joints no worse than before or within
``reinit_max_joint_error`` (:func:`_better_3d`). With ``reinit_3d_insist`` N > 0, once N
such refits in a row were turned down for the silhouette alone (a refit is a short fit and
covers the mask less than a polished tracked frame, so a disagreement that lasts would
never be refitted), the next ones are kept at a silhouette IoU of at least ``reinit_min_iou``
(a refit that is not itself a bad frame), until one is kept or the 3D agrees again.

Back-off: a refit that is turned down doubles the wait before the next attempt, from
the patience up to ``reinit_max_wait`` frames; a refit that is kept, or a frame that is
neither bad nor 3D-bad, ends the wait (a person whose mask the body never covers well,
such as a dancer in a wide dress, would otherwise be refitted on every frame, in vain).
Every attempt turned down is recorded as a ``run.json`` event (:data:`TURNED_DOWN_EVENT`)
that says why: a drift the output shows, with no refit, is explained in the run's log.

Resuming: :meth:`ReinitMonitor.state_dict` holds the verdicts of the last frames and the
last refit attempt and the wait (what the next frames' decisions depend on), and the tracker stores
it with its own state at every frame, so a resumed run decides exactly as an
uninterrupted one. A run written without it re-judges the frames before the resumed one
by their stored 2D joints (``stored_joints2d``) against the detector's (the silhouette
test needs the body rendered and is skipped for them).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from flowmocap.errors import OptimizationError
from flowmocap.fit import energies as en
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.init import InitSpec, fit_to_joints, guess_translation
from flowmocap.fit.objective import FrameState, Scene
from flowmocap.fit.swap import exchanged_2d, exchanged_3d, exchanged_keypoints
from flowmocap.geometry.procrustes import similarity_procrustes
from flowmocap.render import body_mask
from flowmocap.vision.auto import CONFIDENT, MIN_INIT_JOINTS, PersonTrack, facing_rotvec
from flowmocap.vision.detect import KEYPOINT_NAMES
from flowmocap.vision.keypoint_map import detector_points
from flowmocap.vision.masks import mask_iou

#: ``run.json`` event of a refit attempt that was not kept (:meth:`ReinitMonitor.take_events`)
TURNED_DOWN_EVENT = "re-initialisation turned down"
#: the hips among the track's keypoints (the ray an exchanged detection's 3D is turned about)
_HIP_KEYPOINTS = (KEYPOINT_NAMES.index("left_hip"), KEYPOINT_NAMES.index("right_hip"))

__all__ = ["body_silhouette", "joint_disagreement", "joint3d_disagreement", "fit_to_detection", "ReinitMonitor"]


def body_silhouette(scene: Scene, pose: torch.Tensor, trans: torch.Tensor) -> np.ndarray:
    """``(H, W)`` bool: the pixels the body covers (rasterised mesh) with this pose,
    ``pose (72,)`` axis-angle radians and ``trans (3,)`` metres (as :meth:`Scene.forward
    <flowmocap.fit.objective.Scene.forward>` takes them)."""
    with torch.no_grad():
        _, px, d = scene.forward(pose, trans)
    return body_mask(px.numpy().astype(np.float64), d.numpy(), scene.faces, scene.camera.height, scene.camera.width)


def joint_disagreement(joints2d: np.ndarray, j2d: np.ndarray, conf: np.ndarray,
                       min_confidence: float = CONFIDENT) -> float | None:
    """Median pixel distance between the model's joints ``joints2d (24, 2)`` pixels and
    the detected ones ``j2d (24, 2)`` pixels over the joints with ``conf (24,) >=
    min_confidence``, divided by the larger side of the detected joints' box (at least
    1 pixel): a fraction of the person's size, unitless; None with fewer than 4 such joints."""
    ok = conf >= min_confidence
    if ok.sum() < 4:
        return None
    p = j2d[ok]
    height = max(float(p[:, 1].max() - p[:, 1].min()), float(p[:, 0].max() - p[:, 0].min()), 1.0)
    return float(np.median(np.linalg.norm(joints2d[ok] - p, axis=1)) / height)


def joint3d_disagreement(joints_cam: np.ndarray, j3d: np.ndarray, conf: np.ndarray,
                         min_confidence: float = CONFIDENT) -> float | None:
    """Mean distance in metres between the model's joints ``joints_cam (24, 3)`` and
    the detector's 3D joints ``j3d (24, 3)`` (both in the camera's axes; any origin and,
    for the detector, any scale) over the joints with ``conf (24,) >= min_confidence``, after
    the detector's joints are aligned onto the model's by the confidence-weighted
    similarity (scale, rotation, translation) of least squares: a per-frame PA-MPJPE
    against the detector (a mean, not a median: one flipped limb moves only one or two
    of the 12 joints a detector gives). None with fewer than
    :data:`~flowmocap.fit.energies.MIN_DETECTOR_JOINTS` such joints."""
    j3d = np.asarray(j3d, np.float64).reshape(-1, 3)
    conf = np.asarray(conf, np.float64).reshape(-1)
    ok = (conf >= min_confidence) & np.isfinite(j3d).all(1) & np.isfinite(conf)
    if ok.sum() < en.MIN_DETECTOR_JOINTS:
        return None
    x = np.asarray(joints_cam, np.float64).reshape(-1, 3)[ok]
    aligned = similarity_procrustes(j3d[ok], x, weights=conf[ok])[0]
    return float(np.mean(np.linalg.norm(aligned - x, axis=1)))


def fit_to_detection(scene, cfg: TrackerConfig, j2d: np.ndarray, conf: np.ndarray, mask: np.ndarray | None,
                     pose0: torch.Tensor, trans0: torch.Tensor, iterations: int | None = None,
                     joints3d: tuple | None = None, root_distance: float | None = None,
                     unknown: np.ndarray | None = None) -> tuple:
    """Fit pose and translation (shape fixed) to one frame's 2D joints and mask.

    Steps 1 and 2 of the initialisation (:func:`flowmocap.fit.init.fit_frame0`) with the
    scene's betas: translation alone, then pose and translation against the 2D joints
    (robust, ``cfg.init_keypoint_*``) with joint limits, interpenetration and a prior
    towards ``pose0``'s limbs (``cfg.init_pose_prior_weight``; none on the global
    orientation), then the same plus the silhouette term.

    Args:
        scene: the tracker's :class:`~flowmocap.fit.objective.Scene`.
        j2d: ``(24, 2)`` pixels; conf: ``(24,)``; mask: ``(H, W)`` bool or None.
        pose0: ``(72,)`` start and prior; trans0: ``(3,)`` metres.
        joints3d: the detector's 3D joints of the frame for ``E_d`` (see
            :func:`~flowmocap.fit.init.fit_to_joints`), or None.
        root_distance: metres: the root's distance from the camera to stay near
            (``cfg.reinit_depth_weight``), or None.
        unknown: ``(H, W)`` bool pixels where someone else may hide the person
            (:func:`~flowmocap.fit.energies.silhouette_target`), or None.

    Returns:
        ``pose (72,)``, ``trans (3,)`` and the final energy (float).
    """
    sil = en.silhouette_target(mask, unknown=unknown) if mask is not None and mask.any() else None
    pose, trans, _, terms = fit_to_joints(scene.model, scene.camera, j2d, conf, sil, cfg, pose0, trans0,
                                          scene.betas, fit_shape=False, iterations=iterations, joints3d=joints3d,
                                          joints_from_detector=True, root_distance=root_distance)
    return pose, trans, float(sum(terms.values()))


class ReinitMonitor:
    """The tracker's ``monitor``: re-initialise a frame from the detector after a run of
    bad frames (see the module docstring).

    Args:
        track: the detector's keypoints per frame (:class:`~flowmocap.vision.auto.PersonTrack`).
        cfg: the tracker settings (the fit uses its ``init_*`` weights).
        stored_joints2d: after a resume, ``{frame: (24, 2) pixels}`` of the frames tracked
            before it (``motion.npz`` ``joints2d``), to re-judge them.
        min_iou: silhouette IoU below which a frame is bad (default ``cfg.reinit_min_iou``).
        max_joint_error: median joint distance (fraction of the person's height) above which
            a frame is bad (default ``cfg.reinit_max_joint_error``).
        patience: bad frames in a row before re-initialising (default ``cfg.reinit_patience``).
        max_joint3d_error: aligned 3D joint distance (metres, :func:`joint3d_disagreement`)
            above which a frame is 3D-bad; 0 turns the 3D criterion off (default
            ``cfg.reinit_max_joint3d_error``).
        patience3d: 3D-bad frames in a row before re-initialising (default
            ``cfg.reinit_3d_patience``).
        others: ``others(i)``: frame ``i``'s ``(H, W)`` bool pixels where someone else may
            hide the person (``PersonTrack.others``), or None; None: none anywhere.
    """

    def __init__(self, track: PersonTrack, cfg: TrackerConfig, stored_joints2d: dict | None = None,
                 min_iou: float | None = None, max_joint_error: float | None = None, patience: int | None = None,
                 max_joint3d_error: float | None = None, patience3d: int | None = None, others=None):
        self.track = track
        self.cfg = cfg
        # the detector's own 3D takes this share of the turn from the ray's axes; a lifted track's the whole
        self._ray_share = cfg.detector3d_ray_share if cfg.detector3d_source == "mediapipe" else 1.0
        #: ``others(i)``: frame ``i``'s pixels where someone else may hide the person (``(H, W)``
        #: bool or None; ``PersonTrack.others``), left out of the IoU and unknown to the refit's
        #: silhouette; None: none anywhere
        self.others = others
        self.stored = dict(stored_joints2d or {})
        self.min_iou = cfg.reinit_min_iou if min_iou is None else min_iou
        self.max_joint_error = cfg.reinit_max_joint_error if max_joint_error is None else max_joint_error
        self.patience = max(int(cfg.reinit_patience if patience is None else patience), 1)
        self.max_joint3d_error = float(cfg.reinit_max_joint3d_error if max_joint3d_error is None
                                       else max_joint3d_error)
        self.patience3d = max(int(cfg.reinit_3d_patience if patience3d is None else patience3d), 1)
        self.verdicts: dict[int, bool | None] = {}  # frame -> bad (None: cannot tell)
        self.verdicts3d: dict[int, bool | None] = {}  # frame -> 3D-bad (None: cannot tell or criterion off)
        self.scores: dict[int, dict] = {}
        self._last_attempt = -(10 ** 9)
        self._wait = 0  # frames the next attempt waits after the last one (grows while refits are turned down)
        self.max_wait = max(int(cfg.reinit_max_wait), 1)
        #: 3D refits turned down for the silhouette in a row, within one run of 3D-bad frames
        #: (``cfg.reinit_3d_insist``)
        self._refused3d = 0
        #: frames whose detection the tracker exchanged left for right (``detector_swap_check``):
        #: judged and refitted against the exchanged detection
        self.exchanged: set[int] = set()
        #: refit attempts not kept, not yet taken by the tracker (:meth:`take_events`)
        self.turned_down: list[dict] = []

    def _unknown(self, i: int) -> np.ndarray | None:
        return self.others(i) if self.others is not None else None

    def _joints(self, i: int):
        """Frame ``i``'s detected ``(j2d (24, 2), conf (24,))``, exchanged where the tracker did."""
        j2d, conf = self.track.smpl_joints(i)
        return exchanged_2d(j2d, conf) if i in self.exchanged else (j2d, conf)

    def _joints3d(self, i: int, camera):
        """Frame ``i``'s detected 3D joints (``PersonTrack.smpl_joints3d``), turned back where the
        tracker exchanged the frame (about the ray through the detected hips)."""
        det = self.track.smpl_joints3d(i, camera, self._ray_share)
        if det is None or i not in self.exchanged:
            return det
        hips = [self.track.keypoints[i][k] for k in _HIP_KEYPOINTS]
        u, v = np.mean(hips, axis=0)
        return exchanged_3d(*det, camera.ray_rotation(float(u), float(v))[:, 2])

    def _turn_down(self, i: int, in3d: bool, before: dict, after: dict | None, why: str) -> None:
        """Record a refit attempt that was not kept (:meth:`take_events`)."""
        e = {"frame": i, "event": TURNED_DOWN_EVENT, "criterion": "3d" if in3d else "image", "why": why,
             "before": _rounded(before)}
        if after is not None:
            e["after"] = _rounded(after)
        self.turned_down.append(e)

    def take_events(self) -> list[dict]:
        """The refit attempts turned down since the last call, as ``run.json`` events
        (``{"frame", "event": TURNED_DOWN_EVENT, "criterion": "3d" | "image", "why", "before",
        "after"}``, ``after`` absent when no fit was made); the tracker adds them to the
        frame's events, so a run says why a drift it shows was not refitted."""
        out, self.turned_down = self.turned_down, []
        return out

    def state_dict(self) -> dict:
        """JSON-serialisable state the next frames' decisions depend on: the verdicts of
        the last ``max(patience, patience3d)`` frames and the frame of the last refit
        attempt (:meth:`load_state_dict` continues from it)."""
        keep = sorted(self.verdicts)[-max(self.patience, self.patience3d):]
        return {"verdicts": [[j, self.verdicts[j], self.verdicts3d.get(j)] for j in keep],
                "last_attempt": self._last_attempt, "wait": self._wait, "refused3d": self._refused3d}

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        for j, bad, bad3d in state["verdicts"]:
            self.verdicts[int(j)] = bad
            self.verdicts3d[int(j)] = bad3d
        self._last_attempt = int(state["last_attempt"])
        self._wait = int(state.get("wait", 0))  # a state stored before the back-off existed: none
        self._refused3d = int(state.get("refused3d", 0))

    def judge(self, i: int, scene, pose: torch.Tensor, trans: torch.Tensor, mask: np.ndarray | None) -> dict:
        """``{"iou", "joint_error", "bad"}`` of a frame's body against its detections, plus
        ``"joint3d_error"`` (metres or None) and ``"bad3d"`` when the 3D criterion is on.

        Args:
            i: the frame.
            scene: the tracker's :class:`~flowmocap.fit.objective.Scene`.
            pose: ``(72,)`` axis-angle radians; trans: ``(3,)`` metres.
            mask: the frame's ``(H, W)`` bool person mask, or None (no IoU).
        """
        j2d, conf = self._joints(i) if i < len(self.track) else (None, None)
        with torch.no_grad():
            out, _, _ = scene.forward(pose, trans)
            dp = detector_points(out, self.cfg)[0]
            pj = scene.camera.project(dp).numpy()
        err = joint_disagreement(pj, j2d, conf) if j2d is not None else None
        iou = None
        if mask is not None and mask.any():
            body = body_silhouette(scene, pose, trans)
            hidden = self._unknown(i)
            iou = mask_iou(body if hidden is None else body & ~hidden, mask)
        if err is None and iou is None:
            bad = None
        else:
            bad = bool((iou is not None and iou < self.min_iou) or (err is not None and err > self.max_joint_error))
        s = {"iou": iou, "joint_error": err, "bad": bad}
        if self.max_joint3d_error > 0:
            det = self._joints3d(i, scene.camera) if i < len(self.track) else None
            err3 = None
            if det is not None:
                err3 = joint3d_disagreement(scene.camera.to_camera(dp).numpy(), *det)
            s["joint3d_error"] = err3
            s["bad3d"] = None if err3 is None else bool(err3 > self.max_joint3d_error)
        return s

    def _stored_verdict(self, j: int) -> bool | None:
        """Joint-only verdict of a frame tracked before a resume."""
        if j not in self.stored or j >= len(self.track):
            return None
        j2d, conf = self.track.smpl_joints(j)
        err = joint_disagreement(self.stored[j], j2d, conf)
        return None if err is None else err > self.max_joint_error

    def _confident(self, i: int) -> bool:
        if i >= len(self.track) or not self.track.found[i]:
            return False
        _, conf = self.track.smpl_joints(i)
        return int((conf >= CONFIDENT).sum()) >= MIN_INIT_JOINTS

    def __call__(self, i: int, state, scene, mask: np.ndarray | None):
        """Judge tracked frame ``i`` and re-initialise it when due (the tracker's ``monitor``).

        Args:
            i: the frame.
            state: its optimised :class:`~flowmocap.fit.objective.FrameState` (``pose
                (72,)`` radians, ``trans (3,)`` metres).
            scene: the tracker's :class:`~flowmocap.fit.objective.Scene`.
            mask: the frame's ``(H, W)`` bool person mask, or None.

        Returns:
            ``(FrameState, info)`` of a kept refit, or None.
        """
        s = self.judge(i, scene, state.pose, state.trans, mask)
        self.verdicts[i] = s["bad"]
        self.verdicts3d[i] = s.get("bad3d")
        self.scores[i] = s
        if s["bad"] is False and not s.get("bad3d"):
            self._wait = 0  # tracking is fine again: the next failure is refitted without delay
        if not s.get("bad3d"):
            self._refused3d = 0  # the 3D agrees again: a new disagreement starts without insisting
        if s["bad"] and self._due(i, self.patience):
            return self._attempt(i, state, scene, mask, s, self.patience, in3d=False)
        if s.get("bad3d") and self._due(i, self.patience3d, in3d=True):
            return self._attempt(i, state, scene, mask, s, self.patience3d, in3d=True)
        return None

    def _attempt(self, i: int, state, scene, mask, s: dict, patience: int, in3d: bool):
        """Refit frame ``i``; a refit that is turned down doubles the wait before the next
        attempt (from ``patience`` frames up to ``max_wait``), one that is kept ends it."""
        self._last_attempt = i
        out = self._reinitialise(i, state, scene, mask, s, in3d=in3d)
        self._wait = 0 if out is not None else min(max(2 * self._wait, patience), self.max_wait)
        return out

    def _due(self, i: int, patience: int, in3d: bool = False) -> bool:
        """Whether frame ``i`` (bad) ends a run of ``patience`` bad frames (3D-bad with
        ``in3d``) with a confident detection and no refit tried within the run."""
        run = 1
        for j in range(i - 1, i - patience, -1):
            if in3d:
                v = self.verdicts3d.get(j)
            else:
                v = self.verdicts[j] if j in self.verdicts else self._stored_verdict(j)
            if not v:
                break
            run += 1
        return run >= patience and self._confident(i) and i - self._last_attempt >= max(patience, self._wait)

    def _reinitialise(self, i: int, state, scene, mask, before: dict, in3d: bool = False):
        j2d, conf = self._joints(i)
        if collapsed_detection(j2d, conf, scene.camera.height):  # a hidden or folded-up person: keep tracking by flow
            self._turn_down(i, in3d, before, None, "the detection is too small or has too few confident joints "
                                                   "to fit to")
            return None
        joints3d = self._joints3d(i, scene.camera)
        distance = None  # the tracked frame's depth, for cfg.reinit_depth_weight (off by default)
        if self.cfg.reinit_depth_weight > 0:
            with torch.no_grad():
                root = scene.camera.to_camera(scene.forward(state.pose, state.trans)[0].joints[0, 0])
            d = float(root.norm())
            distance = d if math.isfinite(d) and d > 0 and float(root[2]) > 0 else None
        starts = [(state.pose, state.trans)]
        if in3d or _lost(before, self.max_joint_error):  # also from an upright body facing the way the keypoints say
            fresh = np.zeros(72)
            kp, kc = self.track.keypoints[i], self.track.confidence[i]
            fresh[:3] = facing_rotvec(*(exchanged_keypoints(kp, kc) if i in self.exchanged else (kp, kc)),
                                      camera_R=scene.camera.R)
            spec = InitSpec(i, j2d, conf, fresh, None, scene.betas[0].numpy().astype(np.float64))
            starts.append((torch.as_tensor(fresh, dtype=torch.float32), guess_translation(scene.model, scene.camera, spec)))
        best = None
        for pose0, trans0 in starts:
            try:
                pose, trans, e = fit_to_detection(scene, self.cfg, j2d, conf, mask, pose0, trans0,
                                                  iterations=self.cfg.reinit_iterations, joints3d=joints3d,
                                                  root_distance=distance, unknown=self._unknown(i))
            except OptimizationError:
                continue
            if math.isfinite(e) and (best is None or e < best[2]):
                best = (pose, trans, e)
        if best is None:
            self._turn_down(i, in3d, before, None, "no fit of the detection converged")
            return None
        after = self.judge(i, scene, best[0], best[1], mask)
        keep_iou = float(self.cfg.reinit_3d_keep_iou)
        insist = int(self.cfg.reinit_3d_insist)
        insisting = in3d and insist > 0 and self._refused3d >= insist
        if insisting:
            keep_iou = max(keep_iou, float(self.min_iou))
        per_joint = float(self.cfg.reinit_iou_per_joint_error)
        if in3d:  # why it is turned down, None when kept (one evaluation of the verdict)
            refusal = _refused_3d(before, after, self.max_joint_error, keep_iou)
        else:
            refusal = None if _better(before, after, per_joint) else _refused(before, after, per_joint)
        if refusal is not None:
            if in3d and refusal.startswith(_IOU_REFUSAL):
                self._refused3d += 1
            self._turn_down(i, in3d, before, after, refusal)
            return None
        self.verdicts[i] = after["bad"]
        self.verdicts3d[i] = after.get("bad3d")
        self.scores[i] = after
        if in3d:
            why = (f"{self.patience3d} frames in a row with the 3D joints more than {self.max_joint3d_error} m from "
                   f"the detector's (mean, after a similarity alignment)")
            if insisting and not _better_3d(before, after, self.max_joint_error, float(self.cfg.reinit_3d_keep_iou)):
                why += (f"; kept at a silhouette IoU of at least {self.min_iou} after {self._refused3d} such refits "
                        f"in a row were turned down for the silhouette (reinit_3d_insist)")
            self._refused3d = 0
        else:
            why = (f"{self.patience} bad frames in a row (silhouette IoU < {self.min_iou} or joint error > "
                   f"{self.max_joint_error} of the person's height)")
        info = {"why": why, "criterion": "3d" if in3d else "image", "before": _rounded(before),
                "after": _rounded(after)}
        return FrameState(best[0], best[1]), info


#: A detection whose confident joints span less than this fraction of the image height
#: (or that has fewer than :data:`MIN_REFIT_JOINTS` of them) is not refitted to.
MIN_REFIT_EXTENT = 0.08
MIN_REFIT_JOINTS = 6


def collapsed_detection(j2d: np.ndarray, conf: np.ndarray, image_height: int, min_confidence: float = 0.3) -> bool:
    """Whether a frame's detected 2D joints are too few or too bunched up to refit the
    body to: fewer than :data:`MIN_REFIT_JOINTS` with confidence >= ``min_confidence``,
    or spread over less than :data:`MIN_REFIT_EXTENT` of the image height (the detector's
    skeleton of a half-hidden or folded-up person, knees and ankles next to the hips; the
    fit would put the body tens of metres away or fail).

    Args:
        j2d: ``(24, 2)`` pixels; conf: ``(24,)``; image_height: pixels.
    """
    ok = np.asarray(conf) >= min_confidence
    if ok.sum() < MIN_REFIT_JOINTS:
        return True
    extent = float(np.ptp(np.asarray(j2d, np.float64)[ok], axis=0).max())
    return not extent >= MIN_REFIT_EXTENT * image_height


#: A re-initialisation may cost this much silhouette IoU if it brings the 2D joints closer.
IOU_TOLERANCE = 0.02
#: Below this silhouette IoU the body has lost the person: the refit also starts upright.
LOST_IOU = 0.5


def _lost(s: dict, max_joint_error: float) -> bool:
    """Whether a frame's scores say the body has lost the person (not merely drifted):
    IoU below :data:`LOST_IOU`, joints further than ``max_joint_error``, or no mask."""
    return s["iou"] is None or s["iou"] < LOST_IOU or (s["joint_error"] is not None
                                                        and s["joint_error"] > max_joint_error)


def _iou_allowance(before: dict, after: dict, per_joint: float) -> float:
    """How much silhouette IoU a refit may cost: :data:`IOU_TOLERANCE`, plus ``per_joint``
    times how much closer its median 2D joints come (fractions of the person's height)."""
    gain = 0.0
    if after["joint_error"] is not None and before["joint_error"] is not None:
        gain = max(before["joint_error"] - after["joint_error"], 0.0)
    return IOU_TOLERANCE + per_joint * gain


def _better(before: dict, after: dict, per_joint: float = 0.0) -> bool:
    """Whether a re-initialised frame (``after``) beats the tracked one (``before``).

    With a mask on both: a higher silhouette IoU, or closer 2D joints at an IoU at most
    :func:`_iou_allowance` lower (:data:`IOU_TOLERANCE`, plus ``per_joint`` times the 2D
    gain; a detector's glitch, such as swapped or misplaced joints, makes the joints alone
    mislead: the fit to them would leave the person's silhouette). Without: closer 2D
    joints."""
    joints = (after["joint_error"] is not None and before["joint_error"] is not None
              and after["joint_error"] < before["joint_error"])
    if after["iou"] is not None and before["iou"] is not None:
        return after["iou"] > before["iou"] or (
            joints and after["iou"] >= before["iou"] - _iou_allowance(before, after, per_joint))
    return joints


def _better_3d(before: dict, after: dict, max_joint_error: float, keep_iou: float = 0.0) -> bool:
    """Whether a refit after a run of 3D-bad frames beats the tracked frame: its 3D joints
    closer to the detector's (``joint3d_error``), at a silhouette IoU at most
    :data:`IOU_TOLERANCE` lower (or, with ``keep_iou`` > 0, at least ``keep_iou``) and 2D
    joints no further than before or than ``max_joint_error`` (the refit must still fit
    the image)."""
    return _refused_3d(before, after, max_joint_error, keep_iou) is None


#: how :func:`_refused_3d`'s reason for a drop in silhouette IoU begins (counted for
#: ``TrackerConfig.reinit_3d_insist``)
_IOU_REFUSAL = "its silhouette IoU drops by more than"


def _refused_3d(before: dict, after: dict, max_joint_error: float, keep_iou: float = 0.0) -> str | None:
    """Why :func:`_better_3d` turns a refit down, in words; None when it keeps it."""
    b3, a3 = before.get("joint3d_error"), after.get("joint3d_error")
    if a3 is None or b3 is None:
        return "no 3D joints of the detector to compare it with"
    if a3 >= b3:
        return f"its 3D joints are no closer to the detector's ({b3:.3f} -> {a3:.3f} m)"
    if (after["iou"] is not None and before["iou"] is not None and after["iou"] < before["iou"] - IOU_TOLERANCE
            and not (keep_iou > 0 and after["iou"] >= keep_iou)):
        floor = f" and below {keep_iou}" if keep_iou > 0 else ""
        return (f"{_IOU_REFUSAL} {IOU_TOLERANCE}{floor} ({before['iou']:.3f} -> "
                f"{after['iou']:.3f}) although its 3D joints come closer ({b3:.3f} -> {a3:.3f} m)")
    if (after["joint_error"] is not None and before["joint_error"] is not None
            and after["joint_error"] > max(before["joint_error"], max_joint_error)):
        return (f"its 2D joints move away from the detector's ({before['joint_error']:.3f} -> "
                f"{after['joint_error']:.3f} of the person's height)")
    return None


def _refused(before: dict, after: dict, per_joint: float = 0.0) -> str:
    """Why :func:`_better` turned a refit down, in words."""
    def num(v):
        return "none" if v is None else f"{v:.3f}"
    return (f"neither a higher silhouette IoU ({num(before['iou'])} -> {num(after['iou'])}) nor closer 2D joints "
            f"({num(before['joint_error'])} -> {num(after['joint_error'])} of the person's height) at an IoU at "
            f"most {_iou_allowance(before, after, per_joint):.3g} lower")


def _rounded(s: dict) -> dict:
    return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in s.items() if k not in ("bad", "bad3d")}
