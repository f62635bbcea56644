"""Automatic person masks and 2D joints for a whole video, stored in the result folder.

:func:`detect_sequence` runs a :class:`~flowmocap.vision.detect.PersonDetector` over every
frame, keeps one person, cleans the masks and writes::

    OUT/detections/masks/000000.png ...   the person's mask per frame (0 / 255; all 0 = no person)
    OUT/detections/keypoints.npz          keypoints (T, K, 2) px, confidence (T, K), found (T,),
                                          names (K,), box (T, 4) px, world (T, K, 3) m (the
                                          detector's 3D guess, NaN where it gives none)
    OUT/detections/detections.json        detector, size, frames with no person, people ignored

A rerun (or ``--resume``) with the same detector and frames reuses them. :func:`auto_init`
turns one frame's keypoints into an ``init.json`` dict (the schema of
:mod:`flowmocap.fit.init`), with the body's facing direction guessed from the shoulders,
hips, nose and ears.

Keeping one person: the detector follows a person from frame to frame; the detections
are split into tracks wherever one does not continue the previous one
(:func:`~flowmocap.vision.person.same_person`), and the main track is kept: the largest
sum over its frames of box height x (box bottom / image height), i.e. the person seen
biggest, nearest (feet lowest in the image) and longest. The other tracks' frames count
as "no person" (someone else, e.g. in the background).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flowmocap.errors import NoPersonError
from flowmocap.vision.detect import KEYPOINT_NAMES, SMPL_KEYPOINTS, PersonDetector
from flowmocap.vision.person import clean_mask, person_box, same_person

__all__ = ["PersonTrack", "detect_sequence", "detect_joints3d", "load_detections", "auto_init",
           "first_person_frame", "frame_runs", "facing_rotvec", "MIN_INIT_JOINTS"]

#: Confident SMPL keypoints a frame needs to initialise the body on it.
MIN_INIT_JOINTS = 8
#: Keypoint confidence that counts as confident.
CONFIDENT = 0.5


@dataclass
class PersonTrack:
    """The kept person's detections in every frame of a sequence.

    Attributes:
        keypoints: ``(T, K, 2)`` pixels, names :data:`~flowmocap.vision.detect.KEYPOINT_NAMES`.
        confidence: ``(T, K)``; all 0 in frames without the person.
        found: ``(T,)`` bool, the person is in the frame.
        mask_paths: the ``T`` mask PNGs (an all-zero mask where the person is not found).
        info: the contents of ``detections.json``.
        world: ``(T, K, 3)`` metres, the detector's 3D keypoints
            (:attr:`~flowmocap.vision.detect.Detection.world`), NaN where it gave none;
            None for detections stored without them.
    """

    keypoints: np.ndarray
    confidence: np.ndarray
    found: np.ndarray
    mask_paths: list[Path]
    info: dict = field(default_factory=dict)
    world: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.found)

    def mask(self, i: int) -> np.ndarray:
        """``(H, W)`` bool mask of frame ``i``."""
        import cv2

        return cv2.imread(str(self.mask_paths[i]), cv2.IMREAD_GRAYSCALE) > 0

    def _in_smpl_order(self, values: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``i``'s per-keypoint ``values (K, d)`` and confidences as ``(24, d)`` and
        ``(24,)`` in SMPL joint order (0 for the joints the detector does not give)."""
        from flowmocap.body.skeleton import JOINT_NAMES

        out = np.zeros((24, values.shape[-1]))
        conf = np.zeros(24)
        for k, name in enumerate(SMPL_KEYPOINTS):
            j = JOINT_NAMES.index(name)
            out[j] = values[k]
            conf[j] = self.confidence[i, k]
        return out, conf

    def smpl_joints(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(24, 2)`` pixels and ``(24,)`` confidences of frame ``i`` in SMPL joint order
        (0 for the joints the detector does not give)."""
        return self._in_smpl_order(self.keypoints[i], i)

    def smpl_joints3d(self, i: int, camera=None) -> tuple[np.ndarray, np.ndarray] | None:
        """The detector's 3D joints of frame ``i`` in SMPL joint order: ``(24, 3)`` metres
        relative to the middle of the hips and ``(24,)`` confidences (0 for the joints it
        does not give), or None when the frame has none.

        The detector's axes are those of the ray through the person (x right, y down, z
        along the ray); with the ``camera`` (a
        :class:`~flowmocap.geometry.camera.PinholeCamera`) they are turned into the
        camera's own axes (:meth:`~flowmocap.geometry.camera.PinholeCamera.ray_rotation`
        through the middle of the detected hips, or of the confident keypoints).
        """
        if self.world is None or i >= len(self) or not self.found[i] or not np.isfinite(self.world[i]).all():
            return None
        j3d, conf = self._in_smpl_order(self.world[i], i)
        if camera is not None:
            hips = [KEYPOINT_NAMES.index("left_hip"), KEYPOINT_NAMES.index("right_hip")]
            use = hips if (self.confidence[i, hips] > 0).all() else np.nonzero(self.confidence[i] > 0)[0]
            if len(use):
                u, v = self.keypoints[i, use].mean(0)
                j3d = j3d @ camera.ray_rotation(float(u), float(v)).T
        return j3d, conf


def _mask_dir(out_dir: Path) -> Path:
    return Path(out_dir) / "detections" / "masks"


def load_detections(out_dir: str | Path, detector_name: str | None = None, num_frames: int | None = None,
                    size: tuple[int, int] | None = None) -> PersonTrack | None:
    """Stored detections of ``out_dir``, or None when absent or made for other input/settings."""
    d = Path(out_dir) / "detections"
    try:
        info = json.loads((d / "detections.json").read_text())
        with np.load(d / "keypoints.npz", allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (FileNotFoundError, ValueError, OSError):
        return None
    if detector_name is not None and info.get("detector") != detector_name:
        return None
    if num_frames is not None and info.get("frames") != num_frames:
        return None
    if size is not None and list(info.get("size", [])) != list(size):
        return None
    paths = [_mask_dir(out_dir) / f"{i:06d}.png" for i in range(len(arrays["found"]))]
    if not all(p.exists() for p in paths):
        return None
    return PersonTrack(arrays["keypoints"], arrays["confidence"], arrays["found"].astype(bool), paths, info,
                       arrays.get("world"))


def detect_sequence(seq, out_dir: str | Path, detector: PersonDetector | None = None, progress: bool = True,
                    reuse: bool = True, searcher: PersonDetector | None | str = "default") -> PersonTrack:
    """Masks and keypoints of one person in every frame of ``seq``, stored in ``out_dir``.

    A detector that tracks follows the first person it finds. To find the others, the
    ``searcher`` (a second detector) looks at every frame with the found person's box
    blanked out; all detections are then split into people by continuity and the main
    person kept (see the module docstring).

    Args:
        seq: anything with ``len(seq)``, ``seq.frame(i) -> (H, W, 3) uint8 RGB`` and
            ``seq.size = (W, H)`` (a :class:`~flowmocap.io.sequence.Sequence`).
        out_dir: the result folder (detections go to ``out_dir/detections``).
        detector: default :class:`~flowmocap.vision.detect.MediaPipePoseDetector`.
        progress: show a progress bar.
        reuse: return stored detections made by the same detectors for the same frames.
        searcher: the second detector; ``"default"``: MediaPipe without augmentation when
            ``detector`` is the default, else none; None: look for one person only.

    Raises:
        NoPersonError: no frame shows a person.
    """
    from tqdm import tqdm

    if detector is None:
        from flowmocap.vision.detect import MediaPipePoseDetector

        detector = MediaPipePoseDetector()
        if searcher == "default":
            searcher = MediaPipePoseDetector(augment=False)
    if searcher == "default":
        searcher = None
    name = detector.name + (f"+search:{searcher.name}" if searcher is not None else "")
    out_dir = Path(out_dir)
    T = len(seq)
    W, H = seq.size
    if reuse:
        stored = load_detections(out_dir, name, T, (W, H))
        if stored is not None:
            return stored
    detector.reset()
    if searcher is not None:
        searcher.reset()
    cands: list[list[tuple]] = [[] for _ in range(T)]  # per frame: (box, keypoints, confidence, mask, world)
    for i in tqdm(range(T), disable=not progress, unit="frame", desc="finding the person"):
        img = seq.frame(i)
        det = _usable(detector.detect(img))
        if det is None:
            continue
        cands[i].append(det)
        if searcher is not None:
            other = _usable(searcher.detect(_blank(img, det[0])))
            if other is not None:
                cands[i].append(other)

    tracks = _split_tracks(cands)
    K = len(KEYPOINT_NAMES)
    kp = np.zeros((T, K, 2))
    conf = np.zeros((T, K))
    world = np.full((T, K, 3), np.nan)
    boxes: list = [None] * T
    masks: list = [None] * T
    ignored = []
    if tracks:
        # nearer people are taller in the image and, standing on the ground below the
        # camera's height, have their feet lower in it: box height x feet height / H
        score = [sum((cands[i][c][0][3] - cands[i][c][0][1]) * cands[i][c][0][3] / H for i, c in t) for t in tracks]
        main = int(np.argmax(score))
        for i, c in tracks[main]:
            boxes[i], kp[i], conf[i], masks[i], w = cands[i][c]
            if w is not None:
                world[i] = w
        for k, t in enumerate(tracks):
            if k != main and len(t) > 2:
                ignored.append({"frames": [t[0][0], t[-1][0]], "why": "another person (smaller or seen for less time)"})
    found = np.array([m is not None for m in masks])
    mdir = _mask_dir(out_dir)
    mdir.mkdir(parents=True, exist_ok=True)
    import cv2

    empty = np.zeros((H, W), np.uint8)
    paths = []
    for i in range(T):
        p = mdir / f"{i:06d}.png"
        cv2.imwrite(str(p), empty if masks[i] is None else masks[i].astype(np.uint8) * 255)
        paths.append(p)
    info = {
        "detector": name, "frames": T, "size": [W, H], "keypoint_names": list(KEYPOINT_NAMES),
        "frames_with_person": int(found.sum()),
        "no_person": frame_runs(np.nonzero(~found)[0]),
        "ignored_people": ignored,
    }
    box_arr = np.array([b if b is not None else (np.nan,) * 4 for b in boxes], np.float64).reshape(T, 4)
    d = out_dir / "detections"
    np.savez(d / "keypoints.npz", keypoints=kp.astype(np.float32), confidence=conf.astype(np.float32),
             found=found, names=np.array(KEYPOINT_NAMES), box=box_arr, world=world.astype(np.float32))
    (d / "detections.json").write_text(json.dumps(info, indent=2))
    if not found.any():
        raise NoPersonError(f"no person found in any of the {T} frames of {getattr(seq, 'root', 'the input')}; "
                            "check that a whole person is visible, or give --init init.json and --masks FOLDER.")
    return PersonTrack(kp.astype(np.float32), conf.astype(np.float32), found, paths, info, world.astype(np.float32))


def detect_joints3d(seq, out_dir: str | Path, camera=None, progress: bool = True) -> tuple:
    """The detector's 3D joints for ``E_d`` when nothing else runs the detector (an input
    with its own masks and init.json): MediaPipe without the mask augmentation (about
    0.05 s per frame), stored in ``out_dir/detections`` like :func:`detect_sequence`.

    Returns:
        ``(joints3d, note)``: the callable ``joints3d(i) -> (j3d (24, 3), conf (24,)) |
        None`` the tracker takes (:meth:`PersonTrack.smpl_joints3d`, in the axes of the
        ``camera`` when given), or None when no detector is installed or it finds no
        person; and a sentence for ``input.json``.
    """
    from flowmocap.errors import InputError
    from flowmocap.vision.detect import MediaPipePoseDetector

    try:
        track = detect_sequence(seq, out_dir, detector=MediaPipePoseDetector(augment=False), progress=progress)
    except (InputError, NoPersonError) as e:
        return None, f"no 3D joints for E_d: {e}"
    return (lambda i: track.smpl_joints3d(i, camera)), (f"3D joints for E_d: {track.info['detector']}, "
                                                        f"{track.info['frames_with_person']} frames")


def _usable(det) -> tuple | None:
    """``(box, keypoints, confidence, cleaned mask, world keypoints or None)`` of a
    detection, or None if it shows no person (empty cleaned mask or fewer than 2
    confident joints)."""
    if det is None:
        return None
    m = clean_mask(det.mask, det.keypoints, det.confidence)
    if not m.any() or (det.confidence[: len(SMPL_KEYPOINTS)] >= CONFIDENT).sum() < 2:
        return None
    return person_box(det.keypoints, det.confidence, m), det.keypoints, det.confidence, m, getattr(det, "world", None)


def _blank(img: np.ndarray, box, grow: float = 0.1) -> np.ndarray:
    """A copy of ``img`` with ``box`` (enlarged by ``grow`` of its size) filled with the image's mean colour."""
    H, W = img.shape[:2]
    x0, y0, x1, y1 = box
    gx, gy = grow * (x1 - x0), grow * (y1 - y0)
    out = img.copy()
    out[max(0, int(y0 - gy)):min(H, int(np.ceil(y1 + gy))), max(0, int(x0 - gx)):min(W, int(np.ceil(x1 + gx)))] = \
        img.reshape(-1, 3).mean(0).astype(np.uint8)
    return out


def _split_tracks(cands: list[list[tuple]], max_gap: int = 15) -> list[list[tuple[int, int]]]:
    """People as lists of ``(frame, candidate index)``: a candidate joins the track whose
    last box it continues best (:func:`same_person`, at most ``max_gap`` frames later),
    each track taking at most one candidate per frame; otherwise it starts a new track."""
    from flowmocap.vision.person import box_iou

    tracks: list[list[tuple[int, int]]] = []
    for i, frame in enumerate(cands):
        taken: set[int] = set()
        for c, cand in enumerate(frame):
            box = cand[0]
            best, best_score = None, -1.0
            for k, t in enumerate(tracks):
                j, cj = t[-1]
                if k in taken or i - j > max_gap or j == i:
                    continue
                prev = cands[j][cj][0]
                if same_person(prev, box, i - j):
                    score = box_iou(prev, box) - 0.01 * (i - j)
                    if score > best_score:
                        best, best_score = k, score
            if best is None:
                tracks.append([(i, c)])
                taken.add(len(tracks) - 1)
            else:
                tracks[best].append((i, c))
                taken.add(best)
    return tracks


def frame_runs(idx: list[int]) -> list[list[int]]:
    """Sorted frame indices as runs of consecutive frames.

    Args:
        idx: ascending frame numbers (any iterable of ints, e.g. ``np.nonzero(mask)[0]``).

    Returns:
        ``[[first, last], ...]``, one inclusive pair per run; ``[]`` for no frames.
        ``frame_runs([2, 3, 4, 7, 9, 10]) == [[2, 4], [7, 7], [9, 10]]``.
    """
    out: list[list[int]] = []
    for i in (int(v) for v in idx):
        if out and out[-1][1] == i - 1:
            out[-1][1] = i
        else:
            out.append([i, i])
    return out


def first_person_frame(track: PersonTrack, start: int = 0, min_joints: int = MIN_INIT_JOINTS) -> int | None:
    """The first frame from ``start`` on with at least ``min_joints`` confident SMPL
    keypoints (hips and shoulders among them), or None."""
    n = len(SMPL_KEYPOINTS)
    need = [SMPL_KEYPOINTS.index(j) for j in ("left_hip", "right_hip", "left_shoulder", "right_shoulder")]
    for i in range(start, len(track)):
        c = track.confidence[i, :n]
        if track.found[i] and (c >= CONFIDENT).sum() >= min_joints and (c[need] >= CONFIDENT).all():
            return i
    return None


def facing_rotvec(keypoints: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    """A rough global orientation ``(3,)`` axis-angle (radians) of an upright person
    with the given keypoints, for a camera with the identity rotation (OpenCV axes).

    The body stands upright (its up is the image's up) and turns about the vertical by
    the yaw whose cosine is the signed left-right spread of shoulders and hips relative
    to the torso length (a person facing the camera has their left on the image's right);
    which way a side-on person faces comes from the nose against the ears (or the
    shoulders). Yaw 0 faces the camera.
    """
    from scipy.spatial.transform import Rotation

    kp = {n: np.asarray(keypoints[k], np.float64) for k, n in enumerate(KEYPOINT_NAMES)}
    cf = {n: float(confidence[k]) for k, n in enumerate(KEYPOINT_NAMES)}
    mid_s = (kp["left_shoulder"] + kp["right_shoulder"]) / 2
    mid_h = (kp["left_hip"] + kp["right_hip"]) / 2
    torso = max(float(np.linalg.norm(mid_s - mid_h)), 1.0)
    # joint-to-joint widths relative to the torso: shoulders ~0.7, hips ~0.4
    spread = ((kp["left_shoulder"][0] - kp["right_shoulder"][0]) / 0.7
              + (kp["left_hip"][0] - kp["right_hip"][0]) / 0.4) / 2
    c = float(np.clip(spread / torso, -1.0, 1.0))
    ears = [kp[e] for e in ("left_ear", "right_ear") if cf[e] >= 0.3]
    ref = np.mean(ears, axis=0) if ears else mid_s
    side = kp["nose"][0] - ref[0] if cf["nose"] >= 0.3 else 0.0
    # facing direction in the camera frame is (-sin(yaw), 0, -cos(yaw)): facing image right = sin < 0
    s = -math.copysign(math.sqrt(max(0.0, 1.0 - c * c)), side) if side != 0.0 else 0.0
    yaw = math.atan2(s, c)
    R = Rotation.from_euler("y", yaw) * Rotation.from_euler("x", math.pi)
    return R.as_rotvec()


def auto_init(track: PersonTrack, frame: int, min_confidence: float = 0.3) -> dict:
    """An ``init.json`` dict (schema of :mod:`flowmocap.fit.init`) from frame ``frame``'s
    keypoints: the confident SMPL joints with their confidences, and the rough global
    orientation of :func:`facing_rotvec`.

    Raises:
        NoPersonError: the frame has fewer than 4 confident joints.
    """
    kp, cf = track.keypoints[frame], track.confidence[frame]
    joints, conf = {}, {}
    for k, name in enumerate(SMPL_KEYPOINTS):
        if cf[k] >= min_confidence:
            joints[name] = [float(v) for v in kp[k]]
            conf[name] = float(cf[k])
    if len(joints) < 4:
        raise NoPersonError(f"frame {frame}: the detector found fewer than 4 joints of the person; "
                            "give --init init.json with the joints of a frame instead.")
    return {"frame": int(frame), "joints2d": joints, "confidence": conf,
            "pose": {"pelvis": facing_rotvec(kp, cf).tolist()},
            "note": f"automatic: {track.info.get('detector', 'detector')} keypoints of frame {frame}"}
