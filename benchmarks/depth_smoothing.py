"""The root-depth smoother (flowmocap.fit.smooth.smooth_root_depth) on finished synthetic runs.

For every run folder ``RUNS/*/`` holding ``sequence/gt.npz`` and a result (``flowmocap``,
``result`` or ``NAME/result``: the layouts of ``flowmocap bench --suite diverse`` and of
benchmarks/track_seeds.py), the tracker's own frames (``trans_tracked`` where the result
was smoothed already) are depth-smoothed with each window and degree, as
:func:`flowmocap.fit.smooth.depth_smoothed_motion` does at the end of a run (starting
again at each re-initialisation of ``run.json``), and scored against the ground truth:
local / global Procrustes error (cm, 13 joints, ``flowmocap.eval.metrics``) and the 2D
joint error (px, the joints projected with the result's camera against the true ones).

    python benchmarks/depth_smoothing.py --runs /work/bench-runs/diverse_kpo \\
        --out benchmarks/results/depth_smoothing_diverse.json
    python benchmarks/depth_smoothing.py --runs /work/bench-runs/seeds --result kpo/result \\
        --out benchmarks/results/depth_smoothing_cmu.json

Prints a Markdown table (median and mean over the runs) and writes the JSON.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from flowmocap.eval import metrics as m
from flowmocap.fit.smooth import depth_smoothed_motion
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.io.results import read_result

#: (window s, degree); None: the tracker's own frames. (2.0, 2): the default.
SETTINGS = [None, (0.5, 1), (1.0, 1), (1.5, 1), (2.0, 1), (1.0, 2), (2.0, 2), (3.0, 2)]


def _name(s) -> str:
    return "raw" if s is None else f"{s[0]:g} s / {s[1]}"


def tracked_frames(motion: dict) -> dict:
    """The tracker's own frames of a result (undoes the depth smoothing where it was done)."""
    motion = dict(motion)
    if "trans_tracked" not in motion:
        return motion
    shift = np.asarray(motion["trans"], np.float64) - np.asarray(motion["trans_tracked"], np.float64)
    cam = PinholeCamera.from_dict(json.loads(str(np.asarray(motion["camera"]))))
    j3 = np.asarray(motion["joints3d"], np.float64) - shift[:, None]
    motion.update(trans=np.asarray(motion.pop("trans_tracked")), joints3d=j3.astype(np.float32),
                  joints2d=np.asarray(cam.project(j3.reshape(-1, 3))).reshape(len(j3), -1, 2).astype(np.float32))
    return motion


def score(seq_dir: Path, res_dir: Path) -> dict:
    gt = np.load(seq_dir / "gt.npz")
    motion, run = read_result(res_dir)
    raw = tracked_frames(motion)
    idx = np.asarray(raw["frame_index"], int)
    cam = PinholeCamera.from_dict(json.loads((seq_dir / "camera.json").read_text()))
    gt3 = np.asarray(gt["joints3d"], np.float64)[idx]
    gt2 = np.asarray(cam.project(gt3.reshape(-1, 3))).reshape(len(idx), -1, 2)
    refits = [e["frame"] for e in run.get("events", []) if e.get("event") == "re-initialised" and "frame" in e]
    out = {}
    for s in SETTINGS:
        mo = raw if s is None else depth_smoothed_motion(raw, s[0], s[1], breaks=refits)
        pr = np.asarray(mo["joints3d"], np.float64)
        out[_name(s)] = {"local_cm": 100 * float(m.local_procrustes_error(pr, gt3).mean()),
                         "global_cm": 100 * float(m.global_procrustes_error(pr, gt3).mean()),
                         "px2d": float(m.joint2d_error(np.asarray(mo["joints2d"], np.float64), gt2).mean())}
    return out


def _result_dir(run_dir: Path, names: list[str]) -> Path | None:
    for n in names:
        if (run_dir / n / "run.json").exists() or (run_dir / n / "motion.npz").exists():
            return run_dir / n
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", required=True, help="folder of run folders (each with sequence/gt.npz)")
    ap.add_argument("--result", default=None, help="the result folder inside each run folder "
                    "(default: the first of flowmocap, result)")
    ap.add_argument("--out", default=None, help="JSON output")
    args = ap.parse_args()
    names = [args.result] if args.result else ["flowmocap", "result"]
    rows = {}
    for d in sorted(p for p in Path(args.runs).iterdir() if (p / "sequence" / "gt.npz").exists()):
        res = _result_dir(d, names)
        if res is None:
            print(f"{d.name}: no finished result, skipped")
            continue
        rows[d.name] = score(d / "sequence", res)
    if not rows:
        raise SystemExit(f"no run folders with a result under {args.runs}")
    keys = [_name(s) for s in SETTINGS]
    summary = {k: {stat: {q: float(f([r[k][q] for r in rows.values()])) for q in ("local_cm", "global_cm", "px2d")}
                   for stat, f in (("median", np.median), ("mean", np.mean))} for k in keys}
    better = {k: int(sum(r[k]["global_cm"] < r["raw"]["global_cm"] - 0.05 for r in rows.values())) for k in keys}
    worse = {k: int(sum(r[k]["global_cm"] > r["raw"]["global_cm"] + 0.05 for r in rows.values())) for k in keys}
    print(f"{len(rows)} runs of {args.runs}\n")
    print("| setting | median local cm | median global cm | mean global cm | median 2D px | global better / worse |")
    print("|---|---:|---:|---:|---:|---:|")
    for k in keys:
        s = summary[k]
        print(f"| {k} | {s['median']['local_cm']:.2f} | {s['median']['global_cm']:.2f} | {s['mean']['global_cm']:.2f} "
              f"| {s['median']['px2d']:.2f} | {better[k]} / {worse[k]} |")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"runs": args.runs, "settings": keys, "summary": summary,
                                              "better": better, "worse": worse, "per_run": rows}, indent=1))
        print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
