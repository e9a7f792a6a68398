"""The shared latest-frame grabber (V4L2 and stream cameras) with a fake capture source, and the
MJPEG-over-HTTP path against independent ends: a server speaking mjpg-streamer's wire format
(written here from its documented output, not from labctl's server) and OpenCV's FFmpeg client
reading labctl's server."""

from __future__ import annotations

import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from labctl.drivers.cameras import CameraError, GrabberCamera, StreamCamera
from labctl.drivers.serial_link import DeviceTimeout


class FakeSource:
    """A capture source the test feeds frame by frame; records whether release ever raced a read."""

    def __init__(self, interruptible: bool = True):
        self.cond = threading.Condition()
        self.queue: list = []
        self.ended = False
        self.in_read = False
        self.released = False
        self.released_during_read = False
        self.interrupted = False
        if not interruptible:
            self.interrupt = None

    def push(self, value: int, t_wall: float | None = None) -> None:
        with self.cond:
            self.queue.append((np.full((4, 6, 3), value, np.uint8), t_wall))
            self.cond.notify_all()

    def end(self) -> None:
        with self.cond:
            self.ended = True
            self.cond.notify_all()

    def read(self):
        with self.cond:
            self.in_read = True
            try:
                self.cond.wait_for(lambda: self.queue or self.ended or self.interrupted)
                if self.queue:
                    return self.queue.pop(0)
                raise OSError("source ended")
            finally:
                self.in_read = False

    def interrupt(self) -> None:
        with self.cond:
            self.interrupted = True
            self.cond.notify_all()

    def stall_reason(self) -> str | None:
        return None

    def release(self) -> None:
        self.released_during_read = self.in_read
        self.released = True


class FakeCamera(GrabberCamera):
    def __init__(self, source, **kw):
        super().__init__(name="fake", **kw)
        self.source = source

    def _open_source(self):
        return self.source


def wait_until(cond, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.002)


def test_grab_never_returns_a_frame_captured_before_the_call():
    src = FakeSource()
    with FakeCamera(src, timeout_s=2.0) as cam:
        src.push(1)
        wait_until(lambda: cam.frames == 1)
        threading.Timer(0.05, src.push, args=(2,)).start()
        f = cam.grab()  # frame 1 is stale: wait for frame 2
        assert f.image[0, 0, 0] == 2 and f.seq == 2
        assert cam.grab(wait_new=False).seq == 2  # the newest, even though already delivered


def test_dropped_counts_frames_overwritten_unread():
    src = FakeSource()
    with FakeCamera(src) as cam:
        for k in range(3):  # grabbed one by one: nothing dropped (the old counter said frames − 1)
            threading.Timer(0.02, src.push, args=(k,)).start()
            cam.grab()
        assert cam.dropped == 0
        for k in range(5):  # five arrive, nobody grabs until the last: four overwritten unread
            src.push(10 + k)
        wait_until(lambda: cam.frames == 8)
        assert cam.grab(wait_new=False).image[0, 0, 0] == 14
        assert cam.dropped == 4 and cam.info()["dropped"] == 4


def test_grab_recent_hands_a_busy_caller_the_frames_it_missed_in_order():
    src = FakeSource()
    with FakeCamera(src, backlog=4) as cam:
        src.push(1)
        assert [f.seq for f in cam.grab_recent(8)] == [1]
        for k in range(2, 5):  # the caller is busy (a robot command's round trip) while three arrive
            src.push(k)
        wait_until(lambda: cam.frames == 4)
        assert [int(f.image[0, 0, 0]) for f in cam.grab_recent(8)] == [2, 3, 4]  # oldest first, none lost
        assert cam.dropped == 0
        for k in range(5, 12):  # seven while busy: the newest max_frames of them, and at most the backlog
            src.push(k)
        wait_until(lambda: cam.frames == 11)
        assert [f.seq for f in cam.grab_recent(2)] == [10, 11] and cam.dropped == 5
        threading.Timer(0.05, src.push, args=(12,)).start()
        assert [f.seq for f in cam.grab_recent(8)] == [12]  # all delivered: waits for a new one
        for k in range(13, 20):
            src.push(k)
        wait_until(lambda: cam.frames == 19)
        assert [f.seq for f in cam.grab_recent(8)] == [16, 17, 18, 19] and cam.dropped == 8  # backlog 4
        threading.Timer(0.05, src.push, args=(20,)).start()
        assert cam.grab().seq == 20  # grab() delivers too: grab_recent() then waits for frame 21
        threading.Timer(0.05, src.push, args=(21,)).start()
        assert [f.seq for f in cam.grab_recent(8)] == [21]


def test_a_stalled_source_times_out_and_an_ended_one_is_a_camera_error():
    src = FakeSource()
    with FakeCamera(src, timeout_s=0.1) as cam:
        with pytest.raises(DeviceTimeout):
            cam.grab()
        src.push(7)
        assert cam.grab(wait_new=False).image[0, 0, 0] == 7  # recovers when frames come again
        src.end()
        with pytest.raises(CameraError, match="stopped delivering"):
            cam.grab()


def test_close_joins_the_grabber_before_the_source_is_released():
    src = FakeSource()
    cam = FakeCamera(src)
    cam.open()
    wait_until(lambda: src.in_read)
    cam.close()  # the grabber is blocked in read: interrupt, join, then the grabber releases
    assert src.released and not src.released_during_read
    with pytest.raises(CameraError):
        cam.grab()


def test_a_read_blocked_past_the_join_is_not_released_under_it():
    src = FakeSource(interruptible=False)
    cam = FakeCamera(src)
    cam.close_timeout_s = 0.1
    cam.open()
    wait_until(lambda: src.in_read)
    cam.close()  # the read cannot be interrupted: close returns, the source is not released under it
    assert not src.released
    src.push(1)  # the read returns: now the grabber releases, outside the read
    wait_until(lambda: src.released)
    assert not src.released_during_read


def test_timestamps_from_the_source_clock_or_arrival_minus_latency():
    now = {"t": 100.0, "wall": 5000.0}
    src = FakeSource()
    with FakeCamera(src, latency_s=0.04, clock=lambda: now["t"], wall_clock=lambda: now["wall"]) as cam:
        src.push(1)  # no capture time of its own: arrival − latency
        assert cam.grab(wait_new=False).t == pytest.approx(99.96)
        src.push(2, t_wall=4999.9)  # exposed 0.1 s ago on the wall clock: 99.9 on ours
        wait_until(lambda: cam.frames == 2)
        assert cam.grab(wait_new=False).t == pytest.approx(99.9)


# --- MJPEG over HTTP -----------------------------------------------------------------------------

MJPG_STREAMER_BOUNDARY = "boundarydonotcross"  # mjpg-streamer's output_http (httpd.c) wire format


def _jpeg(value: int) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".jpg", np.full((48, 64, 3), value, np.uint8))
    return buf.tobytes()


class _MjpgStreamerLike(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.0"
    frames: list = []

    def log_message(self, *a):
        pass

    def do_GET(self):  # noqa: N802
        self.send_response(200)
        self.send_header("Access-Control-Allow-Origin", "*")
        self.send_header("Content-Type", f"multipart/x-mixed-replace;boundary={MJPG_STREAMER_BOUNDARY}")
        self.end_headers()
        self.wfile.write(f"--{MJPG_STREAMER_BOUNDARY}\r\n".encode())
        try:
            for value, ts in self.frames:
                jpeg = _jpeg(value)
                sec, usec = int(ts), int(round((ts - int(ts)) * 1e6))
                self.wfile.write(f"Content-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n"
                                 f"X-Timestamp: {sec}.{usec:06d}\r\n\r\n".encode() + jpeg)
                self.wfile.write(f"\r\n--{MJPG_STREAMER_BOUNDARY}\r\n".encode())
                self.wfile.flush()
                time.sleep(0.03)
            time.sleep(0.5)
        except OSError:
            pass


def test_stream_camera_reads_mjpg_streamer_wire_format_with_its_timestamps():
    wall0 = time.time()
    _MjpgStreamerLike.frames = [(40 * k, wall0 - 0.25 + 0.03 * k) for k in range(1, 6)]
    srv = ThreadingHTTPServer(("127.0.0.1", 0), _MjpgStreamerLike)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        cam = StreamCamera(f"http://127.0.0.1:{srv.server_address[1]}/?action=stream", timestamps="header")
        with cam:
            frames = [cam.grab() for _ in range(3)]
            wait_until(lambda: cam.frames == 5)
            last = cam.grab(wait_new=False)
    finally:
        srv.shutdown()
        srv.server_close()
    values = [int(f.image[10, 10].mean()) for f in frames + [last]]
    assert all(abs(v - 40 * (f.seq)) <= 3 for v, f in zip(values, frames + [last]))  # JPEG: within 3 grey levels
    # X-Timestamp (wall clock) mapped onto time.monotonic: the frames' spacing and age survive
    assert last.t - frames[0].t == pytest.approx(0.03 * (last.seq - frames[0].seq), abs=2e-3)
    assert time.monotonic() - last.t > 0.1  # stamped when exposed (0.13 s before the wall0 stamp), not on arrival


def test_stream_camera_refuses_what_is_not_an_mjpeg_stream():
    class Plain(BaseHTTPRequestHandler):
        def log_message(self, *a):
            pass

        def do_GET(self):  # noqa: N802
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.end_headers()
            self.wfile.write(b"<html></html>")

    srv = ThreadingHTTPServer(("127.0.0.1", 0), Plain)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        with pytest.raises(CameraError, match="not an MJPEG stream"):
            StreamCamera(f"http://127.0.0.1:{srv.server_address[1]}/").open()
    finally:
        srv.shutdown()
        srv.server_close()
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(CameraError, match="cannot open"):
        StreamCamera(f"http://127.0.0.1:{port}/x.mjpg").open()


class _CountingCamera:
    """A camera whose frame k is grey level 20·k, exposed at t = k/50 s on a monotonic clock."""

    def __init__(self):
        self.k = 0
        self.t0 = time.monotonic()

    def grab(self):
        from labctl.drivers.interfaces import Frame

        self.k += 1
        t = self.t0 + self.k / 50.0
        time.sleep(max(0.0, t - time.monotonic()))
        return Frame(image=np.full((48, 64, 3), (20 * self.k) % 250, np.uint8), t=t, seq=self.k)


def test_labctl_mjpeg_server_is_read_by_opencv_ffmpeg_and_by_the_stream_camera():
    import cv2

    from labctl.sim.mjpeg import MjpegServer

    with MjpegServer({"cam": _CountingCamera()}, clock=time.monotonic) as server:
        cap = cv2.VideoCapture(server.url("cam"), cv2.CAP_FFMPEG)  # an independent MJPEG client
        try:
            assert cap.isOpened()
            ok, img = cap.read()
            assert ok and img.shape == (48, 64, 3)
        finally:
            cap.release()
        with StreamCamera(server.url("cam"), backend="opencv") as cam:  # the stream kind's OpenCV path
            assert cam.grab().image.shape == (48, 64, 3) and cam.info()["backend"].startswith("opencv")
        with StreamCamera(server.url("cam"), timestamps="header") as cam:
            a, b = cam.grab(), cam.grab()
            assert b.seq > a.seq and 0 < b.t - a.t < 0.5
            assert abs(time.monotonic() - b.t) < 0.5  # X-Timestamp: the exposure on the caller's clock


_MJPG_SERVER_PROCESS = r"""
import sys, time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
import cv2, numpy as np

class Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.0"
    def log_message(self, *a):
        pass
    def do_GET(self):  # mjpg-streamer's output_http wire format, one frame every 1/30 s, grey level 10·k
        self.send_response(200)
        self.send_header("Content-Type", "multipart/x-mixed-replace;boundary=boundarydonotcross")
        self.end_headers()
        self.wfile.write(b"--boundarydonotcross\r\n")
        t0 = time.time()
        try:
            for k in range(1, 25):
                time.sleep(max(0.0, t0 + k / 30.0 - time.time()))
                ts = time.time()
                jpeg = cv2.imencode(".jpg", np.full((48, 64, 3), 10 * k, np.uint8))[1].tobytes()
                self.wfile.write(f"Content-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n"
                                 f"X-Timestamp: {int(ts)}.{int((ts % 1) * 1e6):06d}\r\n\r\n".encode() + jpeg
                                 + b"\r\n--boundarydonotcross\r\n")
                self.wfile.flush()
            time.sleep(5)
        except OSError:
            pass

srv = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
print(srv.server_address[1], flush=True)
srv.serve_forever()
"""


def test_stream_camera_catches_up_on_the_frames_a_busy_caller_missed_from_a_server_process():
    """The predictor's loop blocks ~0.15-0.2 s on each robot command at 9600 bps: the frames the camera
    delivered meanwhile come back from grab_recent() in order, none lost (a server in another process)."""
    import subprocess
    import sys

    server = subprocess.Popen([sys.executable, "-c", _MJPG_SERVER_PROCESS], stdout=subprocess.PIPE, text=True)
    try:
        port = int(server.stdout.readline())
        with StreamCamera(f"http://127.0.0.1:{port}/?action=stream", timestamps="header", backlog=16) as cam:
            first = cam.grab_recent(16)[-1]
            time.sleep(0.25)  # busy: ~7 frames arrive meanwhile
            wait_until(lambda: cam.frames >= first.seq + 4)
            missed = cam.grab_recent(16)
    finally:
        server.kill()
        server.wait(timeout=10)
    seqs = [f.seq for f in missed]
    assert len(missed) >= 4 and seqs == list(range(first.seq + 1, first.seq + 1 + len(missed)))
    values = [int(f.image[10, 10].mean()) for f in missed]
    assert all(abs(v - 10 * s) <= 3 for v, s in zip(values, seqs))  # the server's own frame numbers, in order
    assert cam.dropped == 0
    gaps = np.diff([f.t for f in missed])  # each stamped when the server made it, not when it was grabbed
    assert np.all(gaps > 0) and np.median(gaps) == pytest.approx(1 / 30, abs=0.01)
