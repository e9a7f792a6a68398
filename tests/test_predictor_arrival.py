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
    assert (p.t1c is not None) == shared and p._latency_measured == shared  # the reply times the plan, on one clock


# -- the image at the promised arrival (run.image_at_arrival; docs/notes/planning.md "2026-12-02 (c)") ------------
def _promised(ctx, robot, t_arrive=5.0):
    """A planner on the standard view's leg whose controller promised to stand at its end from ``t_arrive``."""
    sent = []
    p = PredictorPlanner(ctx, robot, sent.append, lambda *a, **k: None)
    p.stage, p.segment_id, p.plan_kind = "standard", 7, "standard"
    p.plan = SimpleNamespace(t_hit=t_arrive, trajectory=None)
    p.t_robot_log = float("inf")  # no commanded-path log lines (they read the plan's trajectory)
    p.T_end = make_T(np.eye(3), [100.0, 200.0, 900.0])
    p.t_arrive = t_arrive
    return p, sent


def _identity(ctx):
    from labctl.decisions import messages as m

    return m.Identity(object_id=0, score=0.9, n_candidates=1, candidates=(0,))


def test_the_image_is_requested_at_the_promised_arrival_and_used_only_after_its_done(ctx):
    from labctl.decisions import messages as m

    robot = StubRobot(make_T(np.eye(3), [100.0, 200.0, 900.0]))
    p, sent = _promised(ctx, robot)
    p.tick(4.999)  # not before the arrival the controller promised
    assert not [x for x in sent if isinstance(x, m.CaptureRequest)]
    p.tick(5.0)
    (req,) = [x for x in sent if isinstance(x, m.CaptureRequest)]
    assert req.t_capture == 5.0 and req.kind == "standard" and np.allclose(req.position, p.T_end[:3, 3]
                                                                             + p.T_end[:3, :3] @ ctx.T_f_c2[:3, 3])
    assert p.pending is None and p.provisional is not None and robot.status_calls == 0
    p.on_message(_identity(ctx), 5.034)  # the recognizer answers before the @DONE has come: nothing is used
    assert p.stage == "standard" and p.identity is None and not p.finished
    robot.done_ids.append(7)  # the segment ran to its planned end
    p.tick(5.04)
    assert p.stage == "done" and p.identity is not None and robot.status_calls == 0
    assert p.stage_times.started["match"] == 5.0  # the view's stage starts at the image, not at the @DONE
    assert p.n_images == 1 and not [x for x in sent if isinstance(x, m.Discard)]


def test_a_reply_after_the_done_is_used_at_once(ctx):
    robot = StubRobot(make_T(np.eye(3), [100.0, 200.0, 900.0]))
    p, _ = _promised(ctx, robot)
    p.tick(5.0)
    robot.done_ids.append(7)  # the @DONE came during the exposure: the reply itself confirms the image
    p.on_message(_identity(ctx), 5.034)
    assert p.stage == "done" and p.identity is not None


def test_without_its_done_the_image_is_discarded_and_the_view_retaken_after_status(ctx):
    from labctl.decisions import messages as m

    robot = StubRobot(make_T(np.eye(3), [100.0, 200.0, 900.2]))  # it stands there, but no @DONE says so
    p, sent = _promised(ctx, robot)
    p.tick(5.0)
    p.on_message(_identity(ctx), 5.034)
    p.tick(5.0 + 0.9 * p._done_grace_s)
    assert robot.status_calls == 0 and not p.finished  # the @DONE may still come
    p.tick(_after_grace(p))
    discards = [x for x in sent if isinstance(x, m.Discard)]
    reqs = [x for x in sent if isinstance(x, m.CaptureRequest)]
    assert [d.view_id for d in discards] == [reqs[0].view_id] and robot.status_calls == 1
    assert len(reqs) == 2 and reqs[1].view_id != reqs[0].view_id and reqs[1].t_capture == _after_grace(p)
    assert sent.index(discards[0]) < sent.index(reqs[1])  # the recognizer forgets the first before the retake
    assert p.identity is None and p.pending == reqs[1].view_id and p.n_images == 1  # its reply was dropped
    p.on_message(_identity(ctx), _after_grace(p) + 0.034)
    assert p.stage == "done"


def test_without_its_done_a_robot_short_of_the_view_fails_and_no_reply_is_used(ctx):
    from labctl.decisions import messages as m

    robot = StubRobot(make_T(np.eye(3), [100.0, 230.0, 900.0]))
    p, sent = _promised(ctx, robot)
    p.tick(5.0)
    p.on_message(_identity(ctx), 5.034)
    p.tick(_after_grace(p))
    assert p.stage == "failed" and "30.0 mm" in p.failure and p.identity is None
    assert len([x for x in sent if isinstance(x, m.Discard)]) == 1


def test_image_at_arrival_off_waits_for_the_done(ctx):
    from dataclasses import replace

    from labctl.decisions import messages as m

    lab = ctx.lab
    lab2 = replace(lab, config=replace(lab.config, run=replace(lab.config.run, image_at_arrival=False)))
    robot = StubRobot(make_T(np.eye(3), [100.0, 200.0, 900.0]))
    p, sent = _promised(replace(ctx, lab=lab2), robot)
    assert p._arrival_on_run_clock(1.0, 2.0, 1.1) is None
    p.tick(5.0)
    assert not [x for x in sent if isinstance(x, m.CaptureRequest)]
    robot.done_ids.append(7)
    p.tick(5.02)
    assert [x.t_capture for x in sent if isinstance(x, m.CaptureRequest)] == [5.02]


@pytest.mark.parametrize("offset_s", [-3.0, 0.0, 0.7, 1e4])
def test_an_arrival_on_the_controller_s_own_clock_is_never_mapped_early(ctx, offset_s):
    """Off the run's clock the arrival is the reply's read time plus the segment's duration: the controller starts
    a SEGNOW (or a GO at rest) before it answers, so that is at or after the true arrival, whatever the offset."""
    p = PredictorPlanner(ctx, StubRobot(np.eye(4)), lambda msg: None, lambda *a, **k: None)
    t_start = 1.20  # run clock: the segment started when its line arrived
    t_reply = t_start + 0.026  # its reply (~25 bytes at 9600 bps) read afterwards
    t0c, t1c = t_start + offset_s, t_start + offset_s + 0.8
    t = p._arrival_on_run_clock(t0c, t1c, t_reply)
    assert t_start + 0.8 <= t <= t_start + 0.8 + 0.026 + ctx.lab.config.run.arrival_clock_margin_s + 1e-9
    shared = PredictorPlanner(ctx, StubRobot(np.eye(4)), lambda msg: None, lambda *a, **k: None, shared_clock=True)
    assert shared._arrival_on_run_clock(t_start, t_start + 0.8, t_reply) == pytest.approx(t_start + 0.8 + 1e-4)


def test_a_heartbeat_waits_for_an_arrival_within_its_round_trip_but_never_long(ctx):
    """A robot heartbeat due just before the promised arrival would block the loop past it (~25 ms at 9600 bps):
    it waits for the image request, but only while it is less than a quarter of the watchdog's slack late."""
    robot = StubRobot(make_T(np.eye(3), [100.0, 200.0, 900.0]))
    p, _ = _promised(ctx, robot, t_arrive=5.0)
    rt = 24 * 10.0 / ctx.lab.robot.baud
    slack = ctx.lab.robot.watchdog_s - ctx.lab.robot.heartbeat_s
    assert p.heartbeat_can_wait(5.0 - 0.5 * rt, 0.0)
    assert not p.heartbeat_can_wait(5.0 - 2.0 * rt, 0.0)  # the arrival is beyond the beat's round trip
    assert not p.heartbeat_can_wait(5.0 - 0.5 * rt, 0.25 * slack)  # already late: it goes now
    p.tick(5.0)  # the image is requested: nothing to wait for any more
    assert p.provisional is not None and not p.heartbeat_can_wait(5.0, 0.0)
