"""The last gate before a segment leaves the planner (DESIGN §3, issue 6 "Safety").

Every segment the planners return has passed :func:`check_segment`: its whole position range
inside the workspace box, and its speed, acceleration (Euclidean norms) and rotation rate within
the limits. First rigorous upper bounds (dense samples plus the largest possible overshoot
between samples, :meth:`QuinticSegment.limit_bounds`); where a bound touches a limit, the exact
maxima from the polynomial's critical points decide. A violation is never missed.
"""

from __future__ import annotations

import numpy as np

from .limits import Limits, LimitViolation
from .quintic import QuinticSegment, Trajectory

REL_TOL = 1e-6  # relative slack on v/a/ω limits: round-off of states spliced right at a limit


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
