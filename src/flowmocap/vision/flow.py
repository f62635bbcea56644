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

__all__ = ["FLOW_METHODS", "DIS_PRESETS", "observed_flow", "flow_region", "FlowCache"]

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


#: The smallest side of a :func:`flow_region` (pixels): DIS needs a few patches of context.
MIN_REGION = 64


def flow_region(masks, margin_px: int = 16, margin_frac: float = 0.15) -> tuple[int, int, int, int] | None:
    """The image region a person's observed flow is computed in: the box around the
    pixels of ``masks`` (those of frames ``i`` and ``i - 1``: where frame i's person is
    and where its pixels move to), grown by ``margin_px + margin_frac`` times the box's
    longer side on every side (context for the flow's patches and its coarse levels),
    at least :data:`MIN_REGION` pixels on a side, clipped to the image.

    Args:
        masks: ``(H, W)`` bool arrays of equal shape (None entries are skipped).
        margin_px: pixels; margin_frac: fraction of the box's longer side.

    Returns:
        ``(row0, row1, col0, col1)`` (rows ``[row0, row1)``, columns ``[col0, col1)``), or
        None when no mask has a pixel (the caller computes the whole frame).
    """
    union = None
    for m in masks:
        if m is None:
            continue
        m = np.asarray(m, bool)
        if union is not None and m.shape != union.shape:
            raise InputError(f"masks of different sizes: {union.shape} and {m.shape}")
        union = m.copy() if union is None else union | m
    if union is None or not union.any():
        return None
    H, W = union.shape
    rows = np.flatnonzero(union.any(1))
    cols = np.flatnonzero(union.any(0))
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    grow = int(margin_px + margin_frac * max(r1 - r0, c1 - c0))
    r0, r1, c0, c1 = r0 - grow, r1 + grow, c0 - grow, c1 + grow
    for lo, hi, n in ((0, 1, H), (2, 3, W)):  # at least MIN_REGION (or the image) on a side
        box = [r0, r1, c0, c1]
        short = min(MIN_REGION, n) - (box[hi] - box[lo])
        if short > 0:
            box[lo] -= short // 2
            box[hi] += short - short // 2
        box[lo], box[hi] = max(box[lo], 0), min(box[hi], n)
        if box[hi] - box[lo] < min(MIN_REGION, n):  # pushed against an edge: grow inwards
            box[lo], box[hi] = (0, min(MIN_REGION, n)) if box[lo] == 0 else (n - min(MIN_REGION, n), n)
        r0, r1, c0, c1 = box
    return r0, r1, c0, c1


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
    flows computed with different settings never mix; a flow computed in a region of the
    frames (:meth:`flow` with ``region``) stores its region and is used only for it (a
    whole-frame flow serves any region).

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

    def get(self, index: int, shape: tuple[int, int] | None = None, region: tuple | None = None) -> np.ndarray | None:
        """The cached flow of frame ``index``, or None if absent or unreadable.

        Args:
            index: frame number i (the flow is ``F_o(i, i-1)``).
            shape: optional ``(H, W)`` the flow must have; a cached flow of another size
                counts as absent.
            region: the region the flow is asked for (None: the whole frame): a flow
                computed in another region counts as absent; one of the whole frame
                (e.g. a true flow put here) serves every region.

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
                stored = tuple(int(v) for v in data["region"]) if "region" in data.files else None
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError):
            return None
        if flow.ndim != 3 or flow.shape[2] != 2 or (shape is not None and flow.shape[:2] != tuple(shape)):
            return None
        if stored is not None and stored != (None if region is None else tuple(int(v) for v in region)):
            return None
        return flow

    def put(self, index: int, flow: np.ndarray, region: tuple | None = None) -> Path:
        """Store the flow of frame ``index`` atomically (with the ``region`` it was
        computed in, None: the whole frame); returns the file path.

        Args:
            index: frame number i (the flow is ``F_o(i, i-1)``).
            flow: ``(H, W, 2)`` backward flow in pixels (stored as float32).
            region: ``(row0, row1, col0, col1)`` pixels, or None.

        Raises:
            InputError: ``flow`` is not ``(H, W, 2)``.
        """
        flow = np.asarray(flow, dtype=np.float32)
        if flow.ndim != 3 or flow.shape[2] != 2:
            raise InputError(f"flow must have shape (H, W, 2), got {flow.shape}")
        p = self.path(index)
        extra = {} if region is None else {"region": np.asarray(region, np.int64)}

        def write(tmp):
            with open(tmp, "wb") as fh:
                fh.write(_npz_bytes(flow=flow, **extra))

        atomic_write(p, write)
        return p

    def flow(self, index: int, frame_cur: Any, frame_prev: Any, region: tuple | None = None) -> np.ndarray:
        """The flow of frame ``index`` from the cache, computing and storing it if absent.

        Args:
            index: frame number i.
            frame_cur, frame_prev: ``(H, W, 3)`` uint8 RGB frames i and i-1.
            region: ``(row0, row1, col0, col1)`` (:func:`flow_region`): compute the flow
                of that part of both frames only and give 0 elsewhere (the person's
                flow at a fraction of the cost; cached apart from whole-frame flows).

        Returns:
            ``(H, W, 2)`` float32 backward flow, see :func:`observed_flow`.
        """
        shape = np.shape(frame_cur)[:2]
        if region is not None:
            r0, r1, c0, c1 = (int(v) for v in region)
            if not (0 <= r0 < r1 <= shape[0] and 0 <= c0 < c1 <= shape[1]):
                raise InputError(f"region {tuple(region)} is not a box inside the {shape[1]}x{shape[0]} frame")
            region = (r0, r1, c0, c1)
        cached = self.get(index, shape=shape, region=region)
        if cached is not None:
            return cached
        if region is None:
            flow = observed_flow(frame_cur, frame_prev, self.method, **self.options)
        else:
            cur, prev = np.asarray(frame_cur), np.asarray(frame_prev)
            if cur.shape != prev.shape:  # observed_flow says why
                observed_flow(cur, prev, self.method, **self.options)
            flow = np.zeros(shape + (2,), np.float32)
            flow[r0:r1, c0:c1] = observed_flow(np.ascontiguousarray(cur[r0:r1, c0:c1]),
                                               np.ascontiguousarray(prev[r0:r1, c0:c1]), self.method, **self.options)
        if self.folder is not None:
            self.put(index, flow, region=region)
        return flow
