"""Pins of filterpy 2.0.0's pitfalls (DESIGN §4) and proof that MarkerTracker steers clear of each.

If filterpy changes behaviour, the first test of each pair fails: re-check the workaround then.
"""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.common import kinematic_kf
from filterpy.kalman import KalmanFilter

from labctl.config.lab import TrackingConfig
from labctl.tracking import MarkerTracker, position_matrix


def _cv_filter() -> KalmanFilter:
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.F = np.array([[1, 1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1], [0, 0, 0, 1.0]])
    kf.H = np.array([[1, 0, 0, 0], [0, 0, 1, 0.0]])
    kf.R *= 0.25
    kf.P *= 100
    return kf


def test_pitfall_update_with_H_and_a_1d_measurement_corrupts_the_state():
    good, bad = _cv_filter(), _cv_filter()
    good.update(np.array([[3.0], [4.0]]), H=good.H)
    bad.update(np.array([3.0, 4.0]), H=bad.H)
    assert good.x.shape == (4, 1)
    assert bad.x.shape == (4, 2)  # silently broadcast: the state is no longer a vector


def test_pitfall_column_vectors_are_what_filterpy_expects():
    kf = _cv_filter()
    kf.update(np.array([[3.0], [4.0]]))
    assert kf.x.shape == (4, 1)
    np.testing.assert_allclose(kf.x[[0, 2], 0], [3.0, 4.0], atol=0.01)


def test_pitfall_kinematic_kf_builds_a_wrong_H():
    kf = kinematic_kf(dim=2, order=1, dim_z=2)
    np.testing.assert_array_equal(kf.H, [[1, 0, 1, 0], [1, 0, 1, 0]])  # each row measures x + y
    np.testing.assert_array_equal(position_matrix(2), [[1, 0, 0, 0], [0, 0, 1, 0]])
    np.testing.assert_array_equal(position_matrix(3), [[1, 0, 0, 0, 0, 0], [0, 0, 0, 1, 0, 0]])


def test_pitfall_batch_filter_fails_on_1d_measurements():
    zs_1d = [np.array([i, 2.0 * i]) for i in range(5)]
    with pytest.raises(ValueError):
        _cv_filter().batch_filter(zs_1d)
    means, *_ = _cv_filter().batch_filter([z.reshape(2, 1) for z in zs_1d])
    assert means.shape == (5, 4, 1)


@pytest.mark.parametrize("model", ["cv", "ca", "imm"])
def test_tracker_passes_column_vectors_never_H_and_never_batches(model, monkeypatch):
    calls = []
    original = KalmanFilter.update

    def spy(self, z, R=None, H=None):
        calls.append((np.shape(z), H))
        return original(self, z, R=R, H=H)

    monkeypatch.setattr(KalmanFilter, "update", spy)
    monkeypatch.setattr(KalmanFilter, "batch_filter", lambda *a, **k: pytest.fail("batch_filter used"))
    # built from a TrackingConfig (the only source of the tracker's config defaults), with the noise this pin needs
    trk = MarkerTracker(TrackingConfig(model=model, process_noise=1.0, measurement_noise_mm=0.5))
    for i in range(20):
        trk.update(i / 30, (i / 3.0, 1.0))
    assert calls and all(shape == (2, 1) and H is None for shape, H in calls)


@pytest.mark.parametrize("model", ["cv", "ca", "imm"])
def test_tracker_gives_the_same_answer_for_any_measurement_shape(model):
    shapes = [lambda z: z, lambda z: list(z), lambda z: tuple(z), lambda z: np.asarray(z).reshape(2, 1),
              lambda z: np.asarray(z).reshape(1, 2)]
    rng = np.random.default_rng(0)
    zs = [(t * 10.0 + rng.normal(0, 0.5), 5.0 + rng.normal(0, 0.5)) for t in np.arange(0, 2, 1 / 30)]
    results = []
    for shape in shapes:
        trk = MarkerTracker(TrackingConfig(model=model, process_noise=1.0, measurement_noise_mm=0.5))
        for i, z in enumerate(zs):
            trk.update(i / 30, shape(np.array(z)))
        mean, cov = trk.predict(3.0)
        assert mean.shape == (2,) and cov.shape == (2, 2)
        results.append(np.concatenate([mean, cov.ravel()]))
    for r in results[1:]:
        np.testing.assert_allclose(r, results[0], rtol=1e-12)
