"""Circle pose from one ellipse (paper §3.2, Safaee-Rad et al. 1992) against exact ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.bench.synthetic_images import disc_outline, issue_camera
from labctl.vision import CirclePoseError, Ellipse, circle_poses, fit_ellipse

K = np.array([[2500.0, 0.0, 319.5], [0.0, 2400.0, 239.5], [0.0, 0.0, 1.0]])


def _pose(x, y, z, obliquity, azimuth):
    center = np.array([x, y, z])
    sight = -center / np.linalg.norm(center)
    helper = np.array([1.0, 0, 0]) if abs(sight[0]) < 0.9 else np.array([0, 1.0, 0])
    b1 = np.cross(sight, helper)
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(sight, b1)
    normal = np.cos(obliquity) * sight + np.sin(obliquity) * (np.cos(azimuth) * b1 + np.sin(azimuth) * b2)
    return center, normal


def _image_ellipse(center, normal, radius, K=K):
    rim = disc_outline(center, normal, radius, 60)
    px = rim @ K.T
    return fit_ellipse(px[:, :2] / px[:, 2:])


poses = st.tuples(st.floats(-80, 80), st.floats(-60, 60), st.floats(250, 2000), st.floats(0.0, np.radians(80)),
                  st.floats(0, 2 * np.pi), st.floats(2.0, 40.0))


@settings(max_examples=80, deadline=None)
@given(poses)
def test_one_candidate_is_the_true_pose(p):
    x, y, z, ob, az, radius = p
    center, normal = _pose(x, y, z, ob, az)
    cands = circle_poses(_image_ellipse(center, normal, radius), radius, K)
    assert len(cands) == 2
    for c in cands:
        assert c.center[2] > 0
        assert abs(np.linalg.norm(c.normal) - 1) < 1e-9
        assert c.normal @ c.center < 0  # towards the camera
    errs = [np.degrees(np.arccos(np.clip(c.normal @ normal, -1, 1))) for c in cands]
    best = cands[int(np.argmin(errs))]
    assert min(errs) < 1e-3
    np.testing.assert_allclose(best.center, center, atol=1e-5 * z)


def test_the_ellipse_centre_is_not_the_image_of_the_circle_centre():
    center, normal = _pose(30.0, -20.0, 400.0, np.radians(60), 0.7)
    ell = _image_ellipse(center, normal, 10.0)
    true_px = K @ center
    true_px = true_px[:2] / true_px[2]
    assert np.linalg.norm(ell.center - true_px) > 0.5  # perspective shifts the ellipse centre
    best = min(circle_poses(ell, 10.0, K), key=lambda c: np.linalg.norm(c.center - center))
    np.testing.assert_allclose(best.center, center, atol=1e-6 * 400)
    # the naive back-projection of the ellipse centre misses by ~0.1 mm, 10⁴ × our error
    ray = np.linalg.solve(K, [*ell.center, 1.0])
    naive = ray / ray[2] * center[2]
    assert np.linalg.norm(naive - center) > 1e4 * np.linalg.norm(best.center - center)


def test_frontal_circle_gives_two_equal_candidates():
    center, normal = _pose(0.0, 0.0, 500.0, 0.0, 0.0)
    a, b = circle_poses(_image_ellipse(center, normal, 10.0), 10.0, K)
    assert np.degrees(np.arccos(np.clip(a.normal @ b.normal, -1, 1))) < 0.01
    np.testing.assert_allclose(a.center, center, atol=1e-6 * 500)


def test_scale_follows_the_radius():
    center, normal = _pose(10.0, 5.0, 600.0, np.radians(40), 1.0)
    ell = _image_ellipse(center, normal, 10.0)
    small, big = circle_poses(ell, 10.0, K), circle_poses(ell, 20.0, K)
    np.testing.assert_allclose(big[0].center, 2 * small[0].center, rtol=1e-9)
    np.testing.assert_allclose(big[0].normal, small[0].normal, atol=1e-12)


def test_distorted_marker_pose_via_camera_model():
    from labctl.vision import marker_pose_candidates
    from labctl.vision.markers import Marker

    cam = issue_camera(kappa1=2e-3)  # strong barrel distortion in Tsai's convention
    center, normal = _pose(120.0, 80.0, 700.0, np.radians(50), 2.0)
    rim_px = cam.project(disc_outline(center, normal, 10.0, 200))
    dist_ell = fit_ellipse(rim_px)
    marker = Marker(tuple(dist_ell.center), dist_ell, dist_ell.area, rim_px, np.ones(len(rim_px)), (0, 0, 1, 1))
    best = max(marker_pose_candidates(marker, cam, 10.0), key=lambda c: c.normal @ normal)
    assert np.degrees(np.arccos(np.clip(best.normal @ normal, -1, 1))) < 1e-3
    np.testing.assert_allclose(best.center, center, atol=1e-4 * 700)
    # ignoring the distortion would be wrong by far more
    naive = max(circle_poses(dist_ell, 10.0, cam.K), key=lambda c: c.normal @ normal)
    assert np.linalg.norm(naive.center - center) > 100 * np.linalg.norm(best.center - center)


@pytest.mark.parametrize("radius", [0.0, -5.0, float("nan"), float("inf"), "ten", None])
def test_bad_radius_raises(radius):
    ell = Ellipse.from_params((320, 240), (30, 20), 0.2)
    with pytest.raises(CirclePoseError):
        circle_poses(ell, radius, K)


def test_bad_camera_matrix_raises():
    ell = Ellipse.from_params((320, 240), (30, 20), 0.2)
    for bad in (np.eye(2), np.full((3, 3), np.nan), np.zeros((3, 3))):
        with pytest.raises(CirclePoseError):
            circle_poses(ell, 10.0, bad)
