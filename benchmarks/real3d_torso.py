"""Which way is the body turned? The torso's yaw on the real3d recording (issue 18, a check)

Flow, silhouettes and 2D keypoints see a torso's turn about the vertical only through the
foreshortening of the shoulders and hips, and ``E_3d`` and the lifter refit align the
detector's or lifter's 3D onto the fit by a similarity, so they carry no information
about it. MediaPipe's world landmarks come in the camera's axes, so their turn is a cue
the tracker does not use. Is it a better one? For each person-view of a finished
``flowmocap bench --suite real3d`` folder, on the suite's own frames and joints
(:func:`flowmocap.eval.real3d.scored_frames`), in the view's camera axes:

- the torso's **yaw**: the turn about the vertical of its forward direction
  (left x up, from the shoulders and hips), 0 facing the camera, as
  :func:`flowmocap.vision.auto.facing_rotvec` defines it; the median absolute error
  against the reference (triangulated without the view), of the fit (its keypoints) and
  of MediaPipe's 3D;
- how often the **shoulders' depth order** is wrong (left minus right shoulder depth,
  where the reference's differs by more than 8 cm), for both.

Usage: python benchmarks/real3d_torso.py REAL3D_DIR [--out PREFIX]  (PREFIX.json, PREFIX.md; seconds)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

#: Shoulder depth differences (metres) the order of which is scored.
MIN_DEPTH = 0.08


def torso_yaw(points: np.ndarray, names) -> np.ndarray:
    """``(T,)`` degrees: the yaw of the torso of ``points (T, 13, 3)`` (camera axes: x
    right, y down, z away; in the order of ``names``), 0 facing the camera, positive
    turning the person's front towards the image's left (:func:`facing_rotvec`'s sign)."""
    i = {n: k for k, n in enumerate(names)}
    left = (points[:, i["left_shoulder"]] - points[:, i["right_shoulder"]]
            + points[:, i["left_hip"]] - points[:, i["right_hip"]])
    up = (points[:, i["left_shoulder"]] + points[:, i["right_shoulder"]]
          - points[:, i["left_hip"]] - points[:, i["right_hip"]]) / 2
    forward = np.cross(left, up)
    return np.degrees(np.arctan2(-forward[:, 0], -forward[:, 2]))


def angle_gap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``|a - b|`` in degrees, wrapped to [0, 180]."""
    return np.abs((a - b + 180.0) % 360.0 - 180.0)


def rows_for(bench_dir: Path) -> list[dict]:
    from flowmocap.eval import real3d as R
    from flowmocap.io.calibration import read_qualisys_calibration

    cams = read_qualisys_calibration(Path(R.DATA) / "Calib.qca.txt")
    names = list(R.EVAL_NAMES)
    ls, rs = names.index("left_shoulder"), names.index("right_shoulder")
    rows = []
    for res, person, view, d in R.scored_runs(bench_dir):
        if d["ours_kp"] is None:
            continue
        cam = cams[view]
        ref = d["ref"] @ np.asarray(cam.R).T + np.asarray(cam.t).reshape(3)
        fcam = json.loads(str(d["result"].motion["camera"]))
        ours = d["ours_kp"] @ np.asarray(fcam["R"]).T + np.asarray(fcam["t"])
        mp = d["detector"]
        y_ref = torso_yaw(ref, names)
        row = {"run": res.name, "frames": len(y_ref)}
        deep = (np.abs(ref[:, ls, 2] - ref[:, rs, 2]) > MIN_DEPTH) & d["valid"][:, ls] & d["valid"][:, rs]
        row["shoulder_frames"] = int(deep.sum())
        for name, p in (("fit", ours), ("mediapipe", mp)):
            row[f"{name}_yaw_error_deg"] = float(np.median(angle_gap(torso_yaw(p, names), y_ref)))
            wrong = deep & (np.sign(p[:, ls, 2] - p[:, rs, 2]) != np.sign(ref[:, ls, 2] - ref[:, rs, 2]))
            row[f"{name}_shoulder_order_wrong"] = int(wrong.sum())
        rows.append(row)
    return rows


def table(rows: list[dict]) -> str:
    cols = ("frames", "fit_yaw_error_deg", "mediapipe_yaw_error_deg", "shoulder_frames", "fit_shoulder_order_wrong",
            "mediapipe_shoulder_order_wrong")
    lines = ["| person-view | " + " | ".join(cols) + " |", "|---|" + "---:|" * len(cols)]
    for r in rows:
        lines.append(f"| {r['run']} | " + " | ".join(f"{r[c]:.1f}" if isinstance(r[c], float) else str(r[c])
                                                    for c in cols) + " |")
    med = {c: float(np.median([r[c] for r in rows])) for c in ("fit_yaw_error_deg", "mediapipe_yaw_error_deg")}
    tot = {c: sum(r[c] for r in rows) for c in ("frames", "shoulder_frames", "fit_shoulder_order_wrong",
                                                 "mediapipe_shoulder_order_wrong")}
    lines.append(f"| **median / total** | {tot['frames']} | {med['fit_yaw_error_deg']:.1f} | "
                 f"{med['mediapipe_yaw_error_deg']:.1f} | {tot['shoulder_frames']} | "
                 f"{tot['fit_shoulder_order_wrong']} | {tot['mediapipe_shoulder_order_wrong']} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench", type=Path)
    ap.add_argument("--out")
    a = ap.parse_args()
    rows = rows_for(a.bench)
    md = ("# real3d: the torso's turn, fit against MediaPipe's 3D\n\n"
          f"`python benchmarks/real3d_torso.py {a.bench}`; yaw errors are medians over the scored frames, degrees; "
          f"shoulder order: frames where the reference's shoulders differ in depth by more than {MIN_DEPTH} m, and "
          "those of them with the order wrong.\n\n" + table(rows))
    print(md)
    if a.out:
        Path(a.out + ".md").write_text(md)
        Path(a.out + ".json").write_text(json.dumps({"bench": str(a.bench), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
