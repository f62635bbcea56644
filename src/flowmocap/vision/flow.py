"""Observed optical flow ``F_o(i, i-1)`` between video frames (paper Sec. 3.3).

Direction: **backward**. ``observed_flow(frame_cur, frame_prev)`` returns, at every
pixel of the current frame i, the displacement ``(dx, dy)`` in pixels to where that
scene point is in the previous frame i-1: the point at ``(x, y)`` in frame i was at
``(x + dx, y + dy)`` in frame i-1. If the image content moves right by 2 px from i-1
to i, the flow is ``(-2, 0)``. This is the flow the renderer draws in place
(:func:`flowmocap.render.render_flow`).

Methods (OpenCV / opencv-contrib; the paper's MDP-Flow is not available):

==============  ===============================================  ===========  ==========
method           function                                         time         EPE
==============  ===============================================  ===========  ==========
``dis``          ``cv2.DISOpticalFlow`` (preset MEDIUM)            0.04 s       0.10 px
``dis-fine``     the same, refined to full resolution (``FinestScale=0``)  0.09 s  --
``farneback``    ``cv2.calcOpticalFlowFarneback``                  0.07 s       0.07 px
``deepflow``     ``cv2.optflow.createOptFlow_DeepFlow``            0.6 s        0.07 px
``rlof``         ``cv2.optflow.calcOpticalFlowDenseRLOF`` (BGR)    0.5 s        0.38 px
``tvl1``         ``cv2.optflow.DualTVL1OpticalFlow_create``        1.6 s        0.02 px
==============  ===============================================  ===========  ==========

On the body of a rendered walker (CMU 35_01 at 60 fps, 640x480, 9 pairs against the
true flow) the mean / 95th-percentile end-point errors are: ``dis`` 0.35 / 1.37 px,
``dis-fine`` 0.18 / 0.69 px, ``deepflow`` 0.32 / 1.53 px, ``tvl1`` 0.36 / 2.07 px,
``farneback`` 0.45 / 2.01 px.

Time: one 640x480 pair on 2 CPU cores. EPE: mean end-point error on a smooth random
texture moved by (2.3, -1.7) px, 40 px from the border (a pure translation: motion
boundaries, large displacements and untextured regions are not measured by it).

:class:`FlowCache` keeps computed flows on disk, one ``.npz`` per frame, uncompressed
(float flow fields shrink by only ~10 % under zlib, which costs ~0.1 s per 640x480 frame).
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

from flowmocap.atomic import atomic_write
from flowmocap.errors import DataError, InputError

__all__ = ["FLOW_METHODS", "DIS_PRESETS", "observed_flow", "FlowCache"]

#: DIS presets by name (``preset=`` option of the ``"dis"`` method).
DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


def _gray(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)


def _dis(cur: np.ndarray, prev: np.ndarray, preset: str | int = "medium", **params: Any) -> np.ndarray:
    """DIS; ``params`` are DIS setters without the ``set`` prefix (e.g. ``FinestScale=1``)."""
    if isinstance(preset, str):
        if preset.lower() not in DIS_PRESETS:
            raise InputError(f"unknown DIS preset {preset!r}; choose one of {', '.join(DIS_PRESETS)}")
        preset = DIS_PRESETS[preset.lower()]
    dis = cv2.DISOpticalFlow_create(int(preset))
    for name, value in params.items():
        setter = getattr(dis, f"set{name}", None)
        if setter is None:
            raise InputError(f"DIS has no parameter {name!r} (e.g. FinestScale, PatchSize, PatchStride, "
                             "GradientDescentIterations, VariationalRefinementIterations, UseSpatialPropagation)")
        setter(value)
    return dis.calc(_gray(cur), _gray(prev), None)


def _dis_fine(cur: np.ndarray, prev: np.ndarray, **params: Any) -> np.ndarray:
    """DIS MEDIUM refined down to the full resolution (``FinestScale=0``): on rendered
    people about half the end-point error of plain DIS at twice its (small) cost."""
    return _dis(cur, prev, "medium", **{"FinestScale": 0, **params})


def _deepflow(cur: np.ndarray, prev: np.ndarray) -> np.ndarray:
    return cv2.optflow.createOptFlow_DeepFlow().calc(_gray(cur), _gray(prev), None)


def _tvl1(cur: np.ndarray, prev: np.ndarray, **params: Any) -> np.ndarray:
    return cv2.optflow.DualTVL1OpticalFlow_create(**params).calc(_gray(cur), _gray(prev), None)


def _rlof(cur: np.ndarray, prev: np.ndarray, **params: Any) -> np.ndarray:
    bgr = lambda x: np.ascontiguousarray(x[..., ::-1])  # noqa: E731
    return cv2.optflow.calcOpticalFlowDenseRLOF(bgr(cur), bgr(prev), None, **params)


def _farneback(cur: np.ndarray, prev: np.ndarray, pyr_scale: float = 0.5, levels: int = 5, winsize: int = 15,
               iterations: int = 3, poly_n: int = 5, poly_sigma: float = 1.2, flags: int = 0) -> np.ndarray:
    return cv2.calcOpticalFlowFarneback(_gray(cur), _gray(prev), None, pyr_scale, levels, winsize, iterations,
                                        poly_n, poly_sigma, flags)


#: Flow methods by name: ``observed_flow(..., method=name)``.
FLOW_METHODS: dict[str, Callable[..., np.ndarray]] = {
    "dis": _dis,
    "dis-fine": _dis_fine,
    "deepflow": _deepflow,
    "tvl1": _tvl1,
    "rlof": _rlof,
    "farneback": _farneback,
}


def _check_frame(img: Any, name: str) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 2 or a.shape[1] < 2:
        raise InputError(f"{name} must be an (H, W, 3) RGB image, got shape {a.shape}")
    if a.dtype != np.uint8:
        raise InputError(f"{name} must be uint8 (0..255), got {a.dtype}; convert with "
                         "np.clip(img * 255, 0, 255).astype(np.uint8) for float images in [0, 1]")
    return np.ascontiguousarray(a)


def observed_flow(frame_cur: Any, frame_prev: Any, method: str = "dis", **options: Any) -> np.ndarray:
    """Backward optical flow from the current frame to the previous one.

    Args:
        frame_cur: ``(H, W, 3)`` uint8 RGB frame i.
        frame_prev: ``(H, W, 3)`` uint8 RGB frame i-1, same size.
        method: one of :data:`FLOW_METHODS` (default ``"dis"``).
        **options: method settings: ``dis``: ``preset`` (``"ultrafast"``, ``"fast"``,
            ``"medium"``) and DIS setter names (``FinestScale=1``...); ``tvl1``:
            ``DualTVL1OpticalFlow_create`` keywords; ``rlof``:
            ``calcOpticalFlowDenseRLOF`` keywords; ``farneback``: its parameters.

    Returns:
        ``(H, W, 2)`` float32 flow ``(dx, dy)`` in pixels at frame i's pixels, pointing to
        where each point is in frame i-1 (see the module docstring).

    Raises:
        InputError: unknown method or option, frames not RGB uint8 or of different sizes.
    """
    if method not in FLOW_METHODS:
        raise InputError(f"unknown flow method {method!r}; choose one of {', '.join(FLOW_METHODS)}")
    cur = _check_frame(frame_cur, "frame_cur")
    prev = _check_frame(frame_prev, "frame_prev")
    if cur.shape != prev.shape:
        raise InputError(
            f"frames must have the same size, got {cur.shape[1]}x{cur.shape[0]} (current) and "
            f"{prev.shape[1]}x{prev.shape[0]} (previous)"
        )
    try:
        flow = FLOW_METHODS[method](cur, prev, **options)
    except TypeError as exc:
        raise InputError(f"bad option for flow method {method!r}: {exc}") from None
    return np.ascontiguousarray(flow, dtype=np.float32)


def _npz_bytes(**arrays) -> bytes:
    """``np.savez`` into memory: a failed write to the disk then fails cleanly (numpy's
    zip writer left open on a full disk complains again when it is collected)."""
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


class FlowCache:
    """Observed flows on disk: ``<folder>/flow_<index>_<method>[_<hash>].npz``.

    Each file holds one (uncompressed) float32 ``(H, W, 2)`` array, the backward flow
    ``F_o(i, i-1)`` of frame ``index``. Files are written to a temporary file in the
    same folder and renamed, so an interrupted run leaves either a complete file or
    none. A file that cannot be read (or has the wrong size) counts as missing.
    ``options`` other than the defaults add a short hash of them to the name, so
    flows computed with different settings never mix.

    Args:
        folder: directory (created if missing); None stores nothing (:meth:`flow` then
            computes every flow, e.g. for a long video whose flows would fill the disk).
        method, **options: as for :func:`observed_flow`.
    """

    def __init__(self, folder: str | Path | None, method: str = "dis", **options: Any):
        if method not in FLOW_METHODS:
            raise InputError(f"unknown flow method {method!r}; choose one of {', '.join(FLOW_METHODS)}")
        self.folder = Path(folder) if folder is not None else None
        self.method = method
        self.options = dict(options)
        if self.folder is not None:
            try:
                self.folder.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise DataError(f"cannot create the flow cache folder {self.folder}: {exc}") from None
        tag = method
        if options:
            key = json.dumps(options, sort_keys=True, default=str).encode()
            tag += "_" + hashlib.sha1(key).hexdigest()[:8]
        self._tag = tag

    def path(self, index: int) -> Path:
        """The cache file of frame ``index`` (whether it exists or not); needs a folder."""
        return self.folder / f"flow_{int(index):06d}_{self._tag}.npz"

    def __contains__(self, index: int) -> bool:
        return self.folder is not None and self.path(index).is_file()

    def get(self, index: int, shape: tuple[int, int] | None = None) -> np.ndarray | None:
        """The cached flow of frame ``index``, or None if absent or unreadable.

        Args:
            index: frame number i (the flow is ``F_o(i, i-1)``).
            shape: optional ``(H, W)`` the flow must have; a cached flow of another size
                counts as absent.

        Returns:
            ``(H, W, 2)`` float32 or None.
        """
        if self.folder is None:
            return None
        p = self.path(index)
        if not p.is_file():
            return None
        try:
            with open(p, "rb") as fh, np.load(fh) as data:
                flow = np.asarray(data["flow"], dtype=np.float32)
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError):
            return None
        if flow.ndim != 3 or flow.shape[2] != 2 or (shape is not None and flow.shape[:2] != tuple(shape)):
            return None
        return flow

    def put(self, index: int, flow: np.ndarray) -> Path:
        """Store the flow of frame ``index`` atomically; returns the file path."""
        flow = np.asarray(flow, dtype=np.float32)
        if flow.ndim != 3 or flow.shape[2] != 2:
            raise InputError(f"flow must have shape (H, W, 2), got {flow.shape}")
        p = self.path(index)

        def write(tmp):
            with open(tmp, "wb") as fh:
                fh.write(_npz_bytes(flow=flow))

        atomic_write(p, write)
        return p

    def flow(self, index: int, frame_cur: Any, frame_prev: Any) -> np.ndarray:
        """The flow of frame ``index`` from the cache, computing and storing it if absent.

        Args:
            index: frame number i.
            frame_cur, frame_prev: ``(H, W, 3)`` uint8 RGB frames i and i-1.

        Returns:
            ``(H, W, 2)`` float32 backward flow, see :func:`observed_flow`.
        """
        cached = self.get(index, shape=np.shape(frame_cur)[:2])
        if cached is not None:
            return cached
        flow = observed_flow(frame_cur, frame_prev, self.method, **self.options)
        if self.folder is not None:
            self.put(index, flow)
        return flow
