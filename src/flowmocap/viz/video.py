"""Writing MP4 videos frame by frame (H.264 through PyAV)."""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from fractions import Fraction
from pathlib import Path

import numpy as np

from flowmocap.errors import DataError, InputError

__all__ = ["VideoWriter"]

#: The container a video's name asks for (FFmpeg's muxer names); any other name gets MP4. The
#: video is written under a temporary name first, so the name cannot tell FFmpeg.
CONTAINERS = {".mp4": "mp4", ".m4v": "mp4", ".mov": "mov", ".mkv": "matroska", ".avi": "avi"}


class VideoWriter:
    """An H.264 ``.mp4`` written one RGB frame at a time; use as a context manager.

    Frames are written as ``yuv420p`` (it plays everywhere; ``yuv444p``, which an odd size
    would need, does not play in QuickTime, Safari, most browsers or hardware decoders):
    a frame of odd width or height gets its last column or row repeated once, so the
    video is at most one pixel wider and taller than its frames, their pixels where they were.

    Args:
        path: output file.
        fps: frames per second (Hz).
        quality: x264 CRF (0 lossless ... 51 worst; 18 looks lossless).
    """

    def __init__(self, path: str | Path, fps: float, quality: int = 18):
        if not np.isfinite(fps) or fps <= 0:
            raise InputError(f"fps must be positive, got {fps}.")
        self.path = Path(path)
        self.fps = fps
        self.quality = int(quality)
        self._container = None
        self._stream = None
        self._tmp: str | None = None
        self.size: tuple[int, int] | None = None
        self.frames = 0

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            try:
                self.close()
            except BaseException:  # the last packets or the file's end could not be written (a full disk)
                self.discard()
                raise
        else:  # a failed or interrupted video: nothing under its name
            self.discard()

    def write(self, frame: np.ndarray) -> None:
        """Append one ``(H, W, 3)`` uint8 RGB frame (all frames of one size)."""
        import av

        f = np.ascontiguousarray(frame, dtype=np.uint8)
        if f.ndim != 3 or f.shape[2] != 3:
            raise InputError(f"video frames must be (H, W, 3) RGB, got {f.shape}.")
        h, w = f.shape[:2]
        if w % 2 or h % 2:  # yuv420p needs even sizes: the last column or row once more
            f = np.pad(f, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
        if self._container is None:
            if self.path.is_dir():
                raise InputError(f"{self.path} is a folder; give the path of the video file to write.")
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, self._tmp = tempfile.mkstemp(dir=self.path.parent, prefix=self.path.name + ".", suffix=".tmp")
            os.close(fd)
            try:
                self._container = av.open(self._tmp, mode="w", format=CONTAINERS.get(self.path.suffix.lower(), "mp4"))
            except Exception as e:  # noqa: BLE001 (PyAV raises many kinds)
                self.discard()
                raise DataError(f"cannot write video {self.path} ({e}).") from None
            rate = Fraction(self.fps).limit_denominator(1001)
            s = self._container.add_stream("libx264", rate=rate)
            s.width, s.height = f.shape[1], f.shape[0]
            s.pix_fmt = "yuv420p"
            s.options = {"crf": str(self.quality)}
            self._stream = s
            self.size = (w, h)
        elif (w, h) != self.size:
            raise InputError(f"frame {self.frames} is {w}x{h} but the video is {self.size[0]}x{self.size[1]}.")
        vf = av.VideoFrame.from_ndarray(f, format="rgb24")
        with self._named():
            for packet in self._stream.encode(vf):
                self._container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        """Flush the encoder, close the file and put it under its name (idempotent). Until
        then the video is written to a temporary file beside it."""
        if self._container is None:
            return
        with self._named():
            for packet in self._stream.encode():
                self._container.mux(packet)
            self._container.close()
        self._container = None
        from flowmocap.atomic import current_umask

        os.chmod(self._tmp, 0o666 & ~current_umask())  # mkstemp makes 0600
        os.replace(self._tmp, self.path)
        self._tmp = None

    def discard(self) -> None:
        """Stop writing and remove the unfinished video (nothing is put under its name)."""
        if self._container is not None:
            try:
                self._container.close()
            except Exception:  # noqa: BLE001 (a failed stream may not close cleanly; it is removed anyway)
                pass
            self._container = None
        if self._tmp is not None:
            Path(self._tmp).unlink(missing_ok=True)
            self._tmp = None

    @contextlib.contextmanager
    def _named(self):
        """An ``OSError`` while writing (a full disk, a file size limit) names the video."""
        try:
            yield
        except OSError as e:
            if getattr(e, "filename", None) == str(self.path):
                raise
            raise OSError(e.errno or errno.EIO, e.strerror or str(e), str(self.path)) from e
