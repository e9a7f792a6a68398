"""The robot controller driver for the dialect of docs/protocols/robot.md, over :class:`SerialLink`.

Every request carries a sequence number and waits for its own ``$<seq>`` reply; ``@DONE``,
``@WATCHDOG`` and other asynchronous reports that arrive meanwhile are recorded. ``E<code>``
replies raise :class:`RobotError`. If the link fails or times out, the driver tries a
best-effort ``STOP`` before raising, and the controller's watchdog stops the robot anyway when
heartbeats stop.

With ``reconnect_s`` > 0 a dropped link (the port closes, ser2net restarts) is reopened with
backoff for that long. On return the driver reads the controller's state
again — ``HELLO`` then ``STATUS`` (docs/protocols/robot.md §10: on every reconnect) — before
anything else is sent, and never resends motion blindly: if the controller restarted
(``@BOOT``), latched a fault (its watchdog tripped while the host could not talk), or stands
still before its last accepted segment's end, the host's segments are lost and
:class:`RobotFault` is raised; a motion request the link dropped under (``SEG``, ``SEGNOW``,
``HOME``: taken or not, the host cannot know) stops the robot and raises :class:`LinkLost`.
Only a request that moves nothing is sent again. If the link does not come back,
:class:`LinkLost` after ``reconnect_s`` (plus one open attempt).
"""

from __future__ import annotations

import logging
import math
import re
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, cast

import numpy as np

from ..errors import DeviceError, MotionRefused
from ..geometry import make_T, matrix_to_rotvec, rotvec_to_matrix
from ..timebase import Clock
from .clock import MONOTONIC
from .interfaces import OpenClose, Robot, RobotStatus
from .robot_protocol import ERROR_CODES, MAX_SEQ, RobotReply, fmt_num, format_request, parse_reply
from .serial_link import DeviceTimeout, LinkError, LinkLost, SerialLink

if TYPE_CHECKING:
    from ..config import RobotConfig

log = logging.getLogger(__name__)

HOST_DIALECT = "1.4"  # the highest dialect this driver speaks (1.2: ruckig; 1.3: the arm's joints; 1.4: SET)
ARM_REFUSALS = frozenset({30, 31, 32, 33, 34})  # 1.3: segments the controller's arm cannot fly

# what a supervisor writes straight to the port in an emergency
STOP_LINE = (format_request(0, "STOP") + "\n").encode("ascii")

#: requests that command motion: never sent again after a dropped link (the controller may have taken them)
MOTION_COMMANDS = frozenset({"SEG", "SEGNOW", "HOME", "GO"})

#: what the operator runs to release a latched fault (E40 watchdog, E41 STOP), once the arm is checked
CLEAR_HINT = "check the arm, then run `labctl robot clear`"


class RobotError(DeviceError):
    """The controller refused a request (``E<code>``)."""

    def __init__(self, code: int, message: str = "", command: str = ""):
        self.code = code
        super().__init__(f"robot E{code:02d} {message or ERROR_CODES.get(code, 'error')}"
                         + (f" (for {command!r})" if command else "")
                         + (f"; {CLEAR_HINT}" if code in (40, 41) else "")
                         + ("; the arm cannot fly this segment, nothing moved" if code in ARM_REFUSALS else ""))


class RobotRefusal(RobotError, MotionRefused):
    """The controller's arm cannot fly a segment (E30–E34): refused before it moved."""


class RobotFault(DeviceError):
    """The controller stopped on its own (watchdog) and needs CLEAR."""


class SerialRobot(OpenClose):
    """:class:`labctl.drivers.interfaces.Robot` over a serial port or pyserial URL."""

    def __init__(self, port: str | None = None, baud: int = 9600, *, timeout_s: float = 2.0,
                 heartbeat_s: float = 0.2, serial_port=None, clock: Clock = MONOTONIC,
                 retries: int = 1, reconnect_s: float = 0.0):
        self.link = SerialLink(port, baud, timeout_s, port=serial_port, clock=clock,
                               name=f"robot@{port or getattr(serial_port, 'port', 'port')}")
        self.timeout_s = timeout_s
        self.heartbeat_s = heartbeat_s
        self.clock = clock
        self.retries = retries
        self._seq = 0
        self.done_ids: deque[int] = deque(maxlen=256)  # newest DONE reports; a waited-for id is recent
        self.faults: deque[str] = deque(maxlen=32)
        self.ident = ""
        self.dialect = "1.0"
        self._commanded = False  # a segment or HOME was sent: a @BOOT from now on loses motion
        self.queue = 8
        self.profiles: tuple[str, ...] = ("quintic",)
        self.arm: str | None = None  # the arm the controller names in a 1.3 HELLO (arm=), else None
        self._last_sent = -1e18
        self.reconnect_s = reconnect_s
        self.link_lost = False  # the link dropped and did not come back within reconnect_s
        #: called while waiting to reconnect: the caller's keep-alive (its own heartbeats, other devices)
        self.while_reconnecting: Callable[[], None] | None = None
        self.reconnects = 0
        self._recovering = False
        self._busy_until = -float("inf")  # controller time at which the last accepted segment ends
        self._pending: set[int] = set()  # ids of accepted segments whose @DONE has not come yet
        self._latched: str | None = None  # the fault the host itself latched (STOP) and has not cleared
        #: the session's segment defaults (SET, dialect 1.4): profile and its limits as sent; None: none set
        self._defaults: tuple[str, dict[str, str]] | None = None

    @classmethod
    def from_config(cls, cfg: RobotConfig, **kw) -> SerialRobot:
        """From a :class:`labctl.config.RobotConfig`; ``port``/``baud`` in ``kw`` override it only when not None."""
        port, baud = kw.pop("port", None), kw.pop("baud", None)
        kw.setdefault("reconnect_s", cfg.reconnect_s)
        return cls(port or cfg.port, baud or cfg.baud, timeout_s=cfg.timeout_s,
                   heartbeat_s=cfg.heartbeat_s, **kw)

    # --- connection -------------------------------------------------------------------------
    def open(self) -> None:
        """Open the port, discard stale input and negotiate the dialect; the port is closed again if that fails."""
        self.link.open()
        try:
            self.link.discard_input()
            self.negotiate()
        except BaseException:
            self.link.close()
            raise

    def negotiate(self) -> str:
        """``HELLO 1.3``, or a plain ``HELLO`` if the controller refuses the argument (a strict 1.0
        controller); sets ``dialect`` (the session version), ``queue``, ``profiles`` and ``arm``
        (docs/protocols/robot.md §1). Returns the session version."""
        try:
            reply = self.request("HELLO", HOST_DIALECT)
        except RobotError as exc:
            if exc.code != 2:
                raise
            reply = self.request("HELLO")
        self.ident = " ".join(reply.fields)
        fields = list(reply.fields)
        version = fields[1] if len(fields) > 1 and re.fullmatch(r"\d+\.\d+", fields[1]) else "1.0"
        theirs = tuple(int(x) for x in version.split("."))
        mine = tuple(int(x) for x in HOST_DIALECT.split("."))
        self.dialect = ".".join(map(str, min(theirs, mine)))
        self.profiles = ("quintic",)
        self.arm = None
        for f in fields[2:]:
            key, _, value = f.partition("=")
            if key == "queue" and value.isdigit():
                self.queue = int(value)
            elif key == "profiles" and value:
                self.profiles = tuple(p.lower() for p in value.split(","))
            elif key == "arm" and value and self.dialect_at_least("1.3"):
                self.arm = value
        if self._defaults is not None:  # HELLO starts a session without them: set them again (or drop them)
            profile, limits = self._defaults
            self._defaults = None
            if self.dialect_at_least("1.4") and profile in self.profiles:
                self._set_defaults(profile, limits)
        return self.dialect

    def segment_defaults(self, profile: str, limits: dict | None = None) -> bool:
        """Make ``profile`` with ``limits`` (as :meth:`segment` takes them) the session's segment defaults
        (``SET``, dialect 1.4), so a segment that runs them leaves ``profile=`` and its limits off the line
        (~24 bytes, ~25 ms a segment at 9600 bps). False (nothing sent) in an older session, whose segments
        keep naming them; set again after every HELLO (a reconnect)."""
        profile = profile.lower()
        if not self.dialect_at_least("1.4"):
            return False
        if profile not in self.profiles:
            raise ValueError(f"the controller runs the profiles {', '.join(self.profiles)}, not {profile!r}")
        if limits and profile != "ruckig":
            raise ValueError("segment limits need profile='ruckig'")
        self._set_defaults(profile, {k: fmt_num(float(v)) for k, v in (limits or {}).items()})
        return True

    def _set_defaults(self, profile: str, wire: dict[str, str]) -> None:
        self.request("SET", f"profile={profile}", *(f"{k}={v}" for k, v in wire.items()))
        self._defaults = (profile, wire)

    def dialect_at_least(self, version: str) -> bool:
        """The session speaks ``version`` (``major.minor``) or later."""
        return tuple(int(x) for x in self.dialect.split(".")) >= tuple(int(x) for x in version.split("."))

    def close(self) -> None:
        """Close the port (heartbeats stop with it: the controller's watchdog stops a moving robot)."""
        self.link.close()

    # --- requests ---------------------------------------------------------------------------
    def _on_async(self, line: str) -> None:
        msg = parse_reply(line)
        if msg.kind == "async":
            if msg.report == "DONE" and msg.fields and msg.fields[0].isdigit():
                self.done_ids.append(int(msg.fields[0]))
                self._pending.discard(int(msg.fields[0]))
            elif msg.report == "BOOT":
                self._defaults = None  # a restarted controller has no segment defaults: segments name their own
                if self._commanded:  # the controller restarted: queued and running segments are lost
                    self.faults.append("boot")
                    log.warning("%s: controller restarted (%s)", self.link.name, " ".join(msg.fields))
                else:  # it started up as we connected: nothing of ours was lost
                    log.debug("%s: controller booted (%s)", self.link.name, " ".join(msg.fields))
            elif msg.report == "WATCHDOG":
                self.faults.append("watchdog")
                log.warning("%s: controller watchdog stopped the robot", self.link.name)
            elif msg.report == "ERR":
                log.warning("%s: %s", self.link.name, line)
        elif msg.kind == "unknown" and line.strip():
            log.warning("%s: unexpected line %r", self.link.name, line)

    def request(self, command: str, *args) -> RobotReply:
        """Send ``#<seq> command args`` and return its ``$<seq> ok`` reply; RobotError on ``E<code>``.

        Retries once on a timeout (a lost line); DeviceTimeout if still no reply. A dropped link
        is reconnected once per request (:meth:`_recover`, with ``reconnect_s`` > 0), which sends
        the request again only if it moves nothing.
        """
        last_exc: Exception | None = None
        attempt, recovered = 0, False
        while attempt <= self.retries:
            attempt += 1
            self._seq = self._seq % MAX_SEQ + 1
            seq = self._seq
            line = format_request(seq, command, *args)

            def is_reply(text: str, seq=seq) -> bool:
                msg = parse_reply(text)
                return msg.kind == "reply" and msg.seq == seq

            try:
                got = self.link.request(line, is_reply, self.timeout_s, on_async=self._on_async)
            except DeviceTimeout as exc:
                last_exc = exc
                continue
            except LinkError as exc:
                if recovered:
                    raise
                self._recover(exc, command)  # raises unless `command` may safely be sent again
                recovered, attempt = True, attempt - 1
                continue
            self._last_sent = self.clock.now()
            msg = parse_reply(got)
            if not msg.ok and msg.code == 5:  # damaged on the way: send it again
                last_exc = RobotError(5, msg.text, command)
                continue
            if not msg.ok:
                refusal = RobotRefusal if msg.code in ARM_REFUSALS else RobotError
                raise refusal(msg.code or 0, msg.text, command)
            return msg
        raise DeviceTimeout(f"{self.link.name}: no reply to {command} after {self.retries + 1} tries") from last_exc

    def _lines(self, timeout_s: float) -> list[str]:
        """Lines received (waiting up to ``timeout_s`` for the first); a dropped link is recovered."""
        try:
            return self.link.lines(timeout_s)
        except LinkError as exc:
            self._recover(exc, "")
            return []

    def _recover(self, exc: LinkError, command: str) -> None:
        """The link failed under ``command``. With ``reconnect_s`` > 0, reopen it with backoff
        (LinkLost if it stays down; once lost, later calls try once), then read the controller's
        state again (HELLO, STATUS) before anything moves. Returns only if nothing of the host's
        motion was lost and ``command`` moves nothing (the caller sends it again). Raises
        RobotFault if the controller restarted, latched a fault, or stands still before its last
        segment's end (segments lost; nothing is resent), LinkLost after stopping the robot if
        ``command`` was a motion request (whether the controller took it is unknown)."""
        if self.reconnect_s <= 0 or self._recovering:
            raise exc
        self._recovering = True
        t0 = self.clock.now()
        window = 0.0 if self.link_lost else self.reconnect_s
        if not self.link_lost:
            log.warning("%s: link dropped (%s); reconnecting for up to %g s", self.link.name, exc, window)
        latched, boots = self._latched, sum(f == "boot" for f in self.faults)
        try:
            try:
                self.link.reconnect(window, idle=self.while_reconnecting)
            except LinkLost:
                self.link_lost = True
                raise
            self.link_lost = False
            self.reconnects += 1
            self.poll()  # reports that arrived meanwhile (a @BOOT), then HELLO: §10 on every (re)connect
            self.negotiate()
            st = self.status()
            fault = self._latched
            dt = self.clock.now() - t0
            lost = None
            if sum(f == "boot" for f in self.faults) > boots:
                lost = "the controller restarted (@BOOT)"
            elif fault is not None and fault != latched:
                lost = f"the controller latched '{fault}' (its watchdog stops the robot when the host cannot talk)"
            elif not st.moving and st.t < self._busy_until - 1e-3:
                lost = (f"the robot stands still at controller time {st.t:.3f} s, before its last segment's "
                        f"end {self._busy_until:.3f} s (the controller restarted or stopped)")
            if self._commanded and lost is not None:
                self._busy_until = -float("inf")
                self._pending.clear()
                raise RobotFault(f"{self.link.name}: the link dropped and came back after {dt:.1f} s, but {lost}: "
                                 "the host's segments are lost; nothing was sent again")
            if not st.moving and st.t >= self._busy_until - 1e-3 and self._pending:
                # everything accepted ran to its end while the link was down: their @DONE went nowhere
                self.done_ids.extend(sorted(self._pending))
                self._pending.clear()
            if command in MOTION_COMMANDS:
                if st.moving:
                    self.stop()
                raise LinkLost(f"{self.link.name}: the link dropped under {command} and came back after {dt:.1f} s; "
                               "whether the controller took it is unknown, so nothing was sent again and the robot "
                               "was stopped")
            log.warning("%s: link restored after %.1f s; state read again (moving %d, segment %d, fault %s)",
                        self.link.name, dt, st.moving, st.segment_id, fault or "none")
        finally:
            self._recovering = False

    def poll(self) -> None:
        """Collect asynchronous reports received so far."""
        for line in self._lines(0.0):
            self._on_async(line)

    # --- Robot interface --------------------------------------------------------------------
    def choose_profile(self, wanted: str) -> str:
        """The segment profile to plan with: ``wanted`` if the controller listed it in HELLO, else
        ``quintic`` (every controller runs it), with a warning (docs/protocols/robot.md §1)."""
        wanted = wanted.lower()
        if wanted in self.profiles:
            return wanted
        log.warning("%s: the controller runs the profiles %s, not %r: falling back to quintic",
                    self.link.name, ",".join(self.profiles), wanted)
        return "quintic"

    def segment(self, T_base_flange: np.ndarray, duration_s: float, segment_id: int, *,
                end_velocity_mm_s=None, end_omega_rad_s=None, replace: bool = False,
                profile: str | None = None, end_acceleration_mm_s2=None,
                limits: dict | None = None, hold: bool = False) -> tuple[float, float]:
        """Queue (or with ``replace`` start now) a segment; returns its controller (t0, t1). With ``hold``
        (dialect 1.4, not with ``replace``) the controller keeps it unplanned until :meth:`go`: (NaN, NaN).

        ``profile`` (default the controller's ``quintic``) must be one HELLO listed (pick it with
        :meth:`choose_profile`); id 0 is HOME's from dialect 1.1 on, so ids are 1–65535 there. With
        ``profile="ruckig"`` (dialect 1.2) ``duration_s`` is the least duration (0: as fast as the
        limits allow; t1 says when it arrives), and the segment may end with an acceleration
        ``end_acceleration_mm_s2`` and run under its own ``limits`` (``vmax amax jmax wmax``: mm/s,
        mm/s², mm/s³, deg/s; each at most the controller's, e.g. :meth:`JerkLimits.wire`)."""
        T = np.asarray(T_base_flange, float)
        ruckig = profile is not None and profile.lower() == "ruckig"
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError("T_base_flange must be a finite 4×4 matrix")
        if not ((duration_s >= 0 if ruckig else duration_s > 0) and np.isfinite(duration_s)):
            raise ValueError(f"segment duration must be positive, got {duration_s}")
        if not ruckig and (end_acceleration_mm_s2 is not None or limits):
            raise ValueError("an end acceleration or segment limits need profile='ruckig'")
        if limits and not set(limits) <= {"vmax", "amax", "jmax", "wmax"}:
            raise ValueError(f"segment limits are vmax, amax, jmax, wmax; got {sorted(limits)}")
        lowest = 1 if self.dialect != "1.0" else 0
        if not lowest <= int(segment_id) <= MAX_SEQ:
            raise ValueError(f"segment id must be {lowest}..{MAX_SEQ}, got {segment_id}")
        if profile is not None and profile.lower() not in self.profiles:
            raise ValueError(f"the controller runs the profiles {', '.join(self.profiles)}, not {profile!r}")
        if hold and (replace or not self.holds):
            raise ValueError("a held segment needs dialect 1.4 and SEG (not SEGNOW)")
        rv = matrix_to_rotvec(T[:3, :3])
        args: list = [int(segment_id), *map(float, T[:3, 3]), *map(float, rv), float(duration_s)]
        if end_velocity_mm_s is not None or end_omega_rad_s is not None or end_acceleration_mm_s2 is not None:
            v = np.zeros(3) if end_velocity_mm_s is None else np.asarray(end_velocity_mm_s, float)
            w = np.zeros(3) if end_omega_rad_s is None else np.asarray(end_omega_rad_s, float)
            args += [*map(float, v), *map(float, w)]
        if end_acceleration_mm_s2 is not None:
            args += [*map(float, np.asarray(end_acceleration_mm_s2, float).reshape(3))]
        name = (profile or "quintic").lower()
        wire = {key: fmt_num(float(value)) for key, value in (limits or {}).items()}
        if self._defaults is not None and self._defaults == (name, wire):
            pass  # the session's defaults (SET): the line names neither
        elif name != "quintic" or self._defaults is not None:  # a segment off the defaults names its profile
            args.append(f"profile={name}")
            args += [f"{key}={value}" for key, value in wire.items()]
        if hold:
            args.append("hold=1")
        self._commanded = True
        try:
            reply = self.request("SEGNOW" if replace else "SEG", *args)
        except (DeviceTimeout, LinkError):
            self.emergency_stop()
            raise
        if hold:
            return float("nan"), float("nan")
        return self._accepted(reply, int(segment_id), replace)

    @property
    def holds(self) -> bool:
        """The session holds segments until :meth:`go` (dialect 1.4)."""
        return self.dialect_at_least("1.4")

    def go(self, segment_id: int) -> tuple[float, float]:
        """Run the held segment ``segment_id`` now (``GO``, dialect 1.4): its controller (t0, t1). The line is
        ~12 bytes, where the segment's own is ~70: what is left on the critical path once the segment waits
        at the controller. A refusal raises as :meth:`segment`'s would (E21: nothing held by that id)."""
        self._commanded = True
        try:
            reply = self.request("GO", int(segment_id))
        except (DeviceTimeout, LinkError):
            self.emergency_stop()
            raise
        return self._accepted(reply, int(segment_id), False)

    def _accepted(self, reply: RobotReply, segment_id: int, replace: bool) -> tuple[float, float]:
        """Book an accepted segment (its ``t0 t1`` reply): when the controller is busy until, and its ``@DONE``."""
        times = reply.floats(2)
        if not times:
            return float("nan"), float("nan")
        self._busy_until = times[1] if replace else max(self._busy_until, times[1])
        if replace:  # SEGNOW cut the queue and the running segment: no @DONE for those
            self._pending.clear()
        self._pending.add(segment_id)
        return times[0], times[1]

    def stop(self) -> None:
        """STOP: brake with the stop ramp; in dialect 1.1 it latches ``stopped`` until :meth:`clear`."""
        self.request("STOP")
        self._busy_until = -float("inf")
        self._pending.clear()
        if self.dialect != "1.0":
            self._latched = self._latched or "stopped"

    def emergency_stop(self) -> None:
        """Best effort: send STOP without waiting; never raises (the watchdog is the backstop)."""
        try:
            self._seq = self._seq % MAX_SEQ + 1
            self.link.send_line(format_request(self._seq, "STOP"))
        except Exception:  # the link may be what failed
            log.warning("%s: could not send STOP", self.link.name, exc_info=True)

    def clear(self) -> None:
        """Clear a latched fault (``CLEAR``) so the controller accepts motion again."""
        self.request("CLEAR")
        self._latched = None

    def home(self) -> None:
        """Move to the home pose (``HOME``)."""
        self._commanded = True
        times = self.request("HOME").floats(2)
        self._busy_until = times[1] if times else -float("inf")
        self._pending = {0}

    def heartbeat(self) -> None:
        """Send a heartbeat (``HB``), resetting the controller's watchdog."""
        self.request("HB")

    def maybe_heartbeat(self) -> None:
        """Send HB if nothing was sent for ``heartbeat_s``."""
        if self.clock.now() - self._last_sent >= self.heartbeat_s:
            self.heartbeat()

    def limits(self) -> dict:
        """The controller's LIMITS; dialect 1.1 adds ``a_stop_mm_s2``, ``alpha_stop_deg_s2`` and
        ``home`` (x y z mm, rotation vector rad), 1.2 ``j_max_mm_s3`` (the ruckig profile's jerk limit)."""
        reply = self.request("LIMITS")
        f = reply.floats(10)
        if f is None:
            raise DeviceError(f"{self.link.name}: malformed LIMITS reply")
        out = {"workspace_min_mm": f[0:3], "workspace_max_mm": f[3:6], "v_max_mm_s": f[6],
               "a_max_mm_s2": f[7], "w_max_deg_s": f[8], "watchdog_s": f[9]}
        g = reply.floats(18)
        if g is not None:
            out.update(a_stop_mm_s2=g[10], alpha_stop_deg_s2=g[11], home=g[12:18])
        h = reply.floats(19)
        if h is not None:
            out["j_max_mm_s3"] = h[18]
        return out

    def status(self) -> RobotStatus:
        """Ask for a ``STATUS`` and parse it: flange pose in the base frame (mm), moving, segment id, controller time
        (s), in a 1.3 session with an arm its six joints (degrees on the wire, radians here)."""
        reply = self.request("STATUS")
        f = reply.floats(10)
        if f is None:
            raise DeviceError(f"{self.link.name}: malformed STATUS reply {reply.raw!r}")
        joints = None
        if self.arm is not None:  # 1.3: fields 12–17
            q = RobotReply(reply.kind, reply.raw, fields=reply.fields[11:]).floats()
            if q is None or len(q) != 6:
                raise DeviceError(f"{self.link.name}: malformed STATUS reply (no six joint angles) {reply.raw!r}")
            joints = cast("tuple[float, float, float, float, float, float]", tuple(math.radians(x) for x in q))
        fault = reply.fields[10] if len(reply.fields) > 10 else "none"
        if fault != "none" and fault not in self.faults:
            self.faults.append(fault)
        self._latched = None if fault == "none" else fault
        T = make_T(rotvec_to_matrix(np.array(f[3:6])), f[0:3])
        return RobotStatus(T_base_flange=T, moving=bool(int(f[6])), segment_id=int(f[7]), t=f[9], joints_rad=joints)

    @property
    def latched(self) -> str | None:
        """The fault the controller reported latched at the last ``STATUS`` (``stopped``, ``watchdog``), or None."""
        return self._latched

    def ensure_ready(self) -> RobotStatus:
        """``STATUS`` before a job. A fault latched on the controller (a ``STOP`` or a watchdog trip of an
        earlier session) is the operator's to clear once the arm has been checked: raise RobotFault
        naming it and the command that clears it (docs/protocols/robot.md §7)."""
        st = self.status()
        if self._latched is not None:
            raise RobotFault(f"{self.link.name}: the controller holds a latched '{self._latched}' fault from an "
                             f"earlier stop; {CLEAR_HINT}")
        return st

    def wait_done(self, segment_id: int, timeout_s: float) -> None:
        """Wait for ``@DONE segment_id`` (heartbeating meanwhile); RobotFault if the watchdog tripped."""
        deadline = self.clock.now() + timeout_s
        while segment_id not in self.done_ids:
            if self.faults:
                raise RobotFault(f"{self.link.name}: robot stopped by its controller ({self.faults[-1]})")
            if self.clock.now() > deadline:
                raise DeviceTimeout(f"{self.link.name}: segment {segment_id} not done within {timeout_s:g} s")
            for line in self._lines(min(self.heartbeat_s / 2, 0.05)):
                self._on_async(line)
            self.maybe_heartbeat()


if TYPE_CHECKING:  # mypy (.ci/run) fails here when SerialRobot drifts from the Robot protocol
    _robot_protocol: type[Robot] = SerialRobot
