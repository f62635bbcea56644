"""The real multi-view 3D benchmark (``real3d``): monocular runs on the Pose2Sim
multi-person recording, scored against a 3D reference triangulated from the other views.

Data: ``../shared/data/video/pose2sim-multi/`` (four calibrated, unsynchronised portrait
views ``videos/cam01.mp4 ... cam04.mp4``, 1088 x 1920, 60 fps, 100 frames; two people
plus, in some views, a third in the background; ``Calib.qca.txt``; see its README).

The reference is built with the project's own code and cached in ``OUT/reference/``:

1. **People per view** (:func:`detect_view_people`): MediaPipe (the tracking detector
   and a searcher on the frame with the first person blanked,
   :func:`~flowmocap.vision.auto.find_people`) on each video scaled to a long side of
   960 px (the landmark model sees a 256 px crop of the person either way), split into
   tracks, and each track followed again with everyone else blanked
   (:func:`~flowmocap.vision.auto.follow_person`) so every person has their own
   detections in every frame the detector can see them. Keypoints are stored in the
   videos' full-resolution pixels.
2. **People across views and time offsets** (:func:`associate_people`): every track of
   the reference view (cam01) is paired with every track of each other view at every
   offset in [-15, 15] frames; a pair whose two-view triangulation reprojects within
   ``max_px`` (median over joints and frames) is the same person. The offsets are then
   :func:`~flowmocap.geometry.triangulate.estimate_offsets` over all matched people; that
   estimate is reported, but the reference uses :data:`PINNED_OFFSETS` (it is uncertain by
   about a frame and moved with every change of the detection code).
3. **Triangulation** (:func:`triangulate_person`): robust, confidence-weighted DLT
   (:func:`~flowmocap.geometry.triangulate.triangulate`, the worst view dropped while it
   reprojects more than 20 px off and two views remain) of the 15 detector keypoints at
   every reference time (cam01's frame numbers), once with all views and once without
   each view.

Then each of the two main people (those seen longest over all views) is tracked from
each view by :func:`flowmocap.pipeline.track` (``person="x,y"``: the pixel at the centre
of that person's reference detections in the first frame they appear in; ``max_size``
640 by default), and scored on the paper's 13 joints
(:data:`~flowmocap.body.skeleton.EVAL_JOINTS`; head = the midpoint of the detector's
ears for the reference and the detector, SMPL's head joint for the fit) against the
reference triangulated **without** that view (frame ``f`` of view ``c`` is reference
time ``f + offset[c]``). The fit is scored twice: its joints (``flowmocap``), and its
body at the detector's keypoints (``flowmocap_kp``, :func:`keypoint_joints`: the learned
offsets of :mod:`flowmocap.vision.keypoint_map`, the reference's own convention):

- per-frame PA-MPJPE: a similarity Procrustes per frame, mean joint error, mm;
- per-sequence PA-MPJPE: joints made relative to the middle of the hips, one similarity
  over the whole sequence, mm.

The same for the **detector-3D row**: MediaPipe's world landmarks of the same run
(``OUT/detections/keypoints.npz`` ``world``). Both are scored on the same frames and
joints: frames where the reference has at least :data:`MIN_JOINTS` of the 13 joints
(both hips among them; a joint the remaining views do not agree on within 20 px is
left out), the detection has 3D landmarks and the body was fitted; the others are
counted as skipped.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from flowmocap.body.skeleton import EVAL_JOINTS, JOINT_NAMES
from flowmocap.errors import DataError, FlowMocapError, InputError
from flowmocap.geometry.procrustes import similarity_procrustes
from flowmocap.geometry.triangulate import CalibratedCamera, estimate_offsets, offset_cost, triangulate
from flowmocap.io.calibration import read_qualisys_calibration
from flowmocap.io.results import has_result, json_default
from flowmocap.pipeline import load_result, track
from flowmocap.vision.detect import KEYPOINT_NAMES

__all__ = ["run_real3d", "build_reference", "detect_view_people", "associate_people", "triangulate_person",
           "score_run", "format_real3d_table", "eval_points", "pa_mpjpe", "joint_errors", "person_pixel", "bone_lengths",
           "consistent_joints", "scored_frames", "scored_runs", "BONES", "DATA", "VIEWS", "EVAL_NAMES"]

ROOT = Path(__file__).resolve().parents[3]
#: The Pose2Sim multi-person recording (under ``$FLOWMOCAP_DATA`` where set, else ``../shared/data``).
DATA = Path(os.environ.get("FLOWMOCAP_DATA", "").strip() or ROOT.parent / "shared" / "data").expanduser() / "video" \
    / "pose2sim-multi"
VIEWS = ("cam01", "cam02", "cam03", "cam04")
#: The 13 evaluated joints, in the order of :data:`~flowmocap.body.skeleton.EVAL_JOINTS`.
EVAL_NAMES: tuple[str, ...] = tuple(JOINT_NAMES[j] for j in EVAL_JOINTS)
#: Long side (pixels) of the frames the reference's detector sees.
REF_MAX_SIDE = 960
#: Reprojection error (full-resolution pixels) above which a view is dropped from a point.
REF_MAX_ERROR_PX = 20.0
#: Median two-view reprojection error (pixels) below which two tracks are one person.
ASSOCIATE_MAX_PX = 40.0
OFFSET_SEARCH = range(-15, 16)
#: Change whenever the detections per view would come out differently (their cache is rebuilt).
DETECTION_VERSION = 6  # 4: the follow pass keeps whole detections; the searcher blanks bodies, not boxes; 5: ... and drops what it finds again of a blanked person; 6: the follow pass blanks a person the search lost for 15 frames more
#: Change whenever the reference would come out differently from the same detections.
REFERENCE_VERSION = 4  # 4: the time offsets pinned (PINNED_OFFSETS)
#: The views' time offsets the reference uses (frames at 60 fps: view v's frame f shows
#: cam01's frame f + offset), or None to use the estimate. The estimate
#: (:func:`associate_people`) is made and reported every time the reference is built, but
#: its costs a frame either way lie within 0.3-1.2 % of the best, and it moved by one or
#: two frames with each change of the detection code (detections v3: cam02 -1, cam03 -3,
#: cam04 -1; v5: -1, -4, -1; v6: 0, -2, 0), moving single person-views by up to 11 mm for
#: the same runs; fitted between frames it moves as much. The synchronisation is the
#: recording's, not the code's: pinned at the estimate of detections v6, so that the
#: reference changes only with the points it triangulates.
PINNED_OFFSETS: dict | None = {"cam01": 0, "cam02": 0, "cam03": -2, "cam04": 0}
METHODS = ("flowmocap", "detector3d", "flowmocap_kp")
#: frames per block of the ratio intervals' circular block bootstrap (a quarter of a second at 60 fps)
INTERVAL_BLOCK = 15
#: bootstrap draws of the ratio intervals
INTERVAL_DRAWS = 2000


# ------------------------------------------------------------------ joints


def eval_points(points: np.ndarray) -> np.ndarray:
    """The 13 evaluated joints from detector keypoints.

    Args:
        points: ``(..., K, d)`` in the order of
            :data:`~flowmocap.vision.detect.KEYPOINT_NAMES` (2D pixels or 3D metres).

    Returns:
        ``(..., 13, d)`` in the order of :data:`EVAL_NAMES`; the head is the midpoint of
        the ears (NaN where an ear is NaN).
    """
    p = np.asarray(points, np.float64)
    head = 0.5 * (p[..., KEYPOINT_NAMES.index("left_ear"), :] + p[..., KEYPOINT_NAMES.index("right_ear"), :])
    rest = [p[..., KEYPOINT_NAMES.index(n), :] for n in EVAL_NAMES[1:]]
    return np.stack([head] + rest, axis=-2)


#: The bones whose lengths :func:`consistent_joints` checks (pairs of :data:`EVAL_NAMES`).
BONES: tuple[tuple[str, str], ...] = (
    ("head", "left_shoulder"), ("head", "right_shoulder"), ("left_shoulder", "right_shoulder"),
    ("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"), ("right_shoulder", "right_elbow"),
    ("right_elbow", "right_wrist"), ("left_shoulder", "left_hip"), ("right_shoulder", "right_hip"),
    ("left_hip", "right_hip"), ("left_hip", "left_knee"), ("left_knee", "left_ankle"),
    ("right_hip", "right_knee"), ("right_knee", "right_ankle"),
)
#: A bone more than this fraction longer or shorter than the person's median makes a joint suspect.
BONE_TOLERANCE = 0.25


def bone_lengths(j13: np.ndarray) -> np.ndarray:
    """``(len(BONES),)`` the median over frames of each bone's length (metres; NaN
    frames ignored) of ``(T, 13, 3)`` joints in the order of :data:`EVAL_NAMES`."""
    idx = np.array([[EVAL_NAMES.index(a), EVAL_NAMES.index(b)] for a, b in BONES])
    L = np.linalg.norm(j13[:, idx[:, 0]] - j13[:, idx[:, 1]], axis=-1)
    with np.errstate(all="ignore"):
        return np.nanmedian(np.where(np.isfinite(L), L, np.nan), axis=0) if len(L) else np.full(len(BONES), np.nan)


def consistent_joints(j13: np.ndarray, lengths: np.ndarray, error_px: np.ndarray | None = None,
                      tolerance: float = BONE_TOLERANCE) -> np.ndarray:
    """Which triangulated joints fit the person's skeleton.

    A multi-view reference from a 2D detector has, in some frames, a joint that two
    views agree on wrongly (a left/right mix-up, a limb hidden in all but two views);
    such a joint makes its bones too long or too short. Per frame, while some bone is
    off by more than ``tolerance`` x its median ``lengths``, the joint touching most
    such bones (ties: the larger reprojection error, then the later joint in
    :data:`EVAL_NAMES`, i.e. the more distal) is marked invalid and its bones dropped.
    Then a joint left with no bone to another valid joint is marked invalid too: nothing
    checks it any more (real3d's person1 without cam01: once a wrong shoulder and wrist
    were dropped, the elbow between them, 1.4 m from the hips, stayed and was scored).

    Args:
        j13: ``(T, 13, 3)`` metres (NaN = missing).
        lengths: ``(len(BONES),)`` metres (:func:`bone_lengths`).
        error_px: optional ``(T, 13)`` reprojection errors for the ties.

    Returns:
        ``(T, 13)`` bool, finite and consistent.
    """
    idx = np.array([[EVAL_NAMES.index(a), EVAL_NAMES.index(b)] for a, b in BONES])
    valid = np.isfinite(j13).all(-1)
    err = np.zeros(valid.shape) if error_px is None else np.nan_to_num(np.asarray(error_px, np.float64))
    for t in range(len(j13)):
        while True:
            L = np.linalg.norm(j13[t, idx[:, 0]] - j13[t, idx[:, 1]], axis=-1)
            live = valid[t, idx[:, 0]] & valid[t, idx[:, 1]] & np.isfinite(lengths)
            bad = live & (np.abs(L - lengths) > tolerance * lengths)
            if not bad.any():
                break
            count = np.bincount(idx[bad].ravel(), minlength=len(EVAL_NAMES))
            key = count * 1e6 + err[t] + np.arange(len(EVAL_NAMES)) * 1e-6
            valid[t, int(np.argmax(np.where(count > 0, key, -1.0)))] = False
        live = valid[t, idx[:, 0]] & valid[t, idx[:, 1]] & np.isfinite(lengths)
        valid[t] &= np.bincount(idx[live].ravel(), minlength=len(EVAL_NAMES)) > 0
    return valid


def _hips(j13: np.ndarray) -> np.ndarray:
    return 0.5 * (j13[..., EVAL_NAMES.index("left_hip"), :] + j13[..., EVAL_NAMES.index("right_hip"), :])


# ------------------------------------------------------------------ the reference


def detect_view_people(video: str | Path, max_side: int = REF_MAX_SIDE, min_frames: int = 10,
                       progress: bool = True) -> dict:
    """Every person MediaPipe finds in a video, each followed over the whole video.

    Args:
        video: the video file.
        max_side: the long side (pixels) of the frames the detector sees.
        min_frames: tracks with fewer detections are dropped (stray detections).

    Returns:
        ``keypoints (P, T, K, 2)`` in the video's full-resolution pixels (NaN where the
        person is not found), ``confidence (P, T, K)``, ``score (P,)`` (the main-person
        score of :func:`~flowmocap.vision.auto.track_scores`, at the detector's scale),
        ``size (2,)`` the video's ``(W, H)``; people in decreasing score.
    """
    from flowmocap.io.video import load_video
    from flowmocap.vision.auto import find_people, follow_person, split_tracks, track_scores
    from flowmocap.vision.detect import MediaPipePoseDetector

    seq = load_video(video, max_side=max_side)
    scale = float(seq.meta.get("scale", 1.0))
    W, H = seq.size
    det = MediaPipePoseDetector(augment=False)
    cands = find_people(seq, det, [MediaPipePoseDetector(augment=False)], progress=progress)
    tracks = split_tracks(cands)
    scores = track_scores(cands, tracks, H)
    T, K = len(seq), len(KEYPOINT_NAMES)
    people = []
    for k in sorted(range(len(tracks)), key=lambda k: -scores[k]):
        if len(tracks[k]) < min_frames:
            continue
        followed = follow_person(seq, det, cands, tracks, k, progress=progress)
        kp = np.full((T, K, 2), np.nan)
        conf = np.zeros((T, K))
        for i, c in enumerate(followed):
            if c is not None:
                kp[i], conf[i] = np.asarray(c.keypoints) / scale, c.confidence
        people.append((kp, conf, scores[k]))
    people = _merge_duplicates(people)
    decoded = seq.meta.get("decoded_size", [W, H])
    if not people:
        return {"keypoints": np.zeros((0, T, K, 2)), "confidence": np.zeros((0, T, K)), "score": np.zeros(0),
                "size": np.array(decoded)}
    return {"keypoints": np.stack([p[0] for p in people]), "confidence": np.stack([p[1] for p in people]),
            "score": np.array([p[2] for p in people]), "size": np.array(decoded)}


def _merge_duplicates(people: list, same_px: float = 0.1) -> list:
    """Followed tracks that ended up on the same person (their keypoints within
    ``same_px`` x the person's height in most shared frames) become one, the earlier
    (higher score) first, the other filling its gaps."""
    out: list = []
    for kp, conf, score in people:
        for j, (kp0, conf0, s0) in enumerate(out):
            both = np.isfinite(kp[:, 0, 0]) & np.isfinite(kp0[:, 0, 0])
            if both.sum() < 5:
                continue
            height = np.nanmax(kp0[both, :, 1], axis=1) - np.nanmin(kp0[both, :, 1], axis=1)
            d = np.nanmedian(np.linalg.norm(kp[both] - kp0[both], axis=-1), axis=1)
            if np.mean(d < same_px * np.maximum(height, 1.0)) > 0.5:
                fill = ~np.isfinite(kp0[:, 0, 0]) & np.isfinite(kp[:, 0, 0])
                kp0[fill], conf0[fill] = kp[fill], conf[fill]
                out[j] = (kp0, conf0, s0 + score)
                break
        else:
            out.append((kp.copy(), conf.copy(), score))
    return out


def associate_people(cameras: list[CalibratedCamera], view_tracks: list[list[tuple]], reference: int = 0,
                     search=OFFSET_SEARCH, max_px: float = ASSOCIATE_MAX_PX, min_overlap: int = 10) -> dict:
    """Which tracks of the views are the same person, and each view's time offset.

    Each track of the ``reference`` view is paired with each track of every other view
    at every offset in ``search``; the pair's cost is the median two-view reprojection
    error (:func:`~flowmocap.geometry.triangulate.offset_cost`), its best offset the one
    with the lowest cost. Pairs are taken greedily from the lowest cost while it is
    below ``max_px`` (pixels), each track of the other view joining at most one person,
    a person taking several tracks of a view only where they do not overlap in time
    (a person lost and found again). The offsets then come from
    :func:`~flowmocap.geometry.triangulate.estimate_offsets` over all people so formed.

    Args:
        cameras: ``V`` calibrated cameras.
        view_tracks: per view, a list of tracks ``(keypoints (T_v, K, 2) px NaN where
            absent, confidence (T_v, K))``.
        reference: the view whose tracks define the people and whose frame numbers are
            the reference time.

    Returns:
        ``people``: per person (one per reference-view track with a match), per view the
        list of track indices forming them there (empty where unseen);
        ``tracks``: per person, per view the merged ``(keypoints, confidence)`` or None;
        ``offsets``: ``(V,)`` ints (view ``v``'s frame ``f`` is reference time ``f +
        offsets[v]``); ``offset_cost``: ``(V, len(search))`` px; ``pair_cost``: per view
        ``(A, B_v)`` the best two-view cost of each pair, px.

    Raises:
        InputError: mismatched cameras and views.
    """
    V = len(cameras)
    if len(view_tracks) != V:
        raise InputError(f"need one list of tracks per camera; got {len(view_tracks)} for {V} cameras")
    search = [int(s) for s in search]
    ref_tracks = view_tracks[reference]
    A = len(ref_tracks)
    members: list[list[list[int]]] = [[[] for _ in range(V)] for _ in range(A)]
    for a in range(A):
        members[a][reference] = [a]
    pair_cost: list = [None] * V
    for v in range(V):
        if v == reference:
            continue
        pair = [cameras[reference], cameras[v]]
        B = len(view_tracks[v])
        c = np.full((A, B, len(search)), np.inf)
        for a in range(A):
            for b in range(B):
                for k, d in enumerate(search):
                    c[a, b, k] = offset_cost(pair, [ref_tracks[a], view_tracks[v][b]], [0, d])
        best = c.min(-1) if B and A else np.zeros((A, B))
        pair_cost[v] = best
        taken: set[int] = set()
        for cost, a, b in sorted((best[a, b], a, b) for a in range(A) for b in range(B)):
            if not cost < max_px or b in taken:
                continue
            frames_b = np.isfinite(view_tracks[v][b][0][:, 0, 0])
            clash = any((np.isfinite(view_tracks[v][o][0][:, 0, 0]) & frames_b).sum() > min_overlap
                        for o in members[a][v])
            if not clash:
                members[a][v].append(b)
                taken.add(b)
    people = [m for m in members if sum(bool(x) for x in m) >= 2]
    merged = [[_merge_tracks([view_tracks[v][b] for b in m[v]]) if m[v] else None for v in range(V)]
              for m in people]
    if merged:
        offsets, ocost = estimate_offsets(cameras, merged, search, reference)
    else:
        offsets, ocost = np.zeros(V, int), np.full((V, len(search)), np.nan)
    return {"people": people, "tracks": merged, "offsets": offsets, "offset_cost": ocost, "pair_cost": pair_cost}


def reference_offsets(estimated, pinned: dict | None = None, views=VIEWS) -> np.ndarray:
    """``(V,)`` ints: the time offsets the reference uses, ``pinned`` (view name -> frames,
    :data:`PINNED_OFFSETS`) where given, else the ``estimated`` ones (``(V,)``, in the
    order of ``views``).

    Raises:
        InputError: ``pinned`` leaves out a view or holds a non-integer offset.
    """
    estimated = np.asarray(estimated, int)
    if pinned is None:
        return estimated.copy()
    missing = [v for v in views if v not in pinned]
    if missing:
        raise InputError(f"pinned offsets lack {', '.join(missing)}; give one per view or None.")
    if any(int(pinned[v]) != pinned[v] for v in views):
        raise InputError(f"pinned offsets must be whole frames; got {pinned}.")
    return np.array([int(pinned[v]) for v in views], int)


def _merge_tracks(tracks: list[tuple]) -> tuple[np.ndarray, np.ndarray]:
    kp, conf = tracks[0][0].copy(), tracks[0][1].copy()
    for k2, c2 in tracks[1:]:
        fill = ~np.isfinite(kp[:, 0, 0]) & np.isfinite(k2[:, 0, 0])
        kp[fill], conf[fill] = k2[fill], c2[fill]
    return kp, conf


def triangulate_person(cameras: list[CalibratedCamera], tracks: list, offsets, exclude: int | None = None,
                       max_error_px: float = REF_MAX_ERROR_PX) -> dict:
    """One person's keypoints in 3D at every reference time some view sees them.

    Args:
        cameras: ``V`` calibrated cameras.
        tracks: per view ``(keypoints (T_v, K, 2) px, confidence (T_v, K))`` or None.
        offsets: ``(V,)`` ints (view ``v``'s frame ``f`` is reference time ``f + offsets[v]``).
        exclude: a view left out (the view a monocular run is scored from).
        max_error_px: :func:`~flowmocap.geometry.triangulate.triangulate`'s threshold.

    Returns:
        ``times (T,)`` reference times; ``points (T, K, 3)`` metres, world (NaN where
        fewer than 2 views agree); ``error_px (T, K)`` mean reprojection error over the
        views used; ``views (T, K)`` their number.
    """
    V = len(cameras)
    keep = [v for v in range(V) if tracks[v] is not None and v != exclude]
    offsets = [int(o) for o in offsets]
    if not keep:
        return {"times": np.zeros(0, int), "points": np.zeros((0, len(KEYPOINT_NAMES), 3)),
                "error_px": np.zeros((0, len(KEYPOINT_NAMES))), "views": np.zeros((0, len(KEYPOINT_NAMES)), int)}
    t0 = min(offsets[v] for v in keep)
    t1 = max(offsets[v] + len(tracks[v][0]) for v in keep)
    K = tracks[keep[0]][0].shape[1]
    T = t1 - t0
    pts = np.full((len(keep), T, K, 2), np.nan)
    conf = np.zeros((len(keep), T, K))
    for n, v in enumerate(keep):
        p, c = tracks[v]
        s = offsets[v] - t0
        pts[n, s:s + len(p)], conf[n, s:s + len(p)] = p, c
    if len(keep) < 2:
        X = np.full((T * K, 3), np.nan)
        err = np.full(T * K, np.nan)
        nv = np.zeros(T * K, int)
    else:
        tri = triangulate([cameras[v] for v in keep], pts.reshape(len(keep), -1, 2), conf.reshape(len(keep), -1),
                          max_error_px=max_error_px)
        X, err, nv = tri.points, tri.error_px, np.where(np.isfinite(tri.points).all(1), tri.num_views, 0)
    return {"times": np.arange(t0, t1), "points": X.reshape(T, K, 3), "error_px": err.reshape(T, K),
            "views": nv.reshape(T, K)}


def _file_hashes(data_dir: Path) -> dict:
    import hashlib

    out = {}
    for p in [data_dir / "Calib.qca.txt"] + [data_dir / "videos" / f"{v}.mp4" for v in VIEWS]:
        h = hashlib.sha1()
        with open(p, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        out[p.name] = h.hexdigest()[:16]
    return out


def build_reference(out_dir: str | Path, data_dir: str | Path = DATA, progress: bool = True, log=print,
                    main_people: int = 2) -> dict:
    """The multi-view 3D reference of the recording, cached in ``out_dir/reference``.

    Args:
        out_dir: the benchmark folder; ``reference/reference.npz`` and
            ``reference/reference.json`` are reused when made by the same version from
            the same files, the detections ``reference/views/camXX.npz`` likewise.
        data_dir: the recording (``Calib.qca.txt``, ``videos/camXX.mp4``).
        main_people: how many people (those with the most detections over all views)
            the benchmark uses.

    Returns:
        ``info`` (the JSON: offsets, people, reprojection errors, settings),
        ``cameras`` (name -> :class:`~flowmocap.geometry.triangulate.CalibratedCamera`),
        ``people``: per main person a dict with ``tracks`` (per view ``(keypoints (T, 15,
        2) px, confidence (T, 15))`` or None), ``all`` (:func:`triangulate_person` with
        every view) and ``without`` (view name -> the same without that view).

    Raises:
        DataError: the recording is missing or its people cannot be associated.
    """
    say = log if log is not None else (lambda _m: None)
    data_dir = Path(data_dir)
    if not (data_dir / "Calib.qca.txt").exists():
        raise DataError(f"the real3d recording is not in {data_dir} (Calib.qca.txt, videos/cam01.mp4 ...); "
                        "it is shared/data/video/pose2sim-multi: give bench --data DIR (the folder holding mocap/ and "
                        "video/) or set FLOWMOCAP_DATA.")
    cams = read_qualisys_calibration(data_dir / "Calib.qca.txt")
    missing = [v for v in VIEWS if v not in cams or not (data_dir / "videos" / f"{v}.mp4").exists()]
    if missing:
        raise DataError(f"{data_dir}: no calibration or video for {', '.join(missing)}.")
    cameras = [cams[v] for v in VIEWS]
    ref_dir = Path(out_dir) / "reference"
    (ref_dir / "views").mkdir(parents=True, exist_ok=True)
    settings = {"version": REFERENCE_VERSION, "detection_version": DETECTION_VERSION, "files": _file_hashes(data_dir),
                "detector_max_side": REF_MAX_SIDE,
                "max_error_px": REF_MAX_ERROR_PX, "associate_max_px": ASSOCIATE_MAX_PX,
                "offset_search": [min(OFFSET_SEARCH), max(OFFSET_SEARCH)], "main_people": main_people,
                "pinned_offsets": PINNED_OFFSETS}
    cached = _load_reference(ref_dir, settings, cameras)
    if cached is not None:
        say(f"reference: cached in {ref_dir}")
        return cached
    view_key = {k: settings[k] for k in ("detection_version", "files", "detector_max_side")}
    view_tracks = []
    for v in VIEWS:
        path = ref_dir / "views" / f"{v}.npz"
        stored = None
        if path.exists():
            with np.load(path) as z:
                stored = {k: z[k] for k in z.files}
            if json.loads(str(stored.get("settings", "{}"))) != view_key:
                stored = None
        if stored is None:
            say(f"reference: finding the people in {v} (MediaPipe at {REF_MAX_SIDE} px) ...")
            t0 = time.perf_counter()
            stored = detect_view_people(data_dir / "videos" / f"{v}.mp4", progress=progress)
            stored["settings"] = np.array(json.dumps(view_key))
            np.savez(path, **stored)
            say(f"reference: {v}: {len(stored['score'])} people in {time.perf_counter() - t0:.0f} s")
        view_tracks.append([(stored["keypoints"][p], stored["confidence"][p]) for p in range(len(stored["score"]))])
    say("reference: associating the people across views and estimating the time offsets ...")
    assoc = associate_people(cameras, view_tracks)
    if not assoc["people"]:
        raise DataError("no person of cam01 could be matched in another view; the reference cannot be built "
                        f"(pair costs: {[None if c is None else np.round(c, 1).tolist() for c in assoc['pair_cost']]}).")
    offsets = reference_offsets(assoc["offsets"], PINNED_OFFSETS)
    coverage = [sum(int(np.isfinite(tr[0][:, 0, 0]).sum()) for tr in trs if tr is not None)
                for trs in assoc["tracks"]]
    order = sorted(range(len(coverage)), key=lambda p: -coverage[p])[:main_people]
    arrays: dict = {"offsets": offsets}
    people_info = []
    for n, p in enumerate(order):
        name = f"person{n + 1}"
        trs = assoc["tracks"][p]
        allv = triangulate_person(cameras, trs, offsets)
        arrays.update({f"{name}/all/{k}": val for k, val in allv.items()})
        for c, v in enumerate(VIEWS):
            wo = triangulate_person(cameras, trs, offsets, exclude=c)
            arrays.update({f"{name}/without_{v}/{k}": val for k, val in wo.items()})
            if trs[c] is not None:
                arrays[f"{name}/tracks/{v}/keypoints"], arrays[f"{name}/tracks/{v}/confidence"] = trs[c]
        e = allv["error_px"][np.isfinite(allv["error_px"]) & np.isfinite(allv["points"][..., 0])]
        j13 = eval_points(allv["points"])
        people_info.append({
            "name": name, "cam01_track": assoc["people"][p][0][0],
            "tracks_per_view": {v: assoc["people"][p][c] for c, v in enumerate(VIEWS)},
            "views": [v for c, v in enumerate(VIEWS) if trs[c] is not None],
            "detections_over_views": coverage[p],
            "reference_times": [int(allv["times"][0]), int(allv["times"][-1])] if len(allv["times"]) else None,
            "frames_with_all_13_joints": int(np.isfinite(j13).all((1, 2)).sum()),
            "median_reprojection_px": float(np.median(e)) if len(e) else None,
            "mean_views_per_point": float(allv["views"][allv["views"] > 0].mean()) if (allv["views"] > 0).any() else 0,
        })
    all_err = np.concatenate([arrays[f"{q['name']}/all/error_px"][np.isfinite(arrays[f"{q['name']}/all/points"][..., 0])]
                              for q in people_info])
    info = {
        "settings": settings,
        "views": list(VIEWS),
        "offsets": {v: int(o) for v, o in zip(VIEWS, offsets)},
        "offsets_note": "view v's frame f shows the instant of cam01's frame f + offset[v]",
        "offsets_pinned": PINNED_OFFSETS is not None,
        "offsets_estimated": {v: int(o) for v, o in zip(VIEWS, assoc["offsets"])},
        "offset_search": list(OFFSET_SEARCH),
        "offset_cost": {v: [None if not np.isfinite(x) else round(float(x), 3) for x in assoc["offset_cost"][c]]
                        for c, v in enumerate(VIEWS) if c != 0},
        "offset_cost_note": ("per offset in offset_search: the sum over people of the median reprojection error "
                             "(all views) divided by that person's best (estimate_offsets' last search)"),
        "pair_cost_px": {v: np.round(assoc["pair_cost"][c], 1).tolist() for c, v in enumerate(VIEWS) if c != 0},
        "people": people_info,
        "people_found": len(assoc["people"]),
        "median_reprojection_px": float(np.median(all_err)) if len(all_err) else None,
        "reprojection_note": ("mean over the views used of each triangulated keypoint's reprojection error, in the "
                              "videos' full-resolution pixels (1088 x 1920); median over keypoints and times"),
    }
    np.savez(ref_dir / "reference.npz", **arrays)
    (ref_dir / "reference.json").write_text(json.dumps(info, indent=2))
    return _load_reference(ref_dir, settings, cameras)


def _load_reference(ref_dir: Path, settings: dict, cameras: list) -> dict | None:
    try:
        info = json.loads((ref_dir / "reference.json").read_text())
        with np.load(ref_dir / "reference.npz") as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError):
        return None
    if info.get("settings") != settings:
        return None
    people = {}
    for q in info["people"]:
        name = q["name"]
        get = lambda prefix, name=name: {k: arrays[f"{name}/{prefix}/{k}"] for k in ("times", "points", "error_px", "views")}  # noqa: E731
        people[name] = {
            "info": q, "all": get("all"), "without": {v: get(f"without_{v}") for v in VIEWS},
            "tracks": {v: ((arrays[f"{name}/tracks/{v}/keypoints"], arrays[f"{name}/tracks/{v}/confidence"])
                           if f"{name}/tracks/{v}/keypoints" in arrays else None) for v in VIEWS},
        }
    return {"info": info, "cameras": dict(zip(VIEWS, cameras)), "people": people,
            "offsets": {v: int(info["offsets"][v]) for v in VIEWS}}


def person_pixel(keypoints: np.ndarray, confidence: np.ndarray, min_confidence: float = 0.5) -> tuple | None:
    """``(frame, (x, y))``: the first frame with at least 4 confident keypoints and the
    centre of their box (pixels), or None.

    Args:
        keypoints: ``(T, K, 2)`` pixels (NaN where missing), one view's track.
        confidence: ``(T, K)`` detector confidence per keypoint.
        min_confidence: the confidence a keypoint needs to count.
    """
    for i in range(len(keypoints)):
        ok = (confidence[i] >= min_confidence) & np.isfinite(keypoints[i]).all(-1)
        if ok.sum() >= 4:
            p = keypoints[i][ok]
            return i, (float((p[:, 0].min() + p[:, 0].max()) / 2), float((p[:, 1].min() + p[:, 1].max()) / 2))
    return None


# ------------------------------------------------------------------ scoring


#: Reference joints (of the 13) a frame needs to be scored; both hips always.
MIN_JOINTS = 10


def pa_mpjpe(pred: np.ndarray, ref: np.ndarray, valid: np.ndarray | None = None) -> tuple[float, float, np.ndarray]:
    """Per-frame and per-sequence PA-MPJPE of ``(T, 13, 3)`` joints (metres, in the order
    of :data:`EVAL_NAMES`) against a reference of the same shape.

    Args:
        pred: ``(T, 13, 3)`` joints, metres.
        ref: ``(T, 13, 3)`` reference joints, metres (NaN where missing: not scored).
        valid: ``(T, 13)`` bool, the reference joints to score (default all); both hips
            must be valid in every frame (the per-sequence error is hips-relative).

    Returns:
        ``(per_frame_mm, per_sequence_mm, curve_mm (T,))``: the mean over frames of the
        mean error of the valid joints after a similarity Procrustes per frame (fitted on
        them, :func:`~flowmocap.geometry.procrustes.similarity_procrustes`); the same
        after making both hips-relative (minus the middle of the hips) and one similarity
        over all valid joints of the sequence; the per-frame errors. Millimetres.
    """
    pred, r, valid = _scoring_inputs(pred, ref, valid, hips_needed=True)
    w = valid.astype(np.float64)
    n = valid.sum(1)
    per_frame = np.nanmean(_aligned_errors(pred, r, valid), axis=1)
    rel_p, rel_r = pred - _hips(pred)[:, None], r - _hips(r)[:, None]
    aligned = similarity_procrustes(rel_p.reshape(-1, 3), rel_r.reshape(-1, 3), weights=w.reshape(-1))[0]
    per_seq = (np.linalg.norm(aligned.reshape(pred.shape) - rel_r, axis=-1) * w).sum(1) / n * 1000.0
    return float(per_frame.mean()), float(per_seq.mean()), per_frame


def keypoint_joints(res) -> np.ndarray:
    """``(T, 13, 3)`` a result's bodies at the detector's keypoints, metres: the 12 joints
    moved by the learned keypoint offsets and the head at the middle of the ears
    (:class:`~flowmocap.vision.keypoint_map.KeypointMap`), in the order of
    :data:`EVAL_NAMES`, so they are scored in the reference's own convention (the
    reference is triangulated from the "full" landmark network's keypoints, so its
    offsets, whichever network the run used)."""
    import torch

    from flowmocap.body import load_body_model
    from flowmocap.vision.keypoint_map import load_keypoint_map

    model = load_body_model("default", gender=str(res.motion.get("gender", "neutral")))
    with torch.no_grad():
        out = model(betas=torch.as_tensor(np.asarray(res.betas), dtype=torch.float32).reshape(1, -1),
                    pose=torch.as_tensor(np.asarray(res.poses), dtype=torch.float32),
                    trans=torch.as_tensor(np.asarray(res.trans), dtype=torch.float32))
    joints = out.joints.double().numpy()
    transforms = out.transforms.double().numpy()
    kmap = load_keypoint_map(model="full")
    pts = kmap.apply(joints, transforms)[:, list(EVAL_JOINTS)]
    pts[:, 0] = kmap.ears_middle(joints, transforms)
    return pts


def _scoring_inputs(pred, ref, valid, hips_needed: bool = False, joints: int | None = None):
    """``(pred, ref, valid)`` checked for :func:`pa_mpjpe` and :func:`joint_errors`: float64,
    the valid joints those of ``valid`` (default all) where ``ref`` is finite, the others set
    to 0 in both (weight 0, and no NaN in the SVD). ``hips_needed``: both hips must be valid
    in every frame; ``joints``: the number of joints asked for (None: any)."""
    pred, ref = np.asarray(pred, np.float64), np.asarray(ref, np.float64)
    if pred.shape != ref.shape or pred.ndim != 3 or pred.shape[-1] != 3 or (joints and pred.shape[1] != joints):
        raise InputError(f"pred and ref must be (T, 13, 3) of equal shape; got {pred.shape} and {ref.shape}.")
    valid = np.isfinite(ref).all(-1) if valid is None else np.asarray(valid, bool) & np.isfinite(ref).all(-1)
    hips = [EVAL_NAMES.index("left_hip"), EVAL_NAMES.index("right_hip")]
    if hips_needed and not valid[:, hips].all():
        raise InputError("both hips must be valid in every scored frame.")
    if not np.isfinite(pred[valid]).all():
        raise InputError("pred has non-finite joints where the reference is valid.")
    return np.where(valid[..., None], pred, 0.0), np.where(valid[..., None], ref, 0.0), valid


def _aligned_errors(pred: np.ndarray, ref: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(T, 13)`` mm: each joint's distance after a similarity per frame fitted on the
    valid joints (``pred``, ``ref`` finite everywhere), NaN where not valid."""
    aligned = similarity_procrustes(pred, ref, weights=valid.astype(np.float64))[0]
    return np.where(valid, np.linalg.norm(aligned - ref, axis=-1) * 1000.0, np.nan)


def joint_errors(pred: np.ndarray, ref: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Each joint's mean error after :func:`pa_mpjpe`'s per-frame alignment: where the
    per-frame PA-MPJPE comes from.

    Args:
        pred, ref, valid: as :func:`pa_mpjpe` (``(T, 13, 3)`` metres, ``(T, 13)`` bool).

    Returns:
        ``(13,)`` mm in the order of :data:`EVAL_NAMES`, the mean over the frames where the
        joint is scored (NaN for a joint never scored). When every joint is scored in
        every frame their mean is :func:`pa_mpjpe`'s per-frame error.
    """
    pred, ref, valid = _scoring_inputs(pred, ref, valid, joints=len(EVAL_NAMES))
    e = _aligned_errors(pred, ref, valid)
    with np.errstate(invalid="ignore"):
        n = valid.sum(0)
        return np.where(n > 0, np.nansum(e, axis=0) / np.maximum(n, 1), np.nan)


def scored_frames(res_dir: str | Path, reference: dict, person: str, view: str, frames: int | None = None) -> dict:
    """The frames and joints :func:`score_run` scores, as arrays.

    Returns:
        ``used`` (the run's frame numbers), ``skipped`` (counts: ``no_reference``,
        ``no_detection``, ``no_fit``), ``offset`` (reference time of frame ``f`` is
        ``f + offset``), ``ours`` ``(F, 13, 3)`` the fit's joints (metres, the run's
        world axes), ``ours_kp`` the same at the detector's keypoints (None without the
        body's parameters), ``detector`` ``(F, 13, 3)`` MediaPipe's world landmarks
        (metres, hip-centred, the detector's axes), ``ref`` / ``valid`` ``(F, 13, 3)`` /
        ``(F, 13)`` the reference without the view and its scored joints, ``ref_all`` /
        ``valid_all`` the same from every view, ``result`` and ``detections`` (the
        loaded run), all in the order of :data:`EVAL_NAMES`; F = ``len(used)``, the
        arrays empty when it is 0.
    """
    from flowmocap.vision.auto import load_detections

    res = load_result(res_dir)
    # the body at the detector's keypoints needs the body's parameters (every result of track has them)
    kp13 = keypoint_joints(res) if all(k in res.motion for k in ("poses", "trans", "betas")) else None
    det = load_detections(res_dir)
    if det is None or det.world is None:
        raise DataError(f"{res_dir} holds no detections with 3D landmarks; re-run the benchmark.")
    ref_p = reference["people"][person]
    offset = reference["offsets"][view]
    T = len(det.found) if frames is None else min(frames, len(det.found))
    fit_rows = {int(f): k for k, f in enumerate(res.frame_index)}
    wo, allv = ref_p["without"][view], ref_p["all"]
    hips = [EVAL_NAMES.index("left_hip"), EVAL_NAMES.index("right_hip")]
    lengths = bone_lengths(eval_points(allv["points"]))

    def checked(tri):
        j13 = eval_points(tri["points"])
        err13 = None
        if tri.get("error_px") is not None:
            e = np.asarray(tri["error_px"], np.float64)
            err13 = eval_points(np.stack([e, e], -1))[..., 0]
            err13[:, 0] = np.fmax(e[:, KEYPOINT_NAMES.index("left_ear")], e[:, KEYPOINT_NAMES.index("right_ear")])
        return {"times": tri["times"], "j13": j13, "valid": consistent_joints(j13, lengths, err13)}

    wo_c, all_c = checked(wo), checked(allv)

    def at(c, t):
        """``(joints (13, 3), valid (13,))`` at reference time ``t`` if it has enough joints, else None."""
        idx = t - int(c["times"][0]) if len(c["times"]) else -1
        if not 0 <= idx < len(c["times"]):
            return None
        ok = c["valid"][idx]
        return (c["j13"][idx], ok) if ok.sum() >= MIN_JOINTS and ok[hips].all() else None

    used, skipped = [], {"no_reference": 0, "no_detection": 0, "no_fit": 0}
    ours, ours_kp, mp, ref, ok_wo, ref_all, ok_all = [], [], [], [], [], [], []
    for f in range(T):
        got = at(wo_c, f + offset)
        if got is None:
            skipped["no_reference"] += 1
            continue
        w = det.world[f] if det.found[f] else None
        if w is None or not np.isfinite(eval_points(w)).all():
            skipped["no_detection"] += 1
            continue
        if f not in fit_rows:
            skipped["no_fit"] += 1
            continue
        used.append(f)
        ours.append(np.asarray(res.joints3d[fit_rows[f]], np.float64)[list(EVAL_JOINTS)])
        if kp13 is not None:
            ours_kp.append(kp13[fit_rows[f]])
        mp.append(eval_points(w))
        ref.append(got[0])
        ok_wo.append(got[1])
        got_all = at(all_c, f + offset) or got
        ref_all.append(got_all[0])
        ok_all.append(got_all[1])
    arr = lambda xs: np.asarray(xs, np.float64).reshape(-1, len(EVAL_NAMES), 3)  # noqa: E731
    flags = lambda xs: np.asarray(xs, bool).reshape(-1, len(EVAL_NAMES))  # noqa: E731
    return {"used": used, "skipped": skipped, "offset": offset, "ours": arr(ours),
            "ours_kp": arr(ours_kp) if kp13 is not None else None, "detector": arr(mp), "ref": arr(ref),
            "valid": flags(ok_wo), "ref_all": arr(ref_all), "valid_all": flags(ok_all), "result": res,
            "detections": det}


def scored_runs(bench_dir: str | Path, reference: dict | None = None, data_dir: str | Path = DATA):
    """The person-views of a ``flowmocap bench --suite real3d`` folder with a result and
    scored frames, in name order: yields ``(res_dir, person, view, d)`` with ``d`` the
    :func:`scored_frames` of the run (runs without a ``motion.npz`` or without a scored
    frame are left out). ``reference``: the folder's, built (or read back) from
    ``data_dir`` when not given."""
    bench_dir = Path(bench_dir)
    if reference is None:
        reference = build_reference(bench_dir, data_dir, progress=False, log=None)
    for res in sorted((bench_dir / "runs").iterdir()):
        if not (res / "motion.npz").exists():
            continue
        person, view = res.name.split("-", 1)
        d = scored_frames(res, reference, person, view)
        if d["used"]:
            yield res, person, view, d


def score_run(res_dir: str | Path, reference: dict, person: str, view: str, frames: int | None = None) -> dict:
    """Score one monocular run (view ``view``, person ``person``) against the reference
    triangulated without that view; flowmocap's fit and the detector's own 3D on the
    same frames and joints.

    Frame ``f`` of the run is reference time ``f + offset[view]``. A frame is scored when
    the reference has at least :data:`MIN_JOINTS` of the 13 joints (both hips among
    them) that fit the person's skeleton (:func:`consistent_joints`, bone lengths from
    the all-view reference), the run's detection has 3D landmarks and the run has a
    fitted body; the reference's missing or inconsistent joints are left out of that
    frame, for both methods.

    Returns:
        ``frames_scored``, ``joints_scored`` (mean per frame), ``skipped`` (counts:
        ``no_reference``, ``no_detection``, ``no_fit``), ``flowmocap`` and
        ``detector3d``: ``{"per_frame_mm", "per_sequence_mm", "per_frame_all_views_mm",
        "per_sequence_all_views_mm", "per_frame_curve_mm", "per_joint_mm"}`` (the last
        :func:`joint_errors`, 13 values in the order of :data:`EVAL_NAMES`, None for a joint
        never scored), and ``flowmocap_kp`` the
        same for the fit at the detector's keypoints (:func:`keypoint_joints`; None for a
        result without the body's parameters) (the ``all_views`` ones
        against the reference from every view, the run's own included, on the same
        frames), ``reference_without_vs_all_mm``: per-frame PA-MPJPE between the
        reference without the view and with it (how much leaving the view out moves
        the reference), ``det2d_px``: median distance between the run's confident 2D
        detections and the reference (all views) projected into this view, in
        full-resolution pixels (a check that the run followed the intended person).
    """
    d = scored_frames(res_dir, reference, person, view, frames)
    used, skipped, offset, det = d["used"], d["skipped"], d["offset"], d["detections"]
    ours, ours_kp, mp, ref, ok_wo = d["ours"], d["ours_kp"], d["detector"], d["ref"], d["valid"]
    ref_all, ok_all = d["ref_all"], d["valid_all"]
    allv = reference["people"][person]["all"]
    hips = [EVAL_NAMES.index("left_hip"), EVAL_NAMES.index("right_hip")]
    out = {"person": person, "view": view, "offset": offset, "frames_scored": len(used),
           "frames": [used[0], used[-1]] if used else None, "skipped": skipped}
    if not used:
        return {**out, "flowmocap": None, "detector3d": None, "flowmocap_kp": None, "det2d_px": None}
    out["joints_scored"] = float(np.mean([o.sum() for o in ok_wo]))
    out["flowmocap_kp"] = None
    for name, pred in (("flowmocap", ours), ("detector3d", mp), ("flowmocap_kp", ours_kp)):
        if pred is None:
            continue
        pf, ps, curve = pa_mpjpe(pred, ref, ok_wo)
        pfa, psa, _ = pa_mpjpe(pred, ref_all, ok_all)
        out[name] = {"per_frame_mm": pf, "per_sequence_mm": ps, "per_frame_all_views_mm": pfa,
                     "per_sequence_all_views_mm": psa, "per_frame_curve_mm": np.round(curve, 1).tolist(),
                     "per_joint_mm": [None if not np.isfinite(v) else round(float(v), 1)
                                      for v in joint_errors(pred, ref, ok_wo)]}
    # how much the reference itself moves when the view is left out (its noise floor here)
    both = ok_wo & ok_all
    keep = (both.sum(1) >= MIN_JOINTS) & both[:, hips].all(1)
    out["reference_without_vs_all_mm"] = (pa_mpjpe(ref[keep], ref_all[keep], both[keep])[0]
                                          if keep.any() else None)
    # the run's 2D detections against the reference projected into this view
    cam = reference["cameras"][view]
    scale = det.info["size"][0] / cam.width
    d2 = []
    t0 = int(allv["times"][0]) if len(allv["times"]) else 0
    for f in used:
        if not 0 <= f + offset - t0 < len(allv["times"]):
            continue
        proj = cam.project(allv["points"][f + offset - t0])
        ok = (det.confidence[f] >= 0.5) & np.isfinite(proj).all(-1)
        d2 += list(np.linalg.norm(det.keypoints[f][ok] / scale - proj[ok], axis=-1))
    out["det2d_px"] = float(np.median(d2)) if d2 else None
    return out


def _mean_rows(rows: list[dict]) -> dict:
    out = {}
    for m in METHODS:
        vals = [r[m] for r in rows if r.get(m)]
        out[m] = {k: (float(np.mean([v[k] for v in vals])) if vals else None)
                  for k in ("per_frame_mm", "per_sequence_mm", "per_frame_all_views_mm", "per_sequence_all_views_mm")}
        joints = [v["per_joint_mm"] for v in vals if v.get("per_joint_mm")]
        if joints:  # each joint's mean over the person-views that score it
            a = np.array([[np.nan if x is None else x for x in j] for j in joints], np.float64)
            with np.errstate(invalid="ignore"):
                mean = np.nansum(a, 0) / np.maximum(np.isfinite(a).sum(0), 1)
            out[m]["per_joint_mm"] = [None if not np.isfinite(a[:, j]).any() else round(float(mean[j]), 1)
                                      for j in range(a.shape[1])]
    out["person_views"] = sum(1 for r in rows if r.get("flowmocap"))
    out["frames_scored"] = int(sum(r.get("frames_scored", 0) for r in rows))
    out["intervals"] = ratio_intervals(rows)
    return out


def ratio_intervals(rows: list[dict], block: int = INTERVAL_BLOCK, draws: int = INTERVAL_DRAWS) -> dict:
    """For ``flowmocap`` and ``flowmocap_kp``: the ratio of their mean per-frame error to the
    detector's, per person-view and over the suite, with a circular block bootstrap
    interval over the scored frames (:func:`flowmocap.eval.bootstrap.ratio_interval`; blocks
    of ``block`` frames, the same frames for both methods), from the rows'
    ``per_frame_curve_mm``. The intervals hold which stretches of motion the views happen
    to contain, not the tracker's chaos between trackings. Rows without both curves are
    left out; a method with none gives None.

    Returns:
        ``{method: None or {"person_views": ["person1@cam01", ...], "block", "draws",
        "level", "clips": [...], "suite": {...}}}`` (the fields of ``ratio_interval``).
    """
    from flowmocap.eval.bootstrap import ratio_interval

    out: dict = {}
    for m in ("flowmocap", "flowmocap_kp"):
        use = [r for r in rows if (r.get(m) or {}).get("per_frame_curve_mm") and
               (r.get("detector3d") or {}).get("per_frame_curve_mm")]
        if not use:
            out[m] = None
            continue
        got = ratio_interval([r[m]["per_frame_curve_mm"] for r in use],
                             [r["detector3d"]["per_frame_curve_mm"] for r in use], block=block, draws=draws)
        out[m] = {"person_views": [f"{r['person']}@{r['view']}" for r in use], **got}
    return out


def offset_margins(reference_info: dict) -> dict:
    """Per view, how much worse the better neighbouring offset of the chosen one scores
    (the reference's ``offset_cost`` at offset +-1 over its cost at the offset chosen,
    minus 1): how well the detections determine the time offset. Views without a finite
    cost are left out."""
    cost, out = reference_info.get("offset_cost") or {}, {}
    for view, values in cost.items():
        c = np.array([np.inf if x is None else x for x in values], float)
        k = int(np.argmin(c))
        near = [c[j] for j in (k - 1, k + 1) if 0 <= j < len(c) and np.isfinite(c[j])]
        if np.isfinite(c[k]) and c[k] > 0 and near:
            out[view] = float(min(near) / c[k] - 1.0)
    return out


def format_real3d_table(result: dict) -> str:
    """The benchmark's result as Markdown: one row per person-view and the mean."""
    ref = result["reference"]
    s = result["settings"]
    margins = offset_margins(ref)
    lines = ["# flowmocap bench: suite `real3d` (Pose2Sim multi-person, 4 calibrated views)", "",
             f"Reference: {ref['people_found']} people associated across views, the {len(ref['people'])} seen longest "
             f"used; time offsets to cam01 (frames at 60 fps): "
             + ", ".join(f"{v} {o:+d}" for v, o in ref["offsets"].items())
             + (" (pinned; the detections' estimate now: "
                + ", ".join(f"{v} {o:+d}" for v, o in ref["offsets_estimated"].items()) + ")"
                if ref.get("offsets_pinned") else "")
             + (" (a frame more or less costs only " + ", ".join(f"{v} {100 * m:.1f} %" for v, m in margins.items())
                + " more in the estimate" + ("" if ref.get("offsets_pinned") else
                                             ": the offsets, and with them single person-views, can move by a "
                                             "frame whenever the detections change") + ")" if margins else "")
             + f"; median reprojection error {ref['median_reprojection_px']:.1f} px (full resolution, all views).",
             f"Runs: `flowmocap track VIDEO --person x,y --max-size {s['max_size']}`"
             + (f" on the first {s['frames']} frames" if s.get("frames") else "")
             + ("" if not s.get("tracker_config") else f", tracker overrides {s['tracker_config']}") + ".", "",
             "| person | view | frames | flowmocap per-frame mm | flowmocap per-seq mm | detector3d per-frame mm "
             "| detector3d per-seq mm | ours / det (per-frame) | ours at keypoints per-frame mm | ratio to det "
             "| det 2D px | ref w/o vs all mm |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    fmt = lambda v: "--" if v is None else f"{v:.1f}"  # noqa: E731
    for r in result["rows"]:
        if r.get("skipped_run"):
            lines.append(f"| {r['person']} | {r['view']} | -- | {r['skipped_run']} | | | | | | | | |")
            continue
        a, b, k = r.get("flowmocap") or {}, r.get("detector3d") or {}, r.get("flowmocap_kp") or {}
        ratio = (a["per_frame_mm"] / b["per_frame_mm"]) if a and b else None
        kratio = (k["per_frame_mm"] / b["per_frame_mm"]) if k and b else None
        frames = str(r["frames_scored"]) + (f" (run failed after {r['frames_done']} frames; not in the mean)"
                                            if r.get("failed") else "")
        lines.append(f"| {r['person']} | {r['view']} | {frames} | {fmt(a.get('per_frame_mm'))} | "
                     f"{fmt(a.get('per_sequence_mm'))} | {fmt(b.get('per_frame_mm'))} | {fmt(b.get('per_sequence_mm'))} "
                     f"| {'--' if ratio is None else f'{ratio:.2f}'} | {fmt(k.get('per_frame_mm'))} "
                     f"| {'--' if kratio is None else f'{kratio:.2f}'} | {fmt(r.get('det2d_px'))} "
                     f"| {fmt(r.get('reference_without_vs_all_mm'))} |")
    m = result["mean"]
    a, b, k = m["flowmocap"], m["detector3d"], m.get("flowmocap_kp") or {}
    ratio = a["per_frame_mm"] / b["per_frame_mm"] if a["per_frame_mm"] and b["per_frame_mm"] else None
    kratio = k["per_frame_mm"] / b["per_frame_mm"] if k.get("per_frame_mm") and b["per_frame_mm"] else None
    lines.append(f"| **mean** | {m['person_views']} person-views | {m['frames_scored']} | {fmt(a['per_frame_mm'])} | "
                 f"{fmt(a['per_sequence_mm'])} | {fmt(b['per_frame_mm'])} | {fmt(b['per_sequence_mm'])} | "
                 f"{'--' if ratio is None else f'{ratio:.2f}'} | {fmt(k.get('per_frame_mm'))} | "
                 f"{'--' if kratio is None else f'{kratio:.2f}'} | | |")
    for r in result["rows"]:
        if r.get("failed"):
            lines.append(f"\n{r['person']}@{r['view']}: the run failed: {r['failed']}")
    lines += _interval_lines(m.get("intervals") or {})
    lines += _joint_lines(m)
    lines += ["", "PA-MPJPE on the 13 joints (head = midpoint of the ears for the reference and the detector, SMPL's "
              "head for flowmocap; 'ours at keypoints': the fitted body's points where the detector puts its "
              "keypoints, by the learned offsets of flowmocap.vision.keypoint_map, head = middle of the ears) against the reference triangulated WITHOUT the run's view; per-frame: a similarity "
              "Procrustes per frame; per-seq: hips-relative joints, one similarity over the sequence. Both methods "
              f"on the same frames and joints (>= {MIN_JOINTS} of the 13 reference joints, hips included; a detection "
              "with 3D landmarks; a fitted body). det 2D px: "
              "median distance of the run's 2D detections to the reference projected into the view (full-resolution "
              "px; a check that the intended person was tracked). ref w/o vs all: per-frame PA-MPJPE between the "
              "reference without the view and with it (the reference's own noise there). Against all views (the view's own detections "
              f"included): flowmocap {fmt(a['per_frame_all_views_mm'])} / detector3d "
              f"{fmt(b['per_frame_all_views_mm'])} mm per-frame."]
    return "\n".join(lines)


def _joint_lines(mean: dict) -> list[str]:
    """The per-joint errors of :func:`_mean_rows` as a table (no lines when the rows have none)."""
    rows = [(label, (mean.get(m) or {}).get("per_joint_mm"))
            for m, label in (("flowmocap", "flowmocap"), ("flowmocap_kp", "ours at keypoints"), ("detector3d", "detector3d"))]
    rows = [(label, j) for label, j in rows if j]
    if not rows:
        return []
    lines = ["", "Per joint, mm (after the per-frame alignment; each joint's mean over its scored frames, then over "
             "the person-views):", "", "| | " + " | ".join(n.replace("_", " ") for n in EVAL_NAMES) + " |",
             "|---|" + "---:|" * len(EVAL_NAMES)]
    for label, j in rows:
        lines.append(f"| {label} | " + " | ".join("--" if v is None else f"{v:.1f}" for v in j) + " |")
    return lines


def _interval_lines(intervals: dict) -> list[str]:
    """The ratio intervals of :func:`ratio_intervals` as a paragraph (none: no lines)."""
    parts = []
    for m, label in (("flowmocap", "ours / det"), ("flowmocap_kp", "ours at keypoints / det")):
        iv = intervals.get(m)
        if not iv:
            continue
        s = iv["suite"]
        views = ", ".join(f"{name} {c['ratio']:.2f} [{c['low']:.2f}, {c['high']:.2f}]"
                          for name, c in zip(iv["person_views"], iv["clips"]) if c["high"] > 1)
        parts.append(f"{label}: mean {s['ratio']:.2f} [{s['low']:.2f}, {s['high']:.2f}]"
                     + (f"; person-views whose interval reaches above 1: {views}" if views else
                        "; no person-view's interval reaches above 1"))
    if not parts:
        return []
    iv = next(v for v in intervals.values() if v)
    return ["", f"Ratios with {100 * iv['level']:.0f} % intervals over which frames were scored (circular block "
            f"bootstrap, blocks of {iv['block']} frames, {iv['draws']} draws, the same frames for both methods; "
            "they do not hold the tracker's chance between trackings): " + "; ".join(parts) + "."]


# ------------------------------------------------------------------ the runner


def _finished(res_dir: Path) -> bool:
    try:
        return json.loads((Path(res_dir) / "run.json").read_text()).get("status") == "finished"
    except (OSError, json.JSONDecodeError):
        return False


def _person_views(person_views, people: list[str]) -> list[tuple[str, str]]:
    every = [(p, v) for p in people for v in VIEWS]
    if person_views is None:
        return every
    out = []
    for item in person_views:
        if isinstance(item, str):
            p, sep, v = item.partition("@")
            if not sep:
                raise InputError(f"person_views entries look like 'person1@cam02'; got {item!r}.")
        else:
            try:
                p, v = item
            except (TypeError, ValueError):
                raise InputError(f"person_views entries are 'person@view' or (person, view); got {item!r}.") from None
        if (p, v) not in every:
            raise InputError(f"unknown person-view {p}@{v}; choose from {', '.join(f'{a}@{b}' for a, b in every)}.")
        out.append((p, v))
    return out


def run_real3d(out_dir: str | Path, frames: int | None = None, max_size: int = 640, person_views=None,
               progress: bool = True, log=print, tracker_config: dict | None = None,
               data_dir: str | Path = DATA, fast: bool = False) -> dict:
    """The ``real3d`` benchmark: reference, monocular runs, scores; writes
    ``out_dir/real3d.json`` and ``out_dir/real3d.md``.

    Args:
        out_dir: the benchmark folder (``reference/``, ``runs/PERSON-VIEW/`` result
            folders); finished runs are not recomputed, unfinished ones resume.
        frames: track and score only the first ``frames`` frames of each video (None: all).
        max_size: the long side of the frames the tracker sees (pixels).
        person_views: which runs, e.g. ``["person1@cam02"]`` (default: both main people
            from every view).
        tracker_config: overrides of :class:`~flowmocap.fit.config.TrackerConfig` fields.
        data_dir: the recording.
        fast: track with ``track(fast=True)`` (``flowmocap track --fast``: its settings and
            its detector).

    Returns:
        the contents of ``real3d.json``: ``settings``, ``reference`` (offsets, people,
        reprojection errors), ``rows`` (one per person-view, :func:`score_run`),
        ``mean`` (over the scored person-views, per method).
    """
    say = log if log is not None else (lambda _m: None)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if frames is not None and (not isinstance(frames, (int, np.integer)) or frames < 2):
        raise InputError(f"frames must be None or a number of frames >= 2; got {frames!r}.")
    reference = build_reference(out_dir, data_dir, progress=progress, log=log)
    people = list(reference["people"])
    todo = _person_views(person_views, people)
    settings = {"frames": frames, "max_size": max_size, "tracker_config": tracker_config or {}, "fast": bool(fast),
                "data": str(data_dir), "person_views": [f"{p}@{v}" for p, v in todo],
                "protocol": ("flowmocap.pipeline.track(video, person='x,y' at the person's reference detections in "
                             "the first frame they appear, max_size) with everything else automatic (the camera as "
                             "for any video: not the calibration); scored against the reference without the run's "
                             "view"),
                "min_joints": MIN_JOINTS, "bone_tolerance": BONE_TOLERANCE}
    result = {"settings": settings, "reference": reference["info"], "rows": []}
    for p, v in todo:
        res = out_dir / "runs" / f"{p}-{v}"
        tr = reference["people"][p]["tracks"][v]
        start = person_pixel(*tr) if tr is not None else None
        if start is None:
            result["rows"].append({"person": p, "view": v, "skipped_run": f"{p} is not detected in {v}"})
            continue
        first, (x, y) = start
        spec = f"{x:.0f},{y:.0f}"
        video = Path(data_dir) / "videos" / f"{v}.mp4"
        if _finished(res):
            say(f"[{p}@{v}] finished result found in {res}, not recomputed")
        else:
            say(f"[{p}@{v}] flowmocap track {video} --person {spec} --max-size {max_size} ...")
            t0 = time.perf_counter()
            try:
                track(video, res, person=spec, max_size=max_size, frames=None if frames is None else f"0:{frames}",
                      config=tracker_config or None, resume=has_result(res), progress=progress,
                      log=None, fast=fast)
            except FlowMocapError as e:  # one failed run must not cost the others; reported, not in the mean
                done = load_result(res).frame_index if has_result(res) else []
                msg = f"{type(e).__name__}: {e}"
                say(f"[{p}@{v}] FAILED after {len(done)} frames: {msg}")
                row = {"person": p, "view": v, "person_arg": spec, "failed": msg, "frames_done": len(done)}
                if len(done) >= 2:  # the frames it finished, scored but marked partial
                    row.update(score_run(res, reference, p, v, frames))
                else:
                    row["skipped_run"] = "run failed"
                result["rows"].append(row)
                _write(out_dir, result)
                continue
            say(f"[{p}@{v}] done in {time.perf_counter() - t0:.0f} s")
        row = score_run(res, reference, p, v, frames)
        row["person_arg"] = spec
        row["person_first_frame"] = first
        run = json.loads((res / "run.json").read_text())
        row["s_per_frame"] = run.get("timings", {}).get("s_per_frame_median")
        row["camera"] = run.get("camera_source")
        row["frame_range"] = run.get("frame_range")
        row["reinitialisations"] = sum(1 for e in run.get("events", []) if e.get("event") == "re-initialised")
        row["person_recorded"] = {k: run.get("person", {}).get(k) for k in ("asked", "choice", "rank")}
        result["rows"].append(row)
        _write(out_dir, result)
    result["mean"] = _mean_rows([r for r in result["rows"] if not r.get("skipped_run") and not r.get("failed")])
    _write(out_dir, result)
    say(format_real3d_table(result))
    return result


def _write(out_dir: Path, result: dict) -> None:
    if "mean" not in result:
        result = {**result, "mean": _mean_rows([r for r in result["rows"]
                                                if not r.get("skipped_run") and not r.get("failed")])}
    (out_dir / "real3d.json").write_text(json.dumps(result, indent=2, default=json_default))
    (out_dir / "real3d.md").write_text(format_real3d_table(result) + "\n")
