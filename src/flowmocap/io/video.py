"""Video files as frame sequences (decoded once into memory with PyAV), and the default
camera of a video.

Frames come upright (a phone video's rotation tag is applied, so a portrait video gives
portrait frames), optionally scaled down so that the long side is at most ``max_side``.
Every frame's presentation time is kept: a variable-frame-rate video (phones record
those) is tracked frame by frame as usual, and ``meta["timestamps"]`` says when each
frame was shown; ``meta["fps"]`` is the mean rate over the video.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from flowmocap.errors import DataError
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.io.sequence import Sequence, list_images, read_image

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v")

#: Default focal length, as a multiple of the image's long side: 0.9 x the long side is
#: a 58 degree field of view across it, a 32 mm lens on 35 mm film -- between the
#: usual phone main camera (~26 mm, 69 degrees) and a "normal" 40-50 mm lens.
DEFAULT_FOCAL_FACTOR = 0.9


def decode_video(path: str | Path, max_side: int | None = None) -> tuple[list[np.ndarray], dict]:
    """Decode every frame of a video, upright, with timing and camera metadata.

    Args:
        path: the video file.
        max_side: scale frames down (area interpolation) so that neither side exceeds
            this many pixels; None or 0 keeps the decoded size.

    Returns:
        ``frames`` (list of ``(H, W, 3)`` uint8 RGB) and a dict: ``fps`` (mean rate),
        ``timestamps`` (seconds from the first frame, one per frame),
        ``variable_frame_rate`` (bool: frame intervals differ by more than 10% of their
        median), ``rotation`` (degrees counter-clockwise applied from the stream's
        display matrix), ``decoded_size`` and ``size`` (``[W, H]`` before and after
        scaling), ``scale`` (size / decoded size), ``focal_35mm`` (35 mm-equivalent focal
        length in mm from the metadata, or None), ``metadata`` (container and stream tags).

    Raises:
        DataError: missing file, a file that cannot be decoded, or no frames.
    """
    import av
    import cv2

    path = Path(path)
    if not path.exists():
        raise DataError(f"video {path} does not exist.")
    frames: list[np.ndarray] = []
    times: list[float] = []
    rotation = 0
    tags: dict = {}
    rate = None
    decoded = (0, 0)
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise DataError(f"{path} holds no video stream; give a video file or a folder of frames.")
            stream = container.streams.video[0]
            tags = {**{f"container:{k}": v for k, v in container.metadata.items()},
                    **{k: v for k, v in stream.metadata.items()}}
            rate = float(stream.average_rate) if stream.average_rate else None
            for frame in container.decode(stream):
                img = frame.to_ndarray(format="rgb24")
                rot = int(round(getattr(frame, "rotation", 0) or 0)) if not frames else rotation
                if not frames:
                    rotation = rot if rot % 90 == 0 else 0
                    decoded = (img.shape[1], img.shape[0])
                if rotation:
                    img = np.rot90(img, k=(rotation // 90) % 4)
                if max_side and max(img.shape[:2]) > max_side:
                    s = max_side / max(img.shape[:2])
                    img = cv2.resize(img, (max(1, round(img.shape[1] * s)), max(1, round(img.shape[0] * s))),
                                     interpolation=cv2.INTER_AREA)
                frames.append(np.ascontiguousarray(img))
                times.append(float(frame.time) if frame.time is not None else float("nan"))
    except DataError:
        raise
    except Exception as e:  # PyAV raises many kinds of errors for broken files
        if not frames:  # a truncated file keeps the frames that decoded
            raise DataError(f"cannot decode video {path} ({type(e).__name__}: {e}); check the file, "
                            "or extract its frames into a folder and pass that instead.") from None
    if not frames:
        raise DataError(f"video {path} holds no frames.")
    t = np.asarray(times, np.float64)
    if not np.isfinite(t).all() or (len(t) > 1 and (np.diff(t) <= 0).any()):
        step = 1.0 / (rate or 30.0)
        t = np.arange(len(frames)) * step
    else:
        t = t - t[0]
    vfr = False
    if len(t) > 2:
        d = np.diff(t)
        vfr = bool(np.abs(d - np.median(d)).max() > 0.1 * np.median(d))
        fps = (len(t) - 1) / t[-1]
    else:
        fps = rate or 30.0
    size = [frames[0].shape[1], frames[0].shape[0]]
    upright = list(decoded) if rotation % 180 == 0 else [decoded[1], decoded[0]]
    info = {
        "fps": float(fps), "timestamps": t.round(6).tolist(), "variable_frame_rate": vfr,
        "rotation": rotation, "decoded_size": upright, "size": size, "scale": size[0] / upright[0],
        "focal_35mm": focal_35mm_from_tags(tags), "metadata": {k: str(v) for k, v in tags.items()},
    }
    return frames, info


def focal_35mm_from_tags(tags: dict) -> float | None:
    """The 35 mm-equivalent focal length (mm) in a video's metadata tags, or None.

    Looks for a tag whose name mentions a 35 mm equivalent focal length (e.g. Apple's
    ``com.apple.quicktime.camera.focal_length.35mm_equivalent``, or ``FocalLengthIn35mmFormat``).
    """
    for key, value in tags.items():
        k = key.lower().replace("_", "").replace(".", "").replace(" ", "")
        if "focal" in k and "35" in k:
            m = re.search(r"\d+(\.\d+)?", str(value))
            if m and 5.0 <= float(m.group()) <= 1000.0:
                return float(m.group())
    return None


def default_camera(width: int, height: int, focal_35mm: float | None = None) -> tuple[PinholeCamera, str]:
    """The camera to assume for a video without a known focal length.

    With a 35 mm-equivalent focal length ``f35`` (from the metadata): ``f = f35 / 36 mm``
    times the long side (the 36 mm side of 35 mm film spans the long side of the image;
    this ignores any crop from a 3:2 to the video's aspect ratio). Without one:
    ``f = 0.9 x`` the long side (:data:`DEFAULT_FOCAL_FACTOR`, a 58 degree field of view
    across the long side). Principal point at the image centre, square pixels.

    Returns:
        the camera and a sentence saying where its focal length came from.
    """
    side = max(width, height)
    if focal_35mm:
        f = focal_35mm / 36.0 * side
        how = (f"focal length {f:.1f} px from the video's 35 mm-equivalent focal length "
               f"{focal_35mm:g} mm (f = {focal_35mm:g} / 36 x long side {side} px)")
    else:
        f = DEFAULT_FOCAL_FACTOR * side
        fov = math.degrees(2 * math.atan(side / (2 * f)))
        how = (f"default focal length {f:.1f} px = {DEFAULT_FOCAL_FACTOR} x the long side ({side} px), "
               f"a {fov:.0f} degree field of view across it; no --focal or --camera was given and the "
               "input states no focal length -- give --focal if you know it")
    return PinholeCamera.from_focal(width, height, f), how


class VideoSequence(Sequence):
    """A :class:`~flowmocap.io.sequence.Sequence` whose frames come from a decoded video.

    ``meta`` holds ``fps``, ``source``, ``timestamps`` and the rest of
    :func:`decode_video`'s information.
    """

    def __init__(self, path: Path, frames: list[np.ndarray], fps: float, masks: list[Path] | None,
                 info: dict | None = None):
        h, w = frames[0].shape[:2]
        meta = {"fps": fps, "source": str(path), **(info or {})}
        meta["fps"] = fps
        super().__init__(root=path, frames=[path] * len(frames), masks=masks, camera=None,
                         meta=meta, size=(w, h))
        self._decoded = frames

    def frame(self, i: int) -> np.ndarray:
        f = self._decoded[i]
        if (f.shape[1], f.shape[0]) != self.size:
            raise DataError(f"frame {i} of {self.root} changes size to {f.shape[1]}x{f.shape[0]}; "
                            "re-encode the video at one frame size.")
        return f


def load_video(path: str | Path, masks: str | Path | None = None, max_side: int | None = None) -> VideoSequence:
    """Open a video file as a sequence, with an optional folder of one mask per frame.

    Args:
        path: the video.
        masks: a folder of one mask per frame (at the video's, or the scaled, size).
        max_side: scale frames so that the long side is at most this (pixels); None keeps them.

    Raises:
        DataError: undecodable video, mask count or size not matching the video.
    """
    path = Path(path)
    frames, info = decode_video(path, max_side=max_side)
    mask_paths = None
    if masks is not None:
        mask_dir = Path(masks)
        if not mask_dir.is_dir():
            raise DataError(f"mask folder {mask_dir} does not exist.")
        mask_paths = list_images(mask_dir)
        if len(mask_paths) != len(frames):
            raise DataError(f"{len(mask_paths)} masks in {mask_dir} but {len(frames)} frames in {path}; "
                            "give one mask per frame, in the same order.")
        read_image(mask_paths[0], (frames[0].shape[1], frames[0].shape[0]), gray=True)
    return VideoSequence(path, frames, info["fps"], mask_paths, info)
