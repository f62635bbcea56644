"""Could the refit choose, joint by joint, which 3D source to trust? (issue 18)

The refit blends the tracked fit with the keypoint lifter at one share for every joint and
frame (``lifter_refit_weight`` 0.5). This script asks how much a share chosen per joint
and frame could give, and whether anything observable at run time tells which source is
the better one. Three sources of the 13 evaluation points per frame, all aligned onto the
lifter's by a similarity per frame:

- ``fit``: the tracked body's keypoints (a run tracked with the post-pass off, or with
  it undone, e.g. ``benchmarks/lifter_refit.py``'s inputs);
- ``lifter``: the packaged keypoint lifter of the detector's 2D
  (:func:`flowmocap.vision.lifter.lifted_track`);
- ``mediapipe``: MediaPipe's own world landmarks.

What it reports, per suite:

1. **By keypoint confidence** and **by the lifter's own spread** (the standard deviation of
   ``--mc`` lifts with the network's dropout left on, Monte-Carlo dropout, per point, cm):
   each source's mean point error (cm) in each bin, the reference aligned onto the
   sources' mean by a similarity per frame.
2. **Blends scored as the suite scores a method**: each frame's blend aligned onto the
   reference by a similarity, its mean point error over the scored points, averaged over
   the frames (mm; for real3d the suite's per-frame PA-MPJPE on its own frames and joints,
   for diverse the same over the 13 points of every frame where the lifter and MediaPipe
   give them: not the bench's local error over 24 joints). Rules: one share everywhere;
   shares gated by keypoint confidence; a share that falls with the lifter's spread; the
   three sources mixed; a random pick among the shares 0, 0.5 and 1 per point; limb by limb,
   the fit's limb where the lifter's bones are off their usual length (:func:`bone_deviation`);
   with ``--plausibility``, limb by limb the source whose limb lies nearest a real one of the
   mocap train clips in the torso's frame (:class:`LimbPlausibility`); and an
  **oracle** that picks for every point and frame the best of
   the shares 0, 0.5 and 1 of the lifter by the reference (a bound no rule can pass;
   it also profits from picking among noisy candidates, so it is loose).

The blends are not methods (the result is no longer a body with fixed bones); as with
``benchmarks/fusion_bound.py`` they bound what a refit towards such targets could reach.

Usage: python benchmarks/source_selection.py [--real3d DIR] [--diverse DIR] [--mc 16] [--plausibility
       [--poses-cache FILE]] [--out PREFIX]
  DIR: a ``flowmocap bench --suite real3d`` folder, or a diverse ``tracker_only.py`` folder
  (post-pass off). Writes PREFIX.json and PREFIX.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from flowmocap.geometry.procrustes import similarity_procrustes

#: the lifter's shares the oracle picks among
ORACLE_SHARES = (0.0, 0.5, 1.0)
CONF_BINS = (0.0, 0.3, 0.5, 0.7, 0.9, 1.01)


def _onto(x: np.ndarray, ref: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x aligned onto ref (T, P, 3), scored (T,))``: a similarity per frame fitted on the
    points ``valid (T, P)`` only; frames with fewer than 4 of them are not scored."""
    w = np.asarray(valid, bool) & np.isfinite(ref).all(-1) & np.isfinite(x).all(-1)
    zero = lambda a: np.where(w[..., None], a, 0.0)  # left-out points: weight 0, no NaN in the SVD
    scored = w.sum(1) >= 4
    aligned = np.full(x.shape, np.nan)
    if scored.any():
        aligned[scored] = similarity_procrustes(zero(x)[scored], zero(ref)[scored], weights=w[scored].astype(float))[0]
    return aligned, scored


def frame_errors(x: np.ndarray, ref: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(T,)`` each frame's mean point error (metres) of ``x (T, P, 3)`` after a similarity
    onto ``ref (T, P, 3)`` over the points ``valid (T, P)``; NaN for frames with fewer
    than 4 valid points."""
    aligned, scored = _onto(x, ref, valid)
    w = np.asarray(valid, bool)
    d = np.where(w, np.linalg.norm(aligned - ref, axis=-1), 0.0).sum(1)
    return np.where(scored, d / np.maximum(w.sum(1), 1), np.nan)


def point_errors(sources: list[np.ndarray], ref: np.ndarray, valid: np.ndarray) -> list[np.ndarray]:
    """Each source's ``(T, P)`` point errors (metres; NaN where not valid), the reference
    aligned per frame by a similarity onto the sources' mean (so no source is favoured)."""
    r, scored = _onto(ref, np.mean(sources, axis=0), valid)
    keep = np.asarray(valid, bool) & scored[:, None]
    return [np.where(keep, np.linalg.norm(s - r, axis=-1), np.nan) for s in sources]


def oracle_blend(fit: np.ndarray, lift: np.ndarray, ref: np.ndarray, valid: np.ndarray,
                 shares=ORACLE_SHARES) -> np.ndarray:
    """``(T, P, 3)``: for every frame and point the blend ``(1 - w) fit + w lift`` with the
    ``w`` of ``shares`` nearest the reference (aligned onto the middle share's blend by a
    similarity per frame); points not valid get the middle share."""
    cands = np.stack([(1.0 - w) * fit + w * lift for w in shares])  # (S, T, P, 3)
    mid = len(shares) // 2
    r, scored = _onto(ref, cands[mid], valid)
    pick = np.linalg.norm(cands - r[None], axis=-1).argmin(0)  # (T, P)
    pick = np.where(np.asarray(valid, bool) & scored[:, None], pick, mid)
    return np.take_along_axis(cands, pick[None, ..., None], 0)[0]


def random_blend(fit: np.ndarray, lift: np.ndarray, shares=ORACLE_SHARES, seed: int = 0) -> np.ndarray:
    """``(T, P, 3)``: for every frame and point the blend with a share of ``shares`` drawn at
    random (seeded): what picking among the oracle's candidates gives without knowledge."""
    w = np.asarray(shares)[np.random.default_rng(seed).integers(0, len(shares), fit.shape[:2])][..., None]
    return (1.0 - w) * fit + w * lift


def blend3(fit, lift, mp, a, b):
    """``(1 - a - b) fit + a lift + b mp`` with per-point shares ``a, b`` (scalars or ``(T, P)``)."""
    a = np.broadcast_to(a, fit.shape[:2])[..., None]
    b = np.broadcast_to(b, fit.shape[:2])[..., None]
    return (1.0 - a - b) * fit + a * lift + b * mp


#: the rule the others are compared with
BASE_RULE = "share 0.5 everywhere (today's refit targets)"
#: the rules scored, as (name, function of one run's dict -> (T, P, 3))
RULES = (
    ("fit alone", lambda r: r["fit"]),
    ("lifter alone", lambda r: r["lift"]),
    ("share 0.5 everywhere (today's refit targets)", lambda r: blend3(r["fit"], r["lift"], r["mp"], 0.5, 0.0)),
    ("confidence < 0.3: fit alone", lambda r: blend3(r["fit"], r["lift"], r["mp"], np.where(r["conf"] < 0.3, 0.0, 0.5), 0.0)),
    ("confidence < 0.5: MediaPipe 0.5, lifter 0.25", lambda r: blend3(
        r["fit"], r["lift"], r["mp"], np.where(r["conf"] < 0.5, 0.25, 0.5), np.where(r["conf"] < 0.5, 0.5, 0.0))),
    ("confidence < 0.3: MediaPipe 0.5, lifter 0", lambda r: blend3(
        r["fit"], r["lift"], r["mp"], np.where(r["conf"] < 0.3, 0.0, 0.5), np.where(r["conf"] < 0.3, 0.5, 0.0))),
    ("lifter share 0.5 / (1 + (spread / 5 cm)^2), x1.36", lambda r: blend3(
        r["fit"], r["lift"], r["mp"], np.clip(0.5 * 1.36 / (1.0 + (r["spread"] / 0.05) ** 2), 0, 1), 0.0)),
    ("the three sources' mean", lambda r: (r["fit"] + r["lift"] + r["mp"]) / 3.0),
    ("fit 0.4, lifter 0.4, MediaPipe 0.2", lambda r: blend3(r["fit"], r["lift"], r["mp"], 0.4, 0.2)),
    ("a random pick of lifter shares 0 / 0.5 / 1 per point (the oracle's chance level)", lambda r: random_blend(
        r["fit"], r["lift"])),
    ("oracle: best of lifter shares 0 / 0.5 / 1 per point", lambda r: oracle_blend(r["fit"], r["lift"], r["ref"], r["valid"])),
)

# ------------------------------------------------ limb by limb: plausibility and bone lengths (twenty-third session)

#: each limb of the 13 points (order of EVAL_JOINTS: head, shoulders, elbows, wrists, hips,
#: knees, ankles, left before right) as (root, middle, end); a limb rule replaces the middle
#: and end points
LIMBS = {"left arm": (1, 3, 5), "right arm": (2, 4, 6), "left leg": (7, 9, 11), "right leg": (8, 10, 12)}
#: a limb whose bones differ from their median over the run by more than this share (the
#: largest of its two bones) is "off" in :func:`bone_deviation`'s rule
BONE_TOLERANCES = (0.15, 0.2)


def torso_frame(x: np.ndarray) -> np.ndarray:
    """``(..., 13, 3)`` points in the torso's own frame: origin at the middle of the hips, y
    towards the middle of the shoulders, x along hips and shoulders from right to left (made
    perpendicular to y), z = x cross y; divided by the hips-to-shoulders length. Unchanged by
    any similarity of the input (a rotation, a scale, a translation)."""
    x = np.asarray(x, np.float64)
    mh = 0.5 * (x[..., 7, :] + x[..., 8, :])
    up = 0.5 * (x[..., 1, :] + x[..., 2, :]) - mh
    size = np.linalg.norm(up, axis=-1, keepdims=True)
    y = up / size
    a = (x[..., 7, :] - x[..., 8, :]) + (x[..., 1, :] - x[..., 2, :])
    a = a - (a * y).sum(-1, keepdims=True) * y
    ax = a / np.linalg.norm(a, axis=-1, keepdims=True)
    rows = np.stack([ax, y, np.cross(ax, y)], -2)
    return np.einsum("...ij,...kj->...ki", rows, x - mh[..., None, :]) / size[..., None]


def limb_features(x: np.ndarray) -> dict[str, np.ndarray]:
    """Per limb of :data:`LIMBS`, ``(..., 6)``: its middle and end points relative to its root
    in :func:`torso_frame`."""
    c = torso_frame(x)
    return {name: np.concatenate([c[..., m, :] - c[..., r, :], c[..., e, :] - c[..., r, :]], -1)
            for name, (r, m, e) in LIMBS.items()}


class LimbPlausibility:
    """How far each limb of a pose is from the nearest limb of a set of real poses
    (:func:`limb_features`, nearest neighbour): small for a limb placed as people place
    theirs relative to the torso, large for one that is not.

    Args:
        points: ``(N, 13, 3)`` real poses (e.g. :func:`mocap_points`), metres, any axes.
    """

    def __init__(self, points: np.ndarray):
        from scipy.spatial import cKDTree

        self.size = len(points)
        self.trees = {k: cKDTree(v) for k, v in limb_features(points).items()}

    def distance(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Per limb ``(T,)``: the distance to the nearest real limb (torso lengths) of ``x (T, 13, 3)``."""
        return {k: self.trees[k].query(np.nan_to_num(f), k=1)[0] for k, f in limb_features(x).items()}


def mocap_points(cache: Path | None = None, step: int = 2, bodies: int = 2, seed: int = 0) -> np.ndarray:
    """``(N, 13, 3)`` the detector's 13 points (learned keypoint offsets, head at the middle of
    the ears) on every ``step``-th frame of the ``train`` clips of ``mocap/prior``, each on
    ``bodies`` random bodies and also mirrored left for right, as ``tools/train_lifter.py``
    makes its training data (no test subject: the held-out suite's clips are not among them).
    ``cache``: the retargeted poses' ``.npz`` of ``tools/train_pose_prior.py --cache``."""
    tools = Path(__file__).resolve().parents[1] / "tools"
    sys.path.insert(0, str(tools))
    from train_lifter import keypoint_points
    from train_pose_prior import DEFAULT_DATA, read_index, retarget_all

    from flowmocap.body import load_body_model
    from flowmocap.fit.pose_prior import mirror_pose
    from flowmocap.vision.keypoint_map import load_keypoint_map

    model = load_body_model("default", gender="neutral")
    every = read_index(DEFAULT_DATA)
    poses = retarget_all(every, DEFAULT_DATA, model, cache)  # all clips, as the tools keep the cache
    rows = [r for r in every if r["split"] == "train"]
    kmap, rng, out = load_keypoint_map(), np.random.default_rng(seed), []
    for r in rows:
        P = poses[r["file"]][::step]
        for _ in range(bodies):
            betas = rng.normal(0, 1, 10)
            out += [keypoint_points(P, betas, model, kmap), keypoint_points(mirror_pose(P), betas, model, kmap)]
    return np.concatenate(out)


def bone_deviation(x: np.ndarray) -> dict[str, np.ndarray]:
    """Per limb ``(T,)``: the larger of its two bones' relative difference from that bone's
    median length over the run (0.2: a bone 20 % longer or shorter than usual). The fit's
    bones have fixed lengths; the lifter's and MediaPipe's do not, and a bone of the wrong
    length is a sign of a point in the wrong place."""
    out = {}
    for name, (r, m, e) in LIMBS.items():
        L = np.stack([np.linalg.norm(x[:, r] - x[:, m], axis=-1), np.linalg.norm(x[:, m] - x[:, e], axis=-1)], 1)
        with np.errstate(all="ignore"):
            out[name] = np.nanmax(np.abs(L / np.nanmedian(L, 0) - 1.0), 1)
    return out


def limb_composite(base: np.ndarray, candidates: dict[str, np.ndarray], pick: dict[str, np.ndarray]) -> np.ndarray:
    """``(T, 13, 3)``: ``base`` with each limb's middle and end points taken, frame by frame,
    from the candidate ``pick[limb] (T,)`` names (a name not among ``candidates`` keeps ``base``)."""
    out = np.array(base, np.float64)
    for name, (_, m, e) in LIMBS.items():
        for key, cand in candidates.items():
            sel = np.asarray(pick[name]) == key
            out[np.ix_(sel, [m, e])] = np.asarray(cand, np.float64)[np.ix_(sel, [m, e])]
    return out


def _half(r):
    return blend3(r["fit"], r["lift"], r["mp"], 0.5, 0.0)


def bone_rule(tolerance: float):
    """Share 0.5, but the fit's points for a limb where the lifter's bones are off by more
    than ``tolerance`` (:func:`bone_deviation`)."""
    def rule(r):
        dev = bone_deviation(r["lift"])
        return limb_composite(_half(r), {"fit": r["fit"]}, {k: np.where(v > tolerance, "fit", "") for k, v in dev.items()})
    return rule


def plausibility_rule(db: LimbPlausibility, margin: float):
    """Share 0.5, but per limb and frame the candidate (fit, lifter, MediaPipe) whose limb is
    nearest a real one, where it is nearer by more than ``margin`` times than the share 0.5's."""
    def rule(r):
        cands = {"fit": r["fit"], "lift": r["lift"], "mp": r["mp"]}
        base = _half(r)
        d0 = db.distance(base)
        d = {k: db.distance(v) for k, v in cands.items()}
        pick = {}
        for limb in LIMBS:
            D = np.stack([d[k][limb] for k in cands])
            best = D.argmin(0)
            better = D.min(0) * margin < d0[limb]
            pick[limb] = np.where(better, np.asarray(list(cands))[best], "")
        return limb_composite(base, cands, pick)
    return rule


RULES = RULES + tuple((f"the lifter's limb bones off by more than {int(100 * t)} %: the fit's limb", bone_rule(t))
                      for t in BONE_TOLERANCES)


def plausibility_rules(db: LimbPlausibility) -> tuple:
    return tuple((f"per limb the most plausible of fit / lifter / MediaPipe where {m:g}x nearer a mocap limb than "
                  "the share 0.5's", plausibility_rule(db, m)) for m in (1.0, 2.0))


def _mc(lift_once, lifter, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``(lifted, spread)``: ``lift_once()`` with the network as trained for inference, and
    the per-point standard deviation (metres) of ``k`` lifts with its dropout on."""
    import torch

    lifter.net.eval()
    base = lift_once()
    if k < 2:
        return base, np.zeros(base.shape[:2])
    lifter.net.train()
    torch.manual_seed(0)
    try:
        s = np.stack([lift_once() for _ in range(k)])
    finally:
        lifter.net.eval()
    s = s - s.mean(axis=2, keepdims=True)  # each lift centred per frame
    return base, np.sqrt(((s - s.mean(0)) ** 2).sum(-1).mean(0))


def _run(name, fit, lift, spread, mp, conf, ref, valid) -> dict | None:
    ok = np.isfinite(lift).all((1, 2)) & np.isfinite(mp).all((1, 2)) & np.isfinite(fit).all((1, 2))
    if not ok.any():
        return None
    return {"name": name, "fit": similarity_procrustes(fit[ok], lift[ok])[0], "lift": lift[ok],
            "mp": similarity_procrustes(mp[ok], lift[ok])[0], "conf": conf[ok], "spread": spread[ok],
            "ref": np.asarray(ref, np.float64)[ok], "valid": np.asarray(valid, bool)[ok] & np.isfinite(ref[ok]).all(-1)}


def collect_real3d(bench_dir: Path, mc: int) -> list[dict]:
    from flowmocap.eval import real3d as R
    from flowmocap.vision.lifter import lifted_track, load_lifter

    lifter = load_lifter()
    runs = []
    for res, _, _, d in R.scored_runs(bench_dir):
        tr, used = d["detections"], d["used"]
        fps = float(np.load(res / "motion.npz")["fps"])
        lift, spread = _mc(lambda: R.eval_points(lifted_track(tr, lifter, fps=fps).world[used]), lifter, mc)
        conf = R.eval_points(np.asarray(tr.confidence, np.float64)[used][..., None])[..., 0]
        r = _run(res.name, np.asarray(d["ours"], np.float64), lift, spread, np.asarray(d["detector"], np.float64),
                 conf, d["ref"], d["valid"])
        if r is not None:
            runs.append(r)
    return runs


def collect_diverse(bench_dir: Path, mc: int) -> list[dict]:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from global_error import camera_joints

    from flowmocap.body.skeleton import EVAL_JOINTS, JOINT_INDEX
    from flowmocap.vision.auto import load_detections
    from flowmocap.vision.detect import KEYPOINT_NAMES, SMPL_KEYPOINTS
    from flowmocap.vision.lifter import lifted_track, load_lifter

    E = list(EVAL_JOINTS)
    ears = [KEYPOINT_NAMES.index("left_ear"), KEYPOINT_NAMES.index("right_ear")]

    def smpl_order(values: np.ndarray, found: np.ndarray, head) -> np.ndarray:
        out = np.full((len(values), 24) + values.shape[2:], np.nan)
        for k, name in enumerate(SMPL_KEYPOINTS):
            out[:, JOINT_INDEX[name]] = values[:, k]
        out[:, JOINT_INDEX["head"]] = head(values[:, ears])
        out[~found] = np.nan
        return out

    lifter = load_lifter()
    runs = []
    for seq in sorted(p for p in bench_dir.iterdir() if p.is_dir()):
        res = seq / "flowmocap"
        if not (res / "motion.npz").exists():
            continue
        track = load_detections(res)
        if track is None or track.world is None:
            continue
        gt, pred, _, _, idx = camera_joints(seq / "sequence", res)
        fps = float(np.load(res / "motion.npz")["fps"])
        found = np.asarray(track.found, bool)
        # every point the detector gives (no confidence gate: the gate is what is studied)
        lift, spread = _mc(lambda: smpl_order(np.asarray(lifted_track(track, lifter, fps=fps).world, np.float64),
                                              found, lambda e: e.mean(1))[idx][:, E], lifter, mc)
        mp = smpl_order(np.asarray(track.world, np.float64), found, lambda e: e.mean(1))[idx][:, E]
        conf = smpl_order(np.asarray(track.confidence, np.float64), found, lambda e: e.min(1))[idx][:, E]
        r = _run(seq.name, pred[:, E], lift, spread, mp, np.nan_to_num(conf), gt[:, E], np.ones(gt[:, E].shape[:2], bool))
        if r is not None:
            runs.append(r)
    return runs


def bin_table(runs: list[dict], key: str, edges, unit_scale: float = 1.0) -> list[dict]:
    """Per bin of ``run[key]``: points, each source's mean point error (cm), and the share
    of points where MediaPipe / the lifter is the best of the three."""
    errs, vals = [[], [], []], []
    for r in runs:
        e = point_errors([r["fit"], r["lift"], r["mp"]], r["ref"], r["valid"])
        m = np.isfinite(e[0])
        for k in range(3):
            errs[k].append(e[k][m])
        vals.append(r[key][m])
    E = [np.concatenate(x) for x in errs]
    V = np.concatenate(vals)
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (V >= lo) & (V < hi)
        if not m.any():
            continue
        best = np.argmin(np.stack([x[m] for x in E]), 0)
        rows.append({"from": lo * unit_scale, "to": min(hi, V.max()) * unit_scale, "points": int(m.sum()),
                     "fit_cm": 100 * float(E[0][m].mean()), "lifter_cm": 100 * float(E[1][m].mean()),
                     "mediapipe_cm": 100 * float(E[2][m].mean()),
                     "lifter_best": float(np.mean(best == 1)), "mediapipe_best": float(np.mean(best == 2))})
    return rows


def rule_table(runs: list[dict]) -> dict:
    """Per rule: each run's score (mm) and the mean and median over the runs, and how many
    runs it makes better / worse than the fixed share by more than 0.05 mm."""
    scores = {}
    for name, rule in RULES:
        scores[name] = [1000 * float(np.nanmean(frame_errors(rule(r), r["ref"], r["valid"]))) for r in runs]
    base = np.array(scores[BASE_RULE])
    out = {}
    for name, s in scores.items():
        s = np.array(s)
        out[name] = {"runs": dict(zip([r["name"] for r in runs], s.tolist())), "mean": float(s.mean()),
                     "median": float(np.median(s)), "better": int(np.sum(s < base - 0.05)),
                     "worse": int(np.sum(s > base + 0.05))}
    return out


def markdown(suite: str, result: dict) -> str:
    lines = [f"### {suite}", "", "By keypoint confidence (mean point error, cm; the reference aligned onto the "
             "sources' mean):", "", "| confidence | points | fit | lifter | MediaPipe | lifter best | MediaPipe best |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for b in result["by_confidence"]:
        lines.append(f"| {b['from']:.1f}-{b['to']:.1f} | {b['points']} | {b['fit_cm']:.1f} | {b['lifter_cm']:.1f} | "
                     f"{b['mediapipe_cm']:.1f} | {b['lifter_best']:.2f} | {b['mediapipe_best']:.2f} |")
    lines += ["", "By the lifter's Monte-Carlo dropout spread (quintiles):", "",
              "| spread cm | points | fit | lifter | MediaPipe | lifter best | MediaPipe best |",
              "|---|---:|---:|---:|---:|---:|---:|"]
    for b in result["by_spread"]:
        lines.append(f"| {b['from']:.1f}-{b['to']:.1f} | {b['points']} | {b['fit_cm']:.1f} | {b['lifter_cm']:.1f} | "
                     f"{b['mediapipe_cm']:.1f} | {b['lifter_best']:.2f} | {b['mediapipe_best']:.2f} |")
    lines += ["", f"Blends, per-frame point error after a similarity (mm), {len(result['runs'])} runs; better / worse: "
              "runs moved by more than 0.05 mm against the share 0.5:", "",
              "| rule | mean | median | better / worse |", "|---|---:|---:|---:|"]
    for name, v in result["rules"].items():
        lines.append(f"| {name} | {v['mean']:.2f} | {v['median']:.2f} | {v['better']} / {v['worse']} |")
    return "\n".join(lines) + "\n"


def analyse(runs: list[dict]) -> dict:
    spreads = np.concatenate([r["spread"][np.asarray(r["valid"], bool)] for r in runs])
    q = np.quantile(spreads, [0.0, 0.2, 0.4, 0.6, 0.8]).tolist() + [float(spreads.max()) + 1e-9]
    return {"runs": [r["name"] for r in runs], "by_confidence": bin_table(runs, "conf", CONF_BINS),
            "by_spread": bin_table(runs, "spread", q, unit_scale=100.0), "rules": rule_table(runs)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--real3d", type=Path, help="a flowmocap bench --suite real3d folder")
    ap.add_argument("--diverse", type=Path, help="a diverse tracker_only folder (post-pass off)")
    ap.add_argument("--mc", type=int, default=16, help="lifts with dropout on for the lifter's spread")
    ap.add_argument("--plausibility", action="store_true",
                    help="also the limb plausibility rules (a nearest-neighbour table of the train clips of "
                         "../shared/data/mocap/prior; retargeting them takes minutes without --poses-cache)")
    ap.add_argument("--poses-cache", type=Path, help="tools/train_pose_prior.py --cache's file of retargeted poses")
    ap.add_argument("--out", help="write PREFIX.json and PREFIX.md")
    a = ap.parse_args()
    global RULES
    if a.plausibility:
        db = LimbPlausibility(mocap_points(a.poses_cache))
        print(f"limb plausibility: {db.size} poses of the train clips", flush=True)
        RULES = RULES + plausibility_rules(db)
    if a.real3d is None and a.diverse is None:
        ap.error("give --real3d and/or --diverse")
    result, md = {"mc": a.mc, "oracle_shares": list(ORACLE_SHARES)}, ["# Choosing the 3D source per joint\n"]
    for suite, folder, collect in (("real3d", a.real3d, collect_real3d), ("diverse", a.diverse, collect_diverse)):
        if folder is None:
            continue
        runs = collect(folder, a.mc)
        if not runs:
            sys.exit(f"no scored runs in {folder}")
        result[suite] = {"dir": str(folder), **analyse(runs)}
        md.append(markdown(suite, result[suite]))
        print(md[-1], flush=True)
    if a.out:
        Path(f"{a.out}.json").write_text(json.dumps(result, indent=1))
        Path(f"{a.out}.md").write_text("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
