"""Video files as frame sequences (decoded once into memory with PyAV via imageio)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flowmocap.errors import DataError
from flowmocap.io.sequence import Sequence, list_images, read_image

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v")


def read_video(path: str | Path) -> tuple[list[np.ndarray], float]:
    """Decode every frame of a video.

    Returns:
        ``frames``: list of ``(H, W, 3)`` uint8 RGB arrays, and ``fps`` (frames per second,
        from the container; 30 when it states none).

    Raises:
        DataError: missing file, a file that cannot be decoded, or no frames.
    """
    import imageio.v3 as iio

    path = Path(path)
    if not path.exists():
        raise DataError(f"video {path} does not exist.")
    try:
        meta = iio.immeta(path, plugin="pyav")
        frames = [np.ascontiguousarray(f) for f in iio.imiter(path, plugin="pyav", format="rgb24")]
    except Exception as e:  # PyAV raises many kinds of errors for broken files
        raise DataError(f"cannot decode video {path} ({type(e).__name__}: {e}); check the file, "
                        "or extract its frames into a folder and pass that instead.") from None
    if not frames:
        raise DataError(f"video {path} holds no frames.")
    fps = float(meta.get("fps") or 30.0)
    return frames, fps


class VideoSequence(Sequence):
    """A :class:`~flowmocap.io.sequence.Sequence` whose frames come from a decoded video."""

    def __init__(self, path: Path, frames: list[np.ndarray], fps: float, masks: list[Path] | None):
        h, w = frames[0].shape[:2]
        super().__init__(root=path, frames=[path] * len(frames), masks=masks, camera=None,
                         meta={"fps": fps, "source": str(path)}, size=(w, h))
        self._decoded = frames

    def frame(self, i: int) -> np.ndarray:
        f = self._decoded[i]
        if (f.shape[1], f.shape[0]) != self.size:
            raise DataError(f"frame {i} of {self.root} changes size to {f.shape[1]}x{f.shape[0]}.")
        return f


def load_video(path: str | Path, masks: str | Path | None = None) -> VideoSequence:
    """Open a video file as a sequence, with an optional folder of one mask per frame.

    Raises:
        DataError: undecodable video, mask count or size not matching the video.
    """
    path = Path(path)
    frames, fps = read_video(path)
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
    return VideoSequence(path, frames, fps, mask_paths)
