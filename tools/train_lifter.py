"""Train flowmocap's keypoint lifter (:mod:`flowmocap.vision.lifter`): 2D detector keypoints to 3D.

Data: the ``train`` clips of ``../shared/data/mocap/prior/`` (test subjects 2, 8, 13 and 61
are never used), retargeted onto the default body by :func:`flowmocap.io.retarget.retarget`
as ``tools/train_pose_prior.py`` does (``--cache`` shares its cache file).

Steps:

1. Every frame of every train clip (30 fps) posed on ``--bodies`` random bodies per clip
   (shape coefficients from N(0, 1), one body for the whole clip), each also as its
   left/right mirror (:func:`flowmocap.fit.pose_prior.mirror_pose`); the 13 points where
   the detector puts its keypoints (:mod:`flowmocap.vision.keypoint_map`'s learned
   offsets; the head at the middle of the ears), hip-centred, in the mocap's axes (y up).
2. Each training step draws for every example a frame and a fresh view: azimuth uniform
   over 360 degrees, elevation uniform in +-25 degrees, distance 2.5-8 m, the camera
   looking at the hips; perspective projection; each frame's 2D points normalised as at
   run time (:func:`flowmocap.vision.lifter.normalise_2d` over the points given) with
   Gaussian noise of a random size (standard deviation up to ``--noise`` of the normalised
   scale) and each point but the hips dropped with probability ``--drop``; with
   ``--outliers P`` a share P of the frames also get 1-3 gross errors (a point but the
   hips moved onto another point of the frame, as a detector does under occlusion;
   ``--elevation`` widens the views' elevation, ``--roll`` turns the cameras about their
   optical axis by up to that many degrees, ``--persist`` makes a window's 2D errors last
   over its frames; all tried, none used by the packaged file: docs/experiments.md,
   "Where the real3d error comes from" and the nineteenth session). Target: the 3D
   points in the camera's axes, hip-centred, divided by the hips' depth times the 2D
   scale (so its x, y match the input's under weak perspective and the network learns
   mostly the depth). With a window (``--offsets``, frames at 30 fps around the lifted
   one) the neighbours come from the same clip, body and view, at a tempo drawn from
   ``1 +- --tempo``; a neighbour outside the clip, or dropped with probability
   ``--frame-drop``, is left out, as at run time.
   With ``--detections FOLDER`` (``tools/render_detections.py``'s pairs: the real
   detector's 2D on renders of train clips, none of the tune suite's) a share
   ``--detection-share`` of each batch is drawn from those instead (each mirrored with
   probability 0.5; no added noise: the detector's own errors are the point); every 10th
   of their clips is held back as a check. ``--init FILE`` starts from a lifter file's
   weights (fine-tuning; its ``metres`` is kept).
3. Adam with a one-cycle learning rate, ``--epochs`` passes, loss the mean joint distance.
4. Check (not used to choose anything): the mean per-joint error after a similarity
   alignment on the train frames seen from random views, the same on the held-out
   test clips, and with ``--detections`` on the held-back detections; written into the
   file's info.

The packaged file's settings are in its ``info["settings"]`` (``vision/data/README.md``).
At the defaults (512 wide, two blocks, one frame) about 10 minutes on 2 CPU cores;
``--device cuda`` trains on a GPU (the same steps; the data is made on the CPU).

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
from flowmocap.vision.lifter import HIPS, LIFTER_FILE, POINTS, WINDOW_FPS, Lifter, LifterNet, normalise_2d

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_pose_prior import DEFAULT_DATA, TEST_SUBJECTS, read_index, retarget_all  # noqa: E402


def keypoint_points(poses: np.ndarray, betas: np.ndarray, model, kmap, chunk: int = 2048) -> np.ndarray:
    """``(N, 13, 3)`` the detector's 13 points on ``poses (N, 72)`` posed on one body
    (``betas (10,)``), hip-centred, metres, the mocap's axes."""
    out = []
    for i in range(0, len(poses), chunk):
        p = torch.as_tensor(poses[i:i + chunk], dtype=torch.float32)
        b = torch.as_tensor(np.tile(betas, (len(p), 1)), dtype=torch.float32)
        with torch.no_grad():
            o = model(betas=b, pose=p, trans=torch.zeros(len(p), 3))
        j, t = o.joints.double().numpy(), o.transforms.double().numpy()
        pts = kmap.apply(j, t)[:, list(EVAL_JOINTS)]
        pts[:, 0] = kmap.ears_middle(j, t)
        out.append(pts - pts[:, list(HIPS)].mean(1, keepdims=True))
    return np.concatenate(out)


class Sequences:
    """Clips' 13 points, frame after frame: ``X (N, 13, 3)`` and, for each frame, the
    first and one-past-last frame of its clip (``start``, ``end``, ``(N,)``)."""

    def __init__(self, clips: list[np.ndarray], rng: np.random.Generator, model, kmap, bodies: int, mirror: bool):
        xs, starts, ends, n = [], [], [], 0
        for P in clips:
            for _ in range(bodies):
                betas = rng.normal(0, 1, 10)
                for Q in ((P, mirror_pose(P)) if mirror else (P,)):
                    x = keypoint_points(Q, betas, model, kmap)
                    xs.append(x)
                    starts.append(np.full(len(x), n))
                    ends.append(np.full(len(x), n + len(x)))
                    n += len(x)
        self.X = torch.as_tensor(np.concatenate(xs), dtype=torch.float32)
        self.start = torch.as_tensor(np.concatenate(starts))
        self.end = torch.as_tensor(np.concatenate(ends))

    def __len__(self) -> int:
        return len(self.X)

    def to(self, device) -> "Sequences":
        self.X, self.start, self.end = self.X.to(device), self.start.to(device), self.end.to(device)
        return self


def views(points: torch.Tensor, g: torch.Generator, elevation: float = 25.0,
          roll: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Random views of hip-centred ``points (B, P, 3)`` (y up; one view per row ``B``;
    elevation uniform in +-``elevation`` degrees):
    ``(2D (B, P, 2) on the image plane at depth 1, 3D (B, P, 3) in the camera's axes)``."""
    n, dev = len(points), points.device
    a = torch.rand(n, generator=g, device=dev) * 2 * math.pi
    e = (torch.rand(n, generator=g, device=dev) * 2 - 1) * math.radians(elevation)
    d = 2.5 + torch.rand(n, generator=g, device=dev) * 5.5
    ca, sa, ce, se = a.cos(), a.sin(), e.cos(), e.sin()
    Ry = torch.zeros(n, 3, 3, device=dev)
    Ry[:, 0, 0], Ry[:, 0, 2], Ry[:, 1, 1], Ry[:, 2, 0], Ry[:, 2, 2] = ca, sa, 1, -sa, ca
    Rx = torch.zeros(n, 3, 3, device=dev)
    Rx[:, 0, 0], Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = 1, ce, -se, se, ce
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], device=dev))  # y up -> y down (and z turned: a proper rotation)
    cam = points @ (Rx @ flip @ Ry).transpose(1, 2)
    if roll > 0:  # the camera turned about its optical axis (drawn only then: the stream of draws stays the same without)
        r = (torch.rand(n, generator=g, device=dev) * 2 - 1) * math.radians(roll)
        Rz = torch.zeros(n, 3, 3, device=dev)
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = r.cos(), -r.sin(), r.sin(), r.cos(), 1
        cam = cam @ Rz.transpose(1, 2)
    cam[..., 2] += d[:, None]
    return cam[..., :2] / cam[..., 2:], cam


def outlying(uv: torch.Tensor, g: torch.Generator, rate: float, most: int = 3) -> torch.Tensor:
    """``uv (N, 13, 2)`` with gross detector errors: in a share ``rate`` of the rows, 1 to
    ``most`` points other than the hips are moved onto another point of the same row, plus
    Gaussian scatter of a fifth of the row's size (its RMS distance from the hips) -- a
    joint put on another body part, as the detector does under occlusion."""
    if rate <= 0:
        return uv
    N, P, dev = uv.shape[0], uv.shape[1], uv.device
    c = uv[:, list(HIPS)].mean(1, keepdim=True)
    size = (uv - c).pow(2).sum(-1).mean(1).sqrt()[:, None, None]
    hit = torch.rand(N, generator=g, device=dev) < rate
    count = torch.randint(1, most + 1, (N,), generator=g, device=dev)
    rank = torch.rand(N, P, generator=g, device=dev)
    rank[:, list(HIPS)] = 2.0  # never chosen
    order = rank.argsort(1).argsort(1)
    moved = hit[:, None] & (order < count[:, None])
    onto = torch.randint(0, P, (N, P), generator=g, device=dev)
    target = torch.gather(uv, 1, onto[..., None].expand(N, P, 2))
    target = target + torch.randn(uv.shape, generator=g, device=dev) * 0.2 * size
    return torch.where(moved[..., None], target, uv)


def examples(seq: Sequences, centres: torch.Tensor, offsets: torch.Tensor, g: torch.Generator, noise: float,
             drop: float, frame_drop: float = 0.0, speed: float = 0.0, outliers: float = 0.0,
             elevation: float = 25.0, roll: float = 0.0, persist: float = 0.0):
    """``(inputs (B, F, 13, 2), masks (B, F, 13), targets (B, 13, 3), the middle frames'
    3D in the camera's axes (B, 13, 3) in metres)`` for the windows
    around the frames ``centres (B,)`` of ``seq`` (step 2 of the module docstring): one view
    and one tempo (``1 +- speed``) per window; neighbours outside the clip, or dropped with
    probability ``frame_drop``, are masked out. ``persist`` in [0, 1]: how much the 2D
    errors last over a window, as a detector's do -- the noise is ``persist`` times one draw
    shared by the window's frames plus ``sqrt(1 - persist^2)`` times a draw of its own per
    frame (the same variance), and with probability ``persist`` a window's frames drop the
    same points; 0: every frame's errors independent."""
    B, F, dev = len(centres), len(offsets), seq.X.device
    mid = int((offsets == 0).nonzero()[0])
    tempo = 1 + (torch.rand(B, generator=g, device=dev) * 2 - 1) * speed
    j = centres[:, None] + torch.round(offsets[None].double() * tempo[:, None].double()).long()
    inside = (j >= seq.start[centres, None]) & (j < seq.end[centres, None])
    j = torch.where(inside, j, centres[:, None])
    keep = inside & (torch.rand(B, F, generator=g, device=dev) >= frame_drop)
    keep[:, mid] = True
    uv, cam = views(seq.X[j].reshape(B, F * len(POINTS), 3), g, elevation, roll)
    uv, cam = uv.view(B, F, len(POINTS), 2), cam.view(B, F, len(POINTS), 3)
    clean = uv
    uv = outlying(uv.reshape(B * F, len(POINTS), 2), g, outliers).view(B, F, len(POINTS), 2)
    mask = (torch.rand(B, F, len(POINTS), generator=g, device=dev) > drop).float()
    if persist > 0:  # some windows drop the same points in every frame
        same = torch.rand(B, 1, 1, generator=g, device=dev) < persist
        mask = torch.where(same, mask[:, mid:mid + 1].expand_as(mask), mask)
    mask[..., list(HIPS)] = 1
    mask = mask * keep[..., None].float()
    v, _ = normalise_2d(uv.reshape(B * F, len(POINTS), 2), mask.reshape(B * F, len(POINTS)))
    v = v.view(B, F, len(POINTS), 2)
    e = torch.randn(v.shape, generator=g, device=dev)
    if persist > 0:
        shared = torch.randn(B, 1, len(POINTS), 2, generator=g, device=dev)
        e = persist * shared + math.sqrt(1 - persist ** 2) * e
    v = (v + e * torch.rand(B, 1, 1, 1, generator=g, device=dev) * noise) * mask[..., None]
    _, s = normalise_2d(clean[:, mid], torch.ones(B, len(POINTS), device=dev))
    c = cam[:, mid]
    z0 = c[:, list(HIPS), 2].mean(1)[:, None, None]
    target = (c - c[:, list(HIPS)].mean(1, keepdim=True)) / (z0 * s)
    return v, mask, target, c


class DetectionPairs:
    """Real detector 2D with the true 3D (``tools/render_detections.py``'s files): ``P (N,
    13, 2)`` pixels, ``M (N, 13)`` the points given (confidence >= 0.5, as at run time),
    ``Y (N, 13, 3)`` the target (step 2 of the module docstring: hip-centred, in the axes of
    the ray through the detected hips, divided by the hips' distance times the clean 2D's
    scale), ``clip (N,)`` each frame's clip index. A frame the detector turned about (its
    points nearer the truth's mirror labelling, by half) gets the mirror labelling as its
    target: the lifter lifts the 2D as labelled; which side is which is the tracker's
    business (``detector_swap_check``). Frames with fewer than ``MIN_POINTS`` points or
    without both hips are left out."""

    def __init__(self, folder: Path):
        from flowmocap.geometry.camera import PinholeCamera
        from flowmocap.vision.lifter import MIN_POINTS, MIRROR, eval_points_2d

        files = sorted(folder.glob("*.npz"))
        files = [f for f in files if not f.name.endswith(".part.npz")]
        if not files:
            sys.exit(f"no detection pairs in {folder}: run tools/render_detections.py --out {folder}")
        P, M, Y, C, self.turned = [], [], [], [], 0
        clips = sorted({str(np.load(f)["clip"]) for f in files})
        for f in files:
            z = np.load(f)
            pts, conf = eval_points_2d(z["keypoints"], z["confidence"])
            mask = (conf >= 0.5) & np.isfinite(pts).all(-1)
            ok = mask[:, list(HIPS)].all(1) & (mask.sum(1) >= MIN_POINTS)
            if not ok.any():
                continue
            K = z["K"]
            cam = PinholeCamera(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=640, height=480)
            truth, uv = z["truth"][ok], z["truth_2d"][ok]
            pts, mask = pts[ok], mask[ok]
            d_same = np.where(mask, np.linalg.norm(np.nan_to_num(pts) - uv, axis=-1), 0).sum(1)
            d_mirr = np.where(mask, np.linalg.norm(np.nan_to_num(pts) - uv[:, list(MIRROR)], axis=-1), 0).sum(1)
            turn = d_mirr < 0.5 * d_same
            self.turned += int(turn.sum())
            truth[turn], uv[turn] = truth[turn][:, list(MIRROR)], uv[turn][:, list(MIRROR)]
            for k in range(len(pts)):
                u, v = np.nan_to_num(pts[k, list(HIPS)]).mean(0)
                R = cam.ray_rotation(float(u), float(v))
                hips = truth[k, list(HIPS)].mean(0)
                x = (truth[k] - hips) @ R
                n = (uv[k] - [K[0, 2], K[1, 2]]) / K[0, 0]
                n = n - n[list(HIPS)].mean(0)
                s = np.sqrt((n ** 2).sum(-1).mean())
                Y.append(x / (np.linalg.norm(hips) * s))
            P.append(np.nan_to_num(pts))
            M.append(mask)
            C.append(np.full(len(pts), clips.index(str(z["clip"]))))
        self.P = torch.as_tensor(np.concatenate(P), dtype=torch.float32)
        self.M = torch.as_tensor(np.concatenate(M), dtype=torch.float32)
        self.Y = torch.as_tensor(np.stack(Y), dtype=torch.float32)
        self.clip = torch.as_tensor(np.concatenate(C))
        self.files = len(files)

    def split(self, every: int) -> tuple["DetectionPairs", "DetectionPairs"]:
        """(the frames of clips whose index is not a multiple of ``every``, those that are)."""
        held = (self.clip % every) == 0
        parts = []
        for keep in (~held, held):
            d = object.__new__(DetectionPairs)
            d.P, d.M, d.Y, d.clip = self.P[keep], self.M[keep], self.Y[keep], self.clip[keep]
            d.turned, d.files = self.turned, self.files
            parts.append(d)
        return parts[0], parts[1]

    def __len__(self) -> int:
        return len(self.P)

    def to(self, device) -> "DetectionPairs":
        self.P, self.M, self.Y = self.P.to(device), self.M.to(device), self.Y.to(device)
        return self

    def batch(self, idx: torch.Tensor, g: torch.Generator, mirror: bool = True):
        """``(inputs (B, 1, 13, 2), masks (B, 1, 13), targets (B, 13, 3))`` of the frames
        ``idx``, each mirrored left for right with probability 0.5."""
        from flowmocap.vision.lifter import MIRROR

        p, m, y = self.P[idx], self.M[idx], self.Y[idx]
        v, _ = normalise_2d(p, m)
        if mirror:
            flip = torch.rand(len(idx), generator=g, device=p.device) < 0.5
            sign2, sign3 = torch.tensor([-1.0, 1.0], device=p.device), torch.tensor([-1.0, 1.0, 1.0], device=p.device)
            v = torch.where(flip[:, None, None], v[:, list(MIRROR)] * sign2, v)
            m = torch.where(flip[:, None], m[:, list(MIRROR)], m)
            y = torch.where(flip[:, None, None], y[:, list(MIRROR)] * sign3, y)
        return v[:, None], m[:, None], y


def check_pairs(net: LifterNet, pairs: DetectionPairs, metres: float) -> float:
    """Mean per-point error (cm, in units of an average body) of the lifter on real
    detections after a similarity alignment onto their truth."""
    with torch.no_grad():
        y = net.eval()(*pairs.batch(torch.arange(len(pairs)), None, mirror=False)[:2]).double().numpy()
    ref = pairs.Y.double().numpy()
    aligned = similarity_procrustes(y, ref)[0]
    return 100 * metres * float(np.linalg.norm(aligned - ref, axis=-1).mean())


def check(net: LifterNet, seq: Sequences, offsets: torch.Tensor, metres: float, step: int = 1,
          seed: int = 1) -> float:
    """Mean per-point error (cm) after a similarity alignment over every ``step``-th frame
    of ``seq``: random views, no noise, nothing dropped, the recorded tempo."""
    g = torch.Generator(seq.X.device).manual_seed(seed)
    errs = []
    for part in torch.arange(0, len(seq), step, device=seq.X.device).split(4096):
        v, m, _, cam = examples(seq, part, offsets, g, 0.0, 0.0)
        with torch.no_grad():
            y = net.eval()(v, m).double().cpu().numpy() * metres
        ref = cam.double().cpu().numpy()
        aligned = similarity_procrustes(y, ref)[0]
        errs.append(np.linalg.norm(aligned - ref, axis=-1).mean(1))
    return 100 * float(np.concatenate(errs).mean())


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
    ap.add_argument("--offsets", default="0",
                    help=f"the window: frames at {WINDOW_FPS:g} fps around the lifted one, comma-separated (0: one frame)")
    ap.add_argument("--bodies", type=int, default=2, help="random body shapes per train clip (each also mirrored)")
    ap.add_argument("--frame-drop", type=float, default=0.1, help="probability of leaving a neighbouring frame out")
    ap.add_argument("--tempo", type=float, default=0.2, help="each window's tempo drawn from 1 +- this")
    ap.add_argument("--outliers", type=float, default=0.0,
                    help="share of frames with 1-3 gross 2D errors (a point put on another body part)")
    ap.add_argument("--persist", type=float, default=0.0,
                    help="how much a window's 2D errors last over its frames, 0-1 (noise shared, same points dropped)")
    ap.add_argument("--elevation", type=float, default=25.0, help="views' elevation drawn from +- this (degrees)")
    ap.add_argument("--roll", type=float, default=0.0,
                    help="views' roll about the optical axis drawn from +- this (degrees; 0: upright cameras)")
    ap.add_argument("--detections", type=Path, default=None,
                    help="a folder of tools/render_detections.py's pairs (real detector 2D on renders of train clips)")
    ap.add_argument("--detection-share", type=float, default=0.3, help="share of each batch drawn from --detections")
    ap.add_argument("--init", type=Path, default=None, help="start from this lifter file's weights (fine-tuning)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-clips", type=int, default=None, help="only the first N train and N test clips (a quick try)")
    ap.add_argument("--device", default="cpu", help="where to train (e.g. cuda; the result is the same file)")
    args = ap.parse_args(argv)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    rows = read_index(args.data)
    model = load_body_model("default", dtype=torch.float64)
    train = [r for r in rows if r["split"] == "train"][:args.max_clips]
    test = [r for r in rows if r["split"] == "test"][:args.max_clips]
    if args.max_clips is None:
        poses = retarget_all(rows, args.data, model, args.cache)
    else:  # a subset: retargeted afresh (the cache holds every clip)
        poses = retarget_all(train + test, args.data, model, None)
    assert not {r["subject"] for r in train} & TEST_SUBJECTS
    body = load_body_model("default")
    kmap = load_keypoint_map()
    offsets = torch.as_tensor(sorted({int(k) for k in args.offsets.split(",")}))
    if 0 not in offsets:
        ap.error("--offsets must hold 0 (the lifted frame)")
    if not 0.0 <= args.persist <= 1.0:
        ap.error("--persist must lie in [0, 1]")
    seq = Sequences([poses[r["file"]] for r in train], rng, body, kmap, args.bodies, mirror=True)
    seq_test = Sequences([poses[r["file"]] for r in test], rng, body, kmap, 1, mirror=False)
    # one normalised unit in metres: the 3D target's RMS size per unit of the 2D scale, on average
    g = torch.Generator().manual_seed(args.seed)
    some = torch.randperm(len(seq), generator=g)[:4096]
    _, _, tgt, cam = examples(seq, some, offsets, g, 0.0, 0.0)
    rms_m = (cam - cam[:, list(HIPS)].mean(1, keepdim=True)).double().pow(2).sum(-1).mean(1).sqrt().numpy()
    rms_u = tgt.double().pow(2).sum(-1).mean(1).sqrt().numpy()
    metres = float(np.mean(rms_m / rms_u))
    print(f"{len(train)} train clips: {len(seq)} frames ({args.bodies} bodies each, with mirrors); "
          f"{len(seq_test)} held-out test frames (a check only); window {offsets.tolist()} at {WINDOW_FPS:g} fps")

    pairs = pairs_check = None
    if args.detections is not None:
        if len(offsets) != 1:
            ap.error("--detections trains a one-frame lifter only (the pairs are not windows)")
        pairs, pairs_check = DetectionPairs(args.detections).split(10)
        print(f"detection pairs: {len(pairs)} frames to train on, {len(pairs_check)} held back as a check "
              f"(every 10th clip), from {pairs.files} files; {pairs.turned} frames turned about", flush=True)
    dev = torch.device(args.device)
    seq, seq_test, offsets = seq.to(dev), seq_test.to(dev), offsets.to(dev)
    net = LifterNet(args.hidden, args.blocks, frames=len(offsets))
    if args.init is not None:
        start = Lifter.load(args.init)
        if start.offsets != tuple(offsets.tolist()) or start.net.inp.out_features != args.hidden or \
                len(start.net.blocks) != args.blocks:
            ap.error(f"--init {args.init} has another architecture or window")
        net.load_state_dict(start.net.state_dict())
        metres = start.metres
        if pairs_check is not None:
            print(f"check of the starting lifter on the held-back detections: {check_pairs(start.net, pairs_check, metres):.2f} cm")
    net = net.to(dev)
    if pairs is not None:
        pairs.to(dev)
    n_det = int(round(args.detection_share * args.batch)) if pairs is not None else 0
    opt = torch.optim.Adam(net.parameters(), args.lr)
    steps_per_epoch = len(seq) // args.batch
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, args.lr, total_steps=args.epochs * steps_per_epoch)
    g = torch.Generator(dev).manual_seed(args.seed + 1)
    for epoch in range(args.epochs):
        net.train()
        perm = torch.randperm(len(seq), generator=g, device=dev)
        total = 0.0
        for k in range(steps_per_epoch):
            v, m, y, _ = examples(seq, perm[k * args.batch:(k + 1) * args.batch - n_det], offsets, g, args.noise,
                                  args.drop, args.frame_drop, args.tempo, args.outliers, args.elevation, args.roll,
                                  args.persist)
            if n_det:
                dv, dm, dy = pairs.batch(torch.randint(0, len(pairs), (n_det,), generator=g, device=dev), g)
                v, m, y = torch.cat([v, dv]), torch.cat([m, dm]), torch.cat([y, dy])
            loss = (net(v, m) - y).norm(dim=-1).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item()
        print(f"epoch {epoch + 1}/{args.epochs}: loss {total / steps_per_epoch:.4f} ({time.perf_counter() - t0:.0f} s)",
              flush=True)
    train_cm = check(net, seq, offsets, metres, step=20)
    test_cm = check(net, seq_test, offsets, metres, step=2)
    print(f"check, aligned mean point error from random views without noise: train {train_cm:.2f} cm, "
          f"held-out test clips {test_cm:.2f} cm")
    pairs_cm = None
    if pairs_check is not None:
        net.cpu()
        pairs_cm = check_pairs(net, pairs_check, metres)
        print(f"check on the held-back detections (renders of train clips, real detector 2D): {pairs_cm:.2f} cm")
    info = {
        "source": "CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu), cgspeed BVH conversions, "
                  "../shared/data/mocap/prior, split 'train' only",
        "acknowledgement": "The data used in this project was obtained from mocap.cs.cmu.edu. "
                           "The database was created with funding from NSF EIA-0196217.",
        "train_subjects": sorted({r["subject"] for r in train}), "frames_with_mirrors": len(seq),
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "check_train_cm": train_cm, "check_test_cm": test_cm, "check_detections_cm": pairs_cm,
    }
    Lifter(net.cpu(), info, metres, offsets.tolist()).save(args.out)
    print(f"wrote {args.out} ({args.out.stat().st_size // 1024} KiB) in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
