"""Does ``motion.npz``'s ``disagreement`` flag the joints that are wrong? Measured on
finished runs of the issue-18 suites.

The pipeline's post-pass (the lifter refit, the depth smoothed again, the stance depth
correction and the pose smoothing, at :class:`~flowmocap.fit.config.TrackerConfig`'s
defaults, through ``benchmarks/lifter_refit.py``) is applied to each finished run (runs
made with the post-pass off, or with it undone); the refit gives each frame and scored
joint its disagreement (:mod:`flowmocap.fit.disagreement`). Each frame of the finished
motion is scored against the reference on the 13 joints after a similarity per frame
(mm; real3d: the suite's own frames and joints, :func:`flowmocap.eval.real3d.scored_frames`;
diverse: the rendered truth), and the table says how well the disagreement ranks those
errors:

- ``spearman``: rank correlation between disagreement and error over joint-frames;
- ``auroc_top10``: area under the ROC curve of the disagreement as a detector of the
  tenth of joint-frames with the largest error (0.5: no better than chance);
- ``precision_top10``: of the tenth of joint-frames with the largest disagreement, the
  share that are among the tenth with the largest error (chance: 0.10);
- ``error_flagged_mm`` / ``error_rest_mm``: mean error of that flagged tenth and of the rest;
- ``frame_auroc_top10``: the same AUROC per frame (mean over its joints of both).

Usage: python benchmarks/disagreement.py [--real3d DIR] [--diverse DIR ...] [--out PREFIX]
(``--diverse`` takes ``flowmocap bench --suite diverse`` or ``tune`` folders, or
``benchmarks/tracker_only.py`` folders: one subfolder per clip with ``sequence/`` and
``flowmocap/``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.stats import rankdata, spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parent))
import lifter_refit as L  # noqa: E402

from flowmocap.body.skeleton import EVAL_JOINTS  # noqa: E402
from flowmocap.fit.config import TrackerConfig  # noqa: E402
from flowmocap.geometry.procrustes import similarity_procrustes  # noqa: E402

E = list(EVAL_JOINTS)


def use_pipeline_defaults() -> dict:
    """Set ``lifter_refit``'s post-pass to the pipeline's defaults; returns them."""
    c = TrackerConfig()
    L.OPTIONS.update(pixel_sigma=c.lifter_refit_pixel_sigma or None, blend=c.lifter_refit_blend,
                     iterations=c.lifter_refit_iterations, vote_min_frames=c.lifter_refit_vote_frames,
                     vote_min_reach=c.lifter_refit_vote_reach, vote_sources=c.lifter_refit_vote_sources)
    L.SMOOTH_S = c.depth_smoothing_s if c.lifter_refit_smooth_depth else 0.0
    L.STANCE, L.POSES_S, L.EXCHANGED = c.stance_depth_share, c.pose_smoothing_s, c.detector_swap_check
    return {"weight": c.lifter_refit_weight, **{k: v for k, v in L.OPTIONS.items() if not callable(v)},
            "smooth_depth_s": L.SMOOTH_S, "stance": L.STANCE, "pose_smoothing_s": L.POSES_S}


def per_joint_error(pred: np.ndarray, ref: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(T, P)`` metres: each valid point's distance from the reference after a similarity
    per frame fitted on the frame's valid points (NaN for the others, and for frames with
    fewer than 4 valid points)."""
    pred, ref = np.asarray(pred, np.float64), np.asarray(ref, np.float64)
    valid = np.asarray(valid, bool) & np.isfinite(ref).all(-1) & np.isfinite(pred).all(-1)
    out = np.full(valid.shape, np.nan)
    use = np.flatnonzero(valid.sum(1) >= 4)
    if use.size:
        w = valid[use].astype(np.float64)
        aligned = similarity_procrustes(np.nan_to_num(pred[use]), np.nan_to_num(ref[use]), weights=w)[0]
        d = np.linalg.norm(aligned - np.nan_to_num(ref[use]), axis=-1)
        out[use] = np.where(valid[use], d, np.nan)
    return out


def auroc(score: np.ndarray, positive: np.ndarray) -> float:
    """Area under the ROC curve of ``score`` for the ``positive`` (bool) entries (ties
    count half; the Mann-Whitney form); NaN without both classes."""
    score, positive = np.asarray(score, np.float64), np.asarray(positive, bool)
    n1, n0 = int(positive.sum()), int((~positive).sum())
    if not n1 or not n0:
        return float("nan")
    r = rankdata(score)
    return float((r[positive].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def flag_scores(dis: np.ndarray, err: np.ndarray, share: float = 0.1) -> dict:
    """The table's figures for paired ``dis`` and ``err`` (any shape, NaN pairs left out):
    ``spearman``, ``auroc_top10``, ``precision_top10``, ``error_flagged_mm``,
    ``error_rest_mm`` and ``n``; ``share`` is the tenth (0.1)."""
    dis, err = np.ravel(dis), np.ravel(err)
    ok = np.isfinite(dis) & np.isfinite(err)
    dis, err = dis[ok], err[ok]
    if dis.size < 10:
        return {"n": int(dis.size)}
    bad = err > np.quantile(err, 1 - share)
    flagged = dis > np.quantile(dis, 1 - share)
    return {"n": int(dis.size), "spearman": float(spearmanr(dis, err)[0]), "auroc_top10": auroc(dis, bad),
            "precision_top10": float(bad[flagged].mean()) if flagged.any() else float("nan"),
            "error_flagged_mm": 1000 * float(err[flagged].mean()) if flagged.any() else float("nan"),
            "error_rest_mm": 1000 * float(err[~flagged].mean())}


def real3d_pairs(bench: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    from flowmocap.eval import real3d as R

    out = []
    for res, _, _, d in R.scored_runs(bench):
        motion, refit, _ = L._refit(res, TrackerConfig().lifter_refit_weight, d["detections"])
        at = {int(f): k for k, f in enumerate(motion["frame_index"])}
        rows = [at[f] for f in d["used"]]
        pred = np.asarray(refit["joints3d"], np.float64)[rows][:, E]
        dis = np.asarray(refit["disagreement"], np.float64)[rows][:, E]
        out.append((res.name, dis, per_joint_error(pred, d["ref"], d["valid"])))
    return out


def synthetic_pairs(suite: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    out = []
    for clip in sorted(p for p in suite.iterdir() if p.is_dir()):
        res, seq = clip / "flowmocap", clip / "sequence"
        if not (res / "motion.npz").exists() or not (seq / "gt.npz").exists():
            continue
        motion, refit, _ = L._refit(res, TrackerConfig().lifter_refit_weight)
        idx = np.asarray(motion["frame_index"], int)
        gt = np.asarray(np.load(seq / "gt.npz")["joints3d"], np.float64)[idx][:, E]
        pred = np.asarray(refit["joints3d"], np.float64)[:, E]
        dis = np.asarray(refit["disagreement"], np.float64)[:, E]
        out.append((clip.name, dis, per_joint_error(pred, gt, np.ones(gt.shape[:2], bool))))
    return out


def suite_row(name: str, pairs) -> dict:
    dis = np.concatenate([p[1].ravel() for p in pairs])
    err = np.concatenate([p[2].ravel() for p in pairs])
    fd = np.concatenate([np.nanmean(np.where(np.isfinite(p[2]), p[1], np.nan), 1) for p in pairs])
    fe = np.concatenate([np.nanmean(p[2], 1) for p in pairs])
    row = {"suite": name, "runs": len(pairs), **flag_scores(dis, err)}
    f = flag_scores(fd, fe)
    row["frame_auroc_top10"] = f.get("auroc_top10", float("nan"))
    row["frame_precision_top10"] = f.get("precision_top10", float("nan"))
    per_run = [flag_scores(p[1], p[2]).get("auroc_top10", float("nan")) for p in pairs]
    row["run_auroc_min"], row["run_auroc_median"] = float(np.nanmin(per_run)), float(np.nanmedian(per_run))
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real3d", type=Path)
    ap.add_argument("--diverse", type=Path, nargs="*", default=[])
    ap.add_argument("--out")
    a = ap.parse_args()
    if not a.real3d and not a.diverse:
        ap.error("give --real3d and/or --diverse")
    settings = use_pipeline_defaults()
    rows = []
    if a.real3d:
        rows.append(suite_row(f"real3d ({a.real3d.name})", real3d_pairs(a.real3d)))
        print(rows[-1], flush=True)
    for d in a.diverse:
        rows.append(suite_row(f"renders ({d.name})", synthetic_pairs(d)))
        print(rows[-1], flush=True)
    keys = ["runs", "n", "spearman", "auroc_top10", "precision_top10", "error_flagged_mm", "error_rest_mm",
            "frame_auroc_top10", "frame_precision_top10", "run_auroc_min", "run_auroc_median"]
    md = ["# The 3D sources' disagreement as a flag for wrong joints (finished runs, today's post-pass)\n",
          "| suite | " + " | ".join(keys) + " |", "|---|" + "---:|" * len(keys)]
    for r in rows:
        md.append(f"| {r['suite']} | " + " | ".join(
            (f"{r[k]:.2f}" if isinstance(r.get(k), float) else str(r.get(k, ""))) for k in keys) + " |")
    text = "\n".join(md)
    print(text)
    if a.out:
        Path(f"{a.out}.json").write_text(json.dumps({"settings": settings, "rows": rows}, indent=1, default=str))
        Path(f"{a.out}.md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
