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

import json
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from flowmocap.body import BodyModel, load_body_model
from flowmocap.errors import DataError, InputError, NoPersonError
from flowmocap.fit.config import PROFILES, TrackerConfig
from flowmocap.fit.init import InitSpec, initialise, parse_init
from flowmocap.fit.objective import ENERGY_NAMES, FrameState, Scene, frame_data, keypoint_observation
from flowmocap.fit.reinit import ReinitMonitor
from flowmocap.fit.tracker import FrameResult, KnownStart, SequenceTracker, track_frames
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.io.results import read_result, write_motion, write_run
from flowmocap.io.sequence import Sequence, load_sequence
from flowmocap.io.video import VIDEO_SUFFIXES, default_camera, load_video
from flowmocap.synth import read_camera_json
from flowmocap.version import __version__
from flowmocap.vision import FlowCache
from flowmocap.vision.auto import PersonTrack, auto_init, detect_joints3d, detect_sequence, first_person_frame, frame_runs
from flowmocap.vision.person import describe_person, parse_person

__all__ = ["Result", "track", "load_result", "parse_frame_range"]


@dataclass
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
        """``(T, 24, 3)`` joint positions, metres."""
        return self.motion["joints3d"]

    @property
    def joints2d(self) -> np.ndarray:
        """``(T, 24, 2)`` projected joints, pixels."""
        return self.motion["joints2d"]

    @property
    def frame_index(self) -> np.ndarray:
        """``(T,)`` the input's frame numbers of the rows."""
        return self.motion["frame_index"]

    @property
    def fps(self) -> float:
        return float(self.motion["fps"])

    @property
    def gender(self) -> str:
        return str(self.motion["gender"])

    @property
    def camera(self) -> PinholeCamera:
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
    """Read a result folder written by :func:`track`.

    Raises:
        DataError: the folder holds no (readable) result.
    """
    motion, run = read_result(path)
    return Result(Path(path), motion, run)


def parse_frame_range(frames: str | tuple | None, n: int) -> tuple[int, int]:
    """``(a, b)`` from ``"A:B"`` (either side may be empty), ``(A, B)`` or None (all ``n``
    frames); at least 2 frames. Raises InputError otherwise."""
    if frames is None:
        return 0, n
    if isinstance(frames, str):
        try:
            a, _, b = frames.partition(":")
            a = int(a) if a else 0
            b = int(b) if b else n
        except ValueError:
            raise InputError(f"frames must look like A:B (e.g. 0:100); got {frames!r}.") from None
    else:
        try:
            a, b = (int(v) for v in frames)
        except (TypeError, ValueError):
            raise InputError(f"frames must be 'A:B' or a pair (A, B); got {frames!r}.") from None
    if not (0 <= a < b <= n) or b - a < 2:
        raise InputError(f"frames {a}:{b} do not select at least 2 of the {n} frames.")
    return a, b


def track(source: str | Path, out: str | Path, init="auto", masks: str | Path | None = None,
          camera=None, config: dict | str | Path | None = None, frames: str | tuple | None = None,
          resume: bool = False, progress: bool = True, profile: str | None = None,
          model: str | Path | BodyModel = "default", gender: str = "neutral", flow: str | None = None,
          max_size: int | None = 1280, reinit: bool = True, joints3d: str = "auto",
          log: Callable[[str], None] | None = print, person: str | int | tuple = "largest") -> Result:
    """Track the person in ``source`` and write the result folder ``out``.

    Args:
        source: a video file, a folder of frames, or a sequence folder (``frames/``,
            optional ``masks/`` and ``camera.json``).
        out: the result folder (``motion.npz``, ``run.json``, ``input.json``,
            ``detections/``, ``flow_cache/``).
        init: ``"auto"`` (2D joints found by MediaPipe on the first frame with a whole
            person), an ``init.json`` path or dict (:mod:`flowmocap.fit.init`), or a
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
            the last with the person).
        resume: continue an interrupted run in ``out`` (same input and settings).
        progress: show progress bars.
        profile: ``"video"`` or ``"synthetic"`` (:data:`~flowmocap.fit.config.PROFILES`);
            None chooses ``video`` when the masks come from the detector, else ``synthetic``.
        model: ``"default"`` (the bundled body), an SMPL ``.pkl``/``.npz`` or folder, or a
            loaded :class:`~flowmocap.body.BodyModel`; gender: for the model file.
        flow: the observed-flow method (default: the settings' ``flow_method``).
        max_size: scale video frames down so the long side is at most this many pixels
            (None or 0: keep the size).
        reinit: re-initialise from the detector where tracking fails (when it runs).
        joints3d: ``"auto"``: the detector's 3D joints pull each limb's direction in depth
            (``E_d``), running the detector for them alone if nothing else needs it;
            ``"off"``: no ``E_d``.
        log: where the one-line messages go (None: nowhere).
        person: who to track when the detector runs and several people are in view:
            ``"largest"`` (default: the person seen biggest, nearest and longest), a
            rank ``N`` (0 = the largest, 1 = the next, ...) or a pixel ``"x,y"`` of the
            input's frames at their original size (before ``max_size``): the person
            whose box contains, or lies nearest to, it in the first frame they appear
            in (:func:`~flowmocap.vision.person.parse_person`). Recorded in ``run.json``
            (``person``).

    Returns:
        the :class:`Result`.

    Raises:
        flowmocap.errors.FlowMocapError: bad input (its message says what to do); the
            frames finished before the error stay in ``out``.
    """
    say = log if log is not None else (lambda _msg: None)
    src, out = Path(source), Path(out)
    if not src.exists():
        raise DataError(f"{src} does not exist; give a video file, a folder of frames or a sequence folder.")
    if joints3d not in ("auto", "off"):
        raise InputError(f"joints3d must be 'auto' or 'off'; got {joints3d!r}.")
    choice = parse_person(person)
    if (out / "motion.npz").exists() and not resume:
        raise InputError(f"{out} already holds a result; pass resume=True (--resume) to continue it or choose "
                         "another folder.")
    user_masks = None if masks in (None, "auto") else masks
    is_video = src.is_file() or src.suffix.lower() in VIDEO_SUFFIXES
    seq = load_video(src, masks=user_masks, max_side=max_size or None) if is_video else load_sequence(src, masks=user_masks)
    if len(seq) < 2:
        raise InputError(f"{src} holds only {len(seq)} frame; tracking needs at least 2 frames "
                         "(the flow is measured between neighbouring frames).")
    auto_masks = masks == "auto" or seq.masks is None
    auto_init = isinstance(init, str) and init == "auto"
    cam, camera_source = _camera(camera, seq, src)
    if profile is None:
        profile = "video" if auto_masks else "synthetic"
        why = "automatic masks" if auto_masks else "the input's own masks"
    else:
        why = "chosen"
    if profile not in PROFILES:
        raise InputError(f"unknown profile {profile!r}; use one of {sorted(PROFILES)}.")
    cfg = TrackerConfig.load(config, profile=profile, flow_method=flow)
    say(f"settings: profile '{profile}' ({why})" + (f", then {config}" if isinstance(config, (str, Path)) else
                                                    ", then the given overrides" if config else ""))
    body = model if isinstance(model, BodyModel) else load_body_model(model, gender=gender)

    detections = None
    if choice[0] != "largest" and not (auto_masks or auto_init):
        raise InputError(f"person={describe_person(choice)!r} chooses among the people the detector finds, but with "
                         "your own init and masks the detector does not choose anyone; leave person at 'largest' "
                         "(the init and masks say who is tracked).")
    if choice[0] == "point":  # the user's pixel is in the original frames; the detector sees the scaled ones
        scale = float(seq.meta.get("scale", 1.0))
        choice = ("point", (choice[1][0] * scale, choice[1][1] * scale))
    if auto_masks or auto_init:  # the detections also drive re-initialisation
        say(f"finding the person in {len(seq)} frames (MediaPipe pose; stored in {out / 'detections'}) ...")
        detections = detect_sequence(seq, out, progress=progress,
                                     person="largest" if choice[0] == "largest" else choice[1])
        if auto_masks:
            seq.masks = list(detections.mask_paths)
    notes: dict = {"camera_source": camera_source,
                   "masks": "automatic" if auto_masks else str(user_masks or "input"),
                   "init": "automatic" if auto_init else ("known start" if isinstance(init, KnownStart)
                                                          else str(init) if not isinstance(init, dict) else "given"),
                   "profile": profile}
    if auto_init:
        spec, (a, b), notes["frame_range"] = _auto_start(detections, frames, len(seq), out, seq.size)
    else:
        spec = init if isinstance(init, KnownStart) else parse_init(init, *seq.size)
        a, b = parse_frame_range(frames, len(seq))
    if detections is not None:
        notes["detections"] = {k: detections.info[k] for k in ("detector", "frames_with_person", "no_person",
                                                               "ignored_people")}
        notes["person"] = {"asked": describe_person(parse_person(person)),
                           **detections.info.get("person", {"choice": describe_person(choice)})}
        if choice[0] == "point":
            notes["person"]["pixel_in_tracked_frames"] = [round(v, 1) for v in choice[1]]
    if is_video:
        notes["video"] = {k: seq.meta[k] for k in ("fps", "variable_frame_rate", "rotation", "decoded_size", "size",
                                                   "scale", "focal_35mm", "timestamps") if k in seq.meta}
        notes["video"]["max_side"] = max_size or None
    out.mkdir(parents=True, exist_ok=True)
    (out / "input.json").write_text(json.dumps(notes, indent=2))

    keypoints = j3d = None
    if detections is not None:  # the detector's joints also pull the body (E_j) and say each limb's depth (E_d)
        keypoints = lambda i: detections.smpl_joints(i) if i < len(detections) and detections.found[i] else None  # noqa: E731
        j3d = lambda i: detections.smpl_joints3d(i, cam)  # noqa: E731
    elif joints3d == "auto" and cfg.uses_detector3d:
        say(f"finding the person's 3D joints in {len(seq)} frames (MediaPipe pose; for E_d) ...")
        j3d, notes["joints3d"] = detect_joints3d(seq, out, cam, progress=progress)
        (out / "input.json").write_text(json.dumps(notes, indent=2))
    if joints3d == "off":
        j3d = None
    monitor = detections if (detections is not None and reinit) else None
    run = _run(seq, out, body, cam, spec, cfg, (a, b), resume, progress, monitor, keypoints, j3d, profile)
    if detections is not None:
        notes["gaps"] = [{"frames": r, "why": "no person found: tracked by flow alone, no silhouette term"}
                         for r in frame_runs([i for i in range(a, b) if not detections.found[i]])]
    run.update(notes)
    write_run(out, run)
    t = run["timings"]
    reinits = sum(1 for e in run["events"] if e.get("event") == "re-initialised")
    say(f"tracked frames {a}:{b} of {len(seq)} into {out} ({t.get('s_per_frame_median', float('nan')):.2f} s per "
        f"frame median; {len(run['events'])} recorded events, {reinits} re-initialisations)")
    say(f"camera: {camera_source}")
    if "frame_range" in notes:
        say(notes["frame_range"])
    return load_result(out)


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
        return (PinholeCamera.from_focal(w, h, focal * scale),
                f"focal {focal:g} px" + (f" (x {scale:.4g} for the scaled frames)" if scale != 1.0 else ""))
    elif seq.camera is not None:
        return seq.camera, f"{src / 'camera.json'}"
    else:
        return default_camera(w, h, seq.meta.get("focal_35mm"))
    if (cam.width, cam.height) != (w, h):
        raise InputError(f"the camera ({note}) is for {cam.width}x{cam.height} images but the frames are {w}x{h}"
                         + (" (scaled by max_size / --max-size; pass 0 to keep the video's size)"
                            if scale != 1.0 else "") + ".")
    return cam, note


def _auto_start(detections: PersonTrack, frames, n: int, out: Path, size) -> tuple:
    """Automatic initialisation: the InitSpec, the frame range and a sentence about it."""
    if frames:
        a, b = parse_frame_range(frames, n)
    else:
        found = [i for i in range(n) if detections.found[i]]
        a, b = 0, (found[-1] + 1 if found else n)
    first = first_person_frame(detections, a)
    if first is None or first >= b - 1:
        raise NoPersonError(f"no frame in {a}:{b} shows a whole enough person to start on (hips, shoulders and "
                            "at least 8 of the 12 main joints, each with confidence >= 0.5) before the last frame; "
                            "give --init init.json with the 2D joints of the first frame.")
    init = auto_init(detections, first)
    (out / "init_auto.json").write_text(json.dumps(init, indent=2))
    note = f"frames {first}:{b}"
    if first > a:
        note += f"; started at frame {first}, the first with a confidently detected person (frames {a}..{first - 1} skipped)"
    if not frames and b < n:
        note += f"; stopped after frame {b - 1}, the last with the person (frames {b}..{n - 1} skipped)"
    return parse_init(init, *size), (first, b), note


class ResultWriter:
    """Per-frame results, written to ``motion.npz`` + ``run.json`` on :meth:`flush`."""

    def __init__(self, out_dir: Path, scene: Scene, fps: float, run: dict):
        self.out_dir = Path(out_dir)
        self.scene = scene
        self.fps = fps
        self.run = run
        self.poses, self.trans, self.j3d, self.j2d, self.energies, self.index = [], [], [], [], [], []

    def add(self, frame: int, state: FrameState, terms: dict) -> None:
        with torch.no_grad():
            out, _, _ = self.scene.forward(state.pose, state.trans)
            j3 = out.joints[0]
            self.j3d.append(j3.numpy())
            self.j2d.append(self.scene.camera.project(j3).numpy())
        self.poses.append(state.pose.numpy().astype(np.float32))
        self.trans.append(state.trans.numpy().astype(np.float32))
        self.energies.append([terms.get(n, np.nan) for n in ENERGY_NAMES])
        self.index.append(frame)

    def flush(self) -> None:
        write_motion(self.out_dir, {
            "poses": np.asarray(self.poses, np.float32).reshape(-1, 72),
            "trans": np.asarray(self.trans, np.float32).reshape(-1, 3),
            "betas": self.scene.betas[0].numpy().astype(np.float32),
            "gender": np.array(self.scene.model.gender),
            "fps": np.array(float(self.fps)),
            "camera": np.array(json.dumps(self.scene.camera.to_dict())),
            "joints3d": np.asarray(self.j3d, np.float32).reshape(-1, 24, 3),
            "joints2d": np.asarray(self.j2d, np.float32).reshape(-1, 24, 2),
            "energies": np.asarray(self.energies, np.float64).reshape(-1, len(ENERGY_NAMES)),
            "energy_names": np.array(ENERGY_NAMES),
            "frame_index": np.asarray(self.index, np.int64),
        })
        write_run(self.out_dir, self.run)

    def restore(self, motion: dict) -> None:
        self.poses = list(motion["poses"])
        self.trans = list(motion["trans"])
        self.j3d = list(motion["joints3d"])
        self.j2d = list(motion["joints2d"])
        # by name: a run written by an older version may lack later terms' columns
        names = [str(n) for n in motion.get("energy_names", ENERGY_NAMES)]
        col = {n: k for k, n in enumerate(names)}
        self.energies = [[float(e[col[n]]) if n in col else float("nan") for n in ENERGY_NAMES]
                         for e in motion["energies"]]
        self.index = [int(i) for i in motion["frame_index"]]


def _run(seq: Sequence, out: Path, model: BodyModel, camera: PinholeCamera, init: InitSpec | KnownStart,
         cfg: TrackerConfig, span: tuple[int, int], resume: bool, progress: bool, detections: PersonTrack | None,
         keypoints, joints3d, profile: str) -> dict:
    """Initialise (or restore) and track ``span`` of ``seq`` into ``out``; returns run.json's contents."""
    threads = torch.get_num_threads()
    torch.set_num_threads(int(cfg.torch_threads))
    try:
        return _run_sequence(seq, out, model, camera, init, cfg, span, resume, progress, detections, keypoints,
                             joints3d, profile)
    finally:
        torch.set_num_threads(threads)


def _run_sequence(seq, out, model, camera, init, cfg, span, resume, progress, detections, keypoints, joints3d,
                  profile) -> dict:
    a, b = span
    run = {
        "flowmocap": __version__, "torch": torch.__version__, "python": platform.python_version(),
        "input": str(seq.root), "frames": [a, b], "profile": profile, "config": cfg.to_dict(),
        "model": model.name or model.source, "model_source": model.source, "gender": model.gender,
        "camera": camera.to_dict(), "status": "running", "events": [], "timings": {},
    }
    fps = seq.meta.get("fps", 30.0)
    cache = FlowCache(out / "flow_cache", method=cfg.flow_method)

    def mask_of(i: int):
        mask = seq.mask(i)
        if mask is not None and not mask.any():
            run["events"].append({"frame": i, "event": "empty mask: no silhouette term for this frame"})
            return None
        return mask

    def detected(i: int) -> tuple | None:
        found = keypoints(i) if (keypoints is not None and cfg.keypoint_weight > 0) else None
        return keypoint_observation(*found) if found is not None else None

    def detected3d(i: int) -> tuple | None:
        return joints3d(i) if (joints3d is not None and cfg.uses_detector3d) else None

    def observe(i: int):
        """Mask and observations of frame i (the person-size fallback for a frame without a
        mask is the tracker's)."""
        mask = seq.mask(i)
        usable = mask if (mask is not None and mask.any()) else None
        data = frame_data(usable, cache.flow(i, seq.frame(i), seq.frame(i - 1)), cfg, float("nan"), detected(i))
        data.joints3d = detected3d(i)
        return mask, data

    t_start = time.perf_counter()
    restored = resume and (out / "motion.npz").exists()
    if restored:
        motion, old = read_result(out)
        for key in ("input", "frames", "config"):
            if old.get(key) != json.loads(json.dumps(run[key])):
                raise InputError(f"cannot resume: {key} differs from the interrupted run in {out} "
                                 f"({old.get(key)!r} vs {run[key]!r}); start a new result folder instead.")
        if not isinstance(old.get("tracker"), dict):
            raise InputError(f"cannot resume the run in {out}: it was written by an older flowmocap and holds no "
                             "tracker state; start a new result folder instead.")
        run = old
        run["status"] = "running"
        scene = Scene(model, torch.as_tensor(motion["betas"])[None], camera)
        writer = ResultWriter(out, scene, fps, run)
        writer.restore(motion)
        stored = {int(f): j for f, j in zip(motion["frame_index"], motion["joints2d"])}
        tracker = SequenceTracker(scene, cfg, _monitor(detections, cfg, stored))
        tracker.load_state_dict(run["tracker"])
        done = len(motion["poses"])
    else:
        out.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        if isinstance(init, KnownStart):
            f = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32)  # noqa: E731
            scene = Scene(model, f(init.betas).reshape(1, -1), camera)
            s0, s1 = (FrameState(f(init.poses[k]), f(init.trans[k])) for k in (0, 1))
            terms0 = terms1 = {}
            anchored = True
        else:
            d0 = frame_data(mask_of(a), None, cfg, 1.0)
            d0.joints3d = detected3d(a)
            d1 = frame_data(mask_of(a + 1), cache.flow(a + 1, seq.frame(a + 1), seq.frame(a)), cfg,
                            d0.person_pixels, detected(a + 1))
            d1.joints3d = detected3d(a + 1)
            start = initialise(model, camera, init, d0, d1, cfg)
            scene, s0, s1, terms0, terms1 = start.scene, start.first, start.second, start.first_terms, start.second_terms
            run["timings"]["init_s"] = time.perf_counter() - t0
            anchored = init.states_rough_pose  # E_a holds the track only to a start someone vouched for
        writer = ResultWriter(out, scene, fps, run)
        writer.add(a, s0, terms0)
        writer.add(a + 1, s1, terms1)
        tracker = SequenceTracker(scene, cfg, _monitor(detections, cfg, None))
        tracker.start(s0, s1, anchored)
        run["tracker"] = tracker.state_dict()
        writer.flush()
        done = 2
    frame_times = run["timings"].setdefault("frame_s", [])

    def on_frame(res: FrameResult) -> None:
        run["events"].extend(res.events)
        writer.add(res.frame, res.state, res.terms)
        frame_times.append(res.seconds)
        run["timings"]["s_per_frame_median"] = float(np.median(frame_times))
        run["tracker"] = tracker.state_dict()
        writer.flush()

    track_frames(tracker, range(a + done, b), observe, on_frame, progress=progress, done=done)
    run["status"] = "finished"
    run["timings"]["total_s"] = run["timings"].get("total_s", 0.0) + time.perf_counter() - t_start
    writer.flush()
    return run


def _monitor(detections: PersonTrack | None, cfg: TrackerConfig, stored: dict | None) -> ReinitMonitor | None:
    return ReinitMonitor(detections, cfg, stored_joints2d=stored) if detections is not None else None
