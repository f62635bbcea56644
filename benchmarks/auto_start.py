"""The automatic start measured alone, on the clips of a ``flowmocap bench --as-video`` folder.

A video run starts from the detector: ``init_auto.json`` (the confident 2D keypoints of the
first frame with a whole person, and an upright body facing the way they say), the
automatic mask of that frame, and the detector's 3D joints (``E_d``, ``E_3d``). This script
repeats the start's joint fits (the initialisation's steps 1 and 2,
:func:`flowmocap.fit.init.fit_frame0`, on the `video` profile; not the flow step that
follows) on each clip's stored detections with each named set of settings, and scores the
start against the rendered truth of its frame: the local error (a similarity Procrustes,
the 13 evaluation joints, cm, :func:`flowmocap.eval.metrics.local_procrustes_error`), as
the suite scores a run. Nothing is detected or tracked again: a variant takes a few
seconds a clip.

It is how ``init_pose_prior_weight`` 20 was found (docs/experiments.md, "The automatic
start held the body near the rest pose"): the start of the held-out suite tracked as a
video was worse than both 3D sources it is given.

Usage: python benchmarks/auto_start.py DIR [--variants JSON] [--clips A,B] [--out PREFIX]
  DIR: a ``flowmocap bench --suite diverse --as-video`` folder (its runs finished or not,
  as long as each clip's detections and init_auto.json are there).
  --variants: '{"name": {setting: value, ...}, ...}' over the `video` profile (default: the
  defaults and the weights before 2026-11-28). Writes PREFIX.json and PREFIX.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from flowmocap.body import load_body_model
from flowmocap.eval.metrics import local_procrustes_error
from flowmocap.fit import energies as en
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.init import fit_frame0, parse_init
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.vision.masks import load_mask
from flowmocap.vision.auto import load_detections
from flowmocap.vision.lifter import lifted_track

#: the defaults, and the start's weights before 2026-11-28
DEFAULT_VARIANTS = {"defaults": {}, "before 2026-11-28": {"init_pose_prior_weight": 200.0}}


def clip_start_errors(clip: Path, variants: dict[str, dict], models: dict) -> dict[str, float]:
    """cm: the start's local error at its frame for each variant, on one clip folder of an
    as-video bench (``sequence/`` with ``gt.npz``, ``camera.json``, ``meta.json``;
    ``flowmocap/`` with ``init_auto.json`` and ``detections/``)."""
    res = clip / "flowmocap"
    init = json.loads((res / "init_auto.json").read_text())
    f = int(init["frame"])
    meta = json.loads((clip / "sequence" / "meta.json").read_text())
    gt = np.load(clip / "sequence" / "gt.npz")
    cam = PinholeCamera.from_dict(json.loads((clip / "sequence" / "camera.json").read_text()))
    gender = str(meta.get("gender", "neutral"))
    body = models.setdefault(gender, load_body_model("default", gender=gender))
    track = load_detections(res)
    mask = load_mask(res / "detections" / "masks" / f"{f:06d}.png")
    spec = parse_init(init, mask.shape[1], mask.shape[0])
    sil = en.silhouette_target(mask) if mask.any() else None
    out = {}
    for name, settings in variants.items():
        cfg = TrackerConfig.load(dict(settings), profile="video")
        watch = (track if cfg.detector3d_source == "mediapipe" else
                 lifted_track(track, mix=cfg.detector3d_source == "both", fps=float(meta.get("fps", 30.0))))
        torch.manual_seed(0)
        pose, trans, betas, _ = fit_frame0(body, cam, spec, sil, cfg, watch.smpl_joints3d(f, cam))
        with torch.no_grad():
            joints = body(betas=betas, pose=pose[None], trans=trans[None], with_vertices=False).joints
        out[name] = 100.0 * float(local_procrustes_error(joints.double().numpy(), gt["joints3d"][f:f + 1])[0])
    return out


def summarise(rows: dict[str, dict[str, float]], names: list[str]) -> dict:
    """Median and mean (cm) of each variant over the clips, and the clips each one
    improves on the first variant by more than 0.4 cm."""
    table = np.array([[rows[c][n] for n in names] for c in rows])
    return {n: {"median_cm": float(np.median(table[:, k])), "mean_cm": float(table[:, k].mean()),
                "better_than_first": int((table[:, k] < table[:, 0] - 0.4).sum()),
                "worse_than_first": int((table[:, k] > table[:, 0] + 0.4).sum())}
            for k, n in enumerate(names)}


def markdown(result: dict) -> str:
    names = list(result["variants"])
    lines = [f"# The automatic start alone: `{result['dir']}`", "",
             "Local error (cm, 13 joints, similarity Procrustes) of the start (init steps 1-2, the `video` profile) "
             "at its frame against the truth. Variants over the `video` profile: "
             + "; ".join(f"**{n}** {json.dumps(v)}" for n, v in result["variants"].items()) + ".", "",
             "| clip | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    for clip, row in result["clips"].items():
        lines.append(f"| {clip} | " + " | ".join(f"{row[n]:.2f}" for n in names) + " |")
    s = result["summary"]
    lines.append("| **median** | " + " | ".join(f"**{s[n]['median_cm']:.2f}**" for n in names) + " |")
    lines.append("| **mean** | " + " | ".join(f"{s[n]['mean_cm']:.2f}" for n in names) + " |")
    lines.append(f"| better / worse than {names[0]} (> 0.4 cm) | "
                 + " | ".join(f"{s[n]['better_than_first']} / {s[n]['worse_than_first']}" for n in names) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", type=Path, help="a flowmocap bench --as-video folder")
    ap.add_argument("--variants", help="JSON: {name: {setting: value}} over the video profile")
    ap.add_argument("--clips", help="comma-separated clip names (default: all)")
    ap.add_argument("--out", help="write PREFIX.json and PREFIX.md")
    args = ap.parse_args(argv)
    variants = json.loads(args.variants) if args.variants else DEFAULT_VARIANTS
    for v in variants.values():
        TrackerConfig.load(dict(v), profile="video")  # a misspelt setting stops here, not after the first clip
    wanted = set(args.clips.split(",")) if args.clips else None
    clips = [c for c in sorted(args.dir.iterdir()) if (c / "flowmocap" / "init_auto.json").exists()
             and (wanted is None or c.name in wanted)]
    if not clips:
        print(f"no clip of an as-video bench in {args.dir} (each needs flowmocap/init_auto.json)", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    models: dict = {}
    rows = {}
    names = list(variants)
    for c in clips:
        t0 = time.perf_counter()
        rows[c.name] = clip_start_errors(c, variants, models)
        print(f"{c.name:16s} " + " ".join(f"{rows[c.name][n]:6.2f}" for n in names)
              + f"   ({time.perf_counter() - t0:.0f} s)", flush=True)
    result = {"dir": str(args.dir), "variants": variants, "clips": rows, "summary": summarise(rows, names)}
    md = markdown(result)
    print(md)
    if args.out:
        Path(f"{args.out}.json").write_text(json.dumps(result, indent=1))
        Path(f"{args.out}.md").write_text(md)
        print(f"wrote {args.out}.json and {args.out}.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
