"""Robot limits for planning and the planner's typed errors.

The mobile camera's robot is driven in task space (paper §4.3: time-optimal task-space quintic
polynomials). Its limits come from ``drivers/robot.yaml`` (:class:`labctl.config.devices.RobotConfig`).
``v_max`` and ``a_max`` bound each Cartesian axis separately (a Cartesian manipulator's axes, and
what ruckig takes, so the two planners are compared on the same limits); ``w_max`` bounds the
rotation rate. Units: mm, s, rad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import LabctlError


class PlanningError(LabctlError):
    """A planning request that cannot be served (bad input or an unsafe result)."""


class LimitViolation(PlanningError):
    """A segment would leave the workspace box or exceed a velocity/acceleration/rotation limit.

    ``kind`` is one of ``"box"``, ``"stop"`` (braking at some instant would end outside the box),
    ``"velocity"``, ``"acceleration"``, ``"angular_velocity"``,
    ``"invalid"``; ``value`` and ``limit`` are the offending number and its bound.
    """

    def __init__(self, kind: str, value: float, limit: float, detail: str = ""):
        self.kind, self.value, self.limit = kind, float(value), float(limit)
        extra = f" ({detail})" if detail else ""
        super().__init__(f"segment violates {kind} limit: {value:.6g} vs {limit:.6g}{extra}")


@dataclass(frozen=True)
class Limits:
    """Workspace box (mm, world frame), speed ‖v‖ (mm/s) and acceleration ‖a‖ (mm/s²), rotation rate (rad/s).

    Speed and acceleration are Euclidean norms of the task-space vectors, as the robot controller
    (docs/protocols/robot.md) checks them."""

    box_min: np.ndarray
    box_max: np.ndarray
    v_max: float
    a_max: float
    w_max: float = float(np.deg2rad(120.0))

    def __post_init__(self):
        lo = np.asarray(self.box_min, dtype=float).reshape(3)
        hi = np.asarray(self.box_max, dtype=float).reshape(3)
        object.__setattr__(self, "box_min", lo)
        object.__setattr__(self, "box_max", hi)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)):
            raise PlanningError(f"workspace box needs finite min < max on every axis, got {lo} .. {hi}")
        for name in ("v_max", "a_max", "w_max"):
            value = float(getattr(self, name))
            if not np.isfinite(value) or value <= 0:
                raise PlanningError(f"{name} must be a positive number, got {value!r}")
            object.__setattr__(self, name, value)

    @property
    def a_stop(self) -> float:
        """Per-axis braking deceleration of the robot controller (mm/s²): ``a_max/√3``, so the
        acceleration norm stays within ``a_max`` while all three axes brake (docs/protocols/robot.md)."""
        return self.a_max / float(np.sqrt(3.0))

    @classmethod
    def from_config(cls, robot_cfg) -> Limits:
        """From a :class:`labctl.config.devices.RobotConfig` (degrees converted to radians)."""
        return cls(
            box_min=np.array(robot_cfg.workspace_min_mm, dtype=float),
            box_max=np.array(robot_cfg.workspace_max_mm, dtype=float),
            v_max=float(robot_cfg.v_max_mm_s),
            a_max=float(robot_cfg.a_max_mm_s2),
            w_max=float(np.deg2rad(robot_cfg.w_max_deg_s)),
        )

    def contains(self, points, tol: float = 1e-6) -> np.ndarray:
        """Which of ``points`` (..., 3) lie in the box (with ``tol`` mm slack)."""
        p = np.asarray(points, dtype=float)
        return np.all((p >= self.box_min - tol) & (p <= self.box_max + tol), axis=-1)


#: the planner keeps this fraction of the controller's limits in hand (latency, sampling, round-off)
LIMIT_MARGIN = 0.98


#: the robot controller's angular braking, rad/s² per rad/s of w_max (docs/protocols/robot.md §Stopping:
#: ``alpha_stop = 4·wmax``, full turning rate to rest in 0.25 s)
ANGULAR_STOP_PER_S = 4.0


def stop_budget_caps(a_stop: float, w_max: float, stop_budget_s: float) -> tuple[float, float]:
    """The speed (mm/s) and turning rate (rad/s) from which the controller's stop ramp (each axis at
    ``a_stop``, the rotation at ``ANGULAR_STOP_PER_S·w_max``; docs/protocols/robot.md §Stopping) brings
    the flange to rest within ``stop_budget_s``: ``a_stop·budget`` (‖v‖ bounds every axis's |v_i|) and
    ``alpha_stop·budget``."""
    return a_stop * stop_budget_s, ANGULAR_STOP_PER_S * w_max * stop_budget_s


def planning_limits(robot_cfg, stop_budget_s: float | None = None) -> Limits:
    """The limits the planner plans to: the controller's, with a margin, and — with ``stop_budget_s``
    (s, lab.yaml ``run.robot_stop_budget_s``) — speed and turning rate capped so that the controller's
    stop ramp brings the flange to rest within the budget from any instant (:func:`stop_budget_caps`,
    with ``a_stop = a_max/√3``). Every segment the planner returns passes
    :func:`labctl.planning.safety.check_segment` against these limits."""
    lim = Limits.from_config(robot_cfg)
    v, w = lim.v_max * LIMIT_MARGIN, lim.w_max * LIMIT_MARGIN
    if stop_budget_s is not None:
        v_cap, w_cap = stop_budget_caps(lim.a_stop, lim.w_max, stop_budget_s)
        v, w = min(v, v_cap), min(w, w_cap)
    return Limits(lim.box_min, lim.box_max, v, lim.a_max * LIMIT_MARGIN, w)
