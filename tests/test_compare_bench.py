"""benchmarks/compare_bench.py: the per-sequence comparison of two suite runs."""

from pathlib import Path

import numpy as np
import pytest

from conftest import load_script

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "compare_bench.py"


@pytest.fixture(scope="module")
def cb():
    return load_script(SCRIPT)


def _table(a_local, b_local, a_global, b_global):
    return [{"sequence": f"s{i}", "kind": "", "a_local": al, "b_local": bl, "a_global": ag, "b_global": bg}
            for i, (al, bl, ag, bg) in enumerate(zip(a_local, b_local, a_global, b_global))]


def test_paired_counts_moves_beyond_chance_only(cb):
    a = [5.0] * 8
    b_local = [5.0, 5.3, 4.7, 4.5, 5.5, 5.41, 4.0, 5.0]  # -0.5, -1.0 better; +0.5, +0.41 worse; rest within
    t = _table(a, b_local, a, a)
    p = cb.paired(t, chance_cm=0.4)
    assert (p["local"]["better"], p["local"]["worse"]) == (2, 2)
    assert p["local"]["median_difference_cm"] == pytest.approx(np.median(np.subtract(b_local, a)))
    assert p["global"] == {"better": 0, "worse": 0, "median_difference_cm": 0.0, "wilcoxon_p": None}


def test_paired_signed_rank_p(cb):
    rng = np.random.default_rng(0)
    a = rng.uniform(4, 9, 16)
    sym = np.repeat(np.arange(1, 9) / 4, 2) * np.tile([1, -1], 8)  # each move matched by its opposite
    t = _table(a, a - 1.0 - rng.uniform(0, 0.1, 16), a, a + sym)
    p = cb.paired(t)
    # every sequence better by about 1 cm: the exact two-sided p of 16 positive ranks is 2 / 2^16
    assert p["local"]["better"] == 16 and p["local"]["wilcoxon_p"] == pytest.approx(2 / 2 ** 16)
    assert p["global"]["wilcoxon_p"] == pytest.approx(1.0)
    assert (p["global"]["better"], p["global"]["worse"]) == (7, 7)  # 0.5 .. 2 cm each way; 0.25 within
