"""``labctl table`` through the real ser2net in front of the real GRBL 1.1h firmware, over raw TCP
(``socket://``) and RFC 2217 (``rfc2217://``).

The firmware is grbl-sim on a pty (``../shared/grbl-sim``, as in ``test_grbl_firmware.py``); ser2net
is Debian's package, started here on loopback with one accepter per transport on that pty. Every
command runs out of process, as a user runs it, and each answer is checked against the firmware's
own status report, read straight from its pty. Without ser2net (and not root, so it cannot be
installed) the module is skipped with the reason.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from test_grbl_firmware import Firmware, _shared, firmware_exe  # noqa: F401 — the session's firmware build

from labctl.workspace import init_workspace

TIMEOUT = "15"  # reply time-out: a starved simulator on a loaded machine can pause for seconds


def _ser2net_binary() -> str:
    exe = shutil.which("ser2net") or ("/usr/sbin/ser2net" if Path("/usr/sbin/ser2net").is_file() else None)
    if exe:
        return exe
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        pytest.skip("ser2net is not installed (Debian: apt-get install ser2net) and this user cannot install it")
    done = subprocess.run(["apt-get", "install", "-y", "ser2net"], capture_output=True, text=True, timeout=600,
                          env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"})
    exe = shutil.which("ser2net") or ("/usr/sbin/ser2net" if Path("/usr/sbin/ser2net").is_file() else None)
    if done.returncode != 0 or not exe:
        pytest.skip(f"ser2net could not be installed: {done.stderr.strip().splitlines()[-1:]}")
    return exe


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Ser2net:
    """ser2net 4 on loopback: ``raw`` (plain TCP) and ``rfc2217`` (telnet + RFC 2217) accepters on one pty."""

    def __init__(self, exe: str, device: str, folder: Path):
        self.exe, self.folder = exe, folder
        self.ports = {"socket": _free_port(), "rfc2217": _free_port()}
        self.config = folder / "ser2net.yaml"
        self._configure(device)
        self.proc = None
        self.start()

    def _configure(self, device: str) -> None:
        self.config.write_text(
            f"connection: &raw\n  accepter: tcp,127.0.0.1,{self.ports['socket']}\n"
            f"  connector: serialdev,{device},115200n81,local\n"
            f"connection: &rfc2217\n  accepter: telnet(rfc2217),tcp,127.0.0.1,{self.ports['rfc2217']}\n"
            f"  connector: serialdev,{device},115200n81,local\n")

    def retarget(self, device: str) -> None:
        """Serve another pty (a restarted simulator's), on the same TCP ports."""
        self.stop()
        self._configure(device)
        self.start()

    def url(self, transport: str, options: str = "?ign_set_control") -> str:
        port = self.ports[transport]
        return f"socket://127.0.0.1:{port}" if transport == "socket" else f"rfc2217://127.0.0.1:{port}{options}"

    def start(self) -> None:
        self.proc = subprocess.Popen([self.exe, "-n", "-c", str(self.config), "-P", str(self.folder / "ser2net.pid")],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 10
        for port in self.ports.values():
            while True:
                assert self.proc.poll() is None, "ser2net exited at start"
                try:
                    socket.create_connection(("127.0.0.1", port), timeout=1).close()
                    break
                except OSError:
                    assert time.monotonic() < deadline, "ser2net never listened"
                    time.sleep(0.05)
        time.sleep(0.3)  # let it close the device again after the probes

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture(scope="module")
def fw(firmware_exe):  # noqa: F811 — the fixture imported above
    f = Firmware(firmware_exe, _shared() / "serve_pty.py")
    try:
        f.fresh()
        yield f
    finally:
        f.stop()


@pytest.fixture(scope="module")
def ser2net(fw, tmp_path_factory):
    s = Ser2net(_ser2net_binary(), fw.path, tmp_path_factory.mktemp("ser2net"))
    try:
        yield s
    finally:
        s.stop()


def _labctl(*args, timeout=120, lab: Path | None = None) -> tuple[int, str, str]:
    pre = ("--lab", str(lab)) if lab is not None else ()
    done = subprocess.run([sys.executable, "-m", "labctl", *pre, *args], capture_output=True, text=True,
                          timeout=timeout)
    return done.returncode, done.stdout, done.stderr


def _grbl(fw) -> tuple[str, tuple[float, float]]:
    """The firmware's own word: its state and machine X, Y from a status report read on its pty."""
    report = fw.status()
    m = re.search(r"<([A-Za-z]+(?::\d)?)\|MPos:(-?[\d.]+),(-?[\d.]+),", report)
    assert m, report
    return m.group(1), (float(m.group(2)), float(m.group(3)))


def _xy(d: dict) -> tuple[float, float]:
    return d["position"]["x"], d["position"]["y"]


@pytest.mark.timeout(600)
@pytest.mark.parametrize("transport", ["socket", "rfc2217"])
def test_every_table_command_agrees_with_the_firmware_through_ser2net(fw, ser2net, transport, tmp_path):
    url = ser2net.url(transport)
    common = ("--port", url, "--baud", "115200", "--timeout", TIMEOUT)
    fw.fresh()
    fw.to_machine_zero()

    code, out, err = _labctl("--json", "table", "status", *common)
    assert code == 0, err
    d = json.loads(out)
    assert d["state"] == "Idle" and _xy(d) == pytest.approx((0.0, 0.0), abs=1e-3)
    assert d["version"] == "1.1h.20190830" and d["port"] == url
    assert _grbl(fw) == ("Idle", pytest.approx((0.0, 0.0), abs=1e-3))

    code, out, err = _labctl("--json", "table", "move", "12", "7", "--feed", "6000", *common)
    assert code == 0, err
    assert _xy(json.loads(out)) == pytest.approx((12.0, 7.0), abs=1e-3)
    assert _grbl(fw) == ("Idle", pytest.approx((12.0, 7.0), abs=1e-3))

    prog = tmp_path / "square.gcode"
    prog.write_text("G21 G90\nG53 G1 X20 Y10 F6000\n(a comment)\nG53 G1 X25 Y5\n")
    code, out, err = _labctl("--json", "table", "stream", str(prog), *common)
    assert code == 0, err
    d = json.loads(out)
    assert d["lines"] == 3 and _xy(d) == pytest.approx((25.0, 5.0), abs=1e-3)
    assert _grbl(fw) == ("Idle", pytest.approx((25.0, 5.0), abs=1e-3))

    code, out, err = _labctl("--json", "table", "reset", *common)
    assert code == 0, err
    d = json.loads(out)
    assert d["state"] == "Idle" and _xy(d) == pytest.approx((25.0, 5.0), abs=1e-3)  # a reset at rest keeps it
    assert _grbl(fw) == ("Idle", pytest.approx((25.0, 5.0), abs=1e-3))

    # grbl-sim reads every limit pin as active, so homing must end in its own ALARM, said in one line
    fw.command("$22=1")
    code, out, err = _labctl("table", "home", "--port", url, "--baud", "115200", "--timeout", "20")
    lines = [x for x in err.splitlines() if x.strip() and not x.startswith("homing…")]
    assert code == 3 and len(lines) == 1 and "ALARM:" in lines[0] and "Homing fail" in lines[0], err
    assert _grbl(fw)[0] == "Alarm"
    fw.fresh()


@pytest.mark.timeout(300)
def test_rfc2217_without_ign_set_control_names_the_fix(fw, ser2net):
    """ser2net on a pty never acknowledges a DTR/RTS change: pyserial's open waits 3 s and fails; the
    one line says which URL option makes it work."""
    fw.fresh()
    code, out, err = _labctl("table", "status", "--port", ser2net.url("rfc2217", options=""), "--baud", "115200",
                             "--timeout", TIMEOUT)
    lines = [x for x in err.splitlines() if x.strip()]
    assert code == 3 and len(lines) == 1 and "add ?ign_set_control to the URL" in lines[0], err
    assert "Traceback" not in err


@pytest.mark.timeout(300)
def test_the_serial_host_link_opens_over_rfc2217(fw, ser2net):
    """The host link's serial transport opens the same URLs (pyserial refuses write_timeout there)."""
    from labctl.runtime.transport import SerialHostLink

    link = SerialHostLink.open(ser2net.url("rfc2217"), baud=115200)
    try:
        assert link._port.is_open
    finally:
        link._port.close()


@pytest.mark.timeout(300)
def test_the_supervisors_stop_bytes_reach_the_table_over_rfc2217(fw, ser2net):
    """The supervisor's emergency stop opens the table's URL itself and writes ``!``: over RFC 2217 the
    firmware must end in a feed hold, never keep moving because the stop thread died on the port."""
    from labctl.runtime.stopping import send_stop_bytes

    fw.fresh()
    fw.to_machine_zero()
    fw.command("G53G1X150F1200")  # 7.5 s of motion, 30 s on the simulator's wall clock
    deadline = time.monotonic() + 15
    while _grbl(fw)[0] != "Run":
        assert time.monotonic() < deadline, "the move never started"
    lab = SimpleNamespace(table=SimpleNamespace(port=ser2net.url("rfc2217"), baud=115200),
                          robot=SimpleNamespace(port=None, baud=9600))
    t0 = time.monotonic()
    table = next(o for o in send_stop_bytes(lab, {}) if o["device"] == "table")
    sent_s = time.monotonic() - t0
    assert table["stopped"] and table["error"] is None, table
    deadline = time.monotonic() + 15
    # this check's '?' goes straight to the pty and can overtake the '!' that ser2net still forwards (seen once
    # in a full file run at load ~15: Run at X4.2 on the first read): Run counts as a failure only after 2 s
    t_sent = time.monotonic()
    while (state := _grbl(fw))[0] != "Hold:0":
        running_late = state[0] == "Run" and time.monotonic() - t_sent < 2.0
        assert (state[0].startswith("Hold") or running_late) and time.monotonic() < deadline, state
        time.sleep(0.1)
    x = state[1][0]
    assert 0.0 < x < 150.0, state
    time.sleep(1.0)
    assert _grbl(fw) == ("Hold:0", pytest.approx(state[1], abs=1e-3))  # held: nothing moves any more
    print(f"stop bytes over rfc2217 sent in {sent_s:.2f} s")
    fw.fresh()


@pytest.mark.timeout(300)
def test_table_stream_rides_out_a_ser2net_restart_with_the_labs_reconnect_s(fw, ser2net, tmp_path):
    """With ``reconnect_s`` in the lab's table file, ``labctl table stream`` waits for ser2net to come back,
    then abandons the program and stops the table (the driver never resends motion it cannot account for);
    without it, the command fails at once and can no longer reach the table, which runs on."""
    lab = init_workspace(tmp_path / "lab")
    table_yaml = lab / "drivers" / "table.yaml"
    text = table_yaml.read_text()
    assert not re.search(r"(?m)^reconnect_s:", text), text
    table_yaml.write_text(text + "reconnect_s: 10.0\n")
    fw.fresh()
    fw.to_machine_zero()
    prog = tmp_path / "long.gcode"
    prog.write_text("G21 G90\n" + "".join(f"G53 G1 X{2 * k} Y{k % 2} F1200\n" for k in range(1, 61)))
    p = subprocess.Popen([sys.executable, "-m", "labctl", "--lab", str(lab), "table", "stream", str(prog),
                          "--port", ser2net.url("socket"), "--baud", "115200", "--timeout", TIMEOUT],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # nothing reads the pty meanwhile (a second reader would take the stream's own replies): the
        # command starts in ~2 s and the program runs ~24 s on the simulator's wall clock
        time.sleep(6.0)
        assert p.poll() is None, p.communicate()
        ser2net.stop()
        threading.Timer(1.0, ser2net.start).start()
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        time.sleep(1.5)
        if ser2net.proc.poll() is not None:
            ser2net.start()
    lines = [x for x in err.splitlines() if x.strip()]
    assert p.returncode == 3 and len(lines) == 1, err
    assert "came back after" in lines[0] and "the program was abandoned and the table stopped" in lines[0], err
    assert "cut its power" not in lines[0]
    state, xy = _grbl(fw)
    assert state in ("Idle", "Hold:0", "Alarm") and xy[0] < 120.0, (state, xy)  # stopped short of the end
    time.sleep(1.0)
    assert _grbl(fw)[1] == pytest.approx(xy, abs=1e-3)
    fw.fresh()


@pytest.mark.timeout(300)
def test_table_move_rides_out_a_ser2net_restart_and_lands_at_the_target(fw, ser2net, tmp_path):
    """A drop while ``labctl table move`` waits for the table (its ``G4P0`` in flight) must not abandon the
    move halfway: the wait moves nothing, so after the reconnect the driver goes on waiting, and the table
    lands at the target, in GRBL's own word."""
    lab = init_workspace(tmp_path / "lab")
    table_yaml = lab / "drivers" / "table.yaml"
    table_yaml.write_text(table_yaml.read_text() + "reconnect_s: 10.0\n")
    fw.fresh()
    fw.to_machine_zero()
    p = subprocess.Popen([sys.executable, "-m", "labctl", "--lab", str(lab), "--json", "table", "move", "120", "0",
                          "--feed", "1200", "--port", ser2net.url("socket"), "--baud", "115200",
                          "--timeout", "60"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # the command starts in ~2 s; the move takes 6 s of firmware time, ~24 s on the simulator's wall clock
        time.sleep(6.0)
        assert p.poll() is None, p.communicate()
        ser2net.stop()
        threading.Timer(1.0, ser2net.start).start()
        out, err = p.communicate(timeout=150)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        time.sleep(1.5)
        if ser2net.proc.poll() is not None:
            ser2net.start()
    assert p.returncode == 0, err
    assert _xy(json.loads(out)) == pytest.approx((120.0, 0.0), abs=1e-3)
    assert _grbl(fw) == ("Idle", pytest.approx((120.0, 0.0), abs=1e-3))
    fw.fresh()


@pytest.mark.timeout(300)
def test_a_frozen_ser2net_bounds_the_stop_by_the_table_files_stop_total_s(fw, ser2net, tmp_path):
    """ser2net SIGSTOPped mid-move: the connection stays open and nothing answers. The command notices the
    silence within ``timeout_s`` (3 s here), then the whole stop (hold awaited, reset confirmed, state read
    back) ends within the table file's ``stop_total_s`` (6 s here; before, 3 + 30 + 3 s whatever the file
    said): exit 3, one line that says the budget ran out and to cut the power. Once ser2net runs again, the
    stop bytes it queued reach GRBL and the table is still, in GRBL's own word."""
    lab = init_workspace(tmp_path / "lab")
    table_yaml = lab / "drivers" / "table.yaml"
    table_yaml.write_text(table_yaml.read_text() + "stop_total_s: 6.0\n")
    fw.fresh()
    fw.to_machine_zero()
    p = subprocess.Popen([sys.executable, "-m", "labctl", "--lab", str(lab), "table", "move", "150", "0",
                          "--feed", "1200", "--port", ser2net.url("socket"), "--baud", "115200",
                          "--timeout", "3"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    frozen = False
    try:
        time.sleep(5.0)  # the command starts in ~2 s; the move runs ~30 s on the simulator's wall clock
        assert p.poll() is None, p.communicate()
        os.kill(ser2net.proc.pid, signal.SIGSTOP)
        frozen, t_frozen = True, time.monotonic()
        _, err = p.communicate(timeout=120)
        took = time.monotonic() - t_frozen
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        if frozen:
            os.kill(ser2net.proc.pid, signal.SIGCONT)
    lines = [x for x in err.splitlines() if x.strip()]
    assert p.returncode == 3 and len(lines) == 1, err
    assert "stop_total_s 6 s, ran out" in lines[0] and "cut its power" in lines[0], err
    assert took < 3.0 + 6.0 + 4.0, took  # detection + the stop's budget + start-up slack on a loaded machine
    print(f"frozen ser2net: the command exited {took:.1f} s after the SIGSTOP")
    # the queued '!' and 0x18 now reach GRBL; ser2net reads the pty until it has seen the client's close,
    # and a second reader meanwhile would lose replies to it
    time.sleep(3.0)
    deadline = time.monotonic() + 30
    while (state := _grbl(fw))[0] not in ("Idle", "Alarm", "Hold:0"):
        assert time.monotonic() < deadline, state
        time.sleep(0.2)
    time.sleep(1.0)
    assert _grbl(fw)[1] == pytest.approx(state[1], abs=1e-3) and state[1][0] < 150.0, state
    fw.fresh()


def _pty_speed(path: str) -> int:
    """The line rate ser2net set on the firmware's pty (termios output speed, as a ``termios.B…`` constant)."""
    import termios

    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        return termios.tcgetattr(fd)[5]
    finally:
        os.close(fd)


@pytest.mark.timeout(300)
@pytest.mark.parametrize("set_remote_baud", [False, True])
def test_rfc2217_switches_the_servers_rate_only_when_the_table_file_asks(fw, ser2net, set_remote_baud):
    """ser2net's connector runs the port at 115200 (stock GRBL 1.1h). A table opened at 9600 over RFC 2217
    leaves the port at 115200 unless ``set_remote_baud`` asks; read from the port's own termios while the
    connection is open. Either way the firmware answers (a pty has no real rate)."""
    import termios

    from labctl.drivers.grbl import GrblTable

    fw.fresh()
    table = GrblTable(ser2net.url("rfc2217"), 9600, timeout_s=float(TIMEOUT), reset_on_open=False,
                      set_remote_baud=set_remote_baud)
    table.open()
    try:
        assert table.status().state == "Idle"
        speed = _pty_speed(fw.path)
    finally:
        table.close()
    assert speed == (termios.B9600 if set_remote_baud else termios.B115200), speed
