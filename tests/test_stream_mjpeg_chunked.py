"""The stream camera's own MJPEG reader against chunked bodies: a stdlib server sending
``Transfer-Encoding: chunked`` with odd chunk boundaries (parts with and without Content-Length,
multipart or ``application/octet-stream``), bodies that are not MJPEG, and the real ffmpeg's
``-f mpjpeg`` HTTP listener opened through a lab's ``kind: stream`` driver file."""

from __future__ import annotations

import itertools
import logging
import socket
import subprocess
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest
import yaml

from labctl.drivers.cameras import CameraError, StreamCamera
from labctl.drivers.serial_link import DeviceTimeout

BOUNDARY = "ffmpeg"


def _jpeg(value: int) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".jpg", np.full((48, 64, 3), value, np.uint8))
    return buf.tobytes()


def _part(value: int, ts: float, with_length: bool) -> bytes:
    jpeg = _jpeg(value)
    head = "Content-Type: image/jpeg\r\n" + (f"Content-Length: {len(jpeg)}\r\n" if with_length else "")
    return (head + f"X-Timestamp: {ts:.6f}\r\n\r\n").encode() + jpeg + f"\r\n--{BOUNDARY}\r\n".encode()


class _Chunked(BaseHTTPRequestHandler):
    """Sends ``parts`` (a list of body byte strings, one per frame) in chunks of ``sizes`` (cycled), so
    chunk boundaries fall inside JPEGs, headers and boundary lines; ``ctype`` is the response's type."""

    protocol_version = "HTTP/1.1"
    parts: list = []
    ctype = f"multipart/x-mixed-replace;boundary={BOUNDARY}"
    sizes = (1, 7, 13, 250, 3, 1021, 2, 64)
    opening = f"--{BOUNDARY}\r\n".encode()

    def log_message(self, *a):
        pass

    def _chunk(self, data: bytes) -> None:
        self.wfile.write(f"{len(data):x}\r\n".encode() + data + b"\r\n")

    def do_GET(self):  # noqa: N802
        self.send_response(200)
        self.send_header("Content-Type", self.ctype)
        self.send_header("Transfer-Encoding", "chunked")
        self.end_headers()
        sizes = itertools.cycle(self.sizes)
        try:
            body = self.opening
            for part in self.parts:
                body += part
                while body:
                    n = next(sizes)
                    self._chunk(body[:n])
                    body = body[n:]
                self.wfile.flush()
                time.sleep(0.03)
            time.sleep(0.5)
            self.wfile.write(b"0\r\n\r\n")
        except OSError:
            pass


def _serve(handler):
    srv = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    return srv


def _wait_until(cond, timeout_s=5.0):
    t_end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < t_end, "timed out"
        time.sleep(0.01)


@pytest.mark.parametrize("ctype", [f"multipart/x-mixed-replace;boundary={BOUNDARY}", "application/octet-stream"])
def test_chunked_parts_with_and_without_length_come_whole_with_their_timestamps(ctype):
    wall0 = time.time()
    n = 8
    stamps = [wall0 - 0.3 + 0.03 * k for k in range(1, n + 1)]
    handler = type("H", (_Chunked,), {"ctype": ctype,
                                      "parts": [_part(25 * k, stamps[k - 1], k % 2 == 0) for k in range(1, n + 1)]})
    srv = _serve(handler)
    try:
        with StreamCamera(f"http://127.0.0.1:{srv.server_address[1]}/", timestamps="header", backlog=16) as cam:
            _wait_until(lambda: cam.frames == n)
            frames = cam.grab_recent(16)
            bad = cam._source.undecodable
    finally:
        srv.shutdown()
        srv.server_close()
    assert bad == 0
    assert [f.seq for f in frames] == list(range(1, n + 1))
    values = [int(f.image[10, 10].mean()) for f in frames]
    assert all(abs(v - 25 * f.seq) <= 3 for v, f in zip(values, frames)), values  # each part's own JPEG
    assert all(f.image.shape == (48, 64, 3) for f in frames)
    gaps = np.diff([f.t for f in frames])  # X-Timestamp mapped onto the caller's clock
    assert np.allclose(gaps, 0.03, atol=2e-3), gaps


def test_an_octet_stream_that_is_not_multipart_is_refused_in_one_clear_line():
    handler = type("H", (_Chunked,), {"ctype": "application/octet-stream", "opening": b"\x00\x01binary junk\r\n",
                                      "parts": [b"x" * 100]})
    srv = _serve(handler)
    try:
        with pytest.raises(CameraError, match="does not open with a multipart boundary") as err:
            StreamCamera(f"http://127.0.0.1:{srv.server_address[1]}/").open()
    finally:
        srv.shutdown()
        srv.server_close()
    assert "\n" not in str(err.value) and "-content_type" in str(err.value)


def test_parts_that_never_decode_are_warned_once_and_named_in_the_timeout(caplog):
    junk = [b"Content-Type: image/jpeg\r\n\r\n" + bytes(range(256)) * 4 + f"\r\n--{BOUNDARY}\r\n".encode()] * 40
    handler = type("H", (_Chunked,), {"parts": junk})
    srv = _serve(handler)
    try:
        with caplog.at_level(logging.WARNING, logger="labctl.drivers.cameras"):
            with StreamCamera(f"http://127.0.0.1:{srv.server_address[1]}/", timeout_s=0.5) as cam:
                with pytest.raises((DeviceTimeout, CameraError), match="decoded as a JPEG") as err:
                    cam.grab()
                assert cam._source.undecodable >= 3
    finally:
        srv.shutdown()
        srv.server_close()
    assert "no SOI marker" in str(err.value)
    warnings = [r for r in caplog.records if "does not decode" in r.getMessage()]
    assert len(warnings) == 1


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def ffmpeg_bin():
    from fakes import debian_tool

    return debian_tool("ffmpeg")


def test_the_real_ffmpeg_mpjpeg_stream_opens_through_a_stream_driver_file(tmp_path, ffmpeg_bin):
    from labctl.config import load_lab
    from labctl.drivers.cameras import open_camera
    from labctl.workspace import init_workspace

    port = _free_port()
    url = f"http://127.0.0.1:{port}/"
    # ffmpeg's own HTTP server: Transfer-Encoding chunked, Content-Type application/octet-stream, no X-Timestamp
    proc = subprocess.Popen([ffmpeg_bin, "-hide_banner", "-loglevel", "error", "-re", "-f", "lavfi",
                             "-i", "testsrc=size=320x240:rate=10", "-t", "30", "-c:v", "mjpeg", "-q:v", "5",
                             "-f", "mpjpeg", "-listen", "1", url],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        root = init_workspace(tmp_path / "lab")
        f = root / "drivers" / "fixed_camera.yaml"
        f.write_text(yaml.safe_dump({**yaml.safe_load(f.read_text()), "kind": "stream", "url": url,
                                     "width": 320, "height": 240, "fps": 10.0, "timeout_s": 5.0}))
        cam = open_camera("fixed", load_lab(root))
        t_open = time.monotonic()
        while True:
            try:
                cam.open()
                break
            except CameraError as exc:  # ffmpeg not listening yet (one connection only: no separate probe)
                if "cannot open" not in str(exc):
                    raise
                assert proc.poll() is None, proc.stderr.read().decode(errors="replace")
                assert time.monotonic() - t_open < 20, "cannot open ffmpeg's stream"
                time.sleep(0.1)
        with cam:
            frames = [cam.grab() for _ in range(8)]
            info = cam.info()
            bad = cam._source.undecodable if cam._source is not None else None
    finally:
        proc.kill()
        proc.wait(timeout=10)
    assert info["backend"] == "http" and bad == 0
    assert all(fr.image.shape == (240, 320, 3) for fr in frames)
    for a, b in zip(frames, frames[1:]):  # testsrc's moving pattern and frame counter: every frame differs
        assert np.abs(a.image.astype(int) - b.image.astype(int)).mean() > 1.0
    ts = np.array([fr.t for fr in frames])
    gaps = np.diff(ts)
    assert np.all(gaps > 0)
    assert np.median(gaps) == pytest.approx(0.1, abs=0.03), gaps  # 10 fps, stamped on arrival
