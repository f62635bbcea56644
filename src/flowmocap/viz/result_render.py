"""Pictures and videos of a result folder (``flowmocap render``).

:class:`ResultScene` opens a result together with its input video (or sequence folder)
and body model; the functions below make the outputs:

- :func:`overlay_video`: the fitted body, shaded and semi-transparent, over every
  tracked frame, optionally beside a view from a camera orbited 90 degrees (MP4).
- :func:`figure1`: the paper's Fig. 1 for chosen frames: input frame, colour-coded
  observed flow ``F_o(i, i-1)``, rendered flow ``F_r(i, i-1)`` of the fitted model,
  the resulting pose, and the colour key.
- :func:`joint_traces`: the paper's Fig. 3: the fitted pose with the history of the 13
  evaluated joints drawn in green (ground truth in orange when the input has it).
- :func:`energy_figure`: per-frame energies and, with ground truth, the 3D joint error.
- :func:`people_overlay_video`: several results of one input (``track --person all``),
  every person's body in its own colour over the frames any of them was tracked in.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flowmocap.errors import DataError, InputError
from flowmocap.viz.flow_colors import color_wheel_legend, flow_to_color
from flowmocap.viz.flow_figure import caption_tile, crop_box
from flowmocap.viz.overlay import PEOPLE_RGB, framing_side_camera, overlay_bodies, overlay_body, render_body_view
from flowmocap.viz.traces import GT_TRACE_RGB, TRACE_RGB, draw_traces, trace_box

__all__ = ["ResultScene", "overlay_video", "people_overlay_video", "figure1", "joint_traces", "energy_figure",
           "default_frames"]

_INK = (30, 30, 30)


def _open_input(path: Path, camera):
    from flowmocap.io.sequence import load_sequence
    from flowmocap.io.video import VIDEO_SUFFIXES, load_video

    if path.is_file() or path.suffix.lower() in VIDEO_SUFFIXES:
        # a video tracked at a reduced size (track --max-size) is decoded at that size again
        return load_video(path, max_side=max(camera.width, camera.height))
    return load_sequence(path, max_side=max(camera.width, camera.height))  # a folder tracked at a reduced size


class ResultScene:
    """A result folder with its input frames and body model, in the result's world frame.

    Args:
        result_dir: the result folder (``motion.npz``, ``run.json``).
        input: the input video or sequence folder (default: ``run.json``'s ``"input"``,
            also tried relative to the result folder's parent).
        model: body model override (default: the one recorded in ``run.json``).

    Attributes:
        motion: :class:`~flowmocap.export.motion.FittedMotion` (world frame).
        arrays: the raw ``motion.npz`` arrays.
        camera: the result's camera. seq: the input sequence.
        gt: ground-truth arrays of a synthetic sequence (``{}`` when absent).

    Raises:
        DataError: not a result folder, input not found, or frames of another size.
    """

    def __init__(self, result_dir: str | Path, input: str | Path | None = None, model=None):
        from flowmocap.export.motion import load_fitted_motion
        from flowmocap.io.results import read_result
        from flowmocap.render import prepare_faces

        self.result_dir = Path(result_dir)
        self._model = model
        self.motion = load_fitted_motion(self.result_dir, frame="world", model=model)
        self.arrays, self.run = read_result(self.result_dir)
        self.camera = self.motion.camera
        source = self._find_input(input)
        #: whether the input's content differs from the one tracked (``run.json``'s fingerprint):
        #: the overlay is then drawn on other frames of the same size and length
        self.input_differs = self._differs(source)
        self.seq = _open_input(source, self.camera)
        from flowmocap.io.results import decoded_otherwise_words

        #: a note where the input's frames are now shown otherwise than when tracked (mirrored, pixel aspect)
        self.decoded_otherwise = decoded_otherwise_words(self.run, getattr(self.seq, "meta", {}) or {}, source)
        if tuple(self.seq.size) != (self.camera.width, self.camera.height):
            raise DataError(f"the input frames are {self.seq.size[0]}x{self.seq.size[1]} but the result's camera "
                            f"is {self.camera.width}x{self.camera.height}; pass the input that was tracked.")
        n = len(self.seq)
        if self.motion.frame_index.max() >= n:
            raise DataError(f"the result has frame {int(self.motion.frame_index.max())} but the input has {n} "
                            "frames; pass the input that was tracked (--input).")
        self.gt = getattr(self.seq, "gt", {}) or {}
        if "joints3d" in self.gt and len(self.gt["joints3d"]) != n:
            self.gt = {}
        self.faces = prepare_faces(self.motion.model.faces_np)
        self._verts: dict[int, np.ndarray] = {}

    def _differs(self, source: Path) -> bool:
        """Whether ``source``'s content digest differs from the tracked input's (False where the
        result records none)."""
        from flowmocap.io.fingerprint import digest_input

        recorded = (self.run.get("fingerprint") or {}).get("input")
        return bool(recorded) and digest_input(source) != recorded

    def _find_input(self, given) -> Path:
        if given is not None:
            p = Path(given)
            if not p.exists():
                raise DataError(f"input {p} does not exist.")
            return p
        recorded = self.run.get("input")
        if not recorded:
            raise DataError(f"{self.result_dir / 'run.json'} records no input; pass --input VIDEO_OR_FOLDER.")
        for p in (Path(recorded), self.result_dir.parent / recorded, self.result_dir.parent / Path(recorded).name):
            if p.exists():
                return p
        raise DataError(f"the tracked input {recorded} is not found (moved?); pass --input VIDEO_OR_FOLDER.")

    @property
    def num_frames(self) -> int:
        """Number of frames T of the result."""
        return self.motion.num_frames

    def k_of(self, frame: int) -> int:
        """Row of the result that holds input frame number ``frame``."""
        hits = np.flatnonzero(self.motion.frame_index == int(frame))
        if hits.size == 0:
            fi = self.motion.frame_index
            raise InputError(f"frame {frame} was not tracked; the result has frames {int(fi.min())}..{int(fi.max())}.")
        return int(hits[0])

    def vertices(self, k: int, chunk: int = 32) -> np.ndarray:
        """``(V, 3)`` float64 world vertices of result row ``k``, metres."""
        if k not in self._verts:
            if len(self._verts) > 4 * chunk:
                self._verts.clear()
            s = (k // chunk) * chunk
            verts, _ = self.motion.body(s, s + chunk)
            for i, v in enumerate(verts):
                self._verts[s + i] = v
        return self._verts[k]

    def side_view(self, angle_deg: float = 90.0) -> tuple:
        """The motion seen from the side: ``(motion, camera)``, the motion in the ``"up"`` export
        frame (:func:`~flowmocap.export.motion.load_fitted_motion`: where the camera turned,
        zoomed or was carried, that undone, so the body moves as in the world, not as in the
        camera's view) and :func:`~flowmocap.viz.overlay.framing_side_camera` orbited
        ``angle_deg`` from the first frame's camera about the middle of the whole path, far
        enough back to keep every frame's body in view."""
        from flowmocap.export.motion import load_fitted_motion

        motion = load_fitted_motion(self.result_dir, frame="up", model=self._model, cache_world=False)
        T = motion.num_frames
        rows = np.unique(np.linspace(0, T - 1, min(T, 32)).round().astype(int))
        some = np.concatenate([motion.body(int(r), int(r) + 1)[0][0][::10] for r in rows])  # the body's extent
        points = np.concatenate([motion.joints().reshape(-1, 3), some])
        return motion, framing_side_camera(motion.camera, points, angle_deg)

    def image(self, k: int) -> np.ndarray:
        """``(H, W, 3)`` uint8 RGB input frame of result row ``k``."""
        return self.seq.frame(int(self.motion.frame_index[k]))

    def joints2d(self) -> np.ndarray:
        """``(T, 24, 2)`` fitted joints projected into the input, pixels."""
        return self.camera.project(self.motion.joints())

    def gt_joints2d(self) -> np.ndarray | None:
        """``(T, 24, 2)`` ground-truth joints of the tracked frames, pixels, or None."""
        if "joints2d" not in self.gt:
            return None
        return np.asarray(self.gt["joints2d"], np.float64)[self.motion.frame_index]

    def silhouette(self, k: int) -> np.ndarray:
        """``(H, W)`` bool: the fitted body's pixels at row ``k``."""
        from flowmocap.render import body_mask

        v = self.vertices(k)
        return body_mask(self.camera.project(v), self.camera.depth(v), self.faces, self.camera.height, self.camera.width)

    def observed_flow(self, k: int) -> np.ndarray:
        """``(H, W, 2)`` float32 observed backward flow ``F_o(i, i-1)`` of row ``k``'s frame ``i``,
        pixels: from the result's flow cache, else computed with the tracked flow method."""
        from flowmocap.vision.flow import FlowCache, observed_flow

        i = int(self.motion.frame_index[k])
        if i < 1:
            raise InputError("frame 0 has no previous frame, so no flow; choose a later frame.")
        method = str((self.run.get("config") or {}).get("flow_method", "dis"))
        cache_dir = self.result_dir / "flow_cache"
        if cache_dir.is_dir():
            flow = FlowCache(cache_dir, method=method).get(i, (self.camera.height, self.camera.width))
            if flow is not None:
                return flow
        return observed_flow(self.seq.frame(i), self.seq.frame(i - 1), method=method)

    def rendered_flow(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Rendered backward flow ``F_r(i, i-1)`` of the fitted model between rows ``k - 1``
        and ``k``: ``flow (H, W, 2)`` float32 pixels and ``mask (H, W)`` bool."""
        from flowmocap.render import rasterize, render_flow

        if k < 1 or self.motion.frame_index[k - 1] != self.motion.frame_index[k] - 1:
            raise InputError(f"frame {int(self.motion.frame_index[k])} needs the previous frame in the result; "
                             "choose a later frame.")
        cam = self.camera
        vc, vp = self.vertices(k), self.vertices(k - 1)
        pc, pp = cam.project(vc), cam.project(vp)
        raster = rasterize(pc, cam.depth(vc), self.faces, cam.height, cam.width)
        return render_flow(raster, pc, pp, self.faces)

    def errors_cm(self) -> dict | None:
        """Per-frame 3D joint errors against ground truth in cm (``{"local Procrustes",
        "global Procrustes", "MPJPE"}: (T,)``), or None without ground truth."""
        from flowmocap.eval.metrics import global_procrustes_error, local_procrustes_error, mpjpe

        if "joints3d" not in self.gt:
            return None
        ref = np.asarray(self.gt["joints3d"], np.float64)[self.motion.frame_index]
        pred = self.motion.joints()
        return {"local Procrustes": 100 * local_procrustes_error(pred, ref),
                "global Procrustes": 100 * global_procrustes_error(pred, ref),
                "MPJPE": 100 * mpjpe(pred, ref)}


def default_frames(scene: ResultScene, count: int = 4, first: int = 1) -> list[int]:
    """``count`` input frame numbers spread evenly over the result, from row ``first`` on."""
    fi = scene.motion.frame_index
    rows = np.unique(np.linspace(min(first, len(fi) - 1), len(fi) - 1, count).round().astype(int))
    return [int(fi[r]) for r in rows]


def overlay_video(scene: ResultScene, path: str | Path, alpha: float = 0.6, side: bool = False,
                  progress: bool = True) -> Path:
    """Write the body-over-video MP4: one video frame per tracked frame, the input's size
    (twice as wide with ``side``, on the right: the body as it moves in the world, the
    camera's own turns, zoom and moves undone, seen from a camera orbited 90 degrees about
    the middle of its path and far enough back to keep it in view, :meth:`ResultScene.side_view`). Where the result has the 3D sources' disagreement,
    the frames to review (:func:`~flowmocap.fit.disagreement.review_frames`) get a red frame
    and a caption with the frame's value; frames the person was tracked through without being
    seen (``run.json``'s ``gaps``) say so at the top left.

    Args:
        scene: the result.
        path: output ``.mp4``.
        alpha: body opacity in ``[0, 1]``.
        side: add the side view.
        progress: show a progress bar.

    Returns:
        The path written.
    """
    from tqdm import tqdm

    from flowmocap.viz.video import VideoWriter

    from flowmocap.fit.disagreement import review_frames

    side_motion, cam2 = scene.side_view() if side else (None, None)
    side_verts: dict[int, np.ndarray] = {}

    def side_vertices(k, chunk=32):
        if k not in side_verts:
            side_verts.clear()
            s = (k // chunk) * chunk
            side_verts.update((s + i, v) for i, v in enumerate(side_motion.body(s, s + chunk)[0]))
        return side_verts[k]

    review = review_frames(scene.arrays["disagreement"]) if "disagreement" in scene.arrays else None
    from flowmocap.io.results import UNSEEN_WORDS, unseen_frames

    # frames the person was tracked through without being seen (run.json's gaps): said so, and how
    unseen = {i: UNSEEN_WORDS[how] for i, how in unseen_frames(scene.run).items()}
    with VideoWriter(path, scene.motion.fps) as out:
        for k in tqdm(range(scene.num_frames), disable=not progress, unit="frame", desc="overlay video"):
            v = scene.vertices(k)
            img = overlay_body(scene.image(k), v, scene.faces, scene.camera, alpha=alpha)
            if int(scene.motion.frame_index[k]) in unseen:
                img = np.ascontiguousarray(img)
                scale = max(0.35, min(0.6, img.shape[0] / 800))
                _outlined(img, "not seen: " + unseen[int(scene.motion.frame_index[k])], int(6 + 30 * scale), scale,
                          (255, 255, 255))
            if review is not None and review[1][k]:
                img = _flag(img, f"review: 3D sources part {100 * review[0][k]:.0f} cm")
            if cam2 is not None:
                img = np.concatenate([img, _label(render_body_view(side_vertices(k), scene.faces, cam2), "side view")],
                                     axis=1)
            out.write(img)
    return Path(path)


def people_overlay_video(scenes: list[ResultScene], path: str | Path, names: list[str] | None = None,
                         alpha: float = 0.6, progress: bool = True) -> Path:
    """Write one MP4 with every person's fitted body over the input, each in its own colour
    (:data:`~flowmocap.viz.overlay.PEOPLE_RGB` in the scenes' order) and named in a key at
    the top left (grey where that person's result has no such frame; "not seen" where it was
    tracked through the frame by flow alone or held, run.json's ``gaps``). A frame that is one of a
    person's frames to review (:func:`~flowmocap.fit.disagreement.review_frames`) gets a red
    frame and a caption naming whose and their value. Where bodies overlap, the
    one nearer the camera is drawn, at the depths the scenes' motions give: each fit's own,
    which one camera leaves uncertain (a body's size and distance trade), unless the caller
    stood them on one floor first (``flowmocap render`` does,
    :func:`flowmocap.export.floor.people_floor`).

    Args:
        scenes: the results of one input (e.g. ``DIR/person0``, ``DIR/person1`` of ``track
            --person all``), with the same camera intrinsics and frame size.
        path: output ``.mp4``.
        names: one label per scene (default ``person0``, ``person1``, ...).
        alpha: body opacity in ``[0, 1]``.
        progress: show a progress bar.

    Returns:
        The path written: one video frame per input frame from the first to the last that
        any scene tracked (frames none tracked show the input alone), at the first scene's
        frame rate.

    Raises:
        DataError: no scenes, or scenes of differently sized frames or cameras.
    """
    from tqdm import tqdm

    from flowmocap.viz.video import VideoWriter

    if not scenes:
        raise DataError("no results to draw.")
    names = [f"person{k}" for k in range(len(scenes))] if names is None else list(names)
    if len(names) != len(scenes):
        raise InputError(f"one name per result: {len(scenes)} results, {len(names)} names.")
    ref = scenes[0].camera
    for sc, name in zip(scenes[1:], names[1:]):
        c = sc.camera
        if (c.width, c.height, c.fx, c.fy, c.cx, c.cy) != (ref.width, ref.height, ref.fx, ref.fy, ref.cx, ref.cy):
            raise DataError(f"{name}'s camera ({c.width}x{c.height} px, focal {c.fx:g}) is not "
                            f"{names[0]}'s ({ref.width}x{ref.height} px, focal {ref.fx:g}): draw results of one "
                            "input tracked at one size.")
    colours = [PEOPLE_RGB[k % len(PEOPLE_RGB)] for k in range(len(scenes))]
    first = min(int(sc.motion.frame_index.min()) for sc in scenes)
    last = max(int(sc.motion.frame_index.max()) for sc in scenes)
    rows = [{int(i): k for k, i in enumerate(sc.motion.frame_index)} for sc in scenes]
    # frames a person was tracked through without being seen (by flow alone): their name says so
    from flowmocap.io.results import UNSEEN_WORDS, unseen_frames

    unseen = [{i: UNSEEN_WORDS[how] for i, how in unseen_frames(sc.run).items()} for sc in scenes]
    # each person's frames to review (the 3D sources part most), by input frame: {frame: metres}
    from flowmocap.fit.disagreement import review_frames

    review = []
    for sc in scenes:
        got = review_frames(sc.arrays["disagreement"]) if "disagreement" in sc.arrays else None
        review.append({} if got is None else {int(sc.motion.frame_index[r]): float(got[0][r])
                                               for r in np.flatnonzero(got[1])})
    R0, t0 = np.asarray(ref.R, np.float64), np.asarray(ref.t, np.float64)

    def in_ref_world(sc: ResultScene, v: np.ndarray) -> np.ndarray:
        """A body in ``sc``'s world frame, moved into the first scene's world frame (through
        the camera, which all the scenes share)."""
        return (sc.camera.to_camera(v) - t0) @ R0

    with VideoWriter(path, scenes[0].motion.fps) as out:
        for i in tqdm(range(first, last + 1), disable=not progress, unit="frame", desc="people overlay video"):
            bodies, cols, present = [], [], []
            for sc, row, col, name in zip(scenes, rows, colours, names):
                if i in row:
                    bodies.append((in_ref_world(sc, sc.vertices(row[i])), sc.motion.model.faces_np))
                    cols.append(col)
                    present.append(name)
            img = overlay_bodies(scenes[0].seq.frame(i), bodies, ref, alpha=alpha, colours=cols)
            flagged = [(name, r[i]) for name, r in zip(names, review) if name in present and i in r]
            if flagged:
                img = _flag(img, "review: " + ", ".join(f"{name}'s 3D sources part {100 * d:.0f} cm"
                                                        for name, d in flagged))
            scale = max(0.35, min(0.6, img.shape[0] / 800))
            y = int(6 + 30 * scale)
            for name, col, gaps in zip(names, colours, unseen):
                ink = tuple(int(255 * c) for c in col) if name in present else (150, 150, 150)
                _outlined(img, name + (f" (not seen: {gaps[i]})" if name in present and i in gaps else ""), y, scale, ink)
                y += int(28 * scale) + 4
            out.write(img)
    return Path(path)


#: RGB of the frame drawn round a video frame to review
REVIEW_RGB = (230, 40, 40)


def _outlined(img: np.ndarray, text: str, y: int, scale: float, ink: tuple) -> None:
    """``text`` at the left of ``img`` (in place), baseline ``y`` px, in ``ink`` (RGB) outlined black."""
    import cv2

    cv2.putText(img, text, (7, y + 1), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 2, cv2.LINE_AA)
    cv2.putText(img, text, (6, y), cv2.FONT_HERSHEY_SIMPLEX, scale, ink, 1, cv2.LINE_AA)


def _flag(img: np.ndarray, text: str) -> np.ndarray:
    """``img`` with a red frame round it and ``text`` at the bottom left, white on red."""
    import cv2

    img = np.ascontiguousarray(img)
    t = max(2, round(min(img.shape[:2]) / 120))
    cv2.rectangle(img, (t // 2, t // 2), (img.shape[1] - 1 - t // 2, img.shape[0] - 1 - t // 2), REVIEW_RGB, t)
    scale = max(0.35, min(0.7, img.shape[0] / 700))
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    x, y = t, img.shape[0] - t - base - 4
    cv2.rectangle(img, (x, y - h - 4), (x + w + 8, img.shape[0] - t), REVIEW_RGB, -1)
    cv2.putText(img, text, (x + 4, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def _label(img: np.ndarray, text: str) -> np.ndarray:
    import cv2

    scale = max(0.3, min(0.6, img.shape[0] / 800))
    cv2.putText(img, text, (6, int(6 + 30 * scale)), cv2.FONT_HERSHEY_SIMPLEX, scale, _INK, 1, cv2.LINE_AA)
    return img


def _key_tile(h: int, max_mag: float) -> np.ndarray:
    import cv2

    w = max(110, h // 2)
    key = np.full((h, w, 3), 255, np.uint8)
    d = max(8, min(w - 16, h // 2))
    y0 = max(0, (h - d) // 2 - 8)
    key[y0:y0 + d, (w - d) // 2:(w - d) // 2 + d] = color_wheel_legend(d)
    cv2.putText(key, f"rim: {max_mag:g} px", (6, min(h - 4, y0 + d + 18)), cv2.FONT_HERSHEY_SIMPLEX, 0.42,
                _INK, 1, cv2.LINE_AA)
    return key


def _row(tiles: list[np.ndarray], gap: int = 6) -> np.ndarray:
    h = max(t.shape[0] for t in tiles)
    out = []
    for n, t in enumerate(tiles):
        if t.shape[0] < h:
            t = np.concatenate([t, np.full((h - t.shape[0], t.shape[1], 3), 255, np.uint8)], axis=0)
        if n:
            out.append(np.full((h, gap, 3), 255, np.uint8))
        out.append(t)
    return np.concatenate(out, axis=1)


def _column(rows: list[np.ndarray], gap: int = 6) -> np.ndarray:
    w = max(r.shape[1] for r in rows)
    out = []
    for n, r in enumerate(rows):
        if r.shape[1] < w:
            r = np.concatenate([r, np.full((r.shape[0], w - r.shape[1], 3), 255, np.uint8)], axis=1)
        if n:
            out.append(np.full((gap, w, 3), 255, np.uint8))
        out.append(r)
    return np.concatenate(out, axis=0)


def _upscale(img: np.ndarray, min_height: int) -> np.ndarray:
    import cv2

    if img.shape[0] >= min_height:
        return img
    f = int(np.ceil(min_height / img.shape[0]))
    return cv2.resize(img, (img.shape[1] * f, img.shape[0] * f), interpolation=cv2.INTER_NEAREST)


def figure1(scene: ResultScene, frames: list[int], crop: bool = True, alpha: float = 0.75,
            min_height: int = 160) -> np.ndarray:
    """The paper's Fig. 1 for each of ``frames`` (one row each): frame ``i`` | observed flow
    ``F_o(i, i-1)`` | rendered flow ``F_r(i, i-1)`` of the fit | resulting pose | colour key.

    Both flows of a row share one colour scale: the 99th percentile of the rendered flow's
    length on the body, rounded up to whole pixels (the key's rim). The caption gives the
    mean end-point error between the two on the body.

    Args:
        scene: the result.
        frames: input frame numbers (each tracked, with its previous frame tracked too).
        crop: crop the tiles to the body.
        alpha: body opacity in the pose tile.
        min_height: tiles smaller than this (pixels) are enlarged by a whole factor.

    Returns:
        ``(h, w, 3)`` uint8 RGB image.
    """
    if not frames:
        raise InputError("figure1 needs at least one frame number.")
    rows = []
    for i in frames:
        k = scene.k_of(i)
        ren, mask = scene.rendered_flow(k)
        obs = scene.observed_flow(k)
        lengths = np.linalg.norm(ren[mask], axis=1)
        max_mag = float(max(1.0, np.ceil(np.percentile(lengths, 99)))) if lengths.size else 1.0
        epe = float(np.linalg.norm(obs[mask] - ren[mask], axis=1).mean()) if lengths.size else float("nan")
        r0, r1, c0, c1 = crop_box(mask) if crop else (0, mask.shape[0], 0, mask.shape[1])
        img = scene.image(k)
        pose = overlay_body(img, scene.vertices(k), scene.faces, scene.camera, alpha=alpha)
        up = lambda a: _upscale(a[r0:r1, c0:c1], min_height)  # noqa: E731
        tiles = [
            caption_tile(up(img), [f"input frame {i}"]),
            caption_tile(up(flow_to_color(obs, max_mag)), [f"observed flow F_o({i}, {i - 1})"]),
            caption_tile(up(flow_to_color(ren, max_mag)), [f"rendered flow, EPE {epe:.2f} px"]),
            caption_tile(up(pose), ["resulting pose"]),
        ]
        tiles.append(caption_tile(_key_tile(tiles[0].shape[0] - 26, max_mag), ["colour key"]))
        rows.append(_row(tiles))
    return _column(rows)


def joint_traces(scene: ResultScene, frames: list[int], history: int | None = None, alpha: float = 0.5,
                 with_gt: bool = True, min_height: int = 200) -> np.ndarray:
    """The paper's Fig. 3: for each of ``frames``, the fitted pose over the input with the
    traces of the 13 evaluated joints (green) from the first tracked frame (or ``history``
    frames back); ground-truth traces in orange when the input has them and ``with_gt``.

    All panels share one crop that holds every trace and the body.

    Returns:
        ``(h, w, 3)`` uint8 RGB image, one panel per frame, left to right.
    """
    if not frames:
        raise InputError("joint_traces needs at least one frame number.")
    if history is not None and history < 0:
        raise InputError(f"the joint history must be a number of frames >= 0 (--history); got {history}.")
    j2d = scene.joints2d()
    gt2d = scene.gt_joints2d() if with_gt else None
    ks = [scene.k_of(i) for i in frames]
    masks = [scene.silhouette(k) for k in ks]
    lo = 0 if history is None else max(0, min(ks) - int(history))
    span = slice(lo, max(ks) + 1)
    r0, r1, c0, c1 = trace_box(j2d[span], scene.seq.size, masks=masks)
    f = max(1, int(np.ceil(min_height / max(r1 - r0, 1))))
    to_tile = lambda j: (j - np.array([c0, r0], np.float64)) * f  # noqa: E731  (crop, then enlarge)
    panels = []
    for i, k in zip(frames, ks):
        img = overlay_body(scene.image(k), scene.vertices(k), scene.faces, scene.camera, alpha=alpha)
        img = _upscale(img[r0:r1, c0:c1], (r1 - r0) * f)
        if gt2d is not None:
            img = draw_traces(img, to_tile(gt2d), k, history, colour=GT_TRACE_RGB, thickness=1, dots=False)
        img = draw_traces(img, to_tile(j2d), k, history, colour=TRACE_RGB, thickness=2)
        panels.append(caption_tile(img, [f"frame {i}"]))
    legend = "green: fitted joints" + ("; orange: ground truth" if gt2d is not None else "")
    row = _row(panels)
    return caption_tile(row, [f"history of the 13 evaluated joints ({legend})"])


def energy_figure(scene: ResultScene) -> np.ndarray:
    """Per-frame energy terms, the 3D sources' disagreement (where the result has it) and
    (with ground truth) 3D joint errors as an RGB image, see
    :func:`flowmocap.viz.plots.energy_error_plot`.

    Returns:
        ``(h, w, 3)`` uint8 RGB image of the figure.

    Raises:
        DataError: ``motion.npz`` has no energies.
    """
    from flowmocap.viz.plots import energy_error_plot

    a = scene.arrays
    if "energies" not in a or "energy_names" not in a:
        raise DataError(f"{scene.result_dir / 'motion.npz'} has no energies to plot.")
    errors = scene.errors_cm()
    return energy_error_plot(scene.motion.frame_index, a["energies"], a["energy_names"], errors,
                             title=f"{scene.result_dir.name}: per-frame energies"
                             + (" and 3D joint error" if errors else ""), disagreement=a.get("disagreement"))
