"""The fitted body drawn over a video frame, and seen from a second, orbiting camera."""

from __future__ import annotations

import numpy as np

from flowmocap.errors import InputError
from flowmocap.geometry.camera import PinholeCamera, look_at

__all__ = ["BODY_RGB", "PEOPLE_RGB", "overlay_body", "overlay_bodies", "render_body_view", "side_camera",
           "framing_side_camera", "camera_up"]

#: Default body colour (RGB in [0, 1]): a light blue that stands out on most footage.
BODY_RGB = (0.45, 0.70, 1.0)

#: Body colours (RGB in [0, 1]) of several people drawn together, in their ranks' order
#: (``--person all``: person0 keeps :data:`BODY_RGB`); the list repeats beyond its length.
PEOPLE_RGB = (BODY_RGB, (1.0, 0.62, 0.25), (0.45, 0.88, 0.45), (0.95, 0.45, 0.80), (0.95, 0.90, 0.35),
              (0.70, 0.55, 1.0))


def _shade_over(vertices: np.ndarray, faces, camera: PinholeCamera, background: np.ndarray,
                colour, supersample: int) -> np.ndarray:
    from flowmocap.render import shade

    v = np.asarray(vertices, np.float64)
    v_cam = camera.to_camera(v)
    if not np.all(v_cam[:, 2] > 1e-3):
        return background.copy()  # (part of) the body behind the camera: draw nothing
    px = camera.project(v)
    colours = np.tile(np.asarray(colour, np.float32), (len(v), 1))
    return shade(px, v_cam[:, 2], faces, v_cam, colours, background=background, supersample=supersample)


def _checked_image(image: np.ndarray, camera: PinholeCamera, alpha: float) -> np.ndarray:
    """``image`` as uint8 once it is the camera's size and RGB and ``alpha`` is in [0, 1]."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[:2] != (camera.height, camera.width):
        raise InputError(f"image must be ({camera.height}, {camera.width}, 3) RGB for this camera; "
                         f"got {img.shape}.")
    if not 0.0 <= alpha <= 1.0:
        raise InputError(f"alpha must be in [0, 1], got {alpha}.")
    return img.astype(np.uint8)


def overlay_body(image: np.ndarray, vertices: np.ndarray, faces, camera: PinholeCamera, alpha: float = 0.6,
                 colour=BODY_RGB, supersample: int = 2) -> np.ndarray:
    """Draw a shaded, semi-transparent body over an image.

    Args:
        image: ``(H, W, 3)`` uint8 RGB frame, the camera's size.
        vertices: ``(V, 3)`` world positions in metres.
        faces: ``(F, 3)`` triangle indices (or prepared ``Faces``).
        camera: the camera that took ``image``.
        alpha: opacity of the body in ``[0, 1]``.
        colour: body RGB in ``[0, 1]``.
        supersample: anti-aliasing samples per pixel and axis.

    Returns:
        ``(H, W, 3)`` uint8 RGB; pixels off the body are ``image`` unchanged.
    """
    img = _checked_image(image, camera, alpha)
    shaded = _shade_over(vertices, faces, camera, img, colour, supersample)
    out = alpha * shaded.astype(np.float32) + (1.0 - alpha) * img.astype(np.float32)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def overlay_bodies(image: np.ndarray, bodies, camera: PinholeCamera, alpha: float = 0.6, colours=None,
                   supersample: int = 2) -> np.ndarray:
    """Draw several shaded, semi-transparent bodies over an image in one pass, each in its
    own colour; where they overlap, the surface nearer the camera is drawn.

    Args:
        image: ``(H, W, 3)`` uint8 RGB frame, the camera's size.
        bodies: a list of ``(vertices, faces)``: ``(V_k, 3)`` world positions in metres and
            ``(F_k, 3)`` triangle indices (plain arrays). A body with a vertex behind the
            camera is left out.
        camera: the camera that took ``image``.
        alpha: opacity of the bodies in ``[0, 1]``.
        colours: one RGB in ``[0, 1]`` per body (default :data:`PEOPLE_RGB` in turn).
        supersample: anti-aliasing samples per pixel and axis.

    Returns:
        ``(H, W, 3)`` uint8 RGB; pixels off every body are ``image`` unchanged. One body
        gives what :func:`overlay_body` gives.
    """
    from flowmocap.render import shade

    img = _checked_image(image, camera, alpha)
    if colours is None:
        colours = [PEOPLE_RGB[k % len(PEOPLE_RGB)] for k in range(len(bodies))]
    if len(colours) != len(bodies):
        raise InputError(f"one colour per body: {len(bodies)} bodies, {len(colours)} colours.")
    verts, faces, cols, offset = [], [], [], 0
    for (v, f), c in zip(bodies, colours):
        v = np.asarray(v, np.float64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise InputError(f"each body's vertices must be (V, 3) metres; got {v.shape}.")
        if not np.all(camera.to_camera(v)[:, 2] > 1e-3):
            continue  # (part of) this body behind the camera: not drawn
        verts.append(v)
        faces.append(np.asarray(f, np.int64) + offset)
        cols.append(np.tile(np.asarray(c, np.float32), (len(v), 1)))
        offset += len(v)
    if not verts:
        return img.copy()
    v = np.concatenate(verts)
    v_cam = camera.to_camera(v)
    shaded = shade(camera.project(v), v_cam[:, 2], np.concatenate(faces), v_cam, np.concatenate(cols),
                   background=img, supersample=supersample)
    out = alpha * shaded.astype(np.float32) + (1.0 - alpha) * img.astype(np.float32)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def render_body_view(vertices: np.ndarray, faces, camera: PinholeCamera, background=(235, 235, 235),
                     colour=BODY_RGB, supersample: int = 2) -> np.ndarray:
    """The body, opaque and shaded, over a plain background.

    Args:
        vertices: ``(V, 3)`` world positions in metres.
        faces: ``(F, 3)`` triangle indices.
        camera: the viewing camera.
        background: RGB 0..255.
        colour: the body's RGB, 0..1.
        supersample: samples per pixel side (anti-aliasing), as for :func:`flowmocap.render.shade`.

    Returns:
        ``(camera.height, camera.width, 3)`` uint8 RGB.
    """
    bg = np.empty((camera.height, camera.width, 3), np.uint8)
    bg[:] = background
    return _shade_over(vertices, faces, camera, bg, colour, supersample)


def camera_up(camera: PinholeCamera) -> np.ndarray:
    """``(3,)`` the camera's image-up direction in world coordinates (``-R[1]``, unit)."""
    return -np.asarray(camera.R[1], np.float64)


def framing_side_camera(camera: PinholeCamera, points, angle_deg: float = 90.0, fill: float = 0.9) -> PinholeCamera:
    """:func:`side_camera` about the middle of ``points``, moved back along its view until
    every point lies within ``fill`` of the image's half-width and half-height of its centre
    (never nearer than the orbit puts it): a side view that keeps a whole path in sight.

    Args:
        camera: the input camera.
        points: ``(N, 3)`` world points to keep in view (e.g. the joints of every frame and
            some vertices), metres; the orbit is about the middle of their bounding box.
        angle_deg: orbit angle, degrees (as :func:`side_camera`).
        fill: the share of the half-image the points may reach, in ``(0, 1]``.

    Returns:
        :class:`PinholeCamera` of the same size and intrinsics.
    """
    if not 0.0 < fill <= 1.0:
        raise InputError(f"fill is the share of the half-image the points may reach, in (0, 1]; got {fill}.")
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if not len(pts):
        raise InputError("framing_side_camera needs at least one finite point to keep in view.")
    centre = 0.5 * (pts.min(0) + pts.max(0))
    cam = side_camera(camera, centre, angle_deg)
    R, t = np.asarray(cam.R, np.float64), np.asarray(cam.t, np.float64)
    x = pts @ R.T + t  # camera axes: a move back by d adds d to every z

    def depth_needed(a, f, c, size):  # the depth at which fx x / z + c lies within fill of the image's middle
        half, off = fill * 0.5 * size, c - 0.5 * size
        return np.where(a > 0, f * a / max(half - off, 1e-9), -f * a / max(half + off, 1e-9))

    need = np.maximum(depth_needed(x[:, 0], cam.fx, cam.cx, cam.width), depth_needed(x[:, 1], cam.fy, cam.cy, cam.height))
    back = max(0.0, float(np.max(need - x[:, 2])))
    if back == 0.0:
        return cam
    return PinholeCamera(fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy, width=cam.width, height=cam.height,
                         R=R, t=t + np.array([0.0, 0.0, back]))


def side_camera(camera: PinholeCamera, centre, angle_deg: float = 90.0) -> PinholeCamera:
    """The camera orbited about the vertical axis through ``centre``.

    The vertical is the camera's own image-up direction, so no world up is assumed; the
    new camera keeps the intrinsics and distance to ``centre`` and looks at it.

    Args:
        camera: the input camera.
        centre: ``(3,)`` world point to orbit about (e.g. the mean pelvis), metres.
        angle_deg: orbit angle in degrees (90: a side view; positive is anticlockwise
            seen from above).

    Returns:
        :class:`PinholeCamera` of the same size and intrinsics.
    """
    from scipy.spatial.transform import Rotation

    c = np.asarray(centre, np.float64).reshape(3)
    up = camera_up(camera)
    rot = Rotation.from_rotvec(np.deg2rad(angle_deg) * up).as_matrix()
    eye = c + rot @ (camera.center - c)
    if np.linalg.norm(eye - c) < 1e-6:
        eye = c + rot @ np.asarray(camera.R[2]) * -3.0
    R, t = look_at(eye, c, up=up)
    return PinholeCamera(fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy, width=camera.width,
                         height=camera.height, R=R, t=t)
