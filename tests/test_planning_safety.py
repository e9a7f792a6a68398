"""Safety: nothing that leaves the planner violates the workspace box or the v/a/ω limits (hypothesis)."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from labctl.planning import (
    Limits,
    LimitViolation,
    QuinticSegment,
    camera_placement_trajectory,
    check_segment,
    check_trajectory,
    plan_interception,
)
from labctl.tracking import PredictedPath

# fixed limits (a 1.2 × 1.4 × 1.1 m box, 500 mm/s, 1500 mm/s², 120°/s) so the tests do not move with the sample lab
LIMITS = Limits([-300.0, -700.0, 80.0], [900.0, 700.0, 1200.0], v_max=500.0, a_max=1500.0, w_max=np.deg2rad(120.0))
U = np.linspace(0.0, 1.0, 2001)[:, None]
K = np.arange(6)
POW = U**K
DPOW = K * U ** np.maximum(K - 1, 0)
D2POW = K * (K - 1) * U ** np.maximum(K - 2, 0)


def dense_extremes(seg: QuinticSegment):
    """Independent of the exact/bounded maxima under test: 2001 samples of the segment's polynomial."""
    T = seg.duration
    P, V, A = POW @ seg.coeffs, DPOW @ seg.coeffs / T, D2POW @ seg.coeffs / T**2
    return P.min(axis=0), P.max(axis=0), np.linalg.norm(V, axis=1).max(), np.linalg.norm(A, axis=1).max()


def dense_stop_outside(seg: QuinticSegment, limits: Limits, slack_mm: float = 0.0) -> bool:
    """Independent of stop_envelope_range: does braking each axis at a_max/√3 from any of 2001 sampled
    states end (more than ``slack_mm`` short of) outside the box?"""
    P, V = POW @ seg.coeffs, DPOW @ seg.coeffs / seg.duration
    rest = P + V * np.abs(V) / (2 * limits.a_max / np.sqrt(3.0))
    return bool(np.any(rest < limits.box_min + slack_mm) or np.any(rest > limits.box_max - slack_mm))


def assert_within_limits(seg: QuinticSegment, limits: Limits):
    lo, hi, v, a = dense_extremes(seg)
    assert np.all(lo >= limits.box_min - 1e-6) and np.all(hi <= limits.box_max + 1e-6), (lo, hi)
    assert not dense_stop_outside(seg, limits, slack_mm=-1e-6)
    assert v <= limits.v_max * (1 + 1e-6), v
    assert a <= limits.a_max * (1 + 1e-6), a
    assert seg.max_rotation_rate() <= limits.w_max * (1 + 1e-6)


vec = st.tuples(*[st.floats(-1.0, 1.0)] * 3).map(np.array)
box_pos = st.tuples(*[st.floats(0.0, 1.0)] * 3).map(
    lambda u: LIMITS.box_min + np.array(u) * (LIMITS.box_max - LIMITS.box_min)
)


@settings(max_examples=1500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(p0=box_pos, p1=box_pos, v0=vec, v1=vec, a0=vec, a1=vec, T=st.floats(0.05, 8.0), scale=st.floats(0.0, 1.2))
def test_check_segment_passes_only_safe_segments_and_names_real_violations(p0, p1, v0, v1, a0, a1, T, scale):
    seg = QuinticSegment(0.0, T, p0, v0 * LIMITS.v_max * scale, a0 * LIMITS.a_max * scale,
                         p1, v1 * LIMITS.v_max * scale, a1 * LIMITS.a_max * scale)
    try:
        check_segment(seg, LIMITS)
    except LimitViolation as err:
        exceeded = {
            "velocity": seg.max_speed() > LIMITS.v_max,
            "acceleration": seg.max_accel() > LIMITS.a_max,
            "box": bool(np.any(seg.position_range()[0] < LIMITS.box_min - 1e-6)
                        or np.any(seg.position_range()[1] > LIMITS.box_max + 1e-6)),
            "stop": dense_stop_outside(seg, LIMITS, slack_mm=1e-3),
        }
        assert exceeded[err.kind], (err, exceeded)
    else:
        assert_within_limits(seg, LIMITS)


@st.composite
def interception_case(draw):
    lo, hi = LIMITS.box_min + 20, LIMITS.box_max - 20
    p0 = lo + np.array(draw(st.tuples(*[st.floats(0, 1)] * 3))) * (hi - lo)
    v0 = draw(vec) * LIMITS.v_max * draw(st.floats(0, 0.9))
    a0 = draw(vec) * LIMITS.a_max * draw(st.floats(0, 0.9))
    start = np.array(draw(st.tuples(st.floats(-200, 800), st.floats(-400, 400))))
    speed = draw(st.floats(0, 150))
    heading = draw(st.floats(0, 2 * np.pi))
    acc = np.array(draw(st.tuples(st.floats(-5, 5), st.floats(-5, 5))))
    path = PredictedPath(0.0, start, speed * np.array([np.cos(heading), np.sin(heading)]), acc)
    G = camera_placement_trajectory(path, draw(st.floats(300, 1200)), draw(st.floats(20, 90)),
                                    azimuth_deg=draw(st.floats(-180, 180)), marker_z_mm=draw(st.floats(0, 100)))
    rot = draw(st.booleans())
    return (p0, v0, a0), G, rot


@settings(max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(case=interception_case())
def test_no_planned_segment_violates_the_workspace_or_limits(case):
    state, G, rot = case
    res = plan_interception(state, 0.0, G, LIMITS, 8.0, R0=np.eye(3) if rot else None, follow_s=1.0)
    if not res.reachable:
        assert res.trajectory is None and res.code in {"outside_box", "below_floor", "too_slow"}
        return
    check_trajectory(res.trajectory, LIMITS)
    for seg in res.trajectory.segments:
        assert_within_limits(seg, LIMITS)
    first = res.trajectory.segments[0]
    for got, want in zip(first.state(0.0), state):
        np.testing.assert_allclose(got, want, atol=1e-9)
