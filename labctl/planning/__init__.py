"""labctl.planning — time-optimal interception with task-space quintics, viewpoints, safety (paper §4.3)."""

from .interception import Interception, plan_interception, replan, shortest_quintic
from .limits import Limits, LimitViolation, PlanningError
from .quintic import QuinticSegment, Trajectory, quintic_coefficients, rest_to_rest_times
from .safety import check_segment, check_trajectory
from .targets import TargetPath, camera_placement_trajectory, standard_view_path, standard_view_pose

__all__ = [
    "Interception",
    "LimitViolation",
    "Limits",
    "PlanningError",
    "QuinticSegment",
    "TargetPath",
    "Trajectory",
    "camera_placement_trajectory",
    "check_segment",
    "check_trajectory",
    "plan_interception",
    "quintic_coefficients",
    "replan",
    "rest_to_rest_times",
    "shortest_quintic",
    "standard_view_path",
    "standard_view_pose",
]
