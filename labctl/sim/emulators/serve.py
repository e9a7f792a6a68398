"""``labctl sim serve``'s first engine: the simulated lab's GRBL table and robot controller on pseudo-terminals.

Both emulators run in real time on CLOCK_MONOTONIC, paced at their driver files' baud rates (or
``baud``), until Ctrl-C; the carriage powers up at machine zero and the robot at its controller's
home. ``on_ready`` receives ``{"table": "/dev/pts/N", "robot": "/dev/pts/M"}``. The whole lab
(cameras too) is :class:`labctl.runtime.simlab.ServedLab`; both are built by
:meth:`labctl.sim.lab.SimLab.build`.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from ..clock import RealClock
from ..lab import SimLab


def _served(lab, baud: int | None, clock: RealClock | None) -> SimLab:
    clock = clock if clock is not None else RealClock(time.monotonic())  # origin ≈ 0: monotonic time
    return SimLab.build(lab, clock, ports="pty", devices=("table", "robot"), baud=baud, table_start_mm=(0.0, 0.0),
                        robot_start="controller")


def start_emulators(lab, baud: int | None = None, clock: RealClock | None = None) -> dict:
    """Start both emulators on ptys (``clock``: default CLOCK_MONOTONIC itself); returns {role: PtyDevice}
    (call ``.stop()`` on each)."""
    return dict(_served(lab, baud, clock).ptys)


def serve_forever(lab, baud: int | None = None, on_ready: Callable[[dict], None] | None = None,
                  should_stop: Callable[[], bool] | None = None) -> None:
    """Serve until Ctrl-C (or ``should_stop()``); ``on_ready({role: pty path})`` once both are up."""
    with _served(lab, baud, None) as sim:
        try:
            if on_ready is not None:
                on_ready(sim.endpoints())
            while not (should_stop and should_stop()):
                time.sleep(0.1)
                sim.check_alive()
        except KeyboardInterrupt:
            pass
