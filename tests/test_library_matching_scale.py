"""Issue 15: matching at 1,000 views — the cached-spectrum, gate-first path equals the reference
signature distance of labctl.vision.shape, and per-object results match a plain loop."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.library.matching import LibraryIndex, match, view_scores
from labctl.vision.shape import AOS_SCALES, N_SAMPLES, ShapeFeatures, signature_distance


def _features(rng, ecc=None, size=None):
    return ShapeFeatures(eccentricity=float(rng.uniform(0, 0.95) if ecc is None else ecc),
                         size_mm=float(rng.uniform(20, 100) if size is None else size),
                         perimeter_mm=float(rng.uniform(80, 400)), chain_start=(0, 0),
                         chain_code=np.zeros(0, np.uint8), aos=rng.uniform(1.5, 4.5, (len(AOS_SCALES), N_SAMPLES)),
                         fd=rng.random(16), hu=rng.random(7))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(5, 300))
def test_fast_scores_equal_the_reference_signature_distance(seed, n_views):
    rng = np.random.default_rng(seed)
    views = [(f"obj{k % 37}", k // 37, _features(rng, size=float(rng.uniform(40, 60)))) for k in range(n_views)]
    index = LibraryIndex.from_views(views)
    q = _features(rng, size=50.0)
    s = view_scores(q, index)
    d, _ = signature_distance(q.aos, index.aos)  # the vision module's reference implementation
    dlog = np.abs(np.log(q.size_mm) - index.log_size)
    decc = np.abs(q.eccentricity ** 2 - index.ecc2)
    ok = (decc <= 0.15) & (dlog <= 0.12)
    ref = np.where(ok, d + 2 * dlog + 2 * decc, np.inf)
    assert np.array_equal(np.isinf(s), np.isinf(ref))
    assert np.allclose(s[ok], ref[ok], atol=1e-9)
    r = match(q, index)
    for name in set(index.names):  # each object's score is its best view's
        assert np.isclose(r.scores[name], ref[np.array(index.names) == name].min(), rtol=0, atol=1e-9) or (
            np.isinf(r.scores[name]) and np.isinf(ref[np.array(index.names) == name]).all())
    if np.isfinite(ref).any():
        i = int(np.argmin(ref))
        assert r.best == (index.names[i], int(index.marker_ids[i]))
        assert list(r.scores)[0] == index.names[i]
