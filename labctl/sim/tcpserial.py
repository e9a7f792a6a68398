"""A serial device on a TCP port, as ser2net serves one (raw TCP, one client at a time).

:class:`TcpSerialBridge` opens a tty (here the pty an emulator is served on) and copies bytes
between it and the one connected TCP client, unchanged: the device's pacing, protocol and
timing stay the tty's. Clients reach it with pyserial's ``socket://HOST:PORT`` URL. A second
client is refused while one is connected (ser2net's default), and the tty stays open between
clients so the device keeps its state, as a controller behind a real ser2net does.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import socket
import threading
import tty

log = logging.getLogger(__name__)


class TcpSerialBridge:
    """Serve the tty at ``path`` on ``host:port`` (0: any free port); ``url`` is what clients open."""

    def __init__(self, path: str, host: str = "127.0.0.1", port: int = 0):
        self.path = path
        self._fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        with contextlib.suppress(OSError):
            tty.setraw(self._fd)
        self._sock = socket.create_server((host, port))
        self._sock.settimeout(0.1)
        self.host, self.port = self._sock.getsockname()[:2]
        self._stop = threading.Event()
        self.clients = 0
        self.bytes_to_device = 0
        self.bytes_from_device = 0
        self._thread = threading.Thread(target=self._loop, name=f"ser2net-{port}", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        """The pyserial URL of this bridge (``socket://host:port``)."""
        return f"socket://{self.host}:{self.port}"

    def _loop(self) -> None:
        client: socket.socket | None = None
        try:
            while not self._stop.is_set():
                rlist = [self._sock, self._fd] + ([client] if client is not None else [])
                try:
                    ready, _, _ = select.select(rlist, [], [], 0.1)
                except (OSError, ValueError):
                    return
                if self._sock in ready:
                    with contextlib.suppress(OSError, TimeoutError):
                        conn, _ = self._sock.accept()
                        if client is None:
                            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                            conn.setblocking(True)
                            client = conn
                            self.clients += 1
                        else:
                            conn.close()  # the port is in use (ser2net: one client)
                if self._fd in ready:
                    try:
                        data = os.read(self._fd, 4096)
                    except (BlockingIOError, OSError):
                        data = b""
                    if data and client is not None:  # no client: the device talks to no one
                        try:
                            client.sendall(data)
                            self.bytes_from_device += len(data)
                        except OSError:
                            client.close()
                            client = None
                if client is not None and client in ready:
                    try:
                        data = client.recv(4096)
                    except OSError:
                        data = b""
                    if not data:
                        client.close()
                        client = None
                        continue
                    view = memoryview(data)
                    while view and not self._stop.is_set():
                        try:
                            n = os.write(self._fd, view)
                            view = view[n:]
                            self.bytes_to_device += n
                        except BlockingIOError:
                            select.select([], [self._fd], [], 0.05)
        finally:
            if client is not None:
                client.close()

    def stop(self) -> None:
        """Close the port (clients see the connection drop) and the tty."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(timeout=2.0)
        with contextlib.suppress(OSError):
            self._sock.close()
        with contextlib.suppress(OSError):
            os.close(self._fd)

    def __enter__(self) -> TcpSerialBridge:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
