"""Wall time for the real devices and the live runs: :class:`RealClock`, the :class:`labctl.timebase.Clock` on
CLOCK_MONOTONIC (the simulated lab's virtual time is ``labctl.sim.clock.VirtualClock``)."""

from __future__ import annotations

import math
import time

from ..timebase import ClockError

__all__ = ["MONOTONIC", "RealClock"]


class RealClock:
    """Wall time (monotonic), reported as seconds since an origin: ``origin`` (s on CLOCK_MONOTONIC, e.g. a run's
    origin shared by its processes), or by default ``t0`` seconds before creation. ``RealClock(origin=0.0)``
    reads CLOCK_MONOTONIC itself."""

    def __init__(self, t0: float = 0.0, *, origin: float | None = None):
        self.origin = float(origin) if origin is not None else time.monotonic() - float(t0)

    def now(self) -> float:
        """Seconds since the clock's origin (monotonic wall time)."""
        return time.monotonic() - self.origin

    __call__ = now

    def advance(self, dt: float) -> float:
        """Real time cannot be pushed: this waits ``dt`` seconds (same contract as the virtual clock)."""
        self.sleep(dt)
        return self.now()

    def sleep(self, s: float) -> None:
        """Sleep ``s`` seconds of wall time (≤ 0: no-op); NaN or infinite raises ClockError."""
        if not math.isfinite(s):
            raise ClockError(f"cannot sleep {s} s")
        if s > 0:
            time.sleep(s)

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


#: CLOCK_MONOTONIC itself: the default clock of the real drivers
MONOTONIC = RealClock(origin=0.0)
