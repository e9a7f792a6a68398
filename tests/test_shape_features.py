"""Silhouette, chain code, eccentricity and angle-of-sight signature against synthetic ground truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.vision.shape import (
    N_SAMPLES,
    ShapeError,
    ShapeFeatures,
    angle_of_sight_signature,
    chain_perimeter,
    chain_to_contour,
    eccentricity,
    features_from_image,
    features_from_mask,
    freeman_chain_code,
    hu_distance,
    hu_moments,
    outer_contour,
    resample_closed,
    signature_distance,
    silhouette_mask,
)


def polygon_mask(poly, shape=(480, 640)):
    m = np.zeros(shape, np.uint8)
    cv2.fillPoly(m, [np.round(np.asarray(poly) * 16).astype(np.int32)], 1, shift=4)
    return m.astype(bool)


def transform(poly, angle, scale=1.0, shift=(320, 240)):
    c, s = np.cos(angle), np.sin(angle)
    p = np.asarray(poly, float)
    p = p - p.mean(axis=0)
    return (p @ np.array([[c, s], [-s, c]])) * scale + shift


L_SHAPE = [(0, 0), (120, 0), (120, 50), (50, 50), (50, 100), (0, 100)]
T_SHAPE = [(35, 0), (85, 0), (85, 70), (120, 70), (120, 110), (0, 110), (0, 70), (35, 70)]


def test_chain_code_round_trip_and_perimeter_of_a_square():
    mask = polygon_mask([(100, 100), (200, 100), (200, 200), (100, 200)])
    c = outer_contour(mask)
    code = freeman_chain_code(c)
    assert np.array_equal(chain_to_contour(tuple(c[0]), code), c)
    assert set(np.unique(code)) <= {0, 2, 4, 6}  # axis-aligned square: no diagonal steps
    assert chain_perimeter(code) == pytest.approx(4 * 100, rel=0.02)


def test_eccentricity_of_ellipses_matches_axis_ratio():
    for a, b in [(100, 100), (120, 60), (150, 30)]:
        m = np.zeros((480, 640), np.uint8)
        cv2.ellipse(m, (320, 240), (a, b), 30, 0, 360, 1, -1)
        truth = np.sqrt(1 - (b / a) ** 2)
        assert eccentricity(m.astype(bool)) == pytest.approx(truth, abs=0.03)


def test_angle_of_sight_of_a_square_is_right_angle_at_corners_and_straight_elsewhere():
    sq = np.array([(0, 0), (100, 0), (100, 100), (0, 100)], float)
    sig = angle_of_sight_signature(sq)
    fine = sig[0]  # smallest chord: 1/32 of the perimeter
    assert np.isclose(np.median(fine), np.pi, atol=1e-6)  # straight sides
    assert fine.min() == pytest.approx(np.pi / 2 + 0.0, abs=0.35)  # corners (averaged over a run)
    assert np.all(sig > 0) and np.all(sig < 2 * np.pi)


def test_concave_corner_is_seen_above_pi():
    sig = angle_of_sight_signature(np.array(L_SHAPE, float))
    assert sig[0].max() > np.pi + 0.5 and sig[0].min() < np.pi - 0.5


@settings(max_examples=25, deadline=None)
@given(angle=st.floats(-np.pi, np.pi), scale=st.floats(0.7, 1.4), start=st.integers(0, 300))
def test_signature_distance_invariant_to_rotation_scale_and_start_point(angle, scale, start):
    base = features_from_mask(polygon_mask(transform(L_SHAPE, 0.0)), 1.0)
    m = polygon_mask(transform(L_SHAPE, angle, scale))
    contour = np.roll(outer_contour(m), start, axis=0)
    sig = angle_of_sight_signature(contour)
    d_same, _ = signature_distance(sig, base.aos[None])
    other = angle_of_sight_signature(outer_contour(polygon_mask(transform(T_SHAPE, angle, scale))))
    d_other, _ = signature_distance(other, base.aos[None])
    assert d_same[0] < 0.1  # pixelisation and sampling phase only
    assert d_other[0] > 2 * d_same[0] and d_other[0] > 0.2


def test_signature_distance_finds_the_start_point_shift():
    pts = resample_closed(np.array(T_SHAPE, float))
    sig = angle_of_sight_signature(pts)
    shifted = np.roll(sig, 17, axis=1)
    d, shift = signature_distance(shifted, sig[None])
    assert d[0] == pytest.approx(0.0, abs=1e-9) and shift[0] == (N_SAMPLES - 17) % N_SAMPLES or shift[0] == 17


def test_hu_distance_equals_cv2_matchshapes():
    a = polygon_mask(transform(L_SHAPE, 0.3))
    b = polygon_mask(transform(T_SHAPE, 1.0))
    ref = cv2.matchShapes(a.astype(np.uint8), b.astype(np.uint8), cv2.CONTOURS_MATCH_I1, 0)
    assert hu_distance(hu_moments(a), hu_moments(b)[None])[0] == pytest.approx(ref, rel=1e-6)


def test_silhouette_from_image_with_red_marker_and_noise():
    rng = np.random.default_rng(0)
    poly = transform(L_SHAPE, 0.4)
    truth = polygon_mask(poly)
    img = np.full((480, 640, 3), 60, np.uint8)
    img[truth] = 185
    cv2.circle(img, (300, 230), 18, (40, 40, 200), -1)  # marker inside the object
    img = np.clip(img + rng.normal(0, 3, img.shape), 0, 255).astype(np.uint8)
    m = silhouette_mask(img)
    iou = (m & truth).sum() / (m | truth).sum()
    assert iou > 0.98


def test_features_metric_size_and_json_round_trip():
    side = 100
    mask = polygon_mask([(200, 150), (200 + side, 150), (200 + side, 150 + side), (200, 150 + side)])
    f = features_from_mask(mask, 0.25)
    assert f.size_mm == pytest.approx(side * 0.25, rel=0.02)
    g = ShapeFeatures.from_dict(f.to_dict())
    assert np.allclose(g.aos, f.aos, atol=1e-5) and np.array_equal(g.chain_code, f.chain_code)


def test_bad_images_raise_shape_error():
    with pytest.raises(ShapeError):
        silhouette_mask(np.full((480, 640, 3), 60, np.uint8))  # nothing there
    img = np.full((480, 640, 3), 60, np.uint8)
    img[100:300, 0:200] = 185  # cut by the image border
    with pytest.raises(ShapeError):
        features_from_image(img, 0.25)
    with pytest.raises(ValueError):
        ShapeFeatures.from_dict({**features_from_mask(polygon_mask(L_SHAPE + np.array([100, 100])), 1).to_dict(),
                                 "aos": [[0.0]]})
