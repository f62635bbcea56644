"""Result folders (flowmocap.io.results): atomic writes with a normal file's mode."""

from __future__ import annotations

import json
import os
import stat

import numpy as np
import pytest

from flowmocap.atomic import atomic_write
from flowmocap.errors import DataError
from flowmocap.io.results import read_result, write_motion, write_run
from flowmocap.vision import FlowCache


@pytest.mark.parametrize("umask", [0o022, 0o002])
def test_result_files_get_the_users_normal_permissions(tmp_path, umask):
    old = os.umask(umask)
    try:
        write_motion(tmp_path, {"poses": np.zeros((2, 72))})
        write_run(tmp_path, {"frames": 2})
        cached = FlowCache(tmp_path / "flow_cache", method="dis").put(1, np.zeros((4, 5, 2)))
    finally:
        os.umask(old)
    for path in (tmp_path / "motion.npz", tmp_path / "run.json", cached):
        assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~umask, path.name
    motion, run = read_result(tmp_path)
    assert motion["poses"].shape == (2, 72) and run == {"frames": 2}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flow_cache", "motion.npz", "run.json"]  # no temporary left


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "f.txt"
    target.write_text("old")

    def fail(tmp):
        open(tmp, "w").write("half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(target, fail)
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["f.txt"]


def _finished_result(folder):
    """A minimal finished result folder: motion.npz of 2 frames and run.json."""
    write_motion(folder, {"poses": np.zeros((2, 72)), "trans": np.zeros((2, 3)), "betas": np.zeros(10)})
    write_run(folder, {"flowmocap": "test", "status": "finished"})
    return folder


@pytest.mark.parametrize("damage", ["cut in half", "empty"])
def test_a_truncated_or_empty_motion_npz_is_a_data_error_that_says_to_track_again(tmp_path, damage):
    """A motion.npz cut short (BadZipFile) or of 0 bytes (EOFError) is the project's
    DataError naming the folder and saying to track again with --force, not a traceback."""
    path = _finished_result(tmp_path) / "motion.npz"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2] if damage == "cut in half" else b"")
    with pytest.raises(DataError, match=r"unreadable result.*--force") as e:
        read_result(tmp_path)
    assert str(tmp_path) in str(e.value)


@pytest.mark.parametrize("text", ["[]", '"text"', "3"])
def test_a_run_json_that_is_not_an_object_is_a_data_error_that_says_to_track_again(tmp_path, text):
    """run.json holding valid JSON that is not an object (a list, a string, a number) is a
    DataError naming run.json and saying to track again with --force."""
    _finished_result(tmp_path)
    (tmp_path / "run.json").write_text(text)
    with pytest.raises(DataError, match=r"run\.json holds a JSON .*--force"):
        read_result(tmp_path)


def test_a_progress_header_that_is_not_an_object_is_a_data_error(tmp_path):
    """progress.json whose 'header' is not an object (here a list) is a DataError naming
    progress.json, both for readers (read_result) and for --resume (FrameLog.reopen)."""
    from flowmocap.io.results import FrameLog

    write_run(tmp_path, {"flowmocap": "test", "status": "running"})
    (tmp_path / "progress.json").write_text(json.dumps({"rows": 0, "events_bytes": 0, "state": {}, "header": []}))
    with pytest.raises(DataError, match=r"progress\.json is unreadable.*--force"):
        read_result(tmp_path)
    with pytest.raises(DataError, match=r"progress\.json is unreadable"):
        FrameLog.reopen(tmp_path)


def test_export_of_a_damaged_result_exits_2_with_one_line(tmp_path, capsys):
    """The command line turns a truncated motion.npz into exit 2 and a one-line message."""
    from flowmocap.cli import main

    path = _finished_result(tmp_path / "res") / "motion.npz"
    path.write_bytes(path.read_bytes()[:100])
    assert main(["export", str(tmp_path / "res"), "-f", "json", "-o", str(tmp_path / "m.json")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "--force" in err and len(err.strip().splitlines()) == 1


def test_the_umask_is_read_without_being_changed(tmp_path):
    # os.umask(0); os.umask(old) from two threads at once could leave the process's umask at 0 for good
    import os
    import threading

    from flowmocap.atomic import atomic_write, current_umask

    old = os.umask(0o027)
    try:
        seen = []
        threads = [threading.Thread(target=lambda: seen.extend(current_umask() for _ in range(200))) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert set(seen) == {0o027} and os.umask(0o027) == 0o027
        atomic_write(tmp_path / "f.txt", lambda tmp: open(tmp, "w").write("x"))
        assert (os.stat(tmp_path / "f.txt").st_mode & 0o777) == 0o640
    finally:
        os.umask(old)
