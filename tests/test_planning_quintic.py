"""Quintic segments (paper §4.3): boundary conditions, exact extrema, shortest durations, orientation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from labctl.config.devices import RobotConfig
from labctl.planning import (
    Limits,
    LimitViolation,
    PlanningError,
    QuinticSegment,
    Trajectory,
    camera_placement_trajectory,
    check_segment,
    plan_interception,
    shortest_quintic,
)
from labctl.planning.rotation import exp_so3, log_so3, right_jacobian
from labctl.tracking import PredictedPath

# fixed limits (a 1.2 × 1.4 × 1.1 m box, 500 mm/s, 1500 mm/s², 120°/s) so the tests do not move with the sample lab
LIMITS = Limits([-300.0, -700.0, 80.0], [900.0, 700.0, 1200.0], v_max=500.0, a_max=1500.0, w_max=np.deg2rad(120.0))
v3 = st.tuples(*[st.floats(-500, 500)] * 3).map(np.array)


@settings(max_examples=300, deadline=None)
@given(p0=v3, v0=v3, a0=v3, p1=v3, v1=v3, a1=v3, T=st.floats(0.05, 20.0), t0=st.floats(-100, 100))
def test_quintic_meets_its_six_boundary_conditions(p0, v0, a0, p1, v1, a1, T, t0):
    seg = QuinticSegment(t0, T, p0, v0, a0, p1, v1, a1)
    for got, want in zip(seg.state(t0), (p0, v0, a0)):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-6)
    for got, want in zip(seg.state(t0 + T), (p1, v1, a1)):
        np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-5)


@settings(max_examples=120, deadline=None)
@given(p0=v3, v0=v3, a0=v3, p1=v3, v1=v3, a1=v3, T=st.floats(0.1, 10.0))
def test_exact_extrema_match_dense_sampling_and_bounds_never_underestimate(p0, v0, a0, p1, v1, a1, T):
    seg = QuinticSegment(0.0, T, p0, v0, a0, p1, v1, a1)
    u = np.linspace(0, 1, 20001)[:, None]
    k = np.arange(6)
    c = seg.coeffs  # boundary conditions are checked above; here only the extrema search is under test
    P, V, A = (u**k) @ c, (k * u ** np.maximum(k - 1, 0)) @ c / T, (k * (k - 1) * u ** np.maximum(k - 2, 0)) @ c / T**2
    lo, hi = seg.position_range()
    scale = 1 + np.abs(P).max()
    assert np.all(lo <= P.min(axis=0) + 1e-9 * scale) and np.all(hi >= P.max(axis=0) - 1e-9 * scale)
    assert np.all(lo >= P.min(axis=0) - 1e-5 * scale) and np.all(hi <= P.max(axis=0) + 1e-5 * scale)
    vmax, amax = np.linalg.norm(V, axis=1).max(), np.linalg.norm(A, axis=1).max()  # speed and acceleration are norms
    assert vmax - 1e-9 * (1 + vmax) <= seg.max_speed() <= vmax * (1 + 1e-5) + 1e-9
    assert amax - 1e-9 * (1 + amax) <= seg.max_accel() <= amax * (1 + 1e-4) + 1e-9
    b = seg.limit_bounds()
    assert b["v"] >= seg.max_speed() - 1e-9 and b["a"] >= seg.max_accel() - 1e-9
    assert np.all(b["p_min"] <= lo + 1e-9) and np.all(b["p_max"] >= hi - 1e-9)


def test_shortest_rest_to_rest_quintic_matches_the_closed_form():
    # rest to rest over D: peak speed 1.875 D/T, peak acceleration (10/√3) D/T²
    for D in (50.0, 500.0, 1000.0):
        p0, p1 = np.array([-250.0, 0.0, 500.0]), np.array([D - 250.0, 0.0, 500.0])
        seg = shortest_quintic(p0, np.zeros(3), np.zeros(3), p1, np.zeros(3), np.zeros(3), LIMITS)
        T_ref = max(1.875 * D / LIMITS.v_max, np.sqrt(10 / np.sqrt(3) * D / LIMITS.a_max))
        assert T_ref <= seg.duration <= T_ref * 1.003
        check_segment(seg, LIMITS)
        faster = QuinticSegment(0.0, T_ref * 0.99, p0, np.zeros(3), np.zeros(3), p1, np.zeros(3), np.zeros(3))
        with pytest.raises(LimitViolation):
            check_segment(faster, LIMITS)


def test_shortest_quintic_rejects_impossible_end_states():
    with pytest.raises(PlanningError):  # ending faster than v_max
        shortest_quintic(np.array([0, 0, 500.0]), np.zeros(3), np.zeros(3), np.array([100, 0, 500.0]),
                         np.array([600.0, 0, 0]), np.zeros(3), LIMITS)
    with pytest.raises(PlanningError):  # ending outside the box
        shortest_quintic(np.array([0, 0, 500.0]), np.zeros(3), np.zeros(3), np.array([0, 0, 5000.0]),
                         np.zeros(3), np.zeros(3), LIMITS)


def test_orientation_goes_from_start_rate_to_rest_at_the_target():
    rng = np.random.default_rng(4)
    for _ in range(20):
        R0 = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        R1 = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        w0 = rng.normal(0, 0.5, 3)
        seg = QuinticSegment(2.0, 3.0, np.zeros(3), np.zeros(3), np.zeros(3), np.ones(3), np.zeros(3), np.zeros(3),
                             R0=R0, R1=R1, w0=w0)
        np.testing.assert_allclose(seg.orientation(2.0), R0, atol=1e-12)
        np.testing.assert_allclose(seg.orientation(5.0), R1, atol=1e-9)
        np.testing.assert_allclose(seg.angular_velocity(2.0), w0, atol=1e-12)
        np.testing.assert_allclose(seg.angular_velocity(5.0), 0.0, atol=1e-9)
        # body rate from finite differences of R(t) never exceeds the bound that is checked
        ts = np.linspace(2.0, 5.0, 601)
        Rs = [seg.orientation(t) for t in ts]
        rates = [np.linalg.norm(log_so3(a.T @ b)) / (ts[1] - ts[0]) for a, b in zip(Rs, Rs[1:])]
        assert max(rates) <= seg.max_rotation_rate() * (1 + 1e-3)
        for t in ts[::50]:  # and the analytic body rate agrees with the finite difference
            h = 1e-6
            w_fd = log_so3(seg.orientation(t).T @ seg.orientation(min(t + h, 5.0))) / h
            if t + h <= 5.0:
                np.testing.assert_allclose(seg.angular_velocity(t), w_fd, atol=1e-4)


def test_so3_helpers_round_trip_and_jacobian_is_a_contraction():
    rng = np.random.default_rng(5)
    for _ in range(200):
        axis = rng.normal(size=3)
        r = axis / np.linalg.norm(axis) * rng.uniform(0, 3.1)  # log is defined up to π
        np.testing.assert_allclose(log_so3(exp_so3(r)), r, atol=1e-9)
        assert np.linalg.svd(right_jacobian(r), compute_uv=False).max() <= 1 + 1e-12


def test_rotation_rate_limit_is_respected_when_planning_with_orientation():
    path = PredictedPath(0.0, np.array([100.0, 0.0]), np.array([10.0, 5.0]))
    G = camera_placement_trajectory(path, 1000.0, 63.0, azimuth_deg=-90.0, marker_z_mm=40.0)
    start = (np.array([300.0, -450.0, 900.0]), np.zeros(3), np.zeros(3))
    without = plan_interception(start, 0.0, G, LIMITS, 10.0)
    with_rot = plan_interception(start, 0.0, G, LIMITS, 10.0, R0=np.eye(3))
    seg = with_rot.trajectory.segments[0]
    assert seg.max_rotation_rate() <= LIMITS.w_max * (1 + 1e-6)
    # turning the camera ~120° at 120°/s binds here: the rotation makes the plan longer
    assert with_rot.t_hit > without.t_hit
    assert seg.max_rotation_rate() >= 0.99 * LIMITS.w_max
    np.testing.assert_allclose(seg.orientation(with_rot.t_hit), G.rotation, atol=1e-9)


def test_trajectory_state_clamps_and_limits_validate():
    seg = QuinticSegment(1.0, 2.0, np.zeros(3), np.zeros(3), np.zeros(3), np.ones(3), np.zeros(3), np.zeros(3))
    traj = Trajectory([seg])
    np.testing.assert_allclose(traj.state(0.0)[0], 0.0)
    np.testing.assert_allclose(traj.state(9.0)[0], 1.0)
    with pytest.raises(PlanningError):
        Limits(np.zeros(3), np.ones(3), v_max=-1.0, a_max=1.0)
    with pytest.raises(PlanningError):
        Limits(np.ones(3), np.zeros(3), v_max=1.0, a_max=1.0)
    with pytest.raises(PlanningError):
        plan_interception((np.array([np.nan, 0, 0]), np.zeros(3), np.zeros(3)), 0.0, lambda t: None, LIMITS)
    cfg = RobotConfig(workspace_min_mm=(-1.0, -2.0, 3.0), workspace_max_mm=(4.0, 5.0, 6.0), v_max_mm_s=7.0,
                      a_max_mm_s2=8.0, w_max_deg_s=90.0)
    lim = Limits.from_config(cfg)
    assert lim.v_max == 7.0 and lim.a_max == 8.0 and np.isclose(lim.w_max, np.pi / 2)
    np.testing.assert_allclose([lim.box_min, lim.box_max], [[-1, -2, 3], [4, 5, 6]])
