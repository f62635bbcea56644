"""L-BFGS against Levenberg-Marquardt on the per-frame objective (issue 5, item 5).

On the synthetic CMU 35_01 sequence (640x480, 60 fps; made as benchmarks/track.py makes
it if absent), for each frame i of a range: the previous frame is the ground truth
(``prev``), the start is the ground truth extrapolated at constant velocity from
frames i-2 and i-1 ("extrapolated"), the previous frame's ("previous") or the previous
frame's with noise ("perturbed": N(0, 0.05 rad) on every joint angle, 0.4 times that on
the root, N(0, 2 cm) on the translation; a start as far off as a poor prediction);
--init all runs the three in turn. The observed flow is
DIS between the rendered frames i and i-1, the shape is the ground truth's and the
silhouette term uses the mesh (``silhouette_model="mesh"``, the only one LM supports).
Both solvers optimise the same energy (tracker.frame_energy) from the same start; the
table gives the median seconds per frame (solver only, flow excluded), the final
energy and the 3D joint error against the ground truth (cm, mean over the 13
evaluation joints, no alignment).

Usage: python benchmarks/solver.py [--seq /tmp/w5/seq] [--frames 40:60] [--init previous|extrapolated|perturbed|all]
       [--out benchmarks/results/solver.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CMU = ROOT.parent / "shared" / "data" / "mocap" / "cmu" / "35_01.amc"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seq", default="/tmp/w5/seq")
    ap.add_argument("--frames", default="40:60")
    ap.add_argument("--init", choices=("previous", "extrapolated", "perturbed", "all"), default="all")
    ap.add_argument("--noise", type=float, default=0.05, help="pose noise (rad) of --init perturbed")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "solver.json"))
    args = ap.parse_args()

    import torch

    torch.set_num_threads(1)
    from flowmocap.body import load_body_model
    from flowmocap.body.skeleton import EVAL_JOINTS
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.fit.lm import lm_track_frame
    from flowmocap.fit.tracker import FrameState, Scene, frame_data, frame_energy, track_frame
    from flowmocap.io.sequence import load_sequence
    from flowmocap.vision.flow import observed_flow

    seq_dir = Path(args.seq)
    if not (seq_dir / "gt.npz").exists():
        if not CMU.exists():
            print(f"skipped: {seq_dir} has no sequence and {CMU} is not there to make one")
            return 0
        from flowmocap.synth import synthesize

        synthesize(str(CMU), seq_dir, fps=60.0, frames=130, size="640x480", betas="random", seed=0,
                   azimuth=60.0, flow=False)
    seq = load_sequence(seq_dir)
    gt = seq.gt
    a, b = (int(v) for v in args.frames.split(":"))
    a = max(a, 2)
    cfg = TrackerConfig(silhouette_model="mesh")
    model = load_body_model("default")
    f32 = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32)  # noqa: E731
    scene = Scene(model, f32(gt["betas"]).reshape(1, -1), seq.camera)
    ev = list(EVAL_JOINTS)

    def joint_error_cm(state, i):
        with torch.no_grad():
            out, _, _ = scene.forward(state.pose, state.trans)
        j = out.joints[0].numpy()[ev]
        return float(np.linalg.norm(j - gt["joints3d"][i][ev], axis=1).mean() * 100)

    solvers = {"lbfgs": track_frame, "lm": lm_track_frame}
    flows = {}
    runs = {}
    modes = ("previous", "extrapolated", "perturbed") if args.init == "all" else (args.init,)
    for mode in modes:
        rows = {k: [] for k in ("init", "lbfgs", "lm", "gt")}
        print(f"frames {a}:{b} of {seq_dir}, {seq.size[0]}x{seq.size[1]}, init: {mode}")
        for i in range(a, b):
            prev = FrameState(f32(gt["poses"][i - 1]), f32(gt["trans"][i - 1]))
            if mode == "extrapolated":
                init = FrameState(f32(2 * gt["poses"][i - 1] - gt["poses"][i - 2]),
                                  f32(2 * gt["trans"][i - 1] - gt["trans"][i - 2]))
            elif mode == "perturbed":
                rng = np.random.default_rng(i)
                noise = rng.normal(scale=args.noise, size=72)
                noise[:3] *= 0.4
                init = FrameState(prev.pose + f32(noise), prev.trans + f32(rng.normal(scale=0.02, size=3)))
            else:
                init = FrameState(prev.pose.clone(), prev.trans.clone())
            if i not in flows:
                flows[i] = observed_flow(seq.frame(i), seq.frame(i - 1), method="dis")
            mask = seq.mask(i)
            data = frame_data(mask, flows[i], cfg, float(mask.sum()) if mask is not None else 1.0)
            with torch.no_grad():
                _, prev_px, _ = scene.forward(prev.pose, prev.trans)
                last = len(cfg.stages) - 1
                e_init = float(frame_energy(scene, init, data, cfg, last, prev_px, prev.pose)[0])
                gt_state = FrameState(f32(gt["poses"][i]), f32(gt["trans"][i]))
                e_gt = float(frame_energy(scene, gt_state, data, cfg, last, prev_px, prev.pose)[0])
            rows["init"].append({"frame": i, "energy": e_init, "joint_cm": joint_error_cm(init, i), "s": 0.0})
            rows["gt"].append({"frame": i, "energy": e_gt, "joint_cm": 0.0, "s": 0.0})
            line = [f"frame {i:3d}  init E {e_init:7.4f} {rows['init'][-1]['joint_cm']:.2f} cm  gt E {e_gt:.4f}"]
            for name, solve in solvers.items():
                t0 = time.perf_counter()
                state, terms = solve(scene, init, data, cfg, prev)
                dt = time.perf_counter() - t0
                rows[name].append({"frame": i, "energy": terms["total"], "joint_cm": joint_error_cm(state, i), "s": dt})
                line.append(f"{name} {dt:5.2f} s E {terms['total']:.4f} {rows[name][-1]['joint_cm']:.2f} cm")
            print("  |  ".join(line), flush=True)
        summary = {}
        for name, r in rows.items():
            summary[name] = {
                "s_per_frame_median": float(np.median([x["s"] for x in r])),
                "energy_median": float(np.median([x["energy"] for x in r])),
                "energy_mean": float(np.mean([x["energy"] for x in r])),
                "joint_cm_mean": float(np.mean([x["joint_cm"] for x in r])),
                "joint_cm_median": float(np.median([x["joint_cm"] for x in r])),
            }
        lower = int(sum(m["energy"] < l["energy"] for m, l in zip(rows["lm"], rows["lbfgs"])))
        ratio = summary["lbfgs"]["s_per_frame_median"] / summary["lm"]["s_per_frame_median"]
        print()
        print(f"init: {mode}")
        print(f"{'solver':<10}{'s/frame (median)':>18}{'energy (median)':>18}{'energy (mean)':>16}{'joint cm (mean)':>17}")
        for name, s in summary.items():
            t = f"{s['s_per_frame_median']:.2f}" if name in solvers else "-"
            print(f"{name:<10}{t:>18}{s['energy_median']:>18.4f}{s['energy_mean']:>16.4f}{s['joint_cm_mean']:>17.2f}")
        print(f"L-BFGS / LM median time ratio: {ratio:.2f}; LM reaches the lower energy on {lower} of "
              f"{len(rows['lm'])} frames\n")
        runs[mode] = {"summary": summary, "time_ratio_lbfgs_over_lm": ratio, "lm_lower_energy_frames": lower,
                      "per_frame": rows}
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout.strip()
    result = {
        "benchmark": "solver", "commit": commit, "sequence": str(seq_dir), "frames": [a, b],
        "size": list(seq.size), "config": cfg.to_dict(), "torch_threads": 1, "runs": runs,
        "note": "s = solver wall time only (observed flow excluded), on a shared 2-core machine; "
                "joint_cm = mean 3D distance of the 13 evaluation joints to the ground truth, no alignment",
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
