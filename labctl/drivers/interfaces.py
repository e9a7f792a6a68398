"""What each device can do (labgrid's "protocols"): the interfaces that both the real
drivers and the simulated devices implement. Callers depend on these, never on a driver.

Units: mm, s, rad. Poses are 4×4 ``T_<to>_<from>``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass, field
from typing import Protocol, Self, runtime_checkable

import numpy as np

from ..timebase import Clock


class OpenClose(ABC):
    """``with device:`` opens the device and closes it again (every device has ``open``/``close``)."""

    @abstractmethod
    def open(self) -> None:
        """Connect to the device (port, socket, capture); raises DeviceError when it cannot."""

    @abstractmethod
    def close(self) -> None:
        """Release the device; safe to call twice."""

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class Frame:
    """One camera image with its capture time (s, on the runtime's clock) and sequence number."""

    image: np.ndarray  # H×W×3 uint8 BGR
    t: float
    seq: int
    meta: dict = field(default_factory=dict)


@runtime_checkable
class Camera(Protocol):
    """A camera that delivers the latest frame with its exposure time (fixed camera C1, mobile camera C2)."""
    def open(self) -> None:
        """Start delivering frames."""
    def close(self) -> None:
        """Stop and release the camera."""
    def grab(self) -> Frame:
        """The latest frame (never a stale buffered one); blocks until one is available."""
        ...
    def grab_recent(self, max_frames: int) -> list[Frame]:
        """The frames not yet delivered, oldest first: the newest ``max_frames`` of them (the last is the
        latest); blocks until there is one. A loop that was busy (a robot command's round trip at 9600 bps
        is ~0.15-0.2 s) tracks the frames it would otherwise have missed; older ones are dropped."""
        ...
    def info(self) -> dict:
        """What the camera is and how it is doing (kind, size, frames): plain data for ``labctl devices``."""


@dataclass(frozen=True)
class TableStatus:
    """One status report of the X-Y table: state word, machine position (mm), feed (mm/min), report time (s)."""
    state: str  # GRBL state word: Idle, Run, Hold:0, Jog, Alarm, Door:0, Check, Home, Sleep
    position: tuple[float, float, float]  # machine position, mm
    feed_mm_min: float = 0.0
    t: float = 0.0


@runtime_checkable
class Table(Protocol):
    """The NC X-Y table (object-motion simulator)."""

    def open(self) -> None:
        """Connect to the controller and find it alive."""
    def close(self) -> None:
        """Release the port (stop motion first with :meth:`stop`)."""
    def status(self) -> TableStatus:
        """A fresh status report: state, machine position (mm), feed."""
    def stream(self, lines: Iterable[str]) -> int:
        """Queue a G-code program; returns the number of lines sent, once every one is accepted."""
        ...
    def feed_hold(self) -> None:
        """Decelerate to a stop along the path, keeping the rest of the program."""
    def resume(self) -> None:
        """Continue after a feed hold."""
    def reset(self) -> None:
        """Soft reset: stop at once and discard the program."""
    def stop(self) -> TableStatus:
        """Stop motion now and discard the rest of the program (feed hold then reset); returns the
        confirmed status afterwards."""
        ...
    def ensure_ready(self, unlock: bool | None = None) -> TableStatus:
        """A status before a job, with an Alarm unlocked only if ``unlock`` says so; raises if it is not ready."""
        ...
    def start_program(self, lines: Iterable[str], line_numbers: Iterable[int] | None = None) -> Program:
        """Start streaming a G-code program without waiting: the caller pumps the returned :class:`Program`."""
        ...
    def watch(self) -> None:
        """Read status at its rate without waiting (a dropped link is noticed while the table runs a program)."""
    def wait_idle(self, timeout_s: float | None = None) -> TableStatus:
        """Wait until the table is Idle; returns that status."""
        ...

    #: called while the driver waits to reconnect a dropped link: the caller's keep-alive (other devices)
    while_reconnecting: Callable[[], None] | None

    @property
    def clock(self) -> Clock:
        """The clock the driver's timeouts and waits run on (the virtual clock in the simulated lab)."""
        ...


@runtime_checkable
class Program(Protocol):
    """A G-code program being streamed to the table, pumped by the run loop (:meth:`Table.start_program`)."""

    @property
    def table(self) -> Table:
        """The table it runs on."""
        ...
    @property
    def active(self) -> bool:
        """Lines are still to be sent or acknowledged."""
        ...
    @property
    def done(self) -> bool:
        """Every line was acknowledged."""
        ...
    @property
    def acked(self) -> int:
        """Lines acknowledged so far."""
        ...
    def pump(self, timeout_s: float = 0.0) -> bool:
        """Send what fits in the controller's buffer and read its replies (waiting up to ``timeout_s``)."""
        ...
    def progress(self) -> dict:
        """Lines acknowledged and total, as plain data for the record."""
        ...


@dataclass(frozen=True)
class RobotStatus:
    """One status of the robot: flange pose in the base frame (4×4, mm), moving, last segment id, controller time
    (s), and (dialect 1.3, a controller with an arm) the arm's six joint angles (rad), else None."""
    T_base_flange: np.ndarray  # 4×4
    moving: bool
    segment_id: int
    t: float = 0.0
    joints_rad: tuple[float, float, float, float, float, float] | None = None


@runtime_checkable
class Robot(Protocol):
    """The robot controller carrying the mobile camera (docs/protocols/robot.md)."""

    def open(self) -> None:
        """Connect to the controller and negotiate the dialect (docs/protocols/robot.md)."""
    def close(self) -> None:
        """Release the port (stop motion first with :meth:`stop`)."""
    def segment(self, T_base_flange: np.ndarray, duration_s: float, segment_id: int, *,
                end_velocity_mm_s: np.ndarray | None = None, end_omega_rad_s: np.ndarray | None = None,
                replace: bool = False, profile: str | None = None,
                end_acceleration_mm_s2: np.ndarray | None = None,
                limits: dict | None = None, hold: bool = False) -> tuple[float, float]:
        """Queue (``replace``: start now, dropping the queue) a timed task-space segment ending at
        ``T_base_flange``, with the controller's ``quintic`` or (dialect 1.2) ``ruckig`` ``profile`` under
        its own ``limits``; returns its (t0, t1) on the controller's clock, s (NaN when it does not say).
        ``hold`` (dialect 1.4, :attr:`holds`): kept at the controller, unplanned, until :meth:`go`."""
        ...
    @property
    def holds(self) -> bool:
        """The controller keeps a segment sent with ``hold`` until :meth:`go` (dialect 1.4)."""
        ...
    def go(self, segment_id: int) -> tuple[float, float]:
        """Run the held segment now; its (t0, t1) on the controller's clock, s."""
        ...
    def choose_profile(self, wanted: str) -> str:
        """The segment profile to plan with: ``wanted`` if the controller runs it, else ``quintic``."""
        ...
    def segment_defaults(self, profile: str, limits: dict | None = None) -> bool:
        """Make ``profile`` under ``limits`` the session's segment defaults (dialect 1.4 ``SET``), so segments that
        run them are shorter on the line; False where the session cannot (they keep naming them)."""
        ...
    def poll(self) -> None:
        """Collect the asynchronous reports (``@DONE``) received so far, without waiting."""
    @property
    def done_ids(self) -> Collection[int]:
        """Ids of the segments the controller reported done (``@DONE``), newest last."""
        ...
    @property
    def latched(self) -> str | None:
        """The fault the controller reported latched (``stopped``, ``watchdog``) at the last status, or None."""
        ...
    def clear(self) -> None:
        """Clear a latched fault so the controller accepts motion again."""
    def emergency_stop(self) -> None:
        """Best effort: send STOP without waiting for its reply; never raises."""
    def ensure_ready(self) -> RobotStatus:
        """A status before a job; raises if the controller holds a latched fault."""
        ...
    def maybe_heartbeat(self) -> None:
        """A heartbeat if none was sent for the heartbeat period."""
    def stop(self) -> None:
        """Brake to rest with the controller's stop ramp, dropping queued segments."""
    def status(self) -> RobotStatus:
        """A fresh status: flange pose ``T_base_flange`` (4×4, mm), moving, segment id."""
    def home(self) -> None:
        """Move to the home pose."""
    def heartbeat(self) -> None:
        """Tell the controller the host is alive (its watchdog stops the robot when heartbeats stop)."""

    #: called while the driver waits to reconnect a dropped link: the caller's keep-alive (other devices)
    while_reconnecting: Callable[[], None] | None

    @property
    def clock(self) -> Clock:
        """The clock the driver's timeouts and waits run on (the virtual clock in the simulated lab)."""
        ...
