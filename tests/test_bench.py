"""`flowmocap bench` end to end on a really tiny clip, the DAVIS skip, and the table."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from flowmocap.cli import main
from flowmocap.errors import DataError, InputError
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
    assert "detector3d" in entry  # None where MediaPipe sees no one in the tiny render
    md = (out / "bench.md").read_text()
    assert "| flowmocap |" in md and "| baseline |" in md and data["commit"] in md
    assert "| flowmocap |" in capsys.readouterr().out
    assert not list(out.rglob("flow_*.npz"))  # a suite keeps no observed flows (2.5 MB a frame)
    # re-running resumes: nothing is recomputed
    main(["bench", "--suite", "quick", "--out", str(out), "--config", str(cfg), *FAST])
    assert "not recomputed" in capsys.readouterr().out


def test_bench_as_a_video_tracks_the_renders_with_automatic_masks_joints_and_start(tmp_path, capsys):
    out = tmp_path / "v"
    cfg = tmp_path / "fast.json"
    cfg.write_text(json.dumps({"init_iterations": 20, "init_flow_iterations": 8, "iterations": 8}))
    tiny = ["--num-frames", "4", "--size", "320x240", "--quiet", "--no-isolate", "--baseline-iterations", "8"]
    assert main(["bench", "--suite", "quick", "--as-video", "--out", str(out), "--config", str(cfg), *tiny]) == 0
    data = json.loads((out / "bench.json").read_text())
    assert data["settings"]["as_video"] is True and data["settings"]["protocol"] == bench.AS_VIDEO
    assert data["settings"]["tracker"]["silhouette_model"] == "mesh"  # the video profile's settings recorded
    run = json.loads((out / "walk-quick" / "flowmocap" / "run.json").read_text())
    assert run["profile"] == "video" and run["masks"] == "automatic" and run["init"] == "automatic"
    assert "camera.json" in run["camera_source"]
    # the rendered camera is turned (world y up): the automatic start must stand upright in the image
    from scipy.spatial.transform import Rotation

    R = np.asarray(run["camera"]["R"])
    start = json.loads((out / "walk-quick" / "flowmocap" / "init_auto.json").read_text())
    G = Rotation.from_rotvec(start["pose"]["pelvis"]).as_matrix()
    assert not np.allclose(R, np.eye(3)) and (R @ G @ [0.0, 1.0, 0.0])[1] < -0.9
    row = data["sequences"]["walk-quick"]["flowmocap"]
    assert row["frames"] == 4 and row["local_cm"] < 30
    assert "tracked as a video" in (out / "bench.md").read_text()
    # benchmarks/auto_start.py repeats the start on the stored detections and scores it
    from test_check_scripts import _load

    auto_start = _load("auto_start")
    assert auto_start.main([str(out), "--out", str(tmp_path / "start")]) == 0
    starts = json.loads((tmp_path / "start.json").read_text())
    errors = starts["clips"]["walk-quick"]
    assert set(errors) == set(auto_start.DEFAULT_VARIANTS) and all(0 < e < 30 for e in errors.values())
    assert "| walk-quick |" in (tmp_path / "start.md").read_text()
    # benchmarks/post_steps.py redoes the steps after tracking on the finished run: with the run's own
    # settings it gives the stored result back
    post_steps = _load("post_steps")
    variants = {"as run": {}, "no refit": {"lifter_refit_weight": 0.0, "pose_smoothing_s": 0.0}}
    assert post_steps.main(["--variants", json.dumps(variants), "--diverse", str(out),
                            "--out", str(tmp_path / "post")]) == 0
    post = json.loads((tmp_path / "post.json").read_text())
    rows = post["suites"][f"diverse {out}"]
    assert rows["as run"][0]["name"] == "walk-quick"
    assert rows["as run"][0]["local_cm"] == pytest.approx(row["local_cm"], abs=1e-3)
    assert rows["no refit"][0]["local_cm"] != pytest.approx(row["local_cm"], abs=1e-3)
    # a folder of the other kind is refused before anything runs: its finished results would be reused
    with pytest.raises(InputError, match="as a video"):
        bench.run_bench(bench.suite("quick", frames=4, size="320x240"), out, "quick", isolate=False,
                        log=lambda *a: None)
    proto = tmp_path / "p"
    proto.mkdir()
    (proto / "bench.json").write_text(json.dumps({"settings": {"protocol": "synthetic"}}))
    with pytest.raises(InputError, match="by the protocol"):
        bench.run_bench([], proto, "quick", as_video=True, log=lambda *a: None)
    capsys.readouterr()
    assert main(["bench", "--suite", "real3d", "--as-video", "--out", str(tmp_path / "r")]) != 0
    assert "real3d is tracked as a video already" in capsys.readouterr().err


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
    (tmp_path / "garbage.bvh").write_text("garbage\n")  # read before any work: no empty --out left behind
    with pytest.raises(DataError, match="starts with HIERARCHY"):
        bench.mocap_specs([str(tmp_path / "garbage.bvh")])
    assert bench.commit()


def test_the_shared_data_folder_is_given_with_data_or_flowmocap_data(tmp_path, capsys, monkeypatch):
    # an installed package looked for the data beside site-packages, with no way to point it elsewhere
    data = tmp_path / "data"
    (data / "mocap" / "prior").mkdir(parents=True)
    full = bench.suite("full", data=data)
    assert full[0].motion == str(data / "mocap" / "cmu" / "35_01.amc")
    assert full[2].frames_dir == str(data / "video" / "davis-dance-twirl" / "JPEGImages")
    with pytest.raises(DataError, match=r"needs .*index.csv.*give bench --data DIR"):
        bench.suite("diverse", data=data)
    monkeypatch.setenv("FLOWMOCAP_DATA", str(data))
    assert bench.shared_data() == data
    monkeypatch.delenv("FLOWMOCAP_DATA")
    assert bench.shared_data() == bench.ROOT.parent / "shared" / "data"
    # the command: a missing --data folder is refused; a suite whose data is not there leaves no empty --out
    assert main(["bench", "--suite", "diverse", "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert main(["bench", "--suite", "real3d", "--data", str(data), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "give bench --data DIR" in capsys.readouterr().err and not (tmp_path / "o").exists()
    assert main(["bench", "--suite", "diverse", "--data", str(data), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert not (tmp_path / "o").exists()


def test_the_commit_is_read_only_from_a_source_checkout(tmp_path, monkeypatch):
    # an install inside another git project recorded that project's commit in bench.json
    import subprocess

    if (bench.ROOT / ".git").exists():
        assert bench.commit() != "unknown"  # this checkout
    other = tmp_path / "project"
    (other / "lib").mkdir(parents=True)
    subprocess.run(["git", "init", "-q", str(other)], check=True)
    subprocess.run(["git", "-C", str(other), "-c", "user.email=a@b", "-c", "user.name=a", "commit", "-q",
                    "--allow-empty", "-m", "x"], check=True)
    monkeypatch.setattr(bench, "ROOT", other / "lib")
    assert bench.commit() == "unknown"


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


needs_prior_data = pytest.mark.skipif(not (bench.PRIOR_DATA / "index.csv").exists(),
                                      reason=f"the diverse suite's clips are not here ({bench.PRIOR_DATA})")


@needs_prior_data
def test_diverse_suite_is_held_out_varied_and_seeded():
    import csv

    specs = bench.suite("diverse")
    with (bench.PRIOR_DATA / "index.csv").open(newline="") as f:
        rows = {r["file"]: r for r in csv.DictReader(f)}
    assert len(specs) >= 16 and len({s.kind for s in specs}) >= 6
    for s in specs:
        rel = Path(s.motion).relative_to(bench.PRIOR_DATA).as_posix()
        assert rows[rel]["split"] == "test" and int(rows[rel]["subject"]) in (2, 8, 13, 61)
        assert 0.0 <= s.azimuth < 360.0 and s.fps == 60.0 and s.frames == 100 and s.size == "640x480"
        # the window lies inside the clip (at 60 fps: twice its 30 fps frames, less one)
        assert s.start == 0 or s.start + s.frames <= 2 * int(rows[rel]["frames"]) - 1
    assert len({s.azimuth for s in specs}) == len(specs) and len({s.seed for s in specs}) == len(specs)
    assert [s.name for s in bench.suite("diverse")] == [s.name for s in specs]  # deterministic


@needs_prior_data
def test_tune_suite_uses_train_clips_only_two_of_each_kind():
    import csv

    specs = bench.suite("tune")
    with (bench.PRIOR_DATA / "index.csv").open(newline="") as f:
        rows = {r["file"]: r for r in csv.DictReader(f)}
    assert len(specs) == 2 * len(bench.TUNE_CATEGORIES)
    for s in specs:
        rel = Path(s.motion).relative_to(bench.PRIOR_DATA).as_posix()
        assert rows[rel]["split"] == "train" and int(rows[rel]["subject"]) not in (2, 8, 13, 61)
        assert rows[rel]["category"] == s.kind and s.seed >= 100
        assert 0.0 <= s.azimuth < 360.0 and s.fps == 60.0 and s.frames == 100 and s.size == "640x480"
    assert {s.kind for s in specs} == set(bench.TUNE_CATEGORIES)
    assert all(sum(s.kind == k for s in specs) == 2 for k in bench.TUNE_CATEGORIES)
    assert len({s.motion for s in specs}) == len(specs) and len({s.seed for s in specs}) == len(specs)
    assert not {s.seed for s in specs} & {s.seed for s in bench.suite("diverse")}
    assert [s.name for s in bench.suite("tune")] == [s.name for s in specs]  # deterministic


@needs_prior_data
def test_most_active_window_finds_the_motion(tmp_path):
    from flowmocap.io.mocap import read_mocap, write_bvh

    clip = read_mocap(bench.PRIOR_DATA / "cmu_mb" / "02_01.bvh")
    # freeze every joint (root excluded) outside frames 40..59: the most active window is there
    rot = clip.rotations.copy()
    rot[:40, 1:] = rot[40, 1:]
    rot[60:, 1:] = rot[59, 1:]
    still = replace(clip, rotations=rot)
    path = tmp_path / "still.bvh"
    write_bvh(still, path)
    start = bench.most_active_window(path, 20, 30.0)
    assert 38 <= start <= 42
    assert bench.most_active_window(path, 10_000, 30.0) == 0


def test_summary_gives_medians_kinds_and_ratios():
    def row(local, glob):
        return {"local_cm": local, "global_cm": glob, "px2d": 1.0, "accel_mm": 2.0}

    seqs = {f"c{i}": {"settings": {"kind": "walk" if i < 2 else "jump"},
                      "flowmocap": row(2.0 + i, 3.0 + i), "baseline": row(8.0, 10.0 + 2 * i),
                      "detector3d": {"local_cm": 4.0 + i, "global_cm": None, "px2d": None, "accel_mm": None}}
            for i in range(3)}
    s = bench.summarise({"sequences": seqs})
    assert s["sequences"] == 3
    assert s["median"]["flowmocap"]["local_cm"] == 3.0 and s["mean"]["baseline"]["global_cm"] == 12.0
    assert s["ratios"]["global_vs_baseline"] == pytest.approx(4.0 / 12.0)
    assert s["ratios"]["local_vs_detector3d"] == pytest.approx(3.0 / 5.0)
    assert s["per_kind"]["walk"]["clips"] == 2 and s["per_kind"]["walk"]["flowmocap_local_cm"] == 2.5
    assert s["median"]["detector3d"]["global_cm"] is None
    md = "\n".join(bench.format_summary(s))
    assert "| walk | 2 | 2.5 |" in md and "0.33" in md
    assert s["median_interval"] == {"local_cm": None, "global_cm": None}  # three clips: too few for an interval
    assert "intervals" not in md
    assert bench.summarise({"sequences": {"c0": seqs["c0"]}}) == {}


def test_median_interval_over_the_clips():
    assert bench.median_interval([5.0] * 8) == [5.0, 5.0]  # every draw has the same median
    assert bench.median_interval([1.0, 2.0, 3.0, 4.0]) is None
    rng = np.random.default_rng(0)
    v = rng.normal(5.0, 1.0, 16)
    low, high = bench.median_interval(v)
    assert low < np.median(v) < high and v.min() <= low and high <= v.max()
    assert bench.median_interval(list(v)) == [low, high]  # the same seed: the same interval
    # a wider spread of clips gives a wider interval, in proportion (the draws are the same)
    low2, high2 = bench.median_interval(5.0 + 3 * (v - 5.0))
    assert (high2 - low2) == pytest.approx(3 * (high - low))
    assert bench.median_interval([*v, None, float("nan")]) == [low, high]  # unscored clips left out
    seqs = {f"c{i}": {"settings": {"kind": "walk"}, "flowmocap": {"local_cm": float(x), "global_cm": 2 * float(x),
                                                                   "px2d": 1.0, "accel_mm": 1.0}}
            for i, x in enumerate(v)}
    s = bench.summarise({"sequences": seqs})
    assert s["median_interval"]["local_cm"] == pytest.approx([low, high])
    md = "\n".join(bench.format_summary(s))
    assert f"local {np.median(v):.2f} [{low:.2f}, {high:.2f}] cm" in md


def test_detector_joints3d_maps_keypoints_and_puts_the_head_between_the_ears():
    import numpy as np

    from flowmocap.body.skeleton import JOINT_INDEX
    from flowmocap.eval.scoring import detector_joints3d
    from flowmocap.vision.auto import PersonTrack
    from flowmocap.vision.detect import KEYPOINT_NAMES

    T, K = 2, len(KEYPOINT_NAMES)
    world = np.random.default_rng(0).normal(size=(T, K, 3))
    conf = np.ones((T, K))
    conf[0, KEYPOINT_NAMES.index("left_knee")] = 0.1  # unsure: left out
    track = PersonTrack(np.zeros((T, K, 2)), conf, np.array([True, False]), [], {}, world)
    j = detector_joints3d(track)
    assert j.shape == (T, 24, 3)
    assert np.allclose(j[0, JOINT_INDEX["right_wrist"]], world[0, KEYPOINT_NAMES.index("right_wrist")])
    ears = world[0, [KEYPOINT_NAMES.index("left_ear"), KEYPOINT_NAMES.index("right_ear")]].mean(0)
    assert np.allclose(j[0, JOINT_INDEX["head"]], ears)
    assert np.isnan(j[0, JOINT_INDEX["left_knee"]]).all() and np.isnan(j[0, JOINT_INDEX["pelvis"]]).all()
    assert np.isnan(j[1]).all()  # frame without the person
