"""``labctl worker predictor|recognizer``: one worker on this host, for the two-PC set-up.

On two PCs (as in the paper, §5.1) each host runs one worker; they meet over TCP
(``--link tcp://HOST:PORT``: the predictor listens, the recognizer connects) or over an RS-232
line (``--link /dev/ttyS0``). Each host reads the same lab workspace (calibration, library).
There is no supervisor process: each worker tracks the other's heartbeats and, after
``host_link.dead_after_s`` of silence, stops its own devices, confirms it and exits non-zero
(3) saying why. Ctrl-C (exit 130), SIGTERM (exit 143) and SIGHUP (exit 129) stop the devices the same way.
"""

from __future__ import annotations

import dataclasses
import time
from urllib.parse import urlparse

from ..config import Lab
from ..errors import LabctlError, UserInputError
from .live import WorkerArgs, _child_signals, predictor_main, recognizer_main


class WorkerFailed(LabctlError):
    """A standalone worker ended abnormally; ``exit_code`` is its status (1, 3, 130, 143)."""

    def __init__(self, message: str, exit_code: int):
        super().__init__(message)
        self.exit_code = exit_code


class _NoSupervisor:
    """Stands in for the control pipe when no supervisor runs: keeps the worker's last error for
    the one line the CLI prints; there is no supervisor to lose."""

    supervised = False

    def __init__(self) -> None:
        self.errors: list[str] = []
        self.result: dict | None = None

    def beat(self, *args, **kw) -> None:
        pass

    def send(self, *msg) -> None:
        if msg and msg[0] == "error":
            self.errors.append(str(msg[1]))
        elif msg and msg[0] == "result":
            self.result = msg[1]

    def supervisor_lost(self) -> None:
        return None


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
    _child_signals(supervised=False)  # Ctrl-C and SIGTERM end in the worker's stop path, not a traceback
    ctl = _NoSupervisor()
    code = target(args, None, ctl)
    if code:
        raise WorkerFailed(ctl.errors[-1] if ctl.errors else f"{role} worker failed", code)
    return ctl.result if ctl.result is not None else {"role": role, "ended": "stopped"}
