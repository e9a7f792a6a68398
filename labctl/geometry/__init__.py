"""Rigid transforms and the camera model (pinhole + Tsai κ1). Imports numpy only."""

from .camera import CameraModel
from .transforms import (
    apply,
    invert,
    look_at,
    make_T,
    matrix_to_rotvec,
    orthonormalize,
    rot_x,
    rot_y,
    rot_z,
    rotate,
    rotation_angle,
    rotvec_to_matrix,
    rpy_from_matrix_willson,
    rpy_willson,
)

__all__ = [
    "CameraModel",
    "apply",
    "invert",
    "look_at",
    "make_T",
    "matrix_to_rotvec",
    "orthonormalize",
    "rot_x",
    "rot_y",
    "rot_z",
    "rotate",
    "rotation_angle",
    "rotvec_to_matrix",
    "rpy_from_matrix_willson",
    "rpy_willson",
]
