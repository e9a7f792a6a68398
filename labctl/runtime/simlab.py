"""The simulated lab assembled for a run: emulators, drivers, world, trajectories, emergency stop.

* :class:`SimBench` — virtual time: the GRBL and robot emulators behind the real drivers on
  in-process ports (bytes in the real protocols, paced at the driver files' baud rate on the
  virtual clock), and the world that reads the table and flange poses from the emulators.
* :class:`LiveSimLab` — real time, for ``labctl run``: the same emulators on pseudo-terminals
  paced at the baud rate, and a frame server rendering both cameras from the world.
* :func:`trajectory_program` — where the table starts and the G-code it runs for a trajectory.
* :func:`emergency_stop` — what the supervisor sends when a worker dies.
"""

from __future__ import annotations

import contextlib
import os
import time

import numpy as np

from ..config import Lab
from ..drivers.programs import program
from ..errors import UserInputError

#: where the table's carriage starts for each trajectory (mm, machine coordinates) — the object
#: then crosses the fixed camera's field while the run takes place
TRAJECTORY_STARTS = {"line": (150.0, 200.0), "arc": (200.0, 200.0), "circle": (200.0, 200.0),
                     "zigzag": (150.0, 170.0)}


def table_config(lab: Lab):
    """The lab's table, or (no table: parts on a conveyor) the default table the simulator moves them on."""
    from ..config import TableConfig

    return lab.table if lab.table is not None else TableConfig()


def trajectory_program(name: str, speed_mm_s: float, lab: Lab) -> tuple[tuple[float, float], list[str]]:
    """``(start_xy, gcode_lines)`` of a named trajectory, or of a G-code file (started at the centre).

    ``external`` (labctl does not drive the motion): where the simulator's conveyor starts, and no lines."""
    if name == "external":
        return TRAJECTORY_STARTS["line"], []
    if name in TRAJECTORY_STARTS:
        start = TRAJECTORY_STARTS[name]
        return start, program(name, speed_mm_s, start=start, travel_mm=table_config(lab).travel_mm)
    from ..drivers.programs import load_trajectory

    table = table_config(lab)
    lines = load_trajectory(name, travel_mm=table.travel_mm, max_feed_mm_min=table.max_feed_mm_min)
    travel = table.travel_mm
    return (travel[0] / 2, travel[1] / 2), lines


def _sim_object(lab: Lab, spec: dict, rng: np.random.Generator):
    from ..library.storage import load_library
    from ..sim.world import SimObject, random_placement

    library = load_library(lab.library_dir)
    names = sorted(library)
    if not names:
        raise UserInputError(f"the object library {lab.library_dir} is empty")
    name = spec.get("object_name") or names[int(rng.integers(len(names)))]
    obj = SimObject.from_library(library[name])
    return name, obj, random_placement(obj, rng)


class SimBench:
    """The simulated devices on one virtual clock, behind the real drivers."""

    def __init__(self, lab: Lab, clock, start_xy=(150.0, 200.0)):
        from ..drivers.grbl import GrblTable
        from ..drivers.robot import SerialRobot
        from ..sim.emulators.grbl import GrblEmulator
        from ..sim.emulators.link import EmulatorPort
        from ..sim.emulators.robot import RobotEmulator
        from ..sim.world import home_flange_pose

        self.lab, self.clock = lab, clock
        t = lab.table
        self.grbl = GrblEmulator(clock.now, travel_mm=t.travel_mm, max_feed_mm_min=t.max_feed_mm_min,
                                 accel_mm_s2=t.accel_mm_s2, start_mm=(start_xy[0], start_xy[1], 0.0))
        self.robot_emu = RobotEmulator(clock.now, lab.robot, start_pose=home_flange_pose(lab))
        self.table = GrblTable.from_config(t, serial_port=EmulatorPort(self.grbl, clock.now, t.baud, sleep=clock.sleep),
                                           clock=clock.now, sleep=clock.sleep)
        self.robot = SerialRobot.from_config(
            lab.robot, serial_port=EmulatorPort(self.robot_emu, clock.now, lab.robot.baud, sleep=clock.sleep),
            clock=clock.now, sleep=clock.sleep)
        self.table.open()
        self.robot.open()

    def world(self, obj, placement):
        """The simulated world of this lab with ``obj`` at ``placement``, moving with the emulated table and robot."""
        from ..sim.world import SimWorld

        return SimWorld.from_lab(self.lab, obj=obj, placement=placement, table_position=self.grbl.position_at,
                                 flange_pose_at=self.robot_emu.flange_pose_at)

    def advance(self, t: float) -> None:
        """Advance both emulators to time ``t`` (s)."""
        self.grbl.advance(t)
        self.robot_emu.advance(t)

    def stop(self) -> list[dict]:
        """Stop and confirm both devices; every outcome returned (labctl.runtime.stopping)."""
        from .stopping import stop_devices

        return stop_devices({"robot": self.robot, "table": self.table})


class Conveyor:
    """Moves the simulated table by itself — parts on a conveyor that labctl does not drive.

    The program goes straight into the GRBL emulator (no client on its port) once the fixed
    camera has been watched without a pause for ``delay_s``: the part arrives while a run looks,
    and a single ``labctl devices`` grab does not set it off.
    """

    def __init__(self, grbl, lock, lines: list[str], delay_s: float = 1.0, gap_s: float = 0.5):
        self.grbl, self.lock, self.lines = grbl, lock, lines
        self.delay_s, self.gap_s = delay_s, gap_s
        self.started_at: float | None = None
        self._streak: tuple[float, float] | None = None  # (first, last) grab of the current streak

    def watch(self, camera):
        """``camera`` with every grab reported to :meth:`seen` (the conveyor starts once watched long enough)."""
        conveyor = self

        class Watched:
            def __getattr__(self, name):
                return getattr(camera, name)

            def grab(self):
                frame = camera.grab()
                conveyor.seen(frame.t)
                return frame

            def grab_recent(self, max_frames):
                frames = camera.grab_recent(max_frames)
                conveyor.seen(frames[-1].t)
                return frames

        return Watched()

    def seen(self, t: float) -> None:
        """A fixed-camera grab at time ``t`` (s): start the program once grabs have come without a pause for
        ``delay_s``."""
        if self.started_at is not None:
            return
        first, last = self._streak or (t, t)
        if t - last > self.gap_s:
            first = t
        self._streak = (first, t)
        if t - first >= self.delay_s:
            with self.lock:
                self.grbl.receive(("\n".join(self.lines) + "\n").encode(), t=t)
            self.started_at = t


def _locked(lock, fn):
    def call(*args):
        with lock:
            return fn(*args)

    return call


class LiveSimLab:
    """The simulated lab in real time: emulators on ptys, cameras behind a frame server."""

    #: render each camera's first frame (seconds: it builds the scene) before serving; a live run's
    #: server sets this False and calls :meth:`warm_up` once it has said ready, so the first renders
    #: overlap the workers' device connections instead of delaying them (issue 16, start-up)
    warm_on_enter = True

    def __init__(self, lab: Lab, spec: dict):
        self.lab, self.spec = lab, spec
        self._stack = contextlib.ExitStack()
        self._cams: dict = {}

    def __enter__(self) -> LiveSimLab:
        from ..sim.camera import FrameServer

        try:
            cams = self._start_world()
            self.server = FrameServer(cams).start()
            self._stack.callback(self.server.stop)
        except BaseException:
            self._stack.close()
            raise
        return self

    def _start_world(self) -> dict:
        """The world, both emulators on ptys (real clock) and both (opened) sim cameras, by role."""
        from ..sim.camera import SimCamera
        from ..sim.clock import RealClock
        from ..sim.emulators.grbl import GrblEmulator
        from ..sim.emulators.pty import run_on_pty
        from ..sim.emulators.robot import RobotEmulator
        from ..sim.world import home_flange_pose

        lab = self.lab
        rng = np.random.default_rng(self.spec.get("seed", 0))
        self.object_name, obj, placement = _sim_object(lab, self.spec, rng)
        self.obj, self.placement = obj, placement
        start = self.spec.get("table_start_mm") or trajectory_program(
            self.spec["trajectory"], self.spec["speed_mm_s"], lab)[0]
        self.origin = time.monotonic()
        clock = RealClock()
        clock._origin = self.origin
        t = table_config(lab)
        self.grbl = GrblEmulator(clock.now, travel_mm=t.travel_mm, max_feed_mm_min=t.max_feed_mm_min,
                                 accel_mm_s2=t.accel_mm_s2, start_mm=(start[0], start[1], 0.0))
        self.robot_emu = RobotEmulator(clock.now, lab.robot, start_pose=home_flange_pose(lab))
        baud = self.spec.get("baud")
        self.table_pty = run_on_pty(self.grbl, baud or t.baud, clock=clock.now)
        self._stack.callback(self.table_pty.stop)
        self.robot_pty = run_on_pty(self.robot_emu, baud or lab.robot.baud, clock=clock.now)
        self._stack.callback(self.robot_pty.stop)
        # the cameras see what the served controllers do: positions read from the emulators, under their locks
        self.world = self._make_world(
            obj, placement, table_position=_locked(self.table_pty.lock, self.grbl.position_at),
            flange_pose_at=_locked(self.robot_pty.lock, self.robot_emu.flange_pose_at))
        seed = int(self.spec.get("seed", 0))
        cams = {role: SimCamera(self.world, role, clock, fps=self.spec.get("fps") or getattr(lab, f"{role}_camera").fps,
                                seed=seed)
                for role in ("fixed", "mobile")}
        for cam in cams.values():
            cam.open()
        self._cams = dict(cams)
        if self.warm_on_enter:
            self.warm_up()
        self.clock = clock
        self.conveyor = None
        if self.spec.get("trajectory") == "external" or self.spec.get("conveyor"):
            # parts on a conveyor labctl does not drive: the simulator runs the table itself
            # the conveyor is the simulator's own: it clears GRBL's power-up alarm itself ($X)
            lines = ["$X"] + program(self.spec.get("conveyor") or "line", self.spec["speed_mm_s"], start=start,
                                     travel_mm=t.travel_mm, rapid_to_start=False)
            delay = float(self.spec.get("conveyor_delay_s", 1.0))
            self.conveyor = Conveyor(self.grbl, self.table_pty.lock, lines, delay)
            cams["fixed"] = self.conveyor.watch(cams["fixed"])
        return cams

    def warm_up(self) -> None:
        """Render each camera's first frame: it builds the scene (the table texture, ~0.5 s), which
        should not fall in a client's wait. Under each camera's lock, so a grab meanwhile waits for it."""
        for cam in self._cams.values():
            with cam._lock:
                cam.render_frame(0)

    def _make_world(self, obj, placement, *, table_position, flange_pose_at):
        from ..sim.world import SimWorld

        return SimWorld.from_lab(self.lab, obj=obj, placement=placement, table_position=table_position,
                                 flange_pose_at=flange_pose_at)

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def endpoints(self) -> dict:
        """Where the workers reach the lab: table and robot pty paths, the run clock's origin, the frame server."""
        return {"table": self.table_pty.path, "robot": self.robot_pty.path, "origin": self.origin,
                "frame_server": (self.server.address, self.server.authkey)}

    def truth(self) -> dict:
        """The ground truth for the result: the object placed."""
        return {"true_identity": self.object_name}

    def device_state(self) -> dict:
        """Whether the emulated robot and table are moving now, and the table's GRBL state."""
        with self.robot_pty.lock:
            robot_moving = bool(self.robot_emu.moving)
        with self.table_pty.lock:
            self.grbl.advance(self.clock.now())
            table_moving, table_state = bool(self.grbl.moving), self.grbl.state_word
        return {"t": self.clock.now(), "robot_moving": robot_moving, "table_moving": table_moving,
                "table_state": table_state}

    def robot_stop(self) -> list[float] | None:
        """``[start, end]`` (s, this lab's clock) of the robot controller's latest stop ramp — the braking
        that follows a received ``STOP`` (or the controller's own watchdog): None before any."""
        with self.robot_pty.lock:
            stops = [(s.t0, s.t1) for s in self.robot_emu.segments if s.seg_id == -1]
        return list(stops[-1]) if stops else None


class ServedLab(LiveSimLab):
    """``labctl sim serve``: the whole simulated lab out of process, in real time, from one world.

    The GRBL table and robot controller emulators on ptys (or, ``spec["tcp"]``, on TCP ports
    bridged as ser2net would), and both cameras as MJPEG-over-HTTP streams on localhost
    (:class:`labctl.sim.mjpeg.MjpegServer`) rendering the world whose table and flange poses
    are read from those same emulators. Spec keys: ``seed``, ``object_name``, ``trajectory``
    and ``speed_mm_s`` (only where the table starts), ``table_start_mm``, ``tcp``, ``baud``,
    ``http_port``, ``jpeg_quality``, ``fps`` (both cameras; default the driver files'), ``scene``
    (``"object"``, default, or ``"calibration"``: the lab's calibration target on the carriage).

    The world holds both the object and the lab's calibration target (``calibration/target.yaml``,
    :func:`labctl.sim.rigs.target_world`); the HTTP server's control endpoint
    ``POST /control/scene?calibration=1&spacer_mm=H`` (:meth:`set_scene`) switches between them and
    puts the target on a spacer — what a person does at a real lab when ``labctl calibrate`` prompts.
    With ``tcp``, ``/control/link`` (:meth:`set_link`) stops and restarts a device's bridge as
    ser2net is stopped and restarted (a link dropped mid-run, issue 12 Build 7).
    """

    def _make_world(self, obj, placement, *, table_position, flange_pose_at):
        from ..calibration.run import lab_target
        from ..sim.rigs import target_world

        self.target = lab_target(self.lab.calibration_dir)
        world = target_world(self.lab, self.target, table_position=table_position, flange_pose_at=flange_pose_at,
                             obj=obj, placement=placement)
        world.calibration = self.spec.get("scene") == "calibration"
        return world

    def set_scene(self, params: dict) -> dict:
        """The control endpoint ``/control/scene``: with ``calibration`` (1/0, yes/no, true/false,
        or ``scene=calibration|object``) and ``spacer_mm`` (≥ 0, mm) change the scene for every
        frame exposed from now on; without parameters report it. Returns the scene and the time
        of the change (``t``: the served clock, s; ``t_wall``: wall clock, s). Raises ValueError
        for a bad parameter (the server answers 400)."""
        now = self.clock.now()
        calibration, spacer = self.world.scene_at(now)
        if params:
            unknown = set(params) - {"calibration", "scene", "spacer_mm"}
            if unknown:
                raise ValueError(f"unknown parameter(s) {', '.join(sorted(unknown))} (have: calibration, scene, "
                                 "spacer_mm)")
            if "scene" in params:
                if params["scene"] not in ("calibration", "object"):
                    raise ValueError(f"scene must be calibration or object, got {params['scene']!r}")
                calibration = params["scene"] == "calibration"
            if "calibration" in params:
                word = params["calibration"].strip().lower()
                if word not in ("1", "0", "yes", "no", "true", "false"):
                    raise ValueError(f"calibration must be 1 or 0, got {params['calibration']!r}")
                calibration = word in ("1", "yes", "true")
            if "spacer_mm" in params:
                try:
                    spacer = float(params["spacer_mm"])
                except ValueError:
                    raise ValueError(f"spacer_mm must be a number, got {params['spacer_mm']!r}") from None
                if not (np.isfinite(spacer) and 0 <= spacer <= 1000):
                    raise ValueError(f"spacer_mm must be between 0 and 1000 mm, got {spacer:g}")
            self.world.set_scene(now, calibration, spacer)
        return {"scene": "calibration" if calibration else "object", "spacer_mm": spacer, "t": now,
                "t_wall": time.time() - (self.clock.now() - now)}

    def set_link(self, params: dict) -> dict:
        """The control endpoint ``/control/link``: ``device`` (table or robot) with ``up`` (1/0) stops
        or restarts that device's ser2net-style bridge (down: its client's connection and the port
        close, connecting is refused, what the controller sends meanwhile is lost); ``reset=1`` also
        power-cycles the controller while the link is down (a ser2net restart that pulses DTR resets
        an Arduino's GRBL). Without ``up`` it reports. Returns ``{device, up, drops, resets, t,
        t_wall}`` (served clock and wall clock, s). ValueError (400) for a bad parameter or without
        ``tcp``."""
        if not getattr(self, "bridges", None):
            raise ValueError("link control needs the devices on TCP ports (sim serve --tcp)")
        unknown = set(params) - {"device", "up", "reset"}
        if unknown:
            raise ValueError(f"unknown parameter(s) {', '.join(sorted(unknown))} (have: device, up, reset)")
        device = params.get("device")
        if device not in self.bridges:
            raise ValueError(f"device must be one of {', '.join(self.bridges)}, got {device!r}")

        def flag(name: str) -> bool | None:
            if name not in params:
                return None
            word = params[name].strip().lower()
            if word not in ("1", "0", "yes", "no", "true", "false"):
                raise ValueError(f"{name} must be 1 or 0, got {params[name]!r}")
            return word in ("1", "yes", "true")

        up, reset = flag("up"), flag("reset")
        bridge = self.bridges[device]
        if up is not None and not up and not bridge.set_up(False):
            raise RuntimeError(f"the {device} bridge did not stop")
        if reset:
            dev, emu = (self.table_pty, self.grbl) if device == "table" else (self.robot_pty, self.robot_emu)
            with dev.lock:
                emu.power_cycle()
            self.resets[device] += 1
        if up and not bridge.set_up(True):
            raise RuntimeError(f"the {device} bridge did not start again")
        return {"device": device, "up": bridge.is_up, "drops": bridge.drops, "resets": self.resets[device],
                "t": self.clock.now(), "t_wall": time.time()}

    def __enter__(self) -> ServedLab:
        from ..sim.mjpeg import MjpegServer
        from ..sim.tcpserial import TcpSerialBridge

        try:
            cams = self._start_world()
            self.ports = {"table": self.table_pty.path, "robot": self.robot_pty.path}
            self.bridges: dict = {}
            self.resets = {"table": 0, "robot": 0}
            if self.spec.get("tcp"):
                for role in ("table", "robot"):
                    bridge = TcpSerialBridge(self.ports[role])
                    self._stack.callback(bridge.stop)
                    self.ports[role] = bridge.url
                    self.bridges[role] = bridge
            self.mjpeg = MjpegServer(cams, self.clock.now, port=int(self.spec.get("http_port") or 0),
                                     quality=int(self.spec.get("jpeg_quality") or 90),
                                     controls={"scene": self.set_scene, "link": self.set_link}).start()
            self._stack.callback(self.mjpeg.stop)
        except BaseException:
            self._stack.close()
            raise
        return self

    def endpoints(self) -> dict:
        """Where clients reach the served lab: table and robot ports, the MJPEG stream URLs, the scene control URL."""
        return {"table": self.ports["table"], "robot": self.ports["robot"],
                "fixed_camera": self.mjpeg.url("fixed"), "mobile_camera": self.mjpeg.url("mobile"),
                "scene_control": self.mjpeg.control_url("scene"), "link_control": self.mjpeg.control_url("link")}

    def log_truth(self, path, period_s: float = 0.01) -> TruthLogger:
        """Start logging the served devices' motion to ``path`` (:class:`TruthLogger`); stopped on exit."""
        logger = TruthLogger(self, path, period_s).start()
        self._stack.callback(logger.stop)
        return logger

    def check_alive(self) -> None:
        """Raise if an emulator's thread died (the served lab would silently stop answering)."""
        for role, dev in (("table", self.table_pty), ("robot", self.robot_pty)):
            if not dev._thread.is_alive():
                raise RuntimeError(f"the {role} emulator stopped: {dev.errors[-1] if dev.errors else 'unknown'}")

    def truth(self) -> dict:
        """The served world's ground truth (mm, rad; 4×4 poses ``T_<to>_<from>``), for checks."""
        from ..sim import truth

        lab = self.lab
        return {
            "true_identity": self.object_name,
            "seed": int(self.spec.get("seed", 0)),
            "placement": {"pose_index": self.placement.pose_index, "yaw_rad": self.placement.yaw,
                          "offset_xy_mm": list(self.placement.offset_xy)},
            "T_t_o": self.placement.T_t_o(self.obj).tolist(),
            "table_origin_w_mm": list(table_config(lab).origin_w_mm),
            "conveyor": None if self.conveyor is None else {"program": self.conveyor.lines},
            "fixed_camera": {"T_w_c": truth.fixed_camera_pose(lab.fixed_camera).tolist(),
                             "model": truth.camera_model(lab.fixed_camera).to_dict()},
            "mobile_camera": {"T_f_c": truth.hand_eye(lab.mobile_camera).tolist(),
                              "model": truth.camera_model(lab.mobile_camera).to_dict()},
            "T_w_b": np.eye(4).tolist(),
            "endpoints": self.endpoints(),
            "timestamps": "the cameras' X-Timestamp is the exposure time on the wall clock (time.time, s)",
            "scene": self.spec.get("scene") or "object",
            "calibration_target": self.target.kind,
        }


class TruthLogger:
    """The served world's ground truth of motion as JSON lines (``sim serve --truth-log FILE``, issue 13).

    A thread samples the emulators themselves — not any driver or labctl process — every
    ``period_s`` (default 10 ms) and appends one line per change, plus a first line when it starts:
    ``{"mono": s, "t": s, "robot_moving": bool, "table_moving": bool, "table_state": GRBL state,
    "robot_stop": [start, end] | null}``. ``mono`` is CLOCK_MONOTONIC (``time.monotonic()``, shared
    by every process on the host, so a run's record converts it with its own ``origin``); ``t`` is
    the served lab's clock; ``robot_stop`` is the latest stop ramp on CLOCK_MONOTONIC (when the
    controller began braking and when it is at rest). Each line is one ``os.write`` on an
    ``O_APPEND`` descriptor: a reader never sees half a line except the one being written.
    Resolution: the sampling period, plus the sample's own time under load (``period_s`` bounds it
    only on an idle machine; ``mono`` is taken after the sample, so a change is never early); the
    last line, written on exit, gives the longest gap between samples.
    """

    def __init__(self, lab: LiveSimLab, path, period_s: float = 0.01):
        import threading

        self.lab, self.period_s = lab, float(period_s)
        self._fd = os.open(os.fspath(path), os.O_WRONLY | os.O_CREAT | os.O_APPEND | getattr(os, "O_CLOEXEC", 0),
                           0o666)
        self._halt = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="truth-log", daemon=True)
        self.lines = 0
        self.samples = 0
        self.max_gap_s = 0.0  # the longest time between two samples (the log's real resolution)
        self.gaps_over_20ms = 0

    def start(self) -> TruthLogger:
        """Start sampling in a daemon thread; returns self."""
        self._thread.start()
        return self

    def sample(self) -> dict:
        """The served devices' state now: monotonic time (s), robot/table moving, GRBL state, and the
        robot's stop ramp [start, end] (monotonic s) if one ran."""
        st = self.lab.device_state()
        ramp = self.lab.robot_stop()
        origin = self.lab.origin
        return {"mono": round(st["t"] + origin, 4), "t": round(st["t"], 4), "robot_moving": st["robot_moving"],
                "table_moving": st["table_moving"], "table_state": st["table_state"],
                "robot_stop": None if ramp is None else [round(ramp[0] + origin, 4), round(ramp[1] + origin, 4)]}

    def _write(self, line: dict) -> None:
        import json

        os.write(self._fd, (json.dumps(line) + "\n").encode())
        self.lines += 1

    def _loop(self) -> None:
        last_key, last_t = None, None
        while not self._halt.is_set():
            line = self.sample()
            key = (line["robot_moving"], line["table_moving"], line["table_state"], line["robot_stop"])
            if last_t is not None:
                self.max_gap_s = max(self.max_gap_s, line["mono"] - last_t)
                self.gaps_over_20ms += line["mono"] - last_t > 0.02
            last_t = line["mono"]
            self.samples += 1
            if key != last_key:
                last_key = key
                self._write(line)
            self._halt.wait(self.period_s)

    def stop(self) -> None:
        """Stop sampling; the last line says how well the log kept its period: ``{"mono", "end": true,
        "samples", "max_gap_s", "gaps_over_20ms"}`` (no ``robot_moving``: readers of motion skip it)."""
        import contextlib
        import time

        self._halt.set()
        self._thread.join(timeout=2.0)
        with contextlib.suppress(OSError):
            self._write({"mono": round(time.monotonic(), 4), "end": True, "samples": self.samples,
                         "max_gap_s": round(self.max_gap_s, 4), "gaps_over_20ms": self.gaps_over_20ms})
        os.close(self._fd)


def write_served_lab(lab: Lab, out, served: ServedLab, *, force: bool = False):
    """Write ``out``: a lab whose driver files use only real kinds (grbl, serial, stream) pointing
    at ``served``'s endpoints, plus ``served_truth.json`` (the served world's ground truth).

    Calibration and object library are copied from ``lab`` (the served world is rendered from
    ``lab``'s driver files, so its calibration describes it; ``labctl calibrate`` on the written
    lab measures it again through the devices). The sim-only ground-truth fields are left out
    of the driver files. Written to a temporary folder and renamed: never half-written.
    Refuses a non-empty ``out`` unless it is an earlier served lab and ``force``.
    """
    import dataclasses
    import json
    import shutil
    from pathlib import Path

    import yaml

    from ..config.lab import DriverFiles

    out = Path(out).resolve()
    if out.exists() and any(out.iterdir()):
        if not (force and (out / "served_truth.json").is_file()):
            raise UserInputError(f"{out} is not empty; not overwriting it"
                                 + (" (--force replaces an earlier served lab)" if force or
                                    (out / "served_truth.json").is_file() else ""))
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)

    def plain(o):
        if isinstance(o, dict):
            return {k: plain(v) for k, v in o.items()}
        if isinstance(o, list | tuple):
            return [plain(v) for v in o]
        return o

    def dump(path, data, comment):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(f"# {comment}\n" + yaml.safe_dump(plain(data), sort_keys=False))

    ep = served.endpoints()
    try:
        no_table = served.conveyor is not None  # the conveyor moves the parts: the lab has no table
        drivers = DriverFiles(table=None) if no_table else DriverFiles()
        config = dataclasses.replace(lab.config, drivers=drivers, name=f"served lab ({lab.config.name})")
        if no_table:
            config = dataclasses.replace(config, run=dataclasses.replace(config.run, trajectory="external"))
        dump(tmp / "lab.yaml", dataclasses.asdict(config), "written by `labctl sim serve --lab-out`")
        real = "written by `labctl sim serve --lab-out`: real driver kinds on the served endpoints"
        if not no_table:
            table = dataclasses.replace(lab.table, kind="grbl", port=ep["table"], origin_w_mm=(0.0, 0.0, 0.0))
            dump(tmp / "drivers/table.yaml", dataclasses.asdict(table), real)
        robot = dataclasses.replace(lab.robot, kind="serial", port=ep["robot"])
        dump(tmp / "drivers/robot.yaml", dataclasses.asdict(robot), real)
        for role in ("fixed_camera", "mobile_camera"):
            cfg = dataclasses.replace(getattr(lab, role), kind="stream", url=ep[role], timestamps="header",
                                      eye_w_mm=None, target_w_mm=None)
            if served.spec.get("fps"):
                cfg = dataclasses.replace(cfg, fps=float(served.spec["fps"]))
            d = dataclasses.asdict(cfg)
            for sim_only in ("noise_sigma", "hand_eye_mm", "hand_eye_rpy_deg"):
                d.pop(sim_only, None)
            dump(tmp / f"drivers/{role}.yaml", d, real)
        link = dataclasses.replace(lab.host_link, transport="tcp", port=None)
        dump(tmp / "drivers/host_link.yaml", dataclasses.asdict(link), "written by `labctl sim serve --lab-out`")
        for item in ("calibration", "object_library"):
            if (lab.root / item).is_dir():
                shutil.copytree(lab.root / item, tmp / item, ignore=shutil.ignore_patterns(".*", "__pycache__"))
        (tmp / "runs").mkdir()
        (tmp / "served_truth.json").write_text(json.dumps({**served.truth(), "pid": os.getpid()}, indent=2))
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def emergency_stop(lab: Lab, endpoints: dict, timeout_s: float = 0.3) -> list[dict]:
    """The supervisor's stop bytes straight to the table's and robot's ports, one outcome per device
    (see :func:`labctl.runtime.stopping.send_stop_bytes`; failures are reported, never dropped)."""
    from .stopping import send_stop_bytes

    return send_stop_bytes(lab, endpoints, timeout_s)
