"""A walker followed by a camera carried beside them, tracked end to end, against the truth.

The built-in walk (1.3 m/s along +x, feet on the floor ``y = 0``) is rendered as the project's
synthetic sequences are (:mod:`flowmocap.synth`: the clothed body shaded over the paved ground
and brick wall of :func:`flowmocap.synth.scene.render_background`), but from a camera that moves:
its centre 1.5 m above the floor, 4 m from the walker's line, pitched down 10 degrees, moving
along x with the walker (``--follow`` of their speed; 1 keeps them centred, 0 is a still
camera). The frames are written as a folder and tracked like a user's video (``flowmocap track
FRAMES --focal F``: automatic masks and start), and the fitted motion's ground frame is compared
with the truth:

- **path**: the pelvis's path on the floor after the best rigid alignment about the vertical
  (a turn and a shift, no scale), the median over frames of the distance, metres; and the
  path's length, ours against the truth's;
- **slide**: the slower foot's lowest vertex's speed along the floor, the median over frames
  (m/s; 0 for a walk whose standing foot stays put);
- the camera's move found (``run.json``'s ``camera_motion``) and whether the export undid it.

Each of the fitted results is read four ways: as exported (the move undone where found and
believed), with only the camera's turn undone, with its turn and zoom undone (what a refused
move leaves: a camera carried forward also fits a zoom, :mod:`flowmocap.vision.camera_motion`),
and in the camera's own frame.

Usage::

    python benchmarks/carried_walk.py OUT [--frames 60] [--follow 1.0 0.0] [--size 640x480]

Prints a table and writes ``OUT/carried_walk.md`` / ``.json`` (a few minutes per follow value).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

HEIGHT, PITCH_DEG, DISTANCE, FOCAL_FACTOR = 1.5, 10.0, 4.0, 0.9


def render(out: Path, frames: int, follow: float, size: tuple[int, int], seed: int = 0, pan: bool = False,
           focal_factor: float = FOCAL_FACTOR) -> dict:
    """Write ``out/frames/*.png`` and return the truth: ``joints`` (T, 24, 3) world metres,
    ``centres`` (T, 3) the camera's centre per frame, ``yaws`` (T,) its turn about the vertical
    from the first frame's (radians), and the ``focal`` length (px, ``focal_factor`` times the
    long side). ``pan``: the camera stays where it starts and turns to keep the walker's pelvis
    in the middle of the image (a pan on a tripod; ``follow`` is not used)."""
    import cv2
    import torch
    from scipy.spatial.transform import Rotation

    from flowmocap.body import load_body_model
    from flowmocap.geometry.camera import PinholeCamera
    from flowmocap.io.builtin_walk import builtin_walk
    from flowmocap.render import prepare_faces, shade
    from flowmocap.synth.scene import WORLD_LIGHT, ClothingPattern, render_background

    body = load_body_model("default", dtype=torch.float64)
    walk = builtin_walk(body, fps=30.0, frames=frames, facing=np.pi / 2)  # along +x
    with torch.no_grad():
        o = body(pose=torch.as_tensor(walk.poses), trans=torch.as_tensor(walk.trans))
        rest = body()
    verts, joints = o.vertices.numpy(), o.joints.numpy()
    shift = np.array([-0.5 * (joints[-1, 0, 0] + joints[0, 0, 0]), 0.0, DISTANCE])  # centred, 4 m ahead
    verts, joints = verts + shift, joints + shift
    speed = (joints[-1, 0, 0] - joints[0, 0, 0]) / (frames - 1)
    W, H = size
    f = focal_factor * max(W, H)
    R0 = Rotation.from_euler("x", np.radians(PITCH_DEG)).as_matrix() @ np.diag([-1.0, -1.0, 1.0])
    faces = prepare_faces(body.faces_np)
    clothing = ClothingPattern.for_body(rest.rest_joints[0].numpy(), seed=seed)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    centres, yaws = [], []
    for i in range(frames):
        C = np.array([joints[0, 0, 0] + (0.0 if pan else follow * speed * i), HEIGHT, 0.0])
        # a pan: turned about the vertical towards the pelvis (x_world - C_x to the side, DISTANCE ahead)
        yaw = -float(np.arctan2(joints[i, 0, 0] - C[0], DISTANCE)) if pan else 0.0
        R = R0 @ Rotation.from_euler("y", yaw).as_matrix()
        cam = PinholeCamera(fx=f, fy=f, cx=W / 2, cy=H / 2, width=W, height=H, R=R, t=-R @ C)
        background = render_background(cam, seed=seed, supersample=2, wall_distance=DISTANCE + 4.0,
                                       wall_facing=R0[2] if pan else None)  # a pan: the wall stays where it is
        vc = verts[i] @ R.T + cam.t
        image = shade(cam.project(verts[i]), vc[:, 2], faces, vc, surface_coords=rest.rest_vertices[0].numpy(),
                      pattern=clothing, background=background, light_dir=tuple(R @ WORLD_LIGHT), supersample=2)
        cv2.imwrite(str(out / "frames" / f"{i:06d}.png"), np.ascontiguousarray(image[..., ::-1]))
        centres.append(C)
        yaws.append(yaw)
    return {"joints": joints, "centres": np.asarray(centres), "yaws": np.asarray(yaws), "focal": f}


def _rigid_about_vertical(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a`` (T, 2) floor points turned and shifted onto ``b`` (T, 2) in the least-squares sense."""
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return (a - ca) @ r + cb


def measures(m, truth: dict) -> dict:
    from flowmocap.export.world import foot_vertex_sets

    rows = {int(k): r for r, k in enumerate(m.frame_index)}
    idx = np.array(sorted(rows))
    j = m.joints()[[rows[i] for i in idx]]
    ours = j[:, 0, [0, 2]]
    ref = truth["joints"][idx][:, 0, [0, 2]]
    fitted = _rigid_about_vertical(ours, ref)
    feet = foot_vertex_sets(m.model.weights.cpu().numpy())
    lows = []
    for out in m.posed(with_vertices=True):
        v = out.vertices.numpy()
        lows.append(np.stack([v[:, f][np.arange(len(v)), np.argmin(v[:, f, 1], 1)] for f in feet], 1))
    low = np.concatenate(lows)
    slide = np.linalg.norm(np.diff(low[..., [0, 2]], axis=0), axis=-1).min(1) * m.fps
    length = lambda p: float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())  # noqa: E731
    return {"path_error_m": float(np.median(np.linalg.norm(fitted - ref, axis=1))),
            "path_length_m": length(ours), "true_path_length_m": length(ref),
            "end_to_end_m": float(np.linalg.norm(ours[-1] - ours[0])),
            "true_end_to_end_m": float(np.linalg.norm(ref[-1] - ref[0])),
            "slide_m_s": float(np.median(slide))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--follow", type=float, nargs="+", default=[1.0, 0.0])
    ap.add_argument("--size", default="640x480")
    args = ap.parse_args(argv)
    from flowmocap.cli import main as cli
    from flowmocap.export.motion import load_fitted_motion

    W, H = (int(x) for x in args.size.split("x"))
    out = Path(args.out)
    rows = []
    for follow in args.follow:
        d = out / f"follow{follow:g}"
        if d.exists():
            shutil.rmtree(d)
        truth = render(d, args.frames, follow, (W, H))
        res = d / "result"
        if cli(["track", str(d / "frames"), "--out", str(res), "--focal", str(truth["focal"])]) != 0:
            raise SystemExit(f"flowmocap track failed on {d / 'frames'}")
        run = json.loads((res / "run.json").read_text())
        cm = run.get("camera_motion") or {}
        true_move = float(np.linalg.norm(truth["centres"] - truth["centres"][0], axis=1).max())
        exported = load_fitted_motion(res, frame="ground", cache_world=False)
        row = {"follow": follow, "camera_moves_m": true_move, "moving_sideways": cm.get("moving_sideways"),
               "sideways_h": cm.get("sideways_max"), "move_share": cm.get("move_share"),
               "camera_height_m": exported.camera_height_m, "refused": exported.camera_move_refused,
               "as exported": measures(exported, truth)}
        if cm.get("moving_sideways"):  # the same result with the turn alone undone, and with the turn and zoom
            for read, given in (("turn alone", {"shifts": None, "zooms": None}), ("turn and zoom", {"shifts": None})):
                if read == "turn and zoom" and not cm.get("zooms"):
                    continue
                copy = d / read.replace(" ", "_")
                copy.mkdir()
                shutil.copy(res / "motion.npz", copy / "motion.npz")
                (copy / "run.json").write_text(json.dumps({**run, "camera_motion": {**cm, **given}}))
                row[read] = measures(load_fitted_motion(copy, frame="ground", cache_world=False), truth)
        nocam = d / "camera_frame"
        nocam.mkdir()
        shutil.copy(res / "motion.npz", nocam / "motion.npz")
        (nocam / "run.json").write_text(json.dumps({**run, "camera_motion": {"moving": False}}))
        row["camera's frame"] = measures(load_fitted_motion(nocam, frame="ground", cache_world=False), truth)
        rows.append(row)
        print(json.dumps(row, default=float), flush=True)
    lines = ["| camera (moves, m) | move found (h; cost share) | camera height m (truth 1.5) | read | path error m | "
             "path length m (truth) | end to end m (truth) | slower foot slides m/s |",
             "|---|---|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        found = (f"yes ({r['sideways_h']:.2f}; {r['move_share']:.3f})" if r["moving_sideways"] else
                 f"no ({'' if r['move_share'] is None else round(r['move_share'], 3)})")
        for read in ("as exported", "turn alone", "turn and zoom", "camera's frame"):
            if read not in r:
                continue
            s = r[read]
            h = "" if r["camera_height_m"] is None or read != "as exported" else f"{r['camera_height_m']:.2f}"
            lines.append(f"| follow {r['follow']:g} ({r['camera_moves_m']:.2f}) | {found} | {h} | {read} | "
                         f"{s['path_error_m']:.3f} | {s['path_length_m']:.2f} ({s['true_path_length_m']:.2f}) | "
                         f"{s['end_to_end_m']:.2f} ({s['true_end_to_end_m']:.2f}) | {s['slide_m_s']:.3f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    (out / "carried_walk.md").write_text(f"# A walker followed by a carried camera: `python benchmarks/carried_walk.py`"
                                         f"\n\n{args.frames} frames, {args.size}.\n\n{text}")
    (out / "carried_walk.json").write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
