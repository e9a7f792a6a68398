"""A serial device on a TCP port, as ser2net serves one (raw TCP, one client at a time).

:class:`TcpSerialBridge` opens a tty (here the pty an emulator is served on) and copies bytes
between it and the one connected TCP client, unchanged: the device's pacing, protocol and
timing stay the tty's. Clients reach it with pyserial's ``socket://HOST:PORT`` URL. A second
client is refused while one is connected (ser2net's default), and the tty stays open between
clients so the device keeps its state, as a controller behind a real ser2net does.

:meth:`TcpSerialBridge.set_up` stops and restarts it as ser2net is stopped and restarted (a
dropped link): down, the client's connection and the port close (connecting is
refused) and what the device sends is lost; up, the same port listens again.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import socket
import threading
import tty
from typing import cast

log = logging.getLogger(__name__)


class TcpSerialBridge:
    """Serve the tty at ``path`` on ``host:port`` (0: any free port); ``url`` is what clients open."""

    def __init__(self, path: str, host: str = "127.0.0.1", port: int = 0):
        self.path = path
        self._fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        with contextlib.suppress(OSError):
            tty.setraw(self._fd)
        self._sock: socket.socket | None = socket.create_server((host, port))
        self._sock.settimeout(0.1)
        self.host, self.port = self._sock.getsockname()[:2]
        self._stop = threading.Event()
        self._want_up = True
        self.is_up = True
        self._changed = threading.Event()
        self.drops = 0
        self.clients = 0
        self.bytes_to_device = 0
        self.bytes_from_device = 0
        self._thread = threading.Thread(target=self._loop, name=f"ser2net-{port}", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        """The pyserial URL of this bridge (``socket://host:port``)."""
        return f"socket://{self.host}:{self.port}"

    def set_up(self, up: bool, timeout_s: float = 2.0) -> bool:
        """Stop (``up`` False) or restart (True) serving, as ser2net is stopped and started again;
        returns once the bridge is in that state (False if it did not get there in ``timeout_s``)."""
        self._changed.clear()
        self._want_up = bool(up)
        if self.is_up == self._want_up:
            return True
        return self._changed.wait(timeout_s)

    def _apply_up(self, client: socket.socket | None) -> socket.socket | None:
        """In the loop's thread: close or reopen the listening port as ``set_up`` asked; returns the client."""
        if self._want_up == self.is_up:
            return client
        if not self._want_up:
            if client is not None:
                client.close()
                client = None
            with contextlib.suppress(OSError):
                cast(socket.socket, self._sock).close()  # is_up: the port is listening
            self._sock = None
            self.drops += 1
            log.info("ser2net-style bridge %s:%s stopped", self.host, self.port)
        else:
            try:
                self._sock = socket.create_server((self.host, self.port))
            except OSError:  # the port is not free again yet: try on the next turn
                log.debug("cannot listen on %s:%s again yet", self.host, self.port, exc_info=True)
                return client
            self._sock.settimeout(0.1)
            log.info("ser2net-style bridge %s:%s started again", self.host, self.port)
        self.is_up = self._want_up
        self._changed.set()
        return client

    def _loop(self) -> None:
        client: socket.socket | None = None
        try:
            while not self._stop.is_set():
                client = self._apply_up(client)
                rlist = [self._fd] + ([self._sock] if self._sock is not None else []) + (
                    [client] if client is not None else [])
                try:
                    ready, _, _ = select.select(rlist, [], [], 0.1)
                except (OSError, ValueError):
                    return
                if self._sock is not None and self._sock in ready:
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
        with contextlib.suppress(OSError, AttributeError):
            if self._sock is not None:  # None while the port is down
                self._sock.close()
        with contextlib.suppress(OSError):
            os.close(self._fd)

    def __enter__(self) -> TcpSerialBridge:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
