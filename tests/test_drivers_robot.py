"""The robot driver against the robot controller emulator on real pseudo-terminals."""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest
from fakes import fake_robot, robot_test_limits

from labctl.drivers.robot import RobotError, RobotFault, SerialRobot
from labctl.geometry import make_T, rot_x, rot_z
from labctl.sim.emulators.pty import PtyDevice
from labctl.sim.emulators.robot import RobotEmulator


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


# the new tests are about the dialect, not the watchdog: 2 s keeps them steady on a loaded machine
SLOW_WATCHDOG = dataclasses.replace(robot_test_limits(), watchdog_s=2.0)


class Controller10(RobotEmulator):
    """A dialect 1.0 controller as 1.0 was built: HELLO ignores its argument and STOP does not latch."""

    dialect = "1.0"

    def _cmd_hello(self, req):
        self.session = "1.0"
        self._reply(req.seq, f"{self.name} 1.0 queue={self.queue_size}")


class Strict10(Controller10):
    """A 1.0 controller that follows 1.0's rule "E02 for a wrong argument count" to the letter."""

    def _cmd_hello(self, req):
        if req.args:
            self._error(req.seq, 2)
        else:
            super()._cmd_hello(req)


@pytest.mark.parametrize("cls", [Controller10, Strict10])
def test_driver_negotiates_down_to_a_1_0_controller(cls):
    emu = cls(time.monotonic, SLOW_WATCHDOG)
    with PtyDevice(emu, 115200) as dev, SerialRobot(dev.path, 115200, timeout_s=2.0, heartbeat_s=0.1) as robot:
        assert robot.dialect == "1.0" and robot.profiles == ("quintic",) and robot.queue == 8
        robot.segment(make_T(rot_x(math.pi), [420.0, -380.0, 820.0]), 1.0, 1)
        robot.stop()  # 1.0: no latch, the next segment just runs
        robot.segment(make_T(rot_x(math.pi), [400.0, -400.0, 850.0]), 1.0, 2)
        robot.wait_done(2, timeout_s=5)
        lim = robot.limits()  # a 1.0 session gets the 1.0 text's ten fields (docs/protocols/robot.md §9)
        assert "a_stop_mm_s2" not in lim and lim["watchdog_s"] == 2.0


def test_driver_speaks_1_2_stop_latches_until_clear():
    with fake_robot(limits=SLOW_WATCHDOG) as dev, \
            SerialRobot(dev.path, 115200, timeout_s=2.0, heartbeat_s=0.1) as robot:
        assert robot.dialect == "1.4" and robot.profiles == ("quintic", "ruckig")
        assert robot.limits()["a_stop_mm_s2"] == pytest.approx(1500 / math.sqrt(3), abs=1e-5)
        with pytest.raises(ValueError):
            robot.segment(make_T(rot_x(math.pi), [420.0, -380.0, 820.0]), 1.0, 0)  # HOME's id
        with pytest.raises(ValueError):
            robot.segment(make_T(rot_x(math.pi), [420.0, -380.0, 820.0]), 1.0, 3, profile="trapezoid")
        robot.segment(make_T(rot_x(math.pi), [420.0, -380.0, 820.0]), 1.0, 3)
        robot.stop()
        with pytest.raises(RobotError) as err:
            robot.segment(make_T(rot_x(math.pi), [400.0, -400.0, 850.0]), 1.0, 4)
        assert err.value.code == 41
        robot.clear()
        robot.segment(make_T(rot_x(math.pi), [400.0, -400.0, 850.0]), 1.0, 4)
        robot.wait_done(4, timeout_s=5)


def test_a_reboot_after_motion_was_commanded_is_a_fault():
    with fake_robot(limits=SLOW_WATCHDOG) as dev, \
            SerialRobot(dev.path, 115200, timeout_s=2.0, heartbeat_s=0.1) as robot:
        assert not robot.faults  # the @BOOT of start-up is not a loss
        robot.segment(make_T(rot_x(math.pi), [420.0, -380.0, 820.0]), 1.5, 7)
        dev.reset_after(0.2)
        with pytest.raises(RobotFault):
            robot.wait_done(7, timeout_s=5)
        assert "boot" in robot.faults


def test_driver_speaks_1_3_with_an_arm_reads_its_joints_and_names_each_refusal():
    from arm_dh import rotation_angle, sample_mount, ur10e_fk

    from labctl.config import load_lab
    from labctl.sim.lab import arm_servo
    from labctl.sim.world import home_flange_pose
    from labctl.workspace import sample_lab_path

    lab = load_lab(sample_lab_path())
    with fake_robot(limits=lab.robot, start_pose=home_flange_pose(lab), arm=arm_servo(lab)) as dev, \
            SerialRobot(dev.path, 115200, timeout_s=2.0, heartbeat_s=0.1) as robot:
        assert robot.dialect == "1.4" and robot.arm == "UR10e" and robot.profiles == ("quintic", "ruckig")
        st = robot.status()
        assert st.joints_rad is not None and len(st.joints_rad) == 6
        T = ur10e_fk(st.joints_rad, sample_mount())
        assert np.linalg.norm(T[:3, 3] - st.T_base_flange[:3, 3]) < 0.1
        assert rotation_angle(T[:3, :3].T @ st.T_base_flange[:3, :3]) < 2e-4
        over_axis = st.T_base_flange.copy()  # the wrist point on the base axis: out of the arm's reach
        over_axis[:3, 3] = sample_mount()[:3, 3] + [0.0, 0.0, 580.7] + 116.55 * over_axis[:3, 2]
        with pytest.raises(RobotError) as err:
            robot.segment(over_axis, 4.0, 1)
        assert err.value.code == 30
        msg = str(err.value)
        assert "\n" not in msg and "outside the arm's reach" in msg and "nothing moved" in msg
        assert not robot.status().moving


def test_driver_reads_no_joints_from_a_controller_without_an_arm():
    with fake_robot(limits=SLOW_WATCHDOG) as dev, SerialRobot(dev.path, 115200, timeout_s=2.0) as robot:
        assert robot.dialect == "1.4" and robot.arm is None and robot.status().joints_rad is None


class Controller12(RobotEmulator):
    """The reference as a 1.2 controller (before SET): a 1.4 host speaks 1.2 with it."""

    dialect = "1.2"


def _sent_lines(robot: SerialRobot) -> list[str]:
    """Every request line the driver sends from now on, without its checksum."""
    sent: list[str] = []
    request = robot.link.request

    def spy(line, *args, **kw):
        sent.append(line.rpartition("*")[0] if "*" in line else line)
        return request(line, *args, **kw)

    robot.link.request = spy  # type: ignore[method-assign]
    return sent


def _ruckig_rest_to_rest_s(distance_mm: float, v_max: float, a_max: float, j_max: float) -> float:
    """The time-optimal jerk-limited rest-to-rest move along one axis, from the ruckig library itself."""
    from ruckig import InputParameter, Ruckig, Trajectory

    inp, traj = InputParameter(1), Trajectory(1)
    inp.current_position, inp.target_position = [0.0], [distance_mm]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [v_max], [a_max], [j_max]
    Ruckig(1).calculate(inp, traj)
    return traj.duration


def test_segment_defaults_leave_profile_and_limits_off_the_line_and_still_run_them():
    with fake_robot(limits=SLOW_WATCHDOG) as dev, \
            SerialRobot(dev.path, 115200, timeout_s=2.0, heartbeat_s=0.1) as robot:
        lim = robot.limits()
        T0 = robot.status().T_base_flange
        T1 = T0.copy()
        T1[0, 3] += 100.0
        sent = _sent_lines(robot)
        assert robot.segment_defaults("ruckig", {"vmax": 300.0})
        t0, t1 = robot.segment(T1, 0.0, 1, replace=True, profile="ruckig", limits={"vmax": 300.0})
        assert sent[0].split()[1:] == ["SET", "profile=ruckig", "vmax=300"]
        assert "profile=" not in sent[1] and "vmax" not in sent[1], sent[1]
        # the controller ran the ruckig move under vmax 300 (not a quintic, not its own 500 mm/s)
        want = _ruckig_rest_to_rest_s(100.0, 300.0, lim["a_max_mm_s2"], lim["j_max_mm_s3"])
        assert abs((t1 - t0) - want) < 2e-3, (t1 - t0, want)
        robot.wait_done(1, timeout_s=5)
        t0, t1 = robot.segment(T0, 1.0, 2)  # a quintic off the defaults names its profile
        assert sent[-1].split()[-1].startswith("profile=quintic") and t1 - t0 == pytest.approx(1.0, abs=1e-4)
        robot.wait_done(2, timeout_s=5)
        robot.segment(T1, 0.0, 3, profile="ruckig", limits={"vmax": 200.0})  # other limits: named in full
        assert sent[-1].split()[-2:] == ["profile=ruckig", "vmax=200"], sent[-1]
        robot.wait_done(3, timeout_s=5)
        robot.negotiate()  # a reconnect's HELLO drops the controller's defaults: the driver sets them again
        assert sent[-2].split()[1] == "HELLO" and sent[-1].split()[1:3] == ["SET", "profile=ruckig"]
        robot.segment(T0, 0.0, 4, profile="ruckig", limits={"vmax": 300.0})
        assert "profile=" not in sent[-1]
        robot.wait_done(4, timeout_s=5)


def test_an_older_controller_gets_no_set_and_segments_keep_naming_their_profile():
    emu = Controller12(time.monotonic, SLOW_WATCHDOG)
    with PtyDevice(emu, 115200) as dev, SerialRobot(dev.path, 115200, timeout_s=2.0, heartbeat_s=0.1) as robot:
        assert robot.dialect == "1.2"
        T1 = robot.status().T_base_flange.copy()
        T1[0, 3] += 50.0
        sent = _sent_lines(robot)
        assert not robot.segment_defaults("ruckig", {"vmax": 300.0})
        robot.segment(T1, 0.0, 1, replace=True, profile="ruckig", limits={"vmax": 300.0})
        assert len(sent) == 1 and "profile=ruckig vmax=300" in sent[0], sent
        robot.wait_done(1, timeout_s=5)


def test_a_held_segment_waits_for_go_and_runs_from_then():
    with fake_robot(limits=SLOW_WATCHDOG) as dev, \
            SerialRobot(dev.path, 115200, timeout_s=2.0, heartbeat_s=0.1) as robot:
        assert robot.holds
        T0 = robot.status().T_base_flange
        T1 = T0.copy()
        T1[1, 3] += 40.0
        sent = _sent_lines(robot)
        assert all(math.isnan(x) for x in robot.segment(T1, 1.0, 5, hold=True))
        assert sent[-1].endswith("hold=1")
        time.sleep(0.3)
        st = robot.status()
        assert not st.moving and np.allclose(st.T_base_flange[:3, 3], T0[:3, 3], atol=1e-3)
        t0, t1 = robot.go(5)
        assert st.t <= t0 and t1 - t0 == pytest.approx(1.0, abs=1e-4)  # from the GO, not from the SEG
        robot.wait_done(5, timeout_s=5)
        assert np.allclose(robot.status().T_base_flange[:3, 3], T1[:3, 3], atol=1e-3)
        with pytest.raises(RobotError) as err:
            robot.go(5)  # run once: nothing held any more
        assert err.value.code == 21
        with pytest.raises(ValueError):
            robot.segment(T0, 1.0, 6, hold=True, replace=True)
