"""Where a tracked frame's wall time goes in the pipeline (issue 19): per frame, the wait for
the look-ahead thread's observations, the tracker's step (wall and the optimiser thread's
CPU time), the commit of the frame, and how long the look-ahead took to observe it.

Runs :func:`flowmocap.pipeline.track` on the first ``--frames`` frames of a sequence folder
(e.g. the CMU 35_01 protocol's, from ``benchmarks/track.py --work DIR``: ``DIR/sequence``),
from the protocol's noisy start, reusing the detections stored beside it when there are
some (``--detections``). The CPU time of the optimiser's thread (``time.thread_time``)
is less sensitive to a shared machine's load than the wall clock, so comparing two
checkouts (``PYTHONPATH=CHECKOUT/src``, runs alternating) is best done on it. Prints
medians and means over the frames after the first ``--skip`` and writes JSON.

Usage: python benchmarks/frame_time.py SEQUENCE [--frames 50] [--skip 5] [--detections DIR]
       [--work DIR] [--out JSON]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", help="a sequence folder with gt.npz")
    ap.add_argument("--frames", type=int, default=50, help="frames 0..N-1 are tracked")
    ap.add_argument("--skip", type=int, default=5, help="frames left out of the statistics (warm-up)")
    ap.add_argument("--detections", help="a result folder's detections/ to reuse (skips MediaPipe)")
    ap.add_argument("--work", help="result folder (default: a temporary one, removed)")
    ap.add_argument("--out", help="JSON to write")
    args = ap.parse_args()

    import flowmocap
    import flowmocap.fit.tracker as tracker_module
    import flowmocap.pipeline as pipeline
    from flowmocap.eval.protocol import noisy_init
    from flowmocap.io.sequence import load_sequence

    seq_dir = Path(args.sequence)
    seq = load_sequence(seq_dir)
    out = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="flowmocap_frame_time_"))
    shutil.rmtree(out, ignore_errors=True)
    if args.detections:
        shutil.copytree(args.detections, out / "detections")
    rec: dict[str, list[float]] = {"wait_s": [], "step_s": [], "step_cpu_s": [], "commit_s": [], "observe_s": []}
    track_frames = tracker_module.track_frames

    def timed_track_frames(tracker, frames, observe, on_frame, progress=True, done=0):
        def timed_observe(i):
            t = time.perf_counter()
            r = observe(i)
            rec["observe_s"].append(time.perf_counter() - t)
            return r

        step = tracker.step

        def timed_step(*a, **k):
            t, c = time.perf_counter(), time.thread_time()
            r = step(*a, **k)
            rec["step_s"].append(time.perf_counter() - t)
            rec["step_cpu_s"].append(time.thread_time() - c)
            return r

        tracker.step = timed_step

        def timed_on_frame(res):
            rec["wait_s"].append(max(res.seconds - rec["step_s"][-1], 0.0))
            t = time.perf_counter()
            on_frame(res)
            rec["commit_s"].append(time.perf_counter() - t)

        return track_frames(tracker, frames, timed_observe, timed_on_frame, progress=False, done=done)

    pipeline.track_frames = timed_track_frames
    t0 = time.perf_counter()
    pipeline.track(seq_dir, out, init=noisy_init(seq.gt, frame=0, seed=0), frames=f"0:{args.frames}",
                   progress=False, log=None)
    wall = time.perf_counter() - t0
    if not args.work:
        shutil.rmtree(out, ignore_errors=True)
    stats = {k: {"median": statistics.median(v[args.skip:]), "mean": statistics.mean(v[args.skip:])}
             for k, v in rec.items() if len(v) > args.skip}
    print(f"{args.frames} frames of {seq_dir} with flowmocap from {Path(flowmocap.__file__).parent}: {wall:.1f} s in all")
    print(f"{'per frame':<12}{'median s':>10}{'mean s':>10}")
    for k, s in stats.items():
        print(f"{k:<12}{s['median']:>10.3f}{s['mean']:>10.3f}")
    if args.out:
        Path(args.out).write_text(json.dumps({"sequence": str(seq_dir), "frames": args.frames, "skip": args.skip,
                                              "flowmocap": str(Path(flowmocap.__file__).parent), "wall_s": wall,
                                              "stats": stats, "per_frame": rec}, indent=1))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
