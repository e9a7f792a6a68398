"""The host link: one ``Link`` interface, three transports (local pipe, TCP, RS-232 serial).

The paper joins Host 1 (predictor/planner) and Host 2 (recognizer) with a 9600-bps RS-232 line
(He et al. 1996, §5.1). ``drivers/host_link.yaml`` (``HostLinkConfig``) picks the transport:

* ``local``  — a ``multiprocessing.Pipe`` between two processes on one PC (the default). The
  supervisor makes both ends with :func:`local_pair` and hands one to each worker.
* ``tcp``    — two PCs: the predictor listens on ``host:tcp_port`` (``127.0.0.1`` unless the lab
  says otherwise), the recognizer connects. Before any message both sides prove that they hold
  the shared key (:func:`link_key`: ``$LABCTL_LINK_KEY`` or the file ``host_link.key_file``) by
  a mutual HMAC-SHA256 challenge — the scheme of ``multiprocessing.connection``'s ``authkey``:
  each side sends 32 random bytes, the other answers ``HMAC(key, tag ‖ challenge)``. A peer
  that fails (or stays silent for ``AUTH_TIMEOUT_S``) is refused, logged in one line, and the
  listener waits on for the real one; no byte from it is ever decoded. Frames are a 2-byte
  big-endian length and the message. Connecting retries until ``connect_timeout``; once up there
  is **no silent reconnect**: a broken connection is a dead peer (:class:`LinkClosed`), and the
  supervisor must stop the robot and table.
* ``serial`` — RS-232 via pyserial ``serial_for_url`` (a device, ``socket://``, ``rfc2217://``,
  ``loop://``…) at ``baud``. Each frame is ``00 COBS(message ‖ CRC-16/GENIBUS) 00``:
  COBS removes every zero from the body so ``00`` only ever delimits, the leading ``00`` ends
  any line noise before the frame, and the CRC catches flipped bits. Corrupt frames are dropped
  and counted (``frames_dropped``); the receiver resynchronises at the next ``00``. Overhead is
  5 bytes per message (payloads up to 252 bytes).

Every link counts ``bytes_sent``/``bytes_received`` (bytes on the wire: framing included for
TCP and serial; message bytes for local pipes) and calls ``log_hook(direction, msg, nbytes)``
for each message sent (``"send"``) or received (``"recv"``). Liveness is the workers' business
(heartbeats, ``HostLinkConfig.dead_after_s``), not the link's: a serial line never reports EOF.

:func:`pty_null_modem` is a virtual RS-232 cable: two real pseudo-terminals joined by a copier
thread that can pace bytes at a baud rate (10 bits per byte) and inject corruption.
"""

from __future__ import annotations

import binascii
import contextlib
import hashlib
import hmac
import logging
import os
import secrets
import select
import socket
import struct
import threading
import time
import tty
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from ..config.devices import HostLinkConfig
from ..decisions.messages import Message, MessageError, decode, encode
from ..drivers.serial_link import failed
from ..errors import DeviceError
from ..timebase import BITS_PER_BYTE, wire_time_s

log = logging.getLogger("labctl.link")

__all__ = [
    "AuthError", "authenticate", "link_key", "KEY_ENV",
    "HostLinkError", "LinkClosed", "Link", "LocalLink", "TcpLink", "TcpListener", "SerialHostLink", "local_pair",
    "tcp_listen", "tcp_connect", "open_link", "cobs_encode", "cobs_decode", "crc16", "serial_frame",
    "SerialDeframer", "SERIAL_OVERHEAD", "BITS_PER_BYTE", "wire_time_s", "pty_null_modem", "NullModem",
]

LogHook = Callable[[str, Message, int], None]

SERIAL_OVERHEAD = 5  # leading 00, COBS code byte, 2 CRC bytes, trailing 00
MAX_SERIAL_PAYLOAD = 252  # message + CRC within one 254-byte COBS block
TCP_HEADER = struct.Struct(">H")


class HostLinkError(DeviceError):
    """The host link cannot be opened or used (exit status 3, like other device faults)."""


class LinkClosed(HostLinkError):
    """The peer closed the link or the connection broke."""


class AuthError(HostLinkError):
    """The TCP peer did not prove that it holds the link's shared key."""


# ---- authentication: a mutual HMAC challenge (as multiprocessing.connection's authkey) ------------

KEY_ENV = "LABCTL_LINK_KEY"
AUTH_MAGIC = b"labctl-link-1\n"
AUTH_CHALLENGE = 32
AUTH_TIMEOUT_S = 5.0


def link_key(cfg: HostLinkConfig, lab_root: str | os.PathLike[str] | None = None) -> bytes | None:
    """The host link's shared key: ``$LABCTL_LINK_KEY``, else the file named by ``cfg.key_file``
    (relative to the lab folder), else None. A key shorter than 16 bytes is refused."""
    from pathlib import Path

    raw = os.environ.get(KEY_ENV)
    where = f"${KEY_ENV}"
    if not raw and cfg.key_file:
        path = Path(cfg.key_file).expanduser()
        if not path.is_absolute() and lab_root is not None:
            path = Path(lab_root) / path
        try:
            raw = path.read_text(encoding="utf-8").strip()
        except OSError as exc:
            raise HostLinkError(f"cannot read the host link key file {path}: {exc.strerror or exc}") from None
        where = str(path)
    if not raw:
        return None
    key = raw.encode("utf-8")
    if len(key) < 16:
        raise HostLinkError(f"the host link key from {where} is too short ({len(key)} bytes; use at least 16)")
    return key


def _digest(key: bytes, tag: bytes, challenge: bytes) -> bytes:
    return hmac.new(key, AUTH_MAGIC + tag + challenge, hashlib.sha256).digest()


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise AuthError("the peer closed the connection during authentication")
        buf += chunk
    return bytes(buf)


def authenticate(sock: socket.socket, key: bytes, *, server: bool, timeout_s: float = AUTH_TIMEOUT_S) -> None:
    """Mutual challenge-response over a fresh connection; AuthError if the peer does not hold ``key``.

    Server: sends magic ‖ challenge, checks the client's HMAC, answers the client's challenge.
    Client: answers, then challenges the server (so a fake listener cannot steer the recognizer)."""
    sock.settimeout(timeout_s)
    try:
        if server:
            c1 = secrets.token_bytes(AUTH_CHALLENGE)
            sock.sendall(AUTH_MAGIC + c1)
            if not hmac.compare_digest(_recv_exact(sock, 32), _digest(key, b"C", c1)):
                raise AuthError("wrong key")
            c2 = _recv_exact(sock, AUTH_CHALLENGE)
            sock.sendall(_digest(key, b"S", c2))
        else:
            hello = _recv_exact(sock, len(AUTH_MAGIC) + AUTH_CHALLENGE)
            if not hello.startswith(AUTH_MAGIC):
                raise AuthError("the listener does not speak the labctl host link")
            c2 = secrets.token_bytes(AUTH_CHALLENGE)
            sock.sendall(_digest(key, b"C", hello[len(AUTH_MAGIC):]) + c2)
            if not hmac.compare_digest(_recv_exact(sock, 32), _digest(key, b"S", c2)):
                raise AuthError("the listener does not hold the link key")
    except TimeoutError:
        raise AuthError(f"no authentication within {timeout_s:g} s") from None
    except OSError as exc:
        raise AuthError(f"connection failed during authentication: {exc.strerror or exc}") from None
    finally:
        with contextlib.suppress(OSError):
            sock.settimeout(None)


# ---- serial framing: pure functions -------------------------------------------------------------


def crc16(data: bytes) -> int:
    """CRC-16/GENIBUS (poly 0x1021, init 0xFFFF, xorout 0xFFFF); ``crc16(b"123456789") == 0xD64E``.

    The final inversion matters: with xorout 0 (CRC-16/CCITT-FALSE) a frame whose closing ``00``
    is hit by noise decodes as ``payload ‖ CRC ‖ 00``, and ``payload ‖ CRC[0]`` then checks
    against ``CRC[1] ‖ 00`` — always valid. Inverting the CRC breaks that identity.
    """
    return binascii.crc_hqx(data, 0xFFFF) ^ 0xFFFF


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing (Cheshire & Baker 1999): the result has no zero byte."""
    out = bytearray()
    block = bytearray()
    for b in data:
        if b == 0:
            out.append(len(block) + 1)
            out += block
            block.clear()
        else:
            block.append(b)
            if len(block) == 254:
                out.append(0xFF)
                out += block
                block.clear()
    out.append(len(block) + 1)
    out += block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Invert :func:`cobs_encode`; raise ``ValueError`` on an invalid encoding."""
    out = bytearray()
    i, n = 0, len(data)
    if n == 0:
        raise ValueError("empty COBS block")
    while i < n:
        code = data[i]
        if code == 0:
            raise ValueError("zero byte inside a COBS block")
        end = i + code
        if end > n:
            raise ValueError("truncated COBS block")
        block = data[i + 1:end]
        if 0 in block:
            raise ValueError("zero byte inside a COBS block")
        out += block
        i = end
        if code < 0xFF and i < n:
            out.append(0)
    return bytes(out)


def serial_frame(payload: bytes) -> bytes:
    """The bytes put on the serial line for one message payload: ``00 COBS(payload ‖ CRC) 00``."""
    if len(payload) > MAX_SERIAL_PAYLOAD:
        raise HostLinkError(f"message of {len(payload)} bytes exceeds the serial frame limit {MAX_SERIAL_PAYLOAD}")
    return b"\x00" + cobs_encode(payload + crc16(payload).to_bytes(2, "big")) + b"\x00"


class SerialDeframer:
    """Split a received byte stream into verified payloads (pure: no I/O).

    Bytes between two ``00`` delimiters are one frame; a frame whose COBS or CRC check fails, or
    that grows beyond the longest legal frame, is dropped and counted in ``dropped``.
    """

    MAX_WIRE = MAX_SERIAL_PAYLOAD + 3 + 1  # COBS(payload + CRC) is at most payload + 2 + 2

    def __init__(self) -> None:
        self._buf = bytearray()
        self._overflow = False  # discarding until the next delimiter
        self.dropped = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Feed received bytes; returns the payloads of the frames they complete (bad frames dropped and counted)."""
        out: list[bytes] = []
        for chunk_end in _split_keep(data):
            piece, ends = chunk_end
            if self._overflow:
                if ends:
                    self._overflow = False
                continue
            self._buf += piece
            if len(self._buf) > self.MAX_WIRE:
                self.dropped += 1
                self._buf.clear()
                self._overflow = not ends
                continue
            if ends:
                frame = bytes(self._buf)
                self._buf.clear()
                if frame:
                    payload = self._check(frame)
                    if payload is None:
                        self.dropped += 1
                    else:
                        out.append(payload)
        return out

    @staticmethod
    def _check(frame: bytes) -> bytes | None:
        try:
            body = cobs_decode(frame)
        except ValueError:
            return None
        if len(body) < 3:
            return None
        payload, crc = body[:-2], int.from_bytes(body[-2:], "big")
        return payload if crc16(payload) == crc else None


def _split_keep(data: bytes) -> Iterator[tuple[bytes, bool]]:
    """Yield (piece, ended_by_delimiter) for the zero-delimited pieces of ``data``."""
    start = 0
    while True:
        i = data.find(b"\x00", start)
        if i < 0:
            if start < len(data):
                yield data[start:], False
            return
        yield data[start:i], True
        start = i + 1


# ---- the Link interface --------------------------------------------------------------------------


class Link(ABC):
    """A bidirectional message channel to the other worker.

    ``send(msg)`` and ``recv(timeout)`` are safe to call from different threads (one lock each).
    ``recv`` returns ``None`` when ``timeout`` (s) passes without a message and raises
    :class:`LinkClosed` when the peer is gone (where the transport can tell).
    """

    transport: str = "?"

    def __init__(self, log_hook: LogHook | None = None) -> None:
        self.log_hook = log_hook
        self.bytes_sent = 0
        self.bytes_received = 0
        self.messages_sent = 0
        self.messages_received = 0
        self._undecodable = 0  # well-framed payloads that were not a valid message
        self.closed = False
        self._send_lock = threading.Lock()
        self._recv_lock = threading.Lock()

    # multiprocessing may pickle a LocalLink into a child process: drop locks and the hook
    def __getstate__(self):
        state = self.__dict__.copy()
        for k in ("_send_lock", "_recv_lock", "log_hook"):
            state.pop(k, None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self.log_hook = None
        self._send_lock = threading.Lock()
        self._recv_lock = threading.Lock()

    @property
    def frames_dropped(self) -> int:
        """Frames received but thrown away: corrupt framing (serial) or not a valid message."""
        return self._undecodable + self._framing_dropped()

    def _framing_dropped(self) -> int:
        return 0

    def send(self, msg: Message) -> int:
        """Send one message; return the bytes it took on the wire."""
        payload = encode(msg)
        if self.closed:
            raise LinkClosed(f"{self.transport} link is closed")
        with self._send_lock:
            n = self._send_payload(payload)
            self.bytes_sent += n
            self.messages_sent += 1
        if self.log_hook is not None:
            self.log_hook("send", msg, n)
        return n

    def recv(self, timeout: float | None = None) -> Message | None:
        """The next message, or ``None`` after ``timeout`` seconds (``None`` = wait forever)."""
        if self.closed:
            raise LinkClosed(f"{self.transport} link is closed")
        deadline = None if timeout is None else time.monotonic() + max(0.0, timeout)
        with self._recv_lock:
            while True:
                got = self._next_payload(deadline)
                if got is None:
                    return None
                payload, n = got
                try:
                    msg = decode(payload)
                except MessageError:
                    self._undecodable += 1
                    continue
                self.messages_received += 1
                break
        if self.log_hook is not None:
            self.log_hook("recv", msg, n)
        return msg

    def close(self) -> None:
        """Close the link (idempotent)."""
        if not self.closed:
            self.closed = True
            self._close()

    def stats(self) -> dict:
        """Bytes and messages sent and received, and frames dropped, for the run's result."""
        return {"transport": self.transport, "bytes_sent": self.bytes_sent, "bytes_received": self.bytes_received,
                "messages_sent": self.messages_sent, "messages_received": self.messages_received,
                "frames_dropped": self.frames_dropped}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @abstractmethod
    def _send_payload(self, payload: bytes) -> int:
        """Put one encoded message on the wire; return the wire bytes used."""

    @abstractmethod
    def _next_payload(self, deadline: float | None) -> tuple[bytes, int] | None:
        """Next framed payload and the wire bytes it took (0 if already counted), or None at the deadline."""

    @abstractmethod
    def _close(self) -> None: ...


def _remaining(deadline: float | None) -> float | None:
    return None if deadline is None else max(0.0, deadline - time.monotonic())


# ---- local: multiprocessing pipe -----------------------------------------------------------------


class LocalLink(Link):
    """One end of a ``multiprocessing.Pipe``; picklable into a child process at spawn time."""

    transport = "local"

    def __init__(self, conn, log_hook: LogHook | None = None) -> None:
        super().__init__(log_hook)
        self._conn = conn

    def _send_payload(self, payload):
        try:
            self._conn.send_bytes(payload)
        except (OSError, EOFError, ValueError) as exc:
            raise LinkClosed(f"local link: peer gone ({exc})") from exc
        return len(payload)

    def _next_payload(self, deadline):
        try:
            if not self._conn.poll(_remaining(deadline)):
                return None
            payload = self._conn.recv_bytes()
        except (OSError, EOFError, ValueError) as exc:
            raise LinkClosed("local link: peer closed") from exc
        self.bytes_received += len(payload)
        return payload, len(payload)

    def _close(self):
        self._conn.close()


def local_pair() -> tuple[LocalLink, LocalLink]:
    """Two connected local links (predictor end, recognizer end) over a duplex pipe.

    Hand one to each worker process, then close the parent's copies so that a worker's death
    shows up as :class:`LinkClosed` at the other end (with the ``fork`` start method a child
    also inherits the other end, so rely on heartbeats for liveness).
    """
    import multiprocessing

    a, b = multiprocessing.Pipe(duplex=True)
    return LocalLink(a), LocalLink(b)


# ---- TCP ----------------------------------------------------------------------------------------


class TcpLink(Link):
    """A connected TCP socket carrying ``[u16 length][message]`` frames (TCP_NODELAY)."""

    transport = "tcp"

    def __init__(self, sock: socket.socket, log_hook: LogHook | None = None) -> None:
        super().__init__(log_hook)
        sock.setblocking(True)
        sock.settimeout(None)
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        self._buf = bytearray()
        try:
            self.peer = sock.getpeername()
        except OSError:
            self.peer = None

    def _send_payload(self, payload):
        frame = TCP_HEADER.pack(len(payload)) + payload
        try:
            self._sock.sendall(frame)
        except OSError as exc:
            raise LinkClosed(f"tcp link to {self.peer}: {exc.strerror or exc}") from exc
        return len(frame)

    def _next_payload(self, deadline):
        while True:
            if len(self._buf) >= TCP_HEADER.size:
                (n,) = TCP_HEADER.unpack_from(self._buf)
                if len(self._buf) >= TCP_HEADER.size + n:
                    payload = bytes(self._buf[TCP_HEADER.size:TCP_HEADER.size + n])
                    del self._buf[:TCP_HEADER.size + n]
                    return payload, 0
            wait = _remaining(deadline)
            try:
                ready, _, _ = select.select([self._sock], [], [], wait)
                if not ready:
                    return None
                data = self._sock.recv(65536)
            except (OSError, ValueError) as exc:
                raise LinkClosed(f"tcp link to {self.peer}: {exc}") from exc
            if not data:
                raise LinkClosed(f"tcp link: peer {self.peer} closed the connection")
            self.bytes_received += len(data)
            self._buf += data

    def _close(self):
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)
        self._sock.close()


class TcpListener:
    """A listening socket (the predictor's side); ``port`` is the bound port (useful with port 0)."""

    def __init__(self, host: str, port: int) -> None:
        try:
            self._sock = socket.create_server((host, port), reuse_port=False)
        except OSError as exc:
            raise HostLinkError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from exc
        self.host = host
        self.port = self._sock.getsockname()[1]

    def accept(self, timeout: float | None = 30.0, log_hook: LogHook | None = None, *,
               authkey: bytes | None = None, on_refused: Callable[[str], None] | None = None) -> TcpLink:
        """Wait up to ``timeout`` s for the peer to connect; HostLinkError if it does not.

        With ``authkey`` the peer must pass :func:`authenticate`; a peer that fails is closed, logged
        in one line (``labctl.link`` warning, and ``on_refused(line)``) and the wait goes on."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            ready, _, _ = select.select([self._sock], [], [], _remaining(deadline))
            if not ready:
                raise HostLinkError(f"no peer connected to {self.host}:{self.port} within {timeout:g} s")
            conn, addr = self._sock.accept()
            if authkey is None:
                return TcpLink(conn, log_hook)
            try:
                authenticate(conn, authkey, server=True)
            except AuthError as exc:
                line = f"host link: refused peer {addr[0]}:{addr[1]} ({exc})"
                log.warning(line)
                if on_refused is not None:
                    with contextlib.suppress(Exception):
                        on_refused(line)
                with contextlib.suppress(OSError):
                    conn.close()
                continue
            return TcpLink(conn, log_hook)

    def close(self) -> None:
        """Stop listening."""
        self._sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def tcp_listen(host: str, port: int) -> TcpListener:
    """Listen for one worker's TCP connection on ``host:port`` (port 0: any free port)."""
    return TcpListener(host, port)


def tcp_connect(host: str, port: int, timeout: float = 30.0, retry_s: float = 0.1,
                log_hook: LogHook | None = None, *, authkey: bytes | None = None) -> TcpLink:
    """Connect to ``host:port``, retrying every ``retry_s`` while refused, for up to ``timeout`` s;
    with ``authkey``, then prove the key and check that the listener holds it (AuthError if not)."""
    deadline = time.monotonic() + timeout
    last: OSError | None = None
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        try:
            sock = socket.create_connection((host, port), timeout=min(left, 5.0))
        except OSError as exc:
            last = exc
            time.sleep(min(retry_s, max(0.0, deadline - time.monotonic())))
            continue
        if authkey is not None:
            try:
                authenticate(sock, authkey, server=False)
            except AuthError as exc:
                sock.close()
                raise AuthError(f"host link to {host}:{port}: {exc} (same LABCTL_LINK_KEY on both hosts?)") from None
        return TcpLink(sock, log_hook)
    why = (last.strerror or str(last)) if last else "timed out"
    raise HostLinkError(f"could not connect to {host}:{port} within {timeout:g} s ({why})")


# ---- serial -------------------------------------------------------------------------------------


class SerialHostLink(Link):
    """Messages over an RS-232 line in COBS + CRC-16 frames (see the module docstring)."""

    transport = "serial"
    POLL_S = 0.05  # longest single blocking read; a read returns as soon as one byte arrives

    def __init__(self, port, log_hook: LogHook | None = None) -> None:
        super().__init__(log_hook)
        self._port = port
        self._deframer = SerialDeframer()
        self._ready: list[bytes] = []

    @classmethod
    def open(cls, url: str, baud: int = 9600, log_hook: LogHook | None = None) -> SerialHostLink:
        """Open a pyserial port (device path or URL) at ``baud``, 8N1, no flow control."""
        import serial

        from ..drivers.serial_link import open_port

        try:
            port = open_port(url, write_timeout_s=5.0, baudrate=baud, bytesize=8, parity="N", stopbits=1,
                             timeout=cls.POLL_S)
        except (serial.SerialException, ValueError, OSError) as exc:
            raise HostLinkError(f"cannot open serial port {url!r}: {exc}") from exc
        with contextlib.suppress(Exception):
            port.reset_input_buffer()
        return cls(port, log_hook)

    def _framing_dropped(self) -> int:
        return self._deframer.dropped

    def _send_payload(self, payload):
        import serial

        frame = serial_frame(payload)
        try:
            self._port.write(frame)
        except (serial.SerialException, OSError) as exc:
            raise LinkClosed(f"serial link: {failed('write', exc)}") from exc
        return len(frame)

    def _next_payload(self, deadline):
        import serial

        while not self._ready:
            wait = _remaining(deadline)
            want = self.POLL_S if wait is None else min(self.POLL_S, wait)  # 0: just take what is there
            try:
                if self._port.timeout != want:
                    self._port.timeout = want
                data = self._port.read(max(1, self._port.in_waiting))
            except (serial.SerialException, OSError) as exc:
                raise LinkClosed(f"serial link: {failed('read', exc)}") from exc
            if data:
                self.bytes_received += len(data)
                self._ready.extend(self._deframer.feed(data))
            elif wait is not None and wait <= 0:
                return None
        return self._ready.pop(0), 0

    def _close(self):
        with contextlib.suppress(Exception):
            self._port.close()


# ---- factory ------------------------------------------------------------------------------------


def open_link(cfg: HostLinkConfig, role: str, *, local_end: LocalLink | None = None, connect_timeout: float = 30.0,
              log_hook: LogHook | None = None, authkey: bytes | None = None,
              on_refused: Callable[[str], None] | None = None) -> Link:
    """Open this worker's end of the host link described by ``cfg`` (a ``HostLinkConfig``).

    ``role`` is ``"predictor"`` (Host 1: listens for TCP) or ``"recognizer"`` (Host 2: connects).
    The local transport cannot be opened from one side alone: pass the end that the supervisor
    made with :func:`local_pair` as ``local_end``. TCP always authenticates: ``authkey`` (see
    :func:`link_key`) is required, and refused peers are reported to ``on_refused``.
    """
    if role not in ("predictor", "recognizer"):
        raise HostLinkError(f"link role must be 'predictor' or 'recognizer', not {role!r}")
    kind = cfg.transport
    if kind == "local":
        if local_end is None:
            raise HostLinkError("the local host link is made by the supervisor (local_pair()); pass local_end")
        local_end.log_hook = log_hook or local_end.log_hook
        return local_end
    if kind == "tcp":
        if not authkey:
            raise HostLinkError(f"the TCP host link needs a shared key: set ${KEY_ENV} (16+ characters) on both "
                            "hosts, or name a key file in drivers/host_link.yaml (key_file)")
        if role == "predictor":
            with tcp_listen(cfg.host, cfg.tcp_port) as listener:
                return listener.accept(connect_timeout, log_hook, authkey=authkey, on_refused=on_refused)
        return tcp_connect(cfg.host, cfg.tcp_port, connect_timeout, log_hook=log_hook, authkey=authkey)
    if kind == "serial":
        if not cfg.port:
            raise HostLinkError("a serial host link needs a port (drivers/host_link.yaml: port)")
        return SerialHostLink.open(cfg.port, cfg.baud, log_hook)
    raise HostLinkError(f"unknown host-link transport {kind!r} (local, tcp or serial)")


# ---- a virtual RS-232 cable ---------------------------------------------------------------------


@dataclass
class NullModem:
    """Two pty device paths joined like a crossed RS-232 cable; see :func:`pty_null_modem`."""

    port_a: str
    port_b: str
    bytes_a_to_b: int = 0
    bytes_b_to_a: int = 0


@contextlib.contextmanager
def pty_null_modem(baud: float | None = None,
                   corrupt: Callable[[bytes], bytes] | None = None) -> Iterator[NullModem]:
    """Yield a :class:`NullModem` whose ``port_a``/``port_b`` are real pty slave devices.

    A thread per direction copies bytes between the two pty masters. With ``baud`` each chunk
    is delivered no sooner than its 8N1 wire time after the line became free (so latency and
    throughput are those of a real line); ``corrupt(chunk) -> chunk`` may alter bytes in flight
    (noise injection). Both ptys are in raw mode. Threads and descriptors end with the block.
    """
    m_a, s_a = os.openpty()
    m_b, s_b = os.openpty()
    fds = [m_a, s_a, m_b, s_b]
    for fd in (s_a, s_b):
        tty.setraw(fd)
    modem = NullModem(os.ttyname(s_a), os.ttyname(s_b))
    stop = threading.Event()

    def pump(src: int, dst: int, counter: str) -> None:
        line_free = time.monotonic()
        while not stop.is_set():
            try:
                ready, _, _ = select.select([src], [], [], 0.05)
                if not ready:
                    continue
                chunk = os.read(src, 4096)
            except OSError:
                return
            if not chunk:
                continue
            if baud:
                line_free = max(line_free, time.monotonic()) + wire_time_s(len(chunk), baud)
                delay = line_free - time.monotonic()
                if delay > 0 and stop.wait(delay):
                    return
            if corrupt is not None:
                chunk = corrupt(chunk)
            setattr(modem, counter, getattr(modem, counter) + len(chunk))
            try:
                os.write(dst, chunk)
            except OSError:
                return

    threads = [threading.Thread(target=pump, args=(m_a, m_b, "bytes_a_to_b"), daemon=True),
               threading.Thread(target=pump, args=(m_b, m_a, "bytes_b_to_a"), daemon=True)]
    for t in threads:
        t.start()
    try:
        yield modem
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=2.0)
        for fd in fds:
            with contextlib.suppress(OSError):
                os.close(fd)
