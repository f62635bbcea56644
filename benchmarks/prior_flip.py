"""Does the pose prior tell a person's pose from the same pose with one limb mirrored in depth?

The tracker's depth-flip test (:mod:`flowmocap.fit.flip`) keeps a limb's mirror image in
depth (the child joint moved along its camera ray, the parent kept) where the frame's
energy is lower. Flow, silhouettes and 2D joints barely tell the two apart; the pose prior
``E_p`` is one of the terms that can (the sixth session: without it the flip test takes
mirrors on tiny energy differences). This script measures how often the prior alone
prefers the real pose, on mocap poses it was not fitted to:

1. poses: every ``--every``-th frame of the chosen clips of ``../shared/data/mocap/prior``,
   retargeted as the prior's training does (:mod:`tools/train_pose_prior.py`), at most
   ``--poses`` of them drawn at random;
2. for each pose a random camera 4 m from the pelvis (azimuth uniform, elevation -5 to 25
   degrees, looking at the pelvis), and each limb of
   :data:`~flowmocap.fit.energies.DEPTH_LIMBS` mirrored as the flip test mirrors it
   (:func:`flowmocap.fit.flip.mirrored_rotvec`);
3. per limb: the share of mirrors whose child joint moved more than ``--min-move`` (10 cm)
   that the prior scores higher than the real pose ("accuracy"), and the median energy
   margin (nats).

Which poses (``--split``):

- ``test``: the test subjects (2, 8, 13, 61) with the given prior files (default: the
  packaged one, which never saw them);
- ``train-hold``: train subjects 6, 12 and 135 (``--hold``); with ``--components K ...``
  mixtures of K Gaussians are fitted here to the other train subjects (the packaged
  recipe otherwise, ``n_init`` 2; scikit-learn needed) and scored beside the prior files.
  This is the split for choosing anything about the prior; the test split is for checking.

Usage: python benchmarks/prior_flip.py [--split test|train-hold] [--prior FILE ...]
       [--components K ...] [--poses 600] [--every 15] [--out PREFIX]
Writes PREFIX.json and PREFIX.md (default ``benchmarks/results/prior_flip_<split>``).
About a minute for the packaged prior; each fitted mixture adds 0.5-2 minutes.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from flowmocap.geometry.camera import look_at

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import train_pose_prior as tp  # noqa: E402  (the prior's data, split and retargeting)


def flip_pairs(joints: np.ndarray, rotations: np.ndarray, poses: np.ndarray, limbs, rng,
               distance: float = 4.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """Each pose with each limb mirrored in depth, seen by a random camera per pose.

    Args:
        joints: ``(N, 24, 3)`` posed joints, world axes (y up), metres.
        rotations: ``(N, 24, 3, 3)`` the joints' global rotations.
        poses: ``(N, 72)`` axis-angle, radians.
        limbs: ``(parent, child)`` SMPL joint indices.
        rng: a numpy Generator (the cameras).
        distance: the camera's distance from the pelvis, metres.

    Returns:
        ``(index (M,), limb (M,), flipped (M, 72), cameras)``: which pose and which limb
        (an index into ``limbs``) each mirrored pose comes from, and the ``N`` cameras
        ``(R, t)``. Limbs without a distinct mirror image are left out.
    """
    from flowmocap.fit.flip import mirrored_rotvec

    index, which, flipped, cams = [], [], [], []
    for i in range(len(poses)):
        az, el = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(-5, 25))
        pel = joints[i, 0]
        R, t = look_at(pel + distance * np.array([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)]), pel)
        cams.append((R, t))
        for k, limb in enumerate(limbs):
            rv = mirrored_rotvec(poses[i], joints[i], rotations[i], R, t, limb)
            if rv is None:
                continue
            q = np.array(poses[i], np.float64)
            q[3 * limb[0]:3 * limb[0] + 3] = rv
            index.append(i)
            which.append(k)
            flipped.append(q)
    return np.array(index, int), np.array(which, int), np.array(flipped).reshape(-1, 72), cams


def mirrors(model, poses: np.ndarray, limbs, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`flip_pairs` of ``poses (N, 72)`` posed on ``model`` (a float64
    :class:`~flowmocap.body.BodyModel`, mean shape), and how far each mirror moved its
    limb's child joint: ``(index (M,), limb (M,), flipped (M, 72), moved (M,) metres)``."""
    with torch.no_grad():
        out = model(pose=torch.as_tensor(poses, dtype=torch.float64), with_vertices=False)
        J, G = out.joints.numpy(), out.transforms[:, :, :3, :3].numpy()
        index, which, flipped, _ = flip_pairs(J, G, poses, limbs, rng)
        Jf = model(pose=torch.as_tensor(flipped), with_vertices=False).joints.numpy()
    child = np.array([limbs[k][1] for k in which], int)
    return index, which, flipped, np.linalg.norm(Jf[np.arange(len(which)), child] - J[index, child], axis=-1)


def discrimination(e_real: np.ndarray, e_flip: np.ndarray, index: np.ndarray, which: np.ndarray,
                   moved: np.ndarray, n_limbs: int, min_move: float = 0.10) -> dict:
    """How often an energy prefers the real pose over its mirror.

    Args:
        e_real: ``(N,)`` the energy of each real pose; e_flip: ``(M,)`` of each mirror.
        index, which: ``(M,)`` each mirror's pose and limb (:func:`flip_pairs`).
        moved: ``(M,)`` how far each mirror moved its limb's child joint, metres.
        n_limbs: the number of limbs.
        min_move: mirrors that moved the child less are not counted, metres.

    Returns:
        ``{"accuracy", "median_margin", "mirrors", "per_limb": [{"accuracy", "median_margin",
        "mirrors"}] }``: the share of counted mirrors with ``e_flip > e_real`` (a tie counts
        half) and the median of ``e_flip - e_real`` (nats), over all and per limb.
    """
    d = np.asarray(e_flip, np.float64) - np.asarray(e_real, np.float64)[index]
    use = np.asarray(moved) > min_move

    def one(m):
        if not m.any():
            return {"accuracy": None, "median_margin": None, "mirrors": 0}
        x = d[m]
        return {"accuracy": float((x > 0).mean() + 0.5 * (x == 0).mean()), "median_margin": float(np.median(x)),
                "mirrors": int(m.sum())}

    out = one(use)
    out["per_limb"] = [one(use & (which == k)) for k in range(n_limbs)]
    return out


def _energy(prior, poses: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return prior.energy(torch.as_tensor(poses, dtype=torch.float64)).numpy()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--split", choices=("test", "train-hold"), default="test")
    ap.add_argument("--prior", type=Path, nargs="*", default=None, help="prior .npz files (default: the packaged one)")
    ap.add_argument("--components", type=int, nargs="*", default=[], help="train-hold only: fit mixtures of these sizes")
    ap.add_argument("--hold", type=int, nargs="*", default=[6, 12, 135], help="train-hold: the train subjects held out")
    ap.add_argument("--poses", type=int, default=600)
    ap.add_argument("--every", type=int, default=15, help="take every N-th frame of each clip (30 fps)")
    ap.add_argument("--min-move", type=float, default=0.10, help="metres the child joint must move to count")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data", type=Path, default=tp.DEFAULT_DATA)
    ap.add_argument("--cache", type=Path, default=None, help="retargeted poses (train_pose_prior.py's --cache)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.components and args.split != "train-hold":
        sys.exit("--components fits mixtures on the train subjects; use it with --split train-hold")
    if args.components and args.cache is None:
        sys.exit("--components needs --cache (every clip retargeted once, as train_pose_prior.py keeps them)")

    from flowmocap.body import load_body_model
    from flowmocap.fit.energies import DEPTH_LIMBS
    from flowmocap.fit.flip import limb_name
    from flowmocap.fit.pose_prior import PosePrior, default_prior_path, mirror_pose

    t0 = time.perf_counter()
    rows = tp.read_index(args.data)
    hold = set(args.hold)
    if hold & tp.TEST_SUBJECTS:
        sys.exit("--hold must name train subjects")
    if args.split == "test":
        chosen = [r for r in rows if r["split"] == "test"]
    else:
        chosen = [r for r in rows if r["split"] == "train" and r["subject"] in hold]
    model = load_body_model("default", dtype=torch.float64)
    if args.cache is not None:
        poses_by_file = tp.retarget_all(rows, args.data, model, args.cache)
    else:
        poses_by_file = tp.retarget_all(chosen, args.data, model, None)
    rng = np.random.default_rng(args.seed)
    P = np.concatenate([poses_by_file[r["file"]][::args.every] for r in chosen])
    P = P[np.sort(rng.choice(len(P), min(args.poses, len(P)), replace=False))]
    index, which, flipped, moved = mirrors(model, P, DEPTH_LIMBS, rng)

    priors = {}
    for f in args.prior or [default_prior_path()]:
        priors[Path(f).name + (" (packaged)" if args.prior is None else "")] = PosePrior.load(f)
    if args.components:  # the packaged recipe's joints and training poses, without the held-out subjects
        from sklearn.mixture import GaussianMixture

        joints, _ = tp.choose_joints(rows, poses_by_file, 1.0)
        cols = np.array([3 * j + c for j in joints for c in range(3)])
        fit_rows = [r for r in rows if r["split"] == "train" and r["subject"] not in hold]
        X, _ = tp.balance(fit_rows, poses_by_file, 3000)
        X = np.concatenate([X, mirror_pose(X)])[:, cols]
    for k in args.components:
        g = GaussianMixture(n_components=k, covariance_type="full", reg_covar=1e-3, n_init=2, max_iter=500,
                            tol=1e-4, random_state=args.seed).fit(X)
        priors[f"{k} components, fitted without subjects {sorted(hold)}"] = PosePrior(
            g.weights_, g.means_, g.precisions_cholesky_, joints, {})

    result = {"split": args.split, "subjects": sorted({r["subject"] for r in chosen}), "clips": len(chosen),
              "poses": len(P), "mirrors": len(which), "mirrors_counted": int((moved > args.min_move).sum()),
              "min_move_m": args.min_move, "seed": args.seed, "limbs": [limb_name(l) for l in DEPTH_LIMBS],
              "priors": {}}
    for name, prior in priors.items():
        e_real = _energy(prior, P)
        r = discrimination(e_real, _energy(prior, flipped), index, which, moved, len(DEPTH_LIMBS), args.min_move)
        r["real_energy_median"] = float(np.median(e_real))
        result["priors"][name] = r
    result["seconds"] = round(time.perf_counter() - t0, 1)

    lines = [f"# The pose prior against one limb mirrored in depth ({args.split} split)", "",
             f"{result['poses']} poses of {result['clips']} clips (subjects {result['subjects']}), "
             f"{result['mirrors_counted']} mirrors that move the limb's child joint by more than "
             f"{args.min_move * 100:.0f} cm. Accuracy: the share the prior scores higher than the real pose; "
             "margin: the median energy difference, nats.", "",
             "| prior | real poses' median energy | accuracy | margin | " + " | ".join(result["limbs"]) + " |",
             "|---|---:|---:|---:|" + "---:|" * len(result["limbs"])]
    for name, r in result["priors"].items():
        per = " | ".join("-" if x["accuracy"] is None else f"{x['accuracy']:.2f}" for x in r["per_limb"])
        lines.append(f"| {name} | {r['real_energy_median']:.1f} | {r['accuracy']:.3f} | {r['median_margin']:.1f} | {per} |")
    text = "\n".join(lines) + "\n"
    print(text)
    prefix = Path(args.out) if args.out else ROOT / "benchmarks" / "results" / f"prior_flip_{args.split.replace('-', '_')}"
    prefix.parent.mkdir(parents=True, exist_ok=True)
    Path(f"{prefix}.json").write_text(json.dumps(result, indent=1) + "\n")
    Path(f"{prefix}.md").write_text(text)
    print(f"wrote {prefix}.json and {prefix}.md ({result['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
