"""Cameras: V4L2 and network streams behind one latest-frame grabber, a replay camera, the factory.

* :class:`GrabberCamera` — a grabber thread reads a :class:`CaptureSource` as fast as it
  delivers and keeps only the newest frame, so ``grab()`` never returns a stale buffered one:
  it waits for a frame captured after the call began (``wait_new=False``: the newest, even if
  delivered before). Frame times are on the caller's clock (``time.monotonic`` by default):
  the source's own capture time when it has one, else the time the frame arrived minus the
  configured ``latency_s``. It also keeps the last ``backlog`` frames, so ``grab_recent()`` returns the
  ones not yet delivered, in order. ``dropped`` counts frames never delivered.
  ``close()`` stops the grabber and joins it before the source is released (the thread owns
  the source and releases it itself, so a read blocked past the join timeout cannot race).
* :class:`V4L2Camera` — ``cv2.VideoCapture(device, cv2.CAP_V4L2)`` with resolution, fps and
  exposure from the camera's driver file.
* :class:`StreamCamera` (``kind: stream``) — a network camera by URL: MJPEG over HTTP as
  mjpg-streamer, ustreamer or ffmpeg's ``-f mpjpeg`` serve it (read with the standard library,
  chunked transfer undone, frames decoded with ``cv2.imdecode``, the parts' ``X-Timestamp``
  header usable as the capture time), or any URL
  OpenCV's FFmpeg backend opens (RTSP; ``backend: opencv``).
* :class:`ReplayCamera` serves a folder of images named by capture time (``<t_seconds>.png``,
  e.g. ``12.345678.png``), or listed in ``index.csv`` (``t,file`` rows); ``grab()`` returns the
  frames in order (or, with a clock, the newest frame at or before the clock's time).
* :func:`open_camera(role, lab)` builds the camera a lab's driver file names (v4l2, stream, replay;
  simulated cameras come from the simulated lab: :func:`labctl.runtime.devices.open_device`).
"""

from __future__ import annotations

import contextlib
import csv
import logging
import re
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from ..errors import DeviceError
from .interfaces import Camera, Frame, OpenClose
from .serial_link import DeviceTimeout

if TYPE_CHECKING:
    from ..config import Lab

log = logging.getLogger(__name__)

_STAMP = re.compile(r"^(\d+(?:\.\d+)?)\.(png|jpg|jpeg|bmp|tif|tiff)$", re.IGNORECASE)


#: how long closing an FFmpeg stream waits for its grabber thread (s): a live stream's read returns within a
#: frame period (33 ms at 30 fps); a dead one's only at FFmpeg's read time-out, and the thread then releases
#: the capture by itself
STREAM_CLOSE_WAIT_S = 0.25


class CameraError(DeviceError):
    """The camera could not be opened or stopped delivering frames."""


class CaptureSource(Protocol):
    """Where a :class:`GrabberCamera`'s frames come from (a capture device, a stream, a test fake)."""

    def read(self) -> tuple[np.ndarray | None, float | None]:
        """Block until the next frame: ``(BGR image, capture time on the wall clock or None)``;
        ``(None, None)`` for a frame that could not be decoded. Raises ``OSError``/``CameraError``
        when the source ends."""
        ...

    def interrupt(self) -> None:
        """Unblock a :meth:`read` waiting in another thread (a no-op where a read returns on its own)."""

    def release(self) -> None:
        """Give the device back (close the file, socket or capture)."""

    def stall_reason(self) -> str | None:
        """Why no frame came lately, when the source knows (parts that do not decode); else None."""


class GrabberCamera(OpenClose):
    """Latest-frame semantics over any :class:`CaptureSource` (see the module docstring).

    ``latency_s``: how long before its arrival a frame without its own capture time was exposed
    (the camera's exposure-to-delivery delay; measure it and put it in the driver file). ``backlog``:
    how many of the newest frames :meth:`grab_recent` can return.
    """

    kind = "grabber"

    def __init__(self, *, timeout_s: float = 2.0, latency_s: float = 0.0,
                 clock: Callable[[], float] = time.monotonic, name: str = "",
                 wall_clock: Callable[[], float] = time.time, backlog: int = 16):
        self.timeout_s, self.latency_s = timeout_s, latency_s
        self.clock, self.wall_clock = clock, wall_clock
        self.name = name
        self._source: CaptureSource | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._cond = threading.Condition()
        self._latest: Frame | None = None
        self._recent: deque[Frame] = deque(maxlen=max(1, int(backlog)))
        self._seq = 0  # frames captured
        self._delivered = 0  # seq of the last frame grab() returned
        self._error: str | None = None
        self.dropped = 0  # frames never delivered (counted when a later one is)
        self.close_timeout_s = 2.0  # how long close() waits for the grabber to leave a blocked read

    def _open_source(self) -> CaptureSource:
        raise NotImplementedError

    def _meta(self) -> dict:
        return {}

    def open(self) -> None:
        """Open the source and start the grabber thread that keeps only the latest frame (idempotent)."""
        if self._thread is not None:
            return
        source = self._open_source()
        with self._cond:
            self._latest, self._seq, self._delivered, self._error, self.dropped = None, 0, 0, None, 0
            self._recent.clear()
        self._source = source
        self._stop.clear()
        self._thread = threading.Thread(target=self._grabber, args=(source,), name=f"grabber-{self.name}",
                                        daemon=True)
        self._thread.start()

    def _grabber(self, source: CaptureSource) -> None:
        meta = self._meta()
        try:
            while not self._stop.is_set():
                try:
                    image, t_wall = source.read()
                except Exception as exc:  # the source ended or failed: grab() reports it
                    if not self._stop.is_set():
                        with self._cond:
                            self._error = f"the camera stopped delivering frames ({exc})"
                            self._cond.notify_all()
                    return
                t_arrived = self.clock()
                if image is None or self._stop.is_set():
                    continue
                if image.ndim == 2:
                    image = np.repeat(image[:, :, None], 3, axis=2)
                # the source's own capture time (wall clock) mapped onto our clock, else arrival − latency
                t = t_arrived - (self.wall_clock() - t_wall) if t_wall is not None else t_arrived - self.latency_s
                with self._cond:
                    self._seq += 1
                    self._latest = Frame(image=image, t=t, seq=self._seq, meta={**meta, "t_arrived": t_arrived})
                    self._recent.append(self._latest)
                    self._cond.notify_all()
        finally:
            with contextlib.suppress(Exception):
                source.release()

    def grab(self, wait_new: bool = True) -> Frame:
        """The newest frame; with ``wait_new`` one captured after this call began (never a stale one)."""
        with self._cond:
            return self._deliver(self._seq if wait_new else -1, 1)[-1]

    def grab_recent(self, max_frames: int) -> list[Frame]:
        """The frames captured since the last one delivered, oldest first: the newest ``max_frames`` of them
        (at most ``backlog``); waits for a new one if every frame was delivered."""
        with self._cond:
            return self._deliver(self._delivered, max_frames)

    def _deliver(self, after_seq: int, max_frames: int) -> list[Frame]:
        # under self._cond: wait for a frame newer than after_seq, then hand out the undelivered ones
        if self._thread is None:
            raise CameraError(f"camera {self.name} is not open")
        ok = self._cond.wait_for(lambda: self._error is not None or (
            self._latest is not None and self._latest.seq > after_seq), self.timeout_s)
        if self._error is not None:
            raise CameraError(f"camera {self.name}: {self._error}")
        if not ok or self._latest is None:
            why = self._source.stall_reason() if self._source is not None else None
            raise DeviceTimeout(f"camera {self.name}: no frame within {self.timeout_s:g} s"
                                + (f": {why}" if why else ""))
        frames = [f for f in self._recent if f.seq > self._delivered][-max(1, int(max_frames)):] or [self._latest]
        self.dropped += max(0, frames[-1].seq - self._delivered - len(frames))
        self._delivered = max(self._delivered, frames[-1].seq)
        return frames

    @property
    def frames(self) -> int:
        """Frames grabbed since the camera was opened."""
        return self._seq

    def info(self) -> dict:
        """Kind, name, whether open, frames grabbed and dropped, and the assumed exposure latency (s)."""
        return {"kind": self.kind, "name": self.name, "open": self._thread is not None, "frames": self._seq,
                "dropped": self.dropped, "latency_s": self.latency_s}

    def close(self) -> None:
        """Stop the grabber and join it; the grabber releases the source as it leaves."""
        self._stop.set()
        th, source = self._thread, self._source
        if th is not None:
            if source is not None:  # unblock a read waiting on the network
                with contextlib.suppress(Exception):
                    source.interrupt()
            th.join(timeout=self.close_timeout_s)
            if th.is_alive():
                log.warning("camera %s: the grabber is still blocked in a read; it releases the source when "
                            "the read returns", self.name)
        self._thread = self._source = None


class _CvSource:
    """A ``cv2.VideoCapture`` as a :class:`CaptureSource` (no capture times of its own)."""

    def __init__(self, cap):
        self.cap = cap

    def read(self):
        if not self.cap.grab():
            raise CameraError("no frame from the capture device")
        ok, image = self.cap.retrieve()
        return (image if ok else None), None

    def interrupt(self) -> None:
        """Nothing to unblock: a capture device's read returns on its own (frame or timeout)."""

    def release(self) -> None:
        self.cap.release()

    def stall_reason(self) -> str | None:
        """OpenCV does not say why no frame came."""
        return None


class StreamClock:
    """Capture times for the frames of a stream that buffers them (RTSP through FFmpeg), on the wall clock (s).

    FFmpeg holds back what it read while probing the stream (about 2 s) and then hands it over at
    once: 22 frames 3 ms apart, each stamped at its arrival, compress 2 s of motion into 70 ms. A frame
    arriving less than ``burst_frac`` of a frame period after the one before is part of such a burst.
    Until the first frame arrives at its own pace (the opening probe burst) frames are dropped
    (:attr:`probe_dropped`). After that each frame is stamped by the stream's own time (its
    presentation time ``pts_s`` while those increase, else the frame count × ``period_s``) mapped onto
    the wall clock by the smallest ``arrival − stream time`` seen in the last ``window_s``: the frame that
    came with the least delay anchors the mapping, so frames of a later burst get the times they were
    captured at, never later than their arrival, always increasing. ``latency_s`` (the exposure-to-
    arrival delay of the least-delayed frames) is subtracted, as for arrival stamps."""

    def __init__(self, period_s: float, latency_s: float = 0.0, *, burst_frac: float = 0.25, window_s: float = 5.0):
        self.period_s, self.latency_s, self.window_s = period_s, latency_s, window_s
        self.burst_gap_s = burst_frac * period_s
        self.steady = False
        self.probe_dropped = 0
        self._last_arrival: float | None = None
        self._last_stream: float | None = None
        self._last_stamp = -float("inf")
        self._offsets: deque[tuple[float, float]] = deque()  # (arrival, arrival − stream time), last window_s

    def stamp(self, arrival: float, pts_s: float | None = None) -> float | None:
        """The capture time of a frame that arrived at ``arrival`` (wall clock, s) with presentation time
        ``pts_s`` (s, the stream's clock, or None); None for a frame of the opening probe burst (drop it)."""
        gap = None if self._last_arrival is None else arrival - self._last_arrival
        self._last_arrival = arrival
        last = self._last_stream
        if pts_s is not None and (last is None or pts_s > last):
            s = pts_s
        else:
            s = 0.0 if last is None else last + self.period_s
        self._last_stream = s
        if not self.steady:
            if gap is None or gap < self.burst_gap_s:
                self.probe_dropped += 1
                return None
            self.steady = True
        self._offsets.append((arrival, arrival - s))
        while self._offsets and self._offsets[0][0] < arrival - self.window_s:
            self._offsets.popleft()
        t = s + min(o for _, o in self._offsets)
        t = max(t, min(arrival, self._last_stamp + 1e-6))  # increasing, and never after its arrival
        self._last_stamp = t
        return t - self.latency_s


class _StreamSource(_CvSource):
    """A network stream through ``cv2.VideoCapture`` (FFmpeg), its frames stamped by :class:`StreamClock`."""

    def __init__(self, cap, period_s: float, latency_s: float, wall_clock: Callable[[], float] = time.time):
        super().__init__(cap)
        self.clock = StreamClock(period_s, latency_s)
        self.wall_clock = wall_clock

    def read(self):
        import cv2

        while True:
            if not self.cap.grab():
                raise CameraError("no frame from the stream")
            arrival = self.wall_clock()
            pts_ms = self.cap.get(cv2.CAP_PROP_POS_MSEC)
            t = self.clock.stamp(arrival, pts_ms / 1000.0 if pts_ms and pts_ms > 0 else None)
            if t is None:
                continue  # the opening probe burst: its arrival times say nothing of when it was captured
            ok, image = self.cap.retrieve()
            return (image if ok else None), t


class V4L2Camera(GrabberCamera):
    """A V4L2 camera through OpenCV with latest-frame semantics."""

    kind = "v4l2"

    def __init__(self, device, width: int = 640, height: int = 480, fps: float = 30.0,
                 exposure: float | None = None, timeout_s: float = 2.0, latency_s: float = 0.0,
                 clock: Callable[[], float] = time.monotonic, name: str = "", backlog: int = 16):
        super().__init__(timeout_s=timeout_s, latency_s=latency_s, clock=clock, name=name or str(device),
                         backlog=backlog)
        self.device = int(device) if isinstance(device, str) and device.isdigit() else device
        self.width, self.height, self.fps, self.exposure = width, height, fps, exposure
        self._size: tuple[int, int, float, str] | None = None

    @classmethod
    def from_config(cls, cfg, **kw) -> V4L2Camera:
        """The camera a driver file describes (``device``, size, fps, exposure; time-out and latency in s)."""
        return cls(cfg.device, cfg.width, cfg.height, cfg.fps, cfg.exposure,
                   **({"timeout_s": cfg.timeout_s, "latency_s": cfg.latency_s} | kw))

    def _meta(self) -> dict:
        return {"device": str(self.device)}

    def _open_source(self) -> CaptureSource:
        import cv2

        cap = cv2.VideoCapture(self.device, cv2.CAP_V4L2)
        if not cap.isOpened():
            raise CameraError(f"cannot open V4L2 camera {self.device!r}")
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        cap.set(cv2.CAP_PROP_FPS, self.fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # fewer stale buffers in the driver queue
        if self.exposure is not None:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2: 1 = manual
            cap.set(cv2.CAP_PROP_EXPOSURE, float(self.exposure))
        self._size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                      float(cap.get(cv2.CAP_PROP_FPS)), cap.getBackendName())
        return _CvSource(cap)

    def info(self) -> dict:
        """The base info plus the device path and, once open, the size, fps and backend it negotiated."""
        d = super().info() | {"device": str(self.device)}
        if self._size is not None and d["open"]:
            d.update(zip(("width", "height", "fps", "backend"), self._size))
        return d


class MjpegHttpSource:
    """An MJPEG-over-HTTP stream (``multipart/x-mixed-replace``) read with the standard library.

    The body is read through :class:`http.client.HTTPResponse`, which undoes ``Transfer-Encoding:
    chunked`` (ffmpeg's HTTP server always sends it). Each part's JPEG is decoded with
    ``cv2.imdecode``. ``use_header_time``: take a part's ``X-Timestamp`` header (seconds on the
    server's wall clock, as mjpg-streamer and ustreamer send it) as the capture time. A part
    without ``Content-Length`` runs to the next boundary. A response typed
    ``application/octet-stream`` (ffmpeg's ``-f mpjpeg`` without ``-content_type``) is read when
    its body opens with a boundary line; the boundary is then taken from that line. Parts that do
    not decode are counted (``undecodable``); the first is logged, and once none has decoded for
    ``timeout_s`` while parts keep coming, :meth:`read` raises with the likely cause.
    """

    _MAX_HEADERS = 16384  # bytes of part headers before the framing is taken as broken
    _MAX_PART = 64 << 20  # bytes of a part without Content-Length before the framing is taken as broken

    def __init__(self, url: str, timeout_s: float = 5.0, use_header_time: bool = True):
        import http.client
        from urllib.parse import urlsplit

        u = urlsplit(url)
        if u.scheme not in ("http", "https") or not u.hostname:
            raise CameraError(f"not an http(s) URL: {url!r}")
        conn_cls = http.client.HTTPSConnection if u.scheme == "https" else http.client.HTTPConnection
        self.url, self.use_header_time, self.timeout_s = url, use_header_time, timeout_s
        self.undecodable = 0  # parts that did not decode as an image
        self._bad_since: float | None = None  # monotonic time of the first undecodable part since the last good one
        self._bad_first: bytes = b""
        self._buf = bytearray()
        self._conn = conn_cls(u.hostname, u.port, timeout=timeout_s)
        try:
            self._conn.request("GET", (u.path or "/") + (f"?{u.query}" if u.query else ""))
            resp = self._conn.getresponse()
        except (OSError, http.client.HTTPException) as exc:
            self._conn.close()
            raise CameraError(f"cannot open the stream {url}: {exc}") from None
        self._resp = resp
        self._sock = self._conn.sock
        ctype = resp.getheader("Content-Type", "")
        if resp.status != 200:
            self._conn.close()
            raise CameraError(f"the stream {url} answered HTTP {resp.status} {resp.reason}")
        m = re.search(r'boundary="?([^";]+)"?', ctype)
        if "multipart" in ctype and m:
            b = m.group(1).strip()
            self._boundary = (b if b.startswith("--") else "--" + b).encode()
        elif ctype.split(";")[0].strip().lower() == "application/octet-stream":
            self._boundary = self._sniff_boundary(ctype)
        else:
            self._conn.close()
            raise CameraError(f"{url} is not an MJPEG stream (Content-Type {ctype or 'missing'!r})")

    def _sniff_boundary(self, ctype: str) -> bytes:
        # ffmpeg's mpjpeg muxer opens the body with "--<tag>\r\n" and then the first part's headers
        try:
            line = self._line(limit=256)
        except (OSError, CameraError) as exc:
            self._conn.close()
            raise CameraError(f"{self.url} is not an MJPEG stream (Content-Type {ctype!r}, and no body: {exc})"
                              ) from None
        if not (line.startswith(b"--") and len(line) > 2 and line[2:].strip()
                and all(32 < c < 127 for c in line)):
            self._conn.close()
            raise CameraError(f"{self.url} is not an MJPEG stream (Content-Type {ctype!r} and the body does not "
                              f"open with a multipart boundary: {bytes(line[:40])!r}); serve it as "
                              "multipart/x-mixed-replace (ffmpeg: -content_type 'multipart/x-mixed-replace;"
                              "boundary=ffmpeg')")
        self._buf[:0] = line + b"\r\n"  # read() finds it again as the first boundary
        return bytes(line)

    def _fill(self) -> None:
        data = self._resp.read1(65536)  # de-chunked body bytes
        if not data:
            raise CameraError(f"the stream {self.url} ended")
        self._buf += data

    def _line(self, limit: int = 65536) -> bytes:
        while (i := self._buf.find(b"\n")) < 0:
            if len(self._buf) > limit:
                raise CameraError(f"the stream {self.url} sent a line longer than {limit} bytes: not MJPEG framing")
            self._fill()
        line = bytes(self._buf[:i]).rstrip(b"\r")
        del self._buf[:i + 1]
        return line

    def _take(self, n: int) -> bytes:
        while len(self._buf) < n:
            try:
                self._fill()
            except CameraError:
                raise CameraError(f"the stream {self.url} ended inside a frame") from None
        data = bytes(self._buf[:n])
        del self._buf[:n]
        return data

    def _until_boundary(self) -> bytes:
        # a part without Content-Length: everything up to the CRLF before the next boundary line
        mark = b"\r\n" + self._boundary
        start = 0
        while (i := self._buf.find(mark, start)) < 0:
            if len(self._buf) > self._MAX_PART:
                raise CameraError(f"the stream {self.url}: no boundary within {self._MAX_PART} bytes")
            start = max(0, len(self._buf) - len(mark) + 1)
            self._fill()
        data = bytes(self._buf[:i])
        del self._buf[:i + 2]  # the boundary line stays for the next read
        return data

    def read(self) -> tuple[np.ndarray | None, float | None]:
        """The next JPEG part of the stream, decoded (BGR), with the capture time its headers carry (s), else None."""
        import cv2

        while self._line().strip() != self._boundary:  # skip to the next part
            pass
        headers = {}
        size = 0
        while (line := self._line()):
            size += len(line)
            if size > self._MAX_HEADERS:
                raise CameraError(f"the stream {self.url}: part headers longer than {self._MAX_HEADERS} bytes")
            k, _, v = line.decode("latin-1").partition(":")
            headers[k.strip().lower()] = v.strip()
        n = headers.get("content-length", "")
        data = self._take(int(n)) if n.isdigit() else self._until_boundary()
        t_wall = None
        if self.use_header_time and "x-timestamp" in headers:
            with contextlib.suppress(ValueError):
                t_wall = float(headers["x-timestamp"])
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data else None
        if image is None:
            self._undecodable(data)
        else:
            self._bad_since = None
        return image, t_wall

    def _undecodable(self, data: bytes) -> None:
        self.undecodable += 1
        now = time.monotonic()
        if self._bad_since is None:
            self._bad_since, self._bad_first = now, data[:8]
        if self.undecodable == 1:
            log.warning("stream %s: a part of %d bytes does not decode as a JPEG (starts %r); such parts are "
                        "skipped and counted", self.url, len(data), data[:8])
        if now - self._bad_since >= self.timeout_s:
            raise CameraError(self.stall_reason())

    def stall_reason(self) -> str | None:
        """Why no frame came lately, when parts arrived that did not decode (None if the last part decoded)."""
        if self._bad_since is None:
            return None
        cause = ("the parts are not JPEGs (no SOI marker FF D8 at the start)" if not self._bad_first.startswith(
            b"\xff\xd8") else "the JPEGs are truncated or corrupt (a proxy re-framing the body, or a wrong "
            "Content-Length)")
        return (f"no part of the stream {self.url} decoded as a JPEG for {time.monotonic() - self._bad_since:.1f} s "
                f"({self.undecodable} undecodable parts; the first starts {self._bad_first!r}): {cause}")

    def interrupt(self) -> None:
        """Unblock a read from another thread (the grabber then leaves and releases the source)."""
        import socket

        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.shutdown(socket.SHUT_RDWR)

    def release(self) -> None:
        """Close the HTTP response and its connection."""
        with contextlib.suppress(Exception):
            self._resp.close()
        self._conn.close()


class StreamCamera(GrabberCamera):
    """A network camera (``kind: stream``): MJPEG over HTTP, or any URL OpenCV's FFmpeg opens (RTSP).

    ``backend``: ``auto`` reads http(s) URLs with :class:`MjpegHttpSource` and anything else with
    ``cv2.VideoCapture(url, cv2.CAP_FFMPEG)``; ``http`` or ``opencv`` force one. ``timestamps``:
    ``header`` takes the capture time from the parts' ``X-Timestamp`` (server wall clock; hosts
    kept in step by NTP), ``arrival`` stamps arrival minus ``latency_s``.
    """

    kind = "stream"

    def __init__(self, url: str, *, backend: str = "auto", timestamps: str = "arrival", timeout_s: float = 2.0,
                 latency_s: float = 0.0, clock: Callable[[], float] = time.monotonic, name: str = "",
                 backlog: int = 16, fps: float = 30.0):
        super().__init__(timeout_s=timeout_s, latency_s=latency_s, clock=clock, name=name or url, backlog=backlog)
        self.fps = fps  # the frame period of a stream that does not say its own rate
        if backend not in ("auto", "http", "opencv"):
            raise CameraError(f"unknown stream backend {backend!r} (auto, http or opencv)")
        if timestamps not in ("arrival", "header"):
            raise CameraError(f"unknown timestamps {timestamps!r} (arrival or header)")
        self.url, self.backend, self.timestamps = url, backend, timestamps
        self._backend_used: str | None = None

    @classmethod
    def from_config(cls, cfg, **kw) -> StreamCamera:
        """The camera a driver file describes (``url``, backend, whether the stream carries timestamps, time-out and
        latency in s)."""
        return cls(cfg.url, **({"backend": cfg.backend, "timestamps": cfg.timestamps, "timeout_s": cfg.timeout_s,
                                "latency_s": cfg.latency_s, "fps": cfg.fps} | kw))

    def _meta(self) -> dict:
        return {"url": self.url}

    def _open_source(self) -> CaptureSource:
        http = self.url.lower().startswith(("http://", "https://"))
        if self.backend == "http" or (self.backend == "auto" and http):
            self._backend_used = "http"
            return MjpegHttpSource(self.url, timeout_s=max(self.timeout_s, 1.0),
                                   use_header_time=self.timestamps == "header")
        import cv2

        # FFmpeg's own read time-out: a read on a stream that ended returns within the camera's timeout_s
        ms = int(max(self.timeout_s, 0.5) * 1000)
        cap = cv2.VideoCapture(self.url, cv2.CAP_FFMPEG,
                               [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, max(ms, 5000), cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms])
        if not cap.isOpened():
            raise CameraError(f"OpenCV (FFmpeg) cannot open the stream {self.url}")
        self._backend_used = f"opencv-{cap.getBackendName()}"
        # a blocked read cannot be interrupted, and the grabber releases the capture itself when it returns:
        # close() need not wait for it longer than a few frame periods
        self.close_timeout_s = min(self.close_timeout_s, STREAM_CLOSE_WAIT_S)
        fps = cap.get(cv2.CAP_PROP_FPS)
        period = 1.0 / (fps if 1.0 <= fps <= 240.0 else self.fps)  # FFmpeg says 90000 for some RTP streams
        return _StreamSource(cap, period, self.latency_s, wall_clock=self.wall_clock)

    def info(self) -> dict:
        """The base info plus the URL, the backend in use, whether frames carry timestamps and, once a frame came, its
        size."""
        d = super().info() | {"url": self.url, "backend": self._backend_used or self.backend,
                              "timestamps": self.timestamps}
        if self._latest is not None:
            h, w = self._latest.image.shape[:2]
            d.update(width=w, height=h)
        return d


def list_stamped_frames(folder: str | Path) -> list[tuple[float, Path]]:
    """(t, path) of the frames in a replay folder, by time: ``index.csv`` if present, else the names."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CameraError(f"replay folder not found: {folder}")
    index = folder / "index.csv"
    frames: list[tuple[float, Path]] = []
    if index.exists():
        with index.open(newline="") as fh:
            for row in csv.reader(fh):
                if not row or row[0].strip().lower() in ("t", "time", "t_s"):
                    continue
                try:
                    frames.append((float(row[0]), folder / row[1].strip()))
                except (ValueError, IndexError):
                    raise CameraError(f"{index}: bad row {row!r} (expected t,file)") from None
    else:
        for p in folder.iterdir():
            m = _STAMP.match(p.name)
            if m:
                frames.append((float(m.group(1)), p))
    frames.sort(key=lambda f: f[0])
    if not frames:
        raise CameraError(f"no stamped frames in {folder} (expected <t_seconds>.png or index.csv)")
    return frames


class ReplayCamera(OpenClose):
    """Frames from a folder, each stamped with its recorded capture time (s)."""

    def __init__(self, folder: str | Path, clock: Callable[[], float] | None = None, loop: bool = False,
                 name: str = ""):
        self.folder = Path(folder)
        self.clock = clock
        self.loop = loop
        self.name = name or self.folder.name
        self._frames: list[tuple[float, Path]] = []
        self._next = 0
        self._delivered_i: int | None = None  # with a clock: the index of the last frame delivered

    @classmethod
    def from_config(cls, cfg, root: Path | None = None, **kw) -> ReplayCamera:
        """The camera a driver file describes: ``folder`` of stamped frames, relative to ``root`` (the lab) unless
        absolute."""
        folder = Path(cfg.folder)
        if root is not None and not folder.is_absolute():
            folder = root / folder
        return cls(folder, **kw)

    def open(self) -> None:
        """List the folder's stamped frames, in time order, and start at the first."""
        self._frames = list_stamped_frames(self.folder)
        self._next = 0
        self._delivered_i = None

    def close(self) -> None:
        """Forget the frame list."""
        self._frames = []

    def _load(self, i: int) -> Frame:
        import cv2

        t, path = self._frames[i]
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise CameraError(f"cannot read frame {path}")
        return Frame(image=image, t=t, seq=i + 1, meta={"file": path.name})

    def grab(self) -> Frame:
        """Next frame in order; with a clock, the newest frame stamped at or before the clock's now."""
        if not self._frames:
            raise CameraError(f"replay camera {self.name} is not open")
        if self.clock is not None:
            now = self.clock()
            times = [t for t, _ in self._frames]
            i = int(np.searchsorted(times, now, side="right")) - 1
            if i < 0:
                raise CameraError(f"replay camera {self.name}: no frame before t={now:.3f}")
            self._delivered_i = i
            return self._load(i)
        if self._next >= len(self._frames):
            if not self.loop:
                raise CameraError(f"replay camera {self.name}: end of recording ({len(self._frames)} frames)")
            self._next = 0
        frame = self._load(self._next)
        self._next += 1
        return frame

    def grab_recent(self, max_frames: int) -> list[Frame]:
        """Without a clock, the next frame in order; with one, the frames stamped after the last one delivered
        and at or before the clock's now (the newest ``max_frames``), else the newest one."""
        if self.clock is None or not self._frames:
            return [self.grab()]
        last = self._delivered_i
        newest = self.grab()
        first = newest.seq - 1 if last is None else max(last + 1, newest.seq - max(1, int(max_frames)))
        return [self._load(i) for i in range(first, newest.seq - 1)] + [newest]

    def info(self) -> dict:
        """Kind, folder, frame count and the first and last frame times (s)."""
        d = {"kind": "replay", "folder": str(self.folder), "frames": len(self._frames)}
        if self._frames:
            d.update(t_first=self._frames[0][0], t_last=self._frames[-1][0])
        return d


def save_stamped_frame(folder: str | Path, frame: Frame) -> Path:
    """Write a frame as ``<t>.png`` for :class:`ReplayCamera` (microsecond stamp in the name)."""
    import cv2

    from ..fsutil import atomic_write_bytes

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", frame.image)
    if not ok:
        raise CameraError("cannot encode frame as PNG")
    path = folder / f"{frame.t:.6f}.png"
    atomic_write_bytes(path, buf.tobytes())
    return path


def open_camera(role: str, lab: Lab, **kw):
    """The (unopened) camera for ``role`` (fixed_camera/mobile_camera, or fixed/mobile) of ``lab``."""
    role = role if role.endswith("_camera") else f"{role}_camera"
    if role not in ("fixed_camera", "mobile_camera"):
        raise CameraError(f"the lab has no {role}")
    cfg = lab.fixed_camera if role == "fixed_camera" else lab.mobile_camera
    if cfg.kind == "v4l2":
        return V4L2Camera.from_config(cfg, name=role, **kw)
    if cfg.kind == "stream":
        return StreamCamera.from_config(cfg, name=role, **kw)
    if cfg.kind == "replay":
        return ReplayCamera.from_config(cfg, root=lab.root, name=role, **kw)
    if cfg.kind == "sim":
        raise CameraError(f"{role} is simulated: the simulated lab serves it (labctl.runtime.devices.open_device)")
    raise CameraError(f"{role}: unknown camera kind {cfg.kind!r}")


if TYPE_CHECKING:  # mypy (.ci/run) fails here when a camera drifts from the Camera protocol
    _grabber_protocol: type[Camera] = GrabberCamera
    _replay_protocol: type[Camera] = ReplayCamera
