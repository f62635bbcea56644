"""Video files as frame sequences, decoded as they are read (PyAV), and the default camera
of a video.

A video is scanned once when opened (every frame decoded, nothing kept but its time), so
its frame count and timing are known and a broken file is found at once; afterwards
:meth:`VideoReader.frame` decodes on demand, forwards from where it is or from the
nearest keyframe before a frame asked out of order, and keeps only a few frames. Memory
therefore stays flat however long the video is.

Frames come upright (a phone video's rotation tag is applied, so a portrait video gives
portrait frames), optionally scaled down so that the long side is at most ``max_side``.
Every frame's presentation time is kept: a variable-frame-rate video (phones record
those) is tracked frame by frame as usual, and ``meta["timestamps"]`` says when each
frame was shown; ``meta["fps"]`` is the mean rate over the video.
"""

from __future__ import annotations

import math
import re
import threading
from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from flowmocap.errors import DataError
from flowmocap.io.sequence import Sequence, check_images, check_max_side, list_images, scale_image, scaled_size

if TYPE_CHECKING:  # torch (via the camera) only where a camera is made
    from flowmocap.geometry.camera import PinholeCamera

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mts", ".m2ts", ".ts", ".3gp", ".mpg", ".mpeg",
                  ".wmv", ".flv")  # compared in lower case: .MTS, .MOV (camcorders, phones)

#: Default focal length, as a multiple of the image's long side: 0.9 x the long side is
#: a 58 degree field of view across it, a 32 mm lens on 35 mm film -- between the
#: usual phone main camera (~26 mm, 69 degrees) and a "normal" 40-50 mm lens.
DEFAULT_FOCAL_FACTOR = 0.9


def decode_video(path: str | Path, max_side: int | None = None) -> tuple[list[np.ndarray], dict]:
    """Decode every frame of a video into memory, upright, with timing and camera metadata
    (for short clips; :class:`VideoReader` streams).

    Args:
        path: the video file.
        max_side: scale frames down (area interpolation) so that neither side exceeds
            this many pixels; None or 0 keeps the decoded size.

    Returns:
        ``frames`` (list of ``(H, W, 3)`` uint8 RGB) and :attr:`VideoReader.info`.

    Raises:
        DataError: missing file, a file that cannot be decoded, or no frames.
    """
    with VideoReader(path, max_side) as reader:
        return [reader.frame(i) for i in range(len(reader))], reader.info


def _display_orientation(frame) -> tuple[int, int, int, int] | None:
    """``(a, b, c, d)``, each -1, 0 or 1: the 2x2 part of a decoded frame's display matrix
    (FFmpeg's: a decoded pixel ``(x, y)`` is shown at ``(a x + c y, b x + d y)`` plus a
    shift), or None where the frame has none or it is no quarter turn or mirror."""
    for sd in getattr(frame, "side_data", None) or ():
        if "DISPLAYMATRIX" not in str(getattr(sd, "type", "")):
            continue
        try:
            m = np.frombuffer(bytes(sd), "=i4")
        except (TypeError, ValueError):
            return None
        if m.size != 9:
            return None
        abcd = np.array([m[0], m[1], m[3], m[4]], np.float64) / 65536.0
        q = np.round(abcd)
        if np.abs(abcd - q).max() > 1e-3 or abs(q[0] * q[3] - q[1] * q[2]) != 1:
            return None
        return tuple(int(v) for v in q)
    return None


def _square_width(width: int, sar: float) -> int:
    """A stored frame's width in square pixels (its sample aspect ratio ``sar``: a pixel's
    width over its height)."""
    return max(1, int(round(width * sar)))


def _oriented(img: np.ndarray, abcd: tuple[int, int, int, int]) -> np.ndarray:
    """``img (H, W, C)`` as shown under the display matrix part ``abcd``
    (:func:`_display_orientation`): rows and columns swapped where it swaps the axes, then
    flipped where it reverses them."""
    a, b, c, d = abcd
    if a == 0:  # x' = c y, y' = b x: the shown image is the transpose, flipped
        img = np.swapaxes(img, 0, 1)
        return img[::-1 if b < 0 else 1, ::-1 if c < 0 else 1]
    return img[::-1 if d < 0 else 1, ::-1 if a < 0 else 1]  # x' = a x, y' = d y


class VideoReader:
    """Frames of a video by index, upright and optionally scaled, decoded on demand.

    Args:
        path: the video file.
        max_side: scale frames down (area interpolation) so that neither side exceeds
            this many pixels; None or 0 keeps the decoded size.

    Attributes:
        info: ``fps`` (mean rate), ``timestamps`` (seconds from the first frame, one per
            frame), ``variable_frame_rate`` (bool: frame intervals differ by more than 10%
            of their median), ``rotation`` (degrees counter-clockwise applied from the
            stream's display matrix), ``mirrored`` (the display matrix also mirrors the
            frames, as a player shows them: QuickTime's Flip Horizontal writes one),
            ``sample_aspect_ratio`` (a stored pixel's width over its height; frames of
            non-square pixels are resampled to square ones, as players show them),
            ``stored_size`` (``[W, H]`` of the frames as the file stores them),
            ``decoded_size`` and ``size`` (``[W, H]`` as shown, upright and in square
            pixels, before and after scaling), ``scale`` (width / decoded width),
            ``scale_xy`` (the width's and the height's, which rounding to whole pixels
            makes differ slightly), ``focal_35mm`` (35
            mm-equivalent focal length in mm from the metadata, or None), ``metadata``
            (container and stream tags), ``cut_short`` (None, or for a file that stops
            early -- decoding fails part of the way, or fewer frames or seconds decode
            than the container says it holds -- ``decoded_frames``, ``declared_frames``,
            ``declared_seconds``, ``decoded_seconds`` (None where unknown) and ``error``
            (the decoder's, or None)).

    Thread-safe: the tracker reads the next frame on a second thread.

    Raises:
        DataError: missing file, a file that cannot be decoded, or no frames. A truncated
        file keeps the frames that decode, and says so in ``info["cut_short"]``.
    """

    #: Frames kept decoded (the tracker reads each frame and the one before it).
    KEEP = 4
    #: Frames decoded forwards, rather than seeking, to reach a frame ahead.
    FORWARD = 48

    def __init__(self, path: str | Path, max_side: int | None = None):
        self.path = Path(path)
        self.max_side = max_side or None
        if not self.path.exists():
            raise DataError(f"video {self.path} does not exist.")
        self._lock = threading.RLock()
        self._kept: OrderedDict[int, np.ndarray] = OrderedDict()
        self._container = None
        self._frames = None  # the decoding generator, positioned before frame self._next
        self._next = 0
        self._rotation, self._orient, self._sar = 0, None, 1.0  # set by _scan
        self.info, self._pts = self._scan()
        self._index = {p: i for i, p in enumerate(self._pts)} if self._pts is not None else None

    def __len__(self) -> int:
        return len(self.info["timestamps"])

    def __enter__(self) -> VideoReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Close the file (a later :meth:`frame` opens it again)."""
        with self._lock:
            if self._container is not None:
                self._container.close()
            self._container, self._frames = None, None

    def __getstate__(self) -> dict:
        """Pickled without the open file, its decoder and the kept frames (another process,
        e.g. the person detector's, opens the file again on its first :meth:`frame`)."""
        with self._lock:
            state = dict(self.__dict__)
        for k in ("_lock", "_container", "_frames"):
            state.pop(k, None)
        state.update(_kept=OrderedDict(), _next=0)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.RLock()
        self._container = None
        self._frames = None

    def _scan(self) -> tuple[dict, list | None]:
        import av

        times: list[float] = []
        pts: list = []
        rotation = 0
        mirrored = False
        tags: dict = {}
        rate = None
        decoded = size = (0, 0)
        declared, stopped, duration = 0, None, None
        try:
            with av.open(str(self.path)) as container:
                if not container.streams.video:
                    raise DataError(f"{self.path} holds no video stream; give a video file or a folder of frames.")
                stream = container.streams.video[0]
                sar = stream.sample_aspect_ratio or stream.codec_context.sample_aspect_ratio
                # non-square pixels (a camcorder's 1440x1080 shown 1920x1080, DV): resampled to square ones
                self._sar = float(sar) if sar is not None and 0.1 < float(sar) < 10 and sar != 1 else 1.0
                tags = {**{f"container:{k}": v for k, v in container.metadata.items()},
                        **{k: v for k, v in stream.metadata.items()}}
                rate = float(stream.average_rate) if stream.average_rate else None
                declared = int(stream.frames or 0)  # what the container says it holds (0: unknown)
                if container.duration:  # in microseconds (av.time_base)
                    duration = container.duration / 1e6
                for frame in container.decode(stream):
                    if not times:
                        rot = int(round(getattr(frame, "rotation", 0) or 0))
                        rotation = rot if rot % 90 == 0 else 0
                        decoded = (frame.width, frame.height)
                        self._rotation = rotation
                        self._orient = _display_orientation(frame)
                        if self._orient is not None:
                            mirrored = self._orient[0] * self._orient[3] - self._orient[1] * self._orient[2] < 0
                        first = self._convert(frame)
                        size = (first.shape[1], first.shape[0])
                    elif (frame.width, frame.height) != decoded:
                        raise DataError(f"frame {len(times)} of {self.path} changes size to {frame.width}x"
                                        f"{frame.height} (from {decoded[0]}x{decoded[1]}); re-encode the video "
                                        "at one frame size.")
                    times.append(float(frame.time) if frame.time is not None else float("nan"))
                    pts.append(frame.pts)
        except DataError:
            raise
        except Exception as e:  # PyAV raises many kinds of errors for broken files
            if not times:  # a truncated file keeps the frames that decoded
                raise DataError(f"cannot decode video {self.path} ({type(e).__name__}: {e}); check the file, "
                                "or extract its frames into a folder and pass that instead.") from None
            stopped = f"{type(e).__name__}: {e}"
        if not times:
            raise DataError(f"video {self.path} holds no frames.")
        # a file cut off (a download or copy stopped part of the way) keeps what decodes, and says so
        step = 1.0 / (rate or 30.0)
        span = (times[-1] - times[0] + step) if np.isfinite([times[0], times[-1]]).all() else None
        short_count = declared - len(times) > max(2, 0.01 * declared)
        short_time = duration is not None and span is not None and duration - span > max(3 * step, 0.01 * duration)
        cut_short = None
        if stopped is not None or short_count or short_time:
            cut_short = {"decoded_frames": len(times), "declared_frames": declared or None,
                         "declared_seconds": round(duration, 3) if duration else None,
                         "decoded_seconds": round(span, 3) if span is not None else None, "error": stopped}
        t = np.asarray(times, np.float64)
        if not np.isfinite(t).all() or (len(t) > 1 and (np.diff(t) <= 0).any()):
            t = np.arange(len(times)) * (1.0 / (rate or 30.0))
        else:
            t = t - t[0]
        vfr = False
        if len(t) > 2:
            d = np.diff(t)
            vfr = bool(np.abs(d - np.median(d)).max() > 0.1 * np.median(d))
            fps = (len(t) - 1) / t[-1]
        else:
            fps = rate or 30.0
        swapped = self._orient[0] == 0 if self._orient is not None else rotation % 180 != 0
        shown = (_square_width(decoded[0], self._sar), decoded[1])  # the stored frame in square pixels
        upright = [shown[1], shown[0]] if swapped else list(shown)
        info = {
            "fps": float(fps), "timestamps": t.round(6).tolist(), "variable_frame_rate": vfr,
            "rotation": rotation, "mirrored": mirrored, "sample_aspect_ratio": self._sar, "stored_size": list(decoded),
            "decoded_size": upright, "size": list(size), "scale": size[0] / upright[0],
            "scale_xy": [size[0] / upright[0], size[1] / upright[1]],
            "focal_35mm": focal_35mm_from_tags(tags), "metadata": {k: str(v) for k, v in tags.items()},
            "cut_short": cut_short,
        }
        usable = None not in pts and len(set(pts)) == len(pts)
        return info, (pts if usable else None)

    def _convert(self, frame) -> np.ndarray:
        img = frame.to_ndarray(format="rgb24")
        if self._sar != 1.0:  # square pixels, as a player shows them
            import cv2

            w = _square_width(img.shape[1], self._sar)
            img = cv2.resize(img, (w, img.shape[0]), interpolation=cv2.INTER_AREA if w < img.shape[1] else
                             cv2.INTER_LINEAR)
        if self._orient is not None:  # as a player shows it: the display matrix, mirror included
            img = _oriented(img, self._orient)
        elif self._rotation:
            img = np.rot90(img, k=(self._rotation // 90) % 4)
        size, scale = scaled_size((img.shape[1], img.shape[0]), self.max_side)
        if scale != 1.0:
            img = scale_image(img, size)
        return np.ascontiguousarray(img)

    def _restart(self, i: int) -> None:
        """Position the decoder before frame ``i``: at the keyframe at or before it (from
        the start without usable timestamps)."""
        import av

        if self._container is None:
            self._container = av.open(str(self.path))
        stream = self._container.streams.video[0]
        if self._pts is None or i == 0:
            self._container.seek(0, stream=stream) if self._frames is not None else None
        else:
            self._container.seek(int(self._pts[i]), stream=stream, backward=True, any_frame=False)
        self._frames = self._container.decode(stream)
        self._next = 0 if self._index is None else None  # else known from the first decoded frame

    def frame(self, i: int) -> np.ndarray:
        """Frame ``i`` as ``(H, W, 3)`` uint8 RGB (a shared array: do not modify it).

        Raises:
            DataError: the frame cannot be decoded (again).
        """
        n = len(self)
        if not 0 <= i < n:
            raise IndexError(f"frame {i} of a video of {n} frames")
        with self._lock:
            if i in self._kept:
                self._kept.move_to_end(i)
                return self._kept[i]
            ahead = self.FORWARD if self._index is not None else len(self)  # without timestamps: never seek
            if self._frames is None or self._next is None or not (self._next <= i <= self._next + ahead):
                self._restart(i)
            try:
                for attempt in range(2):
                    for frame in self._frames:
                        k = self._index.get(frame.pts) if self._index is not None else self._next
                        if k is None:
                            continue
                        if k > i:  # the seek went past the frame: decode from the start instead
                            break
                        self._next = k + 1
                        if k >= i - self.KEEP:
                            self._kept[k] = self._convert(frame)
                            while len(self._kept) > self.KEEP:
                                self._kept.popitem(last=False)
                        if k == i:
                            return self._kept[i]
                    self._index_from_start()
            except DataError:
                raise
            except Exception as e:  # noqa: BLE001 -- PyAV's errors for a file changed or broken since the scan
                raise DataError(f"cannot decode frame {i} of {self.path} ({type(e).__name__}: {e}).") from None
        raise DataError(f"cannot decode frame {i} of {self.path} again; the file changed since it was opened.")

    def _index_from_start(self) -> None:
        """Fall back to decoding from the first frame and counting frames."""
        self.close()
        self._index = None
        self._pts = None
        self._restart(0)


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


def cut_short_words(cut: dict) -> str:
    """What :attr:`VideoReader.info`'s ``cut_short`` says, in words (``"4 frames decode
    (0.13 s), but the file says it holds 30 frames"``)."""
    said = (f"the file says it holds {cut['declared_frames']} frames" if cut.get("declared_frames") else
            f"the file says it lasts {cut['declared_seconds']:.2f} s" if cut.get("declared_seconds") else
            "decoding stops with an error")
    text = f"{cut['decoded_frames']} frames decode"
    if cut.get("decoded_seconds"):
        text += f" ({cut['decoded_seconds']:.2f} s)"
    text += f", but {said}"
    if cut.get("error"):
        text += f" ({cut['error']})"
    return text


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
    from flowmocap.geometry.camera import PinholeCamera  # here: it imports torch
    return PinholeCamera.from_focal(width, height, f), how


class VideoSequence(Sequence):
    """A :class:`~flowmocap.io.sequence.Sequence` whose frames come from a video, decoded
    as they are read (:class:`VideoReader`).

    ``meta`` holds ``fps``, ``source``, ``timestamps`` and the rest of
    :attr:`VideoReader.info`. With frames scaled (``max_side``) :attr:`source_size` is the
    video's own (decoded, upright) size, so masks of that size are scaled like the
    frames (:meth:`Sequence.mask`).
    """

    def __init__(self, path: Path, reader: VideoReader, masks: list[Path] | None):
        w, h = reader.info["size"]
        meta = {"source": str(path), **reader.info}
        decoded = tuple(int(v) for v in reader.info["decoded_size"])
        super().__init__(root=path, frames=[path] * len(reader), masks=masks, camera=None, meta=meta, size=(w, h),
                         source_size=decoded if decoded != (w, h) else None)
        self.reader = reader

    def frame(self, i: int) -> np.ndarray:
        """Frame ``i`` (0-based) as uint8 RGB ``(H, W, 3)``, at the sequence's (possibly
        scaled) size: :meth:`VideoReader.frame` (a shared array: do not modify it).

        Raises:
            DataError: the frame cannot be decoded.
        """
        return self.reader.frame(i)


def load_video(path: str | Path, masks: str | Path | None = None, max_side: int | None = None) -> VideoSequence:
    """Open a video file as a sequence, with an optional folder of one mask per frame.

    Args:
        path: the video.
        masks: a folder of one mask per frame (at the video's, or the scaled, size; each
            is checked, from its header, before anything else).
        max_side: scale frames so that the long side is at most this (pixels); None or 0 keeps them.

    Raises:
        DataError: undecodable video, mask count or size not matching the video.
        InputError: a negative ``max_side``.
    """
    check_max_side(max_side)
    path = Path(path)
    reader = VideoReader(path, max_side=max_side)
    size = tuple(reader.info["size"])
    mask_paths = None
    if masks is not None:
        mask_dir = Path(masks)
        if not mask_dir.is_dir():
            raise DataError(f"mask folder {mask_dir} does not exist.")
        mask_paths = list_images(mask_dir)
        if len(mask_paths) != len(reader):
            cut = reader.info["cut_short"]
            raise DataError(f"{len(mask_paths)} masks in {mask_dir} but {len(reader)} frames in {path}"
                            + (f" (the file is cut off: {cut_short_words(cut)}; get it again)" if cut else "")
                            + "; give one mask per frame, in the same order.")
        decoded = tuple(reader.info["decoded_size"])
        check_images(mask_paths, (decoded, size) if decoded != size else size, "mask")
    return VideoSequence(path, reader, mask_paths)
