"""flowmocap: 3D human motion and shape from monocular video via optical flow.

    import flowmocap
    result = flowmocap.track("video.mp4", out="result/")   # automatic masks, joints, init, camera
    result.poses, result.trans, result.joints3d             # (T, 72) rad, (T, 3) m, (T, 24, 3) m
    same = flowmocap.load_result("result/")

Layers (a layer imports only from layers above it): geometry, body, render, vision, fit,
io, export, synth, pipeline, eval, viz, commands, cli. See the README and docs/.
"""

from flowmocap.errors import (
    DataError,
    FlowMocapError,
    InputError,
    ModelFileError,
    NoPersonError,
    OptimizationError,
)
from flowmocap.pipeline import Result, load_result, track
from flowmocap.version import __version__

__all__ = [
    "__version__",
    "track",
    "load_result",
    "Result",
    "FlowMocapError",
    "InputError",
    "ModelFileError",
    "DataError",
    "NoPersonError",
    "OptimizationError",
]
