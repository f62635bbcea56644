"""Input/output of motions: motion-capture files (BVH, ASF/AMC), retargeting onto the
SMPL tree of any body model, and the built-in procedural walk.

Public API:

- :class:`MocapClip`, :func:`read_mocap` (``.bvh`` / ``.amc``), :func:`read_bvh`,
  :func:`read_asf_amc`, :func:`find_asf`, :func:`write_bvh`, :func:`resample`,
  :func:`forward_kinematics` -- clips in metres, y up.
- :class:`SmplMotion` (poses ``(T, 72)``, trans ``(T, 3)``, betas, gender, fps),
  :func:`retarget`, :func:`resolve_joint_map`, :data:`RIGS`, :func:`body_yaw`.
- :func:`builtin_walk`, :func:`walk_poses` -- ``builtin:walk``.
- :func:`read_amass_npz`, :func:`write_amass_npz`, :data:`Y_UP_TO_Z_UP` -- AMASS-layout
  ``.npz`` (z up); :func:`rotate_motion` turns a SMPL motion rigidly.
- :func:`load_motion` -- any of the above by name or path.
"""

from flowmocap.io.amass import Y_UP_TO_Z_UP, read_amass_npz, write_amass_npz
from flowmocap.io.builtin_walk import builtin_walk, walk_poses
from flowmocap.io.mocap import (
    MocapClip,
    find_asf,
    forward_kinematics,
    read_asf_amc,
    read_bvh,
    read_mocap,
    resample,
    write_bvh,
)
from flowmocap.io.motion_source import load_motion
from flowmocap.io.retarget import REST_RELATIVE, RIGS, body_yaw, resolve_joint_map, retarget
from flowmocap.io.smpl_motion import SmplMotion, rotate_motion

__all__ = [
    "MocapClip",
    "find_asf",
    "forward_kinematics",
    "read_asf_amc",
    "read_bvh",
    "read_mocap",
    "resample",
    "write_bvh",
    "SmplMotion",
    "RIGS",
    "REST_RELATIVE",
    "body_yaw",
    "resolve_joint_map",
    "retarget",
    "builtin_walk",
    "walk_poses",
    "load_motion",
    "read_amass_npz",
    "write_amass_npz",
    "Y_UP_TO_Z_UP",
    "rotate_motion",
]
