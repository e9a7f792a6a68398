"""An honest lower bound on a run's time to identity (paper §4.3, §5.3).

No run can identify the object sooner than

    first sight of the marker (s after the run's start)
  + the minimum time of every leg the robot actually flew, under the controller's own limits
  + one mobile-camera frame time per image taken (an image is exposed and read out at rest).

A leg is the move from the state the robot was in when the leg was commanded to the state it took
the image in. Its minimum time is the larger of

* translation: the time-optimal jerk-limited 1-D profile (ruckig) over the straight distance, with
  the start and end velocity and acceleration projected on that line, under ``v_max``, ``a_max``
  and ``j_max``. Projecting any admissible 3-D motion on the line gives an admissible 1-D motion
  (``|u·v| ≤ ‖v‖`` and likewise for a and jerk), so this is a true lower bound for the controller's
  Euclidean-norm limits (docs/protocols/robot.md), whatever profile the robot runs;
* rotation: the geodesic angle between the two orientations over ``w_max`` (‖ω‖ bounds the
  angle's rate).

No tracking allowance: planning may start on the first sighting, so the time spent tracking
before the robot moves counts against the run, not in the bound. Jerk: a leg flown wholly with
ruckig segments is bound by the controller's ``jmax`` (``Leg.j_max``); a leg with any quintic
segment has no jerk limit (the reference controller checks quintics against v and a only), and
then the bound is the bang-bang / trapezoidal time.

An arm (the lab's robot file names one): the leg's least time is also at least the joints' own,
``max_i |q1_i − q0_i| / q̇max_i`` between the configurations the arm had at the leg's start and at its
image (``Leg.q0``, ``Leg.q1``, rad; ``qd_max`` rad/s): no joint moves faster than its data-sheet speed,
whatever the path.
Units: mm, s, rad; world frame.
Functional core: numbers in, numbers out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Leg:
    """One move the robot flew before an image: start and end state (mm, mm/s, mm/s²), orientation
    (3×3 world ← flange; None: not known) and the jerk limit it was flown under (mm/s³: a ruckig leg
    under the controller's ``jmax``; None: no jerk limit binds it, as for the paper's quintics)."""

    kind: str
    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    v0: tuple[float, float, float] = (0.0, 0.0, 0.0)
    a0: tuple[float, float, float] = (0.0, 0.0, 0.0)
    v1: tuple[float, float, float] = (0.0, 0.0, 0.0)
    a1: tuple[float, float, float] = (0.0, 0.0, 0.0)
    R0: np.ndarray | None = None
    R1: np.ndarray | None = None
    j_max: float | None = None
    q0: tuple[float, ...] | None = None  # the arm's configuration at the start and at the image (rad; None: no arm)
    q1: tuple[float, ...] | None = None


def min_line_time(d_mm: float, v0: float, a0: float, v1: float, a1: float, v_max: float, a_max: float,
                  j_max: float | None = None) -> float:
    """Time-optimal duration (s) of a 1-D move over ``d_mm`` from (v0, a0) to (v1, a1) under |v| ≤ v_max
    (mm/s), |a| ≤ a_max (mm/s²), |jerk| ≤ j_max (mm/s³; None: unlimited), by ruckig (Berscheid & Kröger 2021)."""
    from ruckig import InputParameter, Result, Ruckig, Trajectory

    clip = lambda x, m: float(min(max(x, -m), m))  # noqa: E731 — projected states never exceed the limits
    otg, inp, traj = Ruckig(1), InputParameter(1), Trajectory(1)
    inp.current_position, inp.target_position = [0.0], [float(d_mm)]
    inp.current_velocity, inp.target_velocity = [clip(v0, v_max)], [clip(v1, v_max)]
    inp.current_acceleration, inp.target_acceleration = [clip(a0, a_max)], [clip(a1, a_max)]
    inp.max_velocity, inp.max_acceleration = [float(v_max)], [float(a_max)]
    inp.max_jerk = [float(j_max) if j_max is not None else math.inf]
    if otg.calculate(inp, traj) not in (Result.Working, Result.Finished):
        raise ValueError(f"ruckig found no profile for d={d_mm} mm, v0={v0}, v1={v1}")
    return float(traj.duration)


def rotation_angle(R0: np.ndarray, R1: np.ndarray) -> float:
    """Geodesic angle (rad) between two rotation matrices."""
    c = (float(np.trace(np.asarray(R0).T @ np.asarray(R1))) - 1.0) / 2.0
    return float(np.arccos(min(1.0, max(-1.0, c))))


def leg_min_time(leg: Leg, v_max: float, a_max: float, w_max: float | None = None,
                 qd_max: tuple[float, ...] | None = None) -> float:
    """Lower bound (s) of the time any profile within the limits needs for ``leg`` (module docstring); with
    ``qd_max`` (rad/s per joint) and the leg's configurations, also the joints' least time."""
    p0, p1 = np.asarray(leg.p0, float), np.asarray(leg.p1, float)
    d = float(np.linalg.norm(p1 - p0))
    if d > 1e-9:
        u = (p1 - p0) / d
        t = min_line_time(d, float(u @ np.asarray(leg.v0, float)), float(u @ np.asarray(leg.a0, float)),
                          float(u @ np.asarray(leg.v1, float)), float(u @ np.asarray(leg.a1, float)),
                          v_max, a_max, leg.j_max)
    else:
        t = 0.0
    if w_max is not None and leg.R0 is not None and leg.R1 is not None:
        t = max(t, rotation_angle(leg.R0, leg.R1) / w_max)
    if qd_max is not None and leg.q0 is not None and leg.q1 is not None:
        dq = np.abs(np.asarray(leg.q1, float) - np.asarray(leg.q0, float))
        t = max(t, float(np.max(dq / np.asarray(qd_max, float))))
    return t


def identity_bound(first_sight_s: float, legs: list[Leg], n_images: int, frame_period_s: float, *,
                   v_max: float, a_max: float, w_max: float | None = None,
                   qd_max: tuple[float, ...] | None = None) -> dict:
    """The lower bound (s) and its parts: ``first_sight_s`` (s after the run's start), the legs' minimum
    times (with ``qd_max``, rad/s: the arm's joints' too), ``n_images`` mobile frames of ``frame_period_s`` each."""
    legs_s = [leg_min_time(leg, v_max, a_max, w_max, qd_max) for leg in legs]
    frames_s = n_images * frame_period_s
    return {"bound_s": first_sight_s + sum(legs_s) + frames_s, "first_sight_s": first_sight_s,
            "legs_s": legs_s, "frames_s": frames_s}
