"""The lifter refit (``lifter_refit_weight``, :mod:`flowmocap.fit.lift_refit`) applied to
finished runs of the three issue-18 suites and scored before and after.

The refit is a pass after tracking, so it can be judged on runs that were made without
it: the tracking is the same, only the finished motion changes. For each suite given:

- ``--real3d DIR`` (a ``flowmocap bench --suite real3d`` folder): per person-view the
  per-frame and per-sequence PA-MPJPE (mm) on the suite's own frames and joints
  (:func:`flowmocap.eval.real3d.scored_frames`), before and after;
- ``--diverse DIR`` (a diverse bench or ``tracker_only.py`` folder) and ``--seeds DIR``
  (a ``benchmarks/track_seeds.py --work`` folder, CMU 35_01): per clip the local and
  global error (cm), the 2D error of the 24 joints against the truth (px) and the
  acceleration error (mm/frame^2, :func:`flowmocap.eval.metrics.acceleration_error`), before
  and after.

Usage: python benchmarks/lifter_refit.py [--real3d DIR] [--diverse DIR] [--seeds DIR]
       [--weight 0.5] [--pixel-sigma PX] [--lifter FILE] [--blend full|depth]
       [--lifter-input detector|fit|agree|unswap] [--iterations 60] [--smooth-after S]
       [--smooth-poses S] [--stance SHARE] [--raw-detections] [--lifter-flip] [--reg RAD] [--sigma M]
       [--seam-s S] [--out PREFIX]

``--smooth-after 0.5`` smooths the refitted root depth again, as the pipeline's defaults do
(``lifter_refit_smooth_depth``); without it the table is the refit alone. ``--smooth-poses
0.3`` then smooths the poses and translation (``pose_smoothing_s``,
:func:`flowmocap.fit.smooth.pose_smoothed_motion`), the pipeline's last step; with both, the
"after" columns are what the defaults write (with ``--stance 0.5`` too, the stance depth
correction between the two, ``stance_depth_share``). ``--blend`` says how the targets blend:
all three coordinates (``full``, the default, as the pipeline's ``lifter_refit_blend``; with the
pipeline's hold add ``--pixel-sigma 4``) or the depth only (``depth``, the default until 2026-11-28).

``--lifter FILE``: another lifter file (``tools/train_lifter.py --out``) instead of the packaged one.
``--lifter-mean FILE [FILE ...]``: the refit's lifter the mean of several lifter files (``-``
for the packaged one), an ensemble (docs/experiments.md, twenty-first session: not adopted).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from flowmocap.body import load_body_model
from flowmocap.body.skeleton import EVAL_JOINTS
from flowmocap.eval import metrics as M
from flowmocap.fit.lift_refit import lifter_refit_motion
from flowmocap.fit.smooth import depth_smoothed_motion, pose_smoothed_motion, stance_depth_motion
from flowmocap.fit.swap import exchanged_frames
from flowmocap.io.results import read_result
from flowmocap.pipeline import _reinit_frames, _reinit_frames_3d
from flowmocap.vision.auto import load_detections

E = list(EVAL_JOINTS)
_MODELS: dict = {}


class MeanLifter:
    """Several lifters as one: :meth:`lift_points` is the mean of theirs (``(T, 13, 3)``
    metres, hip-centred; NaN where any gives none). ``files``: lifter files, None for the
    packaged one."""

    def __init__(self, files):
        from flowmocap.vision.lifter import Lifter

        if not files:
            raise ValueError("MeanLifter needs at least one lifter file")
        self.lifters = [Lifter.load(f) for f in files]

    @property
    def temporal(self) -> bool:
        return any(lf.temporal for lf in self.lifters)

    def lift_points(self, points, mask, fps=None):
        return np.mean([lf.lift_points(points, mask, fps=fps) for lf in self.lifters], axis=0)


#: Further keyword arguments of lifter_refit_motion (``--pixel-sigma``, ``--lifter``).
OPTIONS: dict = {}
#: The window (s) of the depth smoothing after the refit, 0: none (``--smooth-after``).
SMOOTH_S = 0.0
#: The window (s) of the pose smoothing last, 0: none (``--smooth-poses``).
POSES_S = 0.0
#: Whether the lifter reads the frames the tracker exchanged left for right exchanged back,
#: as the pipeline does (``--raw-detections``: as they came, as the pipeline did before).
EXCHANGED = True
#: The share of the stance depth correction after the refit, 0: none (``--stance``).
STANCE = 0.0


def _refit(res: Path, weight: float, track=None):
    motion, _ = read_result(res)
    gender = str(np.asarray(motion.get("gender", "neutral")))
    model = _MODELS.setdefault(gender, load_body_model("default", gender=gender))
    track = load_detections(res) if track is None else track
    if track is None:
        raise SystemExit(f"{res} holds no detections: the refit needs the detector's 2D keypoints")
    run = json.loads((res / "run.json").read_text())
    exchanged = exchanged_frames(run.get("events", [])) if EXCHANGED else None
    refit, info = lifter_refit_motion(motion, track, model, weight=weight, exchanged=exchanged,
                                      seams=_reinit_frames(run, include_eased=True), ease=_reinit_frames_3d(run),
                                      **OPTIONS)
    reinits = _reinit_frames({**run, "lifter_refit": info})  # as the pipeline: not at the seams eased
    if SMOOTH_S and "trans_tracked" in motion:  # as the pipeline does (lifter_refit_smooth_depth)
        refit = depth_smoothed_motion(refit, SMOOTH_S, breaks=reinits)
    if STANCE:  # as the pipeline does next (stance_depth_share, its other settings the defaults)
        refit, _ = stance_depth_motion(refit, STANCE, breaks=reinits)
    if POSES_S:  # as the pipeline does last (pose_smoothing_s)
        refit, _ = pose_smoothed_motion(refit, model, POSES_S, breaks=reinits)
    return motion, refit, info


def real3d_rows(bench: Path, weight: float) -> list[dict]:
    from flowmocap.eval import real3d as R

    rows = []
    for res, _, _, d in R.scored_runs(bench):
        motion, refit, info = _refit(res, weight, d["detections"])
        at = {int(f): k for k, f in enumerate(motion["frame_index"])}
        after = np.stack([np.asarray(refit["joints3d"][at[f]], np.float64)[E] for f in d["used"]])
        b = R.pa_mpjpe(d["ours"], d["ref"], d["valid"])
        a = R.pa_mpjpe(after, d["ref"], d["valid"])
        # the body at the detector's keypoints (the reference's own convention; the bench's "ours at keypoints")
        kp_after = R.keypoint_joints(SimpleNamespace(motion=refit, poses=refit["poses"], trans=refit["trans"],
                                                     betas=refit["betas"]))
        kp_after = np.stack([kp_after[at[f]] for f in d["used"]])
        rows.append({"name": res.name, "frames": len(d["used"]), "before_per_frame_mm": b[0], "after_per_frame_mm": a[0],
                     "before_per_sequence_mm": b[1], "after_per_sequence_mm": a[1],
                     "mediapipe_per_frame_mm": R.pa_mpjpe(d["detector"], d["ref"], d["valid"])[0],
                     "after_at_keypoints_mm": R.pa_mpjpe(kp_after, d["ref"], d["valid"])[0], **info})
    return rows


def synthetic_rows(pairs: list[tuple[str, Path, Path]], weight: float) -> list[dict]:
    """``pairs``: (name, sequence folder, result folder)."""
    rows = []
    for name, seq, res in pairs:
        if not (res / "motion.npz").exists() or not (seq / "gt.npz").exists():
            continue
        motion, refit, info = _refit(res, weight)
        gt = np.load(seq / "gt.npz")
        idx = np.asarray(motion["frame_index"], int)
        g3, g2 = np.asarray(gt["joints3d"], np.float64)[idx], np.asarray(gt["joints2d"], np.float64)[idx]
        row = {"name": name, "frames": int(idx.size), **info}
        for when, m in (("before", motion), ("after", refit)):
            p3 = np.asarray(m["joints3d"], np.float64)
            row[f"{when}_local_cm"] = 100 * float(M.local_procrustes_error(p3, g3).mean())
            row[f"{when}_global_cm"] = 100 * float(M.global_procrustes_error(p3, g3).mean())
            row[f"{when}_px"] = float(np.linalg.norm(np.asarray(m["joints2d"], np.float64) - g2, axis=-1).mean())
            row[f"{when}_accel_mm"] = 1000 * float(M.acceleration_error(p3, g3).mean()) if len(p3) >= 3 else float("nan")
        rows.append(row)
    return rows


def _summary(rows: list[dict], keys: list[str]) -> dict:
    out = {}
    for k in keys:
        v = np.array([r[k] for r in rows], float)
        out[k] = {"median": float(np.median(v)) if v.size else None, "mean": float(v.mean()) if v.size else None}
    return out


def _table(title: str, rows: list[dict], keys: list[str]) -> str:
    lines = [f"### {title}", "", "| run | " + " | ".join(keys) + " |", "|---|" + "---:|" * len(keys)]
    for r in rows:
        lines.append(f"| {r['name']} | " + " | ".join(f"{r[k]:.2f}" for k in keys) + " |")
    s = _summary(rows, keys)
    for stat in ("median", "mean"):
        lines.append(f"| **{stat}** ({len(rows)}) | " + " | ".join(
            "--" if s[k][stat] is None else f"{s[k][stat]:.2f}" for k in keys) + " |")
    better = sum(1 for r in rows if r[keys[1]] < r[keys[0]])
    lines.append(f"\n{keys[1]} below {keys[0]} on {better} of {len(rows)}\n")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--real3d", type=Path)
    ap.add_argument("--diverse", type=Path)
    ap.add_argument("--seeds", type=Path, help="a benchmarks/track_seeds.py --work folder")
    ap.add_argument("--weight", type=float, default=0.5)
    ap.add_argument("--pixel-sigma", type=float, help="hold the tracked 24 joints' image at this scale (px)")
    ap.add_argument("--lifter", type=Path, help="a lifter file instead of the packaged one")
    ap.add_argument("--lifter-mean", nargs="+", metavar="FILE",
                    help="the mean of these lifter files ('-': the packaged one) instead of one lifter")
    ap.add_argument("--iterations", type=int, default=60,
                    help="L-BFGS iterations of the refit (lifter_refit_iterations; 20 before 2026-11-27's eleventh session)")
    ap.add_argument("--blend", choices=("full", "depth"), default="full",
                    help="the refit's targets: all three coordinates blended (the pipeline's default) or the depth only")
    ap.add_argument("--lifter-input", choices=("detector", "fit", "agree", "unswap"), default="detector",
                    help="the 2D the lifter reads: the detection's keypoints or the fit's own, projected")
    ap.add_argument("--smooth-after", type=float, default=0.0,
                    help="smooth the refitted root depth over this window (s), as the pipeline does with "
                         "lifter_refit_smooth_depth (its window: depth_smoothing_s, 0.5); 0: not")
    ap.add_argument("--smooth-poses", type=float, default=0.0,
                    help="then smooth the poses and translation over this window (s), as the pipeline does last "
                         "with pose_smoothing_s (0.3); 0: not")
    ap.add_argument("--stance", type=float, default=0.0,
                    help="then move each frame so that a foot standing still keeps its depth, at this share, as the "
                         "pipeline does with stance_depth_share (0.5); 0: not")
    ap.add_argument("--lifter-flip", action="store_true",
                    help="the lifter averages each input with its mirror image (Lifter.flip_average)")
    ap.add_argument("--raw-detections", action="store_true",
                    help="the lifter reads every detection as it came, also those the tracker exchanged left for "
                         "right (the pipeline before 2026-11-27's thirteenth session)")
    ap.add_argument("--reg", type=float, default=0.3,
                    help="the refit's pull towards the tracked joint rotations, radians (lifter_refit_motion's reg)")
    ap.add_argument("--sigma", type=float, default=0.02,
                    help="the refit's scale of the keypoint targets, metres (lifter_refit_motion's sigma)")
    ap.add_argument("--vote-frames", type=int, default=0,
                    help="mirror a limb in depth over each run of at least this many frames where the sources "
                         "reach the other way (lifter_refit_motion's vote_min_frames); 0: not")
    ap.add_argument("--vote-reach", type=float, default=0.08,
                    help="metres: the reach along the camera's axis a vote needs (vote_min_reach)")
    ap.add_argument("--vote-sources", choices=("lifter", "detector", "both"), default="detector",
                    help="who votes: the lifter, the detector's own 3D, or both (vote_sources)")
    ap.add_argument("--vote-no-2d", action="store_true",
                    help="mirror an upper arm or thigh even where its wrist or ankle then lies further from the "
                         "detected one (vote_check_2d false)")
    ap.add_argument("--seam-s", type=float, default=0.0,
                    help="ease the jump at each re-initialisation on 3D disagreement into this many seconds before "
                         "it and smooth across it afterwards, as the pipeline's lifter_refit_seam_s (0.3); 0: not")
    ap.add_argument("--out")
    a = ap.parse_args()
    OPTIONS.update(vote_min_frames=a.vote_frames, vote_min_reach=a.vote_reach, vote_sources=a.vote_sources,
                   vote_check_2d=not a.vote_no_2d, seam_s=a.seam_s)
    OPTIONS["reg"], OPTIONS["sigma"] = a.reg, a.sigma
    if not (a.real3d or a.diverse or a.seeds):
        ap.error("give at least one of --real3d, --diverse, --seeds")
    if a.pixel_sigma:
        OPTIONS["pixel_sigma"] = a.pixel_sigma
    OPTIONS["blend"] = a.blend
    OPTIONS["lifter_input"] = a.lifter_input
    OPTIONS["iterations"] = a.iterations
    if a.lifter_mean and (a.lifter or a.lifter_flip):
        ap.error("--lifter-mean goes without --lifter and --lifter-flip")
    if a.lifter_mean:
        OPTIONS["lifter"] = MeanLifter([None if f == "-" else Path(f) for f in a.lifter_mean])
    if a.lifter or a.lifter_flip:
        from flowmocap.vision.lifter import Lifter

        OPTIONS["lifter"] = Lifter.load(a.lifter)  # the packaged one without --lifter
        OPTIONS["lifter"].flip_average = a.lifter_flip
    global SMOOTH_S, POSES_S, EXCHANGED, STANCE
    EXCHANGED = not a.raw_detections
    STANCE = a.stance
    SMOOTH_S = a.smooth_after
    POSES_S = a.smooth_poses
    result = {"weight": a.weight, "pixel_sigma": a.pixel_sigma, "blend": a.blend, "lifter_input": a.lifter_input,
              "iterations": a.iterations, "reg": a.reg, "sigma": a.sigma,
              "lifter": str(a.lifter) if a.lifter else "packaged",
              "smooth_after_s": a.smooth_after, "smooth_poses_s": a.smooth_poses,
              "exchanged_as_tracked": not a.raw_detections, "lifter_flip": a.lifter_flip, "stance_share": a.stance,
              "vote_min_frames": a.vote_frames, "vote_min_reach": a.vote_reach, "vote_sources": a.vote_sources,
              "vote_check_2d": not a.vote_no_2d}
    md = [f"# The lifter refit at weight {a.weight:g}"
          f"{f', image held at {a.pixel_sigma:g} px' if a.pixel_sigma else ''} on finished runs\n"]
    syn_keys = ["before_local_cm", "after_local_cm", "before_global_cm", "after_global_cm", "before_px", "after_px",
                "before_accel_mm", "after_accel_mm", "mean_move_px", "limb_frames_voted"]
    if a.real3d:
        rows = real3d_rows(a.real3d, a.weight)
        keys = ["before_per_frame_mm", "after_per_frame_mm", "before_per_sequence_mm", "after_per_sequence_mm",
                "mediapipe_per_frame_mm", "after_at_keypoints_mm",
                "mean_move_px", "limb_frames_voted"]
        result["real3d"] = {"dir": str(a.real3d), "rows": rows, "summary": _summary(rows, keys)}
        md.append(_table("real3d", rows, keys))
    if a.diverse:
        pairs = [(d.name, d / "sequence", d / "flowmocap") for d in sorted(a.diverse.iterdir()) if d.is_dir()]
        rows = synthetic_rows(pairs, a.weight)
        result["diverse"] = {"dir": str(a.diverse), "rows": rows, "summary": _summary(rows, syn_keys)}
        md.append(_table("diverse", rows, syn_keys))
    if a.seeds:
        pairs = []
        for seq in sorted(a.seeds.glob("seq_s*")):
            for res in sorted(p for p in seq.iterdir() if p.is_dir() and (p / "result").is_dir()):
                pairs.append((f"{seq.name}/{res.name}", res / "sequence" if (res / "sequence" / "gt.npz").exists()
                              else seq / "sequence", res / "result"))
        rows = synthetic_rows(pairs, a.weight)
        result["seeds"] = {"dir": str(a.seeds), "rows": rows, "summary": _summary(rows, syn_keys)}
        md.append(_table("CMU 35_01 seeds", rows, syn_keys))
    text = "\n".join(md)
    print(text)
    if a.out:
        Path(f"{a.out}.json").write_text(json.dumps(result, indent=1))
        Path(f"{a.out}.md").write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
