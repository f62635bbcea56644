"""Many inputs in one command (flowmocap.batch, ``flowmocap track a b c --out DIR``): one
result folder per input, the same results one by one, in worker processes and as Ray tasks,
finished inputs skipped, interrupted ones resumed, a bad input reported without stopping the
others."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import sys
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import flowmocap
from flowmocap.batch import BATCH_FAILED, MANIFEST, expand_inputs, is_batch, plan, track_many
from flowmocap.cli import main
from flowmocap.errors import InputError
from flowmocap.eval.protocol import noisy_init
from flowmocap.io.sequence import load_sequence
from flowmocap.synth import synthesize

QUICK = {"iterations": 4, "init_iterations": 6, "init_flow_iterations": 4}
NAMES = ("walk_a", "walk_b", "walk_c")


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    """Three 4-frame 160x120 sequence folders (other bodies, other phases of the walk), one
    init.json near all three first frames, and the quick settings."""
    d = tmp_path_factory.mktemp("batch")
    for k, name in enumerate(NAMES):
        synthesize("builtin:walk", d / name, fps=30, start=k, frames=4, size="160x120", betas="random", seed=k + 1,
                   azimuth=60.0, flow=False)
    (d / "init.json").write_text(json.dumps(noisy_init(load_sequence(d / NAMES[0]).gt, frame=0, seed=1)))
    (d / "quick.json").write_text(json.dumps(QUICK))
    return d


def _args(clips, out, *more):
    return ["track", *(str(clips / n) for n in NAMES), "--out", str(out), "--init", str(clips / "init.json"),
            "--config", str(clips / "quick.json"), "--joints3d", "off", "--quiet", *more]


def _same(a: flowmocap.Result, b: flowmocap.Result, what: str):
    for k in ("poses", "trans", "betas", "joints3d", "joints2d", "frame_index"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=f"{what}: {k}")


@pytest.fixture(scope="module")
def one_by_one(clips, tmp_path_factory):
    """The three clips tracked one after the other (the reference)."""
    out = tmp_path_factory.mktemp("serial") / "results"
    assert main(_args(clips, out)) == 0
    return out


def _check_same_as(reference, out, what):
    for name in NAMES:
        res = flowmocap.load_result(out / name)
        assert res.run["status"] == "finished" and len(res) == 4
        _same(flowmocap.load_result(reference / name), res, f"{what} {name}")
    manifest = json.loads((out / MANIFEST).read_text())["results"]
    assert sorted(manifest) == sorted(NAMES) and all(manifest[n]["status"] == "tracked" for n in NAMES)


def test_batch_one_by_one_writes_a_folder_per_input_and_a_summary(clips, one_by_one, capsys):
    for name in NAMES:
        assert flowmocap.load_result(one_by_one / name).run["status"] == "finished"
    # the three clips differ, so equal results across modes below mean each went to its own folder
    assert not np.array_equal(flowmocap.load_result(one_by_one / NAMES[0]).poses,
                              flowmocap.load_result(one_by_one / NAMES[1]).poses)
    # run again: everything finished is skipped, nothing is tracked
    assert main(_args(clips, one_by_one)) == 0
    out = capsys.readouterr().out
    assert "3 finished before (skipped)" in out and "0 tracked" in out
    table = [line.split() for line in out.splitlines() if line.startswith(str(clips))]
    assert [row[1:3] for row in table] == [[n, "skipped"] for n in NAMES]


def _workers_of_this_process() -> list[int]:
    """Process ids of this process's spawned multiprocessing workers (not its resource tracker)."""
    pids = []
    for task in Path(f"/proc/{os.getpid()}/task").iterdir():
        for pid in (task / "children").read_text().split():
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes() if Path(f"/proc/{pid}").exists() else b""
            if b"spawn_main" in cmd:
                pids.append(int(pid))
    return pids


def test_worker_processes_give_the_same_results_even_when_one_dies(clips, one_by_one, tmp_path, capsys):
    out = tmp_path / "workers"
    stop, killed, seen = threading.Event(), [], {"workers": 0, "errors": []}

    def kill_a_worker():  # once the first input has committed 2 frames: as the out-of-memory killer would
        while not stop.is_set():
            try:
                workers = _workers_of_this_process()
                seen["workers"] = max(seen["workers"], len(workers))
                if workers and len(flowmocap.load_result(out / NAMES[0])) >= 2:
                    os.kill(workers[0], signal.SIGKILL)
                    killed.append(workers[0])
                    return
            except (flowmocap.FlowMocapError, OSError):  # nothing committed yet; a process just ended
                pass
            except Exception as e:  # noqa: BLE001  (kept for the failure message, not swallowed)
                seen["errors"].append(repr(e))
            stop.wait(0.005)

    linux = Path(f"/proc/{os.getpid()}/task").is_dir()  # where the workers can be found
    watcher = threading.Thread(target=kill_a_worker if linux else stop.wait, daemon=True)
    watcher.start()
    try:
        assert main(_args(clips, out, "--workers", "2")) == 0
    finally:
        stop.set()
        watcher.join()
    text = capsys.readouterr().out
    assert "in 2 worker processes" in text
    if linux:
        assert killed, f"no worker was killed: at most {seen['workers']} seen at once; watcher errors {seen['errors']}"
        assert "a worker process died while tracking" in text and "once more (resuming)" in text, text
    _check_same_as(one_by_one, out, "--workers 2")


class _PoolThatDiesBetweenWaits:
    """Stands in for ProcessPoolExecutor. The first pool runs its first input forever and
    finishes the second at once; the process of the first then dies, so the next submit
    finds the pool broken, as a worker killed between two waits leaves it. Later pools
    finish every input at once."""

    made: list = []

    def __init__(self, max_workers, mp_context):
        from concurrent.futures import Future
        self.first, self.futures, self.Future = not self.made, [], Future
        self.made.append(self)

    def submit(self, fn, item, kwargs, threads):
        from concurrent.futures.process import BrokenProcessPool
        if self.first and len(self.futures) == 2:
            self.futures[0].set_exception(BrokenProcessPool("a child process terminated abruptly"))
            raise BrokenProcessPool("a child process terminated abruptly")
        fut = self.Future()
        if not (self.first and not self.futures):
            fut.set_result(replace(item, status="tracked", frames=4, new_frames=4))
        self.futures.append(fut)
        return fut

    def shutdown(self, wait=True, cancel_futures=False):
        pass


def test_a_pool_that_died_between_two_waits_loses_no_input(tmp_path, monkeypatch):
    # the race the kill test above meets now and then: a submit raised BrokenProcessPool and the batch failed
    from flowmocap import batch
    monkeypatch.setattr(batch, "ProcessPoolExecutor", _PoolThatDiesBetweenWaits)
    monkeypatch.setattr(_PoolThatDiesBetweenWaits, "made", [])
    items = [batch.BatchItem(input=n, name=n, out=tmp_path / n, status="new") for n in ("a", "b", "c")]
    reported, said = [], []
    batch._run_processes(items, {}, 2, reported.append, said.append)
    assert sorted((it.name, it.status) for it in reported) == [("a", "tracked"), ("b", "tracked"), ("c", "tracked")]
    assert len(_PoolThatDiesBetweenWaits.made) == 2
    assert said == ["a worker process died while tracking a; trying a once more (resuming)"], said


def test_ray_tasks_give_the_same_results(clips, one_by_one, tmp_path, capsys):
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install 'flowmocap[cluster]')")
    ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING")  # local, on loopback only
    try:
        out = tmp_path / "ray"
        assert main(_args(clips, out, "--ray")) == 0
        assert ray.is_initialized()  # the command used this instance and left it running
    finally:
        ray.shutdown()
    assert "as Ray tasks" in capsys.readouterr().out
    _check_same_as(one_by_one, out, "--ray")


def test_without_ray_the_ray_option_says_how_to_install_it(clips, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    assert main(_args(clips, tmp_path / "o", "--ray")) == 2
    err = capsys.readouterr().err
    assert err.startswith("flowmocap: error:") and "pip install 'flowmocap[cluster]'" in err
    assert not (tmp_path / "o").exists()  # said before anything was written


def test_a_ray_address_where_nothing_answers_is_a_clear_error(clips, tmp_path, capsys):
    pytest.importorskip("ray", reason="Ray is not installed (pip install 'flowmocap[cluster]')")
    with socket.socket() as s:  # a port on loopback that nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    assert main(_args(clips, tmp_path / "o", f"--ray=127.0.0.1:{port}")) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"flowmocap: error: no Ray cluster answers at 127.0.0.1:{port}") and "ray start" in err
    assert not (tmp_path / "o").exists()


def test_a_single_input_keeps_its_out_folder(clips, one_by_one, tmp_path, capsys):
    out = tmp_path / "single"
    args = _args(clips, out, "--workers", "2")
    args[1:4] = [str(clips / NAMES[0])]
    assert main(args) == 0
    assert "one input: tracking it in this process" in capsys.readouterr().out
    _same(flowmocap.load_result(one_by_one / NAMES[0]), flowmocap.load_result(out), "single input")
    assert not (out / MANIFEST).exists() and not (out / NAMES[0]).exists()


def _interrupt_at_frame_call(monkeypatch, n: int) -> None:
    """Ctrl-C (KeyboardInterrupt) on the ``n``-th tracked frame after the
    initialisation, in this process: deterministic, whatever the machine's speed."""
    import flowmocap.fit.tracker as tracker

    original = tracker.track_frame
    calls = {"n": 0}

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == n:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(tracker, "track_frame", interrupted)


def test_finished_skipped_interrupted_resumed_and_a_bad_input_stops_nothing(clips, one_by_one, tmp_path, capsys,
                                                                           monkeypatch):
    out = tmp_path / "results"
    shutil.copytree(one_by_one, out)  # all three finished before, batch.json knows their names
    shutil.rmtree(out / NAMES[1])
    kw = {"init": clips / "init.json", "config": QUICK, "joints3d": "off", "progress": False, "log": None}
    _interrupt_at_frame_call(monkeypatch, 2)  # after the initialisation's 2 frames and one more, before the 4th
    with pytest.raises(KeyboardInterrupt):
        track_many([clips / NAMES[1]], out, **kw)
    monkeypatch.undo()
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"\x00" * 1000)
    inputs = [bad, clips / NAMES[0], clips / NAMES[1]]
    planned = plan(inputs, out)
    assert [it.status for it in planned] == ["new", "finished", "resume"]
    assert 2 <= planned[2].frames < 4 and planned[2].name == NAMES[1]

    code = main(["track", *map(str, inputs), "--out", str(out), "--init", str(clips / "init.json"),
                 "--config", str(clips / "quick.json"), "--joints3d", "off", "--quiet"])
    text = capsys.readouterr().out
    assert code == BATCH_FAILED  # the bad one failed first; the others went on
    assert "1 resumed, 1 finished before (skipped), 1 failed" in text and f"failed: {bad}:" in text
    resumed = flowmocap.load_result(out / NAMES[1])
    assert resumed.run["status"] == "finished"
    _same(flowmocap.load_result(one_by_one / NAMES[1]), resumed, "interrupted, then resumed")
    manifest = json.loads((out / MANIFEST).read_text())["results"]
    assert manifest[NAMES[1]]["status"] == "resumed" and manifest[NAMES[1]]["new_frames"] == 4 - planned[2].frames
    assert manifest["broken"]["status"] == "failed" and manifest["broken"]["error"]

    anew = track_many([clips / NAMES[0]], out, force=True, **kw)  # force: a finished one too is tracked again
    assert anew[0].status == "tracked" and anew[0].new_frames == 4
    _same(flowmocap.load_result(one_by_one / NAMES[0]), flowmocap.load_result(out / NAMES[0]), "forced")


def test_names_are_stable_and_never_collide(tmp_path):
    for d in ("a", "b"):
        (tmp_path / d).mkdir()
        (tmp_path / d / "walk.mp4").write_bytes(b"")
    (tmp_path / "a" / "Walk.mov").write_bytes(b"")
    (tmp_path / "a" / "run.mp4").write_bytes(b"")
    a, b = tmp_path / "a" / "walk.mp4", tmp_path / "b" / "walk.mp4"
    out = tmp_path / "out"
    alone = plan([a], out)[0].name
    assert alone == "walk"
    names = [it.name for it in plan([tmp_path / "a" / "Walk.mov", b, a, tmp_path / "a" / "run.mp4"], out)]
    assert names[2] == "walk" and names[3] == "run"  # a keeps the name it was given first
    assert names[0].startswith("Walk-") and names[1].startswith("walk-")  # Walk/walk: one folder on macOS
    assert len({n.lower() for n in names}) == 4
    assert [it.name for it in plan([b], out)] == [names[1]]  # b keeps its name without the others
    assert [it.name for it in plan([tmp_path / "c" / "new.mp4"] * 2, out)] == ["new"]  # twice: once


def test_inputs_from_folders_and_list_files(tmp_path):
    videos = tmp_path / "videos"
    videos.mkdir()
    for n in ("b.mp4", "a.MOV", "c.MTS", "notes.txt"):  # .MTS: a camcorder's (a folder of them held "no videos")
        (videos / n).write_bytes(b"")
    seq = videos / "seq"
    (seq / "frames").mkdir(parents=True)
    (tmp_path / "lists").mkdir()
    listed = tmp_path / "lists" / "list.txt"
    listed.write_text("# my clips\n\n../videos/b.mp4\n/elsewhere/c.mp4\n")
    assert is_batch([videos]) and is_batch(["@x.txt"]) and is_batch(["a.mp4", "b.mp4"])
    assert is_batch(["a.mp4"], list_files=[listed])
    assert not is_batch([seq]) and not is_batch([videos / "b.mp4"])  # one input: --out is its result folder
    assert expand_inputs([videos]) == [videos / "a.MOV", videos / "b.mp4", videos / "c.MTS", seq]
    got = expand_inputs([f"@{listed}", videos / "b.mp4"], list_files=[listed])
    assert got == [tmp_path / "lists" / ".." / "videos" / "b.mp4", Path("/elsewhere/c.mp4")]  # each once
    with pytest.raises(InputError, match="list file"):
        expand_inputs(["@" + str(tmp_path / "missing.txt")])
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="holds no videos"):
        expand_inputs([tmp_path / "a.mp4", tmp_path / "empty"])
    with pytest.raises(InputError, match="workers"):
        track_many([videos / "b.mp4"], tmp_path / "o", workers=0)


def test_batch_export_writes_every_finished_result(clips, one_by_one, tmp_path, capsys):
    import shutil

    out = tmp_path / "copy"
    shutil.copytree(one_by_one, out)
    assert main(_args(clips, out, "--export", "json")) == 0  # all finished: nothing tracked, all exported
    assert "3 finished before (skipped)" in capsys.readouterr().out
    for name in NAMES:
        doc = json.loads((out / name / "export" / "motion.json").read_text())
        assert len(doc["frames"]) == 4


def test_a_batch_export_that_fails_for_one_result_exports_the_others_and_says_so(clips, one_by_one, tmp_path,
                                                                                  capsys, monkeypatch):
    import shutil

    import flowmocap.export as export

    out = tmp_path / "copy"
    shutil.copytree(one_by_one, out)
    real = export.export_result

    def failing(result, fmt, **kw):
        if Path(result).name == NAMES[1]:
            raise flowmocap.errors.DataError(f"{result} cannot be exported (a test)")
        return real(result, fmt, **kw)

    monkeypatch.setattr(export, "export_result", failing)
    assert main(_args(clips, out, "--export", "trc")) == BATCH_FAILED
    assert f"export of {out / NAMES[1]} failed: " in capsys.readouterr().err
    assert [(out / n / "export" / "motion.trc").exists() for n in NAMES] == [True, False, True]


def test_a_second_batch_into_the_same_folder_waits_its_turn_and_says_so(clips, one_by_one, tmp_path, capsys):
    """Two batches into one --out both ran, both rewrote batch.json, and one reported an input
    the other had tracked as 'tracked, 4 new'. The batch folder is now held by one batch at a
    time; an input finished by another run after the plan is reported skipped."""
    from flowmocap.batch import BatchItem, _track_one
    from flowmocap.errors import FolderBusyError
    from flowmocap.io.lock import FolderLock

    out = tmp_path / "results"
    shutil.copytree(one_by_one, out)
    with FolderLock(out):  # another batch is running here
        with pytest.raises(FolderBusyError, match="in use by another flowmocap run"):
            track_many([clips / n for n in NAMES], out, log=None, progress=False)
        assert main(_args(clips, out)) == 4
    assert "in use by another flowmocap run" in capsys.readouterr().err
    planned_new = BatchItem(input=str(clips / NAMES[0]), name=NAMES[0], out=out / NAMES[0], status="new")
    res = _track_one(planned_new, {"init": str(clips / "init.json"), "config": str(clips / "quick.json"),
                                   "joints3d": "off"}, log=None)
    assert (res.status, res.frames, res.new_frames) == ("skipped", 4, 0)


def test_one_input_into_a_batch_folder_is_told_its_own_folder(clips, one_by_one, tmp_path):
    """It was told to pass --force, which put a single result into the batch's folder and
    stopped every later batch there; --force does not do that now either."""
    import flowmocap

    for force in (False, True):
        with pytest.raises(InputError, match=rf"holds a batch of results .*this input's result is "
                                             rf"{one_by_one / NAMES[1]}: give --out"):
            flowmocap.track(clips / NAMES[1], one_by_one, force=force, log=None, progress=False)
    with pytest.raises(InputError, match="holds a batch of results .*give several inputs"):
        flowmocap.track(clips / "init.json", one_by_one, log=None, progress=False)
    assert not (one_by_one / "motion.npz").exists() and not (one_by_one / "run.json").exists()
