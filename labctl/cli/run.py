"""``labctl run``, ``labctl replay`` and ``labctl worker``: the main job."""

from __future__ import annotations

import contextlib
from pathlib import Path

import click

from ..config.lab import TRAJECTORIES
from ..errors import LabctlError, UserInputError
from ._common import emit, get_ctx, json_option, live_console


def _trajectory(value: str, lab=None) -> str:
    if lab is not None and lab.table is None and value != "external":
        raise UserInputError(f"this lab has no table (lab.yaml drivers.table: null): only --trajectory external "
                             f"(parts moved by something labctl does not drive), not {value!r}")
    if value in TRAJECTORIES or value == "external":
        return value
    if Path(value).is_file():
        if lab is not None and lab.table is not None:  # read and checked before any motion or record
            from ..drivers.programs import load_trajectory

            load_trajectory(value, travel_mm=lab.table.travel_mm, max_feed_mm_min=lab.table.max_feed_mm_min)
        return str(Path(value).resolve())
    raise UserInputError(f"--trajectory must be one of {', '.join(TRAJECTORIES)}, external or a G-code file; "
                         f"got {value!r}")


def _speed(value: float | None, lab, trajectory: str | None = None) -> float:
    """The run's table speed (mm/s): ``value`` or lab.yaml's, in (0, 200] and, when labctl drives the table
    (not ``external``), at most the table's maximum feed per axis: GRBL would clamp a faster feed without a word
    where the path runs along an axis (every line, arc and circle program does somewhere), and the run would record
    a speed the table never ran."""
    speed = lab.config.run.speed_mm_s if value is None else value
    if not 0 < speed <= 200:
        raise UserInputError(f"--speed must be in (0, 200] mm/s, got {speed}")
    if trajectory != "external" and lab.table is not None and speed > lab.table.max_feed_mm_min / 60.0 + 1e-9:
        where = lab.driver_paths.get("table", "the table's driver file")
        raise UserInputError(f"--speed {speed:g} mm/s is above the table's maximum feed per axis, "
                             f"{lab.table.max_feed_mm_min / 60.0:g} mm/s ({where}: max_feed_mm_min "
                             f"{lab.table.max_feed_mm_min:g} mm/min)")
    return speed


def _print_result(console, result: dict, run_dir: Path | None) -> None:
    if result.get("identity"):
        line = f"[bold green]identity: {result['identity']}[/]"
        if "true_identity" in result:
            line += f"  (true: {result['true_identity']}, {'correct' if result['correct'] else '[red]WRONG[/]'})"
        console.print(line)
        console.print(f"time to identity {result['time_to_identity_s']:.2f} s, "
                      f"{result['views']} standard view(s), stages: "
                      + ", ".join(f"{k} {v:.2f} s" for k, v in result.get("stages", {}).items()))
    first = (result.get("startup_s") or {}).get("first_tracked_frame")
    if first is not None:
        console.print(f"first tracked frame {first:.2f} s after the command")
    if run_dir is not None:
        console.print(f"record: {run_dir}")


@click.command("run")
@click.option("--trajectory", default=None,
              help="line, arc, circle, zigzag, a G-code FILE, or external: wait for a part moved by something "
                   "labctl does not drive (default: lab.yaml).")
@click.option("--speed", type=float, default=None, help="Table speed, mm/s (default: lab.yaml).")
@click.option("--object", "object_name", default=None, help="Object to place (sim; default: random from the library).")
@click.option("--seed", type=int, default=None, help="Seed of the simulated lab (default: random).")
@click.option("--virtual", is_flag=True, help="Simulated lab in virtual time, one process (as fast as the CPU allows).")
@click.option("--view", is_flag=True,
              help="Serve a live view of the run on a local web page (its URL goes to stderr), with a Stop button.")
@click.option("--view-port", type=click.IntRange(0, 65535), default=None,
              help="The live view's port (default: lab.yaml view.port; 0: any free port).")
@json_option
def run_cmd(trajectory, speed, object_name, seed, virtual, view, view_port) -> int | None:
    """A live run: move the table, track, intercept, pose, standard view, identify."""
    import secrets

    if not virtual:  # the live run's process server imports the workers while this process loads the lab
        from ..runtime.live import warm_up

        warm_up()

    from ..decisions.context import RunContext
    from ..records import RunRecord, write_report
    from ..runtime.live import RunAborted
    from .report import report_gates

    c = get_ctx()
    lab = c.lab()
    trajectory = _trajectory(trajectory or lab.config.run.trajectory, lab)
    spec = {"trajectory": trajectory, "speed_mm_s": _speed(speed, lab, trajectory),
            "object_name": object_name, "seed": secrets.randbelow(2**31) if seed is None else seed}
    if (problem := lab.mixed_kinds_problem()) is not None:
        raise UserInputError(problem)
    ctx = RunContext.load(lab)  # fails early, in one line, without a calibration or a library
    if object_name is not None and object_name not in ctx.library:
        raise UserInputError(f"no object {object_name!r} in the library (have: {', '.join(ctx.names)})")
    if virtual and not lab.is_simulated:
        raise UserInputError("--virtual needs the simulated lab (this lab's drivers point at hardware)")
    if virtual and spec["trajectory"] == "external":
        raise UserInputError("--virtual runs the table itself: --trajectory external needs a live run")
    page = _bind_view(lab, view_port) if view else None  # a taken port: refused before the record is made
    record = RunRecord.create(lab.runs_dir, {"command": "run", "virtual": virtual, **spec})
    if page is not None:  # served until the command ends, result and report included
        _start_view(page, record.path)
        click.get_current_context().call_on_close(page.close)
    try:
        if virtual:
            from ..runtime.virtual import TrialSpec, simulate_run

            result = simulate_run(lab, ctx, TrialSpec(**{k: spec[k] for k in ("trajectory", "speed_mm_s", "seed")},
                                                      object_name=object_name), record)
        else:
            result = _run_live(c, lab, spec, record)
    except RunAborted as exc:  # Ctrl-C, SIGTERM or a dead/hung worker: devices stopped and confirmed
        record.finish({"identity": None, "failure": str(exc), "cause": exc.cause, "devices_stopped": exc.outcomes})
        err = LabctlError(f"{exc}; record kept in {record.path}")
        err.exit_code = exc.exit_code
        raise err from None
    except KeyboardInterrupt:  # before any device moved (or a virtual run: nothing physical)
        record.finish({"identity": None, "failure": "interrupted (Ctrl-C)"})
        err = LabctlError(f"interrupted; record kept in {record.path}")
        err.exit_code = 130
        raise err from None
    except LabctlError as exc:
        record.finish({"identity": None, "failure": str(exc)})
        with contextlib.suppress(Exception):  # a report that cannot be drawn must not hide the error
            write_report(record.path, gates=report_gates(ctx, record.path))
        raise LabctlError(f"{exc} (record: {record.path})") from None
    if not virtual:  # command → first tracked frame, phase by phase
        from ..runtime.live import process_start_wall, startup_seconds

        result["startup_s"] = startup_seconds(result.pop("startup_wall", None) or {}, process_start_wall())
    result["record"] = str(record.path)
    record.finish(result)
    with contextlib.suppress(Exception):  # nor the run's own result
        result["report"] = str(write_report(record.path, gates=report_gates(ctx, record.path)))
    emit(result, lambda con: _print_result(con, result, record.path))
    if not result.get("identity"):
        # the run's expected failure: one line on stderr, with where to look next
        click.echo(f"labctl: error: no identity: {result.get('failure')} (next: labctl report {record.path.name})",
                   err=True)
        return 1
    return None


def _stop_like_ctrl_c() -> None:
    """SIGINT to this process's main thread: the live view's Stop takes Ctrl-C's path (the supervisor stops and
    confirms both devices), from whichever thread the page's request came in on."""
    import signal
    import threading

    main = threading.main_thread().ident
    if main is not None:
        signal.pthread_kill(main, signal.SIGINT)


def _bind_view(lab, port: int | None):
    """The live view's server, its port taken (lab.yaml ``view:``; ``port`` overrides); not serving yet."""
    from ..records.liveview import LiveViewError, LiveViewServer

    cfg = lab.config.view
    try:
        return LiveViewServer(None, cfg.host, cfg.port if port is None else port, on_stop=_stop_like_ctrl_c,
                              poll_s=cfg.poll_s)
    except LiveViewError as exc:
        raise UserInputError(str(exc)) from None


def _start_view(page, run_dir: Path) -> None:
    """Serve the live view of ``run_dir`` (it reads only the record folder) and say its URL on stderr."""
    from ..runtime.snapshot import LIVE_DIR

    (run_dir / LIVE_DIR).mkdir(exist_ok=True)  # asks the predictor for the fixed camera's snapshots
    page.follow(run_dir).start()
    click.echo(f"live view: {page.url}", err=True)


def _run_live(c, lab, spec, record) -> dict:
    from ..runtime.live import WorkerDied, run_live

    con = live_console()  # stdout piped or --json: the live view goes to stderr's terminal, not into the result
    view = _LiveView(con) if con is not None else None
    try:
        if view is None:
            return run_live(lab.root, spec, record.path)
        with view:
            result = run_live(lab.root, spec, record.path, on_status=view.update)
            view.finish(result)
            return result
    except WorkerDied as exc:
        raise LabctlError(str(exc)) from None


class _LiveView:
    """Rich live view: start-up phase, then stage, Kalman estimate, robot state, link traffic.

    Redrawn 8 times a second from the latest status, so the start-up clock runs even before the
    workers' first beat; at the end it shows the result's own link byte counts (those of result.json)."""

    def __init__(self, console):
        import time

        from rich.live import Live

        self.state: dict = {}
        self.t0 = time.monotonic()
        self.live = Live(console=console, refresh_per_second=8, transient=False, get_renderable=self._render)

    def _render(self):
        import time

        from rich.table import Table

        t = Table.grid(padding=(0, 2))
        p = self.state.get("predictor", {})
        if not p:  # no beat from the predictor yet: which start-up phase, and for how long
            phase = self.state.get("startup", {}).get("stage", "starting")
            t.add_row("stage", f"starting: {phase}")
            t.add_row("time", f"{time.monotonic() - self.t0:.1f} s since the command started")
            return t
        est = p.get("estimate")
        t.add_row("stage", str(p.get("stage", "starting")))
        t.add_row("time", f"{p.get('t', 0.0):.2f} s")
        t.add_row("Kalman estimate", "-" if est is None else f"x {est[0]:.1f}  y {est[1]:.1f} mm")
        rob = p.get("robot")
        t.add_row("robot flange", "-" if rob is None else "  ".join(f"{v:.0f}" for v in rob) + " mm")
        link = p.get("link") or {}
        t.add_row("link", f"sent {link.get('sent', 0)} B, received {link.get('received', 0)} B")
        t.add_row("standard views", str(p.get("views", 0)))
        return t

    def finish(self, result: dict) -> None:
        """Show the run's final link byte counts, as recorded in result.json."""
        link = result.get("link") or {}
        p = self.state.setdefault("predictor", {"stage": "done"})
        if "bytes_sent" in link:
            p["link"] = {"sent": link["bytes_sent"], "received": link.get("bytes_received", 0)}
        self.live.refresh()

    def update(self, status: dict) -> None:
        self.state[status["role"]] = status  # drawn by the next refresh (8 Hz)

    def __enter__(self):
        self.live.__enter__()
        return self

    def __exit__(self, *exc):
        return self.live.__exit__(*exc)


@click.command("replay")
@click.argument("run_ref", metavar="RUN")
@json_option
def replay_cmd(run_ref: str) -> None:
    """Re-run the recognizer on a recorded run's images (RUN: an id from ``labctl runs list``, ``last`` or a
    path) and compare with what it decided then."""
    from ..experiments.replay import replay_run
    from .runs import resolve_run

    result = replay_run(get_ctx().lab(), resolve_run(run_ref))

    def human(con):
        con.print(f"recorded identity: {result['recorded_identity']}   replayed: {result['identity']}  "
                  f"({'same' if result['same'] else '[red]different[/]'})")

    emit(result, human)


@click.command("worker")
@click.argument("role", type=click.Choice(["predictor", "recognizer"]))
@click.option("--link", "link", default=None, help="tcp://HOST:PORT or a serial port (default: host_link.yaml).")
@click.option("--trajectory", default=None)
@click.option("--speed", type=float, default=None)
@json_option
def worker_cmd(role, link, trajectory, speed) -> int | None:
    """Run one worker on this host (two PCs: start one of each, linked by TCP or RS-232)."""
    from ..runtime.standalone import run_worker

    lab = get_ctx().lab()
    trajectory = _trajectory(trajectory or lab.config.run.trajectory, lab)
    spec = {"trajectory": trajectory, "speed_mm_s": _speed(speed, lab, trajectory), "object_name": None, "seed": 0}
    result = run_worker(lab, role, spec, link)
    emit(result, lambda con: _print_result(con, result, None) if role == "predictor" else con.print(result["ended"]))
    if role == "predictor" and not result.get("identity"):
        return 1
    return None
