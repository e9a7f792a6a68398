"""The NC X-Y table behind a GRBL 1.1 controller (docs/architecture.md, the `drivers` layer), over :class:`SerialLink`.

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
from collections import deque
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING

from ..errors import DeviceError
from ..timebase import Clock
from .clock import MONOTONIC
from .grbl_protocol import (
    ALARM_CODES,
    ERROR_CODES,
    RX_BUFFER_SIZE,
    GrblMessage,
    StatusReport,
    parse_line,
    parse_version,
)
from .interfaces import OpenClose, Table, TableStatus
from .serial_link import DeviceTimeout, LinkError, LinkLost, ProtocolError, SerialLink

if TYPE_CHECKING:
    from ..config import TableConfig
    from .interfaces import Program

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())  # warnings go to the record/-v, not stray stderr lines

MAX_LINE = 79  # GRBL's line buffer (80) minus the terminator


BUSY = ("Run", "Hold", "Jog", "Home", "Door")
_OFFSET_WORDS = re.compile(r"G(?:10|92|5[4-9]|43\.1|49)(?![0-9])")


def base_state(state: str) -> str:
    """``Hold:0`` → ``Hold``: the state without its sub-state."""
    return state.split(":", 1)[0]


class GrblError(DeviceError):
    """GRBL answered ``error:N`` to a line. ``index`` is the line's place among the streamed lines,
    ``file_line`` its 1-based line number in the file it came from (when known)."""

    def __init__(self, code: int, line: str = "", index: int | None = None, file_line: int | None = None):
        self.code, self.line, self.index, self.file_line = code, line, index, file_line
        if file_line is not None:
            where = f" (file line {file_line})"
        elif index is not None:
            where = f" (line {index + 1})"
        else:
            where = ""
        super().__init__(f"GRBL error:{code} {ERROR_CODES.get(code, 'unknown error')}{where}: {line!r}")


class GrblAlarm(DeviceError):
    """GRBL raised ``ALARM:N`` (or is locked in the Alarm state)."""

    def __init__(self, code: int | None, detail: str = ""):
        self.code = code
        text = ALARM_CODES.get(code, "alarm state") if code is not None else "controller is in the Alarm state"
        super().__init__(f"GRBL ALARM:{code if code is not None else '-'} {text}{'; ' + detail if detail else ''}")


class GrblReset(DeviceError):
    """The controller reset (banner) while lines were in flight."""


class TableStall(DeviceError):
    """GRBL kept reporting ``Run`` without the position changing (a stalled or frozen machine)."""


class TableBusy(DeviceError):
    """The table is busy (Run, Hold, Jog, Home) when a command needs it Idle."""


_DWELL = re.compile(r"G0*4P\d*\.?\d*")  # a cleaned line that only dwells


def dwell_s(line: str) -> float:
    """Seconds a cleaned line dwells (``G4 P…``), 0 for anything else."""
    m = re.search(r"G0*4(?![0-9.])", line)
    p = re.search(r"P([-+]?\d*\.?\d+)", line)
    return float(p.group(1)) if m and p else 0.0


def clean_line(line: str) -> str:
    """A G-code line as sent: comments and whitespace removed (GRBL ignores both)."""
    line = re.sub(r"\([^)]*\)", "", line.split(";", 1)[0])
    return "".join(line.split())


class ProgramStream:
    """A G-code program on its way into GRBL by character counting, advanced by :meth:`pump`.

    Nothing here blocks for longer than the ``timeout_s`` given to :meth:`pump`, so a run loop can
    pump it once per iteration while it keeps tracking, planning and sending heartbeats (a long
    ``G2``/``G3`` is acknowledged only when it leaves GRBL's planner, which takes as long as the
    arc). Lines are sent while every unacknowledged line fits in GRBL's receive buffer; each
    ``ok``/``error:N`` releases the oldest line. Progress: :attr:`acked` of :attr:`total`.
    The first fault (``error:N``, alarm, reset, silence, lost replies, stall) is kept in
    :attr:`error` and raised; the lines still in GRBL then keep running until the caller stops
    the table (:meth:`GrblTable.stop`).
    """

    def __init__(self, table: GrblTable, lines: Iterable[str], line_numbers: Iterable[int] | None = None):
        raw = list(lines)
        numbers = list(line_numbers) if line_numbers is not None else list(range(1, len(raw) + 1))
        if len(numbers) != len(raw):
            raise ValueError("line_numbers must match lines")
        pairs = [(n, c) for n, c in ((n, clean_line(r)) for n, r in zip(numbers, raw)) if c]
        self.program = [c for _, c in pairs]
        self.numbers = [n for n, _ in pairs]
        self.numbered = line_numbers is not None
        for i, line in enumerate(self.program):
            if len(line) > MAX_LINE:
                raise GrblError(11, line, i, self.numbers[i] if self.numbered else None)
        self.table = table
        # only dwells (wait_idle's G4P0): a program that moves nothing, so a drop cannot leave it halfway
        self.motionless = bool(self.program) and all(_DWELL.fullmatch(line) for line in self.program)
        self.lost = False  # its link dropped and came back: its replies may never come (motionless only)
        self.in_flight: deque[tuple[int, int]] = deque()  # (index, bytes)
        self.used = 0
        self.sent = 0
        self.acked = 0
        self.error: DeviceError | None = None
        now = table.clock.now()
        self.last_alive = self.last_progress = now
        self.idle_since: float | None = None  # GRBL reported Idle while lines waited for their reply
        self.t_start = now
        #: ``(clock, unacknowledged bytes)`` after every send and every reply, if the table's
        #: ``record_fill`` is set: how full the sender kept GRBL's receive buffer (the benchmarks)
        self.fill: list[tuple[float, int]] | None = [] if table.record_fill else None

    @property
    def total(self) -> int:
        """Lines in the program."""
        return len(self.program)

    @property
    def done(self) -> bool:
        """Every line acknowledged (the motion may still be running)."""
        return self.acked == len(self.program) and self.error is None

    @property
    def active(self) -> bool:
        """Lines remain to be acknowledged and no error stopped the program (nor a drop a motionless one)."""
        return self.error is None and not self.lost and self.acked < len(self.program)

    def progress(self) -> dict:
        """``{"acked", "sent", "total", "in_flight"}`` — lines, for the record."""
        return {"acked": self.acked, "sent": self.sent, "total": self.total, "in_flight": len(self.in_flight)}

    def _on_response(self, msg: GrblMessage) -> None:
        if not self.in_flight:
            self._fail(ProtocolError(f"{self.table.link.name}: a reply {msg.raw!r} with no line in flight"))
            return
        idx, n = self.in_flight.popleft()
        self.used -= n
        self.acked += 1
        self.last_progress = self.table.clock.now()
        if self.fill is not None:
            self.fill.append((self.last_progress, self.used))
        self.idle_since = None
        if msg.kind == "error" and self.error is None:
            self._fail(GrblError(msg.number, self.program[idx], idx, self.numbers[idx] if self.numbered else None))

    def _fail(self, exc: DeviceError) -> None:
        if self.error is None:
            self.error = exc
        self.table._program_ended(self)

    def _fill(self) -> None:
        t = self.table
        while self.sent < len(self.program) and self.error is None:
            line = self.program[self.sent]
            data = (line + "\n").encode("ascii")
            if self.used + len(data) > t.rx_limit:
                break
            if _OFFSET_WORDS.search(line):
                t._wco = None  # GRBL re-sends WCO: in the next report
            t._write(data)
            self.in_flight.append((self.sent, len(data)))
            self.used += len(data)
            t.max_in_flight = max(t.max_in_flight, self.used)
            self.sent += 1
            if self.fill is not None:
                self.fill.append((t.clock.now(), self.used))

    def pump(self, timeout_s: float = 0.0) -> bool:
        """Send what fits, read what came (waiting up to ``timeout_s``), poll status at its rate.
        True while lines remain unacknowledged; raises the program's first fault."""
        if self.error is not None:
            raise self.error
        if not self.active:
            return False
        t = self.table
        try:
            self._fill()
            t._maybe_poll()
            msgs = t._read(timeout_s)
        except DeviceError as exc:
            self._fail(exc)
            raise
        now = t.clock.now()
        if any(m.kind != "unknown" for m in msgs):
            self.last_alive = now
        for msg in msgs:
            if msg.kind == "banner":
                self._fail(GrblReset(f"{t.link.name}: controller reset while streaming "
                                     f"({len(self.in_flight)} lines lost, {self.acked}/{self.total} acknowledged)"))
            elif msg.kind == "status":
                st = msg.report
                if st.state in BUSY:
                    self.last_progress = now  # executing: replies come as the planner drains
                    self.idle_since = None
                elif st.state in ("Idle", "Check") and self.in_flight:
                    self.idle_since = self.idle_since if self.idle_since is not None else now
                if st.state == "Alarm" and self.in_flight:
                    self._fail(GrblAlarm(t.session_alarm, f"the controller entered Alarm while streaming "
                                                          f"({self.acked}/{self.total} lines acknowledged)"))
        if self.error is None and t.stalled:
            self._fail(t._stall_error())
        if self.error is None and now - self.last_alive > t.timeout_s:
            self._fail(DeviceTimeout(f"{t.link.name}: GRBL went silent while streaming "
                                     f"({self.acked}/{self.total} lines acknowledged)"))
        if (self.error is None and self.in_flight and self.idle_since is not None
                and now - self.idle_since > t.timeout_s + sum(dwell_s(self.program[i]) for i, _ in self.in_flight)):
            self._fail(ProtocolError(f"{t.link.name}: {len(self.in_flight)} lines got no reply although GRBL is "
                                     "not busy (replies lost on the line?)"))
        if self.error is not None:
            raise self.error
        if not self.active:
            t._program_ended(self)
        return self.active


class GrblTable(OpenClose):
    """:class:`labctl.drivers.interfaces.Table` for a GRBL 1.1 controller."""

    def __init__(self, port: str | None = None, baud: int = 9600, *, timeout_s: float = 5.0,
                 reset_on_open: bool = True, status_hz: float = 5.0, boot_s: float = 2.5,
                 serial_port=None, clock: Clock = MONOTONIC,
                 rx_buffer: int = RX_BUFFER_SIZE,
                 auto_unlock: bool = True, reset_if_silent: bool = False, stall_reports: int = 25,
                 homing_timeout_s: float = 120.0, reconnect_s: float = 0.0, max_messages: int = 200,
                 stop_confirm_s: float = 30.0, banner_wait_s: float = 3.0, stop_total_s: float = 40.0,
                 set_remote_baud: bool = False):
        self.link = SerialLink(port, baud, timeout_s, port=serial_port, clock=clock,
                               name=f"grbl@{port or getattr(serial_port, 'port', 'port')}",
                               set_remote_baud=set_remote_baud)
        self.timeout_s = timeout_s
        self.reset_on_open = reset_on_open
        self.status_period = 1.0 / max(status_hz, 0.1)
        self.boot_s = boot_s
        self.clock = clock
        self.rx_limit = rx_buffer - 1
        self.last_status: StatusReport | None = None
        self.last_status_t = -1e18
        self._last_query_t = -1e18
        self._wco: tuple[float, float, float] | None = None  # unknown until a report carries WCO:
        self.info: dict = {}
        self.messages: deque[str] = deque(maxlen=max_messages)
        self._alarm: int | None = None
        self._reset_seen = False
        self.connected_by = ""
        self.status_reports = 0
        self.max_in_flight = 0
        self.record_fill = False  # each ProgramStream keeps its fill history (ProgramStream.fill)
        # auto_unlock: release the power-up homing lock with $X, but only after a boot banner this
        # session saw; an Alarm found on a controller that did not just boot is never cleared silently.
        self.auto_unlock = auto_unlock
        self.reset_if_silent = reset_if_silent
        self.stall_reports = stall_reports
        self.homing_timeout_s = homing_timeout_s
        self.reconnect_s = reconnect_s
        self.stop_confirm_s = stop_confirm_s  # how long stop() waits for the reset to be confirmed
        self.banner_wait_s = banner_wait_s  # after a reset, how long the banner alone is waited for
        self.stop_total_s = stop_total_s  # the whole of stop() ends within this, answered or not
        self._stop_by: float | None = None  # while stopping: the clock time every wait ends by
        self.reset_confirmed_by = ""  # "banner" or "status": how the last soft reset was confirmed
        self.locked = False  # GRBL ignores lines until a reset (critical alarm)
        self.session_alarm: int | None = None  # the last ALARM:N seen since open
        self.program: ProgramStream | None = None
        self._orphans = 0  # replies still owed to lines of an abandoned program
        self._stall_n = 0
        self._stall_pos: tuple | None = None
        self.stalled = False
        self._booted = False  # a banner was seen since open (a fresh boot or our own reset)
        self._recovering = False
        self.link_lost = False  # the link dropped and did not come back within reconnect_s
        #: called while waiting to reconnect: the caller's keep-alive (e.g. the robot's heartbeat)
        self.while_reconnecting: Callable[[], None] | None = None

    @classmethod
    def from_config(cls, cfg: TableConfig, **kw) -> GrblTable:
        """From a :class:`labctl.config.TableConfig` (port, baud, timeout, reset_on_open, status_hz,
        stall_reports, homing_timeout_s, reconnect_s, stop_confirm_s, stop_total_s, set_remote_baud). A
        ``port=None`` keyword keeps
        the
        configured port."""
        port = kw.pop("port", None) or cfg.port
        baud = kw.pop("baud", None) or cfg.baud
        kw.setdefault("stall_reports", cfg.stall_reports)
        kw.setdefault("homing_timeout_s", cfg.homing_timeout_s)
        kw.setdefault("reconnect_s", cfg.reconnect_s)
        kw.setdefault("stop_confirm_s", cfg.stop_confirm_s)
        kw.setdefault("stop_total_s", cfg.stop_total_s)
        kw.setdefault("set_remote_baud", cfg.set_remote_baud)
        return cls(port, baud, timeout_s=cfg.timeout_s, reset_on_open=cfg.reset_on_open,
                   status_hz=cfg.status_hz, **kw)

    # --- connection -------------------------------------------------------------------------
    def open(self) -> None:
        """Open the port and find the controller alive (banner or status report); the port is closed again if that
        fails."""
        self.link.open()
        try:
            self._connect()
        except BaseException:
            self.link.close()
            raise

    def close(self) -> None:
        """Close the port (use :meth:`stop` first: closing it does not stop the controller)."""
        self.link.close()

    def _connect(self) -> None:
        """Find the controller alive: banner (board reset on open) or a status report (no reset).

        Never soft-resets on its own (unless ``reset_if_silent``): a controller locked by a
        critical alarm (ALARM:1/2) ignores ``?``, and a reset would discard what it shows."""
        window = self.boot_s if self.reset_on_open else min(self.boot_s, 1.0)
        deadline = self.clock.now() + window
        first_query = self.clock.now() + (0.3 if self.reset_on_open else 0.05)
        next_query = first_query
        garbled = 0
        while self.clock.now() < deadline:
            if self._recovering and self.while_reconnecting is not None:
                self.while_reconnecting()  # the caller's keep-alive, also while the board boots
            if self.clock.now() >= next_query:
                self._query()
                next_query = self.clock.now() + 0.2
            for msg in self._read(0.02, raise_alarm=False):
                if msg.kind in ("banner", "status"):
                    self.connected_by = msg.kind
                    self._after_connect()
                    return
                garbled += msg.kind == "unknown"
        if not self.reset_if_silent:
            hint = (f"garbled bytes came back: the board likely runs at another rate than {self.link.baud} bps "
                    "(stock GRBL 1.1h: 115200)" if garbled else
                    f"nothing answered at {self.link.baud} bps: check the port and the baud rate (stock GRBL 1.1h: "
                    "115200); a controller locked by a critical alarm (ALARM:1/2) also ignores '?' — "
                    "`labctl table reset` soft-resets it")
            raise DeviceTimeout(f"{self.link.name}: no GRBL banner and no status report within {window:g} s; {hint}")
        log.info("%s: no banner and no status report; trying a soft reset", self.link.name)
        self._write(b"\x18")
        deadline = self.clock.now() + self.timeout_s
        while self.clock.now() < deadline:
            for msg in self._read(0.05, raise_alarm=False):
                if msg.kind in ("banner", "status"):
                    self.connected_by = "soft reset"
                    self._after_connect()
                    return
        raise DeviceTimeout(f"{self.link.name}: no GRBL banner, no status report and no answer to a soft reset "
                            f"within {window + self.timeout_s:g} s at {self.link.baud} bps")

    def _after_connect(self) -> None:
        self._alarm = None
        self.session_alarm = None
        self._reset_seen = False
        if self.connected_by == "status" and self.last_status is not None:
            # found alive by the report just read: no banner burst to wait for, and that report is the state
            # (another '?' now would first wait out the polling period, then a round trip: ~0.15 s at 9600 bps)
            state = self.last_status.state
        else:
            self._read(0.05, raise_alarm=False)  # the rest of the banner burst ([MSG:…])
            state = self.status().state
        self.locked = False
        if base_state(state) not in BUSY:
            # a controller that has just answered '?' is not in the critical-alarm loop (1.1h serves no status
            # there): its 'ok' may only be slow (a loaded host), so it gets the whole reply timeout, and no 'ok'
            # is a timeout, not a lock
            answered = self.connected_by == "status"
            self.locked = not self._sync(patient=answered)
            if self.locked and answered:
                raise DeviceTimeout(f"{self.link.name}: a status report came but no 'ok' to an empty line within "
                                    f"{max(self.timeout_s, 1.5):g} s")
        if self.locked:
            log.warning("%s: controller ignores lines (critical alarm: reset to continue)", self.link.name)
            return
        if state not in ("Idle", "Alarm", "Check"):
            return  # $I needs Idle/Alarm; a held or running GRBL would queue the line
        try:
            feedback = self.command("$I")
            self.info.update(parse_version(feedback))
        except (GrblError, GrblAlarm):
            pass
        if "rx_buffer" in self.info and 16 <= self.info["rx_buffer"] <= 4096:
            self.rx_limit = min(self.rx_limit, self.info["rx_buffer"] - 1)

    def _sync(self, patient: bool = False) -> bool:
        """Terminate any half-line left in GRBL's buffer and drain stale replies. False if no reply
        came (GRBL locked by a critical alarm ignores lines until reset) within 1.5 s, or (``patient``)
        within the reply timeout (at least 1.5 s)."""
        self._write(b"\n")
        deadline = self.clock.now() + (max(self.timeout_s, 1.5) if patient else min(self.timeout_s, 1.5))
        got = False
        while self.clock.now() < deadline and not got:
            got = any(m.is_response for m in self._read(0.05, raise_alarm=False))
        quiet_until = self.clock.now() + 0.1
        while self.clock.now() < quiet_until:
            if self._read(0.02, raise_alarm=False):
                quiet_until = self.clock.now() + 0.1
        return got

    # --- reading ----------------------------------------------------------------------------
    def _query(self) -> None:
        self._write(b"?")
        self._last_query_t = self.clock.now()

    def _handle(self, msg: GrblMessage) -> None:
        if msg.kind == "status":
            st = msg.report
            if st.wco is not None:
                self._wco = st.wco
            self._track_stall(st)
            self.last_status, self.last_status_t = st, self.clock.now()
            self.status_reports += 1
        elif msg.is_response:
            if self.program is not None and self.program.in_flight:
                self.program._on_response(msg)
            elif self._orphans > 0:
                self._orphans -= 1
                msg.fields["orphan"] = True
        elif msg.kind == "alarm":
            self._alarm = msg.code
            self.session_alarm = msg.code
            if msg.code in (1, 2):
                self.locked = True  # critical: GRBL now ignores lines and '?' until a reset
            log.warning("%s: ALARM:%s %s", self.link.name, msg.code, msg.text)
        elif msg.kind == "banner":
            self._reset_seen = True
            self._booted = True
            self._orphans = 0
            self._wco = None
            # the banner says "1.1h"; $I's "1.1h.20190830" (read once at connect) is the same and says more
            if not str(self.info.get("version", "")).startswith(msg.text):
                self.info["version"] = msg.text
        elif msg.kind == "msg":
            self.messages.append(msg.text)
            log.info("%s: [MSG:%s]", self.link.name, msg.text)
        elif msg.kind == "unknown":
            log.warning("%s: unexpected line %r", self.link.name, msg.raw)

    def _track_stall(self, st: StatusReport) -> None:
        """Count consecutive ``Run`` reports whose position has not changed (:attr:`stalled`)."""
        pos = st.mpos if st.mpos is not None else st.wpos
        if st.state != "Run" or pos is None:
            self._stall_n, self._stall_pos, self.stalled = 0, None, False
            return
        if self._stall_pos is not None and all(abs(a - b) < 5e-4 for a, b in zip(pos, self._stall_pos)):
            self._stall_n += 1
        else:
            self._stall_n = 0
        self._stall_pos = pos
        self.stalled = self.stall_reports > 0 and self._stall_n >= self.stall_reports

    def _stall_error(self) -> TableStall:
        p = self._stall_pos or (float("nan"),) * 3
        return TableStall(f"{self.link.name}: stalled: GRBL reported Run without moving for {self._stall_n} "
                          f"reports at {p[0]:.3f}, {p[1]:.3f} mm")

    def _write(self, data: bytes) -> None:
        try:
            self.link.write(data)
        except LinkError as exc:
            self._recover(exc)
            self.link.write(data)  # recovered with nothing in flight: the same bytes again

    def _recover(self, exc: LinkError) -> None:
        """The port failed. With ``reconnect_s`` > 0, reopen it with backoff (LinkLost if it stays
        down), then read the controller's state again before anything else is sent. Returns only
        if nothing was in flight and the table is not in Alarm; otherwise stops it if it is still
        moving and raises (GrblAlarm after a reset/alarm, LinkLost after a drop mid-program)."""
        if self.reconnect_s <= 0 or self._recovering:
            raise exc
        self._recovering = True
        t0 = self.clock.now()
        prog, self.program = self.program, None
        # once the link was given up for lost, one quick try (the stop path after a LinkLost must not
        # wait a whole window per command it sends)
        window = 0.0 if self.link_lost else self.reconnect_s
        if not self.link_lost:
            log.warning("%s: link dropped (%s); reconnecting for up to %g s", self.link.name, exc, window)
        deadline = t0 + window
        first = True
        try:
            while True:
                try:  # the whole window the first time (its message names it), what is left after that
                    self.link.reconnect(window if first else max(0.0, deadline - self.clock.now()),
                                        idle=self.while_reconnecting)
                    first = False
                except LinkLost:
                    self.link_lost = True
                    raise
                self._orphans = 0
                try:
                    self._connect()  # banner or status: the state is read again
                    # a banner seen now proves no clean power-up: an ALARM:3 before it may have gone into
                    # the dropped link, so auto_unlock must not clear what follows
                    self._booted = False
                    break
                except (DeviceTimeout, LinkError) as silent:
                    # the port is back but the board still boots (a reset: GRBL answers nothing for ~2 s), or
                    # the port dropped again: try again within the same window
                    if self.clock.now() >= deadline:
                        self.link_lost = True
                        raise LinkLost(f"{self.link.name}: the port came back but GRBL did not answer within "
                                       f"{window:g} s ({silent})") from silent
                    log.info("%s: the port is back, GRBL not yet; trying again", self.link.name)
            self.link_lost = False
            st = self.status()
            dt = self.clock.now() - t0
            if base_state(st.state) == "Alarm":
                raise GrblAlarm(self.session_alarm, f"after the link came back ({dt:.1f} s; the controller reset or "
                                                    "alarmed): the position may be lost; home or unlock before moving")
            if prog is not None and prog.active and prog.motionless:
                # a dwell moves nothing: whether or not it reached GRBL, the motion before it goes on; the
                # waiter (wait_idle) waits for Idle by status and drains the dwell's late ok
                prog.lost = True
                log.warning("%s: link restored after %.1f s during a wait (%s); waiting on", self.link.name, dt,
                            st.state)
                return
            if prog is not None and prog.active:
                prog.error = LinkLost(f"{self.link.name}: the link dropped mid-program ({prog.acked}/{prog.total} "
                                      f"lines acknowledged) and came back after {dt:.1f} s")
                if base_state(st.state) in BUSY:
                    st = self.stop()
                p = st.position
                raise LinkLost(f"{prog.error}; the program was abandoned and the table stopped: {st.state} at "
                               f"X{p[0]:.3f} Y{p[1]:.3f}")
            log.warning("%s: link restored after %.1f s; state %s", self.link.name, dt, st.state)
        finally:
            self._recovering = False

    def _read(self, timeout_s: float, raise_alarm: bool = True) -> list[GrblMessage]:
        out = []
        try:
            lines = self.link.lines(timeout_s)
        except LinkError as exc:
            self._recover(exc)
            lines = []
        for line in lines:
            msg = parse_line(line)
            self._handle(msg)
            out.append(msg)
        if raise_alarm and self._alarm is not None:
            code, self._alarm = self._alarm, None
            raise GrblAlarm(code, _alarm_advice(code))
        return out

    def watch(self) -> None:
        """Keep an eye on the table between commands, without waiting: pump the program if one is
        streaming, else ask for a status report at ``status_hz`` and read what has arrived. So a
        caller busy with other things notices a dropped link here (reconnected within
        ``reconnect_s``, else LinkLost), an alarm (GrblAlarm) or a stall (TableStall)."""
        if self.program is not None and self.program.active:
            self.program.pump(0.0)
            return
        self._maybe_poll()
        self._read(0.0)
        if self.stalled:
            raise self._stall_error()

    def _maybe_poll(self) -> None:
        if self.clock.now() - self._last_query_t >= self.status_period:
            self._query()

    def _program_ended(self, prog: ProgramStream) -> None:
        if self.program is prog:
            self.program = None
            self._orphans += len(prog.in_flight)

    # --- commands ---------------------------------------------------------------------------
    def command(self, line: str, timeout_s: float | None = None) -> list[GrblMessage]:
        """Send one line, wait for its ``ok``; returns the push messages that came before it."""
        if self.program is not None:
            raise TableBusy(f"{self.link.name}: a program is streaming; {line!r} must wait until it is accepted")
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        if _OFFSET_WORDS.search(clean_line(line)):
            self._wco = None
        self._write((line + "\n").encode("ascii"))
        got: list[GrblMessage] = []
        deadline = self.clock.now() + timeout_s
        while True:
            for msg in self._read(0.02):
                if msg.is_response and msg.fields.get("orphan"):
                    continue  # owed to a line of an abandoned program
                if msg.kind == "ok":
                    return got
                if msg.kind == "error":
                    raise GrblError(msg.number, line)
                if msg.kind == "banner":
                    raise GrblReset(f"{self.link.name}: controller reset while running {line!r}")
                if msg.kind != "status":
                    got.append(msg)
                elif msg.report.state in BUSY and msg.report.state != "Hold":
                    deadline = max(deadline, self.clock.now() + timeout_s)  # busy, not silent
            if self.stalled:
                raise self._stall_error()
            if self.clock.now() > deadline:
                raise DeviceTimeout(f"{self.link.name}: no reply to {line!r} within {timeout_s:g} s")
            self._maybe_poll()

    def status(self, max_age_s: float | None = None, paced: bool = True) -> TableStatus:
        """Query ``?`` and return the next report (a fresh one if younger than ``max_age_s``). ``paced``: queries
        at most ``status_hz`` (False: at once, for a single report right after a command's ``ok``).

        The position is the machine position (mm). Until a report has carried ``WCO:`` the work
        offset is unknown; status then keeps asking (GRBL sends WCO in every 10th report, every
        30th while busy, and in the next one after an offset changes) rather than assume zero.
        """
        if self.locked and self.session_alarm in (1, 2):
            raise GrblAlarm(self.session_alarm, _alarm_advice(self.session_alarm))
        if (max_age_s is not None and self.last_status is not None and self._wco is not None
                and self.clock.now() - self.last_status_t <= max_age_s):
            return self._table_status()
        wait = self._last_query_t + self.status_period - self.clock.now()
        if paced and 0 < wait < self.status_period and self.last_status_t >= self._last_query_t:
            self.clock.sleep(wait)  # bounded polling rate
        self._next_report(self.status_period)
        if self._wco is None:
            n = 0
            while self._wco is None:  # at most 30 quick reports: GRBL's own WCO refresh count
                n += 1
                if n > 40:
                    raise ProtocolError(f"{self.link.name}: no WCO: in {n} status reports")
                self._next_report(0.03)
        return self._table_status()

    def _next_report(self, pace_s: float) -> None:
        before = self.status_reports
        deadline = self.clock.now() + self.timeout_s
        if self._stop_by is not None and self._stop_by < deadline:
            deadline = self._stop_by
        self._query()
        next_query = self.clock.now() + max(pace_s, 0.25)
        while self.status_reports == before:
            if self.clock.now() > deadline:
                hint = " (locked by a critical alarm? `labctl table reset`)" if self.locked else ""
                raise DeviceTimeout(f"{self.link.name}: no status report within "
                                    f"{self.timeout_s:g} s{hint}{self._budget_note(deadline)}")
            self._read(0.01, raise_alarm=False)
            if self.clock.now() >= next_query and self.status_reports == before:
                self._query()  # a '?' may be lost on a noisy line
                next_query = self.clock.now() + max(pace_s, 0.25)

    def _report(self) -> StatusReport:
        """The last status report; ProtocolError when none has arrived yet."""
        if self.last_status is None:
            raise ProtocolError(f"{self.link.name}: no status report received yet")
        return self.last_status

    def _table_status(self) -> TableStatus:
        st = self._report()
        pos = st.machine_position(self._wco)
        if pos is None:
            raise ProtocolError(f"{self.link.name}: the machine position is unknown (WPos without a WCO yet)")
        return TableStatus(state=st.state_word, position=(float(pos[0]), float(pos[1]), float(pos[2])),
                           feed_mm_min=float(st.feed or 0.0), t=self.last_status_t)

    @property
    def wco(self) -> tuple[float, float, float] | None:
        """The work coordinate offset (mm, machine − work), None until GRBL has reported it."""
        return self._wco

    def work_position(self) -> tuple[float, float, float] | None:
        """Work position (mm) of the last report; None while the offset is unknown."""
        st = self.last_status
        if st is None:
            return None
        if st.wpos is not None:
            return st.wpos
        if st.mpos is None or self._wco is None:
            return None
        m, o = st.mpos, self._wco
        return (m[0] - o[0], m[1] - o[1], m[2] - o[2])

    def settings(self) -> dict[int, float]:
        """``$$``: every setting as {number: value}."""
        return {m.number: m.fields["value"] for m in self.command("$$") if m.kind == "setting"}

    def unlock(self) -> None:
        """``$X``: leave the Alarm state without homing (the operator vouches for the position)."""
        self.command("$X")
        self.session_alarm = None

    def home(self, timeout_s: float | None = None, on_progress: Callable[[float], None] | None = None,
             progress_every_s: float = 1.0) -> TableStatus:
        """``$H``: run the homing cycle; returns the status after it.

        GRBL answers neither ``?`` nor anything else while homing, so the only signs of life are
        the final ``ok`` or ``ALARM:6..9``; ``on_progress(elapsed_s)`` is called every
        ``progress_every_s`` meanwhile. DeviceTimeout after ``timeout_s`` (default
        :attr:`homing_timeout_s`); GrblError 5 if homing is disabled ($22=0)."""
        if self.program is not None:
            raise TableBusy(f"{self.link.name}: a program is streaming")
        timeout_s = self.homing_timeout_s if timeout_s is None else timeout_s
        self._write(b"$H\n")
        t0 = self.clock.now()
        next_report = t0 + progress_every_s
        while True:
            for msg in self._read(0.05):  # ALARM:N raises GrblAlarm
                if msg.kind == "ok" and not msg.fields.get("orphan"):
                    self.session_alarm = None
                    self._wco = None
                    return self.status()
                if msg.kind == "error":
                    raise GrblError(msg.number, "$H")
                if msg.kind == "banner":
                    raise GrblReset(f"{self.link.name}: controller reset while homing")
            now = self.clock.now()
            if now - t0 > timeout_s:
                raise DeviceTimeout(f"{self.link.name}: homing not finished after {timeout_s:g} s "
                                    "(raise the table's homing_timeout_s or pass --timeout)")
            if on_progress is not None and now >= next_report:
                on_progress(now - t0)
                next_report = now + progress_every_s

    def ensure_ready(self, unlock: bool | None = None, max_age_s: float | None = None) -> TableStatus:
        """Idle (or Check) and unlocked, or a typed error saying what to do. ``max_age_s``: a status report read
        that recently (s; the one :meth:`open` read) stands for the state, else one is queried; after an unlock
        a report is always read back.

        An Alarm is released with ``$X`` only if ``unlock`` (the caller vouches for the position),
        or — with ``auto_unlock`` — when this session saw the controller boot and no ALARM:N since
        (the power-up homing lock). An Alarm found on a controller that did not just boot may be
        an ALARM:3 (reset in motion, position lost): it needs a home or an explicit unlock."""
        st = self.status(max_age_s=max_age_s)
        state = base_state(st.state)
        if state == "Alarm":
            if self.locked:
                raise GrblAlarm(None, "locked after a critical alarm (limits); reset it first: labctl table reset")
            boot_lock = self.auto_unlock and self._booted and self.session_alarm is None
            if not (unlock or boot_lock):
                code = self.session_alarm
                raise GrblAlarm(code, "the table's position may be lost; home it (`labctl table home`) or, if you "
                                      "know it is right, unlock it (`--unlock`)")
            self.unlock()
            st = self.status(paced=False)  # the state $X left, read back before anything may move
            state = base_state(st.state)
        if state in BUSY:
            raise TableBusy(f"{self.link.name}: the table is {st.state}, not Idle; `labctl table reset` stops it "
                            "and discards queued motion")
        return st

    # --- streaming --------------------------------------------------------------------------
    def start_program(self, lines: Iterable[str], line_numbers: Iterable[int] | None = None) -> ProgramStream:
        """Begin streaming ``lines`` without waiting: pump the returned :class:`ProgramStream`."""
        if self.program is not None:
            raise TableBusy(f"{self.link.name}: a program is already streaming")
        prog = ProgramStream(self, lines, line_numbers)
        if self.last_status is None or self.last_status.state == "Alarm":
            self.ensure_ready(unlock=False)
        self._reset_seen = False
        self.program = prog if prog.total else None
        return prog

    def stream(self, lines: Iterable[str], on_progress: Callable[[int, TableStatus | None], None] | None = None,
               line_numbers: Iterable[int] | None = None) -> int:
        """Character-counting stream; returns once every line has its ``ok``. Returns lines sent.

        GrblError on the first ``error:N`` (naming the file line if ``line_numbers`` are given),
        GrblAlarm on an alarm, GrblReset if the controller resets, DeviceTimeout if it goes
        silent, ProtocolError if replies are lost, TableStall if it runs without moving. Lines
        already in GRBL keep running after a fault: callers stop the table (:meth:`stop`).
        """
        prog = self.start_program(lines, line_numbers)
        reports = self.status_reports
        while prog.pump(0.01):
            if on_progress is not None and self.status_reports != reports:
                reports = self.status_reports
                on_progress(prog.acked, self._table_status() if self._wco is not None else None)
        return prog.sent

    def wait_idle(self, timeout_s: float | None = None) -> TableStatus:
        """Wait until the motion queued so far has finished (``G4 P0`` then an Idle report).
        TableStall if it reports Run without moving for ``stall_reports`` reports."""
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        prog = self.start_program(["G4P0"])
        while prog.pump(0.01):
            pass
        deadline = self.clock.now() + timeout_s
        while True:
            st = self.status()
            if st.state == "Idle":
                if prog.lost:
                    self._sync()  # the dwell's ok, if it came after the drop, is not some later line's
                return st
            if self.stalled:
                raise self._stall_error()
            if prog.lost and st.state in BUSY and st.state != "Hold":
                deadline = max(deadline, self.clock.now() + timeout_s)  # the dwell's ok is gone: moving counts
            if self.clock.now() > deadline:
                raise DeviceTimeout(f"{self.link.name}: table not idle after {timeout_s:g} s (state {st.state})")

    def move_to(self, x: float, y: float, feed_mm_min: float | None = None, z: float | None = None) -> TableStatus:
        """Move in machine-table coordinates (``G53`` with G0, or G1 at ``feed_mm_min`` mm/min) and
        wait until there; work offsets (G54…, G92) do not apply."""
        axes = f"X{x:.3f}Y{y:.3f}" + (f"Z{z:.3f}" if z is not None else "")
        motion = f"G53G1{axes}F{feed_mm_min:.1f}" if feed_mm_min else f"G53G0{axes}"
        self.stream(["G21G90", motion])
        return self.wait_idle()

    # --- real-time --------------------------------------------------------------------------
    def feed_hold(self) -> None:
        """Feed hold (``!``): decelerate to a stop along the path, keeping the rest of the program."""
        self._write(b"!")

    def resume(self) -> None:
        """Cycle start (``~``): resume after a feed hold."""
        self._write(b"~")

    def reset(self, timeout_s: float | None = None) -> None:
        """Soft reset (0x18): stop at once, discard the plan; returns once the controller confirms it.

        The confirmation is the ``Grbl 1.1h`` banner GRBL prints once it has re-initialised (~0.1 s;
        ~2 s on grbl-sim at a quarter of real time when it comes back in Alarm). If none has come
        after ``banner_wait_s`` — the line lost or garbled on the way, taken by another reader of
        the port, or a controller starved of CPU that answers late — '?' is asked every 0.25 s and a
        report of Idle, Alarm or Check confirms it too (a held or running GRBL with queued motion
        reports neither until the reset took effect); a report that still shows motion pending
        means the 0x18 was lost, so it is sent again; so does GRBL's ``[MSG:Reset to continue]``
        after the 0x18 (a critical alarm's lock, which drops a reset that came before it). DeviceTimeout
        after ``timeout_s`` (default: the reply time-out) with neither.
        """
        if self.program is not None:
            self._program_ended(self.program)
        self._write(b"\x18")
        t0 = self.clock.now()
        deadline = t0 + (self.timeout_s if timeout_s is None else timeout_s)
        if self._stop_by is not None and self._stop_by < deadline:
            deadline = self._stop_by
        next_query = t0 + self.banner_wait_s
        asked = False
        self.reset_confirmed_by = ""
        while self.clock.now() < deadline:
            for msg in self._read(0.05, raise_alarm=False):
                if msg.kind == "msg" and msg.text == "Reset to continue":
                    # a critical alarm (ALARM:1/2) locks GRBL only after it printed the alarm, and the
                    # lock discards a reset that arrived in between: the lock's message after our 0x18
                    # means it was lost, and only another one ends the lock
                    log.warning("%s: GRBL locked after a critical alarm and dropped the soft reset; sending it "
                                "again", self.link.name)
                    self._write(b"\x18")
                    asked = False
                    next_query = self.clock.now() + self.banner_wait_s
                    continue
                if msg.kind == "banner":
                    self._read(0.05, raise_alarm=False)  # the rest of the banner burst ([MSG:…])
                    self._after_reset("banner")
                    return
                if msg.kind == "status" and asked:
                    state = base_state(msg.report.state)
                    if state in ("Idle", "Alarm", "Check"):
                        log.warning("%s: no banner %.1f s after a soft reset, but GRBL reports %s: taken as "
                                    "reset", self.link.name, self.clock.now() - t0, msg.report.state)
                        self._after_reset("status")
                        return
                    if state in BUSY:  # asked after the 0x18 and still holding/running: it never arrived
                        log.warning("%s: GRBL still reports %s after a soft reset; sending it again",
                                    self.link.name, msg.report.state)
                        self._write(b"\x18")
                        asked = False
                        next_query = self.clock.now() + self.banner_wait_s
            if self.clock.now() >= next_query:
                self._query()
                asked = True
                next_query = self.clock.now() + 0.25
        raise DeviceTimeout(f"{self.link.name}: no banner and no status report within "
                            f"{deadline - t0:.3g} s after a soft reset{self._budget_note(deadline)}")

    def _budget_note(self, deadline: float) -> str:
        """What a time-out inside :meth:`stop` adds: that the stop's whole budget ended the wait."""
        if self._stop_by is None or deadline < self._stop_by:
            return ""
        return (f" (the stop's budget, stop_total_s {self.stop_total_s:g} s, ran out: feed hold ≤ timeout_s, "
                f"reset ≤ stop_confirm_s, read-back ≤ timeout_s)")

    def _after_reset(self, how: str) -> None:
        """State after a confirmed soft reset: no alarm pending, not locked, no replies owed."""
        self._alarm = None
        self.locked = False
        self._orphans = 0
        self._wco = None  # asked for again: a reset may have changed the offsets (G92)
        self.reset_confirmed_by = how

    def stop(self, max_hold_s: float = 30.0) -> TableStatus:
        """Feed hold, wait for the hold to complete, soft reset, and read the state back.

        A reset after ``Hold:0`` keeps the position (GRBL reports Idle); a reset while still moving
        raises ALARM:3. So the hold is awaited for as long as the table is still decelerating
        (its position changes between reports), up to ``max_hold_s``; if it stops changing for a
        second without reaching ``Hold:0`` (or GRBL goes silent), it resets at once. The reset is
        awaited for ``stop_confirm_s`` (at least the reply time-out): stopping is the one thing not
        to give up on early. The whole stop, answered or not, ends within ``stop_total_s`` (every wait in
        it is clipped to that: a link that stays open but silent, e.g. a frozen ser2net, cannot hold the
        caller for longer). Returns the confirmed status (Idle, or Alarm); DeviceError if it still
        reports motion afterwards."""
        t0 = self.clock.now()
        outer = self._stop_by is None
        if outer:
            self._stop_by = t0 + self.stop_total_s
        try:
            return self._stop(t0, max_hold_s)
        finally:
            if outer:
                self._stop_by = None

    def _stop(self, t0: float, max_hold_s: float) -> TableStatus:
        self.feed_hold()
        try:
            n = 0
            last_pos, last_change = None, t0
            while self.clock.now() - t0 < max_hold_s and not self.locked:  # a locked GRBL has already stopped
                try:
                    self._next_report(0.05)
                except DeviceTimeout:
                    break
                n += 1
                st = self._report()
                state = st.state_word
                # the first report may have been asked for before the '!': trust Idle only from the second
                if state == "Hold:0" or (n >= 2 and state in ("Idle", "Alarm", "Check")):
                    break
                pos = st.mpos if st.mpos is not None else st.wpos
                if pos != last_pos:
                    last_pos, last_change = pos, self.clock.now()
                elif self.clock.now() - last_change > 1.0:
                    break
        finally:
            self.reset(timeout_s=max(self.timeout_s, self.stop_confirm_s))
        final = self.status()
        if base_state(final.state) in ("Run", "Jog", "Home"):
            raise DeviceError(f"{self.link.name}: the table still reports {final.state} after a feed hold and a reset")
        return final


def _alarm_advice(code: int | None) -> str:
    if code in (1, 2):
        return "GRBL now ignores everything but a reset: `labctl table reset`, then home or unlock"
    return "reset (labctl table reset), then home or unlock before moving"


if TYPE_CHECKING:  # mypy (.ci/run) fails here when GrblTable drifts from the Table protocol
    _table_protocol: type[Table] = GrblTable
    _program_protocol: type[Program] = ProgramStream
