"""A static pinhole camera in the OpenCV convention.

Axes: camera x right, y down, z forward (points in front of the camera have ``Z > 0``).
World points are mapped to the camera by ``X_cam = R @ X_world + t`` (world-to-camera
rotation ``R`` and translation ``t``; the camera centre in the world is ``-R^T t``).

Pixel convention: **pixel centres at integer + 0.5, so the image spans [0, W] x [0, H]**.
Pixel ``(u, v)`` (column ``u``, row ``v``, integers) covers ``[u, u+1) x [v, v+1)`` and
its centre is at ``(u + 0.5, v + 0.5)``. :meth:`PinholeCamera.project` returns continuous
coordinates in this frame, so the renderer samples pixel ``(u, v)`` at
``(u + 0.5, v + 0.5)`` and the default principal point ``(W/2, H/2)`` is the exact image
centre. Intrinsics calibrated with OpenCV (pixel centres at integers) convert by adding
0.5 to ``cx`` and ``cy``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from flowmocap.errors import DataError, InputError

__all__ = ["PinholeCamera", "look_at", "world_up"]


def _as_vector3(x: Any, name: str) -> np.ndarray:
    try:
        v = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be 3 numbers (metres), got {x!r}") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise InputError(f"{name} must be 3 finite numbers (metres), got shape {v.shape}: {x!r}")
    return v


def look_at(
    eye: Sequence[float],
    target: Sequence[float],
    up: Sequence[float] = (0.0, 1.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera ``R, t`` (OpenCV axes) for a camera at ``eye`` looking at ``target``.

    The world is y-up by default (``up = (0, 1, 0)``); the camera's y axis points *down*
    in the image, so ``up`` ends up pointing towards decreasing image y, and the camera
    has no roll (its x axis is horizontal, perpendicular to ``up``). The target
    projects to the principal point.

    Args:
        eye: ``(3,)`` camera centre in world coordinates, metres.
        target: ``(3,)`` world point the optical axis passes through, metres.
        up: ``(3,)`` world up direction (need not be unit length); must not be
            parallel to ``target - eye``.

    Returns:
        ``R`` ``(3, 3)`` and ``t`` ``(3,)``, float64 numpy, such that
        ``X_cam = R @ X_world + t``; the rows of ``R`` are the camera's x (right),
        y (down) and z (forward) axes in world coordinates.

    Raises:
        InputError: if ``eye == target`` or ``up`` is parallel to the viewing direction.
    """
    eye_v = _as_vector3(eye, "eye")
    forward = _as_vector3(target, "target") - eye_v
    up_v = _as_vector3(up, "up")
    n = np.linalg.norm(forward)
    if n == 0.0:
        raise InputError(
            "look_at: eye and target are the same point; move the camera away from the target"
        )
    z = forward / n
    x = np.cross(z, up_v)
    nx = np.linalg.norm(x)
    if nx < 1e-9 * max(np.linalg.norm(up_v), 1e-300):
        raise InputError(
            "look_at: the up direction is parallel to the viewing direction (or zero); "
            "choose a different up vector or a camera position not straight above/below the target"
        )
    x = x / nx
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye_v


def world_up(R: Any, body_up: Any = None) -> np.ndarray:
    """The up direction of a camera's world.

    Synthetic and :func:`look_at` worlds are y up, and so is a posed camera's world
    unless nothing says so: the world is taken to be y up where the body's mean up
    direction or the image's up direction ``-R.T @ (0, 1, 0)`` lies within 45 degrees of
    ``+y`` (a camera rolled on its side filming a person standing, a level camera filming
    a person lying down). Where neither does (a lab calibration, z up; a checkerboard on
    a wall, y down), the up axis is the one of ``±x, ±y, ±z`` that the image's up and
    the body's up best agree on, the camera counting 1.5 times the body (cameras that film
    people stand roughly level). ``R = I`` (the camera's own frame: a video without a
    calibration, or a calibration whose world is its first camera) gives ``-y``, the
    image's up.

    Args:
        R: ``(3, 3)`` world-to-camera rotation (OpenCV axes), or a camera with an ``R``.
        body_up: ``(3,)`` the body's mean up direction in the world (pelvis to neck, any
            length), or None for the camera alone.

    Returns:
        ``(3,)`` float64 unit vector, in world coordinates.
    """
    R = np.asarray(getattr(R, "R", R), np.float64).reshape(3, 3)
    image_up = -R.T @ np.array([0.0, 1.0, 0.0])
    if np.allclose(R, np.eye(3), atol=1e-9):
        return image_up
    b = None
    if body_up is not None:
        b = np.asarray(body_up, np.float64).reshape(3)
        n = np.linalg.norm(b)
        b = b / n if np.isfinite(n) and n > 0 else None
    y = np.array([0.0, 1.0, 0.0])
    near = np.cos(np.radians(45.0))
    if image_up @ y >= near or (b is not None and b @ y >= near):
        return y
    axes = np.concatenate([np.eye(3), -np.eye(3)])
    score = 1.5 * (axes @ image_up) + (axes @ b if b is not None else 0.0)
    return axes[int(np.argmax(score))].copy()


@dataclass(frozen=True, eq=False)
class PinholeCamera:
    """A pinhole camera: intrinsics ``fx, fy, cx, cy`` and a world pose (OpenCV axes).

    Attributes:
        fx, fy: focal lengths in pixels (> 0).
        cx, cy: principal point in pixels, in the frame where pixel centres are at
            integer + 0.5 (the image spans ``[0, width] x [0, height]``).
        width, height: image size in pixels (positive integers).
        R: ``(3, 3)`` world-to-camera rotation (float64 numpy), default identity.
        t: ``(3,)`` world-to-camera translation in metres (float64 numpy), default zero.
            ``X_cam = R @ X_world + t``.

    Construct directly, or with :meth:`from_focal`, :meth:`from_fov`,
    :meth:`from_dict`; place it in a y-up world with :func:`look_at`. Invalid values
    raise :class:`flowmocap.errors.InputError`.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise InputError(f"camera {name} must be a number (pixels), got {value!r}") from None
            if not math.isfinite(value):
                raise InputError(f"camera {name} must be finite, got {value}")
            set_(name, value)
        for name in ("fx", "fy"):
            if getattr(self, name) <= 0:
                raise InputError(
                    f"camera focal length {name} must be positive (pixels), got {getattr(self, name)}"
                )
        for name in ("width", "height"):
            value = getattr(self, name)
            try:
                ok = float(value) == int(value) and int(value) > 0
            except (TypeError, ValueError, OverflowError):
                ok = False
            if not ok:
                raise InputError(
                    f"camera {name} must be a positive whole number of pixels, got {value!r}"
                )
            set_(name, int(value))
        try:
            R = np.array(self.R, dtype=np.float64)
            t = np.array(self.t, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(
                "camera R must be a 3x3 rotation matrix and t 3 numbers (metres)"
            ) from None
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise InputError(f"camera R must be a finite 3x3 rotation matrix, got shape {R.shape}")
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise InputError(f"camera t must be 3 finite numbers (metres), got shape {t.shape}")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
            raise InputError(
                "camera R must be a rotation (orthonormal, det +1); got a matrix that is not, "
                "e.g. a scaled or reflected one -- check for a transposed or non-normalised R"
            )
        R.setflags(write=False)
        t.setflags(write=False)
        set_("R", R)
        set_("t", t)

    # ------------------------------------------------------------------ constructors

    @classmethod
    def from_focal(
        cls,
        width: int,
        height: int,
        focal: float,
        R: Any = None,
        t: Any = None,
    ) -> "PinholeCamera":
        """Camera with ``fx = fy = focal`` (pixels) and the principal point at ``(W/2, H/2)``.

        Args:
            width, height: image size in pixels.
            focal: focal length in pixels.
            R: optional ``(3, 3)`` world-to-camera rotation (default identity).
            t: optional ``(3,)`` world-to-camera translation in metres (default zero).
        """
        return cls(
            fx=focal, fy=focal, cx=_half(width), cy=_half(height), width=width, height=height,
            R=np.eye(3) if R is None else R, t=np.zeros(3) if t is None else t,
        )

    @classmethod
    def from_fov(
        cls,
        width: int,
        height: int,
        fov_deg: float,
        R: Any = None,
        t: Any = None,
        axis: str = "horizontal",
    ) -> "PinholeCamera":
        """Camera from a field of view in degrees, square pixels, centred principal point.

        ``focal = (S / 2) / tan(fov / 2)`` where ``S`` is the width for
        ``axis="horizontal"`` (default) or the height for ``axis="vertical"``.

        Args:
            width, height: image size in pixels.
            fov_deg: full field of view in degrees, in ``(0, 180)``.
            R: optional ``(3, 3)`` world-to-camera rotation (default identity).
            t: optional ``(3,)`` world-to-camera translation in metres (default zero).
            axis: ``"horizontal"`` or ``"vertical"``: which image side ``fov_deg`` spans.
        """
        try:
            fov = float(fov_deg)
        except (TypeError, ValueError):
            raise InputError(f"fov_deg must be a number of degrees, got {fov_deg!r}") from None
        if not 0.0 < fov < 180.0:
            raise InputError(f"fov_deg must be in (0, 180) degrees, got {fov_deg}")
        if axis not in ("horizontal", "vertical"):
            raise InputError(f"axis must be 'horizontal' or 'vertical', got {axis!r}")
        side = width if axis == "horizontal" else height
        try:
            side = float(side)
        except (TypeError, ValueError):
            raise InputError(
                f"camera width and height must be numbers of pixels, got {side!r}"
            ) from None
        focal = 0.5 * side / math.tan(math.radians(fov) / 2)
        return cls.from_focal(width, height, focal, R=R, t=t)

    @classmethod
    def from_dict(cls, data: dict) -> "PinholeCamera":
        """Camera from a ``camera.json`` dict (keys fx, fy, cx, cy, width, height; optional R, t).

        Args:
            data: mapping with numbers ``fx, fy, cx, cy`` (pixels), ``width, height``
                (pixels) and optionally ``R`` (3x3 nested list) and ``t`` (3 numbers,
                metres).
        """
        if not isinstance(data, dict):
            raise InputError(
                f"camera data must be a dict (parsed camera.json), got {type(data).__name__}"
            )
        missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in data]
        if missing:
            raise InputError(
                f"camera.json is missing {', '.join(missing)}; it needs fx, fy, cx, cy, width, "
                "height (pixels) and optionally R (3x3) and t (3)"
            )
        return cls(
            fx=data["fx"], fy=data["fy"], cx=data["cx"], cy=data["cy"],
            width=data["width"], height=data["height"],
            R=data.get("R", np.eye(3)), t=data.get("t", np.zeros(3)),
        )

    @classmethod
    def from_file(cls, path) -> "PinholeCamera":
        """Camera from a ``camera.json`` file (the fields of :meth:`from_dict`).

        Args:
            path: path of the file (str or Path).

        Raises:
            DataError: the path does not exist, is not a regular file, or is not UTF-8 JSON.
            InputError: the JSON does not describe a camera (:meth:`from_dict`).
        """
        p = Path(path)
        if not p.exists():
            raise DataError(f"camera file not found: {p}")
        if not p.is_file():
            raise DataError(f"camera file {p} is not a file (a folder or a device?); give the path of a camera.json")
        try:
            text = p.read_bytes().decode("utf-8")
        except UnicodeDecodeError:
            raise DataError(f"{p} is not a text file (not UTF-8); a camera.json holds JSON text") from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise DataError(f"{p}:{e.lineno}: not valid JSON ({e.msg})") from None
        return cls.from_dict(data)

    def to_dict(self) -> dict:
        """JSON-ready dict for ``camera.json``.

        Returns:
            ``{"fx", "fy", "cx", "cy"}`` floats (pixels), ``{"width", "height"}`` ints
            (pixels), ``"R"`` 3x3 nested list, ``"t"`` list of 3 (metres).
        """
        return {
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
            "width": self.width, "height": self.height,
            "R": self.R.tolist(), "t": self.t.tolist(),
        }

    # ---------------------------------------------------------------------- properties

    @property
    def K(self) -> np.ndarray:
        """``(3, 3)`` float64 intrinsic matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def center(self) -> np.ndarray:
        """``(3,)`` camera centre in world coordinates, metres (``-R^T t``)."""
        return -self.R.T @ self.t

    def ray_rotation(self, u: float, v: float, share: float = 1.0) -> np.ndarray:
        """``(3, 3)`` rotation taking the optical axis ``(0, 0, 1)`` to the viewing ray through
        pixel ``(u, v)``, the smallest such (about an axis in the image plane); with ``share``,
        that rotation's angle times ``share`` about the same axis (0: the identity).

        A detector that lifts a person to 3D from a crop around them (MediaPipe's world
        landmarks) gives depth along the ray through the crop, not along the optical
        axis; ``ray_rotation(u, v) @ X`` turns such a point into the camera's axes. For a
        person 200 px from the centre of an 854 px wide video the two differ by ~15 degrees.
        """
        d = np.array([(u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0])
        d /= np.linalg.norm(d)
        axis = np.cross([0.0, 0.0, 1.0], d)
        s, c = np.linalg.norm(axis), d[2]
        if s < 1e-12:
            return np.eye(3)
        k = axis / s
        kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        if share != 1.0:
            angle = share * float(np.arctan2(s, c))
            s, c = np.sin(angle), np.cos(angle)
        return np.eye(3) + s * kx + (1.0 - c) * (kx @ kx)

    # ---------------------------------------------------------------------- projection

    def to_camera(self, points):
        """World points to camera coordinates, ``R @ X + t``.

        Args:
            points: ``(..., 3)`` world points in metres, torch (differentiable) or numpy.

        Returns:
            ``(..., 3)`` camera-frame points (x right, y down, z forward), same type.
        """
        if isinstance(points, np.ndarray):
            return self.to_camera(_from_numpy(points)).numpy()
        _check_points(points, 3, "points")
        R, t, _, _ = self._tensors(points.dtype, points.device)
        return points @ R.T + t

    def _tensors(self, dtype, device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``R (3, 3)``, ``t (3,)``, ``(fx, fy)`` and ``(cx, cy)`` as tensors of ``dtype`` on
        ``device``, made once per dtype and device (the camera is immutable)."""
        cache = self.__dict__.setdefault("_tensor_cache", {})
        key = (dtype, device)
        if key not in cache:
            cache[key] = tuple(torch.tensor(x, dtype=dtype, device=device) for x in
                               (self.R, self.t, [self.fx, self.fy], [self.cx, self.cy]))
        return cache[key]

    def depth(self, points):
        """Camera-frame depth ``Z`` of world points.

        Args:
            points: ``(..., 3)`` world points in metres, torch or numpy.

        Returns:
            ``(...)`` depth in metres (positive in front of the camera), same type.
        """
        return self.to_camera(points)[..., 2]

    def project(self, points):
        """Project world points to pixels: ``u = fx X/Z + cx``, ``v = fy Y/Z + cy``.

        ``(X, Y, Z)`` are the camera-frame coordinates ``R @ x + t``. The output is in
        the frame where pixel centres are at integer + 0.5 (the image spans
        ``[0, W] x [0, H]``; see the module docstring). Differentiable w.r.t. the points.

        Points behind the camera (``Z <= 0``) are projected anyway, without clipping:
        for ``Z < 0`` the result is mirrored through the principal point, for ``Z = 0`` it
        is inf/NaN. Callers that care (the renderer's near plane) check :meth:`depth`.

        Args:
            points: ``(..., 3)`` world points in metres, torch or numpy.

        Returns:
            ``(..., 2)`` pixel coordinates ``(x, y)`` (x to the right, y down), same type.
        """
        if isinstance(points, np.ndarray):
            return self.project(_from_numpy(points)).numpy()
        return self._pixels(self.to_camera(points))

    def project_with_depth(self, points):
        """:meth:`project` and :meth:`depth` of the same points from one change of frame.

        Args:
            points: ``(..., 3)`` world points in metres, torch (differentiable).

        Returns:
            ``(..., 2)`` pixel coordinates and ``(...)`` depths in metres, equal to what
            :meth:`project` and :meth:`depth` give.
        """
        pc = self.to_camera(points)
        return self._pixels(pc), pc[..., 2]

    def _pixels(self, pc: torch.Tensor) -> torch.Tensor:
        _, _, f, c = self._tensors(pc.dtype, pc.device)
        return pc[..., :2] / pc[..., 2:3] * f + c

    def unproject(self, pixels, depth):
        """Back-project pixels at given camera depths to world points (inverse of :meth:`project`).

        Args:
            pixels: ``(..., 2)`` pixel coordinates (centres at integer + 0.5), torch or numpy.
            depth: ``(...)`` camera-frame depth ``Z`` in metres, same type as ``pixels``.

        Returns:
            ``(..., 3)`` world points in metres, same type as ``pixels``.
        """
        if isinstance(pixels, np.ndarray):
            return self.unproject(_from_numpy(pixels), _from_numpy(np.asarray(depth))).numpy()
        _check_points(pixels, 2, "pixels")
        depth = torch.as_tensor(depth, dtype=pixels.dtype, device=pixels.device)
        f = torch.tensor([self.fx, self.fy], dtype=pixels.dtype, device=pixels.device)
        c = torch.tensor([self.cx, self.cy], dtype=pixels.dtype, device=pixels.device)
        xy = (pixels - c) / f * depth[..., None]
        pc = torch.cat([xy, depth[..., None].expand_as(xy[..., :1])], dim=-1)
        R = torch.tensor(self.R, dtype=pixels.dtype, device=pixels.device)
        t = torch.tensor(self.t, dtype=pixels.dtype, device=pixels.device)
        return (pc - t) @ R

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PinholeCamera):
            return NotImplemented
        return (
            (self.fx, self.fy, self.cx, self.cy, self.width, self.height)
            == (other.fx, other.fy, other.cx, other.cy, other.width, other.height)
            and np.array_equal(self.R, other.R)
            and np.array_equal(self.t, other.t)
        )

    __hash__ = None  # type: ignore[assignment]


def _half(size: Any) -> float:
    try:
        return 0.5 * float(size)
    except (TypeError, ValueError):
        raise InputError(f"camera width and height must be numbers of pixels, got {size!r}") from None


def _from_numpy(x: np.ndarray) -> torch.Tensor:
    """Copy a numpy array to a tensor, integers promoted to float64."""
    return torch.tensor(x if np.issubdtype(x.dtype, np.floating) else x.astype(np.float64))


def _check_points(x: Any, last: int, name: str) -> None:
    if not isinstance(x, torch.Tensor):
        raise InputError(
            f"{name} must be a torch.Tensor or numpy array of shape (..., {last}), "
            f"got {type(x).__name__}"
        )
    if x.dim() < 1 or x.shape[-1] != last:
        raise InputError(f"{name} must have shape (..., {last}), got {tuple(x.shape)}")
    if not x.is_floating_point():
        raise InputError(f"{name} must be floating point (float32 or float64), got {x.dtype}")
