"""The tracking pipeline: from a video, a frames folder or a sequence folder to a result
folder. :func:`track` is the one entry the command line, the benchmarks and the demo call.

What it does, in order: read the input (a video is decoded and scaled; a sequence folder
brings its frames, masks and camera); choose the camera; run the person detector
(MediaPipe) when the masks or the initialisation are automatic; choose the settings
profile (``video`` for the detector's masks, ``synthetic`` for exact ones); initialise on
the first usable frame (the paper's three steps); track frame by frame, re-initialising
from the detector where the fit loses the person; and write ``motion.npz`` and
``run.json`` after every frame, so an interrupted run keeps what it finished and
``resume=True`` continues it exactly.
"""

from __future__ import annotations

import contextlib
import glob
import json
import math
import os
import platform
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from flowmocap.body import BodyModel, load_body_model
from flowmocap.body.stature import check_height, stature, with_stature
from flowmocap.errors import DataError, InputError, ModelFileError, NoPersonError, OutputError
from flowmocap.fit.config import FAST_SETTINGS, NETWORK_SETTINGS, PROFILES, TrackerConfig
from flowmocap.fit.init import InitSpec, initialise, parse_init
from flowmocap.export.world import WORLD_FILE
from flowmocap.fit.objective import (
    ENERGY_NAMES,
    FrameState,
    Scene,
    configured_keypoints,
    frame_data,
)
from flowmocap.fit.reinit import ReinitMonitor
from flowmocap.fit.smooth import depth_smoothed_motion, pose_smoothed_motion
from flowmocap.fit.tracker import FrameResult, KnownStart, SequenceTracker, track_frames
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.io.fingerprint import (
    differing,
    digest_arrays,
    digest_input,
    digest_model,
    digest_value,
)
from flowmocap.io.lock import FolderLock
from flowmocap.io.results import (
    PEOPLE_MANIFEST,
    RENDER_OUTPUTS,
    RESULT_FILES,
    FrameLog,
    has_result,
    is_result_folder,
    json_default,
    read_result,
    result_folder,
    write_json,
    write_motion,
    write_run,
)
from flowmocap.io.sequence import DEFAULT_FPS, Sequence, check_fps, check_max_side, load_sequence, read_image
from flowmocap.io.video import VIDEO_SUFFIXES, cut_short_words, default_camera, load_video
from flowmocap.synth import read_camera_json
from flowmocap.version import __version__
from flowmocap.vision import FlowCache, flow_region
from flowmocap.vision.auto import (
    PersonTrack,
    auto_init,
    detect_for_given_masks,
    detect_joints3d,
    detect_sequence,
    first_person_frame,
    frame_runs,
    load_detections,
)
from flowmocap.vision.detect import check_model
from flowmocap.vision.lifter import lifted_track
from flowmocap.vision.person import describe_person, parse_person

__all__ = ["Result", "load_result", "parse_frame_range", "read_init", "track"]


@dataclass(eq=False)  # dicts of arrays have no truth value: == is identity (compare the arrays themselves)
class Result:
    """A result folder: ``motion`` (the arrays of ``motion.npz``), ``run`` (``run.json``:
    settings, profile, camera, timings, events) and its ``path``."""

    path: Path
    motion: dict
    run: dict

    @property
    def poses(self) -> np.ndarray:
        """``(T, 72)`` axis-angle per SMPL joint, radians (joint 0: global orientation)."""
        return self.motion["poses"]

    @property
    def trans(self) -> np.ndarray:
        """``(T, 3)`` root translation, metres, in the camera's world frame."""
        return self.motion["trans"]

    @property
    def betas(self) -> np.ndarray:
        """``(10,)`` shape coefficients of the body model."""
        return self.motion["betas"]

    @property
    def joints3d(self) -> np.ndarray:
        """``(T, 24, 3)`` joint positions, metres, in the camera's world frame (as :attr:`trans`:
        the camera's own frame for a video; the frame of ``camera.json``'s ``R``, ``t`` where one
        was given)."""
        return self.motion["joints3d"]

    @property
    def joints2d(self) -> np.ndarray:
        """``(T, 24, 2)`` projected joints, pixels of the tracked frames (:attr:`camera`'s: a
        video scaled by ``max_size`` was tracked at that size: divide x and y by ``input.json``'s
        ``video.scale_xy`` for the video's own pixels, as shown)."""
        return self.motion["joints2d"]

    @property
    def disagreement(self) -> np.ndarray | None:
        """``(T, 24)`` metres, or None (no lifter refit ran): per frame and joint, how far
        the run's three 3D sources (the fit, the keypoint lifter, the detector's own 3D) part
        (:func:`~flowmocap.fit.disagreement.source_disagreement`); NaN outside the 13 scored
        joints and where fewer than two sources give one. Large values flag joints to
        review; it is a ranking, not a calibrated error."""
        return self.motion.get("disagreement")

    @property
    def frame_index(self) -> np.ndarray:
        """``(T,)`` the input's frame numbers of the rows."""
        return self.motion["frame_index"]

    @property
    def fps(self) -> float:
        """Frames per second of the tracked input, as recorded in ``motion.npz``."""
        return float(self.motion["fps"])

    @property
    def gender(self) -> str:
        """The body model's gender: ``neutral``, ``male`` or ``female``."""
        return str(self.motion["gender"])

    @property
    def camera(self) -> PinholeCamera:
        """The camera the result was tracked with (pixels of the tracked frames, after any
        ``max_size`` scaling; OpenCV axes, the result's frame)."""
        return PinholeCamera.from_dict(json.loads(str(self.motion["camera"])))

    @property
    def energies(self) -> dict[str, np.ndarray]:
        """Each energy term at the result, ``{name: (T,)}`` (NaN where a term was off)."""
        names = [str(n) for n in self.motion["energy_names"]]
        return {n: self.motion["energies"][:, k] for k, n in enumerate(names)}

    @property
    def events(self) -> list[dict]:
        """What happened on the way (re-initialisations, empty masks, retries)."""
        return self.run.get("events", [])

    def __len__(self) -> int:
        return len(self.poses)

    def __repr__(self) -> str:
        f = self.frame_index
        span = f"frames {int(f[0])}..{int(f[-1])}" if len(f) else "no frames"
        return f"Result({str(self.path)!r}, {span}, status {self.run.get('status')!r})"


def load_result(path: str | Path) -> Result:
    """Read a result folder written by :func:`track` (its path, or a :class:`Result` to read
    again).

    Raises:
        InputError: ``path`` is not a path.
        DataError: the folder holds no (readable) result.
    """
    path = result_folder(path)
    motion, run = read_result(path)
    return Result(path, motion, run)


def parse_frame_range(frames: str | tuple | None, n: int) -> tuple[int, int]:
    """``(a, b)`` from ``"A:B"`` (either side may be empty), ``(A, B)`` or None (all ``n``
    frames): frames ``a`` to ``b - 1``, at least 2 of them. Raises InputError otherwise (also
    for a number without a colon)."""
    if frames is None:
        return 0, n
    if isinstance(frames, str):
        if ":" not in frames:  # "2" read as "2:" tracked from frame 2 to the end, where 2 frames may be meant
            raise InputError(f"frames must look like A:B, frames A to B - 1 (e.g. 0:100; 2: from frame 2 to the "
                             f"end, :50 the first 50); got {frames!r}.")
        try:
            a, _, b = frames.partition(":")
            a = int(a) if a.strip() else 0
            b = int(b) if b.strip() else n
        except ValueError:
            raise InputError(f"frames must look like A:B, frames A to B - 1 (e.g. 0:100); got {frames!r}.") from None
    else:
        try:
            a, b = (int(v) for v in frames)
            whole = all(float(v) == int(v) for v in frames)
        except (TypeError, ValueError, OverflowError):
            raise InputError(f"frames must be 'A:B' or a pair (A, B); got {frames!r}.") from None
        if not whole:
            raise InputError(f"frames must be whole frame numbers; got {frames!r}.")
    if not (0 <= a < b <= n) or b - a < 2:
        raise InputError(f"frames {a}:{b} are not a range of at least 2 of the input's {n} frames (frames A to "
                         f"B - 1, with 0 <= A < B <= {n}).")
    return a, b


def track(source: str | Path, out: str | Path, init="auto", masks: str | Path | None = None,
          camera=None, config: dict | str | Path | None = None, frames: str | tuple | None = None,
          resume: bool = False, progress: bool = True, profile: str | None = None,
          model: str | Path | BodyModel = "default", gender: str = "neutral", flow: str | None = None,
          max_size: int | None = 640, reinit: bool = True, joints3d: str = "auto",
          log: Callable[[str], None] | None = print, person: str | int | tuple = "largest",
          force: bool = False, keep_flow: bool | None = None, fast: bool = False,
          height: float | None = None, detector: str | None = None,
          search_dir: str | Path | None = None, fps: float | None = None) -> Result:
    """Track the person in ``source`` and write the result folder ``out``.

    Args:
        source: a video file, a folder of frames, or a sequence folder (``frames/``,
            optional ``masks/`` and ``camera.json``).
        out: the result folder (``run.json``, ``motion.npz``, ``input.json``,
            ``detections/``, ``flow_cache/``; while running ``progress.json``,
            ``frames.bin``, ``events.jsonl``: see :mod:`flowmocap.io.results`). One run
            at a time holds it (:class:`~flowmocap.io.lock.FolderLock`).
        init: ``"auto"`` (2D joints found by MediaPipe on the first frame with a whole
            person), an ``init.json`` path or dict (:mod:`flowmocap.fit.init`; its
            ``"frame"`` is the frame tracking starts on), or a
            :class:`~flowmocap.fit.tracker.KnownStart`.
        masks: None (the sequence folder's ``masks/``, else automatic), ``"auto"``
            (MediaPipe's person segmentation) or a folder of masks, one per frame.
        camera: None (the sequence's ``camera.json``, else from the video's metadata, else
            a 58 degree field of view), a focal length in pixels of the input's frames, a
            ``camera.json`` path or a :class:`~flowmocap.geometry.camera.PinholeCamera`.
        config: tracker settings over the profile's (:class:`~flowmocap.fit.config.TrackerConfig`
            fields): a dict or a JSON file.
        frames: ``"A:B"`` or ``(A, B)``, the frames to track (default: all; with the
            automatic init, from the first frame with a confidently detected person to
            the last with the person; with an init.json, from its ``"frame"``).
        resume: continue an interrupted run in ``out``. Only a run of the very same
            input, model, camera, init, settings and flowmocap version is continued (the
            run's fingerprint in ``run.json``); it then ends exactly as an
            uninterrupted run would have. Resuming a finished run returns it.
        progress: show progress bars.
        profile: ``"video"`` or ``"synthetic"`` (:data:`~flowmocap.fit.config.PROFILES`);
            None chooses ``video`` when the masks come from the detector, else ``synthetic``.
        model: ``"default"`` (the bundled body), an SMPL ``.pkl``/``.npz`` or folder, or a
            loaded :class:`~flowmocap.body.BodyModel`; gender: for the model file.
        flow: the observed-flow method (default: the settings' ``flow_method``).
        max_size: scale video frames, and the frames of a folder without its own
            ``camera.json`` or ``gt.npz``, down so the long side is at most this many pixels
            (None or 0: keep the size). The default, 640, is the size the benchmarks track
            real video at: the time of a frame grows with the person's pixels.
        reinit: re-initialise from the detector where tracking fails (when it runs).
        joints3d: ``"auto"``: the detector's 3D joints pull each limb's direction in depth
            (``E_d``), running the detector for them alone if nothing else needs it (and,
            with the ``detector_keypoints`` setting, for its 2D joints too); ``"off"``: no
            ``E_d``, and for an input with its own masks and init no detector at all.
        log: where the one-line messages go (None: nowhere).
        person: who to track when the detector runs and several people are in view:
            ``"largest"`` (default: the person seen biggest, nearest and longest), a
            rank ``N`` (0 = the largest, 1 = the next, ...) or a pixel ``"x,y"`` of the
            input's frames at their original size (before ``max_size``): the person
            whose box contains, or lies nearest to, it in the first frame they appear
            in (:func:`~flowmocap.vision.person.parse_person`). Recorded in ``run.json``
            (``person``).
        force: write into ``out`` even if it is a non-empty folder that flowmocap did not
            make, or start a result in it over (its result files are replaced; stored
            detections and flows are kept where they were made from the same input).
        keep_flow: store the observed flows in ``out/flow_cache`` (about 2.5 MB a frame at
            640x480, float32) for a resume or ``flowmocap render`` to reuse; None (default):
            for frame folders, not for videos, whose flows would fill the disk (a resume and
            ``render`` compute them again, giving the same values).
        fast: the :data:`~flowmocap.fit.config.FAST_SETTINGS` over the profile's (``config``
            still overrides them) and the detector without its mask augmentation: faster at
            some cost in the 2D fit on real video (``docs/settings.md``, "Speed and --fast").
        height: the person's standing height in metres, when known (0.5..2.5): the body is
            given that stature (``TrackerConfig.body_height_m``; :mod:`flowmocap.body.stature`)
            and placed at the depth that goes with it, so lengths, speeds and positions in
            metres are the person's. None: the size the fit gives the body (one camera leaves
            it open). The result's ``run.json`` records the body's stature either way (``body``).
        detector: MediaPipe's landmark model for the detections, "full" or "heavy"
            (``TrackerConfig.detector_model``; :data:`flowmocap.vision.detect.MODELS`), with the
            settings tied to it (:data:`~flowmocap.fit.config.NETWORK_SETTINGS`, under ``config``);
            None: the profile's and ``config``'s (a config naming ``detector_model`` names
            those settings itself).
        search_dir: a folder where the detector's search for everyone in ``source`` is
            kept, for runs of the same input that choose another ``person``
            (:func:`~flowmocap.vision.auto.detect_sequence`; :func:`flowmocap.batch.track_people`
            gives one); the result does not depend on it. None: in ``out``, removed when the
            detection pass ends.
        fps: frames per second of a folder of frames (a video states its own; giving one
            for a video is refused). None: the sequence's ``meta.json`` ``fps``, else 30
            with a note (``run.json`` ``frame_rate`` records the rate and where it came
            from). It sets every time and speed of the result and its exports, and the
            settings given in seconds.

    Returns:
        the :class:`Result`.

    Raises:
        flowmocap.errors.FlowMocapError: bad input (its message says what to do;
            checked before any long work), :class:`~flowmocap.errors.FolderBusyError`
            when another run holds ``out``, :class:`~flowmocap.errors.OutputError` when a
            file cannot be written. The frames finished before an error stay in ``out``,
            ``run.json`` says ``"failed"`` with the error, and ``resume=True`` continues.
    """
    say = log if log is not None else (lambda _msg: None)
    for name, value in (("source", source), ("out", out)):
        if not isinstance(value, (str, os.PathLike)):
            raise InputError(f"{name} must be a path (a str or a Path); got {type(value).__name__}.")
    if not str(source).strip():
        raise InputError("source is empty; give a video file, a folder of frames or a sequence folder.")
    if not str(out).strip():
        raise InputError("the result folder (out, --out) is empty; give the path of a new folder.")
    if not (init == "auto" or isinstance(init, (str, os.PathLike, dict, KnownStart))):
        raise InputError(f"init must be 'auto', an init.json path or dict; got {type(init).__name__}.")
    if not (masks is None or isinstance(masks, (str, os.PathLike))):
        raise InputError(f"masks must be None, 'auto' or a folder of masks; got {type(masks).__name__}.")
    if not isinstance(model, (str, os.PathLike, BodyModel)):
        raise InputError(f"model must be 'default', a body model file or folder, or a BodyModel; got "
                         f"{type(model).__name__}.")
    for name, value, none_ok in (("resume", resume, False), ("progress", progress, False), ("reinit", reinit, False),
                                 ("force", force, False), ("fast", fast, False), ("keep_flow", keep_flow, True)):
        if not (isinstance(value, (bool, np.bool_)) or (none_ok and value is None)):  # force="no" would be true
            raise InputError(f"{name} must be True or False{' (or None)' if none_ok else ''}; got {value!r}.")
    if log is not None and not callable(log):
        raise InputError(f"log must be a function taking a line of text (e.g. print), or None; got "
                         f"{type(log).__name__}.")
    if not (search_dir is None or isinstance(search_dir, (str, os.PathLike))):
        raise InputError(f"search_dir must be None or a folder's path; got {type(search_dir).__name__}.")
    if frames is not None and not isinstance(frames, str):  # numpy or torch numbers: plain ones (JSON, tests)
        try:
            frames = tuple(int(v) if float(v) == int(v) else float(v) for v in frames)
        except (TypeError, ValueError, OverflowError):
            raise InputError(f"frames must be 'A:B' or a pair (A, B); got {frames!r}.") from None
    src, out = Path(source), Path(out)
    if not src.exists():
        raise DataError(f"{src} does not exist; give a video file, a folder of frames or a sequence folder.")
    if not (src.is_file() or src.is_dir()):
        raise DataError(f"{src} is neither a file nor a folder (a pipe or a device?); give a video file, a folder "
                        "of frames or a sequence folder.")
    if joints3d not in ("auto", "off"):
        raise InputError(f"joints3d must be 'auto' or 'off'; got {joints3d!r}.")
    check_max_side(max_size)
    parse_person(person)
    if height is not None:
        check_height(height)
    if detector is not None:
        check_model(detector)
    if fps is not None:
        check_fps(fps, "fps (--fps)")
    _check_out(out, force, src)
    with FolderLock(out):
        try:
            return _track(src, out, init, masks, camera, config, frames, resume, progress, profile, model, gender,
                          flow, max_size, reinit, joints3d, say, person, force, keep_flow, fast, height, detector,
                          search_dir, fps)
        except BaseException as e:
            _failed_before_tracking(out, e)
            if not isinstance(e, OSError):
                raise
            name = getattr(e, "filename", None)
            inside = name is None or Path(name).resolve().is_relative_to(out.resolve())
            what = "could not write the result" if inside else "could not read or write a file"
            raise OutputError(f"{what}{f' ({name})' if name else ''}: {e.strerror or e}. The frames finished so far "
                              f"are kept in {out}; free space or fix the permissions, then run again with --resume "
                              "(resume=True).") from e


def _failed_before_tracking(out: Path, error: BaseException) -> None:
    """Mark a run that stopped before its first frame (``run.json`` still ``"preparing"``)
    as failed (or interrupted), with the error; best effort."""
    try:
        run = json.loads((out / "run.json").read_text())
        if run.get("status") != "preparing":
            return
        run["status"] = "interrupted" if isinstance(error, KeyboardInterrupt) else "failed"
        run["error"] = f"{type(error).__name__}: {error}" if str(error) else type(error).__name__
        write_run(out, run)
    except Exception:  # noqa: BLE001 -- the original error is what the user must see
        pass


def _track(src: Path, out: Path, init, masks, camera, config, frames, resume, progress, profile, model, gender,
           flow, max_size, reinit, joints3d, say, person, force, keep_flow, fast=False, height=None,
           detector=None, search_dir=None, fps=None) -> Result:
    """:func:`track` with ``out`` locked."""
    choice = parse_person(person)
    for name in RESULT_FILES:  # half-written files of a run that was killed (the lock says none is running)
        for tmp in out.glob(f"{glob.escape(name)}.*.tmp"):
            tmp.unlink(missing_ok=True)
    if has_result(out) and not (resume or force):
        raise InputError(f"{out} already holds a result; pass resume=True (--resume) to continue it, force=True "
                         "(--force) to start it over, or choose another folder.")
    user_masks = None if masks in (None, "auto") else masks
    is_video = src.is_file() or src.suffix.lower() in VIDEO_SUFFIXES
    seq = load_video(src, masks=user_masks, max_side=max_size or None) if is_video else load_sequence(src, masks=user_masks, max_side=max_size or None)
    if len(seq) < 2:
        raise InputError(f"{src} holds only {len(seq)} frame; tracking needs at least 2 frames "
                         "(the flow is measured between neighbouring frames).")
    if fps is not None and is_video:
        raise InputError(f"{src} is a video, which states its own frame rate ({float(seq.meta.get('fps', 0)):g} fps); "
                         "--fps is for a folder of frames.")
    rate_source = "video" if is_video else "given" if fps is not None else "meta.json" if "fps" in seq.meta else "assumed"
    if fps is not None and float(fps) == float(seq.meta.get("fps", DEFAULT_FPS)):
        fps = None  # the rate the folder gives anyway: the same run, in the fingerprint too (a resume goes on)
    if fps is not None:
        seq.meta["fps"] = float(fps)
    elif "fps" not in seq.meta:
        seq.meta["fps"] = DEFAULT_FPS
    if rate_source == "assumed":
        say(f"note: the frame rate of {src} is not known: {DEFAULT_FPS:g} fps assumed (give --fps N); it sets the "
            "times and speeds of the result and its exports")
    if is_video and seq.meta.get("mirrored"):
        say(f"note: {src} is shown mirrored (its display matrix, e.g. a Flip Horizontal): it is tracked as shown, so "
            "the person's left and right are swapped in the result")
    if is_video and seq.meta.get("cut_short"):
        say(f"warning: {src} is cut off: {cut_short_words(seq.meta['cut_short'])}; only the frames that decode are "
            "tracked (run.json 'video' 'cut_short'). If the file was cut short in a download or copy, get it again "
            "and track it with --force.")
    _check_person_point(choice, seq, src)
    auto_masks = masks == "auto" or seq.masks is None
    if not auto_masks:
        _check_masks_not_all_empty(seq.masks, user_masks)
    auto_init = isinstance(init, str) and init == "auto"
    cam, camera_source = _camera(camera, seq, src)
    if profile is None:
        profile = "video" if auto_masks else "synthetic"
        why = "automatic masks" if auto_masks else "the input's own masks"
    else:
        why = "chosen"
    if profile not in PROFILES:
        raise InputError(f"unknown profile {profile!r}; use one of {sorted(PROFILES)}.")
    base = {**(FAST_SETTINGS if fast else {}), **NETWORK_SETTINGS.get(detector, {})}  # under the config
    cfg = TrackerConfig.load(config, profile=profile, base=base or None, flow_method=flow,
                             body_height_m=None if height is None else float(height), detector_model=detector)
    body = model if isinstance(model, BodyModel) else load_body_model(model, gender=gender)
    if cfg.body_height_m:  # a model whose shape does not set its height is refused now, not after detection
        with_stature(body, torch.zeros(10, dtype=torch.float64), cfg.body_height_m)
    if choice[0] != "largest" and not (auto_masks or auto_init):
        raise InputError(f"person={describe_person(choice)!r} chooses among the people the detector finds, but with "
                         "your own init and masks the detector does not choose anyone; leave person at 'largest' "
                         "(the init and masks say who is tracked).")
    # everything the user gives is checked before the long work (detection, tracking)
    if auto_init:
        spec = None
        if frames is not None:
            parse_frame_range(frames, len(seq))
    else:
        try:
            spec = init if isinstance(init, KnownStart) else read_init(init, seq.size, len(seq))
        except InputError as e:
            if float(seq.meta.get("scale", 1.0)) == 1.0 or not any(w in str(e) for w in ("outside", "span only")):
                raise
            raise InputError(f"{str(e).rstrip('.')} (frames scaled by --max-size; pass --max-size 0 to keep the "
                             "video's size)") from None
        a, b = _init_span(frames, spec, len(seq))
    # how a video's frames are shown, where it is not as plain pixels: part of the fingerprint and of the
    # caches' key (flowmocap before 2026-12 decoded mirrored and non-square-pixel videos otherwise)
    decoded = {k: seq.meta[k] for k in ("mirrored", "sample_aspect_ratio")
               if k in seq.meta and seq.meta[k] not in (False, 1.0)} if is_video else {}
    uses_detector = auto_masks or auto_init or (joints3d == "auto" and (cfg.uses_detector3d or cfg.detector_keypoints))
    fingerprint = _fingerprint(src, user_masks, body, cam, init, spec, cfg, choice, uses_detector,
                               {"frames": frames if frames is None or isinstance(frames, str) else list(frames),
                                "max_size": max_size or None, "profile": profile, "reinit": bool(reinit),
                                "joints3d": joints3d, "masks": "auto" if auto_masks else "given",
                                **({"fast": True} if fast else {}), **({"fps": float(fps)} if fps is not None else {}),
                                **({"decoded": decoded} if decoded else {})})
    if resume and has_result(out):
        done = _resumable(out, fingerprint)
        if done is not None:
            if _post_pending(out, cfg, joints3d, done.run):  # stopped after tracking, before the steps after it
                _post_steps(out, load_detections(out), body, cfg, done.run, joints3d, say)
                _drop_leftovers(out)
                return load_result(out)
            _drop_leftovers(out)
            say(f"{out} holds the finished run of this input and set-up; nothing to do")
            return done
    elif has_result(out) or (out / "run.json").exists():  # force, or a run that failed before its first frame
        for name in ("motion.npz", "progress.json", "frames.bin", "events.jsonl", "run.json", "input.json",
                     "init_auto.json", "eval.json", WORLD_FILE):
            (out / name).unlink(missing_ok=True)
        _drop_old_outputs(out)
    if not has_result(out):
        write_run(out, {"flowmocap": __version__, "status": "preparing", "input": str(src.resolve()),
                        "fingerprint": fingerprint})
    say(f"settings: profile '{profile}' ({why})" + (", fast" if fast else "") + (f", then {config}" if isinstance(config, (str, Path)) else
                                                    ", then the given overrides" if config else ""))
    cache_key = digest_value([fingerprint["input"], list(seq.size)] + ([decoded] if decoded else []))
    _fresh_cache(out / "detections", cache_key, say)
    _fresh_cache(out / "flow_cache", cache_key, say)
    if uses_detector:  # before the pass: a pass that is stopped goes on from its stored stretches
        write_json(out / "detections" / "source.json", {"input": cache_key})
    keep_flow = (not is_video) if keep_flow is None else bool(keep_flow)
    if keep_flow:
        write_json(out / "flow_cache" / "source.json", {"input": cache_key})

    detections = None
    if choice[0] == "point":  # the user's pixel is in the original frames; the detector sees the scaled ones
        sx, sy = seq.meta.get("scale_xy") or [float(seq.meta.get("scale", 1.0))] * 2
        choice = ("point", (choice[1][0] * sx, choice[1][1] * sy))
    if auto_masks or auto_init:  # the detections also drive re-initialisation
        say(f"finding the person in {len(seq)} frames (MediaPipe pose; stored in {out / 'detections'}) ...")
        # --fast: MediaPipe without the mask augmentation (its three extra runs a frame); the
        # search for other people stays (without it the tracked person can be the wrong one)
        detections = detect_sequence(seq, out, progress=progress, detector="unaugmented" if fast else None,
                                     person="largest" if choice[0] == "largest" else choice[1],
                                     model=cfg.detector_model, search_dir=search_dir)
        if auto_masks:
            seq.masks = list(detections.mask_paths)
    notes: dict = {"camera_source": camera_source,
                   "masks": "automatic" if auto_masks else str(user_masks or "input"),
                   "init": "automatic" if auto_init else ("known start" if isinstance(init, KnownStart)
                                                          else str(init) if not isinstance(init, dict) else "given"),
                   "profile": profile}
    if auto_init:
        spec, (a, b), notes["frame_range"] = _auto_start(detections, frames, len(seq), out, seq.size, cam.R)
    if detections is not None:
        notes["detections"] = {k: detections.info[k] for k in ("detector", "frames_with_person", "no_person",
                                                               "ignored_people")}
        notes["person"] = {"asked": describe_person(parse_person(person)),
                           **detections.info.get("person", {"choice": describe_person(choice)})}
        if choice[0] == "point":
            notes["person"]["pixel_in_tracked_frames"] = [round(v, 1) for v in choice[1]]
        held = cfg.hold_unseen_frames if auto_masks else 0  # longer runs: the body held (_run_sequence), then
        #                                                     filled in between after tracking (_inbetween)
        notes["gaps"] = [{"frames": r, "why": "no person found: held at the last seen pose" if 0 < held < r[1] - r[0] + 1
                          else "no person found: tracked by flow alone, no silhouette term"}
                         for r in frame_runs([i for i in range(a, b) if not detections.found[i]])]
    notes["frame_rate"] = {"fps": float(seq.meta["fps"]), "source": rate_source}
    if is_video:
        notes["video"] = {k: seq.meta[k] for k in ("fps", "variable_frame_rate", "rotation", "mirrored", "sample_aspect_ratio", "stored_size", "decoded_size", "size",
                                                   "scale", "scale_xy", "focal_35mm", "timestamps") if k in seq.meta}
        notes["video"]["max_side"] = max_size or None
        if seq.meta.get("cut_short"):
            notes["video"]["cut_short"] = seq.meta["cut_short"]
    elif seq.source_size is not None:  # a folder of frames scaled like a video's
        notes["frames_scaled"] = {"size": list(seq.size), "source_size": list(seq.source_size),
                                  "scale": seq.meta["scale"], "scale_xy": seq.meta.get("scale_xy"),
                                  "max_side": max_size}

    keypoints = j3d = None
    lift = cfg.detector3d_source != "mediapipe"  # the 3D cues from flowmocap's lifter of the 2D keypoints
    mix = cfg.detector3d_source == "both"  # ... averaged with the detector's own 3D
    ray_share = cfg.detector3d_ray_share if not lift else 1.0  # the lifter's 3D is in the ray's axes
    if lift and joints3d == "auto":
        notes["joints3d_source"] = ("the mean of MediaPipe's 3D keypoints and flowmocap.vision.lifter's" if mix else
                                    "flowmocap.vision.lifter, from the detector's 2D keypoints")
    watch = detections  # the detections the re-initialisation compares each frame with
    seen2d = detections  # the 2D detections of every frame, where there are any (for init_shape_share)
    if detections is not None:  # the detector's joints also pull the body (E_j) and say each limb's depth (E_d)
        keypoints = lambda i: detections.smpl_joints(i) if i < len(detections) and detections.found[i] else None
        if lift:
            watch = lifted_track(detections, mix=mix, fps=seq.meta["fps"])
        j3d = lambda i: watch.smpl_joints3d(i, cam, ray_share)
    elif joints3d == "auto" and cfg.detector_keypoints:  # own masks and init, the detector's joints of every frame too
        say(f"finding the person's joints in {len(seq)} frames (MediaPipe pose; for E_j, E_d and refits) ...")
        watch, notes["joints3d"] = detect_for_given_masks(seq, out, progress=progress, model=cfg.detector_model)
        seen2d = watch
        if watch is not None:
            if lift:
                watch = lifted_track(watch, mix=mix, fps=seq.meta["fps"])
            keypoints = lambda i: watch.smpl_joints(i) if i < len(watch) and watch.found[i] else None
            j3d = lambda i: watch.smpl_joints3d(i, cam, ray_share)
    elif joints3d == "auto" and cfg.uses_detector3d:
        say(f"finding the person's 3D joints in {len(seq)} frames (MediaPipe pose; for E_d) ...")
        j3d, notes["joints3d"] = detect_joints3d(seq, out, cam, progress=progress, lift=lift, mix=mix,
                                                 model=cfg.detector_model, ray_share=ray_share)
    if (out / "detections").is_dir():
        write_json(out / "detections" / "source.json", {"input": cache_key})
    if getattr(seq, "camera", None) is None:  # a video or a folder of frames: the camera may turn
        from scipy.spatial.transform import Rotation

        from flowmocap.vision.camera_motion import camera_motion

        # from the input's first frame, whatever the tracked range: the people of one video
        # (track --person all) are then turned back into one world
        # everyone else left out too: someone walking past is not background
        spent = [0.0]  # seconds over every pass (run.json 'camera_motion' 'seconds')

        def motion(cam, frames, **kw):
            t0 = time.perf_counter()
            try:
                return camera_motion(seq, cam, frames=frames, masks=getattr(seq, "masks", None) is not None,
                                     progress=progress, others=getattr(detections, "people", None), **kw)
            finally:
                spent[0] += time.perf_counter() - t0
        # a guessed focal length is read from the background where the camera turns; only with the
        # detector's own pass (with own masks and init, detect_joints3d has bound the guess already)
        guessed = (camera is None and "default focal length" in camera_source and detections is not None)
        moved = motion(cam, range(0, b), focal=guessed)
        if moved.focal is not None:
            new_cam, focal = _focal_from_turns(moved.focal, cam, lambda c: motion(c, range(0, len(seq)), focal=True,
                                                                                  sideways=False).focal,
                                               whole=b == len(seq))
            # with a wrong focal length a pan looks like a move on the floor; a move the floor
            # still shows with the turns' focal length bends that estimate: then the guess is kept
            again = motion(new_cam, range(0, b)) if focal is not None else None
            if again is not None and not again.moving_sideways:
                cam, moved = new_cam, again
                moved.focal = focal
                notes["camera_source"] = camera_source = (
                    f"focal length {cam.fx:.1f} px from the background's turns (the camera turns up to "
                    f"{moved.turn_deg.max():.0f} degrees; {focal['ratio_to_guess']:.2f} times the guess, "
                    f"{focal['guess_px']:.1f} px = {focal['guess_px'] / max(cam.width, cam.height):.2g} x the long "
                    "side) -- give --focal if you know it")
                say(f"the camera turns, and the background's turns give its focal length: {cam.fx:.0f} px "
                    f"({focal['ratio_to_guess']:.2f} times the guess of {focal['guess_px']:.0f} px); the body is "
                    "tracked with it (run.json 'camera_motion' 'focal'; give --focal if you know the lens)")
            elif again is None:  # the guess is within FOCAL_CHANGE of it
                moved.focal = {**moved.focal, "applied": False}
            else:
                moved.focal = {**focal, "applied": False}
                say(f"the camera turns, and its background's turns would give a focal length of about "
                    f"{focal['focal_px']:.0f} px (the guess is {cam.fx:.0f} px), but the floor shows the camera moving "
                    "with that focal length too, and a camera that moves bends that estimate, so the guess is kept "
                    "(run.json 'camera_motion' 'focal'; give --focal if you know the lens)")
        notes["camera_motion"] = {**moved.to_dict(rotations=moved.moving), "seconds": round(spent[0], 2)}
        if moved.moving_sideways:
            turned = np.degrees(np.linalg.norm(Rotation.from_matrix(moved.floor_rotations).as_rotvec(), axis=1)).max()
            say(f"the floor about the person's feet shows the camera moving: its centre goes up to {moved.sideways:.1f} "
                "times its height above the floor from where it is in the first frame, and it turns up to "
                f"{turned:.0f} degrees by the floor's fit ({notes['camera_motion']['turn_deg_max']:.0f} by the "
                "background's, run.json's 'turn_deg_max'). The body is tracked in the moving camera's "
                "frame; after tracking, the move is checked against the fitted body, and where the two agree, export "
                "and view move each frame back into the world, scaled by the camera's height that the fitted feet "
                "give (run.json 'camera_motion' holds the camera's turn and move per frame)." +
                (f" The background fits a zoom as well (the focal length from {moved.zooms.min():.2f} to "
                 f"{moved.zooms.max():.2f} times the first frame's), which a move forward can look like: where the move "
                 "is not undone, the zoom is." if moved.zooming else ""))
        elif moved.moving:
            say(f"the camera turns (a pan or a tilt): up to {notes['camera_motion']['turn_deg_max']:.0f} degrees from "
                "where it points in the first frame. The body is tracked in the turning camera's frame; export and "
                "view turn each frame back into the world (run.json 'camera_motion' holds the camera's rotation per "
                "frame).")
        if moved.zooming and not moved.moving_sideways:
            say(f"the camera zooms: its focal length goes from {moved.zooms.min():.2f} to {moved.zooms.max():.2f} times "
                "the first frame's. The body is tracked with the first frame's, so it seems to move away as the camera "
                "zooms out (nearer as it zooms in); export and view bring each frame's body back to the depth its "
                "focal length gives (run.json 'camera_motion' 'zooms').")
    write_json(out / "input.json", notes)
    if joints3d == "off":
        j3d = None
    monitor = watch if (watch is not None and reinit) else None
    seen = _seen_proportions(seen2d, cfg, seq.meta["fps"]) if isinstance(spec, InitSpec) else None
    run = _run(seq, out, body, cam, spec, cfg, (a, b), resume, progress, monitor, keypoints, j3d, profile,
               {"fingerprint": fingerprint, **notes}, keep_flow, seen)
    run = _post_steps(out, watch, body, cfg, run, joints3d, say)
    _camera_move_verdict(out, run, say)
    t = run["timings"]
    reinits = sum(1 for e in run["events"] if e.get("event") == "re-initialised")
    per_frame = t.get("s_per_frame_median")
    timing = (f"{per_frame:.2f} s per frame median" if per_frame is not None and math.isfinite(per_frame)
              else "no frame past the start tracked, so no time per frame")
    say(f"tracked frames {a}:{b} of {len(seq)} into {out} ({timing}; {len(run['events'])} recorded events, "
        f"{reinits} re-initialisations)")
    say(f"camera: {camera_source}")
    if "frame_range" in notes:
        say(notes["frame_range"])
    return load_result(out)


def _drop_old_outputs(out: Path) -> None:
    """Remove what ``export`` and ``render`` wrote of a result in ``out`` at their default
    places (``export/``, ``render/``), so a result started over does not sit beside files
    made from the old one. Only the names they write are removed, and the folders when that
    empties them: anything else a user keeps there stays."""
    from flowmocap.export import FORMATS

    for folder, names in (("export", FORMATS.values()), ("render", RENDER_OUTPUTS.values())):
        d = out / folder
        if not d.is_dir() or d.is_symlink():
            continue
        for name in names:
            p = d / name
            if p.is_file() and not p.is_symlink():
                p.unlink()
            elif p.is_dir() and not p.is_symlink() and all(f.suffix in (".obj", ".mtl") for f in p.iterdir()):
                shutil.rmtree(p)  # export's obj/: one OBJ a frame
        if not any(d.iterdir()):
            d.rmdir()


def _check_person_point(choice: tuple, seq: Sequence, src: Path) -> None:
    """Refuse ``person="x,y"`` outside the input's frames at their original size (before
    ``max_size``, the pixels the option takes).

    Raises:
        InputError: the point lies outside the frames, with their size.
    """
    if choice[0] != "point":
        return
    w, h = seq.source_size or seq.size
    x, y = choice[1]
    if not (0 <= x <= w and 0 <= y <= h):
        raise InputError(f"person={describe_person(choice)} lies outside the {w}x{h} frames of {src}; give a pixel "
                         f"x,y with 0 <= x <= {w} and 0 <= y <= {h} (the frames' own size, before --max-size) on "
                         "the person in the first frame they appear in.")


def _check_masks_not_all_empty(paths: list[Path], given) -> None:
    """Refuse masks with no person pixel in any of them (read until the first that has
    one: at once for usual masks).

    Raises:
        NoPersonError: every mask is empty.
        DataError: a mask cannot be read.
    """
    for p in paths:
        if read_image(p, None, gray=True).any():
            return
    folder = Path(given) if given is not None else Path(paths[0]).parent
    raise NoPersonError(f"every mask in {folder} is empty: masks must be non-zero on the person; fix the masks, or "
                        "pass masks='auto' (--masks auto) to have the detector find the person.")


def _check_out(out: Path, force: bool, src: Path | None = None) -> None:
    """Refuse an ``out`` that is a file, a batch's or ``--person all``'s folder (even with
    ``force``: one result written there would stop the batch), or a non-empty folder
    flowmocap did not make (unless ``force``), before anything is written; ``src`` (the
    input) names its result folder inside a batch's."""
    if out.is_symlink() and not out.exists():
        raise InputError(f"{out} is a symbolic link to {os.readlink(out)}, which does not exist; give a new folder, "
                         "or make the folder the link points to.")
    if out.exists() and not out.is_dir():
        raise InputError(f"{out} is a file; the result goes into a folder: give a new folder, or one that holds a "
                         "flowmocap result.")
    if out.is_dir() and (out / "batch.json").is_file():  # flowmocap.batch.MANIFEST
        mine = None
        try:
            results = json.loads((out / "batch.json").read_text())["results"]
            mine = next((name for name, r in results.items()
                         if src is not None and r.get("input") == str(src.resolve())), None)
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            pass
        where = (f"; this input's result is {out / mine}: give --out {out / mine} to go on with it" if mine else
                 "; give several inputs to track them into it as a batch")
        raise InputError(f"{out} holds a batch of results (batch.json), not one result{where}, or give another "
                         "--out folder.")
    if out.is_dir() and (out / PEOPLE_MANIFEST).is_file():
        raise InputError(f"{out} holds the people of `track --person all` ({PEOPLE_MANIFEST}); pass --person all to go "
                         f"on with them, give one person's folder ({out / 'person0'}, ...), or another --out folder.")
    if out.is_dir() and not force and not is_result_folder(out):
        # the lock and flowmocap's own caches (e.g. detections run before tracking) are ours
        # and so are the half-written files of a run killed while it wrote its first ones
        ours = (".lock", ".lock.json", "detections", "flow_cache")
        others = sorted(p.name for p in out.iterdir() if p.name not in ours and not _is_half_written(p.name))
        if others:
            shown = ", ".join(others[:5]) + (", ..." if len(others) > 5 else "")
            raise InputError(f"{out} is not empty ({shown}) and holds no flowmocap result; give a new or empty "
                             "folder, or pass force=True (--force) to write the result into it anyway.")


def _drop_leftovers(out: Path) -> None:
    """Remove what a run killed while it finished can leave beside its ``motion.npz``: the
    frame log (``frames.bin``, ``events.jsonl``) once ``progress.json`` is gone, and the
    temporaries of its result files (:func:`_is_half_written`). No reader uses them."""
    if (out / "progress.json").exists() or not (out / "motion.npz").exists():
        return
    for name in ("frames.bin", "events.jsonl"):
        (out / name).unlink(missing_ok=True)
    for p in out.iterdir():
        if p.is_file() and _is_half_written(p.name):
            p.unlink(missing_ok=True)


def _is_half_written(name: str) -> bool:
    """Whether ``name`` is the temporary of one of flowmocap's result files
    (:func:`~flowmocap.atomic.atomic_write`'s ``NAME.XXXX.tmp``), left by a killed run."""
    return name.endswith(".tmp") and any(name.startswith(f"{r}.") for r in RESULT_FILES)


def read_init(init, size: tuple[int, int], num_frames: int) -> InitSpec:
    """Read and check an init.json (path or dict) for frames of ``size = (W, H)`` pixels:
    :func:`~flowmocap.fit.init.parse_init` plus the checks that need the input: its
    ``"frame"`` (an integer frame of the input) and joints spread over the person (not
    bunched into a few pixels, which would put the body kilometres away).

    Raises:
        InputError: a malformed value, with what to fix.
    """
    data = init
    if not isinstance(init, dict):
        try:
            data = json.loads(Path(init).read_text())
        except FileNotFoundError:
            raise InputError(f"init file {init} does not exist.") from None
        except IsADirectoryError:
            raise InputError(f"init file {init} is a folder, not a JSON file.") from None
        except (ValueError, UnicodeDecodeError) as e:
            raise InputError(f"init file {init} is not valid JSON: {e}") from None
    if not isinstance(data, dict):
        raise InputError(f"init.json must hold a JSON object (joints2d, optional frame, pose, trans, betas); got "
                         f"{type(data).__name__}.")
    frame = data.get("frame", 0)
    if isinstance(frame, bool) or not isinstance(frame, int) or not 0 <= frame < num_frames - 1:
        raise InputError(f"init.json: 'frame' must be the integer number of the frame its joints belong to, "
                         f"0..{num_frames - 2} for this input of {num_frames} frames; got {frame!r}.")
    for key in ("confidence", "pose"):
        if data.get(key) is not None and not isinstance(data[key], dict):
            raise InputError(f"init.json: {key!r} must be an object keyed by joint name; got "
                             f"{type(data[key]).__name__}.")
    try:
        spec = parse_init(data, *size)
    except InputError:
        raise
    except (ValueError, TypeError) as e:
        raise InputError(f"init.json holds a value of the wrong kind ({e}); see docs for its layout: joints2d "
                         "{name: [x, y]}, confidence {name: 0..1}, pose {name: [3 numbers]}, pose72 [72 numbers], "
                         "trans [x, y, z], betas [up to 10 numbers].") from None
    checks = [("confidence", spec.confidence, lambda c: np.isfinite(c).all() and (c >= 0).all() and (c <= 1).all(),
               "numbers in [0, 1]"),
              ("pose", spec.pose, lambda p: np.isfinite(p).all() and (np.abs(p) <= 4 * np.pi).all(),
               "finite axis-angle rotations (radians)"),
              ("betas", spec.betas, lambda v: np.isfinite(v).all() and (np.abs(v) <= 10).all(),
               "finite shape values within +-10")]
    if spec.trans is not None:
        checks.append(("trans", spec.trans, lambda t: t.shape == (3,) and np.isfinite(t).all() and t[2] > 0,
                       "[x, y, z] metres with z > 0 (in front of the camera)"))
    for key, value, ok, expected in checks:
        if not ok(np.asarray(value)):
            raise InputError(f"init.json: {key!r} must be {expected}.")
    used = spec.confidence > 0
    spread = float(np.ptp(spec.joints2d[used], axis=0).max())
    if spread < MIN_INIT_SPREAD * size[1]:
        raise InputError(f"init.json: the joints span only {spread:.1f} px of the {size[0]}x{size[1]} frames; they "
                         f"must mark the person (spread over at least {MIN_INIT_SPREAD:.0%} of the image height), "
                         "or the body would be placed far away. Check the joints' pixel coordinates.")
    return spec


#: Where the camera turns and no focal length was given, the one its background's turns give
#: (:func:`~flowmocap.vision.camera_motion.focal_from_turns`) replaces the guess where the two
#: differ by more than this share.
FOCAL_CHANGE = 0.02
#: Rounds of the focal length's estimate at most, each with the turns fitted with the last
#: (the first, with the guess's turns, is within 4 % on the tests' pans; the next within 1 %).
FOCAL_ROUNDS = 3


def _focal_from_turns(found: dict, cam: PinholeCamera, estimate, whole: bool) -> tuple[PinholeCamera, dict | None]:
    """The camera to track a turning camera's video with, where no focal length was given
    (the caller keeps it only where the floor then shows no move: the estimate assumes a turn
    about the camera's centre).

    Args:
        found: :attr:`~flowmocap.vision.camera_motion.CameraMotion.focal` of the tracked
            frames, fitted with the guess ``cam``.
        cam: the guessed camera.
        estimate: ``estimate(camera)``: the focal found over the whole video with the turns
            fitted with ``camera`` (a dict as ``found``, or None).
        whole: ``found`` is already the whole video's.

    Returns:
        ``(camera, focal)``: the guess and None where the background's focal length is within
        :data:`FOCAL_CHANGE` of it; else a camera with the last estimate, refined over at most
        :data:`FOCAL_ROUNDS` rounds until one moves it by less, and ``focal`` (the last
        estimate's dict, with ``guess_px``, ``ratio_to_guess`` and ``applied`` True).
    """
    guess = float(cam.fx)
    focal = found if whole else estimate(cam)
    last = None
    for _ in range(FOCAL_ROUNDS):
        if focal is None or abs(np.log(focal["focal_px"] / cam.fx)) <= np.log1p(FOCAL_CHANGE):
            break
        cam = PinholeCamera.from_focal(cam.width, cam.height, focal["focal_px"])
        last, focal = focal, estimate(cam)
    if cam.fx == guess:
        return cam, None
    focal = focal or last
    return cam, {**focal, "applied": True, "guess_px": round(guess, 1),
                 "ratio_to_guess": round(float(cam.fx) / guess, 4)}


#: An init's joints must span at least this fraction of the image height.
MIN_INIT_SPREAD = 0.03


def _init_span(frames, spec, n: int) -> tuple[int, int]:
    """The frames to track with a given init: ``frames`` (which must start on the init's
    frame) or from the init's frame to the end."""
    first = 0 if isinstance(spec, KnownStart) else spec.frame
    if frames is None:
        return parse_frame_range((first, n), n)
    a, b = parse_frame_range(frames, n)
    if not isinstance(spec, KnownStart) and a != first:
        raise InputError(f"init.json's joints are of frame {first} ('frame') but the frames to track start at {a}; "
                         f"start at {first} (frames {first}:{b}) or mark the joints of frame {a}.")
    return a, b


def _fingerprint(src: Path, user_masks, body: BodyModel, cam: PinholeCamera, init, spec, cfg: TrackerConfig,
                 choice, uses_detector: bool, options: dict) -> dict:
    """``{part: digest}`` of everything that determines the result (:mod:`flowmocap.io.fingerprint`)."""
    if isinstance(init, KnownStart):
        init_digest = digest_arrays([init.poses, init.trans, init.betas])
    elif spec is not None:
        init_digest = digest_arrays([spec.joints2d, spec.confidence, spec.pose, spec.betas,
                                     np.zeros(0) if spec.trans is None else spec.trans,
                                     np.zeros(0) if spec.pose_given is None else spec.pose_given,
                                     np.array([spec.frame])])
    else:
        init_digest = digest_value(["auto", describe_person(choice)])
    detector = None
    if uses_detector:
        try:
            from importlib.metadata import version

            detector = ["mediapipe", version("mediapipe")]
        except Exception:  # noqa: BLE001 -- not installed: the detector step says so itself
            detector = ["mediapipe", None]
    return {"input": digest_input(src), "masks": digest_input(user_masks) if user_masks else "auto-or-input",
            "model": digest_model(body), "camera": digest_value(cam.to_dict()), "init": init_digest,
            "config": digest_value(cfg.to_dict()), "options": digest_value(options),
            "detector": digest_value(detector), "code": __version__}


def _resumable(out: Path, fingerprint: dict) -> Result | None:
    """Check that the run in ``out`` can be resumed with ``fingerprint``: None when it is
    to be continued, its :class:`Result` when it is finished already."""
    _, old = read_result(out)
    if not (out / "progress.json").exists() and old.get("status") != "finished" and not old.get("tracked"):
        raise InputError(f"cannot resume the run in {out}: it was written by an older flowmocap and holds no "
                         "tracker state; start a new result folder instead (or pass --force to start it over).")
    parts = differing(old.get("fingerprint"), fingerprint)
    if parts:
        named = {"input": "the input", "masks": "the masks", "model": "the body model", "camera": "the camera",
                 "init": "the init", "config": "the config", "options": "the options (frames, max size, profile, "
                 "re-initialisation, joints3d, fast, fps)", "detector": "the detector's version", "code": "the flowmocap version"}
        names = [named.get(p, p) for p in parts]
        what = names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]
        raise InputError(f"cannot resume the run in {out}: {what} differ{'s' if len(parts) == 1 else ''} from the "
                         "interrupted run's; resume with the same set-up, pass --force (force=True) to start it "
                         "over, or choose another folder.")
    if not (out / "progress.json").exists():
        return load_result(out)
    return None


def _fresh_cache(folder: Path, key: str, say) -> None:
    """Remove a cache folder (detections, flow) made from other input than ``key`` says."""
    if not folder.is_dir():
        return
    try:
        stored = json.loads((folder / "source.json").read_text()).get("input")
    except (OSError, ValueError, AttributeError):
        stored = None
    if stored != key:
        say(f"{folder} was made from other input; computing it anew")
        shutil.rmtree(folder)
    

def _camera(camera, seq: Sequence, src: Path) -> tuple[PinholeCamera, str]:
    """The camera and a sentence on where it came from (see :func:`track`)."""
    scale = float(seq.meta.get("scale", 1.0))
    w, h = seq.size
    if isinstance(camera, PinholeCamera):
        cam, note = camera, "given"
    elif isinstance(camera, (str, Path)):
        cam, note = read_camera_json(camera), f"camera file {camera}"
    elif camera is not None:
        try:
            focal = float(camera)
        except (TypeError, ValueError):
            raise InputError(f"camera must be None, a focal length in pixels, a camera.json path or a PinholeCamera; "
                             f"got {camera!r}.") from None
        if not focal > 0:
            raise InputError(f"the focal length must be > 0 pixels; got {focal!r}.")
        cam = PinholeCamera.from_focal(w, h, focal * scale)
        note = f"focal {focal:g} px" + (f" (x {scale:.4g} for the scaled frames)" if scale != 1.0 else "")
    elif seq.camera is not None:
        cam, note = seq.camera, f"{src / 'camera.json'}"
    else:
        f35 = seq.meta.get("focal_35mm")
        cam, note = default_camera(w, h, f35)
        if not _field_of_view_ok(cam) and f35:  # metadata the user did not write: set it aside, say so
            cam, note = default_camera(w, h, None)
            note = f"the video's 35 mm-equivalent focal length {f35:g} mm is not a real lens's, ignored; {note}"
        if not _field_of_view_ok(cam):  # the frames' shape itself: no lens sees a sliver like this
            lo, _ = FIELD_OF_VIEW_DEG
            raise InputError(f"the frames are {w}x{h} pixels: with any ordinary lens a view that narrow spans less "
                             f"than {lo:g} degrees on its short side and cannot hold a person; give frames of an "
                             "ordinary shape (crop less), or --focal/--camera if the lens really is that long.")
        _check_principal_point(cam, note)
        return cam, note
    if (cam.width, cam.height) != (w, h):
        raise InputError(f"the camera ({note}) is for {cam.width}x{cam.height} images but the frames are {w}x{h}"
                         + (" (scaled by max_size / --max-size; pass 0 to keep the video's size)"
                            if scale != 1.0 else "") + ".")
    _check_field_of_view(cam, note)
    _check_principal_point(cam, note)
    return cam, note


#: The widest and narrowest field of view, degrees across the image, a pinhole camera may have
#: for tracking. Wider than 170 degrees no lens is a pinhole (a fisheye needs undistorting
#: first), and the body would be placed at a depth of millimetres; narrower than 0.2 degrees
#: (a 2000 mm lens on a full-frame sensor is 1 degree) the depth is hundreds of metres.
FIELD_OF_VIEW_DEG = (0.2, 170.0)


def _fields_of_view(cam: PinholeCamera) -> tuple[float, float]:
    """The camera's field of view across and down the image, degrees."""
    return (math.degrees(2.0 * math.atan2(cam.width / 2.0, cam.fx)),
            math.degrees(2.0 * math.atan2(cam.height / 2.0, cam.fy)))


def _field_of_view_ok(cam: PinholeCamera) -> bool:
    """Whether both of the camera's fields of view lie in :data:`FIELD_OF_VIEW_DEG`."""
    lo, hi = FIELD_OF_VIEW_DEG
    return all(lo <= fov <= hi for fov in _fields_of_view(cam))


def _check_field_of_view(cam: PinholeCamera, note: str) -> None:
    """Refuse a camera whose focal length cannot be a real pinhole's (``InputError``).

    Args:
        cam: the camera (pixels).
        note: where it came from, for the message.
    """
    lo, hi = FIELD_OF_VIEW_DEG
    for axis, size, focal, fov in zip(("across", "down"), (cam.width, cam.height), (cam.fx, cam.fy),
                                      _fields_of_view(cam)):
        if not lo <= fov <= hi:
            raise InputError(
                f"the camera ({note}) has a field of view of {fov:.3g} degrees {axis} the image "
                f"({'fx' if axis == 'across' else 'fy'} = {focal:g} px for {size} px), outside "
                f"{lo:g}..{hi:g}; check that the focal length is in pixels (not mm), or leave the camera out "
                "and the tool assumes a 58-degree field of view across the long side.")


def _check_principal_point(cam: PinholeCamera, note: str) -> None:
    """Refuse a principal point more than an image's size outside the image (``InputError``).

    A cropped image may have its principal point off centre, even outside it, but not a whole
    image width (or height) beyond its edges: that is a mistyped camera file.

    Args:
        cam: the camera (pixels).
        note: where it came from, for the message.
    """
    for name, c, size in (("cx", cam.cx, cam.width), ("cy", cam.cy, cam.height)):
        if not -size <= c <= 2 * size:
            raise InputError(
                f"the camera ({note}) has its principal point {name} = {c:g} px, more than the image's "
                f"{size} px outside the image; {name} is in pixels from the image's "
                f"{'left' if name == 'cx' else 'top'} edge (about {size / 2:g} for a centred one).")


def _auto_start(detections: PersonTrack, frames, n: int, out: Path, size, camera_R=None) -> tuple:
    """Automatic initialisation: the InitSpec, the frame range and a sentence about it
    (``camera_R``: the camera's rotation, for the start's orientation in the world's axes)."""
    if frames is not None:
        a, b = parse_frame_range(frames, n)
    else:
        found = [i for i in range(n) if detections.found[i]]
        a, b = 0, (found[-1] + 1 if found else n)
    first = first_person_frame(detections, a)
    if first is not None and first >= b - 1:
        raise NoPersonError(f"the person is seen whole enough to start on only in frame {first}, the last of "
                            f"{a}:{b} in which the detector sees them; tracking needs them in at least two frames "
                            "(the flow is measured between neighbouring frames): give a longer clip, --frames that "
                            "reach further, or --init init.json with the 2D joints of an earlier frame.")
    if first is None:
        raise NoPersonError(f"no frame in {a}:{b} shows a whole enough person to start on (hips, shoulders and "
                            "at least 8 of the 12 main joints, each with confidence >= 0.5) before the last frame; "
                            "give --init init.json with the 2D joints of the first frame.")
    init = auto_init(detections, first, camera_R=camera_R)
    (out / "init_auto.json").write_text(json.dumps(init, indent=2))
    note = f"frames {first}:{b}"
    if first > a:
        note += f"; started at frame {first}, the first with a confidently detected person (frames {a}..{first - 1} skipped)"
    if frames is None and b < n:
        note += f"; stopped after frame {b - 1}, the last with the person (frames {b}..{n - 1} skipped)"
    return parse_init(init, *size), (first, b), note


def _append(log: FrameLog, scene: Scene, frame: int, state: FrameState, terms: dict, seconds: float,
            events: list[dict]) -> None:
    """Queue one frame's row (parameters, joints, energies by name) in ``log``."""
    with torch.no_grad():
        out, _, _ = scene.forward(state.pose, state.trans)
        j3 = out.joints[0]
        j2 = scene.camera.project(j3)
    log.append(state.pose.numpy(), state.trans.numpy(), j3.numpy(), j2.numpy(),
               [terms.get(n, np.nan) for n in log.header["energy_names"]], frame, seconds, events)


def _seen_proportions(track: PersonTrack | None, cfg: TrackerConfig, fps: float):
    """``(7,)`` or None: with ``cfg.init_shape_share`` > 0, the median over the video's frames
    of the bone proportions of the lifter's 3D of ``track``'s 2D keypoints
    (:func:`~flowmocap.fit.lift_refit.median_proportions`); None without a track, with the
    setting off, or with too few lifted frames."""
    if track is None or cfg.init_shape_share <= 0:
        return None
    from flowmocap.fit.lift_refit import median_proportions
    from flowmocap.vision.lifter import eval_points_2d

    world = lifted_track(track, fps=fps).world
    return median_proportions(eval_points_2d(world, np.ones(world.shape[:2]))[0])


def _run(seq: Sequence, out: Path, model: BodyModel, camera: PinholeCamera, init: InitSpec | KnownStart,
         cfg: TrackerConfig, span: tuple[int, int], resume: bool, progress: bool, detections: PersonTrack | None,
         keypoints, joints3d, profile: str, notes: dict, keep_flow: bool = True, proportions=None) -> dict:
    """Initialise (or restore) and track ``span`` of ``seq`` into ``out``; returns run.json's contents.
    ``proportions``: ``(7,)`` or None, the body's bone proportions the video shows
    (:func:`~flowmocap.fit.init.initialise`)."""
    with _torch_threads(cfg.torch_threads):
        return _run_sequence(seq, out, model, camera, init, cfg, span, resume, progress, detections, keypoints,
                             joints3d, profile, notes, keep_flow, proportions)


@contextlib.contextmanager
def _torch_threads(n: int):
    """torch's thread pool at ``n`` threads inside the block, as it was after it."""
    threads = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _run_sequence(seq, out, model, camera, init, cfg, span, resume, progress, detections, keypoints, joints3d,
                  profile, notes, keep_flow, proportions=None) -> dict:
    a, b = span
    run = {
        "flowmocap": __version__, "torch": torch.__version__, "python": platform.python_version(),
        "input": str(Path(seq.root).resolve()), "frames": [a, b], "profile": profile, "config": cfg.to_dict(),
        "model": model.name or model.source, "model_source": model.source, "gender": model.gender,
        "camera": camera.to_dict(), "status": "running", **notes,
    }
    fps = seq.meta["fps"]
    cache = FlowCache(out / "flow_cache" if keep_flow else None, method=cfg.flow_method)
    init_events: list[dict] = []

    def mask_of(i: int):
        mask = seq.mask(i)
        if mask is not None and not mask.any():
            init_events.append({"frame": i, "event": "empty mask: no silhouette term for this frame"})
            return None
        return mask

    def detected(i: int) -> tuple | None:
        found = keypoints(i) if (keypoints is not None and cfg.keypoint_weight > 0) else None
        return configured_keypoints(*found, cfg) if found is not None else None

    def detected3d(i: int) -> tuple | None:
        return joints3d(i) if (joints3d is not None and cfg.uses_detector3d) else None

    def flow_of(i: int, mask) -> np.ndarray:
        """The observed flow of frame i: around the person (both frames' masks) when E_f
        uses mask pixels only (``cfg.flow_region``), else of the whole frame."""
        region = None
        if cfg.flow_region and cfg.flow_in_mask and mask is not None and mask.any():
            region = flow_region([mask, seq.mask(i - 1)])
        return cache.flow(i, seq.frame(i), seq.frame(i - 1), region=region)

    def others(i: int):
        """Where other people are seen in frame i (the silhouette's unknown pixels), or None."""
        if not (cfg.occluders_unknown and notes.get("masks") == "automatic" and hasattr(detections, "others")):
            return None  # a user's masks may include what the detector took for someone else
        return detections.others(i)

    # the long runs of frames without the person, where the body is held (TrackerConfig.hold_unseen_frames;
    # _track's gaps say which)
    unseen_runs: dict[int, tuple] = {}
    for g in notes.get("gaps") or []:
        if "held" in str(g.get("why")):
            r = (int(g["frames"][0]), int(g["frames"][1]))
            unseen_runs.update({i: r for i in range(r[0], r[1] + 1)})

    def observe(i: int):
        """Mask and observations of frame i (the person-size fallback for a frame without a
        mask is the tracker's); in a long run without the person, only that."""
        mask = seq.mask(i)
        if i in unseen_runs:
            data = frame_data(None, None, cfg, float("nan"))
            data.unseen = unseen_runs[i]
            return mask, data
        usable = mask if (mask is not None and mask.any()) else None
        data = frame_data(usable, flow_of(i, usable), cfg, float("nan"), detected(i), others(i))
        data.joints3d = detected3d(i)
        return mask, data

    t_start = time.perf_counter()
    log = None
    timings: dict = {}
    try:
        write_run(out, run)
        if resume and (out / "progress.json").exists():
            log, committed = FrameLog.reopen(out)
            timings = dict(committed["state"].get("timings", {}))
            scene = Scene(model, torch.as_tensor(log.header["betas"])[None], camera)
            motion = log.motion()
            stored = {int(f): j for f, j in zip(motion["frame_index"], motion["joints2d"])}
            tracker = SequenceTracker(scene, cfg, _monitor(detections, cfg, stored, others))
            tracker.load_state_dict(committed["state"]["tracker"])
            done = log.rows
        else:
            t0 = time.perf_counter()
            if isinstance(init, KnownStart):
                f = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32)
                scene = Scene(model, f(init.betas).reshape(1, -1), camera)
                s0, s1 = (FrameState(f(init.poses[k]), f(init.trans[k])) for k in (0, 1))
                terms0 = terms1 = {}
                anchored = True
            else:
                d0 = frame_data(mask_of(a), None, cfg, 1.0, unknown=others(a))
                d0.joints3d = detected3d(a)
                m1 = mask_of(a + 1)
                d1 = frame_data(m1, flow_of(a + 1, m1), cfg, d0.person_pixels, detected(a + 1), others(a + 1))
                d1.joints3d = detected3d(a + 1)
                start = initialise(model, camera, init, d0, d1, cfg, proportions)
                scene, s0, s1 = start.scene, start.first, start.second
                if start.shape is not None:
                    run["init_shape"] = start.shape
                if start.stature_held is not None:  # said with the body's stature when the run ends
                    run["init_stature_held"] = start.stature_held
                terms0, terms1 = start.first_terms, start.second_terms
                # E_a holds the track only to a start someone vouched for, unless asked otherwise
                anchored = init.states_rough_pose or cfg.anchor_any_start
            timings["init_s"] = time.perf_counter() - t0
            log = FrameLog.start(out, {"betas": scene.betas[0].numpy(), "gender": scene.model.gender, "fps": fps,
                                       "camera": camera.to_dict(), "energy_names": ENERGY_NAMES})
            tracker = SequenceTracker(scene, cfg, _monitor(detections, cfg, None, others))
            tracker.start(s0, s1, anchored)
            _append(log, scene, a, s0, terms0, float("nan"), init_events)
            _append(log, scene, a + 1, s1, terms1, float("nan"), [])
            log.commit({"tracker": tracker.state_dict(), "timings": timings})
            done = 2
        total_before = float(timings.get("total_s", 0.0))

        def on_frame(res: FrameResult) -> None:
            _append(log, scene, res.frame, res.state, res.terms, res.seconds, res.events)
            timings["total_s"] = total_before + time.perf_counter() - t_start
            log.commit({"tracker": tracker.state_dict(), "timings": timings})

        track_frames(tracker, range(a + done, b), observe, on_frame, progress=progress, done=done)
    except BaseException as e:
        _record_end(out, run, log, timings, "interrupted" if isinstance(e, KeyboardInterrupt) else "failed", e,
                    cfg=cfg)
        raise
    timings["total_s"] = float(timings.get("total_s", 0.0))
    run["tracker"] = tracker.state_dict()  # where it ended (the resume state lived in progress.json)
    run["tracked"] = True  # every frame tracked; "finished" once the steps after tracking are done too
    _record_end(out, run, log, timings, FINISHING, cfg=cfg)
    log.close()
    return run


def _post_steps(out: Path, watch: PersonTrack | None, body: BodyModel, cfg: TrackerConfig, run: dict, joints3d: str,
                say) -> dict:
    """The steps after tracking, each on the finished ``motion.npz`` and each done once:
    the lifter refit (with the detections ``watch``), the stance depth correction and the
    pose smoothing. Returns the run info.

    They run on the settings' ``torch_threads``, as the tracker does: a result is then the same
    to the last bit whatever thread pool the process had (one input tracked alone, or in a
    ``--workers`` process with fewer threads)."""
    if not has_result(out):
        return run
    try:
        run = _synced_steps(out, run)
        with _torch_threads(cfg.torch_threads):
            if cfg.lifter_refit_weight > 0 and watch is not None and joints3d != "off":
                run = _lifter_refit(out, watch, body, cfg, run, say)
            if _inbetween_pending(out, run):
                run = _inbetween(out, body, run, say)
            if _stance_pending(out, cfg, run):
                run = _stance_depth(out, cfg, run, say)
            if cfg.pose_smoothing_s > 0:
                run = _smooth_poses(out, body, cfg, run, say)
        run = _record_body(out, body, cfg, run, say)
    except BaseException as e:  # the steps done so far are in motion.npz; --resume does the rest
        try:
            run = {**json.loads((out / "run.json").read_text()),
                   "status": "interrupted" if isinstance(e, KeyboardInterrupt) else "failed",
                   "error": f"in the steps after tracking: {type(e).__name__}: {e}"}
            write_run(out, run)
        except Exception:  # noqa: BLE001 -- the original error is what the user must see
            pass
        raise
    if run.get("status") != "finished":
        run = {**run, "status": "finished"}
        run.pop("error", None)
        write_run(out, run)
    return run


#: ``run.json``'s status while the steps after tracking run (every frame tracked): a run
#: killed then reads as ``"interrupted"`` (:func:`flowmocap.io.results.read_result`) and
#: ``--resume`` does the steps left.
FINISHING = "finishing"


def _steps_done(motion: dict) -> dict:
    """The steps after tracking applied to this ``motion.npz`` and their records
    (its ``post_steps``, written with the motion they made: one atomic file), by ``run.json``
    key (``lifter_refit``, ``unseen_inbetween``, ``stance_depth``, ``pose_smoothing``)."""
    if "post_steps" not in motion:
        return {}
    try:
        done = json.loads(str(motion["post_steps"]))
    except ValueError:
        return {}
    return done if isinstance(done, dict) else {}


def _with_step(new: dict, key: str, info: dict, before: dict) -> dict:
    """The motion ``new`` a step made from ``before``, with the record of the steps done
    (:func:`_steps_done`: ``before``'s, and ``key: info``)."""
    done = {**_steps_done(before), **_steps_done(new), key: info}
    return {**new, "post_steps": np.array(json.dumps(done, default=json_default))}


def _synced_steps(out: Path, run: dict) -> dict:
    """``run`` with the records of the steps ``motion.npz`` says were applied (a run stopped
    between a step's ``motion.npz`` and its ``run.json`` lost them there), written back."""
    motion, _ = read_result(out)
    missing = {k: v for k, v in _steps_done(motion).items() if run.get(k) != v}
    if missing:
        run = {**run, **missing}
        write_run(out, run)
    return run


def _camera_move_verdict(out: Path, run: dict, say) -> None:
    """Where the floor showed the camera moving (``run.json``'s ``camera_motion``), say whether
    the export frames undo the move: the floor must agree with the fitted body's upright
    direction, and the feet give the camera's height (:mod:`flowmocap.export.motion`)."""
    if not (run.get("camera_motion") or {}).get("moving_sideways") or not has_result(out):
        return
    from flowmocap.export.motion import load_fitted_motion

    m = load_fitted_motion(out, frame="up")
    if m.shifts is None:
        zoom = ("; its turn and zoom are undone instead (the camera's focal length goes from "
                f"{m.zooms.min():.2f} to {m.zooms.max():.2f} times the first frame's)" if m.zooms is not None
                else "; only its turn is undone")
        say(f"the camera's move is not undone: {m.camera_move_refused}{zoom}.")
        return
    centres = -np.einsum("tji,tj->ti", m.turns, m.shifts)
    say(f"export and view undo the camera's move: it stands {m.camera_height_m:.2f} m above the floor (from the "
        f"fitted feet) and its centre goes up to {np.linalg.norm(centres - centres[0], axis=1).max():.2f} m from "
        "where it is in the first tracked frame.")


def _record_body(out: Path, body: BodyModel, cfg: TrackerConfig, run: dict, say) -> dict:
    """``run.json``'s ``body``: the result body's stature (metres, :mod:`flowmocap.body.stature`)
    and the height stated for it (``cfg.body_height_m``, None when not given)."""
    motion, _ = read_result(out)
    try:
        tall = round(stature(body, np.asarray(motion["betas"], np.float64)), 4)
    except ModelFileError:  # a model with no midline to measure (stature_vertices): nothing to record
        tall = None
    info = {"stature_m": tall, "height_given_m": cfg.body_height_m or None}
    if run.get("body") != info:
        run = {**run, "body": info}
        write_run(out, run)
        if tall is not None:
            given = " (as stated)" if cfg.body_height_m else " (one camera's estimate: give --height if you know it)"
            held = run.get("init_stature_held")
            if held and not cfg.body_height_m:
                given = (f" (the first frame's fit made it {held['fitted_m']:.2f} m, which no person is: the mask may "
                         f"hold more than the person; held at {held['held_m']:.2f} m. Give --height if you know it)")
            say(f"the body stands {tall:.2f} m tall{given}")
    return run


def _post_pending(out: Path, cfg: TrackerConfig, joints3d: str, run: dict) -> bool:
    """Whether a finished run was stopped before one of :func:`_post_steps` was done."""
    motion, _ = read_result(out)
    refit = (cfg.lifter_refit_weight > 0 and joints3d != "off" and "poses_tracked" not in motion
             and "lifter_refit" not in run and (out / "detections" / "keypoints.npz").exists())
    unrecorded = any(run.get(k) != v for k, v in _steps_done(motion).items())
    return (refit or _inbetween_pending(out, run) or _stance_pending(out, cfg, run)
            or (cfg.pose_smoothing_s > 0 and "poses_unsmoothed" not in motion)
            or unrecorded or "body" not in run or run.get("status") != "finished")


def _held_runs(run: dict) -> list[tuple[int, int]]:
    """The runs of frames where the body was held, the person not seen (``run["gaps"]``)."""
    return [(int(g["frames"][0]), int(g["frames"][1])) for g in run.get("gaps") or [] if "held" in str(g.get("why"))]


def _inbetween_pending(out: Path, run: dict) -> bool:
    """Whether the held runs are still to be filled in between (:func:`_inbetween`): there
    are some, it is not done, and the pose smoothing (which comes after it) is not either."""
    if not _held_runs(run) or "unseen_inbetween" in run:
        return False
    motion, _ = read_result(out)
    return "poses_unsmoothed" not in motion and "unseen_inbetween" not in _steps_done(motion)


def _inbetween(out: Path, body: BodyModel, run: dict, say) -> dict:
    """The held runs of the finished ``motion.npz`` filled in between the last frame seen
    before and the first seen after, or a walk's cycle carried through them
    (:func:`~flowmocap.fit.smooth.inbetween_unseen`); ``run.json`` records it under
    ``unseen_inbetween``. Returns the run info."""
    from flowmocap.fit.smooth import inbetween_unseen

    return _post_step(out, run, "unseen_inbetween", lambda motion: inbetween_unseen(motion, body, _held_runs(run)),
                      say, inbetween_words)


def inbetween_words(info: dict) -> str:
    """What :func:`~flowmocap.fit.smooth.inbetween_unseen` did (its ``info``), in words for the log."""
    n = len(info["runs"])
    said = (f"filled {info['frames']} frames where the person was not seen in between the poses before and after "
            f"({n} stretch{'es' if n != 1 else ''})")
    if info.get("cycles"):
        sides = {c[3] for c in info["cycles"]}
        said += (f"; through {len(info['cycles'])} of them the walk's cycle seen {' or '.join(sorted(sides))} was "
                 f"carried on (a gait period of {info['cycles'][0][2]} frames)")
    for first, last, walked, side in info.get("stops", []):  # moved too little for a walk all the way
        said += (f"; in frames {first}-{last} the person moved too little to walk all the way: " +
                 (f"the walk stops after {walked} frames and the body settles into the pose seen after"
                  if side == "before" else
                  f"the body settles out of the pose seen before into the walk of the last {walked} frames"))
    return said


def _stance_pending(out: Path, cfg: TrackerConfig, run: dict) -> bool:
    """Whether the stance depth correction is due: on, not done, and the pose smoothing
    (which comes after it) not done either (a run finished before the step existed is
    left as it is)."""
    if cfg.stance_depth_share <= 0 or "stance_depth" in run:
        return False
    motion, _ = read_result(out)
    return "poses_unsmoothed" not in motion and "stance_depth" not in _steps_done(motion)


def _reinit_frames(run: dict, include_eased: bool = False) -> list[int]:
    """The input frame numbers where the tracker re-initialised (``run["events"]``): the
    smoothing steps start again there, except at the seams the lifter refit eased
    (``run["lifter_refit"]["seams_eased"]``), which have no jump left
    (``include_eased``: those too)."""
    frames = [e["frame"] for e in run.get("events", []) if e.get("event") == "re-initialised" and "frame" in e]
    if include_eased:
        return frames
    smooth = set((run.get("lifter_refit") or {}).get("seams_eased", []))
    return [f for f in frames if f not in smooth]


def _reinit_frames_3d(run: dict) -> list[int]:
    """The input frame numbers where the tracker re-initialised on 3D disagreement (the
    event's ``criterion``; a run written before the field existed: its ``why``)."""
    return [e["frame"] for e in run.get("events", []) if e.get("event") == "re-initialised" and "frame" in e
            and e.get("criterion", "3d" if "3D joints" in str(e.get("why", "")) else "image") == "3d"]


def _lifter_refit(out: Path, track: PersonTrack, body: BodyModel, cfg: TrackerConfig, run: dict, say) -> dict:
    """The finished ``motion.npz`` refitted towards the lifter's 3D
    (:func:`~flowmocap.fit.lift_refit.lifter_refit_motion`, ``cfg.lifter_refit_weight``; the
    lifter reads the detections the tracker exchanged left for right as it used them),
    its root depth smoothed again (``cfg.lifter_refit_smooth_depth``, the window of
    ``cfg.depth_smoothing_s``; ``trans_tracked`` stays the tracker's), written atomically;
    ``run.json`` records it under ``lifter_refit``. Returns the run info."""
    from flowmocap.fit.lift_refit import lifter_refit_motion
    from flowmocap.fit.swap import exchanged_frames

    motion, _ = read_result(out)
    if "poses_tracked" in motion:  # already refitted (a resumed run that had finished)
        return run
    t0 = time.perf_counter()
    try:
        refit, info = lifter_refit_motion(motion, track, body, weight=cfg.lifter_refit_weight,
                                          pixel_sigma=cfg.lifter_refit_pixel_sigma or None,
                                          blend=cfg.lifter_refit_blend, iterations=cfg.lifter_refit_iterations,
                                          exchanged=exchanged_frames(run.get("events", [])),
                                          vote_min_frames=cfg.lifter_refit_vote_frames,
                                          vote_min_reach=cfg.lifter_refit_vote_reach,
                                          vote_sources=cfg.lifter_refit_vote_sources,
                                          seams=_reinit_frames(run, include_eased=True),
                                          seam_s=cfg.lifter_refit_seam_s, ease=_reinit_frames_3d(run),
                                          shape_share=cfg.lifter_refit_shape_share,
                                          shape_girth_sigma=cfg.lifter_refit_shape_girth or None,
                                          bridge_s=cfg.lifter_refit_bridge_s,
                                          hidden_share=cfg.lifter_refit_hidden_share,
                                          height=cfg.body_height_m or None,
                                          detector_model=cfg.detector_model,
                                          min_confidence=cfg.lifter_refit_min_confidence,
                                          detector_ray_share=(cfg.detector3d_ray_share
                                                              if cfg.detector3d_source == "mediapipe" else 1.0))
    except InputError as e:  # the tracked motion is written and stays the result
        say(f"the refit towards the lifter's 3D was skipped: {e}")
        run = {**run, "lifter_refit": {"skipped": str(e)}}
        write_run(out, run)
        return run
    if cfg.lifter_refit_smooth_depth and cfg.depth_smoothing_s > 0:  # the refit moved each frame's depth again
        tracked = refit.get("trans_tracked")
        breaks = _reinit_frames({**run, "lifter_refit": info})  # not at the seams just eased
        refit = depth_smoothed_motion(refit, cfg.depth_smoothing_s, breaks=breaks)
        if tracked is not None:
            refit["trans_tracked"] = tracked  # the tracker's own translation, as before the refit
        info["depth_smoothed_s"] = cfg.depth_smoothing_s
    info["seconds"] = round(time.perf_counter() - t0, 2)
    write_motion(out, _with_step(refit, "lifter_refit", info, motion))  # the step and its record in one file
    run = {**run, "lifter_refit": info}
    write_run(out, run)
    say(f"refitted {info['frames_refit']} frames towards the lifter's 3D (share {cfg.lifter_refit_weight:g}, "
        f"{cfg.lifter_refit_blend} blend): "
        f"joints moved {info['mean_move_mm']:.0f} mm, {info['mean_move_px']:.1f} px in the image on average"
        + (f"; {info['limb_frames_voted']} limb-frames mirrored in depth where the {cfg.lifter_refit_vote_sources}"
           f" saw them the other way ({_runs_text(info.get('limb_runs_voted', []))})"
           if info.get("limb_frames_voted") else "")
        + (f"; the jump at {len(info['seams_eased'])} re-initialisation(s) on 3D disagreement eased into the "
           f"{cfg.lifter_refit_seam_s:g} s before" if info.get("seams_eased") else ""))
    if info.get("disagreement_median_mm") is not None:
        stretches = info.get("review_frames", [])
        shown = ", ".join(f"{a}-{b}" if b > a else str(a) for a, b in stretches[:4])
        say(f"the 3D sources (fit, lifter, detector) part by {info['disagreement_median_mm'] / 10:.1f} cm at the "
            f"median joint, {info['disagreement_p90_mm'] / 10:.1f} cm at the 90th percentile; review frames {shown}"
            + (f" and {len(stretches) - 4} more stretches" if len(stretches) > 4 else "")
            + " (run.json 'lifter_refit', motion.npz 'disagreement')")
    return run


def _runs_text(runs: list[dict], most: int = 3) -> str:
    """``"left_elbow->left_wrist frames 50-72, ..."``: the first ``most`` limb runs the
    refit's vote mirrored (``lifter_refit``'s ``limb_runs_voted`` in run.json has them all)."""
    text = ", ".join(f"{r['limb']} frames {r['frames'][0]}-{r['frames'][1]}" for r in runs[:most])
    return text + (f" and {len(runs) - most} more, listed in run.json" if len(runs) > most else "")


def _stance_depth(out: Path, cfg: TrackerConfig, run: dict, say) -> dict:
    """The finished ``motion.npz`` moved so that a foot standing still in the image keeps
    its depth (:func:`~flowmocap.fit.smooth.stance_depth_motion`, ``cfg.stance_depth_*``,
    starting again at every re-initialisation), written atomically; ``run.json`` records
    it under ``stance_depth``. Where the export frames will undo the camera's zoom
    (:mod:`flowmocap.export.motion`), the depth kept is the world's. Returns the run info."""
    from flowmocap.fit.smooth import stance_depth_motion

    def zooms(motion):  # where the export frames undo the camera's zoom (no move undone instead): the world's depth
        if not (run.get("camera_motion") or {}).get("zooming"):
            return None
        from flowmocap.export.motion import load_fitted_motion

        return load_fitted_motion(out, frame="up", cache_world=False).zooms  # the rows of this motion.npz

    return _post_step(out, run, "stance_depth", lambda motion: stance_depth_motion(
        motion, cfg.stance_depth_share, speed=cfg.stance_speed, min_s=cfg.stance_min_s,
        window_s=cfg.stance_window_s, breaks=_reinit_frames(run), zooms=zooms(motion)), say,
        lambda info: f"a foot standing still kept its depth in {info['frames_in_stance']} frames: the body moved "
                     f"{info['mean_shift_mm']:.0f} mm along the camera ray on average")


def _smooth_poses(out: Path, body: BodyModel, cfg: TrackerConfig, run: dict, say) -> dict:
    """The finished ``motion.npz`` with its poses and translation smoothed over
    ``cfg.pose_smoothing_s`` (:func:`~flowmocap.fit.smooth.pose_smoothed_motion`, starting
    again at every re-initialisation), written atomically; the motion before is kept as
    ``poses_unsmoothed`` / ``trans_unsmoothed`` and ``run.json`` records it under
    ``pose_smoothing``. A motion smoothed already (a resumed run that had finished) is left."""
    motion, _ = read_result(out)
    if "poses_unsmoothed" in motion:
        return run
    return _post_step(out, run, "pose_smoothing", lambda m: pose_smoothed_motion(
        m, body, cfg.pose_smoothing_s, breaks=_reinit_frames(run)), say,
        lambda info: f"smoothed the motion over {cfg.pose_smoothing_s:g} s: joints moved {info['mean_move_mm']:.0f} "
                     f"mm, {info['mean_move_px']:.1f} px in the image on average", motion=motion)


def _post_step(out: Path, run: dict, key: str, apply, say, describe, motion: dict | None = None) -> dict:
    """One step after tracking: ``apply(motion) -> (motion, info)`` on the finished
    ``motion.npz`` (read unless given), the result written atomically, ``info`` (with its
    ``seconds``) recorded in ``run.json`` under ``key`` and ``describe(info)`` said.
    Returns the run info."""
    if motion is None:
        motion, _ = read_result(out)
    t0 = time.perf_counter()
    new, info = apply(motion)
    info["seconds"] = round(time.perf_counter() - t0, 2)
    write_motion(out, _with_step(new, key, info, motion))  # the step and its record in one file: done once
    run = {**run, key: info}
    write_run(out, run)
    say(describe(info))
    return run


def _record_end(out: Path, run: dict, log: FrameLog | None, timings: dict, status: str,
                error: BaseException | None = None, cfg: TrackerConfig | None = None) -> None:
    """Write ``motion.npz`` (the committed frames, the root's depth smoothed over
    ``cfg.depth_smoothing_s``: :func:`~flowmocap.fit.smooth.depth_smoothed_motion`) and
    ``run.json`` with the final status, events and timings. On a failure this is best
    effort (the original error matters more, and the commit point already holds the
    finished frames)."""
    try:
        run["status"] = status
        if error is not None:
            run["error"] = f"{type(error).__name__}: {error}" if str(error) else type(error).__name__
        else:
            run.pop("error", None)
        if log is not None:
            recs = log.records()
            frame_s = [float(x) for x in recs["seconds"] if np.isfinite(x)]
            run["events"] = log.events()
            run["timings"] = {**timings, "frame_s": frame_s}
            if frame_s:
                run["timings"]["s_per_frame_median"] = float(np.median(frame_s))
            if log.rows:
                motion = log.motion()
                if cfg is not None and cfg.depth_smoothing_s > 0:
                    motion = depth_smoothed_motion(motion, cfg.depth_smoothing_s, breaks=_reinit_frames(run))
                write_motion(out, motion)
        else:
            run.setdefault("events", [])
            run["timings"] = dict(timings)
        write_run(out, run)
    except Exception:
        if error is None:
            raise


def _monitor(detections: PersonTrack | None, cfg: TrackerConfig, stored: dict | None,
             others=None) -> ReinitMonitor | None:
    return ReinitMonitor(detections, cfg, stored_joints2d=stored, others=others) if detections is not None else None
