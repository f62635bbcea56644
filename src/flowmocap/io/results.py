"""Result folders: what :func:`flowmocap.track` writes, how it commits each frame, and how
readers see it.

A result folder holds

- ``run.json``: what ran (input, settings, camera, model, the run's fingerprint), its
  ``status`` (``"preparing"``, ``"running"``, ``"finishing"`` while the steps after tracking
  run, ``"finished"``, ``"failed"``, ``"interrupted"``) and, once the run has ended, its
  events and timings. Written when the run starts and when it ends. ``motion.npz``'s
  ``post_steps`` records the steps after tracking applied to it, in the same file as the
  motion they made, so none is applied twice or lost from ``run.json`` by a stop between
  the two files.
- while the run goes on, three files written frame by frame:

  - ``frames.bin``: one fixed-size binary record per tracked frame, appended (numpy
    structured dtype :func:`record_dtype`; float32 parameters and joints, float64
    energies and seconds, int64 frame number);
  - ``events.jsonl``: what happened on the way, one JSON object a line, appended;
  - ``progress.json``: **the commit point**. It is replaced atomically after every frame
    and says how many records and event bytes are final (``rows``, ``events_bytes``),
    and holds the tracker's state after the last of them and the result's constant
    parts (``header``: betas, gender, fps, camera, energy names). Records or event lines
    beyond it are from a frame that was not committed: readers ignore them and a resumed
    run cuts them off and redoes that frame. So a run killed at any instant resumes from
    a state that matches its motion exactly, and a frame costs a constant amount of
    writing however long the video is.
- ``motion.npz``: all frames in one file for other tools (layout below), written when
  the run ends (finished, failed or interrupted by an exception). A finished run then
  removes the three progress files (``progress.json`` first: from then on ``motion.npz``
  is the result).

``motion.npz``: ``poses (T, 72)`` axis-angle radians, ``trans (T, 3)`` metres,
``betas (10,)``, ``gender``, ``fps``, ``camera`` (JSON of PinholeCamera.to_dict()),
``joints3d (T, 24, 3)`` metres (camera/world frame of the camera), ``joints2d (T, 24, 2)``
pixels, ``energies (T, K)`` and ``energy_names (K,)``, ``frame_index (T,)`` (the input's
frame numbers); with ``depth_smoothing_s`` (the default) ``trans``, ``joints3d`` and
``joints2d`` are the depth-smoothed ones and ``trans_tracked (T, 3)`` the tracker's own
(:func:`flowmocap.fit.smooth.depth_smoothed_motion`), while the progress files, and so
:func:`read_result` of an unfinished run, hold the tracker's own frames. After the run the
pipeline may replace ``motion.npz`` again: the lifter refit (``poses_tracked`` added, and
``betas_tracked`` where it refitted the shape too) and
the pose smoothing (``poses_unsmoothed`` and ``trans_unsmoothed`` added,
:func:`flowmocap.fit.smooth.pose_smoothed_motion`). :func:`read_result` gives the same arrays for a run that is still going
or was killed.
"""

from __future__ import annotations

import json
import math
import os
import zipfile
from pathlib import Path

import numpy as np

from flowmocap.atomic import atomic_write, atomic_write_npz
from flowmocap.errors import DataError

#: The files of a result folder that flowmocap writes (a folder holding other files is
#: not replaced without ``force``).
RESULT_FILES = ("run.json", "input.json", "init_auto.json", "motion.npz", "progress.json", "frames.bin",
                "events.jsonl", ".lock", ".lock.json")
FORMAT = 2


def write_motion(out_dir: Path, arrays: dict) -> None:
    """Atomically write ``out_dir/motion.npz`` from a dict of arrays."""

    atomic_write_npz(Path(out_dir) / "motion.npz", **arrays)


def write_run(out_dir: Path, info: dict) -> None:
    """Atomically write ``out_dir/run.json``."""
    write_json(Path(out_dir) / "run.json", info)


def write_json(path: Path, info) -> None:
    """Atomically write ``info`` as JSON (numpy values and paths allowed) to ``path``."""

    def write(tmp):
        Path(tmp).write_text(json.dumps(info, indent=2, default=json_default))

    atomic_write(Path(path), write)


def json_default(x):
    """``json.dumps(default=...)`` for numpy arrays and numbers and paths (lists, Python
    numbers, strings); TypeError for anything else.

    Args:
        x: an ``np.ndarray`` of any shape (to nested lists of that shape), a numpy scalar
            (to a Python number) or a ``Path`` (to a string).
    """
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def record_dtype(num_energies: int) -> np.dtype:
    """The numpy structured dtype of one ``frames.bin`` record (little-endian, packed):
    ``poses (72,) f4`` radians, ``trans (3,) f4`` metres, ``joints3d (24, 3) f4`` metres,
    ``joints2d (24, 2) f4`` pixels, ``energies (K,) f8``, ``frame_index i8``,
    ``seconds f8`` (the frame's tracking time)."""
    return np.dtype([("poses", "<f4", (72,)), ("trans", "<f4", (3,)), ("joints3d", "<f4", (24, 3)),
                     ("joints2d", "<f4", (24, 2)), ("energies", "<f8", (num_energies,)), ("frame_index", "<i8"),
                     ("seconds", "<f8")])


class FrameLog:
    """The frame-by-frame part of a result folder being written (see the module
    docstring): :meth:`append` records and events, then :meth:`commit` the state.

    Args:
        out_dir: the result folder.
        header: the result's constant parts: ``betas (10,)``, ``gender``, ``fps``,
            ``camera`` (dict), ``energy_names (K,)``.
    """

    def __init__(self, out_dir: str | Path, header: dict):
        self.out_dir = Path(out_dir)
        self.header = {"betas": [float(b) for b in np.asarray(header["betas"]).ravel()],
                       "gender": str(header["gender"]), "fps": float(header["fps"]),
                       "camera": header["camera"], "energy_names": [str(n) for n in header["energy_names"]]}
        self.dtype = record_dtype(len(self.header["energy_names"]))
        self.rows = 0
        self.events_bytes = 0
        self.pending: list = []
        self.pending_events: list[dict] = []

    @classmethod
    def start(cls, out_dir: str | Path, header: dict) -> FrameLog:
        """A new, empty log (any old progress files are removed)."""
        log = cls(out_dir, header)
        for name in ("progress.json", "frames.bin", "events.jsonl"):
            (log.out_dir / name).unlink(missing_ok=True)
        return log

    @classmethod
    def reopen(cls, out_dir: str | Path) -> tuple[FrameLog, dict]:
        """The log of an interrupted run and its last commit (``progress.json``'s dict),
        with anything written after that commit cut off.

        Raises:
            DataError: no or unreadable progress.
        """
        out_dir = Path(out_dir)
        progress = read_progress(out_dir)
        log = cls(out_dir, progress["header"])
        log.rows, log.events_bytes = int(progress["rows"]), int(progress["events_bytes"])
        _truncate(out_dir / "frames.bin", log.rows * log.dtype.itemsize)
        _truncate(out_dir / "events.jsonl", log.events_bytes)
        return log, progress

    def append(self, poses, trans, joints3d, joints2d, energies, frame: int, seconds: float,
               events: list[dict] = ()) -> None:
        """Queue one frame's record (``poses (72,)`` radians, ``trans (3,)`` metres,
        ``joints3d (24, 3)`` metres, ``joints2d (24, 2)`` pixels, ``energies (K,)`` in
        :attr:`header`'s order; ``frame`` the input frame number, ``seconds`` its tracking
        time) and its events for the next :meth:`commit`."""
        rec = np.zeros((), self.dtype)
        rec["poses"], rec["trans"], rec["joints3d"], rec["joints2d"] = poses, trans, joints3d, joints2d
        rec["energies"], rec["frame_index"], rec["seconds"] = energies, frame, seconds
        self.pending.append(rec)
        self.pending_events.extend(events)

    def commit(self, state: dict) -> None:
        """Write the queued records and events, then ``progress.json`` with ``state`` (the
        tracker's state after the last queued frame, JSON-serialisable): the frames are
        final once this returns."""
        # the counts move on only once progress.json says so: a failed write (a full disk)
        # leaves this log at its last commit, as a reader or --resume sees the folder
        rows, events_bytes = self.rows + len(self.pending), self.events_bytes
        if self.pending:
            with open(self.out_dir / "frames.bin", "ab") as f:
                f.write(np.stack(self.pending).tobytes())
                f.flush()
                os.fsync(f.fileno())
        if self.pending_events:
            text = "".join(json.dumps(e, default=json_default) + "\n" for e in self.pending_events).encode()
            with open(self.out_dir / "events.jsonl", "ab") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
            events_bytes += len(text)
        write_json(self.out_dir / "progress.json", {"format": FORMAT, "rows": rows, "events_bytes": events_bytes,
                                                    "state": state, "header": self.header})
        self.rows, self.events_bytes = rows, events_bytes
        self.pending, self.pending_events = [], []

    def records(self) -> np.ndarray:
        """The committed records, ``(rows,)`` of :attr:`dtype`."""
        return _read_records(self.out_dir, self.dtype, self.rows)

    def events(self) -> list[dict]:
        """The committed events."""
        return _read_events(self.out_dir, self.events_bytes)

    def motion(self) -> dict:
        """The committed frames as ``motion.npz``'s arrays."""
        return _motion(self.header, self.records())

    def close(self) -> None:
        """Remove the progress files once ``motion.npz`` and ``run.json`` hold everything
        (``progress.json`` first: it is what makes a reader use the log)."""
        for name in ("progress.json", "frames.bin", "events.jsonl"):
            (self.out_dir / name).unlink(missing_ok=True)


def read_progress(out_dir: str | Path) -> dict:
    """``progress.json`` of a result folder (the last commit of a run that is going on or
    was interrupted). Raises DataError when absent or unreadable."""
    path = Path(out_dir) / "progress.json"
    try:
        progress = json.loads(path.read_text())
        if not isinstance(progress, dict) or not isinstance(progress.get("header"), dict):
            raise ValueError("it holds no JSON object with a 'header' object")
        for key in ("rows", "events_bytes", "state", "header"):
            progress[key]
        for key in ("rows", "events_bytes"):
            if not isinstance(progress[key], int) or isinstance(progress[key], bool) or progress[key] < 0:
                raise ValueError(f"its {key!r} is {progress[key]!r}, not a count")
    except FileNotFoundError:
        raise DataError(f"{out_dir} holds no run in progress ({path.name} is missing).") from None
    except (ValueError, KeyError, TypeError, OSError) as e:
        raise DataError(f"{path} is unreadable ({e}); the run cannot be resumed: track the input again into this "
                        "folder with --force, or into a new folder.") from None
    return progress


def _truncate(path: Path, size: int) -> None:
    have = path.stat().st_size if path.exists() else 0
    if have < size:
        raise DataError(f"{path} holds {have} bytes but its last commit says {size}; the result folder was changed "
                        "by something else. Start a new result folder.")
    if have > size:
        with open(path, "r+b") as f:
            f.truncate(size)


def _read_records(out_dir: Path, dtype: np.dtype, rows: int) -> np.ndarray:
    path = Path(out_dir) / "frames.bin"
    if rows == 0:
        return np.zeros(0, dtype)
    try:
        recs = np.fromfile(path, dtype=dtype, count=rows)
    except (OSError, ValueError) as e:
        raise DataError(f"{path} is unreadable ({e}).") from None
    if len(recs) < rows:
        raise DataError(f"{path} holds {len(recs)} frames but its last commit says {rows}; the result is damaged: "
                        "track the input again into this folder with --force (or into a new folder).")
    return recs


def _read_events(out_dir: Path, size: int) -> list[dict]:
    if size == 0:
        return []
    with open(Path(out_dir) / "events.jsonl", "rb") as f:
        text = f.read(size).decode()
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def _motion(header: dict, recs: np.ndarray) -> dict:
    return {
        "poses": recs["poses"].reshape(-1, 72), "trans": recs["trans"].reshape(-1, 3),
        "betas": np.asarray(header["betas"], np.float32), "gender": np.array(header["gender"]),
        "fps": np.array(float(header["fps"])), "camera": np.array(json.dumps(header["camera"])),
        "joints3d": recs["joints3d"].reshape(-1, 24, 3), "joints2d": recs["joints2d"].reshape(-1, 24, 2),
        "energies": recs["energies"].reshape(len(recs), len(header["energy_names"])),
        "energy_names": np.array(header["energy_names"]),
        "frame_index": recs["frame_index"].astype(np.int64),
    }


def has_result(out_dir: str | Path) -> bool:
    """Whether ``out_dir`` holds tracked frames (finished or not) to resume or read."""
    out_dir = Path(out_dir)
    return (out_dir / "progress.json").exists() or (out_dir / "motion.npz").exists()


def is_result_folder(out_dir: str | Path) -> bool:
    """Whether ``out_dir`` was made by flowmocap (a ``run.json`` it wrote, or a result)."""
    out_dir = Path(out_dir)
    if has_result(out_dir):
        return True
    try:
        run = json.loads((out_dir / "run.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(run, dict) and "flowmocap" in run


def decoded_otherwise_words(run: dict, meta: dict, source) -> str | None:
    """A note where this flowmocap shows a video's frames otherwise than the run that made
    the result did (``run.json`` ``video`` against the reader's ``meta``: a mirroring display
    matrix or non-square pixels, which flowmocap before 2026-12 did not apply); None where
    they agree or ``source`` is no video."""
    video = run.get("video")
    if not isinstance(video, dict) or "mirrored" not in meta:
        return None
    was = (bool(video.get("mirrored", False)), float(video.get("sample_aspect_ratio", 1.0) or 1.0))
    now = (bool(meta.get("mirrored", False)), float(meta.get("sample_aspect_ratio", 1.0) or 1.0))
    if was == now:
        return None
    return (f"note: {source}'s frames are now shown {'mirrored' if now[0] else 'unmirrored'} with pixels "
            f"{now[1]:.3g} wide, but the result was tracked on frames shown {'mirrored' if was[0] else 'unmirrored'} "
            f"with pixels {was[1]:.3g} wide (an older flowmocap): the body is drawn over frames it was not tracked "
            "on; track the input again with --force")


def unfinished_words(out_dir: str | Path, run: dict, frames: int) -> str | None:
    """What a reader of a result (``export``, ``render``, ``view``) should say when its run
    has not finished, or None when it has.

    Args:
        out_dir: the result folder, for the message.
        run: its ``run.json`` as :func:`read_result` gives it (a stopped run reads
            ``"interrupted"``).
        frames: how many frames the reader got.

    Returns:
        a sentence starting ``"note: "``, or None for a finished run (or one that records no
        status).
    """
    status = run.get("status")
    if status in (None, "finished"):
        return None
    steps = "the steps after tracking (the lifter refit, the smoothing)"
    if status in ("running", "preparing"):
        return (f"note: the run in {out_dir} is still going: this is the {frames} frames tracked so far, without "
                f"{steps}; read it again once the run has finished.")
    if status == "finishing":
        return (f"note: the run in {out_dir} is still doing {steps}: this {frames}-frame motion may lack some of "
                "them; read it again once the run has finished.")
    why = f" ({run['error']})" if status == "failed" and run.get("error") else ""
    return (f"note: the run in {out_dir} is {status}{why}: this is the {frames} frames tracked before it stopped, "
            f"without {steps} where they did not run; `flowmocap track INPUT --out {out_dir} --resume` finishes it.")


#: What ``flowmocap render`` writes into ``RESULT/render/`` by default: output -> file name.
RENDER_OUTPUTS = {
    "video": "overlay.mp4",
    "figure1": "figure1.png",
    "traces": "joint_traces.png",
    "plot": "energies.png",
}


#: The file of a ``track --person all`` folder (:func:`flowmocap.batch.track_people`) that
#: lists the people found and each one's result folder (``person0``, ``person1``, ...).
PEOPLE_MANIFEST = "people.json"


#: How the body was filled in where the person was not seen (:func:`unseen_frames`), in words.
UNSEEN_WORDS = {"flow": "tracked by flow alone", "held": "held at the last seen pose",
                "between": "filled in between the poses before and after"}


def unseen_frames(run: dict) -> dict[int, str]:
    """``{input frame: how}`` for the frames where the person was not seen (``run.json``'s
    ``gaps``): ``"flow"`` (tracked by flow alone), ``"held"`` (held at the last seen pose) or
    ``"between"`` (held, then filled in between the poses before and after, the run's
    ``unseen_inbetween``); :data:`UNSEEN_WORDS` says each in words."""
    between = {(int(a), int(b)) for a, b in (run.get("unseen_inbetween") or {}).get("runs", [])}
    out = {}
    for g in run.get("gaps") or []:
        a, b = int(g["frames"][0]), int(g["frames"][1])
        how = ("between" if (a, b) in between else "held") if "held" in str(g.get("why")) else "flow"
        out.update({i: how for i in range(a, b + 1)})
    return out


def people_results(root: str | Path) -> list[tuple[str, Path]]:
    """The tracked people of a ``track --person all`` folder: ``[(name, result folder)]`` by
    rank, those with a readable result (a person not yet tracked, or whose run failed
    before its first frame, is left out); ``[]`` for a folder without ``people.json``.

    Raises:
        DataError: an unreadable ``people.json``, or none of its people tracked yet.
    """
    root = Path(root)
    path = root / PEOPLE_MANIFEST
    if not path.exists():
        return []
    try:
        names = [str(n) for n in json.loads(path.read_text())["people"]]
    except (OSError, ValueError, KeyError, TypeError):
        raise DataError(f"{path} is not a list of people written by `flowmocap track --person all`; track again into "
                        "this folder to rewrite it.") from None
    found = []
    for name in sorted(names, key=lambda n: int(n.removeprefix("person")) if n.removeprefix("person").isdigit()
                       else 1 << 30):
        try:
            read_result(root / name)
        except DataError:  # not (yet) tracked
            continue
        found.append((name, root / name))
    if not found:
        raise DataError(f"none of the people in {root} has a tracked result yet; run `flowmocap track INPUT --out "
                        f"{root} --person all` first.")
    return found


#: The farthest a result's root may be from the camera, metres: further, the numbers are not
#: a tracked person's but a damaged file's (and the floor's fit overflows).
MAX_TRANS_M = 1.0e4


def checked_motion_arrays(result_dir: str | Path, motion: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(poses (T, 72) radians, trans (T, 3) metres, betas (B,))`` float64 of the motion
    :func:`read_result` gave (whose shapes and values :func:`check_motion` has checked),
    for readers that need the body's parameters: all three there, and ``betas`` not empty.

    Raises:
        DataError: naming ``motion.npz`` and saying to track again, when they are not.
    """
    where = Path(result_dir) / "motion.npz"
    for key in ("poses", "trans", "betas"):
        if key not in motion:
            raise DataError(f"{where} has no {key!r}; it is not a flowmocap result.")
    poses = np.asarray(motion["poses"], np.float64).reshape(-1, 72)
    trans = np.asarray(motion["trans"], np.float64).reshape(-1, 3)
    betas = np.asarray(motion["betas"], np.float64).reshape(-1)
    if betas.size == 0:
        raise DataError(f"{where} 'betas' is empty, expected the body's shape coefficients (10,); the result is "
                        "damaged: track the input again with --force.")
    return poses, trans, betas


def check_motion(result_dir: str | Path, motion: dict) -> None:
    """Check a result's motion arrays as every reader needs them (:func:`read_result`), each
    where present: ``poses`` ``(T, 72)``, ``trans`` ``(T, 3)`` within :data:`MAX_TRANS_M` of
    the camera and ``joints3d`` ``(T, 24, 3)`` finite; ``betas`` finite; ``joints2d``
    ``(T, 24, 2)``; ``frame_index`` ``(T,)`` whole numbers; ``fps`` a positive number;
    ``camera`` the camera's JSON. (What a reader needs present it asks for itself, e.g.
    :func:`checked_motion_arrays` for the body's parameters.)

    Raises:
        DataError: naming ``motion.npz`` and saying to track again, when they are not so.
    """
    where = Path(result_dir) / "motion.npz"
    redo = "the result is damaged: track the input again with --force."
    shapes = {"poses": (72,), "trans": (3,), "joints3d": (24, 3), "joints2d": (24, 2), "frame_index": ()}
    T = None
    for key, tail in shapes.items():
        if key not in motion:
            continue
        try:
            a = np.asarray(motion[key], np.float64)
        except (TypeError, ValueError):
            raise DataError(f"{where} '{key}' is not numeric (dtype {np.asarray(motion[key]).dtype}); {redo}") from None
        if a.size == 0 and T in (None, 0):
            T = 0
            continue
        first = T is None
        if first:
            T = len(a) if a.ndim else -1
        if a.shape != (T, *tail):  # the first array present sets T; the others must match it
            want = ("(T, " + ", ".join(map(str, tail)) + ")" if tail else "(T,)") if first else str((T, *tail))
            raise DataError(f"{where} '{key}' is {a.shape}, expected {want} (one per frame); {redo}")
        if key != "joints2d" and not np.isfinite(a).all():
            bad = np.flatnonzero(~np.isfinite(a.reshape(T, -1)).all(1))
            raise DataError(f"{where} '{key}' holds NaN or infinite values (first at row {int(bad[0])}); {redo}")
        if key == "frame_index" and not np.array_equal(a, np.round(a)):
            raise DataError(f"{where} 'frame_index' holds numbers that are not frame numbers; {redo}")
        if key == "trans":
            far = np.flatnonzero(np.linalg.norm(a, axis=1) > MAX_TRANS_M)
            if len(far):
                raise DataError(f"{where} 'trans' puts the body {np.linalg.norm(a[far[0]]):.3g} m from the camera at "
                                f"row {int(far[0])}, more than {MAX_TRANS_M:g} m; {redo}")
    if "betas" in motion:
        try:
            betas = np.asarray(motion["betas"], np.float64)
        except (TypeError, ValueError):
            raise DataError(f"{where} 'betas' is not numeric (dtype {np.asarray(motion['betas']).dtype}); "
                            f"{redo}") from None
        if not np.isfinite(betas).all():
            raise DataError(f"{where} 'betas' holds NaN or infinite values; {redo}")
    if "fps" in motion:
        try:
            fps = float(motion["fps"])
        except (TypeError, ValueError):
            fps = float("nan")
        if not (math.isfinite(fps) and fps > 0):
            raise DataError(f"{where} 'fps' is {motion['fps']!r}, not a frame rate; {redo}")
    if "camera" in motion:
        try:
            cam = json.loads(str(motion["camera"]))
        except ValueError as e:
            raise DataError(f"{where} 'camera' is not the camera's JSON ({e}); {redo}") from None
        if not isinstance(cam, dict):
            raise DataError(f"{where} 'camera' is not the camera's JSON object; {redo}")


def check_run(result_dir: str | Path, run: dict) -> None:
    """Check the parts of a result's ``run.json`` that the readers compute with: ``gaps``
    (a list of ``{"frames": [first, last], ...}``) and ``camera_motion``'s per-frame arrays
    (``frames``, ``rotvecs``, ``floor_rotvecs``, ``shifts``, ``zooms``, ``floor_normal``: numbers,
    finite).

    Raises:
        DataError: naming ``run.json`` and saying to track again, when they are not so.
    """
    where = Path(result_dir) / "run.json"
    redo = "the result is damaged: track the input again with --force."
    gaps = run.get("gaps")
    if gaps is not None:
        ok = isinstance(gaps, list)
        for g in gaps if ok else []:
            frames = g.get("frames") if isinstance(g, dict) else None
            ok = ok and isinstance(frames, list) and len(frames) == 2 and all(
                isinstance(f, int) and not isinstance(f, bool) for f in frames)
        if not ok:
            raise DataError(f"{where} 'gaps' is not a list of {{'frames': [first, last]}}; {redo}")
    cm = run.get("camera_motion")
    if cm is None:
        return
    if not isinstance(cm, dict):
        raise DataError(f"{where} 'camera_motion' is not an object; {redo}")
    for key in ("frames", "rotvecs", "floor_rotvecs", "shifts", "zooms", "floor_normal"):
        if cm.get(key) is None:
            continue
        try:
            a = np.asarray(cm[key], np.float64)
        except (TypeError, ValueError):
            raise DataError(f"{where} 'camera_motion' '{key}' is not numbers; {redo}") from None
        if not np.isfinite(a).all():
            raise DataError(f"{where} 'camera_motion' '{key}' holds NaN or infinite values; {redo}")


def result_folder(value) -> Path:
    """A result folder argument as a ``Path``: a path (``str`` or ``os.PathLike``), or a
    :class:`flowmocap.Result` (its ``path``).

    Raises:
        InputError: anything else (pathlib would raise a bare ``TypeError``).
    """
    path = getattr(value, "path", None) if not isinstance(value, (str, os.PathLike)) else value
    if not isinstance(path, (str, os.PathLike)):
        from flowmocap.errors import InputError

        raise InputError(f"a result folder is a path (a str or a Path) or a flowmocap.Result; got "
                         f"{type(value).__name__}.")
    return Path(path)


def read_result(out_dir: str | Path) -> tuple[dict, dict]:
    """``(motion arrays, run info)`` of a result folder, finished or not: a run that is
    still going, or was killed, gives its committed frames and events (see the module
    docstring); its ``status`` reads ``"interrupted"`` when no process holds the folder.

    Raises:
        DataError: missing or unreadable files.
    """
    out_dir = result_folder(out_dir)
    if not out_dir.exists():
        raise DataError(f"result folder {out_dir} does not exist; give the --out folder of `flowmocap track`.")
    if not out_dir.is_dir():
        raise DataError(f"{out_dir} is a file, not a result folder; give the --out folder of `flowmocap track`.")
    try:
        run = json.loads((out_dir / "run.json").read_text())
        if not isinstance(run, dict):
            raise DataError(f"{out_dir / 'run.json'} holds a JSON {type(run).__name__}, not a flowmocap run; the "
                            "result is damaged: track the input again into this folder with --force (or into "
                            "a new folder).")
        if (out_dir / "progress.json").exists():
            progress = read_progress(out_dir)
            recs = _read_records(out_dir, record_dtype(len(progress["header"]["energy_names"])), progress["rows"])
            motion = _motion(progress["header"], recs)
            if not run.get("events"):
                run["events"] = _read_events(out_dir, int(progress["events_bytes"]))
            run.setdefault("timings", {}).setdefault("frame_s", recs["seconds"].tolist())
        else:
            if not (out_dir / "motion.npz").exists() and "flowmocap" in run:
                raise DataError(f"{out_dir} holds no tracked frames yet (its run is {run.get('status')!r}"
                                f"{': ' + run['error'] if run.get('error') else ''}).")
            with np.load(out_dir / "motion.npz", allow_pickle=False) as z:
                motion = {k: z[k] for k in z.files}
    except FileNotFoundError as e:
        hint = ""
        if (out_dir / PEOPLE_MANIFEST).exists():
            hint = (f"; it holds the people of `track --person all`: give one of its person folders "
                    f"({out_dir / 'person0'}, ...)")
        elif (out_dir / "batch.json").exists():  # flowmocap.batch.MANIFEST
            hint = "; it holds a batch of results: give one of its result folders"
        raise DataError(f"{out_dir} is not a flowmocap result folder ({Path(e.filename).name} is missing){hint}."
                        ) from None
    except (ValueError, OSError, zipfile.BadZipFile, EOFError, KeyError, TypeError) as e:  # a truncated or empty
        # motion.npz: the third and fourth; a progress file with a key missing or of the wrong kind: the last two
        raise DataError(f"{out_dir} holds an unreadable result ({type(e).__name__}: {e}); the result is damaged: "
                        "track the input again into this folder with --force (or into a new folder).") from None
    check_motion(out_dir, motion)
    check_run(out_dir, run)
    if run.get("status") in ("running", "preparing", "finishing"):  # "finishing": the steps after tracking
        from flowmocap.io.lock import is_locked

        if not is_locked(out_dir):
            run["status"] = "interrupted"
    return motion, run
