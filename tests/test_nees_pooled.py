"""The pooled NEES statistic against answers known in closed form.

Oracles: χ²(2)'s quantiles are exact, ``-2 ln(1 − p)`` (an exponential of mean 2); a Gaussian error
e ~ N(0, Σ) scored against a claimed covariance P has E[eᵀP⁻¹e] = tr(P⁻¹Σ) and variance 2 tr((P⁻¹Σ)²);
and a consistent filter's pooled mean falls inside its 95 % band in 95 % of experiments."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import binom

from labctl.bench.nees import nees_band, pooled_by_family, pooled_nees


def _cells(rng, Sigma, P, runs_per_cell, n_cells, family="line"):
    """Cells of Monte-Carlo NEES: errors drawn from N(0, Sigma), scored against the claimed P."""
    L = np.linalg.cholesky(Sigma)
    Pinv = np.linalg.inv(P)
    out = []
    for k in range(n_cells):
        e = rng.standard_normal((runs_per_cell, 2)) @ L.T
        nees = np.einsum("ni,ij,nj->n", e, Pinv, e)
        out.append({"family": family, "at_s": 2.0 + k % 2, "after_corner": False, "nees": float(nees.mean()),
                    "runs": runs_per_cell, "speed_mm_s": 4.0 * (k + 1)})
    return out


def test_the_band_of_one_sample_is_the_exponentials_quantiles():
    lo, hi = nees_band(1)
    assert lo == pytest.approx(-2 * math.log(0.975), rel=1e-9)
    assert hi == pytest.approx(-2 * math.log(0.025), rel=1e-9)


def test_the_band_narrows_round_two_as_the_normal_limit_says():
    n = 20000
    lo, hi = nees_band(n)  # mean of n χ²(2): 2 ± 1.96·sqrt(4/n) to O(1/n)
    half = 1.959964 * math.sqrt(4.0 / n)
    assert lo == pytest.approx(2 - half, abs=2e-3) and hi == pytest.approx(2 + half, abs=2e-3)
    assert lo < 2 < hi


def test_pooling_weights_cells_by_their_runs():
    cells = [{"nees": 1.0, "runs": 10}, {"nees": 3.0, "runs": 30}]
    p = pooled_nees(cells)
    assert p["nees"] == pytest.approx(2.5) and p["runs"] == 40 and p["cells"] == 2
    assert p["nees_95"] == list(nees_band(40))


def test_the_pooled_mean_is_the_trace_of_claimed_inverse_times_true():
    rng = np.random.default_rng(18)
    Sigma = np.array([[4.0, 1.2], [1.2, 1.0]])
    P = np.array([[3.0, 0.0], [0.0, 2.0]])  # wrong shape and scale
    A = np.linalg.solve(P, Sigma)
    expect, var = float(np.trace(A)), 2.0 * float(np.trace(A @ A))
    p = pooled_nees(_cells(rng, Sigma, P, runs_per_cell=256, n_cells=40))
    se = math.sqrt(var / p["runs"])
    assert abs(p["nees"] - expect) < 4 * se
    assert not p["holds"]  # tr(P⁻¹Σ) = 1.83 + 0.5 ≠ 2, far outside the band of 10,240 runs


@pytest.mark.parametrize("scale, expected_holds", [(1.0, True), (1.3, False), (1 / 1.3, False)])
def test_a_scaled_covariance_is_caught_and_a_consistent_one_is_not(scale, expected_holds):
    rng = np.random.default_rng(33)
    Sigma = np.array([[2.0, -0.5], [-0.5, 1.0]])
    # claimed P = Sigma / scale: E[NEES] = 2·scale
    p = pooled_nees(_cells(rng, Sigma, Sigma / scale, runs_per_cell=64, n_cells=32))
    assert p["holds"] is expected_holds
    assert p["nees"] == pytest.approx(2.0 * scale, rel=0.05)


def test_a_consistent_filters_pooled_mean_is_inside_its_band_95_percent_of_the_time():
    rng = np.random.default_rng(7)
    Sigma = np.diag([1.5, 0.4])
    experiments = 400
    inside = sum(pooled_nees(_cells(rng, Sigma, Sigma, runs_per_cell=16, n_cells=4))["holds"]
                 for _ in range(experiments))
    lo, hi = binom.ppf(0.001, experiments, 0.95), binom.ppf(0.999, experiments, 0.95)
    assert lo <= inside <= hi


def test_by_family_pools_each_family_and_each_instant():
    rng = np.random.default_rng(1)
    S = np.eye(2)
    rows = _cells(rng, S, S, 64, 4, "line") + _cells(rng, S, S / 2.0, 64, 4, "zigzag")
    out = pooled_by_family(rows)
    assert set(out["by_family"]) == {"line", "zigzag"}
    line = out["by_family"]["line"]
    assert line["runs"] == 256 and line["nees"] == pytest.approx(np.mean([r["nees"] for r in rows[:4]]))
    assert line["holds"] == (line["nees_95"][0] <= line["nees"] <= line["nees_95"][1])
    assert not out["by_family"]["zigzag"]["holds"]  # E[NEES] = 4
    assert out["holds"] == f"{int(line['holds'])} / 2"
    assert set(out["by_family_instant"]) == {"line 2 s", "line 3 s", "zigzag 2 s", "zigzag 3 s"}
    assert out["by_family_instant"]["line 2 s"]["runs"] == 128
    merged = pooled_by_family(rows, family_of=lambda r: "all")
    assert merged["by_family"]["all"]["nees"] == pytest.approx(
        (out["by_family"]["line"]["nees"] + out["by_family"]["zigzag"]["nees"]) / 2)


def test_no_runs_is_refused():
    with pytest.raises(ValueError):
        pooled_nees([])
    with pytest.raises(ValueError):
        nees_band(0)
