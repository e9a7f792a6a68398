"""The coordinated-turn geometry the CT refit evaluates (issue 18), checked by hypothesis.

``turn_positions`` (vectorised, any sign of time) against an independent closed form, the circle
through its centre (and the straight line when the curvature is 0), and its analytic Jacobian
against central differences.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.tracking.models import turn_positions, turn_positions_jacobian, turn_transition

coord = st.floats(-500.0, 500.0)
vel = st.floats(-150.0, 150.0)
curv = st.one_of(st.just(0.0), st.floats(-1 / 50, 1 / 50), st.floats(-1e-7, 1e-7))


def _circle_reference(x, d):
    """Independent closed form: rotate the start point about the centre p0 + v⊥/(κ|v|)·|v|... at ω = κ|v|."""
    p0, v, k = np.array([x[0], x[2]]), np.array([x[1], x[3]]), x[4]
    speed = np.hypot(*v)
    if k == 0.0 or speed == 0.0:
        return p0 + np.outer(d, v)
    n = np.array([-v[1], v[0]]) / speed  # left normal
    c = p0 + n / k  # centre of the circle of radius 1/κ (signed)
    w = k * speed
    a = w * d
    r0 = p0 - c
    return c + np.column_stack([np.cos(a) * r0[0] - np.sin(a) * r0[1], np.sin(a) * r0[0] + np.cos(a) * r0[1]])


@settings(max_examples=200, deadline=None)
@given(coord, vel, coord, vel, curv, st.lists(st.floats(-10.0, 10.0), min_size=1, max_size=8))
def test_turn_positions_are_the_circle_and_match_the_recursive_step(x0, vx, y0, vy, k, ds):
    x = np.array([x0, vx, y0, vy, k])
    d = np.array(ds)
    p = turn_positions(x, d)
    scale = 1.0 + np.hypot(vx, vy) * np.abs(d)[:, None]
    if abs(k) * np.hypot(vx, vy) * np.max(np.abs(d)) > 1e-3 or k == 0.0:
        np.testing.assert_allclose(p, _circle_reference(x, d), atol=1e-9 * 1e3, rtol=0)
    step = np.array([turn_transition(x, t)[[0, 2]] for t in d])
    assert np.all(np.abs(p - step) <= 1e-9 * scale), (p, step)


@settings(max_examples=200, deadline=None)
@given(coord, vel, coord, vel, curv, st.lists(st.floats(-6.0, 0.0), min_size=1, max_size=8))
def test_turn_jacobian_matches_central_differences(x0, vx, y0, vy, k, ds):
    x = np.array([x0, vx, y0, vy, k])
    d = np.array(ds)
    J = turn_positions_jacobian(x, d)
    speed = max(np.hypot(vx, vy), 1.0)
    for i, h in enumerate((1e-3, 1e-5 * speed, 1e-3, 1e-5 * speed, 1e-7)):
        e = np.zeros(5)
        e[i] = h
        num = (turn_positions(x + e, d) - turn_positions(x - e, d)) / (2 * h)
        tol = 1e-5 * (1.0 + np.abs(num)) + (1e-2 if i == 4 else 1e-6) * (1 + speed * np.max(np.abs(d)) ** 2)
        assert np.all(np.abs(J[:, :, i] - num) <= tol), (i, J[:, :, i], num)
