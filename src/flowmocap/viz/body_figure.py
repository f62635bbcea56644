"""Pictures of a body model: one render, or a sheet of shapes and poses for the README."""

from __future__ import annotations

import numpy as np
import torch

from flowmocap.body import JOINT_INDEX, load_body_model
from flowmocap.errors import InputError
from flowmocap.geometry.camera import PinholeCamera, look_at
from flowmocap.render import shade

#: Named example poses: joint name -> axis-angle (radians), SMPL joint frames.
POSES: dict[str, dict[str, tuple[float, float, float]]] = {
    "rest": {},
    "walk": {
        "left_hip": (-0.45, 0.0, 0.0), "right_hip": (0.35, 0.0, 0.0),
        "left_knee": (0.25, 0.0, 0.0), "right_knee": (0.5, 0.0, 0.0),
        "left_ankle": (0.1, 0.0, 0.0), "right_ankle": (-0.1, 0.0, 0.0),
        "left_shoulder": (0.0, 0.0, -1.2), "right_shoulder": (0.0, 0.0, 1.2),
        "left_elbow": (0.0, -0.4, 0.0), "right_elbow": (0.0, 0.6, 0.0),
        "spine1": (0.05, 0.0, 0.0),
    },
    "wave": {
        "left_shoulder": (0.0, 0.0, -1.25), "right_shoulder": (0.0, 0.0, -0.4),
        "right_elbow": (0.0, 1.6, 0.0), "left_elbow": (0.0, -0.3, 0.0),
        "left_hip": (0.0, 0.0, 0.15), "right_hip": (0.0, 0.0, -0.1),
        "neck": (0.0, 0.0, 0.15),
    },
}

_VIEWS = {"front": 0.0, "three-quarter": 40.0, "side": 90.0}
BODY_COLOUR = (0.62, 0.68, 0.78)
BACKGROUND = (245, 245, 245)


def pose_vector(name: str) -> torch.Tensor:
    """``(72,)`` axis-angle pose for a name in :data:`POSES`."""
    if name not in POSES:
        raise InputError(f"unknown pose {name!r}; choose one of {', '.join(POSES)}.")
    pose = torch.zeros(24, 3)
    for joint, aa in POSES[name].items():
        pose[JOINT_INDEX[joint]] = torch.tensor(aa)
    return pose.reshape(72)


def render_vertices(vertices: np.ndarray, faces: np.ndarray, width: int, height: int,
                    view: str = "front", colour=BODY_COLOUR, frame=None) -> np.ndarray:
    """Shade a mesh seen from a camera that frames it.

    Args:
        vertices: ``(V, 3)`` world positions in metres (y up, the body facing +z).
        faces: ``(F, 3)`` triangle indices.
        width, height: image size in pixels.
        view: ``"front"``, ``"three-quarter"`` or ``"side"`` (camera azimuth 0/40/90 deg).
        frame: ``(centre (3,), extent)`` to frame; default: the mesh's own bounding box.
            Give the same frame to several renders to compare sizes.

    Returns:
        ``(height, width, 3)`` uint8 image.
    """
    if view not in _VIEWS:
        raise InputError(f"unknown view {view!r}; choose one of {', '.join(_VIEWS)}.")
    if frame is None:
        frame = mesh_frame(vertices, width, height)
    centre, extent = frame
    focal = 2.0 * height
    dist = focal * extent / (0.88 * height)
    az = np.deg2rad(_VIEWS[view])
    eye = centre + dist * np.array([np.sin(az), 0.12, np.cos(az)])
    R, t = look_at(eye, centre)
    cam = PinholeCamera.from_focal(width, height, focal, R=R, t=t)
    v = torch.as_tensor(vertices, dtype=torch.float32)
    v_cam = cam.to_camera(v)
    px = cam.project(v)
    colours = np.tile(np.asarray(colour, dtype=np.float32), (len(vertices), 1))
    background = np.empty((height, width, 3), np.uint8)
    background[:] = BACKGROUND
    return shade(px.numpy(), v_cam[:, 2].numpy(), faces, v_cam.numpy(), colours, background=background)


def mesh_frame(vertices: np.ndarray, width: int, height: int):
    """``(centre (3,), extent)`` in metres that frames ``vertices (V, 3)`` in the image."""
    lo, hi = vertices.min(0), vertices.max(0)
    return 0.5 * (lo + hi), max(hi[1] - lo[1], (hi[0] - lo[0]) * height / width, 1e-3)


def posed_vertices(model, betas=None, pose="rest") -> np.ndarray:
    """``(V, 3)`` vertices of ``model`` with ``betas (10,)`` and a named or ``(72,)`` pose."""
    b = torch.as_tensor(betas if betas is not None else np.zeros(10), dtype=torch.float32)
    with torch.no_grad():
        out = model(betas=b, pose=pose_vector(pose) if isinstance(pose, str) else pose)
    return out.vertices[0].numpy()


def render_body(model="default", gender="neutral", betas=None, pose="rest", width=320, height=480,
                view="front", frame=None) -> np.ndarray:
    """Render a body model in a named pose; see :func:`render_vertices` for the output.

    Args:
        model: a model name for :func:`~flowmocap.body.load_body_model` (e.g.
            ``"default"``) or a :class:`~flowmocap.body.BodyModel`.
        gender: the model's gender when ``model`` is a name.
        betas: ``(10,)`` shape coefficients (default: the mean shape).
        pose: a name in :data:`POSES` or a ``(72,)`` axis-angle pose in radians.
        width, height: image size in pixels.
        view: ``"front"``, ``"three-quarter"`` or ``"side"``.
        frame: ``(centre (3,), extent)`` metres to frame (:func:`mesh_frame`); default:
            the posed mesh's own bounding box.

    Returns:
        ``(height, width, 3)`` uint8 image.

    Raises:
        InputError: ``width`` or ``height`` (pixels) outside 16..8192.
    """
    if not (16 <= width <= 8192 and 16 <= height <= 8192):
        raise InputError(f"image size must be 16..8192 pixels per side, got {width}x{height}.")
    m = load_body_model(model, gender=gender) if isinstance(model, str) else model
    v = posed_vertices(m, betas, pose)
    return render_vertices(v, m.faces_np, width, height, view, frame=frame)


def body_sheet(model="default", gender="neutral", panel=(240, 360)) -> np.ndarray:
    """One row of panels: mean shape, beta0 -/+2, beta1 -/+2, a walking pose, a side view.

    Returns:
        ``(panel_h + 24, 7 * panel_w, 3)`` uint8 image with captions.
    """
    import cv2

    m = load_body_model(model, gender=gender) if isinstance(model, str) else model
    w, h = panel
    specs = [
        ("mean", {}, "rest", "front"),
        ("beta0 = -2", {0: -2.0}, "rest", "front"),
        ("beta0 = +2", {0: 2.0}, "rest", "front"),
        ("beta1 = -2", {1: -2.0}, "rest", "front"),
        ("beta1 = +2", {1: 2.0}, "rest", "front"),
        ("walk pose", {}, "walk", "three-quarter"),
        ("side view", {}, "walk", "side"),
    ]
    meshes = []
    for _, bdict, pose, _ in specs:
        betas = np.zeros(10)
        for k, v in bdict.items():
            betas[k] = v
        meshes.append(posed_vertices(m, betas, pose))
    frame = mesh_frame(np.concatenate(meshes[:5]), w, h)  # shapes share one camera
    panels = []
    for (caption, _, _, view), verts in zip(specs, meshes):
        img = render_vertices(verts, m.faces_np, w, h, view, frame=frame if view == "front" else None)
        strip = np.full((24, w, 3), 255, np.uint8)
        cv2.putText(strip, caption, (8, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (30, 30, 30), 1, cv2.LINE_AA)
        panels.append(np.concatenate([img, strip], axis=0))
    return np.concatenate(panels, axis=1)
