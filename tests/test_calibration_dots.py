"""Dot detection, centroid bias, identification, table registration and calibration files."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.calibration import store
from labctl.calibration.dots import DotError, circle_centroid_bias, detect_dots, identify
from labctl.calibration.table import TableRegistrationError, fit_table_frame, pixel_to_plane
from labctl.calibration.target import PlaneTarget, RoofTarget, TargetError, load_target, target_yaml
from labctl.geometry import CameraModel, apply, invert, look_at, make_T, rot_z
from labctl.geometry.camera_io import load_camera_file

CAM = CameraModel(f=25.0, kappa1=-8e-4, sx=1.0, cx=319.5, cy=239.5, dx=0.0098, dy=0.0098, ncx=640, nfx=640)
T_W_T = make_T(None, [300.0, 200.0, 0.0])  # where the target sits in these tests


def _render_target(target, T_w_c, cam=CAM, seed=0):
    from labctl.sim.render import MarkerDisc, Mesh, render

    s = target.solid().transformed(T_W_T)
    marks = [MarkerDisc(c, n, r, col) for c, n, r, col in zip(s.dots, s.normals, s.radii, target.dot_colours())]
    return render(cam, T_w_c, [Mesh(s.vertices, s.faces, target.plate_colour_bgr, marks)],
                  rng=np.random.default_rng(seed)).image


def test_detected_centres_are_subpixel_after_bias_correction():
    target = RoofTarget()
    T_w_c = look_at(apply(T_W_T, [250.0, -300.0, 950.0]), apply(T_W_T, [0, 0, 45.0]), up=(0, 1, 0))
    img = _render_target(target, T_w_c)
    blobs = detect_dots(img)
    solid = target.solid()
    mi, bi, T0 = identify(blobs, solid.dots, target.fiducial_indices, CAM)
    assert len(mi) == len(solid.dots)  # every dot found and identified
    T_c_t = invert(T_w_c) @ T_W_T
    truth = CAM.project(apply(T_c_t, solid.dots[mi]))
    bias = circle_centroid_bias(CAM, T_c_t, solid.dots[mi], solid.normals[mi], solid.radii[mi])
    err_raw = np.linalg.norm(blobs.centers[bi] - truth, axis=1)
    err = np.linalg.norm(blobs.centers[bi] - bias - truth, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.03
    assert err.max() < 0.1
    assert np.abs(bias).max() > 0.01  # the oblique view does bias centroids ...
    assert np.mean(err**2) < np.mean(err_raw**2)  # ... and the correction removes it
    assert np.linalg.norm(T0[:3, 3] - T_c_t[:3, 3]) < 20.0


def test_bias_vanishes_for_a_disc_facing_the_camera_on_axis():
    b = circle_centroid_bias(CAM.with_(kappa1=0.0), np.eye(4), np.array([[0.0, 0.0, 500.0]]),
                             np.array([[0.0, 0.0, -1.0]]), np.array([5.0]))
    assert np.abs(b).max() < 1e-9


def test_missing_fiducials_are_reported():
    target = RoofTarget()
    # look at the target from far to the side: part of it leaves the image
    T_w_c = look_at(apply(T_W_T, [0.0, 0.0, 900.0]), apply(T_W_T, [170.0, 0, 0]), up=(0, 1, 0))
    blobs = detect_dots(_render_target(target, T_w_c))
    with pytest.raises(DotError):
        identify(blobs, target.solid().dots, target.fiducial_indices, CAM)


def test_detect_dots_ignores_the_dark_table_and_rejects_bad_images():
    from labctl.sim.render import render

    img = render(CAM, look_at([0, 0, 800.0], [0, 0, 0]), [], rng=np.random.default_rng(1)).image
    assert len(detect_dots(img).centers) == 0
    with pytest.raises(DotError):
        detect_dots(np.zeros((10, 10), np.float32))


@settings(max_examples=25, deadline=None)
@given(yaw=st.floats(-0.2, 0.2), ox=st.floats(-50, 50), oy=st.floats(-50, 50), qx=st.floats(-30, 30))
def test_table_frame_is_recovered_from_exact_sightings(yaw, ox, oy, qx):
    T = make_T(rot_z(yaw), [ox, oy, 0.0])
    p = np.array([[0, 0], [300, 0], [600, 0], [0, 400], [300, 200], [600, 400]], float)
    m = np.array([apply(T, [x + qx, y + 5.0, 3.0]) for x, y in p])
    reg = fit_table_frame(p, m, (qx, 5.0))
    assert np.allclose(reg.T_w_table, T, atol=1e-9)
    assert reg.scale == pytest.approx((1.0, 1.0)) and abs(reg.skew_deg) < 1e-9


def test_table_fit_refuses_collinear_or_too_few_positions():
    p = np.array([[0, 0], [100, 0], [200, 0]], float)
    m = np.column_stack([p, np.zeros(3)])
    with pytest.raises(TableRegistrationError, match="collinear"):
        fit_table_frame(p, m)
    with pytest.raises(TableRegistrationError, match="at least 3"):
        fit_table_frame(p[:2], m[:2])


def test_pixel_to_plane_inverts_projection():
    T_w_c = look_at([100.0, 50.0, 1500.0], [0, 0, 0], up=(0, 1, 0))
    pts = np.array([[10.0, 20.0, 0.0], [-150.0, 80.0, 0.0]])
    px = CAM.project_world(invert(T_w_c), pts)
    assert np.allclose(pixel_to_plane(CAM, T_w_c, px, 0.0), pts, atol=1e-6)


def test_target_file_round_trip_and_errors(tmp_path):
    t = RoofTarget(pitch_mm=15.0, mount_on_table=(100.0, 50.0, 30.0))
    (tmp_path / "target.yaml").write_text(target_yaml(t))
    assert load_target(tmp_path / "target.yaml") == t
    p = PlaneTarget(cols=7, rows=5, fiducials=((0, 0), (3, 0), (0, 2), (6, 4), (4, 3)), spacers_mm=(0.0, 45.0))
    (tmp_path / "plane.yaml").write_text(target_yaml(p, with_dots=True))
    q = load_target(tmp_path / "plane.yaml")
    assert isinstance(q, PlaneTarget) and np.allclose(q.solid().dots, p.solid().dots)
    # measured dot centres in the file replace the nominal grid
    text = (tmp_path / "plane.yaml").read_text().replace("- [-66.0, -44.0, 3.0]", "- [-66.2, -44.1, 3.0]")
    (tmp_path / "measured.yaml").write_text(text)
    assert np.allclose(load_target(tmp_path / "measured.yaml").solid().dots[0], [-66.2, -44.1, 3.0])
    (tmp_path / "flat1.yaml").write_text("kind: plane\nspacers_mm: [0.0]\n")
    with pytest.raises(TargetError, match="2 different heights"):
        load_target(tmp_path / "flat1.yaml")
    (tmp_path / "line.yaml").write_text("kind: plane\nregistration_positions_mm: [[0, 0], [10, 10], [20, 20]]\n")
    with pytest.raises(TargetError, match="collinear"):
        load_target(tmp_path / "line.yaml")
    (tmp_path / "bad.yaml").write_text("kind: roof\nwidth_mm: 80\n")
    with pytest.raises(TargetError, match="do not fit"):
        load_target(tmp_path / "bad.yaml")
    (tmp_path / "bad2.yaml").write_text("kind: roof\ncolour: red\n")
    with pytest.raises(TargetError, match="unknown key"):
        load_target(tmp_path / "bad2.yaml")
    with pytest.raises(TargetError, match="not found"):
        load_target(tmp_path / "none.yaml")


def test_calibration_files_round_trip(tmp_path):
    T_w_c = look_at([300.0, 200.0, 1800.0], [300.0, 200.0, 0.0], up=(0, 1, 0))
    X = make_T(rot_z(1.5), [0.0, 60.0, 80.0])
    T_tab = make_T(rot_z(0.01), [1.0, 2.0, 0.0])
    store.write_files(tmp_path / "calibration", {
        store.FIXED_FILE: store.fixed_camera_text(CAM, T_w_c, {"rms_px": 0.01, "method": "m", "n_points": 3}),
        store.MOBILE_FILE: store.mobile_camera_text(CAM.with_(f=24.0), X, {"rms_px": 0.02}),
        store.TABLE_FILE: store.table_text(T_tab, {"rms_mm": 0.1}),
    })
    cal = store.load_calibration(tmp_path)
    assert cal.fixed_camera == CAM and np.allclose(cal.T_w_c1, T_w_c)
    assert cal.mobile_camera.f == 24.0 and np.allclose(cal.T_f_c2, X)
    assert np.allclose(cal.T_w_table, T_tab)
    assert cal.stats["fixed_camera"]["n_points"] == 3
    assert load_camera_file(tmp_path / "calibration" / store.MOBILE_FILE).f == 24.0
    ros = yaml.safe_load(store.ros_camera_info_text(CAM, "mobile_camera"))
    assert ros["distortion_model"] == "plumb_bob" and ros["image_width"] == 640
    (tmp_path / "calibration" / store.TABLE_FILE).unlink()
    with pytest.raises(store.CalibrationFileError, match="table.yaml"):
        store.load_calibration(tmp_path)
    (tmp_path / "calibration" / store.TABLE_FILE).write_text("T_w_table: [[1, 0], [0, 1]]\n")
    with pytest.raises(store.CalibrationFileError, match="4×4"):
        store.load_calibration(tmp_path)
