"""``labctl bench stream``: ``table stream`` of 300 short moves at 9600 bps against the byte-rate bound.

The driver streams the program by character counting, polling status at 5 Hz, to two controllers
on a pseudo-terminal paced at 9600 bps (10 bits per byte, both ways):

* ``emulator``: labctl's GRBL emulator (also on a virtual clock with a modelled wire: the sender's
  logic alone, without thread scheduling);
* ``firmware``: the real GRBL 1.1h (grbl-sim from ``../shared/grbl-sim``) behind the same paced
  relay, its axes set so that its wall-clock motion matches the emulator's table although the
  simulator runs slower than real time. Left out (with the reason) where it cannot be built.

Per run: the stream time (first byte to the last line's ``ok``), the byte-rate bound of the
bytes actually sent (lines and ``?`` polls), their ratio, and the receive-buffer fill as the
sender counts it (unacknowledged bytes, time-weighted while lines remain to be sent). GRBL
acknowledges a motion line only once the planner has taken it: when the planner is full the
firmware, not the wire, sets the pace. So the status reports carry ``Bf:`` (``$10=3``) and the
fill is also given over the time the planner had room. Medians over the repeats.
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import tty
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

from ..drivers.grbl_protocol import RX_BUFFER_SIZE
from ..drivers.serial_link import DeviceError
from ..runtime.transport import wire_time_s
from ._timing import row
from .devices import short_moves

BAUD = 9600
LINES = 300
FULL = 0.8  # "kept full": at least this share of GRBL's receive buffer unacknowledged
FEED_MM_MIN, ACCEL_MM_S2 = 6000.0, 200.0  # the table both controllers emulate (wall-clock motion)
STEP_RATE_HZ = 16000  # grbl-sim's step rate at full feed: steps/mm chosen for it, whatever the time factor
BUSY_LOAD = 3.0  # load average per core above which grbl-sim runs at the slower factor (its README)
TIME_FACTORS = (0.25, 0.1)  # grbl-sim's speed against real time: its default, and for a busy machine
SHARED = (Path(__file__).resolve().parents[2].parent / "shared" / "grbl-sim", Path("/work/shared/grbl-sim"))


def fill_stats(fill: list[tuple[float, int]], reports: list[tuple[float, int | None, int | None]],
               capacity: int = RX_BUFFER_SIZE) -> dict:
    """Receive-buffer fill from a program's ``(t, unacknowledged bytes)`` history while lines remained
    to be sent (first to last send), and the status reports' ``(t, planner_free, rx_free)`` in that
    window: time-weighted mean bytes, share of the time at least ``FULL`` × ``capacity`` bytes, the
    same share over the time the last report showed planner room, and the planner-full share."""
    sends = [i for i in range(1, len(fill)) if fill[i][1] > fill[i - 1][1]]
    if not sends:
        return {}
    t_lo, t_hi = fill[0][0], fill[sends[-1]][0]
    full = FULL * capacity
    span = t_hi - t_lo
    total = at_full = room = room_full = 0.0
    k = 0
    planner_free = None
    for (ta, used), (tb, _) in zip(fill, fill[1:]):
        if ta >= t_hi:
            break
        while k < len(reports) and reports[k][0] <= ta:
            planner_free = reports[k][1]
            k += 1
        dt = min(tb, t_hi) - ta
        total += used * dt
        at_full += dt if used >= full else 0.0
        if planner_free is None or planner_free > 0:
            room += dt
            room_full += dt if used >= full else 0.0
    window = [r for r in reports if t_lo <= r[0] <= t_hi]
    pf = [r[1] for r in window if r[1] is not None]
    rx = [capacity - r[2] for r in window if r[2] is not None]
    return {"mean_bytes": total / span if span > 0 else 0.0, "max_bytes": max(u for _, u in fill),
            "full_share": at_full / span if span > 0 else 0.0,
            "full_share_planner_room": room_full / room if room > 0 else None,
            "planner_full_share": sum(1 for p in pf if p == 0) / len(pf) if pf else None,
            "firmware_rx_median_bytes": statistics.median(rx) if rx else None, "reports": len(window)}


def stream_once(table, lines: list[str], baud: int = BAUD) -> dict:
    """Stream ``lines`` on an open, idle ``table`` as ``GrblTable.stream`` does, recording the fill and
    the status reports; the stream time, the bytes on the wire, the bound and the fill statistics."""
    table.record_fill = True
    reports: list[tuple[float, int | None, int | None]] = []
    seen = table.status_reports
    b0 = table.link.bytes_out
    t0 = table.clock.now()
    prog = table.start_program(lines)
    while prog.pump(0.01):
        if table.status_reports != seen:
            seen = table.status_reports
            st = table.last_status
            reports.append((table.last_status_t, st.planner_free, st.rx_free))
    elapsed = table.clock.now() - t0
    table.record_fill = False
    nbytes = table.link.bytes_out - b0
    bound = wire_time_s(nbytes, baud)
    return {"stream_s": elapsed, "bytes": nbytes, "bound_s": bound, "to_bound": elapsed / bound,
            **fill_stats(prog.fill or [], reports)}


class _Relay:
    """The firmware's pty as a device behind :func:`run_on_pty`'s paced wire (bytes in, bytes out)."""

    def __init__(self, path: str):
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self.fd)

    def receive(self, data: bytes, t: float | None = None) -> None:
        """Bytes off the paced wire, into the firmware."""
        os.write(self.fd, data)

    def read_output(self) -> bytes:
        """What the firmware has written since the last call."""
        try:
            return os.read(self.fd, 4096)
        except (BlockingIOError, OSError):
            return b""

    def close(self) -> None:
        """Close the firmware's pty."""
        os.close(self.fd)


def _grbl_sim() -> Path | str:
    if not (shutil.which("gcc") and shutil.which("make")):
        return "gcc and make are needed to build grbl-sim"
    for p in SHARED:
        if (p / "build.sh").is_file():
            return p
    return f"grbl-sim not found in {', '.join(map(str, SHARED))}"


@contextmanager
def _firmware(time_factor: float):
    """The real firmware on its own pty, booted: yields a :class:`_Relay` to it."""
    here = _grbl_sim()
    assert isinstance(here, Path), here
    with tempfile.TemporaryDirectory(prefix="grbl-sim-") as out:
        done = subprocess.run(["bash", str(here / "build.sh"), out], capture_output=True, text=True, timeout=300)
        if done.returncode != 0:
            raise RuntimeError(f"grbl-sim build failed: {done.stderr[-500:]}")
        exe = Path(done.stdout.strip().splitlines()[-1])
        proc = subprocess.Popen([sys.executable, str(here / "serve_pty.py"), "--exe", str(exe),
                                 "--time-factor", str(time_factor)], stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, text=True, cwd=exe.parent)
        relay = None
        try:
            assert proc.stdout is not None  # piped above
            relay = _Relay(proc.stdout.readline().strip())
            boot, deadline = b"", time.monotonic() + 30.0
            while b"Grbl 1.1" not in boot and time.monotonic() < deadline:  # first boot: error:7, settings
                boot += relay.read_output()
                time.sleep(0.01)
            if b"Grbl 1.1" not in boot:
                raise RuntimeError("grbl-sim printed no banner within 30 s")
            yield relay
        finally:
            if relay is not None:
                relay.close()
            proc.terminate()
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()


def _on_emulator(lines: list[str], repeats: int) -> list[dict]:
    from ..drivers.grbl import GrblTable
    from ..sim.emulators.grbl import GrblEmulator
    from ..sim.emulators.pty import run_on_pty

    runs = []
    for _ in range(repeats):
        emu = GrblEmulator(time.monotonic, homing=False, max_feed_mm_min=FEED_MM_MIN, accel_mm_s2=ACCEL_MM_S2,
                           travel_mm=(600.0, 400.0))
        with run_on_pty(emu, BAUD) as dev, GrblTable(dev.path, BAUD, reset_on_open=False, status_hz=5.0) as table:
            table.command("$10=3")
            table.move_to(100.0, 100.0, FEED_MM_MIN)  # to the program's start, outside the timing
            r = stream_once(table, lines)
            table.wait_idle(timeout_s=120)
        runs.append(r | {"rx_overflows": emu.rx_overflows, "firmware_rx_high_water": emu.rx_high_water})
    return runs


def _on_virtual(lines: list[str]) -> list[dict]:
    """The same driver and emulator on a virtual clock and a modelled 9600-bps wire: no threads, no
    scheduling, so what is left is the sender's own logic."""
    from ..drivers.grbl import GrblTable
    from ..sim.clock import VirtualClock
    from ..sim.emulators.grbl import GrblEmulator
    from ..sim.emulators.link import EmulatorPort

    clk = VirtualClock()
    emu = GrblEmulator(clk, homing=False, strict=True, max_feed_mm_min=FEED_MM_MIN, accel_mm_s2=ACCEL_MM_S2)
    table = GrblTable(serial_port=EmulatorPort(emu, clk, baud=BAUD), clock=clk, status_hz=5.0)
    table.open()
    table.command("$10=3")
    table.move_to(100.0, 100.0, FEED_MM_MIN)
    return [stream_once(table, lines) | {"rx_overflows": emu.rx_overflows}]


def _on_firmware(lines: list[str], repeats: int, time_factor: float) -> tuple[list[dict], list[str]]:
    """Each repeat twice: on the 9600-bps wire, then on an unpaced one (the firmware's own pace: how
    fast it takes these lines when the wire is no limit). Returns (runs, reasons of failed repeats)."""
    from ..drivers.grbl import GrblTable
    from ..sim.emulators.pty import run_on_pty

    k = time_factor
    steps = round(STEP_RATE_HZ / (FEED_MM_MIN / 60.0 / k))
    settings = {100: steps, 101: steps, 110: FEED_MM_MIN / k, 111: FEED_MM_MIN / k,
                120: ACCEL_MM_S2 / k / k, 121: ACCEL_MM_S2 / k / k, 10: 3}

    def once(relay, baud: int | None, setup: bool) -> dict:
        with run_on_pty(relay, baud) as dev, GrblTable(dev.path, BAUD, reset_on_open=False, status_hz=5.0,
                                                       timeout_s=15.0) as table:
            if setup:
                for key, value in settings.items():
                    table.command(f"${key}={value:g}")
            table.ensure_ready(unlock=True)
            table.command("G92X100Y100")  # the program's start, without moving (fewer chances to stall)
            try:
                r = stream_once(table, lines)
                table.wait_idle(timeout_s=300)
            except DeviceError:
                table.stop()  # a starved simulator stalls (its README): stop it, count the run as failed
                raise
        return r

    runs, failed = [], []
    with _firmware(time_factor) as relay:
        for i in range(repeats):
            try:
                paced = once(relay, BAUD, setup=i == 0)
                own = once(relay, None, setup=False)
            except DeviceError as exc:
                failed.append(str(exc))
                continue
            pace_bound = max(paced["bound_s"], own["stream_s"])
            runs.append(paced | {"unpaced_s": own["stream_s"],
                                 "unpaced_planner_full_share": own.get("planner_full_share"),
                                 "pace_bound_s": pace_bound, "to_pace_bound": paced["stream_s"] / pace_bound})
    if not runs:
        raise RuntimeError(f"every firmware run failed: {failed}")
    return runs, failed


def _median(runs: list[dict]) -> dict:
    keys = [k for k in runs[0] if all(isinstance(r.get(k), (int, float)) for r in runs)]
    return {k: statistics.median(r[k] for r in runs) for k in keys}


def run(quick: bool = False) -> dict:
    """Stream 300 short moves at 9600 bps to the emulator and the real firmware; rows plus each run's data."""
    repeats = 1 if quick else 3
    lines = short_moves(LINES)
    out: dict = {"lines": LINES, "baud": BAUD, "repeats": repeats}
    rows = []
    targets: dict[str, Callable[[], tuple[list[dict], list[str]]]] = {
               "emulator, virtual clock": lambda: (_on_virtual(lines), []),
               "emulator": lambda: (_on_emulator(lines, repeats), [])}
    where = _grbl_sim()
    if isinstance(where, Path):
        k = TIME_FACTORS[1] if os.getloadavg()[0] / (os.cpu_count() or 1) > BUSY_LOAD else TIME_FACTORS[0]
        out["load_average"] = os.getloadavg()[0]
        targets[f"firmware (grbl-sim x{k:g})"] = lambda: _on_firmware(lines, repeats, k)
    else:
        out["firmware_skipped"] = where
    for name, fn in targets.items():
        runs, failed = fn()
        m = _median(runs)
        out[name] = {"median": m, "runs": runs, "failed_runs": failed}
        rows.append(row(f"stream {LINES} short moves @{BAUD} bps, {name}", m["stream_s"], baseline="byte-rate bound",
                        baseline_s=m["bound_s"], to_bound=round(m["to_bound"], 3),
                        fill_mean_bytes=round(m.get("mean_bytes", 0.0), 1), fill_max_bytes=m.get("max_bytes"),
                        full_share=round(m.get("full_share", 0.0), 3),
                        full_share_planner_room=_r(m.get("full_share_planner_room")),
                        planner_full_share=_r(m.get("planner_full_share")),
                        firmware_rx_bytes=m.get("firmware_rx_median_bytes"),
                        unpaced_s=_r(m.get("unpaced_s")), to_pace_bound=_r(m.get("to_pace_bound")),
                        runs=len(runs), failed_runs=len(failed)))
    out["rows"] = rows
    return out


def _r(v):
    return None if v is None else round(v, 3)
