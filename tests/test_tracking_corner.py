"""Issue 18: after a zigzag corner the prediction settles back under 1.5× the bound, and stays there.

The reference is :mod:`labctl.bench.track_bound` (the Cramér-Rao bound of the two-leg model with an
unknown corner time, and its ML fit on the very same frames), which shares no code with the filter.
Before the corner-time refinement (docs/notes/planning.md, "Fourth round") the lab tracker was
0.9-1.4× the bound 0.5 s after the corner but 1.7-2.5× 1 s after it: the corner estimate was taken
from a window the corner was sliding out of, and the old track's post-corner innovations triggered a
second, wrong restart.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.bench.synthetic_tracks import compare_with_bound
from labctl.bench.track_bound import make_scenario
from labctl.config.lab import RunConfig, TrackingConfig
from labctl.tracking import MarkerTracker

FPS, SIGMA = RunConfig().fps, TrackingConfig().measurement_noise_mm


def _tracker(family):
    return lambda: MarkerTracker.from_config(TrackingConfig(), family=family)


@pytest.mark.parametrize("speed, family", [(4.0, "zigzag"), (50.0, None)])
def test_zigzag_corner_settles_and_stays_under_the_bound(speed, family):
    """5-s prediction RMS ≤ 1.5× min(CRB, ML) at 0.5 s and 1 s after the corner (slow informed, fast blind)."""
    res = compare_with_bound(_tracker(family), "zigzag", speed, runs=24, rate_hz=FPS, sigma_mm=SIGMA,
                             track_s=(), after_corner_s=(0.5, 1.0), seed=7000 + int(speed))
    for at in (2.5, 3.0):
        r = res[at]
        assert r["rms_mm"] <= 1.5 * min(r["crb_mm"], r["ml_rms_mm"]), (speed, at, r)


def test_one_corner_gives_one_restart_at_its_time():
    """The restart's own transient is not a second corner; the corner time is within a frame at 50 mm/s."""
    rng = np.random.default_rng(11)
    for _ in range(6):
        scn = make_scenario("zigzag", 50.0, 4.0, rate_hz=FPS, sigma_mm=SIGMA, heading_rad=rng.uniform(-np.pi, np.pi))
        trk = _tracker("zigzag")()
        for t, z in zip(scn.times, scn.measure(rng)):
            trk.update(t, z)
        assert len(trk.corners) == 1, trk.corners
        assert abs(trk.corners[0] - 2.0) <= 1.01 / FPS, trk.corners


@pytest.mark.parametrize("seed", [7000, 7005])
def test_a_corner_not_yet_detected_is_in_the_covariance(seed):
    """0.5 s after a 4 mm/s corner (~2 mm off the old line) the GLR has not always fired; the prediction's
    covariance weighs that corner in (``MarkerTracker._corner_suspicion``) instead of extending the old leg
    with a line's confidence. Before: on these seeds one run of 48 had a 5-s NEES of 1500-1700 (mean 65 / 38);
    the target is 2 (chi-square, 2 dof)."""
    rng = np.random.default_rng(seed)
    nees = []
    for _ in range(48):
        scn = make_scenario("zigzag", 4.0, 2.5, rate_hz=FPS, sigma_mm=SIGMA, heading_rad=rng.uniform(-np.pi, np.pi))
        trk = _tracker("zigzag")()
        for t, z in zip(scn.times, scn.measure(rng)):
            trk.update(t, z)
        mean, cov = trk.predict(t + 5.0)
        e = mean - scn.current_motion(t, [t + 5.0])[0]
        nees.append(float(e @ np.linalg.solve(cov, e)))
    assert max(nees) < 300.0 and np.mean(nees) < 6.0, (max(nees), np.mean(nees))


def test_the_path_is_the_predictions_mean_while_corners_are_weighed_in():
    """``predicted_path()`` (what the planner steers by) equals ``predict``'s mean and velocity at every frame
    around a 4 mm/s corner, suspected (not yet detected) and detected (its candidate times) alike."""
    rng = np.random.default_rng(5)
    kinds = set()
    for _ in range(4):
        scn = make_scenario("zigzag", 4.0, 3.5, rate_hz=FPS, sigma_mm=SIGMA, heading_rad=rng.uniform(-np.pi, np.pi))
        trk = _tracker("zigzag")()
        for t, z in zip(scn.times, scn.measure(rng)):
            trk.update(t, z)
            hyp = trk._corner_hypotheses()
            if hyp is None:
                continue
            kinds.add("detected" if hyp["cov"] is None else "suspected")
            future = t + np.array([0.0, 1.0, 5.0])
            p, v, _ = trk.predicted_path()(future)
            means, covs = trk.predict_path(future)
            np.testing.assert_allclose(p, means, atol=1e-9)
            np.testing.assert_allclose(v[0], trk.velocity(), atol=1e-9)
            assert np.all(np.linalg.eigvalsh(covs) > 0)
    assert kinds == {"detected", "suspected"}


def test_a_corner_between_frames_is_not_taken_for_one_on_a_frame():
    """A real corner lies anywhere between two frames; the bench's corners lie exactly on one. The new leg is
    anchored at the old track's position on the frame before the corner, so the anchor carries that frame
    interval's motion as uncertainty (``_anchor_cov``). Before, half a frame off the grid, the 5-s prediction
    1 s after a 100 mm/s corner was 9.7x the bound (NEES 5.3, 64 runs)."""
    res = compare_with_bound(_tracker("zigzag"), "zigzag", 100.0, runs=16, rate_hz=FPS, sigma_mm=SIGMA,
                             track_s=(), after_corner_s=(1.0,), seed=8200, corner_s=2.0 + 0.5 / FPS)
    (r,) = res.values()
    assert r["rms_mm"] <= 1.5 * min(r["crb_mm"], r["ml_rms_mm"]), r
    assert r["nees"] <= 4.0, r


@pytest.mark.parametrize("speed", [12.0, 50.0, 100.0])
def test_a_corner_the_table_stops_at_settles_under_the_bound(speed):
    """The lab's table (GRBL, 200 mm/s²) slows to rest at the zigzag's sharp corner and speeds up again
    (``zigzag_stop``, checked against the GRBL emulator's planner in test_tracking_bound.py). Told the table's
    acceleration, the tracker models both ramps; as an instant corner it was 8.2× / 3.6× / 2.3× the bound
    0.5 / 0.75 / 1 s after the stop at 50 mm/s (NEES 33 at 0.5 s; 16 runs, docs/notes/planning.md)."""
    accel = 200.0
    stops = lambda: MarkerTracker.from_config(TrackingConfig(), family="zigzag", stop_accel_mm_s2=accel)  # noqa: E731
    after = tuple(a for a in (0.5, 1.0, 2.0) if a > speed / accel)  # up to speed: the bound is finite
    res = compare_with_bound(stops, "zigzag_stop", speed, runs=16, rate_hz=FPS, sigma_mm=SIGMA, track_s=(),
                             after_corner_s=after, seed=9100 + int(speed), table_accel_mm_s2=accel)
    for r in res.values():  # NEES: 16 runs' mean, heavy-tailed (docs/notes/planning.md); the instant corner's is 33
        assert r["rms_mm"] <= 1.5 * min(r["crb_mm"], r["ml_rms_mm"]), (speed, r)
        assert r["nees"] <= 5.0, (speed, r)
    if speed == 50.0:  # the instant corner's straight new leg through the ramps, on the same runs
        res = compare_with_bound(_tracker("zigzag"), "zigzag_stop", speed, runs=16, rate_hz=FPS, sigma_mm=SIGMA,
                                 track_s=(), after_corner_s=(0.5,), seed=9150, table_accel_mm_s2=accel)
        (r,) = res.values()
        assert r["rms_mm"] > 3.0 * min(r["crb_mm"], r["ml_rms_mm"]), r



@given(speed1=st.floats(2.0, 120.0), speed2=st.floats(2.0, 120.0), accel=st.floats(20.0, 2000.0),
       h1=st.floats(-np.pi, np.pi), turn=st.floats(0.3, 3.0))
@settings(max_examples=60, deadline=None)
def test_the_trackers_stop_profiles_are_the_bounds_stopping_corner(speed1, speed2, accel, h1, turn):
    """The tracker's stop-corner leg ``p_s + v1·D1(τ) + v2·D2(τ)`` (τ from the slow-down's start) is
    ``bounds.positions("zigzag_stop")``, written apart and checked against the GRBL emulator's planner."""
    from labctl.bench.track_bound import positions
    from labctl.tracking.tracker import _stop_profiles

    v1 = speed1 * np.array([np.cos(h1), np.sin(h1)])
    v2 = speed2 * np.array([np.cos(h1 - turn), np.sin(h1 - turn)])
    th = np.r_[10.0, -5.0, v1, v2, 2.0, accel]
    r1, r2 = speed1 / accel, speed2 / accel
    t_s = 2.0 - r1  # the slow-down starts one ramp before it stands at the corner
    t = t_s + np.linspace(0.0, r1 + r2 + 0.5, 301)
    p_s = positions("zigzag_stop", th, [t_s])[0]
    down, down_rate, up, up_rate = _stop_profiles(t - t_s, r1, r2)
    ours = p_s + down[:, None] * v1 + up[:, None] * v2
    np.testing.assert_allclose(ours, positions("zigzag_stop", th, t), atol=1e-9 * max(1.0, speed1, speed2))
    dt = 1e-6
    vel = (positions("zigzag_stop", th, t + dt) - positions("zigzag_stop", th, t - dt)) / (2 * dt)
    smooth = (np.abs(t - 2.0) > 2 * dt) & (np.abs(t - t_s) > 2 * dt) & (np.abs(t - 2.0 - r2) > 2 * dt)
    np.testing.assert_allclose((down_rate[:, None] * v1 + up_rate[:, None] * v2)[smooth], vel[smooth],
                               atol=1e-4 * max(1.0, speed1, speed2))
