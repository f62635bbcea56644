"""The augmented detector's four runs as four 2D hypotheses (issue 18, a check)

:class:`~flowmocap.vision.detect.MediaPipePoseDetector` with ``augment`` runs MediaPipe
four times on every frame (the image, its mirror image, the image with a black border,
and in single-image mode) and uses only the first run's keypoints; the others serve the
mask. On the real3d recording the detector's 2D is what limits every 3D source
(docs/experiments.md, "Where the real3d error comes from"). Would the other three runs'
keypoints -- a test-time augmentation that costs nothing more, or a second hypothesis
where the first one turns the body about -- be better 2D?

For each view of the recording this runs the default detection (the search pass, then
each long track re-detected with the others blanked, :func:`~flowmocap.vision.auto.follow_person`)
with a detector that also keeps the three other runs' keypoints (the mirror run's
mirrored back, left and right exchanged), matches each track to the reference person it
lies nearest, and scores per keypoint (the 12 body joints) against the real3d reference
triangulated without the view and projected into it (pixels of the 640-high frames):
each run alone, the mean and the coordinate-wise median of the runs, the mean of the
image and mirror runs, and the mean of the runs that agree with the median.

``--max-side N`` runs the detector on the frames scaled to a long side of N pixels instead
of 640 (the tracker's size; 1920 is the recording's own) and still reports pixels of the
640-high frames: does the detector place the keypoints better on sharper frames?

Usage: python benchmarks/detector_runs_2d.py REAL3D_DIR [--views cam01,cam02] [--out PREFIX] [--model heavy]
       [--max-side 640]
       (REAL3D_DIR: a ``flowmocap bench --suite real3d`` folder, for its reference; about
       3 minutes a view on one core)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from flowmocap.vision.detect import KEYPOINT_NAMES, MEDIAPIPE_LANDMARKS, SMPL_KEYPOINTS, MediaPipePoseDetector

RUNS = ("main", "mirror", "border", "single")
COMBINED = ("mean", "median", "main_and_mirror", "mean_of_agreeing")
#: the index of each keypoint's left/right counterpart
SWAP = [KEYPOINT_NAMES.index(n.replace("left", "@").replace("right", "left").replace("@", "right"))
        for n in KEYPOINT_NAMES]
K = len(SMPL_KEYPOINTS)


def landmarks(result, width: int, height: int, dx: float = 0.0, dy: float = 0.0, mirrored: bool = False):
    """``(K, 2)`` pixels of a MediaPipe result in the original image, or None."""
    if result.pose_landmarks is None:
        return None
    lm = result.pose_landmarks.landmark
    kp = np.array([[lm[MEDIAPIPE_LANDMARKS[n]].x * width - dx, lm[MEDIAPIPE_LANDMARKS[n]].y * height - dy]
                   for n in KEYPOINT_NAMES])
    if mirrored:
        kp[:, 0] = width - kp[:, 0]
        kp = kp[SWAP]
    return kp


class RecordingDetector(MediaPipePoseDetector):
    """The augmented detector, also keeping the other runs' keypoints of each detection
    in :attr:`log` as ``(main keypoints, {run: keypoints or None})``."""

    def __init__(self, model: str = "full"):
        super().__init__(augment=True, model=model)
        self.log: list = []
        self._last: dict = {}

    def _start_augmented(self, img):
        import cv2

        b, runs, (H, W) = 64, self._runs, img.shape[:2]
        last = self._last = {}

        def mirror():
            r = runs["mirror"].process(np.ascontiguousarray(img[:, ::-1]))
            last["mirror"] = landmarks(r, W, H, mirrored=True)
            return None if r.segmentation_mask is None else np.asarray(r.segmentation_mask)[:, ::-1]

        def border():
            r = runs["border"].process(cv2.copyMakeBorder(img, b, b, b, b, cv2.BORDER_CONSTANT, value=0))
            last["border"] = landmarks(r, W + 2 * b, H + 2 * b, b, b)
            return None if r.segmentation_mask is None else np.asarray(r.segmentation_mask)[b:-b, b:-b]

        def single():
            r = runs["single"].process(img)
            last["single"] = landmarks(r, W, H)
            return None if r.segmentation_mask is None else np.asarray(r.segmentation_mask)

        return [self._pool.submit(f) for f in (mirror, border, single)]

    def detect(self, image_rgb):
        d = super().detect(image_rgb)
        if d is not None:
            self.log.append((d.keypoints.copy(), dict(self._last)))
        return d


def hypotheses(main: np.ndarray, others: dict) -> dict:
    """``{name: (K, 2) or None}``: each run's body keypoints and their combinations."""
    h = {"main": main[:K]}
    for r in RUNS[1:]:
        h[r] = None if others.get(r) is None else others[r][:K]
    given = [h[r] for r in RUNS if h[r] is not None]
    med = np.median(given, axis=0)
    h["mean"], h["median"] = np.mean(given, axis=0), med
    h["main_and_mirror"] = np.mean([x for x in (h["main"], h["mirror"]) if x is not None], axis=0)
    size = float(np.ptp(med, axis=0).max())
    agree = [x for x in given if np.median(np.linalg.norm(x - med, axis=1)) < 0.1 * size]
    h["mean_of_agreeing"] = np.mean(agree or given, axis=0)
    return h


def score_view(view: str, reference: dict, min_frames: int = 10, model: str = "full", max_side: int = 640) -> dict:
    """``{person: {hypothesis: per-keypoint errors (N, K) px}}`` of one view, in pixels of the
    frames scaled to a long side of 640, the detector run on frames of ``max_side``."""
    from flowmocap.eval import real3d as R
    from flowmocap.io.video import load_video
    from flowmocap.vision import auto

    seq = load_video(Path(R.DATA) / "videos" / f"{view}.mp4", max_side=max_side)
    W = seq.size[0]
    to640 = 640.0 / max(seq.size)
    cands = auto.find_people(seq, MediaPipePoseDetector(augment=True, model=model),
                             MediaPipePoseDetector(augment=False, model=model), progress=False)
    tracks = auto.split_tracks(cands)
    cam, offset = reference["cameras"][view], reference["offsets"][view]
    scale = W / cam.width
    out: dict = {}
    for k, t in enumerate(tracks):
        if len(t) < min_frames:
            continue
        det = RecordingDetector(model)
        found = auto.follow_person(seq, det, cands, tracks, k, progress=False)
        det.close()
        best = None
        for person, ref in reference["people"].items():
            wo = ref["without"][view]
            times = [int(x) for x in wo["times"]]
            errs: dict = {h: [] for h in RUNS + COMBINED}
            for f, c in enumerate(found):
                if c is None or f + offset not in times:
                    continue
                rec = [o for kp, o in det.log if np.array_equal(kp, np.asarray(c.keypoints))]
                if not rec:  # the search's own candidate, not a detection of this pass
                    continue
                uv = np.asarray(cam.project(np.asarray(wo["points"][times.index(f + offset)])), np.float64)[:K] * scale
                for h, p in hypotheses(np.asarray(c.keypoints), rec[-1]).items():
                    errs[h].append(np.full(K, np.nan) if p is None else np.linalg.norm(p - uv, axis=1) * to640)
            if not errs["main"]:
                continue
            e = {h: np.asarray(v) for h, v in errs.items()}
            m = float(np.nanmedian(e["main"]))
            if best is None or m < best[0]:
                best = (m, person, e)
        if best is not None and best[1] not in out:
            out[best[1]] = best[2]
    return out


def summary(e: np.ndarray) -> dict:
    v = e[np.isfinite(e)]
    return {"p50": float(np.median(v)), "p90": float(np.percentile(v, 90)), "mean": float(v.mean())} if v.size else {}


def main() -> int:
    from flowmocap.eval import real3d as R

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench", type=Path)
    ap.add_argument("--views", default=",".join(R.VIEWS))
    ap.add_argument("--out")
    ap.add_argument("--model", default="full", choices=["full", "heavy"],
                    help="the landmark model of the main run (and the search's); the other three runs stay full")
    ap.add_argument("--max-side", type=int, default=640,
                    help="the long side (pixels) of the frames the detector sees; errors stay in 640-frame pixels")
    a = ap.parse_args()
    reference = R.build_reference(a.bench, progress=False, log=None)
    rows, pooled = {}, {h: [] for h in RUNS + COMBINED}
    for view in a.views.split(","):
        for person, e in score_view(view, reference, model=a.model, max_side=a.max_side).items():
            rows[f"{person}-{view}"] = {"frames": int(len(e["main"])), **{h: summary(v) for h, v in e.items()}}
            for h, v in e.items():
                pooled[h].append(v)
    allrow = {h: summary(np.concatenate(v)) for h, v in pooled.items() if v}
    cols = RUNS + COMBINED
    lines = ["# The augmented detector's four runs as 2D hypotheses (real3d)", "",
             f"`python benchmarks/detector_runs_2d.py {a.bench} --model {a.model} --max-side {a.max_side}`: per body keypoint, "
             "pixels of the frames scaled to a long side of 640 "
             "against the reference triangulated without the view; median / 90th percentile / mean.", "",
             "| person-view | frames | " + " | ".join(cols) + " |", "|---|---:|" + "---|" * len(cols)]
    fmt = lambda s: f"{s['p50']:.1f} / {s['p90']:.1f} / {s['mean']:.1f}" if s else "--"  # noqa: E731
    for name, r in sorted(rows.items()):
        lines.append(f"| {name} | {r['frames']} | " + " | ".join(fmt(r[h]) for h in cols) + " |")
    lines.append("| **all** | " + str(sum(r["frames"] for r in rows.values())) + " | "
                 + " | ".join(fmt(allrow.get(h, {})) for h in cols) + " |")
    md = "\n".join(lines) + "\n"
    print(md)
    if a.out:
        Path(a.out + ".md").write_text(md)
        Path(a.out + ".json").write_text(json.dumps({"bench": str(a.bench), "model": a.model, "max_side": a.max_side,
                                                     "rows": rows,
                                                     "all": allrow}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
