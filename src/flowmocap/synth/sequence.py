"""Writing a synthetic sequence folder with ground truth (``flowmocap synth``).

Folder layout (DESIGN.md's sequence folder, plus the true flow)::

    frames/000000.png ...   RGB frames (textured, lit body over a textured static scene)
    masks/000000.png ...    the body's silhouette, 0/255, exactly the rasterised coverage
                            of the frame's pixel centres
    flow/000001.npz ...     true backward flow of frame i to i-1 at frame i's pixels:
                            key "flow", (H, W, 2) float32 (dx, dy) in pixels, zero on
                            the static background (no file for the first frame)
    camera.json             PinholeCamera.to_dict(): fx, fy, cx, cy, width, height, R, t
    gt.npz                  poses (T, 72) rad, trans (T, 3) m, betas (10,), gender,
                            fps, joints3d (T, 24, 3) m, joints2d (T, 24, 2) px,
                            source_frames (T,) index into the motion
    meta.json               how it was made (source, seed, camera placement, body, ...)

Pixels follow the project's convention: centres at integer + 0.5, so a joint at
``joints2d = (u, v)`` lies in pixel column ``floor(u)``, row ``floor(v)``.
"""

from __future__ import annotations

import json
import math
import numbers
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import torch

from flowmocap.version import __version__
from flowmocap.errors import DataError, InputError, OutputError
from flowmocap.geometry import PinholeCamera
from flowmocap.io.motion_source import load_motion
from flowmocap.io.smpl_motion import SmplMotion
from flowmocap.render import prepare_faces, rasterize, render_flow, shade
from flowmocap.synth.scene import WORLD_LIGHT, ClothingPattern, place_camera, render_background

__all__ = ["synthesize", "SynthResult", "parse_betas", "parse_size", "read_camera_json"]


@dataclass
class SynthResult:
    """What :func:`synthesize` wrote.

    Attributes:
        out_dir: the sequence folder.
        camera: the static camera.
        motion: the rendered frames' SMPL motion (poses, trans, betas, fps).
        joints3d: ``(T, 24, 3)`` world joints, metres.
        joints2d: ``(T, 24, 2)`` projected joints, pixels.
        meta: the contents of ``meta.json``.
    """

    out_dir: Path
    camera: PinholeCamera
    motion: SmplMotion
    joints3d: np.ndarray
    joints2d: np.ndarray
    meta: dict


def parse_size(size) -> tuple[int, int]:
    """``"640x480"``, ``(640, 480)`` -> ``(width, height)`` in pixels."""
    if isinstance(size, str):
        parts = size.lower().replace("*", "x").split("x")
        try:
            w, h = (int(p) for p in parts)
        except ValueError:
            raise InputError(f"size must look like 640x480 (width x height in pixels), got {size!r}") from None
    else:
        try:
            w, h = (int(v) for v in size)
        except (TypeError, ValueError):
            raise InputError(f"size must be (width, height) in pixels, got {size!r}") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise InputError(f"image size must be 16..8192 pixels per side, got {w}x{h}")
    return w, h


#: The largest shape coefficient a synthetic body may have, in standard deviations (the
#: shape space's people lie within about +-3; further out the body is no person's).
MAX_ABS_BETA = 10.0

#: The most frames a synthetic clip may have, and the highest and lowest frame rates: every
#: frame's mesh is held in memory while the clip is made (about 0.17 MB a frame).
MAX_SYNTH_FRAMES = 20000
SYNTH_FPS_RANGE = (1.0, 1000.0)

#: The least height, pixels, of the body in a synthetic clip's first frame.
MIN_BODY_PIXELS = 8.0


def parse_betas(betas, num_betas: int, rng: np.random.Generator) -> np.ndarray:
    """Body shape from None (mean), ``"random"`` (seeded, N(0, 0.7^2) clipped to +-2),
    a string of comma-separated numbers, or numbers (at most ``num_betas``; the rest 0).
    ``rng`` draws the random shape.

    Returns:
        ``(num_betas,)`` float64.
    """
    if betas is None:
        return np.zeros(num_betas)
    if isinstance(betas, str):
        if betas.strip().lower() == "random":
            return np.clip(rng.normal(0.0, 0.7, num_betas), -2.0, 2.0)
        try:
            betas = [float(v) for v in betas.replace(",", " ").split()]
        except ValueError:
            raise InputError(f"betas must be 'random' or numbers separated by commas, got {betas!r}") from None
    b = np.asarray(betas, dtype=np.float64).reshape(-1)
    if b.shape[0] > num_betas or not np.all(np.isfinite(b)):
        raise InputError(f"betas takes at most {num_betas} finite values, got {b.shape[0]}")
    if np.abs(b).max(initial=0.0) > MAX_ABS_BETA:
        raise InputError(f"betas are standard deviations of the body's shape, within +-{MAX_ABS_BETA:g} (people lie "
                         f"within about +-3); got {np.abs(b).max():g}")
    return np.pad(b, (0, num_betas - b.shape[0]))


def read_camera_json(path, width: int | None = None, height: int | None = None) -> PinholeCamera:
    """A :class:`PinholeCamera` from a ``camera.json`` file (or a dict)."""
    if isinstance(path, PinholeCamera):
        cam = path
    elif isinstance(path, dict):
        cam = PinholeCamera.from_dict(path)
    else:
        cam = PinholeCamera.from_file(path)
    if width is not None and (cam.width, cam.height) != (width, height):
        raise InputError(
            f"the camera is {cam.width}x{cam.height} but the requested size is {width}x{height}; "
            "leave the size out to use the camera's"
        )
    return cam


def _prepare_out(out_dir: Path, overwrite: bool) -> None:
    """Ready ``out_dir`` (not a file: :func:`synthesize` checked) for a new sequence."""
    existing = [out_dir / n for n in ("frames", "masks", "flow", "gt.npz", "meta.json", "camera.json")]
    if any(p.exists() for p in existing):
        if not overwrite:
            raise InputError(f"{out_dir} already holds a sequence; choose another folder, or pass overwrite=True (--overwrite on the command line)")
        # the old sequence's files that describe it go first: a new one cut short then reads as
        # frames without ground truth, never as new frames with the old truth
        for name in ("gt.npz", "meta.json", "camera.json"):
            (out_dir / name).unlink(missing_ok=True)
        for sub in ("frames", "masks"):
            for f in (out_dir / sub).glob("*.png"):
                f.unlink()
        for f in (out_dir / "flow").glob("*.npz"):
            f.unlink()
    for sub in ("frames", "masks"):
        (out_dir / sub).mkdir(parents=True, exist_ok=True)


def synthesize(
    motion_source: str | Path | SmplMotion,
    out_dir: str | Path,
    fps: float = 30.0,
    start: int = 0,
    frames: int | None = None,
    size: str | Sequence[int] | None = (640, 480),
    focal: float | None = None,
    distance: float | None = None,
    azimuth: float = 60.0,
    elevation: float = 8.0,
    camera: str | Path | dict | PinholeCamera | None = None,
    betas: str | Sequence[float] | None = None,
    gender: str = "neutral",
    seed: int = 0,
    model: str | Path = "default",
    asf: str | Path | None = None,
    flow: bool = True,
    supersample: int = 2,
    overwrite: bool = False,
) -> SynthResult:
    """Render a synthetic video of a body moving as ``motion_source``, with ground truth.

    Args:
        motion_source: ``"builtin:walk"``, a ``.bvh``/``.amc`` mocap file (retargeted
            to the body, see :func:`flowmocap.io.retarget`), or an
            :class:`~flowmocap.io.SmplMotion` (rendered as given, at its own fps).
        out_dir: sequence folder to write (layout in the module docstring).
        fps: frame rate in Hz (mocap is resampled to it).
        start: first frame (at ``fps``) of the motion to render.
        frames: number of frames (default: the rest of the motion; 4 s for
            ``builtin:walk``).
        size: ``(width, height)`` or ``"WxH"`` in pixels; None takes the size of
            ``camera``.
        focal: focal length in pixels (default: the image width).
        distance: camera-to-target metres (default: the body's path fills 85 % of the
            image).
        azimuth: camera direction about the vertical in degrees, from +z towards +x (the
            body starts walking along +z: 0 = from the front, 90 = from its left side).
        elevation: camera height angle above the horizon in degrees.
        camera: a ``camera.json`` path / dict / :class:`PinholeCamera` instead of the
            placement above.
        betas: body shape: None (mean), ``"random"`` (from ``seed``), or numbers.
        gender: ``"neutral"``, ``"male"`` or ``"female"``.
        seed: seeds the shape (``"random"``), clothing and scene; same seed, same files.
        model: body model, ``"default"`` or an SMPL-format file.
        asf: ASF skeleton for an ``.amc`` motion (default: found next to it).
        flow: write the true flow (``flow/*.npz``).
        supersample: anti-aliasing samples per pixel along each axis.
        overwrite: replace an existing sequence in ``out_dir``.

    Returns:
        :class:`SynthResult`.

    Raises:
        InputError: bad arguments, a frame range outside the motion.
        DataError: unreadable mocap or camera file.
    """
    from flowmocap.body import load_body_model

    from flowmocap.errors import check_path

    if not isinstance(motion_source, SmplMotion):
        check_path(motion_source, "motion_source", "a .bvh or .amc file, or 'builtin:walk'")
    check_path(out_dir, "out_dir", "the sequence folder to write")
    t0 = time.perf_counter()
    if not str(out_dir).strip():
        raise InputError("the sequence folder (out_dir, --out) is empty; give the path of a new folder.")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"output path {out_dir} is a file; give a folder")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be a whole number >= 0; got {seed!r}")
    seed = int(seed)  # numpy's as Python's: meta.json
    if camera is not None:
        cam_given = read_camera_json(camera, *(parse_size(size) if size is not None else (None, None)))
        width, height = cam_given.width, cam_given.height
    else:
        cam_given = None
        if size is None:
            raise InputError("give an image size or a camera")
        width, height = parse_size(size)
    lo, hi = SYNTH_FPS_RANGE
    if not (isinstance(fps, numbers.Real) and not isinstance(fps, bool) and math.isfinite(fps) and lo <= fps <= hi):
        raise InputError(f"fps must be a frame rate of {lo:g}..{hi:g} Hz, got {fps!r}")
    fps = float(fps)
    if int(start) != start or start < 0:
        raise InputError(f"start must be a frame index >= 0, got {start!r}")
    if frames is not None and (int(frames) != frames or frames < 1):
        raise InputError(f"frames must be a positive number of frames, got {frames!r}")
    if frames is not None and frames > MAX_SYNTH_FRAMES:
        raise InputError(f"a synthetic clip holds at most {MAX_SYNTH_FRAMES} frames (each frame's mesh is kept in "
                         f"memory while it is made); got {frames}: make several clips with --start")
    if str(motion_source).startswith("builtin:") and start + (frames or 0) > 10 * MAX_SYNTH_FRAMES:
        raise InputError(f"the built-in walk is generated from its first frame: frames {start}.. would need more "
                         f"than {10 * MAX_SYNTH_FRAMES}; start nearer the beginning (it repeats every step cycle)")
    rng = np.random.default_rng(seed)
    body = load_body_model(model, gender=gender, dtype=torch.float64)
    b = parse_betas(betas, body.num_betas, rng)
    clothing_seed, scene_seed = (int(x) for x in rng.integers(0, 1 << 30, 2))

    if isinstance(motion_source, SmplMotion):
        motion = motion_source
        b = np.pad(motion.betas.astype(np.float64), (0, max(0, body.num_betas - motion.betas.shape[0])))[:body.num_betas]
    else:
        n_builtin = None
        if str(motion_source).startswith("builtin:"):
            n_builtin = start + (frames if frames is not None else int(round(4.0 * fps)))
        motion = load_motion(motion_source, body, betas=b, fps=fps, frames=n_builtin, asf=asf)
    stop = motion.num_frames if frames is None else start + int(frames)
    if stop - start > MAX_SYNTH_FRAMES:
        raise InputError(f"the motion has {motion.num_frames - start} frames from frame {start} at {motion.fps:g} fps; "
                         f"a synthetic clip holds at most {MAX_SYNTH_FRAMES}: give --num-frames")
    if start >= motion.num_frames or stop > motion.num_frames:
        raise InputError(
            f"frames {start}..{stop - 1} requested but the motion has {motion.num_frames} frames at "
            f"{motion.fps:g} fps ({motion.source})"
        )
    source_frames = np.arange(start, stop)
    motion = motion.slice(start, stop)
    T = motion.num_frames

    betas_t = torch.as_tensor(b[None])
    verts, joints = [], []
    with torch.no_grad():
        rest = body(betas=betas_t)
        rest_verts = rest.rest_vertices[0].numpy()
        rest_joints = rest.rest_joints[0].numpy()
        for s in range(0, T, 64):
            out = body(betas=betas_t, pose=torch.as_tensor(motion.poses[s:s + 64], dtype=torch.float64),
                       trans=torch.as_tensor(motion.trans[s:s + 64], dtype=torch.float64))
            verts.append(out.vertices.numpy())
            joints.append(out.joints.numpy())
    verts = np.concatenate(verts)
    joints3d = np.concatenate(joints)

    if cam_given is not None:
        cam = cam_given
        placement = {"camera_json": str(camera) if not isinstance(camera, (dict, PinholeCamera)) else "given"}
    else:
        cam, placement = place_camera(verts[:: max(1, T // 40)].reshape(-1, 3), width, height,
                                      focal=focal, distance=distance, azimuth=azimuth, elevation=elevation)
    depth_all = verts @ cam.R[2] + cam.t[2]
    if depth_all.min() <= 0.05:
        raise InputError("the body passes behind or through the camera; move the camera further away")
    tall = float(np.ptp(cam.project(verts[0])[:, 1]))
    if tall < MIN_BODY_PIXELS:
        raise InputError(f"the body would be {tall:.2g} px tall in the {width}x{height} image, too small to see; "
                         "bring the camera nearer (--distance) or give it a longer focal length (--focal)")
    fwd = cam.R[2].copy()
    fwd[1] = 0.0
    fwd /= max(np.linalg.norm(fwd), 1e-9)
    wall = float(((verts[:: max(1, T // 40)].reshape(-1, 3) - cam.center) @ fwd).max()) + 2.5
    background = render_background(cam, seed=scene_seed, supersample=supersample, wall_distance=max(wall, 4.0))
    clothing = ClothingPattern.for_body(rest_joints, seed=clothing_seed)
    light_cam = cam.R @ WORLD_LIGHT

    _prepare_out(out_dir, overwrite)
    if flow:
        (out_dir / "flow").mkdir(exist_ok=True)
    faces = prepare_faces(body.faces_np)
    joints2d = cam.project(joints3d)
    prev = None
    for i in range(T):
        vc = verts[i] @ cam.R.T + cam.t
        px = cam.project(verts[i])
        z = vc[:, 2]
        image = shade(px, z, faces, vc, surface_coords=rest_verts, pattern=clothing,
                      background=background, light_dir=tuple(light_cam), supersample=supersample)
        raster = rasterize(px, z, faces, height, width)
        _write_png(out_dir / "frames" / f"{i:06d}.png", image[..., ::-1])
        _write_png(out_dir / "masks" / f"{i:06d}.png", raster.mask.astype(np.uint8) * 255)
        if flow and prev is not None:
            f, _ = render_flow(raster, px, prev[0], faces, depth_cur=z, depth_prev=prev[1])
            np.savez_compressed(out_dir / "flow" / f"{i:06d}.npz", flow=f)
        prev = (px, z)

    (out_dir / "camera.json").write_text(json.dumps(cam.to_dict(), indent=2))
    np.savez(
        out_dir / "gt.npz",
        poses=motion.poses.astype(np.float32), trans=motion.trans.astype(np.float32),
        betas=b.astype(np.float32), gender=np.array(body.gender), fps=np.float64(motion.fps),
        joints3d=joints3d.astype(np.float32), joints2d=joints2d.astype(np.float32),
        source_frames=source_frames,
    )
    meta = {
        "generator": "flowmocap.synth", "version": __version__,
        "source": str(motion_source) if not isinstance(motion_source, SmplMotion) else motion.source,
        "fps": motion.fps, "num_frames": T, "start": int(start), "size": [width, height],
        "seed": seed, "model": str(model), "model_source": body.source, "gender": body.gender,
        "betas": b.tolist(), "camera": placement, "supersample": supersample,
        "motion_info": _jsonable(motion.info),
        "flow": ("flow/NNNNNN.npz, key 'flow': (H, W, 2) float32 backward flow (dx, dy) in pixels "
                 "from frame i to i-1 at frame i's pixels; zero on the static background") if flow else None,
        "pixels": "pixel centres at integer + 0.5; joints2d in the same frame",
        "units": "metres, radians, pixels; world y up, ground plane y = 0",
        "seconds": round(time.perf_counter() - t0, 2),
    }
    (out_dir / "meta.json").write_text(json.dumps(meta, indent=2))
    return SynthResult(out_dir=out_dir, camera=cam, motion=motion, joints3d=joints3d,
                       joints2d=joints2d, meta=meta)


def _write_png(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), np.ascontiguousarray(image)):
        raise OutputError(f"could not write {path} (a full disk, a file size limit or no permission?); the frames "
                          "before it are written, the sequence is not finished: make it again with --overwrite")


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x
