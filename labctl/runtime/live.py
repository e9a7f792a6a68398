"""The live runtime: real time, two worker processes and a supervisor (docs/architecture.md "Runtimes", paper §5.1).

```
supervisor (the CLI process)                       — run record, live view, watchdog
 ├─ sim lab server   (simulated lab only)          — world, GRBL + robot emulators on ptys, frame server
 ├─ predictor/planner worker (Host 1)              — fixed camera, Kalman filter, planners, robot + table
 └─ recognizer worker        (Host 2)              — mobile camera, marker pose, matching, library
```

The workers exchange :mod:`~labctl.decisions.messages` over the host link of
``drivers/host_link.yaml``; each also has a control pipe to the supervisor carrying heartbeats
and status for the live view. If a worker dies or stalls (no heartbeat for ``dead_after_s``),
the supervisor stops the robot and the table itself — it opens their ports and sends the
controllers' stop commands — ends the run with one clear line and keeps the record.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any, cast

from ..config import load_lab
from ..decisions import messages as m
from ..drivers.clock import RealClock
from ..errors import DeviceError, LabctlError
from ..timebase import wire_time_s

# forkserver: each process still starts from a clean interpreter (no inherited threads or ports),
# but the heavy imports (scipy.stats via filterpy, trimesh, OpenCV) are paid once, in the server,
# which :func:`warm_up` starts while the command is still loading the lab: the sim lab and both
# workers then fork in milliseconds instead of importing for seconds each.
CTX = mp.get_context("forkserver")
# Not the predictor: its tracking imports filterpy → scipy.stats (~0.5 s CPU), which only the predictor
# needs; it imports them after its fork, beside the simulated lab's set-up, instead of holding up the
# lab's fork. Not trimesh (with scipy.spatial, networkx, ~0.8 s CPU): no process of a run needs it when the
# library's meshes were read before (the simulated lab draws them from the disk cache,
# ``LibraryObject.mesh_arrays``), and a first run imports it in the simulated lab alone
_PRELOAD = ["labctl.runtime.live", "labctl.decisions.recognizer", "labctl.runtime.simlab", "labctl.decisions.context"]


# The status report the table's connection read (Alarm or Idle) stands for its state for this long: only ``$I``
# (which moves nothing) was sent since, and an alarm meanwhile is read and raised anyway; a second ``?`` would
# cost the polling period and a round trip at 9600 bps (~0.15 s). After an unlock a report is always read back.
CONNECT_STATUS_AGE_S = 1.0


def warm_up() -> None:
    """Start the process server with the workers' modules imported, in the background (idempotent)."""
    from multiprocessing import forkserver

    CTX.set_forkserver_preload(_PRELOAD)
    if not _in_main_thread():
        forkserver.ensure_running()
        return
    # The server is started ignoring the stop signals (kept across its exec). A signal to the whole
    # process group (timeout, systemd, docker stop) would otherwise end it, and a dead server makes
    # every process it started look exited (exit code 255) while the workers still stop their devices.
    # It needs no signal: it exits by itself when this process does.
    with _ignoring({signal.SIGINT, signal.SIGTERM, signal.SIGHUP}):
        forkserver.ensure_running()


@contextlib.contextmanager
def _ignoring(sigs: set[signal.Signals]):
    """Ignore ``sigs`` meanwhile (a child started now inherits that); one arriving meanwhile is blocked,
    so it waits and is delivered on the way out, not lost. Main thread only."""
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    old = {sig: signal.signal(sig, signal.SIG_IGN) for sig in sigs}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)


def process_start_wall() -> float | None:
    """Unix time (s, ±10 ms) this process started — the command's start, for start-up timing — from
    /proc (Linux); None elsewhere."""
    try:
        stat = Path("/proc/self/stat").read_text()
        start_ticks = int(stat.rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return time.time() - (uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return None


def startup_seconds(marks: dict, t_command: float | None) -> dict:
    """The start-up phases (wall times) as seconds after the command started, in order."""
    if not marks or t_command is None:
        return {}
    return {k: round(v - t_command, 3) for k, v in sorted(marks.items(), key=lambda kv: kv[1])}


@dataclass
class WorkerArgs:
    """Everything a worker process needs (picklable)."""

    role: str
    lab_root: str
    run_dir: str | None
    spec: dict
    origin: float  # the shared clock's origin on CLOCK_MONOTONIC (s)
    table_port: str | None = None
    robot_port: str | None = None
    frame_server: tuple | None = None  # (address, authkey)
    extra: dict = field(default_factory=dict)
    # forked before the simulated lab is ready: its ports and the run clock's origin come by the control pipe
    await_endpoints: bool = False
    # the devices' replies give times on the run's clock: only the simulated lab's, whose origin it sent
    shared_clock: bool = False


def _endpoints(args: WorkerArgs, ctl, timeout_s: float = 60.0, ports_first: bool = False) -> WorkerArgs:
    """``args`` with the simulated lab's ports, frame server and clock origin filled in, once the
    supervisor sends them (``("endpoints", dict)`` on the control pipe); unchanged if they came with
    ``args``. A worker forked early loads its lab, calibration and library while the simulated lab
    starts, and opens no device before this returns. ``ports_first``: the devices' ports and the origin
    alone (``("ports", dict)``, sent while the lab still builds its world) will do; ``await_endpoints``
    stays set, and a second call waits for the rest (the frame server)."""
    if not args.await_endpoints:
        return args
    deadline = time.monotonic() + timeout_s
    conn = ctl.conn
    while time.monotonic() < deadline:
        if _process_gone(ctl.supervisor_pid):
            raise PeerLost("the supervisor is gone (its process exited)")
        try:
            if not conn.poll(0.05):
                continue
            msg = conn.recv()
        except (EOFError, OSError):
            raise PeerLost("the supervisor is gone (control pipe closed)") from None
        if msg and (msg[0] == "endpoints" or (ports_first and msg[0] == "ports")):
            ep = msg[1]
            return dataclasses.replace(args, table_port=ep.get("table"), robot_port=ep.get("robot"),
                                       frame_server=ep.get("frame_server"), origin=ep["origin"],
                                       await_endpoints=msg[0] != "endpoints", shared_clock=True)
    raise PeerLost(f"the simulated lab's ports did not come within {timeout_s:g} s")


EXIT_INTERRUPTED = 130  # SIGINT (Ctrl-C)
EXIT_TERMINATED = 143  # SIGTERM: 128 + 15, as a shell reports it
EXIT_HANGUP = 129  # SIGHUP (the terminal closed, a session ended): 128 + 1
EXIT_DEVICE = 3  # a device, the host link or the peer failed


class Terminated(BaseException):
    """SIGTERM or SIGHUP, raised in the main thread as Python raises KeyboardInterrupt for SIGINT."""

    def __init__(self, signum: int = signal.SIGTERM):
        super().__init__(signum)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        """128 + the signal's number, as a shell reports it: 143 for SIGTERM, 129 for SIGHUP."""
        return EXIT_HANGUP if self.signum == signal.SIGHUP else EXIT_TERMINATED

    @property
    def what(self) -> str:
        """How the run ended, in words."""
        return "hung up (SIGHUP)" if self.signum == signal.SIGHUP else "terminated (SIGTERM)"


def _raise_terminated(signum, frame):
    raise Terminated(signum)


class PeerLost(LabctlError):
    """The other worker or the supervisor went silent or away: stop our devices and leave."""

    exit_code = EXIT_DEVICE


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _shield() -> None:
    """Ignore further SIGINT/SIGTERM/SIGHUP: the stop path itself must run to its end."""
    if _in_main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, signal.SIG_IGN)


def _supervisor_pid() -> int:
    """The pid of the process that created this one (the supervisor). Not ``os.getppid()``: under
    forkserver the parent is the process server, which a signal to the whole process group ends
    while the supervisor is still stopping and confirming the devices."""
    parent = mp.parent_process()
    return parent.pid if parent is not None and parent.pid is not None else os.getppid()


def _process_gone(pid: int) -> bool:
    """Whether process ``pid`` has exited (no such process, or a zombie waiting to be reaped)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except (OSError, IndexError):
        return False


def _alive(p) -> bool:
    """Whether a child process still runs, by its pid. ``Process.is_alive()`` asks the process server,
    and a server that died makes every process it started look exited while it still runs."""
    return p.pid is not None and not _process_gone(p.pid)


def _kill(p, sig: int = signal.SIGKILL) -> None:
    """Send ``sig`` to a child by its pid (``Process.kill()`` does nothing once it thinks it exited)."""
    if p.pid is not None:
        with contextlib.suppress(ProcessLookupError):
            os.kill(p.pid, sig)


def _join(p, timeout_s: float) -> bool:
    """Wait up to ``timeout_s`` for a child to exit, by its pid too; True once it has."""
    deadline = time.monotonic() + timeout_s
    p.join(timeout=timeout_s)
    while _alive(p) and time.monotonic() < deadline:
        time.sleep(0.02)
    return not _alive(p)


def _child_signals(supervised: bool) -> None:
    """A worker's signals. Under a supervisor SIGINT is ignored (Ctrl-C reaches the whole process
    group; the supervisor alone answers it); SIGTERM and SIGHUP raise :class:`Terminated` so the worker stops
    its own devices on the way out. Children start with both blocked (see :func:`_start_quietly`)."""
    if not _in_main_thread():
        return
    signal.signal(signal.SIGTERM, _raise_terminated)
    signal.signal(signal.SIGHUP, _raise_terminated)
    signal.signal(signal.SIGINT, signal.SIG_IGN if supervised else signal.default_int_handler)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM, signal.SIGHUP})


def _start_quietly(proc) -> None:
    """Start a child process that ignores SIGINT and SIGTERM from its first instruction.

    The child inherits ignored dispositions and the blocked mask across fork and exec, so a
    Ctrl-C to the process group while it imports cannot print a traceback; a signal arriving
    at the supervisor meanwhile stays pending and is delivered as soon as the child is started."""
    if not _in_main_thread():
        proc.start()
        return
    with _ignoring({signal.SIGINT, signal.SIGTERM}):
        proc.start()


class PeerWatch:
    """Silence of the other worker on the host link (paper §5.1: two hosts, one RS-232 line).

    Any message counts as a sign of life. Before the first one the peer may take up to
    ``start_timeout_s`` (imports, device opening); after it, ``dead_after_s`` of silence means the
    peer is dead or hung. ``clock`` is injectable (s)."""

    def __init__(self, peer: str, dead_after_s: float, start_timeout_s: float, clock=time.monotonic):
        self.peer, self.dead_after_s, self.start_timeout_s, self.clock = peer, dead_after_s, start_timeout_s, clock
        self.t0 = clock()
        self.t_last: float | None = None
        self.max_gap_s = 0.0

    def heard(self) -> None:
        """Note a message from the peer now (and the longest gap so far)."""
        now = self.clock()
        if self.t_last is not None:
            self.max_gap_s = max(self.max_gap_s, now - self.t_last)
        self.t_last = now

    def lost(self) -> str | None:
        """Why the peer counts as lost, or None while it is alive."""
        now = self.clock()
        if self.t_last is None:
            if now - self.t0 > self.start_timeout_s:
                return f"the {self.peer} worker never answered within {self.start_timeout_s:g} s"
            return None
        if now - self.t_last > self.dead_after_s:
            silent = now - self.t_last
            return f"the {self.peer} worker went silent ({silent:.1f} s > dead_after_s {self.dead_after_s:g} s)"
        return None


class _Control:
    """The worker's end of its control pipe: heartbeats and status to the supervisor, and the
    supervisor's own heartbeats back (a worker whose supervisor dies or hangs stops its devices)."""

    supervised = True

    def __init__(self, conn, role: str, dead_after_s: float = 2.0):
        self.conn, self.role, self.seq = conn, role, 0
        self.t_last = 0.0
        self.dead_after_s = dead_after_s
        self.supervisor_pid = _supervisor_pid()
        self.t_supervisor: float | None = None

    def beat(self, now: float, status: dict | None = None, period: float = 0.1) -> None:
        if now - self.t_last < period and status is None:
            return
        self.t_last = now
        self.seq += 1
        with contextlib.suppress(OSError, BrokenPipeError):
            self.conn.send(("beat", self.role, self.seq, now, status))

    def send(self, *msg) -> None:
        with contextlib.suppress(OSError, BrokenPipeError):
            self.conn.send(msg)

    def supervisor_lost(self) -> str | None:
        """Why the supervisor counts as gone (pipe closed, parent exited, silent), or None."""
        try:
            while self.conn.poll(0):
                msg = self.conn.recv()
                if msg and msg[0] == "beat":
                    self.t_supervisor = time.monotonic()
        except (EOFError, OSError):
            return "the supervisor is gone (control pipe closed)"
        if _process_gone(self.supervisor_pid):
            return "the supervisor is gone (its process exited)"
        if self.t_supervisor is not None and time.monotonic() - self.t_supervisor > self.dead_after_s:
            return f"the supervisor went silent ({time.monotonic() - self.t_supervisor:.1f} s)"
        return None


def _load_lab(args: WorkerArgs):
    """The lab as the worker sees it (a standalone worker may override the host link)."""
    import dataclasses

    from ..config import HostLinkConfig

    lab = load_lab(args.lab_root)
    if "host_link" in args.extra:
        lab = dataclasses.replace(lab, host_link=HostLinkConfig(**args.extra["host_link"]))
    return lab


def plausible(msg: m.Message, ctx) -> bool:
    """Whether a message from the recognizer names only objects of this library (a corrupt or foreign
    message that decodes is dropped here, before the planner sees it)."""
    n = len(ctx.names)
    if isinstance(msg, m.Identity):
        return msg.object_id < n and all(i < n for i in msg.candidates)
    if isinstance(msg, m.Ambiguous):
        return all(i < n for i in msg.candidates)
    return True


def _authkey(args: WorkerArgs, lab) -> bytes | None:
    """The TCP link's shared key: one the supervisor made for this run, else the lab's (env or file)."""
    from .transport import link_key

    key = args.extra.get("link_key")
    return key.encode() if key else link_key(lab.host_link, lab.root)


class _RecordLog(logging.Handler):
    """Driver and link warnings go to the run record as ``log`` events, not to the terminal: a run
    ends with exactly one line on stderr (a port another process left mid-conversation yields
    stale replies that a driver rightly warns about)."""

    def __init__(self, record, role: str):
        super().__init__(logging.INFO)
        self.record, self.role = record, role

    def emit(self, rec: logging.LogRecord) -> None:
        with contextlib.suppress(Exception):
            self.record.event("log", role=self.role, level=rec.levelname, logger=rec.name, message=rec.getMessage())


def _log_to_record(record, role: str):
    """Route the ``labctl`` loggers to ``record`` (unless -v gave the root logger a handler)."""
    lg = logging.getLogger("labctl")
    if record is None or logging.getLogger().handlers:
        return None
    handler = _RecordLog(record, role)
    lg.addHandler(handler)
    return handler


def _exit_reason(role: str, exc: BaseException) -> tuple[int, str]:
    """A worker's exit status and one-line reason for how it left."""
    from .transport import LinkClosed

    if isinstance(exc, Terminated):
        return exc.exit_code, f"{role}: {exc.what}"
    if isinstance(exc, KeyboardInterrupt):
        return EXIT_INTERRUPTED, f"{role}: interrupted"
    if isinstance(exc, PeerLost):
        return EXIT_DEVICE, f"{role}: {exc}"
    if isinstance(exc, LinkClosed):
        return EXIT_DEVICE, f"{role}: the host link closed ({exc})"
    return getattr(exc, "exit_code", 1), f"{role}: {type(exc).__name__}: {exc}"


def _device_code(exc: BaseException, code: int) -> int | None:
    """The exit status a worker reports to its supervisor for the run's own: a device's fault
    (3) decides it; other causes (a peer lost, a crash) leave it to the supervisor (1)."""
    return code if isinstance(exc, DeviceError) else None


def _release(log, role: str, reason: str, *, stop: dict, close=(), link=None, tell_peer: bool = False,
             t: float | None = None, clear_robot: bool = False) -> list[dict]:
    """A worker's exit path: stop and confirm each moving device (every one is tried, every outcome
    recorded), tell the peer why when leaving abnormally, close everything; never raises.
    ``t`` is when the stop began on the run's clock (s), for the record. ``clear_robot``: the run
    ended by itself, so the STOP it latched is its own — cleared once the arm is confirmed still
    (after any other exit the latch stays for the operator: ``labctl robot clear``)."""
    from .stopping import clear_own_stop, close_all, stop_devices

    _shield()
    outcomes = stop_devices(stop)
    if clear_robot and stop.get("robot") is not None:
        clear_own_stop(stop["robot"], next(o for o in outcomes if o["device"] == "robot"))
    if tell_peer and link is not None:
        with contextlib.suppress(Exception):
            link.send(m.Stop.short(reason))
    errors = close_all([*close, link])
    with contextlib.suppress(Exception):  # the record may be what failed
        log("devices_stopped", role=role, t=t, reason=reason, outcomes=outcomes, close_errors=errors)
    return outcomes


def _open_record(args: WorkerArgs):
    if args.run_dir is None:
        return None
    from ..records import RunRecord

    return RunRecord.open(args.run_dir)


def _camera(args: WorkerArgs, lab, role: str):
    """The worker's camera: the sim lab's frame server, else the driver file's camera stamping
    frames on the run's clock (s since ``args.origin``)."""
    from .devices import open_device

    if args.frame_server is not None:
        from ..sim.camera import FrameClient

        return FrameClient(args.frame_server[0], role, args.frame_server[1])
    origin = args.origin
    return open_device(f"{role}_camera", lab, clock=RealClock(origin=origin).now)


def _fixed_camera(args: WorkerArgs, lab):
    from .snapshot import maybe_snapshots  # the live view's JPEG, when the record asks for one

    view = lab.config.view
    return maybe_snapshots(_camera(args, lab, "fixed"), args.run_dir, view.fixed_snapshot_period_s,
                           view.fixed_snapshot_width)


def _mobile_camera(args: WorkerArgs, lab):
    return _camera(args, lab, "mobile")


def predictor_main(args: WorkerArgs, link_end, control) -> int:
    """Host 1's process: fixed camera → Kalman filter → planners → robot and table.

    Returns its exit status (0 ok, 1 job failed, 3 device/peer lost, 130/143 interrupted). On every
    way out it stops the robot and the table and records each outcome (``devices_stopped``)."""
    from ..drivers.grbl import GrblTable
    from ..drivers.robot import SerialRobot
    from .devices import check_robot_limits
    from .simlab import trajectory_program
    from .transport import open_link

    ctl = control
    lab = _load_lab(args)
    hl = lab.host_link
    record = _open_record(args)
    log = record.event if record is not None else (lambda *a, **k: None)
    log("worker_started", role="predictor", pid=os.getpid())
    _log_to_record(record, "predictor")
    table = robot = camera = link = planner = None
    code, reason, report_code = 0, "run finished", None
    alive = {"hello": False, "t_link": 0.0}
    run_clock = RealClock(origin=args.origin)  # the run's clock: s since the origin all its processes share

    def keep_alive(robot_too: bool = True) -> None:
        """While a device's link is being reconnected (the loop waits): feed the robot's watchdog
        (unless its link is the one down), and beat to the peer and the supervisor, so the
        reconnect window, not their silence limits, decides how the run ends."""
        now = run_clock.now()
        if robot_too and robot is not None and robot.link.is_open:
            robot.maybe_heartbeat()
        if alive["hello"] and now - alive["t_link"] >= hl.heartbeat_s:
            assert link is not None  # the peer said hello on it
            link.send(m.Heartbeat(role="predictor", seq=int(now * 10) % 65536, t=now))
            alive["t_link"] = now
        ctl.beat(now, {"stage": "reconnecting"})

    marks = {"predictor_started": time.time()}  # start-up phases, wall clock (command → first tracked frame)

    def load_context():
        # CPU: the planner's imports (tracking → filterpy → scipy.stats, ~0.5 s) and the calibration and
        # library; in a thread, while the main thread waits for the ports and opens the devices (I/O)
        from ..decisions.context import RunContext
        from ..decisions.predictor import PredictorPlanner  # noqa: F401 — imported here, off the critical path

        out = RunContext.load(lab)
        marks["predictor_context_loaded"] = time.time()
        return out

    starting = ThreadPoolExecutor(2, thread_name_prefix="labctl-predictor-start")
    try:
        ctx_job = starting.submit(load_context)
        link = open_link(hl, "predictor", local_end=link_end, authkey=_authkey(args, lab),
                         on_refused=lambda line: log("link_refused", line=line))
        args = _endpoints(args, ctl, ports_first=True)  # the table's and the robot's ports may come first
        run_clock = RealClock(origin=args.origin)
        marks["endpoints"] = time.time()
        # the sim lab's ports when it serves them, else the driver files' (None keeps the file's port);
        # no table to drive when the parts move by something else (--trajectory external)
        external = args.spec["trajectory"] == "external" or lab.table is None
        tcfg = lab.table
        if tcfg is not None and tcfg.kind == "sim":
            # the simulated board sits on a pty: opening it toggles no DTR, so nothing resets it and
            # there is no boot to wait out before the first status query (0.3 s saved)
            tcfg = dataclasses.replace(tcfg, reset_on_open=False)
        table = None if external else GrblTable.from_config(tcfg, port=args.table_port)
        robot = SerialRobot.from_config(lab.robot, port=args.robot_port)

        robot_checked, robot_ok = threading.Event(), threading.Event()

        def table_ready() -> None:
            # a simulated table's power-up lock may be released (the simulator knows where it is); a real
            # table in Alarm must be homed or unlocked by the operator first (its position may be lost)
            assert table is not None  # submitted only with a table
            table.open()
            marks["table_connected"] = time.time()
            st = table.ensure_ready(unlock=lab.table.kind == "sim", max_age_s=CONNECT_STATUS_AGE_S)
            marks["table_unlocked"] = time.time()
            robot_checked.wait()  # the robot's limits first: a run that cannot go on moves nothing
            if robot_ok.is_set():
                _to_start(table, lab.config.run.trajectory_start_mm.get(args.spec["trajectory"]), log,
                          run_clock.now, status=st)
            marks["table_ready"] = time.time()

        # The table's connection (board reset, banner, sync, $I, unlock: ~1 s of 9600-bps round trips)
        # runs beside the robot's and the camera's, not before them. No
        # keep-alive while opening: nothing moves yet, and the two threads must not share a port.
        table_job = starting.submit(table_ready) if table is not None else None
        try:
            robot.open()
            robot_rest = robot.ensure_ready()
            check_robot_limits(robot, lab)  # before anything moves: the plans must be ones it accepts
            from ..decisions.segment_defaults import set_segment_defaults  # light: not the planner's import

            set_segment_defaults(robot, lab)  # dialect 1.4: once, before the run's clock starts
            marks["robot_ready"] = time.time()
            args = _endpoints(args, ctl)  # the frame server: the simulated lab is ready
            # the origin every ``t`` of the record is on; logged once the lab is ready, as before the ports came
            # early, so that the record still opens with both workers' ``worker_started``
            log("run_clock", role="predictor", origin=args.origin)
            camera = _fixed_camera(args, lab)
            camera.open()
            robot_ok.set()  # the table goes to its start only now, as before: robot checked, lab ready
            marks["robot_and_camera_ready"] = time.time()
        finally:
            robot_checked.set()
            if table_job is not None:
                table_job.result()  # the table's own error, if it had one, comes out here
        ctx = ctx_job.result()
        starting.shutdown()
        from ..decisions.predictor import PredictorPlanner, ProgramProgress

        if table is not None:
            table.while_reconnecting = keep_alive
        robot.while_reconnecting = lambda: keep_alive(robot_too=False)
        now = run_clock.now()
        planner = PredictorPlanner(ctx, robot, link.send, log, t_start=now, clock=run_clock.now,
                                   rest=robot_rest, shared_clock=args.shared_clock,
                                   family=None if table is None else args.spec["trajectory"])
        progress = None
        if table is not None:
            # streamed from the loop: a long G2/G3 is acknowledged only when it leaves GRBL's planner
            program = table.start_program(
                trajectory_program(args.spec["trajectory"], args.spec["speed_mm_s"], lab)[1])
            log("table_program", t=now, trajectory=args.spec["trajectory"], speed_mm_s=args.spec["speed_mm_s"],
                lines=program.total)
            progress = ProgramProgress(program, log)
        else:
            log("table_program", t=now, trajectory=args.spec["trajectory"], speed_mm_s=args.spec["speed_mm_s"])
        peer = PeerWatch("recognizer", hl.dead_after_s, hl.start_timeout_s)
        t_beat, hello = 0.0, False
        early = None  # a run that drives the table fails early, with the cause (run.no_marker_s, after_program_s)
        if progress is not None:
            from .early_end import EarlyEnd, program_ended

            early = EarlyEnd(lab.config.run.no_marker_s, lab.config.run.after_program_s, t0=now)
        while not planner.finished:
            if progress is not None:
                progress.pump(run_clock.now())
            # once tracking, also the frames exposed while the loop was busy (a robot command's round trip);
            # before, the newest only, as the virtual run (docs/notes/planning.md, "Frames caught up")
            catch_up = lab.config.run.catch_up_frames if planner.t_first_seen is not None else 1
            planner.on_frames(camera.grab_recent(catch_up))
            if "first_tracked_frame" not in marks and planner.t_first_seen is not None:
                marks["first_tracked_frame"] = time.time()
                log("startup", marks=marks)
            while True:
                msg = link.recv(timeout=0)
                if msg is None:
                    break
                peer.heard()
                if isinstance(msg, m.Stop):
                    raise PeerLost(f"the recognizer stopped: {msg.reason}")
                if not isinstance(msg, m.Heartbeat | m.Hello):
                    if plausible(msg, ctx):
                        planner.on_message(msg, run_clock.now())
                    else:
                        log("message_dropped", t=run_clock.now(), message=repr(msg)[:200])
            now = run_clock.now()
            planner.tick(now)
            if early is not None and progress is not None and table is not None and not planner.finished:
                if early.t_program_end is None and program_ended(progress.program, table):
                    early.program_ended(now)
                    log("table_program_ended", t=now)
                if (why := early.check(now, waiting=planner.stage == "wait")) is not None:
                    planner.fail(now, why)
            if not hello:  # the first message starts the peer's dead_after_s clock: only once the loop runs
                link.send(m.Hello(role="predictor", pid=os.getpid()))
                hello = alive["hello"] = True
            due = now - t_beat - lab.robot.heartbeat_s  # s since the beat was due (>= 0: due)
            if due >= 0.0 and not planner.heartbeat_can_wait(now, due):
                robot.heartbeat()
                link.send(m.Heartbeat(role="predictor", seq=int(now * 10) % 65536, t=now))
                t_beat = now
            lost = peer.lost() or ctl.supervisor_lost()
            if lost:
                raise PeerLost(lost)
            est = planner.tracker.estimate()[0].tolist() if planner.tracker.initialized else None
            ctl.beat(now, {"stage": planner.stage, "estimate": est, "views": planner.views_used,
                           "link": {"sent": link.bytes_sent, "received": link.bytes_received},
                           "robot": planner.robot_path[-1][1] if planner.robot_path else None})
        result = planner.result(run_clock.now())
        if record is not None and result.get("identity") is None:  # the report leads with the camera's last frame
            with contextlib.suppress(Exception):
                record.save_image("fixed_last", camera.grab().image)
        result["startup_wall"] = marks
        link.send(m.Stop(reason="run finished"))
        result["link"] = {**link.stats(), "baud": hl.baud, "duration_s": run_clock.now() - planner.t_start}
        result["link"]["max_peer_gap_s"] = round(peer.max_gap_s, 3)
        if hl.transport == "serial":
            busy = wire_time_s(max(link.bytes_sent, link.bytes_received), hl.baud)  # full duplex: the busier direction
            result["link"]["utilisation"] = busy / max(result["link"]["duration_s"], 1e-9)
        ctl.send("result", result)
    except BaseException as exc:  # every way out, SIGTERM and Ctrl-C included, ends in the stop below
        code, reason = _exit_reason("predictor", exc)
        report_code = _device_code(exc, code)
        if code not in (EXIT_INTERRUPTED, EXIT_TERMINATED, EXIT_HANGUP) and not isinstance(exc, PeerLost):
            with contextlib.suppress(Exception):
                log("worker_error", role="predictor", error=reason, traceback=traceback.format_exc())
    finally:
        starting.shutdown(wait=False, cancel_futures=True)
        outcomes = _release(log, "predictor", reason, stop={"robot": robot, "table": table},
                            close=(camera, robot, table), link=link, tell_peer=code != 0, t=run_clock.now(),
                            clear_robot=code == 0 and planner is not None and planner.finished)
        from .stopping import summary

        if code != 0:  # a supervisor confirms the stop itself and says so; a lone worker says it here
            ctl.send("error", reason if ctl.supervised else f"{reason}; {summary(outcomes)}",
                     report_code)
        ctl.send("stopped", outcomes)
        if record is not None:
            record.close()
    return code


def _to_start(table, start_xy: tuple[float, float] | None, log, now, status=None) -> None:
    """Bring the table to a named trajectory's start (lab.yaml ``run.trajectory_start_mm``) and wait
    there, before tracking begins: a table left elsewhere (after ``labctl calibrate``, say) would
    otherwise carry the object into view on the program's rapid move, which the tracker cannot tell
    from the object's own motion. A G-code file (``start_xy`` None) starts where its own first move
    goes. ``status``: the table's status just read (Idle), to spare another 9600-bps round trip."""
    if start_xy is None:
        return
    x, y = start_xy
    p = (status or table.status()).position
    if abs(p[0] - x) < 0.5 and abs(p[1] - y) < 0.5:
        return
    log("table_to_start", t=now(), start=[x, y], was=list(p[:2]))
    table.stream(["G21G90", f"G0X{x:.3f}Y{y:.3f}"])
    table.wait_idle(timeout_s=60.0)


def recognizer_main(args: WorkerArgs, link_end, control) -> int:
    """Host 2's process: mobile camera → marker pose → standard-view matching. Returns its exit status."""
    from ..decisions.context import RunContext
    from ..decisions.recognizer import Recognizer
    from .transport import open_link

    ctl = control
    lab = _load_lab(args)
    hl = lab.host_link
    record = _open_record(args)
    log = record.event if record is not None else (lambda *a, **k: None)
    # the images go to disk in a thread: a reply does not wait for a PNG encode and an fsync
    images = record.image_writer() if record is not None else None
    save = images.save if images is not None else None
    log("worker_started", role="recognizer", pid=os.getpid())
    _log_to_record(record, "recognizer")
    camera = link = None
    code, reason, report_code = 0, "run finished", None
    run_clock = RealClock(origin=args.origin)  # the run's clock: s since the origin all its processes share
    try:
        ctx = RunContext.load(lab)
        link = open_link(hl, "recognizer", local_end=link_end, authkey=_authkey(args, lab),
                         on_refused=lambda line: log("link_refused", line=line))
        args = _endpoints(args, ctl)
        run_clock = RealClock(origin=args.origin)
        log("run_clock", role="recognizer", origin=args.origin)
        camera = _mobile_camera(args, lab)
        camera.open()
        recognizer = Recognizer(ctx, camera.grab, log, save)
        link.send(m.Hello(role="recognizer", pid=os.getpid()))
        peer = PeerWatch("predictor", hl.dead_after_s, hl.start_timeout_s)
        t_beat = 0.0
        while True:
            msg = link.recv(timeout=0.05)
            now = run_clock.now()
            if msg is not None:
                peer.heard()
            if isinstance(msg, m.Stop):
                reason = f"the predictor stopped the run ({msg.reason})"
                break
            if msg is not None and not isinstance(msg, m.Heartbeat | m.Hello):
                for reply in recognizer.handle(msg):
                    link.send(reply)
            now = run_clock.now()
            if now - t_beat >= hl.heartbeat_s:
                link.send(m.Heartbeat(role="recognizer", seq=int(now * 10) % 65536, t=now))
                t_beat = now
            lost = peer.lost() or ctl.supervisor_lost()
            if lost:
                raise PeerLost(lost)
            ctl.beat(now)
    except BaseException as exc:
        code, reason = _exit_reason("recognizer", exc)
        report_code = _device_code(exc, code)
        if code not in (EXIT_INTERRUPTED, EXIT_TERMINATED, EXIT_HANGUP) and not isinstance(exc, PeerLost):
            with contextlib.suppress(Exception):
                log("worker_error", role="recognizer", error=reason, traceback=traceback.format_exc())
    finally:
        _release(log, "recognizer", reason, stop={}, close=(camera,), link=link, tell_peer=code != 0,
                 t=run_clock.now())
        if images is not None:
            try:
                images.close()
            except Exception as exc:  # the run's images are the record's: a lost one is said, never silent
                with contextlib.suppress(Exception):
                    log("worker_error", role="recognizer", error=f"record: {exc}", traceback="")
        if code != 0:
            ctl.send("error", reason, report_code)
        if record is not None:
            record.close()
    return code


def _worker_process(role: str, args: WorkerArgs, link_end, conn) -> None:
    """Entry point of a supervised worker process: signals, then the worker; exits with its status."""
    _child_signals(supervised=True)
    target = predictor_main if role == "predictor" else recognizer_main
    try:
        lab_link = load_lab(args.lab_root).host_link
        code = target(args, link_end, _Control(conn, role, lab_link.dead_after_s))
    except BaseException as exc:  # before the worker's own handlers (lab, record): one line via the supervisor
        code, reason = _exit_reason(role, exc)
        with contextlib.suppress(Exception):
            conn.send(("error", reason, _device_code(exc, code)))
    sys.exit(code)


def _quietly(write: Callable[[], object]) -> None:
    """``write()``; a record that cannot take it does not stop the simulated lab."""
    with contextlib.suppress(Exception):
        write()


def sim_server_main(lab_root: str, spec: dict, conn, run_dir: str | None = None) -> None:
    """The simulated lab for a live run: world + emulators on ptys + frame server, in real time.

    Answers the supervisor's ``"state?"`` (are the robot and table moving, since when still),
    ``"truth?"`` (the simulator's ground truth) and ``"stop"``. Like real hardware it ignores
    SIGINT/SIGTERM/SIGHUP aimed at the controller; if the supervisor vanishes it keeps simulating until
    the robot and table have been still for a second (at most 10 s), so that the workers can stop
    them and the record keeps the ground truth of when they did."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    from ..sim.lab import TruthLogger
    from .simlab import LiveSimLab

    record = None
    if run_dir is not None:
        from ..records import RunRecord

        record = RunRecord.open(run_dir)
    # the record opens with the workers' own events: ground truth waits for the supervisor's "record"
    pending: list[tuple[str, dict]] = []
    live_log = record.event if record is not None else (lambda *a, **k: None)
    logging_on = {"on": False}  # the supervisor said "record": ground truth goes to the record from then on

    def log(name, **fields):
        if pending is not None and not logging_on["on"]:
            pending.append((name, fields))
            del pending[:-200]
        else:
            live_log(name, **fields)

    def start_logging():
        logging_on["on"] = True
        for name, fields in pending:
            live_log(name, **fields)
        pending.clear()

    supervisor = _supervisor_pid()
    try:
        served = LiveSimLab(load_lab(lab_root), spec)
        served.warm_on_enter = False  # the first renders overlap the workers' device connections
        served.on_ports = lambda ports: conn.send(("ports", ports))  # the devices connect while the world is built
        with served as sim:
            conn.send(("ready", sim.endpoints()))
            sim.warm_up()
            # the record holds changes only, each with the robot's latest stop ramp (labctl.sim.lab.TruthLogger)
            truth = TruthLogger(sim.sim, lambda line: _quietly(lambda: log("sim_truth", **line)), first_line=False,
                                ramp_is_change=False)
            orphaned = None
            while True:
                state = truth.sample()
                if orphaned is not None:
                    start_logging()
                    if truth.still_for() > 1.0 or time.monotonic() - orphaned > 10.0:
                        log("sim_stopped", t=state["t"], reason="supervisor gone", **{
                            k: state[k] for k in ("robot_moving", "table_moving", "table_state")})
                        return
                    time.sleep(0.02)
                    continue
                try:
                    if not conn.poll(0.02):
                        if _process_gone(supervisor):
                            orphaned = time.monotonic()
                        continue
                    req = conn.recv()
                except (EOFError, OSError):
                    orphaned = time.monotonic()
                    continue
                if req == "record":
                    start_logging()
                elif req == "state?":
                    start_logging()
                    conn.send(("state", state))
                elif req == "truth?":
                    conn.send(("truth", sim.truth()))
                else:
                    return
    except (EOFError, OSError):
        return
    except Exception as exc:
        with contextlib.suppress(OSError):
            conn.send(("error", f"sim lab: {type(exc).__name__}: {exc}"))
    finally:
        if record is not None:
            record.close()


def _sim_says(conn, kinds: tuple[str, ...] = ("ports", "ready"), timeout_s: float = 60.0) -> tuple[str, dict]:
    """The simulated lab's next start-up message, ``("ports", …)`` or ``("ready", …)`` (its endpoints); WorkerDied
    when it reports an error, sends something else or says nothing for ``timeout_s``."""
    if not conn.poll(timeout_s):
        raise WorkerDied(f"the simulated lab did not start within {timeout_s:g} s")
    try:
        kind, payload = conn.recv()
    except (EOFError, OSError):
        raise WorkerDied("the simulated lab exited while starting") from None
    if kind not in kinds:
        raise WorkerDied(str(payload))
    return kind, payload


def _ask(conn, request: str, timeout_s: float = 5.0):
    with contextlib.suppress(OSError, EOFError):
        conn.send(request)
        if conn.poll(timeout_s):
            return conn.recv()[1]
    return None


def _stopped(pid: int) -> bool:
    """Whether a process is stopped (SIGSTOP: state T in /proc); a stopped worker cannot act on SIGTERM."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] in ("T", "t")
    except (OSError, IndexError):
        return False


class WorkerDied(Exception):
    """A worker died, hung or reported an error; ``role`` names it, ``hung`` if it is alive but silent."""

    def __init__(self, message: str, role: str | None = None, hung: bool = False, code: int | None = None):
        super().__init__(message)
        self.role, self.hung = role, hung
        self.code = code  # the worker's own exit status when it reported one (3: a device fault)


class RunAborted(LabctlError):
    """A live run ended early: how (``cause``), what the stop did (``outcomes``), the exit status."""

    def __init__(self, message: str, exit_code: int, outcomes: list[dict], cause: str):
        super().__init__(message)
        self.exit_code, self.outcomes, self.cause = exit_code, outcomes, cause


@dataclass
class LiveRun:
    """The supervisor of one live run (the CLI process)."""

    lab_root: Path
    spec: dict
    run_dir: Path | None = None
    on_status: Callable[[dict], None] | None = None  # for the live view

    def run(self) -> dict:
        """Run the live run: load the lab, start the simulated lab (if any) and both workers, supervise them, and return
        the predictor's result."""
        warm_up()
        lab = load_lab(self.lab_root)
        old = ({sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
               if _in_main_thread() else {})
        if _in_main_thread():
            signal.signal(signal.SIGTERM, _raise_terminated)
            signal.signal(signal.SIGHUP, _raise_terminated)
            # Ctrl-C stops the run even if the parent started us ignoring SIGINT (`labctl run &` in a script)
            signal.signal(signal.SIGINT, signal.default_int_handler)
        handler = _log_to_record(self._record(), "supervisor")
        try:
            return self._run(lab)
        finally:
            if handler is not None:
                logging.getLogger("labctl").removeHandler(handler)
                with contextlib.suppress(Exception):
                    handler.record.close()
            for sig, previous in old.items():  # the stop path ignored both; the caller's handlers again
                signal.signal(sig, previous)

    def _say(self, phase: str) -> None:
        """Tell the live view which start-up phase the run is in (before the workers' first beat)."""
        if self.on_status:
            self.on_status({"role": "startup", "stage": phase})

    def _record(self):
        if self.run_dir is None:
            return None
        from ..records import RunRecord

        return RunRecord.open(self.run_dir)

    def _run(self, lab) -> dict:
        from .transport import local_pair, pty_null_modem

        stack = contextlib.ExitStack()
        procs: dict[str, BaseProcess] = {}
        controls = {}
        sim_conn = sim_proc = None
        endpoints = {}
        origin = time.monotonic()
        marks = self._marks
        try:
            if lab.is_simulated:
                self._say("starting the simulated lab")
                marks["sim_lab_starting"] = time.time()
                sim_conn, child = CTX.Pipe()
                sim_proc = CTX.Process(target=sim_server_main, name="labctl-sim", daemon=True,
                                       args=(str(lab.root), self.spec, child,
                                             str(self.run_dir) if self.run_dir else None))
                _start_quietly(sim_proc)
                child.close()
            a_end, b_end = local_pair() if lab.host_link.transport == "local" else (None, None)
            extra: dict[str, dict[str, Any]] = {"predictor": {}, "recognizer": {}}
            if lab.host_link.transport == "tcp":  # both workers on this PC: a fresh key for this run alone
                import secrets

                from .transport import link_key

                key = (link_key(lab.host_link, lab.root) or secrets.token_hex(32).encode()).decode()
                for role in extra:
                    extra[role]["link_key"] = key
            if lab.host_link.transport == "serial" and not lab.host_link.port:
                # one PC, RS-232 as in 1996: a pty null modem paced at the link's baud rate
                modem = stack.enter_context(pty_null_modem(lab.host_link.baud))
                for role, port in (("predictor", modem.port_a), ("recognizer", modem.port_b)):
                    extra[role]["host_link"] = dataclasses.asdict(dataclasses.replace(lab.host_link, port=port))
            self._say("starting the workers")
            # the workers start at once, beside the simulated lab: they load the lab, calibration and
            # library meanwhile and wait for its ports before opening any device
            base: dict[str, Any] = dict(lab_root=str(lab.root), run_dir=str(self.run_dir) if self.run_dir else None,
                        spec=self.spec, origin=origin, await_endpoints=sim_conn is not None)
            p: BaseProcess
            for role, end in (("predictor", a_end), ("recognizer", b_end)):
                parent, child = CTX.Pipe()
                p = CTX.Process(target=_worker_process, name=f"labctl-{role}", daemon=True,
                                args=(role, WorkerArgs(role=role, extra=extra[role], **base), end, child))
                _start_quietly(p)
                child.close()
                procs[role], controls[role] = p, parent
            for end in (a_end, b_end):
                if end is not None:
                    with contextlib.suppress(Exception):
                        end.close()
            marks["workers_forked"] = time.time()
            kind = None
            if sim_conn is not None:
                # first the devices' ports (the emulators serve them before the world is built), then "ready"
                kind, payload = _sim_says(sim_conn)
                endpoints, origin = payload, payload["origin"]
                marks["sim_lab_ports" if kind == "ports" else "sim_lab_ready"] = time.time()
            from .stopping import open_stop_lines

            # the stop lines are open before any worker hears of a port
            self._stop_fds = open_stop_lines(lab, endpoints)
            stack.callback(self._close_stop_lines)
            try:
                if kind == "ports":
                    # the predictor connects the table and the robot while the simulated lab builds its world; it
                    # opens its camera, and moves the table, only once the lab is ready
                    controls["predictor"].send(("ports", endpoints))
                    kind, payload = _sim_says(sim_conn, ("ready",))
                    endpoints, origin = payload, payload["origin"]
                    marks["sim_lab_ready"] = time.time()
                if sim_conn is not None:
                    for conn in controls.values():
                        conn.send(("endpoints", endpoints))
                self._say("workers loading calibration and library, opening the devices")
                result = self._supervise(lab, procs, controls, sim_conn)
                result["startup_wall"] = {**marks, **(result.get("startup_wall") or {})}
                result["devices_stopped"] = self._await_stopped(lab, procs, controls)
            except (WorkerDied, KeyboardInterrupt, Terminated) as exc:
                _shield()
                raise self._abort(lab, exc, endpoints, procs, controls, sim_conn, origin) from None
            if sim_conn is not None:
                truth = _ask(sim_conn, "truth?")
                if truth is not None:
                    result.update(truth)
                    result["correct"] = result.get("identity") == truth["true_identity"]
            return result
        finally:
            _shield()
            for p in procs.values():
                if _alive(p):
                    _kill(p, signal.SIGTERM)
            for p in procs.values():
                if not _join(p, 5):
                    _kill(p)
                    _join(p, 2)
            stack.close()
            if sim_proc is not None:
                if _alive(sim_proc):
                    with contextlib.suppress(OSError):
                        cast(Connection, sim_conn).send("stop")  # the simulated lab's pipe, with its process
                    _join(sim_proc, 3)
                if _alive(sim_proc):  # it ignores SIGTERM, like the hardware it stands for
                    _kill(sim_proc)
                    _join(sim_proc, 2)

    _stop_fds: dict = field(default_factory=dict)
    _marks: dict = field(default_factory=dict)  # start-up phases, wall clock

    def _close_stop_lines(self) -> None:
        for fd in self._stop_fds.values():
            with contextlib.suppress(OSError):
                os.close(fd)
        self._stop_fds = {}

    def _abort(self, lab, exc, endpoints, procs, controls, sim_conn, origin) -> RunAborted:
        """Stop everything after a dead/hung worker, Ctrl-C or SIGTERM; confirm it; record it."""
        from .stopping import _ports, confirm_stopped, confirmed, send_stop_bytes, summary

        t0 = time.monotonic()
        hung = exc.role if isinstance(exc, WorkerDied) and exc.hung else None

        def signal_workers():  # a live worker stops its own devices on SIGTERM; a hung one is killed
            for role, p in procs.items():
                if _alive(p):
                    _kill(p, signal.SIGKILL if role == hung or _stopped(p.pid) else signal.SIGTERM)

        # A port without a stop line of our own (a network URL: a ser2net-style server takes one client,
        # the worker's) cannot take our stop bytes while a worker holds it: the workers' own stop comes first.
        shared = bool(set(_ports(lab, endpoints)) - set(self._stop_fds))
        if shared:
            signal_workers()
        sent = send_stop_bytes(lab, endpoints, fds=self._stop_fds)  # motion ends now, whatever the workers do
        t_sent = time.monotonic() - t0
        after = None
        if sim_conn is not None:  # the simulator can tell when the devices really stood still
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                after = _ask(sim_conn, "state?")
                if after is None or not (after["robot_moving"] or after["table_moving"]):
                    break
                time.sleep(0.01)
            if after is not None:
                after["still_after_s"] = time.monotonic() - t0
        signal_workers()
        deadline = time.monotonic() + 8.0
        for p in procs.values():  # the ports are opened below only once no worker holds them
            if not _join(p, max(0.0, deadline - time.monotonic())):
                _kill(p)
                _join(p, 2)
        if shared:  # the workers are gone and the ports free: the stop bytes now reach every device
            sent = send_stop_bytes(lab, endpoints, fds=self._stop_fds)
        worker_outcomes = {}
        for role, conn in controls.items():
            with contextlib.suppress(EOFError, OSError):
                while conn.poll(0):
                    msg = conn.recv()
                    if msg[0] == "stopped":
                        worker_outcomes[role] = msg[1]
        outcomes = confirm_stopped(lab, endpoints)  # the ports are ours alone now
        if isinstance(exc, KeyboardInterrupt):
            cause, code, what = "interrupted", EXIT_INTERRUPTED, "interrupted (Ctrl-C)"
        elif isinstance(exc, Terminated):
            cause, code, what = "terminated", exc.exit_code, exc.what
        else:
            cause, code, what = "worker", getattr(exc, "code", None) or 1, str(exc)
        if len(confirmed(outcomes)) < len(outcomes):
            code = EXIT_DEVICE
        record = self._record()
        if record is not None:
            with contextlib.suppress(Exception):
                record.event("run_aborted", t=time.monotonic() - origin, reason=what, cause=cause,
                             devices_stopped=confirmed(outcomes), stop_outcomes=outcomes,
                             stop_bytes=sent, worker_stop_outcomes=worker_outcomes, stop_commands_sent_s=t_sent,
                             t_stop_sent=t0 - origin, devices_after_stop=after, exit_code=code)
                record.close()
        return RunAborted(f"{what}: {summary(outcomes)}", code, outcomes, cause)

    def _await_stopped(self, lab, procs, controls, timeout_s: float = 15.0) -> list[str]:
        """After the result: the predictor's report that it stopped and confirmed its devices."""
        from .stopping import confirmed

        conn = controls["predictor"]
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                if conn.poll(0.05):
                    msg = conn.recv()
                    if msg[0] == "stopped":
                        return confirmed(msg[1])
                    if msg[0] == "error":
                        raise WorkerDied(msg[1], "predictor", code=msg[2] if len(msg) > 2 else None)
            except (EOFError, OSError):
                break
        return []

    @staticmethod
    def _raise_dead(procs, skip: str) -> None:
        """A worker that reports its peer gone usually means the peer died: name the dead one."""
        for role, p in procs.items():
            if role != skip:
                p.join(timeout=0.2)
                if not p.is_alive() and (p.exitcode or 0) < 0:  # killed by a signal, not a worker that left
                    raise WorkerDied(f"the {role} worker died (exit code {p.exitcode})", role)

    def _supervise(self, lab, procs, controls, sim_conn=None) -> dict:
        """Watch the workers until the predictor's result: a worker that dies, reports an error or
        goes silent for ``stall_after_s`` after its first beat (before it: ``start_timeout_s``) ends
        the run. The supervisor's own beats go to each worker every ``heartbeat_s``."""
        hl = lab.host_link
        last_beat: dict[str, float | None] = {r: None for r in procs}
        started = time.monotonic()
        t_sent = 0.0
        result = None
        truth_on = sim_conn is None
        stopped_since: dict[str, float] = {}
        while True:
            if not truth_on and all(t is not None for t in last_beat.values()):
                truth_on = True  # both workers run: the simulator's ground truth may join the record
                with contextlib.suppress(OSError):
                    sim_conn.send("record")
            for role, conn in controls.items():
                while True:
                    try:
                        if not conn.poll(0):
                            break
                        msg = conn.recv()
                    except (EOFError, OSError):
                        break
                    kind = msg[0]
                    if kind == "beat":
                        last_beat[role] = time.monotonic()
                        if msg[4] and self.on_status:
                            self.on_status({"role": role, "t": msg[3], **msg[4]})
                    elif kind == "result":
                        result = msg[1]
                    elif kind == "error":
                        self._raise_dead(procs, skip=role)  # the root cause: a peer that died, if one did
                        raise WorkerDied(msg[1], role, code=msg[2] if len(msg) > 2 else None)
            if result is not None:
                return result
            now = time.monotonic()
            if now - t_sent >= hl.heartbeat_s / 2:
                t_sent = now
                for conn in controls.values():
                    with contextlib.suppress(OSError):
                        conn.send(("beat", now))
            for role, p in procs.items():
                if not p.is_alive():
                    if p.exitcode == 0 and any(q.is_alive() for r, q in procs.items() if r != role):
                        continue  # it left as its peer told it to: the peer's own report says why
                    raise WorkerDied(f"the {role} worker died (exit code {p.exitcode})", role)
                if _stopped(p.pid):  # SIGSTOP: caught even during the start-up grace
                    stopped_since.setdefault(role, now)
                    if now - stopped_since[role] > hl.stall_after_s:
                        raise WorkerDied(f"the {role} worker is stopped (SIGSTOP, {now - stopped_since[role]:.1f} s)",
                                         role, hung=True)
                else:
                    stopped_since.pop(role, None)
                beat = last_beat[role]
                if beat is None:
                    if now - started > hl.start_timeout_s:
                        raise WorkerDied(f"the {role} worker did not start within {hl.start_timeout_s:g} s",
                                         role, hung=True)
                elif now - beat > hl.stall_after_s:
                    raise WorkerDied(f"the {role} worker stopped answering ({now - beat:.1f} s)",
                                     role, hung=True)
            time.sleep(0.02)


def run_live(lab_root: Path, spec: dict, run_dir: Path | None, on_status=None) -> dict:
    """A live run of the lab at ``lab_root`` (see :class:`LiveRun`); ``on_status`` receives each status for the live
    view."""
    return LiveRun(Path(lab_root), spec, run_dir, on_status).run()


__all__ = ["LiveRun", "WorkerArgs", "plausible", "WorkerDied", "RunAborted", "PeerWatch", "PeerLost", "Terminated",
           "predictor_main", "recognizer_main", "run_live", "asdict"]
