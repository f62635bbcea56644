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
from flowmocap.version import __version__

#: Imported on first use (PEP 562), so that ``import flowmocap.vision...`` in a helper
#: process (the person detector's, :mod:`flowmocap.vision.detect_worker`) does not load
#: the tracker and torch.
_LAZY = {"track": "flowmocap.pipeline", "load_result": "flowmocap.pipeline", "Result": "flowmocap.pipeline"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'flowmocap' has no attribute {name!r}")


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
