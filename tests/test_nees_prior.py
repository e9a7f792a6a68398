"""The truth drawn from the tracker's own prior, for the Bayes-consistent NEES of ``labctl bench planning``.

Oracles: the lab's config (``tracking.family_prior``) and the tracker's declared defaults (its signature), not the
prior object under test; the distributions themselves by a Kolmogorov-Smirnov test (the curvature against
N(0, σ²)) and an exact binomial test (the share of curves), with a fixed seed, and the same tests rejecting a
prior 30 % too wide; and the drawn runs against the family's own runs on the same seeds.
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import binomtest, kstest, norm

from labctl.bench.nees import TrackPrior
from labctl.bench.synthetic_tracks import compare_with_bound
from labctl.config.lab import RunConfig, TrackingConfig
from labctl.tracking import MarkerTracker

FPS, SIGMA = RunConfig().fps, TrackingConfig().measurement_noise_mm
DECLARED = inspect.signature(MarkerTracker).parameters


def _tracker(family):
    return MarkerTracker.from_config(TrackingConfig(), family=family)


@pytest.mark.parametrize("family", ["line", "arc", "circle", "zigzag"])
def test_the_prior_is_the_one_the_config_and_the_tracker_declare(family):
    prior = TrackPrior.of(_tracker(family))
    assert prior.curve_probability == getattr(TrackingConfig().family_prior, family)
    assert prior.curvature_sigma == DECLARED["init_curvature_sigma"].default
    assert prior.speed_sigma == DECLARED["init_speed_sigma"].default


def test_a_blind_tracker_declares_the_blind_curve_prior():
    assert TrackPrior.of(_tracker(None)).curve_probability == TrackingConfig().curve_prior


@settings(max_examples=60, deadline=None)
@given(p=st.floats(0.0, 1.0), sigma=st.floats(1e-5, 1.0), runs=st.integers(0, 300), seed=st.integers(0, 2**31))
def test_every_draw_lies_in_the_priors_support(p, sigma, runs, seed):
    curved, kappa = TrackPrior(p, sigma, 150.0).draw(runs, seed)
    assert curved.shape == kappa.shape == (runs,) and curved.dtype == bool
    assert np.all(np.isfinite(kappa))
    assert np.all(kappa[~curved] == 0.0)  # a line has no curvature
    assert np.all(kappa[curved] != 0.0)  # a curve's is continuous: 0 has probability 0
    if p == 0.0:
        assert not curved.any()
    if p == 1.0:
        assert curved.all()


@pytest.mark.parametrize("bad", [dict(curve_probability=-0.1), dict(curve_probability=1.5),
                                 dict(curvature_sigma=0.0), dict(speed_sigma=float("nan"))])
def test_a_prior_no_truth_can_be_drawn_from_is_refused(bad):
    with pytest.raises(ValueError):
        TrackPrior(**{"curve_probability": 0.5, "curvature_sigma": 0.01, "speed_sigma": 150.0, **bad})


def test_the_draw_is_the_declared_distribution_and_a_wider_one_is_told_apart():
    declared = TrackPrior.of(_tracker("arc"))
    mixed = TrackPrior(0.3, declared.curvature_sigma, declared.speed_sigma)  # a share a binomial test can see
    n = 4000
    for prior in (declared, mixed):
        curved, kappa = prior.draw(n, seed=18)
        assert binomtest(int(curved.sum()), n, prior.curve_probability).pvalue > 0.01
        assert kstest(kappa[curved], norm(0.0, prior.curvature_sigma).cdf).pvalue > 0.01
    curved, kappa = TrackPrior(0.3 * 1.3, declared.curvature_sigma * 1.3, declared.speed_sigma).draw(n, seed=18)
    assert binomtest(int(curved.sum()), n, 0.3).pvalue < 0.01
    assert kstest(kappa[curved], norm(0.0, declared.curvature_sigma).cdf).pvalue < 0.01


def _cell(family, **kw):
    return compare_with_bound(lambda: _tracker("arc"), family, 12.0, runs=6, rate_hz=FPS, sigma_mm=SIGMA,
                              track_s=(2.0,), seed=12, **kw)[2.0]


def test_a_prior_without_curves_runs_the_lines_own_runs_and_a_prior_of_curves_the_drawn_radius():
    """Drawn straight, an arc's cell is the line's cell on the same seeds (headings, noise, bound, ML fit); drawn
    curved every time, it is the curvature-drawn cell: the mode and the curvature have their own streams."""
    sigma = TrackPrior.of(_tracker("arc")).curvature_sigma
    straight = _cell("arc", prior=TrackPrior(0.0, sigma, 150.0))
    assert straight.pop("curved_runs") == 0
    line = _cell("line")
    assert line.pop("curved_runs") is None
    assert straight == line
    curves = _cell("arc", prior=TrackPrior(1.0, sigma, 150.0))
    assert curves.pop("curved_runs") == 6
    drawn = _cell("arc", curvature_sigma=sigma)
    drawn.pop("curved_runs")
    assert curves == drawn
    assert curves["crb_mm"] != line["crb_mm"]  # the curves' runs are curves: their own bound


def test_a_zigzag_is_not_drawn_from_a_line_or_curve_prior():
    with pytest.raises(ValueError, match="zigzag"):
        _cell("zigzag", prior=TrackPrior(0.5, 0.01, 150.0))


@pytest.mark.slow
def test_the_bench_pools_the_bayes_nees_per_family_inside_its_band():
    """``labctl bench planning``'s Bayes table, quick (16 runs a cell at 12 and 100 mm/s): one family per prior
    (arc and circle declare the same), every cell beside the ML reference on its runs, the curves drawn at the
    prior's share, and each family's pooled mean inside its band."""
    from labctl.bench.nees import nees_band, pooled_by_family
    from labctl.bench.planning import _bayes_table

    rows = _bayes_table(True)
    fams = {r["family"] for r in rows}
    assert fams == {"line", "arc / circle", "zigzag"}
    assert all(r["nees_ml_crb"] is not None and r["runs"] == 16 for r in rows)
    curves = [r for r in rows if r["family"] == "arc / circle"]
    arc = TrackingConfig().family_prior.arc
    for r in curves:  # 16 draws each: a binomial test at the declared share
        assert binomtest(r["curved_runs"], 16, arc).pvalue > 0.001
    pooled = pooled_by_family(rows)
    for fam, p in pooled["by_family"].items():
        cells = [r for r in rows if r["family"] == fam]
        assert p["runs"] == 16 * len(cells) and p["nees_95"] == list(nees_band(p["runs"]))
        assert p["holds"], (fam, p)
    assert pooled["holds"] == "3 / 3"
