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
