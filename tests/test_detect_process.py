"""The person detector in processes of its own (flowmocap.vision.detect_worker): the same
detections as in this process, stretches stored as they finish, a killed detector process
reported as a DetectorError with the finished stretches kept, a rerun going on from them
(also through ``flowmocap.track --resume``), the detector process's errors raised here, and
the stretch files and a video's sequence surviving the trip between processes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import flowmocap.vision.auto as auto
from flowmocap.errors import DataError, DetectorError
from flowmocap.vision.auto import Candidate, PackedMask, detect_sequence, load_chunk, save_chunk
from flowmocap.vision.detect import KEYPOINT_NAMES

needs_mediapipe = pytest.mark.skipif(
    __import__("importlib").util.find_spec("mediapipe") is None,
    reason="mediapipe is not installed (pip install mediapipe==0.10.21): the detector process runs it")


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A 12-frame 320x240 walk: big enough for MediaPipe to find the person in every frame."""
    from flowmocap.synth import synthesize

    d = tmp_path_factory.mktemp("detproc") / "seq"
    synthesize("builtin:walk", d, fps=30, frames=12, size="320x240", seed=1, azimuth=80.0, distance=3.0, flow=False)
    return d


def _same(a, b) -> None:
    np.testing.assert_array_equal(a.found, b.found)
    np.testing.assert_array_equal(a.keypoints, b.keypoints)
    np.testing.assert_array_equal(a.confidence, b.confidence)
    np.testing.assert_array_equal(a.world, b.world)
    for i in range(len(a)):
        np.testing.assert_array_equal(a.mask(i), b.mask(i))


def _kill_detector_process_when_it_starts(timeout: float = 60.0) -> threading.Thread:
    """A thread that SIGKILLs this process's first child running the detector worker."""
    me = os.getpid()

    def watch():
        end = time.time() + timeout
        while time.time() < end:
            for d in Path("/proc").iterdir():
                if not d.name.isdigit():
                    continue
                try:
                    ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
                    cmd = (d / "cmdline").read_bytes()
                except (OSError, IndexError, ValueError):
                    continue
                if ppid == me and b"detect_worker" in cmd:
                    time.sleep(0.5)
                    os.kill(int(d.name), signal.SIGKILL)
                    return
            time.sleep(0.05)

    t = threading.Thread(target=watch, daemon=True)
    t.start()
    return t


@needs_mediapipe
def test_detector_processes_give_the_same_detections_as_this_process(clip, tmp_path, monkeypatch):
    from flowmocap.io.sequence import load_sequence

    seq = load_sequence(clip)
    apart = detect_sequence(seq, tmp_path / "apart", progress=False)
    assert not (tmp_path / "apart" / "detections" / "chunks").exists()  # cleared once the detections are written
    monkeypatch.setattr(auto, "DETECT_IN_CHILD", False)
    here = detect_sequence(seq, tmp_path / "here", progress=False)
    assert apart.info["detector"] == here.info["detector"] and apart.found.all()
    _same(apart, here)
    # the plain detector (an input with its own masks) as well
    monkeypatch.setattr(auto, "DETECT_IN_CHILD", True)
    plain = detect_sequence(seq, tmp_path / "plain", detector="plain", progress=False)
    assert "tta4" not in plain.info["detector"] and "search" not in plain.info["detector"]


def test_the_detector_process_loads_no_torch(tmp_path):
    """Nor do the sequences it is sent (a video's and a frame folder's, unpickled and read
    as its task's are): torch would add ~190 MB to its resident memory."""
    import pickle

    from flowmocap.io.sequence import load_sequence
    from flowmocap.io.video import load_video

    from test_video import write_video

    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 255, (48, 64, 3), np.uint8) for _ in range(3)]
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"{i:03d}.png"), f)
    for k, seq in enumerate((load_video(write_video(tmp_path / "v.mp4", frames)), load_sequence(folder))):
        (tmp_path / f"seq{k}.pkl").write_bytes(pickle.dumps(seq))
    code = ("import sys, pickle, flowmocap.vision.detect_worker, flowmocap.vision.auto\n"
            f"for k in range(2): pickle.loads(open(r'{tmp_path}/seq%d.pkl' % k, 'rb').read()).frame(1)\n"
            "print('torch' in sys.modules, 'flowmocap.pipeline' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "False"]


def test_flowmocap_io_names_stay_the_functions_when_their_modules_load():
    """flowmocap.io imports its names lazily; ``retarget`` and ``builtin_walk`` are also its
    modules' names, and stay the functions even after another module has loaded those."""
    code = ("import types, flowmocap.io.motion_source, flowmocap.io as io\n"
            "from flowmocap.io import retarget, builtin_walk, SmplMotion\n"
            "print(callable(retarget), isinstance(io.builtin_walk, types.ModuleType), "
            "builtin_walk is io.builtin_walk, SmplMotion.__name__, 'read_bvh' in dir(io))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["True", "False", "True", "SmplMotion", "True"]


@needs_mediapipe
def test_a_killed_detector_process_keeps_the_finished_stretches_and_a_rerun_goes_on(clip, tmp_path, monkeypatch):
    from flowmocap.io.sequence import load_sequence

    seq = load_sequence(clip)
    monkeypatch.setattr(auto, "DETECT_CHUNK", 5)  # stretches 0-4, 5-9, 10-11
    monkeypatch.setattr(auto, "DETECT_WARM_UP", 2)
    whole = detect_sequence(seq, tmp_path / "whole", progress=False)
    real = auto._run_detector_process
    calls = []

    def run(task, folder, a, b):
        calls.append(a)
        if a == 5 and len(calls) == 2:  # the second stretch of the first run: killed as the OOM killer would
            _kill_detector_process_when_it_starts()
        return real(task, folder, a, b)

    monkeypatch.setattr(auto, "_run_detector_process", run)
    out = tmp_path / "out"
    with pytest.raises(DetectorError, match=r"frames 5-9 was killed by signal 9.*frame 5"):
        detect_sequence(seq, out, progress=False)
    chunks = out / "detections" / "chunks"
    assert sorted(p.name for p in chunks.iterdir()) == ["find-000000-000005.npz"]
    first = (chunks / "find-000000-000005.npz").stat()
    calls.clear()
    again = detect_sequence(seq, out, progress=False)
    assert calls == [5, 10]  # the stored stretch is not looked at again
    assert not chunks.exists()
    _same(again, whole)
    assert first.st_size > 0


@needs_mediapipe
def test_track_resumes_a_detection_pass_whose_process_was_killed(clip, tmp_path, monkeypatch):
    import flowmocap
    from flowmocap.io.sequence import load_sequence

    from test_video import write_video

    seq = load_sequence(clip)
    video = write_video(tmp_path / "walk.mp4", [seq.frame(i) for i in range(len(seq))])
    monkeypatch.setattr(auto, "DETECT_CHUNK", 6)
    real = auto._run_detector_process
    calls = []

    def run(task, folder, a, b):
        calls.append(a)
        if calls == [0, 6]:
            _kill_detector_process_when_it_starts()
        return real(task, folder, a, b)

    monkeypatch.setattr(auto, "_run_detector_process", run)
    quick = {"iterations": 2, "init_iterations": 4, "init_flow_iterations": 2}
    out = tmp_path / "out"
    with pytest.raises(DetectorError):
        flowmocap.track(video, out, config=quick, progress=False)
    assert (out / "detections" / "chunks" / "find-000000-000006.npz").exists()
    calls.clear()
    result = flowmocap.track(video, out, config=quick, progress=False, resume=True)
    assert calls == [6] and result.run["status"] == "finished" and len(result) >= 10


@needs_mediapipe
def test_an_error_in_the_detector_process_is_raised_here(clip, tmp_path):
    import shutil

    from flowmocap.io.sequence import load_sequence

    copy = tmp_path / "seq"
    shutil.copytree(clip, copy)
    seq = load_sequence(copy)
    seq.frames[3].unlink()
    with pytest.raises(DataError, match="cannot read image .*000003"):
        detect_sequence(seq, tmp_path / "out", progress=False)


def _candidate(rng, world=True, shape=(30, 40)) -> Candidate:
    K = len(KEYPOINT_NAMES)
    m = np.zeros(shape, bool)
    m[5:20, 8:30] = rng.random((15, 22)) > 0.4
    return Candidate(tuple(rng.random(4) * 30), rng.random((K, 2)) * 40, rng.random(K), PackedMask.pack(m),
                     rng.random((K, 3)) if world else None)


def test_stored_stretches_round_trip_exactly(tmp_path):
    rng = np.random.default_rng(3)
    got = [[_candidate(rng), _candidate(rng, world=False)], [], [_candidate(rng)]]
    path = tmp_path / "find-000010-000013.npz"
    save_chunk(path, "key", 10, 13, got)
    back = load_chunk(path, "key", 10, 13)
    assert [len(g) for g in back] == [2, 0, 1]
    for g, h in zip(got, back):
        for c, d in zip(g, h):
            assert c.box == d.box and c.mask.shape == d.mask.shape and c.mask.box == d.mask.box
            np.testing.assert_array_equal(c.keypoints, d.keypoints)
            np.testing.assert_array_equal(c.confidence, d.confidence)
            np.testing.assert_array_equal(c.mask.unpack(), d.mask.unpack())
            assert (c.world is None) == (d.world is None)
            if c.world is not None:
                np.testing.assert_array_equal(c.world, d.world)
    assert load_chunk(path, "other key", 10, 13) is None  # made with other detectors or input
    assert load_chunk(path, "key", 0, 3) is None
    assert load_chunk(tmp_path / "absent.npz", "key", 10, 13) is None
    path.write_bytes(b"half a file")
    assert load_chunk(path, "key", 10, 13) is None
    save_chunk(path, "key", 0, 2, [[], []])  # a stretch with nobody in it
    assert load_chunk(path, "key", 0, 2) == [[], []]


def test_a_video_sequence_travels_to_another_process(tmp_path):
    import pickle

    from flowmocap.io.video import load_video

    from test_video import write_video

    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 255, (48, 64, 3), np.uint8) for _ in range(5)]
    seq = load_video(write_video(tmp_path / "v.mp4", frames))
    before = seq.frame(3)
    copy = pickle.loads(pickle.dumps(seq))
    assert len(copy) == 5 and copy.size == seq.size and copy.meta == seq.meta
    np.testing.assert_array_equal(copy.frame(3), before)
    np.testing.assert_array_equal(copy.frame(0), seq.frame(0))


def test_stretches_read_without_their_masks_give_them_back_in_frame_order(tmp_path):
    """A long video's candidates are held without their masks (StoredMask) until the chosen
    person's are written: each is read back from its stretch file, as stored."""
    from flowmocap.vision.auto import StoredMask, _mask_array

    rng = np.random.default_rng(5)
    got = [[_candidate(rng)], [_candidate(rng), _candidate(rng, world=False)], []]
    path = tmp_path / "find-000000-000003.npz"
    save_chunk(path, "key", 0, 3, got)
    light = load_chunk(path, "key", 0, 3, masks=False)
    assert all(isinstance(c.mask, StoredMask) for g in light for c in g)
    for g, h in zip(got, light):
        for c, d in zip(g, h):
            np.testing.assert_array_equal(_mask_array(d.mask), c.mask.unpack())
            np.testing.assert_array_equal(d.keypoints, c.keypoints)
    again = tmp_path / "copy.npz"  # stored again (a follow stretch keeps a chosen candidate as it came)
    save_chunk(again, "key", 0, 3, light)
    for g, h in zip(got, load_chunk(again, "key", 0, 3)):
        for c, d in zip(g, h):
            np.testing.assert_array_equal(d.mask.unpack(), c.mask.unpack())


_POSE2SIM = Path(__file__).resolve().parents[2] / "shared" / "data" / "video" / "pose2sim-multi" / "videos" / "cam04.mp4"


@needs_mediapipe
@pytest.mark.skipif(not _POSE2SIM.exists(), reason="the Pose2Sim recording (../shared/data/video/pose2sim-multi) "
                    "is not next to the repository")
def test_choosing_another_person_in_detector_processes(tmp_path, monkeypatch):
    """person=1 on two people (the Pose2Sim recording's cam04, 12 frames at 640 px): the
    person is followed in detector processes as in this process (one stretch), and in
    stretches of 5 frames the same person is kept."""
    import av
    import cv2

    from flowmocap.io.sequence import load_sequence
    from flowmocap.vision.person import box_iou

    frames = tmp_path / "frames"
    frames.mkdir()
    with av.open(str(_POSE2SIM)) as container:
        for i, f in enumerate(container.decode(video=0)):
            if i == 12:
                break
            img = f.to_ndarray(format="bgr24")
            s = 640 / max(img.shape[:2])
            cv2.imwrite(str(frames / f"{i:04d}.png"), cv2.resize(img, (round(img.shape[1] * s), round(img.shape[0] * s)),
                                                                   interpolation=cv2.INTER_AREA))
    seq = load_sequence(frames)
    apart = detect_sequence(seq, tmp_path / "apart", progress=False, person=1)
    monkeypatch.setattr(auto, "DETECT_IN_CHILD", False)
    here = detect_sequence(seq, tmp_path / "here", progress=False, person=1)
    _same(apart, here)
    assert apart.found.sum() >= 10 and apart.info["person"]["rank"] == 1
    monkeypatch.setattr(auto, "DETECT_IN_CHILD", True)
    monkeypatch.setattr(auto, "DETECT_CHUNK", 5)
    cut = detect_sequence(seq, tmp_path / "cut", progress=False, person=1)
    both = cut.found & apart.found
    boxes = lambda t, i: tuple(np.concatenate([t.keypoints[i][t.confidence[i] > 0.5].min(0),  # noqa: E731
                                               t.keypoints[i][t.confidence[i] > 0.5].max(0)]))
    assert both.sum() >= 9 and all(box_iou(boxes(cut, i), boxes(apart, i)) > 0.5 for i in np.nonzero(both)[0])


def test_a_full_disk_in_the_detector_process_is_an_output_error_not_a_crash(tmp_path, monkeypatch):
    """A write that failed in the detector's process (a full disk, ulimit -f) came out as its
    traceback, then 'the detector process failed with exit status 1' (exit 7) and 'the frames
    before 0 are kept'; now the process says what failed and the run ends as a full disk does
    elsewhere (OutputError, exit 5)."""
    import json
    import pickle

    from flowmocap.errors import OutputError
    from flowmocap.vision import detect_worker

    def full(task):
        raise OSError(27, "File too large", str(tmp_path / "chunks" / "000000.npz"))

    import signal

    monkeypatch.setattr(auto, "run_chunk", full)
    monkeypatch.setattr(signal, "signal", lambda *a: None)  # main's SIGTERM handler stays out of pytest's process
    monkeypatch.setattr(detect_worker, "_end_with_parent", lambda: None)
    monkeypatch.setattr(detect_worker, "_native_logs_to_devnull", lambda: None)
    job = tmp_path / "task-000000.pkl"
    job.write_bytes(pickle.dumps({}))
    assert detect_worker.main([str(job)]) == auto.WRITE_FAILED
    said = json.loads((tmp_path / "task-000000.error.json").read_text())
    assert said["type"] == "OutputError" and "File too large" in said["message"]

    def process(rc, message=None):  # what the parent sees of a worker that ended so
        class Ended:
            def __init__(self, cmd, env=None):
                if message is not None:
                    (tmp_path / "w" / "task-000000.error.json").write_text(json.dumps(message))

            def wait(self, timeout=None):
                return rc
        return Ended

    monkeypatch.setattr(subprocess, "Popen", process(5, said))
    with pytest.raises(OutputError, match=r"File too large.*free space .*run again \(--resume\) to start it again"):
        auto._run_detector_process({}, tmp_path / "w", 0, 8)
    monkeypatch.setattr(subprocess, "Popen", process(5))  # the disk too full even for the error's file
    with pytest.raises(OutputError, match=r"frames 8-15 could not write .*free space, then the frames before 8 are "
                                          r"kept"):
        auto._run_detector_process({}, tmp_path / "w", 8, 16)
