"""The hot-path shortcuts of labctl.vision agree with the plain formulations they replace:
closed-form cone eigen-frame vs numpy.linalg.eigh, the fit's moment-based residual vs the
Sampson RMS, normalisation invariance of the fit, padded vs margin crops for the boundary
scans, the single-blob labelling shortcut vs connected components, and the inline Tsai
undistortion of marker_pose_candidates vs CameraModel.undistort_pixels."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.bench.synthetic_images import issue_camera, render_disc
from labctl.vision import CirclePose, Ellipse, circle_poses, detect_markers, fit_ellipse, marker_pose_candidates
from labctl.vision.circle_pose import _cone_frame
from labctl.vision.ellipse import _fit
from labctl.vision.markers import _edge_offsets, _sampson

CAM = issue_camera()


def _rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.05, 1.0), st.floats(0.02, 0.95), st.floats(1e-4, 1.0))
def test_cone_frame_matches_eigh(seed, l1, l2_frac, l3):
    """λ1 ≥ λ2 > 0 > λ3 and the eigenvectors of e1, e3 agree with LAPACK (up to sign)."""
    rng = np.random.default_rng(seed)
    lam = np.array([l1, l1 * l2_frac, -l3])
    R = _rotation(rng)
    Q = R @ np.diag(lam) @ R.T * rng.choice([-1.0, 1.0]) * rng.uniform(0.1, 100)
    got_l1, got_l2, got_l3, e1, e3 = _cone_frame(Q.tolist())
    scale = np.linalg.norm(lam)
    np.testing.assert_allclose(np.array([got_l1, got_l2, got_l3]) * scale, lam, atol=1e-9 * scale)
    assert abs(abs(np.dot(e3, R[:, 2])) - 1.0) < 1e-9
    if l1 - l1 * l2_frac > 1e-3 * l1:  # e1 is only defined when λ1 and λ2 differ
        assert abs(abs(np.dot(e1, R[:, 0])) - 1.0) < 1e-6


def test_frontal_circle_gives_one_finite_pose():
    """λ1 = λ2 (the marker squarely facing the camera): both candidates equal the truth."""
    center = np.array([0.0, 0.0, 500.0])
    K = CAM.K
    r_px = 10.0 * K[0, 0] / 500.0
    ell = Ellipse.from_params((K[0, 2], K[1, 2]), (r_px, r_px), 0.0)
    for pose in circle_poses(ell, 10.0, K):
        np.testing.assert_allclose(pose.center, center, atol=1e-6)
        np.testing.assert_allclose(pose.normal, [0.0, 0.0, -1.0], atol=1e-6)


def test_moment_residual_tracks_the_sampson_rms():
    rng = np.random.default_rng(3)
    for axes in ((30.0, 20.0), (50.0, 12.0), (20.0, 19.0)):
        e = Ellipse.from_params((300.0, 200.0), axes, 0.4)
        pts = e.points(200) + rng.normal(0, 0.3, (200, 2))
        w = rng.uniform(1.0, 1.4, 200)
        conic, rms = _fit(pts, w, 0)
        d = _sampson(conic, pts)
        exact = np.sqrt(w @ (d * d) / w.sum())
        assert abs(rms - exact) < 0.1 * exact


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(-50, 50), st.floats(-50, 50), st.floats(0.01, 1.0))
def test_fit_is_invariant_to_its_normalisation(seed, ox, oy, scale):
    rng = np.random.default_rng(seed)
    e = Ellipse.from_params(rng.uniform(100, 500, 2), (rng.uniform(10, 60), rng.uniform(5, 40)), rng.uniform(0, 3))
    pts = e.points(120) + rng.normal(0, 0.2, (120, 2))
    w = rng.uniform(1.0, 1.4, 120)
    base = Ellipse.from_conic(_fit(pts, w, 0)[0])
    other = Ellipse.from_conic(_fit(pts, w, 0, origin=(float(e.center[0]) + ox, float(e.center[1]) + oy),
                                    scale=scale)[0])
    np.testing.assert_allclose(other.conic, base.conic, atol=1e-8)


@settings(max_examples=60, deadline=None)
@given(st.floats(-0.5, 1.5), st.floats(0.05, 1.0), st.floats(0.0, 0.9), st.floats(0.0, 1.0))
def test_area_rule_is_exact_for_a_straight_edge_under_any_shading(edge, inside, outside_frac, slope_deg):
    """A straight edge crossing 8-pixel scans at any sub-pixel phase and angle up to 45°, with
    any inside/outside levels (plateaus clear of the edge): the locally normalised area rule puts
    it exactly where it is."""
    outside = outside_frac * inside
    k0 = np.array([-3])
    # pixel k covers [k − ½, k + ½] along the scan; coverage of a straight edge at `edge`
    # tilted by the angle θ: the exact box-filtered coverage, supersampled across the pixel
    theta = np.radians(45.0 * slope_deg)
    sub = (np.arange(400) + 0.5) / 400 - 0.5
    ks = np.arange(-3, 5)
    xs = ks[:, None] + sub[None, :]
    ys = sub[None, :]
    cov = ((xs[:, :, None] + np.tan(theta) * ys[:, None, :]) < edge).mean(axis=(1, 2))
    prof = (outside + (inside - outside) * cov)[None, :]
    off, kept, local = _edge_offsets(prof, k0, inside - outside)
    assert kept[0]
    assert abs(off[0] - edge) < 1e-2
    np.testing.assert_allclose(local, inside - outside, atol=1e-9)


def test_single_blob_shortcut_matches_connected_components():
    rng = np.random.default_rng(5)
    center = np.array([20.0, 10.0, 700.0])
    normal = -center / np.linalg.norm(center) + np.array([0.3, 0.0, 0.0])
    normal /= np.linalg.norm(normal)
    img = render_disc(CAM, center, normal, 10.0, rng=rng)
    one = detect_markers(img)
    speck = img.copy()
    speck[5:7, 5:7] = (30, 30, 200)  # a second, tiny red blob: the labelling path runs
    two = detect_markers(speck)
    assert len(one) == len(two) == 1
    np.testing.assert_allclose(two[0].centroid, one[0].centroid, atol=1e-9)
    np.testing.assert_allclose(two[0].boundary, one[0].boundary, atol=1e-9)
    np.testing.assert_allclose(two[0].ellipse.conic, one[0].ellipse.conic, atol=1e-9)


def test_inline_undistortion_matches_the_camera_model():
    cam = issue_camera(kappa1=2e-3)
    rng = np.random.default_rng(6)
    center = np.array([60.0, -40.0, 650.0])
    normal = -center / np.linalg.norm(center) + np.array([0.0, 0.5, 0.0])
    normal /= np.linalg.norm(normal)
    marker = detect_markers(render_disc(cam, center, normal, 10.0, rng=rng))[0]
    fast = marker_pose_candidates(marker, cam, 10.0)
    plain = circle_poses(fit_ellipse(cam.undistort_pixels(marker.boundary), marker.weights), 10.0, cam.K)
    for pose in fast:
        match = min(plain, key=lambda p: np.linalg.norm(p.normal - pose.normal))
        np.testing.assert_allclose(pose.normal, match.normal, atol=1e-9)
        np.testing.assert_allclose(pose.center, match.center, rtol=1e-9)


def test_circle_pose_compares_by_value():
    a = CirclePose(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, -1.0]))
    assert a == CirclePose(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, -1.0]))
    assert a != CirclePose(np.array([1.0, 2.0, 3.5]), np.array([0.0, 0.0, -1.0]))
    assert a in (CirclePose(np.zeros(3), np.array([0.0, 0.0, -1.0])), a)


def test_pose_of_a_bad_marker_is_a_typed_error():
    """marker_pose_candidates skips re-validating arrays; bad data still ends in EllipseFitError."""
    import pytest

    from labctl.vision import EllipseFitError
    from labctl.vision.markers import Marker

    e = Ellipse.from_params((320, 240), (30, 20), 0.2)
    pts = e.points(50)
    bad = {
        "zero weights": (pts, np.zeros(50)),
        "NaN point": (np.vstack([[np.nan, 1.0], pts]), np.ones(51)),
        "inf points": (pts * np.inf, np.ones(50)),
        "one point repeated": (np.tile([[3.0, 4.0]], (50, 1)), np.ones(50)),
        "collinear": (np.column_stack([np.arange(50.0), np.arange(50.0)]), np.ones(50)),
        "four points": (pts[:4], np.ones(4)),
        "weights of the wrong length": (pts, np.ones(49)),
    }
    for cam in (CAM, issue_camera(kappa1=2e-3)):
        for name, (boundary, weights) in bad.items():
            marker = Marker((0.0, 0.0), e, 1.0, boundary, weights, (0, 0, 1, 1))
            with pytest.raises(EllipseFitError):
                marker_pose_candidates(marker, cam, 10.0)
                pytest.fail(name)
