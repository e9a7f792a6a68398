"""The NC X-Y table behind a GRBL 1.1 controller (DESIGN §3), over :class:`SerialLink`.

* Connecting works whether or not opening the port resets the board: it waits briefly for the
  ``Grbl 1.1h`` banner while querying ``?``; a status report proves the controller is alive
  without a reset (``socket://``/ser2net); if neither comes, a soft reset (0x18) is tried,
  then :class:`~labctl.drivers.serial_link.DeviceTimeout` — never an endless wait.
* Streaming uses GRBL's character-counting protocol: lines are sent while the bytes of every
  unacknowledged line fit in the 128-byte receive buffer (≤ 127 bytes in flight); each ``ok``
  or ``error:N`` releases the oldest line. Status is polled with ``?`` at ``status_hz`` and
  reports are parsed line by line; a status report is never counted as a response.
* ``error:N`` → :class:`GrblError`, ``ALARM:N`` → :class:`GrblAlarm`, a banner mid-stream →
  :class:`GrblReset`; all are :class:`labctl.errors.DeviceError`.
"""

from __future__ import annotations

import logging
import re
import time
from collections import deque
from collections.abc import Callable, Iterable

from ..errors import DeviceError
from .grbl_protocol import (
    ALARM_CODES,
    ERROR_CODES,
    RX_BUFFER_SIZE,
    GrblMessage,
    StatusReport,
    parse_line,
    parse_version,
)
from .interfaces import OpenClose, TableStatus
from .serial_link import DeviceTimeout, ProtocolError, SerialLink

log = logging.getLogger(__name__)

MAX_LINE = 79  # GRBL's line buffer (80) minus the terminator


class GrblError(DeviceError):
    """GRBL answered ``error:N`` to a line."""

    def __init__(self, code: int, line: str = "", index: int | None = None):
        self.code, self.line, self.index = code, line, index
        where = f" (line {index + 1})" if index is not None else ""
        super().__init__(f"GRBL error:{code} {ERROR_CODES.get(code, 'unknown error')}{where}: {line!r}")


class GrblAlarm(DeviceError):
    """GRBL raised ``ALARM:N`` (or is locked in the Alarm state)."""

    def __init__(self, code: int | None, detail: str = ""):
        self.code = code
        text = ALARM_CODES.get(code, "alarm state") if code is not None else "controller is in the Alarm state"
        super().__init__(f"GRBL ALARM:{code if code is not None else '-'} {text}{'; ' + detail if detail else ''}")


class GrblReset(DeviceError):
    """The controller reset (banner) while lines were in flight."""


def dwell_s(line: str) -> float:
    """Seconds a cleaned line dwells (``G4 P…``), 0 for anything else."""
    m = re.search(r"G0*4(?![0-9.])", line)
    p = re.search(r"P([-+]?\d*\.?\d+)", line)
    return float(p.group(1)) if m and p else 0.0


def clean_line(line: str) -> str:
    """A G-code line as sent: comments and whitespace removed (GRBL ignores both)."""
    line = re.sub(r"\([^)]*\)", "", line.split(";", 1)[0])
    return "".join(line.split())


class GrblTable(OpenClose):
    """:class:`labctl.drivers.interfaces.Table` for a GRBL 1.1 controller."""

    def __init__(self, port: str | None = None, baud: int = 9600, *, timeout_s: float = 5.0,
                 reset_on_open: bool = True, status_hz: float = 5.0, boot_s: float = 2.5,
                 serial_port=None, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep, rx_buffer: int = RX_BUFFER_SIZE,
                 auto_unlock: bool = True):
        self.link = SerialLink(port, baud, timeout_s, port=serial_port, clock=clock, sleep=sleep,
                               name=f"grbl@{port or getattr(serial_port, 'port', 'port')}")
        self.timeout_s = timeout_s
        self.reset_on_open = reset_on_open
        self.status_period = 1.0 / max(status_hz, 0.1)
        self.boot_s = boot_s
        self.clock, self.sleep = clock, sleep
        self.rx_limit = rx_buffer - 1
        self.last_status: StatusReport | None = None
        self.last_status_t = -1e18
        self._last_query_t = -1e18
        self._wco = (0.0, 0.0, 0.0)
        self.info: dict = {}
        self.messages: deque[str] = deque(maxlen=200)  # the newest [MSG:…] lines (bounded)
        self._alarm: int | None = None
        self._reset_seen = False
        self.connected_by = ""
        self.status_reports = 0
        self.max_in_flight = 0
        self.auto_unlock = auto_unlock
        self.locked = False  # GRBL ignores lines until a reset (critical alarm)
        self.session_alarm: int | None = None  # the last ALARM:N seen since open

    @classmethod
    def from_config(cls, cfg, **kw) -> GrblTable:
        """From a :class:`labctl.config.TableConfig` (port, baud, timeout, reset_on_open, status_hz)."""
        return cls(kw.pop("port", cfg.port), kw.pop("baud", cfg.baud), timeout_s=cfg.timeout_s,
                   reset_on_open=cfg.reset_on_open, status_hz=cfg.status_hz, **kw)

    # --- connection -------------------------------------------------------------------------
    def open(self) -> None:
        self.link.open()
        try:
            self._connect()
        except BaseException:
            self.link.close()
            raise

    def close(self) -> None:
        self.link.close()

    def _connect(self) -> None:
        """Find the controller alive: banner (board reset on open) or a status report (no reset)."""
        window = self.boot_s if self.reset_on_open else min(self.boot_s, 1.0)
        deadline = self.clock() + window
        first_query = self.clock() + (0.3 if self.reset_on_open else 0.05)
        next_query = first_query
        while self.clock() < deadline:
            if self.clock() >= next_query:
                self._query()
                next_query = self.clock() + 0.5
            for msg in self._read(0.02):
                if msg.kind == "banner":
                    self.connected_by = "banner"
                    self._after_connect()
                    return
                if msg.kind == "status":
                    self.connected_by = "status"
                    self._after_connect()
                    return
        log.info("%s: no banner and no status report; trying a soft reset", self.link.name)
        self.link.write(b"\x18")
        deadline = self.clock() + self.timeout_s
        while self.clock() < deadline:
            for msg in self._read(0.05):
                if msg.kind in ("banner", "status"):
                    self.connected_by = "soft reset"
                    self._after_connect()
                    return
        raise DeviceTimeout(f"{self.link.name}: no GRBL banner, no status report and no answer to a soft reset "
                            f"within {window + self.timeout_s:g} s")

    def _after_connect(self) -> None:
        self._alarm = None
        self.session_alarm = None
        self._reset_seen = False
        self._read(0.05)  # the rest of the banner burst ([MSG:…])
        st = self.status()
        self.locked = False
        if st.state not in ("Run", "Hold", "Jog", "Home"):
            self.locked = not self._sync()
        if self.locked:
            log.warning("%s: controller ignores lines (critical alarm: reset to continue)", self.link.name)
            return
        try:
            feedback = self.command("$I")
            self.info.update(parse_version(feedback))
        except (GrblError, GrblAlarm):
            pass
        if "rx_buffer" in self.info and 16 <= self.info["rx_buffer"] <= 4096:
            self.rx_limit = min(self.rx_limit, self.info["rx_buffer"] - 1)

    def _sync(self) -> bool:
        """Terminate any half-line left in GRBL's buffer and drain stale replies. False if no reply
        came (GRBL locked by a critical alarm ignores lines until reset)."""
        self.link.write(b"\n")
        deadline = self.clock() + min(self.timeout_s, 1.5)
        got = False
        while self.clock() < deadline and not got:
            got = any(m.is_response for m in self._read(0.05, raise_alarm=False))
        quiet_until = self.clock() + 0.1
        while self.clock() < quiet_until:
            if self._read(0.02, raise_alarm=False):
                quiet_until = self.clock() + 0.1
        return got

    # --- reading ----------------------------------------------------------------------------
    def _query(self) -> None:
        self.link.write(b"?")
        self._last_query_t = self.clock()

    def _handle(self, msg: GrblMessage) -> None:
        if msg.kind == "status":
            st = msg.status
            if st.wco is not None:
                self._wco = st.wco
            self.last_status, self.last_status_t = st, self.clock()
            self.status_reports += 1
        elif msg.kind == "alarm":
            self._alarm = msg.code
            self.session_alarm = msg.code
            log.warning("%s: ALARM:%s %s", self.link.name, msg.code, msg.text)
        elif msg.kind == "banner":
            self._reset_seen = True
            self.info["version"] = msg.text
        elif msg.kind == "msg":
            self.messages.append(msg.text)
            log.info("%s: [MSG:%s]", self.link.name, msg.text)
        elif msg.kind == "unknown":
            log.warning("%s: unexpected line %r", self.link.name, msg.raw)

    def _read(self, timeout_s: float, raise_alarm: bool = True) -> list[GrblMessage]:
        out = []
        for line in self.link.lines(timeout_s):
            msg = parse_line(line)
            self._handle(msg)
            out.append(msg)
        if raise_alarm and self._alarm is not None:
            code, self._alarm = self._alarm, None
            raise GrblAlarm(code, "reset (labctl table reset), then home or unlock before moving")
        return out

    def _maybe_poll(self) -> None:
        if self.clock() - self._last_query_t >= self.status_period:
            self._query()

    # --- commands ---------------------------------------------------------------------------
    def command(self, line: str, timeout_s: float | None = None) -> list[GrblMessage]:
        """Send one line, wait for its ``ok``; returns the push messages that came before it."""
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        self.link.send_line(line)
        got: list[GrblMessage] = []
        deadline = self.clock() + timeout_s
        while True:
            for msg in self._read(0.02):
                if msg.kind == "ok":
                    return got
                if msg.kind == "error":
                    raise GrblError(msg.code, line)
                if msg.kind == "banner":
                    raise GrblReset(f"{self.link.name}: controller reset while running {line!r}")
                if msg.kind != "status":
                    got.append(msg)
                elif msg.status.state in ("Run", "Home", "Jog", "Hold"):
                    deadline = max(deadline, self.clock() + timeout_s)  # busy, not silent
            if self.clock() > deadline:
                raise DeviceTimeout(f"{self.link.name}: no reply to {line!r} within {timeout_s:g} s")
            self._maybe_poll()

    def status(self, max_age_s: float | None = None) -> TableStatus:
        """Query ``?`` and return the next report (a fresh one if younger than ``max_age_s``)."""
        if max_age_s is not None and self.last_status is not None and self.clock() - self.last_status_t <= max_age_s:
            return self._table_status()
        wait = self._last_query_t + self.status_period - self.clock()
        if 0 < wait < self.status_period and self.last_status_t >= self._last_query_t:
            self.sleep(wait)  # bounded polling rate
        before = self.status_reports
        deadline = self.clock() + self.timeout_s
        self._query()
        next_query = self.clock() + max(self.status_period, 0.25)
        while self.status_reports == before:
            if self.clock() > deadline:
                raise DeviceTimeout(f"{self.link.name}: no status report within {self.timeout_s:g} s")
            self._read(0.02, raise_alarm=False)
            if self.clock() >= next_query and self.status_reports == before:
                self._query()  # a '?' may be lost on a noisy line
                next_query = self.clock() + max(self.status_period, 0.25)
        return self._table_status()

    def _table_status(self) -> TableStatus:
        st = self.last_status
        pos = st.machine_position(self._wco) or st.wpos or (0.0, 0.0, 0.0)  # WPos until a WCO arrives
        return TableStatus(state=st.state_word, position=tuple(float(v) for v in pos),
                           feed_mm_min=float(st.feed or 0.0), t=self.last_status_t)

    def work_position(self) -> tuple[float, float, float] | None:
        st = self.last_status
        if st is None:
            return None
        if st.wpos is not None:
            return st.wpos
        return tuple(m - o for m, o in zip(st.mpos, self._wco)) if st.mpos is not None else None

    def settings(self) -> dict[int, float]:
        """``$$``: every setting as {number: value}."""
        return {m.code: m.fields["value"] for m in self.command("$$") if m.kind == "setting"}

    def unlock(self) -> None:
        """``$X``: leave the Alarm state without homing."""
        self.command("$X")

    def home(self, timeout_s: float = 120.0) -> None:
        """``$H``: run the homing cycle (GrblError 5 if homing is disabled)."""
        self.command("$H", timeout_s=timeout_s)

    def ensure_ready(self, unlock: bool = True) -> TableStatus:
        """Idle and unlocked. The power-up homing lock is released with ``$X`` if ``unlock``; an
        alarm raised since open (limits, aborted motion) is never cleared silently: GrblAlarm."""
        st = self.status()
        if st.state == "Alarm":
            if getattr(self, "locked", False):
                raise GrblAlarm(None, "locked after a critical alarm (limits); reset it first: labctl table reset")
            if self.session_alarm is not None:
                raise GrblAlarm(self.session_alarm, "the table alarmed during this session; check it, then reset "
                                "and home or unlock")
            if not unlock:
                raise GrblAlarm(None, "run `labctl table home` or unlock first")
            self.unlock()
            st = self.status()
        if st.state.startswith("Hold"):
            self.resume()
            st = self.status()
        return st

    # --- streaming --------------------------------------------------------------------------
    def stream(self, lines: Iterable[str], on_progress: Callable[[int, TableStatus | None], None] | None = None
               ) -> int:
        """Character-counting stream; returns once every line has its ``ok``. Returns lines sent.

        GrblError on the first ``error:N`` (after the lines in flight are answered), GrblAlarm
        on an alarm, GrblReset if the controller resets, DeviceTimeout if it goes silent, and
        ProtocolError if replies are lost (GRBL idle while lines still wait for their ``ok``).
        """
        program = [c for c in (clean_line(raw) for raw in lines) if c]
        for i, line in enumerate(program):
            if len(line) > MAX_LINE:
                raise GrblError(11, line, i)
        if self.last_status is None or self.last_status.state == "Alarm":
            self.ensure_ready(unlock=self.auto_unlock)
        in_flight: deque[tuple[int, int]] = deque()  # (index, bytes)
        used = 0
        sent = 0
        first_error: GrblError | None = None
        self._reset_seen = False
        last_alive = last_progress = self.clock()
        while sent < len(program) or in_flight:
            while sent < len(program) and first_error is None:
                data = (program[sent] + "\n").encode("ascii")
                if used + len(data) > self.rx_limit:
                    break
                self.link.write(data)
                in_flight.append((sent, len(data)))
                used += len(data)
                self.max_in_flight = max(self.max_in_flight, used)
                sent += 1
            if first_error is not None and not in_flight:
                break
            self._maybe_poll()
            msgs = self._read(0.01)
            now = self.clock()
            if any(m.kind != "unknown" for m in msgs):
                last_alive = now
            for msg in msgs:
                if msg.is_response:
                    if not in_flight:
                        raise ProtocolError(f"{self.link.name}: a reply {msg.raw!r} with no line in flight")
                    idx, n = in_flight.popleft()
                    used -= n
                    last_progress = now
                    if msg.kind == "error" and first_error is None:
                        first_error = GrblError(msg.code, program[idx], idx)
                elif msg.kind == "banner" or self._reset_seen:
                    raise GrblReset(f"{self.link.name}: controller reset while streaming "
                                    f"({len(in_flight)} lines lost, {sent}/{len(program)} sent)")
                elif msg.kind == "status":
                    if msg.status.state in ("Run", "Hold", "Home", "Jog", "Door"):
                        last_progress = now  # busy executing: replies come as the planner drains
                    elif msg.status.state == "Alarm" and in_flight:
                        raise GrblAlarm(None, f"the controller entered Alarm while streaming "
                                              f"({sent}/{len(program)} lines sent)")
                    if on_progress is not None:
                        on_progress(sent - len(in_flight), self._table_status())
            if now - last_alive > self.timeout_s:
                raise DeviceTimeout(f"{self.link.name}: GRBL went silent while streaming "
                                    f"({sent}/{len(program)} lines sent)")
            if (in_flight and now - last_alive < self.timeout_s / 2
                    and now - last_progress > self.timeout_s + sum(dwell_s(program[i]) for i, _ in in_flight)):
                raise ProtocolError(f"{self.link.name}: {len(in_flight)} lines got no reply although GRBL is not "
                                    "busy (replies lost on the line?)")
        if first_error is not None:
            raise first_error
        return sent

    def wait_idle(self, timeout_s: float | None = None) -> TableStatus:
        """Wait until the motion queued so far has finished (``G4 P0`` then an Idle report)."""
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        self.stream(["G4P0"])
        deadline = self.clock() + timeout_s
        while True:
            st = self.status()
            if st.state == "Idle":
                return st
            if self.clock() > deadline:
                raise DeviceTimeout(f"{self.link.name}: table not idle after {timeout_s:g} s (state {st.state})")

    def move_to(self, x: float, y: float, feed_mm_min: float | None = None, z: float | None = None) -> TableStatus:
        """Move (G90 G21 G1, or G0 without a feed) to machine-table coordinates and wait until there."""
        axes = f"X{x:.3f}Y{y:.3f}" + (f"Z{z:.3f}" if z is not None else "")
        motion = f"G1{axes}F{feed_mm_min:.1f}" if feed_mm_min else f"G0{axes}"
        self.stream(["G21G90", motion])
        return self.wait_idle()

    # --- real-time --------------------------------------------------------------------------
    def feed_hold(self) -> None:
        self.link.write(b"!")

    def resume(self) -> None:
        self.link.write(b"~")

    def reset(self) -> None:
        """Soft reset (0x18): stop at once, discard the plan; waits for the banner."""
        self.link.write(b"\x18")
        deadline = self.clock() + self.timeout_s
        while self.clock() < deadline:
            if any(m.kind == "banner" for m in self._read(0.05, raise_alarm=False)):
                self._read(0.05, raise_alarm=False)
                self._alarm = None
                self.locked = False
                return
        raise DeviceTimeout(f"{self.link.name}: no banner after a soft reset")

    def stop(self) -> None:
        """Feed hold, wait (bounded) for the hold to complete, then reset: position is kept."""
        self.feed_hold()
        deadline = self.clock() + self.timeout_s
        try:
            while self.clock() < deadline:
                st = self.status()
                if st.state in ("Hold:0", "Idle", "Alarm"):
                    break
        finally:
            self.reset()
