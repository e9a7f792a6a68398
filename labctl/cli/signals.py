"""Signal handling for commands that must stop their devices on the way out."""

from __future__ import annotations

import signal

#: the signals that end a command through its stop path: Ctrl-C, a terminate (``timeout``, systemd,
#: ``docker stop``) and a hang-up (the terminal or the session closed)
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def interrupt_once(_signum, _frame) -> None:
    """SIGINT/SIGTERM/SIGHUP handler: ignore all three from now on, then raise KeyboardInterrupt.

    The first Ctrl-C, SIGTERM or SIGHUP starts the command's stop path; ignoring further ones inside
    the handler (not later, in the ``except``) leaves no moment at which a second Ctrl-C, as users
    press it, could cut the stop short."""
    ignore_stop_signals()
    raise KeyboardInterrupt


def ignore_stop_signals() -> None:
    """Ignore every signal of :data:`STOP_SIGNALS` (the stop path runs to its end)."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)


def catch_stop_signals() -> dict:
    """Route every signal of :data:`STOP_SIGNALS` to :func:`interrupt_once`; returns the previous
    handlers, for :func:`restore_signals`."""
    return {sig: signal.signal(sig, interrupt_once) for sig in STOP_SIGNALS}


def restore_signals(old: dict) -> None:
    """Put back the handlers :func:`catch_stop_signals` returned."""
    for sig, handler in old.items():
        signal.signal(sig, handler)
