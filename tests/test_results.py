"""Result folders (flowmocap.io.results): atomic writes with a normal file's mode."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from flowmocap.io.results import read_result, write_motion, write_run


@pytest.mark.parametrize("umask", [0o022, 0o002])
def test_result_files_get_the_users_normal_permissions(tmp_path, umask):
    old = os.umask(umask)
    try:
        write_motion(tmp_path, {"poses": np.zeros((2, 72))})
        write_run(tmp_path, {"frames": 2})
    finally:
        os.umask(old)
    for name in ("motion.npz", "run.json"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o666 & ~umask, name
    motion, run = read_result(tmp_path)
    assert motion["poses"].shape == (2, 72) and run == {"frames": 2}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["motion.npz", "run.json"]  # no temporary left
