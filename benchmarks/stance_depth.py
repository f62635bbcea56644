"""A foot standing still keeps its depth: a post-pass tried on the synthetic suites (issue 18).

Where the global error comes from (docs/experiments.md): a monocular fit's root depth
follows its pose's 3D size from frame to frame while the image stays put; with each
frame at its true depth the diverse suite's median global error would be 6.0 cm instead
of 7.6. A foot that does not move in the image is, in the world, planted, so it keeps its
distance from the camera: :func:`flowmocap.fit.smooth.stance_depth_shift` moves each frame along the ray
through its root until a foot in stance keeps its median depth over the stance. This
script applies it to finished runs between the defaults' post-pass steps (the lifter
refit and its depth smoothing before, the pose smoothing after, as the pipeline orders
them) and scores a grid of its settings, or one:

    python benchmarks/stance_depth.py --bench TUNE_DIR [--bench DIR ...] [--seeds SEEDS_WORK]
        [--grid | --settings JSON] [--out PREFIX]

``--bench``: folders of ``flowmocap bench --suite tune|diverse`` or ``benchmarks/tracker_only.py``
(tracked with ``lifter_refit_weight`` 0 and ``pose_smoothing_s`` 0, so the post-pass is
applied here); ``--seeds``: a ``benchmarks/track_seeds.py --work`` folder. The setting
the pipeline uses (``TrackerConfig.stance_depth_*``) was chosen on the ``tune`` suite's
grid, then measured on the others (docs/experiments.md, "A planted foot keeps its depth").
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

from flowmocap.fit.smooth import stance_depth_shift


def _post(res: Path, params: dict | None, models: dict) -> dict:
    """The defaults' post-pass of a finished run, with the stance shift (``params``, or
    None: without it) after the refit's depth smoothing and before the pose smoothing."""
    from flowmocap.body import load_body_model
    from flowmocap.fit.lift_refit import lifter_refit_motion
    from flowmocap.fit.smooth import depth_smoothed_motion, pose_smoothed_motion
    from flowmocap.fit.swap import exchanged_frames
    from flowmocap.geometry.camera import PinholeCamera
    from flowmocap.io.results import read_result
    from flowmocap.vision.auto import load_detections

    key = str(res)
    if key not in models:
        motion, _ = read_result(res)
        gender = str(np.asarray(motion.get("gender", "neutral")))
        model = load_body_model("default", gender=gender)
        run = json.loads((res / "run.json").read_text())
        refit, _ = lifter_refit_motion(motion, load_detections(res), model, weight=0.5, pixel_sigma=6.0,
                                       iterations=60, exchanged=exchanged_frames(run.get("events", [])))
        reinits = [e["frame"] for e in run.get("events", []) if e.get("event") == "re-initialised"]
        models[key] = (depth_smoothed_motion(refit, 0.5, breaks=reinits), reinits, model)
    m, reinits, model = models[key]
    m = dict(m)
    if params is not None:
        cam = PinholeCamera.from_dict(json.loads(str(np.asarray(m["camera"]))))
        shift, _ = stance_depth_shift(np.asarray(m["joints3d"]), np.asarray(m["joints2d"]), cam.R, cam.t,
                                      float(np.asarray(m["fps"])), frame_index=m["frame_index"], breaks=reinits,
                                      **params)
        m["trans"] = np.asarray(m["trans"]) + shift
        j = np.asarray(m["joints3d"], np.float64) + shift[:, None]
        m["joints3d"] = j
        m["joints2d"] = np.asarray(cam.project(j.reshape(-1, 3))).reshape(j.shape[0], -1, 2)
    return pose_smoothed_motion(m, model, 0.3, breaks=reinits)[0]


def _pairs(bench: list[Path], seeds: Path | None) -> list[tuple[str, Path, Path]]:
    out = []
    for b in bench:
        out += [(f"{b.name}/{d.name}", d / "sequence", d / "flowmocap") for d in sorted(b.iterdir())
                if (d / "sequence" / "gt.npz").exists() and (d / "flowmocap" / "motion.npz").exists()]
    if seeds is not None:
        for seq in sorted(seeds.glob("seq_s*")):
            for res in sorted(p for p in seq.iterdir() if p.is_dir() and (p / "result").is_dir()):
                gt = res / "sequence" if (res / "sequence" / "gt.npz").exists() else seq / "sequence"
                out.append((f"{seq.name}/{res.name}", gt, res / "result"))
    return out


def main() -> int:
    from flowmocap.eval import metrics as M

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bench", type=Path, action="append", default=[])
    ap.add_argument("--seeds", type=Path)
    ap.add_argument("--grid", action="store_true", help="speed 0.12/0.18/0.3, min_s 0.1/0.2, window_s 0.1/0.25, "
                                                        "share 0.5/1")
    ap.add_argument("--settings", default='{"speed": 0.12, "min_s": 0.2, "window_s": 0.25, "share": 0.5}',
                    help="one setting (JSON; default: the pipeline's, chosen on the tune suite)")
    ap.add_argument("--out")
    a = ap.parse_args()
    pairs = _pairs(a.bench, a.seeds)
    if not pairs:
        ap.error("no finished runs in --bench / --seeds")
    grid = ([dict(zip(("speed", "min_s", "window_s", "share"), v))
             for v in itertools.product((0.12, 0.18, 0.3), (0.1, 0.2), (0.1, 0.25), (0.5, 1.0))]
            if a.grid else [json.loads(a.settings)])
    models: dict = {}
    rows = []
    base = None
    for params in [None] + grid:
        local, glob = [], []
        for _, seq, res in pairs:
            m = _post(res, params, models)
            gt = np.load(seq / "gt.npz")
            idx = np.asarray(m["frame_index"], int)
            g3, p3 = np.asarray(gt["joints3d"], np.float64)[idx], np.asarray(m["joints3d"], np.float64)
            local.append(100 * float(M.local_procrustes_error(p3, g3).mean()))
            glob.append(100 * float(M.global_procrustes_error(p3, g3).mean()))
        g = np.array(glob)
        base = g if base is None else base
        row = {"settings": params, "median_local_cm": float(np.median(local)), "median_global_cm": float(np.median(g)),
               "mean_local_cm": float(np.mean(local)), "mean_global_cm": float(np.mean(g)),
               "global_better": int((g < base - 0.2).sum()), "global_worse": int((g > base + 0.2).sum()),
               "global_cm": dict(zip([p[0] for p in pairs], glob))}
        rows.append(row)
        print(f"{json.dumps(params)}: median {row['median_local_cm']:.2f} / {row['median_global_cm']:.2f} cm, mean "
              f"{row['mean_local_cm']:.2f} / {row['mean_global_cm']:.2f}; global better / worse by > 0.2 cm: "
              f"{row['global_better']} / {row['global_worse']}", flush=True)
    if a.out:
        Path(a.out + ".json").write_text(json.dumps({"runs": [p[0] for p in pairs], "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
