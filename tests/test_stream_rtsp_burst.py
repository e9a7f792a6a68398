"""RTSP through OpenCV's FFmpeg: the probe burst dropped, frames stamped by the stream's own time, close bounded.

FFmpeg reads about 2 s of an RTSP stream while it probes it and hands that over at once (measured
against GStreamer's RTSP server: 60 frames 0.1 ms apart, after a 4 s open). Stamped at arrival, those
frames squeeze 2 s of motion into a few milliseconds, and ``grab_recent`` hands back compressed times.
:class:`StreamClock` is checked on an RTSP-like burst source (times given), and the camera end to end
against GStreamer's real RTSP server (``gir1.2-gst-rtsp-server-1.0``, run by the system python; skipped
with the reason if it is missing and cannot be installed).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from labctl.drivers.cameras import StreamCamera, StreamClock

P = 1 / 30  # frame period, s


def _rtsp_like(n_probe=22, probe_gap=0.003, n_steady=40, stall_at=20, stall_s=0.7, t_open=2.0):
    """(arrival, pts, true capture time) of an RTSP-like source: the probe's frames captured over ``n_probe``
    periods then delivered ``probe_gap`` apart, steady frames at their pace, and one stall mid-way whose
    frames then come in a burst too."""
    out = []
    t = t_open
    for k in range(n_probe):  # captured 0..n_probe-1 periods after the start, delivered at t_open
        out.append((t + k * probe_gap, k * P, k * P + (t_open - n_probe * P)))
    base = out[-1][0]
    k0 = n_probe
    lag = base - out[-1][2]  # the delay of the last probe frame: from then on frames come at this delay
    for i in range(n_steady):
        k = k0 + i
        captured = (k - k0 + 1) * P + base - lag
        arrival = captured + lag
        if i >= stall_at:
            held_until = base + (stall_at + 1) * P + stall_s
            arrival = max(arrival, held_until + (i - stall_at) * probe_gap)
        out.append((arrival, k * P, captured))
    return out


@pytest.mark.parametrize("with_pts", [True, False])
def test_the_probe_burst_is_dropped_and_a_later_burst_keeps_its_capture_times(with_pts):
    clock = StreamClock(P)
    frames = _rtsp_like()
    stamps = [(clock.stamp(a, pts if with_pts else None), a, true) for a, pts, true in frames]
    kept = [(t, a, true) for t, a, true in stamps if t is not None]
    assert clock.probe_dropped == 22 and len(kept) == 40  # every probe frame, none after
    ts = np.array([t for t, _, _ in kept])
    true = np.array([c for _, _, c in kept])
    arrival = np.array([a for _, a, _ in kept])
    assert np.all(np.diff(ts) > 0) and np.all(ts <= arrival + 1e-9)
    gaps = np.diff(ts)
    assert np.allclose(gaps, P, atol=1e-3), gaps  # a burst's frames keep their 33 ms, not 3 ms
    off = ts - true  # one constant offset: the least-delayed frame's
    assert np.ptp(off) < 1e-3, off
    naive = np.diff(arrival)
    assert naive.min() < 0.01  # what arrival stamps would have handed back


def test_latency_is_subtracted_and_a_steady_stream_is_stamped_at_arrival():
    clock = StreamClock(P, latency_s=0.05)
    arrivals = [10.0 + k * P + (0.002 if k % 3 else 0.0) for k in range(30)]  # jitter
    ts = [clock.stamp(a) for a in arrivals]
    assert ts[0] is None and all(t is not None for t in ts[1:])  # one frame to see the pace
    assert all(abs((a - 0.05) - t) <= 0.0021 for a, t in zip(arrivals[1:], ts[1:])), ts


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _gst_rtsp_python() -> str:
    probe = "import gi; gi.require_version('GstRtspServer', '1.0'); from gi.repository import GstRtspServer"
    py = "/usr/bin/python3"
    if Path(py).is_file() and subprocess.run([py, "-c", probe], capture_output=True).returncode == 0:
        return py
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        pytest.skip("GStreamer's RTSP server is not installed (Debian: apt-get install gir1.2-gst-rtsp-server-1.0 "
                    "gstreamer1.0-plugins-good) and this user cannot install it")
    subprocess.run(["apt-get", "install", "-y", "--no-install-recommends", "gir1.2-gst-rtsp-server-1.0",
                    "gstreamer1.0-plugins-good", "gstreamer1.0-plugins-base", "python3-gi"], capture_output=True,
                   timeout=900, env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"})
    if not Path(py).is_file() or subprocess.run([py, "-c", probe], capture_output=True).returncode != 0:
        pytest.skip("GStreamer's RTSP server could not be installed")
    return py


@pytest.mark.timeout(120)
def test_a_real_rtsp_stream_has_no_compressed_times_and_closes_promptly_when_silent():
    py = _gst_rtsp_python()
    port = _free_port()
    server = subprocess.Popen([py, str(Path(__file__).with_name("rtsp_server.py")), str(port)],
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    cam = None
    try:
        assert server.stdout.readline().strip() == "ready"
        cam = StreamCamera(f"rtsp://127.0.0.1:{port}/test", backend="opencv", timeout_s=10.0)
        t0 = time.monotonic()
        cam.open()
        opened_s = time.monotonic() - t0
        frames = []
        while len(frames) < 45:
            frames += cam.grab_recent(16)
        ts = np.array([f.t for f in frames])
        gaps = np.diff(ts)
        arrived = np.array([f.meta["t_arrived"] for f in frames])
        print(f"rtsp: opened in {opened_s:.2f} s, gaps median {np.median(gaps) * 1e3:.1f} ms, "
              f"min {gaps.min() * 1e3:.1f} ms, arrival gaps min {np.diff(arrived).min() * 1e3:.2f} ms")
        assert np.all(gaps > 0.02), gaps  # 33 ms apart, as captured: never a burst's 0.1 ms
        assert abs(np.median(gaps) - P) < 0.005, gaps
        assert np.all(ts <= arrived + 1e-6)
        assert frames[0].image.shape == (240, 320, 3)
        os.kill(server.pid, signal.SIGSTOP)  # the stream goes silent, its connection open: reads block
        try:
            time.sleep(0.5)
            t0 = time.monotonic()
            cam.close()
            closed_s = time.monotonic() - t0
            cam = None
        finally:
            os.kill(server.pid, signal.SIGCONT)
        print(f"rtsp: close() of a silent stream took {closed_s:.3f} s")
        assert closed_s < 0.5, closed_s
    finally:
        if cam is not None:
            cam.close()
        if server.poll() is None:
            server.kill()
            server.wait()
