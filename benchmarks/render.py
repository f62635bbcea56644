"""Renderer speed: rasterisation, rendered flow, the flow objective E_f with its gradient
(1, 3 and 4 pyramid levels), silhouette, capsule distance map, shading.

The mesh is the default body (``load_body_model("default")``, 6,890 vertices, 13,776
triangles) in the ``walk`` pose of :mod:`flowmocap.viz.body_figure`, seen from a
three-quarter view by a :class:`~flowmocap.geometry.camera.PinholeCamera` placed with
``look_at`` so that the body stands ~60 % of the image height. Frame ``i - 1`` is the
same body with its limbs swung by a few degrees, turned by 3 degrees and moved by 4 cm;
the observed flow is the rendered backward flow of that motion plus noise. The capsule
distance map uses the body's own capsules (``body_capsules`` projected with
``project_capsules``). Everything runs on one core (Numba kernels are single-threaded;
torch is set to one thread).

Usage: python benchmarks/render.py [--repeats 50] [--out benchmarks/results/render.json]
Prints a table and writes the JSON (medians over repeats, ms). Its top level carries
``flow_objective_ms_640x480`` and ``flow_objective_ms_320x240``: E_f + gradient over 3
pyramid levels including rasterisation, with the observed flow prepared once
(``flow_target``), as in an optimisation loop.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import time
from pathlib import Path

import numpy as np
import torch

from flowmocap.body import body_capsules, load_body_model
from flowmocap.geometry.camera import PinholeCamera, look_at
from flowmocap.render import (
    capsule_signed_distance,
    flow_loss,
    flow_target,
    prepare_faces,
    project_capsules,
    rasterize,
    render_flow,
    shade,
    silhouette,
)
from flowmocap.viz.body_figure import pose_vector

HEIGHT_FRACTION = 0.6  # the body's projected height / image height
AZIMUTH_DEG = 30.0  # camera direction about the vertical, from the body's front (+z) towards +x


def _time(fn, repeats: int) -> float:
    fn()  # warm-up (and Numba compilation)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(times)


def _frames(model):
    """Body outputs at frame ``i`` (walk pose) and ``i - 1`` (limbs, turn and place moved)."""
    pose_cur = pose_vector("walk").double()
    pose_prev = 0.9 * pose_cur  # limbs swung back by up to ~7 degrees
    yaw = np.radians(3.0)
    pose_prev[1] = pose_prev[1] + yaw  # global orientation: turned about the vertical
    with torch.no_grad():
        cur = model(pose=pose_cur)
        prev = model(pose=pose_prev, trans=torch.tensor([-0.04, 0.0, -0.01], dtype=torch.float64))
    return cur, prev


def _camera(verts: np.ndarray, H: int, W: int) -> PinholeCamera:
    """Camera (focal = image width) looking at the body's centre from AZIMUTH_DEG, at the
    distance that makes the body HEIGHT_FRACTION of the image height."""
    lo, hi = verts.min(0), verts.max(0)
    centre = 0.5 * (lo + hi)
    focal = float(W)
    az = np.radians(AZIMUTH_DEG)
    direction = np.array([np.sin(az), 0.0, np.cos(az)])
    dist = focal * (hi[1] - lo[1]) / (HEIGHT_FRACTION * H)
    for _ in range(3):  # perspective: refine on the projected height
        R, t = look_at(centre + dist * direction, centre)
        cam = PinholeCamera.from_focal(W, H, focal, R=R, t=t)
        y = cam.project(verts)[:, 1]
        dist *= (y.max() - y.min()) / (HEIGHT_FRACTION * H)
    R, t = look_at(centre + dist * direction, centre)
    return PinholeCamera.from_focal(W, H, focal, R=R, t=t)


def _scene(model, H: int, W: int):
    cur, prev = _frames(model)
    v_cur = cur.vertices[0].numpy()
    v_prev = prev.vertices[0].numpy()
    cam = _camera(v_cur, H, W)
    X_cur, X_prev = cam.to_camera(v_cur), cam.to_camera(v_prev)
    x_cur, x_prev = cam.project(v_cur), cam.project(v_prev)
    return cam, cur, x_cur, X_cur, x_prev, X_prev


def _capsules(model, out, cam: PinholeCamera):
    """The body's capsules, in the camera frame, projected to 2D stadiums (pixels)."""
    caps = body_capsules(model, out)
    start = cam.to_camera(caps.start[0])
    end = cam.to_camera(caps.end[0])
    return project_capsules(start, end, caps.radius[0], cam.fx, cam.fy, cam.cx, cam.cy)


def bench(model, H: int, W: int, repeats: int) -> dict:
    cam, body_out, xc, Xc, xp, Xp = _scene(model, H, W)
    faces = model.faces_np
    pf = prepare_faces(faces)
    zc = Xc[:, 2].copy()
    raster = rasterize(xc, zc, pf, H, W)
    flow, mask = render_flow(raster, xc, xp, pf, depth_cur=zc, depth_prev=Xp[:, 2].copy())
    obs = flow + np.random.default_rng(0).normal(0, 0.3, flow.shape).astype(np.float32)
    moving = np.linalg.norm(flow[mask], axis=1)
    out = {
        "image": f"{W}x{H}",
        "faces": int(len(faces)),
        "covered_pixels": int(mask.sum()),
        "height_fraction": float((xc[:, 1].max() - xc[:, 1].min()) / H),
        "flow_px_median": float(np.median(moving)),
        "flow_px_max": float(moving.max()),
        "rasterize_ms": _time(lambda: rasterize(xc, zc, pf, H, W), repeats),
        "rasterize_cull_backfaces_ms": _time(lambda: rasterize(xc, zc, pf, H, W, cull_backfaces=True), repeats),
        "render_flow_ms": _time(lambda: render_flow(raster, xc, xp, pf), repeats),
        "silhouette_ms": _time(lambda: silhouette(raster), repeats),
    }
    t_cur = torch.tensor(xc, requires_grad=True)
    t_prev = torch.tensor(xp, requires_grad=True)
    for levels in (1, 3, 4):
        target = flow_target(obs, None, levels)
        out[f"flow_target_L{levels}_ms"] = _time(lambda: flow_target(obs, None, levels), repeats)

        def given_raster():
            t_cur.grad = t_prev.grad = None
            flow_loss(t_cur, t_prev, pf, target, raster=raster).backward()

        def with_raster():
            t_cur.grad = t_prev.grad = None
            flow_loss(t_cur, t_prev, pf, target, depth_cur=zc).backward()

        def with_raster_cull():
            t_cur.grad = t_prev.grad = None
            flow_loss(t_cur, t_prev, pf, target, depth_cur=zc, cull_backfaces=True).backward()

        def raw_arrays():
            t_cur.grad = t_prev.grad = None
            flow_loss(t_cur, t_prev, pf, obs, levels=levels, depth_cur=zc).backward()

        out[f"flow_loss_L{levels}_given_raster_ms"] = _time(given_raster, repeats)
        out[f"flow_loss_L{levels}_with_rasterize_ms"] = _time(with_raster, repeats)
        out[f"flow_loss_L{levels}_with_rasterize_cull_ms"] = _time(with_raster_cull, repeats)
        out[f"flow_loss_L{levels}_raw_arrays_ms"] = _time(raw_arrays, max(5, repeats // 5))
    a, b, r = (x.detach()[None] for x in _capsules(model, body_out, cam))
    out["capsules"] = int(a.shape[1])
    for step in (4, 8):
        out[f"capsule_distance_map_step{step}_ms"] = _time(
            lambda: capsule_signed_distance(a, b, r, H, W, grid_step=step), max(5, repeats // 5))
        a_, b_, r_ = (x.clone().requires_grad_() for x in (a, b, r))

        def cap_bwd():
            capsule_signed_distance(a_, b_, r_, H, W, grid_step=step).clamp_min(0).sum().backward()

        out[f"capsule_distance_map_step{step}_fwd_bwd_ms"] = _time(cap_bwd, max(5, repeats // 5))
    bg = np.full((H, W, 3), 128, np.uint8)
    rest_verts = body_out.rest_vertices[0].numpy()
    out["shade_pattern_ss2_ms"] = _time(
        lambda: shade(xc, zc, pf, Xc, surface_coords=rest_verts, background=bg), 3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "render.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = load_body_model("default", dtype=torch.float64)
    results = [bench(model, 240, 320, args.repeats), bench(model, 480, 640, args.repeats)]
    keys = [k for k in results[0] if k.endswith("_ms")]
    print(f"{'median ms (one core)':44s} " + " ".join(f"{r['image']:>10s}" for r in results))
    for k in keys:
        print(f"{k[:-3]:44s} " + " ".join(f"{r[k]:10.3f}" for r in results))
    for k in ("faces", "covered_pixels", "height_fraction", "flow_px_median", "flow_px_max", "capsules"):
        print(f"{k:44s} " + " ".join(f"{r[k]:10.3g}" for r in results))
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).parent, check=False).stdout.strip()
    except OSError:
        commit = ""
    doc = {
        "flow_objective_ms_640x480": results[1]["flow_loss_L3_with_rasterize_ms"],
        "flow_objective_ms_320x240": results[0]["flow_loss_L3_with_rasterize_ms"],
        "definition": "median ms, one core: flow_loss (3 pyramid levels, FlowTarget prepared once) "
                      "forward + backward including rasterisation; the default body (13,776 triangles) in a "
                      "walking pose standing 60% of the image height",
        "commit": commit,
        "machine": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "results": {r["image"]: r for r in results},
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
