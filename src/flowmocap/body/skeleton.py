"""The SMPL kinematic tree: 24 joints, their names and parents.

Joint order is SMPL's (0 pelvis ... 23 right hand); a pose is ``(24, 3)`` axis-angle
in this order, flattened to ``(72,)``. "left" is the body's own left (SMPL convention:
the left hip has positive x in the rest pose, which faces +z with y up).
"""

from __future__ import annotations

JOINT_NAMES: tuple[str, ...] = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
)

#: Parent of each joint; -1 for the root (pelvis).
PARENTS: tuple[int, ...] = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
)

NUM_JOINTS = 24
NUM_POSE = 3 * NUM_JOINTS

JOINT_INDEX: dict[str, int] = {name: i for i, name in enumerate(JOINT_NAMES)}

#: The 13 joints the paper evaluates (head, shoulders, elbows, wrists, hips, knees,
#: ankles), as SMPL joint indices.
EVAL_JOINTS: tuple[int, ...] = tuple(
    JOINT_INDEX[n]
    for n in (
        "head",
        "left_shoulder", "right_shoulder",
        "left_elbow", "right_elbow",
        "left_wrist", "right_wrist",
        "left_hip", "right_hip",
        "left_knee", "right_knee",
        "left_ankle", "right_ankle",
    )
)


def children(joint: int) -> list[int]:
    """Indices of the joints whose parent is ``joint``."""
    return [j for j, p in enumerate(PARENTS) if p == joint]
