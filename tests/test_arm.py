"""The arm model (labctl.planning.arm) against forward kinematics written out here from UR's published DH table."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from labctl.config import ConfigError
from labctl.config.arm import load_arm
from labctl.planning.arm import ArmModel

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parents[1]
UR10E = REPO / "drivers" / "arms" / "ur10e.yaml"
UR5E = REPO / "drivers" / "arms" / "ur5e.yaml"

# Universal Robots' UR10e DH table, metres as published, typed in here (not read from the data file)
D = [0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655]
A = [0.0, -0.6127, -0.57155, 0.0, 0.0, 0.0]
ALPHA = [math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0]


def ur_fk_m(q):
    """Standard DH, link by link, T_{i-1,i} = Rz(θ)·Tz(d)·Tx(a)·Rx(α): the flange in the base, metres."""
    T = np.eye(4)
    for i in range(6):
        c, s = math.cos(q[i]), math.sin(q[i])
        ca, sa = math.cos(ALPHA[i]), math.sin(ALPHA[i])
        Rz = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
        Tz = np.eye(4)
        Tz[2, 3] = D[i]
        Tx = np.eye(4)
        Tx[0, 3] = A[i]
        Rx = np.array([[1, 0, 0, 0], [0, ca, -sa, 0], [0, sa, ca, 0], [0, 0, 0, 1.0]])
        T = T @ Rz @ Tz @ Tx @ Rx
    return T


def dh(theta, i):
    """Link i's standard DH transform (metres)."""
    c, s = math.cos(theta), math.sin(theta)
    ca, sa = math.cos(ALPHA[i]), math.sin(ALPHA[i])
    return np.array([[c, -s*ca, s*sa, A[i]*c], [s, c*ca, -c*sa, A[i]*s], [0, sa, ca, D[i]], [0, 0, 0, 1.0]])

def ur_ik_m(T):
    """Every closed-form solution (Hawkins, "Analytic inverse kinematics for the Universal Robots UR-5/UR-10
    arms", 2013), each checked with ur_fk_m: the arm model's IK is judged against it."""
    d4, d6, a2, a3 = D[3], D[5], A[1], A[2]
    sols = []
    p05 = T @ np.array([0, 0, -d6, 1.0])
    r = math.hypot(p05[0], p05[1])
    if r < abs(d4):
        return sols
    psi, phi = math.atan2(p05[1], p05[0]), math.acos(d4 / r)
    for t1 in (psi + phi + math.pi / 2, psi - phi + math.pi / 2):
        c5 = (T[0, 3] * math.sin(t1) - T[1, 3] * math.cos(t1) - d4) / d6
        if abs(c5) > 1:
            continue
        for t5 in (math.acos(c5), -math.acos(c5)):
            s5 = math.sin(t5)
            if abs(s5) < 1e-9:
                continue
            Ti = np.linalg.inv(T)
            X, Y = Ti[:3, 0], Ti[:3, 1]  # x and y of frame 0 in frame 6
            s1, c1 = math.sin(t1), math.cos(t1)
            t6 = math.atan2((-X[1] * s1 + Y[1] * c1) / s5, (X[0] * s1 - Y[0] * c1) / s5)
            T14 = np.linalg.inv(dh(t1, 0)) @ T @ np.linalg.inv(dh(t5, 4) @ dh(t6, 5))
            p13 = T14 @ np.array([0, -d4, 0, 1.0])
            L = math.hypot(p13[0], p13[1])
            c3 = (L * L - a2 * a2 - a3 * a3) / (2 * a2 * a3)
            if abs(c3) > 1:
                continue
            for t3 in (math.acos(c3), -math.acos(c3)):
                t2 = -math.atan2(p13[1], -p13[0]) + math.asin(a3 * math.sin(t3) / L)
                T34 = np.linalg.inv(dh(t2, 1) @ dh(t3, 2)) @ T14
                t4 = math.atan2(T34[1, 0], T34[0, 0])
                q = np.array([t1, t2, t3, t4, t5, t6])
                if np.allclose(ur_fk_m(q), T, atol=1e-9):
                    sols.append(q)
    return sols

def ur_fk_mm(q):
    T = ur_fk_m(q)
    T[:3, 3] *= 1000.0
    return T


@pytest.fixture(scope="module")
def arm():
    return ArmModel.from_config(load_arm(UR10E))


def test_zero_pose_is_the_published_stretched_arm(arm):
    # at q = 0 the UR lies stretched along −x: x = a2 + a3, y = −(d4 + d6), z = d1 − d5
    T = arm.fk(np.zeros(6))
    assert T[:3, 3] == pytest.approx([-612.7 - 571.55, -(174.15 + 116.55), 180.7 - 119.85], abs=1e-9)
    assert T[:3, 3] == pytest.approx([-1184.25, -290.7, 60.85], abs=1e-9)
    np.testing.assert_allclose(T, ur_fk_mm(np.zeros(6)), atol=1e-9)
    # the flange's z (tool axis) points along −y, out of the last wrist
    np.testing.assert_allclose(T[:3, 2], [0, -1, 0], atol=1e-12)


@pytest.mark.parametrize("q_deg", [
    [0, -90, 0, -90, 0, 0],
    [0, -90, 90, -90, -90, 0],
    [30, -45, 60, -100, 75, 10],
    [-170, -130, 150, 20, -30, 300],
    [355, 12, -260, 180, 90, -355],
])
def test_fk_matches_independent_dh(arm, q_deg):
    q = np.radians(q_deg)
    np.testing.assert_allclose(arm.fk(q), ur_fk_mm(q), atol=1e-9)


def test_mount_and_tool_compose_as_documented():
    cfg = load_arm(UR10E, base_xyz_mm=(100.0, -600.0, 350.0), base_rpy_deg=(0.0, 0.0, 90.0))
    import dataclasses

    cfg = dataclasses.replace(cfg, tool_xyz_mm=(0.0, 0.0, 50.0), tool_rpy_deg=(0.0, 0.0, 180.0))
    arm = ArmModel.from_config(cfg)
    q = np.radians([20, -70, 80, -90, -90, 15])
    Rz90 = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    T_w_base = np.eye(4)
    T_w_base[:3, :3], T_w_base[:3, 3] = Rz90, [100.0, -600.0, 350.0]
    T_f_tool = np.eye(4)
    T_f_tool[:3, :3], T_f_tool[:3, 3] = np.diag([-1.0, -1.0, 1.0]), [0, 0, 50.0]
    np.testing.assert_allclose(arm.fk(q), T_w_base @ ur_fk_mm(q) @ T_f_tool, atol=1e-9)
    np.testing.assert_allclose(arm.fk_flange(q), ur_fk_mm(q), atol=1e-9)


def test_jacobian_is_the_derivative_of_fk(arm):
    q = np.radians([20, -70, 80, -90, -90, 15])
    J = arm.jacobian(q)
    h = 1e-7
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = h
        Tp, Tm = ur_fk_mm(q + dq), ur_fk_mm(q - dq)
        np.testing.assert_allclose(J[:3, j], (Tp[:3, 3] - Tm[:3, 3]) / (2 * h), rtol=1e-5, atol=1e-4)
        W = (Tp[:3, :3] - Tm[:3, :3]) / (2 * h) @ ur_fk_mm(q)[:3, :3].T  # [ω]×
        np.testing.assert_allclose(J[3:, j], [W[2, 1], W[0, 2], W[1, 0]], atol=1e-6)


def test_singularities_show_in_margins_and_manipulability(arm):
    q = np.radians([20, -70, 80, -90, -90, 15])
    assert arm.manipulability(q) > 0.01
    wrist = q.copy()
    wrist[4] = 0.0
    assert arm.singularity_margins(wrist)["wrist"] == pytest.approx(0.0, abs=1e-12)
    assert arm.manipulability(wrist) < 1e-6
    elbow = q.copy()
    elbow[2] = 0.0
    assert arm.singularity_margins(elbow)["elbow"] == pytest.approx(0.0, abs=1e-12)
    assert arm.manipulability(elbow) < 1e-6
    # shoulder: the wrist point (DH frame 5's origin) on the cylinder of radius d4 round the base axis
    p5 = ur_fk_m(q)[:3, 3] - 0.11655 * ur_fk_m(q)[:3, 2]
    assert arm.singularity_margins(q)["shoulder_mm"] == pytest.approx(
        1000 * math.sqrt(p5[0] ** 2 + p5[1] ** 2 - 0.17415 ** 2), rel=1e-9)


def _generic(q) -> bool:
    m = ArmModel.from_config(load_arm(UR10E)).singularity_margins(q)
    return m["shoulder_mm"] > 100 and m["elbow"] > 0.2 and m["wrist"] > 0.2


joints = st.lists(st.floats(-math.pi, math.pi, allow_nan=False), min_size=6, max_size=6).map(np.array)


@settings(max_examples=60, deadline=None)
@given(q=joints, dq=st.lists(st.floats(-0.05, 0.05), min_size=6, max_size=6).map(np.array))
def test_ik_from_a_nearby_seed_returns_the_same_configuration(arm, q, dq):
    if not _generic(q):
        return
    res = arm.ik(ur_fk_mm(q), q + dq)
    assert res.ok
    np.testing.assert_allclose(res.q, q, atol=1e-6)
    assert arm.configuration(res.q) == arm.configuration(q)


@settings(max_examples=60, deadline=None)
@given(q=joints)
def test_ik_finds_every_closed_form_solution_from_random_seeds(arm, q):
    if not _generic(q):
        return
    T = ur_fk_mm(q)
    sols = arm.ik_solutions(T, n_seeds=48)
    for s in sols:
        np.testing.assert_allclose(ur_fk_mm(s), T, atol=1e-3)
    closed = ur_ik_m(ur_fk_m(q))
    assert len(closed) in (2, 4, 6, 8)
    same = lambda x, y: np.allclose(np.remainder(x - y + math.pi, 2 * math.pi) - math.pi, 0, atol=1e-5)  # noqa: E731
    assert any(same(c, q) for c in closed)
    for c in closed:  # each closed-form solution, up to whole turns of the joints, and its branch label
        match = [s for s in sols if same(s, c)]
        assert match, np.degrees(c)
        assert arm.configuration(match[0]) == arm.configuration(c)
    assert len({arm.configuration(s) for s in sols}) == len(closed)


@settings(max_examples=60, deadline=None)
@given(q=joints)
def test_closed_form_solutions_are_the_published_ones(arm, q):
    if not _generic(q):
        return
    mine = arm.closed_form(ur_fk_mm(q))
    theirs = ur_ik_m(ur_fk_m(q))
    assert len(mine) == len(theirs)
    for c in theirs:
        assert any(np.allclose(np.remainder(m - c + math.pi, 2 * math.pi) - math.pi, 0, atol=1e-7) for m in mine)


def test_a_path_through_the_wrist_singularity_is_a_configuration_change(arm):
    q0 = np.radians([20, -70, 80, -90, 20, 15])
    q1 = np.radians([20, -70, 80, -90, -20, 15])
    poses = [ur_fk_mm(q0 + s * (q1 - q0)) for s in np.linspace(0, 1, 200)]
    res = arm.follow(poses, q0)
    assert not res.ok and res.reason in ("configuration", "unreachable")
    ok = arm.follow(poses[:80], q0)  # before the singularity: followed, joint by joint as commanded
    assert ok.ok
    np.testing.assert_allclose(ok.qs[-1], q0 + np.linspace(0, 1, 200)[79] * (q1 - q0), atol=1e-6)


def test_joint_speed_ratio(arm):
    t = np.linspace(0, 1, 101)
    qs = np.zeros((101, 6))
    qs[:, 0] = np.radians(60) * t  # 60 °/s on the base (limit 120)
    qs[:, 2] = np.radians(270) * t  # 270 °/s on the elbow (limit 180)
    np.testing.assert_allclose(arm.joint_speed_ratio(qs, t), [0.5, 0, 1.5, 0, 0, 0], atol=1e-9)


def test_path_followed_through_ik_gives_its_joint_speeds(arm):
    q0 = np.radians([20, -70, 80, -90, -60, 15])
    t = np.arange(0, 0.5, 0.004)
    w = np.radians([100, 40, -150, 60, 30, -200])  # rad/s, constant
    res = arm.follow([ur_fk_mm(q0 + w * ti) for ti in t[1:]], q0)
    assert res.ok
    np.testing.assert_allclose(arm.joint_speed_ratio(np.vstack([q0, res.qs]), t), np.abs(w) / arm.qd_max, rtol=1e-3)


def test_a_second_arm_is_a_second_file():
    ur5 = ArmModel.from_config(load_arm(UR5E))
    assert ur5.fk(np.zeros(6))[:3, 3] == pytest.approx([-425.0 - 392.2, -(133.3 + 99.6), 162.5 - 99.7], abs=1e-9)


def test_arm_file_errors_are_one_line(tmp_path):
    text = UR10E.read_text()
    bad = tmp_path / "arm.yaml"
    bad.write_text(text + "reach_mm: 1300\n")
    with pytest.raises(ConfigError, match="reach_mm: unknown key"):
        load_arm(bad)
    bad.write_text(text.replace("home_deg: [0.0, -90.0,", "home_deg: [400.0, -90.0,"))
    with pytest.raises(ConfigError, match="home_deg"):
        load_arm(bad)
    bad.write_text(text.replace("joint_speed_deg_s: [120.0,", "joint_speed_deg_s: [0.0,"))
    with pytest.raises(ConfigError, match="joint_speed_deg_s"):
        load_arm(bad)


@settings(max_examples=80, deadline=None)
@given(q=joints)
def test_out_of_reach_never_refuses_a_reachable_pose(arm, q):
    assert not arm.out_of_reach(ur_fk_mm(q))


def test_out_of_reach_catches_far_and_axial_poses(arm):
    far = np.eye(4)
    far[:3, 3] = [1500.0, 0.0, 500.0]
    assert arm.out_of_reach(far) and not arm.reachable(far)
    axial = np.eye(4)  # tool up, the wrist point on the base axis
    axial[:3, 3] = [0.0, 0.0, 900.0 + 116.55]
    assert arm.out_of_reach(axial) and not arm.reachable(axial)
    ur5 = ArmModel.from_config(load_arm(UR5E))
    for q in np.random.default_rng(4).uniform(-math.pi, math.pi, (50, 6)):
        assert not ur5.out_of_reach(ur5.fk(q))
