"""Offline smoothing (flowmocap.fit.smooth) on finished CMU protocol runs: before and after.

For every run folder ``RUNS/*/`` (a ``sequence/`` with ``gt.npz`` and a result in
``new/result``, ``result`` or ``flowmocap``: the layouts of benchmarks/track_seeds.py and
of ``flowmocap bench --suite diverse``), the result's motion is smoothed with each setting, the
joints are recomputed with the body model, and the 3D metrics of
``flowmocap.eval.scoring.score_result`` (the same functions of ``flowmocap.eval.metrics``:
local / global Procrustes error, MPJPE in cm, acceleration error in mm/frame^2) are taken
against the ground truth. The raw row is checked against ``score_result`` itself.

    python benchmarks/smooth_cmu.py --runs /work/bench-runs/seeds \
        --out benchmarks/results/smooth_cmu.json
    python benchmarks/smooth_cmu.py --runs /work/bench-runs/diverse-new \
        --out benchmarks/results/smooth_diverse.json

Prints a Markdown table (mean and median over the runs) and writes the JSON.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from flowmocap.body import load_body_model
from flowmocap.eval import metrics as m
from flowmocap.eval.scoring import score_result
from flowmocap.fit.smooth import smooth_motion, window_frames
from flowmocap.io.results import read_result
from flowmocap.io.sequence import load_sequence

SETTINGS = [None, (0.1, 2), (0.2, 2), (0.3, 2), (0.2, 1), (0.4, 3)]  # 0.3 s / 2: the default


def _joints(model, poses, trans, betas) -> np.ndarray:
    with torch.no_grad():
        out = model(betas=torch.as_tensor(betas[None], dtype=torch.float64),
                    pose=torch.as_tensor(poses, dtype=torch.float64), trans=torch.as_tensor(trans, dtype=torch.float64))
    return out.joints.numpy()


def _scores(pred, ref) -> dict:
    return {"local_cm": 100 * float(m.local_procrustes_error(pred, ref).mean()),
            "global_cm": 100 * float(m.global_procrustes_error(pred, ref).mean()),
            "mpjpe_cm": 100 * float(m.mpjpe(pred, ref).mean()),
            "accel_mm": 1000 * float(m.acceleration_error(pred, ref).mean())}


def run(runs: Path) -> dict:
    rows: dict[str, list] = {}
    seeds = []
    for seq_dir in sorted(p for p in runs.iterdir() if p.is_dir()):
        result = next((p for p in (seq_dir / "new" / "result", seq_dir / "result", seq_dir / "flowmocap")
                       if (p / "motion.npz").is_file()), None)
        if result is None or not (seq_dir / "sequence" / "gt.npz").is_file():
            continue
        motion, _ = read_result(result)
        seq = load_sequence(seq_dir / "sequence")
        idx = np.asarray(motion["frame_index"], int)
        ref = np.asarray(seq.gt["joints3d"], np.float64)[idx]
        fps = float(motion["fps"])
        model = load_body_model("default", gender=str(motion["gender"]), dtype=torch.float64)
        poses = np.asarray(motion["poses"], np.float64)
        trans = np.asarray(motion["trans"], np.float64)
        betas = np.asarray(motion["betas"], np.float64)
        official = score_result(result, seq)
        seeds.append({"run": seq_dir.name, "frames": int(idx.size), "fps": fps,
                      "score_result": {k: official[k] for k in ("local_cm", "global_cm", "mpjpe_cm", "accel_mm")}})
        for setting in SETTINGS:
            if setting is None:
                name, p, t = "raw", poses, trans
            else:
                w, order = setting
                name = f"sg {w:g} s / order {order} ({window_frames(w, fps, order)} frames)"
                p, t = smooth_motion(poses, trans, fps, window_s=w, order=order)
            s = _scores(_joints(model, p, t, betas), ref)
            rows.setdefault(name, []).append({"run": seq_dir.name, **s})
    table = {}
    for name, rs in rows.items():
        table[name] = {k: {"mean": float(np.mean([r[k] for r in rs])), "median": float(np.median([r[k] for r in rs]))}
                       for k in ("local_cm", "global_cm", "mpjpe_cm", "accel_mm")}
    return {"runs": seeds, "rows": rows, "table": table}


def markdown(res: dict) -> str:
    lines = ["| smoothing | local cm | global cm | MPJPE cm | accel mm/frame^2 |", "|---|---|---|---|---|"]
    for name, t in res["table"].items():
        cell = lambda k: f"{t[k]['mean']:.2f} ({t[k]['median']:.2f})"  # noqa: E731
        lines.append(f"| {name} | {cell('local_cm')} | {cell('global_cm')} | {cell('mpjpe_cm')} | {cell('accel_mm')} |")
    lines.append(f"\nmean (median) over {len(res['runs'])} runs")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", default="/work/bench-runs/seeds", help="folder of run folders")
    ap.add_argument("--out", default="benchmarks/results/smooth_cmu.json", help="JSON output")
    args = ap.parse_args()
    res = run(Path(args.runs))
    for r in res["runs"]:
        raw = next(x for x in res["rows"]["raw"] if x["run"] == r["run"])
        for k, v in r["score_result"].items():  # the raw row is score_result's own number
            assert v is None or abs(v - raw[k]) < 1e-3 * max(1.0, abs(v)), (r["run"], k, v, raw[k])
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=1))
    print(markdown(res))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
