"""Where the global error of a synthetic bench run comes from (issue 18).

For every finished sequence of a ``flowmocap bench`` folder (``NAME/sequence/gt.npz``,
``NAME/flowmocap/``), in the camera's axes:

- ``local_cm`` / ``global_cm``: the bench's metrics (13 joints, similarity per frame / per
  sequence);
- ``global_true_depth_cm``: the global error once each frame's fit is scaled about the
  camera centre until its root (pelvis) is at its true depth (the image of the fit is
  unchanged, its 3D size scales with the depth: what a perfect depth would give for the
  fitted image);
- ``global_true_root_cm``: ... once the root is moved to its true position (depth and
  across the view);
- ``global_true_orientation_cm``: ... once each frame's torso is turned onto the true one
  about the root (the fit's global orientation corrected, nothing else);
- ``root_depth_bias_cm`` / ``root_depth_sd_cm``: the root's error along the ray, its mean
  and its spread over the frames (< 0: nearer than the truth); ``root_lateral_cm``: its
  mean error across the ray;
- ``bone_ratio``: the fitted body's limb and torso lengths over the true ones (the shape;
  a constant ratio costs no global error, the similarity absorbs it);
- ``depth_ratio_sd``: the spread over the frames of fitted over true root depth (what a
  constant scale cannot absorb); ``extent_depth_corr``: its correlation with the fitted
  over true 3D extent of the pose (per-frame similarity scale), i.e. how much of the
  depth error follows from the pose's 3D size;
- ``torso_orientation_deg``: median angle between fitted and true torso orientation.

Usage: python benchmarks/global_error.py BENCH_DIR [BENCH_DIR ...] [--names a,b] [--out PREFIX]
(writes PREFIX.json and PREFIX.md; default: print only).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from flowmocap.body.skeleton import EVAL_JOINTS, JOINT_INDEX
from flowmocap.eval import metrics as M
from flowmocap.geometry.procrustes import similarity_procrustes
from flowmocap.io.results import read_result

E = list(EVAL_JOINTS)
BONES = [("left_hip", "left_knee"), ("left_knee", "left_ankle"), ("right_hip", "right_knee"),
         ("right_knee", "right_ankle"), ("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"),
         ("right_shoulder", "right_elbow"), ("right_elbow", "right_wrist"), ("left_hip", "left_shoulder"),
         ("right_hip", "right_shoulder")]
TORSO = ("left_hip", "right_hip", "left_shoulder", "right_shoulder", "spine3", "pelvis")
KEYS = ("local_cm", "global_cm", "global_true_depth_cm", "global_true_root_cm", "global_true_orientation_cm",
        "root_depth_bias_cm", "root_depth_sd_cm", "root_lateral_cm", "bone_ratio", "depth_ratio_sd",
        "extent_depth_corr", "torso_orientation_deg")


def _glob(pred, gt) -> float:
    return 100 * float(M.global_procrustes_error(pred, gt).mean())


def camera_joints(seq_dir: Path, res_dir: Path) -> tuple:
    """``(gt, pred, gtz, motion, idx)``: the true and fitted joints ``(T, 24, 3)`` of the
    result's frames ``idx`` in the sequence camera's axes (metres), with the sequence's
    ``gt.npz`` and the result's motion arrays."""
    gtz = np.load(seq_dir / "gt.npz")
    cam = json.loads((seq_dir / "camera.json").read_text())
    R, t = np.asarray(cam["R"], np.float64), np.asarray(cam["t"], np.float64)
    motion, _ = read_result(res_dir)
    idx = np.asarray(motion["frame_index"], int)
    gt = np.asarray(gtz["joints3d"], np.float64)[idx] @ R.T + t
    pr = np.asarray(motion["joints3d"], np.float64) @ R.T + t
    return gt, pr, gtz, motion, idx


def decompose(seq_dir: Path, res_dir: Path) -> dict:
    """The quantities of the module docstring for one sequence and result."""
    gt, pr, _, _, idx = camera_joints(seq_dir, res_dir)
    p = JOINT_INDEX["pelvis"]
    pr_root, gt_root = pr[:, p], gt[:, p]
    ray = gt_root / np.linalg.norm(gt_root, axis=1, keepdims=True)
    err = pr_root - gt_root
    along = (err * ray).sum(1)
    lateral = np.linalg.norm(err - along[:, None] * ray, axis=1)
    depth_fix = pr * (gt_root[:, 2] / pr_root[:, 2])[:, None, None]  # about the camera centre: same image
    root_fix = pr - pr_root[:, None] + gt_root[:, None]
    tor = [JOINT_INDEX[n] for n in TORSO]
    _, _, rot, _ = similarity_procrustes(pr[:, tor] - pr_root[:, None], gt[:, tor] - gt_root[:, None])
    orient_fix = np.einsum("tij,tkj->tki", rot, pr - pr_root[:, None]) + pr_root[:, None]
    angle = np.degrees(np.arccos(np.clip((np.trace(rot, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    _, scale, _, _ = similarity_procrustes(pr[:, E], gt[:, E])
    extent = 1.0 / np.asarray(scale)
    bone = lambda J: np.mean([np.linalg.norm(J[:, JOINT_INDEX[a]] - J[:, JOINT_INDEX[b]], axis=-1)  # noqa: E731
                              for a, b in BONES], 0)
    zratio = pr_root[:, 2] / gt_root[:, 2]
    return {
        "frames": int(idx.size),
        "local_cm": 100 * float(M.local_procrustes_error(pr, gt).mean()), "global_cm": _glob(pr, gt),
        "global_true_depth_cm": _glob(depth_fix, gt), "global_true_root_cm": _glob(root_fix, gt),
        "global_true_orientation_cm": _glob(orient_fix, gt),
        "root_depth_bias_cm": 100 * float(along.mean()), "root_depth_sd_cm": 100 * float(along.std()),
        "root_lateral_cm": 100 * float(lateral.mean()),
        "bone_ratio": float((bone(pr) / bone(gt)).mean()),
        "depth_ratio_sd": float((zratio / zratio.mean()).std()),
        "extent_depth_corr": float(np.corrcoef(extent, zratio)[0, 1]),
        "torso_orientation_deg": float(np.median(angle)),
    }


def run(bench_dir: Path) -> dict:
    rows = {}
    for d in sorted(q for q in bench_dir.iterdir() if (q / "sequence" / "gt.npz").exists()):
        try:
            rows[d.name] = decompose(d / "sequence", d / "flowmocap")
        except Exception as e:  # an unfinished or missing result: say so, go on
            rows[d.name] = {"error": str(e)}
    ok = [r for r in rows.values() if "error" not in r]
    med = {k: float(np.median([r[k] for r in ok])) for k in KEYS} if ok else {}
    return {"bench": str(bench_dir), "sequences": rows, "median": med}


def table(results: list[dict], names: list[str]) -> str:
    short = ("local", "global", "true depth", "true root", "true orient.", "depth bias", "depth sd", "lateral",
             "bone ratio", "depth ratio sd", "corr", "torso deg")
    lines = []
    for name, res in zip(names, results):
        lines += [f"### {name} (`{res['bench']}`)", "",
                  "| sequence | " + " | ".join(short) + " |", "|---|" + "---:|" * len(short)]
        for seq, r in list(res["sequences"].items()) + [("**median**", res["median"])]:
            if "error" in r or not r:
                lines.append(f"| {seq} | " + " | ".join("--" for _ in short) + " |")
                continue
            lines.append(f"| {seq} | " + " | ".join(
                f"{r[k]:.2f}" if k in ("bone_ratio", "depth_ratio_sd", "extent_depth_corr") else f"{r[k]:.1f}"
                for k in KEYS) + " |")
        lines.append("")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench", nargs="+")
    ap.add_argument("--names", default=None)
    ap.add_argument("--out", default=None, help="PREFIX: write PREFIX.json and PREFIX.md")
    args = ap.parse_args()
    names = args.names.split(",") if args.names else [Path(b).name for b in args.bench]
    results = [run(Path(b)) for b in args.bench]
    md = table(results, names)
    print(md)
    if args.out:
        Path(args.out + ".json").write_text(json.dumps(dict(zip(names, results)), indent=1))
        Path(args.out + ".md").write_text(
            "# Where the diverse suite's global error comes from\n\n"
            "`python benchmarks/global_error.py " + " ".join(args.bench) + "`; cm unless said; "
            "see the script's docstring for each column.\n\n" + md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
