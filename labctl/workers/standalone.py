"""``labctl worker predictor|recognizer``: one worker on this host, for the two-PC set-up.

On two PCs (as in the paper, §5.1) each host runs one worker; they meet over TCP
(``--link tcp://HOST:PORT``: the predictor listens, the recognizer connects) or over an RS-232
line (``--link /dev/ttyS0``). Each host reads the same lab workspace (calibration, library).
There is no supervisor process: each worker stops its own devices when the other goes silent.
"""

from __future__ import annotations

import dataclasses
import time
from urllib.parse import urlparse

from ..config import Lab
from ..errors import LabctlError, UserInputError
from .live import WorkerArgs, predictor_main, recognizer_main


class _NoSupervisor:
    """Stands in for the control pipe when no supervisor runs: keeps the worker's error or result."""

    def __init__(self):
        self.error: tuple[str, int] | None = None
        self.result: dict | None = None
        self.done: str | None = None

    def send(self, msg) -> None:
        if not msg:
            return
        if msg[0] == "error":
            self.error = (str(msg[1]), int(msg[2]) if len(msg) > 2 else 1)
        elif msg[0] == "result":
            self.result = msg[1]
        elif msg[0] == "done":
            self.done = str(msg[1])


class WorkerFailed(LabctlError):
    """A standalone worker could not start or stopped on an error; exits with the error's own code."""

    def __init__(self, message: str, exit_code: int = 1):
        super().__init__(message)
        self.exit_code = exit_code


def link_config(lab: Lab, link: str | None):
    """The lab's host link, overridden by ``--link`` (tcp://HOST:PORT or a serial port/URL)."""
    cfg = lab.host_link
    if link is None:
        if cfg.transport == "local":
            raise UserInputError("a standalone worker needs --link (tcp://HOST:PORT or a serial port); "
                                 "host_link.yaml says local")
        return cfg
    if link.startswith("tcp://"):
        u = urlparse(link)
        if not u.hostname or not u.port:
            raise UserInputError(f"--link {link!r}: expected tcp://HOST:PORT")
        return dataclasses.replace(cfg, transport="tcp", host=u.hostname, tcp_port=u.port)
    return dataclasses.replace(cfg, transport="serial", port=link)


def run_worker(lab: Lab, role: str, spec: dict, link: str | None) -> dict:
    """Run one worker in this process; its result (predictor) or how it ended (recognizer).

    Raises :class:`WorkerFailed` (exit code 3 for a device fault) when the worker stops on an error."""
    own = ("table", "robot", "fixed_camera") if role == "predictor" else ("mobile_camera",)
    if any(getattr(lab, r) is not None and getattr(lab, r).kind == "sim" for r in own):
        raise UserInputError(f"labctl worker {role} drives this host's real devices; the lab's driver files say "
                             "'sim' (the simulated lab runs both workers with `labctl run`, any host link)")
    cfg = link_config(lab, link)
    lab = dataclasses.replace(lab, host_link=cfg)
    args = WorkerArgs(role=role, lab_root=str(lab.root), run_dir=None, spec=spec, origin=time.monotonic(),
                      extra={"host_link": dataclasses.asdict(cfg)})
    target = predictor_main if role == "predictor" else recognizer_main
    control = _NoSupervisor()
    target(args, None, control)
    if control.error is not None:  # the device's (or link's) own message, and its exit code (3: device)
        raise WorkerFailed(*control.error)
    return control.result if control.result is not None else {"role": role, "ended": control.done or "stopped"}
