"""The two MediaPipe landmark models a frame: time and agreement.

Runs :class:`~flowmocap.vision.detect.MediaPipePoseDetector` with the "full" and the
"heavy" landmark model (:data:`~flowmocap.vision.detect.MODELS`) over the same frames of a
video, in this process, one model after the other per frame so that the machine's load
falls on both alike. Reports the median seconds a frame of each (the detector alone, with
and without the mask augmentation of the default detection), their ratio, and how far
apart the two models put the 12 body keypoints (median px). The time the tracker spends
on a frame (about 1 s on real clips) is in ``benchmarks/real_video.py``; this isolates
the detector's share.

Usage: python benchmarks/detector_models.py [VIDEO] [--frames 60] [--max-size 640] [--out PREFIX]
       (default VIDEO: the Sports2D walk in ../shared/data; about 2 minutes)
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
WALK = ROOT.parent / "shared" / "data" / "video" / "sports2d-walk" / "walk.mp4"


def time_models(frames: list, augment: bool) -> dict:
    """``{model: {"s": [seconds per frame], "keypoints": [(K, 2) or None]}}`` over ``frames``."""
    from flowmocap.vision.detect import MODELS, MediaPipePoseDetector

    dets = {m: MediaPipePoseDetector(augment=augment, model=m) for m in MODELS}
    out = {m: {"s": [], "keypoints": []} for m in MODELS}
    try:
        for img in frames:
            for m, d in dets.items():
                t0 = time.perf_counter()
                r = d.detect(img)
                out[m]["s"].append(time.perf_counter() - t0)
                out[m]["keypoints"].append(None if r is None else r.keypoints[:12].copy())
    finally:
        for d in dets.values():
            d.close()
    return out


def main() -> int:
    from flowmocap.io.video import load_video

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("video", nargs="?", type=Path, default=WALK)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--max-size", type=int, default=640)
    ap.add_argument("--out")
    a = ap.parse_args()
    if not a.video.exists():
        raise SystemExit(f"{a.video} not found (the shared data's Sports2D walk, or give a video).")
    seq = load_video(a.video, max_side=a.max_size)
    n = min(a.frames, len(seq))
    frames = [seq.frame(i) for i in range(n)]
    rows = {}
    for augment in (False, True):
        got = time_models(frames, augment)
        med = {m: float(np.median(v["s"][1:])) for m, v in got.items()}  # the first frame builds the graphs
        both = [(f, h) for f, h in zip(got["full"]["keypoints"], got["heavy"]["keypoints"])
                if f is not None and h is not None]
        apart = float(np.median([np.linalg.norm(f - h, axis=1) for f, h in both])) if both else float("nan")
        rows["augmented" if augment else "plain"] = {"full_s": med["full"], "heavy_s": med["heavy"],
                                                     "ratio": med["heavy"] / med["full"], "frames": n,
                                                     "both_found": len(both), "keypoints_apart_px": apart}
    lines = ["# MediaPipe's full and heavy landmark models a frame", "",
             f"`python benchmarks/detector_models.py {a.video.name} --frames {n}`: median seconds a frame "
             f"({seq.size[0]}x{seq.size[1]}, one process), the models alternating frame by frame.", "",
             "| detector | full s | heavy s | heavy / full | keypoints apart (median px) |", "|---|---:|---:|---:|---:|"]
    for name, r in rows.items():
        lines.append(f"| {name} | {r['full_s']:.3f} | {r['heavy_s']:.3f} | {r['ratio']:.2f} | "
                     f"{r['keypoints_apart_px']:.1f} |")
    md = "\n".join(lines) + "\n"
    print(md)
    if a.out:
        Path(a.out + ".md").write_text(md)
        Path(a.out + ".json").write_text(json.dumps({"video": str(a.video), "size": list(seq.size), "rows": rows},
                                                    indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
