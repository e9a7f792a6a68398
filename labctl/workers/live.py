"""The live runtime: real time, two worker processes and a supervisor (DESIGN §3, paper §5.1).

```
supervisor (the CLI process)                       — run record, live view, watchdog
 ├─ sim lab server   (simulated lab only)          — world, GRBL + robot emulators on ptys, frame server
 ├─ predictor/planner worker (Host 1)              — fixed camera, Kalman filter, planners, robot + table
 └─ recognizer worker        (Host 2)              — mobile camera, marker pose, matching, library
```

The workers exchange :mod:`~labctl.workers.messages` over the host link of
``drivers/host_link.yaml``; each also has a control pipe to the supervisor carrying heartbeats
and status for the live view. If a worker dies or stalls (no heartbeat for ``dead_after_s``),
the supervisor stops the robot and the table itself — it opens their ports and sends the
controllers' stop commands — ends the run with one clear line and keeps the record.
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing as mp
import os
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ..config import load_lab
from . import messages as m

# forkserver: each process still starts from a clean interpreter (no inherited threads or ports),
# but the heavy imports (scipy.stats via filterpy, trimesh, OpenCV) are paid once, in the server,
# which :func:`warm_up` starts while the command is still loading the lab: the sim lab and both
# workers then fork in milliseconds instead of importing for seconds each (issue 16, start-up).
CTX = mp.get_context("forkserver")
_PRELOAD = ["labctl.workers.live", "labctl.workers.predictor", "labctl.workers.recognizer",
            "labctl.workers.simlab", "labctl.workers.context"]


def warm_up() -> None:
    """Start the process server with the workers' modules imported, in the background (idempotent)."""
    from multiprocessing import forkserver

    CTX.set_forkserver_preload(_PRELOAD)
    forkserver.ensure_running()


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


def _now(origin: float) -> float:
    return time.monotonic() - origin


class _Control:
    """The worker's end of its control pipe: heartbeats and status to the supervisor."""

    def __init__(self, conn, role: str):
        self.conn, self.role, self.seq = conn, role, 0
        self.t_last = 0.0

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


def _load_lab(args: WorkerArgs):
    """The lab as the worker sees it (a standalone worker may override the host link)."""
    import dataclasses

    from ..config import HostLinkConfig

    lab = load_lab(args.lab_root)
    if "host_link" in args.extra:
        lab = dataclasses.replace(lab, host_link=HostLinkConfig(**args.extra["host_link"]))
    return lab


def _release(stop=(), close=()) -> None:
    """Stop the moving devices, then close everything; a worker's exit path must never raise."""
    for dev, method in [(d, "stop") for d in stop] + [(d, "close") for d in close]:
        if dev is not None:
            with contextlib.suppress(Exception):
                getattr(dev, method)()


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
    return open_device(f"{role}_camera", lab, clock=lambda: time.monotonic() - origin)


def _fixed_camera(args: WorkerArgs, lab):
    return _camera(args, lab, "fixed")


def _mobile_camera(args: WorkerArgs, lab):
    return _camera(args, lab, "mobile")


def predictor_main(args: WorkerArgs, link_end, control) -> None:
    """Host 1's process: fixed camera → Kalman filter → planners → robot and table."""
    from ..drivers.grbl import GrblTable
    from ..drivers.robot import SerialRobot
    from .context import RunContext
    from .predictor import PredictorPlanner, ProgramProgress
    from .simlab import trajectory_program
    from .transport import LinkClosed, open_link

    ctl = _Control(control, "predictor")
    lab = _load_lab(args)
    record = _open_record(args)
    log = record.event if record is not None else (lambda *a, **k: None)
    log("worker_started", role="predictor", pid=os.getpid())
    table = robot = camera = link = None
    try:
        ctx = RunContext.load(lab)
        link = open_link(lab.host_link, "predictor", local_end=link_end)
        # the sim lab's ports when it serves them, else the driver files' (None keeps the file's port);
        # no table to drive when the parts move by something else (--trajectory external)
        external = args.spec["trajectory"] == "external" or lab.table is None
        table = None if external else GrblTable.from_config(lab.table, port=args.table_port)
        robot = SerialRobot.from_config(lab.robot, port=args.robot_port)
        camera = _fixed_camera(args, lab)
        for dev in (table, robot, camera):
            if dev is not None:
                dev.open()
        link.send(m.Hello(role="predictor", pid=os.getpid()))
        now = _now(args.origin)
        planner = PredictorPlanner(ctx, robot, link.send, log, t_start=now, clock=lambda: _now(args.origin))
        progress = None
        if table is not None:
            # a simulated table's power-up lock may be released (the simulator knows where it is); a real
            # table in Alarm must be homed or unlocked by the operator first (its position may be lost)
            table.ensure_ready(unlock=lab.table.kind == "sim")
            # streamed from the loop: a long G2/G3 is acknowledged only when it leaves GRBL's planner
            program = table.start_program(
                trajectory_program(args.spec["trajectory"], args.spec["speed_mm_s"], lab)[1])
            log("table_program", t=now, trajectory=args.spec["trajectory"], speed_mm_s=args.spec["speed_mm_s"],
                lines=program.total)
            progress = ProgramProgress(program, log)
        else:
            log("table_program", t=now, trajectory=args.spec["trajectory"], speed_mm_s=args.spec["speed_mm_s"])
        t_beat = 0.0
        while not planner.finished:
            if progress is not None:
                progress.pump(_now(args.origin))
            frame = camera.grab()
            planner.on_frame(frame)
            while True:
                msg = link.recv(timeout=0)
                if msg is None:
                    break
                if not isinstance(msg, m.Heartbeat | m.Hello):
                    planner.on_message(msg, _now(args.origin))
            now = _now(args.origin)
            planner.tick(now)
            if now - t_beat >= lab.robot.heartbeat_s:
                robot.heartbeat()
                link.send(m.Heartbeat(role="predictor", seq=int(now * 10) % 65536, t=now))
                t_beat = now
            est = planner.tracker.estimate()[0].tolist() if planner.tracker.initialized else None
            ctl.beat(now, {"stage": planner.stage, "estimate": est, "views": planner.views_used,
                           "link": {"sent": link.bytes_sent, "received": link.bytes_received},
                           "robot": planner.robot_path[-1][1] if planner.robot_path else None})
        result = planner.result(_now(args.origin))
        link.send(m.Stop(reason="run finished"))
        result["link"] = {**link.stats(), "baud": lab.host_link.baud, "duration_s": _now(args.origin) - planner.t_start}
        if lab.host_link.transport == "serial":
            bits = 10.0 * max(link.bytes_sent, link.bytes_received)  # full duplex: the busier direction
            result["link"]["utilisation"] = bits / lab.host_link.baud / max(result["link"]["duration_s"], 1e-9)
        ctl.send("result", result)
    except LinkClosed:
        ctl.send("error", "predictor: the host link to the recognizer closed")
    except Exception as exc:  # the supervisor reports it in one line; the record keeps the traceback
        log("worker_error", role="predictor", error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc())
        ctl.send("error", f"predictor: {type(exc).__name__}: {exc}", getattr(exc, "exit_code", 1))
    finally:
        _release(stop=(robot, table), close=(camera, robot, table, link))


def recognizer_main(args: WorkerArgs, link_end, control) -> None:
    """Host 2's process: mobile camera → marker pose → standard-view matching."""
    from .context import RunContext
    from .recognizer import Recognizer
    from .transport import LinkClosed, open_link

    ctl = _Control(control, "recognizer")
    lab = _load_lab(args)
    record = _open_record(args)
    log = record.event if record is not None else (lambda *a, **k: None)
    save = record.save_image if record is not None else None
    log("worker_started", role="recognizer", pid=os.getpid())
    camera = link = None
    try:
        ctx = RunContext.load(lab)
        link = open_link(lab.host_link, "recognizer", local_end=link_end)
        camera = _mobile_camera(args, lab)
        camera.open()
        link.send(m.Hello(role="recognizer", pid=os.getpid()))
        recognizer = Recognizer(ctx, camera.grab, log, save)
        t_beat = 0.0
        while True:
            msg = link.recv(timeout=0.05)
            now = _now(args.origin)
            if isinstance(msg, m.Stop):
                break
            if msg is not None and not isinstance(msg, m.Heartbeat | m.Hello):
                for reply in recognizer.handle(msg):
                    link.send(reply)
            if now - t_beat >= lab.host_link.heartbeat_s:
                link.send(m.Heartbeat(role="recognizer", seq=int(now * 10) % 65536, t=now))
                t_beat = now
            ctl.beat(now)
    except LinkClosed:
        ctl.send("done", "recognizer: host link closed")
    except Exception as exc:
        log("worker_error", role="recognizer", error=f"{type(exc).__name__}: {exc}",
            traceback=traceback.format_exc())
        ctl.send("error", f"recognizer: {type(exc).__name__}: {exc}", getattr(exc, "exit_code", 1))
    finally:
        _release(close=(camera, link))


def sim_server_main(lab_root: str, spec: dict, conn) -> None:
    """The simulated lab for a live run: world + emulators on ptys + frame server, in real time.

    Answers the supervisor's ``"state?"`` (are the robot and table moving), ``"truth?"`` (the
    simulator's ground truth) and ``"stop"``."""
    from .simlab import LiveSimLab

    try:
        with LiveSimLab(load_lab(lab_root), spec) as sim:
            conn.send(("ready", sim.endpoints()))
            while True:
                if not conn.poll(0.2):
                    continue
                req = conn.recv()
                if req == "state?":
                    conn.send(("state", sim.device_state()))
                elif req == "truth?":
                    conn.send(("truth", sim.truth()))
                else:
                    return
    except (EOFError, OSError):
        return
    except Exception as exc:
        with contextlib.suppress(OSError):
            conn.send(("error", f"sim lab: {type(exc).__name__}: {exc}"))


def _ask(conn, request: str, timeout_s: float = 5.0):
    with contextlib.suppress(OSError, EOFError):
        conn.send(request)
        if conn.poll(timeout_s):
            return conn.recv()[1]
    return None


class WorkerDied(Exception):
    pass


@dataclass
class LiveRun:
    """The supervisor of one live run (the CLI process)."""

    lab_root: Path
    spec: dict
    run_dir: Path | None = None
    on_status: object = None  # callable(dict) for the live view

    def run(self) -> dict:
        warm_up()
        lab = load_lab(self.lab_root)
        from .transport import local_pair, pty_null_modem

        stack = contextlib.ExitStack()
        procs: dict[str, mp.Process] = {}
        controls = {}
        sim_conn = sim_proc = None
        endpoints = {}
        origin = time.monotonic()
        try:
            if lab.is_simulated:
                sim_conn, child = CTX.Pipe()
                sim_proc = CTX.Process(target=sim_server_main, args=(str(lab.root), self.spec, child),
                                       name="labctl-sim", daemon=True)
                sim_proc.start()
                child.close()
                if not sim_conn.poll(60):
                    raise WorkerDied("the simulated lab did not start within 60 s")
                kind, payload = sim_conn.recv()
                if kind != "ready":
                    raise WorkerDied(str(payload))
                endpoints = payload
                origin = endpoints["origin"]
            a_end, b_end = local_pair() if lab.host_link.transport == "local" else (None, None)
            extra = {"predictor": {}, "recognizer": {}}
            if lab.host_link.transport == "serial" and not lab.host_link.port:
                # one PC, RS-232 as in 1996: a pty null modem paced at the link's baud rate
                modem = stack.enter_context(pty_null_modem(lab.host_link.baud))
                for role, port in (("predictor", modem.port_a), ("recognizer", modem.port_b)):
                    extra[role]["host_link"] = dataclasses.asdict(dataclasses.replace(lab.host_link, port=port))
            base = dict(lab_root=str(lab.root), run_dir=str(self.run_dir) if self.run_dir else None,
                        spec=self.spec, origin=origin, table_port=endpoints.get("table"),
                        robot_port=endpoints.get("robot"), frame_server=endpoints.get("frame_server"))
            for role, target, end in (("predictor", predictor_main, a_end), ("recognizer", recognizer_main, b_end)):
                parent, child = CTX.Pipe()
                p = CTX.Process(target=target, args=(WorkerArgs(role=role, extra=extra[role], **base), end, child),
                                name=f"labctl-{role}", daemon=True)
                p.start()
                child.close()
                procs[role], controls[role] = p, parent
            for end in (a_end, b_end):
                if end is not None:
                    with contextlib.suppress(Exception):
                        end.close()
            try:
                result = self._supervise(lab, procs, controls, origin)
            except (WorkerDied, KeyboardInterrupt) as exc:
                from .simlab import emergency_stop

                t0 = time.monotonic()
                stopped = emergency_stop(lab, endpoints)
                t_sent = time.monotonic() - t0
                for p in procs.values():
                    if p.is_alive():
                        p.terminate()
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
                if self.run_dir is not None:
                    from ..records import RunRecord

                    RunRecord.open(self.run_dir).event(
                        "run_aborted", reason=str(exc) or "interrupted", devices_stopped=stopped,
                        stop_commands_sent_s=t_sent, devices_after_stop=after)
                raise
            if sim_conn is not None:
                truth = _ask(sim_conn, "truth?")
                if truth is not None:
                    result.update(truth)
                    result["correct"] = result.get("identity") == truth["true_identity"]
            return result
        finally:
            for p in procs.values():
                if p.is_alive():
                    p.terminate()
                p.join(timeout=2)
            stack.close()
            if sim_proc is not None:
                if sim_proc.is_alive():
                    with contextlib.suppress(OSError):
                        sim_conn.send("stop")
                    sim_proc.join(timeout=3)
                if sim_proc.is_alive():
                    sim_proc.terminate()
                    sim_proc.join(timeout=2)

    def _supervise(self, lab, procs, controls, origin) -> dict:
        last_beat = {r: time.monotonic() for r in procs}
        stall_after = lab.host_link.stall_after_s
        started = time.monotonic()
        result = None
        while True:
            for role, conn in controls.items():
                while conn.poll(0):
                    try:
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
                        raise WorkerDied(msg[1])
            if result is not None:
                return result
            now = time.monotonic()
            for role, p in procs.items():
                grace = 15.0 if now - started < 15.0 else 0.0  # imports and device opening
                if not p.is_alive():
                    raise WorkerDied(f"the {role} worker died (exit code {p.exitcode})")
                if now - last_beat[role] > stall_after + grace:
                    raise WorkerDied(f"the {role} worker stopped answering ({now - last_beat[role]:.1f} s)")
            time.sleep(min(0.02, lab.host_link.dead_after_s / 10))


def run_live(lab_root: Path, spec: dict, run_dir: Path | None, on_status=None) -> dict:
    return LiveRun(Path(lab_root), spec, run_dir, on_status).run()


__all__ = ["LiveRun", "WorkerArgs", "WorkerDied", "predictor_main", "recognizer_main", "run_live", "asdict"]
