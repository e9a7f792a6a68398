"""A pyserial-compatible port wired straight to an in-process emulator (no pty, any clock).

``EmulatorPort(emulator, clock, baud=None)`` behaves like ``serial.Serial`` for the calls the
drivers make (``write``, ``read``, ``readline``, ``in_waiting``, ``timeout``,
``reset_input_buffer``, ``close``). With ``baud`` set, bytes travel at 10 bits per byte in
both directions on the given clock (a :class:`labctl.timebase.Clock`), and blocking reads sleep on it:
pass the virtual clock to run in virtual time.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

from ...timebase import Clock, wire_time_s


class EmulatorPort:
    """pyserial-like port to ``emulator`` (anything with ``receive(data, t)`` and ``read_output()``)."""

    def __init__(self, emulator, clock: Clock, baud: int | None = None, timeout: float | None = 1.0,
                 name: str = "emulator://"):
        self.emulator = emulator
        self.clock = clock
        self.baudrate = baud
        self.timeout = timeout
        self.write_timeout = None
        self.port = name
        self._byte_s = wire_time_s(1, baud) if baud else 0.0
        self._to_device: deque[tuple[float, int]] = deque()
        self._from_device: deque[tuple[float, int]] = deque()
        self._rx = bytearray()
        self._t_in = -1e18
        self._t_out = -1e18
        self.is_open = True
        self.dtr = True
        self.rts = True

    # --- plumbing ---------------------------------------------------------------------------
    def _pump(self) -> None:
        now = self.clock.now()
        if self._byte_s == 0.0:
            out = self.emulator.read_output()
            self._rx += out
            return
        while self._to_device and self._to_device[0][0] <= now:
            t = self._to_device[0][0]
            chunk = bytearray()
            while self._to_device and self._to_device[0][0] == t:
                chunk.append(self._to_device.popleft()[1])
            self.emulator.receive(bytes(chunk), t=t)
            self._queue_out(self.emulator.read_output(), t)
        self._queue_out(self.emulator.read_output(), now)
        while self._from_device and self._from_device[0][0] <= now:
            self._rx.append(self._from_device.popleft()[1])

    def _queue_out(self, data: bytes, t: float) -> None:
        for b in data:
            self._t_out = max(self._t_out, t) + self._byte_s
            self._from_device.append((self._t_out, b))

    # --- pyserial API -----------------------------------------------------------------------
    def open(self) -> None:
        """Mark the port open."""
        self.is_open = True

    def close(self) -> None:
        """Mark the port closed."""
        self.is_open = False

    def write(self, data: bytes) -> int:
        """Send ``data`` to the emulator, paced at the port's baud rate on its clock; returns the byte count."""
        data = bytes(data)
        if self._byte_s == 0.0:
            self.emulator.receive(data)
            return len(data)
        self._pump()
        now = self.clock.now()
        for b in data:
            self._t_in = max(self._t_in, now) + self._byte_s
            self._to_device.append((self._t_in, b))
        return len(data)

    def flush(self) -> None:
        """Block until every written byte has reached the device."""
        while self._to_device:
            self.clock.sleep(max(self._to_device[-1][0] - self.clock.now(), 1e-4))
            self._pump()

    @property
    def in_waiting(self) -> int:
        """Bytes received from the emulator and not yet read."""
        self._pump()
        return len(self._rx)

    @property
    def out_waiting(self) -> int:
        """Bytes written and not yet delivered to the emulator (baud-rate pacing)."""
        return len(self._to_device)

    def _wait(self, done: Callable[[], bool]) -> None:
        deadline = None if self.timeout is None else self.clock.now() + self.timeout
        self._pump()
        while not done():
            now = self.clock.now()
            if deadline is not None and now >= deadline:
                return
            step = 1e-3
            if self._from_device:
                step = max(min(step, self._from_device[0][0] - now), 1e-5)
            if deadline is not None:
                step = min(step, max(deadline - now, 1e-6))
            self.clock.sleep(step)
            self._pump()

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` received bytes, waiting up to ``timeout`` s for them (pyserial semantics)."""
        if self.timeout == 0:
            self._pump()
        else:
            self._wait(lambda: len(self._rx) >= size)
        out = bytes(self._rx[:size])
        del self._rx[:size]
        return out

    def read_until(self, expected: bytes = b"\n", size: int | None = None) -> bytes:
        """Received bytes up to and including ``expected`` (or ``size`` bytes), waiting up to ``timeout`` s."""
        def done() -> bool:
            return expected in self._rx or (size is not None and len(self._rx) >= size)

        self._wait(done)
        idx = self._rx.find(expected)
        n = idx + len(expected) if idx >= 0 else len(self._rx)
        if size is not None:
            n = min(n, size)
        out = bytes(self._rx[:n])
        del self._rx[:n]
        return out

    def readline(self, size: int | None = None) -> bytes:
        """One received line (up to ``\n``), as pyserial's ``readline``."""
        return self.read_until(b"\n", size)

    def reset_input_buffer(self) -> None:
        """Drop every received byte not yet read, and those still on the wire."""
        self._pump()
        self._rx.clear()
        self._from_device.clear()

    def reset_output_buffer(self) -> None:
        """Drop bytes written and not yet delivered."""
        self._to_device.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
