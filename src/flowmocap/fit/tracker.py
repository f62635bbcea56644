"""Per-frame tracking (paper Sec. 3.7): predict with the Kalman filters, optimise, update.

For each frame i after the first two: the filters (an error-state EKF on SO(3) per joint,
a linear one for translation) predict pose and translation; the objective of
:mod:`flowmocap.fit.objective` is minimised from there, coarse to fine over the flow
pyramid (the stages of :class:`~flowmocap.fit.config.TrackerConfig`), with the shape
fixed after initialisation, ``E_theta`` towards the predicted pose and ``E_z`` (when on)
the root's depth towards the previous (or the predicted) translation; with ``flip_test``
each limb's mirror image in depth is then tried (:mod:`flowmocap.fit.flip`) and kept
where the frame's energy is lower; the result updates the filters. A joint whose confident
detection the fit has stayed far from for ``keypoint_hold_frames`` frames (:func:`lost_joints`)
is held: ``E_j`` gives it a wider scale and more weight until it is back, so the robust
term does not let go of it for good. :class:`SequenceTracker` holds the state between
frames (``start``, ``step``, ``state_dict`` for resuming); :func:`track_frames` runs the loop over a frame
range, preparing the next frame's observations on a second thread while the current one
is optimised. Reading inputs and writing results is the caller's job
(:mod:`flowmocap.pipeline`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from flowmocap.body.skeleton import EVAL_JOINTS, PARENTS
from flowmocap.errors import InputError, OptimizationError
from flowmocap.fit import energies as en
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.energies import DEPTH_LIMBS
from flowmocap.fit.flip import flip_limbs
from flowmocap.fit.kalman import PoseFilter
from flowmocap.fit.lbfgs import minimise
from flowmocap.fit.objective import FrameData, FrameState, Scene, frame_energy
from flowmocap.fit.pose_prior import MIRROR_JOINTS
from flowmocap.fit.swap import EXCHANGED_EVENT, detection_swapped, exchanged_2d, exchanged_3d
from flowmocap.render import body_mask
from flowmocap.vision.keypoint_map import detector_points


@dataclass
class KnownStart:
    """A start that needs no initialisation: the first two frames' ``poses (2, 72)``,
    ``trans (2, 3)`` and the ``betas (10,)`` (e.g. ground truth, for ablations and tests)."""

    poses: np.ndarray
    trans: np.ndarray
    betas: np.ndarray


@dataclass
class FrameResult:
    """One tracked frame: its state, the energies at the result, what happened
    (``events``: dicts with at least ``"event"``) and the seconds it took."""

    frame: int
    state: FrameState
    terms: dict
    events: list = field(default_factory=list)
    seconds: float = 0.0


def track_frame(scene: Scene, init: FrameState, data: FrameData, cfg: TrackerConfig,
                prev: FrameState) -> tuple[FrameState, dict]:
    """Optimise one frame from ``init`` (the prediction, also ``E_theta``'s reference)
    against the previous frame ``prev``.

    Args:
        scene: the body, camera and shape of the run (:class:`~flowmocap.fit.objective.Scene`).
        init: the starting state: ``pose`` ``(72,)`` axis-angle radians, ``trans`` ``(3,)``
            metres (world frame).
        data: the frame's observations (:func:`~flowmocap.fit.objective.frame_data`).
        cfg: the settings (stages, iterations, weights).
        prev: the previous frame's state, same layout as ``init``: the rendered flow is
            from it.

    Returns:
        ``(state, terms)``: the optimised :class:`FrameState` (detached) and the energy's terms
        at it by name, floats (dimensionless weighted energies), ``"total"`` their sum.

    Raises:
        OptimizationError: the energy cannot be evaluated at the result, or turned non-finite.
    """
    with torch.no_grad():
        _, prev_px, _ = scene.forward(prev.pose, prev.trans)
    pose = init.pose.detach().clone().requires_grad_()
    trans = init.trans.detach().clone().requires_grad_()
    state = FrameState(pose, trans)
    ref = init.pose.detach().clone()
    for stage in range(len(cfg.stages)):
        minimise([pose, trans], lambda: frame_energy(scene, state, data, cfg, stage, prev_px, ref)[0],
                 cfg.iterations, cfg.rel_tolerance)
    with torch.no_grad():
        try:
            total, terms = frame_energy(scene, state, data, cfg, len(cfg.stages) - 1, prev_px, ref)
        except InputError as err:
            raise OptimizationError(f"the energy could not be evaluated at the result: {err}") from err
    terms["total"] = float(total)
    return FrameState(pose.detach(), trans.detach()), terms


def new_filter(pose, trans, cfg: TrackerConfig) -> PoseFilter:
    """Kalman filters started at ``pose (72,)`` radians and ``trans (3,)`` metres, with the
    configured joint-rotation process noise."""
    return PoseFilter(np.asarray(pose, np.float64), np.asarray(trans, np.float64),
                      rot_accel_noise=cfg.kalman_rot_accel_noise)


def person_pixels(scene: Scene, state: FrameState) -> float:
    """Projected size of the body in pixels at ``state``: ``E_f``'s normaliser without a mask."""
    with torch.no_grad():
        _, px, d = scene.forward(state.pose, state.trans)
    return float(body_mask(px.numpy(), d.numpy(), scene.faces, scene.camera.height, scene.camera.width).sum())


def depth_reference(scene: Scene, ref: FrameState) -> tuple[torch.Tensor, torch.Tensor]:
    """``E_z``'s reference: ``ref``'s translation ``(3,)`` metres and the unit viewing ray
    ``(3,)`` (world axes) through ``ref``'s root joint."""
    with torch.no_grad():
        out, _, _ = scene.forward(ref.pose, ref.trans)
        root = out.joints[0, 0].double().numpy()
    return ref.trans.detach().clone().float(), en.camera_ray(scene.camera, root)


def _tensor(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, np.float32))


#: ``E_j``'s hold on a joint the fit has lost (``cfg.keypoint_hold_frames``): a detection
#: at least this confident, further than :data:`HOLD_FAR` times ``keypoint_sigma`` from the
#: fit's joint and further than :data:`HOLD_SWAP` times it from the fit's other-side joint
#: (a detector's left/right swap is not followed), counts as a frame the joint is lost. The
#: confidence is ``E_j``'s weight (:func:`~flowmocap.fit.objective.configured_keypoints`): at
#: the default ``keypoint_confidence_floor`` 1 every detected joint is confident enough.
HOLD_CONFIDENCE = 0.9
HOLD_FAR = 1.25
HOLD_SWAP = 0.75


def lost_joints(scene: Scene, state: FrameState, keypoints: tuple | None, cfg: TrackerConfig) -> np.ndarray:
    """``(24,)`` bool: the joints whose confident detection the fitted body at ``state``
    is far from (see :data:`HOLD_CONFIDENCE`), in the detector's convention
    (:func:`~flowmocap.vision.keypoint_map.detector_points`); all False without detections.

    Args:
        keypoints: the frame's ``(j2d (24, 2) px, conf (24,))`` (``FrameData.keypoints``).
    """
    if keypoints is None:
        return np.zeros(24, bool)
    j2d, conf = (np.asarray(k.detach().numpy() if isinstance(k, torch.Tensor) else k, np.float64) for k in keypoints)
    with torch.no_grad():
        out, _, _ = scene.forward(state.pose, state.trans)
        p = scene.camera.project(detector_points(out, cfg)[0]).double().numpy()
    d = np.linalg.norm(p - j2d, axis=1)
    d_other = np.linalg.norm(p[list(MIRROR_JOINTS)] - j2d, axis=1)
    sigma = cfg.keypoint_sigma
    return (conf >= HOLD_CONFIDENCE) & (d > HOLD_FAR * sigma) & (d_other > HOLD_SWAP * sigma)


class SequenceTracker:
    """The tracker's state between frames of one sequence.

    Args:
        scene: the body, its fitted shape and the camera.
        cfg: the settings.
        monitor: optional failure check, called after every tracked frame ``i`` as
            ``monitor(i, state, scene, mask)`` with the optimised :class:`FrameState` and
            the frame's mask (or None). It returns None to accept the frame, or
            ``(new_state, info)`` to re-initialise: the frame is replaced by ``new_state``,
            the Kalman filters restart from it, ``E_a`` is dropped for the rest of the
            sequence, and ``{"event": "re-initialised", **info}`` is recorded. A monitor
            with a ``take_events()`` method is asked for more events of the frame after
            each call (:meth:`~flowmocap.fit.reinit.ReinitMonitor.take_events`: the refits
            it turned down).

    Use :meth:`start` (or :meth:`load_state_dict` to resume), then :meth:`step` per frame.
    """

    def __init__(self, scene: Scene, cfg: TrackerConfig, monitor: Callable | None = None):
        self.scene = scene
        self.cfg = cfg
        self.monitor = monitor
        self.prev: FrameState | None = None
        self.anchor: FrameState | None = None  # E_a's reference (the first frame), None for no E_a
        self.kf: PoseFilter | None = None
        self.lost = np.zeros(24, np.int64)  # frames in a row each joint's detection was far from the fit
        self.votes = np.zeros(len(DEPTH_LIMBS), np.int64)  # frames in a row the detector saw each limb the other way

    def start(self, first: FrameState, second: FrameState, anchored: bool) -> None:
        """Begin after the first two frames. ``anchored``: the start is one someone vouched
        for (an init that states a rough pose, or a known start), so ``E_a`` holds the
        track to ``first``; the automatic init's start is a guess and is not, unless the
        settings' ``anchor_any_start`` says so (the pipeline passes that in ``anchored``)."""
        self.prev = second
        self.anchor = first if anchored else None
        self.kf = new_filter(first.pose.numpy(), first.trans.numpy(), self.cfg) if self.cfg.kalman else None
        if self.kf is not None:
            self.kf.update(second.pose.numpy().astype(np.float64), second.trans.numpy().astype(np.float64))

    def state_dict(self) -> dict:
        """JSON-serialisable state, enough to continue exactly (:meth:`load_state_dict`)."""
        return {
            "prev": {"pose": self.prev.pose.tolist(), "trans": self.prev.trans.tolist()},
            "anchor": None if self.anchor is None else self.anchor.pose.tolist(),
            "kalman": None if self.kf is None else self.kf.state_dict(),
            "monitor": self.monitor.state_dict() if hasattr(self.monitor, "state_dict") else None,
            "lost_joints": self.lost.tolist(),
            "limb_votes": self.votes.tolist(),
        }

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        self.prev = FrameState(_tensor(state["prev"]["pose"]), _tensor(state["prev"]["trans"]))
        anchor = state.get("anchor")
        self.anchor = None if anchor is None else FrameState(_tensor(anchor), torch.zeros(3))
        self.kf = PoseFilter.from_state_dict(state["kalman"]) if self.cfg.kalman and state.get("kalman") else None
        if state.get("monitor") is not None and hasattr(self.monitor, "load_state_dict"):
            self.monitor.load_state_dict(state["monitor"])
        # a state stored before the hold existed: the counts start again
        self.lost = np.asarray(state.get("lost_joints", np.zeros(24)), np.int64)
        self.votes = np.asarray(state.get("limb_votes", np.zeros(len(DEPTH_LIMBS))), np.int64)

    def predict(self) -> FrameState:
        """The Kalman prediction of the next frame (the previous frame without filters)."""
        if self.kf is None:
            return self.prev.clone()
        p, t = self.kf.predict()
        return FrameState(torch.as_tensor(p, dtype=torch.float32), torch.as_tensor(t, dtype=torch.float32))

    def step(self, i: int, mask: np.ndarray | None, data: FrameData) -> FrameResult:
        """Track frame ``i`` from its mask (``(H, W)`` bool or None) and observations.

        A frame in a long run without the person (``data.unseen``) is not optimised: the
        body is held at the last seen pose (nothing in the frame says where it went, and the
        flow there is the occluder's or the background's), the Kalman filter restarts from it
        (no velocity carried across) and the re-initialisation check is not asked; the first
        frame seen again is tracked from there and re-initialised where it does not fit."""
        t0 = time.perf_counter()
        events = []
        prev = self.prev
        if data.unseen is not None:
            state = prev.clone()
            a, b = data.unseen
            events.append({"frame": i, "event": "held: the person is not seen", "frames": [int(a), int(b)]})
            if self.kf is not None:
                self.kf = new_filter(state.pose.numpy(), state.trans.numpy(), self.cfg)
            self.lost[:] = 0
            self.votes[:] = 0
            self.prev = state
            return FrameResult(i, state, {}, events, time.perf_counter() - t0)
        pred = self.predict()
        data.anchor = self.anchor.pose if (self.anchor is not None and self.cfg.anchor_weight > 0) else None
        data.depth_ref = None
        if self.cfg.depth_temporal_weight > 0:
            data.depth_ref = depth_reference(self.scene, pred if self.cfg.depth_temporal_reference == "prediction"
                                             else prev)
        if mask is not None and not mask.any():
            events.append({"frame": i, "event": "empty mask: no silhouette term for this frame"})
            mask = None
        if mask is None:
            data.person_pixels = max(person_pixels(self.scene, prev), 1.0)
        swapped = self.cfg.detector_swap_check and self.exchange_if_swapped(pred, data)
        if swapped:
            events.append({"frame": i, "event": EXCHANGED_EVENT})
        if hasattr(self.monitor, "exchanged"):  # the re-initialisation judges the frame against the same detection
            self.monitor.exchanged = {i} if swapped else set()
        data.keypoint_hold = self.keypoint_hold(data)
        if data.keypoint_hold is not None:
            held = np.flatnonzero(data.keypoint_hold)
            events.append({"frame": i, "event": "held lost joints to the detector", "joints": [int(j) for j in held],
                           "frames_lost": [int(self.lost[j]) for j in held]})
        ref = pred  # E_theta's reference: the start of the optimisation
        try:
            state, terms = track_frame(self.scene, pred, data, self.cfg, prev)
        except OptimizationError as e:
            events.append({"frame": i, "event": "non-finite energy; retried from the previous pose",
                           "detail": str(e)})
            try:
                ref = prev.clone()
                state, terms = track_frame(self.scene, ref, data, self.cfg, prev)
            except OptimizationError as e2:
                events.append({"frame": i, "event": "retry failed; kept the prediction", "detail": str(e2)})
                state, terms, ref = pred, {"total": float("nan")}, None
        if self.cfg.flip_test and ref is not None:
            try:
                state, terms, flips = flip_limbs(self.scene, state, data, self.cfg, prev, ref.pose, frame=i,
                                                 terms=terms)
                events += flips
            except OptimizationError as e:
                events.append({"frame": i, "event": "depth-flip test skipped", "detail": str(e)})
        voted = False
        if self.cfg.flip_vote_frames > 0:
            state, votes = self.vote_flips(state, data, i)
            events += votes
            voted = bool(votes)
        reinit = self.monitor(i, state, self.scene, mask) if self.monitor is not None else None
        if hasattr(self.monitor, "take_events"):  # refit attempts it turned down, and why
            events += self.monitor.take_events()
        if reinit is not None:
            state, info = reinit
            events.append({"frame": i, "event": "re-initialised", **info})
            # the first frame no longer describes the track; with anchor_any_start the refit's pose does
            self.anchor = state.clone() if self.cfg.anchor_any_start else None
            if self.kf is not None:
                self.kf = new_filter(state.pose.numpy(), state.trans.numpy(), self.cfg)
        elif self.kf is not None and voted:  # a limb turned over: no velocity carried across the jump
            self.kf = new_filter(state.pose.numpy(), state.trans.numpy(), self.cfg)
        elif self.kf is not None:
            self.kf.update(state.pose.numpy().astype(np.float64), state.trans.numpy().astype(np.float64))
        if self.cfg.keypoint_hold_frames > 0 and self.cfg.keypoint_weight > 0:
            self.lost = np.where(lost_joints(self.scene, state, data.keypoints, self.cfg), self.lost + 1, 0)
        self.prev = state
        return FrameResult(i, state, terms, events, time.perf_counter() - t0)

    def exchange_if_swapped(self, pred: FrameState, data: FrameData) -> bool:
        """Whether the frame's detection labels the body left for right against the
        prediction ``pred`` (:func:`~flowmocap.fit.swap.detection_swapped`, at least
        ``keypoint_sigma`` px off as labelled); if so ``data.keypoints`` and
        ``data.joints3d`` are exchanged back in place (the 3D turned about the ray
        through the predicted root)."""
        if data.keypoints is None:
            return False
        with torch.no_grad():
            out, _, _ = self.scene.forward(pred.pose, pred.trans)
            p = self.scene.camera.project(detector_points(out, self.cfg)[0])
            root = self.scene.camera.to_camera(out.joints[0, 0]).double().numpy()
        if not detection_swapped(p, *data.keypoints, self.cfg.keypoint_sigma):
            return False
        data.keypoints = exchanged_2d(*data.keypoints)
        if data.joints3d is not None:
            data.joints3d = exchanged_3d(*data.joints3d, root)
        return True

    def vote_flips(self, state: FrameState, data: FrameData, i: int) -> tuple[FrameState, list]:
        """The multi-frame companion of the flip test (``cfg.flip_vote_frames``): for each
        limb of :data:`~flowmocap.fit.energies.DEPTH_LIMBS`, count the frames in a row in
        which the detector's 3D joints (``data.joints3d``, confidence at least 0.5, aligned
        onto the fit's joints by a similarity) and the fit both reach more than
        ``cfg.flip_vote_reach`` metres along the camera's axis from the limb's parent to
        its child, opposite ways; at ``cfg.flip_vote_frames`` the limb is mirrored in this
        frame (:func:`~flowmocap.fit.flip.flipped_pose`; an upper arm or thigh only if its
        wrist or ankle then lies no further from the detected one, when that is detected),
        and the tracking goes on from there. Returns ``(state, events)``."""
        from flowmocap.fit.flip import flipped_pose, limb_name
        from flowmocap.geometry.procrustes import similarity_procrustes

        if data.joints3d is None:
            self.votes[:] = 0
            return state, []
        j3d, conf = (np.asarray(x, np.float64) for x in data.joints3d)
        use = (conf >= 0.5) & np.isfinite(j3d).all(-1)
        if use.sum() < 6:
            self.votes[:] = 0
            return state, []
        events = []

        def posed(st):  # the body, its joints in the camera's axes and the detector's aligned onto them
            with torch.no_grad():
                o, _, _ = self.scene.forward(st.pose, st.trans)
            j = self.scene.camera.to_camera(o.joints[0]).double().numpy()
            aligned = np.full_like(j3d, np.nan)
            aligned[use] = similarity_procrustes(j3d[use], j[use])[0]
            return o, j, aligned

        out, jc, al = posed(state)
        for li, (p, c) in enumerate(DEPTH_LIMBS):
            if not (use[p] and use[c]):
                self.votes[li] = 0
                continue
            rf, rs = jc[c, 2] - jc[p, 2], al[c, 2] - al[p, 2]
            reach = self.cfg.flip_vote_reach
            against = abs(rf) > reach and abs(rs) > reach and np.sign(rf) != np.sign(rs)
            self.votes[li] = self.votes[li] + 1 if against else 0
            if self.votes[li] < self.cfg.flip_vote_frames:
                continue
            pose = flipped_pose(self.scene, state.pose, state.trans, (p, c))
            if pose is None:
                continue
            below = [g for g in range(len(PARENTS)) if PARENTS[g] == c and g in EVAL_JOINTS]
            if below and data.keypoints is not None and float(data.keypoints[1][below[0]]) >= 0.5:
                g = below[0]
                seen = np.asarray(data.keypoints[0][g], np.float64)
                with torch.no_grad():
                    new, _, _ = self.scene.forward(pose, state.trans)
                    px_old = self.scene.camera.project(out.joints[0, g]).double().numpy()
                    px_new = self.scene.camera.project(new.joints[0, g]).double().numpy()
                if np.linalg.norm(px_new - seen) > np.linalg.norm(px_old - seen):
                    continue
            state = FrameState(pose, state.trans.clone())
            out, jc, al = posed(state)
            self.votes[li] = 0
            events.append({"frame": i, "event": "limb flipped in depth by the detector's vote", "limb": limb_name((p, c)),
                           "frames": int(self.cfg.flip_vote_frames)})
        return state, events

    def keypoint_hold(self, data: FrameData) -> np.ndarray | None:
        """``(24,)`` bool: the joints ``E_j`` holds in the next frame (``FrameData.keypoint_hold``:
        scale ``keypoint_hold_sigma``, weight times ``keypoint_hold_weight``), those whose
        confident detection the fit has been far from for ``keypoint_hold_frames`` frames
        in a row and that are detected in this frame; None when none is (or the hold is off)."""
        K = self.cfg.keypoint_hold_frames
        if K <= 0 or data.keypoints is None or self.cfg.keypoint_weight <= 0:
            return None
        held = (self.lost >= K) & (data.keypoints[1].numpy() > 0)
        return held if held.any() else None


def track_frames(tracker: SequenceTracker, frames: range, observe: Callable[[int], tuple],
                 on_frame: Callable[[FrameResult], None], progress: bool = True, done: int = 0) -> None:
    """Track ``frames`` in order.

    Args:
        tracker: a started (or restored) :class:`SequenceTracker`.
        frames: the frame numbers to track.
        observe: ``observe(i) -> (mask (H, W) bool or None, FrameData)``; runs one frame
            ahead in a worker thread (OpenCV and numpy release the GIL, and the optimiser
            is single-threaded), so it must not touch the tracker.
        on_frame: called with each :class:`FrameResult` (``seconds`` includes waiting for
            the observations), e.g. to store it.
        progress: show a progress bar; done: frames already finished before ``frames``
            (for the bar).
    """
    bar = tqdm(frames, initial=done, total=done + len(frames), disable=not progress, unit="frame", desc="tracking")
    ahead = ThreadPoolExecutor(max_workers=1, thread_name_prefix="flowmocap-observe")
    it = iter(frames)
    nxt = next(it, None)
    pending = ahead.submit(observe, nxt) if nxt is not None else None
    try:
        while nxt is not None:
            t0 = time.perf_counter()
            mask, data = pending.result()
            i, nxt = nxt, next(it, None)
            pending = ahead.submit(observe, nxt) if nxt is not None else None
            res = tracker.step(i, mask, data)
            res.seconds = time.perf_counter() - t0
            on_frame(res)
            bar.update(1)
            bar.set_postfix({k[:4]: f"{v:.3g}" for k, v in res.terms.items()})
    finally:
        ahead.shutdown(wait=True, cancel_futures=True)
        bar.close()
