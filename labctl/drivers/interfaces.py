"""What each device can do (labgrid's "protocols"): the interfaces that both the real
drivers and the simulated devices implement. Callers depend on these, never on a driver.

Units: mm, s, rad. Poses are 4×4 ``T_<to>_<from>``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Protocol, Self, runtime_checkable

import numpy as np


class OpenClose(ABC):
    """``with device:`` opens the device and closes it again (every device has ``open``/``close``)."""

    @abstractmethod
    def open(self) -> None: ...

    @abstractmethod
    def close(self) -> None: ...

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
    def open(self) -> None: ...
    def close(self) -> None: ...
    def grab(self) -> Frame:
        """The latest frame (never a stale buffered one); blocks until one is available."""
        ...
    def info(self) -> dict: ...


@dataclass(frozen=True)
class TableStatus:
    state: str  # GRBL state word: Idle, Run, Hold:0, Jog, Alarm, Door:0, Check, Home, Sleep
    position: tuple[float, float, float]  # machine position, mm
    feed_mm_min: float = 0.0
    t: float = 0.0


@runtime_checkable
class Table(Protocol):
    """The NC X-Y table (object-motion simulator)."""

    def open(self) -> None: ...
    def close(self) -> None: ...
    def status(self) -> TableStatus: ...
    def stream(self, lines: Iterable[str]) -> int:
        """Queue a G-code program; returns the number of lines sent, once every one is accepted."""
        ...
    def feed_hold(self) -> None: ...
    def resume(self) -> None: ...
    def reset(self) -> None: ...
    def stop(self) -> TableStatus:
        """Stop motion now and discard the rest of the program (feed hold then reset); returns the
        confirmed status afterwards."""
        ...


@dataclass(frozen=True)
class RobotStatus:
    T_base_flange: np.ndarray  # 4×4
    moving: bool
    segment_id: int
    t: float = 0.0


@runtime_checkable
class Robot(Protocol):
    """The robot controller carrying the mobile camera (docs/protocols/robot.md)."""

    def open(self) -> None: ...
    def close(self) -> None: ...
    def segment(self, T_base_flange: np.ndarray, duration_s: float, segment_id: int) -> tuple[float, float]:
        """Queue a timed task-space segment ending at ``T_base_flange`` (controller interpolates a quintic);
        returns its (t0, t1) on the controller's clock, s."""
        ...
    def stop(self) -> None: ...
    def status(self) -> RobotStatus: ...
    def home(self) -> None: ...
    def heartbeat(self) -> None: ...
