"""``labctl devices`` (check every device) and ``labctl table …`` (drive a GRBL table directly)."""

from __future__ import annotations

from pathlib import Path

import click

from ._common import emit, get_ctx, json_option


@click.command("devices")
@json_option
def devices_cmd() -> int:
    """List the lab's devices, open and identify each, and give a verdict per device."""
    from ..workers.devices import check_devices

    rows = check_devices(get_ctx().lab())

    def human(console):
        from rich.table import Table

        t = Table("role", "kind", "where", "identity", "verdict", title="devices")
        for r in rows:
            style = "green" if r["ok"] else "red"
            t.add_row(r["role"], r["kind"], r["where"], str(r["identity"] or "-"), f"[{style}]{r['verdict']}[/]")
        console.print(t)

    emit({"devices": rows, "ok": all(r["ok"] for r in rows)}, human)
    return 0 if all(r["ok"] for r in rows) else 3


_port = click.option("--port", default=None, help="Device path or pyserial URL (default: the lab's table port).")
_baud = click.option("--baud", type=int, default=None, help="Baud rate (default: the lab's table baud).")
_timeout = click.option("--timeout", "timeout_s", type=float, default=None, help="Reply timeout, s.")


def _open_table(port: str | None, baud: int | None, timeout_s: float | None):
    """The table named by --port/--baud (else the lab's), unopened: use it as ``with _open_table(...) as t``."""
    from ..config import TableConfig
    from ..drivers.grbl import GrblTable
    from ..errors import UserInputError

    cfg = get_ctx().lab().table or TableConfig()  # a lab without a table: --port names one
    port = port or cfg.port
    if not port:
        raise UserInputError("no table port: pass --port PORT (the lab's table is simulated; "
                             "`labctl sim serve` prints a port to use)")
    kw = {"timeout_s": timeout_s} if timeout_s else {}
    return GrblTable(port, baud or cfg.baud, reset_on_open=cfg.reset_on_open, status_hz=cfg.status_hz,
                     **({"timeout_s": cfg.timeout_s} | kw))


def _status_dict(table, st) -> dict:
    wpos = table.work_position()
    return {"state": st.state, "position": dict(zip("xyz", st.position)),
            "work_position": dict(zip("xyz", wpos)) if wpos else None, "feed_mm_min": st.feed_mm_min,
            "port": table.link.url, "version": table.info.get("version"), "connected_by": table.connected_by}


def _print_status(d: dict):
    def human(console):
        p = d["position"]
        console.print(f"[bold]{d['state']}[/]  X {p['x']:.3f}  Y {p['y']:.3f}  Z {p['z']:.3f} mm"
                      f"  (Grbl {d.get('version') or '?'} on {d['port']})")

    return human


@click.group("table")
def table_group() -> None:
    """Drive a GRBL 1.1 table directly (status, home, move, stream)."""


@table_group.command("status")
@_port
@_baud
@_timeout
@json_option
def table_status(port, baud, timeout_s) -> None:
    """The table's state and machine position (mm)."""
    with _open_table(port, baud, timeout_s) as table:
        d = _status_dict(table, table.status())
    emit(d, _print_status(d))


@table_group.command("home")
@_port
@_baud
@_timeout
@json_option
def table_home(port, baud, timeout_s) -> None:
    """Run the homing cycle ($H)."""
    with _open_table(port, baud, timeout_s) as table:
        table.home()
        d = _status_dict(table, table.status())
    emit(d, _print_status(d))


@table_group.command("reset")
@click.option("--unlock", is_flag=True, help="Also leave the Alarm state with $X (no homing).")
@_port
@_baud
@_timeout
@json_option
def table_reset(unlock, port, baud, timeout_s) -> None:
    """Soft reset (Ctrl-X): stop at once and clear a locked alarm; then optionally unlock."""
    with _open_table(port, baud, timeout_s) as table:
        table.reset()
        if unlock and table.status().state == "Alarm":
            table.unlock()
        d = _status_dict(table, table.status())
    emit(d, _print_status(d))


@table_group.command("move")
@click.argument("x", type=float)
@click.argument("y", type=float)
@click.option("--feed", "feed", type=float, default=None, help="Feed rate, mm/min (default: rapid G0).")
@_port
@_baud
@_timeout
@json_option
def table_move(x, y, feed, port, baud, timeout_s) -> None:
    """Move to X Y (mm, absolute) and return when the motion has finished."""
    from ..errors import UserInputError

    if feed is not None and feed <= 0:
        raise UserInputError(f"--feed must be positive (mm/min), got {feed}")
    with _open_table(port, baud, timeout_s) as table:
        table.ensure_ready()
        st = table.move_to(x, y, feed)
        d = _status_dict(table, st)
    emit(d, _print_status(d))


@table_group.command("stream")
@click.argument("file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--no-wait", is_flag=True, help="Return once every line is accepted (do not wait for the motion).")
@_port
@_baud
@_timeout
@json_option
def table_stream(file, no_wait, port, baud, timeout_s) -> None:
    """Stream a G-code FILE by character counting; by default wait until the motion has finished."""
    import time

    from ..drivers.programs import load_gcode

    lines = load_gcode(file)
    with _open_table(port, baud, timeout_s) as table:
        table.ensure_ready()
        t0 = time.monotonic()
        sent = table.stream(lines)
        t_accepted = time.monotonic() - t0
        st = table.status() if no_wait else table.wait_idle(timeout_s=max(table.timeout_s, 3600.0))
        d = _status_dict(table, st) | {"lines": sent, "accepted_s": round(t_accepted, 3),
                                       "total_s": round(time.monotonic() - t0, 3),
                                       "status_reports": table.status_reports}

    def human(console):
        _print_status(d)(console)
        console.print(f"{d['lines']} lines accepted in {d['accepted_s']:.2f} s, done after {d['total_s']:.2f} s")

    emit(d, human)
