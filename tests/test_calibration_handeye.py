"""Tsai–Lenz hand-eye (labctl.calibration.handeye) against synthetic truth and OpenCV 4.x."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.calibration.handeye import HandEyeInputError, pose_error, refine_hand_eye, target_in_base, tsai_lenz
from labctl.geometry import CameraModel, apply, invert, look_at, make_T, rot_z, rotvec_to_matrix


def _stations(X, T_b_t, n, rng, noise_deg=0.0, noise_mm=0.0):
    T_b_f, T_c_t = [], []
    for _ in range(n):
        eye = T_b_t[:3, 3] + rng.uniform([-400, -400, 700], [400, 400, 1000])
        T_b_c = look_at(eye, T_b_t[:3, 3] + rng.normal(0, 30, 3), up=rng.normal(size=3))
        T_b_f.append(T_b_c @ invert(X))
        T = invert(T_b_c) @ T_b_t
        if noise_deg or noise_mm:
            T = make_T(rotvec_to_matrix(rng.normal(0, np.radians(noise_deg), 3)) @ T[:3, :3],
                       T[:3, 3] + rng.normal(0, noise_mm, 3))
        T_c_t.append(T)
    return T_b_f, T_c_t


def _opencv(T_b_f, T_c_t):
    R, t = cv2.calibrateHandEye([T[:3, :3] for T in T_b_f], [T[:3, 3] for T in T_b_f],
                                [T[:3, :3] for T in T_c_t], [T[:3, 3] for T in T_c_t],
                                method=cv2.CALIB_HAND_EYE_TSAI)
    return make_T(R, t.ravel())


@settings(max_examples=20, deadline=None)
@given(rv=st.lists(st.floats(-2.5, 2.5), min_size=3, max_size=3),
       t=st.lists(st.floats(-150, 150), min_size=3, max_size=3), seed=st.integers(0, 10_000))
def test_noise_free_stations_give_x_exactly(rv, t, seed):
    rng = np.random.default_rng(seed)
    X = make_T(rotvec_to_matrix(rv), t)
    T_b_t = make_T(rot_z(rng.uniform(-3, 3)), [300.0, 100.0, 20.0])
    T_b_f, T_c_t = _stations(X, T_b_t, 6, rng)
    rot, trans = pose_error(tsai_lenz(T_b_f, T_c_t), X)
    assert rot < 1e-7 and trans < 1e-6
    assert pose_error(target_in_base(T_b_f, T_c_t, X), T_b_t)[1] < 1e-6


@pytest.mark.parametrize("seed", range(5))
def test_agrees_with_opencv_calibrate_hand_eye_on_noisy_stations(seed):
    rng = np.random.default_rng(seed)
    X = make_T(rotvec_to_matrix([0.02, -0.03, 1.57]), [0.0, 60.0, 80.0])
    T_b_f, T_c_t = _stations(X, make_T(None, [300, 200, 40]), 10, rng, noise_deg=0.02, noise_mm=0.2)
    ours, theirs = tsai_lenz(T_b_f, T_c_t), _opencv(T_b_f, T_c_t)
    rot, trans = pose_error(ours, theirs)
    assert rot < 0.03 and trans < 0.5  # same method; OpenCV weights the pairs slightly differently
    rot, trans = pose_error(ours, X)
    rot_cv, trans_cv = pose_error(theirs, X)
    assert rot < 0.1 and trans < 1.0
    assert rot < 1.5 * rot_cv + 0.01 and trans < 1.5 * trans_cv + 0.1


def test_equals_opencv_on_noise_free_stations():
    rng = np.random.default_rng(7)
    X = make_T(rotvec_to_matrix([0.3, -0.2, 1.2]), [10.0, 60.0, 80.0])
    T_b_f, T_c_t = _stations(X, make_T(None, [300, 200, 40]), 7, rng)
    rot, trans = pose_error(tsai_lenz(T_b_f, T_c_t), _opencv(T_b_f, T_c_t))
    assert rot < 1e-6 and trans < 1e-5


def test_degenerate_pose_sets_are_refused():
    rng = np.random.default_rng(3)
    X = make_T(rotvec_to_matrix([0.0, 0.0, 1.5]), [0.0, 60.0, 80.0])
    T_b_t = make_T(None, [300, 200, 0])
    T_b_c0 = look_at([300, 200, 1000], [300, 200, 0], up=(0, 1, 0))
    # every station: the camera only turns about the one vertical axis (plus translations)
    T_b_f, T_c_t = [], []
    for a in (0.0, 0.4, 0.9, 1.5):
        T_b_c = make_T(rot_z(a), rng.normal(0, 50, 3)) @ T_b_c0
        T_b_f.append(T_b_c @ invert(X))
        T_c_t.append(invert(T_b_c) @ T_b_t)
    with pytest.raises(HandEyeInputError, match="one axis"):
        tsai_lenz(T_b_f, T_c_t)
    with pytest.raises(HandEyeInputError, match="at least 3"):
        tsai_lenz(T_b_f[:2], T_c_t[:2])
    bad = [T.copy() for T in T_c_t]
    bad[1][0, 3] = np.nan
    with pytest.raises(HandEyeInputError, match="not finite"):
        tsai_lenz(T_b_f, bad)
    with pytest.raises(HandEyeInputError, match="4 flange poses but 3"):
        tsai_lenz(T_b_f, T_c_t[:3])


def test_reprojection_refinement_recovers_x_and_focal_length():
    """A focal length 0.3 % off (the single-view f/Tz coupling) biases Tsai–Lenz's translation;
    the refinement over all stations, scaled by the robot's motions, removes it."""
    rng = np.random.default_rng(11)
    cam = CameraModel(f=25.0, kappa1=-8e-4, sx=1.0, cx=319.5, cy=239.5, dx=0.0098, dy=0.0098, ncx=640, nfx=640)
    X = make_T(rotvec_to_matrix([0.02, -0.01, 1.57]), [0.0, 60.0, 80.0])
    T_b_t = make_T(None, [300.0, 200.0, 0.0])
    g = np.arange(6) * 16.0 - 40.0
    gx, gy = np.meshgrid(g, g)
    P_t = np.column_stack([gx.ravel(), gy.ravel(), 0.5 * np.abs(gx.ravel())])
    T_b_f, T_c_t = _stations(X, T_b_t, 8, rng)
    pix = [cam.project(apply(T, P_t)) + rng.normal(0, 0.02, (len(P_t), 2)) for T in T_c_t]
    wrong = cam.with_(f=25.0 * 1.003)
    T_c_t_est = [make_T(T[:3, :3], T[:3, 3] * 1.003) for T in T_c_t]  # what the wrong f implies
    X_tl = tsai_lenz(T_b_f, T_c_t_est)
    cam_r, X_r, T_b_t_r, res = refine_hand_eye(wrong, X_tl, target_in_base(T_b_f, T_c_t_est, X_tl), T_b_f,
                                                [P_t] * len(T_b_f), pix)
    assert pose_error(X_tl, X)[1] > 1.0
    rot, trans = pose_error(X_r, X)
    assert rot < 0.02 and trans < 0.3
    assert cam_r.f == pytest.approx(25.0, rel=3e-4)
    assert np.sqrt(np.mean(np.sum(res**2, axis=1))) < 0.03
