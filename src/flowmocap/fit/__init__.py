"""Fitting: energy terms and joint limits (:mod:`energies`, :mod:`joint_limits`), the
per-frame objective (:mod:`objective`), the optimiser (:mod:`lbfgs`), Kalman filters
(:mod:`kalman`), initialisation (:mod:`init`), per-frame tracking (:mod:`tracker`) and
re-initialisation (:mod:`reinit`). Module order: config, energies, objective, lbfgs,
kalman, init, tracker, reinit; reading inputs and writing results is
:mod:`flowmocap.pipeline`'s.

Every energy has a residual form (``*_residuals -> (B, M)``) and an energy form
(``*_energy -> (B,)``, the sum of squared residuals); see :mod:`flowmocap.fit.energies`.
"""

from flowmocap.fit.energies import (
    SilhouetteTarget,
    capsule_signed_distance,
    interpenetration_energy,
    interpenetration_pairs,
    interpenetration_residuals,
    joint_limit_energy,
    joint_limit_residuals,
    keypoint_energy,
    keypoint_residuals,
    pose_prior_energy,
    pose_prior_residuals,
    segment_segment_distance,
    shape_prior_energy,
    shape_prior_residuals,
    silhouette_energy,
    silhouette_residuals,
    silhouette_target,
    temporal_energy,
    temporal_residuals,
)
from flowmocap.fit.joint_limits import JointLimits, default_joint_limits, joint_angles

__all__ = [
    "joint_limit_residuals",
    "joint_limit_energy",
    "JointLimits",
    "default_joint_limits",
    "joint_angles",
    "interpenetration_pairs",
    "interpenetration_residuals",
    "interpenetration_energy",
    "segment_segment_distance",
    "SilhouetteTarget",
    "silhouette_target",
    "capsule_signed_distance",
    "silhouette_residuals",
    "silhouette_energy",
    "keypoint_residuals",
    "keypoint_energy",
    "pose_prior_residuals",
    "pose_prior_energy",
    "shape_prior_residuals",
    "shape_prior_energy",
    "temporal_residuals",
    "temporal_energy",
]
