"""Duality resolution (paper §3.3): exact cases, bad input, and image pairs with noise."""

from __future__ import annotations

import numpy as np
import pytest

from labctl.bench.synthetic_images import disc_outline, issue_camera, random_disc_pose, render_disc
from labctl.geometry.transforms import rot_x, rot_z
from labctl.vision import (
    CirclePose,
    circle_poses,
    detect_markers,
    fit_ellipse,
    marker_pose_candidates,
    resolve_duality,
    resolve_duality_detailed,
)

CAM = issue_camera()
K = CAM.K


def _cands(center, normal, R_c_w=None, t=None):
    """Exact candidates of a disc given in a world frame, seen by a camera (R_c_w, t)."""
    R_c_w = np.eye(3) if R_c_w is None else R_c_w
    t = np.zeros(3) if t is None else t
    rim = disc_outline(center, normal, 10.0, 80) @ R_c_w.T + t
    px = rim @ K.T
    return circle_poses(fit_ellipse(px[:, :2] / px[:, 2:]), 10.0, K)


def _truth_index(cands, normal):
    return int(np.argmax([c.normal @ normal for c in cands]))


def _oblique(center, deg, az=0.3):
    sight = -center / np.linalg.norm(center)
    b1 = np.cross(sight, [1.0, 0, 0])
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(sight, b1)
    ob = np.radians(deg)
    return np.cos(ob) * sight + np.sin(ob) * (np.cos(az) * b1 + np.sin(az) * b2)


def test_translation_picks_the_normal_common_to_both_images():
    c1 = np.array([-40.0, 10.0, 600.0])
    n = _oblique(c1, 45)
    c2 = c1 + [35.0, -20.0, 10.0]
    first, second = _cands(c1, n), _cands(c2, n)
    res = resolve_duality_detailed(first, second)
    assert not res.ambiguous and res.index == _truth_index(second, n)
    assert res.pose is second[res.index] and resolve_duality(first, second) is second[res.index]
    assert res.margin_rad > np.radians(1.0)
    assert res.scores_rad[res.index] < 1e-6


def test_frontal_marker_is_ambiguous():
    c2 = np.array([0.0, 0.0, 600.0])
    n = -c2 / 600
    first, second = _cands(c2 - [20.0, 0, 0], n), _cands(c2, n)
    # the second image's two candidates merge: no basis for a choice (and none needed)
    res = resolve_duality_detailed(first, second)
    assert res.ambiguous and res.pose is None and res.margin_rad < np.radians(0.01)
    # the other way round the first image pins the normal down, and the second is resolved
    res = resolve_duality_detailed(second, _cands(c2 + [20.0, 0, 0], n))
    assert not res.ambiguous and res.scores_rad[res.index] < 1e-6


def test_motion_along_the_line_of_sight_is_ambiguous():
    c1 = np.array([20.0, -10.0, 600.0])
    n = _oblique(c1, 50)
    second = _cands(c1 * 1.05, n)
    res = resolve_duality_detailed(_cands(c1, n), second)
    assert res.ambiguous and res.pose is None and res.best in second


def test_planar_motion_uses_the_component_along_the_plane_normal():
    # table plane in the world: z up; the camera looks down at 50° from above
    R_c_w = rot_x(np.radians(180 - 50))[:3, :3]
    t = np.array([0.0, 0.0, 700.0])
    plane_normal_w = np.array([0.0, 0.0, 1.0])
    n_w = np.array([np.sin(np.radians(35)), 0.0, np.cos(np.radians(35))])  # marker tilted 35° off the table normal
    c1_w = np.array([0.0, 0.0, 0.0])
    R_motion = rot_z(np.radians(25))[:3, :3]
    c2_w, n2_w = c1_w + [30.0, -15.0, 0.0], R_motion @ n_w
    first, second = _cands(c1_w, n_w, R_c_w, t), _cands(c2_w, n2_w, R_c_w, t)
    res = resolve_duality_detailed(first, second, motion="planar", plane_normal=R_c_w @ plane_normal_w)
    assert not res.ambiguous
    assert res.index == _truth_index(second, R_c_w @ n2_w)
    # under that rotation the true normal changed, so translation logic is not the right test
    assert resolve_duality_detailed(first, second).scores_rad[res.index] > np.radians(5)


def test_moving_camera_needs_the_rotation_between_the_frames():
    c_w = np.array([0.0, 0.0, 0.0])
    n_w = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    R1 = rot_x(np.radians(140))[:3, :3]
    R2 = rot_z(np.radians(20))[:3, :3] @ R1
    t = np.array([0.0, 0.0, 650.0])
    first, second = _cands(c_w, n_w, R1, t), _cands(c_w + [25.0, 10.0, 0.0], n_w, R2, t)
    R_first_second = R1 @ R2.T  # second-camera vectors into the first camera frame
    res = resolve_duality_detailed(first, second, R_first_second=R_first_second)
    assert not res.ambiguous and res.index == _truth_index(second, R2 @ n_w)


def test_bad_arguments_raise_value_errors():
    c = np.array([0.0, 0.0, 500.0])
    pair = _cands(c, _oblique(c, 40))
    with pytest.raises(ValueError):
        resolve_duality(pair, pair, motion="spiral")
    with pytest.raises(ValueError):
        resolve_duality(pair, pair, motion="planar")
    with pytest.raises(ValueError):
        resolve_duality(pair, pair[:1])
    with pytest.raises(ValueError):
        resolve_duality(pair, pair, R_first_second=np.full((3, 3), np.nan))
    nan_pose = CirclePose(np.array([0, 0, 500.0]), np.array([np.nan, 0, 0]))
    with pytest.raises(ValueError):
        resolve_duality(pair, (nan_pose, nan_pose))


def test_image_pairs_under_translation():
    """Issue target: 10–50 mm translation in any direction, obliquity ≥ 20°: the right normal in
    ≥ 99 % of pairs, a confident wrong answer in ≤ 0.5 %."""
    rng = np.random.default_rng(77)
    correct = wrong = ambiguous = 0
    pairs = 0
    while pairs < 120:
        c1, n = random_disc_pose(rng, CAM, obliquity_deg=(20, 70))
        d = rng.normal(size=3)
        c2 = c1 + d / np.linalg.norm(d) * rng.uniform(10, 50)
        if not np.all(CAM.contains(CAM.project(disc_outline(c2, n, 10.0, 64)), margin=8)):
            continue
        if np.degrees(np.arccos(-n @ c2 / np.linalg.norm(c2))) < 20:
            continue
        pairs += 1
        m1 = detect_markers(render_disc(CAM, c1, n, rng=rng))
        m2 = detect_markers(render_disc(CAM, c2, n, rng=rng))
        second = marker_pose_candidates(m2[0], CAM, 10.0)
        res = resolve_duality_detailed(marker_pose_candidates(m1[0], CAM, 10.0), second)
        if res.ambiguous:
            ambiguous += 1
        elif res.index == _truth_index(second, n):
            correct += 1
        else:
            wrong += 1
    print(f"duality over {pairs} pairs: correct {correct}, ambiguous {ambiguous}, confidently wrong {wrong}")
    assert correct >= 0.99 * pairs
    assert wrong <= 0.005 * pairs
