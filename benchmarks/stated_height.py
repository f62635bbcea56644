"""What a stated height (`flowmocap track --height`) buys: bodies of known size, tracked as a user's video.

One camera leaves a body's absolute size open, so every length in metres is the fit's guess.
This script renders four CMU clips (the `cmu_mb` / `cmu_daz` collection of
`../shared/data/mocap/prior/`, 90 frames at 60 fps, 640x480) with bodies made 1.55-1.90 m tall
(:func:`flowmocap.body.stature.with_stature` of a random shape), tracks each as a user's video
(automatic masks, the detector's start, the `video` profile; the rendered camera given) once
without and once with `--height` set to the body's true stature, and scores both against the
truth:

- stature: the fitted body's (`run.json` `body.stature_m`) against the true one, cm;
- bones: the mean absolute error of the 12 limb bones' lengths (upper arm, forearm, thigh,
  shin, collar, hip), cm;
- MPJPE: root-relative, no alignment (cm): the body's pose and size;
- root: the pelvis's absolute position against the truth's, no alignment (cm): where in the
  world the body is, which a wrong size puts at a wrong depth;
- local / global: the protocol's Procrustes errors (cm), which align the size away.

Usage: python benchmarks/stated_height.py --work DIR [--jobs 2] [--out benchmarks/results/stated_height]
Writes PREFIX.json and PREFIX.md. About 15 minutes here with 2 jobs.
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
DATA = ROOT.parent / "shared" / "data" / "mocap" / "prior"
#: (name, clip, start frame at 60 fps, azimuth degrees, stature m, shape seed)
CLIPS = (
    ("walk", "cmu_mb/02_01.bvh", 70, 70.0, 1.90, 1),
    ("jump", "cmu_daz/13_11.bvh", 60, 30.0, 1.55, 2),
    ("dance", "cmu_daz/61_05.bvh", 60, 120.0, 1.85, 3),
    ("balance", "cmu_mb/02_04.bvh", 60, 200.0, 1.58, 4),
)
BONES = (("left_shoulder", "left_elbow"), ("right_shoulder", "right_elbow"), ("left_elbow", "left_wrist"),
         ("right_elbow", "right_wrist"), ("left_hip", "left_knee"), ("right_hip", "right_knee"),
         ("left_knee", "left_ankle"), ("right_knee", "right_ankle"), ("neck", "left_shoulder"),
         ("neck", "right_shoulder"), ("pelvis", "left_hip"), ("pelvis", "right_hip"))


def make(work: Path) -> list[tuple[str, Path, float]]:
    """Render the clips (once) and return ``(name, sequence folder, true stature)``."""
    import torch

    from flowmocap.body import load_body_model
    from flowmocap.body.stature import with_stature
    from flowmocap.synth import synthesize

    model = load_body_model("default", dtype=torch.float64)
    seqs = []
    for name, clip, start, azimuth, height, seed in CLIPS:
        seq = work / f"{name}_{round(height * 100)}"
        if not (seq / "gt.npz").exists():
            betas = with_stature(model, torch.as_tensor(np.random.default_rng(seed).normal(size=10) * 0.5), height)
            synthesize(str(DATA / clip), seq, fps=60, start=start, frames=90, size="640x480",
                       betas=",".join(f"{b:.4f}" for b in betas.numpy()), azimuth=azimuth, flow=False)
        seqs.append((name, seq, height))
    return seqs


def track(seq: Path, out: Path, height: float | None) -> None:
    if (out / "run.json").exists() and json.loads((out / "run.json").read_text()).get("status") == "finished":
        return
    cmd = [str(Path(sys.executable).parent / "flowmocap"), "track", str(seq), "--out", str(out), "--masks", "auto",
           "--profile", "video", "--quiet", "--force"] + (["--height", str(height)] if height else [])
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)


def score(seq: Path, res: Path, height: float) -> dict:
    from flowmocap.body.skeleton import JOINT_INDEX
    from flowmocap.eval.scoring import score_result
    from flowmocap.io.results import read_result

    s = score_result(res, seq)
    motion, run = read_result(res)
    idx = np.asarray(motion["frame_index"], int)
    pred = np.asarray(motion["joints3d"], np.float64)
    truth = np.asarray(np.load(seq / "gt.npz")["joints3d"], np.float64)[idx]
    bone = lambda j, a, b: np.linalg.norm(j[:, JOINT_INDEX[a]] - j[:, JOINT_INDEX[b]], axis=-1).mean()  # noqa: E731
    bones = np.mean([abs(bone(pred, a, b) - bone(truth, a, b)) for a, b in BONES])
    return {"stature_cm": 100 * (run["body"]["stature_m"] - height), "bones_cm": 100 * bones,
            "mpjpe_cm": s["mpjpe_cm"], "root_cm": 100 * float(np.linalg.norm(pred[:, 0] - truth[:, 0], axis=-1).mean()),
            "local_cm": s["local_cm"], "global_cm": s["global_cm"]}


KEYS = ("stature_cm", "bones_cm", "mpjpe_cm", "root_cm", "local_cm", "global_cm")


def markdown(rows: list[dict]) -> str:
    lines = ["| clip | true stature m | variant | " + " | ".join(KEYS) + " |", "|---|---:|---|" + "---:|" * len(KEYS)]
    for r in rows:
        for v in ("own", "given"):
            lines.append(f"| {r['clip']} | {r['height']:.2f} | {v} | "
                         + " | ".join(f"{r[v][k]:+.1f}" if k == "stature_cm" else f"{r[v][k]:.1f}" for k in KEYS) + " |")
    for v in ("own", "given"):
        lines.append(f"| **mean** | | {v} | "
                     + " | ".join(f"{np.mean([abs(r[v][k]) if k == 'stature_cm' else r[v][k] for r in rows]):.1f}"
                                  for k in KEYS) + " |")
    lines.append("")
    lines.append("stature_cm: signed in the rows, absolute in the means.")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "stated_height"))
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    seqs = make(args.work)
    todo = [(seq, args.work / f"res_{v}" / seq.name, h if v == "given" else None) for _, seq, h in seqs
            for v in ("own", "given")]
    with ThreadPoolExecutor(args.jobs) as pool:
        list(pool.map(lambda t: track(*t), todo))
    rows = [{"clip": name, "height": h, **{v: score(seq, args.work / f"res_{v}" / seq.name, h) for v in ("own", "given")}}
            for name, seq, h in seqs]
    text = markdown(rows)
    print(text)
    Path(args.out + ".json").write_text(json.dumps(rows, indent=1))
    Path(args.out + ".md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
