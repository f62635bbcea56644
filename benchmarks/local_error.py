"""Where the local error of a synthetic bench run comes from (issue 18).

For every finished sequence of a ``flowmocap bench`` folder (``NAME/sequence/gt.npz``,
``NAME/flowmocap/`` with its ``detections``), the 13 evaluation joints, each frame's fit
aligned onto the truth by its similarity (the local error's alignment), in the camera's
axes:

- ``local_cm``: the bench's local error; ``in_image_cm`` / ``depth_cm``: the mean over
  joints and frames of the aligned error's part across the camera's axis (x, y) and
  along it (|z|);
- per limb segment (upper arms, forearms, thighs, shins): where the true segment reaches
  more than ``--min-depth`` (default 0.08 m) towards or away from the camera (child
  minus parent along z), the share of those frames in which the fit has the sign wrong
  (``ours_sign_wrong``), the detector's own 3D joints have it wrong
  (``detector_sign_wrong``; MediaPipe's world landmarks, hip-centred, in the camera's
  axes), and the fit has it wrong where the detector has it right
  (``ours_wrong_detector_right``): what a cue from the detector's depth could fix at most;
- ``sign_oracle_cm``: the local error once every such wrong segment is mirrored in depth
  about the camera ray through its child joint (:func:`flowmocap.fit.flip.mirror_child`:
  the same image, the same length; the joints below it move with it), i.e. what a
  perfect per-frame flip test would give;
- ``ours_px`` / ``detector_px``: median 2D error (px) of the fit's and the detector's 12
  limb joints where the detector's confidence is at least 0.3;
- ``per_joint_cm``: each evaluation joint's mean aligned error.

``--real3d``: BENCH_DIR is a ``flowmocap bench --suite real3d`` folder instead; per
person-view, on the frames and joints that suite scores (:func:`flowmocap.eval.real3d.score_run`),
the limb depth-sign shares against the reference triangulated without the view (in that
camera's axes; the fit's joints in its own camera's axes), and the per-frame PA-MPJPE of
the fit, of the fit with its wrong signs mirrored, and of the detector's 3D (mm).

Usage: python benchmarks/local_error.py BENCH_DIR [--real3d] [--min-depth 0.08] [--out PREFIX]
(writes PREFIX.json and PREFIX.md; default: print only).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from flowmocap.body.skeleton import EVAL_JOINTS, JOINT_INDEX, JOINT_NAMES
from flowmocap.eval import metrics as M
from flowmocap.eval.scoring import detector_joints3d
from flowmocap.fit.flip import mirror_child
from flowmocap.geometry.procrustes import similarity_procrustes
from flowmocap.vision.auto import load_detections
from flowmocap.vision.detect import KEYPOINT_NAMES, SMPL_KEYPOINTS
from global_error import camera_joints  # benchmarks/, the script's own folder

E = list(EVAL_JOINTS)
#: (parent, child, joints that move with the child when the segment is mirrored)
SEGMENTS = [("left_shoulder", "left_elbow", ["left_wrist"]), ("left_elbow", "left_wrist", []),
            ("right_shoulder", "right_elbow", ["right_wrist"]), ("right_elbow", "right_wrist", []),
            ("left_hip", "left_knee", ["left_ankle"]), ("left_knee", "left_ankle", []),
            ("right_hip", "right_knee", ["right_ankle"]), ("right_knee", "right_ankle", [])]
SEG_NAMES = [c for _, c, _ in SEGMENTS]


def mirror_wrong_segments(pred: np.ndarray, wrong: np.ndarray, index: dict = JOINT_INDEX) -> np.ndarray:
    """``pred (T, J, 3)`` camera axes with each segment ``k`` mirrored in the frames where
    ``wrong[:, k]``: its child and the joints below it moved by the child's displacement.
    ``index``: joint name -> position in ``pred``'s second axis (default SMPL's 24)."""
    x = pred.copy()
    for k, (p, c, below) in enumerate(SEGMENTS):
        for t in np.flatnonzero(wrong[:, k]):
            m = mirror_child(x[t, index[p]], x[t, index[c]])
            if m is None:
                continue
            d = m - x[t, index[c]]
            for j in [c] + below:
                x[t, index[j]] += d
    return x


def segment_signs(truth: np.ndarray, ours: np.ndarray, det: np.ndarray, index: dict, min_depth: float,
                  usable: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Per segment, the frames where the truth reaches more than ``min_depth`` metres in
    depth (child minus parent along the camera's z) and whose sign the fit / the detector
    has wrong. ``truth``, ``ours``, ``det``: ``(T, J, 3)`` camera axes (the detector's
    hip-centred, NaN where missing); ``usable``: ``(T, J)`` bool, the truth's joints to use.

    Returns ``(wrong (T, 8) bool, the fit's; counts per segment name)``."""
    wrong = np.zeros((len(truth), len(SEGMENTS)), bool)
    seg = {}
    for k, (p, c, _) in enumerate(SEGMENTS):
        dz = lambda x: x[:, index[c], 2] - x[:, index[p], 2]  # noqa: E731
        g, d = dz(truth), dz(det)
        deep = np.abs(g) > min_depth
        if usable is not None:
            deep &= usable[:, index[p]] & usable[:, index[c]]
        wrong[:, k] = deep & (np.sign(dz(ours)) != np.sign(g))
        has = deep & np.isfinite(d)
        det_wrong = has & (np.sign(d) != np.sign(g))
        seg[c] = {"frames": int(deep.sum()), "ours_wrong": int(wrong[:, k].sum()),
                  "detector_frames": int(has.sum()), "detector_wrong": int(det_wrong.sum()),
                  "ours_wrong_detector_right": int((wrong[:, k] & has & ~det_wrong).sum())}
    return wrong, seg


def decompose(seq_dir: Path, res_dir: Path, min_depth: float) -> dict:
    """The quantities of the module docstring for one sequence and result."""
    gt, pr, gtz, motion, idx = camera_joints(seq_dir, res_dir)
    aligned = similarity_procrustes(pr[:, E], gt[:, E])[0]
    err = aligned - gt[:, E]
    track = load_detections(res_dir)
    det = detector_joints3d(track)[idx] if track is not None else np.full_like(pr, np.nan)
    wrong, seg = segment_signs(gt, pr, det, JOINT_INDEX, min_depth)
    fixed = mirror_wrong_segments(pr, wrong)
    out = {
        "frames": int(idx.size),
        "local_cm": 100 * float(M.local_procrustes_error(pr, gt).mean()),
        "in_image_cm": 100 * float(np.linalg.norm(err[..., :2], axis=-1).mean()),
        "depth_cm": 100 * float(np.abs(err[..., 2]).mean()),
        "sign_oracle_cm": 100 * float(M.local_procrustes_error(fixed, gt).mean()),
        "segments": seg,
        "per_joint_cm": {JOINT_NAMES[j]: 100 * float(v) for j, v in zip(E, np.linalg.norm(err, axis=-1).mean(0))},
    }
    if track is not None and "joints2d" in gtz:
        js = [JOINT_INDEX[n] for n in SMPL_KEYPOINTS]
        k = len(SMPL_KEYPOINTS)
        ok = np.asarray(track.confidence)[idx][:, :k] >= 0.3
        g2 = np.asarray(gtz["joints2d"], np.float64)[idx][:, js]
        out["detector_px"] = float(np.median(np.linalg.norm(np.asarray(track.keypoints)[idx][:, :k] - g2, axis=-1)[ok]))
        out["ours_px"] = float(np.median(np.linalg.norm(np.asarray(motion["joints2d"])[:, js] - g2, axis=-1)[ok]))
    return out


def run(bench_dir: Path, min_depth: float) -> dict:
    rows = {}
    for d in sorted(q for q in bench_dir.iterdir() if (q / "sequence" / "gt.npz").exists()):
        try:
            rows[d.name] = decompose(d / "sequence", d / "flowmocap", min_depth)
        except Exception as e:  # an unfinished or missing result: say so, go on
            rows[d.name] = {"error": str(e)}
    ok = [r for r in rows.values() if "error" not in r]
    med = {k: float(np.median([r[k] for r in ok if k in r])) for k in
           ("local_cm", "in_image_cm", "depth_cm", "sign_oracle_cm", "ours_px", "detector_px")} if ok else {}
    rates = _rates(ok)
    joints = {JOINT_NAMES[j]: float(np.mean([r["per_joint_cm"][JOINT_NAMES[j]] for r in ok])) for j in E} if ok else {}
    return {"bench": str(bench_dir), "min_depth_m": min_depth, "sequences": rows, "median": med,
            "sign_rates": rates, "per_joint_mean_cm": joints}


def real3d_run(res_dir: Path, reference: dict, person: str, view: str, min_depth: float) -> dict:
    """The ``--real3d`` quantities of one person-view (module docstring)."""
    from flowmocap.eval import real3d as R3
    from flowmocap.pipeline import load_result

    res, det = load_result(res_dir), load_detections(res_dir)
    cam, offset = reference["cameras"][view], reference["offsets"][view]
    wo = reference["people"][person]["without"][view]
    j13 = R3.eval_points(wo["points"])
    err13 = None
    if wo.get("error_px") is not None:  # as score_run: each joint's reprojection error, the head's the worse ear's
        e = np.asarray(wo["error_px"], np.float64)
        err13 = R3.eval_points(np.stack([e, e], -1))[..., 0]
        err13[:, 0] = np.fmax(e[:, KEYPOINT_NAMES.index("left_ear")], e[:, KEYPOINT_NAMES.index("right_ear")])
    lengths = R3.bone_lengths(R3.eval_points(reference["people"][person]["all"]["points"]))
    valid = R3.consistent_joints(j13, lengths, err13)
    fcam = json.loads(str(res.motion["camera"]))
    FR, Ft = np.asarray(fcam["R"], np.float64), np.asarray(fcam["t"], np.float64)
    CR, Ct = np.asarray(cam.R, np.float64), np.asarray(cam.t, np.float64).reshape(3)
    rows = {int(f): k for k, f in enumerate(res.frame_index)}
    names = list(R3.EVAL_NAMES)
    hips = [names.index("left_hip"), names.index("right_hip")]
    t0 = int(wo["times"][0]) if len(wo["times"]) else 0
    ours, mp, ref, ok = [], [], [], []
    for f in range(len(det.found)):
        i = f + offset - t0
        if not 0 <= i < len(wo["times"]) or valid[i].sum() < R3.MIN_JOINTS or not valid[i, hips].all():
            continue
        w = R3.eval_points(det.world[f]) if det.found[f] else None
        if w is None or not np.isfinite(w).all() or f not in rows:
            continue
        ours.append(np.asarray(res.joints3d[rows[f]], np.float64)[E] @ FR.T + Ft)
        mp.append(w)
        ref.append(np.where(valid[i][:, None], j13[i], 0.0) @ CR.T + Ct)
        ok.append(valid[i])
    ours, mp, ref, ok = map(np.asarray, (ours, mp, ref, ok))
    if not len(ours):
        return {"frames": 0}
    index = {n: k for k, n in enumerate(names)}
    wrong, seg = segment_signs(ref, ours, mp, index, min_depth, usable=ok)
    fixed = mirror_wrong_segments(ours, wrong, index)
    return {"frames": int(len(ours)), "segments": seg,
            "ours_mm": R3.pa_mpjpe(ours, ref, ok)[0], "sign_oracle_mm": R3.pa_mpjpe(fixed, ref, ok)[0],
            "detector_mm": R3.pa_mpjpe(mp, ref, ok)[0]}


def run_real3d(bench_dir: Path, min_depth: float) -> dict:
    from flowmocap.eval import real3d as R3

    reference = R3.build_reference(bench_dir, progress=False, log=None)
    rows = {}
    for d in sorted((bench_dir / "runs").iterdir()):
        person, view = d.name.split("-")
        rows[d.name] = real3d_run(d, reference, person, view, min_depth)
    ok = [r for r in rows.values() if r.get("frames")]
    mean = {k: float(np.mean([r[k] for r in ok])) for k in ("ours_mm", "sign_oracle_mm", "detector_mm")}
    return {"bench": str(bench_dir), "min_depth_m": min_depth, "runs": rows, "mean": mean,
            "sign_rates": _rates(ok)}


def _rates(ok: list[dict]) -> dict:
    rates = {}
    for name in SEG_NAMES:
        s = [r["segments"][name] for r in ok]
        n, nd = sum(x["frames"] for x in s), sum(x["detector_frames"] for x in s)
        rates[name] = {"ours_sign_wrong": sum(x["ours_wrong"] for x in s) / max(n, 1),
                       "detector_sign_wrong": sum(x["detector_wrong"] for x in s) / max(nd, 1),
                       "ours_wrong_detector_right": sum(x["ours_wrong_detector_right"] for x in s) / max(nd, 1)}
    return rates


def _rate_table(res: dict) -> list[str]:
    lines = [f"Limb segments reaching more than {100 * res['min_depth_m']:.0f} cm in depth: share of their frames "
             "with the depth sign wrong", "", "| segment (child joint) | ours | detector | ours wrong, detector right |",
             "|---|---:|---:|---:|"]
    for name, r in res["sign_rates"].items():
        lines.append(f"| {name} | {r['ours_sign_wrong']:.2f} | {r['detector_sign_wrong']:.2f} | "
                     f"{r['ours_wrong_detector_right']:.2f} |")
    return lines


def real3d_table(res: dict) -> str:
    lines = ["| person-view | frames | flowmocap mm | with limb signs right mm | detector-3D mm |",
             "|---|---:|---:|---:|---:|"]
    for name, r in list(res["runs"].items()):
        if not r.get("frames"):
            lines.append(f"| {name} | 0 | -- | -- | -- |")
            continue
        lines.append(f"| {name} | {r['frames']} | {r['ours_mm']:.1f} | {r['sign_oracle_mm']:.1f} | {r['detector_mm']:.1f} |")
    m = res["mean"]
    lines += [f"| **mean** | | {m['ours_mm']:.1f} | {m['sign_oracle_mm']:.1f} | {m['detector_mm']:.1f} |", ""]
    return "\n".join(lines + _rate_table(res) + [""])


def table(res: dict) -> str:
    cols = ("local_cm", "in_image_cm", "depth_cm", "sign_oracle_cm", "ours_px", "detector_px")
    lines = ["| sequence | local | in image | depth | limb signs right | ours 2D px | detector 2D px |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for seq, r in list(res["sequences"].items()) + [("**median**", res["median"])]:
        if "error" in r or not r:
            lines.append(f"| {seq} | " + " | ".join("--" for _ in cols) + " |")
            continue
        lines.append(f"| {seq} | " + " | ".join(f"{r[k]:.1f}" if k in r else "--" for k in cols) + " |")
    lines += [""] + _rate_table(res)
    lines += ["", "Mean aligned error per joint over the sequences (cm): " +
              ", ".join(f"{k} {v:.1f}" for k, v in res["per_joint_mean_cm"].items()), ""]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench")
    ap.add_argument("--real3d", action="store_true", help="BENCH_DIR is a real3d suite folder")
    ap.add_argument("--min-depth", type=float, default=0.08, help="metres (default 0.08)")
    ap.add_argument("--out", default=None, help="PREFIX: write PREFIX.json and PREFIX.md")
    args = ap.parse_args()
    if args.real3d:
        res = run_real3d(Path(args.bench), args.min_depth)
        md = real3d_table(res)
        title = "# Limb depth signs on the real multi-view recording"
    else:
        res = run(Path(args.bench), args.min_depth)
        md = table(res)
        title = "# Where the diverse suite's local error comes from"
    print(md)
    if args.out:
        Path(args.out + ".json").write_text(json.dumps(res, indent=1))
        Path(args.out + ".md").write_text(
            f"{title}\n\n`python benchmarks/local_error.py {args.bench}{' --real3d' if args.real3d else ''}`; "
            f"{'mm' if args.real3d else 'cm'} unless said; see the script's docstring for each column.\n\n" + md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
