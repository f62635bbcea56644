"""Every refit attempt of a tracking run on a real clip, kept or not, and the tracking's time.

Tracks INPUT into WORK with the detections stored in DETECTIONS (copied in, so only the
tracking is timed: no detection pass) and records, for each attempt of the re-initialisation
(:class:`flowmocap.fit.reinit.ReinitMonitor`): the frame, which criterion fired (2D or 3D),
the frame's scores before, whether the refit was kept (and its scores after) and its
seconds. Prints the totals and writes JSON. With ``PYTHONPATH=CHECKOUT/src`` it times
another checkout on the same detections (run the two alternately: this machine's speed
moves by 10-20 % between runs).

Usage: python benchmarks/refit_attempts.py INPUT DETECTIONS WORK [--max-size 640]
       [--config JSON] [--out JSON]
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("input")
    ap.add_argument("detections", help="a result folder's detections/ made at the same --max-size")
    ap.add_argument("work", help="result folder to write (replaced)")
    ap.add_argument("--max-size", type=int, default=640)
    ap.add_argument("--config", help="tracker settings JSON")
    ap.add_argument("--out", help="JSON to write (default WORK_attempts.json)")
    args = ap.parse_args()

    import flowmocap.fit.reinit as ri
    from flowmocap.pipeline import track

    attempts = []
    real = ri.ReinitMonitor._reinitialise

    def logged(self, i, state, scene, mask, before, in3d=False):
        t = time.perf_counter()
        out = real(self, i, state, scene, mask, before, in3d=in3d)
        attempts.append({"frame": i, "in3d": in3d, "before": ri._rounded(before), "kept": out is not None,
                         "after": out[1]["after"] if out is not None else None,
                         "seconds": round(time.perf_counter() - t, 3)})
        return out

    ri.ReinitMonitor._reinitialise = logged
    work = Path(args.work)
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    shutil.copytree(args.detections, work / "detections")
    t0, c0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
    track(args.input, work, progress=False, log=None, max_size=args.max_size,
          config=json.loads(Path(args.config).read_text()) if args.config else None)
    c1 = resource.getrusage(resource.RUSAGE_SELF)
    run = json.loads((work / "run.json").read_text())
    result = {"input": args.input, "max_size": args.max_size, "config": args.config,
              "wall_s": time.perf_counter() - t0, "cpu_s": (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime),
              "tracked_frames": len(run["timings"]["frame_s"]) + 2, "attempts": attempts,
              "attempt_seconds": sum(a["seconds"] for a in attempts), "kept": sum(a["kept"] for a in attempts)}
    out = Path(args.out or f"{work}_attempts.json")
    out.write_text(json.dumps(result, indent=1))
    print(f"wall {result['wall_s']:.1f} s, CPU {result['cpu_s']:.1f} s, {len(attempts)} refit attempts "
          f"({sum(a['in3d'] for a in attempts)} on 3D), {result['kept']} kept, {result['attempt_seconds']:.1f} s in them; "
          f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
