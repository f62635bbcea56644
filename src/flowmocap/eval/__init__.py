"""Evaluation: the paper's 3D joint metrics (more metrics, baseline and bench later)."""

from flowmocap.eval.metrics import global_procrustes_error, local_procrustes_error, mpjpe

__all__ = ["local_procrustes_error", "global_procrustes_error", "mpjpe"]
