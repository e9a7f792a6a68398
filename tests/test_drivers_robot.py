"""The robot driver against the robot controller emulator on real pseudo-terminals."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from fakes import fake_robot

from labctl.drivers.robot import RobotError, RobotFault, SerialRobot
from labctl.geometry import make_T, rot_x, rot_z


def test_identify_status_segment_and_done():
    with fake_robot() as dev, SerialRobot(dev.path, 115200, timeout_s=1.0, heartbeat_s=0.1) as robot:
        assert robot.ident.startswith("labctl-robot")
        st = robot.status()
        assert not st.moving and np.allclose(st.T_base_flange[:3, 3], [300, -450, 900], atol=1e-3)
        T = make_T(rot_x(math.pi) @ rot_z(0.2), [420.0, -380.0, 820.0])
        t0, t1 = robot.segment(T, 1.0, 11)
        assert t1 - t0 == pytest.approx(1.0)
        assert robot.status().moving
        robot.wait_done(11, timeout_s=5)
        st = robot.status()
        assert st.segment_id == 11 and not st.moving
        assert np.allclose(st.T_base_flange, T, atol=1e-3)
        with dev.lock:
            assert np.allclose(dev.emulator.flange_pose_at(dev.emulator.now), T, atol=1e-5)
        assert robot.limits()["v_max_mm_s"] == 500.0


def test_refusals_are_typed():
    with fake_robot() as dev, SerialRobot(dev.path, 115200, timeout_s=1.0) as robot:
        with pytest.raises(RobotError) as err:
            robot.segment(make_T(rot_x(math.pi), [400.0, -300.0, 10.0]), 5.0, 1)
        assert err.value.code == 10
        with pytest.raises(RobotError) as err:
            robot.segment(make_T(rot_x(math.pi), [900.0, 600.0, 700.0]), 0.3, 2)
        assert err.value.code == 12
        with pytest.raises(ValueError):
            robot.segment(np.eye(3), 1.0, 3)


def test_watchdog_fault_surfaces_and_robot_stops():
    with fake_robot() as dev, SerialRobot(dev.path, 115200, timeout_s=1.0, heartbeat_s=0.1) as robot:
        robot.segment(make_T(rot_x(math.pi), [650.0, -100.0, 700.0]), 4.0, 5)
        time.sleep(1.0)  # the host "stalls": no heartbeat
        with pytest.raises(RobotFault):
            robot.wait_done(5, timeout_s=5)
        time.sleep(0.3)
        with dev.lock:
            assert not dev.emulator.moving and dev.emulator.fault == "watchdog"
        robot.clear()
        robot.home()
        assert robot.status().moving


def test_heartbeats_keep_a_long_segment_alive():
    with fake_robot() as dev, SerialRobot(dev.path, 115200, timeout_s=1.0, heartbeat_s=0.1) as robot:
        robot.segment(make_T(rot_x(math.pi), [500.0, -300.0, 800.0]), 1.5, 6)
        robot.wait_done(6, timeout_s=5)  # heartbeats while waiting
        with dev.lock:
            assert dev.emulator.fault is None and dev.emulator.watchdog_trips == 0
