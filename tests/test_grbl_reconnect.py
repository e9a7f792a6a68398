"""A link that drops mid-run (issue 12, Build 7): the GRBL driver reconnects with backoff and reads
the state again before anything moves, or raises a typed error in bounded time.

The table is the GRBL emulator on a real pty; the link is TCP through a relay in the style of
ser2net (``socket://``), which the tests stop and restart; or the pty itself, which they close.
"""

from __future__ import annotations

import math
import select
import socket
import threading
import time

import pytest
import serial
from fakes import fake_grbl

from labctl.drivers.grbl import GrblAlarm, GrblTable
from labctl.drivers.serial_link import LinkError, LinkLost


class Relay:
    """TCP port ↔ the device's pty, one client at a time, like ser2net. ``stop()`` drops both sides."""

    def __init__(self, pty_path: str, port: int = 0):
        self.srv = socket.socket()
        self.srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.srv.bind(("127.0.0.1", port))
        self.srv.listen(1)
        self.port = self.srv.getsockname()[1]
        self.dev = serial.Serial(pty_path, 115200, timeout=0)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        self.srv.settimeout(0.05)
        conn = None
        while not self._stop.is_set():
            if conn is None:
                try:
                    conn, _ = self.srv.accept()
                except (TimeoutError, OSError):
                    continue
            r, _, _ = select.select([conn, self.dev.fileno()], [], [], 0.02)
            if conn in r:
                data = conn.recv(4096)
                if not data:
                    conn.close()
                    conn = None
                    continue
                self.dev.write(data)
            if self.dev.fileno() in r:
                data = self.dev.read(4096)
                if data:
                    conn.sendall(data)
        if conn is not None:
            conn.close()

    def stop(self):
        self._stop.set()
        self.thread.join(2)
        self.srv.close()
        self.dev.close()


def program(n=200):
    return ["G21", "G90", "G1 F1500"] + [f"G1 X{20 + i:.1f} Y{20 + 5 * math.sin(i / 5):.3f}" for i in range(n)]


def restart_later(relay_box, pty_path, port, after_s):
    def go():
        time.sleep(after_s)
        relay_box[0] = Relay(pty_path, port)

    threading.Thread(target=go, daemon=True).start()


def test_status_recovers_when_the_server_comes_back():
    with fake_grbl(homing=False) as dev:
        box = [Relay(dev.path)]
        port = box[0].port
        try:
            with GrblTable(f"socket://127.0.0.1:{port}", 115200, reset_on_open=False, timeout_s=2.0,
                           reconnect_s=5.0) as t:
                assert t.status().state == "Idle"
                box[0].stop()
                restart_later(box, dev.path, port, 0.5)
                t0 = time.monotonic()
                assert t.status().state == "Idle"  # reconnected, state read again
                assert time.monotonic() - t0 < 5.0
                assert t.move_to(30.0, 20.0, 3000).position[:2] == pytest.approx((30.0, 20.0))
        finally:
            box[0].stop()


def test_drop_mid_program_stops_the_table_and_is_typed():
    with fake_grbl(homing=False) as dev:
        box = [Relay(dev.path)]
        port = box[0].port
        try:
            with GrblTable(f"socket://127.0.0.1:{port}", 115200, reset_on_open=False, timeout_s=2.0,
                           reconnect_s=5.0, status_hz=10) as t:
                prog = t.start_program(program())
                t0 = time.monotonic()
                while time.monotonic() - t0 < 1.0:
                    prog.pump(0.01)
                with dev.lock:
                    assert dev.emulator.moving
                box[0].stop()
                restart_later(box, dev.path, port, 0.5)
                with pytest.raises(LinkLost) as err:
                    while prog.pump(0.01):
                        pass
                assert "abandoned" in str(err.value) and "stopped" in str(err.value)
                assert time.monotonic() - t0 < 10.0
            with dev.lock:
                assert not dev.emulator.moving and dev.emulator.state_word in ("Idle", "Alarm")
        finally:
            box[0].stop()


def test_reset_while_away_ends_in_an_alarm_and_nothing_moves():
    """The board reset while the link was down (power-up homing lock): never unlocked silently."""
    with fake_grbl(homing=True) as dev:
        box = [Relay(dev.path)]
        port = box[0].port
        try:
            with GrblTable(f"socket://127.0.0.1:{port}", 115200, reset_on_open=False, timeout_s=2.0,
                           reconnect_s=5.0) as t:
                t.ensure_ready(unlock=True)
                t.move_to(10.0, 10.0, 3000)
                box[0].stop()
                with dev.lock:
                    dev.emulator.power_cycle()
                restart_later(box, dev.path, port, 0.3)
                with pytest.raises(GrblAlarm):
                    t.move_to(50.0, 50.0, 3000)
                with dev.lock:
                    assert not dev.emulator.moving
                    assert dev.emulator.machine_position()[0] == pytest.approx(10.0)  # it never moved
        finally:
            box[0].stop()


@pytest.mark.parametrize("reconnect_s", [0.0, 1.0])
def test_a_closed_pty_is_a_typed_error_in_bounded_time(reconnect_s):
    with fake_grbl(homing=False) as dev:
        t = GrblTable(dev.path, 115200, reset_on_open=False, timeout_s=2.0, reconnect_s=reconnect_s, status_hz=10)
        t.open()
        try:
            prog = t.start_program(program())
            prog.pump(0.2)
            dev.pty.stop()  # the board's USB port goes away
            t0 = time.monotonic()
            with pytest.raises(LinkError):
                while prog.pump(0.01):
                    pass
            assert time.monotonic() - t0 < reconnect_s + 3.0
        finally:
            t.close()
