"""Time and memory of the steps after tracking on a long motion, as the pipeline runs them.

A finished result with detections (e.g. ``benchmarks/real_video.py``'s Sports2D walk) is
put back to what the tracker finished with (``benchmarks/post_steps.py``'s
``tracked_motion``) and repeated ``--repeat`` times end to end (motion, detections and
the run's events alike, frame numbers made consecutive), so the steps see a motion of that
length. Then, in a fresh process, the pipeline's own steps after tracking
(``flowmocap.pipeline._post_steps``: the lifter refit with its shape step, vote and seam
easing, the depth smoothing after it, the stance depth correction, the pose smoothing)
run with the run's own settings (``run.json`` ``config``; settings the run predates take
today's defaults), as ``flowmocap track`` would run them at the end of a video that long.
Reports the seconds of each step (the records they leave in ``run.json``), the whole
pass's seconds and the process's peak resident memory (``ru_maxrss``) before and after.
Prints a table and writes JSON.

Usage: python benchmarks/post_steps_cost.py RESULT_DIR [--repeat 7] [--out PREFIX]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import resource
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

STEPS = ("lifter_refit", "stance_depth", "pose_smoothing")


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def repeated_run(run: dict, frames: int, repeat: int) -> dict:
    """``run.json``'s info for the motion repeated ``repeat`` times: the post steps' records
    dropped and every event with a ``frame`` repeated at ``frame + k * frames``."""
    base = {k: v for k, v in run.items() if k not in STEPS}
    events = run.get("events", [])
    base["events"] = [({**e, "frame": e["frame"] + k * frames} if "frame" in e else e)
                      for k in range(repeat) for e in events]
    return base


def _pass(args) -> dict:
    result, repeat = args
    import numpy as np

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from post_steps import _body, tracked_motion

    from flowmocap.fit.config import TrackerConfig
    from flowmocap.io.results import read_result, write_motion, write_run
    from flowmocap.pipeline import _post_steps
    from flowmocap.vision.auto import load_detections

    motion, _ = read_result(result)
    run = json.loads((Path(result) / "run.json").read_text())
    track = load_detections(result)
    if track is None:
        raise SystemExit(f"{result} holds no detections: the refit needs the detector's 2D keypoints")
    cfg = TrackerConfig.from_dict(run.get("config") or {})
    body = _body(run)
    m = tracked_motion(motion, run, body, cfg)
    idx = np.asarray(m["frame_index"])
    T0 = len(idx)
    if not np.array_equal(idx, np.arange(idx[0], idx[0] + T0)):
        raise SystemExit(f"{result}: its frames are not consecutive; pick a result tracked from its first frame")
    for k, v in list(m.items()):
        v = np.asarray(v)
        if v.ndim >= 1 and v.shape[0] == T0 and k != "frame_index":
            m[k] = np.concatenate([v] * repeat)
    m["frame_index"] = np.arange(T0 * repeat) + idx[0]
    sel = np.concatenate([np.arange(len(track.found))] * repeat)[: idx[0] + T0 * repeat]
    if len(sel) < idx[0] + T0 * repeat:
        raise SystemExit(f"{result}: fewer detections than tracked frames")
    track = replace(track, keypoints=track.keypoints[sel], confidence=track.confidence[sel], found=track.found[sel],
                    mask_paths=[track.mask_paths[i] for i in sel],
                    world=None if track.world is None else track.world[sel])
    fingerprint = run.get("fingerprint")
    joints3d = fingerprint.get("joints3d", "auto") if isinstance(fingerprint, dict) else "auto"
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        write_motion(out, m)
        base = repeated_run(run, T0, repeat)
        write_run(out, base)
        before = _peak_mb()
        t0 = time.perf_counter()
        done = _post_steps(out, track, body, cfg, base, joints3d, lambda *a, **k: None)
        seconds = time.perf_counter() - t0
        after = _peak_mb()
    steps = {s: done[s].get("seconds") for s in STEPS if isinstance(done.get(s), dict)}
    return {"frames": int(T0 * repeat), "seconds": seconds, "step_seconds": steps,
            "peak_mb_before": before, "peak_mb_after": after,
            "settings": {k: getattr(cfg, k) for k in ("lifter_refit_weight", "lifter_refit_iterations",
                                                       "lifter_refit_shape_share", "lifter_refit_vote_frames",
                                                       "lifter_refit_seam_s", "stance_depth_share",
                                                       "pose_smoothing_s")}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("result", type=Path, help="a finished result folder with detections/")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--out", help="write PREFIX.json")
    a = ap.parse_args()
    if a.repeat < 1:
        ap.error("--repeat must be at least 1")
    with mp.get_context("spawn").Pool(1) as pool:
        r = pool.map(_pass, [(a.result, a.repeat)])[0]
    print(f"{'frames':>7s} {'seconds':>8s} {'ms/frame':>9s} {'peak MB before':>15s} {'peak MB after':>14s}  steps (s)")
    print(f"{r['frames']:7d} {r['seconds']:8.1f} {1000 * r['seconds'] / r['frames']:9.1f} {r['peak_mb_before']:15.0f} "
          f"{r['peak_mb_after']:14.0f}  " + ", ".join(f"{k} {v}" for k, v in r["step_seconds"].items()))
    if a.out:
        Path(f"{a.out}.json").write_text(json.dumps({"result": str(a.result), "repeat": a.repeat, **r}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
