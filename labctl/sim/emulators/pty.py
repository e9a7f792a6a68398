"""Run an emulator on a pseudo-terminal in raw mode, paced at the baud rate (10 bits per byte).

``run_on_pty(emulator, baud)`` returns a :class:`PtyDevice`; it unpacks as ``(slave_path, stop)``.
A client opens ``slave_path`` like a serial port (pyserial, screen, ``labctl table --port``).
``on_inbound``/``on_outbound`` hooks (t, bytes) -> bytes let tests drop, corrupt, delay or
stop bytes on the wire (tests/fakes).
"""

from __future__ import annotations

import logging
import os
import select
import threading
import time
import tty
from collections import deque
from collections.abc import Callable

from ...timebase import wire_time_s

log = logging.getLogger(__name__)

Hook = Callable[[float, bytes], bytes]


class PtyDevice:
    """An emulator (``receive(data, t=)``, ``advance(t)``, ``read_output()``) served on a pty by a background
    thread. ``stop()`` ends it and closes the pty."""

    def __init__(self, emulator, baud: int | None, clock: Callable[[], float] = time.monotonic,
                 on_inbound: Hook | None = None, on_outbound: Hook | None = None, tick_s: float = 0.002):
        self.emulator = emulator
        self.baud = baud
        self.clock = clock
        self.on_inbound = on_inbound
        self.on_outbound = on_outbound
        self.tick_s = tick_s
        self.byte_s = wire_time_s(1, baud) if baud else 0.0
        self.lock = threading.RLock()
        self.errors: list[BaseException] = []
        self.bytes_in = 0
        self.bytes_out = 0
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=f"pty-{type(emulator).__name__}", daemon=True)
        self._thread.start()

    def __iter__(self):
        return iter((self.path, self.stop))

    def stop(self) -> None:
        """Stop the serving thread and close both ends of the pty (idempotent)."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(timeout=5.0)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()

    def _loop(self) -> None:
        inbound: deque[tuple[float, bytes]] = deque()
        outbound = bytearray()
        t_in = t_out = -1e18
        while not self._stop.is_set():
            now = self.clock()
            wait = self.tick_s
            if inbound:
                wait = min(wait, max(inbound[0][0] - now, 0.0))
            if outbound:
                wait = min(wait, max(t_out + self.byte_s - now, 0.0))
            try:
                ready, _, _ = select.select([self._master], [], [], wait)
            except (OSError, ValueError):
                break
            now = self.clock()
            if ready:
                try:
                    data = os.read(self._master, 4096)
                except BlockingIOError:
                    data = b""
                except OSError:
                    data = b""  # no client has the slave open: keep serving
                    time.sleep(self.tick_s)
                for byte in data:
                    t_in = max(t_in, now) + self.byte_s
                    inbound.append((t_in, bytes([byte])))
                self.bytes_in += len(data)
            try:
                with self.lock:
                    while inbound and inbound[0][0] <= now:
                        t, b = inbound.popleft()
                        if self.on_inbound is not None:
                            b = self.on_inbound(t, b)
                        if b:
                            self.emulator.receive(b, t=t)
                    self.emulator.advance(now)
                    out = self.emulator.read_output()
                    if out and self.on_outbound is not None:
                        out = self.on_outbound(now, out)
                    outbound += out
            except Exception as exc:  # an emulator assertion (e.g. RX overflow) must not kill the pty
                log.exception("emulator failed")
                self.errors.append(exc)
            if outbound:
                if self.byte_s:
                    t_out = max(t_out, now - self.byte_s)
                    n = int((now - t_out) / self.byte_s + 1e-6)
                else:
                    n = len(outbound)
                if n > 0:
                    try:
                        written = os.write(self._master, bytes(outbound[:n]))
                    except (BlockingIOError, OSError):
                        written = 0
                    del outbound[:written]
                    self.bytes_out += written
                    if self.byte_s:
                        t_out += written * self.byte_s


def run_on_pty(emulator, baud: int | None, **kwargs) -> PtyDevice:
    """Serve ``emulator`` on a new pty; unpack the result as ``(slave_path, stop)``."""
    return PtyDevice(emulator, baud, **kwargs)
