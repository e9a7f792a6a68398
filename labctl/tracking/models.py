"""Kinematic motion models for the marker on the table plane, with exact variable-dt matrices.

The paper (§4.2, after its ref. [13]) tracks the marker's 2D position with a recursive Kalman
filter and extrapolates it for multi-step-ahead predictions. Here each axis of the table plane
follows a continuous-time kinematic chain driven by white noise on its highest derivative, so
the transition ``F(dt)`` and the process covariance ``Q(dt)`` are exact for any ``dt`` (dropped
frames, irregular frame times, and predictions far ahead all use the same formulas;
Bar-Shalom, Li & Kirubarajan 2001, §6.2).

State layout (filterpy's ``order_by_dim`` layout): ``[x, vx, y, vy]`` for constant velocity and
``[x, vx, ax, y, vy, ay]`` for constant acceleration; the coordinated-turn model and the IMM's
modes share ``[x, vx, y, vy, κ]`` (κ the path curvature, 1/mm, so the turn rate is κ·|v|;
Bar-Shalom et al. §11.7). Units: mm, s, rad.
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


# -- the 5-D state shared by the IMM's modes: [x, vx, y, vy, κ] (κ: path curvature, 1/mm) -------------

TURN_DIM = 5


def turn_transition(x, dt: float) -> np.ndarray:
    """Coordinated-turn mean propagation of ``x = [x, vx, y, vy, κ]`` over ``dt`` s (constant speed and curvature).

    Bar-Shalom, Li & Kirubarajan 2001, §11.7.2, with the turn rate written as ``ω = κ·|v|``: the
    velocity rotates by ``ω dt``, the position moves along the circle of radius ``1/κ``; exact
    (series) as ``ω → 0``, where it is the constant-velocity motion. The curvature, unlike ω,
    does not depend on the speed, so one prior on it (the table's tightest radius) fits every speed.
    """
    x = np.asarray(x, dtype=float).reshape(-1)
    vx, vy = x[1], x[3]
    w = x[4] * np.hypot(vx, vy)
    wt = w * dt
    if abs(wt) < 1e-4:
        s_over = dt * (1.0 - wt**2 / 6.0)  # sin(ω dt)/ω
        c_over = dt * (wt / 2.0 - wt**3 / 24.0)  # (1 - cos(ω dt))/ω
    else:
        s_over = np.sin(wt) / w
        c_over = (1.0 - np.cos(wt)) / w
    c, s = np.cos(wt), np.sin(wt)
    return np.array([
        x[0] + s_over * vx - c_over * vy,
        c * vx - s * vy,
        x[2] + c_over * vx + s_over * vy,
        s * vx + c * vy,
        x[4],
    ])


def turn_jacobian(x, dt: float) -> np.ndarray:
    """d turn_transition / dx (5×5) by central differences (steps scaled to each component)."""
    x = np.asarray(x, dtype=float).reshape(-1)
    J = np.zeros((5, 5))
    J[0, 0] = J[2, 2] = J[4, 4] = 1.0  # position and curvature enter linearly / unchanged
    speed = max(np.hypot(x[1], x[3]), 1e-3)
    for k, h in ((1, 1e-5 * speed), (3, 1e-5 * speed), (4, 1e-9)):
        e = np.zeros(5)
        e[k] = h
        J[:4, k] = (turn_transition(x + e, dt)[:4] - turn_transition(x - e, dt)[:4]) / (2 * h)
    return J


def turn_process_noise(dt: float, q_acc: float, q_curv: float) -> np.ndarray:
    """Q (5×5) of the 5-D state: white acceleration (density ``q_acc`` mm²/s³) on each axis and a
    random-walk curvature (density ``q_curv`` mm⁻²/s)."""
    Q = np.zeros((5, 5))
    Q1 = axis_process_noise(1, dt, q_acc)
    Q[0:2, 0:2] = Q1  # slices, not np.ix_: the same assignment, called at every frame's prediction
    Q[2:4, 2:4] = Q1
    Q[4, 4] = q_curv * dt
    return Q


def straight_transition_5d(dt: float) -> np.ndarray:
    """F (5×5) of constant-velocity motion in the 5-D state; κ is carried along unused."""
    F = np.eye(5)
    F[0, 1] = F[2, 3] = dt
    return F


def turn_positions(x, d) -> np.ndarray:
    """Positions (N, 2) mm of the coordinated turn ``x = [x, vx, y, vy, κ]`` after times ``d`` (N,) s.

    The same motion as :func:`turn_transition` (which it matches to round-off), for many times
    at once and for negative ``d`` too (the path before the state's time): what the re-linearised
    batch fit of the turn (``MarkerTracker``'s CT refit) evaluates on every frame.
    """
    x = np.asarray(x, dtype=float).reshape(-1)
    d = np.asarray(d, dtype=float)
    S, C, _, _ = _turn_sc(x[4] * np.hypot(x[1], x[3]), d, derivatives=False)
    return np.column_stack([x[0] + S * x[1] - C * x[3], x[2] + C * x[1] + S * x[3]])


def _turn_sc(w: float, d: np.ndarray, derivatives: bool = True):
    """``S = sin(w d)/w``, ``C = (1 − cos(w d))/w`` and (optionally) their w-derivatives, at every ``d``.

    Series in ``w d`` when the whole span turns by less than 1e-3 rad (the exact forms cancel there).
    """
    if abs(w) * (np.max(np.abs(d)) if d.size else 0.0) < 1e-3:
        wd = w * d
        S = d * (1.0 - wd**2 / 6.0)
        C = d * (wd / 2.0 - wd**3 / 24.0)
        if not derivatives:
            return S, C, None, None
        return S, C, -w * d**3 / 3.0 + w**3 * d**5 / 30.0, d**2 / 2.0 - w**2 * d**4 / 8.0
    sn, cs = np.sin(w * d), np.cos(w * d)
    S, C = sn / w, (1.0 - cs) / w
    if not derivatives:
        return S, C, None, None
    return S, C, (d * cs - S) / w, (d * sn - C) / w


def turn_positions_jacobian(x, d) -> np.ndarray:
    """d turn_positions(x, d) / dx, shape (N, 2, 5), analytic (series for small ω·d).

    With ``w = κ|v|``, ``S = sin(w d)/w``, ``C = (1 − cos(w d))/w``: ``p = p0 + S v + C v⊥``
    (v⊥ = (−vy, vx)), so ``∂p/∂κ = |v| (S' v + C' v⊥)`` and ``∂p/∂v = S I + C [[0, −1], [1, 0]]
    + (S' v + C' v⊥) κ vᵀ/|v|`` with ``S' = ∂S/∂w = (d cos(w d) − S)/w``, ``C' = (d sin(w d) − C)/w``.
    """
    x = np.asarray(x, dtype=float).reshape(-1)
    d = np.asarray(d, dtype=float)
    vx, vy, k = x[1], x[3], x[4]
    speed = np.hypot(vx, vy)
    S, C, dS, dC = _turn_sc(k * speed, d)
    g = np.column_stack([dS * vx - dC * vy, dS * vy + dC * vx])  # ∂p/∂w
    J = np.zeros((len(d), 2, 5))
    J[:, 0, 0] = J[:, 1, 2] = 1.0
    u = np.array([vx, vy]) / speed if speed > 0 else np.zeros(2)
    J[:, 0, 1] = S + g[:, 0] * k * u[0]
    J[:, 1, 1] = C + g[:, 1] * k * u[0]
    J[:, 0, 3] = -C + g[:, 0] * k * u[1]
    J[:, 1, 3] = S + g[:, 1] * k * u[1]
    J[:, :, 4] = g * speed
    return J
