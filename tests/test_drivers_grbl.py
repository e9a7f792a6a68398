"""The GRBL table driver against the GRBL emulator on real pseudo-terminals."""

from __future__ import annotations

import math
import time

import pytest
import serial
from fakes import fake_grbl, silent_port

from labctl.drivers.grbl import GrblAlarm, GrblError, GrblTable, clean_line
from labctl.drivers.programs import load_gcode, program
from labctl.drivers.serial_link import DeviceTimeout, LinkError
from labctl.errors import DeviceError, UserInputError


def short_moves(n: int, step: float = 0.4) -> list[str]:
    """n short feed moves along a gentle curve (byte-rate bound at 9600 bps)."""
    lines = ["G21", "G90", "G1 F3000"]
    for i in range(n):
        a = i * 0.01
        lines.append(f"G1 X{100 + 40 * math.sin(a) + i * step:.3f} Y{100 + 20 * (1 - math.cos(a)):.3f}")
    return lines


def test_connects_without_reset_and_reads_identity():
    with fake_grbl(homing=True) as dev:
        with GrblTable(dev.path, 115200, reset_on_open=False, timeout_s=2.0, auto_unlock=False) as table:
            assert table.connected_by in ("status", "banner")
            assert table.info["version"].startswith("1.1h") and table.rx_limit == 127
            st = table.status()
            assert st.state == "Alarm"  # power-up homing lock, but this session did not see the boot
            with pytest.raises(GrblAlarm):
                table.ensure_ready()  # never unlocked silently
            assert table.ensure_ready(unlock=True).state == "Idle"
            settings = table.settings()
            assert settings[130] == 600.0 and settings[22] == 1


def test_move_returns_when_motion_has_finished():
    with fake_grbl(homing=False) as dev:
        with GrblTable(dev.path, 115200, reset_on_open=False, status_hz=10) as table:
            st = table.move_to(40.0, 30.0, feed_mm_min=3000)
            assert st.state == "Idle" and st.position == pytest.approx((40.0, 30.0, 0.0))
            with dev.lock:
                assert not dev.emulator.moving
                assert dev.emulator.machine_position()[:2] == pytest.approx((40.0, 30.0))


def test_stream_500_lines_counts_characters_and_never_overflows():
    lines = short_moves(500)
    with fake_grbl(homing=False, strict=False) as dev:
        with GrblTable(dev.path, 115200, reset_on_open=False, status_hz=10) as table:
            sent = table.stream(lines)
            st = table.wait_idle(timeout_s=60)
            assert sent == len(lines) and st.state == "Idle"
            assert table.max_in_flight <= 127
            assert table.status_reports >= 5  # status interleaved with the stream
            with dev.lock:
                assert dev.emulator.rx_overflows == 0
                assert dev.emulator.rx_high_water <= 127
                assert dev.emulator.lines_executed >= len(lines)
            last = clean_line(lines[-1])
            x = float(last.split("X")[1].split("Y")[0])
            assert st.position[0] == pytest.approx(x, abs=1e-3)


def test_stream_at_9600_bps_takes_the_byte_time():
    lines = short_moves(60)
    n_bytes = sum(len(clean_line(x)) + 1 for x in lines)
    with fake_grbl(baud=9600, homing=False) as dev:
        with GrblTable(dev.path, 9600, reset_on_open=False, status_hz=5) as table:
            t0 = time.monotonic()
            table.stream(lines)
            elapsed = time.monotonic() - t0
            bound = n_bytes * 10 / 9600
            assert elapsed >= bound * 0.9  # cannot beat the wire
            assert elapsed < bound * 3 + 1.0
            with dev.lock:
                assert dev.emulator.rx_overflows == 0


def test_errors_and_alarms_are_typed():
    with fake_grbl(homing=True) as dev:
        with GrblTable(dev.path, 115200, reset_on_open=False) as table:
            table.unlock()
            with pytest.raises(GrblError) as err:
                table.stream(["G21", "G1 X10"])  # no feed rate
            assert err.value.code == 22 and err.value.index == 1
            assert isinstance(err.value, DeviceError)
            with pytest.raises(GrblAlarm) as alarm:
                table.move_to(900.0, 10.0, 3000)
            assert alarm.value.code == 2
            with pytest.raises(GrblAlarm):
                table.ensure_ready()  # never cleared silently
            table.reset()
            with pytest.raises(GrblAlarm):
                table.ensure_ready()  # still not cleared silently after the reset
            assert table.ensure_ready(unlock=True).state == "Idle"
            assert table.move_to(10.0, 10.0, 3000).position[0] == pytest.approx(10.0)


def test_feed_hold_resume_and_stop():
    with fake_grbl(homing=False) as dev:
        with GrblTable(dev.path, 115200, reset_on_open=False, status_hz=20) as table:
            table.stream(["G1 X200 F3000"])
            time.sleep(0.3)
            table.feed_hold()
            deadline = time.monotonic() + 3
            while table.status().state != "Hold:0" and time.monotonic() < deadline:
                pass
            held = table.status()
            assert held.state == "Hold:0"
            time.sleep(0.2)
            assert table.status().position == held.position
            table.resume()
            deadline = time.monotonic() + 3  # a loaded machine may deliver one report from before '~'
            while table.status().state != "Run" and time.monotonic() < deadline:
                pass
            assert table.status().state == "Run"
            table.stop()  # hold, then reset: position kept, no alarm
            st = table.status()
            assert st.state == "Idle" and 0 < st.position[0] < 200


def test_home_command():
    with fake_grbl(homing=True, settings={24: 600.0, 25: 3000.0}) as dev:
        with GrblTable(dev.path, 115200, reset_on_open=False) as table:
            table.ensure_ready(unlock=True)
            table.move_to(30, 20, 3000)
            table.home()
            assert table.status().position == pytest.approx((0.0, 0.0, 0.0))
    with fake_grbl(homing=False) as dev, GrblTable(dev.path, 115200, reset_on_open=False) as table:
        with pytest.raises(GrblError) as err:
            table.home()
        assert err.value.code == 5


def test_silent_port_times_out_cleanly():
    with silent_port() as dev:
        table = GrblTable(dev.path, 115200, reset_on_open=False, timeout_s=0.5, boot_s=0.5)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout) as err:
            table.open()
        assert time.monotonic() - t0 < 3.0
        assert "115200 bps" in str(err.value) and "baud" in str(err.value)  # says what to check


def test_garbled_replies_suggest_another_baud_rate():
    from fakes import Wire

    with fake_grbl(homing=False, wire=Wire(garbage=True, seed=3)) as dev:
        table = GrblTable(dev.path, 9600, reset_on_open=False, timeout_s=0.5, boot_s=0.5)
        with pytest.raises(DeviceTimeout) as err:
            table.open()
        assert "another rate than 9600 bps" in str(err.value)


def test_missing_port_is_a_link_error():
    with pytest.raises(LinkError):
        GrblTable("/dev/does-not-exist", 9600).open()


def test_spy_url_works(tmp_path):
    with fake_grbl(homing=False) as dev:
        url = f"spy://{dev.path}?file={tmp_path / 'spy.txt'}"
        with GrblTable(url, 115200, reset_on_open=False) as table:
            assert table.status().state == "Idle"
        assert "Idle" in (tmp_path / "spy.txt").read_text()


def test_socket_url_without_banner_recovers_by_query():
    """ser2net-style: a TCP bridge to the device; opening it resets nothing."""
    import socket
    import threading

    with fake_grbl(homing=False) as dev:
        srv = socket.socket()
        srv.bind(("127.0.0.1", 0))
        srv.listen(1)
        port = srv.getsockname()[1]
        ser = serial.Serial(dev.path, 115200, timeout=0.01)
        time.sleep(0.1)
        ser.reset_input_buffer()  # the power-up banner is long gone
        stop = threading.Event()

        def bridge():
            conn, _ = srv.accept()
            conn.settimeout(0.01)
            while not stop.is_set():
                try:
                    data = conn.recv(4096)
                    if data:
                        ser.write(data)
                except TimeoutError:
                    pass
                except OSError:
                    break
                out = ser.read(4096)
                if out:
                    conn.sendall(out)
            conn.close()

        th = threading.Thread(target=bridge, daemon=True)
        th.start()
        try:
            with GrblTable(f"socket://127.0.0.1:{port}", 115200, reset_on_open=False, timeout_s=2) as table:
                assert table.connected_by == "status"
                assert table.move_to(5, 5, 3000).position[:2] == pytest.approx((5.0, 5.0))
        finally:
            stop.set()
            th.join(2)
            srv.close()
            ser.close()


@pytest.mark.parametrize("name", ["line", "arc", "circle", "zigzag"])
def test_trajectory_programs_run_on_the_emulator(name):
    from labctl.sim.clock import VirtualClock
    from labctl.sim.emulators.grbl import GrblEmulator
    from labctl.sim.emulators.link import EmulatorPort

    clk = VirtualClock()
    emu = GrblEmulator(clk, strict=True)
    table = GrblTable(serial_port=EmulatorPort(emu, clk, baud=9600), clock=clk)
    table.open()
    lines = program(name, 40.0, start=(150.0, 200.0), length_mm=200.0)
    table.stream(lines)
    t_start = clk.t
    table.wait_idle(timeout_s=120)
    end = emu.machine_position()
    if name in ("circle",):
        assert end[:2] == pytest.approx((150.0, 200.0), abs=1e-3)
    elif name == "line":
        assert end[:2] == pytest.approx((350.0, 200.0), abs=1e-3)
    assert clk.t > t_start
    assert emu.rx_overflows == 0


def test_program_and_gcode_file_errors(tmp_path):
    with pytest.raises(UserInputError):
        program("spiral", 8)
    with pytest.raises(UserInputError):
        program("line", 8, start=(500, 200), length_mm=300)  # off the 600 mm travel
    with pytest.raises(UserInputError):
        load_gcode(tmp_path / "missing.nc")
    f = tmp_path / "p.nc"
    f.write_text("%\n(header)\nG21 ; mm\n\nG1 X1 F100 (go)\n%\n")
    assert load_gcode(f) == ["G21", "G1 X1 F100 (go)"]
    assert clean_line("G1 X1 F100 (go)") == "G1X1F100"
