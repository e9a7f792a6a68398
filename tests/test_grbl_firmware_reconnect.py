"""The GRBL driver's reconnect (issue 12, Build 7) against the real GRBL 1.1h firmware.

The unchanged firmware (``../shared/grbl-sim``, a quarter of real time) on a pty, behind labctl's
ser2net-style TCP bridge, which the tests stop and start again mid-move. The firmware is the
oracle: it keeps executing what it accepted while nobody is connected, and a reset in motion
gives its own ALARM:3 (the position is unknown); the driver must read that state again before
anything moves, and never clear the alarm by itself.
"""

from __future__ import annotations

import threading
import time

import pytest
from test_grbl_firmware import SLOW, Firmware, _shared, firmware_exe  # noqa: F401 (a fixture)

from labctl.drivers.grbl import GrblAlarm, GrblTable
from labctl.sim.tcpserial import TcpSerialBridge

RECONNECT_S = 5.0


@pytest.fixture(scope="module")
def fw(firmware_exe) -> Firmware:  # noqa: F811 (the imported fixture)
    f = Firmware(firmware_exe, _shared() / "serve_pty.py")
    try:
        f.fresh()
        yield f
    finally:
        f.stop()


def _table(url: str, auto_unlock: bool = False) -> GrblTable:
    return GrblTable(url, 115200, reset_on_open=False, timeout_s=SLOW, status_hz=10, auto_unlock=auto_unlock,
                     reconnect_s=RECONNECT_S)


def _running(t: GrblTable) -> None:
    deadline = time.monotonic() + SLOW
    while t.status().state != "Run":
        assert time.monotonic() < deadline, "the move never started"


def test_a_brief_drop_mid_move_recovers_and_the_firmware_finished_the_move(fw):
    fw.fresh()
    with TcpSerialBridge(fw.path) as bridge, _table(bridge.url) as t:
        t.stream(["G21G90", "G53G1X30F1200"])  # accepted at once; ~1.5 s of motion, ~6 s on the wall clock
        _running(t)
        x_before = t.status().position[0]
        kept = []
        t.while_reconnecting = lambda: kept.append(1)
        assert bridge.set_up(False)
        threading.Timer(0.8, lambda: bridge.set_up(True)).start()
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.5:  # what a run does between frames: watch it
            t.watch()
            time.sleep(0.02)
        deadline = time.monotonic() + RECONNECT_S + 3.0
        while not kept or t.link_lost:  # noticed the drop, waited, reconnected
            assert time.monotonic() < deadline
            t.watch()
            time.sleep(0.02)
        st = t.status()  # the state read again: still running the move it was given, further on
        assert st.state in ("Run", "Idle") and st.position[0] > x_before
        assert t.wait_idle(timeout_s=30).position[0] == pytest.approx(30.0, abs=1e-3)


def test_a_reset_in_motion_while_away_is_alarm3_and_nothing_moves(fw):
    """The ALARM:3 line went into the dropped link and the banner may come after the reconnect (the
    firmware answers nothing for ~2 s after a reset): the driver waits for it within ``reconnect_s``,
    and even with ``auto_unlock`` (which releases a power-up lock it saw) never clears this one."""
    fw.fresh()
    with TcpSerialBridge(fw.path) as bridge, _table(bridge.url, auto_unlock=True) as t:
        t.stream(["G21G90", "G53G1X40F1200"])
        _running(t)
        assert bridge.set_up(False)
        fw.raw(b"\x18", timeout_s=0.3)  # the board resets in motion while the link is down: ALARM:3
        assert bridge.set_up(True)
        with pytest.raises(GrblAlarm, match="position may be lost"):
            t.move_to(5.0, 5.0, 6000)  # the state is read again first: Alarm, so nothing is sent
        x = t.status().position[0]
        time.sleep(1.0)
        st = t.status()
        assert st.state == "Alarm" and st.position[0] == pytest.approx(x, abs=1e-3)  # it never moved
        with pytest.raises(GrblAlarm):
            t.ensure_ready()  # never unlocked silently, though a banner came after the reconnect
    status = fw.status()
    assert "Alarm" in status and f"MPos:{x:.3f}" in status
