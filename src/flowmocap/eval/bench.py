"""The benchmark runner (``flowmocap bench``): our tracker and the per-frame baseline, side
by side on the same sequences, scored by the same code, in one table like the paper's
Table 1.

Protocol on a synthetic sequence (one folder ``DIR/NAME/`` per sequence):

1. ``sequence/``: :func:`flowmocap.synth.synthesize` renders the motion onto a random
   (non-mean) body (``betas="random"``, seeded) from a camera at the given azimuth
   (0 = from the front, 90 = side-on, from the body's left). Skipped when
   ``sequence/gt.npz`` exists, so an interrupted bench resumes.
2. ``init.json``: :func:`flowmocap.eval.protocol.noisy_init` -- frame 0's ground-truth
   2D joints with 3 px noise and a rough pose with 15 degrees of noise on the main
   joints; the tracker starts from the mean shape.
3. ``flowmocap/``: :func:`flowmocap.pipeline.track` from that init, as ``flowmocap track
   SEQ --init init.json`` runs it (the ``synthetic`` profile: the init's keypoints on frame
   0 as in the paper, and MediaPipe's 2D and 3D joints of every rendered frame for ``E_j``,
   ``E_d``, ``E_3d`` and refits, the ``detector_keypoints`` default; the paper used no
   per-frame joints).
4. ``baseline/``: :func:`flowmocap.eval.baseline.run_baseline` on detector-like
   keypoints of every frame (ground truth + 3 px noise + 5 % outliers of 20-60 px),
   its shape fitted on frame 0 from the same init.
5. :func:`flowmocap.eval.scoring.score_result` on both results.

A finished result (``run.json`` status ``finished``) is not recomputed; an unfinished one
resumes. Each method runs in a fresh process (``multiprocessing`` spawn), so the
``peak_rss_mb`` it records is its own. The DAVIS dance-twirl clip needs automatic
initialisation (``flowmocap.vision.auto``, see :func:`run_real`); without it the entry is
recorded as skipped. The real clip runs through :func:`flowmocap.pipeline.track` exactly
as ``flowmocap track FRAMES_DIR`` does, so its row is what a user gets.
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

import torch

from flowmocap.body import JOINT_INDEX, load_body_model
from flowmocap.errors import DataError, InputError
from flowmocap.eval.baseline import KEYPOINT_JOINTS, BaselineConfig, detector_keypoints, run_baseline
from flowmocap.eval.protocol import noisy_init
from flowmocap.eval.scoring import COLUMNS, score_detector3d, score_result
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.init import parse_init
from flowmocap.io.results import has_result, json_default, read_result, write_run
from flowmocap.io.sequence import load_sequence
from flowmocap.pipeline import load_result, track
from flowmocap.synth import synthesize
from flowmocap.version import __version__
from flowmocap.vision.auto import load_detections
from flowmocap.vision.detect import SMPL_KEYPOINTS

ROOT = Path(__file__).resolve().parents[3]


def shared_data() -> Path:
    """The shared data folder (``mocap/``, ``video/``): ``$FLOWMOCAP_DATA`` where set (``bench
    --data``), else ``shared/data`` beside the source checkout (``../shared/data``)."""
    env = os.environ.get("FLOWMOCAP_DATA", "").strip()
    return Path(env).expanduser() if env else ROOT.parent / "shared" / "data"


SHARED = shared_data()
CMU_35_01 = SHARED / "mocap" / "cmu" / "35_01.amc"
DAVIS = SHARED / "video" / "davis-dance-twirl"
PRIOR_DATA = SHARED / "mocap" / "prior"
METHODS = ("flowmocap", "baseline", "detector3d")

#: The diverse suite: held-out CMU clips of ``mocap/prior`` (test subjects 2, 8, 13, 61,
#: never used for training or tuning) and the kind of motion each shows. Chosen to
#: cover every kind of motion the test split has, not by results.
DIVERSE_CLIPS: tuple[tuple[str, str], ...] = (
    ("cmu_mb/02_01.bvh", "walk"), ("cmu_mb/08_04.bvh", "walk"), ("cmu_mb/08_07.bvh", "walk"),
    ("cmu_mb/02_03.bvh", "run"),
    ("cmu_daz/13_11.bvh", "jump"), ("cmu_daz/13_39.bvh", "jump"), ("cmu_daz/13_42.bvh", "jump"),
    ("cmu_mb/02_04.bvh", "balance"), ("cmu_daz/13_10.bvh", "reach"),
    ("cmu_mb/02_05.bvh", "combat"), ("cmu_mb/02_07.bvh", "combat"),
    ("cmu_mb/02_06.bvh", "bend"), ("cmu_mb/02_10.bvh", "everyday"),
    ("cmu_daz/61_01.bvh", "dance"), ("cmu_daz/61_05.bvh", "dance"), ("cmu_daz/61_10.bvh", "dance"),
)
#: The tuning suite's kinds of motion (``category`` of ``mocap/prior/index.csv``, ``train``
#: split): two clips of each, for choosing settings without looking at the held-out clips.
TUNE_CATEGORIES: tuple[str, ...] = (
    "walk", "run", "dance (salsa)", "dance (modern/ballet)", "climb/playground", "sport (basketball)",
    "martial arts (karate)", "jump/reach/tiptoe",
)
#: Keys of a method's entry in bench.json that are always present (None = not applicable).
METRICS = ("local_cm", "global_cm", "mpjpe_cm", "accel_mm", "px2d", "iou", "s_per_frame")


@dataclass(frozen=True)
class SyntheticSpec:
    """One synthetic benchmark sequence."""

    name: str
    motion: str            # "builtin:walk" or a .amc / .bvh path
    frames: int
    size: str              # "WxH"
    fps: float
    azimuth: float         # degrees; 0 = front, 90 = side-on (body's left)
    seed: int = 0
    distance: float | None = None
    start: int = 0         # first frame (at fps) of the motion
    kind: str = ""         # kind of motion (the diverse suite's per-kind summary)


@dataclass(frozen=True)
class RealSpec:
    """A real clip with hand-made masks (scored by silhouette IoU)."""

    name: str
    frames_dir: str
    masks_dir: str


def suite(name: str, frames: int | None = None, size: str | None = None, data: str | Path | None = None) -> list:
    """The sequences of a suite; ``frames``/``size`` override (tests); ``data``: the shared
    data folder (default :func:`shared_data`)."""
    shared = Path(data) if data is not None else SHARED
    cmu, davis = shared / "mocap" / "cmu" / "35_01.amc", shared / "video" / "davis-dance-twirl"
    if name == "quick":
        specs = [SyntheticSpec("walk-quick", "builtin:walk", 20, "320x240", 30.0, 60.0, seed=0)]
    elif name == "full":
        specs = [SyntheticSpec("cmu35_01-side", str(cmu), 130, "640x480", 60.0, 90.0, seed=0),
                 SyntheticSpec("cmu35_01-45deg", str(cmu), 130, "640x480", 60.0, 45.0, seed=0),
                 RealSpec("davis-dance-twirl", str(davis / "JPEGImages"), str(davis / "Annotations"))]
    elif name == "diverse":
        return diverse_specs(frames=frames or 100, size=size or "640x480", data=shared / "mocap" / "prior")
    elif name == "tune":
        return tune_specs(frames=frames or 100, size=size or "640x480", data=shared / "mocap" / "prior")
    else:
        raise InputError(f"unknown suite {name!r}; use 'quick', 'full', 'diverse' or 'tune'.")
    return [_override(s, frames, size) for s in specs]


def most_active_window(path: str | Path, frames: int, fps: float) -> int:
    """First frame (at ``fps``) of the ``frames``-frame window of a mocap clip in which
    its joints move most relative to the root (sum of root-relative joint speeds), so a
    short window of a long clip shows its motion rather than a pause; 0 when the clip is
    not longer than the window."""
    from flowmocap.io.mocap import read_mocap, resample

    clip = resample(read_mocap(path), fps)
    if clip.num_frames <= frames:
        return 0
    rel = clip.positions - clip.positions[:, :1]
    speed = np.linalg.norm(np.diff(rel, axis=0), axis=-1).sum(-1)
    total = np.convolve(speed, np.ones(frames - 1), mode="valid")
    return int(np.argmax(total))


def diverse_specs(frames: int = 100, size: str = "640x480", fps: float = 60.0,
                  data: str | Path | None = None) -> list:
    """The ``diverse`` suite: :data:`DIVERSE_CLIPS` (held-out CMU clips of
    ``mocap/prior``), each its most active ``frames``-frame window
    (:func:`most_active_window`) at ``fps``, on a random body seen from a seeded random
    azimuth (uniform in [0, 360) degrees; seed = the clip's position in the list).

    Raises:
        DataError: the data folder or a clip is missing, or a clip is not in the test split.
    """
    import csv

    data = Path(data) if data is not None else PRIOR_DATA
    index = data / "index.csv"
    if not index.exists():
        raise DataError(f"the diverse suite needs {index} (shared/data/mocap/prior): give bench --data DIR (the folder holding mocap/ and video/) or set FLOWMOCAP_DATA.")
    with index.open(newline="") as f:
        split = {row["file"]: row.get("split", "") for row in csv.DictReader(f)}
    specs = []
    for seed, (rel, kind) in enumerate(DIVERSE_CLIPS):
        if split.get(rel) != "test":
            raise DataError(f"{rel} is not a test clip of {index}; the diverse suite uses held-out clips only.")
        path = data / rel
        azimuth = float(np.random.default_rng(seed).uniform(0.0, 360.0))
        start = most_active_window(path, frames, fps)
        specs.append(SyntheticSpec(f"{Path(rel).stem}-{kind}", str(path), frames, size, fps, round(azimuth, 1),
                                   seed=seed, start=start, kind=kind))
    return specs


def tune_specs(frames: int = 100, size: str = "640x480", fps: float = 60.0, data: str | Path | None = None,
               per_kind: int = 2) -> list:
    """The ``tune`` suite: the diverse suite's protocol (:func:`diverse_specs`) on
    ``train`` clips of ``mocap/prior`` (subjects never in the test split), ``per_kind``
    clips of each of :data:`TUNE_CATEGORIES`, spread evenly over each kind's clips in
    file order (chosen by that rule, not by results); seeds (the azimuth's and the
    body's) 100 and up, so no view repeats the diverse suite's. It is where settings
    are chosen; the diverse suite then says how they generalise. Not for choosing a
    learned part (the pose prior, the lifter): its clips are train clips, and their
    subjects' other clips are in that part's training data.

    Raises:
        DataError: the data folder is missing, or a kind has fewer than ``per_kind`` train clips.
    """
    import csv

    data = Path(data) if data is not None else PRIOR_DATA
    index = data / "index.csv"
    if not index.exists():
        raise DataError(f"the tune suite needs {index} (shared/data/mocap/prior): give bench --data DIR (the folder holding mocap/ and video/) or set FLOWMOCAP_DATA.")
    with index.open(newline="") as f:
        rows = [r for r in csv.DictReader(f) if r.get("split") == "train"]
    specs = []
    for kind in TUNE_CATEGORIES:
        files = sorted(r["file"] for r in rows if r.get("category") == kind)
        if len(files) < per_kind:
            raise DataError(f"{index} has {len(files)} train clips of kind {kind!r}; the tune suite needs {per_kind}.")
        for k in np.unique(np.linspace(0, len(files) - 1, per_kind).round().astype(int)):
            seed = 100 + len(specs)
            path = data / files[k]
            azimuth = float(np.random.default_rng(seed).uniform(0.0, 360.0))
            start = most_active_window(path, frames, fps)
            short = kind.split(" ")[0].split("/")[0]
            specs.append(SyntheticSpec(f"{Path(files[k]).stem}-{short}", str(path), frames, size, fps,
                                       round(azimuth, 1), seed=seed, start=start, kind=kind))
    return specs


def mocap_specs(files: list[str], frames: int = 130, size: str = "640x480", fps: float = 60.0,
                azimuths: tuple = (90.0, 45.0)) -> list:
    """The full suite's protocol on user-given ASF/AMC or BVH clips, one entry per view. Each
    file is read once here, so a damaged one is refused (``DataError``) before any work."""
    from flowmocap.io.amass import read_amass_npz
    from flowmocap.io.mocap import read_mocap

    specs = []
    for f in files:
        p = Path(f)
        if not p.exists():
            raise InputError(f"mocap file {p} does not exist; give .amc (with its .asf beside it) or .bvh files.")
        read_amass_npz(p) if p.suffix.lower() == ".npz" else read_mocap(p)
        for az in azimuths:
            specs.append(SyntheticSpec(f"{p.stem}-az{az:g}", str(p), frames, size, fps, float(az)))
    return specs


def _override(spec, frames, size):
    if isinstance(spec, SyntheticSpec):
        return replace(spec, frames=frames or spec.frames, size=size or spec.size)
    return spec


def commit() -> str:
    """``git rev-parse --short HEAD`` of the source tree (``+dirty`` with local changes), or
    ``unknown``; ``unknown`` too for an installed package (the folder above it is no
    flowmocap checkout, e.g. a virtual environment inside another git project)."""
    if not ((ROOT / "pyproject.toml").is_file() and (ROOT / "src" / "flowmocap").is_dir()):
        return "unknown"
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              timeout=10)
        if head.returncode != 0:
            return "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return head.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


# ------------------------------------------------------------------- method workers


def peak_rss_mb() -> tuple[float, str]:
    """Peak resident memory of this process in MiB, and how it was measured.

    Linux: ``VmHWM`` of ``/proc/self/status`` (the high-water mark of this program's own
    address space; ``ru_maxrss`` would also count the parent's peak inherited through
    fork + exec). Elsewhere: ``resource.getrusage(RUSAGE_SELF).ru_maxrss``.
    """
    import resource
    import sys

    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0, "VmHWM of /proc/self/status"
    except OSError:
        pass
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return (r / (1024.0 * 1024.0) if sys.platform == "darwin" else r / 1024.0), "ru_maxrss"


#: What ``as_video`` changes (recorded in bench.json as the protocol).
AS_VIDEO = ("synthetic sequences tracked as a user's video: flowmocap track FRAMES_DIR with automatic masks, 2D "
            "and 3D joints and starting pose from the detector, the video profile, the rendered camera given (as "
            "with --camera) and the body's gender; no rough pose, no rendered masks. The baseline as in the "
            "protocol: per-frame keypoint fit on GT 2D joints + 3 px noise + 5 % outliers of 20-60 px")


def run_method(method: str, seq_dir: str, res_dir: str, init: dict, baseline_seed: int = 0,
               record_memory: bool = True, progress: bool = False, tracker_config: dict | None = None,
               baseline_config: dict | None = None, as_video: bool = False) -> None:
    """Run one method on one sequence into ``res_dir`` (resuming an unfinished run).

    With ``record_memory`` the process's peak resident memory is added to ``run.json``
    as ``peak_rss_mb`` (meaningful when the method had the process to itself). The
    observed flows are not kept (2.5 MB a frame: a diverse suite's would take 4 GB; a
    resumed run computes the rest again, the same). With ``as_video`` flowmocap tracks
    the sequence's ``frames/`` as a user's frames (:data:`AS_VIDEO`); ``init`` then
    serves the baseline only.
    """
    seq = load_sequence(seq_dir)
    res = Path(res_dir)
    resume = has_result(res)
    gender = str(seq.meta.get("gender", "neutral"))
    if method == "flowmocap":
        source, given = ((str(Path(seq_dir) / "frames"),
                          {"init": "auto", "masks": "auto", "camera": str(Path(seq_dir) / "camera.json")})
                         if as_video else (seq_dir, {"init": init}))
        track(source, res, config=tracker_config or None, resume=resume, progress=progress, gender=gender, log=None,
              keep_flow=False, **given)
    elif method == "baseline":
        spec = parse_init(init, *seq.size)
        model = load_body_model("default", gender=gender)
        cfg = BaselineConfig(**{**(baseline_config or {}), "seed": baseline_seed})
        kp, conf = detector_keypoints(seq.gt["joints2d"], cfg.noise_px, cfg.outlier_rate, cfg.outlier_px, cfg.seed)
        note = (f"ground-truth 2D joints of {', '.join(KEYPOINT_JOINTS)} + N(0, {cfg.noise_px} px) per coordinate; "
                f"{100 * cfg.outlier_rate:g} % outliers displaced {cfg.outlier_px[0]:g}-{cfg.outlier_px[1]:g} px; "
                f"seed {cfg.seed}")
        run_baseline(seq, res, model, seq.camera, spec, kp, conf, cfg=cfg, resume=resume, progress=progress,
                     keypoint_note=note)
    else:
        raise InputError(f"unknown method {method!r}; use one of {METHODS}.")
    if record_memory:
        _, run = read_result(res)
        peak, how = peak_rss_mb()
        run["peak_rss_mb"] = round(peak, 1)
        run["peak_rss_note"] = f"{how} of a fresh process that ran only this method"
        run["torch_threads"] = torch.get_num_threads()
        write_run(res, run)


def _finished(res_dir: Path) -> bool:
    try:
        return json.loads((res_dir / "run.json").read_text()).get("status") == "finished"
    except (OSError, json.JSONDecodeError):
        return False


def _run_method_child(parent: int, **kw) -> None:
    """:func:`run_method` in the bench's child process: it ends with the bench (a bench killed
    outright left it tracking on, holding the result folder), and a Ctrl-C ends it with exit
    status 130 and no traceback (the bench says it was interrupted)."""
    import sys

    from flowmocap.vision.detect_worker import end_with_parent

    end_with_parent(parent)
    try:
        run_method(**kw)
    except KeyboardInterrupt:
        sys.exit(130)


def _run_isolated(isolate: bool, **kw) -> None:
    if not isolate:
        run_method(record_memory=False, **kw)
        return
    import multiprocessing as mp
    import os

    ctx = mp.get_context("spawn")
    proc = ctx.Process(target=_run_method_child, args=(os.getpid(),), kwargs=kw)
    proc.start()
    try:
        proc.join()
    except BaseException:  # Ctrl-C: the child got it too and records its stop; one sent here alone stops it
        proc.join(15)
        if proc.is_alive():
            proc.terminate()
            proc.join(15)
        raise
    if proc.exitcode in (130, -2):  # the child's Ctrl-C (the terminal's reaches both)
        raise KeyboardInterrupt
    if proc.exitcode != 0:
        raise DataError(f"the {kw['method']} run on {kw['seq_dir']} failed (exit code {proc.exitcode}); "
                        f"see the messages above, fix the cause and re-run the bench: it resumes from {kw['res_dir']}.")


# --------------------------------------------------------------------------- runner


def run_synthetic(spec: SyntheticSpec, out_dir: Path, isolate: bool = True, progress: bool = True,
                  log=print, tracker_config: dict | None = None, baseline_config: dict | None = None,
                  as_video: bool = False) -> dict:
    """Synthesise (unless present), run both methods (unless finished), score both
    (``as_video``: :func:`run_method`)."""
    d = out_dir / spec.name
    seq_dir = d / "sequence"
    if spec.motion != "builtin:walk" and not Path(spec.motion).exists():
        raise DataError(f"mocap file {spec.motion} not found; the full suite needs the shared data: "
                        "give bench --data DIR (the folder holding mocap/ and video/) or set FLOWMOCAP_DATA.")
    if not (seq_dir / "gt.npz").exists():
        log(f"[{spec.name}] synthesising {spec.frames} frames {spec.size} at {spec.fps:g} fps, "
            f"azimuth {spec.azimuth:g}")
        kw = dict(fps=spec.fps, size=spec.size, betas="random", seed=spec.seed, azimuth=spec.azimuth,
                  distance=spec.distance, flow=False, overwrite=True, start=spec.start)
        try:
            synthesize(spec.motion, seq_dir, frames=spec.frames, **kw)
        except InputError as e:
            if "requested but the motion has" not in str(e):
                raise
            log(f"[{spec.name}] the motion is shorter than {spec.frames} frames; using all of it")
            synthesize(spec.motion, seq_dir, frames=None, **kw)
    seq = load_sequence(seq_dir)
    init = noisy_init(seq.gt, frame=0, seed=spec.seed)
    (d / "init.json").write_text(json.dumps(init, indent=2))
    entry = {"settings": {**asdict(spec), "frames": len(seq), "baseline_keypoint_seed": spec.seed + 1}}
    for method in ("flowmocap", "baseline"):
        res = d / method
        if _finished(res):
            log(f"[{spec.name}] {method}: finished result found in {res}, not recomputed")
        else:
            log(f"[{spec.name}] running {method} ...")
            t0 = time.perf_counter()
            _run_isolated(isolate, method=method, seq_dir=str(seq_dir), res_dir=str(res), init=init,
                          baseline_seed=spec.seed + 1, progress=progress, tracker_config=tracker_config,
                          baseline_config=baseline_config, as_video=as_video)
            log(f"[{spec.name}] {method} done in {time.perf_counter() - t0:.0f} s")
        scores = score_result(res, seq)
        scores.pop("local_cm_per_frame", None)
        scores.pop("iou_per_frame", None)
        entry[method] = {**{k: scores.get(k) for k in METRICS}, **{k: v for k, v in scores.items() if k not in METRICS}}
    det = score_detector3d(d / "flowmocap", seq)
    if det is not None:
        det.pop("local_cm_per_frame", None)
    entry["detector3d"] = det
    return entry


def run_real(spec: RealSpec, out_dir: Path, progress: bool = True, log=print,
             tracker_config: dict | None = None) -> dict:
    """A real clip, tracked without manual input by :func:`flowmocap.pipeline.track` as
    ``flowmocap track FRAMES_DIR`` runs it (automatic masks, 2D and 3D joints, init,
    camera; the ``video`` profile; re-initialisation), scored by silhouette IoU against
    its hand-made masks; or a skip record when automatic initialisation is unavailable.

    The baseline fits the same detections' keypoints of every frame (frames with fewer
    than 4 confident joints make it ``None``). Joint metrics are ``None`` (no ground truth).
    """
    entry = {"settings": asdict(spec)}
    if not Path(spec.frames_dir).is_dir():
        return {**entry, "skipped": f"{spec.frames_dir} not found"}
    hand = load_sequence(spec.frames_dir, masks=spec.masks_dir)
    w, h = hand.size
    d = out_dir / spec.name
    res = d / "flowmocap"
    if not _finished(res):
        log(f"[{spec.name}] running flowmocap track {spec.frames_dir} (automatic everything) ...")
        track(spec.frames_dir, res, config=tracker_config or None, resume=has_result(res),
              progress=progress, log=log)
    result = load_result(res)
    entry["settings"]["camera"] = result.run.get("camera_source")
    entry["settings"]["profile"] = result.run.get("profile")
    model = load_body_model("default")
    scores = score_result(res, hand, model=model)
    entry["flowmocap"] = {k: scores.get(k) for k in METRICS}
    track_ = load_detections(res)
    init = json.loads((res / "init_auto.json").read_text())
    names = SMPL_KEYPOINTS
    kp = np.full((len(hand), 24, 2), np.nan)
    conf = np.zeros((len(hand), 24))
    for k, n in enumerate(names):
        kp[:, JOINT_INDEX[n]] = track_.keypoints[:, k]
        conf[:, JOINT_INDEX[n]] = track_.confidence[:, k]
    conf = np.where(conf >= 0.3, conf, 0.0)
    if (conf > 0).sum(1).min() < 4:
        entry["baseline"] = None
        entry["baseline_note"] = "some frames have fewer than 4 confident detected joints"
        return entry
    bres = d / "baseline"
    if not _finished(bres):
        log(f"[{spec.name}] running baseline ...")
        run_baseline(hand, bres, model, result.camera, parse_init(init, w, h), kp, conf,
                     resume=has_result(bres), progress=progress,
                     keypoint_note="flowmocap.vision.auto.detect_sequence keypoints (confidence >= 0.3)")
    b = score_result(bres, hand, model=model)
    entry["baseline"] = {k: b.get(k) for k in METRICS}
    return entry


def run_bench(specs: list, out_dir: str | Path, suite_name: str, isolate: bool = True, progress: bool = True,
              log=print, tracker_config: dict | None = None, baseline_config: dict | None = None,
              as_video: bool = False) -> dict:
    """Run the benchmark and write ``out_dir/bench.json`` and ``out_dir/bench.md``.

    Args:
        specs: :class:`SyntheticSpec` / :class:`RealSpec` entries (:func:`suite`,
            :func:`mocap_specs`).
        out_dir: the bench folder (one sub-folder per sequence; re-runs resume).
        suite_name: recorded in bench.json.
        isolate: run each method in a fresh process (peak memory per method).
        tracker_config, baseline_config: overrides of :class:`TrackerConfig` /
            :class:`~flowmocap.eval.baseline.BaselineConfig` fields.
        as_video: track the synthetic sequences as a user's video (:data:`AS_VIDEO`)
            instead of by the paper's protocol.

    Returns:
        the contents of bench.json.

    Raises:
        InputError: ``out_dir`` holds a bench of the other kind (protocol or as a video),
            whose finished runs would be taken for this one's.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        before = json.loads((out_dir / "bench.json").read_text()).get("settings", {}).get("as_video", False)
    except (OSError, json.JSONDecodeError):
        before = as_video
    if bool(before) != bool(as_video):
        raise InputError(f"{out_dir} holds a bench run {'as a video' if before else 'by the protocol'}; its finished "
                         f"results would be reused for a run {'as a video' if as_video else 'by the protocol'}. "
                         "Give another --out.")
    result = {
        "commit": commit(), "suite": suite_name, "flowmocap": __version__, "torch": torch.__version__,
        "settings": {
            "protocol": AS_VIDEO if as_video else
                        ("synthetic: random body shape (seeded), tracker init from noisy_init (frame-0 GT 2D "
                         "joints + 3 px noise, rough pose with 15 deg noise, mean shape); baseline: per-frame "
                         "keypoint fit on GT 2D joints + 3 px noise + 5 % outliers of 20-60 px"),
            "as_video": bool(as_video),
            "tracker": TrackerConfig.load(None, profile="video" if as_video else "synthetic",
                                          **(tracker_config or {})).to_dict(),
            "baseline": BaselineConfig(**(baseline_config or {})).to_dict(),
            "baseline_keypoint_seed": "sequence seed + 1 (the seed field above is not used)",
            "isolated_processes": isolate,
            "metrics": ("local/global: similarity Procrustes per frame / per sequence, mean over the paper's "
                        "13 joints, cm; mpjpe: root-relative, cm; accel: |2nd difference pred - gt| in the world "
                        "frame, mm/frame^2 at the sequence's fps; px2d: 13 joints, px; iou: fitted body vs masks; "
                        "s_per_frame: median seconds per tracked frame (init excluded, see init_s)"),
        },
        "sequences": {},
    }
    for spec in specs:
        t0 = time.perf_counter()
        if isinstance(spec, RealSpec):
            entry = run_real(spec, out_dir, progress=progress, log=log, tracker_config=tracker_config)
        else:
            entry = run_synthetic(spec, out_dir, isolate=isolate, progress=progress, log=log,
                                  tracker_config=tracker_config, baseline_config=baseline_config, as_video=as_video)
        entry["wall_s"] = round(time.perf_counter() - t0, 1)
        result["sequences"][spec.name] = entry
        result["summary"] = summarise(result)
        _write(out_dir, result)
    log(format_table(result))
    _write(out_dir, result)
    return result


#: Metrics summarised over a suite's synthetic sequences.
SUMMARY_METRICS = ("local_cm", "global_cm", "px2d", "accel_mm")
#: fewest scored clips for the medians' bootstrap interval (:func:`median_interval`)
INTERVAL_MIN_CLIPS = 5


def median_interval(values, level: float = 0.95, draws: int = 2000, seed: int = 0) -> list[float] | None:
    """``[low, high]``: a percentile bootstrap interval of the median of per-clip values
    (``scipy.stats.bootstrap``, the clips drawn with replacement), or None for fewer than
    :data:`INTERVAL_MIN_CLIPS` values. It holds which clips a suite happens to contain,
    not the tracker's chance between trackings."""
    from scipy.stats import bootstrap

    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], np.float64)
    if v.size < INTERVAL_MIN_CLIPS:
        return None
    res = bootstrap((v,), np.median, confidence_level=level, n_resamples=draws, method="percentile",
                    random_state=np.random.default_rng(seed), vectorized=True, axis=-1)
    return [float(res.confidence_interval.low), float(res.confidence_interval.high)]


def summarise(result: dict) -> dict:
    """Suite-level figures over the synthetic sequences of bench.json's ``sequences``:
    per method, the median and mean of :data:`SUMMARY_METRICS`; per kind of motion, the
    mean; and the ratios the generalisation targets are stated in (ours / baseline
    global, ours / detector-3D local, each a ratio of medians). Empty when fewer than
    two sequences have scores."""
    rows = {n: e for n, e in result.get("sequences", {}).items()
            if isinstance(e, dict) and isinstance(e.get("flowmocap"), dict) and e["flowmocap"].get("local_cm") is not None}
    if len(rows) < 2:
        return {}

    def values(method, key, names=None):
        v = [rows[n][method].get(key) for n in (names or rows) if isinstance(rows[n].get(method), dict)]
        return np.array([x for x in v if x is not None], np.float64)

    out: dict = {"sequences": len(rows), "median": {}, "mean": {}, "per_kind": {}}
    for method in METHODS:
        out["median"][method] = {k: (float(np.median(values(method, k))) if values(method, k).size else None)
                                 for k in SUMMARY_METRICS}
        out["mean"][method] = {k: (float(values(method, k).mean()) if values(method, k).size else None)
                               for k in SUMMARY_METRICS}
    kinds: dict[str, list[str]] = {}
    for n, e in rows.items():
        kinds.setdefault(e.get("settings", {}).get("kind") or "-", []).append(n)
    for kind, names in kinds.items():
        out["per_kind"][kind] = {"clips": len(names), **{
            f"{method}_{k}": (float(values(method, k, names).mean()) if values(method, k, names).size else None)
            for method in METHODS for k in ("local_cm", "global_cm")}}
    med = out["median"]

    def ratio(a, b):
        return None if a is None or not b else a / b

    out["ratios"] = {
        "global_vs_baseline": ratio(med["flowmocap"]["global_cm"], med["baseline"]["global_cm"]),
        "local_vs_detector3d": ratio(med["flowmocap"]["local_cm"], med["detector3d"]["local_cm"]),
    }
    out["median_interval"] = {k: median_interval(values("flowmocap", k)) for k in ("local_cm", "global_cm")}
    return out


def format_summary(summary: dict) -> list[str]:
    """:func:`summarise`'s figures as Markdown lines (empty for no summary)."""
    if not summary:
        return []

    def f(v, spec=".1f"):
        return "--" if v is None else format(v, spec)

    lines = [f"## Summary over {summary['sequences']} sequences", "",
             "| method | median local cm | median global cm | mean local cm | mean global cm | median 2D px |",
             "|---|---:|---:|---:|---:|---:|"]
    for method in METHODS:
        md, mn = summary["median"][method], summary["mean"][method]
        lines.append(f"| {method} | {f(md['local_cm'])} | {f(md['global_cm'])} | {f(mn['local_cm'])} | "
                     f"{f(mn['global_cm'])} | {f(md['px2d'])} |")
    r = summary["ratios"]
    iv = summary.get("median_interval") or {}
    if iv.get("local_cm") and iv.get("global_cm"):
        lines += ["", "flowmocap's medians with 95 % intervals over which clips the suite holds (a percentile "
                  "bootstrap over the clips; not the tracker's chance between trackings): local "
                  f"{f(summary['median']['flowmocap']['local_cm'], '.2f')} [{iv['local_cm'][0]:.2f}, "
                  f"{iv['local_cm'][1]:.2f}] cm, global {f(summary['median']['flowmocap']['global_cm'], '.2f')} "
                  f"[{iv['global_cm'][0]:.2f}, {iv['global_cm'][1]:.2f}] cm"]
    lines += ["", f"ours / baseline, median global: {f(r['global_vs_baseline'], '.2f')}; "
              f"ours / detector-3D, median local: {f(r['local_vs_detector3d'], '.2f')}", "",
              "| kind | clips | flowmocap local | flowmocap global | baseline local | baseline global | "
              "detector-3D local |", "|---|---:|---:|---:|---:|---:|---:|"]
    for kind, k in sorted(summary["per_kind"].items()):
        lines.append(f"| {kind} | {k['clips']} | {f(k['flowmocap_local_cm'])} | {f(k['flowmocap_global_cm'])} | "
                     f"{f(k['baseline_local_cm'])} | {f(k['baseline_global_cm'])} | {f(k['detector3d_local_cm'])} |")
    lines.append("")
    return lines


def _write(out_dir: Path, result: dict) -> None:
    (out_dir / "bench.json").write_text(json.dumps(result, indent=2, default=json_default))
    (out_dir / "bench.md").write_text(format_table(result) + "\n")


def _fmt(v, key) -> str:
    if v is None:
        return "--"
    return f"{v:.3f}" if key == "iou" else f"{v:.2f}" if key == "s_per_frame" else f"{v:.1f}"


def format_table(result: dict) -> str:
    """bench.json as Markdown: one table per sequence (rows: methods), plus skips."""
    as_video = (result.get("settings") or {}).get("as_video")
    lines = [f"# flowmocap bench: suite `{result['suite']}`{', tracked as a video' if as_video else ''}, "
             f"commit `{result['commit']}`", ""]
    if as_video:
        lines += [f"Protocol: {result['settings']['protocol']}.", ""]
    lines += format_summary(result.get("summary") or {})
    for name, entry in result["sequences"].items():
        s = entry.get("settings", {})
        if "motion" in s:
            desc = (f"{Path(s['motion']).name}, {s['frames']} frames from {s.get('start', 0)}, {s['size']}, "
                    f"{s['fps']:g} fps, azimuth {s['azimuth']:g} deg, seed {s['seed']}"
                    + (f", {s['kind']}" if s.get("kind") else ""))
        else:
            desc = s.get("frames_dir", "")
        lines.append(f"## {name} ({desc})")
        lines.append("")
        if entry.get("skipped"):
            lines += [f"skipped: {entry['skipped']}", ""]
            continue
        lines.append("| method | " + " | ".join(label for _, label in COLUMNS) + " |")
        lines.append("|---|" + "---:|" * len(COLUMNS))
        for method in METHODS:
            row = entry.get(method)
            if row is None and method == "detector3d":
                continue
            if row is None:
                lines.append(f"| {method} | " + " | ".join("--" for _ in COLUMNS) + " |")
                continue
            lines.append(f"| {method} | " + " | ".join(_fmt(row.get(k), k) for k, _ in COLUMNS) + " |")
        lines.append("")
    lines.append("local/global: mean 3D error on 13 joints after per-frame / per-sequence similarity Procrustes; "
                 "MPJPE: root-relative, no alignment; accel: acceleration error (world frame, at the clip's fps); "
                 "2D px: projected joints vs ground truth; IoU: fitted silhouette vs mask; s/frame: median per "
                 "tracked frame (flowmocap: observed flow included; init excluded). detector3d: MediaPipe's own "
                 "3D joints (world landmarks) of the rendered frames, head = middle of the ears, scored on the frames "
                 "where it gives all 13 joints (per-frame alignment only). `--` = not applicable. "
                 "Settings in bench.json.")
    return "\n".join(lines)
