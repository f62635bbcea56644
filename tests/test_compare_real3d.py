"""benchmarks/compare_real3d.py: the per-person-view comparison of two real3d runs."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import load_script

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "compare_real3d.py"


@pytest.fixture(scope="module")
def cr():
    return load_script(SCRIPT)


def _run(per_frame, per_seq, detector=None, skip=()):
    out = []
    for i, (f, s) in enumerate(zip(per_frame, per_seq)):
        person, view = f"person{1 + i // 4}", f"cam0{1 + i % 4}"
        if i in skip:
            out.append({"person": person, "view": view, "skipped_run": "not detected"})
            continue
        row = {"person": person, "view": view, "frames_scored": 50,
               "flowmocap": {"per_frame_mm": f, "per_sequence_mm": s}}
        if detector is not None:
            row["detector3d"] = {"per_frame_mm": detector[i], "per_sequence_mm": detector[i] + 10}
        out.append(row)
    return {"rows": out}


def test_rows_pair_person_views_scored_in_both(cr):
    a = _run([100.0] * 8, [130.0] * 8, skip={3})
    b = _run([90.0] * 8, [120.0] * 8, detector=[95.0] * 8, skip={5})
    t = cr.rows(a, b)
    assert [r["name"] for r in t] == ["person1@cam01", "person1@cam02", "person1@cam03", "person2@cam01",
                                      "person2@cam03", "person2@cam04"]
    assert t[0]["a_per_frame_mm"] == 100.0 and t[0]["b_per_sequence_mm"] == 120.0
    assert t[0]["detector_per_frame_mm"] == 95.0 and t[0]["detector_per_sequence_mm"] == 105.0


def test_paired_counts_moves_beyond_chance_only(cr):
    a = [100.0] * 8
    b = [100.0, 85.0, 111.0, 95.0, 100.0, 120.0, 89.9, 100.0]  # better: -15, -10.1; worse: +11, +20
    t = cr.rows(_run(a, a), _run(b, a, detector=[1.0] * 8))
    p = cr.paired(t, chance_mm=10)
    assert (p["per_frame_mm"]["better"], p["per_frame_mm"]["worse"]) == (2, 2)
    assert p["per_frame_mm"]["largest_move_mm"] == pytest.approx(20.0)
    assert p["per_frame_mm"]["median_difference_mm"] == pytest.approx(np.median(np.subtract(b, a)))
    assert p["per_sequence_mm"]["better"] == p["per_sequence_mm"]["worse"] == 0
    assert p["per_sequence_mm"]["wilcoxon_p"] is None  # no differences at all
    # a consistent shift over all 8 views is what the signed-rank test picks up
    q = cr.paired(cr.rows(_run(a, a), _run(np.subtract(a, np.arange(12, 20)), a)), chance_mm=10)
    assert q["per_frame_mm"]["better"] == 8 and q["per_frame_mm"]["wilcoxon_p"] < 0.01


def test_summary_gives_the_issue_targets(cr):
    det = [100.0, 50.0, 80.0, 60.0, 100.0, 50.0, 80.0, 60.0]
    a = [90.0, 60.0, 70.0, 60.0, 90.0, 60.0, 70.0, 60.0]  # worse than the detector on views 1 and 5
    s = cr.summary(cr.rows(_run(a, a), _run(a, a, detector=det)))
    assert s["a_ratio"] == pytest.approx(np.mean(a) / np.mean(det))
    assert s["a_worse_than_detector"] == 2 and s["person_views"] == 8


def test_command_line_writes_json(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps(_run([100.0] * 8, [130.0] * 8, detector=[98.0] * 8)))
    b.write_text(json.dumps(_run([101.0] * 8, [128.0] * 8, detector=[98.0] * 8)))
    out = tmp_path / "c.json"
    r = subprocess.run([sys.executable, str(SCRIPT), str(a), str(b), "--names", "x,y", "--json", str(out)],
                       capture_output=True, text=True, check=True)
    assert "y against x, per-frame: better on 0, worse on 0 of 8" in r.stdout
    data = json.loads(out.read_text())
    assert data["summary"]["b_ratio"] == pytest.approx(101 / 98) and len(data["rows"]) == 8
