"""Marker detection (paper §3.1, §4.1) on synthetic images with ground truth, and bad input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from labctl.bench.synthetic_images import FACE_BGR, disc_coverage, issue_camera, render_disc
from labctl.vision import (
    MarkerImageError,
    MarkerThresholds,
    detect_markers,
    detect_markers_windowed,
    marker_pose_candidates,
)

CAM = issue_camera()


def _facing(center, obliquity_deg=0.0):
    c = np.asarray(center, float)
    sight = -c / np.linalg.norm(c)
    if obliquity_deg == 0:
        return sight
    b1 = np.cross(sight, [1.0, 0, 0])
    b1 /= np.linalg.norm(b1)
    ob = np.radians(obliquity_deg)
    return np.cos(ob) * sight + np.sin(ob) * b1


def _at_pixel(u, v, z):
    ray = np.linalg.solve(CAM.K, [u, v, 1.0])
    return ray / ray[2] * z


def _true_centroid(center, normal, radius=10.0):
    cov = disc_coverage(CAM, center, normal, radius)
    yy, xx = np.indices(cov.shape)
    return np.array([(cov * xx).sum(), (cov * yy).sum()]) / cov.sum()


def test_one_marker_centroid_and_ellipse():
    rng = np.random.default_rng(0)
    center = _at_pixel(250, 200, 600)
    normal = _facing(center, 45)
    found = detect_markers(render_disc(CAM, center, normal, rng=rng))
    assert len(found) == 1
    m = found[0]
    np.testing.assert_allclose(m.centroid, _true_centroid(center, normal), atol=0.03)
    assert not m.touches_border
    assert m.boundary.shape[1] == 2 and len(m.boundary) == len(m.weights) > 50
    assert np.all(m.weights >= 1.0) and np.all(m.weights <= np.sqrt(2) + 1e-9)
    # the boundary lies on the true rim: each point's distance to the fitted ellipse is tiny
    assert m.fit_rms_px < 0.08
    truth_area = disc_coverage(CAM, center, normal, 10.0).sum()
    assert abs(m.area - truth_area) < 0.01 * truth_area
    assert abs(m.ellipse.area - truth_area) < 0.01 * truth_area


def test_shading_and_colour_window():
    rng = np.random.default_rng(1)
    center = _at_pixel(400, 300, 500)
    normal = _facing(center, 30)
    dim = render_disc(CAM, center, normal, rng=rng, shading=0.45)
    bright = render_disc(CAM, center, normal, rng=rng)
    a, b = detect_markers(dim), detect_markers(bright)
    assert len(a) == len(b) == 1
    pa = max(marker_pose_candidates(a[0], CAM, 10.0), key=lambda c: c.normal @ normal)
    assert np.degrees(np.arccos(np.clip(pa.normal @ normal, -1, 1))) < 0.5
    assert np.linalg.norm(pa.center - center) < 0.005 * 500
    # a green marker is found only with a green hue window
    green = render_disc(CAM, center, normal, rng=rng, disc_bgr=(40, 190, 40))
    assert detect_markers(green) == []
    g = detect_markers(green, thresholds=MarkerThresholds(hue_range_deg=(100, 140)))
    assert len(g) == 1
    np.testing.assert_allclose(g[0].centroid, b[0].centroid, atol=0.1)


def test_several_markers_are_all_reported_largest_first():
    rng = np.random.default_rng(2)
    img = np.full((480, 640, 3), FACE_BGR, np.float64)
    centres = [_at_pixel(150, 150, 400), _at_pixel(450, 320, 800), _at_pixel(500, 100, 600)]
    for c in centres:
        cov = disc_coverage(CAM, c, _facing(c, 20), 10.0)[..., None]
        img = cov * np.array([38, 32, 196.0]) + (1 - cov) * img
    img = np.clip(np.rint(img + rng.normal(0, 2, img.shape)), 0, 255).astype(np.uint8)
    found = detect_markers(img)
    assert len(found) == 3
    expected = [(150, 150), (500, 100), (450, 320)]  # by area: 400, 600, 800 mm away
    for m, xy in zip(found, expected, strict=True):
        assert np.linalg.norm(np.subtract(m.centroid, xy)) < 2.0
    assert found[0].area > found[1].area > found[2].area


def test_border_cut_marker_is_rejected_or_flagged():
    rng = np.random.default_rng(3)
    center = _at_pixel(5, 240, 500)  # half outside the left edge
    img = render_disc(CAM, center, _facing(center, 10), rng=rng)
    assert detect_markers(img) == []
    kept = detect_markers(img, keep_border=True)
    assert len(kept) == 1 and kept[0].touches_border
    assert np.all(kept[0].boundary[:, 0] > 1.5)
    assert np.all(np.isfinite(kept[0].ellipse.conic))


def test_non_elliptical_blobs_are_rejected():
    img = np.full((480, 640, 3), FACE_BGR, np.uint8)
    cv2.rectangle(img, (100, 100), (160, 140), (38, 32, 196), -1)  # a red bar
    cv2.circle(img, (400, 300), 25, (38, 32, 196), -1)  # two touching discs
    cv2.circle(img, (448, 300), 25, (38, 32, 196), -1)
    cv2.circle(img, (300, 400), 1, (38, 32, 196), -1)  # too small
    assert detect_markers(img) == []


def test_windowed_search_and_fallback():
    rng = np.random.default_rng(4)
    center = _at_pixel(380, 260, 700)
    img = render_disc(CAM, center, _facing(center, 35), rng=rng)
    full = detect_markers(img)[0]
    near = detect_markers_windowed(img, (385, 255), 40)
    assert len(near) == 1
    np.testing.assert_allclose(near[0].centroid, full.centroid, atol=1e-9)
    np.testing.assert_allclose(near[0].ellipse.conic, full.ellipse.conic, atol=1e-9)
    # window far from the marker: nothing there, so the full frame is searched
    lost = detect_markers_windowed(img, (60, 60), 30)
    np.testing.assert_allclose(lost[0].centroid, full.centroid, atol=1e-9)
    # a window that cuts the marker does not measure it, and falls back to the full frame
    assert detect_markers(img, window=(380, 200, 460, 330)) == []
    cut = detect_markers_windowed(img, (400, 260), 12)
    np.testing.assert_allclose(cut[0].centroid, full.centroid, atol=1e-9)
    # tracker mode: centroid only, same centroid
    quick = detect_markers_windowed(img, (385, 255), 40, refine=False)
    np.testing.assert_allclose(quick[0].centroid, full.centroid, atol=0.3)  # thresholded-pixel centroid
    assert len(quick[0].boundary) == 0
    # nonsense predictions fall back instead of crashing
    for bad in ((np.nan, 3), ("a", "b")):
        assert len(detect_markers_windowed(img, bad, 30)) == 1
    assert len(detect_markers_windowed(img, (300, 200), -5)) == 1


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((480, 640, 3), np.uint8),  # black
        np.full((480, 640, 3), 128, np.uint8),  # grey
        np.full((480, 640, 3), 255, np.uint8),  # saturated white
        np.dstack([np.zeros((480, 640)), np.zeros((480, 640)), np.full((480, 640), 255)]).astype(np.uint8),  # all red
        np.random.default_rng(5).integers(0, 256, (480, 640, 3), dtype=np.uint8),  # noise
        np.zeros((1, 1, 3), np.uint8),
        np.full((480, 640, 3), np.nan),
        np.full((48, 64, 3), 0.5),  # float image in [0, 1]
    ],
)
def test_bad_images_give_no_markers(image):
    found = detect_markers(image)
    assert found == [] or all(np.all(np.isfinite(m.centroid)) for m in found)
    assert len(found) <= 3


@pytest.mark.parametrize("image", [None, np.zeros((0, 0, 3), np.uint8), np.zeros((480, 640), np.uint8),
                                   np.zeros((4, 4, 4), np.uint8), np.array([["a"] * 3] * 2)])
def test_non_images_raise_a_typed_error(image):
    with pytest.raises(MarkerImageError):
        detect_markers(image)
