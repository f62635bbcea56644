"""The real3d benchmark tracked several times, to read a setting against the tracker's chance.

One tracking of ``flowmocap bench --suite real3d`` moves by about 3 mm of its 68-71 mm
when a weight changes in its last digits (docs/experiments.md, "The settings made with the
full network, tried again with the heavy one"): more than most settings would change it.
This script tracks the suite ``--draws`` times: draw 0 with the given settings, draw ``k``
with ``flow_weight`` times ``1 + 1e-6 k`` (k odd) or ``1 - 1e-6 k`` (k even), which changes
nothing but the tracking's chance. Each draw is a ``flowmocap bench --suite real3d`` folder
``OUT/drawK`` (``flowmocap.eval.real3d.run_real3d``); the later draws reuse draw 0's
reference and detections (copied), so each costs the tracking alone (about 10 minutes on
two cores). Finished draws are not tracked again.

Writes ``OUT/draws.json`` and ``OUT/draws.md``: per draw the mean per-frame PA-MPJPE of the
fit, at the detector's keypoints and of MediaPipe's own 3D (mm), their ratio, and the
person-views at or above MediaPipe's error; per person-view the mean over the draws and the
range; and the mean over the draws.

Usage: python benchmarks/real3d_draws.py OUT [--draws 3] [--config C.json] [--frames N]
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

METHODS = (("flowmocap", "ours"), ("flowmocap_kp", "ours at keypoints"), ("detector3d", "MediaPipe"))


def draw_config(config: dict | None, k: int) -> dict:
    """The settings of draw ``k``: ``config`` for draw 0; for later draws ``flow_weight``
    (``config``'s, else the default 1) times ``1 + 1e-6 k`` (odd ``k``) or ``1 - 1e-6 k``
    (even ``k``)."""
    from flowmocap.fit.config import TrackerConfig

    cfg = dict(config or {})
    if k:
        base = float(cfg.get("flow_weight", TrackerConfig().flow_weight))
        cfg["flow_weight"] = base * (1.0 + (1e-6 * k if k % 2 else -1e-6 * k))
    return cfg


def summarise(results: list[dict]) -> dict:
    """The draws' results (each a ``real3d.json``) summed up: ``draws`` (per draw the mean
    per-frame mm of each method, ``ratio`` ours / MediaPipe, ``at_or_above`` the
    person-views whose ratio is 1 or more), ``views`` (per person-view the mean, lowest and
    highest per-frame mm of ours over the draws that scored it, MediaPipe's mean, and the
    number of draws at or above MediaPipe), and ``mean`` (each method's mean over the draws
    and the ratio of those means)."""
    draws, views = [], {}
    for res in results:
        rows = [r for r in res["rows"] if not r.get("skipped_run") and not r.get("failed") and r.get("flowmocap")]
        d = {}
        for m, _ in METHODS:
            vals = [r[m]["per_frame_mm"] for r in rows if r.get(m)]
            d[m] = float(np.mean(vals)) if vals else None
        d["ratio"] = d["flowmocap"] / d["detector3d"] if d["flowmocap"] and d["detector3d"] else None
        d["at_or_above"] = []
        for r in rows:
            name = f"{r['person']}@{r['view']}"
            ours, det = r["flowmocap"]["per_frame_mm"], r["detector3d"]["per_frame_mm"]
            v = views.setdefault(name, {"ours": [], "detector3d": []})
            v["ours"].append(ours)
            v["detector3d"].append(det)
            if ours >= det:
                d["at_or_above"].append(name)
        draws.append(d)
    mean = {m: (float(np.mean([d[m] for d in draws if d[m] is not None]))
                if any(d[m] is not None for d in draws) else None) for m, _ in METHODS}
    mean["ratio"] = mean["flowmocap"] / mean["detector3d"] if mean["flowmocap"] and mean["detector3d"] else None
    return {"draws": draws, "mean": mean,
            "views": {n: {"mean": float(np.mean(v["ours"])), "low": float(min(v["ours"])), "high": float(max(v["ours"])),
                          "detector3d": float(np.mean(v["detector3d"])),
                          "draws_at_or_above": int(sum(o >= d for o, d in zip(v["ours"], v["detector3d"])))}
                      for n, v in sorted(views.items())}}


def format_summary(summary: dict) -> str:
    """:func:`summarise`'s result as Markdown."""
    fmt = lambda v: "--" if v is None else f"{v:.2f}"  # noqa: E731
    lines = ["# real3d over several trackings", "",
             "| draw | " + " | ".join(f"{label} per frame mm" for _, label in METHODS)
             + " | ours / MediaPipe | person-views at or above MediaPipe |", "|---|---:|---:|---:|---:|---|"]
    for k, d in enumerate(summary["draws"]):
        lines.append(f"| {k} | " + " | ".join(fmt(d[m]) for m, _ in METHODS)
                     + f" | {fmt(d['ratio'])} | {', '.join(d['at_or_above']) or 'none'} |")
    m = summary["mean"]
    lines.append("| **mean** | " + " | ".join(fmt(m[x]) for x, _ in METHODS) + f" | {fmt(m['ratio'])} | |")
    lines += ["", "| person-view | ours mean mm | lowest | highest | MediaPipe mm | draws at or above it |",
              "|---|---:|---:|---:|---:|---:|"]
    for n, v in summary["views"].items():
        lines.append(f"| {n} | {v['mean']:.1f} | {v['low']:.1f} | {v['high']:.1f} | {v['detector3d']:.1f} "
                     f"| {v['draws_at_or_above']} |")
    return "\n".join(lines)


def _reuse(src: Path, dst: Path) -> None:
    """Copy draw 0's reference and each run's detections into a later draw's folder."""
    if (src / "reference").is_dir() and not (dst / "reference").exists():
        shutil.copytree(src / "reference", dst / "reference")
    for run in sorted((src / "runs").glob("*")) if (src / "runs").is_dir() else []:
        det = run / "detections"
        if det.is_dir() and not (dst / "runs" / run.name / "detections").exists():
            shutil.copytree(det, dst / "runs" / run.name / "detections")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--draws", type=int, default=3)
    ap.add_argument("--config", type=Path, help="a JSON file of TrackerConfig settings (as bench --config)")
    ap.add_argument("--frames", type=int, help="track and score only the first N frames of each video")
    a = ap.parse_args(argv)
    if a.draws < 1:
        ap.error("--draws must be 1 or more")
    from flowmocap.eval.real3d import run_real3d

    config = json.loads(a.config.read_text()) if a.config else None
    results = []
    for k in range(a.draws):
        d = a.out / f"draw{k}"
        if k:
            _reuse(a.out / "draw0", d)
        cfg = draw_config(config, k)
        print(f"draw {k}: settings {cfg or 'the defaults'} -> {d}", flush=True)
        results.append(run_real3d(d, frames=a.frames, tracker_config=cfg or None, log=print))
    summary = summarise(results)
    summary["settings"] = {"draws": a.draws, "config": config or {}, "frames": a.frames,
                           "draw_configs": [draw_config(config, k) for k in range(a.draws)]}
    (a.out / "draws.json").write_text(json.dumps(summary, indent=2))
    text = format_summary(summary)
    (a.out / "draws.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
