"""The Middlebury flow colour coding and its legend."""

from __future__ import annotations

import colorsys

import numpy as np
import pytest
import torch

from flowmocap.errors import InputError
from flowmocap.viz.flow_colors import color_wheel, color_wheel_legend, flow_to_color


def _one(dx, dy, max_magnitude=1.0):
    return flow_to_color(np.array([[[dx, dy]]], dtype=np.float64), max_magnitude)[0, 0]


def _hsv(rgb):
    return colorsys.rgb_to_hsv(*(np.asarray(rgb, dtype=np.float64) / 255.0))


def test_wheel_has_55_colours_in_six_ramps():
    w = color_wheel()
    assert w.shape == (55, 3)
    np.testing.assert_array_equal(w[0], [255, 0, 0])  # red
    np.testing.assert_array_equal(w[15], [255, 255, 0])  # yellow
    np.testing.assert_array_equal(w[21], [0, 255, 0])  # green
    np.testing.assert_array_equal(w[25], [0, 255, 255])  # cyan
    np.testing.assert_array_equal(w[36], [0, 0, 255])  # blue
    np.testing.assert_array_equal(w[49], [255, 0, 255])  # magenta
    assert ((w >= 0) & (w <= 255)).all()


def test_pure_right_flow_is_red():
    c = _one(1.0, 0.0)
    h, s, v = _hsv(c)
    assert min(h, 1.0 - h) < 0.03 and s > 0.95 and v > 0.95
    np.testing.assert_array_equal(c, [255, 0, 0])


def test_directions_follow_the_wheel():
    # down (image y) is yellow-orange, left light blue, up violet
    assert abs(_hsv(_one(0.0, 1.0))[0] - 1 / 6) < 0.05
    assert 0.5 <= _hsv(_one(-1.0, 0.0))[0] <= 0.6
    assert 0.7 <= _hsv(_one(0.0, -1.0))[0] <= 0.8


def test_zero_flow_is_white():
    img = flow_to_color(np.zeros((4, 5, 2)))
    assert img.shape == (4, 5, 3) and img.dtype == np.uint8
    assert (img == 255).all()


def test_saturation_grows_with_magnitude_and_hue_stays():
    angle = 2.1
    sats, hues = [], []
    for m in (0.0, 0.2, 0.5, 0.8, 1.0):
        c = _one(m * np.cos(angle), m * np.sin(angle), max_magnitude=1.0)
        h, s, _ = _hsv(c)
        sats.append(s)
        if m > 0:
            hues.append(h)
    assert np.all(np.diff(sats) > 0)
    assert sats[0] == 0.0 and sats[-1] > 0.95
    assert np.ptp(hues) < 0.02


def test_default_max_magnitude_and_overflow():
    flow = np.zeros((1, 3, 2))
    flow[0, 1] = (2.0, 0.0)
    flow[0, 2] = (4.0, 0.0)
    img = flow_to_color(flow)  # max = 4: the longest vector is fully saturated
    np.testing.assert_array_equal(img[0, 2], [255, 0, 0])
    assert 100 < img[0, 1, 1] < 155  # half saturated
    # beyond max_magnitude: same hue, darkened
    over = flow_to_color(flow, max_magnitude=2.0)[0, 2]
    np.testing.assert_array_equal(over, [191, 0, 0])


def test_torch_input_non_finite_and_errors():
    f = torch.zeros(2, 2, 2)
    f[0, 0, 0] = float("nan")
    img = flow_to_color(f, max_magnitude=1.0)
    np.testing.assert_array_equal(img[0, 0], [0, 0, 0])
    assert (img[1, 1] == 255).all()
    with pytest.raises(InputError):
        flow_to_color(np.zeros((3, 3)))
    with pytest.raises(InputError):
        flow_to_color(np.zeros((3, 3, 2)), max_magnitude=0.0)


@pytest.mark.parametrize("size", [3, 64, 101])
def test_legend_shape(size):
    leg = color_wheel_legend(size)
    assert leg.shape == (size, size, 3) and leg.dtype == np.uint8


def test_legend_content():
    size = 101
    leg = color_wheel_legend(size)
    c = size // 2
    assert (leg[c, c] >= 245).all()  # centre: ~zero flow, white
    assert (leg[0, 0] == 255).all()  # corner: background
    right = leg[c, size - 4].astype(int)  # near the rim on the right: red
    assert right[0] > 200 and right[1] < 60 and right[2] < 60
    down = leg[size - 4, c].astype(int)  # near the rim at the bottom: yellow
    assert down[0] > 200 and down[1] > 180 and down[2] < 60
    with pytest.raises(InputError):
        color_wheel_legend(2)
