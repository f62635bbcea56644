"""The synthetic scene: camera placement, a textured static background with a ground
plane, and a clothing-like surface pattern for the body.

World: metres, y up, ground plane ``y = 0``. Camera: OpenCV axes (see
:class:`~flowmocap.geometry.PinholeCamera`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flowmocap.body.skeleton import JOINT_INDEX
from flowmocap.errors import InputError
from flowmocap.geometry import PinholeCamera, look_at
from flowmocap.render import procedural_pattern, value_noise

__all__ = ["place_camera", "render_background", "ClothingPattern", "WORLD_LIGHT"]

#: Direction towards the light in world coordinates (from above, in front, to the left).
WORLD_LIGHT = np.array([-0.4, 1.0, 0.6]) / np.linalg.norm([-0.4, 1.0, 0.6])


def _eye(target: np.ndarray, distance: float, azimuth: float, elevation: float) -> np.ndarray:
    a, e = math.radians(azimuth), math.radians(elevation)
    return target + distance * np.array([math.sin(a) * math.cos(e), math.sin(e), math.cos(a) * math.cos(e)])


def place_camera(
    points: np.ndarray,
    width: int,
    height: int,
    focal: float | None = None,
    distance: float | None = None,
    azimuth: float = 60.0,
    elevation: float = 8.0,
    fill: float = 0.85,
) -> tuple[PinholeCamera, dict]:
    """A static camera looking at the centre of ``points`` from a given direction.

    The camera sits at ``target + distance * (sin(az) cos(el), sin(el), cos(az) cos(el))``
    (azimuth measured from +z towards +x about the vertical, elevation above the
    horizon) and looks at the centre of the points' bounding box. With ``distance``
    None, it is chosen so that all points fit in ``fill`` of the image; ``focal`` None
    is the image width (a 53 deg horizontal field of view).

    Args:
        points: ``(N, 3)`` world points that must be seen (e.g. body vertices over the
            clip), metres.
        width, height: image size in pixels.
        focal: focal length in pixels.
        distance: camera-to-target distance in metres.
        azimuth, elevation: degrees.
        fill: fraction of the image the points may span when ``distance`` is automatic.

    Returns:
        ``(camera, placement)``: the :class:`PinholeCamera` and a dict of the values used
        (target, distance, azimuth, elevation, focal).

    Raises:
        InputError: non-finite points or angles, an elevation of +-90 degrees or beyond, a
            focal length that is not positive.
    """
    if not (math.isfinite(azimuth) and math.isfinite(elevation) and -90.0 < elevation < 90.0):
        raise InputError(f"the camera's azimuth must be finite and its elevation strictly between -90 and 90 "
                         f"degrees (the view direction must not be vertical); got azimuth {azimuth}, "
                         f"elevation {elevation}.")
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if pts.size == 0 or not np.all(np.isfinite(pts)):
        raise InputError("place_camera needs finite points to look at")
    f = float(width) if focal is None else float(focal)
    if not f > 0:
        raise InputError(f"focal must be a positive number of pixels, got {focal}")
    fov = math.degrees(2.0 * math.atan2(0.5 * float(width), f))
    if not 0.2 <= fov <= 170.0:  # the field of view track accepts (flowmocap.pipeline.FIELD_OF_VIEW_DEG)
        raise InputError(f"focal {f:g} px gives a field of view of {fov:.3g} degrees across the {width} px image, "
                         "outside 0.2..170; the focal length is in pixels (the image width is a 53-degree view)")
    target = 0.5 * (pts.min(0) + pts.max(0))

    def camera_at(d):
        R, t = look_at(_eye(target, d, azimuth, elevation), target)
        return PinholeCamera.from_focal(width, height, f, R=R, t=t)

    if distance is None:
        d = 3.0
        for _ in range(30):
            cam = camera_at(d)
            z = cam.depth(pts)
            if z.min() < 0.3:
                d *= 1.5
                continue
            px = cam.project(pts) - np.array([cam.cx, cam.cy])
            need = max(np.abs(px[:, 0]).max() / (0.5 * fill * width),
                       np.abs(px[:, 1]).max() / (0.5 * fill * height))
            if abs(need - 1.0) < 1e-3:
                break
            d *= need ** 0.9
        distance = d
    elif not distance > 0:
        raise InputError(f"distance must be positive (metres), got {distance}")
    cam = camera_at(float(distance))
    if cam.depth(pts).min() <= 0.05:
        raise InputError(
            f"the camera at distance {distance:.2f} m is inside or behind the body's path; "
            "increase the distance"
        )
    placement = {"target": target.tolist(), "distance": float(distance), "azimuth_deg": float(azimuth),
                 "elevation_deg": float(elevation), "focal": f}
    return cam, placement


def render_background(
    camera: PinholeCamera,
    seed: int = 0,
    supersample: int = 2,
    wall_distance: float | None = None,
    light: np.ndarray = WORLD_LIGHT,
    wall_facing: np.ndarray | None = None,
) -> np.ndarray:
    """A static textured scene as seen by ``camera``: paved ground ``y = 0``, a brick wall.

    Each pixel's ray (``supersample`` x ``supersample`` rays per pixel, averaged) is
    intersected with the ground plane and a vertical wall facing the camera, placed
    ``wall_distance`` metres from the camera along its horizontal viewing direction
    (default 8 m); rays that hit
    neither see a sky gradient. Surfaces are Lambertian under ``light``.

    Args:
        camera: the static camera.
        seed: selects colours and patterns.
        supersample: rays per pixel along each axis.
        wall_distance: metres from the camera to the wall.
        light: ``(3,)`` unit direction towards the light, world coordinates.
        wall_facing: ``(3,)`` the horizontal direction from the camera to the wall, world
            (default the camera's horizontal viewing direction). Give it for a camera that
            turns, or the wall turns with it.

    Returns:
        ``(H, W, 3)`` uint8 RGB image.
    """
    H, W, s = camera.height, camera.width, int(supersample)
    C = camera.center
    fwd = (camera.R[2] if wall_facing is None else np.asarray(wall_facing, np.float64)).copy()
    fwd[1] = 0.0
    if np.linalg.norm(fwd) < 1e-6:
        fwd = np.array([0.0, 0.0, 1.0])
    fwd /= np.linalg.norm(fwd)
    if wall_distance is None:
        wall_distance = 8.0
    if not wall_distance > 0:
        raise InputError(f"wall_distance must be positive (metres), got {wall_distance}")
    rng = np.random.default_rng(seed)
    ground_tint = rng.uniform(0.55, 0.85, 3)
    wall_tint = rng.uniform(0.5, 0.9, 3)

    ys, xs = np.mgrid[0:H * s, 0:W * s]
    u = (xs + 0.5) / s
    v = (ys + 0.5) / s
    d_cam = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], -1)
    d = d_cam.reshape(-1, 3) @ camera.R  # rows: R^T d
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(d[:, 1] < -1e-9, -C[1] / d[:, 1], np.inf)
        dw = d @ fwd
        t_wall = np.where(dw > 1e-9, wall_distance / dw, np.inf)
    hit_ground = (t_ground <= t_wall) & np.isfinite(t_ground)
    hit_wall = ~hit_ground & np.isfinite(t_wall)
    rgb = np.empty((d.shape[0], 3))

    # Sky: a vertical gradient.
    sky = ~(hit_ground | hit_wall)
    elev = d[sky, 1] / np.linalg.norm(d[sky], axis=1)
    rgb[sky] = np.array([0.75, 0.85, 0.95]) - 0.25 * np.clip(elev, 0, 1)[:, None]

    if hit_ground.any():
        p = C + t_ground[hit_ground, None] * d[hit_ground]
        xz = p[:, [0, 2]]
        # Paving: 0.5 m slabs with dark joints, noise at 12 cm and 1.5 cm.
        joint = np.minimum(_dist_to_grid(xz[:, 0], 0.5), _dist_to_grid(xz[:, 1], 0.5))
        lines = np.clip(joint / 0.012, 0.0, 1.0)
        coarse = procedural_pattern(p, cell=0.12, octaves=2, seed=seed + 11)
        coarse = 0.3 * coarse + 0.7 * coarse.mean(axis=1, keepdims=True)  # mostly grey stone
        fine = value_noise(p / 0.015, seed=seed + 12)[:, None]
        slab = value_noise(np.floor(xz / 0.5)[:, [0, 0, 1]] * np.array([1.0, 0.0, 1.0]) + 0.5, seed=seed + 13)
        col = ground_tint * (0.55 + 0.35 * slab[:, None]) * (0.7 + 0.3 * coarse) * (0.75 + 0.5 * fine)
        col *= (0.35 + 0.65 * lines)[:, None]
        rgb[hit_ground] = col * (0.5 + 0.5 * max(0.0, float(light[1])))
    if hit_wall.any():
        p = C + t_wall[hit_wall, None] * d[hit_wall]
        side = np.cross(np.array([0.0, 1.0, 0.0]), fwd)
        a = p @ side
        b = p[:, 1]
        # Bricks 0.24 x 0.08 m, every other row shifted by half a brick.
        row = np.floor(b / 0.08)
        a_shift = a + 0.12 * (row % 2)
        mortar = np.minimum(_dist_to_grid(b, 0.08), _dist_to_grid(a_shift, 0.24))
        lines = np.clip(mortar / 0.008, 0.0, 1.0)
        brick = value_noise(np.stack([np.floor(a_shift / 0.24), row, np.zeros_like(a)], 1) + 0.5, seed=seed + 21)
        fine = procedural_pattern(p, cell=0.03, octaves=3, seed=seed + 22).mean(axis=1, keepdims=True)
        col = wall_tint * (0.6 + 0.4 * brick[:, None]) * (0.7 + 0.3 * fine)
        col = col * lines[:, None] + np.array([0.8, 0.8, 0.78]) * (1 - lines[:, None])
        rgb[hit_wall] = col * (0.55 + 0.45 * max(0.0, float(-(light @ fwd))))
    img = rgb.reshape(H, s, W, s, 3).mean(axis=(1, 3))
    return np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)


def _dist_to_grid(x: np.ndarray, spacing: float) -> np.ndarray:
    r = np.mod(x, spacing)
    return np.minimum(r, spacing - r)


@dataclass
class ClothingPattern:
    """A clothing-like albedo for a body, evaluated at *rest-pose* surface points.

    Regions come from the rest pose (a T-pose): shoes below the ankles, trousers below
    the waist, skin on the hands and face, hair on the top and back of the head, a
    long-sleeved shirt elsewhere. The shirt is a plaid (checks of ``check`` metres),
    the trousers a blotchy print (5 cm); everything carries noise at 2.5 cm and 1 cm so
    optical flow has detail to follow everywhere, skin included (mildly).

    Build one with :meth:`for_body`; call it with ``(N, 3)`` rest-pose points to get
    ``(N, 3)`` RGB in ``[0, 1]`` (the ``pattern`` argument of
    :func:`flowmocap.render.shade`).
    """

    rest_joints: np.ndarray
    shirt: np.ndarray
    shirt2: np.ndarray
    trousers: np.ndarray
    shoes: np.ndarray
    skin: np.ndarray
    hair: np.ndarray
    check: float
    seed: int

    @classmethod
    def for_body(cls, rest_joints: np.ndarray, seed: int = 0) -> "ClothingPattern":
        """Colours drawn from ``seed``; ``rest_joints`` ``(24, 3)`` of the shaped rest pose."""
        rng = np.random.default_rng(seed)
        hue = lambda lo, hi: rng.uniform(lo, hi, 3)  # noqa: E731
        skins = np.array([[0.87, 0.68, 0.56], [0.74, 0.54, 0.40], [0.55, 0.38, 0.27], [0.95, 0.80, 0.70]])
        return cls(
            rest_joints=np.asarray(rest_joints, dtype=np.float64),
            shirt=hue(0.3, 0.95), shirt2=hue(0.1, 0.6), trousers=hue(0.35, 0.8),
            shoes=hue(0.15, 0.45), skin=skins[rng.integers(len(skins))], hair=hue(0.05, 0.35),
            check=float(rng.uniform(0.03, 0.06)), seed=int(rng.integers(1 << 30)),
        )

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """``(N, 3)`` float64 RGB in ``[0, 1]`` of ``points (N, 3)``, rest-pose surface
        points in metres (the frame of :attr:`rest_joints`)."""
        p = np.asarray(points, dtype=np.float64)
        J = self.rest_joints
        i = JOINT_INDEX
        y_ankle = 0.5 * (J[i["left_ankle"], 1] + J[i["right_ankle"], 1])
        y_waist = J[i["pelvis"], 1] + 0.25 * (J[i["spine1"], 1] - J[i["pelvis"], 1])
        x_wrist = 0.5 * (J[i["left_wrist"], 0] - J[i["right_wrist"], 0])
        y_neck = J[i["neck"], 1]
        head = J[i["head"]]
        ax = np.abs(p[:, 0])
        fine = value_noise(p / 0.01, seed=self.seed)[:, None]
        mid = value_noise(p / 0.025, seed=self.seed + 1)[:, None]
        big = value_noise(p / 0.05, seed=self.seed + 2)[:, None]
        # shirt: plaid from two stripe families, weave-like fine noise
        c = self.check
        sx = 0.5 + 0.5 * np.sin(2 * np.pi * p[:, 0] / c)
        sy = 0.5 + 0.5 * np.sin(2 * np.pi * p[:, 1] / c + 1.3)
        sz = 0.5 + 0.5 * np.sin(2 * np.pi * p[:, 2] / c + 0.7)
        w = np.clip(0.5 * (sx + np.maximum(sy, sz)), 0, 1)[:, None]
        out = (w * self.shirt + (1 - w) * self.shirt2) * (0.6 + 0.4 * mid) * (0.7 + 0.6 * fine)
        # trousers: a printed, blotchy two-tone fabric with fine noise
        legs = p[:, 1] < y_waist
        blot = np.clip(3.0 * (big - 0.5) + 0.5, 0, 1)
        trousers = (blot * self.trousers + (1 - blot) * 0.45 * self.trousers) * (0.55 + 0.45 * mid) * (0.7 + 0.6 * fine)
        out = np.where(legs[:, None], trousers, out)
        shoes = p[:, 1] < y_ankle + 0.03
        out = np.where(shoes[:, None], self.shoes * (0.5 + 0.5 * mid) * (0.6 + 0.8 * fine), out)
        hands = ax > x_wrist
        neck_up = (p[:, 1] > y_neck + 0.03) & (ax < 0.2)
        skin = self.skin * (0.75 + 0.25 * mid) * (0.85 + 0.25 * fine)
        out = np.where((hands | neck_up)[:, None], skin, out)
        hair = neck_up & ((p[:, 1] > head[1] + 0.07) | (p[:, 2] < head[2] - 0.02))
        out = np.where(hair[:, None], self.hair * (0.5 + 0.5 * mid) * (0.6 + 0.8 * fine), out)
        return np.clip(out, 0.02, 0.98)
