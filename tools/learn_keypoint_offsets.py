"""Learn where the detector's keypoints sit relative to the body model's joints.

MediaPipe's hip, shoulder, knee, ... landmarks are not SMPL's joints: its hips sit
higher and wider than SMPL's hip joints, its shoulders nearer the surface, by 1.5-4 cm
(docs/experiments.md, "Keypoint offsets"). A term that pulls SMPL's joints onto them
bends the body by that much. This tool learns, for each of the 12 keypoints flowmocap
uses (:data:`~flowmocap.vision.detect.SMPL_KEYPOINTS`) and for the middle of the ears
(the head of the real-video reference), a fixed offset in the rest frame of one body
part: the keypoint is ``J_j + R_p o`` (``J_j`` the joint, ``R_p`` the posed rotation of
part ``p``, the joint's own bone or its parent's, whichever predicts held-out clips
better), in metres.

Data: ``train`` clips of ``../shared/data/mocap/prior/`` only (test subjects 2, 8, 13 and
61 are never used), ``--per-category`` clips of each kind, each its most active
``--frames``-frame window at 30 fps rendered by ``flowmocap.synth`` on a random body from a
seeded random azimuth; MediaPipe runs on the frames as it does for an input with its
own masks (:func:`flowmocap.vision.auto.detect_for_given_masks`). The offsets are the
robust least-squares fit of the detector's 2D keypoints (confidence >= 0.5) to the
projections of ``J_j + R_p o``, solved by Gauss-Newton, with residuals beyond 3x the
median + 1 px left out, repeated 3 times.

The choice of part and whether to keep an offset at all are made across the data's two
retargeted skeletons (cgspeed's MotionBuilder and DAZ conversions; their shoulders and
collars move differently): offsets fitted on one skeleton's clips are scored on the
other's. The part with the lower median residual so is kept, then fitted on all clips;
a keypoint whose offset does not lower the residual on both skeletons' clips (fitted
on the other's) keeps none. (With the first version's even/odd split of the clips the
shoulders got 4 cm offsets that fit the DAZ clips and made the MotionBuilder ones worse:
4.1 -> 5.7 px.)

    python tools/learn_keypoint_offsets.py                 # writes src/flowmocap/vision/data/keypoint_offsets.json
    python tools/learn_keypoint_offsets.py --model heavy   # ... keypoint_offsets_heavy.json (the heavy network's)
    python tools/learn_keypoint_offsets.py --work /tmp/kpo --out /tmp/offsets.json

About 10 minutes on 2 CPU cores (rendering and MediaPipe; the fit takes seconds).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "mocap" / "prior"
TEST_SUBJECTS = {"2", "8", "13", "61"}
FPS = 30.0


def choose_clips(data: Path, per_category: int) -> list[dict]:
    """``per_category`` train clips of each category (spread over its list in file order)."""
    with (data / "index.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    by_cat = defaultdict(list)
    for r in rows:
        if r["split"] != "train":
            continue
        if r["subject"] in TEST_SUBJECTS:
            sys.exit(f"index.csv marks {r['file']} (test subject {r['subject']}) as train; refusing.")
        by_cat[r["category"]].append(r)
    chosen = []
    for cat in sorted(by_cat):
        clips = sorted(by_cat[cat], key=lambda r: r["file"])
        picks = np.unique(np.linspace(0, len(clips) - 1, min(per_category, len(clips))).round().astype(int))
        chosen += [clips[i] for i in picks]
    return chosen


def render_and_detect(rows: list[dict], data: Path, work: Path, frames: int, models=("full",)) -> list[dict]:
    """Each clip's ground-truth joints, part rotations and camera, with MediaPipe's
    keypoints of every frame (cached in ``work``): ``keypoints`` and ``confidence`` of the
    first of ``models`` (:data:`flowmocap.vision.detect.MODELS`), and of every model
    ``by_model[name] = (keypoints (T, K, 2), confidence (T, K), found (T,))``."""
    from flowmocap.body import load_body_model
    from flowmocap.errors import InputError, NoPersonError
    from flowmocap.eval.bench import most_active_window
    from flowmocap.io.sequence import load_sequence
    from flowmocap.synth import synthesize
    from flowmocap.vision.auto import detect_for_given_masks, detect_sequence
    from flowmocap.vision.detect import MediaPipePoseDetector

    model = load_body_model("default")
    clips = []
    for k, r in enumerate(rows):
        path = data / r["file"]
        d = work / Path(r["file"]).stem
        seq_dir = d / "sequence"
        rng = np.random.default_rng(1000 + k)
        azimuth = float(rng.uniform(0.0, 360.0))
        t0 = time.perf_counter()
        if not (seq_dir / "gt.npz").exists():
            start = most_active_window(path, frames, FPS)
            kw = dict(fps=FPS, size="640x480", betas="random", seed=1000 + k, azimuth=azimuth, flow=False,
                      overwrite=True, start=start)
            try:
                synthesize(str(path), seq_dir, frames=frames, **kw)
            except InputError:
                synthesize(str(path), seq_dir, frames=None, **kw)
        seq = load_sequence(seq_dir)
        by_model = {}
        for m in models:
            if m.endswith("-raw"):  # the model's visibility as it comes (tools/calibrate_visibility.py)
                detector = MediaPipePoseDetector(augment=False, model=m[:-4], calibrated=False)
                try:
                    track = detect_sequence(seq, d / f"run-{m}", detector=detector, searcher=None, progress=False)
                except NoPersonError as e:
                    track, note = None, str(e)
                finally:
                    detector.close()
            else:
                track, note = detect_for_given_masks(seq, d / ("run" if m == "full" else f"run-{m}"), progress=False,
                                                     model=m)
            if track is None:
                break
            by_model[m] = (np.asarray(track.keypoints, np.float64), np.asarray(track.confidence, np.float64),
                           np.asarray(track.found, bool))
        if track is None:
            print(f"  {r['file']}: {note}; skipped", flush=True)
            continue
        first = by_model[models[0]]
        gt = seq.gt
        with torch.no_grad():
            out = model.forward(torch.as_tensor(gt["betas"], dtype=torch.float32).reshape(1, -1),
                                torch.as_tensor(gt["poses"], dtype=torch.float32),
                                torch.as_tensor(gt["trans"], dtype=torch.float32))
        clips.append({"file": r["file"], "category": r["category"], "skeleton": r["skeleton"], "camera": seq.camera,
                      "joints": out.joints.numpy().astype(np.float64),
                      "rotations": out.transforms[..., :3, :3].numpy().astype(np.float64),
                      "keypoints": first[0], "confidence": first[1], "found": first[2], "by_model": by_model})
        print(f"  {r['file']:24s} {r['category']:24s} {len(seq)} frames, azimuth {azimuth:5.1f}, "
              f"{int(first[2].sum())} with a person ({time.perf_counter() - t0:.0f} s)", flush=True)
    return clips


def observations(clips: list[dict], target, joint: int, part: int):
    """Stacked ``(X (N, 3) joint in world, R (N, 3, 3) part rotation, uv (N, 2) keypoint,
    cam index, clip index)`` for one keypoint; ``target(clip) -> (uv (T, 2), ok (T,))``."""
    rows = []
    for c, clip in enumerate(clips):
        uv, ok = target(clip)
        ok = ok & clip["found"]
        for t in np.nonzero(ok)[0]:
            rows.append((clip["joints"][t, joint], clip["rotations"][t, part], uv[t], c))
    X = np.array([r[0] for r in rows]).reshape(-1, 3)
    R = np.array([r[1] for r in rows]).reshape(-1, 3, 3)
    uv = np.array([r[2] for r in rows]).reshape(-1, 2)
    ci = np.array([r[3] for r in rows], int)
    return X, R, uv, ci


def residuals(clips, X, R, uv, ci, o):
    """``(N, 2)`` pixel residuals of the projections of ``X + R o`` against ``uv``, and
    their ``(N, 2, 3)`` Jacobians with respect to ``o``."""
    res = np.zeros_like(uv)
    jac = np.zeros((len(uv), 2, 3))
    for c in np.unique(ci):
        m = ci == c
        cam = clips[c]["camera"]
        Rc, tc = np.asarray(cam.R, np.float64), np.asarray(cam.t, np.float64).reshape(3)
        P = (X[m] + R[m] @ o) @ Rc.T + tc
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        fx, fy = float(cam.fx), float(getattr(cam, "fy", cam.fx))
        res[m] = np.stack([fx * x / z + float(cam.cx), fy * y / z + float(cam.cy)], 1) - uv[m]
        dproj = np.zeros((m.sum(), 2, 3))
        dproj[:, 0, 0], dproj[:, 0, 2] = fx / z, -fx * x / z ** 2
        dproj[:, 1, 1], dproj[:, 1, 2] = fy / z, -fy * y / z ** 2
        jac[m] = dproj @ Rc @ R[m]
    return res, jac


def fit_offset(clips, X, R, uv, ci, rounds: int = 3, steps: int = 4) -> np.ndarray:
    """Robust Gauss-Newton fit of ``o (3,)`` metres (see the module docstring)."""
    o = np.zeros(3)
    keep = np.ones(len(uv), bool)
    for _ in range(rounds):
        for _ in range(steps):
            r, J = residuals(clips, X, R, uv, ci, o)
            A = J[keep].reshape(-1, 3)
            b = r[keep].reshape(-1)
            o = o - np.linalg.lstsq(A, b, rcond=None)[0]
        e = np.linalg.norm(residuals(clips, X, R, uv, ci, o)[0], axis=1)
        keep = e < 3 * np.median(e) + 1.0
    return o


def median_error(clips, X, R, uv, ci, o) -> float:
    return float(np.median(np.linalg.norm(residuals(clips, X, R, uv, ci, o)[0], axis=1)))


def main(argv=None) -> int:
    from flowmocap.body.skeleton import JOINT_NAMES, PARENTS
    from flowmocap.vision.detect import KEYPOINT_NAMES, SMPL_KEYPOINTS
    from flowmocap.vision.keypoint_map import KEYPOINT_OFFSETS_FILES

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DATA)
    p.add_argument("--work", type=Path, default=Path("/tmp/flowmocap_keypoint_offsets"))
    p.add_argument("--out", type=Path, default=None, help="default: the package's file for --model")
    p.add_argument("--per-category", type=int, default=3)
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--min-confidence", type=float, default=0.5)
    p.add_argument("--model", default="full", choices=sorted(KEYPOINT_OFFSETS_FILES),
                   help="the detector's landmark network (flowmocap.vision.detect.MODELS); its visibility is "
                        "put on the full network's scale as the tracker does (vision/data/heavy_visibility.json)")
    a = p.parse_args(argv)
    a.out = a.out or KEYPOINT_OFFSETS_FILES[a.model]
    if not (a.data / "index.csv").exists():
        sys.exit(f"{a.data}/index.csv not found: the training data (../shared/data/mocap/prior) is needed.")
    rows = choose_clips(a.data, a.per_category)
    print(f"{len(rows)} train clips, {a.frames} frames each at {FPS:g} fps", flush=True)
    a.work.mkdir(parents=True, exist_ok=True)
    clips = render_and_detect(rows, a.data, a.work, a.frames, models=(a.model,))

    def keypoint_target(name):
        k = KEYPOINT_NAMES.index(name)
        return lambda clip: (clip["keypoints"][:, k], clip["confidence"][:, k] >= a.min_confidence)

    def ears_target(clip):
        le, re = KEYPOINT_NAMES.index("left_ear"), KEYPOINT_NAMES.index("right_ear")
        ok = (clip["confidence"][:, le] >= a.min_confidence) & (clip["confidence"][:, re] >= a.min_confidence)
        return 0.5 * (clip["keypoints"][:, le] + clip["keypoints"][:, re]), ok

    targets = [(n, JOINT_NAMES.index(n), keypoint_target(n)) for n in SMPL_KEYPOINTS]
    targets.append(("ears_middle", JOINT_NAMES.index("head"), ears_target))
    result, report = {}, []
    skeletons = sorted({c["skeleton"] for c in clips})
    if len(skeletons) != 2:
        sys.exit(f"the training clips come from {skeletons}; the offsets are checked across two skeletons.")
    groups = [np.array([c["skeleton"] == sk for c in clips]) for sk in skeletons]

    def cross(X, R, uv, ci):
        """Median residual on each skeleton's clips of the offset fitted on the other's, and with none."""
        after, before = [], []
        for g in (0, 1):
            fit_m, test_m = groups[1 - g][ci], groups[g][ci]
            o = fit_offset(clips, X[fit_m], R[fit_m], uv[fit_m], ci[fit_m])
            after.append(median_error(clips, X[test_m], R[test_m], uv[test_m], ci[test_m], o))
            before.append(median_error(clips, X[test_m], R[test_m], uv[test_m], ci[test_m], np.zeros(3)))
        return after, before

    for name, j, target in targets:
        best = None
        for part in (j, PARENTS[j]):
            X, R, uv, ci = observations(clips, target, j, part)
            after, held_before = cross(X, R, uv, ci)
            if best is None or np.mean(after) < np.mean(best[0]):
                best = (after, held_before, part, X, R, uv, ci)
        after, held_before, part, X, R, uv, ci = best
        before = median_error(clips, X, R, uv, ci, np.zeros(3))
        # kept only where it predicts each skeleton's clips better than none when fitted on the other's
        keep = all(a < b for a, b in zip(after, held_before))
        o = fit_offset(clips, X, R, uv, ci) if keep else np.zeros(3)
        held_err = float(np.mean(after)) if keep else float(np.mean(held_before))
        held_before = float(np.mean(held_before))
        result[name] = {"joint": JOINT_NAMES[j], "part": JOINT_NAMES[part], "offset_m": [round(float(v), 4) for v in o],
                        "observations": int(len(uv)), "median_px_before": round(before, 2),
                        "median_px_after": round(median_error(clips, X, R, uv, ci, o), 2),
                        "held_out_median_px_before": round(held_before, 2),
                        "held_out_median_px_after": round(held_err, 2),
                        "cross_skeleton_px": {sk: [round(b, 2), round(a, 2)] for sk, a, b in
                                              zip(skeletons, best[0], best[1])}}
        report.append(f"{name:15s} part {JOINT_NAMES[part]:15s} offset cm {100 * o[0]:6.1f} {100 * o[1]:6.1f} "
                      f"{100 * o[2]:6.1f} (|{100 * np.linalg.norm(o):4.1f}|)  median px {before:4.1f} -> "
                      f"{result[name]['median_px_after']:4.1f}, held out {held_before:4.1f} -> {held_err:4.1f}")
    print("\n".join(report))
    doc = {"description": "Offsets of MediaPipe Pose keypoints from the default body model's joints: keypoint = "
                          "joint + R_part @ offset_m (R_part the posed rotation of the named part, metres in the "
                          "rest pose's axes). Made by tools/learn_keypoint_offsets.py.",
           "detector": "mediapipe pose landmarker (flowmocap.vision.detect.MediaPipePoseDetector, augment=False)",
           "landmark_model": a.model,
           "training_clips": [c["file"] for c in clips], "frames_per_clip": a.frames, "fps": FPS,
           "data": "CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu), train split of "
                   "../shared/data/mocap/prior (see its ATTRIBUTION.md); test subjects 2, 8, 13, 61 not used",
           "keypoints": result}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
