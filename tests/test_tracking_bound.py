"""Issue 18: the estimation bound, and the trackers measured against it (paper §4.2).

The bound (labctl.bench.track_bound) shares no code with the filters; here it is itself checked
against closed forms that owe nothing to it: the textbook variance of a least-squares line's
extrapolation, and an exact circle.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.bench.synthetic_tracks import compare_with_bound
from labctl.bench.track_bound import crb_prediction_cov, crb_prediction_rms, make_scenario, ml_prediction, positions
from labctl.config.lab import RunConfig, TrackingConfig
from labctl.planning import camera_placement_trajectory
from labctl.planning.targets import prediction_margin_mm, viewing_distance_with_margin
from labctl.tracking import MarkerTracker

SIGMA = TrackingConfig().measurement_noise_mm  # the noise the tracker is told about (lab.yaml: 0.7 mm)
FPS = RunConfig().fps


def test_line_bound_is_the_least_squares_extrapolation_variance():
    """Per axis: σ² (1/N + (t_p − t̄)² / Σ(t − t̄)²) for a straight-line fit (any regression textbook)."""
    scn = make_scenario("line", 12.0, 4.0, rate_hz=FPS, sigma_mm=SIGMA)
    for n in (31, 61, 121):
        t = scn.times[:n]
        tp = t[-1] + 5.0
        var_axis = SIGMA**2 * (1 / n + (tp - t.mean()) ** 2 / np.sum((t - t.mean()) ** 2))
        assert crb_prediction_rms(scn, n, 5.0) == pytest.approx(np.sqrt(2 * var_axis), rel=1e-6)


def test_turn_model_is_an_exact_circle_and_ml_recovers_it_from_clean_data():
    scn = make_scenario("circle", 50.0, 6.0, sigma_mm=SIGMA, heading_rad=0.7)
    r = 50.0 / scn.theta[4]
    centre = scn.theta[:2] + r * np.array([-np.sin(0.7), np.cos(0.7)])
    p = positions("circle", scn.theta, scn.times)
    np.testing.assert_allclose(np.hypot(*(p - centre).T), r, rtol=1e-12)
    clean = scn.truth(scn.times)
    np.testing.assert_allclose(ml_prediction(scn, clean, 61, 5.0), scn.truth([scn.times[60] + 5.0])[0], atol=1e-6)
    # the bound shrinks with more data and grows with the horizon
    assert crb_prediction_rms(scn, 121, 5.0) < crb_prediction_rms(scn, 61, 5.0) < crb_prediction_rms(scn, 61, 8.0)


def _lab_tracker():
    return MarkerTracker.from_config(TrackingConfig())


def _ct_tracker():
    return MarkerTracker.from_config(TrackingConfig(model="ct"))


# Where the acceptance holds in `labctl bench planning` with a margin (64 runs; docs/notes/planning.md lists
# every cell, including the ones that fail and why). 16 runs here keep the test quick.
SMOOTH_CASES = [("line", 50.0), ("arc", 100.0), ("circle", 50.0)]


@pytest.mark.parametrize(("family", "speed"), SMOOTH_CASES)
def test_lab_tracker_reaches_the_bound_on_smooth_paths(family, speed):
    """After 2 s: RMS ≤ 1.2× the bound; after 4 s: ≤ 1.3×.

    With this few runs the bound is the ML fit of the true model on the very same measurements
    (paired: the sampling noise of a 12-run RMS, ~20 %, is common to both); the bench's 64-run
    table uses the smaller of that and the CRB. And the 5-s NEES (2 dof) inside its two-sided
    95 % bounds for that many runs: a CV mode at 1e-6 whose 5-s prediction is 500 mm off added as
    much spread as the whole covariance on a fast circle, and the manoeuvre mode's mixing doubled
    the CV mode's velocity variance on fast lines (NEES 0.7-0.9); weights below 1e-3 are dropped now.
    """
    res = compare_with_bound(_lab_tracker, family, speed, runs=12, rate_hz=FPS, sigma_mm=SIGMA, seed=int(speed))
    for t, limit in ((2.0, 1.2), (4.0, 1.3)):
        r = res[t]
        assert r["rms_mm"] <= limit * r["ml_rms_mm"], (family, speed, t, r)
        lo, hi = r["nees_bounds"]
        assert lo <= r["nees"] <= hi, (family, speed, t, r)


def test_ct_refit_is_as_good_as_the_ml_fit_on_a_fast_circle():
    """The CT mode re-linearised over its frames (Gauss-Newton) matches the ML fit of the true model on the
    same measurements; the EKF alone was 1.24× the ML there (1.35× the CRB) after 4 s."""
    res = compare_with_bound(_ct_tracker, "circle", 50.0, runs=12, rate_hz=FPS, sigma_mm=SIGMA, seed=50)
    for t in (2.0, 4.0):
        r = res[t]
        assert r["rms_mm"] <= 1.03 * r["ml_rms_mm"], (t, r)
    assert res[4.0]["rms_mm"] <= 1.3 * min(res[4.0]["crb_mm"], res[4.0]["ml_rms_mm"])


def test_curve_prior_balances_the_confusable_line_and_circle():
    """At 12 mm/s after 2 s the 80 mm circle's curvature is 3.1σ of its CRB from a line: no rule meets 1.2×
    on both (docs/notes/planning.md). The lab's curve prior is chosen so neither is worse than ~2.2× (64
    runs in the bench); the old prior (0.2) left the line at 3.8×."""
    worst = 0.0
    for family in ("line", "circle"):
        r = compare_with_bound(_lab_tracker, family, 12.0, runs=16, rate_hz=FPS, sigma_mm=SIGMA, seed=12,
                               track_s=(2.0,))[2.0]
        worst = max(worst, r["rms_mm"] / min(r["crb_mm"], r["ml_rms_mm"]))
    assert worst <= 2.6, worst


def test_zigzag_corner_switches_modes_within_a_few_frames_and_settles_near_the_bound():
    for speed in (12.0, 50.0):
        scn = make_scenario("zigzag", speed, 2.5, rate_hz=FPS, sigma_mm=SIGMA)
        trk = _lab_tracker()
        switched = None
        for k, (t, z) in enumerate(zip(scn.times, scn.measure(np.random.default_rng(3)))):
            trk.update(t, z)
            if switched is None and t > 2.0 and (trk.mode_probabilities[2] > 0.5 or trk.corners):
                switched = k - 60
        assert switched is not None and switched <= 8, (speed, switched)
        assert trk.corners and abs(trk.corners[-1] - 2.0) <= 0.05
        res = compare_with_bound(_lab_tracker, "zigzag", speed, runs=12, rate_hz=FPS, sigma_mm=SIGMA,
                                 track_s=(), after_corner_s=(0.5,), seed=int(speed))
        r = res[2.5]
        assert r["rms_mm"] <= 1.5 * min(r["crb_mm"], r["ml_rms_mm"]), (speed, r)


def test_predicted_path_follows_the_arc_and_feeds_a_curved_g():
    """The tracker's mean path on a circle is the circle (not its tangent), and so is G(t)."""
    scn = make_scenario("circle", 50.0, 4.0, rate_hz=FPS, sigma_mm=SIGMA, heading_rad=-0.4)
    trk = _lab_tracker()
    for t, z in zip(scn.times, scn.measure(np.random.default_rng(5))):
        trk.update(t, z)
    future = trk.time + np.linspace(0.0, 3.0, 7)
    p, v, a = trk.predicted_path()(future)
    truth = scn.truth(future)
    assert np.max(np.hypot(*(p - truth).T)) < 3.0
    np.testing.assert_allclose(p, trk.predict_path(future)[0], atol=1e-9)  # the same mean as predict()
    np.testing.assert_allclose(np.hypot(*a.T), 50.0**2 / 80.0, rtol=0.1)  # centripetal v²/r
    G = camera_placement_trajectory(trk.predicted_path(), 1000.0, 63.0, marker_z_mm=30.0)
    gp, gv, _ = G(future)
    np.testing.assert_allclose(gp[:, :2] - gp[0, :2], p - p[0], atol=1e-9)
    np.testing.assert_allclose(gv[:, :2], v, atol=1e-9)


def test_prediction_margin_and_viewing_distance():
    cov = np.array([[4.0, 0.0], [0.0, 1.0]])
    assert prediction_margin_mm(cov) == pytest.approx(6.0)
    rot = np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    assert prediction_margin_mm(rot @ cov @ rot.T, n_sigma=2.0) == pytest.approx(4.0)
    assert viewing_distance_with_margin(1000.0, 6.0, np.deg2rad(20.0)) == 1000.0  # a small margin changes nothing
    far = viewing_distance_with_margin(1000.0, 300.0, np.deg2rad(20.0), marker_radius_mm=10.0)
    assert far == pytest.approx(310.0 / (0.5 * np.tan(np.deg2rad(20.0))))


def test_stopping_corner_is_how_the_grbl_planner_turns_the_lab_zigzag():
    """``zigzag_stop`` (the bench's diagnostic of the table's corners) against the GRBL emulator's look-ahead
    planner (junction deviation, trapezoids; checked against the firmware in test_grbl_firmware): the lab
    program's 97° turn at 50 mm/s and 200 mm/s², sampled around the instant the carriage is nearest the
    vertex. The bound's model stands still there; GRBL's junction speed is ~2 mm/s. The bound's corners in
    :data:`FAMILIES` are instant instead: 0.25 s of this ramp at 50 mm/s is where the lab's tracker is furthest
    from it (docs/notes/planning.md, seventh round)."""
    from labctl.bench.track_bound import ZIGZAG_TURN_RAD
    from labctl.sim.clock import VirtualClock
    from labctl.sim.emulators.grbl import GrblEmulator

    clk = VirtualClock()
    g = GrblEmulator(clk, accel_mm_s2=200.0, homing=False, start_mm=(200.0, 250.0, 0.0))
    u2 = np.array([np.cos(-ZIGZAG_TURN_RAD), np.sin(-ZIGZAG_TURN_RAD)])
    vertex, end = np.array([300.0, 250.0]), np.array([300.0, 250.0]) + 100.0 * u2
    g.receive(f"G1 X{vertex[0]:.3f} Y{vertex[1]:.3f} F3000\nG1 X{end[0]:.3f} Y{end[1]:.3f}\n".encode())
    clk.sleep(6.0)
    g.advance(clk.t)
    ts = np.arange(0.5, 5.0, 0.001)
    p = np.array([g.position_at(t)[:2] for t in ts])
    t_c = ts[np.argmin(np.hypot(*(p - vertex).T))]
    window = np.abs(ts - t_c) < 0.8  # both ramps (0.25 s) and cruise on either side
    model = positions("zigzag_stop", np.r_[vertex, 50.0, 0.0, 50.0 * u2, t_c, 200.0], ts[window])
    miss = np.hypot(*(p[window] - model).T)
    # GRBL keeps ~2.2 mm/s through the junction, so its legs run 11 ms (0.55 mm) ahead of a full stop's
    assert np.max(miss) < 0.7 and np.min(miss) < 0.05, (np.max(miss), np.min(miss))


@given(speed=st.floats(2.0, 120.0), accel=st.floats(20.0, 2000.0), h1=st.floats(-np.pi, np.pi),
       turn=st.floats(0.3, 3.0))
@settings(max_examples=60, deadline=None)
def test_stopping_corner_stands_at_the_vertex_keeps_to_its_speed_and_ramps_at_a(speed, accel, h1, turn):
    """``zigzag_stop`` in closed form: at rest on the vertex at t_c, never faster than the leg's speed, its
    acceleration never above ``a``, and the instant corner's legs shifted by half a ramp once it is over."""
    v1 = speed * np.array([np.cos(h1), np.sin(h1)])
    v2 = speed * np.array([np.cos(h1 - turn), np.sin(h1 - turn)])
    th = np.r_[10.0, -5.0, v1, v2, 2.0, accel]
    ramp = speed / accel
    dt = 1e-4
    t = 2.0 + np.linspace(-ramp - 0.2, ramp + 0.2, 401)
    p = positions("zigzag_stop", th, t)
    v = (positions("zigzag_stop", th, t + dt) - positions("zigzag_stop", th, t - dt)) / (2 * dt)
    acc = (positions("zigzag_stop", th, t + dt) - 2 * p + positions("zigzag_stop", th, t - dt)) / dt**2
    np.testing.assert_allclose(positions("zigzag_stop", th, [2.0])[0], th[:2], atol=1e-12)
    assert np.all(np.hypot(*v.T) <= speed * (1 + 1e-6))
    kink = np.abs(np.abs(t - 2.0) - ramp) < 2 * dt  # the trapezoid's corners, and the vertex itself
    kink |= np.abs(t - 2.0) < 2 * dt
    assert np.all(np.hypot(*acc[~kink].T) <= accel * (1 + 1e-3) + 1e-6)
    after = t > 2.0 + ramp
    instant = positions("zigzag", th[:7], t[after] - ramp / 2)
    np.testing.assert_allclose(p[after], instant, atol=1e-9 * max(1.0, speed))


def test_line_bound_with_dropped_frames_is_the_fit_over_the_frames_kept():
    """A bound over a subset of frames (``keep``) is the textbook extrapolation variance over those times."""
    scn = make_scenario("line", 50.0, 3.0, rate_hz=FPS, sigma_mm=SIGMA)
    keep = np.random.default_rng(4).random(len(scn.times)) >= 0.3
    keep[60] = True
    t = scn.times[:61][keep[:61]]
    tp = t[-1] + 5.0
    var_axis = SIGMA**2 * (1 / len(t) + (tp - t.mean()) ** 2 / np.sum((t - t.mean()) ** 2))
    assert crb_prediction_rms(scn, 61, 5.0) < np.sqrt(2 * var_axis)  # fewer frames, a wider bound
    assert np.sqrt(np.trace(crb_prediction_cov(scn, 61, 5.0, keep=keep))) == pytest.approx(np.sqrt(2 * var_axis),
                                                                                           rel=1e-6)
    clean = scn.truth(scn.times)
    np.testing.assert_allclose(ml_prediction(scn, clean, 61, 5.0, keep=keep), scn.truth([scn.times[60] + 5.0])[0],
                               atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(st.floats(-0.6, 0.6), st.floats(-0.6, 0.6), st.floats(0.0, 60.0), st.floats(500.0, 1500.0),
       st.floats(0.3, 1.0))
def test_a_view_holds_the_marker_where_a_pinhole_says_it_lies_in_the_central_image(fx, fy, margin, depth, fill):
    """``view_holds_marker`` against the pinhole projection written out here: a camera looking down from
    ``depth`` mm sees a point at image offset (u, v) px; it holds when |u| + margin·f/depth ≤ fill·w/2 (and in v)."""
    from labctl.bench.synthetic_images import issue_camera
    from labctl.geometry import look_at
    from labctl.planning.targets import view_holds_marker

    cam = issue_camera()
    f = 2500.0
    T_w_c = look_at([0.0, 0.0, depth], [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    u, v = fx * cam.width / 2, fy * cam.height / 2  # the wanted pixel offsets from the image centre
    x_c, y_c = u * depth / f, v * depth / f  # camera frame: +x right, +y down
    marker_w = (T_w_c @ np.array([x_c, y_c, depth, 1.0]))[:3]
    slack = margin * f / depth
    expected = abs(u) + slack <= fill * cam.width / 2 and abs(v) + slack <= fill * cam.height / 2
    if min(abs(abs(u) + slack - fill * cam.width / 2), abs(abs(v) + slack - fill * cam.height / 2)) > 1e-6:
        assert view_holds_marker(cam, T_w_c, marker_w, margin, fill) == expected
    assert not view_holds_marker(cam, T_w_c, (T_w_c @ np.array([0.0, 0.0, -depth, 1.0]))[:3], 0.0)  # behind
