"""The reference controller as an arm (dialect 1.3), out of process: ``labctl sim serve`` on ptys, talked
to by this file's own client (its own framing and checksum). Each refusal kind gets its code and nothing
moves; STATUS's joints, through a hand-written UR10e DH (tests/arm_dh.py, not labctl's arm model), put the
flange where STATUS and the commanded target say; a 1.2 session sees the 1.2 text."""

from __future__ import annotations

import json
import math
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import serial
from arm_dh import rotation_angle, rotvec_matrix, sample_mount, ur10e_fk

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="ptys and the served lab need Linux")


def _xor(body: str) -> str:
    x = 0
    for b in body.encode():
        x ^= b
    return f"{x:02X}"


class Client:
    """Requests one at a time; asynchronous reports are kept aside."""

    def __init__(self, path: str):
        self.port = serial.serial_for_url(path, baudrate=115200, timeout=0.05)
        self.seq = 0
        self.buf = b""
        self.reports: list[str] = []

    def line(self, timeout: float = 5.0) -> str:
        end = time.monotonic() + timeout
        while b"\n" not in self.buf:
            if time.monotonic() > end:
                raise AssertionError("no reply")
            self.buf += self.port.read(4096)
        raw, _, self.buf = self.buf.partition(b"\n")
        body, star, tail = raw.decode().rpartition("*")
        assert star and tail == _xor(body), raw
        return body

    def req(self, text: str) -> list[str]:
        self.seq = self.seq % 60000 + 1
        self.port.write(f"#{self.seq} {text}*{_xor(f'#{self.seq} {text}')}\n".encode())
        while True:
            got = self.line()
            if got.startswith("@"):
                self.reports.append(got)
                continue
            head, *rest = got.split()
            assert head == f"${self.seq}", got
            return rest

    def status(self) -> dict:
        f = self.req("STATUS")
        assert f[0] == "ok", f
        out = {"p": np.array([float(x) for x in f[1:4]]), "rv": np.array([float(x) for x in f[4:7]]),
               "moving": f[7] == "1", "fields": len(f) - 1}
        if len(f) == 18:
            out["q"] = np.radians([float(x) for x in f[12:18]])
        return out

    def wait(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.req("HB")
            time.sleep(0.1)

    def rest(self, timeout: float = 15.0) -> dict:
        end = time.monotonic() + timeout
        while True:
            st = self.status()
            if not st["moving"] or time.monotonic() > end:
                return st
            time.sleep(0.1)

    def seg(self, T: np.ndarray, duration: float, sid: int) -> list[str]:
        p, rv = T[:3, 3], _rotvec(T[:3, :3])
        nums = " ".join(f"{x:.6f}" for x in (*p, *rv))
        return self.req(f"SEG {sid} {nums} {duration:.6f}")

    def fly(self, T: np.ndarray, duration: float, sid: int) -> dict:
        f = self.seg(T, duration, sid)
        assert f[0] == "ok", f
        self.wait(float(f[2]) - float(f[1]) + 0.3)
        return self.rest()


def _rotvec(R: np.ndarray) -> np.ndarray:
    th = math.acos(max(-1.0, min(1.0, (float(np.trace(R)) - 1) / 2)))
    if th < 1e-12:
        return np.zeros(3)
    assert th < math.pi - 1e-6
    return np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2 * math.sin(th)) * th


def _pose(st: dict) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rotvec_matrix(st["rv"]), st["p"]
    return T


class Served:
    """``labctl sim serve`` of a lab as a subprocess; ``info`` its ready line."""

    def __init__(self, lab: Path, log: Path):
        self.log = log.open("w+")
        self.proc = subprocess.Popen([sys.executable, "-m", "labctl", "--lab", str(lab), "--json", "sim", "serve",
                                      "--fps", "1", "--baud", "115200"],
                                     stdout=subprocess.PIPE, stderr=self.log, text=True)
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=lambda: [lines.put(x) for x in self.proc.stdout], daemon=True).start()
        text, deadline = "", time.monotonic() + 90
        self.info = None
        while self.info is None:
            try:
                text += lines.get(timeout=max(0.1, deadline - time.monotonic()))
            except queue.Empty:
                self.stop()
                self.log.seek(0)
                raise AssertionError(f"sim serve did not become ready: {self.log.read()[-2000:]}") from None
            try:
                self.info = json.loads(text)
            except json.JSONDecodeError:
                continue

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=5)
        self.log.close()


def _lab(tmp: Path, **robot) -> Path:
    """A fresh sample lab (``labctl init``), its drivers/robot.yaml changed by ``robot``."""
    import yaml

    lab = tmp / "lab"
    subprocess.run([sys.executable, "-m", "labctl", "init", str(lab)], check=True, capture_output=True, timeout=120)
    path = lab / "drivers" / "robot.yaml"
    cfg = yaml.safe_load(path.read_text())
    cfg.update(robot)
    path.write_text(yaml.safe_dump(cfg))
    return lab


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("arm")
    s = Served(_lab(tmp), tmp / "serve.log")
    try:
        yield s.info
    finally:
        s.stop()


def _session(info, version: str = "1.3") -> Client:
    c = Client(info["robot"])
    hello = c.req(f"HELLO {version}")
    assert hello[0] == "ok", hello
    c.hello = hello
    c.req("STOP")
    c.rest()
    c.req("CLEAR")
    return c


def test_status_joints_are_the_pose_by_a_hand_written_dh(served):
    c = _session(served)
    assert c.hello[1:] == ["labctl-robot", "1.3", "queue=8", "profiles=quintic,ruckig", "arm=UR10e"]
    T_w_base = sample_mount()
    st = c.rest()
    assert st["fields"] == 17
    T0 = _pose(st)
    target = T0.copy()
    target[:3, 3] += [-40.0, 30.0, -25.0]
    f = c.seg(target, 2.0, 1)
    assert f[0] == "ok", f
    c.wait(0.9)
    mid = c.status()
    assert mid["moving"]
    c.wait(1.5)
    end = c.rest()
    for s in (st, mid, end):  # against the pose STATUS reports (four decimals)
        T = ur10e_fk(s["q"], T_w_base)
        assert np.linalg.norm(T[:3, 3] - s["p"]) < 0.1
        assert rotation_angle(T[:3, :3].T @ rotvec_matrix(s["rv"])) < 2e-4
    # at rest on the commanded target (six decimals): 1e-3 deg and 0.01 mm
    T = ur10e_fk(end["q"], T_w_base)
    assert np.linalg.norm(T[:3, 3] - target[:3, 3]) < 0.01
    assert math.degrees(rotation_angle(T[:3, :3].T @ target[:3, :3])) < 1e-3
    c.fly(T0, 2.0, 2)


def _refused(c: Client, T: np.ndarray, duration: float, sid: int, code: str) -> None:
    before = c.status()
    f = c.seg(T, duration, sid)
    after = c.status()
    assert f[0] == code, (f, code)
    assert not after["moving"] and np.allclose(after["p"], before["p"]) and np.allclose(after["q"], before["q"])


def test_each_refusal_kind_gets_its_code_before_moving(served):
    c = _session(served)
    T_w_base = sample_mount()
    st = c.rest()
    q0 = st["q"]
    T0 = ur10e_fk(q0, T_w_base)
    # E30: the wrist point (DH frame 5) on the base axis, inside the cylinder of radius d4 = 174.15 mm
    target = T0.copy()
    target[:3, 3] = T_w_base[:3, 3] + [0.0, 0.0, 180.7 + 400.0] + 116.55 * T0[:3, 2]
    _refused(c, target, 4.0, 10, "E30")
    # E31: the last joint turned by 170° at a time past its +360° limit
    turns = 0
    while True:
        q = q0.copy()
        q[5] += math.radians(170.0) * (turns + 1)
        if q[5] > math.radians(360.0):
            _refused(c, ur10e_fk(q, T_w_base), 3.0, 11, "E31")
            break
        c.fly(ur10e_fk(q, T_w_base), 3.0, 20 + turns)
        turns += 1
    for k in range(turns - 1, -1, -1):  # unwind
        q = q0.copy()
        q[5] += math.radians(170.0) * k
        c.fly(ur10e_fk(q, T_w_base), 3.0, 30 + k)
    assert np.allclose(c.rest()["q"], q0, atol=1e-3)
    # E34: a 1° flick of the last joint in 16 ms (at 95 % of wmax: ~2·10⁴ °/s² at the joint)
    q = q0.copy()
    q[5] += math.radians(1.0)
    _refused(c, ur10e_fk(q, T_w_base), 1.875 * 1.0 / (0.95 * 120.0), 12, "E34")
    # E32: from q5 = −5° to the pose of q5 = +5°, past the wrist singularity (margin |sin q5| 0.05)
    qa, qb = q0.copy(), q0.copy()
    qa[4], qb[4] = math.radians(-5.0), math.radians(5.0)
    c.fly(ur10e_fk(qa, T_w_base), 3.0, 13)
    _refused(c, ur10e_fk(qb, T_w_base), 1.0, 14, "E32")
    c.fly(T0, 3.0, 15)


def test_without_a_margin_passing_the_wrist_singularity_needs_a_configuration_change(tmp_path):
    s = Served(_lab(tmp_path, arm_wrist_margin=0.0), tmp_path / "serve.log")
    try:
        c = _session(s.info)
        T_w_base = sample_mount()
        q0 = c.rest()["q"]
        qa, qb = q0.copy(), q0.copy()
        qa[4], qb[4] = math.radians(-5.0), math.radians(5.0)
        c.fly(ur10e_fk(qa, T_w_base), 3.0, 1)
        _refused(c, ur10e_fk(qb, T_w_base), 1.0, 2, "E33")
    finally:
        s.stop()


def test_a_1_2_session_sees_the_1_2_text(served):
    c = _session(served, "1.2")
    want = (ROOT / "tests" / "data" / "robot" / "session_1_2.txt").read_text().splitlines()
    assert c.hello == want[0].split("*")[0].split()[1:]  # byte for byte: the 1.2 HELLO reply
    assert " ".join(c.req("LIMITS")) == want[1].split("*")[0].split(" ", 1)[1]
    assert c.status()["fields"] == 11
    c10 = _session(served, "1.0")
    assert c10.hello == ["ok", "labctl-robot", "1.0", "queue=8"]  # the 1.0 text: queue= last
    assert len(c10.req("LIMITS")) == 1 + 10
