"""The steps after tracking redone on finished runs with other settings, and scored.

The pipeline's steps after tracking (the lifter refit with its vote and seam easing, the
depth smoothing after it, the stance depth correction and the pose smoothing;
``flowmocap.pipeline._post_steps``) read only the tracked motion, the stored detections
and ``run.json``. So a setting of theirs can be judged on runs already tracked, in
minutes, with no tracking chaos between the variants: each run folder is copied (its
detections linked), its motion put back to what the tracker finished with
(``poses_tracked``, ``trans_tracked``, the root depth smoothed as at the end of tracking),
the post-pass records dropped from ``run.json``, and the pipeline's own post steps run
again with the run's settings and the variant's overrides.

Suites (any number; each folder as the bench or script left it):

- ``--diverse DIR``: a ``flowmocap bench --suite diverse`` folder (by the protocol or
  ``--as-video``; several may be given): per clip local / global error (cm), acceleration
  error (mm/frame^2), 2D error (px) and silhouette IoU (``flowmocap.eval.scoring.score_result``);
- ``--real3d DIR``: a ``flowmocap bench --suite real3d`` folder: per person-view the
  per-frame and per-sequence PA-MPJPE (mm) and MediaPipe's (``flowmocap.eval.real3d.score_run``);
- ``--davis DIR`` / ``--walk DIR``: the result folders ``benchmarks/real_video.py`` wrote
  (``WORK/davis-dance-twirl``, ``WORK/sports2d-walk``): body IoU against DAVIS's masks and
  against the walk's own automatic masks.

Usage: python benchmarks/post_steps.py --variants '{"before": {"lifter_refit_seam_s": 0}, "seams": {}}'
       [--diverse DIR ...] [--real3d DIR] [--davis DIR] [--walk DIR] [--out PREFIX]

Each variant is a dict of ``TrackerConfig`` settings laid over the run's own (``run.json``
``config``; settings the run predates take today's defaults, so name the old value where
it matters). Writes ``PREFIX.json`` and ``PREFIX.md``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.stats import wilcoxon

from flowmocap.body import load_body_model
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.smooth import depth_smoothed_motion, posed_joints
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.io.results import read_result, write_motion, write_run

sys.path.insert(0, str(Path(__file__).resolve().parent))

#: the keys the post steps add to ``run.json`` and to ``motion.npz``
RUN_KEYS = ("lifter_refit", "stance_depth", "pose_smoothing")
MOTION_KEYS = ("poses_tracked", "trans_tracked", "poses_unsmoothed", "trans_unsmoothed", "disagreement", "betas_tracked")
_BODIES: dict = {}


def _body(run: dict):
    model = run.get("model") if run.get("model") and Path(str(run.get("model"))).exists() else "default"
    key = (model, run.get("gender", "neutral"))
    if key not in _BODIES:
        _BODIES[key] = load_body_model(model, gender=run.get("gender", "neutral"))
    return _BODIES[key]


def tracked_motion(motion: dict, run: dict, body, cfg: TrackerConfig) -> dict:
    """The motion as the tracker finished it: ``poses_tracked`` and ``trans_tracked`` with the
    root depth smoothed over ``cfg.depth_smoothing_s`` as at the end of tracking (breaks at
    every re-initialisation), joints recomputed. A motion without ``poses_tracked`` (the
    refit was off or skipped) is returned with only the later steps' arrays dropped."""
    from flowmocap.pipeline import _reinit_frames

    m = {k: v for k, v in motion.items() if k not in MOTION_KEYS}
    if "betas_tracked" in motion:  # the refit changed the shape (lifter_refit_shape_share)
        m["betas"] = motion["betas_tracked"]
    if "poses_tracked" not in motion:
        if "poses_unsmoothed" in motion:
            m["poses"], m["trans"] = motion["poses_unsmoothed"], motion["trans_unsmoothed"]
        return m
    poses = np.asarray(motion["poses_tracked"], np.float64)
    trans = np.asarray(motion["trans_tracked"], np.float64)
    camera = PinholeCamera.from_dict(json.loads(str(np.asarray(motion["camera"]))))
    j, j2d = posed_joints(body, m["betas"], poses, trans, camera)
    m["poses"] = poses.astype(np.asarray(motion["poses"]).dtype)
    m["trans"] = trans.astype(np.asarray(motion["trans"]).dtype)
    m["joints3d"] = j.astype(np.asarray(motion["joints3d"]).dtype)
    m["joints2d"] = j2d.astype(np.asarray(motion["joints2d"]).dtype)
    if cfg.depth_smoothing_s > 0:
        m = depth_smoothed_motion(m, cfg.depth_smoothing_s, breaks=_reinit_frames(run, include_eased=True))
    return m


def redo(res: Path, overrides: dict, work: Path) -> Path:
    """A copy of result folder ``res`` under ``work`` with the post steps redone with the
    run's settings and ``overrides``; returns the copy's folder."""
    from flowmocap.pipeline import _post_steps
    from flowmocap.vision.auto import load_detections

    motion, _ = read_result(res)
    run = json.loads((res / "run.json").read_text())
    cfg = TrackerConfig.from_dict({**(run.get("config") or {}), **overrides})
    body = _body(run)
    out = work / res.name
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    for f in res.iterdir():
        if f.name not in ("motion.npz", "run.json", "progress.json", "frames.bin"):
            (out / f.name).symlink_to(f.resolve())
    base = {k: v for k, v in run.items() if k not in RUN_KEYS}
    write_motion(out, tracked_motion(motion, run, body, cfg))
    write_run(out, base)
    fingerprint = run.get("fingerprint")
    joints3d = fingerprint.get("joints3d", "auto") if isinstance(fingerprint, dict) else "auto"
    _post_steps(out, load_detections(out), body, cfg, base, joints3d, lambda *a, **k: None)
    return out


def diverse_rows(bench: Path, variants: dict, work: Path) -> dict:
    from flowmocap.eval.scoring import score_result

    rows: dict = {name: [] for name in variants}
    for seq in sorted(p.parent for p in bench.glob("*/sequence/gt.npz")):
        res = seq.parent / "flowmocap"
        if not (res / "motion.npz").exists():
            continue
        for name, over in variants.items():
            s = score_result(redo(res, over, work / name), seq)
            rows[name].append({"name": seq.parent.name, **{k: s[k] for k in ("local_cm", "global_cm", "accel_mm",
                                                                                "px2d", "iou")}})
    return rows


def real3d_rows(bench: Path, variants: dict, work: Path) -> dict:
    from flowmocap.eval.real3d import build_reference, score_run

    reference = build_reference(bench, progress=False, log=None)
    rows: dict = {name: [] for name in variants}
    for res in sorted((bench / "runs").iterdir()):
        if not (res / "motion.npz").exists():
            continue
        person, view = res.name.split("-", 1)
        for name, over in variants.items():
            s = score_run(redo(res, over, work / name), reference, person, view)
            if s.get("flowmocap") is None:
                continue
            kp = s.get("flowmocap_kp") or {}
            rows[name].append({"name": res.name, "per_frame_mm": s["flowmocap"]["per_frame_mm"],
                               "per_sequence_mm": s["flowmocap"]["per_sequence_mm"],
                               "at_keypoints_per_frame_mm": kp.get("per_frame_mm", float("nan")),
                               "mediapipe_per_frame_mm": s["detector3d"]["per_frame_mm"]})
    return rows


def clip_rows(res: Path, variants: dict, work: Path, davis: bool) -> dict:
    from real_video import DATA, body_ious

    from flowmocap.vision.auto import load_detections
    from flowmocap.vision.masks import load_mask

    if davis:
        gt = [load_mask(p) for p in sorted((DATA / "davis-dance-twirl" / "Annotations").glob("*.png"))]
        reference = gt.__getitem__
    else:
        reference = load_detections(res).mask
    return {name: [{"name": res.name, "body_iou": float(np.mean(body_ious(redo(res, over, work / name), reference)))}]
            for name, over in variants.items()}


def _summary(rows: list[dict], first: list[dict] | None) -> dict:
    keys = [k for k in rows[0] if k != "name"] if rows else []
    out = {}
    for k in keys:
        v = np.array([r[k] for r in rows], float)
        out[k] = {"median": float(np.nanmedian(v)), "mean": float(np.nanmean(v))}
        if first is not None and len(first) == len(rows):
            f = np.array([r[k] for r in first], float)
            lower = k not in ("iou", "body_iou")
            d = (v - f) if lower else (f - v)
            out[k]["better"], out[k]["worse"] = int((d < -1e-9).sum()), int((d > 1e-9).sum())
            moved = d[np.isfinite(d) & (np.abs(d) > 1e-9)]
            out[k]["wilcoxon_p"] = float(wilcoxon(moved).pvalue) if moved.size >= 5 else None
    return out


def _table(title: str, rows: dict) -> str:
    names = list(rows)
    first = rows[names[0]]
    keys = [k for k in first[0] if k != "name"] if first else []
    lines = [f"### {title}", "", "| variant | " + " | ".join(f"{k} median (mean)" for k in keys)
             + " | better / worse than the first (Wilcoxon p over the runs that moved) |",
             "|---|" + "---:|" * (len(keys) + 1)]
    for n in names:
        s = _summary(rows[n], first if n != names[0] else None)
        bw = ", ".join(f"{k} {s[k]['better']}/{s[k]['worse']}"
                       + (f" (p {s[k]['wilcoxon_p']:.3f})" if s[k].get("wilcoxon_p") is not None else "")
                       for k in keys if "better" in s[k])
        lines.append(f"| {n} | " + " | ".join(f"{s[k]['median']:.3f} ({s[k]['mean']:.3f})" for k in keys)
                     + f" | {bw} |")
    lines.append("")
    lines.append("| run | " + " | ".join(f"{k}: " + " / ".join(names) for k in keys) + " |")
    lines.append("|---|" + "---:|" * len(keys))
    for i, r in enumerate(first):
        lines.append(f"| {r['name']} | " + " | ".join(" / ".join(f"{rows[n][i][k]:.3f}" for n in names) for k in keys)
                     + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variants", required=True,
                    help='JSON: {"name": {setting: value, ...}, ...}; the first is the reference of the counts')
    ap.add_argument("--diverse", type=Path, action="append", default=[])
    ap.add_argument("--real3d", type=Path)
    ap.add_argument("--davis", type=Path, help="benchmarks/real_video.py's WORK/davis-dance-twirl result folder")
    ap.add_argument("--walk", type=Path, help="benchmarks/real_video.py's WORK/sports2d-walk result folder")
    ap.add_argument("--out", type=Path, help="write PREFIX.json and PREFIX.md")
    args = ap.parse_args(argv)
    variants = json.loads(args.variants)
    if not isinstance(variants, dict) or not variants or not all(isinstance(v, dict) for v in variants.values()):
        raise SystemExit('--variants must be a JSON object of named setting objects, e.g. {"a": {}, "b": {...}}')
    for over in variants.values():
        TrackerConfig.from_dict(over)  # a misspelt setting fails here, before any work
    suites: dict = {}
    with tempfile.TemporaryDirectory(prefix="flowmocap-post-steps-") as tmp:
        work = Path(tmp)
        for d in args.diverse:
            suites[f"diverse {d}"] = diverse_rows(d, variants, work)
        if args.real3d:
            suites[f"real3d {args.real3d}"] = real3d_rows(args.real3d, variants, work)
        if args.davis:
            suites[f"davis {args.davis}"] = clip_rows(args.davis, variants, work, davis=True)
        if args.walk:
            suites[f"walk {args.walk}"] = clip_rows(args.walk, variants, work, davis=False)
    text = "\n".join(_table(t, rows) for t, rows in suites.items())
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        summary = {t: {n: _summary(r, rows[next(iter(rows))] if n != next(iter(rows)) else None)
                       for n, r in rows.items()} for t, rows in suites.items()}
        args.out.with_suffix(".json").write_text(json.dumps({"variants": variants, "suites": suites,
                                                             "summary": summary}, indent=1))
        args.out.with_suffix(".md").write_text(f"Variants: `{json.dumps(variants)}`\n\n{text}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
