"""Seconds of the camera's motion (``flowmocap.vision.camera_motion.camera_motion``) as
``flowmocap track`` runs it on a video without a known camera, and on synthetic floors.

1. **A tracked result** (``RESULT``: a ``flowmocap track`` folder of a video or a folder of
   frames, with ``detections/masks``; e.g. ``benchmarks/real_video.py``'s DAVIS
   dance-twirl): the passes ``track`` makes over its input, each timed ``--repeat`` times
   (median):

   - *the guess, with the floor*: the motion fitted with the run's camera, the focal length
     read from the turns and the floor searched for a move (the first pass of every video
     without a known camera);
   - *a focal round, no floor*: the turns fitted again with the estimate
     (``run.json`` ``camera_motion.focal.focal_px``; only where the camera turns);
   - *the estimate, with the floor*: the check that the floor shows no move with it.

   The result's own ``camera_motion`` says which passes its run made; all three are timed
   where it has a focal estimate, the first alone otherwise. Everyone else the detector saw
   is left out as ``track`` does. The found motion's summary is printed with the times, so two
   versions of the code can be seen to agree.
2. **Synthetic floors** (``--synthetic``; :class:`flowmocap.synth.carried.CarriedCamera`, 30
   frames, 320 x 240, focal 300 px): a dolly sideways and a move forward while panning.

To compare with another version of the code, run this script with that version's ``src``
first on ``PYTHONPATH`` (the module the run used is printed).

Usage: python benchmarks/camera_motion_cost.py [RESULT] [--synthetic] [--repeat 3] [--out PREFIX]

Prints a table and writes ``PREFIX.json`` / ``PREFIX.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/camera_move.py's loader


def _summary(m) -> dict:
    return {"turn_deg_max": round(float(m.turn_deg.max()), 4), "moving_sideways": bool(m.moving_sideways),
            "move_share": None if not np.isfinite(m.move_share) else round(float(m.move_share), 6),
            "sideways_h": None if not np.isfinite(m.sideways) else round(float(m.sideways), 6),
            "focal_px": None if m.focal is None else m.focal["focal_px"]}


def _timed(fn, repeat: int) -> tuple[list[float], dict]:
    seconds, got = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        got = fn()
        seconds.append(time.perf_counter() - t0)
    return seconds, _summary(got)


def result_passes(result: Path, repeat: int) -> list[dict]:
    from camera_move import tracked_input

    from flowmocap.geometry.camera import PinholeCamera
    from flowmocap.vision.camera_motion import camera_motion

    run, cam, seq, people = tracked_input(result)
    focal = (run.get("camera_motion") or {}).get("focal")

    def motion(c, **kw):
        return lambda: camera_motion(seq, c, frames=range(len(seq)), masks=seq.masks is not None, others=people, **kw)

    passes = [("the guess, with the floor", motion(cam, focal=True))]
    if focal:
        est = PinholeCamera.from_focal(cam.width, cam.height, float(focal["focal_px"]))
        passes += [("a focal round, no floor", motion(est, focal=True, sideways=False)),
                   ("the estimate, with the floor", motion(est))]
    rows = []
    for name, fn in passes:
        seconds, found = _timed(fn, repeat)
        rows.append({"input": str(result), "pass": name, "frames": len(seq), "seconds": seconds,
                     "median_s": float(np.median(seconds)), "found": found})
        print(f"{result.name} | {name}: median {np.median(seconds):.2f} s {np.round(seconds, 2).tolist()} {found}",
              flush=True)
    return rows


def synthetic(repeat: int) -> list[dict]:
    from flowmocap.geometry.camera import PinholeCamera
    from flowmocap.synth.carried import CarriedCamera
    from flowmocap.vision.camera_motion import camera_motion

    rows = []
    for name, velocity, yaw in (("dolly sideways 5 cm a frame", (0.05, 0, 0), 0.0),
                                ("forward 5 cm a frame, panning 0.3 deg a frame", (0, 0, 0.05), 0.3)):
        scene = CarriedCamera(30, velocity, yaw)
        seconds, found = _timed(lambda: camera_motion(scene, PinholeCamera.from_focal(320, 240, 300.0)), repeat)
        rows.append({"input": "synthetic", "pass": name, "frames": 30, "seconds": seconds,
                     "median_s": float(np.median(seconds)), "found": found})
        print(f"synthetic | {name}: median {np.median(seconds):.2f} s {np.round(seconds, 2).tolist()} {found}", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("result", nargs="?", type=Path, help="a flowmocap track result folder")
    ap.add_argument("--synthetic", action="store_true", help="time the synthetic floors too")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default="benchmarks/results/camera_motion_cost")
    a = ap.parse_args()
    if a.result is None and not a.synthetic:
        ap.error("give a result folder, --synthetic, or both")
    import flowmocap

    rows = (result_passes(a.result, a.repeat) if a.result is not None else []) + (synthetic(a.repeat) if a.synthetic else [])
    doc = {"code": flowmocap.__file__, "repeat": a.repeat, "rows": rows}
    lines = [f"# The camera's motion, seconds: `python benchmarks/camera_motion_cost.py`\n",
             f"Code: `{flowmocap.__file__}`; each pass {a.repeat} times, the median.\n",
             "| input | pass | frames | median s | found: turn deg, moves sideways (h), move's cost share, focal px |",
             "|---|---|---:|---:|---|"]
    for r in rows:
        f = r["found"]
        lines.append(f"| {Path(r['input']).name} | {r['pass']} | {r['frames']} | {r['median_s']:.2f} | {f['turn_deg_max']:.2f}, "
                     f"{'yes' if f['moving_sideways'] else 'no'} ({f['sideways_h']}), {f['move_share']}, {f['focal_px']} |")
    text = "\n".join(lines) + "\n"
    print(text)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1))
    out.with_suffix(".md").write_text(text)


if __name__ == "__main__":
    main()
