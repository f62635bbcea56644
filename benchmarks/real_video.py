"""Real videos with no manual input: automatic masks, automatic initialisation, tracking.

    .venv/bin/python benchmarks/real_video.py [--work DIR] [--only davis|walk] [--config JSON] [--fast]
        [--data DIR] [--out JSON]

* DAVIS dance-twirl (90 frames, 854x480, hand-made masks): mean IoU of the automatic
  masks against the hand-made ones (target >= 0.85), and of the fitted body's silhouette
  (rasterised mesh) against them (target >= 0.75), over all 90 frames.
* Sports2D walk (230 frames, 1768x994, tracked at --max-size): which frames were
  tracked, how many hold the walker, re-initialisations, and the 2D agreement of the
  body's joints with the detector's.

Each clip is tracked with ``flowmocap track INPUT --out WORK/NAME`` (resumed if a run is
there). Prints a table and writes ``benchmarks/results/real_video.json``. Needs the shared
data folder (``../shared/data`` beside the repository).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from flowmocap.io.results import has_result

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "video"


def track(inp: Path, out: Path, extra: list[str]) -> float:
    cmd = [sys.executable, "-m", "flowmocap.cli", "track", str(inp), "--out", str(out), "--quiet", *extra]
    if has_result(out):
        cmd.append("--resume")
    t0 = time.perf_counter()
    print(" ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    return time.perf_counter() - t0


def body_ious(out: Path, reference) -> list[float]:
    """Silhouette IoU of the fitted body per tracked frame against ``reference(frame) -> mask``,
    at the reference masks' size (the body is drawn with the tracked camera scaled to it when
    the frames were tracked at a reduced size)."""
    from flowmocap.body import load_body_model
    from flowmocap.eval.metrics import render_silhouettes
    from flowmocap.geometry.camera import PinholeCamera
    from flowmocap.io.results import read_result
    from flowmocap.vision.masks import mask_iou

    motion, run = read_result(out)
    model = load_body_model(run["model"] if run.get("model") and Path(run["model"]).exists() else "default",
                            gender=run["gender"])
    camera = PinholeCamera.from_dict(json.loads(str(motion["camera"])))
    h, w = reference(int(motion["frame_index"][0])).shape
    if (camera.width, camera.height) != (w, h):
        sx, sy = w / camera.width, h / camera.height  # the image spans [0, W] x [0, H] (flowmocap.geometry.camera)
        camera = PinholeCamera(camera.fx * sx, camera.fy * sy, camera.cx * sx, camera.cy * sy, w, h, camera.R, camera.t)
    body = render_silhouettes(model, motion["poses"], motion["trans"], motion["betas"], camera)
    return mask_iou(body, np.stack([reference(int(f)) for f in motion["frame_index"]])).tolist()


def davis(work: Path, extra: list[str], data: Path = DATA) -> dict:
    from flowmocap.io.results import read_result
    from flowmocap.vision.auto import load_detections
    from flowmocap.vision.masks import load_mask, mask_iou

    clip = data / "davis-dance-twirl"
    out = work / "davis-dance-twirl"
    seconds = track(clip / "JPEGImages", out, extra)
    gt = [load_mask(p) for p in sorted((clip / "Annotations").glob("*.png"))]
    det = load_detections(out)
    auto = np.stack([det.mask(i) for i in range(len(gt))])
    if auto.shape[1:] != gt[0].shape:  # tracked at a reduced size: the hand-made masks scaled down alike
        import cv2

        gt_at = np.stack([cv2.resize(g.astype(np.uint8) * 255, auto.shape[:0:-1], interpolation=cv2.INTER_AREA) >= 128
                          for g in gt])
    else:
        gt_at = np.stack(gt)
    auto_iou = mask_iou(auto, gt_at)
    ious = body_ious(out, lambda f: gt[f])
    motion, run = read_result(out)
    return {
        "clip": "davis-dance-twirl", "frames": len(gt), "tracked_frames": len(motion["frame_index"]),
        "auto_mask_iou_mean": float(np.mean(auto_iou)), "auto_mask_iou_min": float(np.min(auto_iou)),
        "body_iou_mean": float(np.mean(ious)), "body_iou_min": float(np.min(ious)),
        "body_iou_per_frame": [round(v, 4) for v in ious],
        "reinitialisations": [e["frame"] for e in run["events"] if e.get("event") == "re-initialised"],
        "camera_source": run.get("camera_source"), "seconds": seconds,
        "s_per_frame_median": run["timings"].get("s_per_frame_median"),
        "targets": {"auto_mask_iou_mean": 0.85, "body_iou_mean": 0.75},
    }


def walk(work: Path, extra: list[str], max_size: int, data: Path = DATA) -> dict:
    from flowmocap.fit.reinit import joint_disagreement
    from flowmocap.io.results import read_result
    from flowmocap.vision.auto import load_detections

    out = work / "sports2d-walk"
    seconds = track(data / "sports2d-walk" / "walk.mp4", out, ["--max-size", str(max_size), *extra])
    motion, run = read_result(out)
    det = load_detections(out)
    frames = [int(f) for f in motion["frame_index"]]
    errs = []
    for k, f in enumerate(frames):
        j2d, conf = det.smpl_joints(f)
        e = joint_disagreement(motion["joints2d"][k], j2d, conf)
        if e is not None:
            errs.append(e)
    ious = body_ious(out, det.mask)
    return {
        "clip": "sports2d-walk", "frames": len(det), "tracked": [frames[0], frames[-1]],
        "tracked_frames": len(frames), "frames_with_walker": int(det.found.sum()),
        "frame_range_note": run.get("frame_range"), "ignored_people": det.info.get("ignored_people"),
        "joint_error_median_of_height": float(np.median(errs)) if errs else None,
        "body_iou_vs_auto_mask_mean": float(np.mean(ious)),
        "reinitialisations": [e["frame"] for e in run["events"] if e.get("event") == "re-initialised"],
        "gaps": run.get("gaps"), "status": run["status"], "seconds": seconds, "max_size": max_size,
        "s_per_frame_median": run["timings"].get("s_per_frame_median"),
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default=str(ROOT / "benchmarks" / "work" / "real_video"))
    p.add_argument("--only", choices=["davis", "walk"])
    p.add_argument("--config", help="tracker settings JSON passed to flowmocap track --config")
    p.add_argument("--fast", action="store_true", help="pass --fast to flowmocap track")
    p.add_argument("--max-size", type=int, default=640, help="--max-size for the 1768x994 walk (default 640)")
    p.add_argument("--data", default=str(DATA), help="folder holding davis-dance-twirl/ and sports2d-walk/")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "real_video.json"))
    args = p.parse_args()
    data = Path(args.data)
    if not data.exists():
        print(f"shared data not found at {data}; nothing to do")
        return 1
    work = Path(args.work)
    extra = (["--config", args.config] if args.config else []) + (["--fast"] if args.fast else [])
    results = []
    if args.only in (None, "davis"):
        results.append(davis(work, extra, data))
    if args.only in (None, "walk"):
        results.append(walk(work, extra, args.max_size, data))
    print(f"\n{'clip':<20}{'tracked':>10}{'mask IoU':>10}{'body IoU':>10}{'reinits':>9}{'s/frame':>9}")
    for r in results:
        print(f"{r['clip']:<20}{r['tracked_frames']:>10}"
              f"{r.get('auto_mask_iou_mean', float('nan')):>10.3f}"
              f"{r.get('body_iou_mean', r.get('body_iou_vs_auto_mask_mean', float('nan'))):>10.3f}"
              f"{len(r['reinitialisations']):>9}{r['s_per_frame_median'] or float('nan'):>9.2f}")
    res = Path(args.out)
    res.parent.mkdir(parents=True, exist_ok=True)
    res.write_text(json.dumps({"config": args.config, "results": results}, indent=2))
    print(f"wrote {res}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
