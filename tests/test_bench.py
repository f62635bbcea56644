"""`flowmocap bench` end to end on a really tiny clip, the DAVIS skip, and the table."""

from __future__ import annotations

import json

import pytest

from flowmocap.cli import main
from flowmocap.errors import InputError
from flowmocap.eval import bench


FAST = ["--num-frames", "4", "--size", "160x120", "--quiet", "--no-isolate", "--baseline-iterations", "8"]


def test_bench_quick_on_a_tiny_clip_writes_table_and_json(tmp_path, capsys):
    out = tmp_path / "b"
    cfg = tmp_path / "fast.json"
    cfg.write_text(json.dumps({"init_iterations": 20, "init_flow_iterations": 8, "iterations": 8}))
    rc = main(["bench", "--suite", "quick", "--out", str(out), "--config", str(cfg), *FAST])
    assert rc == 0
    data = json.loads((out / "bench.json").read_text())
    assert data["suite"] == "quick" and data["commit"]
    assert data["settings"]["tracker"]["iterations"] == 8 and data["settings"]["baseline"]["iterations"] == 8
    entry = data["sequences"]["walk-quick"]
    assert entry["settings"]["frames"] == 4 and entry["settings"]["size"] == "160x120"
    for method in ("flowmocap", "baseline"):
        row = entry[method]
        for k in ("local_cm", "global_cm", "mpjpe_cm", "accel_mm", "px2d", "s_per_frame"):
            assert row[k] is not None and row[k] >= 0, (method, k)
        assert row["local_cm"] < 30 and row["frames"] == 4
    md = (out / "bench.md").read_text()
    assert "| flowmocap |" in md and "| baseline |" in md and data["commit"] in md
    assert "| flowmocap |" in capsys.readouterr().out
    # re-running resumes: nothing is recomputed
    main(["bench", "--suite", "quick", "--out", str(out), "--config", str(cfg), *FAST])
    assert "not recomputed" in capsys.readouterr().out


def test_davis_entry_is_skipped_without_its_frames(tmp_path):
    spec = bench.RealSpec("davis-dance-twirl", str(tmp_path / "frames"), str(tmp_path / "masks"))
    res = bench.run_bench([spec], tmp_path / "o", "full", log=lambda *a: None)
    entry = res["sequences"]["davis-dance-twirl"]
    assert "not found" in entry["skipped"]
    assert "skipped:" in (tmp_path / "o" / "bench.md").read_text()


def test_suites_and_errors(tmp_path):
    full = bench.suite("full")
    assert [s.azimuth for s in full if isinstance(s, bench.SyntheticSpec)] == [90.0, 45.0]
    assert all(s.frames == 130 and s.size == "640x480" and s.fps == 60.0
               for s in full if isinstance(s, bench.SyntheticSpec))
    with pytest.raises(InputError):
        bench.suite("huge")
    with pytest.raises(InputError, match="does not exist"):
        bench.mocap_specs([str(tmp_path / "missing.bvh")])
    assert bench.commit()


def test_table_shows_null_metrics_as_dashes():
    result = {"suite": "quick", "commit": "abc", "sequences": {"x": {
        "settings": {"motion": "builtin:walk", "frames": 3, "size": "8x8", "fps": 30, "azimuth": 0, "seed": 0},
        "flowmocap": {k: 1.0 for k in bench.METRICS} | {"iou": None}, "baseline": None}}}
    md = bench.format_table(result)
    assert "| flowmocap | 1.0 | 1.0 | 1.0 | 1.0 | 1.0 | -- | 1.00 |" in md
    assert "| baseline | -- |" in md


def test_peak_memory_is_measured():
    mb, how = bench.peak_rss_mb()
    assert 10 < mb < 1e6 and how
