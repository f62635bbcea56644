"""Plain folders of frames scaled like videos (``max_side`` / ``--max-size``): frames and
masks at the scaled size, masks given at either size, sequence folders with their own
camera or ground truth kept as they are, the focal length and the render reading them back."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from flowmocap.errors import DataError
from flowmocap.io.sequence import load_sequence, scaled_size


def _folder(root, n=2, w=160, h=96, masks_size=None):
    (root / "frames").mkdir(parents=True)
    for i in range(n):
        img = np.full((h, w, 3), 40, np.uint8)
        img[: h // 2, : w // 4] = 250  # a bright block: 40 x 48 pixels
        cv2.imwrite(str(root / "frames" / f"{i:06d}.png"), img)
    if masks_size is not None:
        mw, mh = masks_size
        (root / "masks").mkdir()
        for i in range(n):
            m = np.zeros((mh, mw), np.uint8)
            m[mh // 4: 3 * mh // 4, mw // 2: 3 * mw // 4] = 255
            cv2.imwrite(str(root / "masks" / f"{i:06d}.png"), m)
    return root


def test_scaled_size():
    assert scaled_size((854, 480), 640) == ((640, 360), pytest.approx(640 / 854))
    assert scaled_size((480, 854), 640)[0] == (360, 640)
    assert scaled_size((640, 480), 640) == ((640, 480), 1.0)
    assert scaled_size((854, 480), None) == ((854, 480), 1.0)
    assert scaled_size((854, 480), 0) == ((854, 480), 1.0)


def test_folder_frames_and_masks_scaled(tmp_path):
    seq = load_sequence(_folder(tmp_path / "s", masks_size=(160, 96)), max_side=80)
    assert seq.size == (80, 48) and seq.source_size == (160, 96) and seq.meta["scale"] == pytest.approx(0.5)
    img = seq.frame(0)
    assert img.shape == (48, 80, 3) and img.dtype == np.uint8
    assert img[:24, :20].mean() == pytest.approx(250, abs=1) and img[30:, 40:].mean() == pytest.approx(40, abs=1)
    m = seq.mask(1)
    assert m.shape == (48, 80) and m.dtype == bool
    assert m.sum() == 24 * 20 and m[12:36, 40:60].all()  # the 48 x 40 block, halved each way


def test_folder_masks_at_the_scaled_size_are_read_as_they_are(tmp_path):
    seq = load_sequence(_folder(tmp_path / "s"), max_side=80)
    (tmp_path / "det").mkdir()
    m = np.zeros((48, 80), np.uint8)
    m[5:9, 7:11] = 255
    cv2.imwrite(str(tmp_path / "det" / "a.png"), m)
    seq.masks = [tmp_path / "det" / "a.png"] * 2  # as the pipeline sets the detector's masks
    assert np.array_equal(seq.mask(0), m > 0)
    cv2.imwrite(str(tmp_path / "det" / "b.png"), np.zeros((50, 70), np.uint8))
    seq.masks = [tmp_path / "det" / "b.png"] * 2
    with pytest.raises(DataError, match="70x50 but the frames are 160x96 .scaled to 80x48"):
        seq.mask(0)


def test_folder_that_fits_and_sequence_folders_keep_their_size(tmp_path):
    assert load_sequence(_folder(tmp_path / "a"), max_side=160).source_size is None
    assert load_sequence(_folder(tmp_path / "b"), max_side=None).size == (160, 96)
    from flowmocap.geometry.camera import PinholeCamera

    root = _folder(tmp_path / "c")
    (root / "camera.json").write_text(json.dumps(PinholeCamera.from_focal(160, 96, 150.0).to_dict()))
    seq = load_sequence(root, max_side=80)  # its camera is in its pixels
    assert seq.size == (160, 96) and seq.source_size is None and "scale" not in seq.meta
    root = _folder(tmp_path / "d")
    np.savez(root / "gt.npz", joints2d=np.zeros((2, 24, 2)))
    assert load_sequence(root, max_side=80).size == (160, 96)


def test_focal_of_a_scaled_folder_and_render_reads_it_back(tmp_path):
    from flowmocap.pipeline import _camera
    from flowmocap.viz.result_render import _open_input

    root = _folder(tmp_path / "s")
    seq = load_sequence(root, max_side=80)
    cam, note = _camera(300.0, seq, root)  # a focal length of the files' pixels
    assert (cam.width, cam.height) == (80, 48) and cam.fx == pytest.approx(150.0) and "x 0.5" in note
    cam, _ = _camera(None, seq, root)
    assert (cam.width, cam.height) == (80, 48)
    again = _open_input(root, cam)
    assert again.size == (80, 48) and np.array_equal(again.frame(1), seq.frame(1))
