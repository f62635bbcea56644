"""Bad inputs found by the fifty-sixth session's audit of ``flowmocap track``: each used to end
in a traceback (exit status 1), a wrong exit status, a misleading message, a hang or a result
built on a wrong frame order. Each is now one of the project's own errors with a message that
says what to do, before anything is written.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from flowmocap.body.files import read_model_arrays
from flowmocap.cli import main
from flowmocap.errors import DataError, InputError, ModelFileError, NoPersonError, OptimizationError
from flowmocap.fit.lbfgs import minimise
from flowmocap.geometry.camera import PinholeCamera
from flowmocap.io.sequence import frame_order_key, list_images, load_sequence
from flowmocap.pipeline import _auto_start, track

DEFAULT_NPZ = Path(__file__).resolve().parents[1] / "src" / "flowmocap" / "body" / "data" / "default_neutral.npz"


def _frames(folder: Path, n: int, w: int, h: int, name="{:06d}.png") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(n):
        cv2.imwrite(str(folder / name.format(k)), np.full((h, w, 3), 60 + 10 * k, np.uint8))
    return folder


def _track(src, out, **kw):
    return track(src, out, log=None, progress=False, **kw)


def test_frames_too_thin_for_any_lens_are_refused(tmp_path):
    """4x3000 frames: the default camera's view down the image is 0.08 degrees. The fallback
    for a video's implausible metadata used to format a missing focal length (TypeError)."""
    src = _frames(tmp_path / "thin", 3, 3000, 4)
    with pytest.raises(InputError, match="cannot hold a person"):
        _track(src, tmp_path / "out", max_size=0)
    assert not (tmp_path / "out" / "run.json").exists()


@pytest.mark.parametrize("content", [b"\xff\xfe\x00", b""])
def test_a_camera_file_that_is_not_json_text(tmp_path, content):
    p = tmp_path / "camera.json"
    p.write_bytes(content)
    with pytest.raises(DataError, match="not a text file|not valid JSON"):
        PinholeCamera.from_file(p)
    src = _frames(tmp_path / "seq" / "frames", 3, 64, 48).parent
    (src / "camera.json").write_bytes(content)
    with pytest.raises(DataError, match="not a valid camera file"):
        load_sequence(src)
    with pytest.raises(DataError):
        _track(_frames(tmp_path / "plain", 3, 64, 48), tmp_path / "out", camera=p)


def test_a_camera_path_that_is_a_folder_is_bad_input_not_a_write_failure(tmp_path):
    """It used to surface as an OSError: exit status 5 and advice to free space and resume."""
    (tmp_path / "cams").mkdir()
    with pytest.raises(DataError, match="not a file"):
        PinholeCamera.from_file(tmp_path / "cams")
    src = _frames(tmp_path / "plain", 3, 64, 48)
    assert main(["track", str(src), "--camera", str(tmp_path / "cams"), "--out", str(tmp_path / "o"), "--quiet"]) == 2


def test_a_principal_point_far_outside_the_image_is_refused(tmp_path):
    p = tmp_path / "pp.json"
    p.write_text('{"fx": 60, "fy": 60, "cx": 1e9, "cy": -1e9, "width": 64, "height": 48}')
    with pytest.raises(InputError, match="principal point cx = 1e\\+09"):
        _track(_frames(tmp_path / "plain", 3, 64, 48), tmp_path / "out", camera=p)
    # off centre, even just outside the image (a crop), is a real camera
    p.write_text('{"fx": 60, "fy": 60, "cx": -10, "cy": 70, "width": 64, "height": 48}')
    from flowmocap.pipeline import _check_principal_point
    _check_principal_point(PinholeCamera.from_file(p), "test")


def _damaged_model(tmp_path, **change) -> Path:
    with np.load(DEFAULT_NPZ, allow_pickle=False) as z:
        arrays = dict(z)
    for k, f in change.items():
        arrays[k] = f(arrays[k])
    p = tmp_path / "model.npz"
    np.savez(p, **arrays)
    return p


@pytest.mark.parametrize("change, match", [
    ({"weights": lambda w: 0 * w}, "skinning weights of .* do not sum to 1"),
    ({"weights": lambda w: -w}, "do not sum to 1"),
    ({"v_template": lambda v: 0 * v}, "spans 0 m"),
    ({"v_template": lambda v: 1000 * v}, "in other units"),
])
def test_a_model_file_that_cannot_be_a_body(tmp_path, change, match):
    """All-zero skinning weights used to overflow L-BFGS (a RuntimeError, exit 1); a template
    of zeros ended as "the energy became non-finite", blaming the optimiser for the file."""
    with pytest.raises(ModelFileError, match=match):
        read_model_arrays(_damaged_model(tmp_path, **change))


def test_the_bundled_bodies_pass_the_model_checks():
    for gender in ("neutral", "male", "female"):
        read_model_arrays("default", gender)


def test_an_overflow_in_the_line_search_is_an_optimisation_error(monkeypatch):
    x = torch.ones(3, dtype=torch.float64, requires_grad=True)

    def overflow(self, closure):
        closure()
        raise RuntimeError("value cannot be converted to type float without overflow")

    monkeypatch.setattr(torch.optim.LBFGS, "step", overflow)
    with pytest.raises(OptimizationError, match="overflowed"):
        minimise([x], lambda: (x ** 2).sum(), iterations=5)

    def other(self, closure):
        raise RuntimeError("some other failure")

    monkeypatch.setattr(torch.optim.LBFGS, "step", other)
    with pytest.raises(RuntimeError, match="some other failure"):  # a bug stays a bug
        minimise([x], lambda: (x ** 2).sum(), iterations=5)


def test_frames_numbered_without_zero_padding_keep_their_order(tmp_path):
    """ffmpeg's %d names: frame10 used to come right after frame1."""
    folder = _frames(tmp_path / "f", 12, 32, 24, name="frame{}.png")
    assert [p.name for p in list_images(folder)] == [f"frame{k}.png" for k in range(12)]
    padded = [Path(f"{k:06d}.png") for k in (10, 2, 0, 1)]
    assert sorted(padded, key=frame_order_key) == sorted(padded)  # zero-padded names: as before
    seq = load_sequence(folder)
    assert [round(float(seq.frame(k).mean())) for k in (0, 1, 2, 10, 11)] == [60, 70, 80, 160, 170]


def test_a_pipe_as_input_is_refused_not_waited_on(tmp_path):
    fifo = tmp_path / "x.mp4"
    os.mkfifo(fifo)
    with pytest.raises(DataError, match="neither a file nor a folder"):
        _track(fifo, tmp_path / "out")


def test_an_empty_or_dangling_out(tmp_path):
    src = _frames(tmp_path / "plain", 3, 64, 48)
    with pytest.raises(InputError, match="is empty"):
        _track(src, "")
    (tmp_path / "link").symlink_to(tmp_path / "nowhere")
    with pytest.raises(InputError, match="symbolic link to .*nowhere, which does not exist"):
        _track(src, tmp_path / "link")


def test_masks_given_as_a_file(tmp_path):
    src = _frames(tmp_path / "plain", 3, 64, 48)
    (tmp_path / "m.png").write_bytes(b"x")
    with pytest.raises(DataError, match="is a file; give a folder of mask images"):
        load_sequence(src, masks=tmp_path / "m.png")


class _Seen:
    """The detections' two fields :func:`_auto_start` reads: whom it found, and how sure."""

    def __init__(self, confident_frames, n):
        self.found = np.ones(n, bool)
        self.confidence = np.zeros((n, 15))
        self.confidence[list(confident_frames)] = 0.9

    def __len__(self):
        return len(self.found)


def test_a_person_seen_whole_only_in_the_last_frame(tmp_path):
    with pytest.raises(NoPersonError, match="only in frame 1, the last of 0:2"):
        _auto_start(_Seen([1], 2), None, 2, tmp_path, (64, 48))
    with pytest.raises(NoPersonError, match="no frame in 0:2 shows a whole enough person"):
        _auto_start(_Seen([], 2), None, 2, tmp_path, (64, 48))


def test_person_all_with_nobody_exits_as_a_single_run_would(tmp_path, capsys):
    """--person all on a video without a person used to exit 6 ("some inputs failed, the
    others finished") with a made-up person0; a single run of it exits 2."""
    src = _frames(tmp_path / "black", 3, 64, 48)
    assert main(["track", str(src), "--person", "all", "--out", str(tmp_path / "people"), "--quiet"]) == 2
    assert "flowmocap: error:" in capsys.readouterr().err


# --- the readers of a result: the fifty-sixth session's audit of render, export, eval, view ---

def _result(folder: Path, T: int = 4) -> Path:
    """A small result folder as the tracker writes it (values need not be a real body's)."""
    from flowmocap.io.results import write_motion, write_run

    rng = np.random.default_rng(0)
    cam = PinholeCamera.from_focal(64, 48, 60.0)
    j3 = rng.normal(0, 0.3, (T, 24, 3)) + [0, 0, 4]
    write_motion(folder, {
        "poses": rng.normal(0, 0.1, (T, 72)).astype(np.float32), "trans": np.tile([0, 0, 4.0], (T, 1)),
        "betas": np.zeros(10, np.float32), "gender": np.array("neutral"), "fps": np.array(30.0),
        "camera": np.array(__import__("json").dumps(cam.to_dict())), "joints3d": j3, "joints2d": cam.project(j3),
        "energies": np.ones((T, 1)), "energy_names": np.array(["total"]), "frame_index": np.arange(T)})
    write_run(folder, {"input": "nowhere", "model": "default", "gender": "neutral"})
    return folder


@pytest.mark.parametrize("damage, match", [
    (lambda m, r: m.update(joints3d=np.full_like(m["joints3d"], np.nan)), "'joints3d' holds NaN"),
    (lambda m, r: m.update(poses=m["poses"][:, :69]), "'poses' is .*expected \\(T, 72\\)"),
    (lambda m, r: m.update(frame_index=m["frame_index"][:2]), "'frame_index' is"),
    (lambda m, r: m.update(camera=np.array("{not json")), "'camera' is not the camera's JSON"),
    (lambda m, r: m.update(fps=np.array(-1.0)), "'fps' is"),
    (lambda m, r: m.update(trans=m["trans"] * 1e30), "from the camera"),
    (lambda m, r: r.update(gaps=[[999, "x"]]), "'gaps' is not a list"),
    (lambda m, r: r.update(camera_motion={"moving": True, "rotvecs": [[np.nan, 0, 0]]}), "'rotvecs' holds NaN"),
])
def test_a_damaged_result_is_a_data_error_for_every_reader(tmp_path, damage, match):
    """eval read the result unchecked (tracebacks: an SVD of NaN, KeyError, reshape), and
    export's checks left run.json's gaps and camera motion to crash deeper down."""
    import json

    from flowmocap.io.results import read_result, write_motion, write_run

    res = _result(tmp_path / "r")
    motion, run = read_result(res)
    damage(motion, run)
    write_motion(res, motion)
    write_run(res, run)
    with pytest.raises(DataError, match=match):
        read_result(res)
    assert json.loads((res / "run.json").read_text()) == json.loads(json.dumps(run))  # the folder is not changed
    seq = _frames(tmp_path / "seq" / "frames", 4, 64, 48).parent
    assert main(["eval", str(res), "--gt", str(seq), "--out", str(tmp_path / "e.json")]) == 2
    assert main(["export", str(res), "--format", "json", "--out", str(tmp_path / "m.json"), "--quiet"]) == 2


def test_progress_files_of_the_wrong_kind_are_data_errors(tmp_path):
    from flowmocap.io.results import read_result

    res = _result(tmp_path / "r")
    (res / "progress.json").write_text('{"rows": "6", "events_bytes": 0, "state": {}, "header": {}}')
    with pytest.raises(DataError, match="'rows' is '6', not a count"):
        read_result(res)
    (res / "progress.json").write_text('{"rows": 0, "events_bytes": 0, "state": {}, "header": {"fps": 30}}')
    with pytest.raises(DataError, match="unreadable result \\(KeyError"):
        read_result(res)


def test_a_file_given_as_the_result_folder(tmp_path):
    from flowmocap.io.results import read_result

    (tmp_path / "afile").write_text("x")
    with pytest.raises(DataError, match="is a file, not a result folder"):
        read_result(tmp_path / "afile")
    assert main(["export", str(tmp_path / "afile"), "--format", "bvh", "--quiet"]) == 2


def test_eval_checks_its_out_path_first_and_writes_it_whole(tmp_path, monkeypatch, capsys):
    """eval wrote its JSON straight to --out after scoring: a folder there gave an OSError
    (exit 5) once the work was done, and a failed write cut an earlier eval.json short."""
    import json

    res = _result(tmp_path / "r")
    seq = _frames(tmp_path / "seq" / "frames", 4, 64, 48).parent
    (tmp_path / "afolder").mkdir()
    assert main(["eval", str(res), "--gt", str(seq), "--out", str(tmp_path / "afolder")]) == 2
    assert main(["eval", str(res), "--gt", str(seq)]) == 0
    before = (res / "eval.json").read_text()
    assert json.loads(before)["frames"] == 4

    def full_disk(self, data, *a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full_disk)
    assert main(["eval", str(res), "--gt", str(seq)]) == 5
    assert "No space left on device; free space (or raise the file size limit)" in capsys.readouterr().err
    monkeypatch.undo()
    assert (res / "eval.json").read_text() == before
    assert not [p for p in res.iterdir() if p.name.endswith(".tmp")]


def test_eval_needs_the_results_joints_and_a_finite_ground_truth(tmp_path):
    from flowmocap.eval.scoring import score_result
    from flowmocap.io.results import read_result, write_motion

    res = _result(tmp_path / "r")
    seq = _frames(tmp_path / "seq" / "frames", 4, 64, 48).parent
    np.savez(seq / "gt.npz", joints3d=np.full((4, 24, 3), np.nan))
    with pytest.raises(DataError, match="gt.npz 'joints3d' holds NaN"):
        score_result(res, seq)
    motion, _ = read_result(res)
    del motion["frame_index"]
    write_motion(res, motion)
    with pytest.raises(DataError, match="has no frame_index"):
        score_result(res, seq)


def test_writing_over_a_folder_is_bad_input_naming_it(tmp_path):
    """An export's --out that is a folder used to fail with a message naming an internal
    temporary file ("...o2.7_g824n9.tmp: Is a directory") and exit 5."""
    from flowmocap.atomic import atomic_write

    (tmp_path / "o2").mkdir()
    with pytest.raises(InputError, match="o2 is a folder; give the path of the file"):
        atomic_write(tmp_path / "o2", lambda tmp: Path(tmp).write_text("x"))
    assert [p.name for p in tmp_path.iterdir()] == ["o2"]


def test_a_c3d_cut_short_by_a_file_size_limit_fails_and_keeps_the_old_file(tmp_path):
    """ezc3d does not report a failed write: a cut-off file with NaN markers used to replace
    the good one, and export said it wrote it (exit 0). The file's length is now checked
    against its header first (reading it back with ezc3d would crash the process)."""
    import subprocess
    import sys

    target = tmp_path / "m.c3d"
    target.write_bytes(b"the old file")
    code = (f"import numpy as np; from flowmocap.export.markers import write_c3d\n"
            f"j = np.random.default_rng(0).normal(0, 1, (400, 24, 3))\n"
            f"write_c3d({str(target)!r}, j, [f'm{{k}}' for k in range(24)], 60.0)\n")
    done = subprocess.run(["bash", "-c", f"ulimit -f 16; {sys.executable} -c \"$0\"", code],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and "short of what it holds" in done.stderr, done.stderr[-500:]
    assert target.read_bytes() == b"the old file"
    assert [p.name for p in tmp_path.iterdir()] == ["m.c3d"]
    # without the limit, the same file is written and read back whole
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-500:]
    import ezc3d
    assert ezc3d.c3d(str(target))["data"]["points"].shape == (4, 24, 400)


# --- synth, demo, body, bench and the Python API: the fifty-sixth session's third audit ---

def _amass(path: Path, **arrays) -> Path:
    base = {"poses": np.zeros((4, 72)), "trans": np.zeros((4, 3)), "mocap_framerate": np.array(30.0)}
    base.update(arrays)
    np.savez(path, **{k: v for k, v in base.items() if v is not None})
    return path


@pytest.mark.parametrize("make, match", [
    (lambda p: p.write_bytes(b""), "cannot read .* as an AMASS .npz"),
    (lambda p: p.write_bytes(b"PK\x03\x04 cut"), "cannot read .* as an AMASS .npz"),
    (lambda p: _amass(p, poses=np.array([["a"] * 72] * 4)), "poses is not numbers"),
    (lambda p: _amass(p, trans=np.zeros((3, 3))), "trans must be \\(T, 3\\) = \\(4, 3\\)"),
    (lambda p: _amass(p, mocap_framerate=np.array([30.0, 60.0])), "must be one positive number"),
    (lambda p: _amass(p, mocap_framerate=np.array(0.0)), "must be one positive number"),
    (lambda p: _amass(p, mocap_framerate=np.array(np.nan)), "mocap_framerate holds NaN"),
    (lambda p: _amass(p, poses=np.full((4, 72), np.nan)), "poses holds NaN"),
])
def test_a_damaged_amass_file_is_a_data_error(tmp_path, make, match):
    """Each used to end in EOFError, BadZipFile, ValueError, TypeError or LinAlgError (exit 1),
    or, for a NaN frame rate, in a sequence recorded at NaN fps."""
    from flowmocap.io.amass import read_amass_npz

    p = tmp_path / "m.npz"
    make(p)
    with pytest.raises(DataError, match=match):
        read_amass_npz(p)


@pytest.mark.parametrize("kw, match", [
    ({"seed": -1}, "seed must be a whole number >= 0"),
    ({"frames": 10 ** 9}, "at most 20000 frames"),
    ({"start": 10 ** 8, "frames": 3}, "is generated from its first frame"),
    ({"fps": 1e5}, "frame rate of 1..1000 Hz"),
    ({"fps": 1e-300}, "frame rate of 1..1000 Hz"),
    ({"betas": "1e6"}, "within \\+-10"),
    ({"distance": 1e12}, "px tall .* too small to see"),
])
def test_synth_refuses_what_it_cannot_make_before_any_work(tmp_path, kw, match):
    from flowmocap.synth import synthesize

    args = {"frames": 3, "size": "96x72", **kw}
    with pytest.raises(InputError, match=match):
        synthesize("builtin:walk", tmp_path / "s", **args)
    assert not (tmp_path / "s").exists()


def test_synth_into_an_empty_name_or_size(tmp_path, monkeypatch):
    """`--out ""` wrote a sequence into the current folder; `--size ""` became 640x480."""
    from flowmocap.synth import synthesize

    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match="is empty"):
        synthesize("builtin:walk", "", frames=3, size="96x72")
    assert main(["synth", "builtin:walk", "--out", "s", "--num-frames", "3", "--size", ""]) == 2
    assert list(tmp_path.iterdir()) == []


def test_an_overwrite_drops_the_old_ground_truth_first(tmp_path):
    """An overwrite cut short used to leave the new frames with the old gt.npz, meta.json and
    camera.json, which load_sequence read as one sequence."""
    from flowmocap.synth.sequence import _prepare_out

    seq = _frames(tmp_path / "s" / "frames", 3, 32, 24).parent
    for name in ("gt.npz", "meta.json", "camera.json"):
        (seq / name).write_text("old")
    _prepare_out(seq, overwrite=True)
    assert sorted(p.name for p in seq.iterdir()) == ["frames", "masks"]
    assert list((seq / "frames").iterdir()) == []


def test_a_frame_synth_cannot_write_is_an_output_error(tmp_path, monkeypatch):
    """It was a DataError (exit 2, "bad input") with no reason given."""
    import flowmocap.synth.sequence as synth_sequence
    from flowmocap.errors import OutputError

    monkeypatch.setattr(synth_sequence.cv2, "imwrite", lambda *a, **k: False)
    with pytest.raises(OutputError, match="full disk, a file size limit or no permission"):
        synth_sequence.synthesize("builtin:walk", tmp_path / "s", frames=3, size="96x72", flow=False)


@pytest.mark.parametrize("argv, match", [
    (["--num-frames", "1"], "tracks 2..20000 frames"),
    (["--seed", "-1"], "seed must be a whole number"),
    (["--size", "abc"], "size must look like"),
])
def test_demo_checks_its_arguments_before_writing(tmp_path, capsys, argv, match):
    assert main(["demo", "--out", str(tmp_path / "d"), "--quiet", *argv]) == 2
    assert match.split(" ")[0] in capsys.readouterr().err
    assert not (tmp_path / "d").exists()


def test_demo_leaves_a_users_folder_alone(tmp_path, capsys):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "eval.json").write_text("my scores")
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    assert main(["demo", "--out", str(tmp_path / "mine"), "--quiet"]) == 2
    assert "is not empty (notes.txt) and holds no flowmocap demo" in capsys.readouterr().err
    assert (tmp_path / "mine" / "eval.json").read_text() == "my scores"
    (tmp_path / "afile").write_text("x")
    assert main(["demo", "--out", str(tmp_path / "afile"), "--quiet"]) == 2


def test_demo_run_again_with_other_settings_makes_a_new_clip(tmp_path, capsys):
    """The second run used to score the first run's 2-frame clip under the new settings; a
    2-frame demo used to crash formatting its time per frame (None) after the work."""
    import json

    out = tmp_path / "d"
    assert main(["demo", "--out", str(out), "--num-frames", "2", "--size", "96x72", "--quiet"]) == 0
    assert "no time per frame" in capsys.readouterr().out
    assert main(["demo", "--out", str(out), "--num-frames", "3", "--size", "80x64", "--seed", "1", "--quiet"]) == 0
    scores = json.loads((out / "eval.json").read_text())
    assert scores["frames"] == 3 and scores["size"] == [80, 64] and scores["seed"] == 1
    meta = json.loads((out / "sequence" / "meta.json").read_text())
    assert meta["num_frames"] == 3 and meta["seed"] == 1


def test_body_refuses_a_name_it_cannot_write_without_touching_the_file(tmp_path):
    """`body --out notes` emptied the file `notes` and crashed (unknown extension); a folder
    gave exit 5 and a message about reading."""
    (tmp_path / "notes").write_text("precious")
    assert main(["body", "--out", str(tmp_path / "notes")]) == 2
    assert (tmp_path / "notes").read_text() == "precious"
    (tmp_path / "dir.png").mkdir()
    assert main(["body", "--out", str(tmp_path / "dir.png")]) == 2
    assert main(["body", "--out", str(tmp_path / "notes" / "x.png")]) == 2  # under a file


def test_bench_into_a_file_and_no_command(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    assert main(["bench", "--suite", "quick", "--out", str(tmp_path / "afile")]) == 2
    assert "is a file" in capsys.readouterr().err
    assert main([]) == 2  # no command: the usage, on stderr, as for any other usage error
    assert "COMMAND" in capsys.readouterr().err


@pytest.mark.parametrize("kw, match", [
    ({"source": None}, "source must be a path"),
    ({"source": 123}, "source must be a path"),
    ({"out": None}, "out must be a path"),
    ({"source": ""}, "source is empty"),
    ({"init": 123}, "init must be 'auto'"),
    ({"masks": 123}, "masks must be None"),
    ({"model": None}, "model must be 'default'"),
    ({"max_size": "big"}, "whole number of pixels"),
    ({"max_size": float("nan")}, "whole number of pixels"),
    ({"frames": (0.5, 2.7)}, "whole frame numbers"),
])
def test_the_api_refuses_arguments_of_the_wrong_kind(tmp_path, kw, match):
    """Each used to be a bare TypeError (or was silently read another way)."""
    args = {"source": _frames(tmp_path / "plain", 3, 64, 48), "out": tmp_path / "out", **kw}
    with pytest.raises(InputError, match=match):
        track(args.pop("source"), args.pop("out"), log=None, progress=False, **args)
    assert not (tmp_path / "out").exists()


def test_load_result_of_no_path_or_a_missing_one(tmp_path):
    import flowmocap

    with pytest.raises(InputError, match="a result folder is a path"):
        flowmocap.load_result(None)
    with pytest.raises(DataError, match="does not exist"):
        flowmocap.load_result(tmp_path / "nope")


def test_synth_refuses_a_focal_length_no_lens_has(tmp_path):
    """--focal 1e-9 used to end in "the camera at distance 0.00 m is inside the body's path"."""
    from flowmocap.synth import synthesize

    for focal in (1e-9, 1e9):
        with pytest.raises(InputError, match="field of view of .* outside 0.2..170"):
            synthesize("builtin:walk", tmp_path / "s", frames=3, size="96x72", focal=focal)


@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_the_detector_process_ends_with_the_tracking_process(tmp_path):
    """A tracking process killed outright (kill -9, SIGTERM) used to leave its detector
    process running on, orphaned, writing into the result folder outside its lock."""
    import signal
    import subprocess
    import sys
    import time

    from flowmocap.vision.detect_worker import PARENT_ENV

    # the parent names itself in the worker's environment as the tracker does (a worker slow to
    # start on a loaded machine then ends at once if its parent is gone, instead of taking init
    # for its parent), and the worker says when its death signal is set
    child = ("import time; from flowmocap.vision import detect_worker as w; "
             "w._end_with_parent(); print('armed', flush=True); time.sleep(60)")
    parent = (f"import os, subprocess, sys, time; p = subprocess.Popen([sys.executable, '-c', {child!r}], "
              f"env={{**os.environ, {PARENT_ENV!r}: str(os.getpid())}}); print(p.pid, flush=True); time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", parent], stdout=subprocess.PIPE, text=True)
    try:  # the pid and "armed" (the worker has set its death signal), in whichever order they come
        lines = {proc.stdout.readline().strip(), proc.stdout.readline().strip()}
        assert "armed" in lines, lines
        worker = int((lines - {"armed"}).pop())
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    for _ in range(50):
        try:
            os.kill(worker, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
        try:  # reaped by init; a zombie reads as alive to kill(0) on some systems
            if open(f"/proc/{worker}/stat").read().split()[2] == "Z":
                break
        except OSError:
            break
    else:
        os.kill(worker, signal.SIGKILL)
        pytest.fail("the worker outlived its parent")


# --- the fifty-seventh session's audit: the viewer, batches, people and two runs at once ---

@pytest.mark.parametrize("status, words", [
    ("running", "is still going: this is the 4 frames tracked so far"),
    ("finishing", "is still doing the steps after tracking"),
    ("interrupted", "is interrupted: this is the 4 frames tracked before it stopped"),
    ("failed", "is failed (boom): this is the 4 frames"),
])
def test_export_and_render_say_when_the_run_has_not_finished(tmp_path, capsys, status, words):
    """A BVH of 27 of 90 frames, without the refit and smoothing, came out of a run still
    going, with exit 0 and not a word; so did render's video and the viewer's page."""
    import json

    from flowmocap.io.lock import FolderLock
    from flowmocap.io.results import unfinished_words

    res = _result(tmp_path / "r")
    run = json.loads((res / "run.json").read_text())
    assert unfinished_words(res, run, 4) is None
    (res / "run.json").write_text(json.dumps({**run, "status": status, "error": "boom"}))
    frames = _frames(tmp_path / "frames", 4, 64, 48)
    with FolderLock(res) if status in ("running", "finishing") else _nothing():  # a run going on holds the folder
        assert main(["export", str(res), "--format", "json", "--out", str(tmp_path / "m.json"), "--quiet"]) == 0
        said = capsys.readouterr().out
        assert said.startswith(f"note: the run in {res} {words}"), said
        assert main(["render", str(res), "--input", str(frames), "--traces", str(tmp_path / "t.png")]) == 0
        assert f"note: the run in {res} {words}" in capsys.readouterr().out
    if status in ("interrupted", "failed"):
        assert "--resume` finishes it" in said


def _nothing():
    import contextlib

    return contextlib.nullcontext()


def test_eval_scores_the_silhouettes_with_the_body_the_result_was_tracked_with(tmp_path, monkeypatch):
    """eval drew the silhouettes of the bundled body whatever run.json said (IoU 0.64 where
    the tracked body's was 0.81); export, render and view used the recorded one."""
    import json

    from flowmocap.eval import scoring

    from importlib import resources

    with np.load(resources.files("flowmocap.body") / "data" / "default_neutral.npz") as z:
        arrays = dict(z)
    arrays["v_template"] = arrays["v_template"] * 1.15
    big = tmp_path / "big_neutral.npz"
    np.savez(big, **arrays)
    res = _result(tmp_path / "r")
    run = json.loads((res / "run.json").read_text())
    (res / "run.json").write_text(json.dumps({**run, "model": str(big)}))
    seq = _frames(tmp_path / "seq" / "frames", 4, 64, 48).parent
    masks = seq / "masks"
    masks.mkdir()
    for k in range(4):
        cv2.imwrite(str(masks / f"{k:06d}.png"), np.full((48, 64), 255, np.uint8))
    drawn = []
    real = scoring.m.render_silhouettes
    monkeypatch.setattr(scoring.m, "render_silhouettes", lambda model, *a: drawn.append(model) or real(model, *a))
    assert main(["eval", str(res), "--gt", str(seq)]) == 0
    template = drawn[-1].v_template.detach().cpu().numpy()
    np.testing.assert_allclose(template, arrays["v_template"], rtol=1e-5)
    big.unlink()
    assert main(["eval", str(res), "--gt", str(seq)]) == 2  # the recorded model is gone: said, not swapped


# --- the fifty-seventh session's audit of the Python API ---

def test_track_checks_its_switches(tmp_path):
    """force="no" wiped a finished result (any string is true); log and search_dir of the
    wrong kind failed deep inside."""
    src = _frames(tmp_path / "plain", 3, 64, 48)
    for name in ("force", "resume", "fast", "reinit", "progress", "keep_flow"):
        with pytest.raises(InputError, match=rf"{name} must be True or False.*got 'no'"):
            track(src, tmp_path / "o", **{"log": None, "progress": False, name: "no"})
    with pytest.raises(InputError, match="log must be a function"):
        track(src, tmp_path / "o", log=5, progress=False)
    with pytest.raises(InputError, match="search_dir must be None or a folder's path"):
        _track(src, tmp_path / "o", search_dir=5)
    assert not (tmp_path / "o").exists()


def test_batch_takes_one_path_and_refuses_unknown_settings_before_any_work(tmp_path):
    from flowmocap.batch import expand_inputs, plan, track_many

    seq = _frames(tmp_path / "seq", 3, 64, 48)
    assert expand_inputs(str(seq)) == [seq]  # was [s, e, q, ...]: the letters of the path
    assert [it.input for it in plan(str(seq), tmp_path / "b")] == [str(seq)]
    with pytest.raises(InputError, match="takes no bogus; check the names"):
        track_many([seq], tmp_path / "b2", bogus=1, log=None)
    assert not (tmp_path / "b2").exists()
    with pytest.raises(InputError, match="force must be True or False"):
        track_many([seq], tmp_path / "b2", force="no", log=None)
    with pytest.raises(InputError, match="inputs must be paths"):
        expand_inputs([seq, 5])


def test_numpy_values_where_python_ones_are_expected(tmp_path):
    from flowmocap.fit.config import TrackerConfig
    from flowmocap.synth import synthesize

    assert TrackerConfig(kalman=np.bool_(False)).kalman is False  # 'must be true or false; got True' before
    with pytest.raises(InputError, match="the settings must be a dict"):
        TrackerConfig.from_dict(None)
    res = synthesize("builtin:walk", tmp_path / "s", frames=2, size="64x48", seed=np.int64(3), fps=np.float32(24),
                     flow=False)
    assert res.meta["seed"] == 3 and res.meta["fps"] == 24.0  # meta.json was not written (int64), fps refused


def test_results_compare_and_the_readers_take_a_result_or_say_what_a_path_is(tmp_path):
    import flowmocap
    from flowmocap.body import load_body_model
    from flowmocap.export import export_result, load_fitted_motion
    from flowmocap.io import read_bvh, retarget
    from flowmocap.synth import synthesize

    res = flowmocap.load_result(_result(tmp_path / "r"))
    assert (res == res) is True and (res == flowmocap.load_result(res)) is False  # was a ValueError
    assert flowmocap.load_result(res).path == res.path
    assert load_fitted_motion(res, frame="up").num_frames == 4
    export_result(res, "json", tmp_path / "m.json", frame="up")
    for call, match in ((lambda: load_fitted_motion(None), "a result folder is a path"),
                        (lambda: export_result(res, "bvh", out=5), "out must be the path"),
                        (lambda: load_body_model(None), "name_or_path must be the path"),
                        (lambda: load_body_model(num_betas=-1), "num_betas must be"),
                        (lambda: load_body_model(dtype="float64"), "dtype must be a torch dtype"),
                        (lambda: read_bvh(None), "path must be the path of a .bvh"),
                        (lambda: synthesize(None, tmp_path / "x"), "motion_source must be"),
                        (lambda: export_result(res, "bvh", tmp_path / "x.bvh", units_per_metre="100"),
                         "units_per_metre must be a positive number"),
                        (lambda: load_fitted_motion(res, smooth="no"), "smooth must be False, True or a dict"),
                        (lambda: load_fitted_motion(res, smooth={"window": 0.3}), "smooth takes window_s")):
        with pytest.raises(InputError, match=match):
            call()
    from flowmocap.io.mocap import MocapClip  # noqa: F401 (the clip type retarget takes)

    with pytest.raises(InputError, match="model must be a BodyModel"):
        retarget(None, "default")
    body = load_body_model()
    with pytest.raises(InputError, match="at least one body"):
        body(betas=np.zeros((0, 10)), pose=np.zeros((0, 72)), trans=np.zeros((0, 3)))


def test_a_results_own_motion_npz_is_not_read_as_amass(tmp_path):
    from flowmocap.io import read_amass_npz

    res = _result(tmp_path / "r")
    with pytest.raises(DataError, match="is a flowmocap result's motion.npz, not an AMASS file"):
        read_amass_npz(res / "motion.npz")


def test_people_to_track_takes_the_detections_file(tmp_path):
    import json

    from flowmocap.batch import people_to_track

    info = {"person": {"people": [{"rank": 0, "frames": [0, 9], "detections": 10, "score": 1.0,
                                   "first_box": [0, 0, 5, 5]}]}}
    (tmp_path / "detections.json").write_text(json.dumps(info))
    assert people_to_track(tmp_path / "detections.json") == people_to_track(info)
    with pytest.raises(InputError, match="info must be a detections.json's dict"):
        people_to_track(5)


def test_a_demo_killed_while_it_wrote_a_file_runs_again(tmp_path):
    """Its own temporary (default_body.png.XXXX.tmp) made the demo's folder 'not empty and
    holds no flowmocap demo' for every rerun."""
    from flowmocap.eval.demo import check_demo

    out = tmp_path / "demo"
    out.mkdir()
    (out / "default_body.png.x0wge0xn.tmp").write_bytes(b"half")
    check_demo(out, 30, "640x480", 0)
    (out / "mine.tmp").write_text("a user's")
    with pytest.raises(InputError, match=r"is not empty \(mine.tmp\)"):
        check_demo(out, 30, "640x480", 0)


def test_a_child_whose_parent_is_gone_ends_at_once():
    """The bench's tracking child outlived a bench killed outright, holding the result folder."""
    import subprocess
    import sys

    code = "from flowmocap.vision.detect_worker import end_with_parent; end_with_parent(1); print('still here')"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 130 and "still here" not in done.stdout


def test_a_detector_process_sent_sigterm_runs_its_exit_handlers(tmp_path):
    # SIGTERM (its parent gone, a service manager) ended it without exit handlers: the heavy model's temporary
    # resource folder stayed behind
    import pickle
    import signal
    import subprocess
    import sys

    job = tmp_path / "job.pkl"
    job.write_bytes(pickle.dumps({}))
    mark = tmp_path / "exited.txt"
    code = ("import atexit, sys, time; import flowmocap.vision.auto as auto; "
            f"atexit.register(lambda: open({str(mark)!r}, 'w').write('ran')); "
            "auto.run_chunk = lambda task: (print('ready', flush=True), time.sleep(60)); "
            f"from flowmocap.vision import detect_worker as w; sys.exit(w.main([{str(job)!r}]))")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 143
    finally:
        proc.kill()
    assert mark.read_text() == "ran"
