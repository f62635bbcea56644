"""Synthetic sequences with ground truth: a textured, lit body moving as real mocap (or
the built-in walk) over a textured static scene, with exact masks, 3D/2D joints and the
true optical flow.

Public API: :func:`synthesize` (the ``flowmocap synth`` command), :class:`SynthResult`,
and the scene pieces :func:`place_camera`, :func:`render_background`,
:class:`ClothingPattern`. :class:`flowmocap.synth.carried.CarriedCamera` gives the frames of a
camera carried over a textured floor, with the truth (for the camera's motion).
"""

from flowmocap.synth.scene import ClothingPattern, place_camera, render_background
from flowmocap.synth.sequence import SynthResult, parse_betas, parse_size, read_camera_json, synthesize

__all__ = [
    "synthesize",
    "SynthResult",
    "parse_betas",
    "parse_size",
    "read_camera_json",
    "place_camera",
    "render_background",
    "ClothingPattern",
]
