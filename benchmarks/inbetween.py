"""How a run of frames without the person is filled: held, the plain in-between, or a gait's
cycle carried through (:func:`flowmocap.fit.smooth.inbetween_unseen`).

A stretch of ``--gaps`` seconds is cut out of a motion (the tracker holds the last seen pose
there), filled each way, and compared with the motion that was cut out: the mean distance of
the 24 joints from the truth, root-relative (cm), over the cut frames. Motions:

- the built-in walk and the diverse suite's held-out mocap clips (``mocap/prior`` test split),
  true, and with every joint's rotation off by a random 5 degrees in every frame (a fit's
  noise, ``--noise``);
- the motions of tracked results (``--results DIR ...``): the fit's own frames are the
  reference there.

The cut starts at the middle of the motion, or later so that 2.2 s are seen before it, or
earlier so that it ends 5 frames before the end (``late``); or 0.5 s into the motion
(``early``: too little before it for a gait's period, so a cycle can only come from the frames
after it); motions too short are skipped.

Usage::

    python benchmarks/inbetween.py [--gaps 0.7 1.5] [--noise 0 5] [--where late early]
        [--results DIR ...] [--out benchmarks/results/inbetween]

Prints a table and writes ``OUT.md`` / ``OUT.json``; about a minute.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

FPS = 30.0


def cut_and_fill(body, poses: np.ndarray, trans: np.ndarray, fps: float, gap_s: float,
                 where: str = "late") -> dict | None:
    import torch

    from flowmocap.fit.smooth import inbetween_unseen
    from flowmocap.geometry.camera import PinholeCamera

    T, n = len(poses), int(round(gap_s * fps))
    first = min(max(T // 2, int(2.2 * fps)), T - n - 5) if where == "late" else int(0.5 * fps)
    last = first + n - 1
    if (where == "late" and first < int(1.5 * fps)) or n < 1 or last + 5 >= T:
        return None

    def joints(p, t):
        with torch.no_grad():
            return body(pose=torch.as_tensor(p), trans=torch.as_tensor(t)).joints.numpy()

    truth = joints(poses, trans)[first:last + 1]
    held, tr = poses.copy(), trans.copy()
    held[first:last + 1], tr[first:last + 1] = poses[first - 1], trans[first - 1]
    motion = {"poses": held, "trans": tr, "betas": np.zeros(10), "joints3d": np.zeros((T, 24, 3)),
              "joints2d": np.zeros((T, 24, 2)), "camera": np.array(json.dumps(PinholeCamera.from_focal(640, 480, 576.0)
                                                                               .to_dict())),
              "frame_index": np.arange(T)}

    def error(j):
        return float(np.linalg.norm((j - j[:, :1]) - (truth - truth[:, :1]), axis=-1).mean() * 100)

    row = {"where": where, "frames": [first, last], "held_cm": error(joints(held, tr)[first:last + 1])}
    for name, cycles in (("inbetween_cm", False), ("cycle_cm", True)):
        got, info = inbetween_unseen(motion, body, [(first, last)], fps=fps, cycles=cycles)
        row[name] = error(got["joints3d"][first:last + 1])
        if cycles:
            row["period_frames"] = info["cycles"][0][2] if info["cycles"] else None
            row["cycle_seen"] = info["cycles"][0][3] if info["cycles"] else None
            # the frames the walk lasted where it was taken to stop in the cut
            row["walk_stops_after"] = info["stops"][0][2] if info["stops"] else None
    return row


def _noisy(poses: np.ndarray, deg: float, seed: int = 0) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    if not deg:
        return poses
    T = len(poses)
    rng = np.random.default_rng(seed)
    off = Rotation.from_rotvec(rng.normal(0.0, np.radians(deg) / np.sqrt(3), (T * 24, 3)))
    return (off * Rotation.from_rotvec(poses.reshape(-1, 3))).as_rotvec().reshape(T, 72)


def main(argv=None) -> int:
    import torch

    from flowmocap.body import load_body_model
    from flowmocap.eval.bench import DIVERSE_CLIPS, PRIOR_DATA, most_active_window
    from flowmocap.io.builtin_walk import builtin_walk
    from flowmocap.io.motion_source import load_motion

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gaps", type=float, nargs="+", default=[0.7, 1.5])
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 5.0])
    ap.add_argument("--where", nargs="+", choices=["late", "early"], default=["late", "early"])
    ap.add_argument("--results", nargs="*", default=[])
    ap.add_argument("--out", default="benchmarks/results/inbetween")
    args = ap.parse_args(argv)
    body = load_body_model("default", dtype=torch.float64)
    motions = [("builtin walk", "walk", builtin_walk(body, fps=FPS, frames=180))]
    if (PRIOR_DATA / "index.csv").exists():
        for rel, kind in DIVERSE_CLIPS:
            m = load_motion(str(PRIOR_DATA / rel), body, fps=FPS)
            start = most_active_window(PRIOR_DATA / rel, 180, FPS) if m.num_frames > 180 else 0
            motions.append((rel, kind, m.slice(start, min(m.num_frames, start + 180))))
    else:
        print(f"{PRIOR_DATA} is missing: the built-in walk only", file=sys.stderr)
    rows = []
    for where in args.where:
        for noise in args.noise:
            for gap in args.gaps:
                for name, kind, m in motions:
                    r = cut_and_fill(body, _noisy(np.asarray(m.poses, np.float64), noise),
                                     np.asarray(m.trans, np.float64), FPS, gap, where)
                    if r is not None:
                        rows.append({"motion": name, "kind": kind, "noise_deg": noise, "gap_s": gap, **r})
    for res in args.results:
        data = np.load(Path(res) / "motion.npz")
        fps = float(data["fps"]) if "fps" in data else FPS
        for where in args.where:
            for gap in args.gaps:
                r = cut_and_fill(body, np.asarray(data["poses"], np.float64), np.asarray(data["trans"], np.float64),
                                 fps, gap, where)
                if r is not None:
                    rows.append({"motion": str(res), "kind": "tracked", "noise_deg": None, "gap_s": gap, **r})
    lines = ["| motion | kind | cut | noise deg | gap s | held cm | in-between cm | cycle carried cm | period (frames), "
             "seen |", "|---|---|---|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        noise = "" if r["noise_deg"] is None else f"{r['noise_deg']:g}"
        seen = f"{r['period_frames']}, {r['cycle_seen']}" if r["period_frames"] else ""
        if r.get("walk_stops_after") is not None:
            seen += f", stops after {r['walk_stops_after']} frames"
        lines.append(f"| {r['motion']} | {r['kind']} | {r['where']} | {noise} | {r['gap_s']:g} | {r['held_cm']:.1f} | "
                     f"{r['inbetween_cm']:.1f} | {r['cycle_cm']:.1f} | {seen} |")
    summary = ""
    for where in args.where:
        mine = [r for r in rows if r["where"] == where]
        cyc = [r for r in mine if r["period_frames"]]
        other = [r for r in mine if not r["period_frames"]]
        summary += (f"\n{where.capitalize()} cuts: the cycle carried through {len(cyc)} of {len(mine)} "
                    f"({sum(r['cycle_seen'] == 'after' for r in cyc)} seen after the cut): there the in-between's mean "
                    f"{np.mean([r['inbetween_cm'] for r in cyc]) if cyc else float('nan'):.1f} cm, the cycle's "
                    f"{np.mean([r['cycle_cm'] for r in cyc]) if cyc else float('nan'):.1f}; in the other "
                    f"{len(other)} the two are the same. The walk taken to stop in the cut: "
                    f"{sum(r.get('walk_stops_after') is not None for r in cyc)}.\n")
    text = "\n".join(lines) + "\n" + summary
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(f"# Unseen runs filled: `python benchmarks/inbetween.py`\n\n{FPS:g} fps.\n\n{text}")
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
