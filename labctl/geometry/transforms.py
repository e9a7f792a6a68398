"""Rigid transforms as 4×4 homogeneous matrices.

A pose is named ``T_<to>_<from>``: ``T_w_c1`` maps points in the fixed camera's frame C1
into the world frame W, so ``p_w = T_w_c1 @ p_c1`` (homogeneous) and
``T_w_o = T_w_t @ T_t_o``. Millimetres and radians throughout.
"""

from __future__ import annotations

import numpy as np

_I4 = np.eye(4)
_I4.setflags(write=False)  # copied, never written: np.eye per call was a tenth of a pose's cost


def make_T(R: np.ndarray | None = None, t=None) -> np.ndarray:
    """Build a 4×4 transform from a 3×3 rotation ``R`` and a translation ``t`` (mm)."""
    T = _I4.copy()
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform, exact (uses Rᵀ, not a general matrix inverse)."""
    R = T[:3, :3]
    Ti = _I4.copy()
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``T`` to points of shape (..., 3); returns the same shape."""
    p = np.asarray(points, dtype=float)
    return p @ T[:3, :3].T + T[:3, 3]


def rotate(T: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Apply only the rotation of ``T`` to direction vectors of shape (..., 3)."""
    return np.asarray(vectors, dtype=float) @ T[:3, :3].T


def rot_x(a: float) -> np.ndarray:
    """3×3 rotation by ``a`` rad about the x axis."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """3×3 rotation by ``a`` rad about the y axis."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    """3×3 rotation by ``a`` rad about the z axis."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rpy_willson(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rotation from Willson's Tsai-code roll-pitch-yaw angles: R = Rz(rz)·Ry(ry)·Rx(rx).

    This is the convention of Reg Willson's Tsai calibration code (r1..r9 in its README).
    """
    return rot_z(rz) @ rot_y(ry) @ rot_x(rx)


def rpy_from_matrix_willson(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`rpy_willson` (valid away from ry = ±90°)."""
    ry = float(np.arcsin(np.clip(-R[2, 0], -1.0, 1.0)))
    rx = float(np.arctan2(R[2, 1], R[2, 2]))
    rz = float(np.arctan2(R[1, 0], R[0, 0]))
    return rx, ry, rz


def rotvec_to_matrix(rv) -> np.ndarray:
    """Rodrigues: axis-angle vector (rad) to rotation matrix."""
    rv = np.asarray(rv, dtype=float).reshape(3)
    th = float(np.linalg.norm(rv))
    if th < 1e-15:
        return np.eye(3)
    k = rv / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * (K @ K)


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix to axis-angle vector (rad), stable near 0 and π."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def rotation_angle(R: np.ndarray) -> float:
    """Angle (rad) of the rotation ``R``, e.g. the error between two rotations ``Ra.T @ Rb``."""
    c = (np.trace(R) - 1.0) / 2.0
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.arctan2(s, c))  # atan2 keeps precision near 0, where arccos loses half the digits


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_w_c`` of a camera at ``eye`` whose optical axis (+z) points at ``target``.

    Camera axes follow the computer-vision convention: +z forward, +x right, +y down
    in the image. ``up`` is the world direction that should appear towards -y.
    """
    eye = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=float)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.column_stack([x, y, z]), eye)


def orthonormalize(R: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (SVD), for cleaning accumulated round-off."""
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.linalg.det(U @ Vt)])
    return U @ D @ Vt
