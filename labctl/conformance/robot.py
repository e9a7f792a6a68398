"""The robot dialect's conformance suite (docs/protocols/robot.md, dialect 1.4), run over a serial port.

Written from the document, not from the reference controller: its own framing, its own checksum,
its own quintic (a 6×6 solve) and its own stop-ramp arithmetic (dense samples), so it can judge
the reference as well as a lab's bridge. Each rule is named as in the document; a rule yields
PASS, FAIL (with what was seen) or SKIP (with why it could not be run here).

The arm rules (1.3) judge a controller that names its arm (``arm=`` in HELLO) against that arm's
published kinematics, given to the suite as plain numbers (:class:`ArmKinematics`, standard DH written out
here by hand): the joints STATUS reports against the forward kinematics of the pose it reports, and one
segment per refusal the arm must make (E30–E34), built from the joints it reports.

Motion rules command real motion, near the home pose, at most a few hundred millimetres; some send
segments a conforming controller must refuse (a broken one would run them), so keep the arm's
own safety limits on. ``no_motion`` runs only framing and error-reply rules.
"""

from __future__ import annotations

import fnmatch
import math
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import cast

import numpy as np

from ..timebase import wire_time_s  # a leaf: the one wire-time formula, no labctl code to trust

VERSION_RE = re.compile(r"^\d+\.\d+$")
IDEMPOTENT = {"STATUS", "LIMITS", "HB", "CLEAR"}


class CannotTalk(Exception):
    """The port cannot be opened, or nothing answers HELLO."""


@dataclass
class Result:
    """One rule's outcome: its name as in docs/protocols/robot.md, PASS/FAIL/SKIP and what was seen."""

    rule: str
    status: str  # PASS, FAIL, SKIP
    detail: str = ""


def _xor(body: str) -> str:
    x = 0
    for ch in body.encode("ascii", "replace"):
        x ^= ch
    return f"{x:02X}"


def _num(x: float) -> str:
    text = f"{x:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


@dataclass
class Line:
    """One received line: host arrival time (s, monotonic), text without checksum, raw text, checksum verdict."""

    t: float  # host monotonic time of arrival
    text: str  # without checksum
    raw: str
    checksum_ok: bool


class Client:
    """A minimal client of the dialect: raw lines, sequence numbers, checksums checked on every line."""

    def __init__(self, port: str, baud: int, timeout_s: float = 1.0, serial_port=None):
        if serial_port is None:
            import serial

            try:
                serial_port = serial.serial_for_url(port, baudrate=baud, timeout=0)
            except (serial.SerialException, OSError, ValueError) as exc:
                raise CannotTalk(f"cannot open {port}: {exc}") from None
        self.port = serial_port
        self.baud = baud
        self.timeout_s = timeout_s
        self.seq = 0
        self.buf = bytearray()
        self.lines: list[Line] = []  # everything received
        self.pending: list[Line] = []  # not yet consumed
        self.latencies: list[float] = []

    def close(self) -> None:
        """Close the port; errors on closing are swallowed."""
        try:
            self.port.close()
        except Exception:  # noqa: BLE001 — closing a dead port must not hide the result
            pass

    def write(self, data: bytes) -> None:
        """Write raw bytes to the port and flush."""
        self.port.write(data)
        self.port.flush()

    def _pump(self, wait_s: float) -> None:
        deadline = time.monotonic() + wait_s
        while True:
            data = self.port.read(4096)
            if data:
                self.buf += data
                while b"\n" in self.buf:
                    raw, _, rest = bytes(self.buf).partition(b"\n")
                    self.buf = bytearray(rest)
                    text = raw.decode("ascii", "replace").replace("\r", "")
                    body, star, tail = text.rpartition("*")
                    ok = bool(star) and len(tail) == 2 and tail.upper() == _xor(body)
                    line = Line(time.monotonic(), body if star else text, text, ok)
                    self.lines.append(line)
                    self.pending.append(line)
                continue
            if time.monotonic() >= deadline:
                return
            time.sleep(0.002)

    def drain(self, wait_s: float = 0.0) -> list[Line]:
        """Lines received and not yet consumed, after reading for up to ``wait_s`` s."""
        self._pump(wait_s)
        out, self.pending = self.pending, []
        return out

    def next_seq(self) -> int:
        """The next request sequence number (1…65535, wrapping)."""
        self.seq = self.seq % 65535 + 1
        return self.seq

    def request(self, body: str, *, checksum: bool = True, raw_suffix: str = "", eol: str = "\n",
                seq: int | None = None, timeout_s: float | None = None) -> Line | None:
        """Send ``#<seq> body`` and return its ``$<seq>`` reply line (None on timeout)."""
        word = body.split()[0].upper() if body.split() else ""
        tries = 3 if word in IDEMPOTENT and seq is None else 1  # a lost query is simply asked again
        for _ in range(tries):
            seq_now = self.next_seq() if seq is None else seq
            line = f"#{seq_now} {body}"
            if checksum:
                line = f"{line}*{_xor(line)}"
            t_sent = time.monotonic()
            self.write((line + raw_suffix + eol).encode("ascii", "replace"))
            got = self.wait_reply(seq_now, t_sent, timeout_s, len(line) + 1)
            if got is not None:
                return got
        return None

    def wait_reply(self, seq: int, t_sent: float, timeout_s: float | None = None, sent_bytes: int = 0) -> Line | None:
        """The reply ``$<seq>`` to a request sent at ``t_sent`` (None on timeout); logs its latency beyond wire time."""
        deadline = t_sent + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            for i, ln in enumerate(self.pending):
                if ln.text.split(" ", 1)[0] == f"${seq}":
                    del self.pending[i]
                    wire = wire_time_s(sent_bytes + len(ln.raw) + 1, self.baud)
                    self.latencies.append(max(ln.t - t_sent - wire, 0.0))
                    return ln
            if time.monotonic() > deadline:
                return None
            self._pump(0.005)

    def asyncs(self, kind: str | None = None) -> list[Line]:
        """Asynchronous reports received so far (consumed from ``pending``)."""
        self._pump(0.0)
        got = [ln for ln in self.pending if ln.text.startswith("@") and (kind is None or ln.text[1:].startswith(kind))]
        self.pending = [ln for ln in self.pending if ln not in got]
        return got


def reply_fields(line: Line | None) -> tuple[str, list[str]]:
    """('ok', fields) or ('E05', [message words]) or ('none', [])."""
    if line is None:
        return "none", []
    parts = line.text.split()
    if len(parts) < 2:
        return "bad", parts
    return parts[1], parts[2:]


# --- the document's quintic and stop ramp, independently ------------------------------------------

def quintic(p0, v0, a0, p1, v1, a1, T) -> np.ndarray:
    """Coefficients (6, 3) in real time τ of the quintic meeting both states (a 6×6 solve)."""
    M = np.array([[1, 0, 0, 0, 0, 0], [0, 1, 0, 0, 0, 0], [0, 0, 2, 0, 0, 0],
                  [1, T, T**2, T**3, T**4, T**5], [0, 1, 2 * T, 3 * T**2, 4 * T**3, 5 * T**4],
                  [0, 0, 2, 6 * T, 12 * T**2, 20 * T**3]], dtype=float)
    rhs = np.array([p0, v0, a0, p1, v1, a1], dtype=float)
    return np.linalg.solve(M, rhs)


def sample(c: np.ndarray, T: float, n: int = 4001):
    """Positions, velocities, accelerations at n times over [0, T]."""
    tau = np.linspace(0.0, T, n)[:, None]
    k = np.arange(6)
    P = (tau**k) @ c
    V = (k * tau ** np.maximum(k - 1, 0)) @ c
    A = (k * (k - 1) * tau ** np.maximum(k - 2, 0)) @ c
    return tau[:, 0], P, V, A


@dataclass
class Limits:
    """The controller's LIMITS reply (§9): workspace box (mm), vmax (mm/s), amax (mm/s²), wmax (rad/s),
    watchdog (s), stop deceleration a_stop (mm/s²) and home pose (x y z mm, rotation vector rad).
    """

    box_min: np.ndarray
    box_max: np.ndarray
    v_max: float
    a_max: float
    w_max: float  # rad/s
    watchdog_s: float
    a_stop: float
    home: np.ndarray | None = None  # x y z rx ry rz
    j_max: float | None = None  # mm/s³, dialect 1.2 (the ruckig profile)


def _rotvec_matrix(rv) -> np.ndarray:
    """Rodrigues' formula: rotation vector (rad) to matrix."""
    rv = np.asarray(rv, float)
    th = float(np.linalg.norm(rv))
    if th < 1e-15:
        return np.eye(3)
    k = rv / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * (K @ K)


def _matrix_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix to rotation vector (rad), angle in [0, π] (the eigenvector near π)."""
    c = max(-1.0, min(1.0, (float(np.trace(R)) - 1) / 2))
    th = math.acos(c)
    if th < 1e-9:
        return np.zeros(3)
    if th > math.pi - 1e-6:
        w, v = np.linalg.eigh((R + R.T) / 2)
        axis = v[:, int(np.argmax(w))]
        return axis * th
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2 * math.sin(th))
    return axis * th


def _rpy_matrix(rpy_rad) -> np.ndarray:
    """Rz(yaw)·Ry(pitch)·Rx(roll)."""
    r, p, y = rpy_rad
    cx, sx, cy, sy, cz, sz = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]]) @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]]) \
        @ np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])


@dataclass
class ArmKinematics:
    """An arm's published kinematics as the suite uses them: standard DH (``d``, ``a`` mm; ``alpha``,
    ``offset`` rad), joint limits (rad), the base in the world ``T_w_base`` and labctl's flange in the arm's
    flange ``T_flange_tool`` (4×4, mm). The controller's poses are ``T_w_F`` = T_w_base·DH(q)·T_flange_tool."""

    name: str
    d: np.ndarray
    a: np.ndarray
    alpha: np.ndarray
    offset: np.ndarray
    q_min: np.ndarray
    q_max: np.ndarray
    T_w_base: np.ndarray
    T_flange_tool: np.ndarray

    @classmethod
    def from_mapping(cls, m: dict) -> ArmKinematics:
        """From an arm file's keys (``drivers/arms/*.yaml``: mm and degrees)."""
        r = lambda key, default=(0.0,) * 6: np.radians(np.asarray(m.get(key, default), float))  # noqa: E731

        def pose(xyz, rpy) -> np.ndarray:
            T = np.eye(4)
            T[:3, :3] = _rpy_matrix(np.radians(np.asarray(m.get(rpy, (0.0, 0.0, 0.0)), float)))
            T[:3, 3] = np.asarray(m.get(xyz, (0.0, 0.0, 0.0)), float)
            return T

        return cls(str(m["name"]), np.asarray(m["dh_d_mm"], float), np.asarray(m["dh_a_mm"], float),
                   r("dh_alpha_deg"), r("dh_offset_deg"), r("joint_min_deg"), r("joint_max_deg"),
                   pose("base_xyz_mm", "base_rpy_deg"), pose("tool_xyz_mm", "tool_rpy_deg"))

    def fk(self, q) -> np.ndarray:
        """``T_w_F`` at joints ``q`` (rad): the product of Rz(θ+offset)·Tz(d)·Tx(a)·Rx(α)."""
        T = self.T_w_base.copy()
        for th, d, a, al in zip(np.asarray(q, float) + self.offset, self.d, self.a, self.alpha):
            ct, st, ca, sa = math.cos(th), math.sin(th), math.cos(al), math.sin(al)
            T = T @ np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d],
                              [0, 0, 0, 1.0]])
        return T @ self.T_flange_tool


@dataclass
class Suite:
    """The suite's state: client, rule filter, results, and what HELLO and LIMITS reported."""

    client: Client
    no_motion: bool = False
    only: list[str] = field(default_factory=list)
    log: Callable[[Result], None] | None = None
    results: list[Result] = field(default_factory=list)
    version: str = "1.0"
    queue: int = 8
    profiles: tuple[str, ...] = ("quintic",)
    limits: Limits | None = None
    next_id: int = 100
    arm: ArmKinematics | None = None  # the arm's published kinematics (the 1.3 arm rules need them)
    arm_name: str | None = None  # what HELLO names (arm=, 1.3)

    @property
    def lim(self) -> Limits:
        """The LIMITS read by ``hello``; only motion rules use them, and ``hello`` refuses a motion run without."""
        if self.limits is None:
            raise AttributeError("the controller's LIMITS were not read")
        return self.limits

    # --- helpers --------------------------------------------------------------------------
    def want(self, rule: str) -> bool:
        """True if ``rule`` matches one of the ``only`` glob patterns (or there are none)."""
        return not self.only or any(fnmatch.fnmatch(rule, pat) for pat in self.only)

    def record(self, rule: str, ok: bool | None, detail: str = "") -> None:
        """Append the rule's result (None: SKIP, True: PASS, False: FAIL) and pass it to ``log``."""
        status = "SKIP" if ok is None else ("PASS" if ok else "FAIL")
        res = Result(rule, status, detail)
        self.results.append(res)
        if self.log is not None:
            self.log(res)

    def req(self, body: str, **kw) -> tuple[str, list[str]]:
        """Send ``body`` and return the reply as ``(code, fields)`` (see :func:`reply_fields`)."""
        return reply_fields(self.client.request(body, **kw))

    @property
    def v11(self) -> bool:
        """True for a dialect 1.1 (or later) session."""
        return self.version != "1.0"

    @property
    def ruckig(self) -> bool:
        """True for a dialect 1.2 (or later) session whose controller lists the ``ruckig`` profile."""
        return self.version in ("1.2", "1.3", "1.4") and "ruckig" in self.profiles

    def status(self) -> dict:
        """STATUS parsed: ``p`` (mm), rotation vector ``rv`` (rad), moving, segment id, queued, ``t`` (s), fault."""
        code, f = self.req("STATUS")
        if code != "ok" or len(f) < 11:
            raise AssertionError(f"STATUS answered {code} {' '.join(f)}")
        nums = [float(x) for x in f[:6]]
        out = {"p": np.array(nums[:3]), "rv": np.array(nums[3:6]), "moving": f[6] == "1", "seg_id": int(f[7]),
               "queued": int(f[8]), "t": float(f[9]), "fault": f[10]}
        if self.arm_name is not None and len(f) >= 17:  # 1.3: the six joints, degrees
            out["q"] = np.radians([float(x) for x in f[11:17]])
        return out

    def seg(self, p, rv, T, v=None, cmd="SEG", seg_id=None) -> tuple[str, list[str], int]:
        """SEG (or ``cmd``) to pose (``p`` mm, ``rv`` rad) in ``T`` s, end velocity ``v`` (mm/s): (code, fields, id)."""
        sid = self.new_id() if seg_id is None else seg_id
        args = [str(sid), *map(_num, p), *map(_num, rv), _num(T)]
        if v is not None:
            args += [*map(_num, v), "0", "0", "0"]
        code, f = self.req(f"{cmd} {' '.join(args)}")
        return code, f, sid

    def new_id(self) -> int:
        """A fresh segment id (wrapping below 60000)."""
        self.next_id = self.next_id % 60000 + 1
        return self.next_id

    def wait(self, seconds: float) -> None:
        """Wait while feeding the watchdog (a STATUS every watchdog_s/4)."""
        end = time.monotonic() + seconds
        step = (self.limits.watchdog_s / 4) if self.limits else 0.1
        while time.monotonic() < end:
            self.req("HB")
            self.client._pump(min(step, max(end - time.monotonic(), 0.0)))

    def wait_rest(self, timeout_s: float = 10.0) -> dict:
        """Poll STATUS until the arm is at rest or ``timeout_s`` passes; returns the last status."""
        end = time.monotonic() + timeout_s
        while True:
            st = self.status()
            if not st["moving"] or time.monotonic() > end:
                return st
            self.client._pump(min(0.05, self.lim.watchdog_s / 4))

    def _arrival(self, sid: int, p1, took_s: float, expect_s: float, mid_err: float, expected: str,
                 path: str) -> tuple[bool, float, list[str]]:
        """After a timed segment ``sid`` to ``p1`` (mm): wait for its @DONE and for rest, and list what is
        wrong: the controller's duration ``took_s`` against ``expect_s`` (s), no @DONE, resting off the
        target (> 0.01 mm), or ``mid_err`` (mm) off ``path`` on the way (> 0.05 mm)."""
        done = self.wait_done(sid, expect_s + 2.0)
        end_err = float(np.linalg.norm(self.wait_rest()["p"] - p1))
        problems = []
        if abs(took_s - expect_s) > 2e-4:
            problems.append(f"t1 − t0 = {took_s:.4f} s, {expected}")
        if not done:
            problems.append(f"no @DONE {sid}")
        if end_err > 0.01:
            problems.append(f"rests {end_err:.4f} mm from the target")
        if mid_err > 0.05:
            problems.append(f"{mid_err:.3f} mm off {path} on the way")
        return done, end_err, problems

    def wait_done(self, seg_id: int, timeout_s: float) -> bool:
        """True once ``@DONE seg_id`` arrives within ``timeout_s`` (s); feeds the watchdog meanwhile."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            self.client._pump(0.0)
            for ln in self.client.lines:
                if ln.text.split() == ["@DONE", str(seg_id)]:
                    return True
            self.req("HB")
            self.client._pump(min(0.05, self.lim.watchdog_s / 4))
        return False

    def done_seen(self, seg_id: int) -> bool:
        """True if ``@DONE seg_id`` has been received."""
        return any(ln.text.split() == ["@DONE", str(seg_id)] for ln in self.client.lines)

    def recover(self) -> None:
        """STOP, wait for rest, CLEAR: a known state after a rule, whatever it left behind."""
        self.req("STOP")
        self.wait_rest()
        self.req("CLEAR")

    # --- run ------------------------------------------------------------------------------
    def run(self) -> list[Result]:
        """HELLO, every selected rule (a crash is a FAIL), then the checksum and reply-timing rules; the results."""
        self.hello()
        for name, fn in self.rules():
            if not self.want(name):
                continue
            try:
                fn()
            except Exception as exc:  # noqa: BLE001 — a rule that crashes is a FAIL with the reason
                self.record(name, False, f"{type(exc).__name__}: {exc}")
                if not self.no_motion:
                    try:
                        self.recover()
                    except Exception:  # noqa: BLE001
                        pass
        if self.want("checksum.output"):
            bad = [ln.raw for ln in self.client.lines if not ln.checksum_ok]
            self.record("checksum.output", not bad,
                        f"{len(self.client.lines)} lines, all with a correct *HH" if not bad
                        else f"{len(bad)} of {len(self.client.lines)} lines without a correct *HH, e.g. {bad[0]!r}")
        if self.want("timing.reply") and self.client.latencies:
            lat = sorted(self.client.latencies)
            med = lat[len(lat) // 2]
            self.record("timing.reply", med <= 0.05,
                        f"median {med * 1000:.1f} ms, max {lat[-1] * 1000:.1f} ms over {len(lat)} replies "
                        "(beyond transmission time)")
        return self.results

    def rules(self) -> Iterator[tuple[str, Callable[[], None]]]:
        """(rule name, method) pairs in run order; motion rules only without ``no_motion``."""
        yield from [
            ("hello.reply", self.r_hello),
            ("status.format", self.r_status_format),
            ("limits.format", self.r_limits_format),
            ("checksum.optional", self.r_checksum_optional),
            ("checksum.reject", self.r_checksum_reject),
            ("framing.leniency", self.r_leniency),
            ("framing.line_length", self.r_line_length),
            ("errors.unknown", self.r_unknown),
            ("errors.arguments", self.r_arguments),
            ("errors.malformed", self.r_malformed),
        ]
        if self.no_motion:
            return
        yield from [
            ("home.arrives", self.r_home),
            ("timing.arrival", self.r_arrival),
            ("limits.speed", self.r_speed),
            ("limits.acceleration", self.r_accel),
            ("limits.angular", self.r_angular),
            ("limits.box", self.r_box),
            ("limits.path", self.r_path),
            ("stop.refuse_outward_end", self.r_refuse_outward),
            ("stop.ramp", self.r_stop_ramp),
            ("stop.latch", self.r_latch),
            ("done.not_after_cut", self.r_cut),
            ("queue.full", self.r_queue),
            ("watchdog.fed", self.r_watchdog_fed),
            ("watchdog.trips", self.r_watchdog_trips),
            ("ruckig.arrival", self.r_ruckig_arrival),
            ("ruckig.splice", self.r_ruckig_splice),
            ("ruckig.limits", self.r_ruckig_limits),
            ("set.defaults", self.r_set_defaults),
            ("hold.go", self.r_hold_go),
            ("arm.joints", self.r_arm_joints),
            ("arm.reach", self.r_arm_reach),
            ("arm.joint_limit", self.r_arm_joint_limit),
            ("arm.singularity", self.r_arm_singularity),
            ("arm.joint_rate", self.r_arm_joint_rate),
        ]

    def hello(self) -> None:
        """Open the session (HELLO 1.2, else HELLO), read queue size, profiles and LIMITS; CannotTalk if silent."""
        self.client.drain(0.05)
        line = self.client.request("HELLO 1.4")
        if line is None:
            line = self.client.request("HELLO")
        if line is None:
            raise CannotTalk("no reply to HELLO")
        code, f = reply_fields(line)
        if code == "E02":
            code, f = self.req("HELLO")
        self.hello_fields = (code, f)
        if code == "ok" and len(f) >= 2 and VERSION_RE.match(f[1]):
            got = tuple(map(int, f[1].split(".")))
            self.version = ("1.4" if got >= (1, 4) else "1.3" if got >= (1, 3) else "1.2" if got >= (1, 2)
                            else "1.1" if got >= (1, 1) else "1.0")
        for item in f[2:]:
            key, _, value = item.partition("=")
            if key == "queue" and value.isdigit():
                self.queue = int(value)
            elif key == "arm" and value and self.version in ("1.3", "1.4"):
                self.arm_name = value
            elif key == "profiles":
                self.profiles = tuple(value.lower().split(","))
        code, lf = self.req("LIMITS")
        if code == "ok" and len(lf) >= 10:
            x = [float(v) for v in lf]
            self.limits = Limits(np.array(x[0:3]), np.array(x[3:6]), x[6], x[7], math.radians(x[8]), x[9],
                                 x[10] if len(x) >= 18 else x[7] / math.sqrt(3.0),
                                 np.array(x[12:18]) if len(x) >= 18 else None, x[18] if len(x) >= 19 else None)
        if self.limits is None and not self.no_motion:
            raise CannotTalk(f"no usable LIMITS reply ({code} {' '.join(lf)}): motion rules need it")
        if not self.no_motion:
            st = self.status()
            if st["fault"] != "none":
                self.req("CLEAR")

    # --- framing and errors (no motion) -----------------------------------------------------
    def r_hello(self) -> None:
        """hello.reply: HELLO answers ``ok <name> <version>``; a 1.1, 1.2 or 1.3 session lists queue=N and the
        quintic profile (``ruckig`` from 1.2 on), ``arm=`` only in a 1.3 session; a 1.0 reply ends at queue=."""
        code, f = self.hello_fields
        problems = []
        if code != "ok" or len(f) < 2 or not VERSION_RE.match(f[1]):
            problems.append(f"reply {code} {' '.join(f)!r} is not 'ok <name> <version> …'")
        if self.v11:
            if f[1] not in ("1.1", "1.2", "1.3", "1.4"):
                problems.append(f"session version {f[1]} after HELLO 1.4")
            if "ruckig" in self.profiles and f[1] not in ("1.2", "1.3", "1.4"):
                problems.append(f"ruckig listed in a {f[1]} session")
            if any(x.startswith("arm=") for x in f) and f[1] not in ("1.3", "1.4"):
                problems.append(f"arm= listed in a {f[1]} session")
        elif code == "ok" and any(x.startswith("profiles=") for x in f):
            problems.append("profiles= in a 1.0 reply (the 1.0 text ends at queue=)")
            if not any(x.startswith("queue=") for x in f) or "quintic" not in self.profiles:
                problems.append("no queue=N or profiles=… listing quintic")
        self.record("hello.reply", not problems, "; ".join(problems) or f"{' '.join(f)}")

    def r_status_format(self) -> None:
        """status.format: STATUS has 11 fields of the documented types (17 in a 1.3 session with an arm:
        the six joints, degrees)."""
        code, f = self.req("STATUS")
        want = 17 if self.arm_name is not None else 11
        ok = code == "ok" and len(f) == want and f[6] in ("0", "1") and f[7].isdigit() and f[8].isdigit() \
            and f[10] in ("none", "stopped", "watchdog")
        if ok:
            try:
                [float(x) for x in f[:6] + f[9:10] + f[11:]]
            except ValueError:
                ok = False
        self.record("status.format", ok, " ".join(f))

    def r_limits_format(self) -> None:
        """limits.format: LIMITS has 10 (1.0), 18 (1.1) or 19 (1.2) fields, a non-empty box and a_stop ≥ amax/√3."""
        code, f = self.req("LIMITS")
        want = {"1.0": 10, "1.1": 18}.get(self.version, 19)
        ok = code == "ok" and len(f) == want and self.limits is not None \
            and bool(np.all(self.limits.box_min < self.limits.box_max))
        if ok and self.v11:
            ok = self.lim.a_stop >= self.lim.a_max / math.sqrt(3.0) * (1 - 1e-6)
        self.record("limits.format", ok, f"{len(f)} fields (want {want}); a_stop ≥ amax/√3" if ok else " ".join(f))

    def r_checksum_optional(self) -> None:
        """checksum.optional: a request without ``*HH`` is accepted."""
        code, _ = self.req("HB", checksum=False)
        self.record("checksum.optional", code == "ok", f"HB without *HH → {code}")

    def r_checksum_reject(self) -> None:
        """checksum.reject: a STOP with a wrong checksum is answered E05 and not executed."""
        seq = self.client.next_seq()
        line = f"#{seq} STOP"
        bad = "00" if _xor(line) != "00" else "01"
        t = time.monotonic()
        self.client.write(f"{line}*{bad}\n".encode())
        reply = self.client.wait_reply(seq, t)
        got, _ = reply_fields(reply)
        if reply is None:
            errs = [ln for ln in self.client.asyncs("ERR") if ln.text.split()[1:2] == ["E05"]]
            got = "@ERR E05" if errs else "nothing"
        problems = [] if got in ("E05", "@ERR E05") else [f"STOP with a wrong checksum → {got}"]
        if self.v11:
            st = self.status()
            if st["fault"] != "none":
                problems.append(f"it was executed (fault {st['fault']})")
                self.req("CLEAR")
        self.record("checksum.reject", not problems, "; ".join(problems) or "answered E05, not executed")

    def r_leniency(self) -> None:
        """framing.leniency: lower case, extra blanks, CR LF and a lower-case checksum are accepted."""
        checks = {
            "lower-case command": self.req("hb")[0],
            "tabs and double spaces": self.req("\t STATUS  ")[0],
            "\\r\\n line end": self.req("HB", eol="\r\n")[0],
        }
        seq = self.client.next_seq()
        line = f"#{seq} HB"
        t = time.monotonic()
        self.client.write(f"  {line}*{_xor(line).lower()}\n".encode())
        checks["leading blanks, lower-case checksum"] = reply_fields(self.client.wait_reply(seq, t))[0]
        bad = {k: v for k, v in checks.items() if v != "ok"}
        self.record("framing.leniency", not bad, ", ".join(f"{k} → {v}" for k, v in bad.items()) or "all accepted")

    def r_line_length(self) -> None:
        """framing.line_length: a 240-byte line is accepted; a 241-byte one gives @ERR E04 and no reply."""
        seq = self.client.next_seq()
        head = f"#{seq} HB"
        pad = 240 - len(head) - 3
        line = head + " " * pad
        line = f"{line}*{_xor(line)}"
        assert len(line) == 240
        t = time.monotonic()
        self.client.write((line + "\n").encode())
        at_limit = reply_fields(self.client.wait_reply(seq, t))[0]
        seq2 = self.client.next_seq()
        head = f"#{seq2} HB"
        line = head + " " * (241 - len(head) - 3)
        line = f"{line}*{_xor(line)}"
        t = time.monotonic()
        self.client.write((line + "\n").encode())
        over = self.client.wait_reply(seq2, t, timeout_s=0.5)
        errs = [ln for ln in self.client.asyncs("ERR") if ln.text.split()[1:2] == ["E04"]]
        ok = at_limit == "ok" and over is None and bool(errs)
        self.record("framing.line_length", ok,
                    f"240 bytes → {at_limit}; 241 bytes → {reply_fields(over)[0] if over else ''}"
                    f"{' @ERR E04' if errs else ' no @ERR E04'}")

    def r_unknown(self) -> None:
        """errors.unknown: an unknown command is answered E01."""
        code, _ = self.req("FLY")
        self.record("errors.unknown", code == "E01", f"FLY → {code}")

    def r_arguments(self) -> None:
        """errors.arguments: wrong argument counts, NaN, overflow and bad ids are answered E02 and not executed."""
        st = self.status()
        here = [*map(_num, st["p"]), *map(_num, st["rv"])]
        cases = ["STATUS 1", "HB 1", "LIMITS x", "CLEAR 1", "HELLO 1.1 x", "HELLO one", "SEG 1 2 3",
                 f"SEG 5 {' '.join(here)} nan", f"SEG 5 {' '.join(here)} 1e400", f"SEG -5 {' '.join(here)} 5",
                 f"SEG 5.5 {' '.join(here)} 5", f"SEG 5 {' '.join(here[:5])} x 5"]
        if self.v11:
            cases.append(f"SEG 0 {' '.join(here)} 5")
        bad = {}
        for c in cases:
            code, _ = self.req(c)
            if code != "E02":
                bad[c.split(" ", 1)[0] + (" " + c.split(" ", 2)[1] if " " in c else "")] = code
                if code == "ok":
                    self.req("STOP")
                    self.req("CLEAR")
        self.record("errors.arguments", not bad, ", ".join(f"{k!r} → {v}" for k, v in bad.items())
                    or f"{len(cases)} bad requests → E02")

    def r_malformed(self) -> None:
        """errors.malformed: lines without a valid ``#<seq>`` give @ERR E03."""
        got = []
        for text in ("hello", "#abc HB", "#70000 HB"):
            self.client.write((text + "\n").encode())
            self.client._pump(0.2)
            errs = [ln for ln in self.client.asyncs("ERR") if ln.text.split()[1:2] == ["E03"]]
            if not errs:
                got.append(text)
        self.record("errors.malformed", not got, f"no @ERR E03 for {got}" if got else "3 malformed lines → @ERR E03")

    # --- motion -------------------------------------------------------------------------------
    def _room(self, p, nearest_over: float | None = None) -> tuple[int, float, float]:
        """(axis, direction ±1, free mm) of the axis with the most room from p — or, with
        ``nearest_over``, the nearest wall at least that far."""
        L = self.lim
        options = [(ax, sgn, room) for ax in range(3)
                   for sgn, room in ((1.0, L.box_max[ax] - p[ax]), (-1.0, p[ax] - L.box_min[ax]))]
        if nearest_over is not None:
            far_enough = [o for o in options if o[2] >= nearest_over]
            if far_enough:
                return min(far_enough, key=lambda o: o[2])
        return max(options, key=lambda o: o[2])

    def _here(self):
        st = self.status()
        return st["p"], st["rv"]

    def r_home(self) -> None:
        """home.arrives: HOME runs as segment 0, takes at least 1 s, sends @DONE 0 and rests at LIMITS' home."""
        code, f = self.req("HOME")
        if code != "ok":
            self.record("home.arrives", False, f"HOME → {code}")
            return
        t0, t1 = float(f[0]), float(f[1])
        ok = self.wait_done(0, t1 - t0 + 3.0)
        st = self.wait_rest()
        problems = [] if ok else ["no @DONE 0"]
        if self.lim.home is not None:
            err = float(np.linalg.norm(st["p"] - self.lim.home[:3]))
            if err > 0.05:
                problems.append(f"rests {err:.3f} mm from LIMITS' home")
        if t1 - t0 < 1.0 - 1e-4:
            problems.append(f"duration {t1 - t0:.3f} s < 1 s")
        self.record("home.arrives", not problems, "; ".join(problems) or f"home in {t1 - t0:.3f} s, @DONE 0")

    def r_arrival(self) -> None:
        """timing.arrival, done.sent: a rest-to-rest SEG follows the quintic, ends on target in T s and sends @DONE."""
        p0, rv = self._here()
        ax, sgn, room = self._room(p0)
        D = min(60.0, room / 4)
        p1 = p0.copy()
        p1[ax] += sgn * D
        T = max(0.8, 2.5 * 1.875 * D / self.lim.v_max)
        code, f, sid = self.seg(p1, rv, T)
        if code != "ok":
            self.record("timing.arrival", False, f"SEG of {D:.0f} mm in {T:.2f} s → {code}")
            return
        t0, t1 = float(f[0]), float(f[1])
        c = quintic(p0, np.zeros(3), np.zeros(3), p1, np.zeros(3), np.zeros(3), t1 - t0)
        mid_err = 0.0
        for _ in range(3):  # on the way: the document's quintic, to the 4 decimals of t
            self.client._pump(T / 5)
            st = self.status()
            tau = st["t"] - t0
            if 0 < tau < T:
                want = (tau ** np.arange(6)) @ c
                speed = float(np.linalg.norm((np.arange(6) * tau ** np.maximum(np.arange(6) - 1, 0)) @ c))
                mid_err = max(mid_err, float(np.linalg.norm(st["p"] - want)) - speed * 5e-5)
        done, end_err, problems = self._arrival(sid, p1, t1 - t0, T, mid_err, f"asked {T:.4f} s", "the quintic")
        self.record("done.sent", done, f"@DONE {sid} {'at' if done else 'missing after'} the segment's end")
        self.record("timing.arrival", not problems, "; ".join(problems)
                    or f"{D:.0f} mm in {T:.3f} s: on the quintic to {max(mid_err, 0):.4f} mm, target to "
                       f"{end_err:.4f} mm, @DONE")

    def _expect_refusal(self, rule: str, want: str, p1, rv1, T, v=None, why: str = "") -> None:
        code, _, _ = self.seg(p1, rv1, T, v)
        if code == "ok":
            st = self.wait_rest(T + 5.0)
            outside = bool(np.any(st["p"] < self.lim.box_min - 1e-3) or np.any(st["p"] > self.lim.box_max + 1e-3))
            self.record(rule, False, f"{why}: accepted (want {want}); came to rest at {np.round(st['p'], 2).tolist()}"
                        + (" OUTSIDE the box" if outside else ""))
            self.recover()
            return
        self.record(rule, code == want, f"{why} → {code}")

    def r_speed(self) -> None:
        """limits.speed: a rest-to-rest segment peaking at 1.1·vmax is refused with E12."""
        p0, rv = self._here()
        ax, sgn, room = self._room(p0)
        T = 3.6 * self.lim.v_max / self.lim.a_max
        D = 1.1 * self.lim.v_max * T / 1.875  # peak speed 1.1·vmax, peak acceleration 0.93·amax
        if D > room - 5:
            self.record("limits.speed", None, f"needs {D:.0f} mm of room, has {room:.0f}")
            return
        p1 = p0.copy()
        p1[ax] += sgn * D
        self._expect_refusal("limits.speed", "E12", p1, rv, T, why=f"rest-to-rest {D:.0f} mm in {T:.2f} s (1.1·vmax)")

    def r_accel(self) -> None:
        """limits.acceleration: a segment peaking at 1.2·amax is refused with E13."""
        p0, rv = self._here()
        ax, sgn, _ = self._room(p0)
        T = 0.2
        D = 1.2 * self.lim.a_max * T * T / 5.7735
        if 1.875 * D / T > 0.9 * self.lim.v_max:
            T = 0.9 * self.lim.v_max * 5.7735 / (1.875 * 1.2 * self.lim.a_max)
            D = 1.2 * self.lim.a_max * T * T / 5.7735
        p1 = p0.copy()
        p1[ax] += sgn * D
        self._expect_refusal("limits.acceleration", "E13", p1, rv, T, why=f"{D:.1f} mm in {T:.3f} s (1.2·amax)")

    def r_angular(self) -> None:
        """limits.angular: a rotation peaking at 1.2·wmax is refused with E14."""
        p0, rv = self._here()
        T = 0.5
        theta = 1.2 * self.lim.w_max * T / 1.875
        from scipy.spatial.transform import Rotation

        R = Rotation.from_rotvec(rv) * Rotation.from_rotvec([0, 0, theta])  # about the flange z
        self._expect_refusal("limits.angular", "E14", p0, R.as_rotvec(), T,
                             why=f"{math.degrees(theta):.0f}° in {T} s (1.2·wmax)")

    def r_box(self) -> None:
        """limits.box: a target 20 mm outside the workspace box is refused with E10."""
        p0, rv = self._here()
        ax, sgn, room = self._room(p0)
        p1 = p0.copy()
        p1[ax] += sgn * (room + 20.0)
        T = max(4.0, 3 * 1.875 * (room + 20) / self.lim.v_max)
        self._expect_refusal("limits.box", "E10", p1, rv, T, why=f"target 20 mm outside on axis {'xyz'[ax]}")

    def _candidates(self, p0, ax, sgn, wall_gap, v_end, Ts):
        for T in Ts:
            p1 = p0.copy()
            p1[ax] = (self.lim.box_max[ax] if sgn > 0 else self.lim.box_min[ax]) - sgn * wall_gap
            v1 = np.zeros(3)
            v1[ax] = v_end
            c = quintic(p0, np.zeros(3), np.zeros(3), p1, v1, np.zeros(3), T)
            _, P, V, A = sample(c, T)
            if np.linalg.norm(V, axis=1).max() < 0.8 * self.lim.v_max and \
                    np.linalg.norm(A, axis=1).max() < 0.8 * self.lim.a_max:
                yield T, p1, v1, P, V

    def r_path(self) -> None:
        """Both ends inside, the path overshoots the wall in between (a 81-sample check may miss a
        narrow one; any exact check does not): here by 2–10 mm."""
        p0, rv = self._here()
        ax, sgn, room = self._room(p0, nearest_over=120.0)
        wall = self.lim.box_max[ax] if sgn > 0 else self.lim.box_min[ax]
        for u in (40.0, 60.0, 90.0, 130.0):
            for T, p1, v1, P, _V in self._candidates(p0, ax, sgn, 30.0, -sgn * u, np.geomspace(1.0, 20.0, 60)):
                over = float(np.max(sgn * (P[:, ax] - wall)))
                rest = p1[ax] + v1[ax] * abs(v1[ax]) / (2 * self.lim.a_stop)
                if 2.0 < over < 10.0 and sgn * (rest - wall) < 0:
                    self._expect_refusal("limits.path", "E10", p1, rv, T, v1,
                                         why=f"ends 30 mm inside moving inwards, path {over:.1f} mm outside")
                    return
        self.record("limits.path", None, "no overshooting segment found from here within 0.8·limits")

    def r_refuse_outward(self) -> None:
        """Path inside, end 5 mm from the wall moving out at a speed that needs ≥ 15 mm to stop."""
        p0, rv = self._here()
        ax, sgn, _ = self._room(p0)
        u = math.sqrt(2 * self.lim.a_stop * 20.0)  # 20 mm to brake, 5 mm of room
        wall = self.lim.box_max[ax] if sgn > 0 else self.lim.box_min[ax]
        for T, p1, v1, P, _V in self._candidates(p0, ax, sgn, 5.0, sgn * u, np.linspace(0.8, 8.0, 37)):
            if float(np.max(sgn * (P[:, ax] - wall))) < -1.0:  # the path itself stays inside
                self._expect_refusal("stop.refuse_outward_end", "E10", p1, rv, T, v1,
                                     why=f"ends 5 mm from the wall at {u:.0f} mm/s outwards (stops 15 mm outside)")
                return
        self.record("stop.refuse_outward_end", None, "no such segment within 0.8·limits from here")

    def _run_and_stop(self, frac: float = 0.5):
        """A rest-to-rest move along the roomiest axis; STOP near its peak speed. Returns what was seen."""
        p0, rv = self._here()
        ax, sgn, room = self._room(p0)
        D = min(0.45 * room, 200.0)
        # at half the limits the path never decelerates harder than a_stop (≥ amax/√3), so the rest
        # point p + v|v|/(2 a_stop) only grows along the move: a later STOP never rests shorter
        T = max(1.875 * D / (0.5 * self.lim.v_max), math.sqrt(5.7735 * D / (0.5 * self.lim.a_max)))
        p1 = p0.copy()
        p1[ax] += sgn * D
        code, f, sid = self.seg(p1, rv, T)
        if code != "ok":
            raise AssertionError(f"a {D:.0f} mm move in {T:.2f} s was refused ({code})")
        t0 = float(f[0])
        c = quintic(p0, np.zeros(3), np.zeros(3), p1, np.zeros(3), np.zeros(3), T)
        self.wait(frac * T - 0.05)
        before = self.status()
        code, _ = self.req("STOP")
        after = self.status()
        rest = self.wait_rest()
        return c, t0, T, before, after, rest, code, sid

    def r_stop_ramp(self) -> None:
        """stop.ramp: STOP mid-move brakes at a_stop (§6): rests no further than allowed, inside the box, no @DONE."""
        c, t0, T, before, after, rest, code, sid = self._run_and_stop()
        if code != "ok":
            self.record("stop.ramp", False, f"STOP → {code}")
            return
        # the STOP ran at some controller time t_s ∈ [before, after]; stopped at τ an axis rests at
        # e(τ) = p + v|v|/(2 a_stop) (§6), which grows along this move: it may rest short of
        # e(after) (braking harder is allowed) but not beyond it, nor before where it was at `before`
        k = np.arange(6)
        tau = np.linspace(max(before["t"] - t0 - 1e-4, 0), min(after["t"] - t0 + 1e-4, T), 800)
        P = (tau[:, None] ** k) @ c
        V = (k * tau[:, None] ** np.maximum(k - 1, 0)) @ c
        E = P + V * np.abs(V) / (2 * self.lim.a_stop)
        ax = int(np.argmax(np.abs(V).max(axis=0)))
        sgn = float(np.sign(V[:, ax].sum()))
        if after["moving"]:  # still braking at `after`: t_s is where the ramp from there passes p(after)
            d = np.clip(after["t"] - t0 - tau, 0.0, np.abs(V[:, ax]) / self.lim.a_stop)
            x_after = P[:, ax] + V[:, ax] * d - 0.5 * sgn * self.lim.a_stop * d * d
            match = np.abs(x_after - after["p"][ax]) <= 0.3
            if match.any():
                E = E[match]
        far = float(sgn * E[:, ax].max() if sgn > 0 else sgn * E[:, ax].min())
        r = rest["p"]
        inside = bool(np.all(r >= self.lim.box_min) and np.all(r <= self.lim.box_max))
        beyond = sgn * r[ax] - far
        behind = sgn * (before["p"][ax] - r[ax])
        ok = beyond <= 0.5 and behind <= 0.5 and inside and not self.done_seen(sid)
        self.record("stop.ramp", ok, f"stopped at {np.abs(V[:, ax]).max():.0f} mm/s on axis {'xyz'[ax]}: rests "
                    f"{beyond:+.2f} mm from the furthest rest point the document allows"
                    + ("" if inside else "; OUTSIDE the box")
                    + ("; @DONE sent for the cut segment" if self.done_seen(sid) else ""))
        self.req("CLEAR")

    def r_latch(self) -> None:
        """stop.latch (1.1): after STOP, SEG, HOME and SEGNOW get E41 until CLEAR; then SEG is accepted."""
        if not self.v11:
            self.record("stop.latch", None, "a 1.0 session: STOP does not latch")
            return
        p0, rv = self._here()
        self.req("STOP")
        st = self.status()
        c1, _, _ = self.seg(p0, rv, 1.0)
        c2, _ = self.req("HOME")
        c3, _, _ = self.seg(p0, rv, 1.0, cmd="SEGNOW")
        cl, _ = self.req("CLEAR")
        st2 = self.status()
        c4, _, sid = self.seg(p0, rv, 0.5)
        ok = st["fault"] == "stopped" and (c1, c2, c3) == ("E41",) * 3 and cl == "ok" and st2["fault"] == "none" \
            and c4 == "ok"
        self.record("stop.latch", ok, f"after STOP: fault {st['fault']}, SEG {c1}, HOME {c2}, SEGNOW {c3}; "
                    f"CLEAR {cl}, fault {st2['fault']}, SEG {c4}")
        self.wait_done(sid, 2.0)

    def r_cut(self) -> None:
        """done.not_after_cut: a SEGNOW that replaces a running segment sends @DONE for itself only."""
        p0, rv = self._here()
        ax, sgn, room = self._room(p0)
        p1 = p0.copy()
        p1[ax] += sgn * min(80.0, room / 3)
        code, _, a = self.seg(p1, rv, 2.0)
        self.wait(0.4)
        code2, _, b = self.seg(p0, rv, 1.5, cmd="SEGNOW")
        done_b = self.wait_done(b, 3.0)
        self.wait(0.1)
        ok = code == code2 == "ok" and done_b and not self.done_seen(a)
        self.record("done.not_after_cut", ok, f"SEG {a} {code}, SEGNOW {b} {code2}: @DONE {b} "
                    f"{'seen' if done_b else 'missing'}, @DONE {a} {'SENT' if self.done_seen(a) else 'not sent'}")

    def r_queue(self) -> None:
        """queue.full, queue.segnow_when_full: 1 running + ``queue`` waiting SEGs fit, one more is E20; SEGNOW runs."""
        p0, rv = self._here()
        ax, sgn, room = self._room(p0)
        codes = []
        for i in range(self.queue + 1):  # one runs, queue wait
            p = p0.copy()
            p[ax] += sgn * (i + 1) * 1.0
            codes.append(self.seg(p, rv, 2.0)[0])  # 2 s each: the queue cannot drain while it is filled
        over = self.seg(p0, rv, 0.5)[0]
        now = self.seg(p0, rv, 1.0, cmd="SEGNOW")
        ok = all(c == "ok" for c in codes) and over == "E20" and now[0] == "ok"
        self.record("queue.full", ok, f"{len(codes)} SEG → {set(codes)}, one more → {over}")
        self.record("queue.segnow_when_full", now[0] == "ok", f"SEGNOW with a full queue → {now[0]}")
        self.wait_done(now[2], 3.0)

    def r_watchdog_fed(self) -> None:
        """watchdog.fed: any valid request (STATUS here) keeps the watchdog from tripping over a 3-watchdog segment."""
        p0, rv = self._here()
        ax, sgn, room = self._room(p0)
        p1 = p0.copy()
        p1[ax] += sgn * min(30.0, room / 4)
        T = 3 * self.lim.watchdog_s
        code, _, sid = self.seg(p1, rv, T)
        end = time.monotonic() + T + 2.0
        done = False
        while time.monotonic() < end and not done:  # STATUS, not HB: every valid request feeds it
            self.req("STATUS")
            self.client._pump(self.lim.watchdog_s / 3)
            done = self.done_seen(sid)
        trips = self.client.asyncs("WATCHDOG")
        self.record("watchdog.fed", code == "ok" and done and not trips,
                    f"{T:.2f} s segment with a STATUS every {self.lim.watchdog_s / 3:.2f} s: "
                    f"{'@DONE' if done else 'no @DONE'}, {len(trips)} @WATCHDOG")

    def r_watchdog_trips(self) -> None:
        """watchdog.trips: silence past the watchdog stops the arm (@WATCHDOG, fault, E40 on SEG) until CLEAR."""
        p0, rv = self._here()
        ax, sgn, room = self._room(p0)
        p1 = p0.copy()
        p1[ax] += sgn * min(40.0, room / 4)
        T = max(2.0, 4 * self.lim.watchdog_s)
        self.client.asyncs("WATCHDOG")
        code, _, sid = self.seg(p1, rv, T)
        silent = 2 * self.lim.watchdog_s + 0.2
        self.client._pump(silent)  # say nothing
        trips = self.client.asyncs("WATCHDOG")
        st = self.wait_rest()
        refused, _, _ = self.seg(p0, rv, 1.0)
        cl, _ = self.req("CLEAR")
        ok = code == "ok" and bool(trips) and st["fault"] == "watchdog" and refused == "E40" and cl == "ok" \
            and not self.done_seen(sid)
        self.record("watchdog.trips", ok, f"silent for {silent:.2f} s (watchdog {self.lim.watchdog_s:g} s): "
                    f"{'@WATCHDOG' if trips else 'no @WATCHDOG'}, fault {st['fault']}, SEG then {refused}, "
                    f"rest {'short of' if not self.done_seen(sid) else 'AT'} the target")
        if not ok:
            self.recover()


    # --- the ruckig profile (1.2) -------------------------------------------------------------------
    def _ruckig_seg(self, p, rv, T, cmd="SEG", extra: str = "") -> tuple[str, list[str], int]:
        sid = self.new_id()
        args = [str(sid), *map(_num, p), *map(_num, rv), _num(T)]
        code, f = self.req(f"{cmd} {' '.join(args)} profile=ruckig{(' ' + extra) if extra else ''}")
        return code, f, sid

    def _skip_ruckig(self, rule: str) -> bool:
        if not self.ruckig:
            self.record(rule, None, f"the controller does not list ruckig in a 1.2 session (profiles "
                        f"{','.join(self.profiles)}, session {self.version})")
            return True
        if self.lim.j_max is None:
            self.record(rule, False, "ruckig listed but LIMITS has no field 19 (jmax)")
            return True
        return False

    def _ruckig_1d(self, D: float, v_max: float | None = None):
        """The time-optimal jerk-limited rest-to-rest move of D mm under LIMITS' vmax (or ``v_max``, mm/s), amax,
        jmax (ruckig, 1 DoF): the document's ruckig segment along one axis (§5: the limits of the axis of travel
        are the full ones)."""
        from ruckig import InputParameter, Ruckig, Trajectory

        inp, traj = InputParameter(1), Trajectory(1)
        inp.current_position, inp.target_position = [0.0], [D]
        inp.max_velocity = [self.lim.v_max if v_max is None else v_max]
        inp.max_acceleration = [self.lim.a_max]
        inp.max_jerk = [self.lim.j_max]
        Ruckig(1).calculate(inp, traj)
        return traj

    def r_ruckig_arrival(self) -> None:
        """ruckig.arrival (1.2): a rest-to-rest ``profile=ruckig`` SEG with T = 0 along one axis runs the
        time-optimal jerk-limited move (t1 − t0 and the positions on the way as ruckig computes them from
        LIMITS' vmax, amax, jmax), ends on target and sends @DONE."""
        if self._skip_ruckig("ruckig.arrival"):
            return
        p0, rv = self._here()
        ax, sgn, room = self._room(p0)
        D = min(120.0, room / 4)
        p1 = p0.copy()
        p1[ax] += sgn * D
        code, f, sid = self._ruckig_seg(p1, rv, 0)
        if code != "ok":
            self.record("ruckig.arrival", False, f"ruckig SEG of {D:.0f} mm, T = 0 → {code}")
            return
        t0, t1 = float(f[0]), float(f[1])
        ref = self._ruckig_1d(D)
        mid_err = 0.0
        for _ in range(3):
            self.client._pump(ref.duration / 5)
            st = self.status()
            tau = st["t"] - t0
            if 0 < tau < ref.duration:
                pos, vel, _ = ref.at_time(tau)[:3]
                want = p0.copy()
                want[ax] += sgn * pos[0]
                mid_err = max(mid_err, float(np.linalg.norm(st["p"] - want)) - abs(vel[0]) * 5e-5)
        done, end_err, problems = self._arrival(sid, p1, t1 - t0, ref.duration, mid_err,
                                                f"ruckig's time-optimal move takes {ref.duration:.4f} s",
                                                "ruckig's trajectory")
        self.record("ruckig.arrival", not problems, "; ".join(problems)
                    or f"{D:.0f} mm in {t1 - t0:.4f} s (ruckig: {ref.duration:.4f} s), on the way to "
                       f"{max(mid_err, 0):.4f} mm, target to {end_err:.4f} mm, @DONE")

    def r_ruckig_splice(self) -> None:
        """ruckig.splice (1.2): a ruckig SEGNOW sent mid-move (from a moving state: p, v, a) is accepted, runs
        from where the arm is — the STATUS positions around the splice move on smoothly — and ends on target."""
        if self._skip_ruckig("ruckig.splice"):
            return
        p0, rv = self._here()
        ax, sgn, room = self._room(p0)
        D = min(150.0, room / 4)
        p1, p2 = p0.copy(), p0.copy()
        p1[ax] += sgn * D
        p2[ax] += sgn * D / 2
        p2[(ax + 1) % 3] += min(40.0, self._room(p0)[2] / 4) * (1 if p0[(ax + 1) % 3] < np.mean(
            [self.lim.box_min[(ax + 1) % 3], self.lim.box_max[(ax + 1) % 3]]) else -1)
        code, f, a = self._ruckig_seg(p1, rv, 2.0)
        if code != "ok":
            self.record("ruckig.splice", False, f"ruckig SEG of {D:.0f} mm in 2 s → {code}")
            return
        self.wait(0.6)
        before = self.status()
        code2, f2, b = self._ruckig_seg(p2, rv, 0, cmd="SEGNOW")
        after = self.status()
        done = self.wait_done(b, 5.0)
        st = self.wait_rest()
        problems = []
        if code2 != "ok":
            problems.append(f"SEGNOW ruckig mid-move → {code2}")
        else:
            # the arm moved on from `before` at no more than vmax: no jump back to a rest state
            dt = after["t"] - before["t"]
            jump = float(np.linalg.norm(after["p"] - before["p"]))
            if jump > self.lim.v_max * dt + 0.05:
                problems.append(f"moved {jump:.2f} mm in {dt:.4f} s across the splice")
            if not done:
                problems.append(f"no @DONE {b}")
            if self.done_seen(a):
                problems.append(f"@DONE {a} sent for the cut segment")
            if float(np.linalg.norm(st["p"] - p2)) > 0.01:
                problems.append(f"rests {float(np.linalg.norm(st['p'] - p2)):.4f} mm from the new target")
        self.record("ruckig.splice", not problems, "; ".join(problems)
                    or f"spliced at {before['t']:.3f}–{after['t']:.3f} s, ends on the new target, @DONE {b} only")

    def r_ruckig_limits(self) -> None:
        """ruckig.limits (1.2): ``jmax=`` above LIMITS' is E16; a ruckig segment whose end needs more room to
        brake than the box has (5 mm from the wall, ending at a speed that needs 20 mm) is E10; neither runs."""
        if self._skip_ruckig("ruckig.limits"):
            return
        p0, rv = self._here()
        ax, sgn, room = self._room(p0)
        p1 = p0.copy()
        p1[ax] += sgn * min(30.0, room / 4)
        # _skip_ruckig returned False: LIMITS has jmax
        c16, _, _ = self._ruckig_seg(p1, rv, 0, extra=f"jmax={_num(2 * cast(float, self.lim.j_max))}")
        wall = self.lim.box_max[ax] if sgn > 0 else self.lim.box_min[ax]
        p2 = p0.copy()
        p2[ax] = wall - sgn * 5.0
        u = math.sqrt(2 * self.lim.a_stop * 20.0)
        v = np.zeros(3)
        v[ax] = sgn * min(u, 0.9 * self.lim.v_max)
        sid = self.new_id()
        args = [str(sid), *map(_num, p2), *map(_num, rv), "0", *map(_num, v), "0", "0", "0"]
        c10, _ = self.req(f"SEG {' '.join(args)} profile=ruckig")
        for c in (c16, c10):
            if c == "ok":
                self.recover()
        need = float(v[ax] ** 2 / (2 * self.lim.a_stop))
        self.record("ruckig.limits", (c16, c10) == ("E16", "E10"),
                    f"jmax 2·LIMITS → {c16} (want E16); ends 5 mm from the wall at {abs(v[ax]):.0f} mm/s outwards "
                    f"(needs {need:.0f} mm) → {c10} (want E10)")

    # --- segment defaults (1.4) -------------------------------------------------------------------
    def r_set_defaults(self) -> None:
        """set.defaults (1.4): ``SET profile=ruckig vmax=V`` makes a SEG that names no ``profile=`` the ruckig
        move under vmax V (t1 − t0 as ruckig computes it); one naming ``profile=quintic`` runs a quintic of its T;
        limits without ``profile=ruckig`` are E02, above LIMITS' E16; a bare ``SET`` is quintic again (a
        profile-less SEG with T = 0: E11); a 1.3 or older session has no ``SET`` (E01)."""
        rule = "set.defaults"
        if self.version != "1.4":
            code, _ = self.req("SET")
            self.record(rule, None if code == "E01" else False,
                        f"a {self.version} session: SET → {code}" + ("" if code == "E01" else " (want E01)"))
            return
        if self._skip_ruckig(rule):
            return
        problems = []
        c02, _ = self.req(f"SET vmax={_num(0.5 * self.lim.v_max)}")
        c16, _ = self.req(f"SET profile=ruckig vmax={_num(2 * self.lim.v_max)}")
        if (c02, c16) != ("E02", "E16"):
            problems.append(f"SET vmax= without a profile → {c02} (want E02), vmax 2·LIMITS → {c16} (want E16)")
        v_set = 0.5 * self.lim.v_max
        code, _ = self.req(f"SET profile=ruckig vmax={_num(v_set)}")
        p0, rv = self._here()
        ax, sgn, room = self._room(p0)
        D = min(120.0, room / 4)
        p1 = p0.copy()
        p1[ax] += sgn * D
        sid = self.new_id()
        c1, f1 = self.req(f"SEG {sid} {' '.join(map(_num, [*p1, *rv]))} 0")
        ref = self._ruckig_1d(D, v_set)
        if code != "ok" or c1 != "ok":
            problems.append(f"SET profile=ruckig vmax={_num(v_set)} → {code}, then a profile-less SEG → {c1}")
        else:
            took = float(f1[1]) - float(f1[0])
            if abs(took - ref.duration) > 2e-3:
                problems.append(f"the profile-less SEG took {took:.4f} s, ruckig at vmax {v_set:g}: "
                                f"{ref.duration:.4f} s")
            if not self.wait_done(sid, ref.duration + 2.0):
                problems.append(f"no @DONE {sid}")
        self.wait_rest()
        sid = self.new_id()
        cq, fq = self.req(f"SEG {sid} {' '.join(map(_num, [*p0, *rv]))} 1 profile=quintic")
        if cq != "ok" or abs(float(fq[1]) - float(fq[0]) - 1.0) > 1e-3:
            problems.append(f"SEG profile=quintic T=1 → {cq} {' '.join(fq)} (want a 1-s quintic)")
        elif not self.wait_done(sid, 3.0):
            problems.append(f"no @DONE {sid}")
        self.wait_rest()
        cb, _ = self.req("SET")
        c11, _ = self.req(f"SEG {self.new_id()} {' '.join(map(_num, [*p1, *rv]))} 0")
        if (cb, c11) != ("ok", "E11"):
            problems.append(f"bare SET → {cb}, then a profile-less SEG with T = 0 → {c11} (want ok, E11)")
        if c11 == "ok":
            self.recover()
        self.record(rule, not problems, "; ".join(problems)
                    or f"SET vmax {v_set:g}: {D:.0f} mm in {ref.duration:.4f} s as ruckig; profile=quintic ran "
                       "its 1 s; bare SET: quintic again (E11); E02 and E16 as documented")

    def r_hold_go(self) -> None:
        """hold.go (1.4): ``SEG … hold=1`` is answered ``ok`` without times and nothing moves (0.3 s later the
        robot stands where it stood); ``GO id`` runs it then (``t0`` now, ``@DONE``, rests on target); a second
        ``GO id`` is E21, ``SEGNOW … hold=1`` E02, and so is a ``GO`` after ``STOP`` and ``CLEAR`` (STOP drops
        what is held); a 1.3 or older session: GO is E01."""
        rule = "hold.go"
        if self.version != "1.4":
            code, _ = self.req("GO 1")
            self.record(rule, None if code == "E01" else False,
                        f"a {self.version} session: GO → {code}" + ("" if code == "E01" else " (want E01)"))
            return
        problems = []
        p0, rv = self._here()
        ax, sgn, room = self._room(p0)
        p1 = p0.copy()
        p1[ax] += sgn * min(60.0, room / 4)
        sid = self.new_id()
        words = " ".join(map(_num, [*p1, *rv]))
        ch, fh = self.req(f"SEG {sid} {words} 1 hold=1")
        self.wait(0.3)
        st = self.status()
        if ch != "ok" or fh:
            problems.append(f"SEG hold=1 → {ch} {' '.join(fh)} (want ok, no times)")
        if st["moving"] or float(np.linalg.norm(st["p"] - p0)) > 0.01:
            problems.append(f"moved {float(np.linalg.norm(st['p'] - p0)):.3f} mm while held")
        cg, fg = self.req(f"GO {sid}")
        t_go = self.status()["t"]
        if cg != "ok" or len(fg) < 2:
            problems.append(f"GO {sid} → {cg}")
        else:
            if not float(fg[0]) <= t_go + 1e-3 or t_go - float(fg[0]) > 0.1:
                problems.append(f"GO at {t_go:.4f} s started the segment at {fg[0]}")
            if abs(float(fg[1]) - float(fg[0]) - 1.0) > 1e-3:
                problems.append(f"the held 1-s quintic runs {fg[0]}–{fg[1]}")
            if not self.wait_done(sid, 3.0):
                problems.append(f"no @DONE {sid}")
            st = self.wait_rest()
            if float(np.linalg.norm(st["p"] - p1)) > 0.01:
                problems.append(f"rests {float(np.linalg.norm(st['p'] - p1)):.4f} mm from the held target")
        c21, _ = self.req(f"GO {sid}")
        c02, _ = self.req(f"SEGNOW {self.new_id()} {words} 1 hold=1")
        if (c21, c02) != ("E21", "E02"):
            problems.append(f"a second GO → {c21} (want E21), SEGNOW hold=1 → {c02} (want E02)")
        if c02 == "ok":
            self.recover()
        sid = self.new_id()  # STOP drops what is held: a GO after STOP and CLEAR finds nothing to run
        ch, _ = self.req(f"SEG {sid} {words} 1 hold=1")
        self.req("STOP")
        self.req("CLEAR")
        c21, _ = self.req(f"GO {sid}")
        if ch == "ok" and c21 != "E21":
            problems.append(f"GO {sid} after STOP and CLEAR → {c21} (want E21: STOP drops a held segment)")
            self.recover()
        self.record(rule, not problems, "; ".join(problems)
                    or "held without moving for 0.3 s; GO ran it at once to its end, @DONE; E21 and E02 as "
                       "documented; STOP dropped a held segment")

    # --- the arm (1.3) ----------------------------------------------------------------------
    def _skip_arm(self, rule: str) -> bool:
        """Record SKIP (no arm in this session, or no kinematics to judge it by) or FAIL (the kinematics are
        another arm's) and return True; False when the arm rule can run."""
        if self.arm_name is None:
            self.record(rule, None, "not a 1.3 session with an arm (no arm= in HELLO)")
            return True
        if self.arm is None:
            self.record(rule, None, f"the controller names arm={self.arm_name}; give its kinematics (--arm FILE)")
            return True
        if self.arm.name != self.arm_name:
            self.record(rule, False, f"the controller names arm={self.arm_name}, the kinematics are {self.arm.name}'s")
            return True
        return False

    def _arm_rest(self) -> tuple[dict, np.ndarray]:
        """The status at rest and the joints it reports (rad)."""
        st = self.wait_rest()
        if "q" not in st:
            raise AssertionError("STATUS has no joints in a 1.3 session with an arm")
        return st, st["q"]

    def _arm_seg(self, T: np.ndarray, duration: float) -> tuple[str, list[str], int]:
        """SEG to the pose ``T`` (4×4 ``T_w_F``) in ``duration`` s."""
        return self.seg(T[:3, 3], _matrix_rotvec(T[:3, :3]), duration)

    def _move_time(self, T0: np.ndarray, T1: np.ndarray, least: float = 1.0) -> float:
        """A rest-to-rest quintic's duration at half of LIMITS' speeds (1.875·distance / (limit/2))."""
        d = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
        th = float(np.linalg.norm(_matrix_rotvec(T0[:3, :3].T @ T1[:3, :3])))
        return max(least, 1.875 * d / (0.5 * self.lim.v_max), 1.875 * th / (0.5 * self.lim.w_max))

    def _arm_fly(self, T: np.ndarray, duration: float) -> str:
        """Fly to ``T`` and wait for rest; the reply code."""
        code, f, sid = self._arm_seg(T, duration)
        if code == "ok":
            self.wait_done(sid, float(f[1]) - float(f[0]) + 2.0)
            self.wait_rest()
        return code

    def _status_pose(self, st: dict) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = _rotvec_matrix(st["rv"]), st["p"]
        return T

    def _joint_errors(self, st: dict) -> tuple[float, float]:
        """(mm, rad) between the pose STATUS reports and the forward kinematics of the joints it reports."""
        arm = cast(ArmKinematics, self.arm)
        T_fk, T = arm.fk(st["q"]), self._status_pose(st)
        return (float(np.linalg.norm(T_fk[:3, 3] - T[:3, 3])),
                float(np.linalg.norm(_matrix_rotvec(T_fk[:3, :3].T @ T[:3, :3]))))

    def r_arm_joints(self) -> None:
        """arm.joints (1.3): the joints STATUS reports put the flange, by the arm's forward kinematics, where
        the pose STATUS reports says — at rest and mid-move — within 0.1 mm and 2e-4 rad (the pose's four
        decimals)."""
        if self._skip_arm("arm.joints"):
            return
        st, _ = self._arm_rest()
        errs = [self._joint_errors(st)]
        T0 = self._status_pose(st)
        T1 = T0.copy()
        T1[2, 3] += 40.0 if T0[2, 3] + 40.0 < self.lim.box_max[2] else -40.0
        code, f, sid = self._arm_seg(T1, 1.5)
        if code == "ok":
            self.wait(0.7)
            errs.append(self._joint_errors(self.status()))
            self.wait_done(sid, 3.0)
            errs.append(self._joint_errors(self.wait_rest()))
        mm, rad = max(e[0] for e in errs), max(e[1] for e in errs)
        self.record("arm.joints", code == "ok" and mm <= 0.1 and rad <= 2e-4,
                    f"{len(errs)} STATUS (rest, mid-move, rest): FK of the joints within {mm:.4f} mm, {rad:.1e} rad"
                    + ("" if code == "ok" else f"; a 40 mm move → {code}"))

    def r_arm_reach(self) -> None:
        """arm.reach (1.3): a segment that puts the wrist point (DH frame 5) on the base axis, 400 mm above
        the shoulder, keeping the flange's orientation, is E30 (outside the reach of an arm with a shoulder
        offset d4: the cylinder of radius |d4| round the axis) and does not run."""
        if self._skip_arm("arm.reach"):
            return
        arm = cast(ArmKinematics, self.arm)
        st, _ = self._arm_rest()
        T0 = self._status_pose(st)
        T_flange = T0 @ np.linalg.inv(arm.T_flange_tool)
        wrist = arm.T_w_base @ np.array([0.0, 0.0, arm.d[0] + 400.0, 1.0])
        target = T_flange.copy()
        target[:3, 3] = wrist[:3] + arm.d[5] * T_flange[:3, 2]
        T1 = target @ arm.T_flange_tool
        if np.any(T1[:3, 3] < self.lim.box_min) or np.any(T1[:3, 3] > self.lim.box_max):
            self.record("arm.reach", None, "a pose over the base axis is outside the LIMITS box")
            return
        code, _, _ = self._arm_seg(T1, self._move_time(T0, T1, 2.0))
        moved = bool(self.status()["moving"])
        if code == "ok":
            self.recover()
        want = "E30" if abs(arm.d[3]) > 1.0 else "E32"
        self.record("arm.reach", code == want and not moved,
                    f"wrist point on the base axis → {code} (want {want}){', and it moved' if moved else ''}")

    def r_arm_joint_limit(self) -> None:
        """arm.joint_limit (1.3): turning the flange about its own axis (the last joint alone) by 170° a segment
        is accepted while the last joint stays within its limit; the first turn past it is E31; then the
        turns are undone."""
        if self._skip_arm("arm.joint_limit"):
            return
        arm = cast(ArmKinematics, self.arm)
        _, q0 = self._arm_rest()
        step = math.radians(170.0)
        n = int((arm.q_max[5] - q0[5]) // step) + 1  # the first turn that passes the limit
        if n > 6:
            self.record("arm.joint_limit", None, f"the last joint has {math.degrees(arm.q_max[5] - q0[5]):.0f}° to go")
            return
        T_here = arm.fk(q0)
        got = []
        for k in range(1, n + 1):
            q = q0.copy()
            q[5] += k * step
            T = arm.fk(q)
            code = self._arm_fly(T, self._move_time(T_here, T, 1.0))
            got.append(code)
            if code != "ok":
                break
            T_here = T
        for k in range(len([c for c in got if c == "ok"]) - 1, -1, -1):  # undo the turns
            q = q0.copy()
            q[5] += k * step
            T = arm.fk(q)
            self._arm_fly(T, self._move_time(T_here, T, 1.0))
            T_here = T
        want = ["ok"] * (n - 1) + ["E31"]
        self.record("arm.joint_limit", got == want,
                    f"last joint from {math.degrees(q0[5]):.1f}° by 170° turns, limit "
                    f"{math.degrees(arm.q_max[5]):.0f}°: {' '.join(got)} (want {' '.join(want)})")

    def r_arm_singularity(self) -> None:
        """arm.singularity (1.3): from the wrist 5° short of its singularity (q5 = ±5°, the other joints as
        reported), a segment to the pose of q5 = ∓5° passes within 0.1° of it; it is E32 (within the
        controller's margin), or E33 (no margin: the wrist would flip) and does not run."""
        if self._skip_arm("arm.singularity"):
            return
        arm = cast(ArmKinematics, self.arm)
        st, q0 = self._arm_rest()
        T0 = self._status_pose(st)
        side = 1.0 if math.sin(q0[4] + arm.offset[4]) >= 0 else -1.0
        qa, qb = q0.copy(), q0.copy()
        qa[4] = side * math.radians(5.0) - arm.offset[4]
        qb[4] = -side * math.radians(5.0) - arm.offset[4]
        Ta, Tb = arm.fk(qa), arm.fk(qb)
        setup = self._arm_fly(Ta, self._move_time(T0, Ta, 2.0))
        if setup != "ok":
            self.record("arm.singularity", None, f"the move to 5° short of the wrist singularity → {setup}")
            return
        code, _, _ = self._arm_seg(Tb, 1.0)
        moved = bool(self.status()["moving"])
        if code == "ok":
            self.recover()
        self._arm_fly(T0, self._move_time(Ta, T0, 2.0))
        self.record("arm.singularity", code in ("E32", "E33") and not moved,
                    f"q5 {math.degrees(qa[4]):+.0f}° → {math.degrees(qb[4]):+.0f}° in 1 s → {code} (want E32 or E33)"
                    + (", and it moved" if moved else ""))

    def r_arm_joint_rate(self) -> None:
        """arm.joint_rate (1.3): a 1° flick of the last joint at 95 % of LIMITS' wmax (16 ms: a joint
        acceleration of ~2·10⁴ °/s², beyond any arm's) is E34 and does not run; the same turn in 1 s runs."""
        if self._skip_arm("arm.joint_rate"):
            return
        arm = cast(ArmKinematics, self.arm)
        _, q0 = self._arm_rest()
        q = q0.copy()
        q[5] += math.radians(1.0)
        T = arm.fk(q)
        fast = 1.875 * math.radians(1.0) / (0.95 * self.lim.w_max)
        code, _, _ = self._arm_seg(T, fast)
        moved = bool(self.status()["moving"])
        if code == "ok":
            self.recover()
        slow = self._arm_fly(T, 1.0)
        self.record("arm.joint_rate", code == "E34" and not moved and slow == "ok",
                    f"1° in {fast * 1000:.0f} ms → {code} (want E34); in 1 s → {slow} (want ok)"
                    + (", and it moved" if moved else ""))


def run_suite(port: str, baud: int = 9600, *, no_motion: bool = False, only: list[str] | None = None,
              log: Callable[[Result], None] | None = None, timeout_s: float = 1.0, serial_port=None,
              arm: ArmKinematics | None = None) -> list[Result]:
    """Run the suite against the controller on ``port`` (``arm``: the kinematics of the arm it should name,
    for the 1.3 arm rules); CannotTalk if it cannot be reached."""
    client = Client(port, baud, timeout_s, serial_port=serial_port)
    try:
        return Suite(client, no_motion=no_motion, only=list(only or []), log=log, arm=arm).run()
    finally:
        client.close()
