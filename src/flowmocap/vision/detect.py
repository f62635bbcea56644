"""Person detectors: 2D joints and a person mask for one RGB image.

A detector is anything with ``detect(image_rgb) -> Detection | None`` (the
:class:`PersonDetector` protocol); ``None`` means no person in the image. The default is
:class:`MediaPipePoseDetector`, MediaPipe's legacy ``solutions.pose`` (BlazePose GHUM
landmarks and its person segmentation). It runs offline and downloads nothing: the
"full" landmark model ships inside the ``mediapipe==0.10.21`` wheel, and the "heavy" one
(:data:`MODELS`) inside this package (``vision/data/pose_landmark_heavy.tflite``, from
MediaPipe's own ``@mediapipe/pose`` package, Apache-2.0; ``vision/data/README.md``).
MediaPipe's Python solution reads the heavy model only under its resource folder, and
would download it into its own package folder, so the heavy graph is made with a
temporary resource folder that links MediaPipe's files and the shipped model (checked by
its digest): nothing is downloaded or written into MediaPipe's folder.

Keypoints come in the order of :data:`KEYPOINT_NAMES`: the twelve SMPL joints an
``init.json`` takes (hips, knees, ankles, shoulders, elbows, wrists, by SMPL's names,
"left" being the person's own left), then the nose and the ears, which are not SMPL
joints and serve only to tell which way the person faces.

MediaPipe's C++ side (TFLite, absl logging) writes lines such as "INFO: Created
TensorFlow Lite XNNPACK delegate" and "W0000 ... inference_feedback_manager" straight to
file descriptor 2, from its graph threads, whenever a graph is created, run or closed;
no environment variable of mediapipe 0.10.21 turns them off (``GLOG_minloglevel`` and
``TF_CPP_MIN_LOG_LEVEL`` were tried). :class:`MediaPipePoseDetector` therefore points
fd 2 at ``/dev/null`` for the duration of each of those calls.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from flowmocap.errors import InputError

__all__ = ["KEYPOINT_NAMES", "SMPL_KEYPOINTS", "Detection", "PersonDetector", "MediaPipePoseDetector",
           "MEDIAPIPE_LANDMARKS", "MODELS", "check_model", "check_model_files", "visibility_map"]

#: Keypoints that are SMPL joints (the joints of an init.json), in this order.
SMPL_KEYPOINTS: tuple[str, ...] = (
    "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)
#: Every keypoint of a :class:`Detection`, in order: SMPL joints, then face points.
KEYPOINT_NAMES: tuple[str, ...] = SMPL_KEYPOINTS + ("nose", "left_ear", "right_ear")

#: MediaPipe Pose landmark index of each keypoint (its 33-landmark BlazePose topology).
MEDIAPIPE_LANDMARKS: dict[str, int] = {
    "nose": 0, "left_ear": 7, "right_ear": 8,
    "left_shoulder": 11, "right_shoulder": 12, "left_elbow": 13, "right_elbow": 14,
    "left_wrist": 15, "right_wrist": 16, "left_hip": 23, "right_hip": 24,
    "left_knee": 25, "right_knee": 26, "left_ankle": 27, "right_ankle": 28,
}


#: BlazePose GHUM landmark models MediaPipe's legacy Pose runs: name -> its
#: ``model_complexity``. "heavy" is the larger network (about 2.2x the time of "full" a
#: run, benchmarks/detector_models.py): on the real four-camera recording its 2D keypoints
#: are nearer the other views' triangulation (mean 13.3 px against 17.7 for "full";
#: docs/experiments.md, "MediaPipe's heavy landmark model").
MODELS: dict[str, int] = {"full": 1, "heavy": 2}

#: The heavy landmark model shipped with this package, and its MD5 digest (the file of
#: ``@mediapipe/pose`` 0.5.1675469404; the "full" file there is byte for byte the one in
#: the ``mediapipe==0.10.21`` wheel).
HEAVY_MODEL = Path(__file__).parent / "data" / "pose_landmark_heavy.tflite"
HEAVY_MD5 = "52337aea988efa7ce17851641f4b730a"

#: The heavy model's landmark visibility put on the full model's scale, the one the
#: tracker's confidence thresholds were set on: knots of a monotone map made by
#: ``tools/calibrate_visibility.py`` (quantile matching on rendered training clips).
HEAVY_VISIBILITY = Path(__file__).parent / "data" / "heavy_visibility.json"


def check_model(model) -> str:
    """``model`` when it names one of :data:`MODELS`.

    Raises:
        InputError: it does not.
    """
    if model not in MODELS:
        raise InputError(f"unknown detector model {model!r}; choose one of {', '.join(MODELS)}.")
    return model


def visibility_map(model: str) -> tuple[np.ndarray, np.ndarray] | None:
    """``(x, y)`` knots that turn ``model``'s landmark visibility into flowmocap's keypoint
    confidence (``np.interp(v, x, y)``, 0 -> 0, 1 -> 1, non-decreasing), or None where it is
    used as it comes ("full").

    Raises:
        InputError: an unknown model, or the shipped map is missing or malformed.
    """
    if check_model(model) == "full":
        return None
    import json

    try:
        doc = json.loads(HEAVY_VISIBILITY.read_text())
        x, y = np.asarray(doc["heavy"], np.float64), np.asarray(doc["full"], np.float64)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"the heavy model's visibility map ({HEAVY_VISIBILITY}) is missing or damaged ({e}); "
                         "reinstall flowmocap, or use the detector model 'full'.") from e
    if (x.ndim != 1 or x.shape != y.shape or len(x) < 2 or x[0] != 0 or x[-1] != 1 or y[0] != 0 or y[-1] != 1
            or (np.diff(x) <= 0).any() or (np.diff(y) < 0).any()):
        raise InputError(f"the heavy model's visibility map ({HEAVY_VISIBILITY}) is not a monotone map of [0, 1] "
                         "onto itself; reinstall flowmocap, or use the detector model 'full'.")
    return x, y


def _md5(path: Path) -> str:
    h = hashlib.md5()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


_SHIPPED_OK: list = []


def _shipped_ok() -> bool:
    """Whether the shipped heavy model is whole (checked once per process)."""
    if not _SHIPPED_OK:
        _SHIPPED_OK.append(HEAVY_MODEL.is_file() and _md5(HEAVY_MODEL) == HEAVY_MD5)
    return _SHIPPED_OK[0]


def check_model_files(model: str) -> None:
    """Check that ``model`` can run offline: "full" ships inside MediaPipe's wheel; "heavy"
    inside this package, checked against its digest (once per process).

    Raises:
        InputError: an unknown model, or the shipped heavy file is missing or damaged.
    """
    if check_model(model) == "heavy" and not _shipped_ok():
        raise InputError(f"the heavy pose model shipped with flowmocap ({HEAVY_MODEL}) is missing or damaged; "
                         "reinstall flowmocap, or use the detector model 'full'.")


_SHADOW_LOCK = threading.Lock()
_SHADOW: list = []  # this process's resource folder, once made


def _heavy_resources(mp_root: Path) -> Path:
    """A resource folder for MediaPipe's graphs in which MediaPipe's own files are linked
    and the heavy landmark model is the shipped one; made once per process in the
    temporary folder, removed when the process ends.

    MediaPipe's legacy Pose reads ``mediapipe/modules/pose_landmark/pose_landmark_heavy.tflite``
    under its resource folder (its installed package's parent) and downloads the file into
    its own package folder when it is missing. flowmocap neither downloads nor writes into
    another package's folder (a read-only install refused it; an uninstalled MediaPipe
    left it behind). A graph reads its models on its own threads after it is made, so the
    folder stays for the process; one that a killed process left (its exit handlers did not
    run) is removed by the next (:func:`_drop_dead_resources`).

    Args:
        mp_root: the folder that holds MediaPipe's package (``site-packages``).

    Returns:
        The resource folder (it holds ``mediapipe/...``).

    Raises:
        InputError: the shipped model is missing or damaged, or the folder cannot be made.
    """
    import atexit
    import shutil
    import tempfile

    check_model_files("heavy")
    _drop_dead_resources()
    try:
        root = Path(tempfile.mkdtemp(prefix=f"flowmocap-mediapipe-{os.getpid()}-"))
    except OSError as e:
        raise InputError(f"cannot make a temporary folder for the heavy pose model ({e}); set TMPDIR to a writable "
                         "folder, or use the detector model 'full'.") from e
    try:
        chain = ("mediapipe", "modules", "pose_landmark")
        for depth in range(len(chain)):  # each level linked entry by entry, but for the next level down
            here, there = root.joinpath(*chain[:depth + 1]), mp_root.joinpath(*chain[:depth + 1])
            here.mkdir()
            keep_out = chain[depth + 1] if depth + 1 < len(chain) else "pose_landmark_heavy.tflite"
            for entry in there.iterdir():
                if entry.name != keep_out:
                    (here / entry.name).symlink_to(entry)
        target = root.joinpath(*chain, "pose_landmark_heavy.tflite")
        try:
            target.symlink_to(HEAVY_MODEL)
        except OSError:  # pragma: no cover - a file system without symbolic links
            shutil.copyfile(HEAVY_MODEL, target)
    except OSError as e:
        shutil.rmtree(root, ignore_errors=True)
        raise InputError(f"cannot prepare the heavy pose model for MediaPipe in {root} ({e}); set TMPDIR to a "
                         "writable folder, or use the detector model 'full'.") from e
    atexit.register(shutil.rmtree, root, True)
    return root


def _drop_dead_resources() -> None:
    """Remove the resource folders (:func:`_heavy_resources`) that processes killed before
    their exit handlers ran left in the temporary folder (the process id in the name is
    gone); only this user's."""
    import shutil
    import tempfile

    for folder in Path(tempfile.gettempdir()).glob("flowmocap-mediapipe-*-*"):
        try:
            pid = int(folder.name.split("-")[2])
            if folder.is_symlink() or not folder.is_dir() or folder.stat().st_uid != os.getuid():
                continue
            os.kill(pid, 0)  # raises where no such process is left
        except ProcessLookupError:
            shutil.rmtree(folder, ignore_errors=True)
        except (ValueError, IndexError, OSError, AttributeError):  # not ours, another user's process, no getuid
            continue


def _use_heavy_resources(mp) -> Path:
    """Point every MediaPipe graph this process makes from now on at
    :func:`_heavy_resources`' folder (it links all of MediaPipe's own files, so the other
    solutions run as before), and stop Pose downloading the heavy model. Once per process."""
    with _SHADOW_LOCK:
        if _SHADOW:
            return _SHADOW[0]
        from mediapipe.python import solution_base

        root = _heavy_resources(Path(mp.__file__).parent.parent)
        resource_util, pose_module = solution_base.resource_util, mp.solutions.pose
        set_dir, fetch = resource_util.set_resource_dir, pose_module._download_oss_pose_landmark_model
        resource_util.set_resource_dir = lambda _default: set_dir(str(root))
        pose_module._download_oss_pose_landmark_model = lambda complexity: None if complexity == 2 else fetch(complexity)
        set_dir(str(root))
        _SHADOW.append(root)
        return root


def _make_pose(mp, model: str, **options):
    """MediaPipe's legacy ``Pose`` of ``model`` (:data:`MODELS`) with ``options``; a heavy
    one reads the shipped model (:func:`_use_heavy_resources`) and downloads nothing."""
    if model == "heavy":
        _use_heavy_resources(mp)
    return mp.solutions.pose.Pose(model_complexity=MODELS[check_model(model)], **options)


@contextlib.contextmanager
def _native_stderr_to_devnull():
    """File descriptor 2 points at ``/dev/null`` inside the block (C-level writes included).
    Blocks that overlap in several threads (two detectors at once) share one redirect, and
    the last to leave puts fd 2 back (each saving and restoring fd 2 on its own could leave
    it at ``/dev/null`` for good)."""
    with _QUIET_LOCK:
        if not _QUIET:
            sys.stderr.flush()
            saved = os.dup(2)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 2)
            os.close(devnull)
            _QUIET.extend([saved, 0])
        _QUIET[1] += 1
    try:
        yield
    finally:
        with _QUIET_LOCK:
            _QUIET[1] -= 1
            if _QUIET[1] == 0:
                saved = _QUIET[0]
                _QUIET.clear()
                os.dup2(saved, 2)
                os.close(saved)


_QUIET_LOCK = threading.Lock()
_QUIET: list = []  # [fd 2 as it was, blocks inside] while fd 2 points at /dev/null


@dataclass
class Detection:
    """One person in one image.

    Attributes:
        keypoints: ``(K, 2)`` pixels (x right, y down; pixel centres at integer + 0.5),
            in the order of :data:`KEYPOINT_NAMES`.
        confidence: ``(K,)`` in ``[0, 1]``; 0 for a keypoint outside the image or unknown.
        mask: ``(H, W)`` bool, True on the person.
        soft_mask: ``(H, W)`` float32 person probability, or None.
        world: ``(K, 3)`` metres, the keypoints in 3D relative to the middle of the hips,
            in the camera's axes (x right, y down, z away from the camera), as a detector
            that lifts its joints to 3D (MediaPipe's ``pose_world_landmarks``) guesses
            them; None when the detector gives no 3D. Its depth says which way a limb
            points, nearer or further, which flow and silhouettes cannot tell.
    """

    keypoints: np.ndarray
    confidence: np.ndarray
    mask: np.ndarray
    soft_mask: np.ndarray | None = None
    world: np.ndarray | None = None

    def box(self, min_confidence: float = 0.3) -> tuple[float, float, float, float] | None:
        """``(x0, y0, x1, y1)`` pixels around the confident keypoints, or None."""
        ok = self.confidence >= min_confidence
        if ok.sum() < 2:
            return None
        p = self.keypoints[ok]
        return float(p[:, 0].min()), float(p[:, 1].min()), float(p[:, 0].max()), float(p[:, 1].max())


@runtime_checkable
class PersonDetector(Protocol):
    """What the automatic masks and joints need from a detector.

    ``name`` says which detector (and settings) made a stored result, so a rerun can tell
    whether stored detections still apply. ``detect`` takes the frames of one video in
    order, each ``(H, W, 3)`` uint8 RGB (a detector may track the person from frame to
    frame), and returns a :class:`Detection` in that frame's pixels, or None when the
    image shows no person. ``reset`` forgets the tracked person (a new video).
    """

    name: str

    def detect(self, image_rgb: np.ndarray) -> Detection | None:
        """The person in ``image_rgb`` ``(H, W, 3)`` uint8 RGB, the next frame of the video:
        a :class:`Detection` in its pixels, or None where it shows no person."""
        ...

    def reset(self) -> None:
        """Forget the tracked person: the next frame starts a new video."""
        ...


class MediaPipePoseDetector:
    """MediaPipe's legacy Pose solution: 33 landmarks and a person segmentation.

    Runs in tracking mode (``static_image_mode=False``): the person found first is
    followed from frame to frame. With ``augment`` (default) the segmentation is the
    mean of four runs: the image as is, mirrored, with a 64-pixel black border, and in
    single-image mode; a run whose mask does not overlap the tracked person's is left
    out. On DAVIS dance-twirl this raises the mask IoU against the hand-made masks from
    0.843 (one run) to 0.855, for about 4x the detector time (~0.1 s per 854x480 frame
    on one core). The three extra runs go to threads of their own while the main one
    runs (MediaPipe's graphs let go of Python's lock while they work): ~0.07 s a frame
    on two cores; every run sees every frame, also one where the main run finds nobody
    (before the threads, such a frame was not shown to the others). The soft mask is then smoothed with a guided filter
    on the image (radius 4 px), which follows the image edges.

    Args:
        augment: average the segmentation over the four runs described above.
        min_confidence: MediaPipe's detection and tracking confidence thresholds.
        threshold: the soft mask's person probability above which a pixel is the person.
        model: the landmark model of the main run, which gives the keypoints, the 3D
            joints and the first mask (:data:`MODELS`); the three augmentation runs,
            which only add to the mask, stay "full".
        calibrated: put the model's landmark visibility on the full model's scale
            (:func:`visibility_map`) as the keypoints' confidence; False: as it comes (for
            ``tools/calibrate_visibility.py``).
    """

    #: What to do when MediaPipe is not installed.
    NOT_INSTALLED = ("automatic masks and joints need mediapipe 0.10.21 (pip install mediapipe==0.10.21, "
                     "which ships its models); or give --init init.json and --masks FOLDER.")

    def __init__(self, augment: bool = True, min_confidence: float = 0.5, threshold: float = 0.5,
                 model: str = "full", calibrated: bool = True):
        try:
            import mediapipe as mp
        except ImportError as e:  # pragma: no cover - depends on the environment
            raise InputError(self.NOT_INSTALLED) from e
        if not 0.0 < threshold < 1.0:
            raise InputError(f"threshold must be in (0, 1); got {threshold}.")
        check_model_files(model)
        self._visibility = visibility_map(model) if calibrated else None
        self._mp = mp
        self.augment = bool(augment)
        self.min_confidence = float(min_confidence)
        self.threshold = float(threshold)
        self.model = model
        self.name = self.describe(self.augment, self.min_confidence, self.threshold, mp.__version__, model, calibrated)
        self._runs: dict = {}
        self._pool = None  # threads for the augmented runs, made with them
        self.reset()

    @classmethod
    def describe(cls, augment: bool = True, min_confidence: float = 0.5, threshold: float = 0.5,
                 version: str | None = None, model: str = "full", calibrated: bool = True) -> str:
        """The :attr:`name` a detector of these settings has, without loading MediaPipe
        (its installed version read from the package metadata unless given).

        Raises:
            InputError: MediaPipe is not installed.
        """
        if version is None:
            from importlib.metadata import PackageNotFoundError
            from importlib.metadata import version as installed

            try:
                version = installed("mediapipe")
            except PackageNotFoundError as e:  # pragma: no cover - depends on the environment
                raise InputError(cls.NOT_INSTALLED) from e
        if check_model(model) == "full" or not calibrated:
            tag = model if model == "full" else f"{model}-raw"
        else:  # stored detections follow the visibility map (a bad one is refused here too)
            visibility_map(model)
            tag = f"{model}-v{_md5(HEAVY_VISIBILITY)[:6]}"
        return f"mediapipe-pose-{version}-{tag}-3d{'-tta4' if augment else ''}-c{min_confidence:g}-t{threshold:g}"

    def _pose(self, static: bool, model: str = "full"):
        return _make_pose(
            self._mp, model, static_image_mode=static, smooth_landmarks=True, enable_segmentation=True,
            smooth_segmentation=not static, min_detection_confidence=self.min_confidence,
            min_tracking_confidence=self.min_confidence)

    def reset(self) -> None:
        """Forget the tracked person (call between videos)."""
        self.close()
        with _native_stderr_to_devnull():
            self._runs = {"main": self._pose(False, self.model)}
            if self.augment:
                self._runs.update({"mirror": self._pose(False), "border": self._pose(False),
                                   "single": self._pose(True)})
                from concurrent.futures import ThreadPoolExecutor

                self._pool = ThreadPoolExecutor(max_workers=3, thread_name_prefix="flowmocap-mediapipe")

    def close(self) -> None:
        """Release MediaPipe's graphs and the augmentation threads (:meth:`reset` makes new ones)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        with _native_stderr_to_devnull():
            for p in self._runs.values():
                p.close()
        self._runs = {}

    def detect(self, image_rgb: np.ndarray) -> Detection | None:
        """Keypoints and mask of the tracked person in ``image_rgb (H, W, 3)`` uint8 RGB."""
        import cv2

        img = np.asarray(image_rgb)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise InputError(f"detect needs an (H, W, 3) uint8 RGB image; got {img.shape} {img.dtype}.")
        img = np.ascontiguousarray(img)
        H, W = img.shape[:2]
        with _native_stderr_to_devnull():
            extra = self._start_augmented(img) if self.augment else None
            res = self._runs["main"].process(img)
            views = [f.result() for f in extra] if extra is not None else None  # every run sees every frame
            if res.pose_landmarks is None or res.segmentation_mask is None:
                return None
            if self.augment:
                soft = self._augmented(np.asarray(res.segmentation_mask, np.float32), views)
        lm = res.pose_landmarks.landmark
        kp = np.zeros((len(KEYPOINT_NAMES), 2))
        conf = np.zeros(len(KEYPOINT_NAMES))
        for k, name in enumerate(KEYPOINT_NAMES):
            p = lm[MEDIAPIPE_LANDMARKS[name]]
            kp[k] = (p.x * W, p.y * H)
            inside = 0.0 <= kp[k, 0] <= W and 0.0 <= kp[k, 1] <= H
            conf[k] = float(np.clip(p.visibility, 0.0, 1.0)) if inside else 0.0
        if self._visibility is not None:  # the heavy model's visibility on the full model's scale
            conf = np.interp(conf, *self._visibility)
        if not self.augment:
            soft = np.asarray(res.segmentation_mask, np.float32)
        soft = cv2.ximgproc.guidedFilter(img, soft, 4, 1e-3 * 255.0 ** 2) if hasattr(cv2, "ximgproc") else soft
        soft = np.clip(soft, 0.0, 1.0)
        world = None
        if res.pose_world_landmarks is not None:
            wl = res.pose_world_landmarks.landmark
            world = np.array([[wl[MEDIAPIPE_LANDMARKS[n]].x, wl[MEDIAPIPE_LANDMARKS[n]].y, wl[MEDIAPIPE_LANDMARKS[n]].z]
                              for n in KEYPOINT_NAMES])
        return Detection(keypoints=kp, confidence=conf, mask=soft > self.threshold, soft_mask=soft, world=world)

    def _start_augmented(self, img: np.ndarray) -> list:
        """The three extra runs of ``img`` started on the pool; each future's result is
        that run's soft mask in ``img``'s pixels, or None."""
        import cv2

        b = 64
        runs = self._runs

        def mirror():
            r = runs["mirror"].process(np.ascontiguousarray(img[:, ::-1]))
            return None if r.segmentation_mask is None else np.asarray(r.segmentation_mask)[:, ::-1]

        def border():
            r = runs["border"].process(cv2.copyMakeBorder(img, b, b, b, b, cv2.BORDER_CONSTANT, value=0))
            return None if r.segmentation_mask is None else np.asarray(r.segmentation_mask)[b:-b, b:-b]

        def single():
            r = runs["single"].process(img)
            return None if r.segmentation_mask is None else np.asarray(r.segmentation_mask)

        return [self._pool.submit(f) for f in (mirror, border, single)]

    def _augmented(self, soft: np.ndarray, others: list) -> np.ndarray:
        """The mean of the main run's soft mask and those of ``others`` (None: no mask)
        that overlap its person."""
        main = soft > self.threshold
        views = [soft, *others]
        kept = [views[0]]
        for v in views[1:]:
            if v is None:
                continue
            m = v > self.threshold
            union = (m | main).sum()
            if union and (m & main).sum() / union > 0.5:  # the same person
                kept.append(v.astype(np.float32))
        return np.mean(kept, axis=0).astype(np.float32)
