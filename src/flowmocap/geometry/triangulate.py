"""Calibrated cameras with lens distortion, robust multi-view triangulation and the time
offsets of unsynchronised views.

Conventions (the project's, see :mod:`flowmocap.geometry.camera`): world points in
metres; ``X_cam = R @ X_world + t`` with OpenCV camera axes (x right, y down, z forward);
pixels with **pixel centres at integer + 0.5** (the image spans ``[0, W] x [0, H]``, as
the detector's keypoints and :class:`~flowmocap.geometry.camera.PinholeCamera` have
them). Lens distortion is OpenCV's (``dist = (k1, k2, p1, p2, k3)`` on normalised
coordinates); undistortion and projection use OpenCV (``cv2.undistortPointsIter``,
``cv2.projectPoints``).

- :class:`CalibratedCamera`: intrinsics ``K``, distortion, pose; :meth:`~CalibratedCamera.project`,
  :meth:`~CalibratedCamera.normalise`, :meth:`~CalibratedCamera.scaled`.
- :func:`triangulate`: confidence-weighted DLT from ``V`` views, dropping the worst view
  while its reprojection error exceeds a threshold and enough views remain.
- :func:`reprojection_errors`: per point and view, pixels.
- :func:`estimate_offsets`: each view's integer frame offset to a reference view from
  people's 2D joints (the offset that makes the views' joints agree best in 3D);
  :func:`offset_cost` and :func:`prediction_curve` are its two measures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flowmocap.errors import InputError

__all__ = ["CalibratedCamera", "Triangulation", "triangulate", "reprojection_errors", "estimate_offsets",
           "offset_cost", "prediction_curve"]


@dataclass(frozen=True)
class CalibratedCamera:
    """One calibrated view.

    Attributes:
        name: the camera's name (e.g. its serial, ``"cam01"``).
        K: ``(3, 3)`` intrinsics in pixels, principal point in the project's pixel
            convention (pixel centres at integer + 0.5).
        dist: ``(5,)`` OpenCV distortion ``(k1, k2, p1, p2, k3)`` (unitless, on
            normalised coordinates).
        R: ``(3, 3)`` world-to-camera rotation (OpenCV axes).
        t: ``(3,)`` world-to-camera translation, metres.
        width, height: image size in pixels.
    """

    name: str
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731
        try:
            K, dist = np.array(self.K, np.float64), np.array(self.dist, np.float64).reshape(-1)
            R, t = np.array(self.R, np.float64), np.array(self.t, np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise InputError(f"camera {self.name!r}: K, R must be 3x3 and dist 5, t 3 numbers") from None
        if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,) or dist.shape != (5,):
            raise InputError(f"camera {self.name!r}: K and R must be (3, 3), t (3,), dist (5,) "
                             f"(k1, k2, p1, p2, k3); got {K.shape}, {R.shape}, {t.shape}, {dist.shape}")
        if not all(np.isfinite(a).all() for a in (K, dist, R, t)):
            raise InputError(f"camera {self.name!r}: K, dist, R and t must be finite")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError(f"camera {self.name!r}: focal lengths must be positive pixels; got {K[0, 0]}, {K[1, 1]}")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
            raise InputError(f"camera {self.name!r}: R is not a rotation (orthonormal, det +1); check for a "
                             "transposed or reflected matrix")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InputError(f"camera {self.name!r}: width and height must be positive pixels")
        for k, v in (("K", K), ("dist", dist), ("R", R), ("t", t)):
            v.setflags(write=False)
            set_(k, v)
        set_("width", int(self.width))
        set_("height", int(self.height))

    @property
    def center(self) -> np.ndarray:
        """``(3,)`` the camera centre in the world, metres (``-R^T t``)."""
        return -self.R.T @ self.t

    @property
    def projection(self) -> np.ndarray:
        """``(3, 4)`` ``[R | t]``: world points (homogeneous) to normalised, undistorted
        camera coordinates."""
        return np.hstack([self.R, self.t[:, None]])

    def _cv_K(self) -> np.ndarray:
        """K with OpenCV's pixel convention (pixel centres at integers)."""
        K = self.K.copy()
        K[:2, 2] -= 0.5
        return K

    def project(self, points) -> np.ndarray:
        """World points ``(..., 3)`` metres to pixels ``(..., 2)`` with lens distortion.

        Points behind the camera get NaN.
        """
        import cv2

        X = np.asarray(points, np.float64)
        if X.shape[-1] != 3:
            raise InputError(f"points must be (..., 3) metres; got {X.shape}")
        flat = X.reshape(-1, 3)
        out = np.full((len(flat), 2), np.nan)
        ok = np.isfinite(flat).all(1)
        if ok.any():
            rvec = cv2.Rodrigues(self.R)[0]
            px = cv2.projectPoints(flat[ok], rvec, self.t, self._cv_K(), self.dist)[0].reshape(-1, 2) + 0.5
            depth = flat[ok] @ self.R[2] + self.t[2]
            px[depth <= 0] = np.nan
            out[ok] = px
        return out.reshape(X.shape[:-1] + (2,))

    def normalise(self, pixels) -> np.ndarray:
        """Pixels ``(..., 2)`` to undistorted normalised camera coordinates ``(..., 2)``
        (``x / z, y / z`` of the ray), by OpenCV's iterative undistortion."""
        import cv2

        p = np.asarray(pixels, np.float64)
        if p.shape[-1] != 2:
            raise InputError(f"pixels must be (..., 2); got {p.shape}")
        flat = p.reshape(-1, 2)
        out = np.full_like(flat, np.nan)
        ok = np.isfinite(flat).all(1)
        if ok.any():
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
            out[ok] = cv2.undistortPointsIter((flat[ok] - 0.5).reshape(-1, 1, 2), self._cv_K(), self.dist,
                                              None, None, crit).reshape(-1, 2)
        return out.reshape(p.shape)

    def scaled(self, scale: float) -> "CalibratedCamera":
        """The same camera for images scaled by ``scale`` (e.g. a video read with a smaller
        long side): focal length and principal point times ``scale``, size rounded."""
        s = float(scale)
        if not s > 0:
            raise InputError(f"scale must be > 0; got {scale!r}")
        K = self.K.copy()
        K[:2] *= s
        return CalibratedCamera(self.name, K, self.dist, self.R, self.t, round(self.width * s), round(self.height * s))


@dataclass
class Triangulation:
    """Result of :func:`triangulate` for ``N`` points seen by ``V`` views.

    Attributes:
        points: ``(N, 3)`` metres, world frame; NaN where fewer than ``min_views`` views
            saw the point (or, with ``reject``, where its error stayed above the threshold).
        error_px: ``(N,)`` mean reprojection error over the views used, pixels (NaN where
            no point).
        used: ``(N, V)`` bool, the views each point was triangulated from.
        view_error_px: ``(N, V)`` reprojection error into every view with an observation
            (used or dropped), pixels; NaN where the view has none.
    """

    points: np.ndarray
    error_px: np.ndarray
    used: np.ndarray
    view_error_px: np.ndarray

    @property
    def num_views(self) -> np.ndarray:
        """``(N,)`` the number of views each point was triangulated from."""
        return self.used.sum(-1)


def _check_views(cameras, points2d, confidence) -> tuple[np.ndarray, np.ndarray]:
    V = len(cameras)
    p = np.asarray(points2d, np.float64)
    if p.ndim != 3 or p.shape[0] != V or p.shape[2] != 2:
        raise InputError(f"points2d must be (V, N, 2) pixels for V = {V} cameras; got {p.shape}")
    if confidence is None:
        c = np.ones(p.shape[:2])
    else:
        c = np.asarray(confidence, np.float64)
        if c.shape != p.shape[:2]:
            raise InputError(f"confidence must be (V, N) = {p.shape[:2]}; got {c.shape}")
    return p, c


def _dlt(proj: np.ndarray, xn: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted DLT. proj (V, 3, 4), xn (N, V, 2) normalised, w (N, V) >= 0 -> (N, 3)."""
    P = proj[None]  # (1, V, 3, 4)
    rows_x = xn[..., 0:1] * P[..., 2, :] - P[..., 0, :]  # (N, V, 4)
    rows_y = xn[..., 1:2] * P[..., 2, :] - P[..., 1, :]
    A = np.concatenate([rows_x, rows_y], axis=1) * np.concatenate([w, w], axis=1)[..., None]  # (N, 2V, 4)
    A = np.nan_to_num(A)
    _, _, Vh = np.linalg.svd(A)
    X = Vh[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[:, :3] / X[:, 3:4]


def reprojection_errors(cameras, points3d, points2d) -> np.ndarray:
    """Distance between each view's projection of ``points3d (N, 3)`` metres and its
    observation ``points2d (V, N, 2)`` pixels: ``(N, V)`` pixels (NaN where either is
    missing; inf where the point is behind the camera)."""
    X = np.asarray(points3d, np.float64)
    p = np.asarray(points2d, np.float64)
    out = np.empty((len(X), len(cameras)))
    for v, cam in enumerate(cameras):
        proj = cam.project(X)
        e = np.linalg.norm(proj - p[v], axis=-1)
        behind = np.isfinite(X).all(1) & ~np.isfinite(proj).all(1) & np.isfinite(p[v]).all(1)
        e[behind] = np.inf
        out[:, v] = e
    return out


def triangulate(cameras, points2d, confidence=None, min_confidence: float = 0.3, max_error_px: float | None = 15.0,
                min_views: int = 2, reject: bool = True) -> Triangulation:
    """Robust, confidence-weighted DLT triangulation of ``N`` points from ``V`` views.

    Each observation is undistorted (:meth:`CalibratedCamera.normalise`) and enters the
    linear system with its confidence as weight. While some view of a point reprojects
    more than ``max_error_px`` away and dropping a view leaves at least ``min_views``,
    one view is dropped: the one whose removal leaves the smallest worst error among the
    rest (in a least-squares solution pulled by one bad view, a good view can have the
    largest residual), and the point is triangulated again. One bad detection (a
    mirrored limb, another person) thus cannot pull the point away.

    Args:
        cameras: ``V`` :class:`CalibratedCamera`.
        points2d: ``(V, N, 2)`` pixels (NaN = not seen).
        confidence: ``(V, N)`` in [0, 1] (default all 1); observations below
            ``min_confidence`` are not used.
        max_error_px: the reprojection error (pixels) above which the worst view is
            dropped; None: no view is dropped and nothing rejected.
        min_views: views a point needs (>= 2).
        reject: NaN for points whose mean error still exceeds ``max_error_px``.

    Returns:
        a :class:`Triangulation` (points ``(N, 3)`` metres, errors in pixels).
    """
    p, c = _check_views(cameras, points2d, confidence)
    if min_views < 2:
        raise InputError(f"min_views must be >= 2 (a point needs two rays); got {min_views}")
    V, N = p.shape[:2]
    xn = np.stack([cam.normalise(p[v]) for v, cam in enumerate(cameras)], axis=1)  # (N, V, 2)
    valid = (c.T >= min_confidence) & (c.T > 0) & np.isfinite(xn).all(-1)
    proj = np.stack([cam.projection for cam in cameras])
    w = np.where(valid, c.T, 0.0)
    used = valid.copy()
    enough = used.sum(1) >= min_views
    X = np.full((N, 3), np.nan)
    err = np.full((N, V), np.nan)

    def solve(idx, use):
        pts = _dlt(proj, xn[idx], np.where(use, w[idx], 0.0))
        e = reprojection_errors(cameras, pts, p[:, idx])
        return pts, e, np.where(use, np.nan_to_num(e, nan=np.inf), -1.0).max(1)

    idx = np.nonzero(enough)[0]
    if len(idx):
        X[idx], err[idx], worst = solve(idx, used[idx])
    while max_error_px is not None and len(idx):
        bad = (worst > max_error_px) & (used[idx].sum(1) > min_views)
        idx, worst = idx[bad], worst[bad]
        if not len(idx):
            break
        # drop the view whose removal leaves the smallest worst error (one outlier can make a
        # good view's residual the largest in the least-squares solution)
        trials = []
        for v in range(V):
            cand = used[idx, v]
            if not cand.any():
                continue
            k = idx[cand]
            use = used[k].copy()
            use[:, v] = False
            pts, e, wv = solve(k, use)
            trials.append((v, cand, pts, e, wv))
        best_w = np.full(len(idx), np.inf)
        best_v = np.full(len(idx), -1)
        for v, cand, _, _, wv in trials:
            sub = best_w[cand]
            better = wv < sub
            sub[better] = wv[better]
            best_w[cand] = sub
            bv = best_v[cand]
            bv[better] = v
            best_v[cand] = bv
        for v, cand, pts, e, wv in trials:
            pick = best_v[cand] == v
            k = idx[cand][pick]
            X[k], err[k] = pts[pick], e[pick]
            used[k, v] = False
        worst = best_w
    err = np.where(valid, err, np.nan)
    with np.errstate(invalid="ignore"):
        mean_err = np.where(enough, np.nansum(np.where(used, err, 0.0), 1) / np.maximum(used.sum(1), 1), np.nan)
    X[~enough] = np.nan
    used[~enough] = False
    if reject and max_error_px is not None:
        X[~(mean_err <= max_error_px)] = np.nan
    return Triangulation(X, mean_err, used, err)


def _stack_in_time(tracks: list, offsets) -> tuple[np.ndarray, np.ndarray]:
    """Per-view tracks on a common time axis: ``(V, T, J, 2)`` px and ``(V, T, J)``."""
    present = [(v, tr, int(o)) for v, (tr, o) in enumerate(zip(tracks, offsets)) if tr is not None]
    J = present[0][1][0].shape[1]
    t0 = min(o for _, _, o in present)
    t1 = max(o + len(tr[0]) for _, tr, o in present)
    pts = np.full((len(tracks), t1 - t0, J, 2), np.nan)
    conf = np.zeros((len(tracks), t1 - t0, J))
    for v, (p, c), o in present:
        pts[v, o - t0:o - t0 + len(p)] = p
        conf[v, o - t0:o - t0 + len(p)] = c
    return pts, conf


def offset_cost(cameras, tracks: list, offsets, min_confidence: float = 0.3, min_points: int = 20) -> float:
    """Median reprojection error (pixels) of one person's joints triangulated from all
    views with the given frame offsets (no view dropped); inf with fewer than
    ``min_points`` joints seen by two views or more.

    Args:
        cameras: ``V`` :class:`CalibratedCamera`.
        tracks: per view ``(points (T_v, J, 2) px, confidence (T_v, J))`` of the same
            person (frames without the person: confidence 0), or None where the view
            does not see the person.
        offsets: ``(V,)`` ints: view ``v``'s frame ``f`` shows the instant of the
            reference time ``f + offsets[v]``.
    """
    if sum(tr is not None for tr in tracks) < 2:
        return float("inf")
    pts, conf = _stack_in_time(tracks, offsets)
    V = len(cameras)
    tri = triangulate(cameras, pts.reshape(V, -1, 2), conf.reshape(V, -1), min_confidence, max_error_px=None)
    e = tri.error_px[np.isfinite(tri.error_px)]
    return float(np.median(e)) if len(e) >= min_points else float("inf")


def prediction_curve(cameras, tracks: list, offsets, view: int, search, min_confidence: float = 0.3,
                     max_error_px: float | None = 20.0, min_points: int = 20) -> np.ndarray:
    """How well the other views predict ``view`` at each candidate offset: the person is
    triangulated from every other view (their offsets fixed, robustly) and projected
    into ``view``; for each offset ``d`` in ``search``, frame ``f`` of ``view`` is
    compared with the projection at time ``f + d``.

    Args:
        cameras: ``V`` :class:`CalibratedCamera`.
        tracks: per view ``(points (T_v, J, 2) px, confidence (T_v, J))`` or None.
        offsets: ``(V,)`` the views' offsets in frames (``offsets[view]`` is not used).
        view: the index of the view predicted.
        search: the candidate offsets of ``view`` (frames).

    Returns:
        ``(len(search),)`` the median distance in pixels between ``view``'s confident
        observations and the projections; inf with fewer than ``min_points`` pairs or
        fewer than two other views.
    """
    others = [u for u in range(len(cameras)) if u != view and tracks[u] is not None]
    out = np.full(len(search), np.inf)
    if tracks[view] is None or len(others) < 2:
        return out
    pts, conf = _stack_in_time([tracks[u] for u in others], [offsets[u] for u in others])
    t0 = min(int(offsets[u]) for u in others)
    n, T, J = conf.shape
    tri = triangulate([cameras[u] for u in others], pts.reshape(n, -1, 2), conf.reshape(n, -1), min_confidence,
                      max_error_px=max_error_px)
    proj = cameras[view].project(tri.points).reshape(T, J, 2)
    obs, oc = np.asarray(tracks[view][0], np.float64), np.asarray(tracks[view][1])
    f = np.arange(len(obs))
    for k, d in enumerate(search):
        idx = f + int(d) - t0
        ok = (idx >= 0) & (idx < T)
        e = np.linalg.norm(proj[idx[ok]] - obs[ok], axis=-1)
        e = e[(oc[ok] >= min_confidence) & np.isfinite(e)]
        if len(e) >= min_points:
            out[k] = float(np.median(e))
    return out


def estimate_offsets(cameras, people: list, search=range(-15, 16), reference: int = 0,
                     min_confidence: float = 0.3, rounds: int = 3,
                     max_error_px: float | None = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """Each view's integer frame offset to the ``reference`` view, from the 2D joints of
    one or more people seen by several views.

    First each view is paired with the reference alone: the offset whose two-view
    triangulations reproject best (the median error over the joints of the overlapping
    frames). Then, up to ``rounds`` times, each view's offset is searched again by how
    well the other views (their offsets fixed) predict it (:func:`prediction_curve`).
    Each person's curve is divided by its own minimum and the curves summed: a person
    who moves gives a sharp minimum and decides; one who moves little, or whose
    detections in a view are biased, gives a flat curve and barely counts.

    Args:
        cameras: ``V`` :class:`CalibratedCamera`.
        people: per person, per view ``(points (T_v, J, 2) px, confidence (T_v, J))``
            (frames without the person: confidence 0), or None where the view does not
            see them. A single person is ``[tracks]``.
        search: the candidate offsets (frames).
        reference: the view whose frame numbers are the reference time (offset 0).
        max_error_px: the robust triangulation's threshold in the prediction step.

    Returns:
        ``(offsets (V,) int, cost (V, len(search)))``: view ``v``'s frame ``f`` shows
        the instant of the reference view's frame ``f + offsets[v]``; ``cost[v, k]`` is
        the summed relative cost (1 per person at their best) of offset ``search[k]`` for
        view ``v`` in the last search (inf where too few frames overlap; NaN for the
        reference).

    Raises:
        InputError: a person without one entry per camera, or a bad reference.
    """
    V = len(cameras)
    if any(len(p) != V for p in people):
        raise InputError(f"each person needs one track (or None) per camera; cameras: {V}, "
                         f"tracks per person: {[len(p) for p in people]}")
    if not 0 <= reference < V:
        raise InputError(f"reference must be a view index in [0, {V}); got {reference}")
    search = [int(s) for s in search]
    offsets = np.zeros(V, int)
    cost = np.full((V, len(search)), np.inf)

    def relative_sum(curves: list) -> np.ndarray:
        curves = [c for c in curves if np.isfinite(c).any()]
        if not curves:
            return np.full(len(search), np.inf)
        return np.sum([c / c.min() if c.min() > 0 else c for c in curves], axis=0)

    others = [v for v in range(V) if v != reference]
    for v in others:
        curves = []
        for p in people:
            if p[v] is None or p[reference] is None:
                continue
            pair = [cameras[reference], cameras[v]]
            curves.append(np.array([offset_cost(pair, [p[reference], p[v]], [0, d], min_confidence)
                                    for d in search]))
        cost[v] = relative_sum(curves)
        if np.isfinite(cost[v]).any():
            offsets[v] = search[int(np.argmin(cost[v]))]
    for _ in range(rounds if V > 2 else 0):
        changed = False
        for v in others:
            row = relative_sum([prediction_curve(cameras, p, offsets, v, search, min_confidence, max_error_px)
                                for p in people])
            if not np.isfinite(row).any():
                continue  # nobody seen by this view and two others: its offset stays
            cost[v] = row
            best = search[int(np.argmin(row))]
            changed |= best != offsets[v]
            offsets[v] = best
        if not changed:
            break
    cost[reference] = np.nan
    return offsets, cost
