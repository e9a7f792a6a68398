"""`labctl table` stops the table on every exit path, against the GRBL emulator on a pty (issue 13),
and the smaller GRBL findings of issue 12: stalls, homing time-out, --baud/--timeout checks.
The same paths run against the real firmware in tests/test_grbl_firmware.py."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fakes import fake_grbl, run_cli

from labctl.drivers.grbl import GrblTable, TableStall

REPO = Path(__file__).resolve().parents[1]


run = run_cli


def labctl_popen(*args):
    return subprocess.Popen([sys.executable, "-m", "labctl", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})


def wait_moving(dev, timeout_s=30.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with dev.lock:
            if dev.emulator.moving:
                return
        time.sleep(0.05)
    raise AssertionError("the table never started moving")


def assert_still(dev):
    with dev.lock:
        p1 = dev.emulator.machine_position().copy()
        assert not dev.emulator.moving and dev.emulator.state_word in ("Idle", "Alarm")
    time.sleep(0.5)
    with dev.lock:
        assert (dev.emulator.machine_position() == p1).all()
    return p1


@pytest.mark.parametrize("sig,args", [
    (signal.SIGINT, ["move", "500", "300", "--feed", "1500"]),
    (signal.SIGTERM, ["stream", "PROG"]),
])
def test_interrupt_stops_the_emulated_table(tmp_path, sig, args):
    prog = tmp_path / "prog.nc"
    prog.write_text("G21 G90\nG1 F1500\n" + "".join(f"G1 X{10 + i * 5} Y{10 + i * 2}\n" for i in range(80)))
    args = [str(prog) if a == "PROG" else a for a in args]
    with fake_grbl(homing=False) as dev:
        p = labctl_popen("table", *args, "--port", dev.path, "--baud", "115200")
        wait_moving(dev)
        time.sleep(0.3)
        p.send_signal(sig)
        out, err = p.communicate(timeout=30)
        assert p.returncode == 130, err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "interrupted" in lines[0] and "confirmed Idle" in lines[0], err
        pos = assert_still(dev)
        assert 0 < pos[0] < 400  # stopped part-way, position kept (hold before reset: no ALARM:3)


def test_a_grbl_error_mid_stream_stops_the_table(tmp_path, capsys):
    body = ["(test)", "G21 G90", "G1 F1500"] + [f"G1 X{10 + i * 3}" for i in range(60)] + ["G1 X10 Y10 Z"]
    prog = tmp_path / "bad.nc"
    prog.write_text("\n".join(body) + "\n")
    with fake_grbl(homing=False) as dev:
        code, _, err = run(capsys, "table", "stream", str(prog), "--port", dev.path, "--baud", "115200")
        assert code == 3 and f"file line {len(body)}" in err and "confirmed Idle" in err, err
        assert len(err.strip().splitlines()) == 1
        assert_still(dev)


def test_homing_timeout_is_bounded_and_reports_progress(capsys):
    with fake_grbl(homing=True, start_mm=(300.0, 200.0, 0.0), settings={25: 300.0}) as dev:
        t0 = time.monotonic()
        code, _, err = run(capsys, "table", "home", "--timeout", "2.5", "--port", dev.path, "--baud", "115200")
        assert code == 3 and "homing not finished after 2.5 s" in err, err
        assert "homing… 2 s" in err
        assert time.monotonic() - t0 < 15
        assert_still(dev)


@pytest.mark.parametrize("opt,value", [("--baud", "-5"), ("--baud", "0"), ("--timeout", "0")])
def test_bad_numbers_are_input_errors(capsys, opt, value):
    code, _, err = run(capsys, "table", "status", "--port", "/dev/null", opt, value)
    assert code == 2 and opt in err


class FrozenGrbl:
    """A GRBL whose steppers froze while its state still says Run (seen in grbl-sim before its
    interrupt-flag fix): every report is the same Run position; lines are acknowledged."""

    is_open = True
    port = "frozen://"

    def __init__(self):
        self.out = bytearray(b"\r\nGrbl 1.1h ['$' for help]\r\n")

    def write(self, data):
        for b in bytes(data):
            if b == ord("?"):
                self.out += b"<Run|MPos:12.500,3.000,0.000|FS:1200,0|WCO:0.000,0.000,0.000>\r\n"
            elif b == ord("\n"):
                self.out += b"ok\r\n"
        return len(data)

    @property
    def in_waiting(self):
        return len(self.out)

    def read(self, n):
        data, self.out[:n] = bytes(self.out[:n]), b""
        return data

    def open(self):
        pass

    def close(self):
        pass


def test_run_without_motion_is_a_stall():
    t = GrblTable(serial_port=FrozenGrbl(), status_hz=100, stall_reports=10, timeout_s=2.0)
    t.open()
    t.stream(["G1X100F1200"])
    with pytest.raises(TableStall) as err:
        t.wait_idle(timeout_s=30)
    assert "12.500" in str(err.value)


def test_a_device_that_never_ends_a_line_cannot_fill_memory():
    from labctl.drivers.serial_link import SerialLink

    class Noise(FrozenGrbl):
        def __init__(self):
            self.out = bytearray(b"\xff" * 100_000)

    link = SerialLink(port=Noise(), timeout_s=0.1)
    link.open()
    assert link.readline(0.05) is None
    assert link.buffered_bytes <= link.max_buffer and link.bytes_discarded >= 100_000 - link.max_buffer
