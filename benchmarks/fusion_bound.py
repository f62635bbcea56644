"""How much a blend of the fit's 3D joints and the detector's own 3D joints could give
(issue 18): an upper bound on what any cue fusing the two per frame can reach.

For each frame, the fit's 13 evaluation joints are aligned onto MediaPipe's world
landmarks by a similarity (the detector's axes: x right, y down, z along the ray through
the person) and blended with them, ``(1 - w) * fit + w * detector``:

- ``full``: all three coordinates blended;
- ``depth``: only z, the depth along the ray (the fit's image-plane structure kept).

``w = 0`` is the fit alone, ``w = 1`` (``full``) the detector alone. Each blend is scored
the way its suite scores a method, on the frames where the detector gives all 13 joints:

- ``--real3d DIR``: a ``flowmocap bench --suite real3d`` folder; per person-view the
  per-frame PA-MPJPE (mm) against the reference triangulated without the view
  (:func:`flowmocap.eval.real3d.scored_frames`: the suite's own frames and joints);
- ``--diverse DIR``: a ``flowmocap bench --suite diverse`` or ``benchmarks/tracker_only.py``
  folder; per clip the local error (cm, per-frame similarity onto the truth), on the
  frames where the detector found all 13 joints (so ``w = 0`` can differ from the
  bench's figure, which scores every frame).

The blend is not a method (the output would no longer be a body): it says how much the
two sources' errors cancel, i.e. whether a stronger detector term could reach a target.

``--source lifter`` (or ``both``) takes the second source from flowmocap's keypoint lifter
of the detector's 2D keypoints (:func:`flowmocap.vision.lifter.lifted_track`; ``both``:
its mean with MediaPipe's), as the tracker's ``detector3d_source`` setting does; ``w = 1``
is then that source's own score.

``--lifter FILE`` takes another lifter file (``tools/train_lifter.py --out``).

Usage: python benchmarks/fusion_bound.py [--real3d DIR] [--diverse DIR] [--source mediapipe|lifter|both]
       [--lifter FILE] [--weights 0,0.25,0.5,0.75,1] [--out PREFIX]   (PREFIX.json and PREFIX.md)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from flowmocap.body.skeleton import EVAL_JOINTS
from flowmocap.geometry.procrustes import similarity_procrustes

MODES = ("full", "depth")


def blend(fit: np.ndarray, det: np.ndarray, w: float, mode: str) -> np.ndarray:
    """``(T, N, 3)`` the fit aligned onto the detector per frame and blended with it.

    Args:
        fit, det: ``(T, N, 3)`` joints, metres (any axes and origin for ``fit``; the
            detector's axes for ``det``).
        w: the detector's share, in [0, 1].
        mode: ``"full"`` (x, y, z blended) or ``"depth"`` (z only).
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}; got {mode!r}")
    al = similarity_procrustes(np.asarray(fit, np.float64), np.asarray(det, np.float64))[0]
    out = al.copy()
    if mode == "full":
        out = (1.0 - w) * al + w * det
    else:
        out[..., 2] = (1.0 - w) * al[..., 2] + w * det[..., 2]
    return out


#: a lifter file instead of the packaged one (``--lifter``)
LIFTER: dict = {}


def _source(track, source: str, res: Path):
    """The track with its 3D keypoints from ``source`` (see the module docstring); ``res``:
    the result folder (its frame rate, for a temporal lifter)."""
    if source == "mediapipe":
        return track
    from flowmocap.vision.lifter import lifted_track

    fps = float(np.load(res / "motion.npz")["fps"])
    return lifted_track(track, LIFTER.get("lifter"), mix=source == "both", fps=fps)


def real3d_rows(bench_dir: Path, weights: list[float], source: str = "mediapipe") -> list[dict]:
    from flowmocap.eval import real3d as R

    rows = []
    for res, _, _, d in R.scored_runs(bench_dir):
        det = d["detector"]
        if source != "mediapipe":  # the suite's frames, the other source's 3D (NaN where it has none)
            det = R.eval_points(_source(d["detections"], source, res).world[d["used"]])
        ok = np.isfinite(det).all((1, 2))
        row = {"name": res.name, "frames": int(ok.sum())}
        if not ok.any():
            rows.append(row)
            continue
        for mode in MODES:
            row[mode] = [R.pa_mpjpe(blend(d["ours"][ok], det[ok], w, mode), d["ref"][ok], d["valid"][ok])[0]
                         for w in weights]
        rows.append(row)
    return rows


def diverse_rows(bench_dir: Path, weights: list[float], source: str = "mediapipe") -> list[dict]:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from global_error import camera_joints

    from flowmocap.eval import metrics as M
    from flowmocap.eval.scoring import detector_joints3d
    from flowmocap.vision.auto import load_detections

    E = list(EVAL_JOINTS)
    rows = []
    for seq in sorted(bench_dir.iterdir()):
        res = seq / "flowmocap"
        if not (res / "motion.npz").exists():
            continue
        gt, pred, _, _, idx = camera_joints(seq / "sequence", res)
        track = load_detections(res)
        if track is None:
            continue
        det = detector_joints3d(_source(track, source, res))[idx][:, E]
        ok = np.isfinite(det).all((1, 2))
        row = {"name": seq.name, "frames": int(ok.sum())}
        if not ok.any():
            rows.append(row)
            continue
        # the local error is over EVAL_JOINTS of 24; put the blend back in those places
        for mode in MODES:
            vals = []
            for w in weights:
                full = pred[ok].copy()
                full[:, E] = blend(pred[ok][:, E], det[ok], w, mode)
                vals.append(100 * float(M.local_procrustes_error(full, gt[ok]).mean()))
            row[mode] = vals
        rows.append(row)
    return rows


def summary(rows: list[dict], weights: list[float]) -> dict:
    out = {}
    scored = [r for r in rows if "full" in r]
    for mode in MODES:
        a = np.array([r[mode] for r in scored]) if scored else np.zeros((0, len(weights)))
        out[mode] = {"mean": a.mean(0).tolist() if len(a) else None,
                     "median": np.median(a, 0).tolist() if len(a) else None}
    out["scored"] = len(scored)
    return out


def table(name: str, unit: str, rows: list[dict], weights: list[float]) -> str:
    head = " | ".join(f"{m} w={w:g}" for m in MODES for w in weights)
    lines = [f"### {name} ({unit})", "", f"| run | frames | {head} |",
             "|---|---:|" + "---:|" * (2 * len(weights))]
    for r in rows:
        vals = " | ".join(f"{v:.1f}" for m in MODES for v in r[m]) if "full" in r else " | ".join(["--"] * 2 * len(weights))
        lines.append(f"| {r['name']} | {r['frames']} | {vals} |")
    s = summary(rows, weights)
    for stat in ("mean", "median"):
        if s["full"][stat] is not None:
            vals = " | ".join(f"{v:.1f}" for m in MODES for v in s[m][stat])
            lines.append(f"| **{stat}** ({s['scored']}) | | {vals} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--real3d", type=Path, help="a flowmocap bench --suite real3d folder")
    ap.add_argument("--diverse", type=Path, help="a diverse bench or tracker_only folder")
    ap.add_argument("--weights", default="0,0.25,0.5,0.75,1", help="the detector's shares, comma-separated")
    ap.add_argument("--source", default="mediapipe", choices=("mediapipe", "lifter", "both"),
                    help="the second 3D source: MediaPipe's own, flowmocap's lifter, or their mean")
    ap.add_argument("--lifter", type=Path, help="a lifter file instead of the packaged one (--source lifter|both)")
    ap.add_argument("--out", help="write PREFIX.json and PREFIX.md")
    a = ap.parse_args()
    if a.real3d is None and a.diverse is None:
        ap.error("give --real3d and/or --diverse")
    if a.lifter:
        from flowmocap.vision.lifter import Lifter

        LIFTER["lifter"] = Lifter.load(a.lifter)
    weights = [float(x) for x in a.weights.split(",")]
    if any(not 0 <= w <= 1 for w in weights):
        ap.error("weights must lie in [0, 1]")
    result = {"weights": weights, "modes": list(MODES), "source": a.source}
    md = [f"# The fit blended with a second 3D source: {a.source}\n"]
    if a.real3d is not None:
        rows = real3d_rows(a.real3d, weights, a.source)
        result["real3d"] = {"dir": str(a.real3d), "rows": rows, "summary": summary(rows, weights)}
        md.append(table("real3d, per-frame PA-MPJPE", "mm", rows, weights))
    if a.diverse is not None:
        rows = diverse_rows(a.diverse, weights, a.source)
        result["diverse"] = {"dir": str(a.diverse), "rows": rows, "summary": summary(rows, weights)}
        md.append(table("diverse, local error on the detector's frames", "cm", rows, weights))
    text = "\n".join(md)
    print(text)
    if a.out:
        Path(f"{a.out}.json").write_text(json.dumps(result, indent=1))
        Path(f"{a.out}.md").write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
