"""The last gate before a segment leaves the planner (docs/architecture.md "Frames and units").

Every segment the planners return has passed :func:`check_segment`: its whole position range
inside the workspace box, and its speed, acceleration (Euclidean norms) and rotation rate within
the limits. First rigorous upper bounds (dense samples plus the largest possible overshoot
between samples, :meth:`QuinticSegment.limit_bounds`); where a bound touches a limit, the exact
maxima from the polynomial's critical points decide. A violation is never missed.

Stops stay inside (docs/protocols/robot.md §Stopping): the robot controller brakes
each axis on its own at ``a_stop = a_max/√3`` (so ‖a‖ ≤ a_max while braking), so from a state
(x, v) an axis comes to rest at ``x + v|v|/(2 a_stop)``. :func:`stop_envelope_range` gives the
exact range of that rest point over a whole quintic; a segment is safe only if it lies in the
box too, so a STOP (or the watchdog) at any instant of the segment ends inside the box.
"""

from __future__ import annotations

import numpy as np

from .limits import Limits, LimitViolation
from .quintic import QuinticSegment, Trajectory, _derivative, _horner

REL_TOL = 1e-6  # relative slack on v/a/ω limits: round-off of states spliced right at a limit


def stop_point(p, v, a_stop: float) -> np.ndarray:
    """Where each axis comes to rest braking from position ``p`` (mm) and velocity ``v`` (mm/s) at
    ``a_stop`` (mm/s², per axis, constant deceleration): ``p + v|v|/(2 a_stop)``."""
    v = np.asarray(v, dtype=float)
    return np.asarray(p, dtype=float) + v * np.abs(v) / (2.0 * float(a_stop))


def _unit_roots(c: np.ndarray) -> list[float]:
    """Real parts in [0, 1] of the roots of the polynomial with ascending coefficients ``c``; leading
    coefficients below 1e-12 of the largest are dropped (they only move roots far outside [0, 1])."""
    scale = float(np.max(np.abs(c))) if c.size else 0.0
    if scale == 0.0:
        return []
    desc = np.asarray(c, dtype=float)[::-1]
    keep = np.flatnonzero(np.abs(desc) > 1e-12 * scale)
    if keep.size == 0:
        return []
    desc = desc[keep[0]:]
    if len(desc) < 2:
        return []
    r = np.roots(desc).real
    return r[(r >= 0.0) & (r <= 1.0)].tolist()


def stop_envelope_range(b: np.ndarray, T: float, a_stop: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact per-axis (min, max) over the segment of the braking rest point ``e = x + v|v|/(2 a_stop)``.

    ``b`` (6, 3): normalised-time coefficients (``x(u) = Σ b_k u^k``, u = τ/T, T in s). ``e`` is C¹
    with ``de/dτ = |v|·(sign v + a/a_stop)``, so its extrema lie at u = 0, 1, the roots of v (a
    quartic: there e = x) and the roots of a = ∓a_stop (cubics). All roots come from ``np.roots``;
    every real part in [0, 1] is a candidate (a spurious one can only be a point of the segment,
    so the range is never over- or under-stated). Units mm, s.
    """
    b = np.asarray(b, dtype=float)
    d1 = _derivative(b)
    d2 = _derivative(d1)
    lo = np.empty(b.shape[1])
    hi = np.empty(b.shape[1])
    aT2 = float(a_stop) * T * T
    for ax in range(b.shape[1]):
        cands = [0.0, 1.0]
        for poly in (d1[:, ax], d2[:, ax] + np.array([aT2, 0, 0, 0])[: d2.shape[0]],
                     d2[:, ax] - np.array([aT2, 0, 0, 0])[: d2.shape[0]]):
            cands.extend(_unit_roots(poly))
        u = np.asarray(cands)[None, :]
        x = _horner(b[:, ax:ax + 1], u)[0]
        v = _horner(d1[:, ax:ax + 1], u)[0] / T
        e = x + v * np.abs(v) / (2.0 * float(a_stop))
        lo[ax], hi[ax] = e.min(), e.max()
    return lo, hi


def check_segment(seg: QuinticSegment, limits: Limits, tol_mm: float = 1e-6) -> QuinticSegment:
    """Return ``seg`` if it respects ``limits``; raise :class:`LimitViolation` naming the first breach."""
    values = np.concatenate([seg.p0, seg.v0, seg.a0, seg.p1, seg.v1, seg.a1, [seg.t0, seg.duration]])
    if not np.all(np.isfinite(values)) or seg.duration <= 0:
        raise LimitViolation("invalid", float(seg.duration), 0.0, "non-finite state or non-positive duration")
    bounds = seg.limit_bounds()
    lo, hi = bounds["p_min"], bounds["p_max"]
    if np.any(lo < limits.box_min - tol_mm) or np.any(hi > limits.box_max + tol_mm):
        lo, hi = seg.position_range()  # the bound is a hair loose: decide exactly
    below = limits.box_min - tol_mm - lo
    above = hi - (limits.box_max + tol_mm)
    if np.any(below > 0) or np.any(above > 0):
        axis = int(np.argmax(np.maximum(below, above)))
        bad = lo[axis] if below[axis] > above[axis] else hi[axis]
        bound = limits.box_min[axis] if below[axis] > above[axis] else limits.box_max[axis]
        raise LimitViolation("box", bad, bound, f"axis {'xyz'[axis]}")
    elo, ehi = stop_envelope_range(seg.coeffs, seg.duration, limits.a_stop)
    # a start state that already brakes to outside the box is not the segment's fault: it may not
    # make that worse (grown box), and its end must brake to rest inside the box itself
    e0 = stop_point(seg.p0, seg.v0, limits.a_stop)
    e1 = stop_point(seg.p1, seg.v1, limits.a_stop)
    grown_min, grown_max = np.minimum(limits.box_min, e0), np.maximum(limits.box_max, e0)
    below = np.maximum(grown_min - tol_mm - elo, limits.box_min - tol_mm - e1)
    above = np.maximum(ehi - (grown_max + tol_mm), e1 - (limits.box_max + tol_mm))
    if np.any(below > 0) or np.any(above > 0):
        axis = int(np.argmax(np.maximum(below, above)))
        bad = elo[axis] if below[axis] > above[axis] else ehi[axis]
        bound = limits.box_min[axis] if below[axis] > above[axis] else limits.box_max[axis]
        raise LimitViolation("stop", bad, bound, f"a stop on axis {'xyz'[axis]} would end outside")
    v = bounds["v"]
    if v > limits.v_max:
        v = seg.max_speed()
    if v > limits.v_max * (1 + REL_TOL) + 1e-9:
        raise LimitViolation("velocity", v, limits.v_max)
    a = bounds["a"]
    if a > limits.a_max:
        a = seg.max_accel()
    if a > limits.a_max * (1 + REL_TOL) + 1e-9:
        raise LimitViolation("acceleration", a, limits.a_max)
    w = bounds["w"]
    if w > limits.w_max * (1 + REL_TOL) + 1e-12:
        raise LimitViolation("angular_velocity", w, limits.w_max)
    return seg


def check_trajectory(traj: Trajectory, limits: Limits) -> Trajectory:
    """:func:`check_segment` on every segment, and continuity of p, v, a at every joint."""
    for seg in traj.segments:
        check_segment(seg, limits)
    for a, b in zip(traj.segments, traj.segments[1:]):
        joined = np.allclose(a.p1, b.p0, atol=1e-6) and np.allclose(a.v1, b.v0, atol=1e-6)
        if abs(a.t1 - b.t0) > 1e-9 or not (joined and np.allclose(a.a1, b.a0, atol=1e-5)):
            raise LimitViolation("invalid", b.t0, a.t1, "segments do not join continuously")
    return traj
