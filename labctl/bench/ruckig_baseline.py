"""A modern baseline beside the paper's quintics: ruckig's time-optimal jerk-limited motion.

ruckig (Berscheid & Kröger 2021) computes, per call, the time-optimal jerk-limited trajectory
from a full kinematic state to a target state (position, velocity, acceleration per axis) under
per-axis velocity/acceleration/jerk limits, and can be asked to take at least a given duration.
The interception of G(t) is then: the earliest ``T`` for which the trajectory to ``G(t0 + T)``
taking ``T`` is feasible, found by a coarse scan and bisection as for the quintics. ruckig does
not enforce position limits, so the workspace box is checked here from its exact per-axis
position extrema. Units: mm, s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..planning.limits import Limits, PlanningError


@dataclass(frozen=True)
class RuckigInterception:
    """``t_hit`` (s, None if unreachable), the ruckig trajectory taking ``t_hit - t0``, and a reason."""

    t_hit: float | None
    trajectory: object | None
    reason: str | None = None

    @property
    def reachable(self) -> bool:
        """True if ruckig found an interception (``t_hit`` is set)."""
        return self.t_hit is not None


class RuckigInterceptor:
    """Reusable ruckig objects (allocation is the slow part) for :meth:`plan`."""

    def __init__(self, limits: Limits, j_max: float | None = None):
        try:
            from ruckig import InputParameter, Result, Ruckig, Trajectory
        except ImportError as exc:  # pragma: no cover - ruckig is a declared benchmark dependency
            raise PlanningError("the ruckig baseline needs the 'ruckig' package") from exc
        self.limits = limits
        self.j_max = float(j_max if j_max is not None else 10.0 * limits.a_max)
        self._otg = Ruckig(3)
        self._inp = InputParameter(3)
        self._traj = Trajectory(3)
        self._ok = (Result.Working, Result.Finished)
        self._Trajectory = Trajectory
        self._inp.max_velocity = [limits.v_max] * 3
        self._inp.max_acceleration = [limits.a_max] * 3
        self._inp.max_jerk = [self.j_max] * 3

    def _feasible(self, T: float, g) -> bool:
        inp, traj, lim = self._inp, self._traj, self.limits
        gp, gv, ga = g
        if np.any(gp < lim.box_min) or np.any(gp > lim.box_max):
            return False
        inp.target_position = gp.tolist()
        inp.target_velocity = gv.tolist()
        inp.target_acceleration = ga.tolist()
        inp.minimum_duration = T
        if self._otg.calculate(inp, traj) not in self._ok or traj.duration > T * (1 + 1e-9) + 1e-9:
            return False
        ext = traj.position_extrema
        return all(lim.box_min[d] - 1e-6 <= ext[d].min and ext[d].max <= lim.box_max[d] + 1e-6 for d in range(3))

    def plan(self, state0, t0: float, G, horizon_s: float = 10.0, t_min: float = 0.02,
             n_coarse: int = 64, tol_s: float = 1e-3) -> RuckigInterception:
        """Earliest arrival on G(t) with a jerk-limited ruckig trajectory (same limits as the quintics)."""
        p0, v0, a0 = (np.asarray(x, dtype=float).reshape(3) for x in state0)
        inp = self._inp
        inp.current_position, inp.current_velocity, inp.current_acceleration = p0.tolist(), v0.tolist(), a0.tolist()
        Ts = np.geomspace(t_min, horizon_s, n_coarse)
        gp, gv, ga = G(t0 + Ts)
        prev = 0.0
        for k, T in enumerate(Ts):
            if self._feasible(T, (gp[k], gv[k], ga[k])):
                lo, hi = prev, T
                while hi - lo > tol_s:
                    mid = 0.5 * (lo + hi)
                    g = tuple(x[0] for x in G(np.array([t0 + mid])))
                    if self._feasible(mid, g):
                        hi = mid
                    else:
                        lo = mid
                g = tuple(x[0] for x in G(np.array([t0 + hi])))
                self._feasible(hi, g)
                traj = self._Trajectory(3)
                self._otg.calculate(inp, traj)
                return RuckigInterception(t0 + hi, traj)
            prev = T
        return RuckigInterception(None, None, f"ruckig: no feasible interception within {horizon_s:.1f} s")


def plan_interception_ruckig(state0, t0: float, G, limits: Limits, horizon_s: float = 10.0,
                             j_max: float | None = None) -> RuckigInterception:
    """One-off :meth:`RuckigInterceptor.plan` (jerk limit defaults to 10·a_max per second)."""
    return RuckigInterceptor(limits, j_max).plan(state0, t0, G, horizon_s)
