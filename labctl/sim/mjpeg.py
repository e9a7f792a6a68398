"""Cameras as MJPEG-over-HTTP streams, as mjpg-streamer or ustreamer serve a Raspberry Pi camera.

:class:`MjpegServer` (a stdlib ``ThreadingHTTPServer``) serves each named camera at
``/<name>.mjpg`` (``multipart/x-mixed-replace``, one JPEG per part with ``Content-Length``,
``X-Timestamp`` — the exposure time on the wall clock, seconds, as mjpg-streamer sends it — and
``X-Frame-Seq``) and one JPEG at ``/<name>.jpg``. One producer thread per camera grabs frames
(``grab()`` of any :class:`~labctl.drivers.interfaces.Camera`), encodes them once and hands the
newest to every client; it renders only while a client is connected. A slow client skips
frames rather than delaying the others (latest-frame semantics, as the real servers do).

``controls={name: fn}`` adds ``/control/<name>``: ``POST`` (or ``GET``) with query parameters
calls ``fn({key: value})`` and answers its dict as JSON (400 with the message if it raises
ValueError) — the served simulator's stand-in for what a person does at the lab (e.g. put the
calibration target on a spacer).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import cast

log = logging.getLogger(__name__)

BOUNDARY = "labctlframe"


class _Stream:
    """One camera's producer: the newest encoded frame and who is waiting for it."""

    def __init__(self, name: str, camera, clock: Callable[[], float], quality: int,
                 wall_clock: Callable[[], float] = time.time):
        self.name, self.camera, self.clock, self.quality = name, camera, clock, quality
        self.wall_clock = wall_clock
        self.cond = threading.Condition()
        self.clients = 0
        self.jpeg: bytes | None = None
        self.t_wall = 0.0
        self.seq = 0
        self.error: str | None = None
        self.frames = 0
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._run, name=f"mjpeg-{name}", daemon=True)

    def _run(self) -> None:
        import cv2

        while not self.stopping.is_set():
            with self.cond:
                self.cond.wait_for(lambda: self.clients > 0 or self.stopping.is_set(), 0.5)
                if self.clients == 0:
                    continue
            try:
                frame = self.camera.grab()
                ok, buf = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, self.quality])
                if not ok:
                    raise RuntimeError("JPEG encoding failed")
                # the exposure time on the wall clock: now on the wall clock, minus how long ago it was
                t_wall = self.wall_clock() - (self.clock() - frame.t)
            except Exception as exc:  # a camera that fails ends its stream with the reason
                log.exception("camera %s failed", self.name)
                with self.cond:
                    self.error = f"{type(exc).__name__}: {exc}"
                    self.cond.notify_all()
                return
            with self.cond:
                self.jpeg, self.t_wall, self.seq = buf.tobytes(), t_wall, int(frame.seq)
                self.frames += 1
                self.cond.notify_all()

    def next_after(self, seq: int | None, timeout_s: float = 5.0) -> tuple[bytes, float, int] | None:
        """The newest frame newer than ``seq`` (wait up to ``timeout_s``), or None."""
        with self.cond:
            self.cond.wait_for(lambda: self.error is not None or self.stopping.is_set() or (
                self.jpeg is not None and (seq is None or self.seq != seq)), timeout_s)
            if self.error is not None or self.stopping.is_set() or self.jpeg is None or self.seq == seq:
                return None
            return self.jpeg, self.t_wall, self.seq


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.0"

    def log_message(self, fmt, *args) -> None:  # quiet: the serve command prints its own lines
        log.debug("mjpeg %s: " + fmt, self.client_address[0], *args)

    def _control(self) -> bool:
        """Serve ``/control/<name>?k=v…`` if that is the path; True if it was."""
        import json
        from urllib.parse import parse_qs, urlsplit

        parts = urlsplit(self.path)
        head, _, name = parts.path.strip("/").partition("/")
        if head != "control":
            return False
        fn = self.server.controls.get(name)
        if fn is None:
            self.send_error(404, f"no control {name!r} (have: {', '.join(self.server.controls) or 'none'})")
            return True
        params = {k: v[-1] for k, v in parse_qs(parts.query, keep_blank_values=True).items()}
        try:
            body = json.dumps(fn(params)).encode()
        except ValueError as exc:
            body = json.dumps({"error": str(exc)}).encode()
            self.send_response(400)
        else:
            self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)
        return True

    def do_POST(self) -> None:  # noqa: N802 (http.server's name)
        if not self._control():
            self.send_error(405, "POST only to /control/<name>")

    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        if self._control():
            return
        path = self.path.split("?")[0].strip("/")
        name, _, ext = path.partition(".")
        stream = self.server.streams.get(name)
        if stream is None or ext not in ("mjpg", "jpg"):
            self.send_error(404, f"no stream {self.path!r} (have: "
                                 + ", ".join(f"/{n}.mjpg" for n in self.server.streams) + ")")
            return
        with stream.cond:
            stream.clients += 1
            stream.cond.notify_all()
        try:
            if ext == "jpg":
                self._snapshot(stream)
            else:
                self._stream(stream)
        except (BrokenPipeError, ConnectionResetError, TimeoutError, OSError):
            pass  # the client went away
        finally:
            with stream.cond:
                stream.clients -= 1

    def _snapshot(self, stream: _Stream) -> None:
        got = stream.next_after(None)
        if got is None:
            self.send_error(503, f"camera {stream.name}: {stream.error or 'no frame'}")
            return
        jpeg, t_wall, seq = got
        self.send_response(200)
        self.send_header("Content-Type", "image/jpeg")
        self.send_header("Content-Length", str(len(jpeg)))
        self.send_header("X-Timestamp", f"{t_wall:.6f}")
        self.send_header("X-Frame-Seq", str(seq))
        self.end_headers()
        self.wfile.write(jpeg)

    def _stream(self, stream: _Stream) -> None:
        self.send_response(200)
        self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
        self.send_header("Cache-Control", "no-cache, no-store, must-revalidate")
        self.send_header("Connection", "close")
        self.end_headers()
        seq = None
        while not self.server.stopping.is_set():
            got = stream.next_after(seq)
            if got is None:
                if stream.error is not None:
                    return
                continue
            jpeg, t_wall, seq = got
            head = (f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n"
                    f"X-Timestamp: {t_wall:.6f}\r\nX-Frame-Seq: {seq}\r\n\r\n").encode()
            self.wfile.write(head + jpeg + b"\r\n")
            self.wfile.flush()


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True
    streams: dict[str, _Stream]
    controls: dict[str, Callable[[dict], dict]]
    stopping: threading.Event


class MjpegServer:
    """Serve cameras ``{name: Camera}`` (opened by the caller) over HTTP on ``host:port`` (0: any free),
    and ``controls`` ``{name: fn(params) -> dict}`` at ``/control/<name>``."""

    def __init__(self, cameras: dict, clock: Callable[[], float], host: str = "127.0.0.1", port: int = 0,
                 quality: int = 90, controls: dict | None = None):
        self._server = _Server((host, port), _Handler)
        self._server.streams = {n: _Stream(n, cam, clock, quality) for n, cam in cameras.items()}
        self._server.controls = dict(controls or {})
        self._server.stopping = threading.Event()
        bound_host, self.port = self._server.server_address[:2]
        self.host = cast(str, bound_host)  # an IPv4 server's address is (host, port)
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.1},
                                        name="mjpeg-server", daemon=True)

    def url(self, name: str) -> str:
        """URL of the MJPEG stream ``name`` (``fixed`` or ``mobile``)."""
        return f"http://{self.host}:{self.port}/{name}.mjpg"

    def control_url(self, name: str) -> str:
        """URL of the control endpoint ``name`` (e.g. ``scene``)."""
        return f"http://{self.host}:{self.port}/control/{name}"

    @property
    def urls(self) -> dict[str, str]:
        """URL of every stream, by name."""
        return {n: self.url(n) for n in self._server.streams}

    def stats(self) -> dict:
        """Per stream: frames served, clients connected, the last error."""
        return {n: {"frames": s.frames, "clients": s.clients, "error": s.error}
                for n, s in self._server.streams.items()}

    def start(self) -> MjpegServer:
        """Start the streams' render threads and the HTTP server; returns the server."""
        for s in self._server.streams.values():
            s.thread.start()
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the streams and the HTTP server and join their threads."""
        self._server.stopping.set()
        for s in self._server.streams.values():
            s.stopping.set()
            with s.cond:
                s.cond.notify_all()
        if self._thread.is_alive():  # shutdown() waits for serve_forever: only if it runs
            self._server.shutdown()
        self._server.server_close()
        for s in self._server.streams.values():
            if s.thread.is_alive():
                s.thread.join(timeout=2.0)

    def __enter__(self) -> MjpegServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
