"""Camera model and rigid transforms against ground truth and as properties."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.geometry import (
    CameraModel,
    apply,
    invert,
    look_at,
    make_T,
    rotation_angle,
    rotvec_to_matrix,
    rpy_from_matrix_willson,
    rpy_willson,
)

WILLSON_TRUTH = CameraModel(f=70.0, kappa1=-6.0e-4, sx=1.0, cx=262.0, cy=212.0, dx=0.023, dy=0.023,
                            ncx=576, nfx=576, width=576, height=576)


def test_willson_ground_truth_projection_rms(tsai_points):
    """Projecting Willson's 300 points with the generator's truth gives RMS 0.0904 px (data README)."""
    T_c_w = make_T(rpy_willson(np.radians(30), np.radians(1), np.radians(2)), [-100, -85, 2000])
    px = WILLSON_TRUTH.project_world(T_c_w, tsai_points[:, :3])
    err = np.linalg.norm(px - tsai_points[:, 3:], axis=1)
    assert abs(np.sqrt(np.mean(err**2)) - 0.0904) < 0.0005
    assert abs(err.max() - 0.264) < 0.001


cameras = st.builds(
    CameraModel,
    f=st.floats(8, 80), kappa1=st.floats(-1.5e-3, 1.5e-3), sx=st.floats(0.98, 1.02),
    cx=st.floats(300, 340), cy=st.floats(220, 260), dx=st.floats(0.005, 0.015), dy=st.floats(0.005, 0.015),
    ncx=st.just(640.0), nfx=st.floats(600, 700), width=st.just(640), height=st.just(480),
)


@settings(max_examples=60, deadline=None)
@given(cam=cameras, seed=st.integers(0, 2**31))
def test_project_backproject_round_trip(cam, seed):
    """pixel → ray → pixel stays within 1e-9 px over the whole image."""
    rng = np.random.default_rng(seed)
    px = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], size=(200, 2))
    px = np.vstack([px, [[0, 0], [cam.width - 1, cam.height - 1], [0, cam.height - 1], [cam.width - 1, 0]]])
    depth = rng.uniform(100, 3000, size=(len(px), 1))
    rays = cam.backproject(px)
    back = cam.project(rays * depth / rays[:, 2:3])
    assert np.max(np.abs(back - px)) < 1e-9


@settings(max_examples=60, deadline=None)
@given(cam=cameras, seed=st.integers(0, 2**31))
def test_distort_undistort_inverse(cam, seed):
    px = np.random.default_rng(seed).uniform([0, 0], [639, 479], size=(100, 2))
    assert np.max(np.abs(cam.distort_pixels(cam.undistort_pixels(px)) - px)) < 1e-9


def test_opencv_conversion_exact_without_distortion():
    cam = WILLSON_TRUTH.with_(kappa1=0.0)
    K, dist, err = cam.to_opencv()
    assert err == 0 and not np.any(dist)
    back, err2 = CameraModel.from_opencv(K, dist, dx=0.023, dy=0.023, ncx=576, nfx=576, width=576, height=576)
    assert err2 == 0
    for name in ("f", "sx", "cx", "cy"):
        assert abs(getattr(back, name) - getattr(cam, name)) < 1e-9


def test_opencv_conversion_with_distortion_matches_cv2():
    import cv2

    K, dist, err = WILLSON_TRUTH.to_opencv()
    assert err < 0.05
    pts = np.random.default_rng(1).uniform([-60, -60, 900], [60, 60, 1100], size=(200, 3))
    ours = WILLSON_TRUTH.project(pts)
    theirs = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    assert np.max(np.linalg.norm(ours - theirs, axis=1)) < 0.05
    back, err2 = CameraModel.from_opencv(K, dist, dx=0.023, dy=0.023, ncx=576, nfx=576, width=576, height=576)
    assert abs(back.kappa1 - WILLSON_TRUTH.kappa1) / abs(WILLSON_TRUTH.kappa1) < 0.02
    assert err2 < 0.05


rotvecs = st.tuples(*[st.floats(-3.0, 3.0)] * 3).map(np.array)
translations = st.tuples(*[st.floats(-2000, 2000)] * 3).map(np.array)


@settings(max_examples=200, deadline=None)
@given(r1=rotvecs, t1=translations, r2=rotvecs, t2=translations)
def test_transform_composition_and_inversion(r1, t1, r2, t2):
    T_a_b = make_T(rotvec_to_matrix(r1), t1)
    T_b_c = make_T(rotvec_to_matrix(r2), t2)
    T_a_c = T_a_b @ T_b_c
    p_c = np.array([[1.0, -2.0, 3.0], [100.0, 50.0, -20.0]])
    assert np.allclose(apply(T_a_c, p_c), apply(T_a_b, apply(T_b_c, p_c)), atol=1e-8)
    assert np.allclose(invert(T_a_c), invert(T_b_c) @ invert(T_a_b), atol=1e-9)
    assert np.allclose(invert(T_a_b) @ T_a_b, np.eye(4), atol=1e-9)
    assert np.allclose(apply(invert(T_a_b), apply(T_a_b, p_c)), p_c, atol=1e-8)


@settings(max_examples=100, deadline=None)
@given(rx=st.floats(-1.5, 1.5), ry=st.floats(-1.4, 1.4), rz=st.floats(-3.1, 3.1))
def test_willson_rpy_round_trip(rx, ry, rz):
    R = rpy_willson(rx, ry, rz)
    assert rotation_angle(R.T @ rpy_willson(*rpy_from_matrix_willson(R))) < 1e-9


def test_willson_rpy_matches_readme_formula():
    a, b, g = 0.3, 0.1, -0.2
    ca, sa, cb, sb, cg, sg = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(g), np.sin(g)
    R = np.array([[cb * cg, cg * sa * sb - ca * sg, sa * sg + ca * cg * sb],
                  [cb * sg, sa * sb * sg + ca * cg, ca * sb * sg - cg * sa],
                  [-sb, cb * sa, ca * cb]])
    assert np.allclose(rpy_willson(a, b, g), R)


def test_look_at_points_optical_axis_at_target():
    T_w_c = look_at([300, 200, 1800], [300, 200, 0], up=(0, 1, 0))
    assert np.allclose(T_w_c[:3, 2], [0, 0, -1])
    assert np.allclose(T_w_c[:3, 0], [1, 0, 0])  # image columns along world +x
    assert np.isclose(np.linalg.det(T_w_c[:3, :3]), 1.0)
