"""Tsai calibration (labctl.calibration.tsai) against Willson's reference set and synthetic truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from labctl.calibration.tsai import CalibrationInputError, Sensor, calibrate, calibrate_opencv
from labctl.geometry import CameraModel, make_T, rotation_angle, rpy_willson

WILLSON = Sensor(ncx=576, nfx=576, dx=0.023, dy=0.023, cx=258.0, cy=204.0, width=576, height=384)


def test_willson_full_optimisation_reaches_the_noise_floor(tsai_points):
    r = calibrate(tsai_points[:, :3], tsai_points[:, 3:], WILLSON, full=True)
    assert r.rms_px <= 0.0900
    assert abs(r.camera.f - 69.9746) <= 0.2
    assert abs(r.camera.cx - 262.41) <= 0.5 and abs(r.camera.cy - 212.45) <= 0.5
    assert abs(r.camera.kappa1 - (-6.067e-4)) <= 0.02 * 6.067e-4
    # R and T agree with Willson's published full optimisation
    R_ref = rpy_willson(0.52348816339, 0.017487254462, 0.035000288833)
    assert np.degrees(rotation_angle(r.T_c_w[:3, :3].T @ R_ref)) < 0.05
    assert np.allclose(r.T_c_w[:3, 3], [-100.269, -85.323, 1999.76], atol=[0.5, 0.5, 6.0])


def test_willson_basic_method_with_centre_held(tsai_points):
    r = calibrate(tsai_points[:, :3], tsai_points[:, 3:], WILLSON, full=False)
    assert (r.camera.cx, r.camera.cy) == (258.0, 204.0)
    assert abs(r.camera.sx - 1.000158) <= 2e-6
    assert abs(r.camera.f - 68.163) <= 0.005 * 68.163
    assert r.rms_px <= 0.115
    assert abs(r.camera.kappa1 - (-6.0394e-4)) <= 0.02 * 6.0394e-4


def test_opencv_baseline_matches_the_published_numbers(tsai_points):
    cv = calibrate_opencv(tsai_points[:, :3], tsai_points[:, 3:], WILLSON)
    K = np.asarray(cv["K"])
    assert cv["rms_px"] == pytest.approx(0.0895, abs=5e-4)
    assert K[0, 2] == pytest.approx(262.32, abs=0.05) and K[1, 2] == pytest.approx(212.45, abs=0.05)
    assert K[0, 0] == pytest.approx(3038.66, abs=0.5)


def _coplanar_set(seed: int):
    """Willson's coplanar generator constants (data README): f 270, κ1 −6e-4, T (150, −75, 6600),
    R (20°, 5°, 88°), centre (262, 212); 10×10 grid at z = 0; noise 0.04 mm target, 0.02 px."""
    rng = np.random.default_rng(seed)
    g = np.arange(10) * 20.0 + 10.0
    X, Y = np.meshgrid(g, g)
    P = np.column_stack([X.ravel(), Y.ravel(), np.zeros(100)])
    cam = CameraModel(f=270.0, kappa1=-6e-4, sx=1.0, cx=262.0, cy=212.0, dx=0.023, dy=0.023, ncx=576, nfx=576,
                      width=576, height=576)
    T = make_T(rpy_willson(*np.radians([20.0, 5.0, 88.0])), [150.0, -75.0, 6600.0])
    px = cam.project_world(T, P + rng.normal(0, 0.04, P.shape)) + rng.normal(0, 0.02, (100, 2))
    return P, px, cam, T


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_coplanar_fit_is_no_worse_than_the_true_model(seed):
    P, px, cam, T = _coplanar_set(seed)
    truth_rms = float(np.sqrt(np.mean(np.sum((cam.project_world(T, P) - px) ** 2, axis=1))))
    sensor = Sensor(ncx=576, nfx=576, dx=0.023, dy=0.023, cx=258.0, cy=204.0, width=576, height=576)
    r = calibrate(P, px, sensor, coplanar=True, full=True)
    assert r.rms_px <= truth_rms
    assert r.method == "coplanar-full"
    assert abs(r.camera.kappa1 - (-6e-4)) < 0.05 * 6e-4


def test_coplanar_basic_with_true_centre_recovers_the_camera():
    P, px, cam, T = _coplanar_set(0)
    sensor = Sensor.of(cam)
    r = calibrate(P, px, sensor, coplanar=True)
    assert r.rms_px < 0.11
    assert abs(r.camera.f - 270.0) < 0.05 * 270
    assert np.degrees(rotation_angle(r.T_c_w[:3, :3].T @ T[:3, :3])) < 0.5


def test_coplanar_points_on_a_tilted_plane():
    """The coplanar method accepts any plane, not only z = 0; the pose is reported in the world."""
    cam = CameraModel(f=16.0, kappa1=-1e-3, sx=1.0, cx=320.0, cy=240.0, dx=0.01, dy=0.01, ncx=640, nfx=640)
    g = np.arange(8) * 15.0
    X, Y = np.meshgrid(g, g)
    Pp = np.column_stack([X.ravel(), Y.ravel(), np.zeros(64)])
    T_w_p = make_T(rpy_willson(0.3, -0.2, 0.5), [20.0, -30.0, 40.0])
    P = Pp @ T_w_p[:3, :3].T + T_w_p[:3, 3]
    T_c_w = make_T(rpy_willson(0.2, 0.1, 0.3), [-50.0, -40.0, 700.0])
    px = cam.project_world(T_c_w, P)
    r = calibrate(P, px, Sensor.of(cam), coplanar=True, full=True)
    assert r.rms_px < 1e-4
    assert np.allclose(r.T_c_w, T_c_w, atol=1e-3)


@settings(max_examples=12, deadline=None)
@given(f=st.floats(8.0, 50.0), kappa=st.floats(-2e-3, 2e-3), rx=st.floats(-0.6, 0.6), ry=st.floats(-0.4, 0.4),
       rz=st.floats(-3.0, 3.0), fill=st.floats(0.8, 1.6), sx=st.floats(0.99, 1.01))
def test_noise_free_noncoplanar_data_is_recovered_exactly(f, kappa, rx, ry, rz, fill, sx):
    cam = CameraModel(f=f, kappa1=kappa, sx=sx, cx=320.0, cy=240.0, dx=0.01, dy=0.01, ncx=640, nfx=640)
    g = np.arange(6) * 20.0
    X, Y, Z = np.meshgrid(g, g, [0.0, 30.0, 60.0])
    P = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()]) - [30.0, 30.0, 0.0]
    # the grid spans about 1/fill of the image width; the world origin is off the optical axis
    dist = fill * f * 200.0 / (cam.width * cam.dpx)
    T = make_T(rpy_willson(rx, ry, rz), [-0.05 * dist, -0.04 * dist, dist])
    px = cam.project_world(T, P)
    assume(bool(cam.contains(px).all()))
    r = calibrate(P, px, Sensor.of(cam))
    assert r.rms_px < 1e-6
    assert r.camera.f == pytest.approx(f, rel=1e-6)
    assert r.camera.kappa1 == pytest.approx(kappa, abs=1e-9)
    assert r.camera.sx == pytest.approx(sx, rel=1e-8)
    assert np.allclose(r.T_c_w, T, atol=1e-5 * dist)


def test_bad_input_is_refused_with_one_clear_message(tsai_points):
    P, px = tsai_points[:, :3], tsai_points[:, 3:]
    with pytest.raises(CalibrationInputError, match="at least 11 points"):
        calibrate(P[:6], px[:6], WILLSON)
    with pytest.raises(CalibrationInputError, match="coplanar"):
        calibrate(P[:100], px[:100], WILLSON)  # z = 0 only
    with pytest.raises(CalibrationInputError, match="not coplanar"):
        calibrate(P, px, WILLSON, coplanar=True)
    bad = px.copy()
    bad[17, 1] = np.nan
    with pytest.raises(CalibrationInputError, match="point 18"):
        calibrate(P, bad, WILLSON)
    with pytest.raises(CalibrationInputError, match="N×3"):
        calibrate(P[:, :2], px, WILLSON)
