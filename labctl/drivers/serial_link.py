"""The serial link under every line-oriented device driver (GRBL table, robot controller).

Built on pyserial's ``serial_for_url``, so device paths (``/dev/ttyUSB0``, ``/dev/pts/3``) and
the ``socket://``, ``rfc2217://``, ``spy://`` and ``loop://`` URLs all work. It gives:

* a line protocol: complete lines out of the byte stream, with timeouts on an injectable clock;
* request/response matching: :meth:`SerialLink.request` sends a line and returns the first
  line the caller's matcher accepts, handing every other line (asynchronous reports) to
  ``on_async``;
* write pacing (``pace_baud``: never put bytes on the wire faster than a UART at that rate,
  for ``socket://`` links to a slow device) and :meth:`SerialLink.reconnect`;
* a DEBUG log of every byte, with timestamps, on the ``labctl.drivers.serial_link`` logger.

Single-threaded and polled: the caller drives it, which keeps it deterministic in virtual time
(pass the virtual clock (a :class:`labctl.timebase.Clock`) and a ready ``port`` such as
:class:`labctl.sim.emulators.link.EmulatorPort`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from ..errors import DeviceError
from ..timebase import Clock, wire_time_s
from .clock import MONOTONIC
from .interfaces import OpenClose

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())


class DeviceTimeout(DeviceError):
    """A device did not answer within its timeout."""


def failed(verb: str, exc: BaseException) -> str:
    """``"<verb> failed: <why>"``, once: pyserial's own messages often start with the same words."""
    why = str(exc) or type(exc).__name__
    prefix = f"{verb} failed"
    return why if why.lower().startswith(prefix) else f"{prefix}: {why}"


class LinkError(DeviceError):
    """The port could not be opened, or failed while in use."""


class LinkLost(LinkError):
    """The link dropped and did not come back within the configured reconnect window."""


class ProtocolError(DeviceError):
    """The device answered something the protocol does not allow (lost or garbled replies)."""


def remote_baud(url: str | None) -> str:
    """Who sets the line rate of the port behind ``url``: ``"local"`` (a device path: the UART runs at the
    configured baud), ``"server"`` (``socket://``: a raw TCP connection carries no rate, the server's own
    configuration sets it, e.g. ser2net's connector line) or ``"rfc2217"`` (the server's unless the driver
    file's ``set_remote_baud`` asks the client to switch it)."""
    scheme = (url or "").split("://", 1)[0] if "://" in (url or "") else ""
    if scheme in ("socket", "tcp"):
        return "server"
    if scheme == "rfc2217":
        return "rfc2217"
    return "local"


def baud_words(url: str | None, baud: int, set_remote_baud: bool = False) -> str:
    """How ``labctl devices`` says the line rate of ``url``: ``"@ 9600 bps"`` only where it takes effect."""
    who = remote_baud(url)
    if who == "local" or (who == "rfc2217" and set_remote_baud):
        return f"@ {baud} bps" + (" (set on the server)" if who == "rfc2217" else "")
    return "(baud set by the server)"


def _rfc2217_keeping_rate():
    """pyserial's RFC 2217 client that leaves the remote port's baud rate as the server has it.

    Its ``open()`` sends SET-BAUDRATE with the client's rate and waits for the server to take it, so a
    stock 115200-bps board behind ser2net would be switched to whatever labctl was configured with. Here
    that one setting is neither sent nor waited for (data size, parity, stop bits and flow control still
    are); the server's notifications of its rate are still read."""
    import serial.rfc2217

    class _Unchanged:
        active = True

        def set(self, value: bytes) -> None:
            """Send nothing: the server's rate stands."""

    class KeepRate(serial.rfc2217.Serial):
        def _reconfigure_port(self):
            real = self._rfc2217_port_settings["baudrate"]
            self._rfc2217_port_settings["baudrate"] = _Unchanged()
            try:
                super()._reconfigure_port()
            finally:
                self._rfc2217_port_settings["baudrate"] = real

    return KeepRate


def open_port(url: str, *, write_timeout_s: float | None, set_remote_baud: bool = False, **kwargs):
    """``serial.serial_for_url(url, **kwargs)``, opened, with every write bounded by ``write_timeout_s``
    on every transport.

    Over ``rfc2217://`` the remote port's rate is switched to ``baudrate`` only if ``set_remote_baud``
    (a driver file's explicit key); otherwise the server's own rate stands (:func:`remote_baud`).

    pyserial's ``rfc2217://`` client refuses a ``write_timeout`` (``NotImplementedError``), so there
    the port is opened without one and its socket's own timeout is set to the bound instead (a
    blocked send then raises, as a timed-out write does elsewhere). An RFC 2217 server that never
    acknowledges a control-line change (ser2net on a pty does not: there is no DTR to set) fails
    with a hint to add ``?ign_set_control`` to the URL. Raises what ``serial_for_url`` raises."""
    import serial
    import serial.rfc2217

    if url.startswith("rfc2217://") and not set_remote_baud:
        port = _rfc2217_keeping_rate()(None, **kwargs)
        port.port = url
    else:
        port = serial.serial_for_url(url, do_not_open=True, **kwargs)
    rfc2217 = isinstance(port, serial.rfc2217.Serial)
    if not rfc2217:
        port.write_timeout = write_timeout_s
    try:
        port.open()
    except serial.SerialException as exc:
        if rfc2217 and "'control'" in str(exc) and "ign_set_control" not in url:
            raise serial.SerialException(
                f"{exc}: the RFC 2217 server does not acknowledge control-line changes (ser2net on a pty "
                f"does not); add ?ign_set_control to the URL") from exc
        raise
    sock = getattr(port, "_socket", None)
    if rfc2217 and sock is not None and write_timeout_s:
        sock.settimeout(write_timeout_s)  # its reader thread treats a timed-out recv as "nothing yet"
    return port


class SerialLink(OpenClose):
    """A polled line link over a pyserial port (or anything pyserial-like passed as ``port``)."""


    def __init__(self, url: str | None = None, baud: int = 9600, timeout_s: float = 2.0, *, port=None,
                 clock: Clock = MONOTONIC,
                 name: str = "", pace_baud: int | None = None, eol: bytes = b"\n", poll_s: float = 0.005,
                 serial_kwargs: dict | None = None, set_remote_baud: bool = False):
        if url is None and port is None:
            raise LinkError("a serial link needs a port path/URL or a port object")
        self.url = url
        self.baud = baud
        self.timeout_s = timeout_s
        self.clock = clock
        self.name = name or (url or getattr(port, "port", "port"))
        self.pace_baud = pace_baud
        self.eol = eol
        self.poll_s = poll_s
        self.serial_kwargs = serial_kwargs or {}
        self.set_remote_baud = set_remote_baud  # rfc2217://: switch the server's port to ``baud`` (else its own)
        self._given_port = port
        self.port = port
        self._buf = bytearray()
        self._next_write_t = 0.0
        self.bytes_in = 0
        self.bytes_out = 0
        self.max_buffer = 4096  # bytes kept while waiting for a line end
        self.bytes_discarded = 0

    @property
    def buffered_bytes(self) -> int:
        """Bytes received and kept while waiting for a line end (at most ``max_buffer``)."""
        return len(self._buf)

    # --- lifecycle --------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        """The port is open."""
        return self.port is not None and bool(getattr(self.port, "is_open", True))

    def open(self) -> None:
        """Open the port (or adopt the given one); raises DeviceError, with the port named, when it cannot."""
        if self._given_port is not None:
            self.port = self._given_port
            if not getattr(self.port, "is_open", True):
                self.port.open()
        else:
            import serial

            if self.url is None:  # the constructor takes a URL or a port
                raise LinkError("a serial link needs a port path/URL or a port object")
            try:
                self.port = open_port(self.url, write_timeout_s=self.timeout_s, baudrate=self.baud, timeout=0,
                                      set_remote_baud=self.set_remote_baud, **self.serial_kwargs)
            except (serial.SerialException, OSError, ValueError) as exc:
                raise LinkError(f"cannot open {self.url}: {exc}") from exc
        self._buf.clear()
        log.debug("%s open t=%.6f", self.name, self.clock.now())

    def close(self) -> None:
        """Close the port; a close that fails is logged, not raised."""
        if self.port is not None:
            try:
                self.port.close()
            except Exception:  # closing a dead port must not mask the original error
                log.debug("%s close failed", self.name, exc_info=True)
        if self._given_port is None:
            self.port = None
        log.debug("%s closed t=%.6f", self.name, self.clock.now())

    def reconnect(self, window_s: float = 5.0, backoff_s: float = 0.1, max_backoff_s: float = 2.0,
                  idle: Callable[[], None] | None = None, idle_every_s: float = 0.05) -> int:
        """Close and reopen the port until it opens, doubling the pause between tries (from
        ``backoff_s`` up to ``max_backoff_s``); :class:`LinkLost` once ``window_s`` has passed.
        Returns the number of attempts. Bounded in time: never longer than ``window_s`` plus one
        open attempt (``window_s`` 0: exactly one attempt). ``idle`` is called at least every
        ``idle_every_s`` while waiting between tries: the caller's keep-alive (other devices'
        watchdogs, its own heartbeats), which a blocking wait would otherwise starve."""
        t0 = self.clock.now()
        pause = backoff_s
        attempts = 0
        last: Exception | None = None
        while True:
            self.close()
            attempts += 1
            try:
                self.open()
                log.info("%s reconnected after %d attempts (%.2f s)", self.name, attempts, self.clock.now() - t0)
                return attempts
            except LinkError as exc:
                last = exc
            remaining = window_s - (self.clock.now() - t0)
            if remaining <= 0:
                raise LinkLost(f"{self.name}: the link dropped and did not come back within {window_s:g} s "
                               f"({attempts} attempts; last: {last})")
            wake = self.clock.now() + min(pause, remaining)
            while (left := wake - self.clock.now()) > 0:
                if idle is not None:
                    idle()
                self.clock.sleep(min(left, idle_every_s) if idle is not None else left)
            pause = min(pause * 2.0, max_backoff_s)

    # --- bytes ------------------------------------------------------------------------------
    def write(self, data: bytes) -> None:
        """Write bytes (paced at ``pace_baud`` if set); LinkError if the port fails."""
        if not self.is_open:
            raise LinkError(f"{self.name}: port is not open")
        if self.pace_baud:
            wait = self._next_write_t - self.clock.now()
            if wait > 0:
                self.clock.sleep(wait)
            self._next_write_t = max(self._next_write_t, self.clock.now()) + wire_time_s(len(data), self.pace_baud)
        try:
            self.port.write(data)
        except Exception as exc:
            raise LinkError(f"{self.name}: {failed('write', exc)}") from exc
        self.bytes_out += len(data)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("%s tx t=%.6f %r", self.name, self.clock.now(), bytes(data))

    def _read_available(self) -> bytes:
        try:
            n = self.port.in_waiting
            if n and getattr(self.port, "timeout", None) == 0:
                # non-blocking: take everything there is. pyserial's socket:// reports in_waiting as
                # 1 whenever anything is readable, so read(n) would take one byte per poll and a
                # caller polling once per frame falls ever further behind a chatty device
                n = max(n, 4096)
            data = self.port.read(n) if n else b""
        except Exception as exc:
            raise LinkError(f"{self.name}: {failed('read', exc)}") from exc
        if data:
            self.bytes_in += len(data)
            if log.isEnabledFor(logging.DEBUG):
                log.debug("%s rx t=%.6f %r", self.name, self.clock.now(), bytes(data))
        return data

    def poll(self, timeout_s: float = 0.0) -> bool:
        """Read whatever has arrived, waiting up to ``timeout_s`` for the first byte. True if any came."""
        deadline = self.clock.now() + timeout_s
        while True:
            data = self._read_available()
            if data:
                self._buf += data
                if len(self._buf) > self.max_buffer and self.eol not in self._buf[-self.max_buffer:]:
                    # a device that never ends a line (wrong baud, binary noise): keep memory bounded
                    cut = len(self._buf) - self.max_buffer
                    del self._buf[:cut]
                    self.bytes_discarded += cut
                return True
            now = self.clock.now()
            if now >= deadline:
                return False
            self.clock.sleep(min(self.poll_s, deadline - now))

    def discard_input(self) -> bytes:
        """Drop everything received so far (and not yet read as lines)."""
        self.poll(0.0)
        dropped = bytes(self._buf)
        self._buf.clear()
        return dropped

    # --- lines ------------------------------------------------------------------------------
    def _pop_line(self) -> str | None:
        idx = self._buf.find(self.eol)
        if idx < 0:
            return None
        raw = bytes(self._buf[:idx])
        del self._buf[: idx + len(self.eol)]
        return raw.decode("ascii", errors="replace").rstrip("\r")

    def readline(self, timeout_s: float | None = None) -> str | None:
        """The next complete line (without its end), or None after ``timeout_s``."""
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        deadline = self.clock.now() + timeout_s
        while True:
            line = self._pop_line()
            if line is not None:
                return line
            remaining = deadline - self.clock.now()
            if remaining <= 0:  # read what has arrived even with no time to wait (timeout 0: non-blocking)
                return self._pop_line() if self.poll(0.0) else None
            self.poll(remaining)

    def lines(self, timeout_s: float = 0.0) -> list[str]:
        """Every complete line available, waiting up to ``timeout_s`` for the first one."""
        first = self.readline(timeout_s)
        if first is None:
            return []
        out = [first]
        self.poll(0.0)
        while (line := self._pop_line()) is not None:
            out.append(line)
        return out

    def send_line(self, line: str) -> None:
        """Write ``line`` and its line end; the bytes are not read back."""
        self.write(line.encode("ascii") + self.eol)

    def request(self, line: str | None, is_reply: Callable[[str], bool], timeout_s: float | None = None,
                on_async: Callable[[str], None] | None = None) -> str:
        """Send ``line`` (if given) and return the first received line ``is_reply`` accepts.

        Lines that are not the reply go to ``on_async``. DeviceTimeout after ``timeout_s``.
        """
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        if line is not None:
            self.send_line(line)
        deadline = self.clock.now() + timeout_s
        while True:
            remaining = deadline - self.clock.now()
            got = self.readline(max(remaining, 0.0))
            if got is None:
                raise DeviceTimeout(f"{self.name}: no reply to {line!r} within {timeout_s:g} s")
            if is_reply(got):
                return got
            if on_async is not None:
                on_async(got)
