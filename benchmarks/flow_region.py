"""The observed flow around the person against the whole frame's (``TrackerConfig.flow_region``):
DIS's time per frame and, where the true flow is known, its end-point error on the person.

For each clip, frames ``--frames`` (every ``--step``-th): the region is
:func:`flowmocap.vision.flow_region` of the frame's and the previous frame's masks (as the
tracker makes it); the flow is computed over the whole frame and over the region only
(OpenCV on one thread, each timed once, alternating). Reported per clip: median
milliseconds of each and their ratio; the region's share of the frame; with a true flow
(a ``flowmocap synth`` sequence made with ``--flow``) the mean end-point error on the
person's pixels of each; without one, how far the two flows lie apart there (median and
95th percentile, pixels).

Clips are sequence folders (frames + masks) or ``INPUT:RESULT`` (a video, read at
``--max-size``, or a frame folder, and a result folder whose ``detections/`` hold its masks).

Usage: python benchmarks/flow_region.py CLIP [CLIP ...] [--frames 1:41] [--step 1]
       [--max-size 640] [--out benchmarks/results/flow_region.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np


def _clip(spec: str, max_size: int):
    from flowmocap.io.sequence import load_sequence
    from flowmocap.io.video import load_video
    from flowmocap.vision.auto import load_detections

    if ":" in spec:
        source, det = spec.split(":", 1)
        track = load_detections(Path(det).parent if Path(det).name == "detections" else det)
        if track is None:
            raise SystemExit(f"no detections in {det}")
        seq = load_sequence(source) if Path(source).is_dir() else load_video(source, max_side=max_size)
        return seq, track.mask, None
    seq = load_sequence(spec)
    flow_dir = Path(spec) / "flow"
    truth = (lambda i: np.load(flow_dir / f"{i:06d}.npz")["flow"]) if flow_dir.is_dir() else None
    return seq, seq.mask, truth


def measure(spec: str, frames: range, max_size: int) -> dict:
    from flowmocap.vision import flow_region, observed_flow

    seq, mask, truth = _clip(spec, max_size)
    method = "dis-fine"
    rows = []
    for i in frames:
        if i < 1 or i >= len(seq):
            continue
        m, mp = mask(i), mask(i - 1)
        if m is None or not m.any():
            continue
        region = flow_region([m, mp])
        r0, r1, c0, c1 = region
        cur, prev = seq.frame(i), seq.frame(i - 1)
        t = time.perf_counter()
        whole = observed_flow(cur, prev, method)
        t_whole = time.perf_counter() - t
        t = time.perf_counter()
        part = np.zeros_like(whole)
        part[r0:r1, c0:c1] = observed_flow(np.ascontiguousarray(cur[r0:r1, c0:c1]),
                                           np.ascontiguousarray(prev[r0:r1, c0:c1]), method)
        t_part = time.perf_counter() - t
        row = {"frame": i, "whole_ms": 1000 * t_whole, "region_ms": 1000 * t_part,
               "region_share": (r1 - r0) * (c1 - c0) / m.size}
        apart = np.linalg.norm(whole - part, axis=-1)[m]
        row.update(apart_median_px=float(np.median(apart)), apart_p95_px=float(np.percentile(apart, 95)))
        if truth is not None:
            gt = truth(i)
            row.update(epe_whole_px=float(np.linalg.norm(whole - gt, axis=-1)[m].mean()),
                       epe_region_px=float(np.linalg.norm(part - gt, axis=-1)[m].mean()))
        rows.append(row)
    med = lambda k: statistics.median(r[k] for r in rows) if rows and k in rows[0] else None  # noqa: E731
    mean = lambda k: statistics.fmean(r[k] for r in rows) if rows and k in rows[0] else None  # noqa: E731
    return {"clip": spec, "frames": len(rows), "size": list(np.shape(seq.frame(0))[:2]),
            "whole_ms": med("whole_ms"), "region_ms": med("region_ms"),
            "ratio": med("region_ms") / med("whole_ms") if rows else None, "region_share": med("region_share"),
            "epe_whole_px": mean("epe_whole_px"), "epe_region_px": mean("epe_region_px"),
            "apart_median_px": med("apart_median_px"), "apart_p95_px": med("apart_p95_px"), "per_frame": rows}


def main() -> int:
    import cv2

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("clips", nargs="+")
    ap.add_argument("--frames", default="1:41", help="first:last (exclusive) frame")
    ap.add_argument("--step", type=int, default=1)
    ap.add_argument("--max-size", type=int, default=640, help="long side a video of INPUT:RESULT is read at")
    ap.add_argument("--out", default="benchmarks/results/flow_region.json")
    args = ap.parse_args()
    cv2.setNumThreads(1)  # as on the tracker's look-ahead thread beside the optimiser: one core
    a, b = (int(v) for v in args.frames.split(":"))
    results = [measure(c, range(a, b, args.step), args.max_size) for c in args.clips]
    fmt = lambda v, f: "--" if v is None else format(v, f)  # noqa: E731
    print(f"{'clip':58s} {'frames':>6s} {'whole ms':>9s} {'region ms':>9s} {'ratio':>6s} {'share':>6s} "
          f"{'EPE whole':>9s} {'EPE region':>10s} {'apart med/p95 px':>17s}")
    for r in results:
        print(f"{r['clip'][-58:]:58s} {r['frames']:>6d} {fmt(r['whole_ms'], '.1f'):>9s} {fmt(r['region_ms'], '.1f'):>9s} "
              f"{fmt(r['ratio'], '.2f'):>6s} {fmt(r['region_share'], '.2f'):>6s} {fmt(r['epe_whole_px'], '.3f'):>9s} "
              f"{fmt(r['epe_region_px'], '.3f'):>10s} {fmt(r['apart_median_px'], '.2f'):>8s}/{fmt(r['apart_p95_px'], '.1f')}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"benchmark": "flow_region", "frames": args.frames, "step": args.step,
                               "clips": results}, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
