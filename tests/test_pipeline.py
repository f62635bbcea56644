"""The public API (flowmocap.track, flowmocap.load_result): the one pipeline the command
line runs too, its Result, and its errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

import flowmocap
from flowmocap.cli import main
from flowmocap.errors import DataError, InputError, NoPersonError
from flowmocap.eval.protocol import noisy_init
from flowmocap.io.sequence import load_sequence
from flowmocap.pipeline import parse_frame_range
from flowmocap.synth import synthesize

from conftest import SHARED_DATA

QUICK = {"iterations": 4, "init_iterations": 6, "init_flow_iterations": 4}


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("pipe") / "seq"
    synthesize("builtin:walk", d, fps=30, frames=5, size="200x150", betas="random", seed=1, azimuth=60.0,
               flow=False)
    (d.parent / "init.json").write_text(json.dumps(noisy_init(load_sequence(d).gt, frame=0, seed=1)))
    (d.parent / "quick.json").write_text(json.dumps(QUICK))
    return d


def _same(a: flowmocap.Result, b: flowmocap.Result):
    for k in ("poses", "trans", "betas", "joints3d", "joints2d", "frame_index"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)


def test_python_api_gives_what_the_command_line_gives(seq_dir, tmp_path, capsys):
    init = seq_dir.parent / "init.json"
    res = flowmocap.track(seq_dir, tmp_path / "api", init=init, config=QUICK, progress=False, joints3d="off")
    assert "profile 'synthetic'" in capsys.readouterr().out  # printed: the input brings its own masks
    assert main(["track", str(seq_dir), "--out", str(tmp_path / "cli"), "--init", str(init), "--config",
                 str(seq_dir.parent / "quick.json"), "--joints3d", "off", "--quiet"]) == 0
    cli = flowmocap.load_result(tmp_path / "cli")
    _same(res, cli)
    assert len(res) == 5 and res.poses.shape == (5, 72) and res.trans.shape == (5, 3)
    assert res.joints3d.shape == (5, 24, 3) and res.joints2d.shape == (5, 24, 2) and res.betas.shape == (10,)
    assert res.run["status"] == "finished" and res.run["profile"] == "synthetic"
    assert res.run["config"]["iterations"] == 4 and res.fps == pytest.approx(30.0)
    assert res.camera.width == 200 and set(res.energies) >= {"total", "flow", "silhouette"}
    assert res.path == tmp_path / "api" and "status 'finished'" in repr(res)
    # a finished result is not overwritten without resume; resuming a finished one changes nothing
    with pytest.raises(InputError, match="already holds a result"):
        flowmocap.track(seq_dir, tmp_path / "api", init=init, config=QUICK, progress=False, joints3d="off")
    again = flowmocap.track(seq_dir, tmp_path / "api", init=init, config=QUICK, progress=False, joints3d="off",
                            resume=True, log=None)
    _same(res, again)


def test_the_finished_motion_has_its_root_depth_smoothed_and_keeps_the_tracked_translation(seq_dir, tmp_path):
    """motion.npz is the tracked frames with the root's distance from the camera smoothed
    (fit.smooth.depth_smoothed_motion, depth_smoothing_s 0.5 by default) and the
    tracker's own translation kept as trans_tracked; depth_smoothing_s 0 gives the
    tracker's frames; poses are the same."""
    from flowmocap.fit.smooth import depth_smoothed_motion

    kw = dict(init=seq_dir.parent / "init.json", progress=False, joints3d="off", log=None)
    quick = {**QUICK, "pose_smoothing_s": 0.0}  # the depth alone (the pose smoothing: the next test)
    smoothed = flowmocap.track(seq_dir, tmp_path / "s", config=quick, **kw)
    raw = flowmocap.track(seq_dir, tmp_path / "r", config={**quick, "depth_smoothing_s": 0.0}, **kw)
    assert smoothed.run["config"]["depth_smoothing_s"] == 0.5 and "trans_tracked" not in raw.motion
    assert raw.run["config"]["depth_smoothing_s"] == 0.0
    np.testing.assert_array_equal(smoothed.poses, raw.poses)
    np.testing.assert_array_equal(smoothed.motion["trans_tracked"], raw.trans)
    want = depth_smoothed_motion(dict(raw.motion), 0.5)
    for k in ("trans", "joints3d", "joints2d"):
        np.testing.assert_allclose(getattr(smoothed, k), want[k], atol=1e-5, err_msg=k)
    assert np.abs(smoothed.trans - raw.trans).max() > 1e-4  # 5 noisy frames: the depth moved


def test_the_finished_motion_is_smoothed_last_and_keeps_the_motion_before(seq_dir, tmp_path):
    """With pose_smoothing_s (0.3 s by default) motion.npz is the motion of a run without it
    passed through fit.smooth.pose_smoothed_motion; run.json records it."""
    from flowmocap.body import load_body_model
    from flowmocap.fit.smooth import pose_smoothed_motion

    kw = dict(init=seq_dir.parent / "init.json", progress=False, joints3d="off", log=None)
    smoothed = flowmocap.track(seq_dir, tmp_path / "s", config=QUICK, **kw)
    raw = flowmocap.track(seq_dir, tmp_path / "r", config={**QUICK, "pose_smoothing_s": 0.0}, **kw)
    assert smoothed.run["config"]["pose_smoothing_s"] == 0.3 and "pose_smoothing" not in raw.run
    assert "poses_unsmoothed" not in raw.motion and smoothed.run["pose_smoothing"]["window_s"] == 0.3
    np.testing.assert_array_equal(smoothed.motion["poses_unsmoothed"], raw.poses)
    want, _ = pose_smoothed_motion(dict(raw.motion), load_body_model("default"), 0.3)
    for k in ("poses", "trans", "joints3d", "joints2d"):
        np.testing.assert_allclose(getattr(smoothed, k), want[k], atol=1e-4, err_msg=k)
    assert np.abs(smoothed.poses - raw.poses).max() > 1e-4


def test_a_run_stopped_before_its_smoothing_is_smoothed_on_resume(seq_dir, tmp_path):
    """A kill between the end of tracking (motion.npz written, status finished) and the
    steps after it: --resume does the steps instead of calling the run finished."""
    from flowmocap.io.results import read_result, write_motion, write_run

    kw = dict(init=seq_dir.parent / "init.json", progress=False, joints3d="off", log=None)
    done = flowmocap.track(seq_dir, tmp_path / "r", config=QUICK, **kw)
    motion, run = read_result(tmp_path / "r")
    before = {k: v for k, v in motion.items() if k not in ("poses_unsmoothed", "trans_unsmoothed")}
    before["poses"], before["trans"] = motion["poses_unsmoothed"], motion["trans_unsmoothed"]
    write_motion(tmp_path / "r", before)  # joints3d stay the smoothed ones: only the poses are compared
    write_run(tmp_path / "r", {k: v for k, v in run.items() if k != "pose_smoothing"})
    again = flowmocap.track(seq_dir, tmp_path / "r", config=QUICK, resume=True, **kw)
    np.testing.assert_allclose(again.poses, done.poses, atol=1e-6)
    np.testing.assert_allclose(again.trans, done.trans, atol=1e-6)
    assert "pose_smoothing" in again.run
    third = flowmocap.track(seq_dir, tmp_path / "r", config=QUICK, resume=True, **kw)  # now nothing to do
    np.testing.assert_array_equal(third.poses, again.poses)


def test_profile_can_be_chosen_and_is_recorded(seq_dir, tmp_path):
    res = flowmocap.track(seq_dir, tmp_path / "r", init=seq_dir.parent / "init.json", config=QUICK,
                          frames="0:3", profile="video", progress=False, joints3d="off", log=None)
    assert res.run["profile"] == "video" and res.run["config"]["silhouette_model"] == "mesh"
    assert res.frame_index.tolist() == [0, 1, 2]


def test_the_detector_named_brings_its_network_settings_under_the_config(seq_dir, tmp_path):
    from flowmocap.fit.config import FAST_SETTINGS, NETWORK_SETTINGS, TrackerConfig

    defaults = TrackerConfig()
    assert all(getattr(defaults, k) == v for k, v in NETWORK_SETTINGS["heavy"].items())  # heavy: the default
    assert set(NETWORK_SETTINGS["full"]) == set(NETWORK_SETTINGS["heavy"])
    assert all(FAST_SETTINGS[k] == v for k, v in NETWORK_SETTINGS["full"].items())  # --fast runs full
    kw = dict(init=seq_dir.parent / "init.json", frames="0:3", progress=False, joints3d="off", log=None)
    full = flowmocap.track(seq_dir, tmp_path / "full", config=QUICK, detector="full", **kw).run["config"]
    assert full["detector_model"] == "full" and all(full[k] == v for k, v in NETWORK_SETTINGS["full"].items())
    heavy_fast = flowmocap.track(seq_dir, tmp_path / "hf", config=QUICK, detector="heavy", fast=True, **kw).run["config"]
    assert heavy_fast["detector_model"] == "heavy" and heavy_fast["rel_tolerance"] == FAST_SETTINGS["rel_tolerance"]
    assert all(heavy_fast[k] == v for k, v in NETWORK_SETTINGS["heavy"].items())
    mine = flowmocap.track(seq_dir, tmp_path / "mine", config={**QUICK, "keypoint_confidence_floor": 0.3},
                           detector="full", **kw).run["config"]
    assert mine["keypoint_confidence_floor"] == 0.3  # the config file still decides


def test_fast_layers_its_settings_under_the_config_and_is_part_of_the_fingerprint(seq_dir, tmp_path, capsys):
    from flowmocap.fit.config import FAST_SETTINGS, TrackerConfig

    init = seq_dir.parent / "init.json"
    kw = dict(init=init, frames="0:3", progress=False, joints3d="off")
    res = flowmocap.track(seq_dir, tmp_path / "fast", config=QUICK, fast=True, **kw)
    assert "fast" in capsys.readouterr().out
    assert FAST_SETTINGS and all(res.run["config"][k] == v for k, v in FAST_SETTINGS.items())
    defaults = TrackerConfig()
    assert all(getattr(defaults, k) != v for k, v in FAST_SETTINGS.items())  # --fast changes something
    assert res.run["config"]["iterations"] == 4  # the config still applies
    mine = flowmocap.track(seq_dir, tmp_path / "mine", config={**QUICK, "rel_tolerance": 5e-4}, fast=True, **kw)
    assert mine.run["config"]["rel_tolerance"] == 5e-4  # and overrides fast's
    with pytest.raises(InputError, match="set-up"):  # a resume must use the same settings
        flowmocap.track(seq_dir, tmp_path / "fast", config=QUICK, resume=True, **kw)
    assert main(["track", str(seq_dir), "--out", str(tmp_path / "cli"), "--init", str(init), "--config",
                 str(seq_dir.parent / "quick.json"), "--joints3d", "off", "--frames", "0:3", "--fast", "--quiet"]) == 0
    _same(res, flowmocap.load_result(tmp_path / "cli"))


def test_bad_input_gives_the_projects_errors(seq_dir, tmp_path):
    init = seq_dir.parent / "init.json"
    kw = dict(init=init, progress=False, joints3d="off", log=None)
    with pytest.raises(DataError, match="does not exist"):
        flowmocap.track(tmp_path / "missing.mp4", tmp_path / "o1", **kw)
    with pytest.raises(InputError, match="unknown profile"):
        flowmocap.track(seq_dir, tmp_path / "o2", profile="cinema", **kw)
    with pytest.raises(InputError, match="focal length"):
        flowmocap.track(seq_dir, tmp_path / "o3", camera=-5.0, **kw)
    with pytest.raises(InputError, match="camera must be"):
        flowmocap.track(seq_dir, tmp_path / "o4", camera=[1, 2], **kw)
    with pytest.raises(InputError, match="iterations"):
        flowmocap.track(seq_dir, tmp_path / "o5", config={"iterations": "ten"}, **kw)
    with pytest.raises(InputError, match="removed"):
        flowmocap.track(seq_dir, tmp_path / "o6", config={"optimizer": "lm"}, **kw)
    with pytest.raises(InputError, match="joints3d"):
        flowmocap.track(seq_dir, tmp_path / "o7", init=init, joints3d="maybe", progress=False)
    with pytest.raises(DataError, match="not a flowmocap result"):
        flowmocap.load_result(tmp_path)


def test_a_wrongly_typed_config_file_is_a_clear_cli_error(seq_dir, tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"iterations": "ten"}))
    code = main(["track", str(seq_dir), "--out", str(tmp_path / "o"), "--init", str(seq_dir.parent / "init.json"),
                 "--config", str(bad), "--joints3d", "off", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("flowmocap: error:") and "iterations" in err and "Traceback" not in err


def test_frame_ranges():
    assert parse_frame_range(None, 10) == (0, 10)
    assert parse_frame_range("2:", 10) == (2, 10) and parse_frame_range(":5", 10) == (0, 5)
    assert parse_frame_range((3, 6), 10) == (3, 6)
    assert parse_frame_range(" 1 : 4 ", 10) == (1, 4)
    for bad in ("5:4", "0:1", "a:b", "0:11", (1,), "x"):
        with pytest.raises(InputError):
            parse_frame_range(bad, 10)
    with pytest.raises(InputError, match=r"A:B, frames A to B - 1 .*2: from frame 2 to the end"):
        parse_frame_range("2", 10)  # was read as 2: (frame 2 to the end), where 2 frames may be meant
    with pytest.raises(InputError, match=r"0 <= A < B <= 10"):
        parse_frame_range("0:100", 10)


DAVIS = SHARED_DATA / "video" / "davis-dance-twirl" / "JPEGImages"


@pytest.mark.skipif(not DAVIS.is_dir(), reason=f"{DAVIS} not found: the shared data folder is absent")
def test_a_real_clip_from_python_matches_the_command_line(tmp_path):
    """Automatic everything on the first frames of DAVIS dance-twirl (frames copied into a
    small folder so the detector runs on 4 frames only)."""
    import shutil

    frames = tmp_path / "frames"
    frames.mkdir()
    for p in sorted(DAVIS.glob("*.jpg"))[:4]:
        shutil.copy(p, frames / p.name)
    cfg = tmp_path / "quick.json"
    cfg.write_text(json.dumps({**QUICK, "reinit_iterations": 4}))
    res = flowmocap.track(frames, tmp_path / "api", config=cfg, progress=False, log=None)
    assert main(["track", str(frames), "--out", str(tmp_path / "cli"), "--config", str(cfg), "--quiet"]) == 0
    _same(res, flowmocap.load_result(tmp_path / "cli"))
    assert res.run["profile"] == "video" and res.run["init"] == "automatic" and res.run["masks"] == "automatic"


def _frame_folder(folder, n=4, size=(32, 24)):
    """A plain folder of ``n`` small frames."""
    import cv2

    folder.mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i:06d}.png"), np.full((size[1], size[0], 3), 20 * i, np.uint8))
    return folder


@pytest.mark.parametrize("name, content, match", [
    ("gt.npz", b"", r"gt.npz is unreadable \(EOFError"),
    ("gt.npz", b"PK\x03\x04 half of an archive", r"gt.npz is unreadable \(BadZipFile"),
    ("meta.json", b"{not json", r"meta.json is not valid JSON"),
    ("meta.json", b"[1, 2]", r"meta.json must hold a JSON object but holds a list"),
])
def test_a_damaged_gt_npz_or_meta_json_is_a_data_error(tmp_path, name, content, match):
    """A truncated, empty or garbage gt.npz, or a meta.json that is not a JSON object, is
    a DataError naming the file and saying to regenerate or remove it (was a traceback in
    track and eval)."""
    seq = tmp_path / "seq"
    _frame_folder(seq / "frames")
    (seq / name).write_bytes(content)
    with pytest.raises(DataError, match=match) as e:
        load_sequence(seq)
    assert str(seq / name) in str(e.value) and "regenerate it" in str(e.value) and "remove it" in str(e.value)


def test_every_frame_and_mask_of_a_folder_is_checked_before_any_work(tmp_path):
    """A mask or frame of another size, or not an image, late in a folder is refused when
    the folder is opened, naming it, instead of when tracking reaches it."""
    import cv2

    frames = _frame_folder(tmp_path / "frames")
    masks = _frame_folder(tmp_path / "masks")
    assert len(load_sequence(frames, masks=masks)) == 4
    cv2.imwrite(str(masks / "000003.png"), np.zeros((12, 16), np.uint8))
    with pytest.raises(DataError, match=r"masks/000003.png is 16x12 but the sequence's frames are 32x24"):
        load_sequence(frames, masks=masks)
    (masks / "000003.png").write_text("not an image")
    with pytest.raises(DataError, match=r"cannot read image .*masks/000003.png"):
        load_sequence(frames, masks=masks)
    cv2.imwrite(str(frames / "000002.png"), np.zeros((30, 40, 3), np.uint8))
    with pytest.raises(DataError, match=r"frames/000002.png is 40x30 but the sequence's frames are 32x24"):
        load_sequence(frames)


def test_masks_that_are_all_empty_are_refused_before_tracking(seq_dir, tmp_path):
    """User masks with no person pixel in any of them give NoPersonError before any work
    (they used to give a 'finished' result, exit 0, with an 'empty mask' event a frame)."""
    from flowmocap.errors import NoPersonError

    black = _frame_folder(tmp_path / "black", n=5, size=(200, 150))
    for p in black.iterdir():
        p.write_bytes((black / "000000.png").read_bytes())  # all black
    with pytest.raises(NoPersonError, match=r"every mask in .*black is empty: masks must be non-zero on the person"):
        flowmocap.track(seq_dir, tmp_path / "o", init=seq_dir.parent / "init.json", masks=black, config=QUICK,
                        progress=False, joints3d="off", log=None)
    assert not (tmp_path / "o" / "motion.npz").exists()


def test_run_json_records_the_input_as_an_absolute_path(seq_dir, tmp_path, monkeypatch):
    """A relative input is recorded resolved, so render and view started from another
    folder find it."""
    monkeypatch.chdir(seq_dir.parent)
    res = flowmocap.track(seq_dir.name, tmp_path / "r", init=seq_dir.parent / "init.json", config=QUICK,
                          frames="0:2", progress=False, joints3d="off", log=None)
    assert res.run["input"] == str(seq_dir.resolve())
    assert json.loads((tmp_path / "r" / "run.json").read_text())["input"] == str(seq_dir.resolve())


def test_a_camera_no_pinhole_lens_could_be_is_refused_before_any_work(seq_dir, tmp_path):
    kw = dict(init=seq_dir.parent / "init.json", progress=False, joints3d="off", log=None)
    # fx = 1e-9 px: a field of view of 180 degrees; before, tracking failed with "a capsule is
    # not in front of the camera" and no word on the camera
    with pytest.raises(InputError, match=r"field of view of 180 degrees across .*not mm"):
        flowmocap.track(seq_dir, tmp_path / "o1", camera=1e-9, **kw)
    cam = json.loads((seq_dir / "camera.json").read_text())
    cam["fy"] = 1e7  # 0.00086 degrees down the image
    (tmp_path / "tele.json").write_text(json.dumps(cam))
    with pytest.raises(InputError, match=r"tele\.json\) has a field of view of 0.000\d+ degrees down"):
        flowmocap.track(seq_dir, tmp_path / "o2", camera=tmp_path / "tele.json", **kw)
    assert not (tmp_path / "o1").exists()  # nothing tracked, nothing written: the folder made for it is gone too


def test_a_videos_focal_length_no_lens_could_have_is_set_aside_and_said():
    from flowmocap import pipeline
    from flowmocap.io.video import DEFAULT_FOCAL_FACTOR

    class _Seq:
        size = (640, 360)
        camera = None
        meta = {"focal_35mm": 0.01}  # 0.01 mm: a tag written wrong

    cam, note = pipeline._camera(None, _Seq(), None)
    assert cam.fx == pytest.approx(DEFAULT_FOCAL_FACTOR * 640)
    assert "0.01 mm is not a real lens's, ignored" in note
    _Seq.meta = {"focal_35mm": 26.0}  # a phone's: kept
    cam, note = pipeline._camera(None, _Seq(), None)
    assert cam.fx == pytest.approx(26.0 / 36.0 * 640)


def test_track_export_writes_the_formats_after_tracking_and_refuses_unknown_ones_first(seq_dir, tmp_path, capsys):
    args = ["track", str(seq_dir), "--init", str(seq_dir.parent / "init.json"), "--config",
            str(seq_dir.parent / "quick.json"), "--joints3d", "off", "--quiet"]
    assert main([*args, "--out", str(tmp_path / "bad"), "--export", "bvh,fbx"]) == 2
    assert "--export takes export formats" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()  # refused before the result folder was made
    assert main([*args, "--out", str(tmp_path / "bad"), "--export", "bvh", "--export-markers", "halpe26"]) == 2
    assert "--export-markers halpe26 sets the markers of the trc and c3d exports" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    out = tmp_path / "o"
    assert main([*args, "--out", str(out), "--export", "trc, bvh,trc", "--export-markers", "halpe26"]) == 0
    said = capsys.readouterr().out
    assert sorted(p.name for p in (out / "export").iterdir()) == ["motion.bvh", "motion.trc"]
    assert said.count("wrote ") == 2
    from flowmocap.export import export_result

    assert "\tRHip\t" in (out / "export" / "motion.trc").read_text()  # the marker set reached the trc
    direct = np.loadtxt(export_result(out, "trc", tmp_path / "direct.trc", markers="halpe26"), skiprows=6)
    np.testing.assert_allclose(np.loadtxt(out / "export" / "motion.trc", skiprows=6), direct, atol=2e-6)
    assert "-0.000000" not in (out / "export" / "motion.trc").read_text()


def test_force_starts_over_without_the_old_results_exports(seq_dir, tmp_path):
    """--force started the result over but left export/motion.bvh, render/ and eval.json
    made from the old input beside it; what a user keeps in export/ stays."""
    args = ["track", str(seq_dir), "--init", str(seq_dir.parent / "init.json"), "--config",
            str(seq_dir.parent / "quick.json"), "--joints3d", "off", "--quiet", "--out", str(tmp_path / "o")]
    out = tmp_path / "o"
    assert main([*args, "--export", "bvh,obj"]) == 0
    assert (out / "export" / "motion.bvh").is_file() and any((out / "export" / "obj").iterdir())
    (out / "render").mkdir()
    (out / "render" / "joint_traces.png").write_bytes(b"old")
    (out / "eval.json").write_text("{}")
    (out / "export" / "notes.txt").write_text("mine")
    assert main([*args, "--force"]) == 0
    assert sorted(p.name for p in (out / "export").iterdir()) == ["notes.txt"]
    assert not (out / "render").exists() and not (out / "eval.json").exists()
    assert (out / "motion.npz").is_file()


def test_repeated_and_conflicting_options_are_not_dropped_without_a_word(seq_dir, tmp_path, capsys, monkeypatch):
    """--export given twice kept the last; export -f twice wrote the last format alone;
    --camera with --focal dropped --focal; body --betas 1e6 drew a mangled body; a format that
    failed after a good tracking stopped the others and hid that the tracking had finished."""
    args = ["track", str(seq_dir), "--init", str(seq_dir.parent / "init.json"), "--config",
            str(seq_dir.parent / "quick.json"), "--joints3d", "off", "--quiet"]
    out = tmp_path / "o"
    assert main([*args, "--out", str(out), "--export", "bvh", "--export", "json"]) == 0
    assert sorted(p.name for p in (out / "export").iterdir()) == ["motion.bvh", "motion.json"]
    capsys.readouterr()
    assert main(["export", str(out), "-f", "bvh", "-f", "json"]) == 2
    assert "export writes one format at a time; got bvh, json" in capsys.readouterr().err
    assert main([*args, "--out", str(tmp_path / "c"), "--camera", str(seq_dir / "camera.json"), "--focal", "100"]) == 2
    assert "give --camera" in capsys.readouterr().err and not (tmp_path / "c").exists()
    assert main(["body", "--betas", "1e6", "--out", str(tmp_path / "b.png")]) == 2
    assert "within +-10" in capsys.readouterr().err and not (tmp_path / "b.png").exists()
    assert main(["synth", "builtin:walk", "--out", str(tmp_path / "s"), "--camera", str(seq_dir / "camera.json"),
                 "--azimuth", "90"]) == 2
    assert "leave out --azimuth" in capsys.readouterr().err
    from flowmocap import export as export_module

    real = export_module.export_result

    def glb_full(result, fmt, *a, **k):
        if fmt == "glb":
            raise OSError(27, "File too large", str(out / "export" / "motion.glb"))
        return real(result, fmt, *a, **k)

    monkeypatch.setattr(export_module, "export_result", glb_full)
    assert main([*args, "--out", str(out), "--resume", "--export", "glb,trc"]) == 5
    err = capsys.readouterr().err
    assert f"{out} is tracked and finished, but its export to glb failed" in err and "once there is space" in err
    assert (out / "export" / "motion.trc").is_file()  # the format after the failed one is written
    monkeypatch.undo()
    assert main([*args, "--out", str(tmp_path / "nf"), "--no-keep-flow"]) == 0  # a frame folder on a small disk
    assert (tmp_path / "o" / "flow_cache").is_dir() and not (tmp_path / "nf" / "flow_cache").exists()


def test_frames_of_numpy_or_torch_are_taken_as_numbers(seq_dir, tmp_path):
    """frames=np.array([0, 3]) with the automatic start failed after the detection pass (numpy's
    'truth value of an array'), and a torch tensor in the run's fingerprint ('not JSON
    serialisable'); both are a pair of frame numbers."""
    import torch

    kw = {"init": seq_dir.parent / "init.json", "config": seq_dir.parent / "quick.json", "joints3d": "off",
          "log": None, "progress": False}
    a = flowmocap.track(seq_dir, tmp_path / "a", frames=np.array([0, 3]), **kw)
    b = flowmocap.track(seq_dir, tmp_path / "b", frames=torch.tensor([0, 3]), **kw)
    assert list(a.frame_index) == list(b.frame_index) == [0, 1, 2]
    np.testing.assert_array_equal(a.poses, b.poses)
    from flowmocap.pipeline import _auto_start

    class Nobody:  # the automatic start's range: read as numbers, not tested for truth
        found = [False] * 4
        confidence = np.zeros((4, 40))

        def __len__(self):
            return 4

    with pytest.raises(NoPersonError):
        _auto_start(Nobody(), (np.int64(0), np.int64(3)), 4, tmp_path, (64, 48))


def test_the_frame_rate_of_a_folder_is_its_meta_json_or_given_or_assumed_with_a_note(seq_dir, tmp_path, capsys):
    # a folder without meta.json was taken as 30 fps without a word, and no option could say otherwise; a meta.json
    # fps of 0 failed only after the whole tracking
    import shutil

    init = seq_dir.parent / "init.json"
    bare = tmp_path / "bare"
    shutil.copytree(seq_dir, bare)
    (bare / "meta.json").unlink()
    kw = {"init": init, "config": QUICK, "progress": False, "joints3d": "off"}
    res = flowmocap.track(bare, tmp_path / "assumed", **kw)
    assert "frame rate of" in capsys.readouterr().out and res.fps == 30.0
    assert res.run["frame_rate"] == {"fps": 30.0, "source": "assumed"}
    assert main(["track", str(bare), "--out", str(tmp_path / "given"), "--init", str(init), "--config",
                 str(seq_dir.parent / "quick.json"), "--joints3d", "off", "--quiet", "--fps", "24"]) == 0
    given = flowmocap.load_result(tmp_path / "given")
    assert given.fps == 24.0 and given.run["frame_rate"] == {"fps": 24.0, "source": "given"}
    assert "frame rate of" not in capsys.readouterr().out
    # the rate is part of what a resume must match, where it changes the rate
    with pytest.raises(InputError, match=r"joints3d, fast, fps\)"):
        flowmocap.track(bare, tmp_path / "given", resume=True, fps=25.0, log=None, **kw)
    again = flowmocap.track(bare, tmp_path / "assumed", resume=True, fps=30.0, log=None, **kw)  # the rate it had
    assert again.fps == 30.0 and again.run["status"] == "finished"
    own = flowmocap.track(seq_dir, tmp_path / "own", log=None, **kw)
    assert own.run["frame_rate"] == {"fps": 30.0, "source": "meta.json"}
    for bad in (0, -1, float("nan"), "24", True):
        with pytest.raises(InputError, match="frames per second"):
            flowmocap.track(bare, tmp_path / "bad", fps=bad, **kw)
    (bare / "meta.json").write_text(json.dumps({"fps": 0}))
    with pytest.raises(DataError, match=r"meta.json's \"fps\" must be a number of frames per second"):
        flowmocap.track(bare, tmp_path / "bad", **kw)
    assert not (tmp_path / "bad" / "motion.npz").exists()


def test_a_rate_given_for_a_video_is_refused(tmp_path):
    import imageio.v3 as iio

    video = tmp_path / "v.mp4"
    iio.imwrite(video, np.zeros((4, 48, 64, 3), np.uint8), plugin="pyav", codec="libx264", fps=25)
    with pytest.raises(InputError, match=r"is a video, which states its own frame rate \(25 fps\)"):
        flowmocap.track(video, tmp_path / "r", fps=30.0, progress=False, log=None)
