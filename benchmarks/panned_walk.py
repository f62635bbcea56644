"""A walker followed by a camera that pans on a tripod, tracked with its focal length given,
guessed, and read from the background's turns, against the truth.

The built-in walk of ``benchmarks/carried_walk.py`` (1.3 m/s along +x, 4 m from the camera,
the project's synthetic scene) rendered by a camera that stays where it starts, 1.5 m above
the floor, and turns about the vertical to keep the walker's pelvis in the middle of the image
(about 33 degrees over 60 frames), with a longer lens than the guess every video gets
(``--focal-factor`` times the long side; the guess is 0.9). The frames are tracked like a
user's video three ways:

- ``--focal F``, the true focal length;
- ``--focal G``, the guess (what ``track`` did without ``--focal`` before it read the focal
  length from the turns, and still does where the camera does not turn);
- no ``--focal``: ``track`` reads it from the background's turns
  (:func:`flowmocap.vision.camera_motion.focal_from_turns`).

Each result's ground frame (the pan turned back) is compared with the truth as
``carried_walk.py`` does (the pelvis's path on the floor after the best turn and shift about
the vertical; its length; the slower foot's slide), with the focal length tracked with and the
camera's turn found at the last frame.

Usage::

    python benchmarks/panned_walk.py OUT [--frames 60] [--size 640x480] [--focal-factor 1.3]

Prints a table and writes ``OUT/panned_walk.md`` / ``.json`` (a few minutes).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from carried_walk import FOCAL_FACTOR, measures, render  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--focal-factor", type=float, default=1.3, help="the true focal length over the long side")
    args = ap.parse_args(argv)
    from flowmocap.cli import main as cli
    from flowmocap.export.motion import load_fitted_motion

    W, H = (int(x) for x in args.size.split("x"))
    out = Path(args.out)
    if out.exists():
        shutil.rmtree(out)
    truth = render(out, args.frames, 0.0, (W, H), pan=True, focal_factor=args.focal_factor)
    true_turn = float(np.degrees(abs(truth["yaws"][-1])))
    rows = []
    for name, extra in (("true focal given", ["--focal", str(truth["focal"])]),
                        ("the guess given", ["--focal", str(FOCAL_FACTOR * max(W, H))]),
                        ("none given: read from the turns", [])):
        res = out / name.split(":")[0].replace(" ", "_")
        if cli(["track", str(out / "frames"), "--out", str(res), *extra]) != 0:
            raise SystemExit(f"flowmocap track failed on {out / 'frames'}")
        run = json.loads((res / "run.json").read_text())
        cm = run.get("camera_motion") or {}
        row = {"tracked": name, "focal_px": run["camera"]["fx"], "true_focal_px": truth["focal"],
               "turn_deg_end": cm.get("turn_deg_end"), "true_turn_deg_end": true_turn, "focal_found": cm.get("focal"),
               "ground": measures(load_fitted_motion(res, frame="ground", cache_world=False), truth)}
        rows.append(row)
        print(json.dumps(row, default=float), flush=True)
    lines = ["| tracked | focal px (truth) | turn at the end, deg (truth) | path error m | path length m (truth) | "
             "end to end m (truth) | slower foot slides m/s |", "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        s = r["ground"]
        lines.append(f"| {r['tracked']} | {r['focal_px']:.1f} ({r['true_focal_px']:.1f}) | "
                     f"{r['turn_deg_end']:.2f} ({r['true_turn_deg_end']:.2f}) | {s['path_error_m']:.3f} | "
                     f"{s['path_length_m']:.2f} ({s['true_path_length_m']:.2f}) | "
                     f"{s['end_to_end_m']:.2f} ({s['true_end_to_end_m']:.2f}) | {s['slide_m_s']:.3f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    (out / "panned_walk.md").write_text(f"# A walker followed by a panning camera: `python benchmarks/panned_walk.py`"
                                        f"\n\n{args.frames} frames, {args.size}, the true focal length "
                                        f"{args.focal_factor:g} x the long side.\n\n{text}")
    (out / "panned_walk.json").write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
