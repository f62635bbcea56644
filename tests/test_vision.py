"""Observed optical flow, its cache, person masks and chamfer maps (flowmocap.vision)."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from flowmocap.errors import DataError, InputError, NoPersonError
from flowmocap.vision import FLOW_METHODS, FlowCache, chamfer_map, flow_region, load_mask, observed_flow
from flowmocap.vision.flow import MIN_REGION

DAVIS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "video" / "davis-dance-twirl"


def _shifted_pair(H, W, dx, dy, seed=0):
    """A smooth random texture (frame i-1) and the same texture moved by (dx, dy) px (frame i)."""
    rng = np.random.default_rng(seed)
    pad = 24
    base = cv2.GaussianBlur(rng.random((H + 2 * pad, W + 2 * pad, 3)).astype(np.float32), (0, 0), 2.0)
    base = (255 * (base - base.min()) / (base.max() - base.min())).astype(np.uint8)
    M = np.float32([[1, 0, dx], [0, 1, dy]])  # content moves by +(dx, dy)
    moved = cv2.warpAffine(base, M, base.shape[1::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    crop = (slice(pad, pad + H), slice(pad, pad + W))
    return moved[crop].copy(), base[crop].copy()


def test_dis_recovers_a_subpixel_translation_as_backward_flow():
    dx, dy = 2.3, -1.7
    cur, prev = _shifted_pair(240, 320, dx, dy)
    flow = observed_flow(cur, prev)
    assert flow.shape == (240, 320, 2) and flow.dtype == np.float32
    inner = flow[24:-24, 24:-24]
    # backward: a point of frame i is found at p - (dx, dy) in frame i-1
    epe = np.linalg.norm(inner - np.array([-dx, -dy]), axis=-1)
    assert epe.mean() < 0.3
    assert np.percentile(epe, 95) < 0.5
    # the forward direction would be the opposite sign
    np.testing.assert_allclose(inner.reshape(-1, 2).mean(0), [-dx, -dy], atol=0.15)


@pytest.mark.parametrize("method", sorted(FLOW_METHODS))
def test_every_method_gives_backward_flow(method):
    dx, dy = 1.5, 1.0
    cur, prev = _shifted_pair(64, 96, dx, dy, seed=1)
    flow = observed_flow(cur, prev, method)
    assert flow.shape == (64, 96, 2) and flow.dtype == np.float32
    med = np.median(flow[16:-16, 16:-16].reshape(-1, 2), axis=0)
    np.testing.assert_allclose(med, [-dx, -dy], atol=0.5)


def test_dis_presets_and_options():
    cur, prev = _shifted_pair(64, 96, 1.0, 0.0)
    for preset in ("ultrafast", "fast", "medium"):
        assert observed_flow(cur, prev, "dis", preset=preset).shape == (64, 96, 2)
    assert observed_flow(cur, prev, "dis", FinestScale=1).shape == (64, 96, 2)
    with pytest.raises(InputError, match="preset"):
        observed_flow(cur, prev, "dis", preset="slowest")
    with pytest.raises(InputError, match="parameter"):
        observed_flow(cur, prev, "dis", Colour=3)


def test_flow_input_errors():
    cur, prev = _shifted_pair(64, 96, 1.0, 0.0)
    with pytest.raises(InputError, match="dis, dis-fine, deepflow, tvl1, rlof, farneback"):
        observed_flow(cur, prev, "mdp")
    with pytest.raises(InputError, match="same size"):
        observed_flow(cur, prev[:-2])
    with pytest.raises(InputError, match="uint8"):
        observed_flow(cur.astype(np.float32), prev)
    with pytest.raises(InputError, match="RGB"):
        observed_flow(cur[..., 0], prev[..., 0])


def test_flow_cache_stores_returns_and_survives_bad_files(tmp_path, monkeypatch):
    cur, prev = _shifted_pair(48, 64, 1.0, 0.5)
    cache = FlowCache(tmp_path / "flow")
    assert 7 not in cache and cache.get(7) is None
    calls = []
    real = FLOW_METHODS["dis"]
    monkeypatch.setitem(FLOW_METHODS, "dis", lambda *a, **k: calls.append(1) or real(*a, **k))
    f1 = cache.flow(7, cur, prev)
    f2 = cache.flow(7, cur, prev)
    assert len(calls) == 1 and 7 in cache
    np.testing.assert_array_equal(f1, f2)
    assert cache.path(7).name == "flow_000007_dis.npz"
    assert sorted(os.listdir(tmp_path / "flow")) == ["flow_000007_dis.npz"]  # no temp files left
    # another cache on the same folder (a resumed run) finds it; other settings do not
    np.testing.assert_array_equal(FlowCache(tmp_path / "flow").get(7), f1)
    other = FlowCache(tmp_path / "flow", "dis", preset="fast")
    assert other.get(7) is None and other.path(7) != cache.path(7)
    assert FlowCache(tmp_path / "flow", "farneback").get(7) is None
    # a wrong size or a truncated file counts as missing and is recomputed
    assert cache.get(7, shape=(10, 10)) is None
    cache.path(7).write_bytes(cache.path(7).read_bytes()[:100])
    assert cache.get(7) is None
    np.testing.assert_array_equal(cache.flow(7, cur, prev), f1)
    assert len(calls) == 2
    with pytest.raises(InputError):
        cache.put(8, np.zeros((4, 4, 3)))
    with pytest.raises(InputError):
        FlowCache(tmp_path / "x", "mdp")


def test_flow_region_is_the_masks_box_with_a_margin_clipped_to_the_image():
    H, W = 200, 300
    a, b = np.zeros((H, W), bool), np.zeros((H, W), bool)
    a[50:90, 100:120] = True  # 40 x 20
    b[60:100, 110:130] = True  # the next frame's person, moved
    grow = int(16 + 0.15 * 50)  # the union is 50 rows x 30 columns
    assert flow_region([a, b]) == (50 - grow, 100 + grow, 100 - grow, 130 + grow)
    r0, r1, c0, c1 = flow_region([a, None], margin_px=0, margin_frac=0.0)  # grown to MIN_REGION about its middle
    assert (r1 - r0, c1 - c0) == (MIN_REGION, MIN_REGION) and (r0 + r1) // 2 == 70 and (c0 + c1) // 2 == 110
    corner = np.zeros((H, W), bool)
    corner[0:3, W - 3:] = True  # against two edges: clipped, still MIN_REGION on a side
    assert flow_region([corner], margin_px=0, margin_frac=0.0) == (0, MIN_REGION, W - MIN_REGION, W)
    big = np.ones((H, W), bool)
    assert flow_region([big]) == (0, H, 0, W)
    tiny = np.zeros((40, 50), bool)
    tiny[5, 5] = True  # an image smaller than MIN_REGION: the whole image
    assert flow_region([tiny]) == (0, 40, 0, 50)
    assert flow_region([np.zeros((H, W), bool), None]) is None and flow_region([]) is None
    with pytest.raises(InputError, match="different sizes"):
        flow_region([a, np.ones((10, 10), bool)])


def test_flow_cache_computes_a_region_only_and_keeps_regions_apart(tmp_path, monkeypatch):
    cur, prev = _shifted_pair(96, 128, 1.5, -0.5, seed=3)
    region = (10, 80, 20, 100)
    cache = FlowCache(tmp_path / "flow")
    calls = []
    real = FLOW_METHODS["dis"]
    monkeypatch.setitem(FLOW_METHODS, "dis", lambda c, p, **k: calls.append(c.shape) or real(c, p, **k))
    f = cache.flow(3, cur, prev, region=region)
    assert calls == [(70, 80, 3)]  # only the region's pixels went to the flow method
    inside = observed_flow(np.ascontiguousarray(cur[10:80, 20:100]), np.ascontiguousarray(prev[10:80, 20:100]))
    np.testing.assert_array_equal(f[10:80, 20:100], inside)
    outside = np.ones((96, 128), bool)
    outside[10:80, 20:100] = False
    assert f.shape == (96, 128, 2) and not f[outside].any()
    np.testing.assert_array_equal(cache.flow(3, cur, prev, region=region), f)  # from the cache
    assert len(calls) == 2  # (the check above called the method once itself)
    assert cache.get(3, region=region) is not None
    assert cache.get(3) is None and cache.get(3, region=(0, 96, 0, 128)) is None  # another region: absent
    whole = cache.flow(3, cur, prev)  # recomputed for the whole frame, and it serves any region after
    assert len(calls) == 3 and cache.get(3, region=region) is not None
    np.testing.assert_array_equal(cache.flow(3, cur, prev, region=region), whole)
    assert len(calls) == 3
    for bad in [(0, 0, 0, 10), (-1, 10, 0, 10), (0, 97, 0, 10), (5, 4, 0, 10)]:
        with pytest.raises(InputError, match="is not a box inside the 128x96 frame"):
            cache.flow(4, cur, prev, region=bad)
    with pytest.raises(InputError, match="same size"):
        cache.flow(4, cur, prev[:-2], region=region)


def test_chamfer_map_is_the_same_every_call_on_several_threads():
    """OpenCV's precise distance transform on 2 threads gave last-bit differences from
    call to call (146 pixels of a 90x120 person mask), which set two tracker runs apart;
    the map is exact and the same every time (against SciPy's exact transform)."""
    import cv2
    from scipy import ndimage

    yy, xx = np.mgrid[:90, :120]
    mask = ((yy - 45) / 35.0) ** 2 + ((xx - 60) / 12.0) ** 2 < 1  # a body-sized blob
    mask[60:85, 50:56] = True
    old = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        maps = {chamfer_map(mask.copy()).tobytes() for _ in range(100)}
    finally:
        cv2.setNumThreads(old)
    assert len(maps) == 1
    exact = ndimage.distance_transform_edt(~mask).astype(np.float32)
    np.testing.assert_array_equal(chamfer_map(mask), exact)


def test_chamfer_map_is_the_euclidean_distance_to_the_mask():
    mask = np.zeros((30, 40), bool)
    mask[10, 12] = True
    mask[20:25, 30:33] = True
    c = chamfer_map(mask)
    assert c.dtype == np.float32 and c.shape == (30, 40)
    yy, xx = np.mgrid[:30, :40]
    pts = np.argwhere(mask)
    ref = np.sqrt((yy[..., None] - pts[:, 0]) ** 2 + (xx[..., None] - pts[:, 1]) ** 2).min(-1)
    np.testing.assert_array_equal(c, ref.astype(np.float32))  # exact: the correctly rounded distance
    assert (c[mask] == 0).all() and (c[~mask] >= 1).all()
    np.testing.assert_array_equal(chamfer_map(np.ones((3, 4), bool)), 0)
    with pytest.raises(NoPersonError, match="empty"):
        chamfer_map(np.zeros((5, 5), bool))
    with pytest.raises(InputError):
        chamfer_map(np.zeros((5, 5, 3), bool))


def test_load_mask_palette_grey_and_colour_images(tmp_path):
    truth = np.zeros((20, 30), bool)
    truth[5:12, 8:20] = True
    # palette image as DAVIS stores it: index 0 background, index 1 the person
    idx = truth.astype(np.uint8)
    pal = Image.fromarray(idx, mode="P")
    pal.putpalette([0, 0, 0, 128, 0, 0] + [0] * (254 * 3))
    pal.save(tmp_path / "p.png")
    Image.fromarray(truth.astype(np.uint8) * 255).save(tmp_path / "l.png")
    rgb = np.zeros((20, 30, 3), np.uint8)
    rgb[truth] = (0, 0, 200)
    Image.fromarray(rgb).save(tmp_path / "rgb.png")
    rgba = np.concatenate([rgb, np.full((20, 30, 1), 255, np.uint8)], -1)
    Image.fromarray(rgba).save(tmp_path / "rgba.png")
    for name in ("p.png", "l.png", "rgb.png", "rgba.png"):
        m = load_mask(tmp_path / name)
        assert m.dtype == bool
        np.testing.assert_array_equal(m, truth)


def test_load_mask_errors(tmp_path):
    with pytest.raises(DataError, match="not found"):
        load_mask(tmp_path / "missing.png")
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(DataError, match="cannot read"):
        load_mask(tmp_path / "junk.png")
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(tmp_path / "empty.png")
    with pytest.raises(NoPersonError, match="empty"):
        load_mask(tmp_path / "empty.png")


@pytest.mark.skipif(not DAVIS.is_dir(), reason="DAVIS clip not available")
def test_load_mask_on_a_davis_annotation():
    m = load_mask(DAVIS / "Annotations" / "00000.png")
    assert m.shape == (480, 854) and 0.01 < m.mean() < 0.5


def test_dis_fine_is_more_accurate_than_dis_on_a_rotating_zooming_texture():
    """Non-uniform motion (rotation + zoom about the centre), known backward flow."""
    rng = np.random.default_rng(4)
    H, W = 240, 320
    prev = cv2.GaussianBlur(rng.random((H, W, 3)).astype(np.float32), (0, 0), 1.0)
    prev = (255 * (prev - prev.min()) / (prev.max() - prev.min())).astype(np.uint8)
    c = np.array([W / 2, H / 2])
    a, s = np.radians(3.0), 1.03
    A = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    # frame i at pixel p shows frame i-1 at q = c + A^-1 (p - c): the backward flow is q - p
    Ai = np.linalg.inv(A)
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32) + 0.5
    p = np.stack([xs, ys], -1)
    q = (p - c) @ Ai.T + c
    cur = cv2.remap(prev, (q[..., 0] - 0.5).astype(np.float32), (q[..., 1] - 0.5).astype(np.float32),
                    cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    truth = q - p
    inner = (slice(30, -30), slice(30, -30))
    epe = {m: np.linalg.norm(observed_flow(cur, prev, m)[inner] - truth[inner], axis=-1).mean()
           for m in ("dis", "dis-fine")}
    assert epe["dis-fine"] < 0.7 * epe["dis"], epe  # measured 0.52-0.55 over three textures


def test_mask_iou_on_squares():
    from flowmocap.vision import mask_iou

    a = np.zeros((2, 10, 10), bool)
    b = np.zeros((2, 10, 10), bool)
    a[0, 0:4, 0:4] = True          # 16 px
    b[0, 2:6, 0:4] = True          # 16 px, overlap 8 -> 8 / 24
    a[1, 0:5, 0:5] = True
    b[1, 0:5, 0:5] = True
    iou = mask_iou(a, b)
    assert iou.shape == (2,) and np.allclose(iou, [8 / 24, 1.0])
    assert mask_iou(a[0], b[0]) == pytest.approx(8 / 24) and isinstance(mask_iou(a[0], b[0]), float)
    assert mask_iou(np.zeros((4, 4)), np.zeros((4, 4))) == 1.0
    assert mask_iou(np.ones((4, 4)), np.zeros((4, 4))) == 0.0
    with pytest.raises(InputError):
        mask_iou(a, b[:, :5])
