"""Clocks for the simulated lab: virtual time (trials, tests) and real time (live runs).

Both have the same interface: ``now()`` in seconds, ``sleep(dt)``, ``sleep_until(t)``, and are
callable (``clock()`` is ``clock.now()``), so they can be handed to anything that wants a
``Callable[[], float]`` such as the GRBL emulator.
"""

from __future__ import annotations

import math
import threading
import time


class ClockError(ValueError):
    """A clock asked to go backwards or by a non-finite amount."""


class VirtualClock:
    """Simulated time: starts at ``t0`` and moves only when someone sleeps or advances it.

    Sleeping returns at once with the clock moved forward, so a trial runs as fast as the CPU
    allows and is deterministic. Thread-safe (one lock), but meant for one-process simulation.
    """

    def __init__(self, t0: float = 0.0):
        if not math.isfinite(t0):
            raise ClockError(f"start time must be finite, got {t0}")
        self._t = float(t0)
        self._lock = threading.Lock()

    def now(self) -> float:
        """Virtual time now (s)."""
        return self._t

    __call__ = now

    @property
    def t(self) -> float:
        """Virtual time now (s), as an attribute."""
        return self._t

    def advance(self, dt: float) -> float:
        """Move time forward by ``dt`` ≥ 0 seconds; returns the new time."""
        if not math.isfinite(dt) or dt < 0:
            raise ClockError(f"a clock cannot advance by {dt} s")
        with self._lock:
            self._t += float(dt)
            return self._t

    def sleep(self, dt: float) -> None:
        """Advance by ``dt`` seconds (negative: no-op); a NaN or infinite ``dt`` raises ClockError."""
        self.advance(max(float(dt), 0.0) if math.isfinite(dt) else dt)

    def sleep_until(self, t: float) -> None:
        """Advance to time ``t`` if it is in the future (no-op otherwise)."""
        if not math.isfinite(t):
            raise ClockError(f"cannot sleep until {t}")
        with self._lock:
            if t > self._t:
                self._t = float(t)

    @property
    def is_virtual(self) -> bool:
        """True: time moves only when advanced."""
        return True


class RealClock:
    """Wall time (monotonic), reported as seconds since ``t0`` seconds before creation."""

    def __init__(self, t0: float = 0.0):
        self._origin = time.monotonic() - float(t0)

    def now(self) -> float:
        """Seconds since the clock's origin (monotonic wall time)."""
        return time.monotonic() - self._origin

    __call__ = now

    def advance(self, dt: float) -> float:
        """Real time cannot be pushed: this waits ``dt`` seconds (same contract as the virtual clock)."""
        self.sleep(dt)
        return self.now()

    def sleep(self, dt: float) -> None:
        """Sleep ``dt`` seconds of wall time (≤ 0: no-op); NaN or infinite raises ClockError."""
        if not math.isfinite(dt):
            raise ClockError(f"cannot sleep {dt} s")
        if dt > 0:
            time.sleep(dt)

    def sleep_until(self, t: float) -> None:
        """Sleep until the clock reads ``t`` (s); a NaN or infinite ``t`` raises ClockError."""
        if not math.isfinite(t):
            raise ClockError(f"cannot sleep until {t}")
        while True:
            remaining = t - self.now()
            if remaining <= 0:
                return
            time.sleep(remaining)

    @property
    def is_virtual(self) -> bool:
        """False: wall time."""
        return False


Clock = VirtualClock | RealClock
