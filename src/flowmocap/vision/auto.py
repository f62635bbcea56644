"""Automatic person masks and 2D joints for a whole video, stored in the result folder.

:func:`detect_sequence` runs a :class:`~flowmocap.vision.detect.PersonDetector` over every
frame, keeps one person, cleans the masks and writes::

    OUT/detections/masks/000000.png ...   the person's mask per frame (0 / 255; all 0 = no person)
    OUT/detections/keypoints.npz          keypoints (T, K, 2) px, confidence (T, K), found (T,),
                                          names (K,), box (T, 4) px, world (T, K, 3) m (the
                                          detector's 3D guess, NaN where it gives none)
    OUT/detections/detections.json        detector, size, frames with no person, people ignored
    OUT/detections/others/000000.png ...  where someone nearer the camera is seen in a frame (0 / 255):
                                          the bodies of the people whose feet are lower in the
                                          image, outside the kept person's mask; only frames
                                          with some, none for a video of one person
    OUT/detections/people/000000.png ...  where anyone other than the kept person is seen, nearer
                                          or further (0 / 255; only frames with some): not
                                          background, so the camera's motion leaves them out

A rerun (or ``--resume``) with the same detector and frames reuses them. :func:`auto_init`
turns one frame's keypoints into an ``init.json`` dict (the schema of
:mod:`flowmocap.fit.init`), with the body's facing direction guessed from the shoulders,
hips, nose and ears.

Keeping one person: the detector follows a person from frame to frame; the detections
are split into tracks wherever one does not continue the previous one
(:func:`~flowmocap.vision.person.same_person`), and the main track is kept: the largest
sum over its frames of box height x (box bottom / image height), i.e. the person seen
biggest, nearest (feet lowest in the image) and longest. The other tracks' frames count
as "no person" (someone else, e.g. in the background).

Choosing another person (``person=N`` or ``"x,y"``, :func:`~flowmocap.vision.person.parse_person`):
the tracks are ranked by that score and one is chosen; since the searcher saw that
person with someone else blanked out (and not in every frame), the tracking detector
then runs over the video again with every other track's mask blanked
(:func:`follow_person`), so it locks onto the chosen person and gives them its full
quality (augmented masks, every frame it can).

The same steps serve the multi-view reference (:mod:`flowmocap.eval.real3d`):
:func:`find_people` (candidates per frame, up to ``max_people``), :func:`split_tracks`,
:func:`track_scores` and :func:`follow_person` for each person.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from flowmocap.errors import InputError, NoPersonError
from flowmocap.memory import release_free_memory
from flowmocap.vision.detect import KEYPOINT_NAMES, SMPL_KEYPOINTS, PersonDetector
from flowmocap.vision.person import (box_iou, choose_person, clean_mask, describe_person, parse_person, person_box,
                                     same_person)

__all__ = ["PersonTrack", "detect_sequence", "detect_joints3d", "detect_for_given_masks", "load_detections", "auto_init",
           "first_person_frame", "frame_runs", "facing_rotvec", "MIN_INIT_JOINTS", "find_people", "split_tracks",
           "link_tracks", "appearance", "appearance_distance", "LINK_MAX_S", "LINK_MAX_DISTANCE",
           "track_scores", "follow_person", "Candidate"]

#: Frames between two hand-backs of freed C-heap pages in a detection pass (:mod:`flowmocap.memory`).
TRIM_EVERY = 50
#: Run the default (MediaPipe) detectors of :func:`detect_sequence` in processes of their
#: own (:mod:`flowmocap.vision.detect_worker`): the tracking process never loads MediaPipe,
#: whose graphs hold ~0.5 GB and grow while they run, and a killed pass keeps the stretches
#: it finished. False: in this process (stand-in detectors in tests).
DETECT_IN_CHILD = True
#: Frames one detector process looks at before a fresh one takes over: the augmented
#: detector grows by ~30-50 kB a frame while it runs (MediaPipe's, not given back until
#: its process ends), so a 10-minute video in one process would end ~0.7 GB larger.
DETECT_CHUNK = 1000
#: Frames before its stretch a detector process looks at first, results not kept: MediaPipe
#: follows the person and smooths their landmarks over time, so a detector started cold
#: at a stretch's first frame would differ there from one that ran through.
DETECT_WARM_UP = 30
#: Confident SMPL keypoints a frame needs to initialise the body on it.
MIN_INIT_JOINTS = 8
#: Keypoint confidence that counts as confident.
CONFIDENT = 0.5


@dataclass
class PersonTrack:
    """The kept person's detections in every frame of a sequence.

    Attributes:
        keypoints: ``(T, K, 2)`` pixels, names :data:`~flowmocap.vision.detect.KEYPOINT_NAMES`.
        confidence: ``(T, K)``; all 0 in frames without the person.
        found: ``(T,)`` bool, the person is in the frame.
        mask_paths: the ``T`` mask PNGs (an all-zero mask where the person is not found).
        info: the contents of ``detections.json``.
        world: ``(T, K, 3)`` metres, the detector's 3D keypoints
            (:attr:`~flowmocap.vision.detect.Detection.world`), NaN where it gave none;
            None for detections stored without them.
        others_dir: the folder of the other people's regions (:meth:`others`), or None
            (detections stored before it, or made without a search for other people).
        people_dir: the folder of every other person's region (:meth:`people`), or None
            (detections stored before it).
    """

    keypoints: np.ndarray
    confidence: np.ndarray
    found: np.ndarray
    mask_paths: list[Path]
    info: dict = field(default_factory=dict)
    world: np.ndarray | None = None
    others_dir: Path | None = None
    people_dir: Path | None = None

    def __len__(self) -> int:
        return len(self.found)

    def mask(self, i: int) -> np.ndarray:
        """``(H, W)`` bool mask of frame ``i``."""
        import cv2

        return cv2.imread(str(self.mask_paths[i]), cv2.IMREAD_GRAYSCALE) > 0

    def others(self, i: int) -> np.ndarray | None:
        """``(H, W)`` bool: the pixels of frame ``i`` where people nearer the camera than
        the kept one are seen (their feet lower in the image), outside the kept person's
        mask (their bodies as :func:`follow_person` blanks them, :func:`others_region`), or
        None where nobody is. They may hide the kept person there, so the silhouette term
        treats these pixels as unknown (:func:`~flowmocap.fit.energies.silhouette_target`);
        someone further away hides nothing and stays background."""
        return self._region(self.others_dir, i)

    def people(self, i: int) -> np.ndarray | None:
        """``(H, W)`` bool: the pixels of frame ``i`` where anyone other than the kept person
        is seen, nearer the camera or further (:func:`others_region` of all the frame's
        people), or None where nobody is or the detections were stored without them. Not
        background: the camera's motion (:func:`~flowmocap.vision.camera_motion.camera_motion`)
        leaves them out, or someone walking past would look like the camera turning or
        moving."""
        return self._region(self.people_dir, i)

    def _region(self, folder: Path | None, i: int) -> np.ndarray | None:
        if folder is None or i < 0 or i >= len(self):
            return None
        p = Path(folder) / f"{i:06d}.png"
        if not p.exists():
            return None
        import cv2

        m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        return None if m is None or not m.any() else m > 0

    def _in_smpl_order(self, values: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``i``'s per-keypoint ``values (K, d)`` and confidences as ``(24, d)`` and
        ``(24,)`` in SMPL joint order (0 for the joints the detector does not give)."""
        from flowmocap.body.skeleton import JOINT_NAMES

        out = np.zeros((24, values.shape[-1]))
        conf = np.zeros(24)
        for k, name in enumerate(SMPL_KEYPOINTS):
            j = JOINT_NAMES.index(name)
            out[j] = values[k]
            conf[j] = self.confidence[i, k]
        return out, conf

    def smpl_joints(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(24, 2)`` pixels and ``(24,)`` confidences of frame ``i`` in SMPL joint order
        (0 for the joints the detector does not give)."""
        return self._in_smpl_order(self.keypoints[i], i)

    def smpl_joints3d(self, i: int, camera=None, ray_share: float = 1.0) -> tuple[np.ndarray, np.ndarray] | None:
        """The detector's 3D joints of frame ``i`` in SMPL joint order: ``(24, 3)`` metres
        relative to the middle of the hips and ``(24,)`` confidences (0 for the joints it
        does not give), or None when the frame has none.

        The detector's axes are those of the ray through the person (x right, y down, z
        along the ray); with the ``camera`` (a
        :class:`~flowmocap.geometry.camera.PinholeCamera`) they are turned into the
        camera's own axes (:meth:`~flowmocap.geometry.camera.PinholeCamera.ray_rotation`
        through the middle of the detected hips, or of the confident keypoints; ``ray_share``
        of that turn, see :attr:`~flowmocap.fit.config.TrackerConfig.detector3d_ray_share`).
        """
        if self.world is None or i >= len(self) or not self.found[i] or not np.isfinite(self.world[i]).all():
            return None
        j3d, conf = self._in_smpl_order(self.world[i], i)
        if camera is not None:
            hips = [KEYPOINT_NAMES.index("left_hip"), KEYPOINT_NAMES.index("right_hip")]
            use = hips if (self.confidence[i, hips] > 0).all() else np.nonzero(self.confidence[i] > 0)[0]
            if len(use):
                u, v = self.keypoints[i, use].mean(0)
                j3d = j3d @ camera.ray_rotation(float(u), float(v), ray_share).T
        return j3d, conf


def _mask_dir(out_dir: Path) -> Path:
    return Path(out_dir) / "detections" / "masks"


def _others_dir(out_dir: Path) -> Path:
    return Path(out_dir) / "detections" / "others"


def _people_dir(out_dir: Path) -> Path:
    return Path(out_dir) / "detections" / "people"


#: A candidate counts as someone else in a frame (:func:`others_region`) when less than
#: this share of its body lies in the kept person's mask.
OTHER_MAX_INSIDE = 0.5


def others_region(cands: list, mask: np.ndarray, bodies: list | None = None) -> np.ndarray:
    """The pixels of one frame where people other than the kept one are seen.

    Args:
        cands: the frame's :class:`Candidate` s (:func:`find_people`), the kept person's
            own among them or not.
        mask: ``(H, W)`` bool, the kept person's mask.
        bodies: the candidates' :func:`_body_region` s where already drawn (else drawn here).

    Returns:
        ``(H, W)`` bool: the union of the bodies (:func:`_body_region`) of the candidates
        with less than :data:`OTHER_MAX_INSIDE` of their body inside ``mask`` (the kept
        person's own detection and fragments of it are not someone else), less ``mask``.
    """
    m = np.asarray(mask, bool)
    out = np.zeros(m.shape, bool)
    for k, c in enumerate(cands):
        body = _body_region(c, m.shape) if bodies is None else bodies[k]
        n = int(body.sum())
        if n and (body & m).sum() < OTHER_MAX_INSIDE * n:
            out |= body
    return out & ~m


def load_detections(out_dir: str | Path, detector_name: str | None = None, num_frames: int | None = None,
                    size: tuple[int, int] | None = None) -> PersonTrack | None:
    """Stored detections of ``out_dir``, or None when absent, unreadable (a damaged file is
    computed anew, not an error) or made for other input/settings (``detector_name``,
    ``num_frames``, ``size = (width, height)`` pixels; None: not checked)."""
    d = Path(out_dir) / "detections"
    try:
        info = json.loads((d / "detections.json").read_text())
        with np.load(d / "keypoints.npz", allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        T = len(arrays["found"])
        K = len(KEYPOINT_NAMES)
        usable = (isinstance(info, dict) and arrays["found"].shape == (T,)
                  and arrays["keypoints"].shape == (T, K, 2) and arrays["confidence"].shape == (T, K)
                  and ("world" not in arrays or arrays["world"].shape == (T, K, 3)))
    except Exception:  # noqa: BLE001 -- a damaged cache (BadZipFile, EOFError, bad JSON, ...): computed anew
        return None
    if not usable:
        return None
    if detector_name is not None and info.get("detector") != detector_name:
        return None
    if num_frames is not None and info.get("frames") != num_frames:
        return None
    if size is not None and list(info.get("size", [])) != list(size):
        return None
    paths = [_mask_dir(out_dir) / f"{i:06d}.png" for i in range(len(arrays["found"]))]
    if not all(p.exists() for p in paths):
        return None
    others = _others_dir(out_dir)
    return PersonTrack(arrays["keypoints"], arrays["confidence"], arrays["found"].astype(bool), paths, info,
                       arrays.get("world"), others if info.get("others_stored") else None,
                       _people_dir(out_dir) if info.get("people_stored") else None)


def detect_sequence(seq, out_dir: str | Path, detector: PersonDetector | None = None, progress: bool = True,
                    reuse: bool = True, searcher: PersonDetector | None | str = "default",
                    person="largest", model: str = "full", search_dir: str | Path | None = None) -> PersonTrack:
    """Masks and keypoints of one person in every frame of ``seq``, stored in ``out_dir``.

    A detector that tracks follows the first person it finds. To find the others, the
    ``searcher`` (a second detector) looks at every frame with the found person's body
    blanked out; all detections are then split into people by continuity and the main
    person kept, or the one ``person`` chooses (see the module docstring).

    Args:
        seq: anything with ``len(seq)``, ``seq.frame(i) -> (H, W, 3) uint8 RGB`` and
            ``seq.size = (W, H)`` (a :class:`~flowmocap.io.sequence.Sequence`).
        out_dir: the result folder (detections go to ``out_dir/detections``).
        detector: None: :class:`~flowmocap.vision.detect.MediaPipePoseDetector` (with its
            mask augmentation); ``"unaugmented"``: MediaPipe without it (the searcher as
            with None); ``"plain"``: MediaPipe without it and no searcher; each
            runs in processes of its own (:data:`DETECT_IN_CHILD`, :class:`_InChildren`)
            when ``seq`` can be pickled. A detector object runs in this process.
        progress: show a progress bar.
        reuse: return stored detections made by the same detectors for the same frames
            and person.
        searcher: the second detector; ``"default"``: MediaPipe without augmentation when
            ``detector`` is the default, else none; None: look for one person only.
        person: ``"largest"`` (default), a rank ``N`` or a pixel ``"x,y"`` / ``(x, y)`` of
            ``seq``'s frames (:func:`~flowmocap.vision.person.parse_person`). ``0`` is
            the largest. Any other choice, and the largest where someone else shares
            a quarter of their frames (:data:`LARGEST_FOLLOW_SHARE`), runs the detector
            a second time (:func:`follow_person`).
        model: the landmark model of the MediaPipe detectors made here
            (:data:`~flowmocap.vision.detect.MODELS`: "full" or "heavy"); not used with a
            detector object.
        search_dir: a folder where the search for everyone (the pass before the chosen
            person is followed, the same whoever is chosen) is stored by stretches and kept,
            to be read by later passes over the same ``seq`` that choose another person
            (:func:`flowmocap.batch.track_people` gives one for all the people of an
            input); None: inside ``out_dir/detections``, removed when the pass ends. Used
            when the detector runs in processes of its own (the default).

    Raises:
        NoPersonError: no frame shows a person.
        InputError: a bad ``person``, or a rank beyond the people found; MediaPipe not installed.
        DetectorError: the detector's process died (the stretches it finished are kept
            and a rerun goes on from there).
    """
    choice = parse_person(person)
    if choice == ("index", 0):
        choice = ("largest", None)
    out_dir = Path(out_dir)
    from flowmocap.vision.detect import MediaPipePoseDetector, check_model_files

    if isinstance(detector, str) and detector not in ("plain", "unaugmented"):
        raise InputError(f"detector must be None, 'plain', 'unaugmented' or a detector object; got {detector!r}.")
    plain = detector == "plain"
    augment = detector is None
    if detector is None or isinstance(detector, str):  # here, before any pass: a failure is clear and early
        check_model_files(model)
    if (detector is None or isinstance(detector, str)) and searcher in ("default", None) and DETECT_IN_CHILD \
            and _picklable(seq):
        spec = {"augment": augment, "search": searcher == "default" and not plain, "model": model}
        base = MediaPipePoseDetector.describe(augment=spec["augment"], model=model)
        if spec["search"]:
            base += f"+search:{MediaPipePoseDetector.describe(augment=False, model=model)}"
        name = base + _choice_suffix(choice, spec["search"])
        passes = _InChildren(seq, out_dir, spec, name, progress, base=base, search_dir=search_dir)
        track = _detect_sequence(seq, out_dir, passes, name, choice, reuse)
        passes.clear()  # the stretches are in keypoints.npz and the masks now
        return track
    own = detector is None or isinstance(detector, str)  # made here: closed here once the pass is over
    if own:
        detector = MediaPipePoseDetector(augment=augment, model=model)
        if searcher == "default" and not plain:
            searcher = MediaPipePoseDetector(augment=False, model=model)
    if searcher == "default":
        searcher = None
    name = detector.name + (f"+search:{searcher.name}" if searcher is not None else "")
    name += _choice_suffix(choice, searcher is not None)
    try:
        return _detect_sequence(seq, out_dir, _InProcess(seq, detector, searcher, progress), name, choice, reuse)
    finally:
        if own:  # MediaPipe's graphs hold ~0.5 GB (the augmented detector's four): not kept while tracking
            for d in (detector, searcher):
                getattr(d, "close", lambda: None)()
        release_free_memory()


def _picklable(seq) -> bool:
    """Whether ``seq`` can be sent to a detector process (a
    :class:`~flowmocap.io.sequence.Sequence` or a video's can)."""
    import pickle

    try:
        pickle.dumps(seq)
    except Exception:  # noqa: BLE001 -- any object that cannot travel stays in this process
        return False
    return True


class _InProcess:
    """The detection passes of :func:`detect_sequence` with detectors of this process."""

    def __init__(self, seq, detector: PersonDetector, searcher, progress: bool):
        self.seq, self.detector, self.searcher, self.progress = seq, detector, searcher, progress

    def find(self) -> list[list[Candidate]]:
        return find_people(self.seq, self.detector, self.searcher, progress=self.progress)

    def follow(self, cands, tracks, chosen: int) -> list[Candidate | None]:
        return follow_person(self.seq, self.detector, cands, tracks, chosen, progress=self.progress)


class _InChildren:
    """The detection passes of :func:`detect_sequence` with MediaPipe in processes of its
    own, :data:`DETECT_CHUNK` frames each (:mod:`flowmocap.vision.detect_worker`).

    Each stretch's candidates are stored in ``OUT/detections/chunks/`` as it finishes, so
    a pass that is stopped (Ctrl-C, ``kill``, the detector's process killed for memory)
    goes on from the first stretch not stored; :meth:`clear` removes them once the
    detections are written. ``spec``: ``{"augment": bool, "search": bool, "model": str}``.
    ``name`` names the detections (``base``, the detectors, and the person chosen); the
    search's stretches are tagged with ``base`` and the input alone, and stored in
    ``search_dir`` where one is given (kept there for passes that choose another person).
    """

    def __init__(self, seq, out_dir: Path, spec: dict, name: str, progress: bool, base: str | None = None,
                 search_dir: str | Path | None = None):
        self.seq, self.spec, self.name, self.progress = seq, spec, name, progress
        self.base = name if base is None else base
        self.folder = _chunk_dir(out_dir)
        self.search_folder = self.folder if search_dir is None else Path(search_dir)

    def find(self) -> list[list[Candidate]]:
        if not any(self.search_folder.glob("find-*.npz")):  # a new pass: no person followed in an older one
            for old in self.folder.glob("follow-*.npz"):
                old.unlink()
        return self._chunks("find", f"{self.base}|{getattr(self.seq, 'root', '')}", lambda a, b, got: {})

    def follow(self, cands, tracks, chosen: int) -> list[Candidate | None]:
        own, others = _chosen_and_others(cands, tracks, chosen)
        reach = 15 + 3  # follow_person's max_gap, and the others' nearest frame within 3

        def near(by_frame: dict, a: int, b: int) -> dict:  # with their masks: the others' are blanked
            return {i: _in_memory(c) for i, c in by_frame.items() if a - reach <= i < b + reach}

        def task(a: int, b: int, got: list[list[Candidate]]) -> dict:
            before = [i for i in range(a) if got[i]]
            return {"own": near(own, a, b), "others": [near(o, a, b) for o in others],
                    "last": (got[before[-1]][0], before[-1]) if before else None}

        got = self._chunks("follow", f"{self.name}|chosen {len(own)} frames from {min(own, default=-1)}", task)
        return [g[0] if g else None for g in got]

    def _chunks(self, kind: str, key: str, task) -> list[list[Candidate]]:
        """One entry per frame, from the stored stretches and, for the others, a detector
        process per stretch in turn; ``task(a, b, got_so_far)`` adds to a stretch's task."""
        T = len(self.seq)
        key = f"{key}|{kind}|{T}|{self.seq.size[0]}x{self.seq.size[1]}"
        got: list[list[Candidate]] = [[] for _ in range(T)]
        store = self.search_folder if kind == "find" else self.folder
        store.mkdir(parents=True, exist_ok=True)
        for a in range(0, T, DETECT_CHUNK):
            b = min(T, a + DETECT_CHUNK)
            path = store / f"{kind}-{a:06d}-{b:06d}.npz"
            stretch = load_chunk(path, key, a, b, masks=False)
            if stretch is None:
                _run_detector_process({**task(a, b, got), "seq": self.seq, "spec": self.spec, "kind": kind,
                                       "frames": (a, b), "path": str(path), "key": key, "progress": self.progress,
                                       "warm_up": DETECT_WARM_UP},
                                      self.folder, a, b)
                stretch = load_chunk(path, key, a, b, masks=False)
                if stretch is None:
                    from flowmocap.errors import DetectorError

                    raise DetectorError(f"the person detector's process for frames {a}-{b - 1} ended without "
                                        f"writing {path}; run again (--resume) to go on from frame {a}.")
            got[a:b] = stretch
        return got

    def clear(self) -> None:
        import shutil

        _BITS.clear()
        shutil.rmtree(self.folder, ignore_errors=True)


def _chunk_dir(out_dir: Path) -> Path:
    return Path(out_dir) / "detections" / "chunks"


def run_chunk(task: dict) -> None:
    """One stretch of a detection pass, in the detector's own process
    (:mod:`flowmocap.vision.detect_worker`): makes the detectors of ``task["spec"]``, looks
    at ``task["frames"]`` (``(a, b)``) of ``task["seq"]`` (``"find"``: :func:`find_people`;
    ``"follow"``: :func:`follow_person`'s loop from ``task["last"]``) and stores the
    candidates with :func:`save_chunk` at ``task["path"]``."""
    from flowmocap.vision.detect import MediaPipePoseDetector

    seq, (a, b) = task["seq"], task["frames"]
    model = task["spec"].get("model", "full")
    detector = MediaPipePoseDetector(augment=task["spec"]["augment"], model=model)
    searcher = (MediaPipePoseDetector(augment=False, model=model) if task["spec"]["search"] and task["kind"] == "find"
                else None)
    try:
        if task["kind"] == "find":
            start = max(0, a - task.get("warm_up", DETECT_WARM_UP))
            got = find_people(seq, detector, searcher, progress=task["progress"], frames=range(start, b))[a:b]
        else:
            out = _follow(seq, detector, task["own"], task["others"], range(a, b), task["last"], 15, task["progress"])
            got = [[c] if c is not None else [] for c in out[a:b]]
    finally:
        for d in (detector, searcher):
            getattr(d, "close", lambda: None)()
    save_chunk(task["path"], task["key"], a, b, got)


def save_chunk(path: str | Path, key: str, a: int, b: int, got: list[list[Candidate]]) -> None:
    """Store the candidates ``got`` of frames ``a..b-1`` (one list per frame) atomically in
    ``path`` (``.npz``, no pickled objects), tagged with ``key``."""
    from flowmocap.atomic import atomic_write_npz

    rows = [(i, c) for i, cs in zip(range(a, b), got) for c in cs]
    K = len(KEYPOINT_NAMES)
    n = len(rows)
    packed = [c.mask.load() if isinstance(c.mask, StoredMask) else c.mask if isinstance(c.mask, PackedMask)
              else PackedMask.pack(c.mask) for _, c in rows]
    bits = [m.bits for m in packed]
    arrays = {
        "meta": np.array(json.dumps({"key": key, "frames": [a, b]})),
        "frame": np.array([i for i, _ in rows], np.int64),
        "box": np.array([c.box for _, c in rows], np.float64).reshape(n, 4),
        "keypoints": np.array([c.keypoints for _, c in rows], np.float64).reshape(n, K, 2),
        "confidence": np.array([c.confidence for _, c in rows], np.float64).reshape(n, K),
        "world": np.array([c.world if c.world is not None else np.full((K, 3), np.nan) for _, c in rows],
                          np.float64).reshape(n, K, 3),
        "has_world": np.array([c.world is not None for _, c in rows], bool),
        "mask_shape": np.array([m.shape for m in packed], np.int64).reshape(n, 2),
        "mask_box": np.array([m.box for m in packed], np.int64).reshape(n, 4),
        "mask_end": np.cumsum([len(x) for x in bits], dtype=np.int64),
        "mask_bits": np.concatenate(bits) if bits else np.zeros(0, np.uint8),
    }
    atomic_write_npz(path, **arrays)


class StoredMask(NamedTuple):
    """A candidate's mask left in its stretch file (:func:`load_chunk` with ``masks=False``):
    the file, its bits' range ``[start, end)`` in the file's ``mask_bits``, and the
    :class:`PackedMask`'s ``shape`` and ``box``. A long video's candidates are held for
    choosing the person (boxes, keypoints) without their masks, which are read back in
    frame order when the chosen person's are written (:meth:`load`)."""

    path: str
    start: int
    end: int
    shape: tuple
    box: tuple

    def load(self) -> PackedMask:
        """The mask's bits read from its stretch file (the file must still be there)."""
        return PackedMask(self.shape, self.box, _stored_bits(self.path)[self.start:self.end].copy())


#: The mask bits of the stretch file read last (masks are read in frame order: each file once).
_BITS: dict = {}


def _stored_bits(path: str) -> np.ndarray:
    if _BITS.get("path") != path:
        with np.load(path, allow_pickle=False) as z:
            _BITS.clear()
            _BITS.update(path=path, bits=z["mask_bits"])
    return _BITS["bits"]


def load_chunk(path: str | Path, key: str, a: int, b: int, masks: bool = True) -> list[list[Candidate]] | None:
    """The candidates :func:`save_chunk` stored for frames ``a..b-1``, or None when the file
    is absent, unreadable or made for another ``key`` or stretch. ``masks=False`` leaves
    each mask in the file (a :class:`StoredMask`; the file must stay until it is read)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            z = {k: z[k] for k in z.files if masks or k != "mask_bits"}
        meta = json.loads(str(z["meta"]))
    except Exception:  # noqa: BLE001 -- a damaged stretch file (BadZipFile, EOFError, ...): computed anew
        return None
    if not isinstance(meta, dict) or meta.get("key") != key or meta.get("frames") != [a, b]:
        return None
    got: list[list[Candidate]] = [[] for _ in range(b - a)]
    start = 0
    for r, i in enumerate(z["frame"]):
        end = int(z["mask_end"][r])
        shape, box = tuple(int(v) for v in z["mask_shape"][r]), tuple(int(v) for v in z["mask_box"][r])
        mask = (PackedMask(shape, box, z["mask_bits"][start:end].copy()) if masks
                else StoredMask(str(path), start, end, shape, box))
        start = end
        got[int(i) - a].append(Candidate(tuple(float(v) for v in z["box"][r]), z["keypoints"][r].copy(),
                                         z["confidence"][r].copy(), mask,
                                         z["world"][r].copy() if z["has_world"][r] else None))
    return got


#: The exit status of a detector process (:mod:`flowmocap.vision.detect_worker`) whose
#: writes failed (a full disk, a file size limit).
WRITE_FAILED = 5


def _run_detector_process(task: dict, folder: Path, a: int, b: int) -> None:
    """Run one stretch's ``task`` in a fresh ``python -m flowmocap.vision.detect_worker``
    and wait for it; its error (one of the project's) is raised here.

    Raises:
        DetectorError: the process died (killed, crashed) or left no result.
    """
    import os
    import pickle
    import subprocess
    import sys

    from flowmocap import errors

    folder.mkdir(parents=True, exist_ok=True)
    job = folder / f"task-{a:06d}.pkl"
    failed = folder / f"task-{a:06d}.error.json"
    failed.unlink(missing_ok=True)
    with open(job, "wb") as f:
        pickle.dump(task, f, protocol=pickle.HIGHEST_PROTOCOL)
    env = dict(os.environ)  # the same flowmocap as this process, wherever it was imported from
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[2])]
                                        + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    env["FLOWMOCAP_DETECT_PARENT"] = str(os.getpid())  # detect_worker.PARENT_ENV: it ends when this process does
    try:
        proc = subprocess.Popen([sys.executable, "-m", "flowmocap.vision.detect_worker", str(job)], env=env)
        try:
            rc = proc.wait()
        except BaseException:  # Ctrl-C, SIGTERM: asked to end first, so its exit handlers run; killed if it hangs
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            raise
    finally:
        job.unlink(missing_ok=True)
    kept = (f"the frames before {a} are kept in {folder}: run again (--resume) to go on from frame {a}" if a > 0
            else "run again (--resume) to start it again")
    if failed.exists():
        err = json.loads(failed.read_text())
        failed.unlink()
        cls = getattr(errors, err.get("type", ""), None)
        if not (isinstance(cls, type) and issubclass(cls, errors.FlowMocapError)):
            cls = errors.DetectorError
        message = err.get("message", "the person detector failed")
        if rc == WRITE_FAILED:
            message += f"; free space (or raise the file size limit), then {kept}."
        raise cls(message)
    if rc != 0:
        import signal

        if rc in (130, -signal.SIGINT):
            raise KeyboardInterrupt
        if rc == WRITE_FAILED:
            raise errors.OutputError(f"the person detector's process for frames {a}-{b - 1} could not write its "
                                     f"detections (the disk is full?); free space, then {kept}.")
        how = (f"was killed by signal {-rc}{' (SIGKILL: out of memory?)' if rc == -signal.SIGKILL else ''}"
               if rc < 0 else f"failed with exit status {rc}")
        raise errors.DetectorError(f"the person detector's process for frames {a}-{b - 1} {how}; {kept}.")


def _choice_suffix(choice: tuple, search: bool) -> str:
    """What the detections' name adds for the person chosen: ``+person:...`` for a choice
    other than the largest; ``+follow`` for the largest where a searcher looks for others
    (they are re-detected with the others blanked, :func:`follow_person`, where someone
    else shares at least :data:`LARGEST_FOLLOW_SHARE` of their frames)."""
    if choice[0] != "largest":
        return f"+person:{describe_person(choice)}"
    return "+follow" if search else ""


#: The largest person is re-detected with the others blanked (:func:`follow_person`) when
#: another track shares at least this share of their frames: someone really there, not
#: a stray detection (on DAVIS dance-twirl, three short tracks of 3-15 frames, mixes of
#: the audience and the dancer's own limbs, whose blanking cut her masks: mask IoU 0.855
#: -> 0.840).
LARGEST_FOLLOW_SHARE = 0.25


def _others_share_frames(tracks: list, chosen: int, share: float = LARGEST_FOLLOW_SHARE) -> bool:
    """Whether another track has at least ``share`` of ``tracks[chosen]``'s frames in common with it."""
    own = {i for i, _ in tracks[chosen]}
    return any(sum(i in own for i, _ in t) >= share * len(own) for k, t in enumerate(tracks) if k != chosen)


def _detect_sequence(seq, out_dir: Path, passes, name: str, choice: tuple, reuse: bool) -> PersonTrack:
    """:func:`detect_sequence` once its detection ``passes`` (:class:`_InProcess` or
    :class:`_InChildren`) are chosen."""
    T = len(seq)
    W, H = seq.size
    if reuse:
        stored = load_detections(out_dir, name, T, (W, H))
        if stored is not None:
            return stored
    cands = passes.find()
    pieces = split_tracks(cands)
    tracks, links = link_tracks(seq, cands, pieces)  # one person seen again after a time out of sight
    K = len(KEYPOINT_NAMES)
    kp = np.zeros((T, K, 2))
    conf = np.zeros((T, K))
    world = np.full((T, K, 3), np.nan)
    boxes: list = [None] * T
    masks: list = [None] * T
    ignored = []
    refound = False  # whether the chosen person was re-detected with the others blanked
    people: list[dict] = []
    rank: list[int] = []
    if tracks:
        score = track_scores(cands, tracks, H)
        main = choose_person([cands[t[0][0]][t[0][1]].box for t in tracks], score, choice)
        rank = sorted(range(len(tracks)), key=lambda k: -score[k])
        people = [{"rank": r, "frames": [tracks[k][0][0], tracks[k][-1][0]], "detections": len(tracks[k]),
                   "score": round(float(score[k]), 1),
                   "first_box": [round(float(v), 1) for v in cands[tracks[k][0][0]][tracks[k][0][1]].box]}
                  for r, k in enumerate(rank)]
        refound = choice[0] != "largest" or _others_share_frames(tracks, main)
        if not refound:  # the largest person, alone in their frames: as the search found them
            chosen = [cands[i][c] for i, c in tracks[main]]
            frames = [i for i, _ in tracks[main]]
        else:  # the others blanked as the search saw them: each piece alone
            mine = set(tracks[main])
            followed = passes.follow(cands, [tracks[main]] + [t for t in pieces if not set(t) <= mine], 0)
            frames = [i for i in range(T) if followed[i] is not None]
            chosen = [followed[i] for i in frames]
        for i, cand in zip(frames, chosen):
            boxes[i], kp[i], conf[i], masks[i], w = cand
            if w is not None:
                world[i] = w
        why = ("another person (smaller or seen for less time)" if choice[0] == "largest"
               else f"another person (not the one chosen by person={describe_person(choice)})")
        for k, t in enumerate(tracks):
            if k != main and len(t) > 2:
                ignored.append({"frames": [t[0][0], t[-1][0]], "why": why})
    found = np.array([m is not None for m in masks])
    d = out_dir / "detections"
    # detections.json is written last (every file atomically): while the masks are rewritten
    # the stored detections are absent, so a pass stopped here is done again, never half-used
    (d / "detections.json").unlink(missing_ok=True)
    mdir = _mask_dir(out_dir)
    mdir.mkdir(parents=True, exist_ok=True)
    empty = np.zeros((H, W), np.uint8)
    paths = []
    odir, pdir = _others_dir(out_dir), _people_dir(out_dir)
    for folder in (odir, pdir):
        if folder.exists():  # from an earlier pass
            for old in folder.glob("*.png"):
                old.unlink()
        folder.mkdir(parents=True, exist_ok=True)
    with_others = with_people = 0
    for i in range(T):
        p = mdir / f"{i:06d}.png"
        own = None if masks[i] is None else _mask_array(masks[i])
        _write_png(p, empty if own is None else own.astype(np.uint8) * 255)
        paths.append(p)
        bodies = [_body_region(c, (H, W)) for c in cands[i]]  # drawn once for both regions
        if bodies:  # everyone else, nearer or further: not background
            region = others_region(cands[i], np.zeros((H, W), bool) if own is None else own, bodies)
            if region.any():
                _write_png(pdir / f"{i:06d}.png", region.astype(np.uint8) * 255)
                with_people += 1
        if own is not None and len(cands[i]) > 0:
            # only people nearer the camera may hide the kept one: standing on the same floor
            # below the camera, the nearer has their feet lower in the image (track_scores)
            front = [k for k, c in enumerate(cands[i]) if boxes[i] is not None and c.box[3] > boxes[i][3]]
            region = others_region([cands[i][k] for k in front], own, [bodies[k] for k in front])
            if region.any():
                _write_png(odir / f"{i:06d}.png", region.astype(np.uint8) * 255)
                with_others += 1
    info = {
        "detector": name, "frames": T, "size": [W, H], "keypoint_names": list(KEYPOINT_NAMES),
        "frames_with_person": int(found.sum()),
        "no_person": frame_runs(np.nonzero(~found)[0]),
        "ignored_people": ignored,
        "others_stored": True,
        "frames_with_others": with_others,
        "people_stored": True,
        "frames_with_people": with_people,
        "person": {"choice": describe_person(choice),
                   "rank": rank.index(main) if tracks else None,
                   "people": people,
                   "seen_again": [lk for lk in links if tracks and any(i == lk["frames"][1] for i, _ in tracks[main])],
                   "note": ("people ranked by the sum over their frames of box height x box bottom / image height; "
                            "rank 0 is 'largest'" + ("; the chosen one re-detected with the others blanked"
                                                     if refound else ""))},
    }
    box_arr = np.array([b if b is not None else (np.nan,) * 4 for b in boxes], np.float64).reshape(T, 4)
    from flowmocap.atomic import atomic_write, atomic_write_npz

    arrays = dict(keypoints=kp.astype(np.float32), confidence=conf.astype(np.float32), found=found,
                  names=np.array(KEYPOINT_NAMES), box=box_arr, world=world.astype(np.float32))

    atomic_write_npz(d / "keypoints.npz", **arrays)
    atomic_write(d / "detections.json", lambda tmp: Path(tmp).write_text(json.dumps(info, indent=2)))
    if not found.any():
        raise NoPersonError(f"no person found in any of the {T} frames of {getattr(seq, 'root', 'the input')}; "
                            "check that a whole person is visible, or give --init init.json and --masks FOLDER.")
    return PersonTrack(kp.astype(np.float32), conf.astype(np.float32), found, paths, info, world.astype(np.float32),
                       odir, pdir)


def _write_png(path: Path, image: np.ndarray) -> None:
    """Write ``image`` (uint8) as the PNG ``path`` atomically (:func:`flowmocap.atomic.atomic_write`)."""
    import cv2

    from flowmocap.atomic import atomic_write

    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"could not encode {path} as PNG")
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(data.tobytes()))


class PackedMask(NamedTuple):
    """A bool mask kept as the bits of its bounding box: ``shape`` ``(H, W)`` of the
    frame, ``box`` ``(y0, y1, x0, x1)`` pixels, ``bits`` (``np.packbits`` of the box's
    pixels). :func:`find_people` holds one per person per frame of the whole video: a
    person of 150x400 px costs 7.5 kB instead of the frame's 300 kB at 640x480."""

    shape: tuple
    box: tuple
    bits: np.ndarray

    @classmethod
    def pack(cls, mask: np.ndarray) -> PackedMask:
        """``mask`` ``(H, W)`` bool as the bits of its bounding box (an empty mask: no bits)."""
        m = np.asarray(mask, bool)
        rows, cols = np.nonzero(m.any(1))[0], np.nonzero(m.any(0))[0]
        if not len(rows):
            return cls(m.shape, (0, 0, 0, 0), np.zeros(0, np.uint8))
        y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        return cls(m.shape, (y0, y1, x0, x1), np.packbits(m[y0:y1, x0:x1]))

    def unpack(self) -> np.ndarray:
        """The ``(H, W)`` bool mask."""
        out = np.zeros(self.shape, bool)
        y0, y1, x0, x1 = self.box
        n = (y1 - y0) * (x1 - x0)
        if n:
            out[y0:y1, x0:x1] = np.unpackbits(self.bits, count=n).reshape(y1 - y0, x1 - x0).astype(bool)
        return out


def _mask_array(mask) -> np.ndarray | None:
    """A candidate's mask as ``(H, W)`` bool (packed, stored or not), or None."""
    if mask is None:
        return None
    if isinstance(mask, StoredMask):
        mask = mask.load()
    return mask.unpack() if isinstance(mask, PackedMask) else np.asarray(mask, bool)


def _in_memory(c: Candidate) -> Candidate:
    """``c`` with its mask read back if it was left in its stretch file."""
    return c._replace(mask=c.mask.load()) if isinstance(c.mask, StoredMask) else c


class Candidate(NamedTuple):
    """One detected person in one frame.

    ``box`` ``(x0, y0, x1, y1)`` px; ``keypoints`` ``(K, 2)`` px; ``confidence`` ``(K,)``;
    ``mask`` the cleaned person mask, a :class:`PackedMask` (or an ``(H, W)`` bool array;
    read either with ``_mask_array``); ``world`` ``(K, 3)`` m or None (the detector's 3D).
    """

    box: tuple
    keypoints: np.ndarray
    confidence: np.ndarray
    mask: np.ndarray
    world: np.ndarray | None


def find_people(seq, detector: PersonDetector, searchers=None, progress: bool = True,
                frames: range | None = None) -> list[list[Candidate]]:
    """Every person the detectors find in each frame of ``seq``.

    The (tracking) ``detector`` looks at each frame as it is; each of the ``searchers``
    in turn looks again with the people found so far blanked out (their bodies, as
    :func:`follow_person` blanks the other people: thick limbs, torso and head cut to
    their dilated mask), so up to ``1 + len(searchers)`` people per frame are found.
    Their bodies, not their boxes: a box also hides whoever stands behind them (on the
    real3d recording's cam03 the woman behind the man was found in 36 of 100 frames with
    boxes blanked, 95 with bodies). What is left of a blanked body (a dress, hair) can be
    found as the same person again; a detection with the keypoints of someone found
    already (:func:`_same_detection`) ends the search of that frame. Each searcher sees
    only its own sequence of images (a tracking detector must not jump between them).
    All detectors are reset first.

    Args:
        searchers: None, one :class:`~flowmocap.vision.detect.PersonDetector` or a list.
        frames: the frames to look at (a ``range`` of frame indices; default all).

    Returns:
        per frame of ``seq``, a list of :class:`Candidate` (the detector's first, then
        the searchers'); empty where nobody is found and outside ``frames``.
    """
    from tqdm import tqdm

    searchers = [] if searchers is None else list(searchers) if isinstance(searchers, (list, tuple)) else [searchers]
    detector.reset()
    for s in searchers:
        s.reset()
    T = len(seq)
    frames = range(T) if frames is None else frames
    cands: list[list[Candidate]] = [[] for _ in range(T)]

    def search(img: np.ndarray, first: Candidate) -> list[Candidate]:
        found: list[Candidate] = []
        blanked, last = img, first
        for s in searchers:
            blanked = _blank_people(blanked, [last])
            other = _usable(s.detect(blanked))
            if other is None or any(_same_detection(other, c) for c in [first] + found):
                break  # nobody else, or what was left of someone found already
            found.append(other)
            last = other
        return found

    # the searchers look at frame i on a thread of their own while the detector looks at
    # frame i + 1 (each detector still sees its frames in order: the same detections)
    from concurrent.futures import ThreadPoolExecutor

    pending = None  # (frame, future) of the search of the last frame with a person
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="flowmocap-search") as pool:
        for i in tqdm(frames, disable=not progress, unit="frame", desc="finding the person", total=T,
                      initial=frames.start):
            if i % TRIM_EVERY == 0:
                release_free_memory()
            img = seq.frame(i)
            det = _usable(detector.detect(img))
            if pending is not None:
                cands[pending[0]].extend(pending[1].result())
                pending = None
            if det is None:
                continue
            cands[i].append(det)
            if searchers:
                pending = (i, pool.submit(search, img, det))
        if pending is not None:
            cands[pending[0]].extend(pending[1].result())
    return cands


def track_scores(cands: list[list[Candidate]], tracks: list[list[tuple[int, int]]], height: int) -> list[float]:
    """Each track's main-person score: the sum over its frames of box height x box
    bottom / ``height`` (pixels): nearer people are taller in the image and, standing on
    the ground below the camera's height, have their feet lower in it."""
    return [sum((cands[i][c].box[3] - cands[i][c].box[1]) * cands[i][c].box[3] / height for i, c in t)
            for t in tracks]


def follow_person(seq, detector: PersonDetector, cands: list[list[Candidate]], tracks: list[list[tuple[int, int]]],
                  chosen: int, progress: bool = True, max_gap: int = 15) -> list[Candidate | None]:
    """The chosen track's person in every frame, re-detected with everyone else blanked.

    The (reset) ``detector`` runs over ``seq`` again; in each frame the bodies of the
    people of the other tracks that share frames with the chosen one (a track that
    never does may be the chosen person lost and found again) are filled with the
    image's mean colour (their detection of that frame, else of their nearest frame
    within 3, else their last one if it is at most :data:`LOST_HOLD` frames before:
    thick limbs, torso and head cut to their dilated mask), so a tracking
    detector locks onto the chosen person. A detection counts when it continues
    (:func:`_continues`) either the chosen track's candidate of that frame (else of its
    nearest frame within ``max_gap``) or this pass's last kept detection (within
    ``max_gap`` frames): the same person by :func:`~flowmocap.vision.person.same_person`,
    between half and twice that box's height (a partly hidden person can come out as a
    collapsed skeleton) and overlapping no other person's box more than that one.
    Either may be the better guide: the searcher's candidate can be a fragment where
    someone stands in front of the chosen person (on the real3d recording, a man bending
    over behind a woman came out a third of his height while the searcher blanked whole
    boxes, and the full detections were all refused). Otherwise the
    detector is reset and the chosen track's own candidate (if any) is kept for that
    frame.

    Returns:
        per frame, the chosen person's :class:`Candidate` or None.
    """
    own, others = _chosen_and_others(cands, tracks, chosen)
    return _follow(seq, detector, own, others, range(len(seq)), None, max_gap, progress)


#: Frames after the last detection of another person in which :func:`follow_person` still
#: blanks them there (:func:`_chosen_and_others`).
LOST_HOLD = 15


def _chosen_and_others(cands, tracks, chosen: int) -> tuple[dict, list[dict]]:
    """:func:`follow_person`'s chosen person ``{frame: Candidate}`` and the other people
    that share frames with them (one such dict each). Each other person is also given
    their last detection for the :data:`LOST_HOLD` frames after it: where the search loses
    someone, it is mostly because they merged with the chosen person (stood behind them,
    or the detector took the two for one), and they are still there; left unblanked, a
    tracking detector slides from the chosen person onto them (on the real3d recording's
    cam03 the man's detections moved onto the woman once the search stopped finding her
    at frame 82: 11 of his 100 frames more than 20 px from the reference, 3 with the
    hold)."""
    own = {i: cands[i][c] for i, c in tracks[chosen]}
    others = []
    for k, t in enumerate(tracks):
        if k == chosen or not any(i in own for i, _ in t):
            continue
        other = {i: cands[i][c] for i, c in t}
        end = max(other)
        for j in range(end + 1, end + 1 + LOST_HOLD):
            other.setdefault(j, other[end])
        others.append(other)
    return own, others


def _follow(seq, detector: PersonDetector, own: dict, others: list[dict], frames: range, last, max_gap: int,
            progress: bool) -> list[Candidate | None]:
    """:func:`follow_person` over ``frames`` (a range), given the chosen person's ``own``
    candidates, the ``others`` and ``last`` ``(Candidate, frame)``, the chosen person's
    latest frame before ``frames`` (or None); returns one entry per frame of ``seq``
    (None outside ``frames``)."""
    from tqdm import tqdm

    T = len(seq)

    def nearest(by_frame: dict, i: int, within: int):
        for d in range(within + 1):
            for j in (i - d, i + d):
                if j in by_frame:
                    return by_frame[j], abs(j - i)
        return None, None

    detector.reset()
    out: list[Candidate | None] = [None] * T
    for i in tqdm(frames, disable=not progress, unit="frame", desc="following the chosen person", total=T,
                  initial=frames.start):
        if i % TRIM_EVERY == 0:
            release_free_memory()
        refs = []  # what a detection may continue: the searcher's candidate, this pass's last one
        ref, gap = nearest(own, i, max_gap)
        if ref is not None:
            refs.append((ref, gap))
        if last is not None and i - last[1] <= max_gap:
            refs.append((last[0], i - last[1]))
        if not refs:
            continue  # the chosen person is nowhere near this frame
        img = seq.frame(i)
        other_now = [c for c in (nearest(o, i, 3)[0] for o in others) if c is not None]
        blanked = _blank_people(img, other_now)
        det = _usable(detector.detect(blanked))
        ok = det is not None and any(_continues(det, r, g, other_now) for r, g in refs)
        if ok:
            out[i] = det
            last = (det, i)
        else:
            if det is not None:
                detector.reset()
            out[i] = own.get(i)
            if out[i] is not None:
                last = (out[i], i)
    return out


#: Two detections of one frame are the same person when the median distance of the
#: keypoints confident in both is below this share of the first one's box height.
SAME_DETECTION = 0.1
#: ... or when their boxes overlap by more than this IoU.
SAME_BOX_IOU = 0.5


def _same_detection(a: Candidate, b: Candidate) -> bool:
    """Whether two detections of one frame show the same person: boxes overlapping by
    more than :data:`SAME_BOX_IOU`, or at least 4 keypoints confident in both at a median
    distance below :data:`SAME_DETECTION` of ``b``'s box height. A searcher finds what is
    left of a blanked person (on DAVIS dance-twirl, the dancer again from frame 14, in a
    box overlapping hers by about 0.85, and her track then continued in that one); the
    box test also keeps out someone standing almost exactly behind another, whom blanking
    boxes, as before, did not find either."""
    if box_iou(a.box, b.box) > SAME_BOX_IOU:
        return True
    ka, kb = np.asarray(a.keypoints, np.float64), np.asarray(b.keypoints, np.float64)
    ca, cb = np.asarray(a.confidence), np.asarray(b.confidence)
    both = (ca >= CONFIDENT) & (cb >= CONFIDENT) & np.isfinite(ka).all(1) & np.isfinite(kb).all(1)
    if both.sum() < 4:
        return False
    height = max(float(b.box[3] - b.box[1]), 1.0)
    return float(np.median(np.linalg.norm(ka[both] - kb[both], axis=1))) < SAME_DETECTION * height


def _continues(det: Candidate, ref: Candidate, gap: int, others: list) -> bool:
    """Whether :func:`follow_person`'s detection ``det`` continues the chosen person's
    candidate ``ref`` from ``gap`` frames before (0: the same frame): the same person by
    :func:`~flowmocap.vision.person.same_person`, between half and twice ``ref``'s box
    height (a person does not halve or double in height from one detection to the next)
    and overlapping no box of the ``others`` more than ``ref``'s."""
    if not same_person(ref.box, det.box, max(gap, 1)):
        return False
    h, h_ref = det.box[3] - det.box[1], ref.box[3] - ref.box[1]
    if not 0.5 * h_ref <= h <= 2.0 * h_ref:
        return False
    mine = box_iou(ref.box, det.box)
    return all(box_iou(c.box, det.box) < max(mine, 0.1) for c in others)


def detect_for_given_masks(seq, out_dir: str | Path, progress: bool = True, model: str = "full") -> tuple:
    """The detector's keypoints and 3D joints when nothing else runs the detector (an
    input with its own masks and init.json): MediaPipe without the mask augmentation
    (about 0.05 s per frame with the "full" ``model``), stored in ``out_dir/detections`` like
    :func:`detect_sequence`.

    Returns:
        ``(track, note)``: the :class:`PersonTrack` (2D joints in pixels of ``seq``'s
        frames, 3D joints in metres), or None when no detector is installed or it finds
        no person; and a sentence for ``input.json``.
    """
    from flowmocap.errors import InputError

    try:
        track = detect_sequence(seq, out_dir, detector="plain", progress=progress, model=model)
    except (InputError, NoPersonError) as e:
        return None, f"no detector joints: {e}"
    return track, f"detector joints: {track.info['detector']}, {track.info['frames_with_person']} frames"


def detect_joints3d(seq, out_dir: str | Path, camera=None, progress: bool = True, lift: bool = False,
                    mix: bool = False, model: str = "full", ray_share: float = 1.0) -> tuple:
    """The detector's 3D joints for ``E_d`` when nothing else runs the detector (an input
    with its own masks and init.json): MediaPipe without the mask augmentation (about
    0.05 s per frame), stored in ``out_dir/detections`` like :func:`detect_sequence`.

    Returns:
        ``(joints3d, note)``: the callable ``joints3d(i) -> (j3d (24, 3), conf (24,)) |
        None`` the tracker takes (:meth:`PersonTrack.smpl_joints3d`, in the axes of the
        ``camera`` when given), or None when no detector is installed or it finds no
        person; and a sentence for ``input.json``. ``lift``: the 3D joints from
        :func:`flowmocap.vision.lifter.lifted_track` (``mix``: its mean with the
        detector's own) instead of the detector's own. ``model``: as
        :func:`detect_for_given_masks`. ``ray_share``: as :meth:`PersonTrack.smpl_joints3d`.
    """
    track, note = detect_for_given_masks(seq, out_dir, progress, model)
    if track is None:
        return None, note.replace("no detector joints", "no 3D joints for E_d")
    if lift:
        from flowmocap.vision.lifter import lifted_track

        track = lifted_track(track, mix=mix, fps=seq.meta.get("fps", 30.0))
    return (lambda i: track.smpl_joints3d(i, camera, ray_share)), (f"3D joints for E_d: {track.info['detector']}, "
                                                        f"{track.info['frames_with_person']} frames")


def _usable(det) -> Candidate | None:
    """The :class:`Candidate` of a detection, or None if it shows no person (empty
    cleaned mask or fewer than 2 confident joints)."""
    if det is None:
        return None
    m = clean_mask(det.mask, det.keypoints, det.confidence)
    if not m.any() or (det.confidence[: len(SMPL_KEYPOINTS)] >= CONFIDENT).sum() < 2:
        return None
    return Candidate(person_box(det.keypoints, det.confidence, m), det.keypoints, det.confidence,
                     PackedMask.pack(m), getattr(det, "world", None))


#: Segments of the body drawn to blank another person (keypoint names).
_BONES = (("left_shoulder", "right_shoulder"), ("left_hip", "right_hip"), ("left_shoulder", "left_elbow"),
          ("left_elbow", "left_wrist"), ("right_shoulder", "right_elbow"), ("right_elbow", "right_wrist"),
          ("left_hip", "left_knee"), ("left_knee", "left_ankle"), ("right_hip", "right_knee"),
          ("right_knee", "right_ankle"), ("left_shoulder", "left_hip"), ("right_shoulder", "right_hip"))


def _body_region(cand: Candidate, shape: tuple[int, int], width: float = 0.08) -> np.ndarray:
    """``(H, W)`` bool: the person's body as limbs ``width`` x their box height thick, a
    filled torso and a head disc, cut to their mask dilated by half that width (a
    segmentation often joins two people who touch; the limbs say which part is whose)."""
    import cv2

    H, W = shape
    b = cand.box
    t = max(3, round(width * (b[3] - b[1])))
    kp, cf = np.asarray(cand.keypoints, np.float64), np.asarray(cand.confidence)
    ok = {n: cf[k] >= 0.3 and np.isfinite(kp[k]).all() for k, n in enumerate(KEYPOINT_NAMES)}
    pt = {n: tuple(round(v) for v in kp[k]) for k, n in enumerate(KEYPOINT_NAMES) if ok[n]}
    region = np.zeros((H, W), np.uint8)
    for a, c in _BONES:
        if a in pt and c in pt:
            cv2.line(region, pt[a], pt[c], 1, t)
    for n in ("left_wrist", "right_wrist", "left_ankle", "right_ankle"):
        if n in pt:
            cv2.circle(region, pt[n], int(0.6 * t), 1, -1)
    torso = [pt[n] for n in ("left_shoulder", "right_shoulder", "right_hip", "left_hip") if n in pt]
    if len(torso) >= 3:
        cv2.fillPoly(region, [np.array(torso, np.int32)], 1)
    face = [kp[KEYPOINT_NAMES.index(n)] for n in ("nose", "left_ear", "right_ear") if ok[n]]
    if face:
        centre = np.mean(face, axis=0)
        cv2.circle(region, tuple(round(v) for v in centre), max(2, int(0.07 * (b[3] - b[1]))), 1, -1)
        shoulders = [pt[n] for n in ("left_shoulder", "right_shoulder") if n in pt]
        if shoulders:
            cv2.line(region, tuple(round(v) for v in np.mean(shoulders, axis=0)),
                     tuple(round(v) for v in centre), 1, t)
    if not region.any():  # no confident keypoints: the box
        region[max(0, int(b[1])):min(H, int(np.ceil(b[3]))), max(0, int(b[0])):min(W, int(np.ceil(b[2])))] = 1
    m = _mask_array(cand.mask)
    if m is not None and m.shape == (H, W) and m.any():
        r = max(1, t // 2)
        grown = cv2.dilate(m.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        region &= grown
    return region > 0


def _blank_people(img: np.ndarray, people: list) -> np.ndarray:
    """A copy of ``img`` with each :class:`Candidate`'s body (:func:`_body_region`)
    filled with the image's mean colour."""
    if not people:
        return img
    out = img.copy()
    fill = img.reshape(-1, 3).mean(0).astype(np.uint8)
    for c in people:
        out[_body_region(c, img.shape[:2])] = fill
    return out


def split_tracks(cands: list[list[tuple]], max_gap: int = 15) -> list[list[tuple[int, int]]]:
    """People as lists of ``(frame, candidate index)``: a candidate joins the track whose
    last box it continues best (:func:`same_person`, at most ``max_gap`` frames later),
    each track taking at most one candidate per frame; otherwise it starts a new track.

    Args:
        cands: per frame, the candidates (:func:`find_people`; anything whose item 0 is
            the box ``(x0, y0, x1, y1)`` px).

    Returns:
        the tracks in the order they started (each a list of ``(frame, index into
        cands[frame])`` in frame order).
    """
    tracks: list[list[tuple[int, int]]] = []
    for i, frame in enumerate(cands):
        taken: set[int] = set()
        for c, cand in enumerate(frame):
            box = cand[0]
            best, best_score = None, -1.0
            for k, t in enumerate(tracks):
                j, cj = t[-1]
                if k in taken or i - j > max_gap or j == i:
                    continue
                prev = cands[j][cj][0]
                if same_person(prev, box, i - j):
                    score = box_iou(prev, box) - 0.01 * (i - j)
                    if score > best_score:
                        best, best_score = k, score
            if best is None:
                tracks.append([(i, c)])
                taken.add(len(tracks) - 1)
            else:
                tracks[best].append((i, c))
                taken.add(best)
    return tracks


#: Tracks one person's time apart (more than :func:`split_tracks`' ``max_gap`` frames, out of
#: sight: a cut, an occluder, a flip the detector cannot follow) are linked by
#: :func:`link_tracks` when the later one starts at most this many seconds after the earlier
#: one ends ...
LINK_MAX_S = 3.0
#: ... and their clothes look alike: the Bhattacharyya distance of :func:`appearance` below
#: this. Measured on the project's real clips (docs/experiments.md, "A person seen again"):
#: one person 35 frames apart, 38 pairs, at most 0.465; two people in the same frames, 28
#: pairs, at least 0.491.
LINK_MAX_DISTANCE = 0.48
#: ... and each of the two has at least this many detections (a fragment is not a person).
LINK_MIN_DETECTIONS = 10
#: The detections at the end of the earlier track and the start of the later one compared.
LINK_FRAMES = 5


def appearance(image: np.ndarray, cand: Candidate) -> tuple[np.ndarray, np.ndarray] | None:
    """What a person's clothes look like: the hue-saturation histograms (16 x 8 bins, each
    summing to 1) of the upper and the lower half of their box, over their mask shrunk by
    2 px (away from the background), or None where either half has fewer than 50 pixels.

    Args:
        image: ``(H, W, 3)`` uint8 RGB frame.
        cand: the person's :class:`Candidate` in it.
    """
    import cv2

    m = _mask_array(cand.mask)
    if m is None:
        return None
    m = cv2.erode(m.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=2)
    hsv = cv2.cvtColor(np.ascontiguousarray(image[..., :3]), cv2.COLOR_RGB2HSV)
    mid = int(round((cand.box[1] + cand.box[3]) / 2))
    out = []
    for rows in (slice(0, mid), slice(mid, None)):
        part = np.zeros_like(m)
        part[rows] = m[rows]
        if part.sum() < 50:
            return None
        h = cv2.calcHist([hsv], [0, 1], part, [16, 8], [0, 180, 0, 256]).astype(np.float32)
        out.append(h / h.sum())
    return out[0], out[1]


def appearance_distance(a, b) -> float:
    """The mean over the two halves of the Bhattacharyya distance of two :func:`appearance`
    (0: the same colours, 1: none in common)."""
    import cv2

    return float(np.mean([cv2.compareHist(x, y, cv2.HISTCMP_BHATTACHARYYA) for x, y in zip(a, b)]))


def _track_appearance(seq, cands, items) -> tuple | None:
    got = [appearance(seq.frame(i), cands[i][c]) for i, c in items]
    got = [g for g in got if g is not None]
    if not got:
        return None
    return tuple(np.mean([g[k] for g in got], 0) for k in range(2))


def link_tracks(seq, cands: list[list[Candidate]], tracks: list[list[tuple[int, int]]], max_gap: int = 15,
                max_s: float = LINK_MAX_S, max_distance: float = LINK_MAX_DISTANCE,
                min_detections: int = LINK_MIN_DETECTIONS) -> tuple[list[list[tuple[int, int]]], list[dict]]:
    """One person's tracks joined across a time out of sight.

    :func:`split_tracks` ends a track after ``max_gap`` frames without the person, so someone
    hidden for longer (behind an occluder, across a cut, in a flip the detector cannot
    follow) comes back as a new track, and ``--person largest`` would keep only one of the
    two stretches. Here a track that starts more than ``max_gap`` frames but at most
    ``max_s`` seconds after another ends continues it when both have at least
    ``min_detections`` detections and the clothes look alike (:func:`appearance` of the last
    :data:`LINK_FRAMES` detections against the first ones, distance below ``max_distance``).
    The pairs are taken in order of distance, each end and start at most once, so a track
    can be joined several times over.

    Args:
        seq: the frames (``seq.frame(i)``: ``(H, W, 3)`` uint8 RGB; ``seq.meta["fps"]``, else
            30 frames a second).
        cands, tracks: :func:`find_people` and :func:`split_tracks`.

    Returns:
        ``(people, links)``: the tracks with the linked ones joined, in the order they start,
        and per link ``{"frames": [last frame before, first frame after], "distance": d}``.
    """
    fps = float((getattr(seq, "meta", None) or {}).get("fps") or 30.0)
    reach = int(round(max_s * fps))
    long = [k for k, t in enumerate(tracks) if len(t) >= min_detections]
    apart = [(a, b) for a in long for b in long if max_gap < tracks[b][0][0] - tracks[a][-1][0] <= reach]
    if not apart:
        return [list(t) for t in tracks], []
    # the looks only of the tracks that could be joined (each costs LINK_FRAMES frames read)
    ends = {a: _track_appearance(seq, cands, tracks[a][-LINK_FRAMES:]) for a in {a for a, _ in apart}}
    starts = {b: _track_appearance(seq, cands, tracks[b][:LINK_FRAMES]) for b in {b for _, b in apart}}
    pairs = []
    for a, b in apart:
        if ends[a] is not None and starts[b] is not None:
            d = appearance_distance(ends[a], starts[b])
            if d < max_distance:
                pairs.append((d, a, b))
    nxt: dict[int, int] = {}
    prev: dict[int, int] = {}
    links = []
    for d, a, b in sorted(pairs):
        if a in nxt or b in prev:
            continue
        nxt[a], prev[b] = b, a
        links.append({"frames": [int(tracks[a][-1][0]), int(tracks[b][0][0])], "distance": round(d, 3)})
    people = []
    for k in range(len(tracks)):
        if k in prev:
            continue
        joined, j = list(tracks[k]), k
        while j in nxt:
            j = nxt[j]
            joined += tracks[j]
        people.append(joined)
    people.sort(key=lambda t: t[0][0])
    return people, sorted(links, key=lambda x: x["frames"])


def frame_runs(idx: list[int]) -> list[list[int]]:
    """Sorted frame indices as runs of consecutive frames.

    Args:
        idx: ascending frame numbers (any iterable of ints, e.g. ``np.nonzero(mask)[0]``).

    Returns:
        ``[[first, last], ...]``, one inclusive pair per run; ``[]`` for no frames.
        ``frame_runs([2, 3, 4, 7, 9, 10]) == [[2, 4], [7, 7], [9, 10]]``.
    """
    out: list[list[int]] = []
    for i in (int(v) for v in idx):
        if out and out[-1][1] == i - 1:
            out[-1][1] = i
        else:
            out.append([i, i])
    return out


def first_person_frame(track: PersonTrack, start: int = 0, min_joints: int = MIN_INIT_JOINTS) -> int | None:
    """The first frame from ``start`` on with at least ``min_joints`` confident SMPL
    keypoints (hips and shoulders among them), or None."""
    n = len(SMPL_KEYPOINTS)
    need = [SMPL_KEYPOINTS.index(j) for j in ("left_hip", "right_hip", "left_shoulder", "right_shoulder")]
    for i in range(start, len(track)):
        c = track.confidence[i, :n]
        if track.found[i] and (c >= CONFIDENT).sum() >= min_joints and (c[need] >= CONFIDENT).all():
            return i
    return None


def facing_rotvec(keypoints: np.ndarray, confidence: np.ndarray, camera_R=None) -> np.ndarray:
    """A rough global orientation ``(3,)`` axis-angle (radians) of an upright person
    with the given keypoints.

    The body stands upright (its up is the image's up) and turns about the vertical by
    the yaw whose cosine is the signed left-right spread of shoulders and hips relative
    to the torso length (a person facing the camera has their left on the image's right);
    which way a side-on person faces comes from the nose against the ears (or the
    shoulders). Yaw 0 faces the camera.

    Args:
        keypoints: ``(K, 2)`` the detector's keypoints, pixels; confidence: ``(K,)``.
        camera_R: ``(3, 3)`` the camera's world-to-camera rotation (``x_cam = R x + t``),
            or None for the identity (OpenCV axes). The orientation is found in the
            camera's axes and returned in the world's (``R^T`` times it), as the body
            model's global orientation is.
    """
    from scipy.spatial.transform import Rotation

    kp = {n: np.asarray(keypoints[k], np.float64) for k, n in enumerate(KEYPOINT_NAMES)}
    cf = {n: float(confidence[k]) for k, n in enumerate(KEYPOINT_NAMES)}
    mid_s = (kp["left_shoulder"] + kp["right_shoulder"]) / 2
    mid_h = (kp["left_hip"] + kp["right_hip"]) / 2
    torso = max(float(np.linalg.norm(mid_s - mid_h)), 1.0)
    # joint-to-joint widths relative to the torso: shoulders ~0.7, hips ~0.4
    spread = ((kp["left_shoulder"][0] - kp["right_shoulder"][0]) / 0.7
              + (kp["left_hip"][0] - kp["right_hip"][0]) / 0.4) / 2
    c = float(np.clip(spread / torso, -1.0, 1.0))
    ears = [kp[e] for e in ("left_ear", "right_ear") if cf[e] >= 0.3]
    ref = np.mean(ears, axis=0) if ears else mid_s
    side = kp["nose"][0] - ref[0] if cf["nose"] >= 0.3 else 0.0
    # facing direction in the camera frame is (-sin(yaw), 0, -cos(yaw)): facing image right = sin < 0
    s = -math.copysign(math.sqrt(max(0.0, 1.0 - c * c)), side) if side != 0.0 else 0.0
    yaw = math.atan2(s, c)
    R = Rotation.from_euler("y", yaw) * Rotation.from_euler("x", math.pi)
    if camera_R is not None:
        R = Rotation.from_matrix(np.asarray(camera_R, np.float64).T) * R
    return R.as_rotvec()


def auto_init(track: PersonTrack, frame: int, min_confidence: float = 0.3, camera_R=None) -> dict:
    """An ``init.json`` dict (schema of :mod:`flowmocap.fit.init`) from frame ``frame``'s
    keypoints: the confident SMPL joints with their confidences, and the rough global
    orientation of :func:`facing_rotvec` (in the world's axes of a camera of rotation
    ``camera_R``, a ``(3, 3)`` world-to-camera rotation matrix; None: the identity).

    Raises:
        NoPersonError: the frame has fewer than 4 confident joints.
    """
    kp, cf = track.keypoints[frame], track.confidence[frame]
    joints, conf = {}, {}
    for k, name in enumerate(SMPL_KEYPOINTS):
        if cf[k] >= min_confidence:
            joints[name] = [float(v) for v in kp[k]]
            conf[name] = float(cf[k])
    if len(joints) < 4:
        raise NoPersonError(f"frame {frame}: the detector found fewer than 4 joints of the person; "
                            "give --init init.json with the joints of a frame instead.")
    return {"frame": int(frame), "joints2d": joints, "confidence": conf,
            "pose": {"pelvis": facing_rotvec(kp, cf, camera_R).tolist()}, "joints_from": "detector",
            "note": f"automatic: {track.info.get('detector', 'detector')} keypoints of frame {frame}"}
