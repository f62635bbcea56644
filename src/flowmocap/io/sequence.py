"""Sequence folders (DESIGN.md): frames, optional masks, camera.json, optional gt.npz.

    SEQ/frames/000000.png ...   RGB frames
    SEQ/masks/000000.png ...    person masks (optional; non-zero = person)
    SEQ/camera.json             PinholeCamera.to_dict()
    SEQ/gt.npz                  optional ground truth: poses, trans, betas, joints3d, joints2d
    SEQ/meta.json               optional
"""

from __future__ import annotations

import json
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from flowmocap.errors import DataError, InputError

if TYPE_CHECKING:  # torch (via the camera) only where a camera is made
    from flowmocap.geometry.camera import PinholeCamera

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass
class Sequence:
    """A frame sequence on disk.

    Attributes:
        frames: paths of the frames in order, length T.
        masks: paths of the masks (length T) or ``None``.
        camera: the camera, or ``None`` when the folder has no camera.json.
        gt: ground-truth arrays from gt.npz (empty dict when absent).
        meta: meta.json contents (empty dict when absent).
        size: ``(width, height)`` of the frames in pixels (as :meth:`frame` returns them).
        source_size: ``(width, height)`` of the image files when :func:`load_sequence`
            scales them down to ``size`` (``max_side``), else ``None``.
    """

    root: Path
    frames: list[Path]
    masks: list[Path] | None
    camera: PinholeCamera | None
    gt: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    size: tuple[int, int] = (0, 0)
    source_size: tuple[int, int] | None = None

    def __len__(self) -> int:
        return len(self.frames)

    def frame(self, i: int) -> np.ndarray:
        """Frame ``i`` as ``(H, W, 3)`` uint8 RGB (scaled to :attr:`size`)."""
        if self.source_size is None:
            return read_image(self.frames[i], self.size)
        return scale_image(read_image(self.frames[i], self.source_size), self.size)

    def mask(self, i: int) -> np.ndarray | None:
        """Mask ``i`` as ``(H, W)`` bool, or ``None`` without masks. With scaled frames a
        mask may have the files' size (scaled too: a pixel is the person's where most of
        the area it covers is) or the scaled size (e.g. the detector's masks)."""
        if self.masks is None:
            return None
        if self.source_size is None:
            return read_image(self.masks[i], self.size, gray=True) > 0
        m = read_image(self.masks[i], None, gray=True)
        if (m.shape[1], m.shape[0]) == tuple(self.source_size):
            return scale_image(((m > 0) * np.uint8(255)), self.size) >= 128
        if (m.shape[1], m.shape[0]) != tuple(self.size):
            raise DataError(f"{self.masks[i]} is {m.shape[1]}x{m.shape[0]} but the frames are "
                            f"{self.source_size[0]}x{self.source_size[1]} (scaled to {self.size[0]}x{self.size[1]}); "
                            "give masks of the frames' size.")
        return m > 0


def scale_image(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``img`` resized to ``size = (width, height)`` by area averaging (OpenCV).

    Args:
        img: ``(H, W)`` or ``(H, W, C)`` image (e.g. uint8 RGB or a 0/255 uint8 mask).
        size: ``(width, height)`` in pixels.

    Returns:
        ``(height, width)`` or ``(height, width, C)``, the input's dtype.
    """
    import cv2

    return cv2.resize(img, tuple(int(v) for v in size), interpolation=cv2.INTER_AREA)


def scaled_size(size: tuple[int, int], max_side: int | None) -> tuple[tuple[int, int], float]:
    """``(width, height)`` scaled so that the long side is at most ``max_side`` pixels
    (as videos are, :class:`flowmocap.io.video.VideoReader`), and the scale; ``size``
    and 1.0 when it already fits or ``max_side`` is None or 0."""
    w, h = (int(v) for v in size)
    if not max_side or max(w, h) <= max_side:
        return (w, h), 1.0
    s = max_side / max(w, h)
    return (max(1, round(w * s)), max(1, round(h * s))), s


def frame_order_key(path: Path) -> tuple:
    """Sort key for frame file names: runs of digits compare as numbers, so ``frame2.png``
    comes before ``frame10.png`` (names numbered without leading zeros, as ffmpeg's ``%d``
    writes them) and zero-padded names keep their order. Ties (``f01``, ``f1``) go by name."""
    parts = re.split(r"(\d+)", path.name)
    return tuple((0, int(x), "") if x.isdigit() else (1, 0, x) for x in parts), path.name


def list_images(folder: Path) -> list[Path]:
    """The image files directly in ``folder`` (suffixes :data:`IMAGE_SUFFIXES`, any case) in
    frame order: by name, the numbers in names compared as numbers (:func:`frame_order_key`)."""
    return sorted((p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=frame_order_key)


def read_image(path: Path, size: tuple[int, int] | None = None, gray: bool = False) -> np.ndarray:
    """Read an image as uint8 RGB ``(H, W, 3)`` (or ``(H, W)`` with ``gray``).

    Raises:
        DataError: unreadable file or a size other than ``size = (width, height)``.
    """
    import cv2

    flag = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR
    img = cv2.imread(str(path), flag)
    if img is None:
        raise DataError(f"cannot read image {path}: the file is missing or not an image.")
    if not gray:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        raise DataError(
            f"{path} is {img.shape[1]}x{img.shape[0]} but the sequence's frames are "
            f"{size[0]}x{size[1]}; frames and masks must all have one size."
        )
    return img


def _read_gt(path: Path) -> dict:
    """The arrays of a sequence's ``gt.npz``.

    Raises:
        DataError: a damaged file (truncated, empty, not an .npz, a member that does not load).
    """
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):  # a plain .npy under the name
            raise ValueError("an .npy array, not an .npz archive")
        with z:
            return {k: z[k] for k in z.files}
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
        raise DataError(f"{path} is unreadable ({type(e).__name__}: {e}); regenerate it (flowmocap synth), or "
                        "remove it to use the sequence without ground truth.") from None


def _read_meta(path: Path) -> dict:
    """A sequence's ``meta.json`` (a JSON object).

    Raises:
        DataError: not valid JSON, or not a JSON object.
    """
    try:
        meta = json.loads(path.read_text())
    except (ValueError, OSError) as e:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise DataError(f"{path} is not valid JSON ({e}); regenerate it (flowmocap synth), or remove it.") from None
    if not isinstance(meta, dict):
        raise DataError(f"{path} must hold a JSON object but holds a {type(meta).__name__}; regenerate it "
                        "(flowmocap synth), or remove it.")
    if "fps" in meta:  # checked here: a bad rate used to fail after the whole tracking
        check_fps(meta["fps"], f"{path}'s \"fps\"", DataError)
    return meta


def check_images(paths: list[Path], size: tuple[int, int] | tuple[tuple[int, int], ...], what: str) -> None:
    """Check, from their headers only (PIL, a millisecond a file), that every image in
    ``paths`` can be opened and has one of the sizes ``size`` (a ``(width, height)`` or a
    tuple of them), so a bad file late in a folder is found before any work starts. A
    file PIL cannot open, or whose header gives another size (e.g. an EXIF rotation,
    which OpenCV applies), is read in full by OpenCV, as the tracker reads it.

    Raises:
        DataError: an unreadable file or one of another size, named, with what to do.
    """
    from PIL import Image

    sizes = (tuple(size),) if isinstance(size[0], int) else tuple(tuple(s) for s in size)
    for p in paths:
        try:
            with Image.open(p) as img:
                got = tuple(img.size)
        except Exception:  # noqa: BLE001 -- PIL raises many kinds for a broken file: OpenCV decides below
            got = None
        if got not in sizes:  # unreadable for PIL, or of another size (an EXIF rotation?): as OpenCV reads it
            img = read_image(p, None, gray=True)  # DataError when OpenCV cannot read it either
            got = (img.shape[1], img.shape[0])
            if got not in sizes:
                shown = " or ".join(f"{w}x{h}" for w, h in sizes)
                raise DataError(f"{p} is {got[0]}x{got[1]} but the sequence's frames are {shown}; frames and masks "
                                f"must all have one size: resize or replace this {what}.")


#: The smallest long side, pixels, frames may be scaled to (``--max-size``): in a smaller frame
#: a person is too few pixels for the detector or the flow.
MIN_MAX_SIDE = 64

#: Frames per second taken for a folder of frames that states no rate (``meta.json``
#: ``fps``, ``track --fps``).
DEFAULT_FPS = 30.0
#: The highest frame rate taken (high-speed cameras film at 1000 fps).
MAX_FPS = 10000.0


def check_fps(value, what: str = "fps", error=InputError) -> float:
    """``value`` as a frame rate in frames per second: a finite number in (0, :data:`MAX_FPS`].

    Raises:
        ``error`` (InputError by default): anything else, with ``what`` named.
    """
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    if not ok or not (np.isfinite(value) and 0 < value <= MAX_FPS):
        raise error(f"{what} must be a number of frames per second, more than 0 and at most {MAX_FPS:g}; got {value!r}.")
    return float(value)


def check_max_side(max_side) -> None:
    """Refuse a ``max_side`` (``--max-size``) that is negative or, other than 0 (keep the size),
    below :data:`MIN_MAX_SIDE`.

    Raises:
        InputError: ``max_side`` < 0 or 0 < ``max_side`` < :data:`MIN_MAX_SIDE`.
    """
    try:
        whole = max_side is None or (not isinstance(max_side, bool) and float(max_side) == int(max_side))
    except (TypeError, ValueError, OverflowError):  # text, NaN, infinity
        whole = False
    if not whole:
        raise InputError(f"--max-size must be a whole number of pixels (0 keeps the video's size); got {max_side!r}.")
    if max_side is not None and (max_side < 0 or 0 < max_side < MIN_MAX_SIDE):
        raise InputError(f"--max-size must be 0 (keep the video's size) or at least {MIN_MAX_SIDE} px (in smaller "
                         f"frames a person is too few pixels to find); got {max_side}.")


def load_sequence(path: str | Path, masks: str | Path | None = None, max_side: int | None = None) -> Sequence:
    """Open a sequence folder, or a plain folder of frames.

    Args:
        path: a sequence folder (with ``frames/``) or a folder of images.
        masks: a folder of masks overriding ``path/masks`` (at the frames' size).
        max_side: scale the frames (and masks) so that the long side is at most this many
            pixels, as videos are; None or 0 keeps them. A folder with its own
            ``camera.json`` or ``gt.npz`` (e.g. made by ``flowmocap synth``) keeps its size:
            its camera and ground truth are in its pixels. ``meta["scale"]`` is the scale.

    Raises:
        DataError: no frames, unreadable files (every frame and mask is checked, from its
            header, before anything else), mask count or size not matching, a damaged
            gt.npz or meta.json.
        InputError: a negative ``max_side``.
    """
    check_max_side(max_side)
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"{root} is not a folder of frames or a sequence folder.")
    frame_dir = root / "frames" if (root / "frames").is_dir() else root
    frames = list_images(frame_dir)
    if not frames:
        raise DataError(f"no images ({', '.join(IMAGE_SUFFIXES)}) found in {frame_dir}.")
    first = read_image(frames[0])
    size = (first.shape[1], first.shape[0])
    mask_dir = Path(masks) if masks is not None else (root / "masks" if (root / "masks").is_dir() else None)
    mask_paths = None
    if mask_dir is not None:
        if not mask_dir.is_dir():
            raise DataError(f"mask folder {mask_dir} " + ("is a file; give a folder of mask images, one per frame."
                                                          if mask_dir.exists() else "does not exist."))
        mask_paths = list_images(mask_dir)
        if len(mask_paths) != len(frames):
            raise DataError(
                f"{len(mask_paths)} masks in {mask_dir} but {len(frames)} frames in {frame_dir}; "
                "give one mask per frame, in the same order."
            )
        read_image(mask_paths[0], size, gray=True)
    check_images(frames[1:], size, "frame")  # before any work: a bad file late in the folder is found now
    if mask_paths is not None:
        check_images(mask_paths, size, "mask")
    camera = None
    if (root / "camera.json").exists():
        try:
            from flowmocap.geometry.camera import PinholeCamera  # here: it imports torch
            camera = PinholeCamera.from_file(root / "camera.json")
        except (DataError, InputError) as e:
            raise DataError(f"{root / 'camera.json'} is not a valid camera file: {e}") from e
        if (camera.width, camera.height) != size:
            raise DataError(f"camera.json is for {camera.width}x{camera.height} images but the frames are {size[0]}x{size[1]}.")
    gt = _read_gt(root / "gt.npz") if (root / "gt.npz").exists() else {}
    meta = _read_meta(root / "meta.json") if (root / "meta.json").exists() else {}
    source_size = None
    if camera is None and not gt:
        scaled, scale = scaled_size(size, max_side)
        if scale != 1.0:
            source_size, size = size, scaled
            meta = {**meta, "scale": scaled[0] / source_size[0], "scale_xy": [scaled[0] / source_size[0],
                                                                              scaled[1] / source_size[1]],
                    "source_size": list(source_size), "max_side": max_side}
    return Sequence(root=root, frames=frames, masks=mask_paths, camera=camera, gt=gt, meta=meta, size=size,
                    source_size=source_size)
