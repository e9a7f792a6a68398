"""The paired bootstrap of the suite's p95 difference (issue 14), checked against numpy's own
percentile and against known shifts, plus the per-image record of ``run_case``."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.bench import _vision_oracle as oracle
from labctl.bench._vision_paired import paired_p95
from labctl.bench._vision_suite import run_case


def test_identical_methods_give_zero_difference_and_zero_width_interval():
    x = np.random.default_rng(1).gamma(2.0, 1.0, 400)
    r = paired_p95(x, x, n_boot=300)
    assert r["diff"] == 0.0 and r["lo"] == 0.0 and r["hi"] == 0.0
    assert r["ours"] == np.percentile(x, 95)


@settings(max_examples=25, deadline=None)
@given(shift=st.floats(0.5, 5.0), seed=st.integers(0, 10_000))
def test_a_constant_shift_is_recovered_inside_the_interval(shift, seed):
    base = np.random.default_rng(seed).gamma(2.0, 1.0, 200)
    r = paired_p95(base + shift, base, n_boot=200, seed=seed)
    assert math.isclose(r["diff"], shift, rel_tol=1e-9)
    assert r["lo"] <= shift + 1e-9 and r["hi"] >= shift - 1e-9


def test_nan_images_are_left_out_per_method_and_odd_lengths_rejected():
    base = np.arange(1.0, 41.0)
    ours = base.copy()
    ours[-1] = np.nan  # the worst image not detected by us: our p95 comes from the rest
    r = paired_p95(ours, base, n_boot=50)
    assert r["ours"] == np.percentile(base[:-1], 95) and r["base"] == np.percentile(base, 95)
    assert r["diff"] < 0
    try:
        paired_p95(base[:-1], base[:-1], n_boot=5)
    except ValueError:
        pass
    else:
        raise AssertionError("an odd number of images is not whole pairs")


def test_run_case_per_image_matches_its_own_percentiles():
    res = run_case(oracle.Conditions(noise_std=8.0), {}, {}, n_pairs=3, seed=7, per_image=True)
    for m in ("labctl", "opencv"):
        v = np.asarray(res["per_image"][m]["normal_deg"])
        assert len(v) == 6
        assert np.isclose(np.percentile(v[~np.isnan(v)], 95), res[m]["normal_deg_p95"])


def test_nothing_detected_gives_none_not_nan():
    r = paired_p95([np.nan] * 4, [1.0, 2.0, 3.0, 4.0], n_boot=20)
    assert r["ours"] is None and r["diff"] is None and r["lo"] is None and r["base"] == np.percentile([1, 2, 3, 4], 95)


def _row(o, b, lo, hi):
    stats = {"confident_wrong": 0.0, "detected": 1.0, "normal_deg_median": 0.1, "centre_pct_median": 0.1}
    return {"condition": "gaussian noise", "strength": "σ 16", "visible": 1.0,
            "labctl": {**stats, "normal_deg_p95": o}, "opencv": {**stats, "normal_deg_p95": b},
            "paired": {"normal_deg_p95": {"diff": o - b, "lo": lo, "hi": hi}}}


def test_acceptance_fails_a_worse_p95_only_when_the_paired_interval_excludes_zero():
    from labctl.bench._vision_suite import acceptance

    noise = acceptance([_row(3.79, 3.38, -0.2, 1.1)])
    assert noise["ok"] and len(noise["inconclusive"]) == 1 and "σ 16" in noise["inconclusive"][0]
    worse = acceptance([_row(3.79, 3.38, 0.1, 0.9)])
    assert not worse["ok"] and "normal_deg_p95" in worse["failures"][0]
    better = acceptance([_row(2.0, 3.38, -2.0, -0.5)])
    assert better["ok"] and not better["inconclusive"]
