"""Writing MP4 videos frame by frame (H.264 through PyAV)."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import numpy as np

from flowmocap.errors import DataError, InputError

__all__ = ["VideoWriter"]


class VideoWriter:
    """An H.264 ``.mp4`` written one RGB frame at a time; use as a context manager.

    Even frame sizes use ``yuv420p`` (plays everywhere); odd ones ``yuv444p`` so the
    video keeps the exact size of its frames.

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
        self.size: tuple[int, int] | None = None
        self.frames = 0

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def write(self, frame: np.ndarray) -> None:
        """Append one ``(H, W, 3)`` uint8 RGB frame (all frames of one size)."""
        import av

        f = np.ascontiguousarray(frame, dtype=np.uint8)
        if f.ndim != 3 or f.shape[2] != 3:
            raise InputError(f"video frames must be (H, W, 3) RGB, got {f.shape}.")
        h, w = f.shape[:2]
        if self._container is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            try:
                self._container = av.open(str(self.path), mode="w")
            except Exception as e:  # noqa: BLE001 (PyAV raises many kinds)
                raise DataError(f"cannot write video {self.path} ({e}).") from None
            rate = Fraction(self.fps).limit_denominator(1001)
            s = self._container.add_stream("libx264", rate=rate)
            s.width, s.height = w, h
            s.pix_fmt = "yuv420p" if w % 2 == 0 and h % 2 == 0 else "yuv444p"
            s.options = {"crf": str(self.quality)}
            self._stream = s
            self.size = (w, h)
        elif (w, h) != self.size:
            raise InputError(f"frame {self.frames} is {w}x{h} but the video is {self.size[0]}x{self.size[1]}.")
        vf = av.VideoFrame.from_ndarray(f, format="rgb24")
        for packet in self._stream.encode(vf):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        """Flush the encoder and close the file (idempotent)."""
        if self._container is None:
            return
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()
        self._container = None
