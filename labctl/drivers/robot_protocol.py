"""The robot controller's ASCII dialect (docs/protocols/robot.md), parsed and formatted (pure).

Requests ``#<seq> <COMMAND> [args…]``, replies ``$<seq> ok [fields…]`` or
``$<seq> E<code> [message]``, asynchronous reports ``@<KIND> [fields…]``; one line each,
ended by ``\\n`` (a ``\\r`` before it is ignored). Modelled on the uArm Swift Pro protocol.
The parsers accept any text and never raise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

ERROR_CODES = {
    1: "unknown command", 2: "bad arguments", 3: "malformed request", 4: "line too long",
    10: "target outside the workspace", 11: "bad duration", 12: "too fast (linear speed limit)",
    13: "acceleration limit exceeded", 14: "too fast (angular speed limit)", 20: "segment queue full",
    40: "stopped by the watchdog: send CLEAR", 41: "stopped: send CLEAR",
}

MAX_LINE = 240
MAX_SEQ = 65535


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


def parse_reply(line: str | bytes) -> RobotReply:
    """Classify one line from the controller (without its line end). Never raises."""
    if isinstance(line, bytes | bytearray):
        line = bytes(line).decode("ascii", errors="replace")
    raw = line
    s = line.strip()
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


def format_request(seq: int, command: str, *args) -> str:
    """``#<seq> COMMAND arg…`` with floats to 6 decimals, trailing zeros dropped (mm, rad, s)."""
    parts = [f"#{seq}", command]
    for a in args:
        if isinstance(a, float):
            text = f"{a:.6f}".rstrip("0").rstrip(".")
            parts.append("0" if text in ("", "-0") else text)
        else:
            parts.append(str(a))
    return " ".join(parts)


@dataclass(frozen=True)
class Request:
    seq: int
    command: str
    args: tuple[str, ...]


def parse_request(line: str) -> Request | int:
    """A request line as the controller reads it; an error code (3 malformed) if it is not one."""
    s = line.strip()
    if not s.startswith("#"):
        return 3
    parts = s[1:].split()
    if len(parts) < 2 or not parts[0].isdigit() or len(parts[0]) > 5 or int(parts[0]) > MAX_SEQ:
        return 3
    return Request(int(parts[0]), parts[1].upper(), tuple(parts[2:]))
