"""Issue 18: the 5-s prediction's covariance sits at the Cramér-Rao bound where the filter reaches it.

The reference is :func:`labctl.bench.track_bound.crb_prediction_cov` (independent of the filters). Before the
sixth round (docs/notes/planning.md) the lab's process noise (0.01 mm/s^1.5) put a line's 5-s covariance
after 4 s of tracking at 1.058x the bound. (After a corner: tests/test_tracking_corner.py.)
"""

from __future__ import annotations

import numpy as np

from labctl.bench.synthetic_tracks import compare_with_bound
from labctl.config.lab import RunConfig, TrackingConfig
from labctl.tracking import MarkerTracker

FPS, SIGMA = RunConfig().fps, TrackingConfig().measurement_noise_mm


def _tracker(family):
    return lambda: MarkerTracker.from_config(TrackingConfig(), family=family)


def test_a_lines_covariance_is_the_bound_after_4_s():
    r = compare_with_bound(_tracker("line"), "line", 50.0, runs=12, rate_hz=FPS, sigma_mm=SIGMA, with_ml=False,
                           track_s=(4.0,), seed=8050)[4.0]
    assert 0.98 <= r["cov_to_crb"] <= 1.02, r  # measured 1.000; 1.058 with process noise 0.01


class _LastMeasurement:
    """A stand-in tracker (the reference NEES does not depend on it): the newest measurement, unit covariance."""

    def update(self, t, z):
        self.z = z
        return True

    def predict(self, t):
        return self.z, np.eye(2)


def test_the_reference_nees_is_consistent_on_a_line():
    """On a line the ML fit is the optimal filter and the Cramér-Rao covariance is its own, so its mean NEES over
    many runs is chi-square(2)'s: inside the 95 % band (the ML fit and the bound are separate code)."""
    r = compare_with_bound(_LastMeasurement, "line", 12.0, runs=256, rate_hz=FPS, sigma_mm=SIGMA,
                           track_s=(2.0,), seed=12)[2.0]
    lo, hi = r["nees_bounds"]
    assert lo <= r["nees_ml_crb"] <= hi, r


def test_the_bench_names_the_nees_cells_the_reference_fails_too():
    from labctl.bench.planning import acceptance_summary

    def cell(at, nees, ref):
        return {"model": "m", "family": "line", "speed_mm_s": 12.0, "at_s": at, "ratio": 1.0, "ratio_limit": 1.2,
                "ratio_holds": True, "nees": nees, "nees_holds": 1.54 <= nees <= 2.52, "nees_ml_crb": ref,
                "ml_nees_holds": None if ref is None else 1.54 <= ref <= 2.52}

    s = acceptance_summary([cell(2.0, 1.36, 1.44), cell(4.0, 3.0, 2.0), cell(1.0, 2.0, 2.0), cell(3.0, 1.0, None)])["m"]
    assert (s["cells"], s["nees_holds"], s["nees_fails_reference_too"]) == (4, 1, 1)
    assert s["nees_fails"] == ["line @ 12 at 2 s: 1.36 (reference 1.44)", "line @ 12 at 4 s: 3.00 (reference 2.00)",
                               "line @ 12 at 3 s: 1.00"]


def test_the_curve_covariance_is_the_posteriors_where_the_truth_follows_the_prior():
    """After 2 s at 4 mm/s (8 mm of path) the curvature is the prior's, N(0, (1/80 mm)²). On the bench's one 200-mm
    arc, at 0.4 σ of the prior's mean, the errors are smaller than the posterior says (NEES far below 2). With
    each run's curvature drawn from that prior, as a Bayesian filter's covariance assumes, the same tracker's
    mean NEES is chi-square(2)'s. The truth, the scenarios and the NEES are :mod:`labctl.bench.track_bound` and
    :func:`compare_with_bound`, not the tracker."""
    sigma = _tracker("arc")().curvature_prior_sigma
    assert sigma == 1 / 80

    def cell(curvature_sigma):
        return compare_with_bound(_tracker("arc"), "arc", 4.0, runs=128, rate_hz=FPS, sigma_mm=SIGMA, with_ml=False,
                                  track_s=(2.0,), seed=4, curvature_sigma=curvature_sigma)[2.0]

    fixed, drawn = cell(None), cell(sigma)
    lo, hi = drawn["nees_bounds"]
    assert lo <= drawn["nees"] <= hi, drawn  # measured 2.05 (the bench's 256 runs: 2.05)
    assert fixed["nees"] < lo, fixed  # measured 0.97 (the bench's 64 runs: 1.03, 256: 1.09)
