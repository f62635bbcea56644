"""Where the real3d suite's error comes from: the 2D, or the lifting of it (issue 18).

For each person-view of a finished ``flowmocap bench --suite real3d`` folder, on the
suite's own frames and joints (:func:`flowmocap.eval.real3d.scored_frames`):

- **2D errors** (pixels of the run's frames, median and 90th percentile over the scored
  joints): the detector's 13 keypoints and the fit's own 13 keypoints (the body at the
  detector's keypoints, projected by the run's camera), each against the reference
  triangulated WITHOUT the view, projected into the view by its calibrated camera;
- **3D errors** (per-frame PA-MPJPE, mm, against the same reference):
  MediaPipe's world landmarks; the fit; flowmocap's keypoint lifter reading three 2D
  sources in turn: the detector's keypoints (confidence >= 0.5; what the pipeline's
  lifter refit reads), the fit's own keypoints, and the reference's projection (an
  oracle: a lifter given 2D without detector errors; its image-plane structure is the
  reference's own, so only the depth is left to err).

The oracle column against the detector column says how much of the lifter's real-video
error is the detector's 2D; the fit column, whether the tracker's 2D is a better input.

Usage: python benchmarks/real3d_2d_sources.py REAL3D_DIR [--lifter FILE] [--data DIR] [--out PREFIX]
       (PREFIX.json and PREFIX.md; a few seconds)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

COLUMNS = ("mediapipe_3d", "fit", "lifter_detector_2d", "lifter_fit_2d", "lifter_reference_2d")


def _pct(e: np.ndarray, q: float) -> float:
    e = e[np.isfinite(e)]
    return float(np.percentile(e, q)) if e.size else float("nan")


def rows_for(bench_dir: Path, lifter, data: Path | None = None) -> list[dict]:
    """One row per person-view (see the module docstring); ``data``: the recording (default
    the suite's, ``../shared/data/video/pose2sim-multi``)."""
    from flowmocap.eval import real3d as R
    from flowmocap.io.calibration import read_qualisys_calibration
    from flowmocap.vision.lifter import eval_points_2d

    data = Path(R.DATA if data is None else data)
    cams = read_qualisys_calibration(data / "Calib.qca.txt")
    rows = []
    for res, _, view, d in R.scored_runs(bench_dir, data_dir=data):
        if d["ours_kp"] is None:
            continue
        ref, valid, det = d["ref"], d["valid"], d["detections"]
        run_cam = d["result"].camera
        cam = cams[view].scaled(run_cam.height / cams[view].height)
        used = np.asarray(d["used"])
        det2, conf2 = eval_points_2d(det.keypoints[used], det.confidence[used])
        given = (conf2 >= 0.5) & np.isfinite(det2).all(-1)
        ref2 = np.asarray(cam.project(ref.reshape(-1, 3)), np.float64).reshape(ref.shape[:2] + (2,))
        ref_ok = valid & np.isfinite(ref2).all(-1)
        fit2 = np.asarray(run_cam.project(d["ours_kp"].reshape(-1, 3)), np.float64).reshape(ref.shape[:2] + (2,))
        e_det = np.where(ref_ok & given, np.linalg.norm(np.nan_to_num(det2) - np.nan_to_num(ref2), axis=-1), np.nan)
        e_fit = np.where(ref_ok, np.linalg.norm(fit2 - np.nan_to_num(ref2), axis=-1), np.nan)
        lifted = {
            "lifter_detector_2d": lifter.lift_points(det2, given),
            "lifter_fit_2d": lifter.lift_points(fit2, np.ones(given.shape, bool)),
            "lifter_reference_2d": lifter.lift_points(np.nan_to_num(ref2), ref_ok),
        }
        preds = {"mediapipe_3d": d["detector"], "fit": d["ours"], **lifted}
        ok = np.all([np.isfinite(p).all((1, 2)) for p in preds.values()], 0)  # frames every source has
        row = {"name": res.name, "frames": int(ok.sum()),
               "detector_2d_px_p50": _pct(e_det[ok], 50), "detector_2d_px_p90": _pct(e_det[ok], 90),
               "fit_2d_px_p50": _pct(e_fit[ok], 50), "fit_2d_px_p90": _pct(e_fit[ok], 90)}
        for k in COLUMNS:
            row[k] = R.pa_mpjpe(preds[k][ok], ref[ok], valid[ok])[0] if ok.any() else float("nan")
        rows.append(row)
    return rows


def table(rows: list[dict]) -> str:
    keys = ["frames", "detector_2d_px_p50", "detector_2d_px_p90", "fit_2d_px_p50", "fit_2d_px_p90", *COLUMNS]
    out = ["| person-view | " + " | ".join(keys) + " |", "|---|" + "---:|" * len(keys)]
    for r in rows:
        cells = (f"{r[k]:.0f}" if k == "frames" else f"{r[k]:.1f}" for k in keys)
        out.append(f"| {r['name']} | " + " | ".join(cells) + " |")
    for name, f in (("mean", np.nanmean), ("median", np.nanmedian)):
        cells = (f"{f([r[k] for r in rows]):.1f}" for k in keys[1:])
        out.append(f"| **{name}** ({len(rows)}) | | " + " | ".join(cells) + " |")
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("real3d", type=Path, help="a finished flowmocap bench --suite real3d folder")
    ap.add_argument("--lifter", type=Path, help="a lifter file instead of the packaged one")
    ap.add_argument("--data", type=Path, help="the recording (default: the suite's)")
    ap.add_argument("--out", help="write PREFIX.json and PREFIX.md")
    a = ap.parse_args()
    from flowmocap.vision.lifter import Lifter, load_lifter

    lifter = Lifter.load(a.lifter) if a.lifter else load_lifter()
    rows = rows_for(a.real3d, lifter, a.data)
    text = ("# real3d: the 2D sources and the lifter\n\n2D: pixels of the run's frames against the reference "
            "(without the view) projected into it; 3D: per-frame PA-MPJPE, mm, on the frames every source has.\n\n"
            + table(rows))
    print(text)
    if a.out:
        summary = {k: float(np.nanmean([r[k] for r in rows])) for k in rows[0] if k != "name"} if rows else {}
        Path(f"{a.out}.json").write_text(json.dumps({"dir": str(a.real3d), "lifter": str(a.lifter or "packaged"),
                                                     "rows": rows, "mean": summary}, indent=1))
        Path(f"{a.out}.md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
