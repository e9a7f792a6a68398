"""Pairing markers across the two initial images: the object translated by an unknown shift."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.decisions.recognizer import pair_markers


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 6), shift=st.tuples(*[st.floats(-80, 80)] * 2))
def test_pairs_follow_the_common_shift_not_the_nearest_centre(seed, n, shift):
    rng = np.random.default_rng(seed)
    # markers on an object: at least 25 mm apart, so a 40-80 mm shift puts a wrong marker nearest
    pts = [rng.uniform(-40, 40, 3)]
    while len(pts) < n:
        p = rng.uniform(-40, 40, 3)
        if min(np.linalg.norm(p - q) for q in pts) > 25:
            pts.append(p)
    first = np.array(pts)
    d = np.array([shift[0], shift[1], 0.0])
    order = rng.permutation(n)
    second = first[order] + d + rng.normal(0, 1.0, (n, 3))  # the second image lists them in another order
    pairs = pair_markers(list(first), list(second))
    assert len(pairs) == n
    for k, j in pairs:
        assert order[j] == k


def test_a_marker_missing_from_one_image_leaves_the_others_paired():
    first = [np.array([0.0, 0, 30]), np.array([30.0, 0, 20]), np.array([0.0, 30, 20])]
    d = np.array([45.0, 0, 0])
    second = [first[2] + d, first[0] + d]  # marker 1 went out of view
    assert sorted(pair_markers(first, second)) == [(0, 1), (2, 0)]
    assert pair_markers([], second) == [] and pair_markers(first, []) == []
