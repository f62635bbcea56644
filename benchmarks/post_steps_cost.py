"""Time and memory of the steps after tracking on a long motion: the lifter refit
(:func:`flowmocap.fit.lift_refit.lifter_refit_motion`) and the pose smoothing
(:func:`flowmocap.fit.smooth.pose_smoothed_motion`).

A finished result with detections (e.g. ``benchmarks/real_video.py``'s Sports2D walk) is
repeated ``--repeat`` times end to end (motion and detections alike, frame numbers made
consecutive), so the steps see a motion of that length; each step runs in a fresh process
and reports its seconds and the process's peak resident memory (``ru_maxrss``) before and
after. Prints a table and writes JSON.

Usage: python benchmarks/post_steps_cost.py RESULT_DIR [--repeat 7] [--out PREFIX]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import resource
import time
from dataclasses import replace
from pathlib import Path


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _step(args) -> dict:
    result, repeat, step = args
    import numpy as np

    from flowmocap.body import load_body_model
    from flowmocap.io.results import read_result
    from flowmocap.vision.auto import load_detections

    motion, _ = read_result(result)
    track = load_detections(result)
    if track is None:
        raise SystemExit(f"{result} holds no detections: the refit needs the detector's 2D keypoints")
    body = load_body_model("default", gender=str(np.asarray(motion.get("gender", "neutral"))))
    idx = np.asarray(motion["frame_index"])
    m = {k: np.asarray(v) for k, v in motion.items()}
    T0 = len(idx)
    for k, v in list(m.items()):
        if v.ndim >= 1 and v.shape[0] == T0 and k != "frame_index":
            m[k] = np.concatenate([v] * repeat)
    m["frame_index"] = np.arange(T0 * repeat)
    sel = np.concatenate([idx] * repeat)
    track = replace(track, keypoints=track.keypoints[sel], confidence=track.confidence[sel], found=track.found[sel],
                    mask_paths=[track.mask_paths[i] for i in sel],
                    world=None if track.world is None else track.world[sel])
    before = _peak_mb()
    t0 = time.perf_counter()
    if step == "refit":
        from flowmocap.fit.lift_refit import lifter_refit_motion

        lifter_refit_motion(m, track, body, weight=0.5, pixel_sigma=6.0)
    else:
        from flowmocap.fit.smooth import pose_smoothed_motion

        pose_smoothed_motion(m, body, 0.3)
    return {"step": step, "frames": int(T0 * repeat), "seconds": time.perf_counter() - t0,
            "peak_mb_before": before, "peak_mb_after": _peak_mb()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("result", type=Path, help="a finished result folder with detections/")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--out", help="write PREFIX.json")
    a = ap.parse_args()
    if a.repeat < 1:
        ap.error("--repeat must be at least 1")
    ctx = mp.get_context("spawn")
    rows = []
    for step in ("refit", "smoothing"):
        with ctx.Pool(1) as pool:
            rows.append(pool.map(_step, [(a.result, a.repeat, step)])[0])
    print(f"{'step':10s} {'frames':>7s} {'seconds':>8s} {'ms/frame':>9s} {'peak MB before':>15s} {'peak MB after':>14s}")
    for r in rows:
        print(f"{r['step']:10s} {r['frames']:7d} {r['seconds']:8.1f} {1000 * r['seconds'] / r['frames']:9.1f} "
              f"{r['peak_mb_before']:15.0f} {r['peak_mb_after']:14.0f}")
    if a.out:
        Path(f"{a.out}.json").write_text(json.dumps({"result": str(a.result), "repeat": a.repeat, "rows": rows},
                                                    indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
