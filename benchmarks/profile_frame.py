"""Where a tracked frame's time goes (issue 19): the tracker's per-frame step on the CMU
protocol clip under cProfile, in CPU seconds (``time.process_time``: a busy machine slows
the wall clock, not this), grouped by part of the pipeline.

The clip is a sequence folder (``flowmocap synth`` of CMU 35_01 at 640x480, 60 fps, as
``benchmarks/track.py`` makes; or any sequence folder with ``gt.npz``). Tracking starts
from the true first two frames (no initialisation) so that every profiled second is a
per-frame step: observed flow (computed on the look-ahead thread in a real run, here in
line so that it is counted), energies and gradients, the renderer, the body model, the
optimiser, the flip test and the bookkeeping.

Usage: python benchmarks/profile_frame.py SEQUENCE [--frames 2:14] [--out benchmarks/results/profile_frame.json]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Parts of a frame, by the module (and function) a profiled function lives in; the first
#: match wins. Own time of each function is counted (tottime), so every second counts once.
GROUPS = [
    ("observed flow (OpenCV)", ("vision/flow.py",)),
    ("rendered flow + its Jacobian", ("render/flow.py", "render/interpolate.py")),
    ("pyramid", ("render/pyramid.py",)),
    ("rasteriser / silhouette", ("render/raster.py", "render/primitives.py")),
    ("capsule distance map", ("render/capsules.py", "body/capsules.py")),
    ("body model (LBS)", ("body/lbs.py", "body/model.py")),
    ("joint limits, priors, rotations", ("fit/rotation_terms.py", "fit/joint_limits.py", "fit/pose_prior.py")),
    ("energies (assembly)", ("fit/energies.py", "fit/objective.py")),
    ("flip test", ("fit/flip.py",)),
    ("optimiser (L-BFGS)", ("fit/lbfgs.py",)),
    ("Kalman filters", ("fit/kalman.py", "filterpy")),
    ("torch (autograd, ops)", ("torch/",)),
    ("numpy", ("numpy/",)),
    ("tracker bookkeeping", ("fit/tracker.py",)),
]


#: Compiled functions (cProfile's ``~``) by name; the rest go to their callers' part.
BUILTINS = [
    ("observed flow (OpenCV)", ("cv2.DenseOpticalFlow", "calcOpticalFlow", "cv2.optflow")),
    ("autograd backward (torch)", ("run_backward",)),
    ("reading frames and masks", ("imread", "cvtColor")),
]


def group_of(filename: str, func: str = "") -> str:
    f = filename.replace("\\", "/")
    if f == "~":
        for name, keys in BUILTINS:
            if any(k in func for k in keys):
                return name
        return "~"
    for name, keys in GROUPS:
        if any(k in f for k in keys):
            return name
    return "other"


def attribute(stats) -> tuple[dict, list]:
    """Own CPU seconds per part, and ``(seconds, function, part)`` per function; a compiled
    function's time goes to the part of the Python function that called it."""
    groups: dict[str, float] = {}
    top = []
    for (filename, line, func), (_cc, _nc, tottime, _ct, callers) in stats.stats.items():
        g = group_of(filename, func)
        top.append((tottime, f"{Path(filename).name}:{line} {func}", g))
        if g != "~":
            groups[g] = groups.get(g, 0.0) + tottime
            continue
        for (cfile, _cline, cfunc), (_c, _n, tt, _t) in callers.items():
            cg = group_of(cfile, cfunc)
            cg = "other compiled calls" if cg == "~" else cg
            groups[cg] = groups.get(cg, 0.0) + tt
    return groups, top


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", help="a sequence folder with gt.npz (e.g. from benchmarks/track.py --work DIR)")
    ap.add_argument("--frames", default="2:14", help="A:B, the frames to profile (from A-2 and A-1 known)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "profile_frame.json"))
    args = ap.parse_args()

    import numpy as np
    import torch

    from flowmocap.body import load_body_model
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.fit.objective import FrameState, Scene, frame_data
    from flowmocap.fit.tracker import SequenceTracker
    from flowmocap.io.sequence import load_sequence
    from flowmocap.pipeline import parse_frame_range
    from flowmocap.vision.flow import observed_flow

    seq = load_sequence(args.sequence)
    a, b = parse_frame_range(args.frames, len(seq))
    if a < 2:
        a = 2
    cfg = TrackerConfig.load(None, profile="synthetic")
    torch.set_num_threads(int(cfg.torch_threads))
    gt = seq.gt
    f32 = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32)  # noqa: E731
    model = load_body_model("default", gender=str(seq.meta.get("gender", "neutral")))
    scene = Scene(model, f32(gt["betas"])[None], seq.camera)
    tracker = SequenceTracker(scene, cfg)
    tracker.start(*(FrameState(f32(gt["poses"][k]), f32(gt["trans"][k])) for k in (a - 2, a - 1)), anchored=True)
    # warm up the JIT-compiled kernels on one frame outside the profile
    warm = SequenceTracker(scene, cfg)
    warm.start(*(FrameState(f32(gt["poses"][k]), f32(gt["trans"][k])) for k in (a - 2, a - 1)), anchored=True)
    mask = seq.mask(a)
    warm.step(a, mask, frame_data(mask, observed_flow(seq.frame(a), seq.frame(a - 1), cfg.flow_method), cfg,
                                  float("nan")))

    prof = cProfile.Profile(time.process_time)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    prof.enable()
    for i in range(a, b):
        mask = seq.mask(i)
        flow = observed_flow(seq.frame(i), seq.frame(i - 1), cfg.flow_method)
        tracker.step(i, mask, frame_data(mask, flow, cfg, float("nan")))
    prof.disable()
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    n = b - a
    groups, top = attribute(pstats.Stats(prof))
    total = sum(groups.values())
    rows = sorted(groups.items(), key=lambda kv: -kv[1])
    print(f"{n} frames of {args.sequence} ({seq.size[0]}x{seq.size[1]}), CPU {cpu / n:.3f} s per frame "
          f"(wall {wall / n:.3f} s on this machine now)\n")
    print(f"{'part':<40}{'CPU s/frame':>12}{'share':>8}")
    for g, t in rows:
        print(f"{g:<40}{t / n:>12.3f}{100 * t / total:>7.1f}%")
    print("\nthe 15 functions with the most own time:")
    for t, name, g in sorted(top, reverse=True)[:15]:
        print(f"  {t / n:8.4f} s/frame  {name}  [{g}]")
    out = {"sequence": str(args.sequence), "frames": [a, b], "size": list(seq.size), "cpu_s_per_frame": cpu / n,
           "wall_s_per_frame": wall / n, "profile_overhead_note": "cProfile adds per-call overhead; shares matter",
           "parts": {g: t / n for g, t in rows},
           "top": [{"s_per_frame": t / n, "function": name, "part": g} for t, name, g in sorted(top, reverse=True)[:30]]}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2))
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
