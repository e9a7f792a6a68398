"""The initial view's margin (issue 18): the prediction's 3-σ uncertainty widens the viewing distance, but a
widened view out of the robot's reach must not leave the robot flying to an older aim or fail the run. While
the table speeds up from rest (0.5 s to 100 mm/s) the manoeuvre mode holds the track and its margin put every
widened view out of reach: 96 of 100 trials on the circle at 100 mm/s failed once every frame was tracked
(docs/notes/planning.md, "Frames caught up")."""

from __future__ import annotations

import numpy as np
import pytest

from labctl.config import load_lab
from labctl.drivers.interfaces import RobotStatus
from labctl.sim.world import home_flange_pose
from labctl.workers.context import RunContext
from labctl.workers.predictor import PredictorPlanner
from labctl.workspace import sample_lab_path

AZIMUTH_STEPS = (0.0, 20.0, -20.0, 45.0, -45.0, 90.0, -90.0, 180.0)


@pytest.fixture(scope="module")
def ctx():
    return RunContext.load(load_lab(sample_lab_path()))


class SegmentRobot:
    """A controller on its own clock that takes every segment and stands at ``pose`` until then."""

    def __init__(self, pose):
        self.pose, self.segments = pose, []

    def status(self):
        return RobotStatus(T_base_flange=self.pose, moving=False, segment_id=0, t=0.0)

    def segment(self, T_end, duration, seg_id, replace=True, **kw):
        self.segments.append((np.array(T_end), float(duration)))
        return float("nan"), float("nan")


def _track(p, t0, t1, start, v):
    for t in np.arange(t0, t1 + 1e-9, 1.0 / 30.0):
        p.tracker.update(float(t), np.asarray(start, float) + np.asarray(v, float) * t)


def test_a_view_the_margin_puts_out_of_reach_is_planned_and_re_planned_at_the_nominal_distance(ctx, monkeypatch):
    robot = SegmentRobot(home_flange_pose(ctx.lab))
    p = PredictorPlanner(ctx, robot, lambda msg: None, lambda *a, **k: None)
    _track(p, 0.0, 1.0, (150.0, 200.0), (50.0, 0.0))
    p.t_first_seen, p.stage = 0.0, "intercept"
    p.azimuth_deg = p._choose_azimuth()
    monkeypatch.setattr(p, "_commit_margin_mm", lambda: 2000.0)  # a prediction too uncertain for any widened view
    assert not any(p._plan(1.0, "initial1", p._initial_view_target(p.azimuth_deg + d)).reachable
                   for d in AZIMUTH_STEPS)
    nominal = p._plan(1.0, "initial1", p._initial_view_target(p.azimuth_deg, margin=False))
    assert nominal.reachable
    assert p._plan_initial(1.0, "initial1") and not p.finished and len(robot.segments) == 1
    assert np.allclose(robot.segments[0][0][:3, 3], nominal.trajectory.segments[0].state(
        nominal.trajectory.segments[0].t1)[0], atol=0.01)  # the nominal view, not a failed run
    _track(p, 1.0 + 1.0 / 30.0, 1.3, (150.0 - 0.2 * 50.0, 200.0), (60.0, 0.0))  # it sped up: a new aim
    p._replan(1.3)
    assert len(robot.segments) == 2 and not p.finished


@pytest.mark.parametrize("stop_corners, family, told", [(True, "zigzag", True), (False, "zigzag", False),
                                                        (True, None, False)])
def test_the_tracker_is_told_the_tables_stops_only_when_set_and_labctl_drives_the_table(ctx, stop_corners, family,
                                                                                         told):
    import dataclasses

    cfg = ctx.lab.config
    cfg = dataclasses.replace(cfg, tracking=dataclasses.replace(cfg.tracking, stop_corners=stop_corners))
    lab = dataclasses.replace(ctx.lab, config=cfg)
    p = PredictorPlanner(dataclasses.replace(ctx, lab=lab), SegmentRobot(home_flange_pose(lab)), lambda msg: None,
                         lambda *a, **k: None, family=family)
    assert p.tracker._stop_accel == (lab.table.accel_mm_s2 if told else None)
