"""Train flowmocap's keypoint lifter (:mod:`flowmocap.vision.lifter`): 2D detector keypoints to 3D.

Data: the ``train`` clips of ``../shared/data/mocap/prior/`` (test subjects 2, 8, 13 and 61
are never used), retargeted onto the default body by :func:`flowmocap.io.retarget.retarget`
as ``tools/train_pose_prior.py`` does (``--cache`` shares its cache file).

Steps:

1. Every second frame of every train clip and its left/right mirror
   (:func:`flowmocap.fit.pose_prior.mirror_pose`), posed on a random body (shape
   coefficients from N(0, 1)); the 13 points where the detector puts its keypoints
   (:mod:`flowmocap.vision.keypoint_map`'s learned offsets; the head at the middle of the
   ears), hip-centred, in the mocap's axes (y up).
2. Each training step draws for every pose a fresh view: azimuth uniform over 360
   degrees, elevation uniform in +-25 degrees, distance 2.5-8 m, the camera looking at the
   hips; perspective projection; the 2D points normalised
   (:func:`flowmocap.vision.lifter.normalise_2d`) with Gaussian noise of a random size
   (standard deviation up to ``--noise`` of the normalised scale) and each point but the
   hips dropped with probability ``--drop``. Target: the 3D points in the camera's axes,
   hip-centred, divided by the hips' depth times the 2D scale (so its x, y match the
   input's under weak perspective and the network learns mostly the depth).
3. Adam with a one-cycle learning rate, ``--epochs`` passes, loss the mean joint distance.
4. Check (not used to choose anything): the mean per-joint error after a similarity
   alignment on the train poses seen from random views, and the same on the held-out
   test clips; written into the file's info.

About 5 minutes on 2 CPU cores at the defaults.

    python tools/train_lifter.py --cache /tmp/prior_poses.npz     # writes src/flowmocap/vision/data/lifter.npz
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from flowmocap.body import load_body_model
from flowmocap.body.skeleton import EVAL_JOINTS
from flowmocap.fit.pose_prior import mirror_pose
from flowmocap.geometry.procrustes import similarity_procrustes
from flowmocap.vision.keypoint_map import load_keypoint_map
from flowmocap.vision.lifter import HIPS, LIFTER_FILE, Lifter, LifterNet, normalise_2d

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_pose_prior import DEFAULT_DATA, TEST_SUBJECTS, read_index, retarget_all  # noqa: E402


def keypoint_points(poses: np.ndarray, rng: np.random.Generator, model, kmap, chunk: int = 2048) -> np.ndarray:
    """``(N, 13, 3)`` the detector's 13 points on ``poses (N, 72)`` posed on random bodies,
    hip-centred, metres, the mocap's axes."""
    out = []
    for i in range(0, len(poses), chunk):
        p = torch.as_tensor(poses[i:i + chunk], dtype=torch.float32)
        b = torch.as_tensor(rng.normal(0, 1, (len(p), 10)), dtype=torch.float32)
        with torch.no_grad():
            o = model(betas=b, pose=p, trans=torch.zeros(len(p), 3))
        j, t = o.joints.double().numpy(), o.transforms.double().numpy()
        pts = kmap.apply(j, t)[:, list(EVAL_JOINTS)]
        pts[:, 0] = kmap.ears_middle(j, t)
        out.append(pts - pts[:, list(HIPS)].mean(1, keepdims=True))
    return np.concatenate(out)


def views(points: torch.Tensor, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Random views of hip-centred ``points (B, 13, 3)`` (y up): ``(2D (B, 13, 2) on the
    image plane at depth 1, 3D (B, 13, 3) in the camera's axes)``."""
    n = len(points)
    a = torch.rand(n, generator=g) * 2 * math.pi
    e = (torch.rand(n, generator=g) * 2 - 1) * math.radians(25)
    d = 2.5 + torch.rand(n, generator=g) * 5.5
    ca, sa, ce, se = a.cos(), a.sin(), e.cos(), e.sin()
    Ry = torch.zeros(n, 3, 3)
    Ry[:, 0, 0], Ry[:, 0, 2], Ry[:, 1, 1], Ry[:, 2, 0], Ry[:, 2, 2] = ca, sa, 1, -sa, ca
    Rx = torch.zeros(n, 3, 3)
    Rx[:, 0, 0], Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = 1, ce, -se, se, ce
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0]))  # y up -> y down (and z turned: a proper rotation)
    cam = points @ (Rx @ flip @ Ry).transpose(1, 2)
    cam[..., 2] += d[:, None]
    return cam[..., :2] / cam[..., 2:], cam


def examples(points: torch.Tensor, g: torch.Generator, noise: float, drop: float):
    """``(inputs, masks, targets)`` for a batch of poses (step 2 of the module docstring)."""
    uv, cam = views(points, g)
    n = len(points)
    mask = (torch.rand(n, uv.shape[1], generator=g) > drop).float()
    mask[:, list(HIPS)] = 1
    v, s = normalise_2d(uv, torch.ones_like(mask))
    z0 = cam[:, list(HIPS), 2].mean(1)[:, None, None]
    target = (cam - cam[:, list(HIPS)].mean(1, keepdim=True)) / (z0 * s)
    v = (v + torch.randn(v.shape, generator=g) * torch.rand(n, 1, 1, generator=g) * noise) * mask[..., None]
    return v, mask, target


def check(net: LifterNet, points: np.ndarray, metres: float, seed: int = 1) -> float:
    """Mean per-point error (cm) after a similarity alignment, random views, no noise."""
    g = torch.Generator().manual_seed(seed)
    v, m, _ = examples(torch.as_tensor(points, dtype=torch.float32), g, 0.0, 0.0)
    _, cam = views(torch.as_tensor(points, dtype=torch.float32), torch.Generator().manual_seed(seed))
    with torch.no_grad():
        y = net.eval()(v, m).double().numpy() * metres
    ref = cam.double().numpy()
    aligned = similarity_procrustes(y, ref)[0]
    return 100 * float(np.linalg.norm(aligned - ref, axis=-1).mean())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the mocap/prior folder")
    ap.add_argument("--out", type=Path, default=LIFTER_FILE, help="the lifter file to write (.npz)")
    ap.add_argument("--cache", type=Path, default=None, help="retargeted poses (shared with train_pose_prior.py)")
    ap.add_argument("--hidden", type=int, default=512)
    ap.add_argument("--blocks", type=int, default=2)
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--noise", type=float, default=0.06, help="largest 2D noise, fraction of the normalised scale")
    ap.add_argument("--drop", type=float, default=0.05, help="probability of leaving a point out")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    rows = read_index(args.data)
    model = load_body_model("default", dtype=torch.float64)
    poses = retarget_all(rows, args.data, model, args.cache)
    train = [r for r in rows if r["split"] == "train"]
    test = [r for r in rows if r["split"] == "test"]
    assert not {r["subject"] for r in train} & TEST_SUBJECTS
    P = np.concatenate([poses[r["file"]][::2] for r in train])
    P = np.concatenate([P, mirror_pose(P)])
    body = load_body_model("default")
    kmap = load_keypoint_map()
    X = keypoint_points(P, rng, body, kmap)
    X_test = keypoint_points(np.concatenate([poses[r["file"]][::4] for r in test]), rng, body, kmap)
    # one normalised unit in metres: the 3D target's RMS size per unit of the 2D scale, on average
    g = torch.Generator().manual_seed(args.seed)
    _, _, tgt = examples(torch.as_tensor(X[:4096], dtype=torch.float32), g, 0.0, 0.0)
    rms_m = np.sqrt((X[:4096] ** 2).sum(-1).mean(1))
    rms_u = tgt.double().pow(2).sum(-1).mean(1).sqrt().numpy()
    metres = float(np.mean(rms_m / rms_u))
    print(f"{len(train)} train clips, {len(X)} poses with mirrors; {len(X_test)} held-out test poses (a check only)")

    net = LifterNet(args.hidden, args.blocks)
    opt = torch.optim.Adam(net.parameters(), args.lr)
    steps_per_epoch = len(X) // args.batch
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, args.lr, total_steps=args.epochs * steps_per_epoch)
    Xt = torch.as_tensor(X, dtype=torch.float32)
    g = torch.Generator().manual_seed(args.seed + 1)
    for epoch in range(args.epochs):
        net.train()
        perm = torch.randperm(len(Xt), generator=g)
        total = 0.0
        for k in range(steps_per_epoch):
            v, m, y = examples(Xt[perm[k * args.batch:(k + 1) * args.batch]], g, args.noise, args.drop)
            loss = (net(v, m) - y).norm(dim=-1).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item()
        print(f"epoch {epoch + 1}/{args.epochs}: loss {total / steps_per_epoch:.4f} ({time.perf_counter() - t0:.0f} s)",
              flush=True)
    train_cm = check(net, X[::10], metres)
    test_cm = check(net, X_test, metres)
    print(f"check, aligned mean point error from random views without noise: train {train_cm:.2f} cm, "
          f"held-out test clips {test_cm:.2f} cm")
    info = {
        "source": "CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu), cgspeed BVH conversions, "
                  "../shared/data/mocap/prior, split 'train' only",
        "acknowledgement": "The data used in this project was obtained from mocap.cs.cmu.edu. "
                           "The database was created with funding from NSF EIA-0196217.",
        "train_subjects": sorted({r["subject"] for r in train}), "poses_with_mirrors": len(X),
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "check_train_cm": train_cm, "check_test_cm": test_cm,
    }
    Lifter(net, info, metres).save(args.out)
    print(f"wrote {args.out} ({args.out.stat().st_size // 1024} KiB) in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
