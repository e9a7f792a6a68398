"""Ellipse fit (paper §3.1, eqs. 1–2): exactness, noise behaviour against OpenCV, bad input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.vision import Ellipse, EllipseFitError, ellipse_from_cv_box, fit_ellipse

ellipse_params = st.tuples(
    st.floats(-500, 1000), st.floats(-500, 1000),  # centre
    st.floats(2.0, 300.0), st.floats(0.2, 1.0),  # major semi-axis, minor/major ratio
    st.floats(-np.pi, np.pi),
)


def _make(params) -> Ellipse:
    cx, cy, a, ratio, ang = params
    return Ellipse.from_params((cx, cy), (a, a * ratio), ang)


def _same_angle(a1, a2, tol):
    d = (a1 - a2 + np.pi / 2) % np.pi - np.pi / 2
    return abs(d) < tol


@settings(max_examples=60, deadline=None)
@given(ellipse_params)
def test_params_conic_round_trip(params):
    e = _make(params)
    back = Ellipse.from_conic(e.conic * -3.7)  # scale and sign do not matter
    np.testing.assert_allclose(back.center, e.center, atol=1e-6 * (1 + np.abs(e.center).max()))
    np.testing.assert_allclose(back.axes, e.axes, rtol=1e-7)
    if e.axes[0] / e.axes[1] > 1.001:
        assert _same_angle(back.angle, e.angle, 1e-6)
    assert -np.pi / 2 < back.angle <= np.pi / 2
    # its own points lie on it
    assert np.max(e.sampson_distances(e.points(50))) < 1e-6 * e.axes[0]


@settings(max_examples=60, deadline=None)
@given(ellipse_params, st.integers(5, 200), st.floats(0.0, 2 * np.pi))
def test_exact_points_give_the_exact_ellipse(params, n, t0):
    e = _make(params)
    arc = np.pi if n < 12 else 2 * np.pi  # even a few points on half the ellipse determine it
    fit = fit_ellipse(e.points(n, t0, t0 + arc))
    scale = e.axes[0]
    np.testing.assert_allclose(fit.center, e.center, atol=1e-5 * scale + 1e-7 * np.abs(e.center).max())
    np.testing.assert_allclose(fit.axes, e.axes, rtol=1e-5)


@settings(max_examples=30, deadline=None)
@given(ellipse_params, st.integers(0, 2**31 - 1))
def test_a_doubled_weight_equals_a_duplicated_point(params, seed):
    e = _make(params)
    rng = np.random.default_rng(seed)
    pts = e.points(40) + rng.normal(0, 0.02 * e.axes[1], (40, 2))
    dup = np.vstack([pts, pts[:7]])
    w = np.ones(40)
    w[:7] = 2.0
    a, b = fit_ellipse(dup), fit_ellipse(pts, w)
    np.testing.assert_allclose(a.conic, b.conic, atol=1e-8)


def test_weights_compensate_non_uniform_sampling():
    # dense sampling of one half, sparse of the other, with a constant radial error on the dense
    # half: arc-length weights (paper's w_i) restore the balance the unweighted fit loses
    t = np.concatenate([np.linspace(0, np.pi, 300, endpoint=False), np.linspace(np.pi, 2 * np.pi, 20, endpoint=False)])
    ca, sa = np.cos(0.3), np.sin(0.3)
    x, y = 50 * np.cos(t), 30 * np.sin(t)
    pts = np.column_stack([ca * x - sa * y, sa * x + ca * y])
    grow = np.where(t < np.pi, 1.01, 0.99)[:, None]  # dense half 1 % out, sparse half 1 % in
    pts = pts * grow
    w = np.where(t < np.pi, np.pi / 300, np.pi / 20)
    unweighted, weighted = fit_ellipse(pts), fit_ellipse(pts, w)
    assert abs(weighted.axes[0] - 50) < 0.2 * abs(unweighted.axes[0] - 50)


def _centre_rms(arc: float, trials: int, seed: int):
    rng = np.random.default_rng(seed)
    errs = {"ours": [], "fitEllipse": [], "AMS": [], "Direct": []}
    for _ in range(trials):
        e = Ellipse.from_params(rng.uniform(200, 400, 2), (rng.uniform(15, 80), rng.uniform(8, 60)),
                                rng.uniform(0, np.pi))
        t0 = rng.uniform(0, 2 * np.pi)
        pts = e.points(360, t0, t0 + arc) + rng.normal(0, 0.5, (360, 2))
        p32 = pts.astype(np.float32)
        results = {"ours": fit_ellipse(pts), "fitEllipse": ellipse_from_cv_box(cv2.fitEllipse(p32)),
                   "AMS": ellipse_from_cv_box(cv2.fitEllipseAMS(p32)),
                   "Direct": ellipse_from_cv_box(cv2.fitEllipseDirect(p32))}
        for name, r in results.items():
            errs[name].append(np.linalg.norm(r.center - e.center))
    return {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errs.items()}


def test_full_boundary_centre_rms_within_5_percent_of_fitellipse():
    rms = _centre_rms(2 * np.pi, 200, seed=1)
    assert rms["ours"] <= 1.05 * rms["fitEllipse"], rms


def test_half_arc_centre_rms_no_worse_than_ams():
    rms = _centre_rms(np.pi, 200, seed=2)
    assert rms["ours"] <= rms["AMS"], rms
    assert rms["ours"] < rms["Direct"], rms


@pytest.mark.parametrize(
    "points",
    [
        np.empty((0, 2)),
        np.array([[0, 0], [1, 1], [2, 0], [3, 1]], float),  # 4 points
        np.column_stack([np.arange(20.0), 2 * np.arange(20.0) + 1]),  # collinear
        np.tile([[3.0, 4.0]], (10, 1)),  # all coincide
        np.array([[0, 0], [1, 1], [2, 0], [3, 1], [np.nan, 2], [5, 5]], float),
        np.array([[0, 0], [1, 1], [2, 0], [3, 1], [np.inf, 2], [5, 5]], float),
        np.zeros((10, 3)),
        "not points",
    ],
)
def test_degenerate_point_sets_raise_a_typed_error(points):
    with pytest.raises(EllipseFitError):
        fit_ellipse(points)


def test_bad_weights_raise_a_typed_error():
    pts = Ellipse.from_params((0, 0), (5, 3), 0).points(20)
    for w in (np.ones(19), -np.ones(20), np.full(20, np.nan), np.r_[np.ones(4), np.zeros(16)]):
        with pytest.raises(EllipseFitError):
            fit_ellipse(pts, w)


def test_a_hyperbola_is_not_an_ellipse():
    with pytest.raises(EllipseFitError):
        Ellipse.from_conic([1, 0, -1, 0, 0, -1])
    with pytest.raises(EllipseFitError):
        Ellipse.from_conic([1, 0, 1, 0, 0, 1])  # imaginary
    with pytest.raises(EllipseFitError):
        Ellipse.from_conic([0, 0, 0, 0, 0, 0])
    x = np.linspace(1, 5, 30)
    # points on two crossing lines: the direct fit still returns an ellipse (it is
    # ellipse-specific), finite, with large residuals that callers can reject on
    e = fit_ellipse(np.vstack([np.column_stack([x, x]), np.column_stack([x, -x])]))
    assert np.all(np.isfinite(e.conic)) and min(e.axes) > 0
