"""GRBL-style motion: look-ahead planner with junction deviation and trapezoidal velocity profiles.

A pure model on explicit times (no clock inside): blocks are straight moves; the executing
block's profile is recomputed from its exact current state (speed, remaining distance) whenever
the plan changes (a block is queued, a feed hold, a resume), as GRBL's stepper segment buffer does.
Every executed stretch is recorded as a constant-acceleration piece, so the carriage position
at any past time is exact and deterministic. Units: mm, s.

Implements the planner of GRBL 1.1 (``planner.c``: junction deviation cornering speed,
reverse/forward passes) with the trapezoid of ``stepper.c``'s ``st_prep_buffer``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import cast

import numpy as np

MIN_JUNCTION_SPEED = 0.0  # mm/s
_EPS = 1e-9


@dataclass
class Block:
    """One queued straight move (mm, mm/s, mm/s²)."""

    start: np.ndarray
    target: np.ndarray
    unit: np.ndarray
    length: float
    nominal_speed: float
    accel: float
    max_entry_speed: float
    entry_speed: float = 0.0
    kind: str = "feed"  # feed | rapid | home


@dataclass(frozen=True)
class Piece:
    """A stretch of constant acceleration: p(t) = p0 + unit·(v0·τ + a·τ²/2), τ = t − t0 ∈ [t0, t1]."""

    t0: float
    t1: float
    p0: tuple[float, float, float]
    unit: tuple[float, float, float]
    v0: float
    a: float

    def at(self, t: float) -> np.ndarray:
        """Position (mm) at time ``t`` (s), clamped to the piece's interval."""
        tau = min(max(t - self.t0, 0.0), self.t1 - self.t0)
        s = self.v0 * tau + 0.5 * self.a * tau * tau
        return np.asarray(self.p0) + np.asarray(self.unit) * s


def limit_by_axes(values: np.ndarray, unit: np.ndarray) -> float:
    """Largest scalar rate along ``unit`` keeping every axis within ``values`` (GRBL limit_value_by_axis_maximum)."""
    out = math.inf
    for v, u in zip(values, unit):
        if abs(u) > _EPS:
            out = min(out, v / abs(u))
    return out


def trapezoid(v0: float, distance: float, v_nominal: float, v_exit: float, accel: float) -> list[tuple[float, float]]:
    """Phases ``[(duration_s, accel)]`` taking speed v0 to v_exit over ``distance`` mm, capped at v_nominal.

    Accelerate at +accel, cruise, decelerate at −accel (a triangle when the cruise does not fit).
    If v0 is too fast to stop in time (only from rounding), the deceleration is stretched to fit.
    """
    if distance <= _EPS:
        return []
    v_exit = min(v_exit, math.sqrt(v0 * v0 + 2 * accel * distance))
    phases: list[tuple[float, float]] = []
    if v0 * v0 - v_exit * v_exit > 2 * accel * distance + 1e-9:
        a = (v0 * v0 - v_exit * v_exit) / (2 * distance)
        return [(2 * distance / (v0 + v_exit), -a)]
    if v0 > v_nominal + _EPS:  # entered faster than nominal (override lowered): slow down first
        d = (v0 * v0 - v_nominal * v_nominal) / (2 * accel)
        if d >= distance:
            a = (v0 * v0 - v_exit * v_exit) / (2 * distance)
            return [(2 * distance / (v0 + v_exit), -a)]
        phases.append(((v0 - v_nominal) / accel, -accel))
        distance -= d
        v0 = v_nominal
    d_acc = (v_nominal * v_nominal - v0 * v0) / (2 * accel)
    d_dec = (v_nominal * v_nominal - v_exit * v_exit) / (2 * accel)
    if d_acc + d_dec <= distance:
        if d_acc > 0:
            phases.append(((v_nominal - v0) / accel, accel))
        cruise = distance - d_acc - d_dec
        if cruise > 0:
            phases.append((cruise / v_nominal, 0.0))
        if d_dec > 0:
            phases.append(((v_nominal - v_exit) / accel, -accel))
    else:
        vp = math.sqrt(max(0.0, (2 * accel * distance + v0 * v0 + v_exit * v_exit) / 2))
        vp = max(vp, v0, v_exit)
        if vp > v0:
            phases.append(((vp - v0) / accel, accel))
        if vp > v_exit:
            phases.append(((vp - v_exit) / accel, -accel))
    return [(d, a) for d, a in phases if d > 0]


class Planner:
    """GRBL's look-ahead planner and stepper on a virtual time line."""

    def __init__(self, max_rate_mm_s, accel_mm_s2, junction_deviation_mm: float = 0.01, capacity: int = 15,
                 position=(0.0, 0.0, 0.0), t0: float = 0.0, history_s: float = 600.0):
        self.max_rate = np.asarray(max_rate_mm_s, float)
        self.accel = np.asarray(accel_mm_s2, float)
        self.junction_deviation = float(junction_deviation_mm)
        self.capacity = int(capacity)
        self.blocks: deque[Block] = deque()
        self.pos = np.asarray(position, float).copy()  # exact current position
        self.speed = 0.0  # along the executing block
        self.t = float(t0)
        self.hold = False
        self.history: deque[Piece] = deque()
        self.history_s = history_s
        self._prev_unit: np.ndarray | None = None
        self._planned_pos = self.pos.copy()  # end of the last queued block

    # --- queueing ---------------------------------------------------------------------------
    @property
    def full(self) -> bool:
        """The planner buffer holds ``capacity`` blocks."""
        return len(self.blocks) >= self.capacity

    @property
    def empty(self) -> bool:
        """No block is queued."""
        return not self.blocks

    @property
    def planned_position(self) -> np.ndarray:
        """Where the carriage will be (mm) once every queued block has run."""
        return self._planned_pos.copy()

    def add(self, target, feed_mm_s: float | None, kind: str = "feed") -> bool:
        """Queue a straight move to ``target`` (mm) at ``feed_mm_s`` (None: rapid). False if zero length."""
        target = np.asarray(target, float)
        delta = target - self._planned_pos
        length = float(np.linalg.norm(delta))
        if length < 1e-6:
            return False
        unit = delta / length
        rapid = limit_by_axes(self.max_rate, unit)
        nominal = rapid if feed_mm_s is None else min(float(feed_mm_s), rapid)
        accel = limit_by_axes(self.accel, unit)
        if not self.blocks and self.speed <= _EPS:
            max_entry = 0.0
        else:
            prev = self._prev_unit if self._prev_unit is not None else unit
            cos_theta = -float(np.dot(prev, unit))
            if cos_theta > 0.999999:
                junction = MIN_JUNCTION_SPEED
            elif cos_theta < -0.999999:
                junction = math.inf
            else:
                jv = unit - prev
                jv /= np.linalg.norm(jv)
                j_accel = limit_by_axes(self.accel, jv)
                sin_half = math.sqrt(0.5 * (1.0 - cos_theta))
                junction = math.sqrt(max(MIN_JUNCTION_SPEED ** 2,
                                         j_accel * self.junction_deviation * sin_half / (1.0 - sin_half)))
            prev_nominal = self.blocks[-1].nominal_speed if self.blocks else nominal
            max_entry = min(junction, nominal, prev_nominal)
        self.blocks.append(Block(self._planned_pos.copy(), target.copy(), unit, length, nominal, accel, max_entry,
                                 kind=kind))
        self._planned_pos = target.copy()
        self._prev_unit = unit
        self._replan()
        return True

    def clear(self) -> None:
        """Drop every queued block and stop dead (a reset): the position stays where it is."""
        self.blocks.clear()
        self.speed = 0.0
        self.hold = False
        self._planned_pos = self.pos.copy()
        self._prev_unit = None

    def set_position(self, position) -> None:
        """Drop every block and put the carriage at ``position`` (mm) at rest."""
        self.clear()
        self.pos = np.asarray(position, float).copy()
        self._planned_pos = self.pos.copy()

    def _remaining(self) -> float:
        if not self.blocks:
            return 0.0
        return max(0.0, float(np.dot(self.blocks[0].target - self.pos, self.blocks[0].unit)))

    def _replan(self) -> None:
        """Reverse then forward pass over the queue (entry speeds; the last block ends at rest)."""
        n = len(self.blocks)
        if n == 0:
            return
        blocks = self.blocks
        exit_speed = 0.0
        for i in range(n - 1, 0, -1):
            b = blocks[i]
            b.entry_speed = min(b.max_entry_speed, math.sqrt(exit_speed ** 2 + 2 * b.accel * b.length))
            exit_speed = b.entry_speed
        blocks[0].entry_speed = self.speed
        v = self.speed
        d0 = self._remaining()
        for i in range(1, n):
            prev = blocks[i - 1]
            dist = d0 if i == 1 else prev.length
            reach = math.sqrt(v * v + 2 * prev.accel * dist)
            blocks[i].entry_speed = min(blocks[i].entry_speed, reach)
            v = blocks[i].entry_speed

    def _exit_speed(self) -> float:
        return self.blocks[1].entry_speed if len(self.blocks) > 1 else 0.0

    # --- time -------------------------------------------------------------------------------
    def _record(self, t0, t1, p0, unit, v0, a) -> None:
        last = self.history[-1] if self.history else None
        if (a == 0.0 and v0 == 0.0 and last is not None and last.a == 0.0 and last.v0 == 0.0
                and last.t1 == t0 and last.p0 == tuple(float(x) for x in p0)):
            self.history[-1] = Piece(last.t0, t1, last.p0, last.unit, 0.0, 0.0)  # merge idle stretches
            return
        # p0 and unit are 3-vectors
        self.history.append(Piece(t0, t1, cast("tuple[float, float, float]", tuple(float(x) for x in p0)),
                                  cast("tuple[float, float, float]", tuple(float(x) for x in unit)), v0, a))
        while self.history and self.history[0].t1 < t1 - self.history_s:
            self.history.popleft()

    def advance(self, t: float, stop_at_block_end: bool = False) -> float:
        """Run the motion up to time ``t``; returns the time reached (earlier if a block ended and
        ``stop_at_block_end``)."""
        while self.t < t:
            if not self.blocks or (self.hold and self.speed <= _EPS):
                self.speed = 0.0 if not self.blocks or self.hold else self.speed
                self._record(self.t, t, self.pos, (0.0, 0.0, 0.0), 0.0, 0.0)
                self.t = t
                break
            b = self.blocks[0]
            d = self._remaining()
            if self.hold:
                phases = [(self.speed / b.accel, -b.accel)]
                if self.speed ** 2 / (2 * b.accel) > d:
                    v_end = math.sqrt(max(0.0, self.speed ** 2 - 2 * b.accel * d))
                    phases = [((self.speed - v_end) / b.accel, -b.accel)] if d > _EPS else []
            else:
                phases = trapezoid(self.speed, d, b.nominal_speed, self._exit_speed(), b.accel)
            block_done = True
            for dur, a in phases:
                end = self.t + dur
                if end > t:
                    tau = t - self.t
                    s = self.speed * tau + 0.5 * a * tau * tau
                    self._record(self.t, t, self.pos, b.unit, self.speed, a)
                    self.pos = self.pos + b.unit * s
                    self.speed = max(0.0, self.speed + a * tau)
                    self.t = t
                    block_done = False
                    break
                s = self.speed * dur + 0.5 * a * dur * dur
                self._record(self.t, end, self.pos, b.unit, self.speed, a)
                self.pos = self.pos + b.unit * s
                self.speed = max(0.0, self.speed + a * dur)
                self.t = end
            if not block_done:
                break
            if self.hold and self._remaining() > 1e-6 and self.speed <= 1e-6:
                self.speed = 0.0  # stopped inside the block
                continue
            self.pos = b.target.copy()
            self.blocks.popleft()
            if not self.blocks:
                self.speed = 0.0
            if stop_at_block_end:
                return self.t
        return self.t

    def feed_hold(self) -> None:
        """Decelerate to a stop along the path (GRBL feed hold), keeping the blocks."""
        self.hold = True

    def resume(self) -> None:
        """Continue after a feed hold, re-planning from rest."""
        if self.hold:
            self.hold = False
            self._replan()

    @property
    def moving(self) -> bool:
        """The carriage moves, or has blocks to run and no hold."""
        return self.speed > _EPS or (bool(self.blocks) and not self.hold)

    def position_at(self, t: float) -> np.ndarray:
        """Carriage position (mm) at a time already run (≤ ``self.t``); clamps to the recorded history."""
        if t >= self.t or not self.history:
            return self.pos.copy()
        hist = self.history
        lo, hi = 0, len(hist) - 1
        if t <= hist[0].t0:
            return hist[0].at(hist[0].t0)
        while lo < hi:  # last piece with t0 <= t
            mid = (lo + hi + 1) // 2
            if hist[mid].t0 <= t:
                lo = mid
            else:
                hi = mid - 1
        return hist[lo].at(t)
