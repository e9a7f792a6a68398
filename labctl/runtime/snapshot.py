"""The fixed camera's frames for the live view: a downscaled JPEG in the record folder, at most twice a second.

:class:`SnapshotCamera` wraps the predictor's camera. Each ``grab``/``grab_recent`` hands the newest
frame (a reference, copied only when one is due) to a writer thread and returns at once; the thread
scales it down, encodes it and replaces ``live/fixed.jpg`` atomically, with ``live/fixed.json`` saying
which frame it is (``t``, ``seq``, the scale from full-size pixels). A frame that arrives while the
writer is busy replaces the one waiting: frames are dropped for the viewer, never for the run, and
the run's loop never waits on the disk. The viewer never grabs from the camera itself (that would
take frames from the predictor). Snapshots are written only when the record folder holds a
``live/`` folder (``labctl run --view`` makes it): without the view a run writes nothing more.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path

from ..fsutil import atomic_write_bytes, atomic_write_text

__all__ = ["LIVE_DIR", "SnapshotCamera", "maybe_snapshots"]

LIVE_DIR = "live"  # inside the record folder
_log = logging.getLogger(__name__)


class SnapshotCamera:
    """A camera that also offers its newest frame to a low-rate JPEG writer (see the module docstring)."""

    def __init__(self, camera, folder: Path, period_s: float, width: int, clock=time.monotonic):
        self._camera = camera
        self._folder = Path(folder)
        self._period_s = float(period_s)
        self._width = int(width)
        self._clock = clock
        self._t_last = -float("inf")
        self._pending: tuple | None = None
        self._wake = threading.Condition()
        self._closed = False
        self.written = 0  # snapshots written (for tests and the notes)
        self._thread = threading.Thread(target=self._writer, name="labctl-live-snapshot", daemon=True)
        self._thread.start()

    def __getattr__(self, name):  # open, info, anything else: the camera's own
        return getattr(self._camera, name)

    def grab(self):
        """The camera's latest frame (offered to the writer when one is due)."""
        frame = self._camera.grab()
        self._offer(frame)
        return frame

    def grab_recent(self, max_frames: int):
        """The camera's undelivered frames, as :meth:`Camera.grab_recent`; the newest is offered to the writer."""
        frames = self._camera.grab_recent(max_frames)
        if frames:
            self._offer(frames[-1])
        return frames

    def _offer(self, frame) -> None:
        now = self._clock()
        if now - self._t_last < self._period_s:
            return
        self._t_last = now
        # a copy: a driver may reuse its buffer; ~1 ms at 640×480, twice a second
        snap = (frame.image.copy(), float(frame.t), int(frame.seq))
        with self._wake:
            self._pending = snap  # a snapshot still waiting is replaced, never queued
            self._wake.notify()

    def _writer(self) -> None:
        import cv2

        while True:
            with self._wake:
                while self._pending is None and not self._closed:
                    self._wake.wait()
                if self._pending is None:
                    return
                image, t, seq = self._pending
                self._pending = None
            try:
                h, w = image.shape[:2]
                scale = min(1.0, self._width / max(w, 1))
                small = cv2.resize(image, (max(1, round(w * scale)), max(1, round(h * scale))),
                                   interpolation=cv2.INTER_AREA) if scale < 1.0 else image
                ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 80])
                if not ok:
                    continue
                self._folder.mkdir(exist_ok=True)
                atomic_write_bytes(self._folder / "fixed.jpg", buf.tobytes())
                atomic_write_text(self._folder / "fixed.json", json.dumps(
                    {"t": t, "seq": seq, "scale": scale, "width": small.shape[1], "height": small.shape[0]}))
                self.written += 1
            except Exception as exc:  # noqa: BLE001 — the viewer's snapshot must never end the run
                _log.debug("live snapshot not written: %s", exc)

    def close(self) -> None:
        """Stop the writer (a snapshot still waiting is written first), then close the camera."""
        with self._wake:
            self._closed = True
            self._wake.notify()
        self._thread.join(timeout=1.0)
        self._camera.close()


def maybe_snapshots(camera, run_dir: str | Path | None, period_s: float, width: int):
    """``camera`` wrapped in a :class:`SnapshotCamera` when the record folder asks for the live view (it holds a
    ``live/`` folder), else ``camera`` itself."""
    if run_dir is None or not (Path(run_dir) / LIVE_DIR).is_dir():
        return camera
    return SnapshotCamera(camera, Path(run_dir) / LIVE_DIR, period_s, width)
