"""A camera carried over a textured floor, with the truth: frames for checking
:mod:`flowmocap.vision.camera_motion` (tests and ``benchmarks/camera_move.py``).

The world is y up with the floor at ``y = 0``; the camera stands ``height`` metres above it,
pitched down by ``pitch_deg``, and in frame ``i`` its centre has moved by ``i * velocity`` (world
axes, metres) and it has turned by ``i * yaw_deg`` about the vertical. The floor is 12 x 12 m of
blurred noise and colour blocks at 1 cm a pixel; above its horizon, and beyond 10 m, the frame
is a flat grey (no corners). Frames are rendered four times larger and scaled down, so the far
floor does not alias.
"""

from __future__ import annotations

import numpy as np

__all__ = ["CarriedCamera", "floor_texture"]


def floor_texture(seed: int = 0, size: int = 1200) -> np.ndarray:
    """``(size, size, 3)`` uint8: blurred noise with 400 colour blocks of 5-40 px."""
    import cv2

    rng = np.random.default_rng(seed)
    tex = rng.integers(0, 255, (size, size, 3)).astype(np.uint8)
    tex = cv2.GaussianBlur(tex, (0, 0), 2.0)
    for _ in range(400):
        x, y = rng.integers(0, size - 40, 2)
        tex[y:y + rng.integers(5, 40), x:x + rng.integers(5, 40)] = rng.integers(0, 255, 3)
    return tex


class CarriedCamera:
    """Frames (``frame(i)``, ``(H, W, 3)`` uint8 RGB) of a camera carried over a floor.

    Args:
        frames: the number of frames.
        velocity: ``(3,)`` the camera centre's move a frame, metres, world axes (x right, y up,
            z away from the camera in the first frame, before its pitch).
        yaw_deg: its turn a frame about the vertical, degrees.
        K: ``(3, 3)`` the intrinsics, pixels; ``size``: ``(W, H)``.
        height: the camera's height above the floor in the first frame, metres.
        pitch_deg: how far it looks down, degrees.
        zoom: each frame's focal length over the frame before's (1: no zoom; the principal
            point stays): frame ``i`` is seen with ``zoom ** i`` times ``K``'s focal length.

    ``masks`` and ``camera`` are None (a sequence without a person or a given camera).
    """

    masks, camera = None, None

    def __init__(self, frames: int, velocity, yaw_deg: float = 0.0, K=None, size=(320, 240), height: float = 1.5,
                 pitch_deg: float = 15.0, zoom: float = 1.0):
        from scipy.spatial.transform import Rotation

        self.n, self.velocity, self.yaw = int(frames), np.asarray(velocity, np.float64), float(yaw_deg)
        self.size = tuple(size)
        default = np.array([[300.0, 0, size[0] / 2], [0, 300.0, size[1] / 2], [0, 0, 1.0]])
        self.K = default if K is None else np.asarray(K, np.float64)
        self.height = float(height)
        self.zoom = float(zoom)
        self.base = Rotation.from_euler("x", np.radians(pitch_deg)).as_matrix() @ np.diag([-1.0, -1.0, 1.0])
        self.tex = floor_texture()

    def __len__(self) -> int:
        return self.n

    def pose(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """World to camera ``i``: ``(R, C)`` with ``x = R (X - C)``."""
        from scipy.spatial.transform import Rotation

        turn = Rotation.from_euler("y", self.yaw * i, degrees=True).as_matrix()
        return self.base @ turn.T, np.array([0.0, self.height, 0.0]) + self.velocity * i

    def frame(self, i: int) -> np.ndarray:
        """``(H, W, 3)`` uint8 RGB: frame ``i``, the floor's texture seen through :meth:`pose`
        and :meth:`K_of` (4x supersampled); grey above the horizon and beyond 10 m."""
        import cv2

        W, H = self.size
        R, C = self.pose(i)
        K = self.K_of(i)
        ss = 4
        texture_to_floor = np.array([[0.01, 0, -6.0], [0, 0.01, -2.0], [0, 0, 1.0]])  # pixels -> (x, z) metres
        M = np.diag([ss, ss, 1.0]) @ K @ np.c_[R[:, 0], R[:, 2], -R @ C] @ texture_to_floor
        img = cv2.resize(cv2.warpPerspective(self.tex, M, (W * ss, H * ss), flags=cv2.INTER_LINEAR), (W, H),
                         interpolation=cv2.INTER_AREA)
        px = np.stack(np.meshgrid(np.arange(W), np.arange(H)), -1).reshape(-1, 2)
        rays = np.c_[px, np.ones(len(px))] @ np.linalg.inv(K).T
        depth_share = rays @ (R @ np.array([0.0, -1.0, 0.0]))  # the ray's drop a metre forward
        img.reshape(-1, 3)[depth_share * 10.0 <= self.height] = 128  # above the horizon or beyond 10 m
        return img

    def K_of(self, i: int) -> np.ndarray:
        """``(3, 3)`` frame ``i``'s intrinsics, pixels: ``K`` with its focal lengths times ``zoom ** i``."""
        z = self.zoom ** i
        return np.array([[self.K[0, 0] * z, self.K[0, 1] * z, self.K[0, 2]], [0.0, self.K[1, 1] * z, self.K[1, 2]],
                         [0.0, 0.0, 1.0]])

    def truth(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Camera ``i``'s centre in camera 0's axes in units of ``height``, and the floor's
        normal there (pointing down, camera 0's axes)."""
        R0, C0 = self.pose(0)
        _, C = self.pose(i)
        return R0 @ (C - C0) / self.height, R0 @ np.array([0.0, -1.0, 0.0])
