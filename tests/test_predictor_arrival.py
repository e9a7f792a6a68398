"""Arrival at a view (issue 16): on the controller's @DONE without a round trip, and never an image from
a robot its controller stopped short of the view (a live run under heavy load once tripped the watchdog
mid-move and matched a view taken from where the robot stood)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from fakes import StillRobot

from labctl.config import load_lab
from labctl.decisions.context import RunContext
from labctl.decisions.predictor import PredictorPlanner
from labctl.drivers.interfaces import RobotStatus
from labctl.geometry import make_T
from labctl.sim.world import home_flange_pose
from labctl.workspace import sample_lab_path


@pytest.fixture(scope="module")
def ctx():
    return RunContext.load(load_lab(sample_lab_path()))


class StubRobot(StillRobot):
    """A controller that reports ``pose`` standing still, with ``latched`` fault and ``done`` segment ids."""

    def __init__(self, pose, latched=None, done=()):
        self.pose, self.latched, self.done_ids = pose, latched, list(done)
        self.status_calls = self.stops = 0

    def status(self):
        self.status_calls += 1
        return RobotStatus(T_base_flange=self.pose, moving=False, segment_id=1, t=0.0)

    def stop(self):
        self.stops += 1


def _planner(ctx, robot):
    p = PredictorPlanner(ctx, robot, lambda msg: None, lambda *a, **k: None)
    p.stage, p.segment_id = "standard", 7
    p.plan = SimpleNamespace(t_hit=5.0)
    p.T_end = make_T(np.eye(3), [100.0, 200.0, 900.0])
    return p


def _after_grace(p):
    """A time past the planned arrival (5 s) and the wait for its @DONE."""
    return 5.0 + p._done_grace_s + 0.01


def test_no_status_round_trip_while_done_may_still_come(ctx):
    robot = StubRobot(make_T(np.eye(3), [100.0, 200.0, 900.0]))
    p = _planner(ctx, robot)
    assert 0.0 < p._done_grace_s < 0.25
    assert p._arrived(5.0) is None and p._arrived(5.0 + 0.9 * p._done_grace_s) is None
    assert robot.status_calls == 0 and not p.finished
    robot.done_ids.append(7)  # the @DONE arrives: at the view, still without a round trip
    assert np.allclose(p._arrived(5.0 + 0.95 * p._done_grace_s), p.T_end) and robot.status_calls == 0


def test_done_means_at_the_commanded_pose_without_asking(ctx):
    robot = StubRobot(make_T(np.eye(3), [0.0, 0.0, 0.0]), done=[7])
    p = _planner(ctx, robot)
    T = p._arrived(5.1)
    assert np.allclose(T, p.T_end) and robot.status_calls == 0 and not p.finished


def test_a_watchdog_stop_fails_the_run_instead_of_taking_the_view(ctx):
    robot = StubRobot(make_T(np.eye(3), [40.0, 150.0, 700.0]), latched="watchdog")
    p = _planner(ctx, robot)
    assert p._arrived(_after_grace(p)) is None
    assert p.stage == "failed" and "watchdog" in p.failure and robot.stops == 1


def test_standing_short_of_the_view_fails_the_run(ctx):
    robot = StubRobot(make_T(np.eye(3), [100.0, 230.0, 900.0]))
    p = _planner(ctx, robot)
    assert p._arrived(_after_grace(p)) is None
    assert p.stage == "failed" and "30.0 mm" in p.failure


def test_at_the_view_without_done_is_read_from_status(ctx):
    robot = StubRobot(make_T(np.eye(3), [100.0, 200.0, 900.2]))
    p = _planner(ctx, robot)
    assert p._arrived(5.0 + 0.5 * p._done_grace_s) is None and robot.status_calls == 0  # @DONE may be on its way
    T = p._arrived(_after_grace(p))
    assert T is not None and robot.status_calls == 1 and np.allclose(T[:3, 3], [100.0, 200.0, 900.2])


class OffsetClockRobot(StubRobot):
    """A controller on its own clock, ``offset_s`` ahead of the run's (another process's origin, or real
    hardware's): each segment starts on receipt and arrives at its commanded duration."""

    def __init__(self, pose, clock, offset_s):
        super().__init__(pose)
        self.clock, self.offset_s, self.segments = clock, offset_s, 0

    def choose_profile(self, profile):
        return profile

    def segment(self, T, duration_s, segment_id, **kw):
        self.segments += 1
        t0c = self.clock() + 0.1 + self.offset_s  # ~100 bytes at 9600 bps, then its own clock
        return t0c, t0c + duration_s


@pytest.mark.parametrize("shared", [False, True])
@pytest.mark.parametrize("profile", ["quintic", "ruckig"])
def test_a_controller_on_its_own_clock_still_arrives(ctx, shared, profile):
    """A served lab or real controller whose clock is 0.7 s off the run's: its times are not the run's, so
    they are never taken for the command latency. (They were, when the offset fell in [0, 1) s: every
    re-plan then started ~1 s ahead, its arrival receded as fast as time passed, and the run timed out.)
    On the run's own clock (the simulated lab) the reply times the plan."""
    now = {"t": 0.0}
    robot = OffsetClockRobot(home_flange_pose(ctx.lab), lambda: now["t"], 0.0 if shared else 0.7)
    p = PredictorPlanner(ctx, robot, lambda msg: None, lambda *a, **k: None, clock=lambda: now["t"],
                         shared_clock=shared, profile=profile)
    for k in range(6):  # a marker on a line at 8 mm/s, seen at 15 Hz
        p.tracker.update(k / 15.0, np.array([150.0 + 8.0 * k / 15.0, 200.0]))
    now["t"] = 5 / 15.0
    p.azimuth_deg = p._choose_azimuth()
    assert p._plan_initial(now["t"], "initial1")
    t_hit0 = p.plan.t_hit
    while now["t"] < t_hit0 + 2.0 and now["t"] < p.plan.t_hit + p.plan_shift:
        now["t"] += 1 / 15.0
        p._replan(now["t"])
    assert p.plan.t_hit < t_hit0 + 0.5, (t_hit0, p.plan.t_hit, p.latency_s)
    assert (p.t1c is not None) == shared and (p.plan_shift != 0.0) == shared
