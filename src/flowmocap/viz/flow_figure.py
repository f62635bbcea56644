"""A picture of what the flow objective compares: observed vs rendered flow of a walking body.

:func:`flow_figure` synthesises two consecutive frames of the built-in walk with
:func:`flowmocap.synth.synthesize` (textured clothing over a textured static scene),
computes the *observed* backward flow ``F_o(i, i-1)`` from the two images with OpenCV's
DIS optical flow, renders the model's backward flow ``F_r(i, i-1)`` with
:func:`flowmocap.render.rasterize` and :func:`flowmocap.render.render_flow`, and tiles
frame ``i`` | observed flow | rendered flow | colour key, both flows in the Middlebury
colour coding at the same scale (:mod:`flowmocap.viz.flow_colors`).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import torch

from flowmocap.errors import InputError
from flowmocap.viz.flow_colors import color_wheel_legend, flow_to_color

__all__ = ["flow_figure", "flow_pair"]

_CAPTION_H = 26
_INK = (30, 30, 30)


def flow_pair(frame: int = 20, fps: float = 30.0, size=(640, 480), azimuth: float = 45.0,
              elevation: float = 8.0, seed: int = 0, model: str = "default") -> dict:
    """Frames ``i - 1`` and ``i`` of the built-in walk with observed and rendered backward flow.

    Args:
        frame: the index ``i`` (>= 1) in the walk at ``fps``.
        fps: frame rate in Hz.
        size: ``(width, height)`` in pixels.
        azimuth, elevation: camera direction in degrees (see
            :func:`flowmocap.synth.synthesize`; 0 = from the front, 90 = from the
            walker's left side).
        seed: clothing and scene colours.
        model: body model, ``"default"`` or an SMPL-format file.

    Returns:
        dict with ``image`` (frame ``i``, ``(H, W, 3)`` uint8 RGB), ``image_prev``,
        ``observed`` and ``rendered`` (``(H, W, 2)`` float32 backward flow in pixels, from
        frame ``i`` to ``i - 1`` at frame ``i``'s pixels), ``mask`` (``(H, W)`` bool, the
        body at frame ``i``).

    Raises:
        InputError: ``frame < 1``, or bad synthesis arguments.
    """
    import cv2

    from flowmocap.body import load_body_model
    from flowmocap.render import prepare_faces, rasterize, render_flow
    from flowmocap.synth import synthesize

    if int(frame) != frame or frame < 1:
        raise InputError(f"frame must be an index >= 1 (it needs frame - 1), got {frame!r}")
    with tempfile.TemporaryDirectory() as tmp:
        res = synthesize("builtin:walk", Path(tmp) / "seq", fps=fps, start=int(frame) - 1, frames=2,
                         size=size, azimuth=azimuth, elevation=elevation, seed=seed, model=model,
                         flow=False)
        prev_bgr, cur_bgr = (cv2.imread(str(Path(tmp) / "seq" / "frames" / f"{k:06d}.png"))
                             for k in (0, 1))
    # observed flow, backward: calc(I_i, I_{i-1}) gives F with I_i(x) ~ I_{i-1}(x + F(x))
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    observed = dis.calc(cv2.cvtColor(cur_bgr, cv2.COLOR_BGR2GRAY), cv2.cvtColor(prev_bgr, cv2.COLOR_BGR2GRAY),
                        None)
    # rendered flow of the model at frames i and i - 1
    body = load_body_model(model, gender=res.meta["gender"], dtype=torch.float64)
    betas = torch.as_tensor(res.meta["betas"], dtype=torch.float64)
    with torch.no_grad():
        out = body(betas=betas, pose=torch.as_tensor(res.motion.poses, dtype=torch.float64),
                   trans=torch.as_tensor(res.motion.trans, dtype=torch.float64))
    cam = res.camera
    verts = out.vertices.numpy()
    px_prev, px_cur = cam.project(verts[0]), cam.project(verts[1])
    faces = prepare_faces(body.faces_np)
    raster = rasterize(px_cur, cam.depth(verts[1]), faces, cam.height, cam.width)
    rendered, mask = render_flow(raster, px_cur, px_prev, faces)
    return {"image": cur_bgr[..., ::-1].copy(), "image_prev": prev_bgr[..., ::-1].copy(),
            "observed": observed.astype(np.float32), "rendered": rendered, "mask": mask}


def crop_box(mask: np.ndarray, aspect: float = 0.75, margin: float = 0.08) -> tuple[int, int, int, int]:
    """``(r0, r1, c0, c1)``: the mask's bounding box plus a margin, widened to ``aspect`` (w/h)."""
    H, W = mask.shape
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if rows.size == 0:
        return 0, H, 0, W
    pad = int(round(margin * (rows[-1] - rows[0] + 1)))
    r0, r1 = max(0, rows[0] - pad), min(H, rows[-1] + 1 + pad)
    h = r1 - r0
    w = min(W, max(cols[-1] + 1 - cols[0] + 2 * pad, int(round(aspect * h))))
    c0 = int(np.clip((cols[0] + cols[-1] + 1) // 2 - w // 2, 0, W - w))
    return int(r0), int(r1), c0, c0 + w


def caption_tile(tile: np.ndarray, lines: list[str]) -> np.ndarray:
    """``tile (H, W, 3)`` uint8 with a white strip of text ``lines`` below it."""
    import cv2

    strip = np.full((_CAPTION_H * len(lines), tile.shape[1], 3), 255, np.uint8)
    for k, text in enumerate(lines):
        scale = 0.5
        while scale > 0.3 and cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] > tile.shape[1] - 8:
            scale -= 0.02
        cv2.putText(strip, text, (5, _CAPTION_H * k + 18), cv2.FONT_HERSHEY_SIMPLEX, scale, _INK, 1,
                    cv2.LINE_AA)
    return np.concatenate([strip, tile], axis=0)


def flow_figure(frame: int = 20, fps: float = 30.0, size=(640, 480), azimuth: float = 45.0,
                elevation: float = 8.0, seed: int = 0, model: str = "default", crop: bool = True) -> np.ndarray:
    """Frame ``i`` | observed flow (DIS) | rendered flow | colour key, of the built-in walk.

    Both flows are colour-coded with the same maximum magnitude (the 99th percentile of the
    rendered flow's length on the body, rounded up to whole pixels), so equal colours
    mean equal vectors. Arguments as in :func:`flow_pair`; ``crop`` crops the tiles to
    the body.

    Returns:
        ``(h, w, 3)`` uint8 RGB image with captions.
    """
    import cv2

    p = flow_pair(frame=frame, fps=fps, size=size, azimuth=azimuth, elevation=elevation, seed=seed,
                  model=model)
    mask, obs, ren = p["mask"], p["observed"], p["rendered"]
    lengths = np.linalg.norm(ren[mask], axis=1)
    max_mag = float(np.ceil(np.percentile(lengths, 99))) if lengths.size else 1.0
    epe = float(np.linalg.norm(obs[mask] - ren[mask], axis=1).mean()) if lengths.size else float("nan")
    r0, r1, c0, c1 = crop_box(mask) if crop else (0, mask.shape[0], 0, mask.shape[1])
    tiles = [
        caption_tile(p["image"][r0:r1, c0:c1], [f"frame i (built-in walk, {fps:g} fps)", "synthetic video"]),
        caption_tile(flow_to_color(obs, max_mag)[r0:r1, c0:c1],
                 ["observed F_o(i, i-1): OpenCV DIS", f"on the frames; EPE {epe:.2f} px on body"]),
        caption_tile(flow_to_color(ren, max_mag)[r0:r1, c0:c1],
                 ["rendered F_r(i, i-1): the model", "at frames i and i-1 (render_flow)"]),
    ]
    h, w = r1 - r0, max(120, (c1 - c0) // 2 + 40)
    key = np.full((h, w, 3), 255, np.uint8)
    d = min(w - 16, h // 2)
    y0 = (h - d) // 2
    key[y0:y0 + d, (w - d) // 2:(w - d) // 2 + d] = color_wheel_legend(d)
    cv2.putText(key, f"rim: {max_mag:g} px", ((w - d) // 2, y0 + d + 22), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                _INK, 1, cv2.LINE_AA)
    tiles.append(caption_tile(key, ["colour key (Middlebury)", "flow (dx, dy), y down"]))
    gap = np.full((tiles[0].shape[0], 6, 3), 255, np.uint8)
    row = [tiles[0]]
    for t in tiles[1:]:
        row += [gap, t]
    return np.concatenate(row, axis=1)
