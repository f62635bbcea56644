"""A learned lifter from the detector's 2D keypoints to root-relative 3D (issue 18).

MediaPipe's own 3D keypoints ("world landmarks") are the depth cue of ``E_d``, ``E_3d``
and the 3D re-initialisation criterion. This module offers a second source for the same
cues: a small network (a residual MLP in the manner of Martinez et al., "A simple yet
effective baseline for 3d human pose estimation", 2017) that maps the 13 evaluation
keypoints of one frame's 2D detection to their 3D positions relative to the middle of the
hips. It was trained by ``tools/train_lifter.py`` on the ``train`` clips of
``../shared/data/mocap/prior`` only (CMU mocap retargeted onto the body model, the
detector's keypoints placed on the posed body by the learned offsets of
:mod:`flowmocap.vision.keypoint_map`, random bodies, random views, 2D noise and
dropped joints); the weights ship with the package (``vision/data/lifter.npz``, licence in
``vision/data/README.md``).

Conventions:

- Input: pixels of one camera (any size; square pixels), the keypoints of
  :data:`~flowmocap.vision.detect.KEYPOINT_NAMES` with their confidences. The 13 points are
  those of :func:`flowmocap.eval.real3d.eval_points` (the head is the middle of the ears).
  They are centred on the middle of the hips and divided by their RMS distance from it,
  so neither the image size nor the focal length matters.
- Output: metres in the axes of the ray through the person (x right, y down, z away from
  the camera along the ray), hip-centred, like the detector's world landmarks; the size
  is that of an average training body (only the shape is learned: every consumer aligns
  it by a similarity).
"""

from __future__ import annotations

import json
from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from flowmocap.errors import InputError, ModelFileError

__all__ = ["LIFTER_FILE", "LIFTER_KIND", "MIRROR", "WINDOW_FPS", "Lifter", "LifterNet", "bridge_gaps", "eval_points_2d",
           "lifted_track",
           "load_lifter", "normalise_2d", "window_indices"]

LIFTER_KIND = "flowmocap-keypoint-lifter"
#: 2 added ``offsets`` (a window of frames); format 1 files (one frame) still load
LIFTER_FORMAT = 2
#: the frame rate a window's offsets count in
WINDOW_FPS = 30.0
LIFTER_FILE = Path(__file__).resolve().parent / "data" / "lifter.npz"
#: the 13 points, in the order of :data:`flowmocap.eval.real3d.EVAL_NAMES`
POINTS = ("head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
          "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle")
HIPS = (7, 8)
#: each of the 13 points' left/right counterpart (the head is its own)
MIRROR = tuple(POINTS.index(n.replace("left", "@").replace("right", "left").replace("@", "right")) for n in POINTS)
#: fewer confident points than this (both hips among them) and a frame is not lifted
MIN_POINTS = 8


class LifterNet(torch.nn.Module):
    """``(B, F, 13, 2)`` normalised 2D points of a window of ``F`` frames and ``(B, F,
    13)`` masks (1 = given) to ``(B, 13, 3)``, the normalised 3D of the window's middle
    frame (``F = 1``: ``(B, 13, 2)`` and ``(B, 13)`` are taken too): a linear layer to
    ``hidden``, ``blocks`` residual blocks (two linear layers with layer norm, ReLU and
    dropout each), a linear layer out."""

    def __init__(self, hidden: int = 512, blocks: int = 2, dropout: float = 0.1, frames: int = 1):
        super().__init__()
        n = len(POINTS)
        self.frames = int(frames)
        self.inp = torch.nn.Linear(3 * n * self.frames, hidden)

        def half():
            return [torch.nn.Linear(hidden, hidden), torch.nn.LayerNorm(hidden), torch.nn.ReLU(),
                    torch.nn.Dropout(dropout)]

        self.blocks = torch.nn.ModuleList([torch.nn.Sequential(*half(), *half()) for _ in range(blocks)])
        self.out = torch.nn.Linear(hidden, 3 * n)

    def forward(self, points: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The normalised 3D of the window's middle frame.

        Args:
            points: ``(B, F, 13, 2)`` (or ``(B, 13, 2)`` for ``F = 1``) normalised 2D
                points (:func:`normalise_2d`), in the order of :data:`POINTS`.
            mask: ``(B, F, 13)`` (or ``(B, 13)``) float, 1 where a point is given, 0 where not.

        Returns:
            ``(B, 13, 3)`` in normalised units (times :attr:`Lifter.metres`: metres), in
            the ray's axes; :meth:`Lifter.lift_points` re-centres it on the hips.
        """
        x = torch.cat([(points * mask[..., None]).flatten(1), mask.flatten(1)], 1)
        x = torch.relu(self.inp(x))
        for b in self.blocks:
            x = x + b(x)
        return self.out(x).view(-1, len(POINTS), 3)


def normalise_2d(points: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(points - hips) / s`` and ``s (B, 1, 1)``: ``points (B, 13, 2)`` centred on the
    middle of the hips and divided by the RMS distance of the masked points from it
    (masked-out points: 0). ``mask (B, 13)`` float, 1 for a given point; ``s`` is in the
    points' unit (pixels), the normalised points ``(B, 13, 2)`` are unitless."""
    v = points - points[:, list(HIPS)].mean(1, keepdim=True)
    s = (((v ** 2).sum(-1) * mask).sum(1) / mask.sum(1).clamp(min=1)).sqrt().clamp(min=1e-9)[:, None, None]
    return v / s * mask[..., None], s


def eval_points_2d(keypoints: np.ndarray, confidence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(T, 13, d)`` points and ``(T, 13)`` confidences from ``keypoints (T, K, d)`` (2D
    pixels, or 3D) and ``confidence (T, K)`` of :data:`~flowmocap.vision.detect.KEYPOINT_NAMES`
    (the head: the middle of the ears, with the lower of their confidences)."""
    from flowmocap.vision.detect import KEYPOINT_NAMES

    kp, cf = np.asarray(keypoints, np.float64), np.asarray(confidence, np.float64)
    ears = [KEYPOINT_NAMES.index("left_ear"), KEYPOINT_NAMES.index("right_ear")]
    idx = [KEYPOINT_NAMES.index(n) for n in POINTS[1:]]
    pts = np.concatenate([kp[:, ears].mean(1, keepdims=True), kp[:, idx]], 1)
    conf = np.concatenate([cf[:, ears].min(1, keepdims=True), cf[:, idx]], 1)
    return pts, conf


def bridge_gaps(points: np.ndarray, given: np.ndarray, max_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Each point's runs of frames not given, of at most ``max_frames`` frames and with a
    given frame on both sides, filled by straight-line interpolation in time between
    those two frames, and marked given.

    A lifter told a point is missing guesses it from the rest of the pose; where the
    detector loses a limb for a moment (hidden behind the body, blurred), the line
    between where it was last and first seen is the better guess (docs/experiments.md,
    thirty-third session). Runs at the start or end of the sequence stay missing.

    Args:
        points: ``(T, N, d)`` positions (pixels, or any unit), frames in order.
        given: ``(T, N)`` bool, the points to trust; the others' values are ignored.
        max_frames: the longest run to fill; 0 fills none.

    Returns:
        ``(points, given)``: new arrays of the same shapes.
    """
    pts = np.array(points, np.float64)
    ok = np.array(given, bool)
    if pts.ndim != 3 or ok.shape != pts.shape[:2]:
        raise InputError(f"points must be (T, N, d) and given (T, N); got {pts.shape} and {np.shape(given)}.")
    if not (int(max_frames) == max_frames and max_frames >= 0):
        raise InputError(f"max_frames must be a whole number >= 0; got {max_frames!r}.")
    ok &= np.isfinite(pts).all(-1)
    out_ok = ok.copy()
    if max_frames == 0:
        return pts, out_ok
    for j in range(pts.shape[1]):
        seen = np.flatnonzero(ok[:, j])
        for a, b in zip(seen[:-1], seen[1:]):
            if 1 < b - a <= max_frames + 1:
                f = ((np.arange(a + 1, b) - a) / (b - a))[:, None]
                pts[a + 1:b, j] = (1.0 - f) * pts[a, j] + f * pts[b, j]
                out_ok[a + 1:b, j] = True
    return pts, out_ok


def window_indices(frames: int, offsets, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """``(index (T, F), inside (T, F))``: for each of ``frames`` frames at ``fps`` the
    frame nearest in time to each window offset (``offsets``, ``F`` ints, frames at
    :data:`WINDOW_FPS`), and whether it lies inside the sequence (``index`` clipped).
    ``index`` is int frame indices, ``inside`` bool."""
    t = np.arange(frames)[:, None] + np.rint(np.asarray(offsets, np.float64) * (fps / WINDOW_FPS)).astype(int)[None]
    inside = (t >= 0) & (t < frames)
    return np.clip(t, 0, max(frames - 1, 0)), inside


class Lifter:
    """The trained network with its metadata (``info``: training data, settings, the
    held-out check), ``metres``, the size of one normalised unit in metres, and
    ``offsets``, the window of frames it reads (frames at :data:`WINDOW_FPS` around the
    lifted one; ``(0,)``: one frame alone). ``flip_average``: :meth:`lift_points` also
    lifts each input mirrored left for right (the 2D's x negated about the hips and the
    labels exchanged), mirrors that 3D back and returns the mean of the two (test-time
    flip augmentation; the output then treats a pose and its mirror image alike)."""

    def __init__(self, net: LifterNet, info: dict, metres: float, offsets=(0,), flip_average: bool = False):
        self.flip_average = bool(flip_average)
        self.net = net.eval()
        self.info = info
        self.metres = float(metres)
        self.offsets = tuple(int(k) for k in offsets)
        if len(self.offsets) != net.frames or 0 not in self.offsets:
            raise ModelFileError(f"a lifter's window {self.offsets} must hold 0 and match its network's "
                                 f"{net.frames} frames.")

    @property
    def temporal(self) -> bool:
        """Whether it reads neighbouring frames (then :meth:`lift` needs ``fps``)."""
        return self.offsets != (0,)

    def lift_points(self, points: np.ndarray, mask: np.ndarray, fps: float | None = None) -> np.ndarray:
        """The 13 points of :data:`POINTS` in 3D, from their 2D.

        Args:
            points: ``(T, 13, 2)`` pixels in the order of :data:`POINTS` (the head at the
                middle of the ears), ``T`` consecutive frames of one video.
            mask: ``(T, 13)`` bool, the points given (others are left out of the input).
            fps: as in :meth:`lift`.

        Returns:
            ``(T, 13, 3)`` metres in the ray's axes, hip-centred; NaN for frames with fewer
            than :data:`MIN_POINTS` points given or without both hips.

        Raises:
            InputError: wrong shapes, or no usable ``fps`` for a temporal lifter.
        """
        pts = np.asarray(points, np.float64)
        if pts.ndim != 3 or pts.shape[1:] != (len(POINTS), 2):
            raise InputError(f"points must be (T, {len(POINTS)}, 2) pixels; got {pts.shape}.")
        mask = np.asarray(mask, bool)
        if mask.shape != pts.shape[:2]:
            raise InputError(f"mask must be (T, {len(POINTS)}); got {mask.shape}.")
        if self.temporal and not (fps is not None and np.isfinite(fps) and fps > 0):
            raise InputError(f"this lifter reads a window of frames {self.offsets} at {WINDOW_FPS:g} fps; pass the "
                             f"video's frame rate (fps > 0), got {fps!r}.")
        mask = mask & np.isfinite(pts).all(-1)
        ok = mask[:, list(HIPS)].all(1) & (mask.sum(1) >= MIN_POINTS)
        out = np.full((len(pts), len(POINTS), 3), np.nan)
        if not ok.any():
            return out
        mask &= ok[:, None]
        m_all = torch.as_tensor(mask, dtype=torch.float32)
        v_all, _ = normalise_2d(torch.as_tensor(np.nan_to_num(pts), dtype=torch.float32), m_all)
        index, inside = window_indices(len(pts), self.offsets, fps if self.temporal else WINDOW_FPS)
        index, inside = index[ok], torch.as_tensor(inside[ok], dtype=torch.float32)
        v, m = v_all[index], m_all[index] * inside[..., None]  # (n, F, 13, 2), (n, F, 13)
        with torch.no_grad():
            y = self.net(v * m[..., None], m).double().numpy() * self.metres
            if self.flip_average:  # the mirror image lifted, mirrored back, averaged
                flip = torch.tensor([-1.0, 1.0])
                vm, mm = v[..., list(MIRROR), :] * flip, m[..., list(MIRROR)]
                ym = self.net(vm * mm[..., None], mm).double().numpy() * self.metres
                y = 0.5 * (y + ym[:, list(MIRROR)] * np.array([-1.0, 1.0, 1.0]))
        out[ok] = y - y[:, list(HIPS)].mean(1, keepdims=True)
        return out

    def lift(self, keypoints: np.ndarray, confidence: np.ndarray, min_confidence: float = 0.5,
             fps: float | None = None) -> np.ndarray:
        """The detector's keypoints in 3D.

        Args:
            keypoints: ``(T, K, 2)`` pixels, :data:`~flowmocap.vision.detect.KEYPOINT_NAMES`,
                ``T`` consecutive frames of one video.
            confidence: ``(T, K)``; a point below ``min_confidence`` is left out of the
                input (the network was trained with dropped points).
            fps: the frames' rate (Hz); needed by a temporal lifter, which reads for each
                frame the frames nearest its window's offsets (frames outside the sequence
                or without the person are left out, as in training).

        Returns:
            ``(T, K, 3)`` metres in the ray's axes, hip-centred (see the module
            docstring), in the order of ``KEYPOINT_NAMES``: the 12 limb keypoints, both
            ears and the nose at the head point; NaN for frames with fewer than
            :data:`MIN_POINTS` confident points or without both hips.

        Raises:
            InputError: wrong shapes, or no ``fps`` (or not a positive number) for a
                temporal lifter.
        """
        from flowmocap.vision.detect import KEYPOINT_NAMES

        kp = np.asarray(keypoints, np.float64)
        if kp.ndim != 3 or kp.shape[1:] != (len(KEYPOINT_NAMES), 2):
            raise InputError(f"keypoints must be (T, {len(KEYPOINT_NAMES)}, 2) pixels; got {kp.shape}.")
        cf = np.asarray(confidence, np.float64)
        if cf.shape != kp.shape[:2]:
            raise InputError(f"confidence must be (T, {len(KEYPOINT_NAMES)}); got {cf.shape}.")
        if self.temporal and not (fps is not None and np.isfinite(fps) and fps > 0):
            raise InputError(f"this lifter reads a window of frames {self.offsets} at {WINDOW_FPS:g} fps; pass the "
                             f"video's frame rate (fps > 0), got {fps!r}.")
        pts, conf = eval_points_2d(kp, cf)
        y = self.lift_points(pts, (conf >= min_confidence) & np.isfinite(pts).all(-1), fps=fps)
        ok = np.isfinite(y).all((1, 2))
        out = np.full((len(kp), len(KEYPOINT_NAMES), 3), np.nan)
        y = y[ok]
        for k, name in enumerate(POINTS[1:], start=1):
            out[ok, KEYPOINT_NAMES.index(name)] = y[:, k]
        for name in ("left_ear", "right_ear", "nose"):
            out[ok, KEYPOINT_NAMES.index(name)] = y[:, 0]
        return out

    def save(self, path: str | Path) -> None:
        """Write the ``.npz`` (weights as float16, ``info`` and the architecture as JSON)."""
        arrays = {f"w/{k}": v.detach().numpy().astype(np.float16) for k, v in self.net.state_dict().items()}
        meta = {"kind": LIFTER_KIND, "format": LIFTER_FORMAT, "metres": self.metres,
                "hidden": self.net.inp.out_features, "blocks": len(self.net.blocks), "offsets": list(self.offsets),
                "window_fps": WINDOW_FPS, "info": self.info}
        np.savez_compressed(path, meta=np.array(json.dumps(meta)), **arrays)

    @classmethod
    def load(cls, path: str | Path | None = None) -> "Lifter":
        """Read a lifter file (default: the packaged one).

        Raises:
            ModelFileError: missing, unreadable, or not a lifter file of this format.
        """
        p = LIFTER_FILE if path is None else Path(path).expanduser()
        try:
            with np.load(p, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                weights = {k[2:]: torch.as_tensor(z[k].astype(np.float32)) for k in z.files if k.startswith("w/")}
        except (OSError, KeyError, ValueError) as e:
            raise ModelFileError(f"{p} is not a readable lifter file ({e}); reinstall flowmocap or retrain it with "
                                 "tools/train_lifter.py of the source repository.") from e
        if meta.get("kind") != LIFTER_KIND or meta.get("format") not in (1, LIFTER_FORMAT):
            raise ModelFileError(f"{p} is not a flowmocap keypoint lifter (kind {meta.get('kind')!r}, format "
                                 f"{meta.get('format')!r}; expected {LIFTER_KIND!r}, 1 or {LIFTER_FORMAT}).")
        offsets = meta.get("offsets", [0])
        if float(meta.get("window_fps", WINDOW_FPS)) != WINDOW_FPS:
            raise ModelFileError(f"{p}: its window counts frames at {meta['window_fps']} fps; this flowmocap reads "
                                 f"{WINDOW_FPS:g}.")
        net = LifterNet(hidden=int(meta["hidden"]), blocks=int(meta["blocks"]), frames=len(offsets))
        try:
            net.load_state_dict(weights)
        except RuntimeError as e:
            raise ModelFileError(f"{p}: the weights do not fit the stated architecture ({e}).") from e
        return cls(net, meta.get("info", {}), meta["metres"], offsets)


@lru_cache(maxsize=2)
def load_lifter(path: str | None = None) -> Lifter:
    """:meth:`Lifter.load`, once per process and path."""
    return Lifter.load(path)


def lifted_track(track, lifter: Lifter | None = None, mix: bool = False, fps: float | None = None):
    """A copy of a :class:`~flowmocap.vision.auto.PersonTrack` whose ``world`` (the 3D
    keypoints every depth cue reads) is the lifter's 3D of its 2D keypoints; frames
    without the person, or with too few confident points, get NaN (no 3D cue there).
    ``fps``: the video's frame rate (a temporal lifter needs it; :meth:`Lifter.lift`).

    ``mix``: where the track has the detector's own 3D keypoints too, the mean of the two
    instead (the lifter's aligned onto the detector's by a similarity per frame, fitted on
    the 12 limb keypoints, then averaged point by point); the lifter's alone where the
    detector gave none.
    """
    from flowmocap.geometry.procrustes import similarity_procrustes
    from flowmocap.vision.detect import KEYPOINT_NAMES, SMPL_KEYPOINTS

    lifter = load_lifter() if lifter is None else lifter
    conf = np.where(np.asarray(track.found, bool)[:, None], track.confidence, 0.0)
    world = lifter.lift(track.keypoints, conf, fps=fps)
    world[~np.asarray(track.found, bool)] = np.nan
    if mix and track.world is not None:
        own = np.asarray(track.world, np.float64)
        both = np.isfinite(world).all((1, 2)) & np.isfinite(own).all((1, 2))
        if both.any():
            w = np.isin(np.asarray(KEYPOINT_NAMES), SMPL_KEYPOINTS).astype(np.float64)
            aligned = similarity_procrustes(world[both], own[both], weights=w)[0]
            world[both] = 0.5 * (aligned + own[both])
    return replace(track, world=world)
