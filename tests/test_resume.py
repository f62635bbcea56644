"""Results that are never lost or mixed (issue 21): a kill at any instant resumes exactly,
one writer per result folder, resume only with the same set-up, caches tied to their
input, inputs checked before any long work, and every failure a clear error that keeps
the finished frames."""

from __future__ import annotations

import json
import multiprocessing
import os
import random
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import flowmocap
from flowmocap.cli import main
from flowmocap.errors import DataError, FolderBusyError, InputError, OutputError
from flowmocap.fit.config import TrackerConfig
from flowmocap.eval.protocol import noisy_init
from flowmocap.io.lock import FolderLock, is_locked
from flowmocap.io.results import FrameLog, has_result, read_result
from flowmocap.io.sequence import load_sequence
from flowmocap.synth import synthesize

#: rel_tolerance 0: every frame takes its few iterations, so that the frames (not the start-up)
#: fill most of a run and the random kills land at many stages of it.
QUICK = {"iterations": 4, "init_iterations": 6, "init_flow_iterations": 4, "rel_tolerance": 0.0}
#: The kill test's tracker: one pyramid level, a few iterations and no flip test, so that
#: 40 runs fit in a minute; the commit protocol it tests is the same for any settings.
LEAN = {**QUICK, "iterations": 3, "levels": 1, "stages": [[0]], "flip_test": False}
FRAMES = 8
KILL_POINTS = 20


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    d = tmp_path_factory.mktemp("resume") / "seq"
    synthesize("builtin:walk", d, fps=30, frames=FRAMES, size="120x90", betas="random", seed=2, azimuth=60.0,
               flow=False)
    init = noisy_init(load_sequence(d).gt, frame=0, seed=2)
    (d.parent / "init.json").write_text(json.dumps(init))
    return d


def _kw(clip: Path) -> dict:
    return dict(init=clip.parent / "init.json", config=QUICK, joints3d="off", progress=False, log=None)


def _known_start(clip: Path):
    from flowmocap.fit.tracker import KnownStart

    gt = load_sequence(clip).gt
    return KnownStart(gt["poses"][:2], gt["trans"][:2], gt["betas"])


def _run(clip: str, out: str, crash: str | None = None, known: bool = False) -> None:
    """Child process: track ``clip`` into ``out`` (resuming what is there), from the
    init.json or, with ``known``, the true first two frames (no initialisation: the run
    is all frames and commits); ``crash`` names a point of the commit at which the
    process kills itself (SIGKILL)."""
    import flowmocap.atomic as atomic
    import flowmocap.io.results as results

    if crash:
        where, nth = crash.split(":")
        count = {"n": 0}

        def die_at(point: str) -> None:
            if point == where:
                count["n"] += 1
                if count["n"] == int(nth):
                    os.kill(os.getpid(), signal.SIGKILL)

        write_json, replace = results.write_json, atomic.os.replace

        def patched_write_json(path, info):
            if Path(path).name == "progress.json":
                die_at("before-progress")  # frames.bin and events.jsonl appended, not committed
            return write_json(path, info)

        class _Os:  # os for flowmocap.atomic: a kill between the temporary file and its rename
            def __getattr__(self, name):
                return getattr(os, name)

            @staticmethod
            def replace(src, dst):
                die_at("before-rename")
                replace(src, dst)
                die_at("after-rename")

        results.write_json = patched_write_json
        atomic.os = _Os()
    kw = _kw(Path(clip))
    if known:
        kw["init"], kw["config"] = _known_start(Path(clip)), LEAN
    flowmocap.track(clip, out, resume=True, **kw)


@pytest.fixture(scope="module")
def ctx():
    """Children forked from a server that has imported flowmocap: a start costs
    milliseconds, not the seconds of a fresh interpreter. ``torch._dynamo`` too: torch
    imports it on the first optimiser made (2.6 s here), which otherwise fell in each
    child's first tracked frame and left the kill test's random instants hardly any
    chance to land after it."""
    mp = multiprocessing.get_context("forkserver")
    mp.set_forkserver_preload(["flowmocap", "flowmocap.pipeline", "torch._dynamo"])
    return mp


def _child(ctx, clip, out, crash=None, known=False):
    p = ctx.Process(target=_run, args=(str(clip), str(out), crash, known))
    p.start()
    return p


@pytest.fixture(scope="module")
def reference(clip, ctx, tmp_path_factory):
    out = tmp_path_factory.mktemp("reference") / "ref"
    t0 = time.perf_counter()
    p = _child(ctx, clip, out)
    p.join(300)
    assert p.exitcode == 0
    motion, run = read_result(out)
    assert run["status"] == "finished" and len(motion["poses"]) == FRAMES
    return motion, time.perf_counter() - t0



@pytest.fixture(scope="module")
def reference_known(clip, ctx, tmp_path_factory):
    """The uninterrupted run from the true first two frames (no initialisation)."""
    out = tmp_path_factory.mktemp("reference_known") / "ref"
    p = _child(ctx, clip, out, known=True)
    p.join(300)
    assert p.exitcode == 0
    return read_result(out)[0]


#: Two uninterrupted runs of the same input are equal to the last bit (the initialisation
#: once ended in one of two states at random: OpenCV's multi-threaded distance transform
#: varied in the last bit, see docs/errors.md, "What is not exact"), so "the same result"
#: is equality within 1e-3 rad / 1 mm / 0.1 px, a hundred times below what a stale resume
#: state caused (0.13 rad, 7.8 cm), with room for float rounding on other machines.
SAME = {"rad": 1e-3, "m": 1e-3, "px": 0.1}


def _assert_same(out: Path, ref: dict, tol: dict = SAME) -> None:
    motion, run = read_result(out)
    assert run["status"] == "finished"
    np.testing.assert_array_equal(motion["frame_index"], ref["frame_index"])
    for k, unit in (("poses", "rad"), ("trans", "m"), ("joints3d", "m"), ("betas", "rad")):
        np.testing.assert_allclose(motion[k], ref[k], rtol=0, atol=tol[unit], err_msg=k)
    np.testing.assert_allclose(motion["joints2d"], ref["joints2d"], rtol=0, atol=tol["px"], err_msg="joints2d")
    assert not list(out.glob("*.tmp")) and not (out / "progress.json").exists()


def test_a_kill_at_any_instant_resumes_exactly(clip, ctx, tmp_path):
    """SIGKILL at 20 random instants of a run (its start, any frame, any file write), each
    resumed to the end: always the uninterrupted run's result."""
    for name in ("ref0", "ref"):  # the second run's time: the first also starts the fork server
        t0 = time.perf_counter()
        p = _child(ctx, clip, tmp_path / name, known=True)
        p.join(300)
        seconds = time.perf_counter() - t0
    ref, ref_run = read_result(tmp_path / "ref")
    # The start-up (reading the clip, building the tracker) can take most of a run this
    # short, so every other kill is drawn over the frames' part only: the last
    # sum(frame_s) seconds, measured by the reference run itself.
    frames_s = min(seconds, float(np.nansum(ref_run["timings"]["frame_s"])))
    rng = random.Random(21)
    killed = []
    for attempt in range(5 * KILL_POINTS):
        if len(killed) == KILL_POINTS:
            break
        out = tmp_path / f"k{attempt}"
        t0 = time.perf_counter()
        p = _child(ctx, clip, out, known=True)
        delay = rng.uniform(0.0 if attempt % 2 else seconds - frames_s, seconds)
        p.join(delay)
        if not p.is_alive():  # finished before its kill point: the machine is quicker now than when
            # the reference was timed (a loaded machine); draw the next instants over this run's time
            took = time.perf_counter() - t0
            frames_s, seconds = frames_s * min(1.0, took / seconds), min(seconds, took)
            continue
        p.kill()
        p.join()
        motion, run = read_result(out) if has_result(out) else ({"poses": []}, {})
        assert len(motion["poses"]) <= FRAMES and run.get("status") in (None, "interrupted", "finished")
        killed.append((round(delay, 2), len(motion["poses"])))
        p = _child(ctx, clip, out, known=True)
        p.join(300)
        assert p.exitcode == 0, f"resume after a kill at {delay:.2f} s failed"
        _assert_same(out, ref)
    print(f"kills (seconds after start, frames committed) in a run of {seconds:.1f} s "
          f"({frames_s:.2f} s of frames):", killed)
    assert len(killed) == KILL_POINTS, f"only {len(killed)} runs were still going at their kill point"
    assert len({n for _, n in killed}) >= 3  # kills landed at different stages of the run


@pytest.mark.parametrize("known", [True, False], ids=["known-start", "with-init"])
@pytest.mark.parametrize("crash", ["before-progress:2", "before-rename:3", "after-rename:3", "before-rename:7"])
def test_a_kill_between_the_files_of_a_commit_resumes_exactly(clip, ctx, reference, reference_known, tmp_path,
                                                               crash, known):
    """The moments a run of the old layout lost its state: after the frame's record is
    appended but before the commit point, and around each rename; from a known start and
    through the initialisation."""
    out = tmp_path / "r"
    p = _child(ctx, clip, out, crash, known=known)
    p.join(300)
    assert p.exitcode == -signal.SIGKILL
    p = _child(ctx, clip, out, known=known)
    p.join(300)
    assert p.exitcode == 0
    _assert_same(out, reference_known if known else reference[0])


def test_only_the_same_setup_is_resumed(clip, reference, tmp_path, toy_files):
    out = tmp_path / "r"
    kw = _kw(clip)
    flowmocap.track(clip, out, frames="0:4", **kw)
    with pytest.raises(InputError, match="already holds a result"):
        flowmocap.track(clip, out, frames="0:4", **kw)
    with pytest.raises(InputError, match="the body model differs"):
        flowmocap.track(clip, out, frames="0:4", resume=True, model=toy_files["npz"], **kw)
    with pytest.raises(InputError, match="the camera differs"):
        flowmocap.track(clip, out, frames="0:4", resume=True, camera=150.0, **kw)
    other = noisy_init(load_sequence(clip).gt, frame=0, seed=3)
    with pytest.raises(InputError, match="the init differs"):
        flowmocap.track(clip, out, frames="0:4", resume=True, **{**kw, "init": other})
    with pytest.raises(InputError, match="the config differs"):
        flowmocap.track(clip, out, frames="0:4", resume=True, **{**kw, "config": {**QUICK, "iterations": 5}})
    # the same set-up: the finished run is returned as it is
    same = flowmocap.track(clip, out, frames="0:4", resume=True, **kw)
    assert len(same) == 4 and same.run["status"] == "finished"
    fp = same.run["fingerprint"]
    assert set(fp) == {"input", "masks", "model", "camera", "init", "config", "options", "detector", "code"}
    # other input of the same length and size: refused too
    changed = tmp_path / "seq2"
    synthesize("builtin:walk", changed, fps=30, frames=FRAMES, size="120x90", betas="random", seed=5, azimuth=60.0,
               flow=False)
    with pytest.raises(InputError, match="cannot resume.*: the input (and|differs)"):
        flowmocap.track(changed, out, frames="0:4", resume=True, **kw)
    # --force starts it over
    again = flowmocap.track(clip, out, frames="0:4", force=True, **{**kw, "config": {**QUICK, "iterations": 5}})
    assert again.run["config"]["iterations"] == 5


def test_stored_detections_and_flows_of_other_input_are_not_reused(clip, tmp_path):
    out = tmp_path / "r"
    flowmocap.track(clip, out, frames="0:3", **_kw(clip))
    source = json.loads((out / "flow_cache" / "source.json").read_text())["input"]
    stale = out / "detections"
    stale.mkdir()
    (stale / "detections.json").write_text(json.dumps({"detector": "mediapipe", "frames": FRAMES, "size": [120, 90]}))
    (stale / "source.json").write_text(json.dumps({"input": "another video"}))
    flowmocap.track(clip, out, frames="0:3", force=True, **_kw(clip))
    assert not stale.exists()  # made from other input: removed, to be computed anew when needed
    assert json.loads((out / "flow_cache" / "source.json").read_text())["input"] == source  # same input: kept


def test_one_run_per_result_folder(clip, ctx, tmp_path):
    out = tmp_path / "r"
    with FolderLock(out):
        assert is_locked(out)
        with pytest.raises(FolderBusyError, match=f"in use by another flowmocap run \\(pid {os.getpid()}"):
            flowmocap.track(clip, out, **_kw(clip))
        assert main(["track", str(clip), "--out", str(out), "--joints3d", "off", "--quiet"]) == 4
    assert not is_locked(out)
    # a lock whose process was killed is no lock
    p = ctx.Process(target=_hold_lock, args=(str(out),))
    p.start()
    deadline = time.time() + 60
    while not (out / ".lock.json").exists() and time.time() < deadline:
        time.sleep(0.05)
    assert is_locked(out)
    p.kill()
    p.join()
    assert not is_locked(out)
    res = flowmocap.track(clip, out, frames="0:3", **_kw(clip))
    assert len(res) == 3 and not (out / ".lock.json").exists()


def _hold_lock(out: str) -> None:
    with FolderLock(out):
        time.sleep(600)


def test_the_result_folder_is_checked_before_any_work(clip, tmp_path, capsys):
    kw = _kw(clip)
    afile = tmp_path / "afile"
    afile.write_text("mine")
    with pytest.raises(InputError, match="is a file"):
        flowmocap.track(clip, afile, **kw)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "run.json").write_text('{"my": "own file"}')
    (mine / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match="holds no flowmocap result.*--force"):
        flowmocap.track(clip, mine, **kw)
    assert (mine / "run.json").read_text() == '{"my": "own file"}'  # untouched
    assert main(["track", str(clip), "--out", str(mine), "--quiet"]) == 2
    assert "flowmocap: error:" in capsys.readouterr().err
    res = flowmocap.track(clip, mine, frames="0:3", force=True, **kw)
    assert len(res) == 3 and (mine / "notes.txt").read_text() == "keep me"
    if sys.platform.startswith("linux"):  # not writable even by root
        with pytest.raises(InputError, match="cannot create the result folder"):
            flowmocap.track(clip, "/proc/flowmocap-out", **kw)


def test_a_folder_holding_only_flowmocap_caches_is_accepted(tmp_path):
    # e.g. benchmarks/track.py runs the detector into the result folder before tracking
    from flowmocap.pipeline import _check_out
    out = tmp_path / "r"
    (out / "detections").mkdir(parents=True)
    (out / "flow_cache").mkdir()
    _check_out(out, force=False)
    (out / "mine.txt").write_text("x")
    with pytest.raises(InputError, match=r"not empty \(mine.txt\)"):
        _check_out(out, force=False)


def test_a_run_killed_while_writing_its_first_file_resumes(clip, ctx, reference_known, tmp_path):
    # SIGKILL inside the first atomic write of run.json leaves only its temporary behind:
    # that folder is flowmocap's, and --resume starts the run (removing the temporary)
    from flowmocap.pipeline import _check_out
    out = tmp_path / "r"
    out.mkdir()
    (out / "run.json.k2x9_abc.tmp").write_text('{"status": "prep')
    _check_out(out, force=False)
    (out / "results.json.k2x9_abc.tmp").write_text("not ours")  # not one of flowmocap's files
    with pytest.raises(InputError, match=r"not empty \(results.json.k2x9_abc.tmp\)"):
        _check_out(out, force=False)
    (out / "results.json.k2x9_abc.tmp").unlink()
    p = _child(ctx, clip, out, known=True)
    p.join(300)
    assert p.exitcode == 0 and not list(out.glob("*.tmp"))
    np.testing.assert_array_equal(read_result(out)[0]["poses"], reference_known["poses"])


def test_results_get_normal_permissions(clip, tmp_path):
    old = os.umask(0o022)
    try:
        out = tmp_path / "r"
        flowmocap.track(clip, out, frames="0:3", **_kw(clip))
    finally:
        os.umask(old)
    for name in ("run.json", "motion.npz", "input.json"):
        assert (out / name).stat().st_mode & 0o777 == 0o644, name


def test_a_failed_write_is_a_clear_error_that_keeps_the_finished_frames(clip, reference, tmp_path, monkeypatch):
    out = tmp_path / "r"
    original = FrameLog.commit
    calls = {"n": 0}

    def full(self, state):
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError(28, "No space left on device", str(self.out_dir / "frames.bin"))
        return original(self, state)

    monkeypatch.setattr(FrameLog, "commit", full)
    with pytest.raises(OutputError, match="No space left on device.*--resume"):
        flowmocap.track(clip, out, **_kw(clip))
    motion, run = read_result(out)
    assert run["status"] == "failed" and "No space left" in run["error"] and len(motion["poses"]) == 3
    monkeypatch.setattr(FrameLog, "commit", original)
    flowmocap.track(clip, out, resume=True, **_kw(clip))
    _assert_same(out, reference[0])


def test_a_full_disk_at_the_first_commit_then_resume_starts_it_over(clip, reference, tmp_path, monkeypatch):
    """frames.bin was written, progress.json was not: the log counted the frames as committed
    all the same, so motion.npz was written of them without a progress.json, and --resume,
    as the error advised, refused ('written by an older flowmocap')."""
    from flowmocap.io import results

    out = tmp_path / "r"
    original = results.write_json

    def full(path, info):
        if Path(path).name == "progress.json":
            raise OSError(27, "File too large", str(path))
        return original(path, info)

    monkeypatch.setattr(results, "write_json", full)
    with pytest.raises(OutputError, match="File too large.*--resume"):
        flowmocap.track(clip, out, **_kw(clip))
    assert json.loads((out / "run.json").read_text())["status"] == "failed"
    assert not (out / "motion.npz").exists()  # no frame was committed
    monkeypatch.setattr(results, "write_json", original)
    flowmocap.track(clip, out, resume=True, **_kw(clip))
    _assert_same(out, reference[0])


def test_a_resume_of_a_finished_run_tidies_what_a_kill_while_it_finished_left(clip, reference, tmp_path):
    """A kill inside the frame log's close (or an atomic write) can leave frames.bin,
    events.jsonl or a result file's temporary beside the finished motion.npz."""
    out = tmp_path / "r"
    flowmocap.track(clip, out, **_kw(clip))
    for name in ("frames.bin", "events.jsonl", "motion.npz.k2j3h4.tmp", "notes.txt"):
        (out / name).write_bytes(b"left")
    flowmocap.track(clip, out, resume=True, **_kw(clip))
    left = {p.name for p in out.iterdir()}
    assert not {"frames.bin", "events.jsonl", "motion.npz.k2j3h4.tmp"} & left and "notes.txt" in left
    _assert_same(out, reference[0])


def test_a_file_size_limit_ends_the_command_with_one_line(clip, tmp_path):
    """``ulimit -f``: writes fail with EFBIG (Python ignores SIGXFSZ); the command ends with
    ``flowmocap: error:`` and exit status 5, not a traceback."""
    import resource
    import subprocess

    init = clip.parent / "init.json"
    quick = tmp_path / "quick.json"
    quick.write_text(json.dumps(QUICK))

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (40_000, 40_000))

    out = tmp_path / "r"
    proc = subprocess.run([sys.executable, "-m", "flowmocap.cli", "track", str(clip), "--out", str(out), "--init",
                           str(init), "--config", str(quick), "--joints3d", "off", "--quiet"],
                          preexec_fn=limit, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 5, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert lines[-1].startswith("flowmocap: error: could not write the result") and "Traceback" not in proc.stderr
    assert json.loads((out / "run.json").read_text())["status"] == "failed"


def test_init_files_are_checked_before_any_work(clip, tmp_path):
    kw = {**_kw(clip)}
    good = json.loads((clip.parent / "init.json").read_text())

    def bad(change: dict, match: str):
        with pytest.raises(InputError, match=match):
            flowmocap.track(clip, tmp_path / "o", **{**kw, "init": {**good, **change}})
        assert not (tmp_path / "o" / "progress.json").exists()

    bunched = {name: [60.0, 45.0] for name in good["joints2d"]}
    bad({"joints2d": bunched}, "joints span only 0.0 px")
    bad({"frame": 9}, "'frame' must be")
    bad({"frame": "0"}, "'frame' must be")
    bad({"pose": {"left_knee": ["a", 0, 0]}}, "wrong kind")
    bad({"pose": [0, 0, 0]}, "'pose' must be an object")
    bad({"confidence": {"left_hip": -1}}, "'confidence' must be numbers in")
    bad({"trans": [0, 0, -3]}, "'trans' must be")
    with pytest.raises(InputError, match="start at 0"):
        flowmocap.track(clip, tmp_path / "o", frames="1:4", **kw)
    # the init's frame is where tracking starts
    later = noisy_init(load_sequence(clip).gt, frame=2, seed=2)
    res = flowmocap.track(clip, tmp_path / "later", **{**kw, "init": later})
    assert res.frame_index.tolist() == list(range(2, FRAMES))


def test_the_reinit_monitor_state_round_trips(tmp_path):
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.fit.reinit import ReinitMonitor

    class Detections:  # every frame a confident detection
        found = [True] * 10

        def __len__(self):
            return 10

        def smpl_joints(self, i):
            return np.zeros((24, 2)), np.ones(24)

    mon = ReinitMonitor(Detections(), TrackerConfig(reinit_patience=3, reinit_3d_patience=2))
    for j, (bad, bad3d) in enumerate([(True, None), (False, True), (True, True), (None, False), (True, True)]):
        mon.verdicts[j], mon.verdicts3d[j] = bad, bad3d
    mon._last_attempt = 2
    state = json.loads(json.dumps(mon.state_dict()))
    assert [v[0] for v in state["verdicts"]] == [2, 3, 4]  # the frames the next decisions look back on
    fresh = ReinitMonitor(Detections(), TrackerConfig(reinit_patience=3, reinit_3d_patience=2))
    fresh.load_state_dict(state)
    assert fresh._last_attempt == 2
    assert all(fresh.verdicts[j] == mon.verdicts[j] and fresh.verdicts3d[j] == mon.verdicts3d[j] for j in (2, 3, 4))
    assert mon._due(5, 2, in3d=True) and not mon._due(5, 3)  # both ways, so the comparison below can fail
    for i in (5, 6):
        assert fresh._due(i, 3) == mon._due(i, 3) and fresh._due(i, 2, in3d=True) == mon._due(i, 2, in3d=True)


@pytest.mark.parametrize("config, match", [
    ({"iterations": -3}, "'iterations' must be an integer >= 1"),
    ({"stages": []}, "'stages' must be a non-empty list"),
    ({"flow_weight": -1.0}, "'flow_weight' must be a number >= 0"),
    ({"silhouette_weight": "5"}, "'silhouette_weight' must be a finite number"),
    ({"no_such_setting": 1}, "unknown config settings"),
    # these passed the checks and failed after tracking (seconds x fps overflowed to infinity),
    # in the first frame (numba's thread pool out of memory) or after detection (the pyramid)
    ({"pose_smoothing_s": 1e308}, "'pose_smoothing_s' must be a number in \\[0, 86400\\]"),
    ({"stance_min_s": 1e308}, "'stance_min_s' must be a number in \\[0, 86400\\]"),
    ({"lifter_refit_bridge_s": 1e308}, "'lifter_refit_bridge_s' must be"),
    ({"torch_threads": 100000}, "'torch_threads' must be an integer in \\[1, 1024\\]"),
    ({"levels": 40, "stages": [[39], [0]]}, "'levels' must be an integer in \\[1, 16\\]"),
])
def test_bad_settings_are_refused_before_any_work(clip, tmp_path, config, match):
    out = tmp_path / "o"
    with pytest.raises(InputError, match=match):
        flowmocap.track(clip, out, **{**_kw(clip), "config": config})
    assert not (out / "run.json").exists() and not (out / "detections").exists()


def test_a_video_is_tracked_from_a_stream_and_its_flows_are_not_kept(clip, tmp_path):
    """A video is decoded as the tracker reads it, and its flows (2.5 MB a frame at 640x480)
    are not stored unless asked for; frame folders keep them for render and resume."""
    from test_video import write_video

    seq = load_sequence(clip)
    video = write_video(tmp_path / "clip.mp4", [seq.frame(i) for i in range(len(seq))])
    kw = {**_kw(clip), "masks": clip / "masks", "camera": seq.camera}
    res = flowmocap.track(video, tmp_path / "v", frames="0:4", **kw)
    assert len(res) == 4 and not list((tmp_path / "v" / "flow_cache").glob("*.npz"))
    kept = flowmocap.track(video, tmp_path / "k", frames="0:4", keep_flow=True, **kw)
    assert len(list((tmp_path / "k" / "flow_cache").glob("flow_*.npz"))) == 3
    np.testing.assert_allclose(kept.poses, res.poses, atol=SAME["rad"])  # the same flows, kept or not
    folder = flowmocap.track(clip, tmp_path / "f", frames="0:4", **_kw(clip))
    assert len(list((tmp_path / "f" / "flow_cache").glob("flow_*.npz"))) == 3 and len(folder) == 4


def test_the_observed_flow_is_computed_around_the_person_only(clip, tmp_path):
    """With ``flow_region`` (and E_f on mask pixels, ``flow_in_mask``) the tracker computes
    each frame's flow in the box of its and the previous frame's masks, 0 outside; by
    default (off), over the whole frame."""
    from flowmocap.vision import FlowCache, flow_region, observed_flow

    seq = load_sequence(clip)
    flowmocap.track(clip, tmp_path / "r", frames="0:4", **{**_kw(clip), "config": {**QUICK, "flow_region": True}})
    cache = FlowCache(tmp_path / "r" / "flow_cache", method=TrackerConfig().flow_method)
    for i in (1, 2, 3):
        region = flow_region([seq.mask(i), seq.mask(i - 1)])
        r0, r1, c0, c1 = region
        assert (r1 - r0) * (c1 - c0) < 0.9 * 120 * 90  # a part of the frame
        f = cache.get(i, region=region)
        assert f is not None and cache.get(i) is None  # stored for that region
        np.testing.assert_array_equal(f[r0:r1, c0:c1], observed_flow(
            np.ascontiguousarray(seq.frame(i)[r0:r1, c0:c1]), np.ascontiguousarray(seq.frame(i - 1)[r0:r1, c0:c1]),
            TrackerConfig().flow_method))
        outside = np.ones(f.shape[:2], bool)
        outside[r0:r1, c0:c1] = False
        assert not f[outside].any()
    flowmocap.track(clip, tmp_path / "w", frames="0:4", **_kw(clip))
    whole = FlowCache(tmp_path / "w" / "flow_cache", method=TrackerConfig().flow_method)
    for i in (1, 2, 3):
        np.testing.assert_array_equal(whole.get(i, region=None), observed_flow(seq.frame(i), seq.frame(i - 1),
                                                                               TrackerConfig().flow_method))


def test_a_run_that_fails_before_its_first_frame_is_marked_failed(clip, tmp_path, monkeypatch):
    import flowmocap.pipeline as pipeline
    from flowmocap.errors import NoPersonError

    out = tmp_path / "r"
    with pytest.raises(InputError, match="'frame' must be"):
        flowmocap.track(clip, out, **{**_kw(clip), "init": {**json.loads((clip.parent / "init.json").read_text()),
                                                             "frame": 99}})
    assert not (out / "run.json").exists()  # refused before anything was written

    def no_person(*args, **kwargs):
        raise NoPersonError("no person in any frame (test)")

    monkeypatch.setattr(pipeline, "detect_joints3d", no_person)  # fails after the folder is claimed
    monkeypatch.setattr(pipeline, "detect_for_given_masks", no_person)  # (the detector_keypoints path)
    with pytest.raises(NoPersonError):
        flowmocap.track(clip, out, **{**_kw(clip), "joints3d": "auto"})
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "failed" and "no person in any frame" in run["error"]
    with pytest.raises(DataError, match="holds no tracked frames yet.*failed"):
        flowmocap.load_result(out)
    monkeypatch.undo()
    assert len(flowmocap.track(clip, out, frames="0:3", **_kw(clip))) == 3  # and it can simply be run again
