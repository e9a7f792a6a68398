"""``labctl table`` and the GRBL driver against the real GRBL 1.1h firmware (grbl-sim on a pty).

The oracle is the unchanged firmware from ``../shared/grbl-sim``, compiled once per session into
a temporary directory and served on a pty by its ``serve_pty.py`` (at a quarter of real time), so
every motion here is short and fast. The driver runs in-process on the pty; the CLI runs as a
subprocess, as a user runs it. Issue 12 (findings 1–7, 9, 11) and issue 13 (stop on every exit).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import serial
from fakes import run_cli

from labctl.drivers.grbl import GrblAlarm, GrblTable
from labctl.sim.tcpserial import TcpSerialBridge

log = logging.getLogger("grbl-sim")
REPO = Path(__file__).resolve().parents[1]
SHARED_CANDIDATES = (REPO.parent / "shared", Path("/work/shared"))
# fast axes for a 4x-slow simulator: 40 steps/mm keeps the step rate low, 6000 mm/min, 1000 mm/s²
FAST = {100: 40, 101: 40, 102: 40, 110: 6000, 111: 6000, 120: 1000, 121: 1000}


def _shared() -> Path:
    for p in SHARED_CANDIDATES:
        if (p / "grbl-sim" / "build.sh").is_file():
            return p / "grbl-sim"
    pytest.fail(f"the GRBL firmware is not beside the repository: looked in {', '.join(map(str, SHARED_CANDIDATES))}")


class OracleSilent(AssertionError):
    """The simulator (relay or firmware) answered nothing; the message says which side went silent."""


class Firmware:
    """The firmware served on a pty; ``raw()`` talks to it byte-wise (a second, independent client)."""

    def __init__(self, exe: Path, serve: Path):
        self.exe, self.serve = exe, serve
        self.restarts = 0
        self._start()

    def _start(self) -> None:
        # cwd: grbl-sim keeps its EEPROM in ./EEPROM.DAT — a fresh one per session, beside the build
        self.proc = subprocess.Popen([sys.executable, str(self.serve), "--exe", str(self.exe)],
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, cwd=self.exe.parent)
        self.path = self.proc.stdout.readline().strip()
        assert self.path.startswith("/dev/"), self.path
        self.raw("", until="Grbl 1.1h", timeout_s=30)  # first boot: error:7, settings dump, banner

    def raw(self, data: str | bytes, until: str | None = None, timeout_s: float = 5.0, wait_s: float = 0.0) -> str:
        with serial.Serial(self.path, 115200, timeout=0) as port:
            port.write(data.encode() if isinstance(data, str) else data)
            out = ""
            deadline = time.monotonic() + timeout_s
            quiet = time.monotonic() + wait_s
            while time.monotonic() < deadline:
                chunk = port.read(4096).decode(errors="replace")
                out += chunk
                if until is not None and until in out:
                    break
                if until is None and time.monotonic() > quiet and not chunk:
                    break
                time.sleep(0.02)
            else:
                if until is not None:
                    raise OracleSilent(f"no {until!r} from the firmware; got {out!r}; {self.describe()}")
        return out

    def _pids(self) -> dict[str, int]:
        pids = {"relay": self.proc.pid}
        with contextlib.suppress(OSError):
            kids = Path(f"/proc/{self.proc.pid}/task/{self.proc.pid}/children").read_text().split()
            if kids:
                pids["firmware"] = int(kids[0])
        return pids

    @staticmethod
    def _proc(pid: int) -> tuple[str, int, str] | None:
        """(state letter, CPU ticks so far, kernel wait channel) of a process, None if it is gone."""
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
            wchan = Path(f"/proc/{pid}/wchan").read_text().strip() or "-"
        except OSError:
            return None
        fields = stat[stat.rindex(")") + 2:].split()
        return fields[0], int(fields[11]) + int(fields[12]), wchan

    def describe(self, dt: float = 0.5) -> str:
        """Which side of the oracle went silent: the pty relay (serve_pty.py) or the firmware (grbl-sim), by each
        process's state, CPU used over ``dt`` s and kernel wait channel."""
        pids = self._pids()
        before = {k: self._proc(p) for k, p in pids.items()}
        time.sleep(dt)
        after = {k: self._proc(p) for k, p in pids.items()}
        tick = os.sysconf("SC_CLK_TCK")
        parts, verdict = [], None
        for side in ("relay", "firmware"):
            a, b = before.get(side), after.get(side)
            if a is None or b is None:
                parts.append(f"{side} gone")
                verdict = verdict or f"the {side} has exited"
                continue
            cpu = (b[1] - a[1]) / tick
            parts.append(f"{side} pid {pids[side]} {b[0]} {cpu:.2f} s CPU in {dt:g} s, waits in {b[2]}")
            if b[0] == "T":
                verdict = verdict or f"the {side} is stopped (SIGSTOP)"
            elif side == "firmware" and cpu > 0.3 * dt:
                verdict = verdict or "the firmware runs but says nothing (grbl-sim's own wedge)"
        if "firmware" not in pids:
            verdict = verdict or "the relay has no firmware child"
        if verdict is None:
            verdict = "both sides idle: the bytes were lost between the relay and the firmware"
        return f"oracle silent: {verdict} ({'; '.join(parts)})"

    def silent_side(self, timeout_s: float = 10.0) -> str | None:
        """None while the simulator answers ``?`` within ``timeout_s``; else which side went silent."""
        try:
            self.raw("?", until=">", timeout_s=timeout_s)
            return None
        except OracleSilent as exc:
            return str(exc)

    def restart(self, why: str) -> None:
        """A new simulator in place of a wedged one (a new pty path), set up as :meth:`fresh` leaves it."""
        log.warning("GRBL simulator wedged (%s): starting a new one", why)
        self.stop()
        self.restarts += 1
        self._start()
        self.fresh()

    def command(self, line: str) -> str:
        return self.raw(line + "\n", until="ok\r\n" if not line.startswith("$C") else "ok", timeout_s=10)

    def status(self) -> str:
        # as long as a stop waits (stop_confirm_s): under load the simulator's pty relay stalls for
        # seconds, right after a reset too (docs/notes/devices.md); a healthy firmware answers in ms
        return self.raw("?", until=">", timeout_s=30)

    def fresh(self) -> None:
        """Soft reset to Idle with fast settings, no work offset, $10=1.

        A simulator that gives no banner for 30 s after a reset is started again: once (CI, 11:21 on
        2026-11-30, load ~1) it stayed silent after a confirmed `[2-stream]` stop and then answered every later
        reset with `ALARM:3` and no banner, failing the five tests after it (docs/notes/devices.md). The test
        that met it still fails; the ones after it get a working oracle.
        """
        try:
            out = self.raw(b"\x18", until="Grbl 1.1h", timeout_s=30, wait_s=0.3)
        except AssertionError:
            self.stop()
            self.restarts += 1
            self._start()
            out = "restarted"
        if "Alarm" in self.status():
            self.command("$X")
        for k, v in {**FAST, 10: 1, 20: 0, 22: 0}.items():
            self.command(f"${k}={v}")
        self.command("G10L2P1X0Y0Z0")
        self.command("G92.1")
        assert "Idle" in self.status(), out

    def to_machine_zero(self) -> None:
        """G53 G0 to X0 Y0 and wait for Idle: each motion test then starts from the same place, not from
        wherever the previous test stopped (a 30 mm move begun at X29.975 ends at once)."""
        self.command("G53G0X0Y0")
        deadline = time.monotonic() + 60
        while "<Idle" not in self.status():
            assert time.monotonic() < deadline, "the table never came back to machine zero"
            time.sleep(0.2)

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        with contextlib.suppress(OSError):
            self.proc.stdout.close()


@pytest.fixture(scope="session")
def firmware_exe(tmp_path_factory) -> Path:
    if not (shutil.which("gcc") and shutil.which("make")):
        pytest.skip("gcc and make are needed to build the GRBL firmware simulator")
    here = _shared()
    out = tmp_path_factory.mktemp("grbl-sim")
    done = subprocess.run(["bash", str(here / "build.sh"), str(out)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return Path(done.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def fw(firmware_exe) -> Firmware:
    f = Firmware(firmware_exe, _shared() / "serve_pty.py")
    try:
        f.fresh()
        yield f
    finally:
        f.stop()


SLOW = 15.0  # reply time-out: generous, as a starved simulator on a loaded machine can pause for seconds


def table(fw, **kw) -> GrblTable:
    return GrblTable(fw.path, 115200, reset_on_open=False, timeout_s=SLOW, status_hz=10, auto_unlock=False, **kw)


@pytest.fixture
def labctl(capsys):
    """``labctl …`` in this process (the signal tests start their own): (exit code, stdout, stderr)."""

    def run(*args, timeout=None):
        return run_cli(capsys, *args)

    return run


def test_work_offsets_and_report_masks_g53_moves(fw, labctl):
    """$10=0..3 with a G54 offset: the machine position is right from the first status of a new
    session (WCO asked for, never assumed zero), and moves land in machine coordinates (G53)."""
    fw.fresh()
    fw.command("G10L2P1X5Y7")
    fw.command("G54")
    with table(fw) as t:
        assert t.status().state == "Idle"
        st = t.move_to(20.0, 15.0, feed_mm_min=6000)
        assert st.position[:2] == pytest.approx((20.0, 15.0), abs=1e-3)
        assert t.wco[:2] == pytest.approx((5.0, 7.0))
    assert "MPos:20.000,15.000" in fw.status()  # the firmware's own word: machine 20,15, not 25,22
    for mask in (0, 1, 2, 3):
        fw.command(f"$10={mask}")
        for _ in range(3):  # make the next reports carry no WCO: a new session must still get it right
            fw.status()
        with table(fw) as t:
            st = t.status()
            assert st.position[:2] == pytest.approx((20.0, 15.0), abs=1e-3), mask
            assert t.work_position()[:2] == pytest.approx((15.0, 8.0), abs=1e-3), mask
    code, out, err = labctl("--json", "table", "move", "-5", "-5", "--feed", "6000", "--port", fw.path,
                            "--baud", "115200", "--timeout", "15")  # negative numbers without `--`
    assert code == 0, err
    d = json.loads(out)
    assert (d["position"]["x"], d["position"]["y"]) == pytest.approx((-5.0, -5.0), abs=1e-3)
    assert (d["work_position"]["x"], d["work_position"]["y"]) == pytest.approx((-10.0, -12.0), abs=1e-3)
    fw.command("$10=1")


def test_devices_reads_the_firmwares_settings_against_the_table_file(fw, labctl, tmp_path):
    """``labctl devices`` reads ``$$`` from the real firmware and names a table file that promises more travel or
    feed than GRBL has ($130/$131, $110/$111); a file inside them is OK. Nothing moves."""
    import yaml

    from labctl.workspace import sample_lab_path

    fw.fresh()  # $110 = $111 = 6000 mm/min; $130, $131: the firmware's own defaults
    settings = {int(k): float(v) for k, v in (line[1:].split("=") for line in fw.command("$$").split()
                                              if line.startswith("$") and "=" in line)}
    lab = tmp_path / "lab"
    shutil.copytree(sample_lab_path(), lab, ignore=shutil.ignore_patterns("runs", ".git", "labctl", "tests", "docs",
                                                                          ".venv", ".ci"))
    table_file = lab / "drivers" / "table.yaml"
    base = {**yaml.safe_load(table_file.read_text()), "kind": "grbl", "port": fw.path, "baud": 115200,
            "reset_on_open": False, "timeout_s": SLOW}
    before = fw.status()

    def table_row(**cfg):
        table_file.write_text(yaml.safe_dump({**base, **cfg}))
        code, out, err = labctl("--json", "--lab", str(lab), "devices")
        return code, next(r for r in json.loads(out)["devices"] if r["role"] == "table")

    code, row = table_row(travel_mm=[settings[130] + 100.0, settings[131]], max_feed_mm_min=settings[110])
    assert code == 3 and not row["ok"] and "travel_mm: " in row["verdict"] and "$130" in row["verdict"], row
    assert f"at most {settings[130]:g}" in row["verdict"]
    code, row = table_row(travel_mm=[settings[130], settings[131]], max_feed_mm_min=settings[111] * 1.5)
    assert not row["ok"] and "max_feed_mm_min: " in row["verdict"] and "$110" in row["verdict"], row
    # every mismatch at once, not only the first ($110 is checked before $130)
    code, row = table_row(travel_mm=[settings[130] + 100.0, settings[131]], max_feed_mm_min=settings[110] * 1.5)
    assert code == 3 and not row["ok"] and "\n" not in row["verdict"], row
    assert all(s in row["verdict"] for s in ("$110", "$111", "$130", f"at most {settings[130]:g}")), row
    code, row = table_row(travel_mm=[settings[130], settings[131]], max_feed_mm_min=settings[110])
    assert row["ok"], row
    assert fw.status().split("|")[1] == before.split("|")[1]  # the same machine position: nothing moved


def test_hold_check_and_stop_keep_the_position(fw, labctl):
    """Status in Run, Hold:1/Hold:0 (no sync line sent to a held GRBL), Check ($C); a stop is a
    hold then a reset, which the firmware answers with Idle, not ALARM:3."""
    fw.fresh()
    with table(fw) as t:
        x0 = t.status().position[0]
        t.stream(["G21G90", "G53G1X80Y0F1500"])
        seen = set()
        deadline = time.monotonic() + 10
        while "Run" not in seen and time.monotonic() < deadline:
            seen.add(t.status().state)
        t.feed_hold()
        # its own deadline: a starved simulator can report Run/Hold:1 unchanged for seconds (docs/notes/devices.md)
        deadline = time.monotonic() + SLOW
        while "Hold:0" not in seen and time.monotonic() < deadline:
            seen.add(t.status().state)
        assert {"Run", "Hold:0"} <= seen
    code, out, err = labctl("--json", "table", "status", "--port", fw.path, "--baud", "115200", "--timeout", "15")
    assert code == 0, err
    held = json.loads(out)
    assert held["state"] == "Hold:0" and x0 < held["position"]["x"] < 80  # no "ignores lines", nothing queued
    with table(fw) as t:
        st = t.stop()
        assert st.state == "Idle" and st.position[0] == pytest.approx(held["position"]["x"], abs=1e-3)
        assert t.session_alarm is None
        t.command("$C")
        assert t.status().state == "Check"
    fw.command("$C")  # leaving check mode soft-resets GRBL
    assert "Idle" in fw.status()


def test_alarm3_is_never_cleared_silently(fw, labctl):
    """A reset in motion (ALARM:3): the next `table move` refuses without --unlock and does not move."""
    fw.fresh()
    with table(fw) as t:
        t.stream(["G21G90", "G53G1X60F1500"])
        while t.status().state != "Run":
            pass
        t.reset()
        assert t.session_alarm == 3 and t.status().state == "Alarm"
        x = t.status().position[0]
    code, _, err = labctl("table", "move", "1", "1", "--port", fw.path, "--baud", "115200", "--timeout", "15")
    assert code == 3 and "ALARM" in err and "--unlock" in err and len(err.strip().splitlines()) == 1
    assert f"MPos:{x:.3f}" in fw.status() and "Alarm" in fw.status()
    code, out, err = labctl("--json", "table", "move", "1", "1", "--feed", "6000", "--unlock", "--port", fw.path,
                            "--baud", "115200", "--timeout", "15")
    assert code == 0, err
    assert json.loads(out)["state"] == "Idle"


def test_stream_300_lines_then_an_error_names_the_file_line_and_stops(fw, tmp_path, labctl):
    fw.fresh()
    moves = [f"G1 X{i * 0.2:.1f} Y0" for i in range(1, 301)]
    good = tmp_path / "good.nc"
    good.write_text("; 300 moves\nG21 G90\nG1 F6000\n\n" + "\n".join(moves) + "\n")
    code, out, err = labctl("--json", "table", "stream", str(good), "--port", fw.path, "--baud", "115200",
                            "--timeout", "15")
    assert code == 0, err
    d = json.loads(out)
    assert d["lines"] == 302 and d["state"] == "Idle"
    assert (d["position"]["x"], d["position"]["y"]) == pytest.approx((60.0, 0.0), abs=1e-3)
    assert "MPos:60.000,0.000" in fw.status()
    bad = tmp_path / "bad.nc"
    body = ["(header)", "G21 G90", "", "G1 F6000"] + [f"G1 X{60 - i * 0.1:.1f}" for i in range(1, 147)]
    body.append("G1 X10 Q5")  # file line 151: error:20 unsupported command... any error:N will do
    body += [f"G1 X{i:.1f}" for i in range(10)]
    bad.write_text("\n".join(body) + "\n")
    assert body[150] == "G1 X10 Q5"
    code, out, err = labctl("table", "stream", str(bad), "--port", fw.path, "--baud", "115200", "--timeout", "15")
    assert code == 3 and "file line 151" in err and "error:" in err, err
    assert len(err.strip().splitlines()) == 1 and "stopped" in err
    s1 = fw.status()
    time.sleep(0.5)
    s2 = fw.status()
    assert "<Idle" in s1 and s1.split("|")[1] == s2.split("|")[1]  # stopped, not Run with lines still queued


@pytest.mark.timeout(330)  # two scenarios of up to 6 + 90 + 2 × 30 s when the first oracle falls silent
@pytest.mark.parametrize("sig,cmd", [(signal.SIGINT, "stream"), (signal.SIGTERM, "move"), (signal.SIGHUP, "move")])
def test_interrupt_stops_the_table(fw, tmp_path, sig, cmd):
    """Ctrl-C / SIGTERM / SIGHUP (twice) during `table stream|move`: hold, reset, status read back; exit 130,
    one line. (SIGHUP, a closed terminal, used to end the command at once with the table still moving.)

    Twice in ~9 clean-clone CI runs (2026-11-30, `[2-stream]`) the simulator fell silent for good right after
    a stop the product had confirmed from the firmware's own report, so the independent read-back got nothing
    (docs/notes/devices.md). Then the whole scenario runs once more on a new simulator (``fresh()`` starts
    one): a product that does not stop the table fails both times; a silent oracle twice still fails. A third
    time (the merge of 2026-11-30 16:10) the re-run itself was cut by the suite's 120-s per-test time-out while it
    read back, after both stops had been confirmed (Alarm: the simulator starved); hence the test's own time-out.
    """
    try:
        _interrupt_and_read_back(fw, tmp_path, sig, cmd)
    except OracleSilent:
        _interrupt_and_read_back(fw, tmp_path, sig, cmd)


def _interrupt_and_read_back(fw, tmp_path, sig, cmd):
    fw.fresh()
    fw.to_machine_zero()  # so that the move below is long whatever ran before
    prog = tmp_path / "long.nc"
    prog.write_text("G21 G90\nG1 F1200\n" + "".join(f"G1 X{i * 2}\n" for i in range(1, 60)))
    args = ["stream", str(prog)] if cmd == "stream" else ["move", "100", "0", "--feed", "1200"]
    p = subprocess.Popen([sys.executable, "-m", "labctl", "table", *args, "--port", fw.path, "--baud", "115200",
                          "--timeout", "15"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "PYTHONPATH": str(REPO)})
    time.sleep(6.0)  # python start-up and connect (slow on a loaded machine), then some motion
    p.send_signal(sig)
    time.sleep(0.01)
    p.send_signal(sig)  # pressed twice, as users do: the second must not cut the stop short
    # the hold (a few s) and the reset, whose confirmation a stop awaits up to stop_confirm_s (30 s): on a
    # loaded machine the simulator's pty relay has been seen silent for 20 s (docs/notes/devices.md)
    out, err = p.communicate(timeout=90)
    assert p.returncode == 130, err
    # Idle when the hold completed before the reset (the usual case); Alarm (ALARM:3) if a starved
    # simulator was still decelerating after 30 s — stopped either way, never Run
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err and "confirmed " in err, err
    try:
        s1 = fw.status()
    except AssertionError as exc:
        raise OracleSilent(f"{exc} (after the product's confirmed stop: {err.strip()})") from None
    time.sleep(0.5)
    s2 = fw.status()
    assert ("<Idle" in s1 or "<Alarm" in s1) and s1.split("|")[1] == s2.split("|")[1], (s1, err)
    x = float(s1.split("|")[1].split(":")[1].split(",")[0])
    assert 0 < x < 100  # it was moving, and stopped part-way


class LossyPort:
    """The firmware's port as a noisy line would deliver it: ``garble_banner`` damages one byte of every
    ``Grbl 1.1h`` banner line on the way in; ``drop_resets`` loses that many 0x18 bytes on the way out."""

    def __init__(self, path: str, garble_banner: bool = False, drop_resets: int = 0):
        self._port = serial.Serial(path, 115200, timeout=0)
        self.garble_banner, self.drop_resets = garble_banner, drop_resets
        self.garbled = self.dropped = 0
        self._held = b""  # a partial line, released once complete (a banner may come in pieces)

    def __getattr__(self, name):
        return getattr(self._port, name)

    @property
    def in_waiting(self) -> int:
        return self._port.in_waiting + len(self._held)

    def read(self, n: int = 1) -> bytes:
        data = self._held + self._port.read(max(n, 4096))
        cut = data.rfind(b"\n") + 1
        out, self._held = data[:cut], data[cut:]
        if self.garble_banner and b"Grbl 1.1h" in out:
            self.garbled += out.count(b"Grbl 1.1h")
            out = out.replace(b"Grbl 1.1h", b"Gr\xffl 1.1h")
        return out

    def write(self, data: bytes) -> int:
        if self.drop_resets and b"\x18" in data:
            self.drop_resets -= 1
            self.dropped += 1
            data = data.replace(b"\x18", b"", 1)
        return self._port.write(data)


@pytest.mark.parametrize("lossy", [{"garble_banner": True}, {"drop_resets": 1}], ids=["banner-garbled", "reset-lost"])
def test_a_stop_is_confirmed_when_the_banner_or_the_reset_is_lost(fw, lossy):
    """The stop's soft reset on a line that garbles the banner GRBL prints after it (the driver never sees
    one) or that loses the 0x18 itself: GRBL's own status reports confirm the reset, and a report that
    still shows the hold makes the driver send the reset again. Either way the table is stopped part-way
    and says so; before, the stop gave up after the reply time-out ("no banner after a soft reset")."""
    fw.fresh()
    fw.to_machine_zero()
    port = LossyPort(fw.path, **lossy)
    with GrblTable(fw.path, 115200, serial_port=port, reset_on_open=False, timeout_s=SLOW, status_hz=10,
                   auto_unlock=False) as t:
        t.stream(["G21G90", "G53G1X60F1200"])
        _until_running(t)
        st = t.stop()
        assert st.state == "Idle" and 0 < st.position[0] < 60
        if "garble_banner" in lossy:
            assert port.garbled >= 1 and t.reset_confirmed_by == "status"
        else:
            assert port.dropped == 1 and t.reset_confirmed_by == "banner"  # the second 0x18 got through
    s1 = fw.status()
    time.sleep(0.5)
    s2 = fw.status()
    assert "<Idle" in s1 and s1.split("|")[1] == s2.split("|")[1]
    assert s1.split("|")[1].startswith(f"MPos:{st.position[0]:.3f},")  # where the driver said it stopped


def test_a_stop_waits_out_a_silent_link_and_confirms(fw):
    """The firmware's pty relay frozen for 8 s (SIGSTOP; in CI a CPU-starved kernel tty worker froze it for
    up to 20 s, docs/notes/devices.md) just as the stop begins, with a 3 s reply time-out: nothing reaches
    GRBL or comes back. The stop waits for the reset's confirmation up to ``stop_confirm_s`` rather than
    give up after the time-out (it did: "no banner after a soft reset"), and the table stays where it was held."""
    fw.fresh()
    fw.to_machine_zero()
    with GrblTable(fw.path, 115200, reset_on_open=False, timeout_s=3.0, status_hz=10, auto_unlock=False) as t:
        t.stream(["G21G90", "G53G1X60F1200"])
        _until_running(t)
        t.feed_hold()
        deadline = time.monotonic() + SLOW
        while (st := t.status()).state != "Hold:0":
            assert time.monotonic() < deadline, st.state
        os.kill(fw.proc.pid, signal.SIGSTOP)
        thaw = threading.Timer(8.0, os.kill, (fw.proc.pid, signal.SIGCONT))
        thaw.start()
        try:
            t0 = time.monotonic()
            stopped = t.stop()
            waited = time.monotonic() - t0
        finally:
            thaw.cancel()
            os.kill(fw.proc.pid, signal.SIGCONT)
        assert waited > 6.0  # past two reply time-outs (the hold's and the reset's): where the old stop gave up
        assert stopped.state == "Idle" and stopped.position[0] == pytest.approx(st.position[0], abs=1e-3)
    s1 = fw.status()
    time.sleep(0.5)
    assert "<Idle" in s1 and s1.split("|")[1] == fw.status().split("|")[1]
    assert s1.split("|")[1].startswith(f"MPos:{st.position[0]:.3f},")


def test_critical_alarm_status_never_resets_and_homing_times_out(fw, labctl):
    """ALARM:2 (soft limit) locks GRBL: it ignores '?'. `table status` says so and does not reset it;
    `table reset` does; `table home` is bounded by --timeout and ends in the firmware's homing alarm."""
    fw.fresh()
    for k, v in {22: 1, 20: 1, 130: 200, 131: 200}.items():
        fw.command(f"${k}={v}")
    out = fw.raw("G53G0X10\n", until="ALARM:2", timeout_s=10)
    assert "ALARM:2" in out
    code, _, err = labctl("table", "status", "--port", fw.path, "--baud", "115200", "--timeout", "2")
    assert code == 3 and "reset" in err and len(err.strip().splitlines()) == 1, err
    assert "Grbl 1.1h" not in fw.raw("?", wait_s=1.0)  # still locked: nobody reset it
    code, out, err = labctl("--json", "table", "reset", "--port", fw.path, "--baud", "115200", "--timeout", "15")
    assert code == 0 and json.loads(out)["state"] == "Alarm", err  # homing lock after the reset
    code, out, err = labctl("table", "home", "--timeout", "20", "--port", fw.path, "--baud", "115200")
    assert code == 3 and "ALARM:" in err and "Homing fail" in err, err  # grbl-sim: every limit pin reads active
    with table(fw) as t, pytest.raises(GrblAlarm):
        t.ensure_ready()
    fw.fresh()


# --- a link that drops mid-move (issue 12, Build 7): the firmware behind labctl's ser2net-style TCP
# bridge, stopped and started again. The firmware keeps executing what it accepted while nobody is
# connected, and a reset in motion gives its own ALARM:3 (position unknown): the driver must read
# that state again before anything moves, and never clear the alarm by itself.

RECONNECT_S = 5.0


def _reconnecting_table(url: str, auto_unlock: bool = False) -> GrblTable:
    return GrblTable(url, 115200, reset_on_open=False, timeout_s=SLOW, status_hz=10, auto_unlock=auto_unlock,
                     reconnect_s=RECONNECT_S)


def _until_running(t: GrblTable) -> None:
    deadline = time.monotonic() + SLOW
    while t.status().state != "Run":
        assert time.monotonic() < deadline, "the move never started"


def test_a_brief_drop_mid_move_recovers_and_the_firmware_finished_the_move(fw):
    fw.fresh()
    fw.to_machine_zero()
    with TcpSerialBridge(fw.path) as bridge, _reconnecting_table(bridge.url) as t:
        t.stream(["G21G90", "G53G1X30F1200"])  # accepted at once; ~1.5 s of motion, ~6 s on the wall clock
        _until_running(t)
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
    fw.to_machine_zero()
    with TcpSerialBridge(fw.path) as bridge, _reconnecting_table(bridge.url, auto_unlock=True) as t:
        t.stream(["G21G90", "G53G1X40F1200"])
        _until_running(t)
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


def test_a_soft_limit_alarm_is_stopped_and_confirmed_not_cut_power(fw):
    """Soft limits on: a move past the travel is GRBL's ALARM:2, and its critical-event lock begins only after
    the alarm line, discarding a reset that came in between (the simulator's slow threads make that the usual
    case). The stop must send the reset again on ``[MSG:Reset to continue]`` and confirm the table, instead of
    waiting out stop_confirm_s and telling the user to cut its power while one more 0x18 would do."""
    fw.fresh()
    fw.to_machine_zero()
    for k, v in {22: 1, 20: 1, 130: 200, 131: 200}.items():  # soft limits need homing enabled
        fw.command(f"${k}={v}")
    fw.raw(b"\x18", until="Grbl 1.1h", timeout_s=30)
    fw.command("$X")
    try:
        p = subprocess.run([sys.executable, "-m", "labctl", "table", "move", "900", "0", "--feed", "6000",
                            "--port", fw.path, "--baud", "115200", "--timeout", "15"], capture_output=True, text=True,
                           timeout=120, env={**os.environ, "PYTHONPATH": str(REPO)})
        lines = [x for x in p.stderr.splitlines() if x.strip()]
        assert p.returncode == 3 and len(lines) == 1, p.stderr
        assert "ALARM:2" in lines[0] and "confirmed Alarm" in lines[0] and "cut its power" not in lines[0], p.stderr
        assert "<Alarm|MPos:0.000,0.000" in fw.status()  # answering again: out of the lock, nothing moved
    finally:
        fw.raw(b"\x18", until="Grbl 1.1h", timeout_s=30)
        fw.command("$X")
        for k, v in {20: 0, 22: 0}.items():
            fw.command(f"${k}={v}")
        fw.fresh()


def test_a_reset_in_motion_says_the_position_is_lost(fw):
    """`table reset` during a move: GRBL's ALARM:3 (steps may be lost). The command still succeeds (the table
    stopped), but says so in one line on stderr, with what to do, and ``position_lost`` in its output."""
    fw.fresh()
    fw.to_machine_zero()
    fw.command("G53G1X150F1200")  # 30 s on the simulator's wall clock
    deadline = time.monotonic() + 15
    while "<Run" not in fw.status():
        assert time.monotonic() < deadline, "the move never started"
    try:
        p = subprocess.run([sys.executable, "-m", "labctl", "--json", "table", "reset", "--port", fw.path, "--baud",
                            "115200", "--timeout", "15"], capture_output=True, text=True, timeout=120,
                           env={**os.environ, "PYTHONPATH": str(REPO)})
        assert p.returncode == 0, p.stderr
        d = json.loads(p.stdout)
        lines = [x for x in p.stderr.splitlines() if x.strip()]
        assert d["state"] == "Alarm" and d["position_lost"] is True
        assert len(lines) == 1 and "ALARM:3" in lines[0] and "position is lost" in lines[0], p.stderr
        assert "labctl table home" in lines[0]
        assert "<Alarm" in fw.status()
        # at rest, a reset loses nothing and says nothing
        fw.command("$X")
        p = subprocess.run([sys.executable, "-m", "labctl", "--json", "table", "reset", "--port", fw.path, "--baud",
                            "115200", "--timeout", "15"], capture_output=True, text=True, timeout=120,
                           env={**os.environ, "PYTHONPATH": str(REPO)})
        assert p.returncode == 0 and json.loads(p.stdout)["position_lost"] is False and not p.stderr.strip(), p.stderr
    finally:
        fw.fresh()


@pytest.mark.timeout(180)
def test_a_silent_simulator_names_the_silent_side_and_is_restarted(firmware_exe):
    """The oracle's own diagnosis: with the firmware frozen, then the relay frozen, a read names which side went
    silent; ``restart`` then gives a new simulator that answers (what the conftest's retry does for the test that
    met a wedge)."""
    f = Firmware(firmware_exe, _shared() / "serve_pty.py")
    try:
        pids = f._pids()
        assert set(pids) == {"relay", "firmware"}, pids
        assert f.silent_side() is None
        os.kill(pids["firmware"], signal.SIGSTOP)
        try:
            why = f.silent_side(timeout_s=2.0)
        finally:
            os.kill(pids["firmware"], signal.SIGCONT)
        assert why is not None and "the firmware is stopped (SIGSTOP)" in why, why
        f.raw("", wait_s=0.5)  # what the frozen firmware answers late goes here
        os.kill(pids["relay"], signal.SIGSTOP)
        try:
            why = f.silent_side(timeout_s=2.0)
        finally:
            os.kill(pids["relay"], signal.SIGCONT)
        assert why is not None and "the relay is stopped (SIGSTOP)" in why, why
        f.restart(why)
        assert f.restarts == 1  # (the new pty may reuse the old number)
        assert f.silent_side() is None and "Idle" in f.status()
    finally:
        f.stop()


_WEDGED: dict[str, int] = {}


@pytest.mark.timeout(180)
def test_a_test_that_meets_a_wedged_simulator_runs_again_on_a_new_one(fw):
    """The conftest's retry: the first run freezes the firmware under itself (a wedge, as a test meets one) and
    fails on the silence; the retry probes the oracle, finds it silent, starts a new simulator and runs the test
    once more, which now passes. (A failure while the simulator still answers is not retried.)"""
    _WEDGED["runs"] = _WEDGED.get("runs", 0) + 1
    if _WEDGED["runs"] == 1:
        os.kill(fw._pids()["firmware"], signal.SIGSTOP)
    assert ">" in fw.raw("?", until=">", timeout_s=3.0)
    assert _WEDGED["runs"] == 2 and fw.restarts >= 1
