"""Renderer speed: rasterisation, rendered flow, the flow objective E_f with its gradient
(1, 3 and 4 pyramid levels), silhouette, capsule distance map, shading.

The mesh is a person-shaped stand-in (flowmocap.render.primitives.mannequin: 11
subdivided ellipsoids, 14,080 triangles, SMPL has 13,776) standing ~58 % of the image
height, turning by 3 degrees between the two frames; the observed flow is its rendered
flow plus noise. Everything runs on one core (Numba kernels are single-threaded; torch
is set to one thread).

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

from flowmocap.render import (
    capsule_distance_map,
    flow_loss,
    flow_target,
    prepare_faces,
    rasterize,
    render_flow,
    shade,
    silhouette,
)
from flowmocap.render.primitives import mannequin


def _time(fn, repeats: int) -> float:
    fn()  # warm-up (and Numba compilation)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(times)


def _scene(H: int, W: int):
    verts, faces = mannequin(3)
    f = 1.08 * H  # the 1.75 m figure at 3.2 m fills ~58 % of the height

    def view(angle: float):
        c, s = np.cos(angle), np.sin(angle)
        R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        X = (verts - [0, 0.88, 0]) @ R.T * np.array([1.0, -1.0, -1.0]) + np.array([0.0, 0.0, 3.2])
        xy = np.stack([f * X[:, 0] / X[:, 2] + W / 2, f * X[:, 1] / X[:, 2] + H / 2], axis=1)
        return xy, X

    x_cur, X_cur = view(0.0)
    x_prev, X_prev = view(np.radians(3.0))
    return verts, faces, x_cur, X_cur, x_prev, X_prev


def _capsules(x_cur: np.ndarray, verts: np.ndarray):
    # one capsule per ellipsoid of the mannequin: its long axis in the image
    parts = np.array_split(np.arange(len(verts)), 11)
    a, b, r = [], [], []
    for idx in parts:
        p = x_cur[idx]
        c = p.mean(0)
        u, s, vt = np.linalg.svd(p - c, full_matrices=False)
        ext = np.abs((p - c) @ vt[0]).max()
        rad = np.abs((p - c) @ vt[1]).max()
        a.append(c - vt[0] * max(ext - rad, 0))
        b.append(c + vt[0] * max(ext - rad, 0))
        r.append(rad)
    return torch.tensor(np.array(a)), torch.tensor(np.array(b)), torch.tensor(np.array(r))


def bench(H: int, W: int, repeats: int) -> dict:
    verts, faces, xc, Xc, xp, Xp = _scene(H, W)
    pf = prepare_faces(faces)
    zc = Xc[:, 2].copy()
    raster = rasterize(xc, zc, pf, H, W)
    flow, mask = render_flow(raster, xc, xp, pf)
    obs = flow + np.random.default_rng(0).normal(0, 0.3, flow.shape).astype(np.float32)
    out = {
        "image": f"{W}x{H}",
        "faces": int(len(faces)),
        "covered_pixels": int(mask.sum()),
        "height_fraction": float((xc[:, 1].max() - xc[:, 1].min()) / H),
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
    a, b, r = _capsules(xc, verts)
    for step in (4, 8):
        out[f"capsule_distance_map_step{step}_ms"] = _time(
            lambda: capsule_distance_map(a, b, r, H, W, grid_step=step), max(5, repeats // 5))
        a_ = a.clone().requires_grad_()

        def cap_bwd():
            capsule_distance_map(a_, b, r, H, W, grid_step=step).sum().backward()

        out[f"capsule_distance_map_step{step}_fwd_bwd_ms"] = _time(cap_bwd, max(5, repeats // 5))
    bg = np.full((H, W, 3), 128, np.uint8)
    out["shade_pattern_ss2_ms"] = _time(
        lambda: shade(xc, zc, pf, Xc, surface_coords=verts, background=bg), 3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "render.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    results = [bench(240, 320, args.repeats), bench(480, 640, args.repeats)]
    keys = [k for k in results[0] if k.endswith("_ms")]
    print(f"{'median ms (one core)':44s} " + " ".join(f"{r['image']:>10s}" for r in results))
    for k in keys:
        print(f"{k[:-3]:44s} " + " ".join(f"{r[k]:10.3f}" for r in results))
    for k in ("faces", "covered_pixels", "height_fraction"):
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
                      "forward + backward including rasterisation, 14,080-triangle mannequin",
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
