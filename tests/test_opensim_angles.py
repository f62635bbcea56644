"""benchmarks/opensim_angles.py: the file handling around OpenSim (OpenSim itself is not
needed here: the benchmark runs it in an environment of its own)."""

from pathlib import Path

import numpy as np
import pytest

from flowmocap.export.markers import write_trc

from conftest import load_script

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "opensim_angles.py"


@pytest.fixture(scope="module")
def oa():
    return load_script(SCRIPT)


def test_scaling_reads_only_the_frames_with_every_marker(oa, tmp_path):
    pts = np.random.default_rng(0).normal(size=(6, 3, 3))
    pts[1, 0] = np.nan  # a frame missing a marker
    pts[:, 2] = np.nan  # a marker never seen: not one of the source's markers
    trc = write_trc(tmp_path / "m.trc", pts, ["a", "b", "c"], 60.0, missing_ok=True)
    assert oa._trc_markers(trc) == {"a", "b"}
    kept = oa._complete_rows(trc, tmp_path / "scale.trc").read_text().splitlines()
    assert kept[2].split("\t")[2] == "5" and kept[2].split("\t")[7] == "5"  # NumFrames, OrigNumFrames
    rows = np.genfromtxt(kept[6:], delimiter="\t")
    assert rows[:, 0].tolist() == [1, 3, 4, 5, 6]  # frame 2 (1-based) left out
    np.testing.assert_allclose(rows[:, 2:5], pts[[0, 2, 3, 4, 5], 0], atol=1e-6)
    pts[1:, 0] = np.nan  # a only in the first frame,
    pts[0, 1] = np.nan  # b only in the others: never together
    with pytest.raises(RuntimeError, match="no frame has all its markers"):
        oa._complete_rows(write_trc(tmp_path / "n.trc", pts, ["a", "b", "c"], 60.0, missing_ok=True),
                          tmp_path / "scale2.trc")


def test_an_opensim_storage_file_is_read_by_column(oa, tmp_path):
    sto = tmp_path / "ik.mot"
    sto.write_text("Coordinates\nversion=1\nnRows=2\nnColumns=3\ninDegrees=yes\nendheader\n"
                   "time\tknee_angle_r\tknee_angle_l\n0.0\t10.5\t-3\n0.016667\t11\t-2.5\n")
    cols = oa.read_sto(sto)
    assert list(cols) == ["time", "knee_angle_r", "knee_angle_l"]
    np.testing.assert_allclose(cols["knee_angle_r"], [10.5, 11.0])
    assert oa._wrapped(np.array([350.0, -190.0, 10.0])).tolist() == [-10.0, 170.0, 10.0]
