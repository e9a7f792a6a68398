"""``labctl bench devices``: GRBL streaming at 9600 bps against the byte-rate bound, and the parsers.

The acceptance case: the driver streams a 500-line program of short moves to the GRBL emulator
on a real pseudo-terminal paced at 9600 bps (10 bits per byte), polling status at 5 Hz. The
bound is the program's bytes × 10 / 9600 s; a character-counting streamer should come close
to it (the ratio bound/measured approaches 1). The emulator counts receive-buffer overflows.
"""

from __future__ import annotations

import math
import time

from ..timebase import wire_time_s
from ._timing import median_time, row


def short_moves(n: int, step_mm: float = 0.4) -> list[str]:
    """An n-line program of short G1 moves from (100, 100) along a gentle curve: byte-rate bound at
    9600 bps (the motion could go faster)."""
    lines = ["G21", "G90", "G1 F6000"]
    for i in range(n - 3):
        a = i * 0.01
        lines.append(f"G1 X{100 + 40 * math.sin(a) + i * step_mm:.3f} Y{100 + 20 * (1 - math.cos(a)):.3f}")
    return lines


def _stream_on_pty(lines: list[str], baud: int) -> dict:
    from ..drivers.grbl import GrblTable, clean_line
    from ..sim.emulators.grbl import GrblEmulator
    from ..sim.emulators.pty import run_on_pty

    emu = GrblEmulator(time.monotonic, homing=False, max_feed_mm_min=6000.0, accel_mm_s2=200.0,
                       travel_mm=(600.0, 400.0))
    dev = run_on_pty(emu, baud)
    try:
        with GrblTable(dev.path, baud, reset_on_open=False, status_hz=5.0, timeout_s=5.0) as table:
            table.move_to(100.0, 100.0, 6000.0)  # to the program's start, outside the timing
            t0 = time.monotonic()
            table.stream(lines)
            elapsed = time.monotonic() - t0
            table.wait_idle(timeout_s=120)
            reports = table.status_reports
            in_flight = table.max_in_flight
    finally:
        dev.stop()
    n_bytes = sum(len(clean_line(x)) + 1 for x in lines)
    return {"elapsed_s": elapsed, "bytes": n_bytes, "bound_s": wire_time_s(n_bytes, baud), "status_reports": reports,
            "rx_overflows": emu.rx_overflows, "rx_high_water": emu.rx_high_water, "max_in_flight": in_flight}


def _stream_virtual(lines: list[str], baud: int) -> dict:
    from ..drivers.grbl import GrblTable, clean_line
    from ..sim.clock import VirtualClock
    from ..sim.emulators.grbl import GrblEmulator
    from ..sim.emulators.link import EmulatorPort

    clk = VirtualClock()
    emu = GrblEmulator(clk, homing=False, strict=True)
    table = GrblTable(serial_port=EmulatorPort(emu, clk, baud=baud), clock=clk, status_hz=5.0)
    table.open()
    table.move_to(100.0, 100.0, 6000.0)
    w0 = time.perf_counter()
    t0 = clk.t
    table.stream(lines)
    n_bytes = sum(len(clean_line(x)) + 1 for x in lines)
    return {"virtual_s": clk.t - t0, "wall_s": time.perf_counter() - w0, "bound_s": wire_time_s(n_bytes, baud),
            "rx_overflows": emu.rx_overflows}


def run(quick: bool = False) -> dict:
    """Time GRBL streaming at 9600 bps (pty and virtual) and the GRBL/robot reply parsers; rows plus raw data."""
    from ..drivers.grbl_protocol import parse_line
    from ..drivers.robot_protocol import parse_reply

    n = 150 if quick else 500
    lines = short_moves(n)
    pty = _stream_on_pty(lines, 9600)
    virt = _stream_virtual(lines, 9600)
    report = "<Run|MPos:123.456,78.901,0.000|FS:3000,0|WCO:0.000,0.000,0.000>"
    rows = [
        row(f"stream {n} lines @9600 bps, pty, real time", pty["elapsed_s"], baseline="byte-rate bound",
            baseline_s=pty["bound_s"], status_reports=pty["status_reports"], rx_overflows=pty["rx_overflows"]),
        row(f"stream {n} lines @9600 bps, virtual clock (virtual s)", virt["virtual_s"], baseline="byte-rate bound",
            baseline_s=virt["bound_s"], wall_s=virt["wall_s"]),
        row("parse GRBL status report", median_time(lambda: parse_line(report), repeat=2000),
            baseline="str.split('|')", baseline_s=median_time(lambda: report[1:-1].split("|"), repeat=2000)),
        row("parse robot reply", median_time(lambda: parse_reply("$12 ok 1.0 2.0 3.0*3A"), repeat=2000)),
    ]
    return {"rows": rows, "grbl_9600_pty": pty, "grbl_9600_virtual": virt, "lines": n}
