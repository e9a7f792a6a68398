"""Task-space quintic segments (paper §4.3: "time-optimal task-space quintic polynomials").

A segment joins two full kinematic states ``(p, v, a)`` in 3D over a duration ``T``:
``p(u) = Σ b_k u^k`` with normalised time ``u = τ/T ∈ [0, 1]``, so velocity is ``p'(u)/T`` and
acceleration ``p''(u)/T²``. The six coefficients per axis are the unique quintic meeting the six
boundary conditions (Croft, Fenton & Benhabib 1995 use the same form for interception). An
optional orientation part interpolates ``R(u) = R0·exp([r(u)]×)`` with ``r`` a quintic of the same
form, from the start's body angular velocity/acceleration to rest at the target rotation.
Units: mm, s, rad; world frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np

from .rotation import exp_so3, right_jacobian

_POW = np.arange(6)


def quintic_coefficients(p0, v0, a0, p1, v1, a1, T) -> np.ndarray:
    """Normalised-time coefficients ``b`` (..., 6, D) of the quintic joining two states in time ``T``.

    Inputs broadcast: states (..., D), ``T`` (...). ``p(u) = Σ_k b[..., k, :] u^k``.
    """
    T = np.asarray(T, dtype=float)[..., None]
    p0, v0, a0, p1, v1, a1 = (np.asarray(x, dtype=float) for x in (p0, v0, a0, p1, v1, a1))
    dp = p1 - p0
    V0, V1 = v0 * T, v1 * T
    A0, A1 = a0 * T * T, a1 * T * T
    shape = np.broadcast_shapes(dp.shape, V0.shape, V1.shape, A0.shape, A1.shape)
    b = np.empty(shape[:-1] + (6, shape[-1]))
    b[..., 0, :] = p0
    b[..., 1, :] = V0
    b[..., 2, :] = 0.5 * A0
    b[..., 3, :] = 10 * dp - 6 * V0 - 4 * V1 - 1.5 * A0 + 0.5 * A1
    b[..., 4, :] = -15 * dp + 8 * V0 + 7 * V1 + 1.5 * A0 - A1
    b[..., 5, :] = 6 * dp - 3 * V0 - 3 * V1 - 0.5 * A0 + 0.5 * A1
    return b


def basis(u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows of u^k, d/du and d²/du² of u^k (k = 0..5) at normalised times ``u`` (S,): three (S, 6)."""
    u = np.atleast_1d(np.asarray(u, dtype=float))[:, None]
    k = _POW[None, :]
    Bp = u**k
    Bv = k * np.where(k >= 1, u ** np.maximum(k - 1, 0), 0.0)
    Ba = k * (k - 1) * np.where(k >= 2, u ** np.maximum(k - 2, 0), 0.0)
    return Bp, Bv, Ba


def _horner(c: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Evaluate column polynomials ``c`` (n, D) at points ``u`` (D, M) → (D, M)."""
    out = np.broadcast_to(c[-1][:, None], u.shape).copy()
    for k in range(c.shape[0] - 2, -1, -1):
        out = out * u + c[k][:, None]
    return out


def _poly_range(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact per-column (min, max) over u ∈ [0, 1] of polynomials ``c`` (n, D), ascending coefficients.

    Candidates are the end points and the real roots of the derivative in (0, 1), found for all
    columns at once from the eigenvalues of their companion matrices; a column whose derivative's
    leading coefficient vanishes (lower degree) is handled by ``np.roots``.
    """
    c = np.asarray(c, dtype=float)
    n, D = c.shape
    ends = _horner(c, np.tile([0.0, 1.0], (D, 1)))
    lo, hi = ends.min(axis=1), ends.max(axis=1)
    if n <= 2:
        return lo, hi
    d = _derivative(c)
    deg = n - 2
    lead = d[-1]
    regular = np.abs(lead) > 1e-12 * np.max(np.abs(d), axis=0)
    if np.any(regular):
        cols = np.flatnonzero(regular)
        comp = np.zeros((len(cols), deg, deg))
        comp[:, 0, :] = -(d[-2::-1, cols] / lead[cols]).T
        if deg > 1:
            comp[:, np.arange(1, deg), np.arange(deg - 1)] = 1.0
        eig = np.linalg.eigvals(comp) if deg > 1 else comp[:, :, 0]
        ur = eig.real
        valid = (np.abs(eig.imag) <= 1e-7 * (1 + np.abs(ur))) & (ur > 0.0) & (ur < 1.0)
        vals = _horner(c[:, cols], np.where(valid, ur, 0.0))
        lo[cols] = np.minimum(lo[cols], np.where(valid, vals, np.inf).min(axis=1))
        hi[cols] = np.maximum(hi[cols], np.where(valid, vals, -np.inf).max(axis=1))
    for col in np.flatnonzero(~regular):
        if np.any(d[:, col] != 0.0):
            r = np.roots(d[::-1, col])
            r = r.real[(np.abs(r.imag) <= 1e-7 * (1 + np.abs(r.real))) & (r.real > 0) & (r.real < 1)]
            if r.size:
                vals = np.polyval(c[::-1, col], r)
                lo[col], hi[col] = min(lo[col], vals.min()), max(hi[col], vals.max())
    return lo, hi


def _abs_max(c: np.ndarray) -> float:
    """max over columns and u ∈ [0, 1] of |polynomial|, exact."""
    lo, hi = _poly_range(c)
    return float(max(np.max(-lo), np.max(hi)))


def _norm_max(c: np.ndarray) -> float:
    """max over u ∈ [0, 1] of the Euclidean norm of the vector polynomial ``c`` (n, D), exact:
    the extrema of ‖c(u)‖² (a polynomial of degree 2n − 2) from its critical points."""
    sq = np.zeros(2 * c.shape[0] - 1)
    for d in range(c.shape[1]):
        sq += np.convolve(c[:, d], c[:, d])
    return float(np.sqrt(max(_abs_max(sq[:, None]), 0.0)))


def _derivative(b: np.ndarray) -> np.ndarray:
    """Ascending coefficients (n, D) → coefficients of d/du, (n-1, D)."""
    return b[1:] * np.arange(1, b.shape[0])[:, None]


_DENSE = 257
_H2_8 = (1.0 / (_DENSE - 1)) ** 2 / 8.0  # h²/8: max overshoot of a smooth f between samples per unit |f''|
_DENSE_BASIS = np.vstack(basis(np.linspace(0.0, 1.0, _DENSE)))


def _abs_coeff_sum(c: np.ndarray) -> np.ndarray:
    """Per-column Σ|c_k|: an upper bound of |Σ c_k u^k| on [0, 1]."""
    return np.abs(c).sum(axis=0)


class LimitBounds(TypedDict):
    """:meth:`QuinticSegment.limit_bounds`: the position box (mm, per axis) and the speed, acceleration and
    rotation-rate maxima."""

    p_min: np.ndarray  # (3,) mm
    p_max: np.ndarray  # (3,) mm
    v: float  # mm/s
    a: float  # mm/s²
    w: float  # rad/s


@dataclass(frozen=True)
class QuinticSegment:
    """One quintic from ``(p0, v0, a0)`` at ``t0`` to ``(p1, v1, a1)`` at ``t0 + duration`` (mm, s).

    Orientation (optional): start rotation ``R0`` (world ← tool), target rotation ``R1`` reached at
    rest, starting with body angular velocity ``w0`` (rad/s) and acceleration ``dw0`` (rad/s²).
    """

    t0: float
    duration: float
    p0: np.ndarray
    v0: np.ndarray
    a0: np.ndarray
    p1: np.ndarray
    v1: np.ndarray
    a1: np.ndarray
    R0: np.ndarray | None = None
    R1: np.ndarray | None = None
    w0: np.ndarray | None = None
    dw0: np.ndarray | None = None
    coeffs: np.ndarray = field(init=False, repr=False)
    rot_coeffs: np.ndarray | None = field(init=False, repr=False, default=None)

    def __post_init__(self):
        for name in ("p0", "v0", "a0", "p1", "v1", "a1"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=float).reshape(3))
        object.__setattr__(self, "t0", float(self.t0))
        object.__setattr__(self, "duration", float(self.duration))
        b = quintic_coefficients(self.p0, self.v0, self.a0, self.p1, self.v1, self.a1, self.duration)
        object.__setattr__(self, "coeffs", b)
        if self.R0 is not None:
            from .rotation import log_so3

            R0 = np.asarray(self.R0, dtype=float)
            R1 = R0 if self.R1 is None else np.asarray(self.R1, dtype=float)
            w0 = np.zeros(3) if self.w0 is None else np.asarray(self.w0, dtype=float).reshape(3)
            dw0 = np.zeros(3) if self.dw0 is None else np.asarray(self.dw0, dtype=float).reshape(3)
            object.__setattr__(self, "R0", R0)
            object.__setattr__(self, "R1", R1)
            object.__setattr__(self, "w0", w0)
            object.__setattr__(self, "dw0", dw0)
            r1 = log_so3(R0.T @ R1)
            rc = quintic_coefficients(np.zeros(3), w0, dw0, r1, np.zeros(3), np.zeros(3), self.duration)
            object.__setattr__(self, "rot_coeffs", rc)

    @property
    def t1(self) -> float:
        """End time (s)."""
        return self.t0 + self.duration

    def _u(self, t) -> float:
        if self.duration <= 0:
            return 1.0
        return float(np.clip((float(t) - self.t0) / self.duration, 0.0, 1.0))

    def state(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (mm), velocity (mm/s), acceleration (mm/s²) at time ``t`` (clamped to the segment)."""
        Bp, Bv, Ba = basis([self._u(t)])
        T = self.duration
        return (Bp @ self.coeffs)[0], (Bv @ self.coeffs)[0] / T, (Ba @ self.coeffs)[0] / (T * T)

    def orientation(self, t) -> np.ndarray | None:
        """Rotation (world ← tool) at ``t``; None if the segment carries no orientation."""
        if self.rot_coeffs is None:
            return None
        Bp, _, _ = basis([self._u(t)])
        return self.R0 @ exp_so3((Bp @ self.rot_coeffs)[0])

    def angular_velocity(self, t) -> np.ndarray | None:
        """Body-frame angular velocity (rad/s) at ``t``; None without orientation."""
        if self.rot_coeffs is None:
            return None
        Bp, Bv, _ = basis([self._u(t)])
        r = (Bp @ self.rot_coeffs)[0]
        return right_jacobian(r) @ ((Bv @ self.rot_coeffs)[0] / self.duration)

    def max_speed(self) -> float:
        """Largest speed ‖v‖ over the segment (mm/s), exact (critical points of ‖p'(u)‖²)."""
        return _norm_max(_derivative(self.coeffs)) / self.duration

    def max_accel(self) -> float:
        """Largest acceleration ‖a‖ over the segment (mm/s²), exact."""
        return _norm_max(_derivative(_derivative(self.coeffs))) / self.duration**2

    def position_range(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-axis (min, max) position over the segment (mm), exact."""
        return _poly_range(self.coeffs)

    def limit_bounds(self) -> LimitBounds:
        """Rigorous upper bounds for the safety check, from 257 samples plus a curvature bound.

        Between samples ``h`` apart, a polynomial's extremum exceeds the best sample by at most
        ``h²/8 · max|f''|`` and ``max|f''| ≤ Σ|coefficients of f''|`` on [0, 1]; so these bounds
        never under-estimate (they over-estimate by ~1e-4 relative). Keys: ``p_min``, ``p_max``
        (mm, per axis), ``v`` (mm/s) and ``a`` (mm/s²) maxima of the vector norms, ``w`` (rad/s) rotation rate.
        """
        T = self.duration
        b = self.coeffs
        X = _DENSE_BASIS @ b
        n = _DENSE
        d2 = _derivative(_derivative(b))
        d3 = _derivative(d2)
        d4 = _derivative(d3)
        p_slack = _H2_8 * _abs_coeff_sum(d2)
        out: LimitBounds = {
            "p_min": X[:n].min(axis=0) - p_slack,
            "p_max": X[:n].max(axis=0) + p_slack,
            # ‖f‖ between samples ≤ the larger end sample's norm + h²/8·‖(max|f_d''|)_d‖
            "v": float(np.linalg.norm(X[n : 2 * n], axis=1).max() + _H2_8 * np.linalg.norm(_abs_coeff_sum(d3))) / T,
            "a": float(np.linalg.norm(X[2 * n :], axis=1).max() + _H2_8 * np.linalg.norm(_abs_coeff_sum(d4))) / (T * T),
            "w": 0.0,
        }
        out["w"] = self.max_rotation_rate()  # exact (critical points of |dr/du|²)
        return out

    def max_rotation_rate(self) -> float:
        """Upper bound on the angular speed (rad/s): max |dr/dt|, which is ≥ |ω| since ‖J_r‖ ≤ 1.

        Exact (critical points of |dr/du|²); 0 without orientation.
        """
        if self.rot_coeffs is None:
            return 0.0
        return _norm_max(_derivative(self.rot_coeffs)) / self.duration


@dataclass(frozen=True)
class Trajectory:
    """Consecutive quintic segments; ``state(t)`` clamps to the first/last segment outside its span."""

    segments: tuple[QuinticSegment, ...]

    def __post_init__(self):
        object.__setattr__(self, "segments", tuple(self.segments))
        if not self.segments:
            raise ValueError("a trajectory needs at least one segment")

    @property
    def t_start(self) -> float:
        """Start time (s) of the first segment."""
        return self.segments[0].t0

    @property
    def t_end(self) -> float:
        """End time (s) of the last segment."""
        return self.segments[-1].t1

    def segment_at(self, t) -> QuinticSegment:
        """The segment active at ``t`` (the first one before it starts, the last one after it ends)."""
        for seg in self.segments:
            if t < seg.t1:
                return seg
        return self.segments[-1]

    def state(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration (mm, mm/s, mm/s²) at ``t``."""
        return self.segment_at(t).state(t)

    def orientation(self, t) -> np.ndarray | None:
        """Tool rotation at ``t`` (holding the last one defined), or None if no segment carries one."""
        seg = self.segment_at(t)
        if seg.rot_coeffs is not None:
            return seg.orientation(t)
        for s in reversed(self.segments):
            if s.rot_coeffs is not None and s.t1 <= t:
                return s.R1
        return None


def rest_to_rest_times(p0, p1, v_max: float, a_max: float) -> tuple[float, float]:
    """Minimum durations (s) of a straight rest-to-rest move from ``p0`` to ``p1`` (mm) under speed
    ``v_max`` (mm/s) and acceleration ``a_max`` (mm/s²), with no margin: (any profile — bang-bang or
    trapezoidal, the physical lower bound; the paper's quintic, whose peak speed is 1.875·D/T and
    peak acceleration 10/√3·D/T²). Paper §4.3: the lower bounds a run's time to identity is held to."""
    d = float(np.linalg.norm(np.asarray(p1, dtype=float) - np.asarray(p0, dtype=float)))
    any_profile = 2 * math.sqrt(d / a_max) if d < v_max * v_max / a_max else d / v_max + v_max / a_max
    return any_profile, max(1.875 * d / v_max, math.sqrt(10 / math.sqrt(3) * d / a_max))
