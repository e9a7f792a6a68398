"""Driver files (``drivers/*.yaml``): *where* each device is and how to reach it.

One dataclass per role. ``kind: sim`` selects the simulated device; other kinds name a real
driver. Fields marked *sim* describe the simulator's ground truth and are ignored by real
drivers. Units: mm, s, degrees only where the name says ``_deg``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from .schema import Fraction, NonNegative, Positive, PositiveInt


@dataclass(frozen=True)
class TableConfig:
    """NC X-Y table behind a GRBL 1.1 controller (the paper's object-motion simulator)."""

    kind: Literal["sim", "grbl"] = "sim"
    port: str | None = None  # device path or pyserial URL (socket://, rfc2217://, spy://)
    baud: PositiveInt = 9600
    # rfc2217:// only: switch the server's port to `baud` (false: the server's own rate stands, e.g. ser2net's
    # connector line); socket:// carries no rate at all, and a device path always runs at `baud`
    set_remote_baud: bool = False
    timeout_s: Positive = 5.0
    reset_on_open: bool = True  # does opening the port reset the board (DTR)?
    travel_mm: tuple[float, float] = (600.0, 400.0)
    max_feed_mm_min: Positive = 6000.0
    accel_mm_s2: Positive = 200.0
    status_hz: Positive = 5.0
    stall_reports: int = 25  # Run reports in a row without motion before the table counts as stalled (0: off)
    homing_timeout_s: Positive = 120.0  # GRBL sends nothing while homing: give up after this long
    reconnect_s: NonNegative = 0.0  # after the port drops, retry opening it (with backoff) for this long
    stop_confirm_s: Positive = 30.0  # a stop waits this long (at least timeout_s) for GRBL to confirm its reset
    # the whole stop (feed hold awaited, soft reset confirmed, state read back) ends within this, answered or not:
    # 40 s is the sum of its stages at the defaults on a silent link (hold timeout_s 5 + reset stop_confirm_s 30 +
    # read-back timeout_s 5); a real board answers each in milliseconds, so a lab may lower it (e.g. 10)
    stop_total_s: Positive = 40.0
    # sim: T_w_table of the table's machine zero (the table plane is z = 0 in W)
    origin_w_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def validate(self):
        """Cross-field check after loading: ``(key, what was expected)`` for the first problem, or None."""
        if self.kind == "grbl" and not self.port:
            return "port", "a grbl table needs a port (device path or pyserial URL)"
        if self.baud <= 0:
            return "baud", f"expected a positive baud rate, got {self.baud}"
        if self.stall_reports < 0:
            return "stall_reports", f"expected 0 (off) or a positive count, got {self.stall_reports}"
        if not self.homing_timeout_s > 0:
            return "homing_timeout_s", f"expected a positive time, got {self.homing_timeout_s}"
        if not self.stop_total_s > 0:
            return "stop_total_s", f"expected a positive time, got {self.stop_total_s}"
        if self.reconnect_s < 0:
            return "reconnect_s", f"expected a time ≥ 0, got {self.reconnect_s}"
        return None


@dataclass(frozen=True)
class RobotConfig:
    """Robot controller speaking the dialect of docs/protocols/robot.md, carrying camera C2."""

    kind: Literal["sim", "serial"] = "sim"
    port: str | None = None
    baud: PositiveInt = 9600
    timeout_s: Positive = 2.0
    heartbeat_s: Positive = 0.2  # controller stops if no heartbeat for watchdog_s
    watchdog_s: Positive = 0.5
    workspace_min_mm: tuple[float, float, float] = (-800.0, -900.0, -150.0)
    workspace_max_mm: tuple[float, float, float] = (1400.0, 1300.0, 1300.0)
    v_max_mm_s: Positive = 500.0
    a_max_mm_s2: Positive = 1500.0
    w_max_deg_s: Positive = 120.0
    j_max_mm_s3: Positive | None = None  # jerk limit of ruckig segments (dialect 1.2); null: 20·a_max per second
    home_mm: tuple[float, float, float] = (300.0, -450.0, 900.0)
    reconnect_s: NonNegative = 0.0  # after the port drops, retry opening it (with backoff) for this long
    # the arm's kinematic data file (drivers/arms/<arm>.yaml), relative to this file; null: a task-space box only
    arm: str | None = None
    # where that arm's base is bolted in the world (T_w_base, roll-pitch-yaw); null: the arm file's own mount
    arm_base_xyz_mm: tuple[float, float, float] | None = None
    arm_base_rpy_deg: tuple[float, float, float] | None = None
    # how the reference controller (the simulated arm) keeps its arm out of trouble: margins round the
    # shoulder (mm of the wrist point from the base-axis cylinder), elbow (|sin q3|) and wrist (|sin q5|)
    # singularities, the joints' acceleration limits, and the interval its segment check samples at
    arm_shoulder_margin_mm: NonNegative = 50.0
    arm_elbow_margin: NonNegative = 0.05
    arm_wrist_margin: NonNegative = 0.05
    arm_joint_accel_deg_s2: tuple[Positive, Positive, Positive, Positive, Positive, Positive] = (
        1500.0, 1500.0, 1500.0, 1500.0, 1500.0, 1500.0)
    arm_check_dt_s: Positive = 0.004

    def validate(self):
        """Cross-field check (port, workspace box, heartbeat < watchdog, home inside): ``(key, message)`` or None."""
        if self.kind == "serial" and not self.port:
            return "port", "a serial robot needs a port (device path or pyserial URL)"
        if any(lo >= hi for lo, hi in zip(self.workspace_min_mm, self.workspace_max_mm)):
            return "workspace_min_mm", "each minimum must be below its maximum"
        if not self.heartbeat_s < self.watchdog_s:
            return "heartbeat_s", (f"the heartbeat ({self.heartbeat_s:g} s) must be shorter than the controller's "
                                   f"watchdog ({self.watchdog_s:g} s), or the controller stops between beats")
        if not all(lo <= h <= hi for lo, h, hi in zip(self.workspace_min_mm, self.home_mm, self.workspace_max_mm)):
            return "home_mm", f"home {list(self.home_mm)} is outside the workspace box"
        if self.reconnect_s < 0:
            return "reconnect_s", f"expected a time ≥ 0, got {self.reconnect_s}"
        return None


@dataclass(frozen=True)
class LensConfig:
    """Nominal sensor and lens (Tsai's parameters); the sim uses them as the true camera."""

    f_mm: Positive = 25.0
    dx_mm: Positive = 0.013
    dy_mm: Positive = 0.013
    ncx: Positive = 640.0
    nfx: Positive = 640.0
    kappa1: float = 0.0
    sx: Positive = 1.0
    cx: float | None = None  # default: image centre
    cy: float | None = None


@dataclass(frozen=True)
class CameraConfig:
    """A camera driver file (``drivers/*_camera.yaml``): source, image size (px), fps, timing (s), lens, response."""

    kind: Literal["sim", "v4l2", "stream", "replay"] = "sim"
    device: str | int | None = None  # v4l2: index or /dev/videoN
    url: str | None = None  # stream: http://host:8080/?action=stream (MJPEG), rtsp://… (OpenCV/FFmpeg)
    backend: Literal["auto", "http", "opencv"] = "auto"  # stream: http(s) read by labctl, others by OpenCV
    timestamps: Literal["arrival", "header"] = "arrival"  # stream: capture time = arrival − latency, or X-Timestamp
    latency_s: NonNegative = 0.0  # exposure-to-arrival delay subtracted from the arrival time (v4l2, stream)
    timeout_s: Positive = 2.0  # no frame for this long: the camera has stalled
    folder: str | None = None  # replay: folder of stamped frames
    width: PositiveInt = 640
    height: PositiveInt = 480
    fps: Positive = 30.0
    exposure: float | None = None
    marker_hue_deg: tuple[float, float] = (-15.0, 15.0)  # red straddles 0°
    marker_min_saturation: Fraction = 0.45
    # the camera's response (labctl.vision.response): linear | srgb | "gamma G" | G | 256-entry LUT
    response: str | float | list[float] = "linear"
    # who stated it: declared (the lab measured or knows it), learned (`labctl vision learn-response` wrote it);
    # null: nobody did — a `linear` left so counts as undeclared and pose stays conservative (docs/notes/vision.md)
    response_source: Literal["declared", "learned"] | None = None
    lens: LensConfig = field(default_factory=LensConfig)
    # sim: the fixed camera's true pose (eye and look-at target, W frame)
    eye_w_mm: tuple[float, float, float] | None = None
    target_w_mm: tuple[float, float, float] | None = None
    noise_sigma: NonNegative = 2.0  # sim: grey levels
    hand_eye_mm: tuple[float, float, float] = (0.0, 60.0, 80.0)  # sim: C2 origin in flange F
    hand_eye_rpy_deg: tuple[float, float, float] = (1.5, -1.0, 90.0)  # sim: C2 axes in F

    def validate(self):
        """Cross-field check (source settings, timing, image size, response curve): ``(key, message)`` or None."""
        if self.kind == "v4l2" and self.device is None:
            return "device", "a v4l2 camera needs a device (index or /dev/videoN)"
        if self.kind == "stream" and not self.url:
            return "url", "a stream camera needs a url (http://… MJPEG or rtsp://…)"
        if self.latency_s < 0 or self.timeout_s <= 0:
            return "latency_s", "latency_s must be >= 0 and timeout_s > 0"
        if self.kind == "replay" and not self.folder:
            return "folder", "a replay camera needs a folder of stamped frames"
        if self.width <= 0 or self.height <= 0:
            return "width", "image size must be positive"
        r = self.response.strip().lower() if isinstance(self.response, str) else self.response
        if isinstance(r, str) and not (r in ("linear", "srgb") or r.startswith("gamma")):
            return "response", f"expected linear, srgb, 'gamma G', a number or a 256-entry list, got {r!r}"
        if isinstance(r, list) and len(r) != 256:
            return "response", f"a response lookup table needs 256 entries, got {len(r)}"
        if isinstance(r, list) and (any(b < a for a, b in zip(r, r[1:])) or not r[-1] > r[0]):
            return "response", "a response lookup table must be non-decreasing (code 0…255 → radiance)"
        gamma = r if isinstance(r, float | int) and not isinstance(r, bool) else None
        if isinstance(r, str) and r.startswith("gamma"):
            try:
                gamma = float(r[5:].strip(" :="))
            except ValueError:
                return "response", f"expected 'gamma G' with a number G, got {r!r}"
        if gamma is not None and not (math.isfinite(gamma) and 0.2 <= gamma <= 5.0):
            return "response", f"a response gamma must be within 0.2–5, got {gamma:g}"
        return None


@dataclass(frozen=True)
class HostLinkConfig:
    """How the two workers talk: one PC (local), two PCs (tcp) or RS-232 as in 1996 (serial)."""

    transport: Literal["local", "tcp", "serial"] = "local"
    host: str = "127.0.0.1"
    tcp_port: PositiveInt = 5757
    port: str | None = None  # serial device or pyserial URL; null on one PC: a paced pty null modem
    baud: PositiveInt = 9600
    heartbeat_s: Positive = 0.2
    dead_after_s: Positive = 3.0  # a worker whose peer (other worker, supervisor) is silent this long stops its devices
    stall_after_s: Positive = 4.0  # the supervisor: a worker silent this long after its first beat is hung (SIGSTOP)
    start_timeout_s: Positive = 60.0  # grace before a worker's (or peer's) first beat: imports, device opening
    key_file: str | None = None  # tcp: file holding the shared HMAC key (or $LABCTL_LINK_KEY); relative to the lab

    def validate(self):
        """Cross-field check (baud; heartbeat below dead_after_s and stall_after_s): ``(key, message)`` or None."""
        if self.baud <= 0:
            return "baud", f"expected a positive baud rate, got {self.baud}"
        if not self.heartbeat_s < min(self.dead_after_s, self.stall_after_s):
            return "heartbeat_s", (f"the heartbeat ({self.heartbeat_s:g} s) must be shorter than dead_after_s "
                                   f"({self.dead_after_s:g} s) and stall_after_s ({self.stall_after_s:g} s)")
        return None


ROLE_TYPES = {
    "table": TableConfig,
    "robot": RobotConfig,
    "fixed_camera": CameraConfig,
    "mobile_camera": CameraConfig,
    "host_link": HostLinkConfig,
}
