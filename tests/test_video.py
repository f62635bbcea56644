"""Video input: decoding, timestamps of variable-frame-rate videos, rotation tags
(portrait phone videos), scaling, broken and too-short files, the default camera."""

from __future__ import annotations

import struct
from fractions import Fraction

import numpy as np
import pytest

from flowmocap.errors import DataError, InputError, NoPersonError
from flowmocap.io.video import (DEFAULT_FOCAL_FACTOR, VideoReader, decode_video, default_camera, focal_35mm_from_tags,
                                load_video)


def write_video(path, frames, times_ms=None, codec="mpeg4"):
    """Write RGB frames with PyAV; ``times_ms`` gives each frame's presentation time."""
    import av

    h, w = frames[0].shape[:2]
    with av.open(str(path), "w") as c:
        s = c.add_stream(codec, rate=30)
        s.width, s.height, s.pix_fmt = w, h, "yuv420p"
        s.time_base = Fraction(1, 1000)
        for i, img in enumerate(frames):
            f = av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24")
            f.pts = int(times_ms[i]) if times_ms is not None else int(round(i * 1000 / 30))
            f.time_base = Fraction(1, 1000)
            for p in s.encode(f):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return path


def _frames(n, w=64, h=48):
    out = []
    for i in range(n):
        img = np.full((h, w, 3), 40, np.uint8)
        img[: h // 4, : w // 3] = 255  # a white block in the top-left corner
        img[h // 2, (4 * i) % w] = 128
        out.append(img)
    return out


def test_constant_rate_video(tmp_path):
    v = write_video(tmp_path / "a.mp4", _frames(5))
    frames, info = decode_video(v)
    assert len(frames) == 5 and frames[0].shape == (48, 64, 3)
    assert info["fps"] == pytest.approx(30.0, rel=0.02)
    assert not info["variable_frame_rate"]
    assert info["timestamps"][0] == 0.0 and len(info["timestamps"]) == 5


def test_variable_frame_rate_keeps_timestamps(tmp_path):
    times = [0, 33, 100, 133, 200, 233]
    v = write_video(tmp_path / "vfr.mp4", _frames(6), times_ms=times)
    seq = load_video(v)
    assert len(seq) == 6
    assert seq.meta["variable_frame_rate"]
    assert np.allclose(seq.meta["timestamps"], np.array(times) / 1000, atol=2e-3)
    assert seq.meta["fps"] == pytest.approx(5 / 0.233, rel=0.02)  # the mean rate


def _rotate_tag(src, dst, matrix):
    """Write the track's display matrix (tkhd) of an mp4, as phones do for portrait video."""
    data = bytearray(src.read_bytes())
    ident = struct.pack(">9I", 0x10000, 0, 0, 0, 0x10000, 0, 0, 0, 0x40000000)
    pos = data.rfind(ident)  # the last one is the video track's (the first is the movie's)
    assert pos > 0
    data[pos:pos + 36] = struct.pack(">9i", *matrix)
    dst.write_bytes(bytes(data))
    return dst


def test_portrait_video_from_rotation_tag(tmp_path):
    v = write_video(tmp_path / "land.mp4", _frames(3))
    # a 90 degree display rotation: shown upright, the stored 64x48 frames are 48x64
    rot = _rotate_tag(v, tmp_path / "portrait.mp4", (0, 0x10000, 0, -0x10000, 0, 0, 0, 0, 0x40000000))
    seq = load_video(rot)
    assert seq.size == (48, 64) and seq.frame(0).shape == (64, 48, 3)
    assert seq.meta["rotation"] == -90 and seq.meta["decoded_size"] == [48, 64]
    white = np.argwhere(seq.frame(0)[..., 0] > 200)
    # turned clockwise: the top-left block is now top-right
    assert white[:, 1].min() >= 48 - 16 - 1 and white[:, 0].max() <= 21


@pytest.mark.parametrize("a, b, c, d", [(1, 0, 0, 1), (0, 1, -1, 0), (-1, 0, 0, -1), (0, -1, 1, 0),
                                        (-1, 0, 0, 1), (1, 0, 0, -1), (0, 1, 1, 0), (0, -1, -1, 0)])
def test_every_display_matrix_shows_the_frames_as_a_player_does(tmp_path, a, b, c, d):
    # a mirror matrix (QuickTime's Flip Horizontal) was taken for a 180 degree turn: the clip tracked upside down
    src = _frames(2)[0]
    v = write_video(tmp_path / "plain.mp4", _frames(2))
    one = 0x10000
    tagged = _rotate_tag(v, tmp_path / "tagged.mp4", (a * one, b * one, 0, c * one, d * one, 0, 0, 0, 0x40000000))
    seq = load_video(tagged)
    # what a player shows: decoded pixel (x, y) at (a x + c y, b x + d y), moved to start at 0
    h, w = src.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w]
    X, Y = a * xs + c * ys, b * xs + d * ys
    X, Y = X - X.min(), Y - Y.min()
    shown = np.zeros((Y.max() + 1, X.max() + 1, 3), np.uint8)
    shown[Y, X] = src
    got = seq.frame(0)
    assert got.shape == shown.shape and seq.size == (shown.shape[1], shown.shape[0])
    assert np.abs(got.astype(float) - shown).mean() < 6.0  # the codec's loss; a wrong turn or mirror is ~50
    assert seq.meta["mirrored"] == (a * d - b * c < 0)


def test_non_square_pixels_are_shown_square_as_a_player_does(tmp_path):
    # a camcorder's anamorphic frames (stored 48 px wide, shown 64) were tracked squeezed by a square-pixel camera
    import av
    import cv2

    src = _frames(2, w=64, h=48)
    with av.open(str(tmp_path / "anamorphic.mp4"), "w") as c:
        s = c.add_stream("libx264", rate=30)
        s.width, s.height, s.pix_fmt = 48, 48, "yuv420p"
        s.options = {"crf": "10"}
        s.codec_context.sample_aspect_ratio = Fraction(4, 3)
        for img in src:
            squeezed = np.ascontiguousarray(cv2.resize(img, (48, 48), interpolation=cv2.INTER_AREA))  # 64 -> 48 wide
            for p in s.encode(av.VideoFrame.from_ndarray(squeezed, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    seq = load_video(tmp_path / "anamorphic.mp4")
    assert seq.size == (64, 48) and seq.meta["sample_aspect_ratio"] == pytest.approx(4 / 3)
    white = np.argwhere(seq.frame(0)[..., 0] > 200)  # the top-left block, a third of the width as shown
    assert abs(white[:, 1].max() + 1 - 64 / 3) <= 1.5


def test_the_scale_of_each_axis_is_recorded(tmp_path):
    # only the width's was: joints2d divided by it were 1.8 px off at the bottom of a 1088x1920 video
    v = write_video(tmp_path / "p.mp4", _frames(2, w=110, h=192))
    seq = load_video(v, max_side=64)
    assert seq.size == (37, 64)
    assert seq.meta["scale_xy"] == [37 / 110, 64 / 192] and seq.meta["scale"] == 37 / 110


def test_portrait_video_without_tag(tmp_path):
    v = write_video(tmp_path / "p.mp4", _frames(3, w=48, h=96))
    seq = load_video(v)
    assert seq.size == (48, 96)
    cam, how = default_camera(*seq.size)
    assert cam.fx == pytest.approx(DEFAULT_FOCAL_FACTOR * 96) and "long side" in how


def test_max_side_scales_frames(tmp_path):
    v = write_video(tmp_path / "big.mp4", _frames(2, w=160, h=96))
    seq = load_video(v, max_side=80)
    assert seq.size == (80, 48) and seq.meta["scale"] == pytest.approx(0.5)
    assert seq.meta["decoded_size"] == [160, 96]


def test_undecodable_and_missing(tmp_path):
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"\x00\x00\x00\x18ftypmp42 this is not a video")
    with pytest.raises(DataError, match="cannot decode"):
        load_video(broken)
    with pytest.raises(DataError, match="does not exist"):
        load_video(tmp_path / "missing.mp4")
    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    with pytest.raises(DataError):
        load_video(empty)


def test_truncated_video_keeps_decoded_frames(tmp_path):
    v = write_video(tmp_path / "full.mkv", _frames(20))
    data = v.read_bytes()
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    frames, _ = decode_video(cut)
    assert 1 <= len(frames) < 20


def test_a_cut_off_video_says_so(tmp_path):
    """A file cut short in a download decoded a few frames without an error and was tracked
    as a shorter clip with nothing said. The container's frame count (an MP4 with its index
    first) or duration (MKV) shows what is missing; a whole file says nothing."""
    import av

    whole = tmp_path / "whole.mp4"
    with av.open(str(whole), "w", options={"movflags": "faststart"}) as c:
        s = c.add_stream("mpeg4", rate=30)
        s.width, s.height, s.pix_fmt = 64, 48, "yuv420p"
        for img in _frames(30):
            for p in s.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    assert VideoReader(whole).info["cut_short"] is None
    data = whole.read_bytes()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    r = VideoReader(cut)
    assert 1 <= len(r) < 30
    assert r.info["cut_short"]["declared_frames"] == 30 and r.info["cut_short"]["decoded_frames"] == len(r)
    mkv = write_video(tmp_path / "whole.mkv", _frames(20))
    assert VideoReader(mkv).info["cut_short"] is None
    cut_mkv = tmp_path / "cut.mkv"
    cut_mkv.write_bytes(mkv.read_bytes()[: int(mkv.stat().st_size * 0.6)])
    info = VideoReader(cut_mkv).info["cut_short"]
    assert info["declared_seconds"] == pytest.approx(20 / 30, abs=0.01) and info["decoded_seconds"] < 0.5


def test_track_says_a_video_is_cut_off(tmp_path):
    """Before any work, in the log and in the mask-count error (masks made for the whole file)."""
    import av
    import cv2

    from flowmocap.pipeline import track

    whole = tmp_path / "whole.mp4"
    with av.open(str(whole), "w", options={"movflags": "faststart"}) as c:
        s = c.add_stream("mpeg4", rate=30)
        s.width, s.height, s.pix_fmt = 64, 48, "yuv420p"
        s.codec_context.gop_size = 1  # every frame decodes on its own: the cut file keeps several
        for img in _frames(30):
            for p in s.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(whole.read_bytes()[: int(whole.stat().st_size * 0.6)])
    n = len(VideoReader(cut))
    assert 2 <= n < 30
    masks = tmp_path / "masks"
    masks.mkdir()
    for i in range(30):
        cv2.imwrite(str(masks / f"{i:06d}.png"), np.zeros((48, 64), np.uint8))
    with pytest.raises(DataError, match=rf"30 masks .* but {n} frames .*the file is cut off: {n} frames decode "
                                        r"\([\d.]+ s\), but the file says it holds 30 frames; get it again"):
        track(cut, tmp_path / "r", masks=masks, log=None, progress=False)
    said = []
    with pytest.raises(NoPersonError):  # the empty masks are refused next, after the warning
        track(cut, tmp_path / "r2", masks=_first(masks, n, tmp_path), log=said.append, progress=False)
    assert any(m.startswith(f"warning: {cut} is cut off: {n} frames decode") for m in said), said


def _first(masks, n, tmp_path):
    import shutil

    some = tmp_path / "some_masks"
    some.mkdir()
    for p in sorted(masks.iterdir())[:n]:
        shutil.copy(p, some / p.name)
    return some


def test_default_camera_and_metadata():
    cam, how = default_camera(854, 480)
    assert cam.fx == pytest.approx(0.9 * 854) and cam.cx == pytest.approx(427.0)
    assert "58 degree" in how
    tags = {"com.apple.quicktime.camera.focal_length.35mm_equivalent": "26"}
    assert focal_35mm_from_tags(tags) == 26.0
    cam, how = default_camera(1920, 1080, 26.0)
    assert cam.fx == pytest.approx(26 / 36 * 1920) and "35 mm" in how
    assert focal_35mm_from_tags({"handler_name": "VideoHandler"}) is None


def test_track_refuses_one_frame(tmp_path):
    from flowmocap.cli import main

    v = write_video(tmp_path / "one.mp4", _frames(1))
    assert main(["track", str(v), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    with pytest.raises(InputError, match="at least 2 frames"):
        from flowmocap.cli import build_parser

        args = build_parser().parse_args(["track", str(v), "--out", str(tmp_path / "out2"), "--quiet"])
        args.func(args)


@pytest.mark.parametrize("codec, gop", [("mpeg4", 8), ("libx264", 12), ("libx264", 250)])
def test_frames_read_in_any_order_equal_the_sequential_decode(tmp_path, codec, gop):
    """The streaming reader seeks to the keyframe before a frame asked out of order and
    decodes forwards: every frame, in any order, is the pixel-exact frame of a plain decode
    from the start; and it holds only a few frames."""
    import av

    from flowmocap.io.video import VideoReader

    if codec not in av.codecs_available:
        pytest.skip(f"PyAV has no {codec} encoder here")
    rng = np.random.default_rng(0)
    frames = [np.clip(f.astype(int) + rng.integers(0, 60, f.shape), 0, 255).astype(np.uint8) for f in _frames(70)]
    path = tmp_path / "g.mp4"
    with av.open(str(path), "w") as c:
        s = c.add_stream(codec, rate=30)
        s.width, s.height, s.pix_fmt, s.gop_size = 64, 48, "yuv420p", gop
        if codec == "libx264":
            s.options = {"bf": "2"}  # B-frames: decode order differs from presentation order
        for img in frames:
            for p in s.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    with av.open(str(path)) as c:  # the plain decode from the start
        plain = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    with VideoReader(path) as reader:
        assert len(reader) == len(plain) == 70
        order = [0, 1, 2, 69, 35, 34, 36, 10, 9, 68, 5] + list(rng.permutation(70))
        for i in order:
            np.testing.assert_array_equal(reader.frame(i), plain[i], err_msg=f"frame {i}")
        assert len(reader._kept) <= reader.KEEP
    seq = load_video(path)
    np.testing.assert_array_equal(seq.frame(40), plain[40])
    assert not hasattr(seq, "_decoded")  # nothing but the reader's few frames is held


def _write_masks(folder, n, w, h, bad=None):
    """``n`` masks of ``w x h`` (a block on the person) in ``folder``; ``bad``: ``{i: (w, h)}``
    masks of another size, or ``{i: None}`` a file that is not an image."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        size = (bad or {}).get(i, (w, h))
        if size is None:
            (folder / f"{i:06d}.png").write_text("not an image")
            continue
        m = np.zeros((size[1], size[0]), np.uint8)
        m[size[1] // 4: 3 * size[1] // 4, size[0] // 3: 2 * size[0] // 3] = 255
        cv2.imwrite(str(folder / f"{i:06d}.png"), m)
    return folder


def test_masks_at_the_videos_own_size_are_scaled_with_its_frames(tmp_path):
    """With frames scaled by max_side (--max-size) the user's masks may have the video's
    own size (as load_video's docstring promises): they are scaled like the frames, as a
    plain folder's are; masks at the scaled size still work."""
    v = write_video(tmp_path / "big.mp4", _frames(3, w=160, h=96))
    full = _write_masks(tmp_path / "full", 3, 160, 96)
    seq = load_video(v, masks=full, max_side=80)
    assert seq.size == (80, 48) and seq.source_size == (160, 96)
    m = seq.mask(2)
    assert m.shape == (48, 80) and m[24, 40] and not m[2, 2]
    small = _write_masks(tmp_path / "small", 3, 80, 48)
    np.testing.assert_array_equal(load_video(v, masks=small, max_side=80).mask(2), m)
    assert load_video(v, masks=_write_masks(tmp_path / "same", 3, 160, 96)).source_size is None  # not scaled


def test_every_video_mask_is_checked_before_any_work(tmp_path):
    """A mask of another size, or a file that is not an image, late in the folder is
    refused when the video is opened (before tracking), naming the file."""
    v = write_video(tmp_path / "a.mp4", _frames(4))
    with pytest.raises(DataError, match="000003.png is 20x20 but"):
        load_video(v, masks=_write_masks(tmp_path / "size", 4, 64, 48, bad={3: (20, 20)}))
    with pytest.raises(DataError, match="000002.png"):
        load_video(v, masks=_write_masks(tmp_path / "text", 4, 64, 48, bad={2: None}))


def test_a_negative_or_tiny_max_size_is_refused(tmp_path):
    """max_side < 0 (--max-size -5) used to shrink the frames to 1x1, and 1-8 to a few pixels
    where "no person found" hid the cause; each is an InputError in the loaders and in
    flowmocap.track, before anything is written. 0 keeps the size; 64 is the least."""
    from flowmocap.io.sequence import MIN_MAX_SIDE, load_sequence
    from flowmocap.pipeline import track

    v = write_video(tmp_path / "a.mp4", _frames(2))
    with pytest.raises(InputError, match=r"--max-size must be 0 \(keep the video's size\) or at least 64 px"):
        load_video(v, max_side=-5)
    with pytest.raises(InputError, match="--max-size must be 0"):
        load_sequence(tmp_path, max_side=-1)
    for tiny in (1, 8, MIN_MAX_SIDE - 1):
        with pytest.raises(InputError, match="too few pixels"):
            load_video(v, max_side=tiny)
    with pytest.raises(InputError, match="--max-size must be 0"):
        track(v, tmp_path / "out", max_size=-5, log=None, progress=False)
    with pytest.raises(InputError, match="--max-size must be 0"):
        track(v, tmp_path / "out", max_size=4, log=None, progress=False)
    assert not (tmp_path / "out").exists()
    assert load_video(v, max_side=0).size == (64, 48)
    assert load_video(v, max_side=MIN_MAX_SIDE).size == (64, 48)


def test_an_init_in_the_videos_own_pixels_says_the_frames_are_scaled(tmp_path):
    """An init.json whose joints lie outside the scaled frames (given in the video's own
    pixels) is refused with a hint on --max-size."""
    from flowmocap.body.skeleton import JOINT_NAMES
    from flowmocap.pipeline import track

    v = write_video(tmp_path / "big.mp4", _frames(3, w=160, h=96))
    masks = _write_masks(tmp_path / "m", 3, 160, 96)
    init = {"frame": 0, "joints2d": {n: [100.0 + (i % 5) * 10, 10.0 + 3 * i] for i, n in enumerate(JOINT_NAMES)}}
    with pytest.raises(InputError, match=r"outside the 80x48 image \(frames scaled by --max-size; pass --max-size 0 "
                                         r"to keep the video's size\)$"):
        track(v, tmp_path / "out", init=init, masks=masks, max_size=80, joints3d="off", log=None, progress=False)


def test_a_mirrored_video_is_said_and_a_result_tracked_otherwise_is_noted(tmp_path):
    from flowmocap.io.results import decoded_otherwise_words
    from flowmocap.pipeline import track

    v = write_video(tmp_path / "plain.mp4", _frames(3))
    mirrored = _rotate_tag(v, tmp_path / "mirrored.mp4", (-0x10000, 0, 0, 0, 0x10000, 0, 0, 0, 0x40000000))
    masks = tmp_path / "masks"
    masks.mkdir()
    import cv2

    for i in range(3):
        cv2.imwrite(str(masks / f"{i:06d}.png"), np.zeros((48, 64), np.uint8))
    said = []
    with pytest.raises(NoPersonError):  # empty masks are refused after the note
        track(mirrored, tmp_path / "r", masks=masks, log=said.append, progress=False)
    assert any("is shown mirrored" in m and "left and right are swapped" in m for m in said), said
    # a result an older flowmocap tracked on the unmirrored frames: render and view say so
    meta = load_video(mirrored).meta
    old_run = {"video": {"rotation": -180}}
    assert "tracked on frames shown unmirrored" in decoded_otherwise_words(old_run, meta, mirrored)
    assert decoded_otherwise_words({"video": {"mirrored": True, "sample_aspect_ratio": 1.0}}, meta, mirrored) is None
    assert decoded_otherwise_words({}, meta, mirrored) is None  # a folder of frames' result
