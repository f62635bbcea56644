"""The issue-5 tracking protocol over several seeds (and settings), run side by side.

Each (setting, seed) pair is one ``benchmarks/track.py`` process (its own synthetic body,
noise and result folder); ``--jobs`` of them run at once. Prints local / global error in
cm and s/frame per seed, the median over seeds and how many seeds meet the targets
(5.5 / 7.6 cm), and writes JSON. Seconds per frame are only comparable between runs with
the same ``--jobs`` on the same machine: with more jobs than cores they grow.

Usage: python benchmarks/track_seeds.py [--seeds 0,1,2,3] [--jobs 2]
       [--config NAME=cfg.json ...] [--work DIR] [--out benchmarks/results/track_seeds.json]
       [--motion PATH] [--num-frames 130]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CMU = ROOT.parent / "shared" / "data" / "mocap" / "cmu" / "35_01.amc"
TARGETS = {"local_cm": 5.5, "global_cm": 7.6}


def run_one(name: str, config: str | None, seed: int, args, work: Path) -> dict:
    out = work / f"{name}_s{seed}.json"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "track.py"), "--seed", str(seed), "--motion", args.motion,
           "--num-frames", str(args.num_frames), "--work", str(work / f"seq_s{seed}" / name), "--out", str(out)]
    if config:
        cmd += ["--config", config]
    # the synthetic sequence depends on the seed only (made by synth_once): every setting links to it
    link = work / f"seq_s{seed}" / name / "sequence"
    link.parent.mkdir(parents=True, exist_ok=True)
    if not link.exists():
        link.symlink_to((work / f"seq_s{seed}" / "sequence").resolve())
    log = work / f"{name}_s{seed}.log"
    with log.open("w") as fh:
        p = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT)
    if p.returncode != 0 or not out.exists():
        return {"setting": name, "seed": seed, "error": f"exit {p.returncode}, see {log.name}"}
    r = json.loads(out.read_text())
    return {"setting": name, "seed": seed, "local_cm": r["local_cm"], "global_cm": r["global_cm"],
            "s_per_frame": r["s_per_frame_median"], "events": len(r["events"]),
            "local_cm_per_frame": r["local_cm_per_frame"], "joints": r.get("joints")}


def split_means(rows: list[dict]) -> dict:
    """Mean over seeds and the 13 joints of the image-plane and depth errors (cm), and the
    per-joint means (``joints``), from the runs' ``joints`` tables; {} when they lack them."""
    tables = [r["joints"] for r in rows if r.get("joints")]
    if not tables:
        return {}
    per_joint = {j: {k: float(np.mean([t[j][k] for t in tables])) for k in tables[0][j]} for j in tables[0]}
    return {"plane_cm": float(np.mean([e["plane_cm"] for e in per_joint.values()])),
            "depth_cm": float(np.mean([e["depth_cm"] for e in per_joint.values()])), "joints": per_joint}


def synth_once(seed: int, args, work: Path) -> None:
    """Synthesise each seed's sequence once (all settings then share it)."""
    from flowmocap.synth import synthesize

    seq = work / f"seq_s{seed}" / "sequence"
    if not (seq / "gt.npz").exists():
        synthesize(args.motion, seq, fps=60.0, frames=args.num_frames, size="640x480", betas="random", seed=seed,
                   azimuth=60.0, flow=False)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2,3")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--config", action="append", default=[],
                    help="NAME=cfg.json (repeatable); the defaults run as 'default' unless --no-default")
    ap.add_argument("--no-default", action="store_true")
    ap.add_argument("--motion", default=str(CMU))
    ap.add_argument("--num-frames", type=int, default=130)
    ap.add_argument("--work", default=str(ROOT / "benchmarks" / "work" / "seeds"))
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "track_seeds.json"))
    args = ap.parse_args()
    if not Path(args.motion).exists():
        print(f"skipped: {args.motion} not found (../shared/data is absent)")
        return 0
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    settings = [] if args.no_default else [("default", None)]
    for c in args.config:
        name, _, path = c.partition("=")
        if not path:
            ap.error(f"--config wants NAME=PATH; got {c!r}")
        settings.append((name, str(Path(path).resolve())))
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        list(pool.map(lambda s: synth_once(s, args, work), seeds))
        jobs = [(n, c, s) for n, c in settings for s in seeds]
        rows = list(pool.map(lambda j: run_one(*j, args, work), jobs))

    print(f"{'setting':<24}{'seed':>5}{'local cm':>10}{'global cm':>11}{'s/frame':>9}{'events':>8}")
    summary = {}
    for name, _ in settings:
        mine = [r for r in rows if r["setting"] == name]
        for r in mine:
            if "error" in r:
                print(f"{name:<24}{r['seed']:>5}  {r['error']}")
            else:
                print(f"{name:<24}{r['seed']:>5}{r['local_cm']:>10.2f}{r['global_cm']:>11.2f}"
                      f"{r['s_per_frame']:>9.2f}{r['events']:>8}")
        ok = [r for r in mine if "error" not in r]
        if ok:
            med = {k: float(np.median([r[k] for r in ok])) for k in ("local_cm", "global_cm", "s_per_frame")}
            met = sum(r["local_cm"] <= TARGETS["local_cm"] and r["global_cm"] <= TARGETS["global_cm"] for r in ok)
            summary[name] = {**med, "seeds_meeting_targets": met, "seeds": len(ok), **split_means(ok)}
            print(f"{name:<24}{'med':>5}{med['local_cm']:>10.2f}{med['global_cm']:>11.2f}{med['s_per_frame']:>9.2f}"
                  f"   {met}/{len(ok)} seeds meet {TARGETS['local_cm']}/{TARGETS['global_cm']} cm")
            if "plane_cm" in summary[name]:
                print(f"{'':<29}root-relative error, mean over joints and seeds: {summary[name]['plane_cm']:.1f} cm "
                      f"across the view, {summary[name]['depth_cm']:.1f} cm along it (depth)")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"benchmark": "track_seeds", "jobs": args.jobs, "seeds": seeds,
                                          "settings": dict(settings), "summary": summary, "runs": rows},
                                         indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
