"""The honest time-to-identity bound (issue 16, Build 3) against oracles it does not share code with:
the closed-form trapezoid, the quintic planner's own limit-checked segments, and a virtual run."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from labctl.planning import Limits, shortest_quintic
from labctl.planning.tti_bound import Leg, identity_bound, leg_min_time, min_line_time, rotation_angle

V, A = 500.0, 3000.0
LIMITS = Limits(np.full(3, -5000.0), np.full(3, 5000.0), V, A, math.radians(120.0))
finite = st.floats(-800.0, 800.0, allow_nan=False)


def trapezoid(d: float, v: float, a: float) -> float:
    """Textbook minimum rest-to-rest time with |v| ≤ v, |a| ≤ a: triangle below d = v²/a, trapezoid above."""
    return 2.0 * math.sqrt(d / a) if d < v * v / a else d / v + v / a


@given(st.floats(0.01, 3000.0), st.floats(50.0, 1000.0), st.floats(200.0, 10000.0))
def test_no_jerk_limit_is_the_trapezoid(d, v, a):
    assert min_line_time(d, 0, 0, 0, 0, v, a) == pytest.approx(trapezoid(d, v, a), rel=1e-9, abs=1e-9)


@given(st.floats(1.0, 2000.0), st.floats(1e3, 1e6))
def test_a_jerk_limit_only_lengthens(d, j):
    assert min_line_time(d, 0, 0, 0, 0, V, A, j) >= min_line_time(d, 0, 0, 0, 0, V, A) - 1e-12


@settings(max_examples=25, deadline=None)
@given(st.tuples(finite, finite, finite), st.tuples(finite, finite, finite),
       st.tuples(*[st.floats(-200.0, 200.0)] * 3))
def test_no_limit_respecting_quintic_beats_the_bound(p0, p1, v0):
    """The planner's shortest quintic passes the exact limit check (‖v‖, ‖a‖ of the controller), so its
    duration can never be below the bound, from rest or from a moving start."""
    seg = shortest_quintic(p0, v0, np.zeros(3), p1, np.zeros(3), np.zeros(3), LIMITS)
    leg = Leg("x", p0, p1, v0=v0)
    assert leg_min_time(leg, V, A) <= seg.t1 - seg.t0 + 1e-9


def test_rotation_counts_when_it_is_slower():
    Rz = lambda t: np.array([[math.cos(t), -math.sin(t), 0], [math.sin(t), math.cos(t), 0], [0, 0, 1.0]])  # noqa: E731
    assert rotation_angle(np.eye(3), Rz(2.0)) == pytest.approx(2.0)
    leg = Leg("x", (0, 0, 0), (1, 0, 0), R0=np.eye(3), R1=Rz(math.pi / 2))
    assert leg_min_time(leg, V, A, w_max=math.radians(120.0)) == pytest.approx(0.75)  # 90° at 120°/s
    assert leg_min_time(leg, V, A) == pytest.approx(trapezoid(1.0, V, A))  # no w_max: translation only


def test_bound_parts_add_up():
    legs = [Leg("a", (0, 0, 0), (300, 0, 0)), Leg("b", (300, 0, 0), (300, 400, 0))]
    out = identity_bound(0.5, legs, 3, 1 / 30, v_max=V, a_max=A)
    assert out["legs_s"] == pytest.approx([trapezoid(300, V, A), trapezoid(400, V, A)])
    assert out["bound_s"] == pytest.approx(0.5 + sum(out["legs_s"]) + 0.1)


def test_a_virtual_run_reports_an_honest_bound():
    from labctl.config import load_lab
    from labctl.decisions.context import RunContext
    from labctl.runtime.virtual import TrialSpec, simulate_run
    from labctl.workspace import sample_lab_path

    lab = load_lab(sample_lab_path())
    res = simulate_run(lab, RunContext.load(lab), TrialSpec("line", 8.0, "block", 2))
    assert res["correct"], res
    b = res["bound"]
    # one leg per image, the first sight is the wait stage, and no run beats its bound
    assert len(b["legs_s"]) == len(b["legs"]) and b["frames_s"] == pytest.approx(len(b["legs"]) / 30.0)
    assert b["first_sight_s"] == pytest.approx(res["stages"]["wait"], abs=1e-3)  # stages are rounded
    assert b["bound_s"] <= res["time_to_identity_s"]
    assert res["ratio_to_bound"] == pytest.approx(res["time_to_identity_s"] / res["lower_bound_s"])
    assert res["time_from_first_sight_s"] == pytest.approx(res["time_to_identity_s"] - b["first_sight_s"])


@settings(max_examples=25, deadline=None)
@given(st.tuples(finite, finite, finite), st.tuples(finite, finite, finite),
       st.tuples(*[st.floats(-200.0, 200.0)] * 3))
def test_no_controller_ruckig_segment_beats_the_jerk_limited_bound(p0, p1, v0):
    """A leg flown with ruckig segments is bound with the controller's jmax: the controller's own
    time-optimal segment (3-D, per-axis shares of the norm limits) never beats that 1-D bound."""
    from labctl.planning.ruckig_profile import JerkLimits, plan_ruckig

    lim = JerkLimits.from_limits(LIMITS)
    plan = plan_ruckig((p0, v0, np.zeros(3), np.eye(3), np.zeros(3)), p1, np.eye(3), np.zeros(3), np.zeros(3),
                       np.zeros(3), 0.0, lim, full=False)
    assume(plan.code == 0)  # a start beyond an axis's share is refused (E17), not flown
    leg = Leg("x", p0, p1, v0=v0, j_max=lim.j_max)
    assert leg_min_time(leg, V, A) <= plan.duration + 1e-9
    assert leg_min_time(leg, V, A) >= leg_min_time(Leg("x", p0, p1, v0=v0), V, A) - 1e-12  # jerk only lengthens
