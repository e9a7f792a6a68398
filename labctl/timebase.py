"""The run's one time base: the :class:`Clock` protocol every runtime, driver and emulator port runs on, and
the one formula for a byte's time on an RS-232 line.

A bottom layer (it imports nothing of labctl, and no clock: the functional core may import it), so that
drivers, the simulator, the decisions and the runtimes share one clock type and one wire time. Its two
implementations: ``sim.clock.VirtualClock`` (simulated time) and ``drivers.clock.RealClock`` (wall time,
CLOCK_MONOTONIC, from an origin). Units: s.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

#: RS-232 8N1: a start bit, 8 data bits and a stop bit on the line per byte
BITS_PER_BYTE = 10


def wire_time_s(n_bytes: int, baud: float) -> float:
    """Seconds to clock ``n_bytes`` over an 8N1 serial line at ``baud`` bit/s (10 bits per byte)."""
    return n_bytes * BITS_PER_BYTE / baud


@runtime_checkable
class Clock(Protocol):
    """A time base: ``now()`` in s and ``sleep(s)`` on the same clock (wall time, or virtual time that moves
    only when slept or advanced)."""

    def now(self) -> float:
        """Time now (s)."""
        ...

    def sleep(self, s: float) -> None:
        """Let ``s`` seconds pass on this clock (≤ 0: no-op)."""


class ClockError(ValueError):
    """A clock asked to go backwards or by a non-finite amount."""
