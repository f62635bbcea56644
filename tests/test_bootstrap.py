"""The circular block bootstrap of a ratio of mean errors (flowmocap.eval.bootstrap), and
its use in the real3d table."""

import numpy as np
import pytest

from flowmocap.errors import InputError
from flowmocap.eval.bootstrap import circular_block_indices, ratio_interval


def test_indices_are_blocks_of_consecutive_frames_wrapping_round():
    rng = np.random.default_rng(1)
    for n, block in ((10, 3), (7, 7), (5, 9), (1, 1), (60, 15)):
        i = circular_block_indices(n, block, rng)
        assert i.shape == (n,) and i.min() >= 0 and i.max() < n
        b = min(block, n)
        for start in range(0, n, b):  # within each block the next index is the previous one plus 1, modulo n
            part = i[start:start + b]
            assert np.array_equal(np.diff(part) % n, np.ones(len(part) - 1, int))


def test_every_frame_is_equally_likely_so_the_resampled_mean_is_unbiased():
    # a curve with a trend: the plain moving-block bootstrap draws the ends less often and
    # its mean would be biased towards the middle; the circular one is not
    rng = np.random.default_rng(2)
    n, block, draws = 20, 6, 40000
    counts = np.zeros(n)
    for _ in range(draws):
        counts += np.bincount(circular_block_indices(n, block, rng), minlength=n)
    share = counts / counts.sum()
    assert np.abs(share - 1 / n).max() < 0.002  # each frame 1/20 of the draws, to sampling noise
    curve = np.arange(n, dtype=float) ** 2
    got = ratio_interval([curve], [np.ones(n)], block=block, draws=4000, seed=3)
    assert got["clips"][0]["ratio"] == pytest.approx(curve.mean())
    assert got["clips"][0]["low"] < curve.mean() < got["clips"][0]["high"]


def test_block_of_one_frame_matches_the_iid_standard_error():
    rng = np.random.default_rng(4)
    n = 400
    pred = rng.normal(10.0, 2.0, n)
    got = ratio_interval([pred], [np.full(n, 10.0)], block=1, draws=4000, level=0.95, seed=5)
    half = (got["clips"][0]["high"] - got["clips"][0]["low"]) / 2
    expected = 1.96 * pred.std() / np.sqrt(n) / 10.0  # the ratio's standard error over the constant base
    assert half == pytest.approx(expected, rel=0.1)


def test_closed_forms_of_the_ratio():
    rng = np.random.default_rng(6)
    a = [rng.uniform(20, 80, 50), rng.uniform(40, 90, 30)]
    same = ratio_interval(a, a, block=5, draws=200)
    for r in [*same["clips"], same["suite"]]:
        assert r["ratio"] == pytest.approx(1.0) and r["low"] == pytest.approx(1.0) and r["high"] == pytest.approx(1.0)
        assert r["p_above_1"] == 0.0
    half = ratio_interval(a, [2 * x for x in a], block=5, draws=200)  # paired draws: exactly 0.5 every time
    for r in [*half["clips"], half["suite"]]:
        assert r["low"] == pytest.approx(0.5) and r["high"] == pytest.approx(0.5)
    worse = ratio_interval([x + 100 for x in a], a, block=5, draws=200)
    assert worse["suite"]["p_above_1"] == 1.0 and worse["suite"]["low"] > 1.0


def test_the_suite_weighs_each_clip_alike():
    got = ratio_interval([np.full(10, 1.0), np.full(1000, 3.0)], [np.full(10, 2.0), np.full(1000, 2.0)], block=4,
                         draws=50)
    assert got["suite"]["ratio"] == pytest.approx((1 + 3) / (2 + 2))
    assert [c["ratio"] for c in got["clips"]] == pytest.approx([0.5, 1.5])


def test_reproducible_with_the_seed():
    rng = np.random.default_rng(7)
    a, b = [rng.uniform(1, 2, 40)], [rng.uniform(1, 2, 40)]
    assert ratio_interval(a, b, seed=9, draws=300) == ratio_interval(a, b, seed=9, draws=300)


@pytest.mark.parametrize("pred, base, kw", [
    ([], [], {}),
    ([np.ones(3)], [np.ones(4)], {}),
    ([np.ones(3)], [np.ones(3), np.ones(3)], {}),
    ([np.array([1.0, np.nan])], [np.ones(2)], {}),
    ([np.ones(3)], [np.ones(3)], {"level": 1.0}),
    ([np.ones(3)], [np.ones(3)], {"draws": 0}),
    ([np.ones(3)], [np.ones(3)], {"block": 0}),
    ([np.ones(3)], [np.array([1.0, 0.0, 1.0])], {}),
    ([np.array([1.0, -1.0, 1.0])], [np.ones(3)], {}),
])
def test_bad_input_is_refused(pred, base, kw):
    with pytest.raises(InputError):
        ratio_interval(pred, base, **kw)


def _row(person, view, ours, det, kp=None):
    row = {"person": person, "view": view, "frames_scored": len(ours),
           "flowmocap": {"per_frame_mm": float(np.mean(ours)), "per_sequence_mm": 1.0, "per_frame_all_views_mm": 1.0,
                         "per_sequence_all_views_mm": 1.0, "per_frame_curve_mm": list(ours)},
           "detector3d": {"per_frame_mm": float(np.mean(det)), "per_sequence_mm": 1.0, "per_frame_all_views_mm": 1.0,
                          "per_sequence_all_views_mm": 1.0, "per_frame_curve_mm": list(det)},
           "flowmocap_kp": None}
    if kp is not None:
        row["flowmocap_kp"] = {**row["flowmocap"], "per_frame_mm": float(np.mean(kp)), "per_frame_curve_mm": list(kp)}
    return row


def test_real3d_mean_and_table_carry_the_intervals():
    from flowmocap.eval.real3d import _interval_lines, _mean_rows, ratio_intervals

    rng = np.random.default_rng(8)
    rows = [_row("person1", "cam01", rng.uniform(50, 70, 40), rng.uniform(70, 90, 40), kp=rng.uniform(45, 65, 40)),
            _row("person2", "cam04", rng.uniform(60, 80, 30), rng.uniform(50, 60, 30), kp=rng.uniform(55, 75, 30))]
    iv = ratio_intervals(rows, block=5, draws=300)
    assert iv["flowmocap"]["person_views"] == ["person1@cam01", "person2@cam04"]
    s = iv["flowmocap"]["suite"]
    ours = np.mean([np.mean(r["flowmocap"]["per_frame_curve_mm"]) for r in rows])
    det = np.mean([np.mean(r["detector3d"]["per_frame_curve_mm"]) for r in rows])
    assert s["ratio"] == pytest.approx(ours / det) and s["low"] < s["ratio"] < s["high"]
    assert iv["flowmocap"]["clips"][1]["p_above_1"] == 1.0  # person2: ours 60-80 against 50-60 in every frame
    assert _mean_rows(rows)["intervals"]["flowmocap_kp"]["suite"]["ratio"] == pytest.approx(
        np.mean([np.mean(r["flowmocap_kp"]["per_frame_curve_mm"]) for r in rows]) / det)
    text = "\n".join(_interval_lines(iv))
    assert "ours / det: mean" in text and "person2@cam04" in text and "person1@cam01" not in text
    # rows without the fit at the keypoints: that method has no interval, the table says nothing of it
    no_kp = [_row("person1", "cam01", np.full(10, 50.0), np.full(10, 60.0))]
    got = ratio_intervals(no_kp, block=3, draws=20)
    assert got["flowmocap_kp"] is None
    assert "no person-view's interval reaches above 1" in "\n".join(_interval_lines(got))
    assert _interval_lines({"flowmocap": None, "flowmocap_kp": None}) == []


def test_real3d_mean_and_table_carry_the_joints():
    from flowmocap.eval.real3d import EVAL_NAMES, _joint_lines, _mean_rows

    rows = [_row("person1", "cam01", np.full(10, 50.0), np.full(10, 60.0)),
            _row("person2", "cam04", np.full(10, 70.0), np.full(10, 80.0))]
    rows[0]["flowmocap"]["per_joint_mm"] = [40.0] * 12 + [None]  # the right ankle never scored here
    rows[1]["flowmocap"]["per_joint_mm"] = [60.0] * 12 + [90.0]
    m = _mean_rows(rows)
    assert m["flowmocap"]["per_joint_mm"] == [50.0] * 12 + [90.0]  # each joint over the views that score it
    assert "per_joint_mm" not in m["detector3d"]  # rows without them: none in the mean
    text = "\n".join(_joint_lines(m))
    assert "| flowmocap | 50.0 |" in text and "right ankle" in text and "detector3d" not in text
    assert len(EVAL_NAMES) == 13 and _joint_lines({"flowmocap": {"per_frame_mm": 1.0}}) == []
