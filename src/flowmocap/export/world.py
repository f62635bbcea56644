"""The world frame of a result: gravity up, the floor at height 0, computed from the fit.

:func:`world_frame` looks at the fitted feet over the whole sequence (the lowest vertex of
each foot per frame), labels the frames where a foot stands still
(:func:`flowmocap.geometry.ground.foot_contacts`), fits the floor through those points
robustly (:func:`flowmocap.geometry.ground.fit_ground_plane`) and builds a y-up frame on it
(:func:`flowmocap.geometry.ground.ground_frame`): origin under the first frame's pelvis,
``+z`` towards the camera. The expected up direction before the fit is the body's own
(mean direction from the ankles to the neck), or the world's up
(:func:`flowmocap.geometry.camera.world_up`: image up for a video without a calibration, a
calibrated world's up axis) where the body lies down; with no still foot the floor goes
through the lowest foot point of the sequence.

The frame is a function of ``motion.npz`` (poses, trans, betas) and the body model;
:func:`load_world_frame` caches it as ``RESULT/world.json`` (written atomically) with a
fingerprint of those inputs, so a result that is resumed or re-tracked gets a new one.
``world.json``: ``{"format": "flowmocap-world", "version": 1, "fingerprint", "rotation"
(3x3), "offset" (3, metres; x_world = rotation @ x_result + offset), "up" (3, the floor's
normal in the result's frame), "floor_height_m" (along "up", from the result's origin),
"method" ("contacts" | "fallback"), "contact_points", "residual_mm", "prior_up",
"camera" (the result's camera re-expressed in the world frame: overlays stay exact),
"frame_index" (T), "contacts" (T x 2, left/right foot on the ground, 0/1)}``.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flowmocap.geometry.camera import world_up
from flowmocap.geometry.ground import GroundPlane, fit_ground_plane, foot_contacts, ground_frame

__all__ = ["WorldFrame", "world_frame", "load_world_frame", "foot_vertex_sets", "camera_in_frame",
           "WORLD_FILE"]

WORLD_FILE = "world.json"

_LEFT_FOOT, _RIGHT_FOOT = (7, 10), (8, 11)  # ankle, foot (toes) joints of SMPL


@dataclass
class WorldFrame:
    """Where a result's motion stands: ``x_world = rotation @ x_result + offset``.

    Attributes:
        rotation: ``(3, 3)`` float64 rotation from the result's frame to the world (y up).
        offset: ``(3,)`` metres.
        plane: the fitted floor in the result's frame.
        contacts: ``(T, 2)`` bool, left/right foot standing on the floor per frame.
        prior_up: ``(3,)`` the up direction expected before the fit (result's frame).
        camera: the result's camera in the world frame (``PinholeCamera``).
        fingerprint: hash of the inputs the frame was computed from.
    """

    rotation: np.ndarray
    offset: np.ndarray
    plane: GroundPlane
    contacts: np.ndarray
    prior_up: np.ndarray
    camera: object
    fingerprint: str

    def to_dict(self, frame_index=None) -> dict:
        """The ``world.json`` document (see the module docstring); ``frame_index``: ``(T,)``
        source-video frame numbers to record (None: an empty list)."""
        r = lambda a, n=9: np.round(np.asarray(a, np.float64), n).tolist()  # noqa: E731
        return {
            "format": "flowmocap-world", "version": 1, "fingerprint": self.fingerprint,
            "rotation": r(self.rotation), "offset": r(self.offset), "up": r(self.plane.normal),
            "floor_height_m": round(float(self.plane.height), 9), "method": self.plane.method,
            "contact_points": self.plane.inliers,
            "residual_mm": None if not np.isfinite(self.plane.residual_m) else round(1000 * self.plane.residual_m, 3),
            "prior_up": r(self.prior_up), "camera": self.camera.to_dict(),
            "frame_index": [] if frame_index is None else [int(i) for i in frame_index],
            "contacts": self.contacts.astype(int).tolist(),
        }

    @classmethod
    def from_dict(cls, doc: dict) -> "WorldFrame":
        """The frame of a ``world.json`` document (the inverse of :meth:`to_dict`).

        Raises:
            KeyError, TypeError, ValueError: if a field is missing or malformed.
        """
        from flowmocap.geometry.camera import PinholeCamera

        res = doc.get("residual_mm")
        plane = GroundPlane(normal=np.asarray(doc["up"], np.float64), height=float(doc["floor_height_m"]),
                            inliers=int(doc["contact_points"]), method=str(doc["method"]),
                            residual_m=float("nan") if res is None else res / 1000.0)
        return cls(rotation=np.asarray(doc["rotation"], np.float64), offset=np.asarray(doc["offset"], np.float64),
                   plane=plane, contacts=np.asarray(doc["contacts"], bool).reshape(-1, 2),
                   prior_up=np.asarray(doc["prior_up"], np.float64), camera=PinholeCamera.from_dict(doc["camera"]),
                   fingerprint=str(doc["fingerprint"]))


def camera_in_frame(camera, rotation: np.ndarray, offset: np.ndarray):
    """The camera re-expressed in a frame ``x_new = rotation @ x_old + offset``.

    ``X_cam = R x_old + t = (R rotation^T) x_new + (t - R rotation^T offset)``, so it
    projects the moved points to the same pixels.

    Args:
        camera: a ``PinholeCamera`` (world-to-camera ``R``, ``t``).
        rotation: ``(3, 3)`` rotation from the old frame to the new.
        offset: ``(3,)`` metres.

    Returns:
        A new ``PinholeCamera``, same intrinsics.
    """
    from flowmocap.geometry.camera import PinholeCamera

    W = np.asarray(rotation, np.float64)
    Rn = camera.R @ W.T
    return PinholeCamera(fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy, width=camera.width,
                         height=camera.height, R=Rn, t=camera.t - Rn @ np.asarray(offset, np.float64))


def foot_vertex_sets(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertex indices of the left and right foot: vertices skinned mostly to the ankle or toes.

    Args:
        weights: ``(V, 24)`` skinning weights.

    Returns:
        ``left`` and ``right``, 1-D int64 vertex indices (into the ``V`` vertices).
    """
    top = np.argmax(np.asarray(weights), axis=1)
    return np.flatnonzero(np.isin(top, _LEFT_FOOT)), np.flatnonzero(np.isin(top, _RIGHT_FOOT))


#: Bump when :func:`world_frame` changes, so cached ``world.json`` files are recomputed.
ALGORITHM = "ground-v3"  # v3: the world's up from the camera's orientation (a z-up calibration)


def _fingerprint(poses, trans, betas, model) -> str:
    h = hashlib.sha1(ALGORITHM.encode())
    for a in (poses, trans, betas):
        h.update(np.ascontiguousarray(np.asarray(a, np.float64)).tobytes())
    h.update(str(getattr(model, "source", "")).encode())
    h.update(str(getattr(model, "gender", "")).encode())
    return h.hexdigest()[:16]


def world_frame(poses: np.ndarray, trans: np.ndarray, betas: np.ndarray, model, camera, fps: float,
                chunk: int = 64) -> WorldFrame:
    """Estimate the floor and the world frame of a fitted motion (see the module docstring).

    Args:
        poses: ``(T, 72)`` axis-angle radians; trans: ``(T, 3)`` metres; betas: ``(10,)``;
            all in the result's frame (the camera's world).
        model: the :class:`~flowmocap.body.BodyModel` of the fit.
        camera: the result's ``PinholeCamera``.
        fps: frames per second (Hz).

    Returns:
        :class:`WorldFrame`.
    """
    import torch

    poses = np.asarray(poses, np.float64).reshape(-1, 72)
    trans = np.asarray(trans, np.float64).reshape(-1, 3)
    T = poses.shape[0]
    left, right = foot_vertex_sets(model.weights.cpu().numpy())
    dt = model.v_template.dtype
    b = torch.as_tensor(np.asarray(betas, np.float64)[None], dtype=dt)
    shaped = model.shaped(b)  # one shape for every frame: shaped once

    def posed(s, vertices):
        return model(betas=b, pose=torch.as_tensor(poses[s:s + chunk], dtype=dt),
                     trans=torch.as_tensor(trans[s:s + chunk], dtype=dt), shaped=shaped, with_vertices=vertices)

    with torch.no_grad():
        joints = np.concatenate([posed(s, False).joints.double().numpy() for s in range(0, T, chunk)])
    body_up = joints[:, 12] - 0.5 * (joints[:, 7] + joints[:, 8])
    body_up = body_up / np.linalg.norm(body_up, axis=1, keepdims=True)
    prior = body_up.mean(0)
    prior = prior / np.linalg.norm(prior)
    cam_up = world_up(camera, prior)  # the calibrated world's up axis (image up for R = I)
    if prior @ cam_up < np.cos(np.radians(45)):  # lying or upside down: trust the camera
        prior = cam_up

    def lowest(up):  # (T, 2, 3): the lowest vertex of each foot along up
        # the mesh posed again chunk by chunk: a long motion's foot vertices are never all held
        out = np.empty((T, 2, 3))
        with torch.no_grad():
            for s in range(0, T, chunk):
                v = posed(s, True).vertices
                for k, feet in enumerate((left, right)):
                    f = v[:, feet].double().numpy()
                    out[s:s + chunk, k] = np.take_along_axis(f, np.argmin(f @ up, axis=1)[:, None, None], axis=1)[:, 0]
        return out

    low = lowest(prior)  # (T, 2, 3)
    still = foot_contacts(low, fps, prior)
    plane = fit_ground_plane(low[still], prior, fallback_points=low.reshape(-1, 3))
    low = lowest(plane.normal)
    contacts = foot_contacts(low, fps, plane.normal) & (np.abs(plane.elevation(low)) < 0.05)
    rotation, offset = ground_frame(plane, joints[0, 0], camera.center)
    return WorldFrame(rotation=rotation, offset=offset, plane=plane, contacts=contacts, prior_up=prior,
                      camera=camera_in_frame(camera, rotation, offset),
                      fingerprint=_fingerprint(poses, trans, betas, model))


def load_world_frame(result_dir: str | Path, poses, trans, betas, model, camera, fps: float,
                     frame_index=None, cache: bool = True) -> WorldFrame:
    """:func:`world_frame` of a result folder, cached in ``RESULT/world.json``.

    With ``cache``, a cached file is used when its fingerprint matches the inputs (and this
    version of the estimate); otherwise (also when the file is unreadable: not JSON, not a
    JSON object, parts missing) the frame is computed and written atomically. A
    result folder that cannot be written to still gets its frame. ``cache=False`` neither
    reads nor writes the file.

    Args:
        result_dir: the result folder (``world.json`` is read and written there).
        poses, trans, betas, model, camera, fps: as for :func:`world_frame` (``(T, 72)``
            radians, ``(T, 3)`` metres, ``(10,)``, in the result's frame).
        frame_index: ``(T,)`` source-video frame numbers, stored in ``world.json`` only
            (not part of the fingerprint); None stores an empty list.
        cache: read and write ``world.json``.

    Returns:
        :class:`WorldFrame`.
    """
    from flowmocap.atomic import atomic_write

    path = Path(result_dir) / WORLD_FILE
    fp = _fingerprint(poses, trans, betas, model)
    if cache and path.is_file():
        try:
            doc = json.loads(path.read_text())
            if isinstance(doc, dict) and doc.get("fingerprint") == fp and doc.get("format") == "flowmocap-world":
                return WorldFrame.from_dict(doc)
        except (ValueError, KeyError, TypeError, AttributeError, IndexError, OSError):
            pass  # an unreadable cache (not JSON, not an object, missing parts) is computed again
    wf = world_frame(poses, trans, betas, model, camera, fps)
    text = json.dumps(wf.to_dict(frame_index), indent=1)
    if cache:
        try:
            atomic_write(path, lambda tmp: Path(tmp).write_text(text))
        except OSError:
            pass
    # as the cache will give it (9 decimals): an export made now and one made later from
    # world.json are equal to the last digit
    return WorldFrame.from_dict(json.loads(text))
