"""GRBL 1.1 serial protocol: what the controller sends back, parsed line by line (pure functions).

Follows the GRBL 1.1 interface documents (gnea/grbl ``doc/markdown/interface.md``): every
line sent gets exactly one response ``ok`` or ``error:N``; push messages (``<…>`` status
reports, ``ALARM:N``, ``[MSG:…]`` and other ``[…]`` feedback, ``$N=V`` settings, the
``Grbl 1.1h ['$' for help]`` welcome banner, ``>…:ok`` startup echoes) may arrive at any time
and are never responses. The parsers accept any text and never raise.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

RX_BUFFER_SIZE = 128  # GRBL 1.1 serial receive buffer (bytes); [OPT:…,128] reports it
PLANNER_BLOCKS = 15

ERROR_CODES = {
    1: "Expected command letter", 2: "Bad number format", 3: "Invalid statement", 4: "Value < 0",
    5: "Setting disabled (homing not enabled)", 6: "Value < 3 usec", 7: "EEPROM read fail. Using defaults",
    8: "Not idle", 9: "G-code lock (alarm or jog state)", 10: "Soft limits need homing enabled",
    11: "Line overflow", 12: "Step rate > 30kHz", 13: "Check door", 14: "Line length exceeded",
    15: "Jog travel exceeded", 16: "Invalid jog command", 17: "Laser mode requires PWM",
    20: "Unsupported command", 21: "Modal group violation", 22: "Undefined feed rate",
    23: "Command requires integer value", 24: "Two G-code commands both need axis words",
    25: "Repeated G-code word", 26: "No axis words", 27: "Invalid line number", 28: "Missing value word",
    29: "G59.x not supported", 30: "G53 only with G0/G1", 31: "Axis words not used", 32: "Arc needs in-plane axis",
    33: "Invalid motion target", 34: "Invalid arc radius", 35: "Arc needs in-plane offset",
    36: "Unused value words", 37: "G43.1 axis", 38: "Tool number too large",
}

ALARM_CODES = {
    1: "Hard limit triggered", 2: "Soft limit: motion target exceeds machine travel",
    3: "Reset while in motion (position may be lost)", 4: "Probe fail: not in expected initial state",
    5: "Probe fail: no contact", 6: "Homing fail: reset during homing", 7: "Homing fail: door opened",
    8: "Homing fail: pull-off did not clear limit switch", 9: "Homing fail: limit switch not found",
}

STATES = ("Idle", "Run", "Hold", "Jog", "Alarm", "Door", "Check", "Home", "Sleep")


@dataclass(frozen=True)
class StatusReport:
    """One ``<…>`` real-time status report. Positions in the controller's report units."""

    state: str  # Idle, Run, Hold, Jog, Alarm, Door, Check, Home, Sleep
    substate: int | None = None  # Hold:0 complete / Hold:1 holding; Door:0..3
    mpos: tuple[float, float, float] | None = None
    wpos: tuple[float, float, float] | None = None
    wco: tuple[float, float, float] | None = None
    feed: float | None = None
    spindle: float | None = None
    planner_free: int | None = None  # Bf: free planner blocks
    rx_free: int | None = None  # Bf: free bytes in the serial receive buffer
    line_number: int | None = None
    pins: str | None = None
    overrides: tuple[int, int, int] | None = None

    @property
    def state_word(self) -> str:
        """The state as GRBL prints it, with the substate: ``Hold:0``, ``Door:1``, ``Idle``."""
        return self.state if self.substate is None else f"{self.state}:{self.substate}"

    def machine_position(self, wco: tuple[float, float, float] | None = None) -> tuple[float, float, float] | None:
        """MPos; from WPos + WCO when the controller reports WPos ($10=0). None when unknown."""
        if self.mpos is not None:
            return self.mpos
        offset = self.wco or wco
        if self.wpos is not None and offset is not None:
            w, o = self.wpos, offset
            return (w[0] + o[0], w[1] + o[1], w[2] + o[2])
        return None


@dataclass(frozen=True)
class GrblMessage:
    """A parsed line from GRBL. ``kind`` is one of: ok, error, alarm, status, banner, msg,
    feedback, setting, startup, empty, unknown."""

    kind: str
    raw: str
    code: int | None = None
    status: StatusReport | None = None
    text: str = ""
    fields: dict = field(default_factory=dict)

    @property
    def is_response(self) -> bool:
        """True only for the one reply each sent line gets (``ok`` / ``error:N``)."""
        return self.kind in ("ok", "error")

    @property
    def report(self) -> StatusReport:
        """The report of a ``status`` message (``parse_line`` sets one on every such message)."""
        if self.status is None:
            raise ValueError(f"not a status report: {self.raw!r}")
        return self.status

    @property
    def number(self) -> int:
        """The code of an ``error``/``alarm`` message or the number of a ``setting`` one."""
        if self.code is None:
            raise ValueError(f"a GRBL message without a code: {self.raw!r}")
        return self.code


_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)"
_BANNER = re.compile(r"^Grbl\s+(\S+)\s*\[.*\]$")
_SETTING = re.compile(rf"^\$(\d+)=({_NUM})(?:\s*\(.*\))?$")


def _floats(text: str, n: int | None = None) -> tuple[float, ...] | None:
    parts = text.split(",")
    if n is not None and len(parts) != n:
        return None
    out = []
    for p in parts:
        if not re.fullmatch(_NUM, p.strip()):
            return None
        v = float(p)
        if not math.isfinite(v):
            return None
        out.append(v)
    return tuple(out)


def parse_status(text: str) -> StatusReport | None:
    """Parse ``<State|MPos:x,y,z|FS:f,s|…>``; None when it is not a well-formed report."""
    if not (text.startswith("<") and text.endswith(">")) or len(text) < 3:
        return None
    parts = text[1:-1].split("|")
    word = parts[0]
    state, _, sub = word.partition(":")
    if state not in STATES:
        return None
    substate = None
    if sub:
        if not sub.isdigit() or len(sub) > 3:
            return None
        substate = int(sub)
    values: dict = {}
    for part in parts[1:]:
        key, sep, val = part.partition(":")
        if not sep:
            continue
        if key in ("MPos", "WPos", "WCO"):
            v = _floats(val)
            if v is None or len(v) < 3:
                return None
            values[key.lower()] = v[:3]
        elif key == "FS":
            v = _floats(val)
            if v is None or len(v) < 1:
                return None
            values["feed"] = v[0]
            values["spindle"] = v[1] if len(v) > 1 else None
        elif key == "F":
            v = _floats(val, 1)
            if v is None:
                return None
            values["feed"] = v[0]
        elif key == "Bf":
            v = _floats(val, 2)
            if v is None:
                return None
            values["planner_free"], values["rx_free"] = int(v[0]), int(v[1])
        elif key == "Ln":
            if val.isdigit():
                values["line_number"] = int(val)
        elif key == "Pn":
            values["pins"] = val
        elif key == "Ov":
            v = _floats(val, 3)
            if v is not None:
                values["overrides"] = tuple(int(x) for x in v)
        # unknown fields (A:, future ones) are ignored, as the interface document asks
    if "mpos" not in values and "wpos" not in values:
        return None
    return StatusReport(state=state, substate=substate, **values)


def parse_line(line: str | bytes) -> GrblMessage:
    """Classify one line received from GRBL (without its line ending). Never raises."""
    if isinstance(line, bytes | bytearray):
        line = bytes(line).decode("ascii", errors="replace")
    raw = line
    s = line.strip()
    if not s:
        return GrblMessage("empty", raw)
    if s == "ok":
        return GrblMessage("ok", raw)
    if s.startswith("error:"):
        code = s[6:]
        return GrblMessage("error", raw, code=int(code), text=ERROR_CODES.get(int(code), "")) if code.isdigit() \
            and len(code) < 4 else GrblMessage("unknown", raw)
    if s.startswith("ALARM:"):
        code = s[6:]
        return GrblMessage("alarm", raw, code=int(code), text=ALARM_CODES.get(int(code), "")) if code.isdigit() \
            and len(code) < 4 else GrblMessage("unknown", raw)
    if s.startswith("<"):
        st = parse_status(s)
        return GrblMessage("status", raw, status=st) if st is not None else GrblMessage("unknown", raw)
    if s.startswith("[") and s.endswith("]"):
        body = s[1:-1]
        key, sep, val = body.partition(":")
        if key == "MSG" and sep:
            return GrblMessage("msg", raw, text=val)
        return GrblMessage("feedback", raw, text=val if sep else body, fields={"key": key if sep else ""})
    m = _BANNER.match(s)
    if m:
        return GrblMessage("banner", raw, text=m.group(1))
    m = _SETTING.match(s)
    if m:
        return GrblMessage("setting", raw, code=int(m.group(1)), fields={"value": float(m.group(2))})
    if s.startswith(">") and s.endswith((":ok", ":error")) or s.startswith(">") and ":error:" in s:
        return GrblMessage("startup", raw, text=s[1:])
    return GrblMessage("unknown", raw)


def parse_version(feedback: list[GrblMessage]) -> dict:
    """Version and buffer sizes from the ``$I`` feedback lines ``[VER:…]`` and ``[OPT:…]``."""
    info: dict = {}
    for msg in feedback:
        if msg.kind != "feedback":
            continue
        key = msg.fields.get("key")
        if key == "VER":
            info["version"] = msg.text.split(":")[0]
        elif key == "OPT":
            parts = msg.text.split(",")
            info["options"] = parts[0]
            if len(parts) >= 3 and parts[1].isdigit() and parts[2].isdigit():
                info["planner_blocks"] = int(parts[1])
                info["rx_buffer"] = int(parts[2])
    return info
