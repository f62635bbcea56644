"""Train flowmocap's pose prior: a Gaussian mixture over body-joint rotations (SMPLify's recipe).

Data: the ``train`` clips of ``../shared/data/mocap/prior/`` (its README; ``index.csv``'s
``split`` column; test subjects 2, 8, 13 and 61 are never used for fitting), two cgspeed
BVH conversions of the CMU database (MotionBuilder-friendly ``cmu_mb/`` and DAZ-friendly
``cmu_daz/``), each retargeted onto the default body's SMPL tree by
:func:`flowmocap.io.retarget.retarget`, so both skeletons give SMPL local rotations
(axis-angle, radians) before they are pooled.

Steps:

1. Retarget every clip (train and test; the test clips only for the held-out check).
2. Joints: the root is excluded; a joint is left out when one of the two skeletons never
   moves it (its rotation's RMS angle about the clip's mean rotation, averaged over that
   skeleton's training frames, is below ``--still-deg``): the DAZ skeleton has no toes
   and one spine joint fewer (spine3 follows spine2), its collar and finger channels are
   constant, the MotionBuilder skeleton's collar and hand channels are constant. Pooling
   a joint that is a constant in half the data with real motion in the other half would
   give the mixture near-singular directions; the prior says nothing about those joints.
3. Balance: each category keeps at most ``--per-category`` frames (the README: long
   playground and salsa clips hold half the frames), shared evenly between its clips
   (a clip gives all its frames if it has fewer than its share), evenly spaced in time.
4. Mirror: every kept pose is added again mirrored left/right
   (:func:`flowmocap.fit.pose_prior.mirror_pose`).
5. Fit ``sklearn.mixture.GaussianMixture`` (``--components`` full-covariance Gaussians,
   ``--reg-covar`` added to each covariance's diagonal) and write the ``.npz``
   (:meth:`flowmocap.fit.pose_prior.PosePrior.save`) with its training statistics.

   ``--reg-covar`` 1e-3 rad^2 (a standard-deviation floor of 1.8 degrees): the CMU
   MotionBuilder skeleton has one-axis knees and elbows, so their off-axis rotations are
   exactly 0 in half the data (0.1 degrees RMS knee abduction), and a mixture that learns
   that asks a tracked 3-axis SMPL knee to hold its twist to a fraction of a degree. With
   1e-4 a 10-degree knee twist cost 106 nats against 9 for bending a knee 20 degrees
   backwards; with 1e-3, 15 against 8. Measured on train subjects 6, 12 and 135 held
   out of a fit to the other train subjects (never on the test split): their
   log-likelihood favours smaller values (32.6 nats at 1e-4, 22.3 at 1e-3), which is the
   one-axis joints being learnt, not better poses.
6. Report: clips and frames used, the mixture's mean log-likelihood on the training
   poses and on every frame of the held-out test clips (a check only: no setting is
   chosen from it), and prior energies on held-out poses against implausible ones.

Needs scikit-learn (``pip install -e '.[train]'``). About 2-3 minutes on 2 CPU cores.

    python tools/train_pose_prior.py                       # writes src/flowmocap/fit/data/pose_prior.npz
    python tools/train_pose_prior.py --out /tmp/prior.npz --cache /tmp/prior_poses.npz
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from flowmocap.body import JOINT_NAMES, load_body_model
from flowmocap.fit.pose_prior import PosePrior, mirror_pose
from flowmocap.geometry import axis_angle_to_matrix
from flowmocap.io import read_mocap
from flowmocap.io.retarget import retarget

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "mocap" / "prior"
DEFAULT_OUT = ROOT / "src" / "flowmocap" / "fit" / "data" / "pose_prior.npz"
#: CMU subjects of the test split (the data README); checked against index.csv.
TEST_SUBJECTS = {2, 8, 13, 61}


def read_index(data: Path) -> list[dict]:
    """Rows of index.csv, each with ``subject`` an int; refuses an index whose split
    would put a test subject into training."""
    path = data / "index.csv"
    if not path.is_file():
        sys.exit(f"{path} not found: pass --data with the mocap/prior folder (see its README)")
    rows = list(csv.DictReader(path.open(newline="")))
    for r in rows:
        r["subject"] = int(r["subject"])
        if r["split"] not in ("train", "test"):
            sys.exit(f"{path}: unknown split {r['split']!r} for {r['file']}")
        if (r["subject"] in TEST_SUBJECTS) != (r["split"] == "test"):
            sys.exit(f"{path}: {r['file']} (subject {r['subject']}) is marked {r['split']}; "
                     f"test subjects are {sorted(TEST_SUBJECTS)}")
    return rows


def retarget_all(rows: list[dict], data: Path, model, cache: Path | None) -> dict[str, np.ndarray]:
    """``{file: (T, 72) SMPL poses, radians}`` for every row (read from ``cache`` when it
    holds the same files)."""
    files = [r["file"] for r in rows]
    if cache is not None and cache.is_file():
        with np.load(cache, allow_pickle=False) as z:
            if sorted(z.files) == sorted(f.replace("/", "__") for f in files):
                print(f"retargeted poses read from {cache}")
                return {f: z[f.replace("/", "__")] for f in files}
    out, rigs = {}, defaultdict(int)
    t0 = time.perf_counter()
    for i, r in enumerate(rows):
        clip = read_mocap(data / r["file"])
        if clip.num_frames != int(r["frames"]):
            sys.exit(f"{r['file']}: {clip.num_frames} frames, index.csv says {r['frames']}")
        motion = retarget(clip, model, origin=None, ground=None)
        rigs[(r["skeleton"], motion.info["rig"])] += 1
        out[r["file"]] = motion.poses.astype(np.float64)
        if (i + 1) % 25 == 0:
            print(f"  retargeted {i + 1}/{len(rows)} clips ({time.perf_counter() - t0:.0f} s)")
    print("skeleton -> retarget rig:", ", ".join(f"{s} -> {g} ({n} clips)" for (s, g), n in sorted(rigs.items())))
    if any(s == "cgspeed-MB" and g != "cmu_bvh" or s == "cgspeed-DAZ" and g != "daz" for s, g in rigs):
        sys.exit("a skeleton was retargeted with an unexpected rig; check flowmocap.io.retarget.RIGS")
    if cache is not None:
        np.savez_compressed(cache, **{f.replace("/", "__"): p for f, p in out.items()})
    return out


def rms_motion_deg(poses: np.ndarray) -> np.ndarray:
    """``(24,)`` per joint: RMS angle (degrees) between each frame's local rotation and
    the clip's mean rotation (the chordal mean: the rotation nearest the mean matrix)."""
    R = axis_angle_to_matrix(torch.as_tensor(poses.reshape(-1, 24, 3))).numpy()
    U, _, Vt = np.linalg.svd(R.mean(0))
    d = np.ones(U.shape[:-1])
    d[:, -1] = np.sign(np.linalg.det(U @ Vt))
    M = (U * d[:, None, :]) @ Vt
    cos = (np.einsum("tjab,jab->tj", R, M) - 1) / 2
    ang = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    return np.sqrt((ang ** 2).mean(0))


def choose_joints(rows, poses, still_deg: float) -> tuple[list[int], dict]:
    """Joints 1..23 that both skeletons move (see the module docstring, step 2)."""
    table = {}
    for skel in sorted({r["skeleton"] for r in rows}):
        clips = [r for r in rows if r["split"] == "train" and r["skeleton"] == skel]
        frames = np.array([len(poses[r["file"]]) for r in clips], dtype=float)
        rms = np.stack([rms_motion_deg(poses[r["file"]]) for r in clips])
        table[skel] = np.sqrt((frames[:, None] * rms ** 2).sum(0) / frames.sum())
    keep = [j for j in range(1, 24) if all(t[j] >= still_deg for t in table.values())]
    print(f"\nper-joint motion (RMS angle about each clip's mean rotation, degrees; kept if >= {still_deg} in both):")
    print(f"  {'joint':16s}" + "".join(f"{s:>13s}" for s in table) + "  kept")
    for j in range(1, 24):
        print(f"  {JOINT_NAMES[j]:16s}" + "".join(f"{t[j]:13.1f}" for t in table.values())
              + ("  yes" if j in keep else "  no"))
    return keep, {s: [round(float(v), 2) for v in t] for s, t in table.items()}


def balance(rows: list[dict], poses: dict, per_category: int) -> tuple[np.ndarray, dict]:
    """Training poses ``(N, 72)``: at most ``per_category`` frames per category, shared
    evenly by its clips, evenly spaced within each clip."""
    by_cat = defaultdict(list)
    for r in rows:
        by_cat[r["category"]].append(r)
    out, summary = [], {}
    for cat, clips in sorted(by_cat.items()):
        lengths = np.array([len(poses[r["file"]]) for r in clips])
        if lengths.sum() <= per_category:
            take = lengths
        else:  # water-filling: the largest share q with sum(min(len, q)) <= per_category
            lo, hi = 0, int(lengths.max())
            while lo < hi:
                q = (lo + hi + 1) // 2
                lo, hi = (q, hi) if np.minimum(lengths, q).sum() <= per_category else (lo, q - 1)
            take = np.minimum(lengths, lo)
        for r, n, k in zip(clips, lengths, take):
            idx = np.unique(np.round(np.linspace(0, n - 1, int(k))).astype(int)) if k < n else np.arange(n)
            out.append(poses[r["file"]][idx])
        summary[cat] = {"clips": len(clips), "frames": int(lengths.sum()), "used": int(take.sum())}
    return np.concatenate(out), summary


def implausible_poses(base: np.ndarray, seed: int) -> dict[str, np.ndarray]:
    """``{name: (n, 72)}`` poses no person makes, radians, from ``base (n, 72)`` poses.

    ``knees_backward``: the base pose with both knees bent 40-90 degrees the wrong way
    (SMPL knee flexion is about +x); ``elbows_hyperextended``: the base pose with both
    elbows bent 40-90 degrees the wrong way (flexion turns the forearm forward: about -y
    on the left, +y on the right); ``random_rotations``: every joint 1..23 a uniformly
    random rotation.
    """
    rng = np.random.default_rng(seed)
    n = len(base)
    knees = base.reshape(n, 24, 3).copy()
    knees[:, [4, 5]] = 0.0
    knees[:, [4, 5], 0] = -np.radians(rng.uniform(40, 90, (n, 2)))
    elbows = base.reshape(n, 24, 3).copy()
    elbows[:, [18, 19]] = 0.0
    a = np.radians(rng.uniform(40, 90, (n, 2)))
    elbows[:, 18, 1], elbows[:, 19, 1] = a[:, 0], -a[:, 1]
    q = rng.standard_normal((n, 23, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q *= np.sign(q[..., :1])
    ang = 2 * np.arccos(np.clip(q[..., 0], -1, 1))
    axis = q[..., 1:] / np.maximum(np.linalg.norm(q[..., 1:], axis=-1, keepdims=True), 1e-12)
    rand = np.zeros((n, 24, 3))
    rand[:, 1:] = axis * ang[..., None]
    return {k: v.reshape(n, 72) for k, v in
            (("knees_backward", knees), ("elbows_hyperextended", elbows), ("random_rotations", rand))}


def _pct(x: np.ndarray) -> dict:
    return {k: round(float(v), 2) for k, v in zip(("p10", "median", "p90"), np.percentile(x, [10, 50, 90]))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the mocap/prior folder (index.csv, cmu_mb/, cmu_daz/)")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="the prior file to write (.npz)")
    ap.add_argument("--components", type=int, default=8, help="Gaussians in the mixture (SMPLify: 8)")
    ap.add_argument("--per-category", type=int, default=3000, help="most frames one motion category gives (before mirroring)")
    ap.add_argument("--still-deg", type=float, default=1.0, help="joints either skeleton moves less than this (RMS, degrees) are left out")
    ap.add_argument("--reg-covar", type=float, default=1e-3, help="added to each covariance's diagonal, rad^2")
    ap.add_argument("--n-init", type=int, default=4, help="EM restarts (the best is kept)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the EM initialisation and the implausible poses")
    ap.add_argument("--cache", type=Path, default=None, help="keep the retargeted poses here (an .npz) to skip retargeting next time")
    args = ap.parse_args(argv)
    try:
        from sklearn.mixture import GaussianMixture
    except ImportError:
        sys.exit("scikit-learn is needed to train the prior: pip install -e '.[train]'")

    t0 = time.perf_counter()
    rows = read_index(args.data)
    train = [r for r in rows if r["split"] == "train"]
    test = [r for r in rows if r["split"] == "test"]
    assert not {r["subject"] for r in train} & TEST_SUBJECTS
    model = load_body_model("default", dtype=torch.float64)
    poses = retarget_all(rows, args.data, model, args.cache)

    joints, motion_table = choose_joints(rows, poses, args.still_deg)
    cols = np.array([3 * j + c for j in joints for c in range(3)])
    X_train, per_cat = balance(train, poses, args.per_category)
    X = np.concatenate([X_train, mirror_pose(X_train)])[:, cols]
    print(f"\ntraining frames by category (train split; cap {args.per_category} per category, then x2 mirrored):")
    for cat, s in per_cat.items():
        print(f"  {cat:24s} {s['clips']:3d} clips {s['frames']:6d} frames -> {s['used']:5d} used")
    print(f"  {'total':24s} {len(train):3d} clips {sum(s['frames'] for s in per_cat.values()):6d} frames -> "
          f"{len(X_train):5d} used, {len(X)} with mirrors; {len(joints)} joints, {X.shape[1]} dimensions")

    gmm = GaussianMixture(n_components=args.components, covariance_type="full", reg_covar=args.reg_covar,
                          n_init=args.n_init, max_iter=500, tol=1e-4, random_state=args.seed)
    t1 = time.perf_counter()
    gmm.fit(X)
    print(f"\nGaussianMixture: {args.components} components, converged={gmm.converged_}, "
          f"{gmm.n_iter_} iterations, {time.perf_counter() - t1:.0f} s")

    X_test = np.concatenate([poses[r["file"]] for r in test])
    info = {
        "source": "CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu), cgspeed BVH conversions "
                  "(MotionBuilder-friendly and DAZ-friendly), ../shared/data/mocap/prior, split 'train' only",
        "acknowledgement": "The data used in this project was obtained from mocap.cs.cmu.edu. "
                           "The database was created with funding from NSF EIA-0196217.",
        "retarget": "flowmocap.io.retarget.retarget onto flowmocap's default neutral body (mean shape)",
        "train_subjects": sorted({r["subject"] for r in train}),
        "test_subjects": sorted({r["subject"] for r in test}),
        "train_clips": len(train), "train_frames": int(sum(len(poses[r["file"]]) for r in train)),
        "frames_used": len(X_train), "samples_with_mirrors": len(X),
        "per_category": per_cat, "per_category_cap": args.per_category,
        "still_deg": args.still_deg, "joint_motion_rms_deg": motion_table,
        "left_out_joints": [JOINT_NAMES[j] for j in range(1, 24) if j not in joints],
        "components": args.components, "covariance": "full", "reg_covar": args.reg_covar,
        "n_init": args.n_init, "seed": args.seed, "sklearn_converged": bool(gmm.converged_),
        "mean_log_likelihood_train": round(float(gmm.score(X)), 3),
        "mean_log_likelihood_test": round(float(gmm.score(X_test[:, cols])), 3),
        "test_clips": len(test), "test_frames": len(X_test),
    }
    prior = PosePrior(gmm.weights_, gmm.means_, gmm.precisions_cholesky_, joints, info)

    def energy(p: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return prior.energy(torch.as_tensor(p, dtype=torch.float32)).double().numpy()

    # Energies: training poses, held-out test poses (all frames), per test category, implausible.
    e_test = energy(X_test)
    by_cat = defaultdict(list)
    for r in test:
        by_cat[r["category"]].append(energy(poses[r["file"]]))
    base = X_test[np.random.default_rng(args.seed).choice(len(X_test), 1000, replace=False)]
    bad = {k: energy(v) for k, v in implausible_poses(base, args.seed).items()}
    info["energy"] = {
        "train_used": _pct(energy(X_train)),
        "test_all_frames": _pct(e_test),
        "test_by_category": {c: _pct(np.concatenate(v)) for c, v in sorted(by_cat.items())},
        "rest_pose": round(float(energy(np.zeros((1, 72)))[0]), 2),
        "implausible": {k: _pct(v) for k, v in bad.items()},
        "implausible_from": "1000 random test-split frames, knees/elbows replaced; random rotations on their own",
    }
    prior.info = info
    path = prior.save(args.out)

    print(f"\nmean log-likelihood per pose ({X.shape[1]}-d, nats): train {info['mean_log_likelihood_train']}, "
          f"held-out test split {info['mean_log_likelihood_test']} ({len(test)} clips, {len(X_test)} frames; a check only)")
    print("\nprior energy (0 = the best attainable; p10 / median / p90):")
    rowsfmt = [("train (used frames)", info["energy"]["train_used"]), ("test, all frames", info["energy"]["test_all_frames"])]
    rowsfmt += [(f"  test {c}", v) for c, v in info["energy"]["test_by_category"].items()]
    rowsfmt += [(f"test frames, {k}" if k != "random_rotations" else k, v) for k, v in info["energy"]["implausible"].items()]
    for name, v in rowsfmt:
        print(f"  {name:34s} {v['p10']:10.1f} {v['median']:10.1f} {v['p90']:10.1f}")
    print(f"  {'rest pose (all zeros)':34s} {info['energy']['rest_pose']:10.1f}")
    print(f"\nwrote {path} ({path.stat().st_size / 1024:.0f} KiB): {prior!r}; {time.perf_counter() - t0:.0f} s in all")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
