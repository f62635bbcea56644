"""Does the real3d cameras' roll throw the keypoint lifter? (issue 18, a check)

The lifter was trained on upright cameras (azimuth and elevation, no turn about the optical
axis); the recording's cam04 is turned by 26 degrees and cam01 by 13 (from its
calibration, world up +z). For each person-view of a finished ``flowmocap bench --suite
real3d`` folder this lifts the detector's 2D (confidence >= 0.5) as it is and turned
upright by the calibrated camera's roll, and scores both (per-frame PA-MPJPE, mm, on the
suite's own frames and joints; PA-MPJPE does not see the turn of the output) beside
MediaPipe's own 3D.

Usage: python benchmarks/real3d_roll.py REAL3D_DIR [LIFTER_FILE]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from flowmocap.eval import real3d as R
from flowmocap.io.calibration import read_qualisys_calibration
from flowmocap.vision.lifter import Lifter, eval_points_2d

UP = np.array([0.0, 0.0, 1.0])  # the calibration's world up


def upright_turn(camera) -> np.ndarray:
    """``(2, 2)`` the rotation of pixel offsets that turns the world's up in ``camera``'s
    image to straight up (``(0, -1)``)."""
    right, down, _ = camera.R
    th = np.arctan2(-1.0, 0.0) - np.arctan2(down @ UP, right @ UP)
    return np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])


def main() -> int:
    bench = Path(sys.argv[1])
    lifter = Lifter.load(sys.argv[2] if len(sys.argv) > 2 else None)
    cams = read_qualisys_calibration(Path(R.DATA) / "Calib.qca.txt")
    total = {"raw": [], "upright": [], "mediapipe": []}
    for res, _, view, d in R.scored_runs(bench):
        turn = upright_turn(cams[view])
        used = np.asarray(d["used"])
        p2, conf = eval_points_2d(d["detections"].keypoints[used], d["detections"].confidence[used])
        given = (conf >= 0.5) & np.isfinite(p2).all(-1)
        row = {"mediapipe": R.pa_mpjpe(d["detector"], d["ref"], d["valid"])[0]}
        for name, pts in (("raw", p2), ("upright", p2 @ turn.T)):
            y = lifter.lift_points(pts, given)
            y = np.where(np.isfinite(y).all((1, 2))[:, None, None], y, 0.0)
            row[name] = R.pa_mpjpe(y, d["ref"], d["valid"])[0]
        for k in total:
            total[k].append(row[k])
        deg = np.degrees(np.arctan2(turn[1, 0], turn[0, 0]))
        print(f"{res.name:15s} turned {deg:6.1f} deg: lifter as is {row['raw']:6.1f}, upright {row['upright']:6.1f}, "
              f"MediaPipe {row['mediapipe']:6.1f} mm")
    print("mean:", ", ".join(f"{k} {np.mean(v):.1f}" for k, v in total.items()), "mm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
