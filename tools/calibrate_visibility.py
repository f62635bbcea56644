"""Put the heavy landmark model's keypoint confidences on the full model's scale.

MediaPipe gives each landmark a "visibility" in [0, 1], which flowmocap reads as the
keypoint's confidence: below 0.5 a keypoint counts as hidden, below 0.3 it is dropped,
and the 2D term weighs a joint by it. Those thresholds were set with the "full" model.
The "heavy" model (:data:`flowmocap.vision.detect.MODELS`) is more cautious: on the same
frames it gives lower visibilities, while its keypoints are nearer the truth at every
level. Taken as they come, the tracker would count more of its good keypoints as hidden.

This tool renders training clips (the same ones, on the same bodies and views, as
``tools/learn_keypoint_offsets.py``: ``train`` clips of ``../shared/data/mocap/prior/``,
test subjects 2, 8, 13, 61 never used), runs both models on every frame as
:func:`flowmocap.vision.auto.detect_for_given_masks` does, and matches the two models'
visibility distributions over the keypoints both found: the heavy model's quantile at
level p maps onto the full model's at the same p (a monotone piecewise-linear map, 0 to 0
and 1 to 1), so as many keypoints pass each threshold as with the full model. It writes
the knots to ``src/flowmocap/vision/data/heavy_visibility.json`` with a table of the 2D
error (against the renders' true joints) per confidence band, before and after.

    python tools/calibrate_visibility.py            # about 15 minutes on 2 CPU cores
    python tools/calibrate_visibility.py --work /tmp/kpo --out /tmp/heavy_visibility.json
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "src" / "flowmocap" / "vision" / "data" / "heavy_visibility.json"
#: quantile levels of the knots: dense near 0 and 1, where the visibilities gather
LEVELS = np.unique(np.concatenate([[0.0, 0.005, 0.01, 0.02, 0.03, 0.05, 0.075], np.linspace(0.1, 0.9, 17),
                                   [0.925, 0.95, 0.97, 0.98, 0.99, 1.0]]))
BANDS = ((0.0, 0.1), (0.1, 0.3), (0.3, 0.5), (0.5, 0.8), (0.8, 1.01))


def _offsets_tool():
    spec = importlib.util.spec_from_file_location("learn_keypoint_offsets", ROOT / "tools" / "learn_keypoint_offsets.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def quantile_map(source: np.ndarray, target: np.ndarray, levels=LEVELS) -> tuple[np.ndarray, np.ndarray]:
    """Knots ``(x, y)`` of the monotone map that sends ``source``'s quantiles onto ``target``'s
    (both 1D samples in [0, 1]), rounded to 5 decimals; ``x`` strictly increasing from 0 to
    1, ``y`` non-decreasing from 0 to 1. Apply with ``np.interp(v, x, y)``."""
    x = np.quantile(np.asarray(source, np.float64), levels)
    y = np.quantile(np.asarray(target, np.float64), levels)
    x, y = np.round(x, 5), np.round(y, 5)  # as stored
    x[0], y[0], x[-1], y[-1] = 0.0, 0.0, 1.0, 1.0
    keep = np.concatenate([np.diff(x) > 0, [True]])  # ties in the source: keep the last knot of each
    x, y = x[keep], y[keep]
    if x[0] > 0:
        x, y = np.concatenate([[0.0], x]), np.concatenate([[0.0], y])
    y[0] = 0.0  # an unseen keypoint (0) stays unseen
    return x, np.maximum.accumulate(y)


def band_table(conf: np.ndarray, err: np.ndarray) -> list[dict]:
    """Per confidence band: how many keypoints and their median / mean 2D error (px)."""
    rows = []
    for lo, hi in BANDS:
        m = (conf >= lo) & (conf < hi) & np.isfinite(err)
        rows.append({"band": [lo, min(hi, 1.0)], "keypoints": int(m.sum()),
                     "median_px": round(float(np.median(err[m])), 2) if m.any() else None,
                     "mean_px": round(float(np.mean(err[m])), 2) if m.any() else None})
    return rows


def main(argv=None) -> int:
    from flowmocap.body.skeleton import JOINT_NAMES
    from flowmocap.vision.detect import SMPL_KEYPOINTS

    tool = _offsets_tool()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=tool.DATA)
    p.add_argument("--work", type=Path, default=Path("/tmp/flowmocap_keypoint_offsets"))
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--per-category", type=int, default=3)
    p.add_argument("--frames", type=int, default=60)
    a = p.parse_args(argv)
    if not (a.data / "index.csv").exists():
        sys.exit(f"{a.data}/index.csv not found: the training data (../shared/data/mocap/prior) is needed.")
    rows = tool.choose_clips(a.data, a.per_category)
    print(f"{len(rows)} train clips, {a.frames} frames each at {tool.FPS:g} fps, both landmark models", flush=True)
    a.work.mkdir(parents=True, exist_ok=True)
    clips = tool.render_and_detect(rows, a.data, a.work, a.frames, models=("full", "heavy-raw"))

    idx = [JOINT_NAMES.index(n) for n in SMPL_KEYPOINTS]
    K = len(SMPL_KEYPOINTS)
    vis = {"full": [], "heavy": []}
    err = {"full": [], "heavy": []}
    for c in clips:
        both = c["by_model"]["full"][2] & c["by_model"]["heavy-raw"][2]
        uv = np.asarray(c["camera"].project(c["joints"][:, idx]), np.float64)
        for m in vis:
            kp, conf, _ = c["by_model"]["heavy-raw" if m == "heavy" else m]
            vis[m].append(conf[both][:, :K].ravel())
            err[m].append(np.linalg.norm(kp[both][:, :K] - uv[both], axis=-1).ravel())
    vis = {m: np.concatenate(v) for m, v in vis.items()}
    err = {m: np.concatenate(v) for m, v in err.items()}
    x, y = quantile_map(vis["heavy"], vis["full"])
    mapped = np.interp(vis["heavy"], x, y)
    doc = {
        "description": "Monotone map of MediaPipe's heavy landmark model's visibility onto the full model's scale: "
                       "confidence = interp(visibility, heavy, full). Made by tools/calibrate_visibility.py (quantile "
                       "matching over the 12 body keypoints of frames both models found).",
        "heavy": [float(v) for v in x], "full": [float(v) for v in y],
        "levels": [round(float(v), 4) for v in LEVELS],
        "clips": [c["file"] for c in clips], "frames_per_clip": a.frames, "keypoints": int(vis["heavy"].size),
        "data": "CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu), train split of ../shared/data/mocap/prior; "
                "test subjects 2, 8, 13, 61 not used",
        "error_by_band": {"full": band_table(vis["full"], err["full"]), "heavy": band_table(vis["heavy"], err["heavy"]),
                          "heavy_mapped": band_table(mapped, err["heavy"])},
        "median_px": {m: round(float(np.median(e)), 2) for m, e in err.items()},
    }
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {a.out}: {len(x)} knots over {vis['heavy'].size} keypoints")
    for name, t in doc["error_by_band"].items():
        print(f"  {name:13s} " + "  ".join(f"[{r['band'][0]:.1f},{r['band'][1]:.1f}) n={r['keypoints']} "
                                          f"{r['median_px']}/{r['mean_px']} px" for r in t))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
