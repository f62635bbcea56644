"""Is MediaPipe's image-landmark depth a better 3D source than its world landmarks?

MediaPipe Pose gives two 3D outputs per frame. The tracker uses the *world landmarks*
(metres, hip-centred). The *image landmarks* carry a depth too: ``z`` relative to the
middle of the hips, "in roughly the same scale as x" (the image width). If those depths
were better, or erred differently, they would be a second 3D source for free. This script
scores both on real3d against the reference triangulated without the run's view:

1. for each scored frame of each person-view of a ``flowmocap bench --suite real3d``
   folder, the frame of the full-resolution video cropped around the run's own detection
   (its confident keypoints' box, grown by ``--margin`` and ``--pad`` px);
2. MediaPipe Pose on the crop (``static_image_mode``, model complexity 1, the model the
   project's detector runs); its image landmarks as 3D points ``(x w, y h, z w)`` in crop
   pixels (:func:`image_landmarks_3d`; ``--z-scale`` multiplies ``z``) and its world landmarks;
3. per-frame PA-MPJPE (:func:`flowmocap.eval.real3d.pa_mpjpe`, which takes out the scale)
   of: the run's stored world landmarks (the benchmark's detector-3D row), the crop's world
   landmarks, the crop's image landmarks, their mean (the image landmarks first aligned to
   the world ones by one similarity per frame) and flowmocap's fit, on the same frames.

Usage: python benchmarks/mediapipe_image_depth.py BENCH_DIR [--z-scale 1] [--out PREFIX]
Writes PREFIX.json and PREFIX.md (default
``benchmarks/results/mediapipe_image_depth``). About 3 minutes for the 8 person-views.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

ROWS = ("stored_world", "crop_world", "crop_image", "mean_of_both", "flowmocap")


def crop_box(keypoints: np.ndarray, confidence: np.ndarray, size: tuple[int, int], margin: float = 1.4,
             pad: float = 40.0, min_confidence: float = 0.3) -> tuple[int, int, int, int] | None:
    """The square around a detection: ``(x0, y0, x1, y1)`` integer pixels inside an image
    of ``size = (width, height)``, centred on the box of the keypoints ``(K, 2)`` px with
    ``confidence (K,)`` at least ``min_confidence``
    (:func:`flowmocap.vision.person.person_box`), side ``margin`` times the box's longer
    side plus ``pad`` px; None with fewer than 2 such keypoints."""
    from flowmocap.vision.person import person_box

    finite = np.isfinite(keypoints).all(-1)
    box = person_box(np.where(finite[:, None], keypoints, 0.0), np.where(finite, confidence, 0.0),
                     min_confidence=min_confidence)
    if box is None:
        return None
    x0, y0, x1, y1 = box
    cx, cy, half = (x0 + x1) / 2, (y0 + y1) / 2, (max(x1 - x0, y1 - y0) * margin + pad) / 2
    w, h = size
    return (int(max(cx - half, 0)), int(max(cy - half, 0)), int(min(cx + half, w)), int(min(cy + half, h)))


def image_landmarks_3d(landmarks: np.ndarray, width: int, height: int, z_scale: float = 1.0) -> np.ndarray:
    """``(K, 3)`` MediaPipe image landmarks (``x``, ``y`` as fractions of the image's
    width and height, ``z`` a depth on the scale of ``x``) as 3D points in pixels:
    ``(x width, y height, z_scale z width)`` (x right, y down, z away from the camera)."""
    lm = np.asarray(landmarks, np.float64)
    return lm * np.array([width, height, z_scale * width], np.float64)


def score_views(bench: Path, z_scale: float = 1.0, log=print) -> dict:
    """Per person-view of ``bench``: the per-frame PA-MPJPE (mm) of each row of
    :data:`ROWS` on the frames MediaPipe found a person in the crop, and how many."""
    import imageio.v3 as iio
    import mediapipe as mp

    from flowmocap.eval.real3d import DATA, build_reference, eval_points, pa_mpjpe, scored_runs
    from flowmocap.geometry.procrustes import similarity_procrustes
    from flowmocap.vision.detect import KEYPOINT_NAMES, MEDIAPIPE_LANDMARKS

    reference = build_reference(bench, progress=False, log=None)
    pose = mp.solutions.pose.Pose(static_image_mode=True, model_complexity=1, enable_segmentation=False)
    index = [MEDIAPIPE_LANDMARKS[n] for n in KEYPOINT_NAMES]
    out = {}
    for _res, person, view, d in scored_runs(bench, reference):
        det = d["detections"]
        frames = iio.imread(DATA / "videos" / f"{view}.mp4", plugin="pyav")
        height, width = frames.shape[1:3]
        scale = width / det.info["size"][0]
        kept, image3d, world3d = [], [], []
        for k, f in enumerate(d["used"]):
            box = crop_box(det.keypoints[f] * scale, det.confidence[f], (width, height))
            if box is None:
                continue
            crop = np.ascontiguousarray(frames[f][box[1]:box[3], box[0]:box[2]])
            r = pose.process(crop)
            if r.pose_landmarks is None or r.pose_world_landmarks is None:
                continue
            lm, wl = r.pose_landmarks.landmark, r.pose_world_landmarks.landmark
            image3d.append(eval_points(image_landmarks_3d(
                np.array([[lm[i].x, lm[i].y, lm[i].z] for i in index]), crop.shape[1], crop.shape[0], z_scale)))
            world3d.append(eval_points(np.array([[wl[i].x, wl[i].y, wl[i].z] for i in index])))
            kept.append(k)
        if not kept:
            continue
        kept = np.array(kept)
        ref, valid = d["ref"][kept], d["valid"][kept]
        image3d, world3d = np.array(image3d), np.array(world3d)
        aligned = similarity_procrustes(image3d, world3d, weights=np.ones(image3d.shape[:2]))[0]
        preds = {"stored_world": d["detector"][kept], "crop_world": world3d, "crop_image": image3d,
                 "mean_of_both": 0.5 * (aligned + world3d), "flowmocap": d["ours"][kept]}
        row = {name: pa_mpjpe(p, ref, valid)[0] for name, p in preds.items()}
        row.update(frames=int(len(kept)), frames_scored=len(d["used"]))
        out[f"{person}-{view}"] = row
        log(f"{person}-{view}: " + ", ".join(f"{n} {row[n]:.1f}" for n in ROWS) + f" mm ({len(kept)} frames)")
    return out


def table(views: dict) -> str:
    lines = ["| person-view | frames | " + " | ".join(f"{n} mm" for n in ROWS) + " |",
             "|---|---:|" + "---:|" * len(ROWS)]
    for name, r in views.items():
        lines.append(f"| {name} | {r['frames']} / {r['frames_scored']} | "
                     + " | ".join(f"{r[n]:.1f}" for n in ROWS) + " |")
    lines.append("| **mean** | | " + " | ".join(f"{np.mean([r[n] for r in views.values()]):.1f}" for n in ROWS)
                 + " |")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bench", type=Path, help="a `flowmocap bench --suite real3d` folder")
    ap.add_argument("--z-scale", type=float, default=1.0, help="multiplies the image landmarks' z (default 1)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "mediapipe_image_depth"))
    args = ap.parse_args(argv)
    views = score_views(args.bench, args.z_scale)
    md = ("# MediaPipe's image-landmark depth against its world landmarks on real3d\n\n"
          f"Runs: `{args.bench}`. Per-frame PA-MPJPE on the 13 joints against the reference without the "
          "run's view, on the frames MediaPipe found a person in the crop (frames / scored). stored_world: "
          "the run's own detections (the detector-3D row); crop_*: MediaPipe on a crop of the full-resolution "
          "frame around the run's detection, static image mode; crop_image: image landmarks (x w, y h, z w); "
          f"mean_of_both: their mean after one similarity per frame. z scale: {args.z_scale}.\n\n" + table(views) + "\n")
    Path(args.out + ".md").write_text(md)
    Path(args.out + ".json").write_text(json.dumps({"bench": str(args.bench), "z_scale": args.z_scale,
                                                    "views": views}, indent=1))
    print(md)


if __name__ == "__main__":
    main()
