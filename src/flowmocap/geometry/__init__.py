"""Geometry: rotations (axis-angle, matrices, quaternions, Euler, 6D), the pinhole camera,
and similarity Procrustes alignment.

Units: metres, radians, pixels. Camera axes follow OpenCV (x right, y down, z forward);
quaternions are (w, x, y, z), scalar first. Torch functions broadcast over leading
batch dimensions and are differentiable in float32 and float64.
"""

from flowmocap.geometry.camera import PinholeCamera, look_at
from flowmocap.geometry.procrustes import similarity_procrustes
from flowmocap.geometry.rotations import (
    axis_angle_to_matrix,
    axis_angle_to_quaternion,
    euler_to_matrix,
    matrix_to_axis_angle,
    matrix_to_euler,
    matrix_to_quaternion,
    matrix_to_rotation_6d,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_to_axis_angle,
    quaternion_to_matrix,
    rotation_6d_to_matrix,
)

__all__ = [
    "axis_angle_to_matrix",
    "matrix_to_axis_angle",
    "axis_angle_to_quaternion",
    "quaternion_to_axis_angle",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "quaternion_multiply",
    "quaternion_conjugate",
    "euler_to_matrix",
    "matrix_to_euler",
    "rotation_6d_to_matrix",
    "matrix_to_rotation_6d",
    "PinholeCamera",
    "look_at",
    "similarity_procrustes",
]
