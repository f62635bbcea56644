"""BVH export: SMPL's 24-joint tree with the fitted shape's bone lengths.

The skeleton's offsets are the rest (T-pose) joints of the fitted ``betas`` (child minus
parent), so forward kinematics of the file gives exactly the fitted body's joints. The
root (pelvis) has a zero ``OFFSET`` and its position channels hold its world position,
so readers that add the root offset and readers that do not agree. The joints' local
rotations are SMPL's (the rest pose has identity rotations, bones along the world
axes). Leaves (head, feet, hands) get an ``End Site`` half as long as their own bone
(horizontal for the feet), so no bone has zero length in Blender.
"""

from __future__ import annotations

import numbers
from pathlib import Path

import numpy as np

from flowmocap.body.skeleton import JOINT_NAMES, PARENTS
from flowmocap.errors import InputError

__all__ = ["motion_to_clip", "write_motion_bvh"]

_LEAVES = {"head": False, "left_foot": True, "right_foot": True, "left_hand": False, "right_hand": False}


def motion_to_clip(poses: np.ndarray, trans: np.ndarray, rest_joints: np.ndarray, fps: float, source: str = ""):
    """An SMPL motion as a :class:`~flowmocap.io.mocap.MocapClip` (24 joints + 5 end sites).

    Args:
        poses: ``(T, 72)`` axis-angle in radians, SMPL joint order.
        trans: ``(T, 3)`` SMPL translation in metres.
        rest_joints: ``(24, 3)`` joints of the shaped rest pose in metres.
        fps: frames per second.
        source: where the motion came from (recorded in the clip).

    Returns:
        ``MocapClip`` whose ``positions[:, :24]`` are the SMPL joints ``(T, 24, 3)``.
    """
    from scipy.spatial.transform import Rotation

    from flowmocap.io.mocap import MocapClip, forward_kinematics

    poses = np.asarray(poses, np.float64).reshape(-1, 72)
    trans = np.asarray(trans, np.float64).reshape(-1, 3)
    rest = np.asarray(rest_joints, np.float64).reshape(24, 3)
    T = poses.shape[0]
    if trans.shape[0] != T:
        raise InputError(f"poses have {T} frames but trans {trans.shape[0]}.")
    names = list(JOINT_NAMES)
    parents = list(PARENTS)
    offsets = [np.zeros(3)] + [rest[j] - rest[PARENTS[j]] for j in range(1, 24)]
    for leaf, flat in _LEAVES.items():
        j = JOINT_NAMES.index(leaf)
        tip = 0.5 * (rest[j] - rest[PARENTS[j]])
        if flat:
            tip[1] = 0.0
        names.append(f"{leaf}_end")
        parents.append(j)
        offsets.append(tip)
    J = len(names)
    offsets = np.asarray(offsets)
    rotations = np.tile(np.eye(3), (T, J, 1, 1))
    rotations[:, :24] = Rotation.from_rotvec(poses.reshape(-1, 3)).as_matrix().reshape(T, 24, 3, 3)
    translations = np.tile(offsets, (T, 1, 1))
    translations[:, 0] = rest[0] + trans
    _, positions = forward_kinematics(parents, rotations, translations)
    end_site = np.arange(J) >= 24
    return MocapClip(names=tuple(names), parents=np.asarray(parents, np.int64), offsets=offsets,
                     rotations=rotations, translations=translations, positions=positions,
                     end_site=end_site, fps=float(fps), source=str(source),
                     info={"rig": "smpl24", "unit": "m"})


def write_motion_bvh(path: str | Path, poses: np.ndarray, trans: np.ndarray, rest_joints: np.ndarray,
                     fps: float, units_per_metre: float = 1.0, order: str = "ZYX") -> Path:
    """Write an SMPL motion as BVH (see the module docstring).

    Args:
        path: output ``.bvh`` file.
        poses, trans, rest_joints, fps: as for :func:`motion_to_clip`.
        units_per_metre: file units per metre (1 = metres, Blender's default import scale;
            100 = centimetres). A BVH states no unit: :func:`flowmocap.io.mocap.read_bvh`
            reads flowmocap's own files back as metres or centimetres; give it ``scale``
            for any other unit.
        order: rotation channel order (intrinsic, e.g. ``"ZYX"`` writes ``Zrotation
            Yrotation Xrotation``).

    Returns:
        The path written.
    """
    from flowmocap.io.mocap import write_bvh

    if (isinstance(units_per_metre, bool) or not isinstance(units_per_metre, numbers.Real)
            or not np.isfinite(units_per_metre) or units_per_metre <= 0):
        raise InputError(f"units_per_metre must be a positive number (100 for centimetres), got {units_per_metre!r}.")
    clip = motion_to_clip(poses, trans, rest_joints, fps)
    return write_bvh(clip, path, units_per_metre=units_per_metre, order=order)
