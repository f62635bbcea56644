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
:func:`camera_motion` finds each frame's turn against a keyframe, which moves on as the
camera turns away from it (:data:`KEYFRAME_MAX_PX`): turns chained frame by frame drifted.
Measured on the project's clips with everyone the detector sees left out, each turn fitted
with the zoom (below; docs/experiments.md, "A camera that zooms"): DAVIS dance-twirl turns up
to 37.7 degrees from where it pointed in the first frame (29.2 with the turn alone, which took
some of its zoom for a turn); the Sports2D walk (a camera on a stand, 230 frames) at most 0.02
degrees (0.08 with the turn alone), and the four calibrated cameras of the real3d recording at
most 0.00-0.01 (100 frames; 0.01-0.04 with the turn alone; chained frame by frame, up to 2.24
with the first person walking through the background): the estimate's drift.
:data:`MOVING_DEG` lies between.

A camera that zooms scales the image about its centre as well: ``H = K Z R K^-1``, ``Z =
diag(z, z, 1)`` with ``z`` its focal length over the first frame's. Each pair's turn and zoom
are fitted together (:func:`frame_turn_zoom`): the still cameras of the project's clips come
out at 0.999-1.000, DAVIS dance-twirl zooms out to 0.62 of its first focal length over its
90 frames (the turn alone left its background corners 2.8 px off, the median over its frames;
turn and zoom 1.0 px). A tracker that
keeps one focal length sees a person shrink as the camera zooms out and puts them further
away; the export frames bring each frame's body back to the depth its focal length gives
(:mod:`flowmocap.export.motion`), where no move of the camera is undone. Over one frame a
camera carried forward over a floor looks much like one that zooms in (the synthetic dolly
shots below come out "zooming" by 0.94-1.33): a move the floor shows and the body agrees with
is undone instead of the zoom, and the zoom where it is not.

A camera that also moves (carried along, on a dolly or a vehicle) moves the points of the
floor by the homography a plane induces, ``H = K (R + tau n^T) K^-1``, where ``n`` is the
floor's normal in the earlier frame's camera axes (pointing down, to the floor) and ``tau``
the camera's move in units of its height above the floor. :func:`floor_motion` tracks
corners of the floor near the person's feet, searches the floor's normal with which the frame
pairs that show a move are explained best (their turns and moves fitted and chained), believes
the move only where it explains the floor's corners clearly better than a turn and a zoom, then
fits each pair's turn and move with that normal and chains them: the camera's path in units of
its height above the floor in the first frame. That height, in metres, is not in the
images; the export frames take it from the fitted body's feet on the floor
(:mod:`flowmocap.export.motion`), so the path comes out in metres and the body is moved back
by it. A camera whose centre stays within :data:`SIDEWAYS_SHARE` of its height of where it
started is taken not to move (only its turn, if any, is kept): the still cameras of the
project's clips stay within that (``docs/experiments.md``, "A camera carried along").

Nothing here changes the tracking; the export frames turn (and move) each frame's body back by
it (:mod:`flowmocap.export.motion`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flowmocap.errors import InputError

__all__ = ["CameraMotion", "frame_rotation", "frame_turn_zoom", "focal_from_turns", "camera_motion", "floor_motion",
           "floor_region", "MOVING_DEG", "ZOOMING", "SIDEWAYS_SHARE"]

#: A camera whose direction lies more than this many degrees from its first frame's in some
#: frame is said to move (the estimate's drift on the project's still cameras: at most 0.5 degrees).
MOVING_DEG = 2.0

#: A camera whose focal length lies more than this share above or below its first frame's in
#: some frame is said to zoom (the still cameras of the project's clips: within 0.1 %).
ZOOMING = 0.02

#: A corner counts when, tracked to the next frame and back, it lands within this many pixels
#: of where it started (a corner lost, e.g. into a cut to another shot or a grey frame, does not).
FORWARD_BACK_PX = 1.0
#: A frame pair's turn is taken only where at least this share of the corners agree with it ...
MIN_INLIER_SHARE = 0.5
#: ... and it is at most this many degrees (300 degrees a second at 30 fps: no pan; a cut).
MAX_STEP_DEG = 10.0
#: Each frame's turn is found against a keyframe, not chained from the frame before (which
#: drifts: 2.0-2.2 degrees over 100 frames of a still real3d camera with the other person
#: walking through the background); the keyframe moves on where the turn from it moves the
#: image's centre more than this many pixels, or where the frame cannot be matched with it.
KEYFRAME_MAX_PX = 40.0

#: A camera is said to move sideways where its centre lies further than this share of its
#: height above the floor from where it was in the first frame (15 cm for a camera held 1.5 m up).
SIDEWAYS_SHARE = 0.1
#: Frame pairs whose floor shows a move of at least this share of the camera's height tell the
#: floor's normal (a pair that only turns leaves it open).
NORMAL_MIN_MOVE = 0.01
#: ... and whose floor corners move by at least this many pixels (median): the homography of a
#: still floor is noise, and noise decomposes into any move (one pair of a still real3d camera,
#: its corners 0.004 px apart, showed a move and brought the move's cost share to 0.668).
MOVE_MIN_PX = 0.5
#: A move is believed only where, over the pairs the floor's normal is searched with, it
#: leaves at most this share of the floor corners' cost that a turn and a zoom leave.
MOVE_EVIDENCE = 0.7
#: Floor corners are taken from the image rows below the person's lowest pixel less this share
#: of their height (the floor about their feet), or without a person from the lowest
#: :data:`FLOOR_ROWS_NO_PERSON` of the image.
FEET_MARGIN = 0.1
FLOOR_ROWS_NO_PERSON = 0.4
#: Where the floor gives too few corners of the background's quality (OpenCV's quality level
#: 0.01, relative to the strongest corner), they are taken down to this one (a floor near the
#: camera is often smooth; a corner that does not come back when tracked there and back is
#: left out anyway). Not at once: on the still real3d cameras the weaker corners brought the
#: move's cost share from 0.915 down to 0.807, nearer the 0.7 that believes a move.
FLOOR_CORNER_QUALITY = 0.002

#: The focal length is read from the background (:func:`focal_from_turns`) only where the
#: camera turns by at least this many degrees (a turn's perspective tells the focal length;
#: the turn of a still camera is noise) ...
FOCAL_MIN_TURN_DEG = 5.0
#: ... and kept only where the background's fit is at least this many times worse at 0.8 and
#: at 1.25 times the estimate than at it (else the background does not tell).
FOCAL_SHARPNESS = 1.1
#: The frame pairs it reads at most: those that turn the most.
FOCAL_PAIRS = 30
#: The focal lengths it searches, as shares of the image's long side (fields of view of
#: 14-118 degrees across it).
FOCAL_RANGE = (0.3, 4.0)


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
        shifts: ``(T, 3)`` where the camera moved sideways (:attr:`moving_sideways`), each
            frame's move in its own axes in units of the camera's height above the floor in the
            first frame ``h``: ``x_t = F_t x_0 + h shifts_t`` for a point's camera coordinates
            (the first row zero), ``F_t`` the floor's turns ``floor_rotations``
            (:func:`floor_motion`; the whole background's ``rotations`` are bent by the move).
            None where the camera did not move sideways or the floor could not tell.
        floor_rotations: ``(T, 3, 3)`` the turns that go with ``shifts``, or None.
        floor_normal: ``(3,)`` the floor's unit normal in the first frame's camera axes,
            pointing down (to the floor), where the floor showed a move; else None.
        sideways: the largest distance of the camera's centre from where it was in the first
            frame, in units of ``h`` (NaN where the floor could not tell).
        floor_unknown: frames whose floor motion could not be fitted (held from the frame before).
        move_share: where some frame pair's floor showed a move, the share of the cost a turn
            and a zoom leave on the floor's corners that the move leaves (:data:`MOVE_EVIDENCE`);
            NaN where none did.
        zooms: ``(T,)`` each frame's focal length over the first frame's (1 where the camera
            does not zoom; below 1 where it zooms out), or None where not found.
        focal: where asked for and the camera turned enough, the first frame's focal length
            the background's turns give (:func:`focal_from_turns`: ``focal_px``, ``used_px``
            the one the motion was fitted with, ``ratio`` the two's, ``pairs``, ``sharpness``);
            else None.
    """

    frames: np.ndarray
    rotations: np.ndarray
    turn_deg: np.ndarray
    residual_px: float
    unknown: list
    shifts: np.ndarray | None = None
    floor_rotations: np.ndarray | None = None
    floor_normal: np.ndarray | None = None
    sideways: float = float("nan")
    floor_unknown: list | None = None
    move_share: float = float("nan")
    zooms: np.ndarray | None = None
    focal: dict | None = None

    @property
    def zooming(self) -> bool:
        """Whether the focal length moved by more than :data:`ZOOMING` of the first frame's."""
        return bool(self.zooms is not None and len(self.zooms)
                    and np.nanmax(np.abs(np.log(self.zooms))) > np.log1p(ZOOMING))

    @property
    def turning(self) -> bool:
        """Whether the camera turned by more than :data:`MOVING_DEG` at some frame."""
        return bool(len(self.turn_deg) and np.nanmax(self.turn_deg) > MOVING_DEG)

    @property
    def moving_sideways(self) -> bool:
        """Whether the camera's centre moved by more than :data:`SIDEWAYS_SHARE` of its height
        above the floor (``shifts`` then holds the move)."""
        return self.shifts is not None

    @property
    def moving(self) -> bool:
        """Whether the camera turned (:attr:`turning`), zoomed (:attr:`zooming`) or moved
        sideways (:attr:`moving_sideways`)."""
        return self.turning or self.zooming or self.moving_sideways

    def centres(self) -> np.ndarray | None:
        """``(T, 3)`` the camera's centre in each frame in the first frame's camera axes, in
        units of its height above the floor there (``-F_t^T shifts_t``); None without a move."""
        if self.shifts is None:
            return None
        return -np.einsum("tji,tj->ti", self.floor_rotations, self.shifts)

    def to_dict(self, rotations: bool = False) -> dict:
        """A JSON summary: ``moving``, ``turn_deg_max``, ``turn_deg_end``, ``residual_px``,
        ``unknown_frames``, ``sideways_max`` (units of the camera's height above the floor, or
        None), ``move_share`` (or None), ``moving_sideways``, ``zooming`` and ``zoom_min`` /
        ``zoom_max`` (the focal length over the first frame's), ``focal`` where found
        (:attr:`focal`); with ``rotations``, also
        ``rotvecs`` (T x 3 radians, the first frame's camera axes) and ``frames``, where the
        camera zoomed ``zooms`` (T), and where it moved sideways ``shifts`` (T x 3),
        ``floor_rotvecs`` (T x 3), ``floor_normal`` (3) and ``floor_unknown_frames``."""
        from scipy.spatial.transform import Rotation

        doc = {"moving": self.moving, "turn_deg_max": round(float(np.nanmax(self.turn_deg, initial=0.0)), 2),
               "turn_deg_end": round(float(self.turn_deg[-1]) if len(self.turn_deg) else 0.0, 2),
               "residual_px": round(float(self.residual_px), 2), "unknown_frames": len(self.unknown),
               "sideways_max": None if not np.isfinite(self.sideways) else round(float(self.sideways), 3),
               "move_share": None if not np.isfinite(self.move_share) else round(float(self.move_share), 3),
               "moving_sideways": self.moving_sideways, "zooming": self.zooming}
        if self.focal is not None:
            doc["focal"] = self.focal
        if self.zooms is not None and len(self.zooms):
            doc["zoom_min"], doc["zoom_max"] = round(float(np.min(self.zooms)), 4), round(float(np.max(self.zooms)), 4)
        if rotations:
            doc["frames"] = [int(f) for f in self.frames]
            doc["rotvecs"] = np.round(Rotation.from_matrix(self.rotations).as_rotvec(), 6).tolist()
            if self.zooming:
                doc["zooms"] = np.round(self.zooms, 6).tolist()
            if self.shifts is not None:
                doc["shifts"] = np.round(self.shifts, 6).tolist()
                doc["floor_rotvecs"] = np.round(Rotation.from_matrix(self.floor_rotations).as_rotvec(), 6).tolist()
                doc["floor_normal"] = np.round(self.floor_normal, 6).tolist()
                doc["floor_unknown_frames"] = len(self.floor_unknown or [])
        return doc


def _intrinsics(camera) -> np.ndarray:
    return np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])


def _homography(prev: np.ndarray, cur: np.ndarray, exclude: np.ndarray | None, max_corners: int, min_points: int,
                who: str, quality: float = 0.01, spacing: int = 8
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Corners of ``prev`` outside ``exclude`` tracked into ``cur`` and back, and the
    homography most of them agree with: ``(a, b, H, agree)``, ``a``/``b`` ``(N, 2)`` the
    tracked corners' pixels in each frame and ``agree`` ``(N,)`` bool those that agree with
    ``H``; None where too few are tracked or agree. ``quality`` and ``spacing`` (px) are
    OpenCV's ``goodFeaturesToTrack`` quality level and minimum distance."""
    import cv2

    prev, cur = np.asarray(prev), np.asarray(cur)
    if prev.shape != cur.shape or prev.ndim != 3 or prev.shape[2] < 3:
        raise InputError(f"{who} needs two RGB frames of one size; got {prev.shape} and {cur.shape}.")
    g0 = cv2.cvtColor(np.ascontiguousarray(prev[..., :3]), cv2.COLOR_RGB2GRAY)
    g1 = cv2.cvtColor(np.ascontiguousarray(cur[..., :3]), cv2.COLOR_RGB2GRAY)
    allowed = None if exclude is None else np.where(np.asarray(exclude, bool), 0, 255).astype(np.uint8)
    p0 = cv2.goodFeaturesToTrack(g0, max_corners, quality, spacing, mask=allowed)
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
    return a, b, H, inliers[:, 0].astype(bool)


def _calibrated_homography(prev, cur, K: np.ndarray, exclude, max_corners: int, min_points: int, who: str):
    """:func:`_homography` of the background between two frames, in the camera's normalised
    coordinates: ``(a, b, agree, M)`` with ``M = K^-1 H K`` scaled to determinant 1; None
    where :func:`_homography` gives none or ``M`` is singular."""
    got = _homography(prev, cur, exclude, max_corners, min_points, who)
    if got is None:
        return None
    a, b, H, agree = got
    M = np.linalg.inv(K) @ H @ K
    d = np.linalg.det(M)
    if not np.isfinite(d) or abs(d) < 1e-12:
        return None
    return a, b, agree, M / np.cbrt(d)


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

    got = _calibrated_homography(prev, cur, K, exclude, max_corners, min_points, "frame_rotation")
    if got is None:
        return None
    a, b, _, M = got
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        return None
    if _angle(R) > MAX_STEP_DEG:
        return None
    moved = cv2.perspectiveTransform(a[None], K @ R @ np.linalg.inv(K))[0]
    return R, float(np.median(np.linalg.norm(moved - b, axis=1)))


def frame_turn_zoom(prev: np.ndarray, cur: np.ndarray, K: np.ndarray, exclude: np.ndarray | None = None,
                    max_corners: int = 400, min_points: int = 20, found: list | None = None
                    ) -> tuple[np.ndarray, float, float] | None:
    """The camera's turn and zoom from one frame to the next, from the background.

    The background's corners (as :func:`frame_rotation`) fitted through ``K Z R K^-1``,
    ``Z = diag(z, z, 1)``: a turn ``R`` and the focal length scaled by ``z`` (robust least
    squares on the corners that agree with the pair's homography, from the rotation nearest
    that homography and the zoom its rows give).

    Args:
        prev, cur, K, exclude, max_corners, min_points: as :func:`frame_rotation` (``K`` the
            intrinsics of ``prev``).
        found: a list to append the pair's agreeing corners to, ``(a, b, H)`` (``(N, 2)``
            pixels of ``prev`` and ``cur``, the pixel homography), where the fit is kept
            (:func:`focal_from_turns` reads them).

    Returns:
        ``(R, z, residual_px)``: ``x_cur = R x_prev`` for directions in the camera axes,
        ``cur``'s focal length over ``prev``'s, and the median distance (pixels) of the tracked
        background points from where the two put them; None as for :func:`frame_rotation`
        (and where the zoom is more than a third either way: a cut).

    Raises:
        InputError: frames of different sizes or not RGB.
    """
    from scipy.spatial.transform import Rotation

    got = _calibrated_homography(prev, cur, K, exclude, max_corners, min_points, "frame_turn_zoom")
    if got is None:
        return None
    a, b, agree, M = got
    fit = _turn_zoom_fit(a[agree], b[agree], M, K)
    if fit is None:
        return None
    x, _, moved = fit
    R, z = Rotation.from_rotvec(x[:3]).as_matrix(), float(np.exp(x[3]))
    if np.degrees(np.linalg.norm(x[:3])) > MAX_STEP_DEG or not 0.75 < z < 1.33:
        return None
    if found is not None:
        found.append((a[agree], b[agree], K @ M @ np.linalg.inv(K)))
    return R, z, float(np.median(np.linalg.norm(moved(x, _rays(K, a)) - b, axis=1)))


def _turn_zoom_fit(a: np.ndarray, b: np.ndarray, M: np.ndarray, K: np.ndarray):
    """``K Z R K^-1`` fitted to corners ``a`` -> ``b`` (``(N, 2)`` pixels) from ``M``, the
    pair's homography in ``K``'s normalised coordinates (determinant 1): ``(x, cost, moved)``
    with ``x`` the turn's rotation vector and the zoom's log, ``cost`` the robust least
    squares' (soft L1, 1 px) and ``moved(x, rays)`` the pixels ``x`` puts the rays
    ``_rays(K, px)`` of pixels ``px`` at; None where
    ``M``'s zoom is more than a third either way or it holds a reflection."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    z0 = float(np.linalg.norm(M[:2], axis=1).mean() / max(np.linalg.norm(M[2]), 1e-12))
    if not 0.67 < z0 < 1.5:
        return None
    U, _, Vt = np.linalg.svd(np.diag([1.0 / z0, 1.0 / z0, 1.0]) @ M)
    R0 = U @ Vt
    if np.linalg.det(R0) < 0:
        return None
    f, c = np.array([K[0, 0], K[1, 1]]), np.array([K[0, 2], K[1, 2]])

    def moved(x, rays):
        p = rays @ Rotation.from_rotvec(x[:3]).as_matrix().T
        return p[:, :2] / p[:, 2:3] * np.exp(x[3]) * f + c

    # the floor fit's model without a move (the pixels moved() gives), its Jacobian in closed form
    rays, unused = _rays(K, a), np.zeros(3)
    fit = least_squares(lambda x: _pair_residual(x, rays, b, K, unused, False, True),
                        np.r_[Rotation.from_matrix(R0).as_rotvec(), np.log(z0)],
                        jac=lambda x: _pair_jacobian(x, rays, K, unused, False, True),
                        loss="soft_l1", f_scale=1.0, x_scale=0.01)
    return fit.x, float(fit.cost), moved


def focal_from_turns(pairs: list, centre: tuple[float, float], side: float) -> tuple[float, float] | None:
    """The focal length a turning camera's background gives.

    A turn about the camera's centre moves the image by a homography ``K Z R K^-1`` that
    only the right focal length in ``K`` fits: a wrong one bends the background's corners off
    it, the more the larger the turn. So each pair's turn and zoom are fitted
    (:func:`_turn_zoom_fit`) with focal lengths searched over :data:`FOCAL_RANGE` times
    ``side``, and the one whose summed robust cost is least is kept.

    Args:
        pairs: per frame pair ``(a, b, H, scale)``: the background's corners ``(N, 2)`` in
            pixels of the two frames, the pair's pixel homography ``(3, 3)``, and the first
            frame's focal length relative to the clip's first frame (the zoom so far).
        centre: the principal point ``(cx, cy)``, pixels.
        side: the image's long side, pixels.

    Returns:
        ``(focal_px, sharpness)``: the clip's first frame's focal length (pixels) and how much
        worse the fit is at 0.8 and 1.25 times it (the smaller of the two cost ratios); None
        without pairs, or where the least cost lies at the end of the range searched.
    """
    from scipy.optimize import minimize_scalar

    if not pairs:
        return None

    def cost(log_f):
        total = 0.0
        for a, b, H, scale in pairs:
            f = np.exp(log_f) * scale
            K = np.array([[f, 0.0, centre[0]], [0.0, f, centre[1]], [0.0, 0.0, 1.0]])
            M = np.linalg.inv(K) @ H @ K
            d = np.linalg.det(M)
            fit = _turn_zoom_fit(a, b, M / np.cbrt(d), K) if np.isfinite(d) and abs(d) > 1e-12 else None
            total += fit[1] / len(a) if fit is not None else 1e3  # a pair it cannot fit: far off
        return total

    lo, hi = np.log(FOCAL_RANGE[0] * side), np.log(FOCAL_RANGE[1] * side)
    grid = np.linspace(lo, hi, 12)
    costs = [cost(g) for g in grid]
    k = int(np.argmin(costs))
    if k in (0, len(grid) - 1):
        return None
    best = minimize_scalar(cost, bounds=(grid[k - 1], grid[k + 1]), method="bounded", options={"xatol": 1e-3})
    f, c0 = float(np.exp(best.x)), float(best.fun)
    sharp = min(cost(best.x + np.log(0.8)), cost(best.x + np.log(1.25))) / max(c0, 1e-12)
    return f, float(sharp)


def _zoomed(K: np.ndarray, z: float) -> np.ndarray:
    """``K`` with its focal lengths scaled by ``z`` (the principal point kept)."""
    return np.array([[K[0, 0] * z, K[0, 1] * z, K[0, 2]], [0.0, K[1, 1] * z, K[1, 2]], [0.0, 0.0, 1.0]])


def _step_px(R: np.ndarray, z: float, K: np.ndarray) -> float:
    """How far a turn ``R`` and zoom ``z`` move the image's centre, or its corners by the
    zoom alone, pixels (whichever is more)."""
    return max(_turn_px(R, K), abs(z - 1.0) * float(np.hypot(K[0, 2], K[1, 2])))


def _turn_px(R: np.ndarray, K: np.ndarray) -> float:
    """How far the turn ``R`` moves the image's centre, pixels."""
    c = np.array([K[0, 2], K[1, 2], 1.0])
    p = K @ R @ np.linalg.inv(K) @ c
    return float(np.linalg.norm(p[:2] / p[2] - c[:2]))


def floor_region(shape: tuple, mask: np.ndarray | None = None) -> np.ndarray:
    """``(H, W)`` bool: the pixels floor corners are taken from: the rows below the person's
    lowest pixel less :data:`FEET_MARGIN` of their height (the floor about their feet), or the
    lowest :data:`FLOOR_ROWS_NO_PERSON` of the image where ``mask`` (``(H, W)`` bool, the
    person) is None or empty. The person's own pixels are left out by the caller."""
    H, W = shape[:2]
    start = (1.0 - FLOOR_ROWS_NO_PERSON) * H
    if mask is not None and np.asarray(mask).any():
        rows = np.flatnonzero(np.asarray(mask, bool).any(1))
        start = rows[-1] - FEET_MARGIN * (rows[-1] - rows[0])
    return np.broadcast_to(np.arange(H)[:, None] >= start, (H, W)).copy()


def _rays(K: np.ndarray, px: np.ndarray) -> np.ndarray:
    return np.c_[px, np.ones(len(px))] @ np.linalg.inv(K).T


def _plane_normal(pairs: list, chain: np.ndarray, K: np.ndarray, zooms: np.ndarray | None = None
                  ) -> tuple[np.ndarray, float] | None:
    """The floor's normal in the first frame's camera axes, from the pairs that show a move
    (:data:`NORMAL_MIN_MOVE`; None where none does): the normal with which the pairs' turns
    and moves (:func:`_fit_pair`) leave the floor's corners nearest where they are seen (the
    sum of squared distances cut at 3 px, over the :data:`NORMAL_PAIRS` pairs from the first
    that moves, their turns chained), searched on a grid of tilts about the camera's down and
    then refined (Nelder-Mead). Returns the normal and the share of the cost a turn and a zoom
    leave (each pair its own, no move; the earlier frame seen with its focal length of ``zooms``,
    ``(T,)`` times the first frame's, the background's, where given) that the move leaves (near
    1: the floor shows no move; a camera on a tripod that zooms over a floor moves its corners
    much as a move forward would).

    One pair alone tells the normal poorly: over a frame a small move sideways looks much
    like a small turn, and only the floor's near corners moving more than its far ones tell
    them apart. The decomposition of each pair's homography (OpenCV) was 10-15 degrees off
    on synthetic dolly shots where this search is within a degree or two; it is used only to
    tell which pairs show a move."""
    from scipy.optimize import minimize
    from scipy.spatial.transform import Rotation

    moving = _moving_pairs(pairs, chain, K)
    if not moving:
        return None
    window = range(moving[0], min(len(pairs), moving[0] + NORMAL_PAIRS))  # from the first pair that moves
    last: dict = {}  # (pair, move) -> its latest fit (R, tau): the next normal's fit starts there

    def normal(angles):  # in the axes of the window's first frame
        return Rotation.from_euler("xz", angles).as_matrix() @ np.array([0.0, 1.0, 0.0])

    def cost(angles, move=True, above=np.inf, zoom=False):
        """The cost at the normal of ``angles``; once the sum (of terms >= 0) passes ``above``,
        that sum at once: the rest cannot bring it back. ``zoom``: each pair with a zoom too."""
        n, R_k, total = normal(angles), np.eye(3), 0.0
        for k in window:
            if pairs[k] is None:
                continue
            a, b, _ = pairs[k]
            K_k = _zoomed(K, float(zooms[k])) if zoom and zooms is not None else K
            got = _fit_pair(a, b, K_k, R_k @ n, chain[k + 1] @ chain[k].T, move, last.get((k, move, zoom)), zoom)
            if got is None:
                total += 9.0 * len(a)
            else:
                last[(k, move, zoom)] = got[:2]
                total += float(np.sum(np.minimum(got[3], 3.0) ** 2)) + 9.0 * (len(a) - len(got[3]))  # off the floor: cut
                R_k = got[0] @ R_k  # the floor's own turn (the background's is bent by the move)
            if total > above:
                return total
        return total

    lo, hi = np.radians([-20.0, -30.0]), np.radians([60.0, 30.0])  # the tilts searched: a camera upright-ish
    grid = [(np.radians(x), np.radians(z)) for x in range(-20, 61, 10) for z in range(-30, 31, 10)]
    start, least = grid[0], np.inf  # the grid's first least cost (as min() would), the rest cut short
    for g in grid:
        c = cost(g, above=least)
        if c < least:
            start, least = g, c
    bounded = lambda x: cost(x) if np.all((x >= lo) & (x <= hi)) else np.inf  # noqa: E731
    best = minimize(bounded, np.asarray(start), method="Nelder-Mead",
                    options={"xatol": np.radians(0.2), "fatol": 1e-3, "initial_simplex":
                             np.asarray(start) + np.radians([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]])})
    # the evidence for a move: the floor's corners with the move against with a turn and a zoom
    # (a zoom moves the floor's corners much as a move forward does, a turn alone cannot tell)
    no_move = min(cost(best.x, move=False), cost(best.x, move=False, zoom=True))
    share = best.fun / no_move if no_move > 0 else 1.0
    # into the first frame's axes, through the background's turn up to the window (no move there)
    return chain[window[0]].T @ normal(best.x), float(share)


#: Frame pairs the floor's normal is searched with, at most (from the first that moves).
NORMAL_PAIRS = 40


def _moving_pairs(pairs: list, chain: np.ndarray, K: np.ndarray) -> list[int]:
    """The pairs whose floor corners move by at least :data:`MOVE_MIN_PX` and whose floor
    homography, decomposed (OpenCV), shows a move of at least :data:`NORMAL_MIN_MOVE` of the
    camera's height in its solution with the floor in front of the corners and the normal
    nearest the camera's down."""
    import cv2

    out = []
    down = np.array([0.0, 1.0, 0.0])
    for k, pair in enumerate(pairs):
        if pair is None:
            continue
        a, b, H = pair
        if np.median(np.linalg.norm(b - a, axis=1)) < MOVE_MIN_PX:
            continue
        _, _, ts, ns = cv2.decomposeHomographyMat(H, K)
        rays = _rays(K, a)
        best = None
        for t, n in zip(ts, ns):
            n, t = n[:, 0], t[:, 0]
            if np.median(rays @ n) <= 0:  # the corners would lie behind the plane
                continue
            n0 = chain[k].T @ n  # into the first frame's axes
            if best is None or n0 @ down > best[0] @ down:
                best = (n0, float(np.linalg.norm(t)))
        if best is not None and best[1] >= NORMAL_MIN_MOVE and best[0] @ down > 0:
            out.append(k)
    return out


def _fit_pair(a: np.ndarray, b: np.ndarray, K: np.ndarray, n: np.ndarray, R0: np.ndarray, move: bool = True,
              start: tuple | None = None, zoom: bool = False):
    """The turn ``R`` and move ``tau`` (units of the camera's height above the floor in the
    earlier frame) that carry the floor corners ``a`` onto ``b`` through
    ``K (R + tau n^T) K^-1``, the median distance (px) they leave and each corner's distance;
    robust least squares from ``R0`` and no move, or from ``start`` = ``(R, tau)`` where given
    (a fit of the same pair with a normal near ``n``: fewer steps to the same minimum); None
    with fewer than 8 corners on the floor. ``move=False`` fits the turn alone (``tau`` zero);
    ``zoom`` fits a zoom of the later frame too (``K`` scaled about its principal point;
    :func:`_pair_residual`)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    rays = _rays(K, a)
    on = rays @ n > 1e-6  # corners whose ray meets the floor
    rays, b = rays[on], b[on]
    if len(rays) < 8:
        return None

    def residual(x):
        return _pair_residual(x, rays, b, K, n, move, zoom)

    def jacobian(x):
        return _pair_jacobian(x, rays, K, n, move, zoom)

    R_start, tau_start = (R0, np.zeros(3)) if start is None else start
    x0 = Rotation.from_matrix(R_start).as_rotvec()
    if move:
        x0 = np.r_[x0, tau_start]
    if zoom:
        x0 = np.r_[x0, 0.0]
    fit = least_squares(residual, x0, jac=jacobian, loss="soft_l1", f_scale=1.0, x_scale=0.01)
    r = np.linalg.norm(fit.fun.reshape(-1, 2), axis=1)
    tau = fit.x[3:6] if move else np.zeros(3)
    return Rotation.from_rotvec(fit.x[:3]).as_matrix(), tau, float(np.median(r)), r


def _pair_residual(x: np.ndarray, rays: np.ndarray, b: np.ndarray, K: np.ndarray, n: np.ndarray,
                   move: bool = True, zoom: bool = False) -> np.ndarray:
    """:func:`_fit_pair`'s residuals ``(2N,)`` pixels: the rays ``(N, 3)`` of the earlier
    frame's corners carried through ``Z K (R + tau n^T)`` against where they are seen, ``b``
    ``(N, 2)``; ``x`` is ``R``'s rotation vector (radians) then, with ``move``, ``tau`` (units
    of the camera's height above the floor) and, with ``zoom``, ``log s``: ``Z`` scales the
    image by ``s`` about ``K``'s principal point (the identity without ``zoom``)."""
    M = _exp_so3(x[:3])[0] + (np.outer(x[3:6], n) if move else 0.0)
    p = rays @ (_zoomed_px(K, x, move, zoom) @ M).T
    return (p[:, :2] / p[:, 2:3] - b).ravel()


def _zoomed_px(K: np.ndarray, x: np.ndarray, move: bool, zoom: bool) -> np.ndarray:
    """``Z K``: ``K`` with the zoom of ``x`` (its last value, ``log s``, with ``zoom``) about its principal point."""
    if not zoom:
        return K
    return _zoomed(K, float(np.exp(x[6 if move else 3])))


def _pair_jacobian(x: np.ndarray, rays: np.ndarray, K: np.ndarray, n: np.ndarray, move: bool = True,
                   zoom: bool = False) -> np.ndarray:
    """The derivative of :func:`_pair_residual` by ``x``: ``(2N, P)``, ``P`` = 3, 6 with ``move``,
    one more with ``zoom``; pixels per radian, per unit of ``tau`` and of ``log s``. With ``R =
    exp([w])``, the rotation vector ``w`` changed by ``d`` turns a ray ``r`` by ``-R [r]_x J_r(w)
    d``, ``J_r`` the exponential map's right Jacobian; ``tau`` moves it by ``(n . r) d``; ``log s``
    scales ``K``'s image about its principal point."""
    R, Jr = _exp_so3(x[:3])
    Kz = _zoomed_px(K, x, move, zoom)
    M = R + (np.outer(x[3:6], n) if move else 0.0)
    q = rays @ (Kz @ M).T  # (N, 3) the carried corners, homogeneous px
    KR = Kz @ R
    # column j of [r]_x Jr is r x Jr[:, j] = -[Jr[:, j]]_x r: d q / d w_j = K R [Jr[:, j]]_x r
    cols = [rays @ (KR @ _cross_matrix(Jr[:, j])).T for j in range(3)]
    if move:
        cols += [(rays @ n)[:, None] * Kz[:, j] for j in range(3)]  # d q / d tau_j = (n . r) K e_j
    if zoom:  # dZ/dlog s = s D, D = [[1, 0, -cx], [0, 1, -cy], [0, 0, 0]], and s D = D Z: d q / d log s = D q
        D = np.array([[1.0, 0.0, -K[0, 2]], [0.0, 1.0, -K[1, 2]], [0.0, 0.0, 0.0]])
        cols.append(q @ D.T)
    dq = np.stack(cols, axis=2)  # (N, 3, P)
    z = q[:, 2, None]
    du = (dq[:, :2] - (q[:, :2] / z)[:, :, None] * dq[:, 2:3]) / z[:, :, None]  # (N, 2, P)
    return du.reshape(2 * len(rays), -1)


def _exp_so3(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R, J_r)``, both ``(3, 3)``: the rotation of the rotation vector ``w`` (radians; Rodrigues'
    formula, as :meth:`scipy.spatial.transform.Rotation.from_rotvec`) and the exponential map's
    right Jacobian there (``exp([w + d]) = exp([w]) exp([J_r d])`` to first order in ``d``)."""
    w = np.asarray(w, np.float64)
    W = _cross_matrix(w)
    t2 = float(w @ w)
    if t2 < 1e-8:  # the series, to the theta^4 terms
        s0, c0, c2 = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0
    else:
        t = np.sqrt(t2)
        s0, c0, c2 = np.sin(t) / t, (1.0 - np.cos(t)) / t2, (t - np.sin(t)) / (t2 * t)
    WW = W @ W
    return np.eye(3) + s0 * W + c0 * WW, np.eye(3) - c0 * W + c2 * WW


def _cross_matrix(v: np.ndarray) -> np.ndarray:
    """``(3, 3)``: ``[v]_x``, the matrix of ``u -> v x u``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def floor_motion(pairs: list, K: np.ndarray, rotations: np.ndarray, zooms: np.ndarray | None = None) -> dict | None:
    """The camera's turn and move over a clip, from the floor corners of each frame pair.

    Args:
        pairs: per frame pair ``(k, k+1)``, ``(a, b, H)``: the floor corners ``(N, 2)`` pixels
            in frame ``k`` and ``k+1`` that agree with the homography ``H`` between them, or None.
        K: ``(3, 3)`` the intrinsics, pixels.
        rotations: ``(T, 3, 3)`` the turn of each frame since the first, from the whole
            background (:func:`frame_rotation`): the start of each pair's fit and the frame
            each pair's normal is turned back through.
        zooms: ``(T,)`` each frame's focal length over the first frame's, from the whole
            background (:func:`frame_turn_zoom`), or None (1): the focal lengths with which a
            turn and a zoom, the alternative to a move, see the floor.

    Returns:
        None where no pair shows a move; ``{"share": s}`` where the move leaves more than
        :data:`MOVE_EVIDENCE` of the cost a turn and a zoom leave on the floor's corners (``s``,
        the move not believed); else also ``rotations`` ``(T, 3, 3)``, ``shifts`` ``(T, 3)``
        (``x_t = R_t x_0 + h shifts_t``, ``h`` the camera's height above the floor in the first
        frame), ``normal`` ``(3,)`` (first frame's axes, pointing down), ``residual_px``
        (median over pairs) and ``unknown`` (frames whose pair could not be fitted; held: no
        turn or move from the frame before).
    """
    got = _plane_normal(pairs, rotations, K, zooms)
    if got is None:
        return None
    n0, share = got
    if share > MOVE_EVIDENCE:
        return {"share": share}
    Rs, ts = [np.eye(3)], [np.zeros(3)]
    residuals, unknown = [], []
    for k, pair in enumerate(pairs):
        R_k, t_k = Rs[-1], ts[-1]
        n_k = R_k @ n0
        h_k = 1.0 + n_k @ t_k  # the camera's height over the floor, in units of the first frame's
        got = None
        if pair is not None and h_k > 0.05:
            got = _fit_pair(pair[0], pair[1], K, n_k, rotations[k + 1] @ rotations[k].T)
        if got is None:
            unknown.append(k + 1)
            Rs.append(R_k)
            ts.append(t_k)
            continue
        R, tau, res, _ = got
        residuals.append(res)
        Rs.append(R @ R_k)
        ts.append(R @ t_k + tau * h_k)
    return {"share": share, "rotations": np.asarray(Rs), "shifts": np.asarray(ts), "normal": n0,
            "residual_px": float(np.median(residuals)) if residuals else float("nan"), "unknown": unknown}


def camera_motion(seq, camera, frames: range | None = None, masks: bool = True, dilate_px: int = 15,
                  progress: bool = False, sideways: bool = True, others=None, focal: bool = False) -> CameraMotion:
    """:func:`frame_rotation` chained over ``frames`` of ``seq``, and where the floor shows the
    camera moving sideways, :func:`floor_motion`.

    Args:
        seq: ``seq.frame(i)`` ``(H, W, 3)`` uint8 RGB, and with ``masks`` ``seq.mask(i)``
            (the person's pixels, or None) left out, grown by ``dilate_px``; the floor's corners
            are taken about the person's feet (:func:`floor_region`).
        camera: the tracked camera (its intrinsics, pixels of ``seq``'s frames).
        frames: the frames (default all).
        progress: show a progress bar.
        sideways: look for a sideways move too (the floor's corners).
        others: ``others(i)``: ``(H, W)`` bool, where anyone else is seen in frame ``i``, or
            None (:meth:`~flowmocap.vision.auto.PersonTrack.people`); left out like the
            person, grown by ``dilate_px``. Someone walking past moves over the background
            and the floor like a camera would.
        focal: read the first frame's focal length from the background's turns too
            (:func:`focal_from_turns`, where the camera turns by :data:`FOCAL_MIN_TURN_DEG` or
            more; the motion itself stays fitted with ``camera``'s).

    Returns:
        :class:`CameraMotion` (the first frame's rotation the identity and zoom 1; each frame's
        turn and zoom fitted together, :func:`frame_turn_zoom`; ``shifts`` where the camera
        moved more than :data:`SIDEWAYS_SHARE` of its height above the floor).
    """
    import cv2
    from tqdm import tqdm

    frames = range(len(seq)) if frames is None else frames
    K = _intrinsics(camera)
    Rs = [np.eye(3)]
    residuals, unknown, pairs = [], [], []
    kernel = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)

    def person(i):  # the person's mask of frame i and the pixels left out around it (everyone's)
        m = seq.mask(i) if masks and hasattr(seq, "mask") else None
        if m is not None and not np.asarray(m).any():
            m = None
        left = None if m is None else np.asarray(m, bool)
        other = others(i) if others is not None else None
        if other is not None and np.asarray(other).any():
            left = np.asarray(other, bool) if left is None else left | np.asarray(other, bool)
        return m, None if left is None else cv2.dilate(left.astype(np.uint8), kernel) > 0

    prev = seq.frame(frames[0]).copy() if len(frames) else None
    m, exclude = person(frames[0]) if len(frames) else (None, None)
    zs = [1.0]
    turned: list = []  # with focal: the pairs that turn the most (corners, pixel homography, zoom so far, degrees)

    def keep(found, zoom, R):
        if focal and found:
            turned.extend((a, b, H, zoom, _angle(R)) for a, b, H in found)
            if len(turned) > 2 * FOCAL_PAIRS:  # bounded, however long the video
                turned.sort(key=lambda t: -t[4])
                del turned[FOCAL_PAIRS:]
    key = (prev, exclude, np.eye(3), 0, 1.0)  # the keyframe: image, pixels left out, turn, its row, zoom
    for row, i in enumerate(tqdm(frames[1:], disable=not progress, unit="frame", desc="camera motion"), start=1):
        cur = seq.frame(i).copy()
        # against the keyframe first: a turn chained frame by frame drifts (a person walking
        # through the background bends each step a little), one from the keyframe does not
        Kk = _zoomed(K, key[4])  # the keyframe's own intrinsics
        found: list = []  # the pair's corners, where its fit is kept
        got = frame_turn_zoom(key[0], cur, Kk, key[1], found=found)
        new_m, new_exclude = person(i)
        if got is not None:
            keep(found, key[4], got[0])
            Rs.append(got[0] @ key[2])
            zs.append(got[1] * key[4])
            residuals.append(got[2])
            if _step_px(got[0], got[1], Kk) > KEYFRAME_MAX_PX:
                key = (cur, new_exclude, Rs[-1], row, zs[-1])
        else:
            got = frame_turn_zoom(prev, cur, _zoomed(K, zs[-1]), exclude, found=found) if key[3] != row - 1 else None
            if got is None:  # a cut, a blank frame: held (the keyframe stays)
                unknown.append(int(i))
                Rs.append(Rs[-1])
                zs.append(zs[-1])
            else:
                keep(found, zs[-1], got[0])
                Rs.append(got[0] @ Rs[-1])
                zs.append(got[1] * zs[-1])
                residuals.append(got[2])
                key = (cur, new_exclude, Rs[-1], row, zs[-1])
        if sideways:
            region = floor_region(prev.shape, m if masks else None)
            if exclude is not None:
                region &= ~exclude
            floor = _homography(prev, cur, ~region, 400, 20, "camera_motion")
            if floor is None:  # a smooth floor: weaker corners
                floor = _homography(prev, cur, ~region, 400, 20, "camera_motion", FLOOR_CORNER_QUALITY, 6)
            pairs.append(None if floor is None else (floor[0][floor[3]], floor[1][floor[3]], floor[2]))
        prev, m, exclude = cur, new_m, new_exclude
    R = np.asarray(Rs, np.float64)
    zooms = np.asarray(zs, np.float64)
    fl = floor_motion(pairs, K, R, zooms) if sideways and len(pairs) else None
    shifts = normal = floor_R = None
    far = float("nan")
    floor_unknown = None
    share = float("nan") if fl is None else fl["share"]
    if fl is not None and "shifts" in fl:
        centres = -np.einsum("tji,tj->ti", fl["rotations"], fl["shifts"])
        far = float(np.linalg.norm(centres, axis=1).max())
        if far > SIDEWAYS_SHARE:
            floor_R, shifts, normal, floor_unknown = fl["rotations"], fl["shifts"], fl["normal"], fl["unknown"]
    turn = _angle(R)
    focal_found = None
    if focal and len(turn) and turn.max() >= FOCAL_MIN_TURN_DEG:
        most = sorted(turned, key=lambda t: -t[4])[:FOCAL_PAIRS]
        got = focal_from_turns([t[:4] for t in most], (K[0, 2], K[1, 2]), float(max(prev.shape[:2])))
        if got is not None and got[1] >= FOCAL_SHARPNESS:
            focal_found = {"focal_px": round(got[0], 1), "used_px": round(float(K[0, 0]), 1),
                           "ratio": round(got[0] / float(K[0, 0]), 4), "pairs": len(most),
                           "sharpness": round(got[1], 3)}
    return CameraMotion(np.asarray(list(frames), np.int64), R, turn,
                        float(np.median(residuals)) if residuals else float("nan"), unknown,
                        shifts=shifts, floor_rotations=floor_R, floor_normal=normal, sideways=far,
                        floor_unknown=floor_unknown, move_share=share, zooms=zooms, focal=focal_found)


def _angle(R: np.ndarray):
    """The angle of the rotation ``R`` ``(3, 3)`` (a float) or of each of ``(T, 3, 3)`` (``(T,)``), degrees."""
    a = np.degrees(np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)))
    return float(a) if np.ndim(a) == 0 else a
