"""Kinematic motion models for the marker on the table plane, with exact variable-dt matrices.

The paper (§4.2, after its ref. [13]) tracks the marker's 2D position with a recursive Kalman
filter and extrapolates it for multi-step-ahead predictions. Here each axis of the table plane
follows a continuous-time kinematic chain driven by white noise on its highest derivative, so
the transition ``F(dt)`` and the process covariance ``Q(dt)`` are exact for any ``dt`` (dropped
frames, irregular frame times, and predictions far ahead all use the same formulas;
Bar-Shalom, Li & Kirubarajan 2001, §6.2).

State layout (filterpy's ``order_by_dim`` layout): ``[x, vx, y, vy]`` for constant velocity and
``[x, vx, ax, y, vy, ay]`` for constant acceleration. Units: mm, s.
"""

from __future__ import annotations

import numpy as np


def axis_transition(order: int, dt: float) -> np.ndarray:
    """Per-axis transition over ``dt`` seconds of a kinematic chain of ``order`` (1 = CV, 2 = CA)."""
    if order == 1:
        return np.array([[1.0, dt], [0.0, 1.0]])
    if order == 2:
        return np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    raise ValueError(f"order must be 1 or 2, got {order}")


def axis_process_noise(order: int, dt: float, q: float) -> np.ndarray:
    """Per-axis exact covariance over ``dt`` of continuous white noise of spectral density ``q``.

    ``order`` 1: white acceleration (q in mm²/s³); ``order`` 2: white jerk (q in mm²/s⁵).
    """
    if order == 1:
        return q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    if order == 2:
        return q * np.array(
            [
                [dt**5 / 20, dt**4 / 8, dt**3 / 6],
                [dt**4 / 8, dt**3 / 3, dt**2 / 2],
                [dt**3 / 6, dt**2 / 2, dt],
            ]
        )
    raise ValueError(f"order must be 1 or 2, got {order}")


def plane_matrices(order: int, dt: float, q: float, embed_in_ca: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(F, Q)`` for both table axes.

    With ``embed_in_ca`` a constant-velocity model is written in the 6-D constant-acceleration
    state (acceleration forced to zero), so that an IMM can mix it with the CA model.
    """
    F1 = axis_transition(order, dt)
    Q1 = axis_process_noise(order, dt, q)
    if embed_in_ca and order == 1:
        F3 = np.zeros((3, 3))
        F3[:2, :2] = F1
        Q3 = np.zeros((3, 3))
        Q3[:2, :2] = Q1
        Q3[2, 2] = 1e-9  # keeps P positive definite; the acceleration is pinned to zero by F
        F1, Q1 = F3, Q3
    return _two_blocks(F1), _two_blocks(Q1)


def _two_blocks(A: np.ndarray) -> np.ndarray:
    n = A.shape[0]
    out = np.zeros((2 * n, 2 * n))
    out[:n, :n] = A
    out[n:, n:] = A
    return out


def position_matrix(dim_axis: int) -> np.ndarray:
    """Measurement matrix H picking ``(x, y)`` out of the per-axis blocks of size ``dim_axis``.

    Built by hand: filterpy 2.0.0's ``kinematic_kf`` puts a 1 in *every* position column of
    every row, so its H measures ``x + y`` (pinned in tests/test_tracking_filterpy_pitfalls.py).
    """
    H = np.zeros((2, 2 * dim_axis))
    H[0, 0] = 1.0
    H[1, dim_axis] = 1.0
    return H
