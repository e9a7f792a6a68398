"""Issue 13: the robot at rest within 0.5 s of a stop command — the planned speed fits a stop budget.

``run.robot_stop_budget_s`` caps the planner's speed and turning rate so that the robot
controller's stop ramp brings the flange to rest within the budget from any instant of any planned
segment. The oracle here is the robot controller emulator's own stop ramp (``StopRamp``, written
from docs/protocols/robot.md §Stopping, not from the planner), applied to states sampled along
plans made with the sample lab's limits.
"""

from __future__ import annotations

import numpy as np
import pytest
from interception_cases import stop_time, view_targets

from labctl.config import load_lab
from labctl.planning import check_segment, plan_interception
from labctl.planning.limits import LimitViolation, planning_limits
from labctl.planning.quintic import QuinticSegment
from labctl.sim.emulators.robot import RobotEmulator
from labctl.workspace import sample_lab_path


@pytest.fixture(scope="module")
def lab():
    return load_lab(sample_lab_path())


def test_the_sample_lab_sets_a_budget_its_robot_can_keep(lab):
    budget = lab.config.run.robot_stop_budget_s
    assert budget is not None and budget <= 0.3  # leaves ≥ 0.2 s of the 0.5 s for the STOP to arrive
    emu = RobotEmulator(lambda: 0.0, lab.robot)
    lim = planning_limits(lab.robot, budget)
    assert lim.v_max / emu.a_stop <= budget + 1e-9 and lim.w_max / emu.alpha_stop <= budget + 1e-9
    free = planning_limits(lab.robot)  # no budget: the controller's speed, which brakes too long
    assert free.v_max / emu.a_stop > budget


def test_every_planned_segment_brakes_within_the_budget_by_the_controllers_stop_ramp(lab):
    budget = lab.config.run.robot_stop_budget_s
    lim = planning_limits(lab.robot, budget)
    emu = RobotEmulator(lambda: 0.0, lab.robot)
    home = np.asarray(lab.robot.home_mm, float)
    worst, planned = 0.0, 0
    for G in view_targets(40):
        res = plan_interception((home, np.zeros(3), np.zeros(3)), 0.0, G, lim, 15.0)
        if not res.reachable:
            continue
        for seg in res.trajectory.segments:
            planned += 1
            for t in np.linspace(seg.t0, seg.t1, 101):
                p, v, _ = seg.state(t)
                worst = max(worst, stop_time(emu, p, v, seg.angular_velocity(t)))
    assert planned >= 20
    assert worst <= budget * (1 + 1e-6), worst
    assert worst > 0.8 * budget  # the cap is what binds: the plans do run near it


def test_check_segment_refuses_a_segment_too_fast_to_stop_in_the_budget(lab):
    lim = planning_limits(lab.robot, lab.config.run.robot_stop_budget_s)
    free = planning_limits(lab.robot)
    p0 = np.asarray(lab.robot.home_mm, float)
    d = 0.5 * (lim.v_max + free.v_max) * 1.0 / 1.875  # a 1 s rest-to-rest quintic peaking between the two caps
    seg = QuinticSegment(0.0, 1.0, p0, np.zeros(3), np.zeros(3), p0 + [d, 0, 0], np.zeros(3), np.zeros(3))
    check_segment(seg, free)
    with pytest.raises(LimitViolation) as err:
        check_segment(seg, lim)
    assert err.value.kind == "velocity"
