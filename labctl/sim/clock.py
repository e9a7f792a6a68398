"""Clocks for the simulated lab: virtual time (trials, tests) and real time (live runs; ``RealClock`` lives in
:mod:`labctl.drivers.clock`); both implement the :class:`labctl.timebase.Clock` protocol.

Both have the same interface: ``now()`` in seconds, ``sleep(dt)``, ``sleep_until(t)``, and are
callable (``clock()`` is ``clock.now()``), so they can be handed to anything that wants a
``Callable[[], float]`` such as the GRBL emulator.
"""

from __future__ import annotations

import math
import threading

from ..drivers.clock import RealClock
from ..timebase import Clock, ClockError

__all__ = ["Clock", "ClockError", "RealClock", "VirtualClock"]


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
