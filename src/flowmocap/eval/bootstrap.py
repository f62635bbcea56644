"""How much a benchmark's ratio of mean errors owes to which frames were scored.

A per-frame error curve is correlated in time: a fit that goes wrong stays wrong for a
stretch of frames. So the frames of one clip are not independent draws, and an ordinary
bootstrap over them would claim too narrow an interval. The circular block bootstrap
(Politis and Romano, 1992) resamples whole stretches of ``block`` consecutive frames, each
starting at a uniformly drawn frame and wrapping round the clip's end. Wrapping keeps every
frame equally likely in every position, so the resampled mean is unbiased, which the
plain moving-block bootstrap is not at the clip's ends.

What such an interval holds: the chance of which stretches of motion a clip happens to
contain, given the tracking. What it does not hold: the tracker's own chaos (another
tracking of the same video moves single runs too; docs/experiments.md, "How much real3d
moves by chance"), nor any error of the reference the curves are scored against.

The index arithmetic is written here rather than taken from ``arch.bootstrap`` (which has
the same resampler), so that the package does not need pandas and statsmodels for it.
"""

from __future__ import annotations

import numpy as np

from flowmocap.errors import InputError

__all__ = ["circular_block_indices", "ratio_interval"]


def circular_block_indices(n: int, block: int, rng: np.random.Generator) -> np.ndarray:
    """One circular block bootstrap draw of ``n`` frame indices.

    Args:
        n: frames in the clip (>= 1).
        block: frames per block (>= 1); a block longer than the clip is cut to it.
        rng: the random generator.

    Returns:
        ``(n,)`` int indices in ``[0, n)``: ``ceil(n / block)`` blocks of consecutive
        frames (modulo ``n``), each from a uniform start, cut to ``n`` in all.
    """
    if n < 1 or block < 1:
        raise InputError(f"need n >= 1 frames and a block of >= 1 frames; got n={n!r}, block={block!r}.")
    block = min(int(block), int(n))
    starts = rng.integers(0, n, size=-(-n // block))
    return ((starts[:, None] + np.arange(block)[None, :]) % n).reshape(-1)[:n]


def ratio_interval(pred: list, base: list, block: int = 15, draws: int = 2000, level: float = 0.95,
                   seed: int = 0) -> dict:
    """The ratio of mean errors, ``mean_c(mean_t pred_c) / mean_c(mean_t base_c)``, with a
    circular block bootstrap interval, for each clip alone and for the suite.

    Both methods are scored on the same frames of each clip, so each draw resamples the
    same frames of ``pred_c`` and ``base_c`` (paired); the clips are resampled
    independently of each other, and the suite's mean is over the clips as drawn (each
    clip weighs alike, as the benchmarks' means do).

    Args:
        pred, base: lists of ``(T_c,)`` per-frame errors of the same clips in the same
            order (any unit; equal lengths per clip, ``T_c >= 1``, finite; ``pred >= 0``,
            ``base > 0``).
        block: frames per resampled block (at 60 fps the default is a quarter of a second).
        draws: bootstrap draws; level: the central interval's coverage, in (0, 1).
        seed: the generator's seed (the result is reproducible).

    Returns:
        ``{"block": block, "draws": draws, "level": level, "clips": [{"ratio", "low",
        "high", "p_above_1"}, ...], "suite": {"ratio", "low", "high", "p_above_1"}}``:
        ``ratio`` the ratio of the data as scored, ``low`` / ``high`` the percentile
        interval of the draws' ratios, ``p_above_1`` the share of draws in which
        ``pred`` comes out worse than ``base`` (ratio above 1).
    """
    if len(pred) != len(base) or not pred:
        raise InputError(f"pred and base must be lists of the same clips (at least one); got {len(pred)} and {len(base)}.")
    if not 0 < level < 1 or draws < 1:
        raise InputError(f"need 0 < level < 1 and draws >= 1; got level={level!r}, draws={draws!r}.")
    p = [np.asarray(x, np.float64).reshape(-1) for x in pred]
    b = [np.asarray(x, np.float64).reshape(-1) for x in base]
    for k, (x, y) in enumerate(zip(p, b)):
        if x.shape != y.shape or x.size == 0 or not (np.isfinite(x).all() and np.isfinite(y).all()):
            raise InputError(f"clip {k}: pred and base must be finite per-frame errors of the same frames; got "
                             f"{x.size} and {y.size} frames.")
        if (x < 0).any() or (y <= 0).any():
            raise InputError(f"clip {k}: errors must be >= 0, and base's > 0 (it divides); got pred from {x.min()!r}, "
                             f"base from {y.min()!r}.")
    rng = np.random.default_rng(seed)
    means = np.empty((draws, len(p), 2))
    for d in range(draws):
        for c, (x, y) in enumerate(zip(p, b)):
            i = circular_block_indices(x.size, block, rng)
            means[d, c] = x[i].mean(), y[i].mean()
    q = ((1 - level) / 2, (1 + level) / 2)

    def summary(ratio: float, drawn: np.ndarray) -> dict:
        low, high = np.quantile(drawn, q)
        return {"ratio": float(ratio), "low": float(low), "high": float(high), "p_above_1": float(np.mean(drawn > 1))}

    clips = [summary(x.mean() / y.mean(), means[:, c, 0] / means[:, c, 1]) for c, (x, y) in enumerate(zip(p, b))]
    suite = summary(np.mean([x.mean() for x in p]) / np.mean([y.mean() for y in b]),
                    means[:, :, 0].mean(1) / means[:, :, 1].mean(1))
    return {"block": int(block), "draws": int(draws), "level": float(level), "clips": clips, "suite": suite}
