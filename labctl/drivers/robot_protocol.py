"""The robot controller's ASCII dialect (docs/protocols/robot.md), parsed and formatted (pure).

Requests ``#<seq> <COMMAND> [args…]``, replies ``$<seq> ok [fields…]`` or
``$<seq> E<code> [message]``, asynchronous reports ``@<KIND> [fields…]``; one line each,
ended by ``\\n`` (a ``\\r`` before it is ignored). Modelled on the uArm Swift Pro protocol.
The parsers accept any text and never raise.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

ERROR_CODES = {
    1: "unknown command", 2: "bad arguments", 3: "malformed request", 4: "line too long",
    5: "checksum mismatch",
    10: "outside the workspace (path or stop)", 11: "bad duration", 12: "too fast (linear speed limit)",
    13: "acceleration limit exceeded", 14: "too fast (angular speed limit)", 15: "profile not supported",
    16: "jerk limit above the controller's", 17: "no jerk-limited trajectory to that state",
    20: "segment queue full", 21: "no such held segment",
    30: "outside the arm's reach", 31: "a joint would pass its limit", 32: "too close to a singularity of the arm",
    33: "needs a configuration change of the arm", 34: "too fast for a joint (joint speed or acceleration limit)",
    40: "stopped by the watchdog: send CLEAR", 41: "stopped: send CLEAR",
}

MAX_LINE = 240
MAX_SEQ = 65535
_NUMBER = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?$")


def parse_number(text: str) -> float | None:
    """A request number as dialect 1.1 defines it: ``[+-]digits[.digits][e[+-]digits]`` (also
    ``.5``, ``5.``; what C's strtod and Python's float read, without inf, nan, hex or ``_``);
    None if ``text`` is not one or overflows to infinity."""
    if not _NUMBER.match(text):
        return None
    value = float(text)
    return value if math.isfinite(value) else None


def fmt_num(value: float, decimals: int = 6) -> str:
    """A number as the controller prints it: fixed point, at most ``decimals`` decimals, trailing
    zeros dropped, never an exponent, never ``-0``."""
    text = f"{float(value):.{decimals}f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


def fmt_fixed(value: float, decimals: int = 4) -> str:
    """Fixed point with exactly ``decimals`` decimals, never ``-0.0000`` (STATUS, t0/t1)."""
    text = f"{float(value):.{decimals}f}"
    return text[1:] if text.startswith("-") and not text.strip("-0.") else text


def canonical_rotvec(rv) -> np.ndarray:
    """The rotation vector (rad, angle in [0, π]) as the controller reports it: within 1e-6 rad of
    an angle of π, r and −r are (to 2e-6 rad) the same rotation, and the one whose first non-zero
    component (|c| > 1e-6) is positive is reported."""
    rv = np.asarray(rv, dtype=float).reshape(3).copy()
    if np.linalg.norm(rv) > math.pi - 1e-6:
        for c in rv:
            if abs(c) > 1e-6:
                if c < 0:
                    rv = -rv
                break
    return rv


@dataclass(frozen=True)
class RobotReply:
    """One line from the controller. ``kind``: reply, async or unknown."""

    kind: str
    raw: str
    seq: int | None = None
    ok: bool = False
    code: int | None = None
    report: str = ""  # async report kind (DONE, WATCHDOG, BOOT, ERR…)
    fields: tuple[str, ...] = field(default_factory=tuple)
    text: str = ""

    def floats(self, n: int | None = None) -> tuple[float, ...] | None:
        """The fields as finite floats (None if any is not a number or the count differs)."""
        if n is not None and len(self.fields) < n:
            return None
        out = []
        for f in self.fields[: n if n is not None else len(self.fields)]:
            try:
                v = float(f)
            except ValueError:
                return None
            if not math.isfinite(v):
                return None
            out.append(v)
        return tuple(out)


def checksum(body: str) -> str:
    """NMEA-style check: XOR of the body's bytes as two hex digits."""
    x = 0
    for b in body.encode("ascii", errors="replace"):
        x ^= b
    return f"{x:02X}"


def add_checksum(line: str) -> str:
    """``line`` with its ``*HH`` checksum appended (docs/protocols/robot.md)."""
    return f"{line}*{checksum(line)}"


def strip_checksum(line: str) -> str | None:
    """The line without its ``*HH`` suffix; None if the suffix is present and wrong."""
    body, star, tail = line.rpartition("*")
    if not star or len(tail) != 2:
        return line
    return body if tail.upper() == checksum(body) else None


def parse_reply(line: str | bytes) -> RobotReply:
    """Classify one line from the controller (without its line end). Never raises.

    A line with a wrong ``*HH`` checksum is ``unknown`` (corrupted on the wire)."""
    if isinstance(line, bytes | bytearray):
        line = bytes(line).decode("ascii", errors="replace")
    raw = line
    checked = strip_checksum(line.strip())
    if checked is None:
        return RobotReply("unknown", raw)
    s = checked
    if s.startswith("$"):
        head, _, rest = s[1:].partition(" ")
        if not head.isdigit() or len(head) > 5:
            return RobotReply("unknown", raw)
        seq = int(head)
        parts = rest.split()
        if not parts:
            return RobotReply("unknown", raw)
        if parts[0] == "ok":
            return RobotReply("reply", raw, seq=seq, ok=True, fields=tuple(parts[1:]))
        if parts[0].startswith("E") and parts[0][1:].isdigit() and len(parts[0]) <= 4:
            code = int(parts[0][1:])
            msg = rest.split(None, 1)[1] if len(parts) > 1 else ERROR_CODES.get(code, "")
            return RobotReply("reply", raw, seq=seq, ok=False, code=code, text=msg)
        return RobotReply("unknown", raw)
    if s.startswith("@") and len(s) > 1:
        parts = s[1:].split()
        if parts and parts[0].isalnum():
            return RobotReply("async", raw, report=parts[0].upper(), fields=tuple(parts[1:]))
    return RobotReply("unknown", raw)


def format_request(seq: int, command: str, *args, check: bool = True) -> str:
    """``#<seq> COMMAND arg…*HH`` with floats to 6 decimals, trailing zeros dropped (mm, rad, s)."""
    parts = [f"#{seq}", command]
    for a in args:
        if isinstance(a, float):
            parts.append(fmt_num(a))
        else:
            parts.append(str(a))
    line = " ".join(parts)
    return add_checksum(line) if check else line


@dataclass(frozen=True)
class Request:
    """A parsed host request: sequence number, command word, arguments (as sent)."""
    seq: int
    command: str
    args: tuple[str, ...]


def parse_request(line: str) -> Request | int:
    """A request line as the controller reads it; an error code (3 malformed, 5 checksum) if not one."""
    checked = strip_checksum(line.strip())
    if checked is None:
        return 5
    s = checked
    if not s.startswith("#"):
        return 3
    parts = s[1:].split()
    if len(parts) < 2 or not parts[0].isdigit() or len(parts[0]) > 5 or int(parts[0]) > MAX_SEQ:
        return 3
    return Request(int(parts[0]), parts[1].upper(), tuple(parts[2:]))
