"""The ground plane under a tracked person, and the world frame that stands on it.

A monocular result lives in its camera's frame: the floor is somewhere below, tilted by
the camera's pitch and roll. Feet that stand still touch the floor, so the floor is the
plane through the lowest points of still feet. This module works on plain arrays (no
body model): :func:`foot_contacts` labels still feet, :func:`fit_ground_plane` fits the
plane robustly, :func:`ground_frame` builds a frame with gravity up and the floor at
height 0.

Units are metres and seconds; every 3D point is in one frame (the result's world frame,
called "source" here). The ground frame is y up (glTF, Blender's glTF importer, three.js),
with ``x_ground = rotation @ x_source + offset``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flowmocap.errors import InputError

__all__ = ["GroundPlane", "foot_contacts", "fit_ground_plane", "ground_frame", "plane_prior_scatter"]


@dataclass(frozen=True)
class GroundPlane:
    """A plane ``normal . x = height`` with ``normal`` pointing up (away from gravity).

    Attributes:
        normal: ``(3,)`` unit normal, source frame.
        height: signed distance of the plane from the source origin along ``normal``, metres
            (a point ``x`` is ``normal . x - height`` metres above the floor).
        inliers: number of contact points that support the plane (0 for a fallback plane).
        residual_m: robust spread (1.4826 x median absolute deviation) of the inliers'
            heights above the plane, metres (``nan`` for a fallback plane).
        method: ``"contacts"`` (fitted to still feet) or ``"fallback"`` (no still feet: the
            prior normal through the lowest foot point, or at ``fallback_height`` below the
            origin).
    """

    normal: np.ndarray
    height: float
    inliers: int
    residual_m: float
    method: str

    def elevation(self, points: np.ndarray) -> np.ndarray:
        """Height above the plane of ``(..., 3)`` points, metres ``(...)``."""
        return np.asarray(points, np.float64) @ self.normal - self.height


def foot_contacts(feet: np.ndarray, fps: float, up: np.ndarray, max_speed: float = 0.3,
                  max_height: float = 0.06, speed_quantile: float = 0.25, speed_cap: float = 1.0) -> np.ndarray:
    """Which feet stand still on the ground, per frame.

    A foot is in contact when its lowest point moves slower than a threshold (central
    differences, metres per second) and lies within ``max_height`` of the lowest still
    points of the sequence (their 5th percentile), measured along ``up``. The threshold is
    ``max_speed``, raised to the ``speed_quantile`` of that foot's speeds (at most
    ``speed_cap``): a fitted stance foot slides and jitters, and a walking foot spends
    about 60 % of the time on the ground, so its slowest quarter is stance. The height
    test keeps a foot that hovers still in the air (a raised knee held) out.

    Args:
        feet: ``(T, F, 3)`` lowest point of each of F feet per frame, metres.
        fps: frames per second (Hz), > 0.
        up: ``(3,)`` direction of "up" (need not be unit length).
        max_speed: speed threshold, m/s.
        max_height: height band above the lowest still foot point, metres.

    Returns:
        ``(T, F)`` bool.
    """
    feet = np.asarray(feet, np.float64)
    if feet.ndim != 3 or feet.shape[2] != 3:
        raise InputError(f"feet must have shape (T, F, 3); got {feet.shape}.")
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"fps must be positive, got {fps}.")
    up = _unit(up, "up")
    T = feet.shape[0]
    if T < 2:
        return np.ones(feet.shape[:2], bool)
    speed = np.linalg.norm(np.gradient(feet, axis=0), axis=-1) * fps  # (T, F)
    limit = np.clip(np.quantile(speed, speed_quantile, axis=0), max_speed, max(speed_cap, max_speed))
    still = speed <= limit[None]
    h = feet @ up
    if not still.any():
        return still
    floor = np.percentile(h[still], 5)
    return still & (h < floor + max_height)


def plane_prior_scatter(points: np.ndarray, weights: np.ndarray, prior: np.ndarray,
                        prior_weight: float) -> tuple[np.ndarray, np.ndarray]:
    """The normal minimising ``sum_i w_i (n . (p_i - c))^2 + lam (1 - (n . n0)^2)``.

    The second term is ``lam sin^2`` of the angle to the prior normal ``n0``; it decides
    the directions the points do not (feet that step along one line leave the plane's
    tilt about that line open). The minimiser over unit ``n`` is the eigenvector of the
    smallest eigenvalue of ``S + lam (I - n0 n0^T)``, with ``S`` the weighted scatter
    about the weighted centroid ``c``.

    Args:
        points: ``(N, 3)`` metres. weights: ``(N,)`` >= 0. prior: ``(3,)`` unit normal.
        prior_weight: ``lam`` in square metres (weight-sum x squared metres).

    Returns:
        ``normal (3,)`` unit, on ``prior``'s side, and ``centroid (3,)``.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    w = np.asarray(weights, np.float64).reshape(-1)
    n0 = _unit(prior, "prior")
    c = (w[:, None] * p).sum(0) / max(w.sum(), 1e-12)
    d = p - c
    S = (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0)
    S = S + prior_weight * (np.eye(3) - np.outer(n0, n0))
    _, vecs = np.linalg.eigh(S)
    n = vecs[:, 0]
    return (n if n @ n0 >= 0 else -n), c


def fit_ground_plane(points: np.ndarray, prior_up: np.ndarray, fallback_points: np.ndarray | None = None,
                     fallback_height: float | None = None, max_tilt_deg: float = 30.0,
                     prior_sigma_deg: float = 5.0, iterations: int = 10, scale_m: float = 0.02) -> GroundPlane:
    """Fit the floor to contact points robustly (IRLS with Tukey's biweight).

    The plane's normal is pulled towards ``prior_up`` as if by ``prior_sigma_deg`` of
    angular noise (see :func:`plane_prior_scatter`), so a walk along a straight line (all
    contacts on one line) still gets a plane; points further than ``4.685 x`` the robust
    scale from the plane get zero weight. A fitted normal more than ``max_tilt_deg`` from
    ``prior_up`` is not believed, and neither are fewer than 3 points: then the plane is
    the fallback (``method="fallback"``) with normal ``prior_up``, through the lowest of
    ``fallback_points`` (e.g. every foot point of the sequence) or, without those, at
    ``fallback_height`` metres below the origin.

    Args:
        points: ``(N, 3)`` contact points (lowest points of still feet), metres.
        prior_up: ``(3,)`` the up direction expected before looking at the feet.
        fallback_points: ``(M, 3)`` points the floor must lie under, or None.
        fallback_height: metres from the origin down to the floor along ``prior_up``
            (e.g. the camera's assumed height above the floor), used when nothing else is.
        max_tilt_deg, prior_sigma_deg: degrees. iterations: IRLS steps.
        scale_m: smallest robust scale of the residuals, metres (fit noise of the feet).

    Returns:
        :class:`GroundPlane`.
    """
    n0 = _unit(prior_up, "prior_up")
    p = np.asarray(points, np.float64).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) >= 3:
        w = np.ones(len(p))
        lam_per_point = (scale_m / np.sin(np.radians(prior_sigma_deg))) ** 2
        n = n0
        h = float(np.median(p @ n0))
        sigma = scale_m
        for _ in range(iterations):
            n, _ = plane_prior_scatter(p, w, n0, lam_per_point * max(w.sum(), 1.0))
            r = p @ n
            h = _weighted_median(r, w) if w.sum() > 0 else float(np.median(r))
            res = r - h
            sigma = max(1.4826 * np.median(np.abs(res)), scale_m)
            u = res / (4.685 * sigma)
            w = np.where(np.abs(u) < 1, (1 - u ** 2) ** 2, 0.0)
        inl = w > 0
        tilt = np.degrees(np.arccos(np.clip(n @ n0, -1, 1)))
        if inl.sum() >= 3 and tilt <= max_tilt_deg:
            res = p[inl] @ n - h
            return GroundPlane(normal=n, height=float(h), inliers=int(inl.sum()),
                               residual_m=float(1.4826 * np.median(np.abs(res - np.median(res)))),
                               method="contacts")
    if fallback_points is not None and np.isfinite(np.asarray(fallback_points, np.float64)).any():
        q = np.asarray(fallback_points, np.float64).reshape(-1, 3)
        q = q[np.all(np.isfinite(q), axis=1)]
        return GroundPlane(normal=n0, height=float(np.min(q @ n0)), inliers=0, residual_m=float("nan"),
                           method="fallback")
    if fallback_height is None:
        raise InputError("no contact points and no fallback for the ground plane; give foot points or a "
                         "camera height.")
    return GroundPlane(normal=n0, height=-float(fallback_height), inliers=0, residual_m=float("nan"),
                       method="fallback")


def ground_frame(plane: GroundPlane, origin: np.ndarray, toward: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A y-up frame on the floor: ``x_ground = rotation @ x_source + offset``.

    ``+y`` is the plane's normal, the floor is ``y = 0``, the origin is ``origin``
    dropped onto the floor, and ``+z`` is ``toward - origin`` flattened onto the floor
    (e.g. ``toward`` = the camera centre: the camera then looks along ``-z`` as a glTF
    viewer's default camera, and a person facing the camera faces ``+z`` as SMPL's rest
    pose does). ``x = y cross z``; right-handed.

    Args:
        plane: the floor. origin, toward: ``(3,)`` source-frame points, metres.

    Returns:
        ``rotation (3, 3)`` (rows: the ground axes in source coordinates), ``offset (3,)``.
    """
    y = _unit(plane.normal, "normal")
    o = np.asarray(origin, np.float64).reshape(3)
    o = o - plane.elevation(o) * y
    z = np.asarray(toward, np.float64).reshape(3) - o
    z = z - (z @ y) * y
    if np.linalg.norm(z) < 1e-9:  # looking straight down: any horizontal direction
        z = np.cross(y, [1.0, 0.0, 0.0] if abs(y[0]) < 0.9 else [0.0, 0.0, 1.0])
    z = z / np.linalg.norm(z)
    x = np.cross(y, z)
    R = np.stack([x, y, z])
    return R, -R @ o


def _unit(v, name: str) -> np.ndarray:
    v = np.asarray(v, np.float64).reshape(-1)
    n = np.linalg.norm(v) if v.shape == (3,) else 0.0
    if not np.isfinite(n) or n < 1e-12:
        raise InputError(f"{name} must be a non-zero 3-vector; got {v}.")
    return v / n


def _weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    order = np.argsort(x)
    cw = np.cumsum(w[order])
    return float(x[order][np.searchsorted(cw, 0.5 * cw[-1])])
