"""Result folders (flowmocap.io.results): atomic writes with a normal file's mode."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from flowmocap.atomic import atomic_write
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
