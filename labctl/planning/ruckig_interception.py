"""Interception with one ``ruckig`` segment (robot dialect 1.2; paper §4.3, jerk-limited).

The problem of :func:`labctl.planning.interception.plan_interception` — the earliest ``t`` at
which the robot, from its state at ``t0``, arrives on the target path G(t) with G's velocity and
acceleration — solved with the segment the controller's ``ruckig`` profile runs
(:func:`labctl.planning.ruckig_profile.plan_ruckig`, the same code and inputs the controller
uses): for an arrival time ``t0 + T`` the segment to G(t0 + T) asked to last at least ``T``
is feasible when it lasts no longer than ``T`` and passes the controller's exact check
(:func:`~labctl.planning.ruckig_profile.check_ruckig`). A geometric coarse grid, bisection to
``tol_s``, then the exact check (bumping T a little, as the quintic search does, if it fails).
Re-planning from the current ruckig segment's state (p, v, a; R, ω) splices continuously: the
controller itself starts the new segment from its state. Units: mm, s, rad; world = robot base.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .interception import Interception, TargetFn, _checked_start, _unreachable_reason, end_rotation
from .limits import Limits, stop_budget_caps
from .ruckig_profile import JerkLimits, RuckigPlan, check_ruckig, controller_limits, plan_ruckig


class RuckigTrajectory:
    """A planned ruckig segment on the host's time line, with the interface the run uses of a
    :class:`labctl.planning.quintic.Trajectory` (``t_start``, ``t_end``, ``state``, ``orientation``,
    ``segments``) and of its one segment (``t0``, ``t1``, ``rot_coeffs``); ``profile`` is ``"ruckig"``."""

    profile = "ruckig"

    def __init__(self, plan: RuckigPlan, t0: float, limits: JerkLimits | None = None, base: JerkLimits | None = None):
        self.plan, self.t0, self.t1 = plan, float(t0), float(t0) + plan.duration
        self.limits, self.base = limits, base  # the segment carries ``limits.wire(base)``
        self.rot_coeffs = True  # it carries an orientation (the run reads the end pose from it)

    @property
    def t_start(self) -> float:
        """Start time (s)."""
        return self.t0

    @property
    def t_end(self) -> float:
        """Arrival time (s)."""
        return self.t1

    @property
    def segments(self) -> tuple[RuckigTrajectory]:
        """The one segment (itself)."""
        return (self,)

    def segment_at(self, t: float) -> RuckigTrajectory:
        """The segment running at ``t`` (itself)."""
        return self

    def _tau(self, t: float) -> float:
        return min(max(float(t) - self.t0, 0.0), self.plan.duration)

    def state(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (mm), velocity (mm/s), acceleration (mm/s²) at ``t`` (clamped to the segment)."""
        return self.plan.position.state(self._tau(t))

    def orientation(self, t: float) -> np.ndarray:
        """Rotation world ← flange at ``t``."""
        return self.plan.state(self._tau(t))[3]

    def angular_velocity(self, t: float) -> np.ndarray:
        """True angular velocity (rad/s, base frame) at ``t``; 0 after the end."""
        if float(t) >= self.t1:
            return np.zeros(3)
        return self.plan.state(self._tau(t))[4]


def ruckig_limits(robot_cfg, stop_budget_s: float | None = None) -> JerkLimits:
    """The limits a run's ruckig segments carry: the controller's own (:func:`controller_limits`) with the
    speed capped, with ``stop_budget_s`` (lab.yaml ``run.robot_stop_budget_s``), so that the stop ramp
    brings the arm to rest within the budget (:func:`~labctl.planning.limits.stop_budget_caps`, as for the
    quintic planner). No further margin: the controller re-plans the segment from its own state and checks it
    exactly. The turning rate stays the controller's: at the lab's 0.25 s budget its cap is ``w_max`` itself."""
    ctrl = controller_limits(robot_cfg)
    if stop_budget_s is None:
        return ctrl
    v_cap, _ = stop_budget_caps(ctrl.a_stop, ctrl.w_max, float(stop_budget_s))
    return replace(ctrl, v_max=min(ctrl.v_max, v_cap))



def _ruckig_inputs(state, G: TargetFn, limits: Limits, R0, w0, jerk: JerkLimits | None, base: JerkLimits | None):
    """The start ``(p0, v0, a0, R0, w0)`` of a checked state, the end rotation (G's, else ``R0``), the segment's
    limits as the controller runs them and the limits it checks against (its own, ``base``, when given)."""
    p0, v0, a0 = state
    R0 = np.eye(3) if R0 is None else np.asarray(R0, float)
    w0 = np.zeros(3) if w0 is None else np.asarray(w0, float).reshape(3)
    R1 = end_rotation(G)
    lim = (jerk if jerk is not None else JerkLimits.from_limits(limits)).rounded(base)
    return (p0, v0, a0, R0, w0), R0 if R1 is None else R1, lim, base if base is not None else lim

def plan_interception_ruckig(state0, t0: float, G: TargetFn, limits: Limits, horizon_s: float = 10.0, *,
                             R0=None, w0=None, jerk: JerkLimits | None = None, base: JerkLimits | None = None,
                             t_min: float = 0.02,
                             n_coarse: int = 64, tol_s: float = 1e-3) -> Interception:
    """Earliest arrival on G(t) by one controller-checked ruckig segment from ``state0 = (p, v, a)`` at ``t0``.

    ``R0`` is the flange's rotation now (world ← flange; identity if None), ``w0`` its angular
    velocity (rad/s, base frame; 0 if None); the segment ends at ``G.rotation`` (or keeps ``R0``)
    with zero angular velocity. ``jerk`` are the limits the segment will carry (``vmax amax jmax
    wmax`` on the wire; default :meth:`JerkLimits.from_limits` of ``limits``), ``base`` the
    controller's own (those equal to it are not sent): the plan uses them as the controller runs them
    (:meth:`JerkLimits.rounded`), so it is what the controller runs from the same state. Returns an
    :class:`~labctl.planning.interception.Interception` whose trajectory is a :class:`RuckigTrajectory`;
    unreachable targets come back with ``t_hit=None`` and a reason, never as an exception.
    """
    start = _checked_start(state0, t0, horizon_s, t_min, limits, G)
    if isinstance(start, Interception):
        return start
    start, R1, lim, check = _ruckig_inputs(start, G, limits, R0, w0, jerk, base)
    zero = np.zeros(3)

    def segment(T: float, g, full: bool = True) -> RuckigPlan:
        return plan_ruckig(start, g[0], R1, g[1], zero, g[2], T, lim, full=full)

    def in_time(T: float, g) -> bool:
        if np.any(g[0] < limits.box_min) or np.any(g[0] > limits.box_max):
            return False
        plan = segment(T, g, full=False)
        return plan.code == 0 and plan.duration <= T * (1 + 1e-9) + 1e-9

    def at(T: float):
        gp, gv, ga = G(np.array([t0 + T]))
        return gp[0], gv[0], ga[0]

    Ts = np.geomspace(t_min, horizon_s, n_coarse)
    gp, gv, ga = G(t0 + Ts)
    in_box = limits.contains(gp)
    prev = 0.0
    for k, T in enumerate(Ts):
        if not in_box[k] or not in_time(T, (gp[k], gv[k], ga[k])):
            prev = T
            continue
        lo, hi = prev, float(T)
        while hi - lo > tol_s:
            mid = 0.5 * (lo + hi)
            if in_time(mid, at(mid)):
                hi = mid
            else:
                lo = mid
        for bump in (0.0, 0.001, 0.004, 0.016, 0.064):  # the exact check decides
            Tb = hi * (1.0 + bump)
            plan = segment(Tb, at(Tb))
            if plan.code == 0 and plan.duration <= Tb * (1 + 1e-9) + 1e-9 and check_ruckig(plan, check) == 0:
                traj = RuckigTrajectory(plan, t0, lim, base)
                return Interception(traj.t1, traj, None, "ok", G)
        prev = T
    code, reason = _unreachable_reason(bool(in_box.any()), gp, limits, horizon_s)
    return Interception(None, None, reason.replace("quintic", "ruckig segment"), code, G)


def plan_ruckig_arriving(state0, t0: float, G: TargetFn, T: float, limits: Limits, *, R0=None, w0=None,
                         jerk: JerkLimits | None = None, base: JerkLimits | None = None) -> Interception:
    """One controller-checked ruckig segment from ``state0`` at ``t0`` arriving on G at ``t0 + T`` (s), the
    segment asked to last ``T`` (ruckig's minimum duration): a slower flight than
    :func:`plan_interception_ruckig`'s earliest, as when a segment is stretched for the arm's joint speeds.
    The same inputs and checks as that search's final step; unreachable: ``t_hit`` None and a reason."""
    start = _checked_start(state0, t0, max(T, 0.02) * 2.0, 0.01, limits, G)
    if isinstance(start, Interception):
        return start
    start, R1, lim, check = _ruckig_inputs(start, G, limits, R0, w0, jerk, base)
    gp, gv, ga = (x[0] for x in G(np.array([t0 + T])))
    if not limits.contains(gp):
        return Interception(None, None, f"the target at {T:.3f} s is outside the workspace box", "outside_box", G)
    plan = plan_ruckig(start, gp, R1, gv, np.zeros(3), ga, T, lim)
    if plan.code == 0 and plan.duration <= T * (1 + 1e-6) + 1e-6 and check_ruckig(plan, check) == 0:
        traj = RuckigTrajectory(plan, t0, lim, base)
        return Interception(traj.t1, traj, None, "ok", G)
    return Interception(None, None, f"no controller-checked ruckig segment lasting {T:.3f} s", "too_slow", G)
