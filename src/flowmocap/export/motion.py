"""A result folder's motion, ready to export: parameters, the body model, the up axis.

A result's 3D quantities live in the world frame of its camera (``X_cam = R X + t``).
Synthetic sequences and cameras placed with :func:`flowmocap.geometry.look_at` have a
y-up world, lab calibrations often a z-up one (:func:`flowmocap.geometry.camera.world_up`
finds the up axis); a result tracked with only a focal length has ``R = I``, so its world *is*
the camera frame (x right, y down, z forward) and a person standing in the video stands
upside down there, under a floor tilted by the camera's pitch. Export frames
(:data:`FRAMES`):

- ``"ground"`` (the default): gravity up (+y), the floor at y = 0, estimated from the
  fitted feet (:mod:`flowmocap.export.world`, cached in ``RESULT/world.json``);
- ``"up"``: only turned y up by :func:`up_rotation` (no floor estimate);
- ``"world"``: the result's own world frame.

In every frame :attr:`FittedMotion.camera` is the result's camera moved along, so it
projects the exported body onto the input pixels exactly as the fit did.

Where the camera turned during the clip (a pan or a tilt: ``run.json``'s ``camera_motion``,
:mod:`flowmocap.vision.camera_motion`), the body was tracked in the turning camera's frame.
``"ground"`` and ``"up"`` first turn each frame's body back by the camera's turn since the
input's first frame (the same for every person of a ``track --person all`` folder), so the
path, the foot contacts and the floor are the world's, not the camera's:
:attr:`FittedMotion.turns` holds those turns, :attr:`FittedMotion.camera` is the camera of the
input's first frame and :meth:`FittedMotion.camera_at` each row's, which projects the body
onto that frame's pixels. ``"world"`` stays the result's own frame (the camera's, turning).

Where the camera also moved (carried along: ``camera_motion``'s ``shifts``, found from the
floor in units of the camera's height above it), that height in metres is taken from the fitted
body's feet (:func:`camera_height_from_feet`) and each frame's body is moved back by the
camera's move too (:attr:`FittedMotion.shifts`, :attr:`FittedMotion.camera_height_m`), so a
person followed by a moving camera walks their path in the world instead of on the spot.

Where the camera zoomed (``camera_motion``'s ``zooms``: each frame's focal length over the
first frame's) and no move of it is undone, the tracker, which keeps the first frame's focal
length, put a person further away as the camera zoomed out (nearer as it zoomed in). Each
frame's body is then brought to the depth that frame's focal length gives (its depth times the
zoom, :func:`zoomed_depth`) before it is turned back (:attr:`FittedMotion.zooms`), so its
distance is the world's; :meth:`FittedMotion.camera_at` gives each row's camera its focal
length, which projects the body onto that frame's pixels (its root exactly; the body's own
size kept: a few pixels at its edges where a zoom is large).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from flowmocap.errors import DataError, InputError
from flowmocap.io.smpl_motion import rotate_motion

__all__ = ["FittedMotion", "FIXED_RATE_FORMATS", "variable_rate_note", "input_times", "load_fitted_motion", "motion_in_frame_of", "up_rotation", "rotate_motion", "FRAMES",
           "camera_turns", "camera_shifts", "camera_zooms", "zoomed_depth", "camera_height_from_feet",
           "camera_move_refused", "shared_move_refusal", "turned_camera", "FLOOR_BODY_MAX_DEG"]

#: Export frames: ``"ground"`` (y up, floor at 0), ``"up"`` (y up; see :func:`up_rotation`) or
#: ``"world"`` (the result's own).
FRAMES = ("ground", "up", "world")

#: 180 degrees about x: the camera frame (y down, z forward) to y up, z towards the camera.
CAMERA_TO_Y_UP = np.diag([1.0, -1.0, -1.0])


@dataclass
class FittedMotion:
    """T frames of a fitted body, in one export frame.

    Attributes:
        poses: ``(T, 72)`` float64 axis-angle in radians, SMPL joint order.
        trans: ``(T, 3)`` float64 translation in metres.
        betas: ``(10,)`` float64 shape coefficients of ``model``.
        gender: ``"neutral"``, ``"male"`` or ``"female"``.
        fps: frames per second (Hz).
        frame_index: ``(T,)`` int64 frame numbers in the input video.
        rotation: ``(3, 3)`` the rotation applied to the result's world frame
            (``x_export = rotation @ x_world + offset``).
        model: the :class:`~flowmocap.body.BodyModel` (float64) the motion was fitted with.
        joints2d: ``(T, 24, 2)`` float64 projected joints in input-image pixels.
        camera: the result's :class:`~flowmocap.geometry.PinholeCamera`, re-expressed in the
            export frame (it projects the exported joints onto ``joints2d``).
        run: the result's ``run.json``.
        frame: one of :data:`FRAMES`, the frame the motion is in.
        offset: ``(3,)`` metres, see ``rotation``.
        world: the :class:`~flowmocap.export.world.WorldFrame` (floor, foot contacts) for
            ``frame="ground"``, else None.
        smoothed: the smoothing applied (``{"window_s", "order", "window_frames"}``) or None.
        disagreement: ``(T, 24)`` metres, the result's ``disagreement``
            (:func:`~flowmocap.fit.disagreement.source_disagreement`; NaN outside the 13
            scored joints), or None where the result has none.
        contacts: ``(T, 2)`` bool, left/right foot standing still on the floor, where the
            motion was moved out of its own ground frame (:func:`motion_in_frame_of`) and so
            has no ``world``; else None (see :attr:`foot_contacts`).
        turns: ``(T, 3, 3)`` the camera's turn in each row since the input's first frame (``x_t = turns[k]
            x_0`` for directions in the camera's axes), where the motion was turned back by
            it (see the module docstring); None where the camera stood still or the frame is
            ``"world"``.
        shifts: ``(T, 3)`` metres, the camera's move in each row since the input's first
            frame, in that row's camera axes (a point's camera coordinates ``x_t = turns[k]
            x_0 + shifts[k]``), where the motion was moved back by it; None where the camera
            did not move sideways or the frame is ``"world"``.
        camera_height_m: the camera's height above the floor in the input's first frame (metres,
            from the fitted feet: :func:`camera_height_from_feet`) that scales ``shifts``; None
            without them.
        camera_move_refused: where ``run.json`` holds a move of the camera that was not
            undone, why (:func:`camera_move_refused`); else None.
        zooms: ``(T,)`` each row's focal length over the input's first frame's, where the
            camera zoomed and the body was brought to the depth it gives (see the module
            docstring); None where it did not, a move was undone instead, or the frame is
            ``"world"``.
    """

    poses: np.ndarray
    trans: np.ndarray
    betas: np.ndarray
    gender: str
    fps: float
    frame_index: np.ndarray
    rotation: np.ndarray
    model: object
    joints2d: np.ndarray
    camera: object
    run: dict
    frame: str = "ground"
    offset: np.ndarray = None
    world: object = None
    smoothed: dict | None = None
    disagreement: np.ndarray | None = None
    contacts: np.ndarray | None = None
    turns: np.ndarray | None = None
    shifts: np.ndarray | None = None
    camera_height_m: float | None = None
    camera_move_refused: str | None = None
    zooms: np.ndarray | None = None

    def __post_init__(self):
        if self.offset is None:
            self.offset = np.zeros(3)

    def camera_at(self, k: int):
        """The camera of row ``k`` in the export frame: :attr:`camera`, turned by
        ``turns[k]`` (and moved by ``shifts[k]``) where the camera turned or moved, its focal
        length scaled by ``zooms[k]`` where it zoomed (a
        :class:`~flowmocap.geometry.PinholeCamera`)."""
        if self.turns is None:
            return self.camera
        cam = turned_camera(self.camera, self.turns[k], None if self.shifts is None else self.shifts[k])
        if self.zooms is not None:
            cam = replace(cam, fx=cam.fx * float(self.zooms[k]), fy=cam.fy * float(self.zooms[k]))
        return cam

    def project(self, points: np.ndarray) -> np.ndarray:
        """``(T, N, 2)`` pixels of ``points`` ``(T, N, 3)`` (metres, export frame), each row by
        its frame's camera (:meth:`camera_at`)."""
        points = np.asarray(points, np.float64)
        if self.turns is None:
            return np.asarray(self.camera.project(points), np.float64)
        return np.stack([np.asarray(self.camera_at(k).project(points[k]), np.float64) for k in range(len(points))])

    @property
    def foot_contacts(self) -> np.ndarray | None:
        """``(T, 2)`` bool, left/right foot standing still on the floor: the ground frame's
        (``world``), or those the motion kept when it was moved into another's frame; None
        where neither is known."""
        if self.world is not None:
            return np.asarray(self.world.contacts, bool)
        return None if self.contacts is None else np.asarray(self.contacts, bool)

    @property
    def num_frames(self) -> int:
        """Number of frames T."""
        return int(self.poses.shape[0])

    @property
    def variable_rate(self) -> bool:
        """Whether the input is a video whose frames are unevenly spaced in time (``run.json``
        ``video.variable_frame_rate``, frame intervals differing by more than 10 %)."""
        return bool((self.run.get("video") or {}).get("variable_frame_rate"))

    @property
    def times(self) -> np.ndarray:
        """``(T,)`` float64 seconds of each row since the input's first frame: the video's own
        time stamps where its rate varies (:attr:`variable_rate`), else ``frame_index / fps``."""
        return input_times(self.run, self.frame_index, self.fps)

    @property
    def seen(self) -> np.ndarray:
        """``(T,)`` bool: False for the rows of frames in which the detector found no person
        (``run.json`` ``gaps``: tracked by flow alone, held, or filled in between), True
        elsewhere (and everywhere for a run whose masks were given)."""
        seen = np.ones(self.num_frames, bool)
        index = np.asarray(self.frame_index, np.int64)
        for gap in self.run.get("gaps") or []:
            try:
                a, b = (int(v) for v in gap["frames"])
            except (KeyError, TypeError, ValueError):
                continue
            seen &= ~((index >= a) & (index <= b))
        return seen

    def rest_joints(self) -> np.ndarray:
        """``(24, 3)`` float64 joints of the fitted shape in the rest (T-) pose, metres, y up."""
        import torch

        with torch.no_grad():
            out = self.model(betas=torch.as_tensor(self.betas[None], dtype=torch.float64))
        return out.rest_joints[0].numpy()

    def body(self, start: int = 0, stop: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Posed vertices and joints of frames ``start:stop``.

        Args:
            start, stop: frame range, as in ``poses[start:stop]`` (``stop=None``: to the end).

        Returns:
            ``vertices (n, V, 3)`` and ``joints (n, 24, 3)``, float64 metres, export frame.
        """
        import torch

        with torch.no_grad():
            out = self.model(betas=torch.as_tensor(self.betas[None], dtype=torch.float64),
                             pose=torch.as_tensor(self.poses[start:stop], dtype=torch.float64),
                             trans=torch.as_tensor(self.trans[start:stop], dtype=torch.float64))
        return out.vertices.numpy(), out.joints.numpy()

    def posed(self, chunk: int = 1024, with_vertices: bool = False):
        """The body posed ``chunk`` frames at a time, the shape made once: yields a
        :class:`~flowmocap.body.model.BodyOutput` (float64, metres, export frame) per chunk,
        in frame order; ``with_vertices=False`` leaves the mesh out."""
        import torch

        dt = torch.float64
        b = torch.as_tensor(self.betas[None], dtype=dt)
        with torch.no_grad():
            shaped = self.model.shaped(b)
            for s in range(0, self.num_frames, chunk):
                yield self.model(betas=b, pose=torch.as_tensor(self.poses[s:s + chunk], dtype=dt),
                                 trans=torch.as_tensor(self.trans[s:s + chunk], dtype=dt), shaped=shaped,
                                 with_vertices=with_vertices)

    def joints(self, chunk: int = 1024) -> np.ndarray:
        """``(T, 24, 3)`` float64 posed joints in metres, export frame (:meth:`posed`)."""
        out = [o.joints.double().numpy() for o in self.posed(chunk)]
        return np.concatenate(out) if out else np.zeros((0, 24, 3))


def up_rotation(camera, body_up=None) -> np.ndarray:
    """``(3, 3)`` rotation from a result's world frame to a y-up frame.

    It turns :func:`~flowmocap.geometry.camera.world_up` (the world axis that the camera's
    image up and the body's mean up agree on) to ``+y``: the identity for a y-up world
    (synthetic sequences, :func:`~flowmocap.geometry.look_at`), ``(x, y, z) -> (x, z, -y)``
    for a z-up lab calibration, and 180 degrees about x (:data:`CAMERA_TO_Y_UP`) when the
    world is the camera frame (``R = I``, a video without a calibration).

    Args:
        camera: the result's ``PinholeCamera``.
        body_up: ``(3,)`` the body's mean up direction in the world, or None.
    """
    from flowmocap.geometry.camera import world_up

    up = world_up(camera, body_up)
    if up[1] > 0.5:
        return np.eye(3)
    if up[1] < -0.5:
        return CAMERA_TO_Y_UP.copy()
    k = np.cross(up, [0.0, 1.0, 0.0])  # a unit axis: up is at right angles to y
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + K + K @ K  # 90 degrees about k (Rodrigues)


def input_times(run: dict, frame_index, fps: float) -> np.ndarray:
    """``(N,)`` float64 seconds since the input's first frame of the input frames
    ``frame_index`` (``(N,)`` ints): a variable-rate video's own time stamps (``run.json``
    ``video``), else ``frame_index / fps``."""
    index = np.asarray(frame_index, np.int64).reshape(-1)
    video = run.get("video") or {}
    stamps = video.get("timestamps")
    if video.get("variable_frame_rate") and isinstance(stamps, list) and len(index) and 0 <= index.min() \
            and index.max() < len(stamps):
        t = np.asarray(stamps, np.float64)[index]
        if np.isfinite(t).all() and (np.diff(t) > 0).all():
            return t
    return index / float(fps)


#: Export formats that hold one frame rate (a variable-rate video's frames are put at its mean rate).
FIXED_RATE_FORMATS = ("bvh", "trc", "c3d", "npz", "glb-frames")  # obj holds no time: its files are numbered


def variable_rate_note(run: dict, fmt: str) -> str | None:
    """A note for an export of ``fmt`` (or ``"overlay video"``: ``flowmocap render --video``)
    from a result whose video's frame rate varies, where the format holds one rate; None
    otherwise."""
    video = run.get("video") or {}
    if not video.get("variable_frame_rate") or fmt not in FIXED_RATE_FORMATS + ("overlay video",):
        return None
    stamps = np.asarray(video.get("timestamps") or [], np.float64)
    fps = float(video.get("fps") or 0)
    off = ""
    if len(stamps) > 1 and fps > 0:
        off = f", off the video's own times by up to {np.abs(stamps - np.arange(len(stamps)) / fps).max():.2f} s"
    return (f"note: the video's frame rate varies; {fmt} holds one rate, so its frames are put at the mean "
            f"{fps:.3g} fps{off}. The json and glb exports keep each frame's own time.")


def _root_up(poses: np.ndarray) -> np.ndarray:
    """``(3,)`` the pelvis's mean up direction (its rest ``+y`` turned by the root), from
    ``(T, 72)`` axis-angle poses; frames that are not finite are left out."""
    from scipy.spatial.transform import Rotation

    root = np.asarray(poses, np.float64).reshape(-1, 72)[:, :3]
    root = root[np.isfinite(root).all(1)]
    if not len(root):
        return np.array([0.0, 1.0, 0.0])
    return Rotation.from_rotvec(root).apply([0.0, 1.0, 0.0]).mean(0)


def _model_for(run: dict, gender: str, model):
    import torch

    from flowmocap.body import BodyModel, load_body_model

    if isinstance(model, BodyModel):
        import copy

        return copy.deepcopy(model).to(torch.float64)  # .to() is in place; leave the caller's model alone
    name = model if model is not None else recorded_model(run, gender)
    return load_body_model(name, gender=gender, dtype=torch.float64)


def recorded_model(run: dict, gender: str) -> str:
    """The body model a result was fitted with, as :func:`flowmocap.body.load_body_model`
    takes it: ``"default"`` for the bundled one, else the model file ``run.json`` names.

    Args:
        run: the result's ``run.json``.
        gender: the result's gender (the bundled model's file differs by it).

    Raises:
        DataError: the recorded model file is not there any more.
    """
    from flowmocap.body.files import read_model_arrays
    from flowmocap.errors import DataError

    recorded = str(run.get("model", "default"))
    if recorded == "default" or recorded == read_model_arrays("default", gender).source:
        return "default"
    if Path(recorded).exists():
        return recorded
    raise DataError(f"the result was fitted with the body model {recorded!r}, which is not there any more; "
                    "pass the model file (--model PATH).")


def load_fitted_motion(result_dir: str | Path, frame: str = "ground", model=None, smooth: bool | dict = False,
                       cache_world: bool = True, camera_move_of: FittedMotion | None = None) -> FittedMotion:
    """Read a result folder's ``motion.npz`` and ``run.json`` for export.

    Args:
        result_dir: the result folder written by ``flowmocap track`` / ``demo``.
        frame: ``"ground"`` (y up, floor at 0), ``"up"`` (turned y up, see
            :func:`up_rotation`) or ``"world"`` (see the module docstring).
        model: the body model: ``None`` for the one recorded in ``run.json`` (or the
            default body when that path is gone), a name/path for
            :func:`~flowmocap.body.load_body_model`, or a ``BodyModel``.
        smooth: False, True (the defaults of :func:`flowmocap.fit.smooth.smooth_motion`) or
            a dict of its keyword arguments (``window_s``, ``order``): smooth the motion
            offline; ``joints2d`` are then re-projected from the smoothed body. The floor
            is always estimated from the unsmoothed fit.
        cache_world: write the ground frame to ``RESULT/world.json`` (``frame="ground"``).
        camera_move_of: None, or another person's motion of the same input (loaded), whose
            decision on the camera's move this one takes: the people of one video share one
            camera, so its move is undone for all of them or for none. Where it was undone
            for ``camera_move_of``, it is undone here along that run's floor, turns and move
            (the camera's height from this body's own feet, in its own size); where it was
            not, it is not (:func:`shared_move_refusal`). None: the result's own run and body
            decide (:func:`camera_move_refused`).

    Raises:
        DataError: not a result folder, or a result without frames.
        InputError: unknown ``frame``.
    """
    from flowmocap.geometry.camera import PinholeCamera
    from flowmocap.io.results import checked_motion_arrays, read_result

    if frame not in FRAMES:
        raise InputError(f"unknown export frame {frame!r}; choose one of {', '.join(FRAMES)}.")
    from flowmocap.io.results import result_folder

    result_dir = result_folder(result_dir)
    if not result_dir.is_dir():
        raise DataError(f"result folder {result_dir} " + ("is a file" if result_dir.exists() else "does not exist")
                        + "; give the --out folder of "
                        "`flowmocap track` or the result/ folder of `flowmocap demo`.")
    motion, run = read_result(result_dir)  # its arrays' shapes and values checked (check_motion)
    poses, trans, betas = checked_motion_arrays(result_dir, motion)
    if poses.shape[0] == 0:
        raise DataError(f"{result_dir} holds no tracked frames yet; run or resume the tracking first.")
    gender = str(motion["gender"]) if "gender" in motion else str(run.get("gender", "neutral"))
    fps = float(motion["fps"]) if "fps" in motion else 30.0
    T = poses.shape[0]
    index = np.asarray(motion.get("frame_index", np.arange(T)), np.int64)
    cam_dict = json.loads(str(motion["camera"])) if "camera" in motion else run.get("camera")
    if cam_dict is None:
        raise DataError(f"{result_dir} records no camera (motion.npz 'camera' or run.json 'camera').")
    camera = PinholeCamera.from_dict(cam_dict)
    body = _model_for(run, gender, model)
    turns = camera_turns(run, index) if frame != "world" else None
    shifts = height = refused = None
    # the run whose move of the camera is undone: this one's, or under camera_move_of the owner's where it was
    src = camera_move_of.run if camera_move_of is not None and camera_move_of.shifts is not None else run
    unit = camera_shifts(src, index) if frame != "world" else None
    if unit is not None:  # the floor's turns go with its moves
        normal = np.asarray((src.get("camera_motion") or {})["floor_normal"], np.float64)
        floor_turns = camera_turns(src, index, floor=True)
        if src is not run:
            refused = _uncovered(src, index)
        elif camera_move_of is not None:
            refused = shared_move_refusal(camera_move_of)
        else:
            refused = camera_move_refused(body, poses, trans, betas, camera, floor_turns, normal)
        if refused is None:
            height = camera_height_from_feet(body, poses, trans, betas, camera, floor_turns, unit, normal)
            refused = None if height is not None else "the fitted feet are nowhere below the camera"
        if refused is None:
            shifts, turns = unit * height, floor_turns
    zooms = camera_zooms(run, index) if frame != "world" and shifts is None else None
    if zooms is not None:  # the tracker's one focal length put the body further as the camera zoomed out
        R, t = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
        trans = zoomed_depth(body, betas, trans, R, t, zooms)
    if turns is not None:  # each frame's body turned (and moved) back by the camera's since the first frame
        R, t = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
        moved = t[None] if shifts is None else t[None] - shifts
        A = np.einsum("ji,tkj,kl->til", R, turns, R)  # R^T turns_k^T R: the turn back, in the result's world
        b = np.einsum("ji,tkj,tk->ti", R, turns, moved) - t @ R  # R^T (turns_k^T (t - shifts_k) - t)
        import torch

        with torch.no_grad():
            J0 = body(betas=torch.as_tensor(betas[None], dtype=torch.float64)).rest_joints[0, 0].numpy()
        poses, trans = rotate_motion(poses, trans, J0, A)
        trans = trans + b
    world = None
    offset = np.zeros(3)
    if frame == "ground":
        from flowmocap.export.world import load_world_frame

        world = load_world_frame(result_dir, poses, trans, betas, body, camera, fps, frame_index=index,
                                 cache=cache_world)
        W, offset = world.rotation, world.offset
    else:
        W = up_rotation(camera, _root_up(poses)) if frame == "up" else np.eye(3)
    smoothed = None
    if not isinstance(smooth, (bool, dict)):  # smooth="no" would smooth
        raise InputError(f"smooth must be False, True or a dict of window_s and order; got {smooth!r}.")
    if isinstance(smooth, dict) and set(smooth) - {"window_s", "order"}:
        raise InputError(f"smooth takes window_s (seconds) and order; got {sorted(smooth)}.")
    if smooth:
        from flowmocap.fit.smooth import DEFAULT_ORDER, DEFAULT_WINDOW_S, smooth_motion, window_frames

        kw = {"window_s": DEFAULT_WINDOW_S, "order": DEFAULT_ORDER, **(smooth if isinstance(smooth, dict) else {})}
        poses, trans = smooth_motion(poses, trans, fps, frame_index=index, **kw)
        smoothed = {**kw, "window_frames": window_frames(kw["window_s"], fps, kw["order"])}
    from flowmocap.export.world import camera_in_frame

    fm = FittedMotion(poses=poses, trans=trans, betas=betas, gender=gender, fps=fps, frame_index=index,
                      rotation=W, model=body, camera=camera_in_frame(camera, W, offset), run=run, frame=frame,
                      joints2d=np.asarray(motion.get("joints2d", np.full((T, 24, 2), np.nan)), np.float64),
                      offset=offset, world=world, smoothed=smoothed,
                      disagreement=(np.asarray(motion["disagreement"], np.float64) if "disagreement" in motion
                                    else None), turns=turns, shifts=shifts, camera_height_m=height,
                      camera_move_refused=refused, zooms=zooms)
    if not np.allclose(W, np.eye(3)) or np.any(offset != 0):
        p, t = rotate_motion(poses, trans, fm.rest_joints()[0], W)
        fm.poses, fm.trans = p, t + offset
    if smoothed is not None:
        fm.joints2d = fm.project(fm.joints())
    return fm


def turned_camera(camera, turn: np.ndarray, shift: np.ndarray | None = None):
    """``camera`` (a :class:`~flowmocap.geometry.PinholeCamera`) turned about its centre by
    ``turn`` ``(3, 3)`` and then moved so that a point's camera coordinates become ``turn x +
    shift`` (``shift`` ``(3,)`` metres in the turned camera's axes, or None for no move):
    ``R' = turn R``, ``t' = turn t + shift``."""
    T = np.asarray(turn, np.float64)
    t = T @ np.asarray(camera.t, np.float64)
    if shift is not None:
        t = t + np.asarray(shift, np.float64)
    return replace(camera, R=T @ np.asarray(camera.R, np.float64), t=t)


def _nearest_rows(frames: np.ndarray, frame_index) -> np.ndarray:
    frame_index = np.asarray(frame_index, np.int64)
    idx = np.clip(np.searchsorted(frames, frame_index), 0, len(frames) - 1)
    prev = np.clip(idx - 1, 0, len(frames) - 1)
    nearer = np.abs(frames[prev] - frame_index) < np.abs(frames[idx] - frame_index)
    return np.where(nearer, prev, idx)


def camera_zooms(run: dict, frame_index) -> np.ndarray | None:
    """``(T,)`` the camera's focal length over the input's first frame's at each of
    ``frame_index``, from ``run.json``'s ``camera_motion`` ``zooms``
    (:mod:`flowmocap.vision.camera_motion`); None where the camera did not zoom. A frame the
    estimate does not cover takes the nearest one's."""
    cm = run.get("camera_motion") or {}
    if not cm.get("moving") or not cm.get("zooms"):
        return None
    frames = np.asarray(cm["frames"], np.int64)
    zooms = np.asarray(cm["zooms"], np.float64).reshape(-1)
    if len(frames) != len(zooms) or not len(frames) or not np.all(zooms > 0):
        raise DataError("run.json 'camera_motion' holds a different number of frames and zooms, or a zoom that is "
                        "not positive; the result is damaged: track the input again with --force.")
    return zooms[_nearest_rows(frames, frame_index)]


def zoomed_depth(body, betas: np.ndarray, trans: np.ndarray, R: np.ndarray, t: np.ndarray,
                 zooms: np.ndarray) -> np.ndarray:
    """``trans`` ``(T, 3)`` metres with each frame's body where a camera of focal length
    ``zooms[k]`` times the tracked one's puts it: the root's depth (its camera ``z``,
    ``x_cam = R x + t``) ``zooms[k]`` times the tracked one, its camera ``x`` and ``y`` kept.

    A camera ``z`` times the focal length shows a body at depth ``d`` as large as one of the
    first focal length shows it at ``d / z``, at the same pixel when its ``x`` and ``y`` are
    the same; so a tracker that keeps the first focal length puts it at ``(x, y, d / z)``.
    The body's size and pose are unchanged (the pixels off the root move by its depth's share
    of the root's, a few pixels at the edges of a body where a zoom is large)."""
    import torch

    with torch.no_grad():
        J0 = body(betas=torch.as_tensor(np.asarray(betas)[None], dtype=torch.float64)).rest_joints[0, 0].numpy()
    root = (np.asarray(trans, np.float64) + J0) @ R.T + t  # the posed root, camera coordinates
    root[:, 2] *= np.asarray(zooms, np.float64)
    return (root - t) @ R - J0


def camera_shifts(run: dict, frame_index) -> np.ndarray | None:
    """``(T, 3)`` the camera's move since the input's first frame at each of ``frame_index``,
    in that frame's camera axes and in units of the camera's height above the floor in the
    first frame, from ``run.json``'s ``camera_motion`` ``shifts``
    (:mod:`flowmocap.vision.camera_motion`); None where the camera did not move sideways. A frame
    the estimate does not cover takes the nearest one's."""
    cm = run.get("camera_motion") or {}
    if not cm.get("moving") or not cm.get("shifts"):
        return None
    frames = np.asarray(cm["frames"], np.int64)
    shifts = np.asarray(cm["shifts"], np.float64).reshape(-1, 3)
    if (len(frames) != len(shifts) or not len(frames) or len(cm.get("floor_normal") or []) != 3
            or len(cm.get("floor_rotvecs") or []) != len(frames)):
        raise DataError("run.json 'camera_motion' holds a different number of frames and moves, or no floor "
                        "normal or turns with them; the result is damaged: track the input again with --force.")
    return shifts[_nearest_rows(frames, frame_index)]


#: The camera's move found from the floor is undone only where the floor's normal lies within
#: this many degrees of the body's upright direction (the median over the frames of the
#: pelvis-to-neck direction, turned back by the camera's turn): a floor the images made up
#: disagrees with the person standing on it.
FLOOR_BODY_MAX_DEG = 25.0


def camera_move_refused(body, poses: np.ndarray, trans: np.ndarray, betas: np.ndarray, camera, turns: np.ndarray,
                        normal: np.ndarray) -> str | None:
    """Why a camera move found from the floor should not be undone, or None where it may: the
    floor's normal more than :data:`FLOOR_BODY_MAX_DEG` from the body's upright direction.

    Args:
        body: the body model (float64).
        poses, trans, betas: ``(T, 72)``, ``(T, 3)``, ``(10,)`` the result's own parameters.
        camera: the result's camera (``x_cam = R x + t``).
        turns: ``(T, 3, 3)`` the camera's turn per row (:func:`camera_turns`).
        normal: ``(3,)`` the floor's unit normal in the first frame's camera axes, pointing down.
    """
    from flowmocap.fit.smooth import posed_joints

    j = posed_joints(body, betas, poses, trans, camera, chunk=1024)[0]
    R = np.asarray(camera.R, np.float64)
    spine = (j[:, 12] - j[:, 0]) @ R.T  # pelvis to neck, camera axes of each frame
    spine = np.einsum("tji,tj->ti", turns, spine)  # turned back into the first frame's axes
    spine /= np.linalg.norm(spine, axis=1, keepdims=True)
    up = np.median(spine, axis=0)
    up /= np.linalg.norm(up)
    angle = float(np.degrees(np.arccos(np.clip(-up @ np.asarray(normal, np.float64), -1.0, 1.0))))
    if angle > FLOOR_BODY_MAX_DEG:
        return (f"the floor found in the images lies {angle:.0f} degrees from the body's upright direction "
                f"(more than {FLOOR_BODY_MAX_DEG:.0f}): its move is not trusted")
    return None


def _uncovered(run: dict, frame_index) -> str | None:
    """Why another person's frames ``frame_index`` cannot take ``run``'s move of the camera
    (it was found up to the last frame that run tracked), or None where they can."""
    last = int(max((run.get("camera_motion") or {}).get("frames") or [-1]))
    beyond = int(np.max(frame_index))
    if beyond > last:
        return (f"the move was found up to frame {last} (the run of the person whose floor and frame are shared), "
                f"and this person is tracked to frame {beyond}")
    return None


def shared_move_refusal(holder: FittedMotion) -> str | None:
    """Why another person of ``holder``'s input should not have the camera's move undone, or
    None where it should: ``holder`` (the person whose floor and frame the people share,
    loaded) had it undone. A move ``holder``'s own body refused, or that ``holder``'s run did
    not find, is refused for everyone, so that no two people of one video are moved back along
    different cameras."""
    if holder.shifts is not None:
        return None
    why = holder.camera_move_refused or "that person's run found no move of the camera"
    return f"the person whose floor and frame are shared did not have it undone, so nobody does ({why})"


def camera_height_from_feet(body, poses: np.ndarray, trans: np.ndarray, betas: np.ndarray, camera,
                            turns: np.ndarray, unit_shifts: np.ndarray, normal: np.ndarray,
                            chunk: int = 256) -> float | None:
    """The camera's height above the floor in the input's first frame, metres, from the
    fitted body's feet: in each frame the lowest foot vertex's distance from the camera along
    the floor's normal there (``turns[k] normal``), over the camera's height then in units of
    the first frame's (``1 + n_k . unit_shifts[k]``); the median over the frames (a walk or a
    stand has a foot on the floor in nearly every frame).

    Args:
        body: the body model (float64).
        poses, trans, betas: ``(T, 72)``, ``(T, 3)``, ``(10,)`` the result's own parameters
            (its world frame).
        camera: the result's camera (``x_cam = R x + t``).
        turns, unit_shifts: ``(T, 3, 3)``, ``(T, 3)`` (:func:`camera_turns`, :func:`camera_shifts`).
        normal: ``(3,)`` the floor's unit normal in the first frame's camera axes, pointing down.

    Returns:
        metres, or None where the feet are nowhere below the camera.
    """
    import torch

    from flowmocap.export.world import foot_vertex_sets

    feet = np.concatenate(foot_vertex_sets(body.weights.cpu().numpy()))
    R, t = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
    n = np.einsum("tij,j->ti", turns, np.asarray(normal, np.float64))
    scale = 1.0 + np.einsum("ti,ti->t", n, unit_shifts)
    per = []
    b = torch.as_tensor(betas[None], dtype=torch.float64)
    with torch.no_grad():
        shaped = body.shaped(b)
        for s in range(0, len(poses), chunk):
            v = body(betas=b, pose=torch.as_tensor(poses[s:s + chunk], dtype=torch.float64),
                     trans=torch.as_tensor(trans[s:s + chunk], dtype=torch.float64), shaped=shaped).vertices.numpy()
            cam = v[:, feet] @ R.T + t
            per.append(np.einsum("tvi,ti->tv", cam, n[s:s + chunk]).max(1) / scale[s:s + chunk])
    h = np.concatenate(per)
    h = h[np.isfinite(h) & (scale > 0.05)]
    if not len(h) or np.median(h) <= 0:
        return None
    return float(np.median(h))


def camera_turns(run: dict, frame_index, floor: bool = False) -> np.ndarray | None:
    """``(T, 3, 3)`` the camera's turn since the input's first frame at each of ``frame_index``
    (``x_t = turns[k] x_0`` in the camera's axes), from ``run.json``'s ``camera_motion``
    (:mod:`flowmocap.vision.camera_motion`): the whole background's, or with ``floor`` the
    floor's (those that go with the camera's move, ``shifts``); None where the camera stood
    still or the run says nothing. A frame the estimate does not cover takes the nearest one's."""
    from scipy.spatial.transform import Rotation

    cm = run.get("camera_motion") or {}
    key = "floor_rotvecs" if floor else "rotvecs"
    if not cm.get("moving") or not cm.get(key):
        return None
    frames = np.asarray(cm["frames"], np.int64)
    rotvecs = np.asarray(cm[key], np.float64).reshape(-1, 3)
    if len(frames) != len(rotvecs) or not len(frames):
        raise DataError("run.json 'camera_motion' holds a different number of frames and rotations; the result is "
                        "damaged: track the input again with --force.")
    return Rotation.from_rotvec(rotvecs[_nearest_rows(frames, frame_index)]).as_matrix()


def motion_in_frame_of(motion: FittedMotion, other: FittedMotion) -> FittedMotion:
    """``motion`` moved rigidly into ``other``'s export frame, through the camera both were
    tracked with: the people of one video (``track --person all``) share its camera, so one
    person's ground frame can hold them all.

    With ``X_cam = R_m x_m + t_m`` (``motion.camera``) and ``X_cam = R_o x_o + t_o``
    (``other.camera``): ``x_o = R_o^T R_m x_m + R_o^T (t_m - t_o)``.

    Args:
        motion, other: two :class:`FittedMotion` of one input, with cameras of the same
            intrinsics and size.

    Returns:
        A new :class:`FittedMotion`: ``poses`` (the root turned), ``trans``, ``rotation``,
        ``offset``, ``camera`` (``other``'s) and ``frame`` (``other``'s) changed, ``world``
        None (the floor is ``other``'s) and ``contacts`` the motion's own foot contacts
        (:attr:`FittedMotion.foot_contacts`); the body projects onto the same pixels as before.

    Raises:
        DataError: the cameras differ in intrinsics or size (not one input's results).
    """
    a, b = motion.camera, other.camera
    if (a.width, a.height, a.fx, a.fy, a.cx, a.cy) != (b.width, b.height, b.fx, b.fy, b.cx, b.cy):
        raise DataError(f"the two results were tracked with other cameras ({a.width}x{a.height} px, focal {a.fx:g} "
                        f"against {b.width}x{b.height} px, focal {b.fx:g}); only results of one input tracked at "
                        "one size share a frame.")
    M = b.R.T @ a.R
    off = b.R.T @ (a.t - b.t)
    poses, trans = rotate_motion(motion.poses, motion.trans, motion.rest_joints()[0], M)
    return replace(motion, poses=poses, trans=trans + off, rotation=M @ motion.rotation,
                   offset=M @ motion.offset + off, camera=b, frame=other.frame, world=None,
                   contacts=motion.foot_contacts)
