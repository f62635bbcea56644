"""The body model: SMPL-format linear blend skinning in torch, model files, capsules.

Public API: :func:`load_body_model`, :class:`BodyModel`, :class:`BodyOutput`,
:func:`body_capsules`, and the kinematic tree in :mod:`flowmocap.body.skeleton`.
"""

from flowmocap.body.capsules import CAPSULE_NAMES, Capsules, body_capsules
from flowmocap.body.files import load_body_model, read_model_arrays
from flowmocap.body.model import BodyModel, BodyOutput, ModelArrays
from flowmocap.body.skeleton import EVAL_JOINTS, JOINT_INDEX, JOINT_NAMES, NUM_JOINTS, PARENTS

__all__ = [
    "load_body_model",
    "read_model_arrays",
    "BodyModel",
    "BodyOutput",
    "ModelArrays",
    "body_capsules",
    "Capsules",
    "CAPSULE_NAMES",
    "JOINT_NAMES",
    "JOINT_INDEX",
    "PARENTS",
    "NUM_JOINTS",
    "EVAL_JOINTS",
]
