"""``labctl devices`` (check every device) and ``labctl table …`` (drive a GRBL table directly)."""

from __future__ import annotations

import contextlib
from pathlib import Path

import click

from ._common import emit, get_ctx, json_option


@click.command("devices")
@json_option
def devices_cmd() -> int:
    """List the lab's devices, open and identify each, and give a verdict per device."""
    from ..runtime.devices import check_devices

    rows = check_devices(get_ctx().lab())

    def human(console):
        from rich.table import Table

        t = Table("role", "kind", "where", "identity", "verdict", title="devices")
        for r in rows:
            style = "green" if r["ok"] else "red"
            t.add_row(r["role"], r["kind"], r["where"], str(r["identity"] or "-"), f"[{style}]{r['verdict']}[/]")
        console.print(t)
        for r in rows:
            if r.get("response"):
                console.print(f"{r['role']}: {r['response']}", highlight=False)

    emit({"devices": rows, "ok": all(r["ok"] for r in rows)}, human)
    return 0 if all(r["ok"] for r in rows) else 3


def _positive_baud(ctx, param, value):
    if value is not None and value <= 0:
        raise click.BadParameter(f"must be a positive number of bits per second, got {value}")
    return value


def _positive_timeout(ctx, param, value):
    if value is not None and not value > 0:
        raise click.BadParameter(f"must be a positive number of seconds, got {value}")
    return value


_port = click.option("--port", default=None, help="Device path or pyserial URL (default: the lab's table port).")
_baud = click.option("--baud", type=int, default=None, callback=_positive_baud,
                     help="Baud rate (default: the lab's table baud; stock GRBL 1.1h: 115200).")
_timeout = click.option("--timeout", "timeout_s", type=float, default=None, callback=_positive_timeout,
                        help="Reply timeout, s (for `home`: the homing time-out).")
_unlock = click.option("--unlock", is_flag=True,
                       help="Leave an Alarm with $X first: you vouch that the table's position is right.")
# `table move -5 -5`: negative numbers are arguments, not options
_NUMBERS = {"ignore_unknown_options": True}


def _open_table(port: str | None, baud: int | None, timeout_s: float | None, *, reset_if_silent: bool = False):
    """The table named by --port/--baud (else the lab's), unopened: use it as ``with _open_table(...) as t``.

    Never unlocks an Alarm on its own and never soft-resets unless ``reset_if_silent``."""
    from ..config import TableConfig
    from ..drivers.grbl import GrblTable
    from ..errors import UserInputError

    cfg = get_ctx().lab().table or TableConfig()  # a lab without a table: --port names one
    port = port or cfg.port
    if not port:
        raise UserInputError("no table port: pass --port PORT (the lab's table is simulated; "
                             "`labctl sim serve` prints a port to use)")
    return GrblTable(port, baud or cfg.baud, reset_on_open=cfg.reset_on_open, status_hz=cfg.status_hz,
                     timeout_s=timeout_s or cfg.timeout_s, auto_unlock=False, reset_if_silent=reset_if_silent,
                     stall_reports=cfg.stall_reports, homing_timeout_s=cfg.homing_timeout_s,
                     stop_confirm_s=cfg.stop_confirm_s, stop_total_s=cfg.stop_total_s,
                     reconnect_s=cfg.reconnect_s, set_remote_baud=cfg.set_remote_baud)


@contextlib.contextmanager
def stops_table(table):
    """Stop the table on every exit that is not a normal return (README "Exit status").

    Ctrl-C, SIGTERM, SIGHUP, a device error or any other exception: feed hold, soft reset, status
    read back (:meth:`GrblTable.stop`), while further signals are ignored; then one line, with exit
    130 for an interrupt (any of the three signals) and the error's own code otherwise."""
    from ..errors import LabctlError
    from .signals import catch_stop_signals, ignore_stop_signals, restore_signals

    old = catch_stop_signals()
    try:
        yield
    except BaseException as exc:
        if isinstance(exc, SystemExit | GeneratorExit):
            raise
        ignore_stop_signals()
        try:
            st = table.stop()
            p = st.position
            stopped = f"table stopped (feed hold, reset) and confirmed {st.state} at X{p[0]:.3f} Y{p[1]:.3f}"
        except Exception as stop_exc:  # noqa: BLE001 — said in the one line, never hidden
            stopped = f"stopping the table FAILED ({type(stop_exc).__name__}: {stop_exc}); cut its power"
        if isinstance(exc, KeyboardInterrupt):
            err = LabctlError(f"interrupted; {stopped}")
            err.exit_code = 130
        elif isinstance(exc, LabctlError):
            err = LabctlError(f"{exc}; {stopped}")
            err.exit_code = exc.exit_code
        else:
            err = LabctlError(f"{type(exc).__name__}: {exc}; {stopped}")
        raise err from None
    finally:
        restore_signals(old)


def _status_dict(table, st) -> dict:
    wpos = table.work_position()
    return {"state": st.state, "position": dict(zip("xyz", st.position)),
            "work_position": dict(zip("xyz", wpos)) if wpos else None,
            "wco": dict(zip("xyz", table.wco)) if table.wco else None, "feed_mm_min": st.feed_mm_min,
            "port": table.link.url, "version": table.info.get("version"), "connected_by": table.connected_by}


def _print_status(d: dict):
    def human(console):
        p = d["position"]
        console.print(f"[bold]{d['state']}[/]  X {p['x']:.3f}  Y {p['y']:.3f}  Z {p['z']:.3f} mm (machine)"
                      f"  (Grbl {d.get('version') or '?'} on {d['port']})")

    return human


@click.group("table")
def table_group() -> None:
    """Drive a GRBL 1.1 table directly (status, home, move, stream, reset)."""


@table_group.command("status")
@_port
@_baud
@_timeout
@json_option
def table_status(port, baud, timeout_s) -> None:
    """The table's state and machine position (mm). Never resets or unlocks the controller."""
    with _open_table(port, baud, timeout_s) as table:
        d = _status_dict(table, table.status())
    emit(d, _print_status(d))


@table_group.command("home")
@_port
@_baud
@_timeout
@json_option
def table_home(port, baud, timeout_s) -> None:
    """Run the homing cycle ($H); --timeout bounds it (default: the lab's homing_timeout_s)."""
    def progress(elapsed):
        click.echo(f"homing… {elapsed:.0f} s", err=True)

    with _open_table(port, baud, None) as table, stops_table(table):
        st = table.home(timeout_s=timeout_s, on_progress=progress, progress_every_s=2.0)
        d = _status_dict(table, st)
    root = get_ctx().lab_root
    d["next"] = f"labctl --lab {root} calibrate"  # a homed table's position is known: calibrate it to the cameras
    show = _print_status(d)
    emit(d, lambda c: (show(c), c.print(f"next: {d['next']}", highlight=False)))


@table_group.command("reset")
@_unlock
@_port
@_baud
@_timeout
@json_option
def table_reset(unlock, port, baud, timeout_s) -> None:
    """Soft reset (Ctrl-X): stop at once and clear a locked alarm; then optionally unlock.

    A reset while the table moves stops it without deceleration: GRBL says ALARM:3 (position lost,
    steps may have been skipped), and this is said on stderr in one line: home before moving."""
    with _open_table(port, baud, timeout_s, reset_if_silent=True) as table:
        table.session_alarm = None  # only what this reset brings
        table.reset()
        lost = table.session_alarm == 3
        if unlock and table.status().state == "Alarm":
            table.unlock()
        d = _status_dict(table, table.status()) | {"position_lost": lost}
    if lost:
        then = ("it was unlocked as asked, but its position is not to be trusted: home it (labctl table home)"
                if unlock else "home it (labctl table home) before moving; `labctl table reset --unlock` only "
                               "if you know where it stands")
        click.echo(f"labctl: warning: the reset stopped the table in motion (GRBL ALARM:3): its position is lost; "
                   f"{then}", err=True)
    emit(d, _print_status(d))


@table_group.command("move", context_settings=_NUMBERS)
@click.argument("x", type=float)
@click.argument("y", type=float)
@click.option("--feed", "feed", type=float, default=None, help="Feed rate, mm/min (default: rapid G0).")
@_unlock
@_port
@_baud
@_timeout
@json_option
def table_move(x, y, feed, unlock, port, baud, timeout_s) -> None:
    """Move to X Y (mm, machine coordinates: G53) and return when the motion has finished."""
    from ..errors import UserInputError

    if feed is not None and not feed > 0:
        raise UserInputError(f"--feed must be positive (mm/min), got {feed}")
    with _open_table(port, baud, timeout_s) as table, stops_table(table):
        table.ensure_ready(unlock=unlock)
        st = table.move_to(x, y, feed)
        d = _status_dict(table, st)
    emit(d, _print_status(d))


@table_group.command("stream")
@click.argument("file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--no-wait", is_flag=True, help="Return once every line is accepted (do not wait for the motion).")
@_unlock
@_port
@_baud
@_timeout
@json_option
def table_stream(file, no_wait, unlock, port, baud, timeout_s) -> None:
    """Stream a G-code FILE by character counting; by default wait until the motion has finished.

    Ctrl-C, SIGTERM or a GRBL error stops the table (feed hold, reset) before exiting."""
    import time

    from ..drivers.programs import load_gcode_numbered

    numbered = load_gcode_numbered(file)
    with _open_table(port, baud, timeout_s) as table, stops_table(table):
        table.ensure_ready(unlock=unlock)
        t0 = time.monotonic()
        sent = table.stream([line for _, line in numbered], line_numbers=[n for n, _ in numbered])
        t_accepted = time.monotonic() - t0
        st = table.status() if no_wait else table.wait_idle(timeout_s=max(table.timeout_s, 3600.0))
        d = _status_dict(table, st) | {"lines": sent, "accepted_s": round(t_accepted, 3),
                                       "total_s": round(time.monotonic() - t0, 3),
                                       "status_reports": table.status_reports}

    def human(console):
        _print_status(d)(console)
        console.print(f"{d['lines']} lines accepted in {d['accepted_s']:.2f} s, done after {d['total_s']:.2f} s")

    emit(d, human)
