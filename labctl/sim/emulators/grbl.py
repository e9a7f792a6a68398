"""A GRBL 1.1h controller, byte for byte, on an injectable clock.

What it models (GRBL 1.1 ``protocol.c``, ``gcode.c``, ``system.c``, ``report.c``, ``planner.c``):

* the welcome banner ``Grbl 1.1h ['$' for help]`` on power-up and soft reset (0x18);
* one ``ok`` / ``error:N`` per received line, sent when the line has been executed (for motion:
  when it is in the planner; for ``G4`` dwell and ``M0/M2``: after the planner drains);
* the serial receive buffer (``rx_buffer`` bytes, 127 by default): bytes that arrive while it is
  full are lost and counted in ``rx_overflows`` (``strict=True`` raises :class:`RxOverflow`);
* line pre-filtering (spaces, ``( )`` and ``;`` comments, upper-casing, 79-character lines → ``error:11``);
* the 15-block look-ahead planner with junction deviation and trapezoidal acceleration
  (:mod:`.motion`), G0/G1/G2/G3 (arcs split into chords within ``$12``), G4, G17-19, G20/21,
  G28/G30, G53, G54-59, G80, G90/91, G91.1, G92/G92.1, G93 unsupported, G94, M0/M1/M2/M30,
  M3/M4/M5, M7/M8/M9, F, S, T, N;
* real-time commands taken out of band: ``?`` status report ``<Idle|MPos:x,y,z|FS:f,s|…>``
  (with ``WCO:`` and ``Ov:`` refreshes as 1.1 does), ``!`` feed hold, ``~`` resume, 0x18 reset,
  extended bytes ≥ 0x80 never enter the buffer;
* ``$$`` settings, ``$N=V``, ``$#``, ``$G``, ``$I``, ``$N``, ``$C``, ``$X``, ``$H`` homing, ``$SLP``;
* soft limits → ``ALARM:2`` + ``[MSG:Reset to continue]`` (locked until reset), reset during
  motion → ``ALARM:3``, homing lock at power-up → ``[MSG:'$H'|'$X' to unlock]``.

Machine space is [0, travel] on each axis (GRBL's ``HOMING_FORCE_SET_ORIGIN`` with homing
towards −): the table's machine zero is the corner the world model places at ``origin_w_mm``.
"""

from __future__ import annotations

import copy
import math
import re
from collections.abc import Callable

import numpy as np

from .motion import Planner

VERSION = "1.1h"
BUILD = "20190830"
LINE_BUFFER_SIZE = 80

STATUS_OK = 0


class RxOverflow(AssertionError):
    """The host sent more than the receive buffer holds (a character-counting bug)."""


class _SoftLimit(Exception):
    pass


def default_settings(travel_mm, max_feed_mm_min, accel_mm_s2, z_travel_mm, homing, soft_limits) -> dict[int, float]:
    """GRBL 1.1 defaults (defaults.h, generic) adjusted to the table."""
    return {
        0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0,
        20: 1 if soft_limits else 0, 21: 0, 22: 1 if homing else 0, 23: 7, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0,
        30: 1000.0, 31: 0.0, 32: 0,
        100: 250.0, 101: 250.0, 102: 250.0,
        110: float(max_feed_mm_min), 111: float(max_feed_mm_min), 112: min(float(max_feed_mm_min), 500.0),
        120: float(accel_mm_s2), 121: float(accel_mm_s2), 122: float(accel_mm_s2),
        130: float(travel_mm[0]), 131: float(travel_mm[1]), 132: float(z_travel_mm),
    }


_INT_SETTINGS = {0, 1, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 26, 32}
_NUM = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)")

_MODAL_GROUPS = {  # G-code (×10) -> modal group name
    **{g: "nonmodal" for g in (40, 100, 280, 281, 300, 301, 530, 920, 921)},
    **{g: "motion" for g in (0, 10, 20, 30, 800)},
    **{g: "plane" for g in (170, 180, 190)},
    **{g: "distance" for g in (900, 910)},
    911: "arc_distance", 930: "feed_mode", 940: "feed_mode",
    200: "units", 210: "units", 400: "cutter", 431: "tlo", 490: "tlo",
    **{g: "coord" for g in (540, 550, 560, 570, 580, 590)},
    610: "control",
}
_M_GROUPS = {0: "stop", 1: "stop", 2: "stop", 30: "stop", 3: "spindle", 4: "spindle", 5: "spindle",
             7: "coolant", 8: "coolant", 9: "coolant"}


class GcodeError(Exception):
    """A G-code line GRBL rejects: ``code`` is GRBL's ``error:N`` number."""
    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


def parse_words(line: str) -> list[tuple[str, float, str]]:
    """Split a pre-filtered GRBL line into (letter, value, text) words (error:1 / error:2)."""
    words = []
    i = 0
    while i < len(line):
        letter = line[i]
        if not ("A" <= letter <= "Z"):
            raise GcodeError(1)
        m = _NUM.match(line, i + 1)
        if not m:
            raise GcodeError(2)
        words.append((letter, float(m.group(0)), m.group(0)))
        i = m.end()
    return words


class GrblEmulator:
    """GRBL 1.1h on a clock ``clock() -> s``. Feed it with :meth:`receive`, drain :meth:`read_output`."""

    def __init__(self, clock: Callable[[], float], *, travel_mm=(600.0, 400.0), max_feed_mm_min: float = 6000.0,
                 accel_mm_s2: float = 200.0, z_travel_mm: float = 50.0, rx_buffer: int = 127,
                 planner_blocks: int = 15, homing: bool = True, soft_limits: bool = True, strict: bool = False,
                 settings: dict[int, float] | None = None, start_mm=(0.0, 0.0, 0.0)):
        self.clock = clock
        self.rx_capacity = int(rx_buffer)
        self.planner_blocks = int(planner_blocks)
        self.strict = strict
        self.settings = default_settings(travel_mm, max_feed_mm_min, accel_mm_s2, z_travel_mm, homing, soft_limits)
        if settings:
            self.settings.update(settings)
        self.rx_overflows = 0
        self.rx_high_water = 0
        self.lines_executed = 0
        self.status_reports = 0
        self.now = float(clock())
        self.planner = self._new_planner(np.asarray(start_mm, float))
        self.out = bytearray()
        self.g28 = np.zeros(3)
        self.g30 = np.zeros(3)
        self.coord = [np.zeros(3) for _ in range(6)]
        self.hold_substate = 0
        self._power_on()

    # --- lifecycle ------------------------------------------------------------------------
    def _new_planner(self, pos) -> Planner:
        s = self.settings
        return Planner([s[110] / 60, s[111] / 60, s[112] / 60], [s[120], s[121], s[122]],
                       junction_deviation_mm=s[11], capacity=self.planner_blocks, position=pos, t0=self.now)

    def _power_on(self) -> None:
        self.state = "Alarm" if self.settings[22] else "Idle"
        self._reinit()

    def power_cycle(self) -> None:
        """Power loss and restart (a board reset by DTR or a brown-out): buffers, plan and modes are lost."""
        self.advance(max(self.now, self.clock()))
        self.planner.clear()
        self._power_on()

    def _reinit(self) -> None:
        """What GRBL's main() does after power-up or a soft reset (abort)."""
        self.rx = bytearray()
        self.line = bytearray()
        self.line_flags: set[str] = set()
        self.task = None  # generator executing the current line
        self.wake_at: float | None = None
        self.locked = False  # critical alarm: only a reset is served ('?' too is ignored, as in 1.1h)
        self.hold_pending = False
        self.planner.clear()
        self.motion = 0  # G0
        self.plane = (0, 1, 2)
        self.inches = False
        self.absolute = True
        self.coord_index = 0
        self.g92 = np.zeros(3)
        self.feed = 0.0  # mm/min
        self.spindle_speed = 0.0
        self.spindle = 5
        self.coolant = 9
        self.tool = 0
        self.wco_counter = 0
        self._wco_reported: np.ndarray | None = None
        self.ovr_counter = 1
        self._write("\r\nGrbl " + VERSION + " ['$' for help]\r\n")
        if self.state in ("Alarm", "Sleep"):
            self.state = "Alarm"
            self._write("[MSG:'$H'|'$X' to unlock]\r\n")
        else:
            self.state = "Idle"

    # --- wire -------------------------------------------------------------------------------
    def _write(self, text: str) -> None:
        self.out += text.encode("ascii")

    def read_output(self) -> bytes:
        """Bytes GRBL has sent since the last call."""
        self.advance(max(self.now, self.clock()))
        data = bytes(self.out)
        self.out.clear()
        return data

    def receive(self, data: bytes, t: float | None = None) -> None:
        """Bytes arriving on GRBL's serial RX at time ``t`` (default: the clock's now)."""
        self.advance(max(self.now, self.clock() if t is None else t))
        for b in bytes(data):
            if b == 0x3F:  # '?'
                if not self.locked:  # 1.1h's critical-event loop serves no status reports (firmware-verified)
                    self._status_report()
            elif b == 0x21:  # '!'
                self._feed_hold()
            elif b == 0x7E:  # '~'
                self._cycle_start()
            elif b == 0x18:
                self._soft_reset()
            elif b >= 0x80:
                pass  # extended real-time commands (overrides, door, jog cancel) are picked off; not modelled
            elif len(self.rx) >= self.rx_capacity:
                self.rx_overflows += 1
                if self.strict:
                    raise RxOverflow(f"GRBL receive buffer overflow ({self.rx_capacity} bytes)")
            else:
                self.rx.append(b)
                self.rx_high_water = max(self.rx_high_water, len(self.rx))
        self._run_main_loop()

    # --- time -------------------------------------------------------------------------------
    def advance(self, t: float) -> None:
        """Run motion and the main loop up to time ``t`` (s)."""
        while True:
            self._run_main_loop()
            if self.now >= t:
                break
            target = t if self.wake_at is None else min(t, max(self.wake_at, self.now))
            was_moving = bool(self.planner.blocks)
            self.now = self.planner.advance(target, stop_at_block_end=True)
            if self.wake_at is not None and self.now >= self.wake_at:
                self.wake_at = None
            if was_moving or self.state == "Hold":
                self._update_cycle_state()
        self._update_cycle_state()

    def _update_cycle_state(self) -> None:
        if self.state == "Run" and not self.planner.blocks:
            self.state = "Idle"
        elif self.state == "Hold" and self.hold_substate == 1 and not self.planner.moving:
            self.hold_substate = 0

    # --- positions --------------------------------------------------------------------------
    def machine_position(self) -> np.ndarray:
        """Carriage position in machine coordinates (mm) now."""
        self.advance(max(self.now, self.clock()))
        return self.planner.pos.copy()

    def position_at(self, t: float) -> np.ndarray:
        """Carriage machine position (mm) at time ``t``: exact for t up to the clock's now; for a
        future t, the motion already planned (no input yet to come)."""
        now = self.clock()
        if t <= now:
            self.advance(max(self.now, t))
            return self.planner.position_at(t)
        self.advance(max(self.now, now))
        probe = copy.deepcopy(self.planner)
        probe.history.clear()
        probe.advance(t)
        return probe.pos.copy()

    @property
    def moving(self) -> bool:
        """The carriage is moving (or has motion queued and no feed hold)."""
        return self.planner.moving

    # --- real-time commands -----------------------------------------------------------------
    @property
    def state_word(self) -> str:
        """The state as GRBL reports it: ``Hold:N`` with the hold substate, ``Door:0``, else the state."""
        if self.state == "Hold":
            return f"Hold:{self.hold_substate}"
        if self.state == "Door":
            return "Door:0"
        return self.state

    def _fmt(self, v: float) -> str:
        return f"{v / 25.4:.4f}" if self.settings[13] else f"{v:.3f}"

    def _status_report(self) -> None:
        self.status_reports += 1
        mpos = self.planner.pos
        wco = self.coord[self.coord_index] + self.g92
        if int(self.settings[10]) & 1:
            pos = "MPos:" + ",".join(self._fmt(v) for v in mpos)
        else:
            pos = "WPos:" + ",".join(self._fmt(v) for v in mpos - wco)
        parts = [self.state_word, pos]
        if int(self.settings[10]) & 2:
            # the firmware reports 128 free bytes when its 127-byte ring buffer is empty
            parts.append(f"Bf:{self.planner.capacity - len(self.planner.blocks)},{self.rx_capacity + 1 - len(self.rx)}")
        speed = self.planner.speed * 60.0
        if self.settings[13]:
            speed /= 25.4
        spindle = self.spindle_speed if self.spindle in (3, 4) else 0.0
        parts.append(f"FS:{speed:.0f},{spindle:.0f}")
        busy = self.state in ("Run", "Hold", "Home", "Jog", "Door")
        if self._wco_reported is None or not np.array_equal(wco, self._wco_reported):
            self.wco_counter = 0  # an offset changed: GRBL sends WCO in the very next report
        self._wco_reported = wco.copy()
        if self.wco_counter > 0:
            self.wco_counter -= 1
        else:
            self.wco_counter = (30 if busy else 10) - 1
            if self.ovr_counter == 0:
                self.ovr_counter = 1
            parts.append("WCO:" + ",".join(self._fmt(v) for v in wco))
        if self.ovr_counter > 0:
            self.ovr_counter -= 1
        else:
            self.ovr_counter = (20 if busy else 10) - 1
            parts.append("Ov:100,100,100")
        self._write("<" + "|".join(parts) + ">\r\n")

    def _feed_hold(self) -> None:
        if self.state in ("Alarm", "Check", "Sleep", "Door", "Hold"):
            return
        if self.state == "Run" or self.state == "Home":
            self.planner.feed_hold()
            self.state, self.hold_substate = "Hold", (1 if self.planner.moving else 0)
        elif self.state == "Idle":
            self.planner.feed_hold()
            self.state, self.hold_substate = "Hold", 0

    def _cycle_start(self) -> None:
        if self.state == "Hold" and self.hold_substate == 0:
            self.planner.resume()
            self.state = "Run" if self.planner.blocks else "Idle"
            self._run_main_loop()

    def _soft_reset(self) -> None:
        moving = self.state in ("Run", "Home", "Jog") or (self.state == "Hold" and self.hold_substate == 1)
        if self.locked:
            moving = False
        if moving:
            self.planner.clear()
            self._write("ALARM:3\r\n" if self.state != "Home" else "ALARM:6\r\n")
            self.state = "Alarm"
        elif self.state != "Alarm":
            self.state = "Idle"
        self._reinit()

    # --- main loop --------------------------------------------------------------------------
    def _run_main_loop(self) -> None:
        """Resume the blocked line, then read and execute lines while nothing blocks (protocol_main_loop)."""
        if self.locked:
            return
        while True:
            if self.task is not None:
                try:
                    wait = next(self.task)
                except StopIteration as stop:
                    self.task = None
                    self._reply(stop.value)
                    continue
                except _SoftLimit:
                    self.task = None
                    self._soft_limit_alarm()
                    return
                self.wake_at = wait if isinstance(wait, float) else None
                self._auto_cycle_start()
                return
            if not self.rx:
                self._auto_cycle_start()
                return
            c = self.rx.pop(0)
            if c in (0x0A, 0x0D):
                self._execute_line()
            elif self.line_flags:
                if c == 0x29 and "paren" in self.line_flags:  # ')'
                    self.line_flags.discard("paren")
            elif c <= 0x20 or c == 0x2F:
                pass
            elif c == 0x28:
                self.line_flags.add("paren")
            elif c == 0x3B:
                self.line_flags.add("semi")
            elif len(self.line) >= LINE_BUFFER_SIZE - 1:
                self.line_flags.add("overflow")
            elif 0x61 <= c <= 0x7A:
                self.line.append(c - 0x20)
            else:
                self.line.append(c)

    def _auto_cycle_start(self) -> None:
        if self.planner.blocks and self.state == "Idle":
            self.state = "Run"

    def _reply(self, code: int | None) -> None:
        if code is None:
            return  # the line died with an alarm or a reset
        self.lines_executed += 1
        self._write("ok\r\n" if code == STATUS_OK else f"error:{code}\r\n")

    def _execute_line(self) -> None:
        text = self.line.decode("ascii", errors="replace")
        overflow = "overflow" in self.line_flags
        self.line.clear()
        self.line_flags = set()
        if overflow:
            self._reply(11)
        elif not text:
            self._reply(STATUS_OK)
        elif text.startswith("$"):
            self.task = self._system_command(text)
        elif self.state in ("Alarm", "Jog"):
            self._reply(9)
        else:
            self.task = self._gcode(text)

    def _soft_limit_alarm(self) -> None:
        self.planner.clear()
        self.state = "Alarm"
        self.locked = True
        self._write("ALARM:2\r\n[MSG:Reset to continue]\r\n")

    def _sync(self):
        """protocol_buffer_synchronize: wait until the planner has drained."""
        while self.planner.blocks or self.state == "Hold":
            self._auto_cycle_start()
            yield None

    # --- $ commands -------------------------------------------------------------------------
    def _system_command(self, line: str):
        yield from ()  # a generator, stepped as ``self.task``, even where it never waits
        rest = line[1:]
        if rest in ("", "$", "G", "C", "X") and len(rest) <= 1:
            if rest == "":
                self._write("[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]\r\n")
                return STATUS_OK
            if rest == "$":
                if self.state in ("Run", "Hold"):
                    return 8
                for k in sorted(self.settings):
                    v = self.settings[k]
                    self._write(f"${k}={int(v)}\r\n" if k in _INT_SETTINGS else f"${k}={v:.3f}\r\n")
                return STATUS_OK
            if rest == "G":
                self._write(self._gc_state() + "\r\n")
                return STATUS_OK
            if rest == "C":
                if self.state == "Check":
                    self.state = "Idle"
                    self._write("[MSG:Disabled]\r\n")
                    self._reinit()
                    return None
                if self.state != "Idle":
                    return 8
                self.state = "Check"
                self._write("[MSG:Enabled]\r\n")
                return STATUS_OK
            if rest == "X":
                if self.state == "Alarm":
                    self._write("[MSG:Caution: Unlocked]\r\n")
                    self.state = "Idle"
                return STATUS_OK
        if rest.startswith("J="):
            return 16  # jogging is not modelled
        if self.state not in ("Idle", "Alarm"):
            return 8
        if rest == "#":
            for i, off in enumerate(self.coord):
                self._write(f"[G{54 + i}:{','.join(self._fmt(v) for v in off)}]\r\n")
            self._write(f"[G28:{','.join(self._fmt(v) for v in self.g28)}]\r\n")
            self._write(f"[G30:{','.join(self._fmt(v) for v in self.g30)}]\r\n")
            self._write(f"[G92:{','.join(self._fmt(v) for v in self.g92)}]\r\n[TLO:0.000]\r\n")
            self._write("[PRB:0.000,0.000,0.000:0]\r\n")
            return STATUS_OK
        if rest == "H":
            if not self.settings[22]:
                return 5
            result = yield from self._homing()
            return result
        if rest == "I":
            self._write(f"[VER:{VERSION}.{BUILD}:]\r\n[OPT:V,{self.planner_blocks},128]\r\n")
            return STATUS_OK
        if rest == "N":
            self._write("$N0=\r\n$N1=\r\n")
            return STATUS_OK
        if rest == "SLP":
            self.state = "Sleep"
            self._write("[MSG:Sleeping]\r\n")
            return STATUS_OK
        if rest.startswith("N") and "=" in rest:
            return STATUS_OK
        m = re.fullmatch(r"(\d+)=(.*)", rest)
        if not m:
            return 3
        key = int(m.group(1))
        vm = _NUM.fullmatch(m.group(2))
        if not vm:
            return 2
        value = float(m.group(2))
        if value < 0:
            return 4
        if key not in self.settings:
            return 3
        if key == 20 and value and not self.settings[22]:
            return 10
        if key == 0 and value < 3:
            return 6
        self.settings[key] = int(value) if key in _INT_SETTINGS else value
        if key in (11, 110, 111, 112, 120, 121, 122):
            p = self.planner
            p.max_rate = np.array([self.settings[110], self.settings[111], self.settings[112]]) / 60.0
            p.accel = np.array([self.settings[120], self.settings[121], self.settings[122]], float)
            p.junction_deviation = float(self.settings[11])
        return STATUS_OK

    def _homing(self):
        self.state = "Home"
        seek = self.settings[25] / 60.0
        self.planner.set_position(self.planner.pos)
        self.planner.add(np.zeros(3), seek, kind="home")
        while self.planner.blocks:
            yield None
        locate_s = 2 * self.settings[27] / max(self.settings[24] / 60.0, 1e-3)
        until = self.now + locate_s
        while self.now < until:
            yield until
        self.planner.set_position(np.zeros(3))
        self.state = "Idle"
        return STATUS_OK

    def _gc_state(self) -> str:
        plane = {(0, 1, 2): "G17", (2, 0, 1): "G18", (1, 2, 0): "G19"}[self.plane]
        motion = {0: "G0", 10: "G1", 20: "G2", 30: "G3", 800: "G80"}[self.motion]
        feed = self.feed / 25.4 if self.inches else self.feed
        return (f"[GC:{motion} G{54 + self.coord_index} {plane} {'G20' if self.inches else 'G21'} "
                f"{'G90' if self.absolute else 'G91'} G94 M{self.spindle} M{self.coolant} T{self.tool} "
                f"F{feed:g} S{self.spindle_speed:g}]")

    # --- G-code -----------------------------------------------------------------------------
    def _check_soft_limits(self, target: np.ndarray):
        if not self.settings[20]:
            return
        travel = np.array([self.settings[130], self.settings[131], self.settings[132]])
        if np.any(target < -1e-6) or np.any(target > travel + 1e-6):
            if self.state == "Run" and self.planner.moving:
                self._feed_hold()
                while self.planner.moving:
                    yield None
            raise _SoftLimit()

    def _line_to(self, target: np.ndarray, feed_mm_s: float | None):
        """mc_line: wait for planner room, check soft limits, queue the block."""
        yield from self._check_soft_limits(target)
        if self.state == "Check":
            return
        while self.planner.full:
            self._auto_cycle_start()
            yield None
        self.planner.add(target, feed_mm_s)

    def _gcode(self, line: str):
        try:
            words = parse_words(line)
        except GcodeError as e:
            return e.code
        yield from ()  # a generator, stepped as ``self.task``, even where it never waits
        groups: dict[str, int] = {}
        values: dict[str, float] = {}
        mgroups: dict[str, int] = {}
        for letter, value, _text in words:
            if letter == "G":
                code = int(round(value * 10))
                if code not in _MODAL_GROUPS:
                    return 20
                group = _MODAL_GROUPS[code]
                if group in groups:
                    return 21
                groups[group] = code
            elif letter == "M":
                if value != int(value):
                    return 20
                if int(value) not in _M_GROUPS:
                    return 20
                group = _M_GROUPS[int(value)]
                if group in mgroups:
                    return 21
                mgroups[group] = int(value)
            elif letter in "FIJKLNPRSTXYZ":
                if letter in values:
                    return 25
                if letter in "FNPST" and value < 0:
                    return 4
                values[letter] = value
            else:
                return 20
        if "N" in values and values["N"] > 10_000_000:
            return 27
        scale = 25.4 if (groups.get("units", 200 if self.inches else 210) == 200) else 1.0
        axis_words = {k: values[k] * scale for k in "XYZ" if k in values}
        nonmodal = groups.get("nonmodal")
        axis_cmd_nonmodal = nonmodal in (100, 280, 300, 920)
        if axis_cmd_nonmodal and "motion" in groups and axis_words:
            return 24
        if "feed_mode" in groups and groups["feed_mode"] == 930:
            return 20  # inverse time feed is not modelled
        if nonmodal == 40 and "P" not in values:
            return 28
        if "coord" in groups and groups["coord"] > 540 and groups["coord"] % 10:
            return 29
        # execution order (gcode.c): feed, spindle, tool, dwell, plane, units, distance, non-modal, motion, stop
        if "F" in values:
            self.feed = values["F"] * scale
        if "S" in values:
            self.spindle_speed = values["S"]
        if "T" in values:
            if values["T"] > 255:
                return 38
            self.tool = int(values["T"])
        if "spindle" in mgroups:
            self.spindle = mgroups["spindle"]
        if "coolant" in mgroups:
            self.coolant = mgroups["coolant"]
        if nonmodal == 40:
            yield from self._sync()
            until = self.now + values["P"]
            while self.now < until:
                yield until
        if "plane" in groups:
            self.plane = {170: (0, 1, 2), 180: (2, 0, 1), 190: (1, 2, 0)}[groups["plane"]]
        if "units" in groups:
            self.inches = groups["units"] == 200
        if "coord" in groups:
            self.coord_index = (groups["coord"] - 540) // 10
        if "distance" in groups:
            self.absolute = groups["distance"] == 900
        motion = groups.get("motion", self.motion)
        if "motion" in groups:
            self.motion = motion
        pos = self.planner.planned_position
        wco = self.coord[self.coord_index] + self.g92
        machine_coords = nonmodal == 530
        if machine_coords and motion not in (0, 10):
            return 30

        def target_of(words) -> np.ndarray:
            t = pos.copy()
            for i, k in enumerate("XYZ"):
                if k in words:
                    if machine_coords:
                        t[i] = words[k]
                    elif self.absolute:
                        t[i] = words[k] + wco[i]
                    else:
                        t[i] = pos[i] + words[k]
            return t

        if nonmodal in (280, 300):
            if axis_words:
                yield from self._line_to(target_of(axis_words), None)
            yield from self._line_to((self.g28 if nonmodal == 280 else self.g30).copy(), None)
            return STATUS_OK
        if nonmodal in (281, 301):
            (self.g28 if nonmodal == 281 else self.g30)[:] = pos
            return STATUS_OK
        if nonmodal == 920:
            if not axis_words:
                return 26
            for i, k in enumerate("XYZ"):
                if k in axis_words:
                    self.g92[i] = pos[i] - self.coord[self.coord_index][i] - axis_words[k]
            return STATUS_OK
        if nonmodal == 921:
            self.g92[:] = 0
        if nonmodal == 100:
            if "L" not in values or "P" not in values:
                return 28
            p = int(values["P"])
            if p > 6 or values["L"] not in (2, 20):
                return 20
            idx = self.coord_index if p == 0 else p - 1
            for i, k in enumerate("XYZ"):
                if k in axis_words:
                    self.coord[idx][i] = axis_words[k] if values["L"] == 2 else pos[i] - axis_words[k]
            return STATUS_OK
        stop = mgroups.get("stop")
        if axis_words and not axis_cmd_nonmodal and motion != 800:
            target = target_of(axis_words)
            if motion == 0:
                yield from self._line_to(target, None)
            elif motion in (10, 20, 30):
                if self.feed <= 0:
                    return 22
                feed_s = self.feed / 60.0
                if motion == 10:
                    yield from self._line_to(target, feed_s)
                else:
                    try:
                        chords = self._arc_chords(pos, target, values, scale, clockwise=motion == 20)
                    except GcodeError as e:
                        return e.code
                    for chord in chords:
                        yield from self._line_to(chord, feed_s)
        elif axis_words and motion == 800:
            return 31
        else:
            unused = [k for k in "IJKR" if k in values]
            if unused:
                return 36
        if stop is not None:
            yield from self._sync()
            if stop in (0, 1):
                self.state, self.hold_substate = "Hold", 0
                self.planner.feed_hold()
            else:
                self.motion, self.plane, self.absolute, self.coord_index = 10, (0, 1, 2), True, 0
                self.spindle, self.coolant = 5, 9
                self.g92[:] = 0
                self._write("[MSG:Pgm End]\r\n")
        return STATUS_OK

    def _arc_chords(self, pos, target, values, scale, clockwise) -> list[np.ndarray]:
        """mc_arc: the arc from pos to target as chords within the arc tolerance $12 (mm)."""
        a0, a1, lin = self.plane
        letters = "IJK"
        dx, dy = target[a0] - pos[a0], target[a1] - pos[a1]
        if "R" in values:
            r = values["R"] * scale
            if abs(dx) < 1e-9 and abs(dy) < 1e-9:
                raise GcodeError(33)
            h2 = 4.0 * r * r - dx * dx - dy * dy
            if h2 < 0:
                raise GcodeError(34)
            h = -math.sqrt(h2) / math.hypot(dx, dy)
            if not clockwise:
                h = -h
            if r < 0:
                h, r = -h, -r
            off0, off1 = 0.5 * (dx - dy * h), 0.5 * (dy + dx * h)
        else:
            if letters[a0] not in values and letters[a1] not in values:
                raise GcodeError(35)
            off0 = values.get(letters[a0], 0.0) * scale
            off1 = values.get(letters[a1], 0.0) * scale
            r = math.hypot(off0, off1)
            r_end = math.hypot(dx - off0, dy - off1)
            dr = abs(r_end - r)
            if dr > 0.005 and (dr > 0.5 or dr > 0.001 * r):
                raise GcodeError(33)
        if r <= 0:
            raise GcodeError(33)
        c0, c1 = pos[a0] + off0, pos[a1] + off1
        r_ax0, r_ax1 = -off0, -off1
        rt_ax0, rt_ax1 = target[a0] - c0, target[a1] - c1
        angular = math.atan2(r_ax0 * rt_ax1 - r_ax1 * rt_ax0, r_ax0 * rt_ax0 + r_ax1 * rt_ax1)
        eps = 5e-7
        if clockwise:
            if angular >= -eps:
                angular -= 2 * math.pi
        elif angular <= eps:
            angular += 2 * math.pi
        tol = self.settings[12]
        segments = int(math.floor(abs(0.5 * angular * r) / math.sqrt(tol * (2 * r - tol)))) if 2 * r > tol else 1
        segments = max(segments, 1)
        theta = angular / segments
        lin_step = (target[lin] - pos[lin]) / segments
        chords = []
        for i in range(1, segments):
            ang = math.atan2(r_ax1, r_ax0) + theta * i
            p = pos.copy()
            p[a0] = c0 + r * math.cos(ang)
            p[a1] = c1 + r * math.sin(ang)
            p[lin] = pos[lin] + lin_step * i
            chords.append(p)
        chords.append(target.copy())
        return chords
