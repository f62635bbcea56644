"""Evaluation: the paper's metrics (:mod:`.metrics`), scoring a result folder
(:mod:`.scoring`), the per-frame keypoint baseline (:mod:`.baseline`), the benchmark
suites behind ``flowmocap bench`` (:mod:`.bench`) and the demo (:mod:`.demo`)."""

from flowmocap.eval.metrics import (
    acceleration_error,
    global_procrustes_error,
    joint2d_error,
    local_procrustes_error,
    mpjpe,
)

__all__ = ["local_procrustes_error", "global_procrustes_error", "mpjpe", "acceleration_error",
           "joint2d_error"]
