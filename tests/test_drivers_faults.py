"""Injected faults on real ptys: each ends, within the configured timeout, in recovery or a typed
DeviceError; after any fault the robot emulator is stopped."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from fakes import Wire, fake_grbl, fake_robot

from labctl.drivers.grbl import GrblTable
from labctl.drivers.robot import SerialRobot
from labctl.errors import DeviceError
from labctl.geometry import make_T, rot_x

TIMEOUT = 1.0


def moves(n):
    return ["G21", "G90", "G1 F6000"] + [f"G1 X{20 + i * 0.5:.3f} Y{20 + 5 * math.sin(i / 5):.3f}" for i in range(n)]


def run_stream(dev, lines, **kw):
    """Stream; returns ('ok', status) or ('error', exc). Bounded in time by the driver's timeouts."""
    table = GrblTable(dev.path, 115200, reset_on_open=False, timeout_s=TIMEOUT, status_hz=10, boot_s=0.5, **kw)
    t0 = time.monotonic()
    try:
        table.open()
        table.ensure_ready()
        table.stream(lines)
        st = table.wait_idle(timeout_s=20)
        return "ok", st, time.monotonic() - t0
    except DeviceError as exc:
        return "error", exc, time.monotonic() - t0
    finally:
        table.close()


def test_delayed_bytes_recover():
    with fake_grbl(homing=False, wire=Wire(delay_out_s=0.15)) as dev:
        outcome, st, _ = run_stream(dev, moves(80))
        assert outcome == "ok" and st.position[0] == pytest.approx(20 + 79 * 0.5, abs=1e-3)
        with dev.lock:
            assert dev.emulator.rx_overflows == 0


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_dropped_bytes_end_in_recovery_or_typed_error(seed):
    wire = Wire(seed=seed)
    with fake_grbl(homing=False, wire=wire) as dev:
        table = GrblTable(dev.path, 115200, reset_on_open=False, timeout_s=TIMEOUT, status_hz=10)
        table.open()
        wire.drop_in, wire.drop_out = 0.01, 0.01  # faults start once connected
        t0 = time.monotonic()
        try:
            table.stream(moves(150))
            outcome = "ok"
        except DeviceError as exc:
            outcome = type(exc).__name__
        finally:
            table.close()
        assert outcome in ("ok", "GrblError", "GrblAlarm", "ProtocolError", "DeviceTimeout", "GrblReset")
        assert time.monotonic() - t0 < 30
        assert wire.log  # faults really were injected


@pytest.mark.parametrize("seed", [4, 5])
def test_corrupted_bytes_end_in_recovery_or_typed_error(seed):
    wire = Wire(seed=seed)
    with fake_grbl(homing=False, wire=wire) as dev:
        table = GrblTable(dev.path, 115200, reset_on_open=False, timeout_s=TIMEOUT, status_hz=10)
        table.open()
        wire.corrupt_in, wire.corrupt_out = 0.01, 0.01
        t0 = time.monotonic()
        with pytest.raises(DeviceError):
            table.stream(moves(300))
            table.wait_idle(timeout_s=20)
            raise DeviceError("no fault surfaced")  # only acceptable if nothing was corrupted
        table.close()
        assert time.monotonic() - t0 < 30
        assert wire.log


def test_reset_mid_stream_is_a_typed_error():
    with fake_grbl(homing=False) as dev:
        table = GrblTable(dev.path, 115200, reset_on_open=False, timeout_s=TIMEOUT, status_hz=10)
        table.open()
        dev.reset_after(0.3)
        t0 = time.monotonic()
        with pytest.raises(DeviceError) as err:
            table.stream(moves(400))
            table.wait_idle(20)
        assert type(err.value).__name__ in ("GrblReset", "GrblAlarm")
        assert time.monotonic() - t0 < 10
        table.close()


def test_device_that_stops_answering_times_out():
    wire = Wire()
    with fake_grbl(homing=False, wire=wire) as dev:
        table = GrblTable(dev.path, 115200, reset_on_open=False, timeout_s=TIMEOUT, status_hz=10)
        table.open()
        wire.mute = True
        t0 = time.monotonic()
        with pytest.raises(DeviceError) as err:
            table.stream(moves(400))
        assert type(err.value).__name__ == "DeviceTimeout", str(err.value)
        assert time.monotonic() - t0 < TIMEOUT + 2.0
        table.close()


def test_device_answering_garbage_fails_to_connect_cleanly():
    with fake_grbl(homing=False, wire=Wire(garbage=True)) as dev:
        outcome, exc, elapsed = run_stream(dev, moves(10))
        assert outcome == "error" and type(exc).__name__ == "DeviceTimeout"
        assert elapsed < 0.5 + TIMEOUT + 2.0


# --- robot ---------------------------------------------------------------------------------
def _robot(dev):
    return SerialRobot(dev.path, 115200, timeout_s=0.3, heartbeat_s=0.1, retries=1)


def _assert_robot_stops(dev, within_s=1.5):
    """No heartbeats from here on: the watchdog (or a STOP) brings the arm to rest."""
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        with dev.lock:
            if not dev.emulator.moving:
                return
        time.sleep(0.05)
    with dev.lock:
        assert not dev.emulator.moving, "robot still moving after the fault"


FAR = make_T(rot_x(math.pi), [700.0, 0.0, 700.0])


@pytest.mark.parametrize("fault", ["mute", "garbage", "deaf"])
def test_robot_link_loss_ends_in_timeout_and_stop(fault):
    wire = Wire()
    with fake_robot(wire=wire) as dev:
        robot = _robot(dev)
        robot.open()
        robot.segment(FAR, 5.0, 1)
        setattr(wire, fault, True)
        t0 = time.monotonic()
        with pytest.raises(DeviceError):
            robot.status()
            robot.wait_done(1, timeout_s=3)
        assert time.monotonic() - t0 < 2 * (0.3 * 2) + 3.5
        robot.close()
        _assert_robot_stops(dev)


@pytest.mark.parametrize("seed", [7, 8])
def test_robot_dropped_and_corrupted_bytes(seed):
    wire = Wire(seed=seed)
    with fake_robot(wire=wire) as dev:
        robot = _robot(dev)
        robot.open()
        wire.drop_in = wire.drop_out = 0.005
        wire.corrupt_in = wire.corrupt_out = 0.005
        done = 0
        try:
            for i in range(20):
                robot.segment(make_T(rot_x(math.pi), [300.0 + 5 * (i % 2), -450.0, 900.0]), 0.1, i + 1)
                robot.status()
                done += 1
        except DeviceError:
            pass
        robot.close()
        # every pose the controller accepted was exactly one the driver sent (checksums)
        with dev.lock:
            for seg in dev.emulator.segments:
                end = seg.state(seg.t1)[0]
                if seg.seg_id > 0:
                    assert end[0] in (pytest.approx(300.0), pytest.approx(305.0))
                    assert np.allclose(end[1:], [-450.0, 900.0], atol=1e-6)
        _assert_robot_stops(dev)


def test_robot_reset_mid_motion_stops_and_is_reported():
    with fake_robot() as dev:
        robot = _robot(dev)
        robot.open()
        robot.segment(FAR, 5.0, 2)
        dev.reset_after(0.3)
        with pytest.raises(DeviceError):
            robot.wait_done(2, timeout_s=1.5)
        robot.close()
        _assert_robot_stops(dev, within_s=0.5)
