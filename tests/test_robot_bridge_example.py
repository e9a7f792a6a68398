"""The bridge skeleton of docs/protocols/robot_bridge_example.py, on a pty, against the conformance suite."""

from __future__ import annotations

import importlib.util
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from fakes import robot_test_limits

from labctl.geometry import make_T, rot_x
from labctl.sim.emulators.pty import PtyDevice

ROOT = Path(__file__).resolve().parents[1]


def load_example():
    path = ROOT / "docs" / "protocols" / "robot_bridge_example.py"
    spec = importlib.util.spec_from_file_location("robot_bridge_example", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_bridge_skeleton_passes_conformance_and_streams_a_continuous_trajectory():
    ex = load_example()
    cfg = robot_test_limits()
    arm = ex.ArmAPI(make_T(rot_x(math.pi), cfg.home_mm))
    bridge = ex.Bridge(arm, time.monotonic, cfg)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    rules = ["hello.*", "checksum.*", "errors.*", "timing.arrival", "stop.ramp", "watchdog.trips"]
    with PtyDevice(bridge, 115200) as dev:
        cmd = [sys.executable, "-m", "labctl", "robot", "conformance", "--port", dev.path, "--baud", "115200",
               "--timeout", "3"] + [x for r in rules for x in ("--only", r)]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
        assert not dev.errors
        with dev.lock:
            pts = list(arm.setpoints)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "0 failed" in res.stdout.splitlines()[-1]
    t = np.array([s[0] for s in pts])
    p = np.array([s[1][:3, 3] for s in pts])
    assert len(pts) > 100 and np.allclose(np.diff(t), bridge.servo_period_s, atol=1e-9)
    assert np.ptp(p, axis=0).max() > 30.0  # the arm was really moved
    # continuous setpoints: no jump beyond v_max per servo period, all inside the box
    assert np.linalg.norm(np.diff(p, axis=0), axis=1).max() <= cfg.v_max_mm_s * bridge.servo_period_s * (1 + 1e-6)
    assert np.all(p >= np.array(cfg.workspace_min_mm) - 1e-6) and np.all(p <= np.array(cfg.workspace_max_mm) + 1e-6)


def test_bridge_with_the_arm_streams_joint_setpoints_of_the_checked_trajectory():
    """With the sample lab's UR10e the bridge streams joints (servoJ): each setpoint, put through a
    hand-written DH forward kinematics, is the pose the controller's trajectory has at that instant;
    the setpoints are continuous within the joints' speed limits; the arm rules pass against it."""
    from arm_dh import rotation_angle, sample_mount, ur10e_fk

    from labctl.config import load_lab
    from labctl.sim.lab import arm_servo
    from labctl.sim.world import home_flange_pose
    from labctl.workspace import sample_lab_path

    ex = load_example()
    lab = load_lab(sample_lab_path())
    servo = arm_servo(lab)
    start = home_flange_pose(lab)
    sdk = ex.ArmAPI(start, servo.initial(start))
    bridge = ex.Bridge(sdk, time.monotonic, lab.robot, arm=servo)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    rules = ["hello.*", "status.format", "timing.arrival", "arm.*"]
    with PtyDevice(bridge, 115200) as dev:
        cmd = [sys.executable, "-m", "labctl", "robot", "conformance", "--port", dev.path, "--baud", "115200",
               "--timeout", "3"] + [x for r in rules for x in ("--only", r)]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
        assert not dev.errors
        with dev.lock:
            pts = list(sdk.joint_setpoints)
            poses = [bridge.state_at(t) for t, _ in pts]
    assert res.returncode == 0, res.stdout + res.stderr
    assert "0 failed, 0 skipped" in res.stdout.splitlines()[-1], res.stdout
    assert not sdk.setpoints  # joint mode only
    t = np.array([s[0] for s in pts])
    q = np.array([s[1] for s in pts])
    assert len(pts) > 500 and np.allclose(np.diff(t), bridge.servo_period_s, atol=1e-9)
    assert np.ptp(q, axis=0).max() > math.radians(150)  # the wrist was really turned (arm.joint_limit)
    T_w_base = sample_mount()
    pos_err = rot_err = 0.0
    for qi, (p, _, _, R, _) in zip(q, poses):
        T = ur10e_fk(qi, T_w_base)
        pos_err = max(pos_err, float(np.linalg.norm(T[:3, 3] - p)))
        rot_err = max(rot_err, rotation_angle(T[:3, :3].T @ R))
    assert pos_err < 1e-4 and rot_err < 1e-7
    qd_max = np.radians([120.0, 120.0, 180.0, 180.0, 180.0, 180.0])  # the UR10e data sheet
    assert np.all(np.abs(np.diff(q, axis=0)) <= qd_max * bridge.servo_period_s * 1.02)
