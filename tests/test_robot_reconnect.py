"""A robot link that drops mid-run (issue 12, Build 7): the robot driver reconnects with backoff,
reads the controller's state again (HELLO, STATUS) before anything moves, never sends motion
again blindly, and raises a typed error in bounded time when the link stays down.

The controller is the reference robot controller (docs/protocols/robot.md) on a real pty; the
link is TCP through labctl's ser2net-style bridge (``socket://``), which the tests stop and
start again as ser2net is restarted; or the pty itself, which they close (the USB port goes away).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import threading
import time

import numpy as np
import pytest
from fakes import Wire, fake_robot, robot_test_limits

from labctl.drivers.robot import RobotFault, SerialRobot
from labctl.drivers.serial_link import LinkError, LinkLost
from labctl.geometry import make_T, rot_x
from labctl.runtime.stopping import stop_robot
from labctl.sim.tcpserial import TcpSerialBridge

RECONNECT_S = 3.0


class Tap(Wire):
    """The host → controller bytes, as the controller received them."""

    def __init__(self):
        super().__init__()
        self.received = bytearray()

    def inbound(self, t: float, data: bytes) -> bytes:
        self.received += data
        return data

    def requests(self, word: str) -> int:
        return sum(1 for line in self.received.decode().splitlines() if f" {word}" in line.upper())


def _pose(x: float) -> np.ndarray:
    return make_T(rot_x(math.pi), [x, -450.0, 900.0])


def _later(seconds: float, fn) -> threading.Thread:
    def go():
        time.sleep(seconds)
        fn()

    th = threading.Thread(target=go, daemon=True)
    th.start()
    return th


@contextlib.contextmanager
def _served(watchdog_s: float = 0.5):
    tap = Tap()
    limits = dataclasses.replace(robot_test_limits(), watchdog_s=watchdog_s)
    with fake_robot(wire=tap, limits=limits) as dev, TcpSerialBridge(dev.path) as bridge:
        robot = SerialRobot(bridge.url, 115200, timeout_s=2.0, heartbeat_s=0.1, reconnect_s=RECONNECT_S)
        robot.open()
        try:
            yield dev, tap, bridge, robot
        finally:
            robot.close()


@pytest.fixture
def served():
    """(fake device, its wire tap, the bridge, the driver opened over socket://)."""
    with _served() as got:
        yield got


def test_a_brief_drop_at_rest_recovers_and_the_state_is_read_again_first(served):
    dev, tap, bridge, robot = served
    kept_alive = []
    robot.while_reconnecting = lambda: kept_alive.append(time.monotonic())
    hellos = tap.requests("HELLO")
    assert bridge.set_up(False)
    _later(0.5, lambda: bridge.set_up(True))
    t0 = time.monotonic()
    st = robot.status()  # the link is down: reconnect, HELLO, STATUS, then this STATUS again
    took = time.monotonic() - t0
    # back within reconnect_s, then HELLO and two STATUS round trips (each within the 2 s timeout)
    assert 0.4 < took < RECONNECT_S + 2.0 and robot.reconnects == 1 and not st.moving
    assert tap.requests("HELLO") == hellos + 1  # §10: HELLO on every reconnect, before anything else
    assert len(kept_alive) >= 5  # the caller's keep-alive ran while it waited (every ≤ 50 ms)
    robot.segment(_pose(350.0), 0.5, 7)  # and it moves again once the state was read
    robot.wait_done(7, timeout_s=3.0)


def test_a_drop_shorter_than_the_watchdog_keeps_the_motion_and_its_done():
    """The controller runs its queue on while the host is away (< watchdog_s, here 3 s so that a
    loaded machine's reconnect stays well inside it); a @DONE sent into the dropped link is
    recovered from STATUS (the robot at rest past the segment's end)."""
    with _served(watchdog_s=3.0) as (dev, tap, bridge, robot):
        robot.segment(_pose(380.0), 0.6, 11)
        bridge.set_up(False)
        _later(0.25, lambda: bridge.set_up(True))
        robot.wait_done(11, timeout_s=5.0)
        _check_kept(dev, tap, robot)


def _check_kept(dev, tap, robot):
    assert robot.reconnects == 1 and tap.requests("SEG") == 1  # nothing sent twice
    with dev.lock:
        assert np.allclose(dev.emulator.flange_pose_at(dev.emulator.now)[:3, 3], [380.0, -450.0, 900.0], atol=1e-3)


def test_a_drop_longer_than_the_watchdog_is_a_robot_fault_and_nothing_is_sent_again(served):
    dev, tap, bridge, robot = served
    robot.segment(_pose(700.0), 3.0, 21)
    bridge.set_up(False)
    _later(1.2, lambda: bridge.set_up(True))  # the controller's watchdog (0.5 s) stops the arm meanwhile
    with pytest.raises(RobotFault, match="watchdog") as err:
        robot.wait_done(21, timeout_s=10.0)
    assert "nothing was sent again" in str(err.value)
    assert tap.requests("SEG") == 1 and tap.requests("CLEAR") == 0
    with dev.lock:
        assert dev.emulator.fault == "watchdog" and not dev.emulator.moving


def test_a_controller_restart_while_away_is_a_robot_fault(served):
    """The @BOOT went into the dropped link: the host still sees its segments lost, because the robot
    stands still before the end of the segment it accepted."""
    dev, tap, bridge, robot = served
    robot.segment(_pose(700.0), 3.0, 31)
    bridge.set_up(False)
    with dev.lock:
        dev.emulator.power_cycle()
    _later(0.2, lambda: bridge.set_up(True))
    with pytest.raises(RobotFault, match="before its last segment's end"):
        robot.wait_done(31, timeout_s=10.0)
    assert tap.requests("SEG") == 1


def test_a_motion_request_under_a_drop_is_never_sent_again(served):
    dev, tap, bridge, robot = served
    bridge.set_up(False)
    _later(0.3, lambda: bridge.set_up(True))
    with pytest.raises(LinkLost, match="nothing was sent again"):
        robot.segment(_pose(400.0), 1.0, 41)
    assert tap.requests("SEG") == 0  # the SEG went into the dropped connection, and was not resent
    with dev.lock:
        assert not dev.emulator.moving


def test_a_link_that_stays_down_is_link_lost_in_bounded_time_and_the_stop_path_is_quick(served):
    dev, tap, bridge, robot = served
    robot.segment(_pose(700.0), 3.0, 51)
    bridge.set_up(False)  # ser2net does not come back
    t0 = time.monotonic()
    with pytest.raises(LinkLost, match=f"within {RECONNECT_S:g} s"):
        robot.wait_done(51, timeout_s=30.0)
    assert RECONNECT_S - 0.1 < time.monotonic() - t0 < RECONNECT_S + 1.0
    t1 = time.monotonic()
    out = stop_robot(robot)  # a worker's exit path: one quick try per command once the link is lost
    assert time.monotonic() - t1 < 1.0 and not out["confirmed"] and "LinkLost" in out["error"]
    time.sleep(0.6)
    with dev.lock:  # the controller's own watchdog stopped the arm
        dev.emulator.advance(time.monotonic())
        assert dev.emulator.fault == "watchdog"


@pytest.mark.parametrize("reconnect_s", [0.0, 1.0])
def test_a_closed_pty_is_a_typed_error_in_bounded_time(reconnect_s):
    with fake_robot() as dev:
        robot = SerialRobot(dev.path, 115200, timeout_s=1.0, heartbeat_s=0.1, reconnect_s=reconnect_s)
        robot.open()
        try:
            dev.stop()  # the controller's USB port goes away
            t0 = time.monotonic()
            with pytest.raises(LinkError):
                robot.status()
            assert time.monotonic() - t0 < reconnect_s + 1.5
        finally:
            robot.close()
