"""Cameras: V4L2 through OpenCV, a replay camera over a folder of stamped frames, and the factory.

* :class:`V4L2Camera` opens ``cv2.VideoCapture(device, cv2.CAP_V4L2)``, applies resolution,
  fps and exposure from the camera's driver file, and runs a grabber thread that keeps only
  the newest frame (``grab()`` never returns a stale buffered one: it waits for a frame captured
  after the call began, unless ``wait_new=False``). Frames carry the capture time on the
  caller's clock (``time.monotonic`` by default), taken when the driver dequeued the buffer.
* :class:`ReplayCamera` serves a folder of images named by capture time (``<t_seconds>.png``,
  e.g. ``12.345678.png``), or listed in ``index.csv`` (``t,file`` rows); ``grab()`` returns the
  frames in order (or, with a clock, the newest frame at or before the clock's time).
* :func:`open_camera(role, lab)` builds the camera a lab's driver file names (v4l2, replay; simulated
  cameras come from the simulated lab: :func:`labctl.workers.devices.open_device`).
"""

from __future__ import annotations

import csv
import logging
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import DeviceError
from .interfaces import Frame, OpenClose
from .serial_link import DeviceTimeout

log = logging.getLogger(__name__)

_STAMP = re.compile(r"^(\d+(?:\.\d+)?)\.(png|jpg|jpeg|bmp|tif|tiff)$", re.IGNORECASE)


class CameraError(DeviceError):
    """The camera could not be opened or stopped delivering frames."""


class V4L2Camera(OpenClose):
    """A V4L2 camera through OpenCV with latest-frame semantics."""

    def __init__(self, device, width: int = 640, height: int = 480, fps: float = 30.0,
                 exposure: float | None = None, timeout_s: float = 2.0,
                 clock: Callable[[], float] = time.monotonic, name: str = ""):
        self.device = int(device) if isinstance(device, str) and device.isdigit() else device
        self.width, self.height, self.fps, self.exposure = width, height, fps, exposure
        self.timeout_s = timeout_s
        self.clock = clock
        self.name = name or str(device)
        self._cap = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._cond = threading.Condition()
        self._latest: Frame | None = None
        self._seq = 0
        self._error: str | None = None
        self.dropped = 0  # frames overwritten before anyone grabbed them

    @classmethod
    def from_config(cls, cfg, **kw) -> V4L2Camera:
        return cls(cfg.device, cfg.width, cfg.height, cfg.fps, cfg.exposure, **kw)

    def open(self) -> None:
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
        self._cap = cap
        self._stop.clear()
        self._thread = threading.Thread(target=self._grabber, name=f"v4l2-{self.name}", daemon=True)
        self._thread.start()

    def _grabber(self) -> None:
        while not self._stop.is_set():
            ok = self._cap.grab()
            t = self.clock()
            if not ok:
                with self._cond:
                    self._error = "the camera stopped delivering frames"
                    self._cond.notify_all()
                return
            ok, image = self._cap.retrieve()
            if not ok or image is None:
                continue
            if image.ndim == 2:
                image = np.repeat(image[:, :, None], 3, axis=2)
            with self._cond:
                if self._latest is not None and self._latest.seq == self._seq:
                    self.dropped += 1
                self._seq += 1
                self._latest = Frame(image=image, t=t, seq=self._seq, meta={"device": str(self.device)})
                self._cond.notify_all()

    def grab(self, wait_new: bool = True) -> Frame:
        """The newest frame; with ``wait_new`` one captured after this call began."""
        if self._cap is None:
            raise CameraError(f"camera {self.name} is not open")
        with self._cond:
            start_seq = self._seq
            ok = self._cond.wait_for(lambda: self._error is not None or (
                self._latest is not None and (not wait_new or self._latest.seq > start_seq)), self.timeout_s)
            if self._error is not None:
                raise CameraError(f"camera {self.name}: {self._error}")
            if not ok:
                raise DeviceTimeout(f"camera {self.name}: no frame within {self.timeout_s:g} s")
            return self._latest

    def info(self) -> dict:
        import cv2

        if self._cap is None:
            return {"kind": "v4l2", "device": str(self.device), "open": False}
        c = self._cap
        return {"kind": "v4l2", "device": str(self.device), "open": True,
                "width": int(c.get(cv2.CAP_PROP_FRAME_WIDTH)), "height": int(c.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                "fps": float(c.get(cv2.CAP_PROP_FPS)), "backend": c.getBackendName(), "frames": self._seq,
                "dropped": self.dropped}

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._cap is not None:
            self._cap.release()
            self._cap = None


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

    @classmethod
    def from_config(cls, cfg, root: Path | None = None, **kw) -> ReplayCamera:
        folder = Path(cfg.folder)
        if root is not None and not folder.is_absolute():
            folder = root / folder
        return cls(folder, **kw)

    def open(self) -> None:
        self._frames = list_stamped_frames(self.folder)
        self._next = 0

    def close(self) -> None:
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
            return self._load(i)
        if self._next >= len(self._frames):
            if not self.loop:
                raise CameraError(f"replay camera {self.name}: end of recording ({len(self._frames)} frames)")
            self._next = 0
        frame = self._load(self._next)
        self._next += 1
        return frame

    def info(self) -> dict:
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


def open_camera(role: str, lab, **kw):
    """The (unopened) camera for ``role`` (fixed_camera/mobile_camera, or fixed/mobile) of ``lab``."""
    role = role if role.endswith("_camera") else f"{role}_camera"
    cfg = getattr(lab, role, None)
    if cfg is None:
        raise CameraError(f"the lab has no {role}")
    if cfg.kind == "v4l2":
        return V4L2Camera.from_config(cfg, name=role, **kw)
    if cfg.kind == "replay":
        return ReplayCamera.from_config(cfg, root=getattr(lab, "root", None), name=role, **kw)
    if cfg.kind == "sim":
        raise CameraError(f"{role} is simulated: the simulated lab serves it (labctl.workers.devices.open_device)")
    raise CameraError(f"{role}: unknown camera kind {cfg.kind!r}")
