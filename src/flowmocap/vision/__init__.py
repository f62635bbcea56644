"""Image-side inputs of the tracker: observed optical flow and person masks.

Public API: :func:`observed_flow` (backward flow ``F_o(i, i-1)``, OpenCV DIS by
default), :data:`FLOW_METHODS`, :class:`FlowCache`, :func:`flow_region`; :func:`load_mask`,
:func:`chamfer_map`, :func:`mask_iou`.
"""

from flowmocap.vision.flow import DIS_PRESETS, FLOW_METHODS, FlowCache, flow_region, observed_flow
from flowmocap.vision.masks import chamfer_map, load_mask, mask_iou

__all__ = ["observed_flow", "flow_region", "FLOW_METHODS", "DIS_PRESETS", "FlowCache", "chamfer_map", "load_mask",
           "mask_iou"]
