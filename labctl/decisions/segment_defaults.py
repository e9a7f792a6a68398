"""The robot controller's segment defaults for a run (dialect 1.4 ``SET``), set once when it is opened.

Apart from :mod:`labctl.decisions.predictor` so that a live predictor's device thread sets them without waiting
for the planner's own import (tracking → filterpy → scipy.stats, ~0.5 s CPU), which another thread is doing
meanwhile: a module being imported holds its import lock (docs/notes/run.md, "2026-12-02 (c)").
"""

from __future__ import annotations

from ..drivers.interfaces import Robot
from ..planning.ruckig_interception import ruckig_limits
from ..planning.ruckig_profile import controller_limits
from .context import Lab

__all__ = ["set_segment_defaults"]


def set_segment_defaults(robot: Robot, lab: Lab, profile: str | None = None) -> bool:
    """Tell the controller once, when it is opened and before the run's clock starts, what every segment of
    the run carries (dialect 1.4 ``SET``): the ``ruckig`` profile (``profile``, else ``run.profile``, if the
    controller runs it) under the ``robot_stop_budget_s`` speed cap — the limits :class:`PredictorPlanner`
    plans with. Each segment line is then ~24 bytes shorter (~25 ms at 9600 bps, on the critical path of
    every leg); False where nothing was set (a quintic run, an older controller)."""
    cfg = lab.config
    if robot.choose_profile(profile or cfg.run.profile) != "ruckig":
        return False
    limits = ruckig_limits(lab.robot, cfg.run.robot_stop_budget_s).wire(controller_limits(lab.robot))
    return robot.segment_defaults("ruckig", limits)
