"""SO(3) helpers for the orientation part of a segment: exp/log and the right Jacobian.

A segment's orientation is ``R(u) = R0 · exp([r(u)]×)`` with ``r`` a quintic in normalised time
(same boundary-condition form as the position quintic, paper §4.3). The body angular velocity
is ``J_r(r) · dr/dt``; since every singular value of ``J_r`` is ≤ 1, ``|dr/dt|`` bounds the
angular speed from above, which is what the planner checks against ``w_max``. Radians.
"""

from __future__ import annotations

import numpy as np

_I3 = np.eye(3)
_I3.setflags(write=False)  # only ever added to: a new array each time


def hat(w) -> np.ndarray:
    """Skew-symmetric matrix of ``w`` (3,)."""
    x, y, z = np.asarray(w, dtype=float).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def exp_so3(r) -> np.ndarray:
    """Rotation matrix of the rotation vector ``r`` (rad), Rodrigues' formula."""
    r = np.asarray(r, dtype=float).reshape(3)
    th = float(np.linalg.norm(r))
    K = hat(r)
    if th < 1e-8:
        return _I3 + K + 0.5 * K @ K
    return _I3 + (np.sin(th) / th) * K + ((1 - np.cos(th)) / th**2) * (K @ K)


def log_so3(R) -> np.ndarray:
    """Rotation vector (rad) of the rotation matrix ``R``, stable near 0 and π."""
    R = np.asarray(R, dtype=float)
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    th = float(np.arccos(c))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-6:
        return 0.5 * w
    if th < np.pi - 1e-3:
        return (th / (2.0 * np.sin(th))) * w
    from scipy.spatial.transform import Rotation  # near π: the skew part vanishes

    return Rotation.from_matrix(R).as_rotvec()


def right_jacobian(r) -> np.ndarray:
    """``J_r(r)`` with ``ω_body = J_r(r) · ṙ`` for ``R = R0 · exp([r]×)``."""
    r = np.asarray(r, dtype=float).reshape(3)
    th = float(np.linalg.norm(r))
    K = hat(r)
    if th < 1e-6:
        return _I3 - 0.5 * K + (K @ K) / 6.0
    return _I3 - ((1 - np.cos(th)) / th**2) * K + ((th - np.sin(th)) / th**3) * (K @ K)
