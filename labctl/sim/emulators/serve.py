"""``labctl sim serve``: the simulated lab's GRBL table and robot controller on pseudo-terminals.

Both emulators run on the real clock, paced at their driver files' baud rates (or ``baud``),
until Ctrl-C. ``on_ready`` receives ``{"table": "/dev/pts/N", "robot": "/dev/pts/M"}``.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from .grbl import GrblEmulator
from .pty import run_on_pty
from .robot import RobotEmulator


def start_emulators(lab, baud: int | None = None, clock: Callable[[], float] = time.monotonic) -> dict:
    """Start both emulators on ptys; returns {role: PtyDevice} (call ``.stop()`` on each)."""
    t = lab.table
    grbl = GrblEmulator(clock, travel_mm=t.travel_mm, max_feed_mm_min=t.max_feed_mm_min, accel_mm_s2=t.accel_mm_s2)
    robot = RobotEmulator(clock, lab.robot)
    devices = {}
    try:
        devices["table"] = run_on_pty(grbl, baud or t.baud, clock=clock)
        devices["robot"] = run_on_pty(robot, baud or lab.robot.baud, clock=clock)
    except BaseException:
        for d in devices.values():
            d.stop()
        raise
    return devices


def serve_forever(lab, baud: int | None = None, on_ready: Callable[[dict], None] | None = None,
                  should_stop: Callable[[], bool] | None = None) -> None:
    """Serve until Ctrl-C (or ``should_stop()``); ``on_ready({role: pty path})`` once both are up."""
    devices = start_emulators(lab, baud)
    try:
        if on_ready is not None:
            on_ready({role: d.path for role, d in devices.items()})
        while not (should_stop and should_stop()):
            time.sleep(0.1)
            for role, d in devices.items():
                if not d._thread.is_alive():
                    raise RuntimeError(f"the {role} emulator stopped: {d.errors[-1] if d.errors else 'unknown'}")
    except KeyboardInterrupt:
        pass
    finally:
        for d in devices.values():
            d.stop()
