"""Whether the camera turns during a clip, from the background.

flowmocap tracks the body in the camera's frame and assumes the camera stands still (the
README's limitations). A camera that pans or tilts does not spoil the poses: the body's
rendered flow and silhouette are compared with the images in that same moving frame. But
the body's path, its foot contacts and the floor fitted to them are then in a frame that
turns with the camera, until the export frames turn each frame back by the rotations found
here.

A camera that turns about its centre moves every background point by one homography
``H = K R K^-1`` between two frames. :func:`frame_rotation` tracks corners of the
background (OpenCV's Shi-Tomasi corners and pyramidal Lucas-Kanade, the person's pixels
left out), fits ``H`` robustly (RANSAC) and takes the rotation nearest ``K^-1 H K``;
:func:`camera_motion` chains them over the frames. Measured on the project's clips with the
tracked person's masks left out (docs/experiments.md, "A person seen again, ..."): DAVIS
dance-twirl turns 0.45 degrees a frame at the median, up to 29.4 degrees from where it
pointed in the first frame; the Sports2D walk (a camera on a stand, 230 frames) at most 0.26
degrees, and the four calibrated cameras of the real3d recording at most 0.07-0.51 (100
frames): the estimate's drift. :data:`MOVING_DEG` lies between.

Only the camera's turn is found, not a sideways move of it (a camera carried along): that
shows as a larger ``residual_px``. Nothing here changes the tracking; the export frames turn
each frame's body back by it (:mod:`flowmocap.export.motion`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flowmocap.errors import InputError

__all__ = ["CameraMotion", "frame_rotation", "camera_motion", "MOVING_DEG"]

#: A camera whose direction lies more than this many degrees from its first frame's in some
#: frame is said to move (the estimate's drift on the project's still cameras: at most 0.5 degrees).
MOVING_DEG = 2.0

#: A corner counts when, tracked to the next frame and back, it lands within this many pixels
#: of where it started (a corner lost, e.g. into a cut to another shot or a grey frame, does not).
FORWARD_BACK_PX = 1.0
#: A frame pair's turn is taken only where at least this share of the corners agree with it ...
MIN_INLIER_SHARE = 0.5
#: ... and it is at most this many degrees (300 degrees a second at 30 fps: no pan; a cut).
MAX_STEP_DEG = 10.0


@dataclass
class CameraMotion:
    """How the camera turned over a clip.

    Attributes:
        frames: ``(T,)`` the frame numbers.
        rotations: ``(T, 3, 3)`` each frame's camera orientation relative to the first:
            ``x_t = R_t x_0`` for a direction ``x_0`` in the first frame's camera axes
            (OpenCV axes; the first is the identity).
        turn_deg: ``(T,)`` the angle of each ``R_t``, degrees.
        residual_px: the median over frames of the median distance of the background
            points from where the fitted rotation puts them (pixels; large where the camera
            also moves sideways, or the background moves).
        unknown: frames whose rotation could not be fitted (too few background corners);
            the previous frame's rotation is kept there.
    """

    frames: np.ndarray
    rotations: np.ndarray
    turn_deg: np.ndarray
    residual_px: float
    unknown: list

    @property
    def moving(self) -> bool:
        """Whether the camera turned by more than :data:`MOVING_DEG` at some frame."""
        return bool(len(self.turn_deg) and np.nanmax(self.turn_deg) > MOVING_DEG)

    def to_dict(self, rotations: bool = False) -> dict:
        """A JSON summary: ``moving``, ``turn_deg_max``, ``turn_deg_end``, ``residual_px``,
        ``unknown_frames``; with ``rotations``, also ``rotvecs`` (T x 3 radians, the first
        frame's camera axes) and ``frames``."""
        from scipy.spatial.transform import Rotation

        doc = {"moving": self.moving, "turn_deg_max": round(float(np.nanmax(self.turn_deg, initial=0.0)), 2),
               "turn_deg_end": round(float(self.turn_deg[-1]) if len(self.turn_deg) else 0.0, 2),
               "residual_px": round(float(self.residual_px), 2), "unknown_frames": len(self.unknown)}
        if rotations:
            doc["frames"] = [int(f) for f in self.frames]
            doc["rotvecs"] = np.round(Rotation.from_matrix(self.rotations).as_rotvec(), 6).tolist()
        return doc


def _intrinsics(camera) -> np.ndarray:
    return np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])


def frame_rotation(prev: np.ndarray, cur: np.ndarray, K: np.ndarray, exclude: np.ndarray | None = None,
                   max_corners: int = 400, min_points: int = 20) -> tuple[np.ndarray, float] | None:
    """The camera's turn from one frame to the next, from the background.

    Args:
        prev, cur: ``(H, W, 3)`` uint8 RGB frames of one camera.
        K: ``(3, 3)`` the intrinsics (pixels).
        exclude: ``(H, W)`` bool pixels of ``prev`` not to take corners from (people), or None.
        max_corners: corners tracked at most; min_points: fewer tracked ones give None.

    Returns:
        ``(R, residual_px)``: ``R`` ``(3, 3)`` with ``x_cur = R x_prev`` for directions in
        the camera axes, and the median distance (pixels) of the tracked background points
        from where ``R`` puts them; None where too few corners could be tracked there and
        back (:data:`FORWARD_BACK_PX`), too few agree (:data:`MIN_INLIER_SHARE`) or the turn
        is too large for one frame (:data:`MAX_STEP_DEG`: a cut).

    Raises:
        InputError: frames of different sizes or not RGB.
    """
    import cv2

    prev, cur = np.asarray(prev), np.asarray(cur)
    if prev.shape != cur.shape or prev.ndim != 3 or prev.shape[2] < 3:
        raise InputError(f"frame_rotation needs two RGB frames of one size; got {prev.shape} and {cur.shape}.")
    g0 = cv2.cvtColor(np.ascontiguousarray(prev[..., :3]), cv2.COLOR_RGB2GRAY)
    g1 = cv2.cvtColor(np.ascontiguousarray(cur[..., :3]), cv2.COLOR_RGB2GRAY)
    allowed = None if exclude is None else np.where(np.asarray(exclude, bool), 0, 255).astype(np.uint8)
    p0 = cv2.goodFeaturesToTrack(g0, max_corners, 0.01, 8, mask=allowed)
    if p0 is None or len(p0) < min_points:
        return None
    p1, status, _ = cv2.calcOpticalFlowPyrLK(g0, g1, p0, None)
    back, status_back, _ = cv2.calcOpticalFlowPyrLK(g1, g0, p1, None)  # tracked back: a corner lost comes back elsewhere
    ok = (status[:, 0] == 1) & (status_back[:, 0] == 1) & (np.linalg.norm(back - p0, axis=-1)[:, 0] < FORWARD_BACK_PX)
    a, b = p0[ok, 0].astype(np.float64), p1[ok, 0].astype(np.float64)
    if len(a) < min_points:
        return None
    H, inliers = cv2.findHomography(a, b, cv2.RANSAC, 1.5)
    if H is None or inliers is None or inliers.sum() < max(min_points, MIN_INLIER_SHARE * len(a)):
        return None
    M = np.linalg.inv(K) @ H @ K
    d = np.linalg.det(M)
    if not np.isfinite(d) or abs(d) < 1e-12:
        return None
    U, _, Vt = np.linalg.svd(M / np.cbrt(d))
    R = U @ Vt
    if np.linalg.det(R) < 0:
        return None
    if np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))) > MAX_STEP_DEG:
        return None
    moved = cv2.perspectiveTransform(a[None], K @ R @ np.linalg.inv(K))[0]
    return R, float(np.median(np.linalg.norm(moved - b, axis=1)))


def camera_motion(seq, camera, frames: range | None = None, masks: bool = True, dilate_px: int = 15,
                  progress: bool = False) -> CameraMotion:
    """:func:`frame_rotation` chained over ``frames`` of ``seq``.

    Args:
        seq: ``seq.frame(i)`` ``(H, W, 3)`` uint8 RGB, and with ``masks`` ``seq.mask(i)``
            (the person's pixels, or None) left out, grown by ``dilate_px``.
        camera: the tracked camera (its intrinsics, pixels of ``seq``'s frames).
        frames: the frames (default all).
        progress: show a progress bar.

    Returns:
        :class:`CameraMotion` (the first frame's rotation the identity).
    """
    import cv2
    from tqdm import tqdm

    frames = range(len(seq)) if frames is None else frames
    K = _intrinsics(camera)
    Rs = [np.eye(3)]
    residuals, unknown = [], []
    kernel = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
    prev = seq.frame(frames[0]).copy() if len(frames) else None
    for i in tqdm(frames[1:], disable=not progress, unit="frame", desc="camera motion"):
        cur = seq.frame(i).copy()
        exclude = None
        if masks:
            m = seq.mask(i - 1) if hasattr(seq, "mask") else None
            if m is not None and np.asarray(m).any():
                exclude = cv2.dilate(np.asarray(m, np.uint8), kernel) > 0
        got = frame_rotation(prev, cur, K, exclude)
        if got is None:
            unknown.append(int(i))
            Rs.append(Rs[-1])
        else:
            Rs.append(got[0] @ Rs[-1])
            residuals.append(got[1])
        prev = cur
    R = np.asarray(Rs, np.float64)
    turn = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    return CameraMotion(np.asarray(list(frames), np.int64), R, turn,
                        float(np.median(residuals)) if residuals else float("nan"), unknown)
