"""The GRBL streamer keeps the receive buffer full by character counting.

Never more than 127 bytes (RX_BUFFER_SIZE - 1) unacknowledged, and at least 100 on a program of
short lines while the controller keeps accepting them: against labctl's emulator on a virtual
clock (deterministic, the wire paced at 9600 bps), and against the real GRBL 1.1h firmware.
Speeds are the benchmark's business (``labctl bench stream``), not asserted here.
"""

from __future__ import annotations

import pytest
from test_grbl_firmware import firmware_exe, fw, table  # noqa: F401  (the real firmware's fixtures)

from labctl.bench.devices import short_moves
from labctl.bench.stream import FULL, fill_stats
from labctl.drivers.grbl import GrblTable
from labctl.drivers.grbl_protocol import RX_BUFFER_SIZE
from labctl.sim.clock import VirtualClock
from labctl.sim.emulators.grbl import GrblEmulator
from labctl.sim.emulators.link import EmulatorPort

LIMIT = RX_BUFFER_SIZE - 1


def _stream_virtual(max_feed_mm_min: float, n: int = 300):
    clk = VirtualClock()
    emu = GrblEmulator(clk, homing=False, strict=True, max_feed_mm_min=max_feed_mm_min)
    t = GrblTable(serial_port=EmulatorPort(emu, clk, baud=9600), clock=clk, status_hz=5.0)
    t.open()
    t.command("$10=3")
    t.move_to(100.0, 100.0, max_feed_mm_min)
    t.record_fill = True
    reports = []
    prog = t.start_program(short_moves(n))
    while prog.pump(0.01):
        st = t.last_status
        if not reports or reports[-1][0] != t.last_status_t:
            reports.append((t.last_status_t, st.planner_free, st.rx_free))
    return emu, prog, reports


def test_short_lines_fill_the_buffer_and_never_overflow_it():
    emu, prog, reports = _stream_virtual(6000.0)
    used = [u for _, u in prog.fill]
    assert prog.done and prog.sent == 300
    assert max(used) <= LIMIT
    assert max(used) >= 100
    assert emu.rx_overflows == 0 and emu.rx_high_water <= LIMIT
    s = fill_stats(prog.fill, reports)
    # the emulator's planner keeps room on this program: the wire sets the pace, and the buffer stays full
    assert s["planner_full_share"] == 0.0
    assert s["full_share"] >= FULL
    assert s["mean_bytes"] >= FULL * RX_BUFFER_SIZE


def test_a_full_planner_holds_the_replies_and_the_count_still_stays_within_the_buffer():
    # a slow table: the planner fills, GRBL stops taking lines, its receive buffer fills up to the count
    emu, prog, reports = _stream_virtual(120.0, n=60)
    s = fill_stats(prog.fill, reports)
    assert max(u for _, u in prog.fill) <= LIMIT
    assert emu.rx_overflows == 0
    assert s["planner_full_share"] > 0.5
    assert s["firmware_rx_median_bytes"] >= 80  # the bytes wait in GRBL itself, not on the wire


def test_fill_stats_weights_time_while_lines_remain_to_be_sent():
    # 0..1 s at 110 bytes, 1..3 s at 50, last send at 3 s, then replies only (outside the window)
    fill = [(0.0, 20), (0.1, 110), (1.1, 50), (2.0, 60), (2.1, 50), (3.1, 70), (4.0, 10), (5.0, 0)]
    reports = [(0.0, 5, 100), (1.5, 0, 10), (2.5, 3, 60)]
    s = fill_stats(fill, reports, capacity=128)
    assert s["mean_bytes"] == pytest.approx((20 * 0.1 + 110 * 1.0 + 50 * 0.9 + 60 * 0.1 + 50 * 1.0) / 3.1)
    assert s["full_share"] == pytest.approx(1.0 / 3.1)
    # each step counts as planner room by the latest report at its start: the steps starting at 0.0,
    # 0.1 and 1.1 s (2.0 s, the one at 0.1 s full), not those at 2.0 and 2.1 s (after the 1.5-s "full")
    assert s["full_share_planner_room"] == pytest.approx(1.0 / 2.0)
    assert s["max_bytes"] == 110
    assert s["planner_full_share"] == pytest.approx(1 / 3)
    assert s["firmware_rx_median_bytes"] == 68  # 128 - 60
    assert s["reports"] == 3


def test_the_real_firmware_takes_a_full_buffer_of_short_lines(fw):  # noqa: F811
    fw.fresh()
    with table(fw) as t:
        t.command("$10=3")
        t.command("G92X100Y100")
        t.record_fill = True
        prog = t.start_program(short_moves(300))
        while prog.pump(0.01):
            pass
        t.wait_idle(timeout_s=120)
    used = [u for _, u in prog.fill]
    assert prog.done and prog.sent == 300
    assert max(used) <= LIMIT
    assert max(used) >= 100
