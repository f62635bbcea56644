"""The renderer: a few small composable ops on already-projected vertices.

``rasterize -> interpolate -> shade`` for colour images; ``rasterize -> render_flow``
and ``flow_loss`` / ``flow_residuals`` for the differentiable flow renderer of the
paper (Sec. 3.2-3.3); ``body_mask`` (a posed body's pixels), ``silhouette`` and
``capsule_signed_distance`` for the silhouette coverage term (Sec. 3.5).

Inputs are projected vertices ``verts_px (V, 2)`` in pixels (pixel centres at integer
+ 0.5; the image spans ``[0, W] x [0, H]``), camera-space ``depth (V,)`` in metres and
``faces (F, 3)``; the ops know nothing of the body model or the camera.
"""

from flowmocap.render._checks import Faces, prepare_faces
from flowmocap.render.capsules import capsule_signed_distance, project_capsules
from flowmocap.render.flow import (
    FlowResiduals,
    FlowTarget,
    flow_loss,
    flow_loss_async,
    flow_residuals,
    flow_target,
    render_flow,
)
from flowmocap.render.interpolate import interpolate
from flowmocap.render.pyramid import pyr_down
from flowmocap.render.raster import Raster, body_mask, rasterize, silhouette
from flowmocap.render.shade import (
    face_normals,
    procedural_pattern,
    shade,
    value_noise,
    vertex_normals,
)

__all__ = [
    "Faces",
    "prepare_faces",
    "Raster",
    "rasterize",
    "silhouette",
    "body_mask",
    "interpolate",
    "render_flow",
    "flow_target",
    "FlowTarget",
    "flow_loss",
    "flow_loss_async",
    "flow_residuals",
    "FlowResiduals",
    "capsule_signed_distance",
    "project_capsules",
    "pyr_down",
    "shade",
    "face_normals",
    "vertex_normals",
    "procedural_pattern",
    "value_noise",
]
