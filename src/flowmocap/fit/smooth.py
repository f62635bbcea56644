"""Offline smoothing of a fitted motion: Savitzky-Golay filtering done on SO(3).

The tracker fits frame by frame, so its curves carry frame-to-frame jitter. This pass
looks at the whole sequence afterwards. For each frame ``t`` it fits a polynomial of
degree ``order`` by least squares to the frames of a window of ``window`` frames around
``t`` and keeps the polynomial's value at ``t`` (Savitzky & Golay 1964). Near the ends the
window is the first (last) ``window`` frames, as ``scipy.signal.savgol_filter`` does with
``mode="interp"``; the weights of every frame are exactly those.

Translations are filtered as they are. Rotations are not vectors, so each joint's
rotations are filtered in the tangent space of the current estimate ``R_c`` of frame t:
``R_c <- R_c exp(sum_k w_tk log(R_c^T R_k))`` with the Savitzky-Golay weights ``w_tk``
(they sum to 1), repeated a few times (a weighted Karcher mean with signed weights). The
result does not depend on the frame the rotations are expressed in (left-multiplying
all ``R_k`` by one rotation rotates the result the same way), and a rotation at constant
angular velocity (``R_k = R_0 exp(k w)``) is reproduced exactly, as a straight line is by
the Euclidean filter.

Units: radians, metres, frames (``window``) or seconds (``window_s``).
"""

from __future__ import annotations

import numpy as np

from flowmocap.errors import InputError

__all__ = ["savgol_weights", "smooth_translations", "smooth_rotations", "smooth_motion", "window_frames",
           "smooth_root_depth", "depth_smoothed_motion", "pose_smoothed_motion", "DEFAULT_WINDOW_S", "DEFAULT_ORDER", "DEPTH_WINDOW_S",
           "DEPTH_ORDER", "FOOT_JOINTS", "stance_depth_shift", "stance_depth_motion", "seam_blend", "posed_joints"]

#: Default window length in seconds and polynomial degree: the best order-2 window on the
#: CMU 35_01 protocol runs (8 seeds, 60 fps), the same on the held-out diverse suite;
#: numbers in docs/experiments.md, "The smoothing filter chosen" (benchmarks/smooth_cmu.py).
DEFAULT_WINDOW_S = 0.3
DEFAULT_ORDER = 2

#: The root-depth smoother's window in seconds and its degree (:func:`smooth_root_depth`,
#: ``TrackerConfig.depth_smoothing_s``): a local straight line over half a second. Of the
#: windows and degrees tried on finished runs of the CMU 35_01 protocol (8 seeds) and the
#: diverse suite together (benchmarks/depth_smoothing.py), the one that made no run of
#: either worse and cost no 2D accuracy (docs/experiments.md, "Root depth smoothed over time").
DEPTH_WINDOW_S = 0.5
DEPTH_ORDER = 1

#: :func:`smooth_rotations` handles at most about this many rotations at once (frames x
#: joints x window; a few hundred bytes each in its intermediates), taking the joints a
#: few at a time beyond it (an 18000-frame motion: 60 MB, not 700).
MAX_ROTATIONS = 200_000


def window_frames(window_s: float, fps: float, order: int = DEFAULT_ORDER) -> int:
    """The odd number of frames closest to ``window_s`` seconds at ``fps``, at least ``order + 2``."""
    if not np.isfinite(window_s) or window_s <= 0:
        raise InputError(f"the smoothing window must be a positive number of seconds, got {window_s}.")
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"fps must be positive, got {fps}.")
    n = int(round(min(window_s * fps, 1e9)))  # a window longer than any clip is cut to the clip later
    n = n + 1 if n % 2 == 0 else n
    m = order + 2 if (order + 2) % 2 == 1 else order + 3
    return max(n, m)


def savgol_weights(num_frames: int, window: int, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Savitzky-Golay weights of every frame, ends included (scipy's ``mode="interp"``).

    Args:
        num_frames: T. window: odd window length in frames, ``order < window <= T``.
        order: polynomial degree.

    Returns:
        ``index (T, window)`` int64 frames each output frame reads, and ``weights (T,
        window)`` float64 (each row sums to 1): ``y_t = sum_k weights[t, k] x[index[t, k]]``.
    """
    T = int(num_frames)
    if window % 2 != 1 or window < 1:
        raise InputError(f"the smoothing window must be an odd number of frames, got {window}.")
    if not 0 <= order < window:
        raise InputError(f"the polynomial order must be below the window ({window} frames), got {order}.")
    if window > T:
        raise InputError(f"the smoothing window ({window} frames) is longer than the motion ({T} frames).")
    half = window // 2
    start = np.clip(np.arange(T) - half, 0, T - window)
    index = start[:, None] + np.arange(window)[None]
    offsets = np.arange(window, dtype=np.float64) - half
    V = np.vander(offsets, order + 1, increasing=True)  # (window, order+1)
    P = np.linalg.pinv(V)  # coefficients = P @ x
    at = (np.arange(T) - start - half).astype(np.float64)  # where frame t sits in its window
    basis = at[:, None] ** np.arange(order + 1)[None]  # (T, order+1)
    return index, basis @ P


def _check(window: int, order: int, T: int) -> tuple[int, int] | None:
    """The window actually used for T frames (shrunk to T), or None when T is too short."""
    if window > T:
        window = T if T % 2 == 1 else T - 1
    if window <= order:
        return None
    return window, order


def smooth_translations(trans: np.ndarray, window: int, order: int = DEFAULT_ORDER) -> np.ndarray:
    """Savitzky-Golay filter along time of ``(T, ...)`` values (metres, or anything linear).

    A window longer than the motion shrinks to it; a motion of at most ``order`` frames is
    returned unchanged. Returns float64 of the input's shape.
    """
    x = np.asarray(trans, np.float64)
    used = _check(window, order, x.shape[0])
    if used is None:
        return x.copy()
    index, w = savgol_weights(x.shape[0], *used)
    return np.einsum("tk,tk...->t...", w, x[index])


def smooth_rotations(rotvecs: np.ndarray, window: int, order: int = DEFAULT_ORDER,
                     iterations: int = 3) -> np.ndarray:
    """Savitzky-Golay filter on SO(3) (see the module docstring).

    Args:
        rotvecs: ``(T, J, 3)`` or ``(T, 3)`` axis-angle in radians.
        window: odd window in frames (shrunk to T when longer). order: polynomial degree.
        iterations: tangent-space updates per frame (3 converge to about 1e-9 rad for
            window-sized rotation changes under a radian).

    Returns:
        float64 axis-angle of the input's shape.
    """
    from scipy.spatial.transform import Rotation

    r = np.asarray(rotvecs, np.float64)
    single = r.ndim == 2
    if single:
        r = r[:, None]
    if r.ndim != 3 or r.shape[2] != 3:
        raise InputError(f"rotations must have shape (T, J, 3) axis-angle; got {np.shape(rotvecs)}.")
    if not np.all(np.isfinite(r)):
        raise InputError("the rotations to smooth contain NaN or infinite values.")
    T, J = r.shape[:2]
    used = _check(window, order, T)
    if used is None:
        return np.asarray(rotvecs, np.float64).copy()
    index, w = savgol_weights(T, *used)
    n = index.shape[1]
    block = max(1, MAX_ROTATIONS // (T * n))
    if block < J:  # the joints are independent: a few at a time bounds the memory on long motions
        out = np.concatenate([smooth_rotations(r[:, a:a + block], window, order, iterations)
                              for a in range(0, J, block)], axis=1)
        return out[:, 0] if single else out
    R = Rotation.from_rotvec(r.reshape(-1, 3))  # (T*J)
    # neighbours of (t, j): frame index[t, k], joint j -> flat (index * J + j)
    nb = (index[:, None, :] * J + np.arange(J)[None, :, None]).reshape(-1)  # (T*J*n)
    Rk = R[nb]
    est = R
    for _ in range(iterations):
        rel = (est[np.repeat(np.arange(T * J), n)].inv() * Rk).as_rotvec().reshape(T, J, n, 3)
        step = np.einsum("tk,tjkd->tjd", w, rel).reshape(-1, 3)
        est = est * Rotation.from_rotvec(step)
    out = est.as_rotvec().reshape(T, J, 3)
    return out[:, 0] if single else out


def smooth_motion(poses: np.ndarray, trans: np.ndarray, fps: float, window_s: float = DEFAULT_WINDOW_S,
                  order: int = DEFAULT_ORDER, frame_index=None, breaks=()) -> tuple[np.ndarray, np.ndarray]:
    """Smooth a fitted SMPL motion offline: every joint's rotation on SO(3), and the translation.

    Args:
        poses: ``(T, 72)`` axis-angle in radians, SMPL joint order.
        trans: ``(T, 3)`` metres.
        fps: frames per second (Hz).
        window_s: window length in seconds (:func:`window_frames` turns it into an odd
            number of frames). order: polynomial degree (2 keeps accelerations' shape; 1
            is a moving average on SO(3) that flattens peaks more).
        frame_index: ``(T,)`` the input's frame numbers, or None (consecutive). Runs of
            consecutive frames are smoothed separately: the filter never reaches across a
            gap in time.
        breaks: input frame numbers that start a new run (e.g. the tracker's
            re-initialisations, where the pose may jump); needs ``frame_index`` or counts
            frames from 0.

    Returns:
        ``poses (T, 72)``, ``trans (T, 3)``, float64.
    """
    poses = np.asarray(poses, np.float64)
    trans = np.asarray(trans, np.float64)
    if poses.ndim != 2 or poses.shape[1] != 72:
        raise InputError(f"poses must have shape (T, 72); got {poses.shape}.")
    if trans.shape != (poses.shape[0], 3):
        raise InputError(f"trans must have shape ({poses.shape[0]}, 3); got {trans.shape}.")
    if not isinstance(order, (int, np.integer)) or order < 0:
        raise InputError(f"the smoothing order must be a whole number >= 0, got {order!r}.")
    window = window_frames(window_s, fps, order)
    T = poses.shape[0]
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(trans))):
        raise InputError("the motion to smooth contains NaN or infinite values.")
    p, t = poses.copy(), trans.copy()
    for a, b in _runs(frame_index, T, np.ones(T, bool), breaks):
        p[a:b] = smooth_rotations(poses[a:b].reshape(b - a, 24, 3), window, order).reshape(b - a, 72)
        t[a:b] = smooth_translations(trans[a:b], window, order)
    return p, t


def _runs(frame_index, T: int, ok: np.ndarray, breaks=()) -> list[tuple[int, int]]:
    """``[(a, b), ...]``: the runs of consecutive input frames (``frame_index``, None:
    consecutive) whose rows are all ``ok``; a frame number in ``breaks`` starts a new run."""
    idx = np.arange(T) if frame_index is None else np.asarray(frame_index).reshape(-1)
    if idx.shape != (T,):
        raise InputError(f"frame_index must have {T} entries, one per frame; got {idx.shape}.")
    starts = {int(b) for b in breaks}
    out, a = [], None
    for i in range(T + 1):
        good = i < T and bool(ok[i]) and (a is None or (idx[i] == idx[i - 1] + 1 and int(idx[i]) not in starts))
        if a is not None and not good:
            out.append((a, i))
            a = None
        if i < T and bool(ok[i]) and a is None:
            a = i
    return out


def seam_blend(poses: np.ndarray, trans: np.ndarray, frame_index, seams, fps: float,
               window_s: float, ease=None) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """The frames before each seam (a re-initialisation) eased into the pose it restarts from.

    Where the tracker re-initialises at frame ``s`` the motion jumps: the frames before
    ``s`` come from a track that drifted, the frames from ``s`` on from the refit. Let
    ``J`` be the jump, the difference at ``s`` between the motion and the motion
    extrapolated at constant velocity from the two frames before it: per joint the
    rotation ``D = R_s (V R_{s-1})^T`` with ``V = R_{s-1} R_{s-2}^T``, and the translation
    ``d = t_s - (2 t_{s-1} - t_{s-2})``. The frames ``s - k .. s - 1`` (``k`` = ``window_s``
    times ``fps``, rounded; fewer where the previous seam or the start of the run of
    consecutive frames is nearer) take a growing part of it, ``R_t <- exp(w_t log D) R_t``
    and ``t_t <- t_t + w_t d``, with ``w_t`` the smoothstep ``3x^2 - 2x^3`` of ``x = (t - a +
    1) / (s - a + 1)`` (``a`` the first frame eased): 0 before the ramp, nearly 1 at the
    seam, with no kink at either end. So the motion has no jump at the seam (a step of
    size ``J`` becomes a ramp over ``k`` frames), and the frames from the seam on are
    unchanged. A seam with fewer than two consecutive frames before it is left as it is.

    Args:
        poses: ``(T, 72)`` axis-angle, radians, SMPL joint order (each joint relative to
            its parent). trans: ``(T, 3)`` metres.
        frame_index: ``(T,)`` the input's frame numbers, or None (consecutive from 0).
        seams: input frame numbers of the re-initialisations.
        fps: frames per second (Hz). window_s: seconds eased before each seam (> 0).
        ease: the seams to ease (input frame numbers), or None: all; the others still
            end the frames eased before a later seam.

    Returns:
        ``poses (T, 72)``, ``trans (T, 3)``, float64 (copies), and the input frame
        numbers of the seams eased (in order).
    """
    from scipy.spatial.transform import Rotation

    poses = np.array(poses, np.float64)
    trans = np.array(trans, np.float64)
    T = poses.shape[0]
    if poses.ndim != 2 or poses.shape[1] != 72 or trans.shape != (T, 3):
        raise InputError(f"poses must have shape (T, 72) and trans (T, 3); got {poses.shape} and {trans.shape}.")
    if not np.isfinite(window_s) or window_s <= 0:
        raise InputError(f"the window eased before a seam must be a positive number of seconds, got {window_s}.")
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"fps must be positive, got {fps}.")
    idx = np.arange(T) if frame_index is None else np.asarray(frame_index).reshape(-1)
    if idx.shape != (T,):
        raise InputError(f"frame_index must have {T} entries, one per frame; got {idx.shape}.")
    at = {int(f): i for i, f in enumerate(idx)}
    starts = sorted({at[int(f)] for f in seams if int(f) in at})
    k = max(int(round(window_s * fps)), 1)
    eased_at = None if ease is None else {at[int(f)] for f in ease if int(f) in at}
    done: list[int] = []
    for n, s in enumerate(starts):
        if eased_at is not None and s not in eased_at:
            continue
        a = max(s - k, starts[n - 1] if n else 0)
        while a < s and np.any(np.diff(idx[a:s + 1]) != 1):  # only the consecutive frames before the seam
            a += 1
        if s - a < 2:
            continue
        R = Rotation.from_rotvec(poses[s - 2:s + 1].reshape(-1, 3)).as_matrix().reshape(3, 24, 3, 3)
        pred = R[1] @ np.swapaxes(R[0], -1, -2) @ R[1]
        jump = Rotation.from_matrix(R[2] @ np.swapaxes(pred, -1, -2)).as_rotvec()  # (24, 3)
        d = trans[s] - (2 * trans[s - 1] - trans[s - 2])
        x = (np.arange(a, s) - a + 1) / (s - a + 1)
        w = x * x * (3 - 2 * x)  # (s - a,)
        eased = Rotation.from_rotvec((w[:, None, None] * jump[None]).reshape(-1, 3))
        poses[a:s] = (eased * Rotation.from_rotvec(poses[a:s].reshape(-1, 3))).as_rotvec().reshape(s - a, 72)
        trans[a:s] += w[:, None] * d
        done.append(int(idx[s]))
    return poses, trans, done


def smooth_root_depth(root: np.ndarray, camera_R: np.ndarray, camera_t: np.ndarray, fps: float,
                      window_s: float = DEPTH_WINDOW_S, order: int = DEPTH_ORDER,
                      frame_index=None, breaks=()) -> np.ndarray:
    """How far to move the body in each frame so that its root's distance from the camera
    follows a Savitzky-Golay filter of itself, along the camera ray through the root.

    Monocular fits pin the body's image but not its distance: the depth follows the fitted
    pose's 3D size and jitters from frame to frame while the image stays put. Moving each
    frame along the ray through its root keeps the root's pixel where it is (the rest of
    the body's image scales about it by the ratio of the depths, a few per cent) and
    replaces the distance by its smoothed value. Runs of consecutive frames are smoothed
    apart (never across a gap, a non-finite frame or a frame in ``breaks``, such as a
    re-initialisation, where the depth may jump); a window longer than a run shrinks to
    it; a run of at most ``order`` frames, or a frame whose smoothed distance is not
    positive, is left where it is.

    Args:
        root: ``(T, 3)`` the root joint (pelvis) in world coordinates, metres.
        camera_R: ``(3, 3)`` world-to-camera rotation; camera_t: ``(3,)`` metres
            (``x_cam = R x + t``).
        fps: frames per second (Hz). window_s: the window in seconds
            (:func:`window_frames`). order: polynomial degree.
        frame_index: ``(T,)`` the input's frame numbers, or None (consecutive).
        breaks: input frame numbers that start a new run.

    Returns:
        ``(T, 3)`` float64 shift in world coordinates (metres) to add to the translation and
        to every joint and vertex of each frame (zero where nothing moves).
    """
    root = np.asarray(root, np.float64)
    if root.ndim != 2 or root.shape[1] != 3:
        raise InputError(f"root must have shape (T, 3); got {root.shape}.")
    R = np.asarray(camera_R, np.float64)
    t = np.asarray(camera_t, np.float64).reshape(3)
    if not isinstance(order, (int, np.integer)) or order < 0:
        raise InputError(f"the smoothing order must be a whole number >= 0, got {order!r}.")
    window = window_frames(window_s, fps, order)
    cam = root @ R.T + t
    dist = np.linalg.norm(cam, axis=1)
    ok = np.isfinite(dist) & (dist > 0) & (cam[:, 2] > 0)
    shift = np.zeros_like(root)
    for a, b in _runs(frame_index, root.shape[0], ok, breaks):
        d = smooth_translations(dist[a:b], window, order)
        good = np.isfinite(d) & (d > 0)
        moved = cam[a:b] * (np.where(good, d, dist[a:b]) / dist[a:b])[:, None]
        shift[a:b] = (moved - cam[a:b]) @ R  # camera -> world: R^T (moved - cam)
    return shift


def depth_smoothed_motion(motion: dict, window_s: float = DEPTH_WINDOW_S, order: int = DEPTH_ORDER,
                          breaks=()) -> dict:
    """A result's ``motion.npz`` arrays with the root's depth smoothed (:func:`smooth_root_depth`).

    ``trans`` and ``joints3d`` move by the shift, ``joints2d`` is projected again with the
    result's camera; the tracker's own per-frame values are kept as ``trans_tracked``
    (``(T, 3)`` metres; ``joints3d`` before = ``joints3d - (trans - trans_tracked)``).
    ``window_s`` 0 returns the arrays unchanged (and no ``trans_tracked``).

    Args:
        motion: ``poses (T, 72)``, ``trans (T, 3)``, ``joints3d (T, 24, 3)``, ``joints2d
            (T, 24, 2)``, ``fps``, ``camera`` (JSON of ``PinholeCamera.to_dict()``),
            ``frame_index (T,)`` and anything else (kept).
        breaks: input frame numbers where the depth may jump (re-initialisations): the
            smoothing starts again there.
    """
    if window_s == 0:
        return dict(motion)
    import json

    from flowmocap.geometry.camera import PinholeCamera

    camera = PinholeCamera.from_dict(json.loads(str(np.asarray(motion["camera"]))))
    joints = np.asarray(motion["joints3d"], np.float64)
    shift = smooth_root_depth(joints[:, 0], camera.R, camera.t, float(np.asarray(motion["fps"])), window_s, order,
                              frame_index=motion.get("frame_index"), breaks=breaks)
    out = dict(motion)
    trans = np.asarray(motion["trans"])
    out["trans_tracked"] = trans.copy()
    out["trans"] = (trans + shift).astype(trans.dtype)
    moved = joints + shift[:, None, :]
    out["joints3d"] = moved.astype(np.asarray(motion["joints3d"]).dtype)
    j2d = np.asarray(camera.project(moved.reshape(-1, 3)), np.float64).reshape(joints.shape[0], -1, 2)
    out["joints2d"] = j2d.astype(np.asarray(motion["joints2d"]).dtype)
    return out


def posed_joints(body, betas, poses: np.ndarray, trans: np.ndarray, camera, chunk: int = 64):
    """The body's 24 joints for ``poses (T, 72)`` radians and ``trans (T, 3)`` metres with
    shape ``betas (10,)`` (posed ``chunk`` frames at a time, no vertices): ``joints (T, 24,
    3)`` world metres and their pixels ``(T, 24, 2)`` through ``camera`` (a
    :class:`~flowmocap.geometry.camera.PinholeCamera`), both float64."""
    import torch

    dt = body.v_template.dtype
    b = torch.as_tensor(np.asarray(betas, np.float64).reshape(1, -1), dtype=dt)
    T = len(poses)
    joints = np.empty((T, 24, 3))
    with torch.no_grad():
        for a in range(0, T, chunk):
            e = min(a + chunk, T)
            out = body(betas=b.expand(e - a, -1), pose=torch.as_tensor(np.asarray(poses[a:e]), dtype=dt),
                       trans=torch.as_tensor(np.asarray(trans[a:e]), dtype=dt), with_vertices=False)
            joints[a:e] = out.joints.double().numpy()
    return joints, np.asarray(camera.project(joints.reshape(-1, 3)), np.float64).reshape(T, -1, 2)


def pose_smoothed_motion(motion: dict, body, window_s: float = DEFAULT_WINDOW_S, order: int = DEFAULT_ORDER,
                         breaks=(), chunk: int = 64) -> tuple[dict, dict]:
    """A result's ``motion.npz`` arrays with the poses and translation smoothed over time
    (:func:`smooth_motion`: every joint's rotation on SO(3), the translation alike).

    ``joints3d`` are recomputed with ``body`` and ``joints2d`` projected with the result's
    camera; the motion before is kept as ``poses_unsmoothed`` and ``trans_unsmoothed``.
    Runs of consecutive input frames are smoothed apart, and a frame number in ``breaks`` (a
    re-initialisation, where the pose and the depth may jump) starts a new run. (Smoothing
    the rotations across re-initialisations was tried: better 3D on the real multi-view
    recording, a worse overlay on the real clips; docs/experiments.md, "The motion
    smoothed last".)

    Args:
        motion: ``poses (T, 72)`` radians, ``trans (T, 3)`` metres, ``betas``, ``joints3d
            (T, 24, 3)``, ``joints2d (T, 24, 2)``, ``fps``, ``camera`` (JSON of
            ``PinholeCamera.to_dict()``), ``frame_index (T,)`` and anything else (kept).
        body: the :class:`~flowmocap.body.BodyModel` of the fit.
        window_s: seconds (:func:`window_frames`); order: polynomial degree.

    Returns:
        ``(motion, info)``: the new arrays, and ``{"window_s", "order", "mean_move_mm",
        "mean_move_px"}`` (how far the 24 joints moved on average, in 3D and in the image).
    """
    import json

    from flowmocap.geometry.camera import PinholeCamera

    poses0 = np.asarray(motion["poses"], np.float64)
    trans0 = np.asarray(motion["trans"], np.float64)
    fps = float(np.asarray(motion["fps"]))
    poses, trans = smooth_motion(poses0, trans0, fps, window_s, order, frame_index=motion.get("frame_index"),
                                 breaks=breaks)
    camera = PinholeCamera.from_dict(json.loads(str(np.asarray(motion["camera"]))))
    T = poses.shape[0]
    joints, j2d = posed_joints(body, motion["betas"], poses, trans, camera, chunk)
    before3d = np.asarray(motion["joints3d"], np.float64)
    before2d = np.asarray(motion["joints2d"], np.float64)
    out = dict(motion)
    out["poses_unsmoothed"] = np.asarray(motion["poses"]).copy()
    out["trans_unsmoothed"] = np.asarray(motion["trans"]).copy()
    out["poses"] = poses.astype(np.asarray(motion["poses"]).dtype)
    out["trans"] = trans.astype(np.asarray(motion["trans"]).dtype)
    out["joints3d"] = joints.astype(np.asarray(motion["joints3d"]).dtype)
    out["joints2d"] = j2d.astype(np.asarray(motion["joints2d"]).dtype)
    info = {"window_s": float(window_s), "order": int(order),
            "mean_move_mm": float(1000 * np.linalg.norm(joints - before3d, axis=-1).mean()) if T else 0.0,
            "mean_move_px": float(np.linalg.norm(j2d - before2d, axis=-1).mean()) if T else 0.0}
    return out, info


#: The seen frames before a held run in which a repeating motion (a walk, a run) is looked
#: for: at most this many seconds ...
CYCLE_WINDOW_S = 3.0
#: ... periods from this to this many seconds (a gait cycle, two steps, is about 1 s walking
#: and 0.7 s running) ...
CYCLE_PERIOD_S = (0.4, 2.0)
#: ... and a motion repeats where its legs' poses one period apart correlate at least this
#: much (the normalised autocorrelation of the hips' and knees' rotations, each trend removed):
#: tracked walks 0.61-0.76 (a synthetic walker, the Sports2D woman), true mocap walks above
#: 0.9; tracked dancing, turning and standing clips of the project 0.06-0.38.
CYCLE_MIN_CORRELATION = 0.6
#: The joints whose rotations the period is found from (SMPL hips and knees).
CYCLE_JOINTS = (1, 2, 4, 5)
#: A gait alternates: the left hip's and knee's flexion correlates with the right's half a
#: period later at least this much, and not positively in the same frame. Walks, true and
#: tracked: 0.71-1.0 and -0.23 to -0.68; the mocap clips that repeat without alternating
#: (balancing on one leg, jumping, a bend, a combat stance) fail it.
CYCLE_MIN_ALTERNATION = 0.6
#: A walk carried through a held run stops part of the way where the root moves, between the
#: two ends of the run, less than this share of what the walk's own speed (seen over the
#: cycle's last period next to the run) would cover in the run's time, and the other side
#: shows no gait: the person stopped behind the occluder (or, with the cycle seen after the
#: run, started walking there).
STOP_MAX_SHARE = 0.6
#: ... then the body settles from the carried cycle into the pose seen on the other side over
#: this many seconds (a stop from a walk takes about one step).
STOP_SETTLE_S = 0.4


def motion_period(poses: np.ndarray, fps: float, window_s: float = CYCLE_WINDOW_S,
                  period_s: tuple[float, float] = CYCLE_PERIOD_S,
                  min_correlation: float = CYCLE_MIN_CORRELATION) -> tuple[int, float] | None:
    """The period of a gait (a walk, a run): the lag, in frames, at which the hips' and knees'
    rotations correlate best with themselves, where that correlation is at least
    ``min_correlation`` and the legs alternate (:data:`CYCLE_MIN_ALTERNATION`).

    Args:
        poses: ``(T, 72)`` axis-angle radians of consecutive frames (the last ``window_s``
            seconds are used; :data:`CYCLE_JOINTS` only, each coordinate's straight-line
            trend removed).
        fps: frames per second.

    Returns:
        ``(lag_frames, correlation)``, or None where no lag in ``period_s`` reaches
        ``min_correlation``, the legs do not alternate, or there are fewer than 1.5 of the
        shortest periods of frames.
    """
    legs = np.asarray(poses, np.float64)[-max(2, int(round(window_s * fps))):].reshape(-1, 24, 3)
    x = legs[:, list(CYCLE_JOINTS)].reshape(len(legs), -1)
    lo, hi = max(2, int(round(period_s[0] * fps))), int(round(period_s[1] * fps))
    hi = min(hi, int(len(x) / 1.5))
    if hi < lo:
        return None
    t = np.c_[np.arange(len(x)), np.ones(len(x))]
    x = x - t @ np.linalg.lstsq(t, x, rcond=None)[0]
    best = None
    for lag in range(lo, hi + 1):
        a, b = x[:-lag], x[lag:]
        den = np.sqrt((a * a).sum() * (b * b).sum())
        r = float((a * b).sum() / den) if den > 0 else 0.0
        if best is None or r > best[1]:
            best = (lag, r)
    if best is None or best[1] < min_correlation:
        return None
    left, right = legs[:, [1, 4], 0], legs[:, [2, 5], 0]  # hips' and knees' flexion (about x)
    half = max(1, best[0] // 2)
    if _correlation(left[:-half], right[half:]) < CYCLE_MIN_ALTERNATION or _correlation(left, right) > 0:
        return None
    return best


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(0), b - b.mean(0)
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else 0.0


def inbetween_unseen(motion: dict, body, gaps, chunk: int = 64, fps: float | None = None,
                     cycles: bool = True) -> tuple[dict, dict]:
    """A result's ``motion.npz`` arrays with each run of frames where the person was not seen
    (and the body held, ``TrackerConfig.hold_unseen_frames``) filled in between the last frame
    seen before it and the first seen after it, the translation linearly in time, and the
    joints' rotations one of two ways:

    - where the seen frames before the run repeat (a walk, a run: :func:`motion_period`), the
      motion's cycle carried on through the run (each frame takes the pose one or more periods
      before it), eased into both ends: the rotation by which the cycle misses the pose seen
      at each end is blended in, fully at that end and not at the other; where those before
      do not (too few of them: a run early in the clip), but those after it do, the cycle
      seen after carried back through the run the same way (each frame takes the pose one or
      more periods after it);
      Where the root moves across the run much less than that walk's speed would take it
      (:data:`STOP_MAX_SHARE`) and the other side shows no gait, the person stopped behind
      the occluder (or started walking there): the cycle is carried only for the frames
      that speed needs, the root covering the move in them, and the body then settles into
      the pose seen on the other side (:data:`STOP_SETTLE_S`) and stands;
    - else every joint's rotation by spherical linear interpolation between the two ends.

    The tracker holds the body at the last seen pose through such a run, and the first frame
    seen again re-initialises it: the motion freezes, then jumps. An animator keys the same
    two poses and lets the curve run between them, or carries a walk cycle through; so does
    this. The frames stay marked as not seen (``run.json``'s ``gaps``). A run at the start or
    the end of the motion, without a frame on both sides, is left held.

    Args:
        motion: ``poses (T, 72)`` radians, ``trans (T, 3)`` metres, ``betas``, ``joints3d``,
            ``joints2d``, ``camera``, ``frame_index (T,)`` and anything else (kept).
        body: the :class:`~flowmocap.body.BodyModel` of the fit.
        gaps: ``[(first, last), ...]`` input frame numbers of the held runs.
        fps: frames per second (default: ``motion["fps"]``, else 30).
        cycles: carry a repeating motion's cycle through (else always the plain in-between).

    Returns:
        ``(motion, info)``: the new arrays (``joints3d`` recomputed, ``joints2d``
        projected), and ``{"runs": [[first, last], ...] (those filled), "frames": n,
        "cycles": [[first, last, period_frames, "before" | "after"], ...] (the runs the cycle
        was carried through, and the side of the run it was seen on), "stops": [[first, last,
        walked_frames, "before" | "after"], ...] (those of them in which the walk stops, or
        with "after" starts, and for how many of the run's frames it walks)}``.
    """
    import json

    from scipy.spatial.transform import Rotation, Slerp

    from flowmocap.geometry.camera import PinholeCamera

    poses = np.array(motion["poses"], np.float64)
    trans = np.array(motion["trans"], np.float64)
    index = np.asarray(motion.get("frame_index", np.arange(len(poses))), np.int64)
    fps = float(fps if fps is not None else np.asarray(motion.get("fps", 30.0)))
    row = {int(f): k for k, f in enumerate(index)}
    unseen = {f for first, last in gaps for f in range(int(first), int(last) + 1)}
    done, cycled, stopped = [], [], []
    for first, last in gaps:
        a, b = row.get(int(first) - 1), row.get(int(last) + 1)
        inside = [row[f] for f in range(int(first), int(last) + 1) if f in row]
        if a is None or b is None or not inside:
            continue
        u = (index[inside] - index[a]) / float(index[b] - index[a])  # (n,) in (0, 1)
        period = side = None
        if cycles:
            window = int(round(CYCLE_WINDOW_S * fps))
            seen, periods = {}, {}
            for sd, f, step in (("before", int(first) - 1, -1), ("after", int(last) + 1, 1)):
                seen[sd] = []  # the seen frames next to the run, consecutive, the nearest first
                while f in row and f not in unseen and len(seen[sd]) < window:
                    seen[sd].append(row[f])
                    f += step
                # in time towards the run (after it: time reversed), so the run's side is the last
                periods[sd] = motion_period(poses[seen[sd][::-1]], fps) if len(seen[sd]) > 2 else None
            side = "before" if periods["before"] is not None else "after"
            period = periods[side]
        walked = None  # where the walk stops (or starts) within the run: its frames from the cycle's side
        if period is not None and periods["before" if side == "after" else "after"] is None:
            walked = _walked_frames(trans, seen[side], period[0], a, b, index, fps)
        if period is not None:
            lag = period[0]
            ends = np.r_[index[a], index[b]]
            if side == "before":  # each frame takes the pose whole periods before it, seen before the run
                source = [row[int(g - lag * int(np.ceil((g - (int(first) - 1)) / lag)))] for g in index[inside]]
                at = (row[int(first) - 1 - lag], row[int(ends[1] - lag * int(np.ceil((ends[1] - first + 1) / lag)))])
            else:  # ... whole periods after it, seen after the run
                source = [row[int(g + lag * int(np.ceil((int(last) + 1 - g) / lag)))] for g in index[inside]]
                at = (row[int(ends[0] + lag * int(np.ceil((last + 1 - ends[0]) / lag)))], row[int(last) + 1 + lag])
            carried = poses[source].reshape(-1, 24, 3)  # the cycle through the run
            # how the cycle misses the pose seen at each end
            d0 = (Rotation.from_rotvec(poses[a].reshape(24, 3)) * Rotation.from_rotvec(
                poses[at[0]].reshape(24, 3)).inv()).as_rotvec()  # (24, 3)
            d1 = (Rotation.from_rotvec(poses[b].reshape(24, 3)) * Rotation.from_rotvec(
                poses[at[1]].reshape(24, 3)).inv()).as_rotvec()
            if walked is None:
                for k, (r, w) in enumerate(zip(inside, u)):
                    fix = Rotation.from_rotvec((1 - w) * d0 + w * d1)
                    poses[r] = (fix * Rotation.from_rotvec(carried[k])).as_rotvec().reshape(-1)
            else:  # the walk for its frames next to the cycle's side, then a settle into the other side's pose
                _stop_within(poses, trans, inside, carried, d0 if side == "before" else d1, a, b, index, walked,
                             side, max(1, int(round(STOP_SETTLE_S * fps))))
                stopped.append([int(first), int(last), int(walked), side])
            cycled.append([int(first), int(last), int(lag), side])
        else:
            ends = Rotation.from_rotvec(np.stack([poses[a], poses[b]]).reshape(2, 24, 3).transpose(1, 0, 2)
                                        .reshape(-1, 3))
            for j in range(24):
                poses[inside, 3 * j:3 * j + 3] = Slerp([0.0, 1.0], ends[2 * j:2 * j + 2])(u).as_rotvec()
        if walked is None:
            trans[inside] = (1 - u)[:, None] * trans[a] + u[:, None] * trans[b]
        done.append([int(first), int(last)])
    out = dict(motion)
    if done:
        camera = PinholeCamera.from_dict(json.loads(str(np.asarray(motion["camera"]))))
        joints, j2d = posed_joints(body, motion["betas"], poses, trans, camera, chunk)
        out["poses"] = poses.astype(np.asarray(motion["poses"]).dtype)
        out["trans"] = trans.astype(np.asarray(motion["trans"]).dtype)
        out["joints3d"] = joints.astype(np.asarray(motion["joints3d"]).dtype)
        out["joints2d"] = j2d.astype(np.asarray(motion["joints2d"]).dtype)
    return out, {"runs": done, "frames": int(sum(b - a + 1 for a, b in done)), "cycles": cycled,
                 "stops": stopped}


def _walked_frames(trans: np.ndarray, seen: list, lag: int, a: int, b: int, index: np.ndarray,
                   fps: float) -> int | None:
    """How many of a held run's frames (between rows ``a`` and ``b``) a walk seen next to it
    lasts, where it stops (or starts) within the run: the root's move from ``a`` to ``b``
    over the walk's speed, that of the cycle's last period next to the run (``seen``, rows,
    the nearest first; ``lag`` frames); None where the move is at least
    :data:`STOP_MAX_SHARE` of what that speed covers in the run's time, or there is no
    speed to go by."""
    if len(seen) <= lag:
        return None
    speed = np.linalg.norm(trans[seen[0]] - trans[seen[lag]]) / abs(int(index[seen[0]] - index[seen[lag]]))  # m/frame
    span = int(index[b] - index[a])
    if not speed > 0:
        return None
    share = float(np.linalg.norm(trans[b] - trans[a]) / (speed * span))
    if share >= STOP_MAX_SHARE:
        return None
    return max(1, int(round(share * span)))


def _stop_within(poses, trans, inside, carried, miss, a, b, index, walked, side, settle) -> None:
    """Fill a held run (rows ``inside`` between rows ``a`` and ``b``) in place with a walk
    that stops (``side`` "before": the cycle seen before it) or starts (``side`` "after")
    within it: the frames up to ``walked`` frames from the cycle's side take the carried cycle
    (``carried`` ``(n, 24, 3)``), its miss of the pose seen there (``miss`` ``(24, 3)``) eased
    out, while the root covers the whole move from one end to the other in a straight line;
    the rest settle from the last walking pose into the pose seen on the other side over
    ``settle`` frames and hold it there, the root still."""
    from scipy.spatial.transform import Rotation

    near, far = (a, b) if side == "before" else (b, a)
    dist = np.abs(index[inside] - index[near])  # frames from the cycle's side
    order = np.argsort(dist)
    end_pose = Rotation.from_rotvec(poses[far].reshape(24, 3))
    stop_pose = None
    for k in order:
        r, d = inside[k], int(dist[k])
        if d <= walked:
            w = d / walked
            pose = Rotation.from_rotvec((1 - w) * miss) * Rotation.from_rotvec(carried[k])
            trans[r] = (1 - w) * trans[near] + w * trans[far]
            stop_pose = pose
        else:
            if stop_pose is None:  # no walking frame inside (the walk ends at the run's first frame)
                stop_pose = Rotation.from_rotvec(poses[near].reshape(24, 3))
            w = min(1.0, (d - walked) / settle)
            pose = stop_pose * Rotation.from_rotvec(w * (stop_pose.inv() * end_pose).as_rotvec())
            trans[r] = trans[far]
        poses[r] = pose.as_rotvec().reshape(-1)


#: the body model's foot joints (SMPL ``left_foot``, ``right_foot``): the stance test's points
FOOT_JOINTS = (10, 11)


def stance_depth_shift(joints: np.ndarray, joints2d: np.ndarray, camera_R: np.ndarray, camera_t: np.ndarray,
                       fps: float, speed: float = 0.12, min_s: float = 0.2, window_s: float = 0.25,
                       share: float = 0.5, frame_index=None, breaks=(),
                       zooms: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """How far to move the body in each frame, along the camera ray through its root, so
    that a foot standing still in the image also stands still in depth.

    A monocular fit's depth follows its pose's 3D size from frame to frame (see
    :func:`flowmocap.fit.smooth.smooth_root_depth`); a foot that does not move in the image is, in the world,
    planted, and so keeps its distance from the camera. For each foot joint
    (:data:`FOOT_JOINTS`) the frames where its image speed stays below ``speed`` body
    heights per second (the slower of the steps to and from the frame; the body's height
    is the median over the frames of its 2D joints' vertical extent) for at least
    ``min_s`` seconds are a stance; within a stance the foot's camera depth should be
    its median there, and the difference is the frame's depth correction (the mean over
    the feet in stance). Between stances the correction is interpolated (held before
    the first and after the last), smoothed by a moving average over ``window_s``
    seconds and applied at ``share``. Runs of consecutive frames are treated apart (a
    gap, a non-finite frame or a frame in ``breaks`` starts a new one); a run without
    a stance is not moved.

    Args:
        joints: ``(T, J, 3)`` world coordinates, metres (SMPL order, joint 0 the root).
        joints2d: ``(T, J, 2)`` their image, pixels.
        camera_R: ``(3, 3)`` world-to-camera rotation; camera_t: ``(3,)`` metres.
        fps: frames per second (Hz). speed: body heights per second. min_s, window_s:
            seconds. share: the part of the correction applied, in [0, 1].
        frame_index: ``(T,)`` input frame numbers, or None (consecutive).
        breaks: input frame numbers that start a new run (re-initialisations).
        zooms: ``(T,)`` each frame's focal length over the tracked one's, where the camera
            zoomed (:mod:`flowmocap.vision.camera_motion`), or None: a tracked depth ``d``
            is then ``zooms * d`` in the world (:func:`flowmocap.export.motion.zoomed_depth`),
            and a planted foot keeps that depth, not the tracked one.

    Returns:
        ``(shift (T, 3), stance (T,) bool)``: the world shift (metres) to add to the
        translation and every point of each frame, and the frames with a foot in stance.
    """
    J = np.asarray(joints, np.float64)
    P = np.asarray(joints2d, np.float64)
    if J.ndim != 3 or J.shape[2] != 3 or J.shape[1] <= max(FOOT_JOINTS) or P.shape != J.shape[:2] + (2,):
        raise InputError(f"joints must be (T, J, 3) and joints2d (T, J, 2) with J > {max(FOOT_JOINTS)}; "
                         f"got {J.shape} and {P.shape}.")
    if not (fps > 0 and speed > 0 and min_s >= 0 and window_s >= 0 and 0.0 <= share <= 1.0):
        raise InputError(f"fps, speed must be > 0, min_s, window_s >= 0 and share in [0, 1]; got {fps}, {speed}, "
                         f"{min_s}, {window_s}, {share}.")
    R = np.asarray(camera_R, np.float64)
    t = np.asarray(camera_t, np.float64).reshape(3)
    T = J.shape[0]
    cam = J @ R.T + t
    zoom = np.ones(T) if zooms is None else np.asarray(zooms, np.float64).reshape(-1)
    if zoom.shape != (T,) or not np.all(zoom > 0):
        raise InputError(f"zooms must be ({T},) positive ratios; got {zoom.shape}.")
    shift = np.zeros((T, 3))
    stance = np.zeros(T, bool)
    ok = np.isfinite(cam).all((1, 2)) & np.isfinite(P).all((1, 2)) & (cam[:, :, 2] > 0).all(1)
    if not ok.any():
        return shift, stance
    height = float(np.median(np.ptp(P[ok, :, 1], axis=1)))
    if not height > 0:
        return shift, stance
    need = max(int(np.ceil(min_s * fps)), 2)
    width = max(int(round(window_s * fps)), 1)
    for a, b in _runs(frame_index, T, ok, breaks):
        n = b - a
        total, count = np.zeros(n), np.zeros(n)
        for f in FOOT_JOINTS:
            step = np.linalg.norm(np.diff(P[a:b, f], axis=0), axis=-1) * fps / height
            v = np.minimum(np.r_[np.inf, step], np.r_[step, np.inf])
            for s0, s1 in _runs(None, n, v < speed):
                if s1 - s0 < need:
                    continue
                zw = zoom[a + s0:a + s1]
                z = cam[a + s0:a + s1, f, 2] * zw  # the world's depth where the camera zoomed
                total[s0:s1] += (np.median(z) - z) / zw
                count[s0:s1] += 1
        have = count > 0
        if not have.any():
            continue
        stance[a:b] = have
        k = np.arange(n)
        dz = np.interp(k, k[have], total[have] / count[have])
        if width > 1:
            pad = np.pad(dz, (width // 2, width - 1 - width // 2), mode="edge")
            dz = np.convolve(pad, np.ones(width) / width, mode="valid")
        root = cam[a:b, 0]
        moved = root * ((root[:, 2] + share * dz) / root[:, 2])[:, None]
        moved[~(moved[:, 2] > 0)] = root[~(moved[:, 2] > 0)]
        shift[a:b] = (moved - root) @ R
    return shift, stance


def stance_depth_motion(motion: dict, share: float, speed: float = 0.12, min_s: float = 0.2,
                        window_s: float = 0.25, breaks=(), zooms: np.ndarray | None = None) -> tuple[dict, dict]:
    """A result's ``motion.npz`` arrays moved by :func:`stance_depth_shift`: ``trans`` and
    ``joints3d`` shifted, ``joints2d`` projected again with the result's camera; the
    poses are unchanged. ``share`` 0 returns the arrays unchanged.

    Args:
        motion: ``trans (T, 3)``, ``joints3d (T, 24, 3)``, ``joints2d (T, 24, 2)``,
            ``fps``, ``camera`` (JSON of ``PinholeCamera.to_dict()``), ``frame_index (T,)``
            and anything else (kept).
        share, speed, min_s, window_s: as :func:`stance_depth_shift` (the defaults of
            ``TrackerConfig``'s ``stance_depth_*`` settings).
        breaks: input frame numbers where the depth may jump (re-initialisations).
        zooms: ``(T,)`` or None, as :func:`stance_depth_shift`.

    Returns:
        ``(motion, info)``: the new arrays, and ``frames_in_stance``, ``mean_shift_mm``
        (mean distance each frame moved).
    """
    if share == 0:
        return dict(motion), {"frames_in_stance": 0, "mean_shift_mm": 0.0}
    import json

    from flowmocap.geometry.camera import PinholeCamera

    camera = PinholeCamera.from_dict(json.loads(str(np.asarray(motion["camera"]))))
    joints = np.asarray(motion["joints3d"], np.float64)
    shift, stance = stance_depth_shift(joints, np.asarray(motion["joints2d"], np.float64), camera.R, camera.t,
                                       float(np.asarray(motion["fps"])), speed=speed, min_s=min_s,
                                       window_s=window_s, share=share, frame_index=motion.get("frame_index"),
                                       breaks=breaks, zooms=zooms)
    out = dict(motion)
    trans = np.asarray(motion["trans"])
    out["trans"] = (trans + shift).astype(trans.dtype)
    moved = joints + shift[:, None, :]
    out["joints3d"] = moved.astype(np.asarray(motion["joints3d"]).dtype)
    j2d = np.asarray(camera.project(moved.reshape(-1, 3)), np.float64).reshape(joints.shape[0], -1, 2)
    out["joints2d"] = j2d.astype(np.asarray(motion["joints2d"]).dtype)
    info = {"frames_in_stance": int(stance.sum()),
            "mean_shift_mm": float(1000 * np.linalg.norm(shift, axis=1).mean()) if len(shift) else 0.0}
    return out, info
