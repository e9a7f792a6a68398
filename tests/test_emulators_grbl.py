"""The GRBL 1.1 emulator against the protocol and against motion computed by hand."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from labctl.sim.clock import VirtualClock
from labctl.sim.emulators.grbl import GrblEmulator, RxOverflow

STATUS_RE = re.compile(r"^<(Idle|Run|Hold:[01]|Alarm|Home|Check)\|MPos:-?\d+\.\d{3},-?\d+\.\d{3},-?\d+\.\d{3}"
                       r"\|FS:\d+,\d+(\|WCO:[-\d.,]+)?(\|Ov:\d+,\d+,\d+)?>$")


def make(**kw):
    clk = VirtualClock()
    kw.setdefault("homing", False)
    g = GrblEmulator(clk, **kw)
    g.read_output()
    return clk, g


def send(g, text: str) -> list[str]:
    g.receive(text.encode())
    return [ln for ln in g.read_output().decode().split("\r\n") if ln]


def run_until_idle(clk, g, dt=0.01, limit=600.0):
    while (g.state != "Idle" or g.task is not None) and clk.t < limit:
        clk.sleep(dt)
        g.advance(clk.t)
    return clk.t


def test_banner_and_homing_lock():
    clk = VirtualClock()
    g = GrblEmulator(clk)
    out = g.read_output().decode()
    assert out == "\r\nGrbl 1.1h ['$' for help]\r\n[MSG:'$H'|'$X' to unlock]\r\n"
    assert send(g, "G0 X1\n") == ["error:9"]
    assert send(g, "$X\n") == ["[MSG:Caution: Unlocked]", "ok"]
    assert g.state == "Idle"


@pytest.mark.parametrize("line,code", [
    ("G1 X10\n", 22),       # no feed rate yet
    ("G5 X1\n", 20),        # unsupported G-code
    ("G0 G1 X1\n", 21),     # two motion commands
    ("G0 X1 X2\n", 25),     # repeated word
    ("X1.2.3\n", 1),        # '.3' parses, then '.' is not a letter -> expected command letter
    ("GX1\n", 2),           # bad number
    ("G4\n", 28),           # dwell without P
    ("$Q\n", 3),            # invalid $ statement
    ("F-5\n", 4),           # negative feed
    ("G0 X" + "1" * 90 + "\n", 11),  # line overflow
    ("$20=1\n", 10),        # soft limits need homing
    ("G2 X10 Y0\n", 22),    # arcs need a feed too
])
def test_error_codes(line, code):
    _, g = make(soft_limits=False)
    assert send(g, line) == [f"error:{code}"]


def test_one_reply_per_line_and_comments_ignored():
    _, g = make()
    out = send(g, "G21 (mm) G90 ; absolute\n\nG94\n")
    assert out == ["ok", "ok", "ok"]


def test_status_report_format_and_refresh_fields():
    _, g = make()
    reports = []
    for _ in range(12):
        reports += send(g, "?")
    assert all(STATUS_RE.match(r) for r in reports), reports
    assert "WCO:" in reports[0] and "Ov:" in reports[1] and "WCO:" in reports[10]


def test_realtime_status_is_out_of_band():
    _, g = make()
    g.receive(b"G1 X1")
    g.receive(b"?")  # '?' in the middle of a line is picked off, never enters the line
    g.receive(b"0 F600\n")
    out = g.read_output().decode().split("\r\n")
    assert out[0].startswith("<Idle|") and out[1] == "ok"
    assert g.planner.blocks[-1].target[0] == pytest.approx(10.0)


def test_rx_buffer_overflow_is_detected():
    _, g = make(soft_limits=False)
    g.receive(b"G4 P100\n")  # blocks the main loop for 100 s
    g.receive(b"G0X1\n" * 25)  # 125 bytes: fits in 127
    assert g.rx_overflows == 0 and len(g.rx) == 125
    g.receive(b"G0X2\n")
    assert g.rx_overflows == 3
    _, strict = make(strict=True)
    strict.receive(b"G4 P100\n")
    with pytest.raises(RxOverflow):
        strict.receive(b"G0X1\n" * 26)


def test_planner_holds_15_blocks_and_oks_wait_for_room():
    clk, g = make()
    lines = [f"G1 X{i + 1} F60\n" for i in range(20)]  # 1 mm at 1 mm/s: one second each
    g.receive("".join(lines[:10]).encode())
    g.receive("".join(lines[10:]).encode())
    acked = g.read_output().decode().count("ok")
    assert acked == 15 and len(g.planner.blocks) == 15
    clk.sleep(1.5)
    g.advance(clk.t)
    assert g.read_output().decode().count("ok") >= 1


def test_trapezoid_timing_matches_closed_form():
    clk, g = make(accel_mm_s2=200.0)
    send(g, "G1 X100 F3000\n")  # v = 50 mm/s, a = 200 mm/s²
    t0 = g.planner.history[-1].t0 if g.planner.history else 0.0
    t_acc = 50 / 200
    # during the acceleration phase x = a t² / 2
    assert g.position_at(t0 + 0.1)[0] == pytest.approx(0.5 * 200 * 0.01, abs=1e-9)
    end = run_until_idle(clk, g, dt=0.001)
    total = 100 / 50 + t_acc  # cruise distance/speed + one accel time
    assert end - t0 == pytest.approx(total, abs=2e-3)
    assert g.machine_position()[0] == pytest.approx(100.0)


def test_collinear_segments_do_not_stop_at_junctions():
    clk, g = make(accel_mm_s2=200.0)
    send(g, "G1 X10 F3000\nG1 X20\nG1 X30\n")
    clk.sleep(0.3)
    g.advance(clk.t)
    assert g.planner.speed == pytest.approx(50.0)  # cruising through the first junction
    # a 90° corner slows down (junction deviation), but not to zero
    clk2, g2 = make(accel_mm_s2=200.0)
    send(g2, "G1 X20 F3000\nG1 Y20\n")
    speeds = []
    for _ in range(200):
        clk2.sleep(0.005)
        g2.advance(clk2.t)
        speeds.append(g2.planner.speed)
    assert 0 < min(s for s in speeds if s > 0) < 50


def test_arc_chords_stay_on_the_circle():
    clk, g = make(soft_limits=False)
    send(g, "G0 X100 Y100\n")
    run_until_idle(clk, g)
    send(g, "G2 X100 Y100 I20 J0 F1200\n")  # full circle, centre (120, 100)
    t_start = clk.t
    end = run_until_idle(clk, g, dt=0.01)
    for t in np.linspace(t_start, end, 50):
        p = g.position_at(t)
        assert math.hypot(p[0] - 120, p[1] - 100) == pytest.approx(20.0, abs=0.01)
    assert end - t_start == pytest.approx(2 * math.pi * 20 / 20, rel=0.05)


def test_feed_hold_stops_within_braking_distance_and_resume_finishes():
    clk, g = make(accel_mm_s2=200.0)
    send(g, "G1 X200 F3000\n")
    clk.sleep(1.0)
    g.advance(clk.t)
    x_hold = g.machine_position()[0]
    g.receive(b"!")
    assert g.state_word == "Hold:1"
    clk.sleep(1.0)
    g.advance(clk.t)
    assert g.state_word == "Hold:0"
    assert g.machine_position()[0] == pytest.approx(x_hold + 50 ** 2 / (2 * 200), abs=1e-6)
    g.receive(b"~")
    run_until_idle(clk, g)
    assert g.machine_position()[0] == pytest.approx(200.0)


def test_soft_limit_alarm_locks_until_reset():
    clk, g = make(homing=True)
    send(g, "$X\n")
    out = send(g, "G0 X700\n")
    assert out == ["ALARM:2", "[MSG:Reset to continue]"]
    assert send(g, "G0 X1\n") == []  # ignored while locked
    assert send(g, "?") == []  # the real 1.1h serves no status report in the critical lock either
    out = send(g, "\x18")
    assert out == ["Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]


def test_reset_during_motion_raises_alarm_3():
    clk, g = make()
    send(g, "G1 X100 F3000\n")
    clk.sleep(0.5)
    out = send(g, "\x18")
    assert out[0] == "ALARM:3" and g.state == "Alarm"


def test_homing_and_settings():
    clk, g = make(homing=True)
    send(g, "$X\nG0 X50 Y50\n")
    run_until_idle(clk, g)
    g.receive(b"$H\n")
    assert g.state == "Home"
    run_until_idle(clk, g)
    assert "ok" in g.read_output().decode()
    assert np.allclose(g.machine_position(), 0.0)
    settings = send(g, "$$\n")
    assert settings[-1] == "ok" and "$130=600.000" in settings and "$22=1" in settings
    assert send(g, "$110=3000\n") == ["ok"]
    assert g.planner.max_rate[0] == pytest.approx(50.0)


def test_inches_relative_and_dwell():
    clk, g = make()
    send(g, "G20 G91 G1 X1 F60\n")  # 1 inch at 60 in/min
    run_until_idle(clk, g)
    assert g.machine_position()[0] == pytest.approx(25.4)
    t0 = clk.t
    g.receive(b"G4 P0.5\n")
    assert "ok" not in g.read_output().decode()
    run_until_idle(clk, g, dt=0.01)
    clk.sleep(0.6)
    assert "ok" in g.read_output().decode()
    assert clk.t - t0 >= 0.5


def test_check_mode_parses_without_moving():
    clk, g = make()
    assert send(g, "$C\n") == ["[MSG:Enabled]", "ok"]
    assert send(g, "G1 X10 F100\n") == ["ok"]
    assert not g.planner.blocks
