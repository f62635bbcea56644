"""Render ``train`` mocap clips and run the detector on them: pairs of real detector 2D and
true 3D for the keypoint lifter (``tools/train_lifter.py --detections``).

The lifter is otherwise trained on the true 2D of the detector's keypoints with Gaussian
noise and dropped points. MediaPipe's real errors are not like that: they last over
frames, depend on the pose and the view (a limb hidden behind the body, a person seen
from behind whose labels are exchanged) and follow the image. This tool makes examples
of those errors without touching a held-out clip:

- clips: the ``train`` clips of ``../shared/data/mocap/prior/`` (test subjects 2, 8, 13
  and 61 never), **less those of the tune suite** (:func:`flowmocap.eval.bench.tune_specs`),
  so that a lifter trained on them can still be judged on ``tune``;
- ``--views`` views of each: seed ``1000 + 10 * clip + view`` draws a window of
  ``--frames`` frames at ``--fps`` anywhere in the clip, a random body, an azimuth
  uniform over 360 degrees and an elevation in 0-20 degrees; rendered by
  :func:`flowmocap.synth.synthesize` as the diverse suite renders (640x480, the same
  clothing and background generator, other seeds);
- the detector the pipeline uses (:class:`~flowmocap.vision.detect.MediaPipePoseDetector`,
  tracking mode; its segmentation is not needed, so without the mask augmentation) over
  the frames in order;
- the truth: the 13 points where the detector puts its keypoints
  (:mod:`flowmocap.vision.keypoint_map`'s learned offsets on the true body; the head at
  the middle of the ears), in the camera's axes.

One ``.npz`` per clip and view in ``--out`` (written when done, so an interrupted run
goes on where it stopped): ``keypoints (T, K, 2)`` pixels and ``confidence (T, K)`` of
:data:`~flowmocap.vision.detect.KEYPOINT_NAMES` (NaN / 0 where nobody was found),
``world (T, K, 3)`` the detector's own 3D, ``truth (T, 13, 3)`` metres in the camera's
axes, ``truth_2d (T, 13, 2)`` pixels, ``K (3, 3)``, ``clip``, ``fps``. About 0.25 s a frame
per process here; ``--part i/n`` splits the work between processes.

    python tools/render_detections.py --out /tmp/detpairs --part 0/2 &
    python tools/render_detections.py --out /tmp/detpairs --part 1/2
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from flowmocap.body import load_body_model
from flowmocap.body.skeleton import EVAL_JOINTS
from flowmocap.io.mocap import read_mocap, resample
from flowmocap.vision.keypoint_map import load_keypoint_map

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_pose_prior import DEFAULT_DATA, TEST_SUBJECTS, read_index  # noqa: E402


def true_points(gt: dict, camera, model, kmap) -> np.ndarray:
    """``(T, 13, 3)`` the detector's 13 points on the true body of ``gt`` (a sequence's
    ``gt.npz``), metres in ``camera``'s axes."""
    T = len(gt["poses"])
    with torch.no_grad():
        o = model(betas=torch.as_tensor(np.tile(gt["betas"], (T, 1)), dtype=torch.float64),
                  pose=torch.as_tensor(gt["poses"], dtype=torch.float64),
                  trans=torch.as_tensor(gt["trans"], dtype=torch.float64))
    j, t = o.joints.numpy(), o.transforms.numpy()
    pts = kmap.apply(j, t)[:, list(EVAL_JOINTS)]
    pts[:, 0] = kmap.ears_middle(j, t)
    return pts @ camera.R.T + camera.t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the mocap/prior folder")
    ap.add_argument("--out", type=Path, required=True, help="folder for the per-view .npz files")
    ap.add_argument("--views", type=int, default=3, help="views per clip")
    ap.add_argument("--frames", type=int, default=40, help="frames per view")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--part", default="0/1", help="i/n: do every n-th clip-view from the i-th")
    args = ap.parse_args(argv)
    from flowmocap.eval.bench import tune_specs
    from flowmocap.io.sequence import load_sequence
    from flowmocap.synth import synthesize
    from flowmocap.vision.detect import KEYPOINT_NAMES, MediaPipePoseDetector

    part, parts = (int(x) for x in args.part.split("/"))
    rows = [r for r in read_index(args.data) if r["split"] == "train"]
    assert not {r["subject"] for r in rows} & TEST_SUBJECTS
    tune = {Path(s.motion).resolve() for s in tune_specs(data=args.data)}
    clips = [r for r in rows if (args.data / r["file"]).resolve() not in tune]
    jobs = [(c, v) for c in range(len(clips)) for v in range(args.views)][part::parts]
    print(f"{len(clips)} train clips ({len(rows) - len(clips)} of the tune suite left out); "
          f"{len(jobs)} clip-views in this part", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    model = load_body_model("default", dtype=torch.float64)
    kmap = load_keypoint_map()
    det = MediaPipePoseDetector(augment=False)
    t0, done = time.perf_counter(), 0
    for c, v in jobs:
        row = clips[c]
        out = args.out / f"{Path(row['file']).stem}-v{v}.npz"
        if out.exists():
            continue
        seed = 1000 + 10 * c + v
        rng = np.random.default_rng(seed)
        n = resample(read_mocap(args.data / row["file"]), args.fps).num_frames
        frames = min(args.frames, n)
        start = int(rng.integers(0, n - frames + 1))
        tmp = Path(tempfile.mkdtemp(prefix="flowmocap-detpairs-"))
        try:
            synthesize(args.data / row["file"], tmp / "seq", fps=args.fps, start=start, frames=frames, size="640x480",
                       betas="random", seed=seed, azimuth=float(rng.uniform(0, 360)),
                       elevation=float(rng.uniform(0, 20)), flow=False, overwrite=True)
            seq = load_sequence(tmp / "seq")
            det.reset()
            K = len(KEYPOINT_NAMES)
            kp, cf, world = np.full((frames, K, 2), np.nan), np.zeros((frames, K)), np.full((frames, K, 3), np.nan)
            for i in range(frames):
                d = det.detect(seq.frame(i))
                if d is not None:
                    kp[i], cf[i] = d.keypoints, d.confidence
                    if d.world is not None:
                        world[i] = d.world
            truth = true_points(seq.gt, seq.camera, model, kmap)
            uv = truth[..., :2] / truth[..., 2:] * [seq.camera.fx, seq.camera.fy] + [seq.camera.cx, seq.camera.cy]
            part_file = out.with_suffix(".part.npz")
            np.savez_compressed(part_file, keypoints=kp, confidence=cf, world=world, truth=truth, truth_2d=uv,
                                K=seq.camera.K, clip=row["file"], category=row["category"], fps=args.fps, seed=seed)
            part_file.replace(out)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        done += 1
        el = time.perf_counter() - t0
        print(f"{out.name}: {frames} frames, found on {int((cf.max(1) > 0).sum())}; {done} done, "
              f"{el / done:.1f} s each", flush=True)
    det.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
