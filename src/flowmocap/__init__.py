"""flowmocap: 3D human motion and shape from monocular video via optical flow.

Layers (a layer imports only from layers above it): geometry, body, render, vision,
fit, io, synth, eval, viz, cli. See DESIGN.md in the shared folder and the README.
"""

from flowmocap.errors import (
    DataError,
    FlowMocapError,
    InputError,
    ModelFileError,
    NoPersonError,
    OptimizationError,
)

__version__ = "0.1.0"

__all__ = [
    "__version__",
    "FlowMocapError",
    "InputError",
    "ModelFileError",
    "DataError",
    "NoPersonError",
    "OptimizationError",
]
