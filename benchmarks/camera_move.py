"""How well ``flowmocap.vision.camera_motion`` finds a camera that moves, and what it says on
tracked real clips.

1. **Synthetic floors** (:class:`flowmocap.synth.carried.CarriedCamera`: a textured floor
   1.5 m below a camera pitched 15 degrees, 320 x 240, focal 300 px, 30 frames): a dolly
   sideways, a move forward while panning, a diagonal move while panning, a pan alone and a
   still camera. For each: whether it is said to move, the floor normal's error (degrees),
   the error of the camera's last centre as a share of its path, the floor's turn at the end
   against the truth, the whole background's turn and zoom
   (:func:`flowmocap.vision.camera_motion.frame_turn_zoom`: a move forward looks like a zoom
   to it), seconds.
2. **Tracked results** (``--results DIR ...``, ``flowmocap track`` output folders of videos
   or folders of frames, with ``detections/masks``): the camera's motion found again from the
   input and the result's masks, the camera's zoom (its focal length over the first frame's),
   the share of the turn-alone cost the move leaves on the floor's corners, and what the
   export frames make of it with the result's body (undone, or refused and why:
   ``flowmocap.export.motion.camera_move_refused``; where no move is undone, the zoom is).
   Everyone else the
   detector saw is left out as ``flowmocap track`` does (``detections/people``); where the
   result stores them, the same is also found with only the tracked person left out (the
   "others in" columns). The result folders are not changed (the export is read from a copy).

Usage::

    python benchmarks/camera_move.py [--results DIR ...] [--out benchmarks/results/camera_move]

Prints the tables and writes ``OUT.md`` / ``OUT.json``. The synthetic part takes about a minute.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SCENES = [("dolly sideways 5 cm a frame", (0.05, 0, 0), 0.0),
          ("forward 5 cm a frame, panning 0.3 deg a frame", (0, 0, 0.05), 0.3),
          ("diagonal 3+3 cm a frame, panning -0.4 deg a frame", (0.03, 0, 0.03), -0.4),
          ("pan 0.5 deg a frame, no move", (0, 0, 0), 0.5),
          ("still", (0, 0, 0), 0.0)]


def _deg(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def synthetic(frames: int = 30) -> list[dict]:
    from scipy.spatial.transform import Rotation

    from flowmocap.geometry.camera import PinholeCamera
    from flowmocap.synth.carried import CarriedCamera
    from flowmocap.vision.camera_motion import camera_motion

    rows = []
    for name, velocity, yaw in SCENES:
        scene = CarriedCamera(frames, velocity, yaw)
        t0 = time.perf_counter()
        got = camera_motion(scene, PinholeCamera.from_focal(320, 240, 300.0))
        seconds = time.perf_counter() - t0
        centre, normal = scene.truth(frames - 1)
        row = {"scene": name, "moving_sideways": got.moving_sideways, "sideways_h": got.sideways,
               "true_turn_deg": abs(yaw) * (frames - 1), "background_turn_deg": float(got.turn_deg[-1]),
               "seconds": seconds, "move_share": got.move_share,
               "zoom_range": [float(got.zooms.min()), float(got.zooms.max())]}
        if got.moving_sideways:
            row.update(normal_error_deg=_deg(got.floor_normal, normal),
                       path_error_share=float(np.linalg.norm(got.centres()[-1] - centre) / np.linalg.norm(centre)),
                       floor_turn_deg=float(np.degrees(np.linalg.norm(
                           Rotation.from_matrix(got.floor_rotations[-1]).as_rotvec()))))
        rows.append(row)
        print(f"{name}: {row}", flush=True)
    return rows


def tracked_input(result: Path) -> tuple:
    """``(run, camera, seq, people)`` of a ``flowmocap track`` result: its ``run.json``, its
    camera, its input opened at the size it was tracked with the result's masks
    (``seq.masks``, None without one per frame), and everyone else the detector saw
    (``PersonTrack.people``, None where the result does not store them)."""
    from flowmocap.geometry.camera import PinholeCamera
    from flowmocap.io.sequence import load_sequence
    from flowmocap.io.video import load_video
    from flowmocap.vision.auto import load_detections

    run = json.loads((result / "run.json").read_text())
    cam = PinholeCamera.from_dict(run["camera"])
    src = Path(run["input"])
    side = max(cam.width, cam.height)
    seq = load_sequence(src, max_side=side) if src.is_dir() else load_video(src, max_side=side)
    masks = sorted((result / "detections" / "masks").glob("*.png"))
    seq.masks = masks if len(masks) == len(seq) else None
    det = load_detections(result)
    people = det.people if det is not None and det.people_dir is not None else None
    return run, cam, seq, people


def tracked(result: Path) -> dict:
    from flowmocap.export.motion import load_fitted_motion
    from flowmocap.vision.camera_motion import camera_motion

    run, cam, seq, people = tracked_input(result)
    t0 = time.perf_counter()
    got = camera_motion(seq, cam, masks=seq.masks is not None, others=people)
    seconds = time.perf_counter() - t0
    row = {"result": str(result), "frames": len(seq), "ms_per_frame": 1000 * seconds / max(len(seq), 1),
           **got.to_dict(), "export": "unchanged",
           "frames_with_others": None if people is None else sum(people(i) is not None for i in range(len(seq)))}
    if people is not None:
        alone = camera_motion(seq, cam, masks=seq.masks is not None).to_dict()
        row["others_in"] = {k: alone[k] for k in ("turn_deg_max", "move_share", "moving_sideways", "sideways_max")}
    if got.floor_normal is not None:
        row["floor_normal"] = np.round(got.floor_normal, 3).tolist()
    if got.moving_sideways or got.zooming:
        with tempfile.TemporaryDirectory() as tmp:
            copy = Path(tmp) / "result"
            copy.mkdir()
            shutil.copy(result / "motion.npz", copy / "motion.npz")
            (copy / "run.json").write_text(json.dumps({**run, "camera_motion": got.to_dict(rotations=True)}))
            m = load_fitted_motion(copy, frame="up")
            zoom = "" if m.zooms is None else f"zoom undone ({m.zooms.min():.2f}-{m.zooms.max():.2f})"
            if not got.moving_sideways:
                row["export"] = zoom
            elif m.shifts is None:
                row["export"] = "refused: " + m.camera_move_refused + (f"; {zoom}" if zoom else "")
            else:
                row["export"] = f"undone: the camera {m.camera_height_m:.2f} m above the floor"
    print(f"{result}: {row}", flush=True)
    return row


def _fmt(v, spec="{:.2f}"):
    return "" if v is None or (isinstance(v, float) and not np.isfinite(v)) else spec.format(v)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", nargs="*", default=[], help="tracked result folders (with detections/masks)")
    ap.add_argument("--out", default="benchmarks/results/camera_move")
    ap.add_argument("--frames", type=int, default=30, help="frames of each synthetic scene")
    args = ap.parse_args(argv)
    syn = synthetic(args.frames)
    real = [tracked(Path(r)) for r in args.results]
    lines = [f"## Synthetic floors ({args.frames} frames, 1.5 m up, pitched 15 deg, 320 x 240, focal 300 px)", "",
             "| camera | said to move (centre's furthest, h) | floor normal error deg | path end error, % | "
             "floor's turn at the end (truth) deg | background's turn deg | background's zoom | "
             "move's cost / turn's alone | s |",
             "|---|---|---:|---:|---:|---:|---|---:|---:|"]
    for r in syn:
        moved = f"yes ({r['sideways_h']:.2f})" if r["moving_sideways"] else "no"
        lines.append(f"| {r['scene']} | {moved} | {_fmt(r.get('normal_error_deg'), '{:.1f}')} | "
                     f"{_fmt(100 * r['path_error_share'] if 'path_error_share' in r else None, '{:.1f}')} | "
                     f"{_fmt(r.get('floor_turn_deg'))} ({r['true_turn_deg']:.2f}) | {r['background_turn_deg']:.2f} | "
                     f"{r['zoom_range'][0]:.3f}-{r['zoom_range'][1]:.3f} | "
                     f"{_fmt(r['move_share'], '{:.3f}')} | {r['seconds']:.1f} |")
    if real:
        lines += ["", "## Tracked results", "", "Everyone else the detector saw left out (frames with others); "
                  "\"others in\": only the tracked person left out.", "",
                  "| result | frames (with others) | background's turn deg (others in) | zoom | move's cost / turn's "
                  "alone (others in) | said to move (h) (others in) | floor normal | export | ms a frame |",
                  "|---|---:|---:|---|---:|---|---|---|---:|"]

        def moved(r):
            return f"yes ({r['sideways_max']:.2f})" if r["moving_sideways"] else "no"

        for r in real:
            o = r.get("others_in")
            lines.append(f"| {r['result']} | {r['frames']} ({_fmt(r['frames_with_others'], '{}')}) | "
                         f"{r['turn_deg_max']:.2f} ({_fmt(o and o['turn_deg_max'])}) | "
                         f"{r['zoom_min']:.3f}-{r['zoom_max']:.3f} | "
                         f"{_fmt(r['move_share'], '{:.3f}')} ({_fmt(o and o['move_share'], '{:.3f}')}) | "
                         f"{moved(r)} ({moved(o) if o else ''}) | {r.get('floor_normal', '')} | {r['export']} | "
                         f"{r['ms_per_frame']:.0f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(f"# A camera that moves: `python benchmarks/camera_move.py`\n\n{text}")
    out.with_suffix(".json").write_text(json.dumps({"synthetic": syn, "tracked": real}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
