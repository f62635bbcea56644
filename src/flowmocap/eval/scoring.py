"""All metrics of a result folder against a sequence (``flowmocap eval RESULT --gt SEQ``).

Which metrics apply depends on what the sequence has: the 3D and 2D joint errors need
``gt.npz`` (synthetic sequences), the silhouette IoU needs ``masks/``; a metric that
does not apply is ``None``. Speed and memory come from the result's ``run.json``:

- ``s_per_frame``: the median of ``timings.frame_s`` (one tracked frame, observed flow
  included; the one-time initialisation is ``init_s``), as the tracker records it.
- ``peak_rss_mb``: peak resident memory (MiB) of the process that produced the result
  (Linux ``VmHWM``, else ``ru_maxrss``; :func:`flowmocap.eval.bench.peak_rss_mb`),
  recorded in ``run.json`` by :mod:`flowmocap.eval.bench`, which runs each method in a
  fresh process, so the figure is that method's own peak, Python and torch included;
  ``None`` for results made elsewhere (or with the bench's in-process mode). GPU memory
  is not measured (the tracker runs on the CPU).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from flowmocap.errors import DataError
from flowmocap.eval import metrics as m
from flowmocap.vision.masks import mask_iou

#: The headline metrics, in table order, with their table headers.
COLUMNS = (
    ("local_cm", "local cm"),
    ("global_cm", "global cm"),
    ("mpjpe_cm", "MPJPE cm"),
    ("accel_mm", "accel mm/f^2"),
    ("px2d", "2D px"),
    ("iou", "IoU"),
    ("s_per_frame", "s/frame"),
)


def _mean(x) -> float | None:
    x = np.asarray(x, np.float64)
    return float(x.mean()) if x.size else None


def score_result(result: str | Path, seq, model=None) -> dict:
    """Score a result folder against a sequence.

    Args:
        result: a result folder (``motion.npz`` + ``run.json``, see
            :mod:`flowmocap.io.results`).
        seq: a :class:`~flowmocap.io.sequence.Sequence` (or its folder) with ``gt.npz``
            and/or masks.
        model: the body model of the result, for the silhouettes (default: the one
            ``run.json`` records, as ``export`` and ``render`` use).

    Returns:
        dict with ``frames``, ``local_cm``, ``global_cm``, ``mpjpe_cm``, ``accel_mm``
        (mm/frame^2 at the sequence's frame rate), ``px2d``, ``iou``, ``s_per_frame``,
        ``init_s``, ``total_s``, ``peak_rss_mb`` (``None`` where not applicable) and
        per-frame lists ``local_cm_per_frame``, ``iou_per_frame``.

    Raises:
        DataError: unreadable result, or frames of the result outside the sequence or its
            ``gt.npz``.
    """
    from flowmocap.geometry.camera import PinholeCamera
    from flowmocap.io.results import read_result
    from flowmocap.io.sequence import Sequence, load_sequence

    from flowmocap.errors import check_path

    if not isinstance(seq, Sequence):
        check_path(seq, "seq", "a sequence folder")
    motion, run = read_result(result)
    missing = [k for k in ("frame_index", "joints3d") if k not in motion]
    if missing:
        raise DataError(f"{result}'s motion has no {', '.join(missing)}; it is not a flowmocap result, or a damaged "
                        "one: track the input again with --force.")
    if not isinstance(seq, Sequence):
        seq = load_sequence(seq)
    idx = np.asarray(motion["frame_index"], int)
    if idx.size == 0:
        raise DataError(f"{result} holds no frames yet; track some frames before scoring.")
    if idx.max() >= len(seq):
        raise DataError(f"{result} has frame {idx.max()} but the sequence {seq.root} has {len(seq)} frames; "
                        "score the result against the sequence it was made from.")
    out: dict = {"frames": int(idx.size)}
    for k in ("local_cm", "global_cm", "mpjpe_cm", "accel_mm", "px2d", "iou"):
        out[k] = None
    gt = seq.gt
    for key in ("joints3d", "joints2d"):  # per-frame ground truth, indexed by the result's frame numbers
        if key not in gt:
            continue
        have = np.asarray(gt[key]).shape[0] if np.ndim(gt[key]) else 0
        if have <= idx.max():
            raise DataError(f"{seq.root}/gt.npz '{key}' has {have} frames but the result has "
                            f"frame {idx.max()}; the ground truth is cut short: regenerate the sequence, or score "
                            "against the sequence the result was made from.")
    if "joints3d" in gt:
        pred = np.asarray(motion["joints3d"], np.float64)
        ref = np.asarray(gt["joints3d"], np.float64)[idx]
        if not np.isfinite(ref).all():
            raise DataError(f"{seq.root}/gt.npz 'joints3d' holds NaN or infinite values in the frames the result has; "
                            "the ground truth is damaged: regenerate the sequence (flowmocap synth).")
        local = m.local_procrustes_error(pred, ref)
        out["local_cm"] = 100 * _mean(local)
        out["global_cm"] = 100 * _mean(m.global_procrustes_error(pred, ref))
        out["mpjpe_cm"] = 100 * _mean(m.mpjpe(pred, ref))
        if idx.size >= 3 and np.all(np.diff(idx) == 1):
            out["accel_mm"] = 1000 * _mean(m.acceleration_error(pred, ref))
        out["local_cm_per_frame"] = (100 * local).round(2).tolist()
    if "joints2d" in gt and "joints2d" in motion:
        out["px2d"] = _mean(m.joint2d_error(motion["joints2d"], np.asarray(gt["joints2d"])[idx]))
    if seq.masks is not None:
        from flowmocap.body import load_body_model

        if "camera" not in motion:
            raise DataError(f"{result}'s motion records no camera, which the silhouettes need; it is not a flowmocap "
                            "result, or a damaged one: track the input again with --force.")
        camera = PinholeCamera.from_dict(json.loads(str(motion["camera"])))
        if model is None:  # the one the result was fitted with
            from flowmocap.export.motion import recorded_model

            gender = str(motion.get("gender", "neutral"))
            model = load_body_model(recorded_model(run, gender), gender=gender)
        sil = m.render_silhouettes(model, motion["poses"], motion["trans"], motion["betas"], camera)
        masks = np.stack([seq.mask(int(i)) for i in idx])
        if masks.shape[1:] != sil.shape[1:]:
            raise DataError(f"the masks of {seq.root} are {masks.shape[2]}x{masks.shape[1]} but the result's camera "
                            f"is {sil.shape[2]}x{sil.shape[1]}; score against the sequence the result was made from.")
        iou = mask_iou(sil, masks)
        out["iou"] = _mean(iou)
        out["iou_per_frame"] = iou.round(3).tolist()
    t = run.get("timings", {})
    frame_s = t.get("frame_s") or []
    out["s_per_frame"] = t.get("s_per_frame_median", float(np.median(frame_s)) if frame_s else None)
    out["init_s"] = t.get("init_s")
    out["total_s"] = t.get("total_s")
    out["peak_rss_mb"] = run.get("peak_rss_mb")
    out["status"] = run.get("status")
    return out


def detector_joints3d(track) -> np.ndarray:
    """The detector's own 3D joints of every frame in SMPL joint order.

    Args:
        track: a :class:`~flowmocap.vision.auto.PersonTrack` with ``world`` keypoints
            (MediaPipe's world landmarks, metres, hip-centred, in the detector's axes).

    Returns:
        ``(T, 24, 3)`` metres: the 12 limb joints the detector names, and SMPL's ``head``
        as the middle of the two ears; NaN for every other joint, for keypoints with
        confidence < 0.3 and for frames without the person.
    """
    from flowmocap.body.skeleton import JOINT_INDEX
    from flowmocap.vision.detect import KEYPOINT_NAMES, SMPL_KEYPOINTS

    T = len(track.found)
    out = np.full((T, 24, 3), np.nan)
    if track.world is None:
        return out
    world = np.asarray(track.world, np.float64)
    ok = (np.asarray(track.confidence) >= 0.3) & np.asarray(track.found)[:, None]
    for k, name in enumerate(SMPL_KEYPOINTS):
        out[:, JOINT_INDEX[name]] = np.where(ok[:, k, None], world[:, k], np.nan)
    ears = [KEYPOINT_NAMES.index("left_ear"), KEYPOINT_NAMES.index("right_ear")]
    both = ok[:, ears].all(1)
    out[:, JOINT_INDEX["head"]] = np.where(both[:, None], world[:, ears].mean(1), np.nan)
    return out


def score_detector3d(result: str | Path, seq) -> dict | None:
    """The detector-3D row: the detector's own 3D joints stored with a result
    (``result/detections``, e.g. for ``E_d``) scored against the sequence's ground truth
    like a fit, on the frames where the detector gives all 13 evaluation joints.

    Returns:
        dict with ``local_cm`` (per-frame similarity Procrustes, 13 joints, cm),
        ``frames`` (frames scored), ``coverage`` (their share of the result's frames),
        ``local_cm_per_frame``; the other headline metrics ``None`` (the detector gives
        no trajectory, no body, and its 2D joints are scored elsewhere); or None when the
        result has no stored 3D detections.
    """
    from flowmocap.body.skeleton import EVAL_JOINTS
    from flowmocap.io.sequence import Sequence, load_sequence
    from flowmocap.vision.auto import load_detections

    track = load_detections(result)
    if track is None or track.world is None:
        return None
    if not isinstance(seq, Sequence):
        seq = load_sequence(seq)
    if "joints3d" not in seq.gt:
        return None
    det = detector_joints3d(track)
    T = min(len(det), len(seq))
    det = det[:T]
    ref = np.asarray(seq.gt["joints3d"], np.float64)[:T]
    use = np.isfinite(det[:, list(EVAL_JOINTS)]).all(axis=(1, 2))
    out: dict = {k: None for k, _ in COLUMNS}
    out.update(frames=int(use.sum()), coverage=float(use.mean()) if T else 0.0, local_cm_per_frame=[])
    if use.any():
        local = m.local_procrustes_error(det[use], ref[use])
        out["local_cm"] = 100 * _mean(local)
        out["local_cm_per_frame"] = (100 * local).round(2).tolist()
    return out


def format_scores(scores: dict) -> str:
    """The headline metrics as aligned ``name value`` lines."""
    lines = []
    for key, label in COLUMNS + (("peak_rss_mb", "peak MB"), ("frames", "frames")):
        v = scores.get(key)
        lines.append(f"{label:<14}{'n/a' if v is None else format(v, '.3f' if key == 'iou' else '.2f')}")
    return "\n".join(lines)
