"""Signal handling for commands that must stop their devices on the way out (issue 13)."""

from __future__ import annotations

import signal


def interrupt_once(_signum, _frame) -> None:
    """SIGINT/SIGTERM handler: ignore both from now on, then raise KeyboardInterrupt.

    The first Ctrl-C or SIGTERM starts the command's stop path; ignoring further ones inside the
    handler (not later, in the ``except``) leaves no moment at which a second Ctrl-C, as users
    press it, could cut the stop short."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise KeyboardInterrupt
