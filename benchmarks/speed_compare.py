"""Speed side by side (issue 19): two checkouts of flowmocap, the same clips, one run.

Each clip is tracked by both checkouts in turn (old first on even seeds, new first on
odd ones, so that a change in the machine's load hits both), each with its own
benchmark script (``benchmarks/track.py`` for the CMU 35_01 protocol at 640x480, 60 fps,
``benchmarks/real_video.py --only CLIP`` for the real clips) and its own source tree
(``PYTHONPATH=CHECKOUT/src``). The synthetic sequences are made once and shared.

Reported per clip: the CMU protocol's median seconds per tracked frame (the tracker's
own timing, observed flow included) with its local / global error, and for the real
clips the mean seconds per tracked frame of the whole ``flowmocap track`` command
(detection, masks, initialisation, refits and start-up included) with the number of
re-initialisations; then the medians over the CMU seeds and the new/old ratios. Prints a
table and writes JSON.

Usage: python benchmarks/speed_compare.py --old CHECKOUT [--new CHECKOUT] [--seeds 0,1,2]
       [--real davis,walk] [--old-config JSON] [--new-config JSON] [--new-fast] [--work DIR]
       [--out benchmarks/results/speed_compare.json]

``--old-config`` / ``--new-config``: tracker settings (a JSON file, as ``flowmocap track
--config``) for that side's runs, e.g. the same checkout twice with and without the
``--fast`` settings.

``CHECKOUT`` is a folder holding ``src/flowmocap`` and ``benchmarks/``, e.g. a git
worktree of an older commit (``git worktree add /tmp/old COMMIT``). Needs the shared data
folder (``../shared/data``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(checkout: Path, args: list[str], log: Path, check: bool = True) -> None:
    env = dict(os.environ, PYTHONPATH=str(checkout / "src"))
    log.parent.mkdir(parents=True, exist_ok=True)  # --seeds '' (real clips only) makes no CMU folder first
    with open(log, "w") as f:
        subprocess.run([sys.executable, *args], cwd=checkout, env=env, check=check, stdout=f, stderr=subprocess.STDOUT)


def _commit(checkout: Path) -> str:
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                          cwd=checkout).stdout.strip()


def _config(config: str | None) -> list[str]:
    return ["--config", str(Path(config).resolve())] if config else []


def cmu(checkout: Path, name: str, seed: int, work: Path, config: str | None = None) -> dict:
    folder = work / name / f"seq_s{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    shared = work / "sequences" / f"seq_s{seed}"
    link = folder / "sequence"
    if (shared / "gt.npz").exists() and not link.exists():
        link.symlink_to(shared.resolve())
    out = work / name / f"cmu_s{seed}.json"
    _run(checkout, ["benchmarks/track.py", "--seed", str(seed), "--work", str(folder), "--out", str(out),
                    *_config(config)],
         work / name / f"cmu_s{seed}.log")
    r = json.loads(out.read_text())
    if not (shared / "gt.npz").exists():  # the first run made it: share it with the other checkout
        shared.parent.mkdir(parents=True, exist_ok=True)
        (folder / "sequence").rename(shared)
        link.symlink_to(shared.resolve())
    return {"s_per_frame_median": r["s_per_frame_median"], "local_cm": r["local_cm"], "global_cm": r["global_cm"]}


def real(checkout: Path, name: str, clip: str, work: Path, config: str | None = None, fast: bool = False) -> dict:
    out = work / name / f"real_{clip}.json"
    _run(checkout, ["benchmarks/real_video.py", "--only", clip, "--work", str(work / name / "real"), "--out", str(out),
                    *_config(config), *(["--fast"] if fast else [])],
         work / name / f"real_{clip}.log")
    r = json.loads(out.read_text())["results"][0]
    return {"clip": r["clip"], "tracked_frames": r["tracked_frames"], "seconds": r["seconds"],
            "s_per_frame_mean": r["seconds"] / max(r["tracked_frames"], 1),
            "reinitialisations": len(r["reinitialisations"]),
            "body_iou_mean": r.get("body_iou_mean", r.get("body_iou_vs_auto_mask_mean"))}


def warm_up(checkout: Path, folder: Path) -> float:
    """Track a few frames of a small synthetic clip with the checkout, untimed, so that its
    Numba kernels are compiled and cached (in its ``__pycache__``) before the timed runs: a
    fresh checkout compiles them on its first run, about 25 s, which would count against
    whichever side runs first. Returns the seconds it took."""
    t = time.perf_counter()
    seq = folder / "seq"
    if not (seq / "frames").is_dir():
        _run(checkout, ["-m", "flowmocap.cli", "synth", "builtin:walk", "--out", str(seq), "--num-frames", "6",
                        "--size", "320x240", "--no-flow"], folder / "synth.log")
    out = folder / "out"
    _run(checkout, ["-m", "flowmocap.cli", "track", str(seq), "--out", str(out), "--quiet", "--force"], folder / "track.log")
    _run(checkout, ["-m", "flowmocap.cli", "track", str(seq / "frames"), "--out", str(folder / "auto"), "--quiet",
                    "--force"], folder / "auto.log", check=False)  # automatic masks: the video profile's kernels
    return time.perf_counter() - t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", required=True, help="the checkout to compare against (holds src/ and benchmarks/)")
    ap.add_argument("--new", default=str(ROOT))
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--real", default="davis,walk", help="real clips (real_video.py --only); '' for none")
    ap.add_argument("--old-config", help="tracker settings JSON for the old side's runs")
    ap.add_argument("--new-config", help="tracker settings JSON for the new side's runs")
    ap.add_argument("--new-fast", action="store_true", help="the new side's real clips with flowmocap track --fast "
                    "(its detector settings too; a config cannot say those)")
    ap.add_argument("--work", default=str(ROOT / "benchmarks" / "work" / "speed_compare"))
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "speed_compare.json"))
    args = ap.parse_args()
    trees = {"old": Path(args.old).resolve(), "new": Path(args.new).resolve()}
    configs = {"old": args.old_config, "new": args.new_config}
    for name, tree in trees.items():
        if not (tree / "src" / "flowmocap").is_dir() or not (tree / "benchmarks" / "track.py").exists():
            print(f"{name} checkout {tree} holds no src/flowmocap or benchmarks/track.py", file=sys.stderr)
            return 2
    work = Path(args.work)
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    clips = [c for c in args.real.split(",") if c.strip()]
    rows: dict = {"cmu": {}, "real": {}}
    warm = {name: warm_up(tree, work / f"warm_{name}") for name, tree in trees.items()}
    t0 = time.perf_counter()
    for k, seed in enumerate(seeds):
        order = ("old", "new") if k % 2 == 0 else ("new", "old")
        rows["cmu"][seed] = {name: cmu(trees[name], name, seed, work, configs[name]) for name in order}
        print(f"CMU seed {seed}: " + ", ".join(f"{n} {r['s_per_frame_median']:.3f} s/frame" for n, r in
                                                rows["cmu"][seed].items()), flush=True)
    for k, clip in enumerate(clips):
        order = ("old", "new") if k % 2 == 0 else ("new", "old")
        rows["real"][clip] = {name: real(trees[name], name, clip, work, configs[name], name == "new" and args.new_fast)
                              for name in order}
        print(f"{clip}: " + ", ".join(f"{n} {r['s_per_frame_mean']:.3f} s/frame" for n, r in
                                      rows["real"][clip].items()), flush=True)

    print(f"\nold {trees['old']} ({_commit(trees['old'])}{', ' + configs['old'] if configs['old'] else ''}), "
          f"new {trees['new']} ({_commit(trees['new'])}{', ' + configs['new'] if configs['new'] else ''})\n")
    print(f"{'clip':<22}{'old s/fr':>10}{'new s/fr':>10}{'ratio':>8}{'old loc/glob cm':>17}{'new loc/glob cm':>17}")
    summary: dict = {}
    for seed, r in rows["cmu"].items():
        o, n = r["old"], r["new"]
        print(f"{'CMU 35_01 seed ' + str(seed):<22}{o['s_per_frame_median']:>10.3f}{n['s_per_frame_median']:>10.3f}"
              f"{n['s_per_frame_median'] / o['s_per_frame_median']:>8.2f}"
              f"{o['local_cm']:>9.2f} /{o['global_cm']:>5.2f}{n['local_cm']:>9.2f} /{n['global_cm']:>5.2f}")
    if rows["cmu"]:
        med = {name: {k: statistics.median(r[name][k] for r in rows["cmu"].values())
                      for k in ("s_per_frame_median", "local_cm", "global_cm")} for name in trees}
        summary["cmu_median"] = med
        summary["cmu_ratio"] = med["new"]["s_per_frame_median"] / med["old"]["s_per_frame_median"]
        print(f"{'CMU median':<22}{med['old']['s_per_frame_median']:>10.3f}{med['new']['s_per_frame_median']:>10.3f}"
              f"{summary['cmu_ratio']:>8.2f}{med['old']['local_cm']:>9.2f} /{med['old']['global_cm']:>5.2f}"
              f"{med['new']['local_cm']:>9.2f} /{med['new']['global_cm']:>5.2f}")
    print(f"\n{'real clip (mean, all in)':<26}{'old s/fr':>10}{'new s/fr':>10}{'ratio':>8}{'old reinits':>13}"
          f"{'new reinits':>13}")
    for clip, r in rows["real"].items():
        o, n = r["old"], r["new"]
        print(f"{clip:<26}{o['s_per_frame_mean']:>10.3f}{n['s_per_frame_mean']:>10.3f}"
              f"{n['s_per_frame_mean'] / o['s_per_frame_mean']:>8.2f}{o['reinitialisations']:>13}"
              f"{n['reinitialisations']:>13}")
    if rows["real"]:
        mean = {name: statistics.mean(r[name]["s_per_frame_mean"] for r in rows["real"].values()) for name in trees}
        summary["real_mean"] = mean
        summary["real_ratio"] = mean["new"] / mean["old"]
        print(f"{'mean over the clips':<26}{mean['old']:>10.3f}{mean['new']:>10.3f}{summary['real_ratio']:>8.2f}")
    out = {"benchmark": "speed_compare",
           "old": {"path": str(trees["old"]), "commit": _commit(trees["old"]), "config": configs["old"]}, "warm_up_s": warm,
           "new": {"path": str(trees["new"]), "commit": _commit(trees["new"]), "config": configs["new"], "fast": bool(args.new_fast)},
           "seeds": seeds, "clips": clips,
           "rows": {"cmu": {str(k): v for k, v in rows["cmu"].items()}, "real": rows["real"]}, "summary": summary,
           "wall_s": time.perf_counter() - t0, "load_average_end": os.getloadavg()}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2))
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
