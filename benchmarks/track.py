"""Tracker accuracy and speed on the issue-5 protocol.

CMU 35_01 (../shared/data) retargeted onto a random (non-mean) body, rendered at 60 fps,
130 frames, 640x480 by `flowmocap synth`; the tracker starts from the mean shape, the
ground-truth 2D joints of frame 0 with 3 px noise and a rough pose with 15 degrees of noise
on the main joints. Prints the paper's local / global Procrustes errors on 13 joints and
the median seconds per frame (observed flow included) and the detector's time for the 3D
joints of E_d (run once over the clip before tracking), and writes JSON.

Usage: python benchmarks/track.py [--num-frames 130] [--size 640x480] [--fps 60] [--motion PATH]
       [--out benchmarks/results/track.json] [--work DIR] [--config cfg.json]
       [--gt-init] [--true-flow] [--track-frames A:B]

Ablations that separate the tracker's own error from its inputs': ``--gt-init`` starts
from the true poses of the first two frames (no initialisation), ``--true-flow`` gives the
tracker the renderer's exact flow instead of the observed (OpenCV) one.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from flowmocap.io.results import has_result

ROOT = Path(__file__).resolve().parents[1]
CMU = ROOT.parent / "shared" / "data" / "mocap" / "cmu" / "35_01.amc"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--motion", default=str(CMU))
    ap.add_argument("--num-frames", type=int, default=130)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--fps", type=float, default=60.0)
    ap.add_argument("--azimuth", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--config", default=None)
    ap.add_argument("--work", default=None, help="folder for the sequence and result (default: temporary)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "track.json"))
    ap.add_argument("--gt-init", action="store_true", help="start from the true first two frames")
    ap.add_argument("--true-flow", action="store_true", help="track on the renderer's exact flow")
    ap.add_argument("--track-frames", default=None, help="A:B, the frames to track (default all)")
    args = ap.parse_args()
    if args.motion == str(CMU) and not CMU.exists():
        print(f"skipped: {CMU} not found (../shared/data is absent)")
        return 0

    from flowmocap.eval.protocol import evaluate, noisy_init
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.fit.tracker import KnownStart
    from flowmocap.io.sequence import load_sequence
    from flowmocap.pipeline import track
    from flowmocap.synth import synthesize
    from flowmocap.vision import FlowCache
    from flowmocap.vision.auto import detect_joints3d

    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="flowmocap_track_"))
    seq_dir, res_dir = work / "sequence", work / "result"
    if not (seq_dir / "gt.npz").exists() or (args.true_flow and not (seq_dir / "flow").is_dir()):
        synthesize(args.motion, seq_dir, fps=args.fps, frames=args.num_frames, size=args.size, betas="random",
                   seed=args.seed, azimuth=args.azimuth, flow=args.true_flow)
    seq = load_sequence(seq_dir)
    gt = seq.gt
    start = 0 if args.track_frames is None else int(args.track_frames.split(":")[0] or 0)
    if args.gt_init:
        init = KnownStart(poses=gt["poses"][start:start + 2], trans=gt["trans"][start:start + 2], betas=gt["betas"])
    else:
        init = noisy_init(gt, frame=start, seed=args.seed)
    cfg = TrackerConfig.load(args.config)
    if args.true_flow:  # the tracker reads its observed flow from this cache
        cache = FlowCache(res_dir / "flow_cache", method=cfg.flow_method)
        for f in sorted((seq_dir / "flow").glob("*.npz")):
            if int(f.stem) not in cache:
                with np.load(f) as z:
                    cache.put(int(f.stem), z["flow"])
    t0 = time.perf_counter()
    joints3d, detect_note = None, "E_d off"
    if cfg.uses_detector3d:  # timed here; track() below finds the stored detections
        joints3d, detect_note = detect_joints3d(seq, res_dir, seq.camera, progress=False)
    detect_s = time.perf_counter() - t0
    result = track(seq_dir, res_dir, init=init, config=args.config, frames=args.track_frames,
                   resume=has_result(res_dir), progress=True, log=None)
    wall = time.perf_counter() - t0
    motion, run = result.motion, result.run
    scores = evaluate(motion, seq.gt)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout.strip()
    result = {
        "benchmark": "track", "commit": commit, "motion": Path(args.motion).name, "frames": args.num_frames,
        "size": args.size, "fps": args.fps, "azimuth": args.azimuth, "seed": args.seed,
        "gt_init": args.gt_init, "true_flow": args.true_flow, "track_frames": args.track_frames,
        "config": cfg.to_dict(), "local_cm": scores["local_cm"], "global_cm": scores["global_cm"],
        "mpjpe_cm": scores["mpjpe_cm"], "s_per_frame_median": run["timings"].get("s_per_frame_median"),
        "init_s": run["timings"].get("init_s"), "detect_s": detect_s, "joints3d": detect_note, "wall_s": wall,
        "events": run["events"],
        "local_cm_per_frame": scores["local_cm_per_frame"], "joints": scores.get("joints"),
        "targets": {"local_cm": 5.5, "global_cm": 7.6, "s_per_frame": 1.0},
    }
    print(f"{'metric':<28}{'ours':>10}{'target':>10}")
    print(f"{'local (per-frame PA) cm':<28}{scores['local_cm']:>10.2f}{5.5:>10.1f}")
    print(f"{'global (per-sequence PA) cm':<28}{scores['global_cm']:>10.2f}{7.6:>10.1f}")
    print(f"{'MPJPE (root-relative) cm':<28}{scores['mpjpe_cm']:>10.2f}{'':>10}")
    print(f"{'s per frame (median)':<28}{result['s_per_frame_median']:>10.2f}{1.0:>10.1f}")
    print(f"{'3D joint detection, s/frame':<28}{detect_s / max(len(seq), 1):>10.2f}{'':>10}  ({detect_note})")
    print("\nroot-relative error per joint, cm: across the view / along it (depth) / depth bias (< 0: nearer)")
    for name, e in (scores.get("joints") or {}).items():
        print(f"  {name:<16}{e['plane_cm']:>8.1f}{e['depth_cm']:>8.1f}{e['depth_bias_cm']:>8.1f}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out} (work folder {work})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
