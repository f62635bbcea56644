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
