"""The simulated lab, assembled in one place: emulators, their ports and drivers, the world, the cameras.

:meth:`SimLab.build` is every simulated lab labctl runs:

* virtual trials, soak and tests — ``ports="inproc"`` on a :class:`~labctl.sim.clock.VirtualClock`:
  the real drivers (:class:`~labctl.drivers.grbl.GrblTable`, :class:`~labctl.drivers.robot.SerialRobot`)
  talk the real protocols to the emulators through in-process ports paced at the driver files' baud
  rates in virtual time;
* ``labctl calibrate`` on the simulator — the same, with the calibration target on the carriage
  (``Scene(target=…)``, :func:`labctl.sim.rigs.target_world`);
* a live run's lab and ``labctl sim serve`` — ``ports="pty"`` (or ``"tcp"``: each pty bridged to a TCP
  port as ser2net would) on a :class:`~labctl.sim.clock.RealClock`; the world then reads the emulators
  under their ptys' locks, so a frame never sees an emulator half-way through a byte;
* ``labctl devices`` — one device (``devices=("table",)``, ``("fixed",)``, ...): a camera alone renders
  the world with the table and robot standing where the emulators would stand (the world's defaults).

The GRBL emulator's carriage drives the world's table; the robot emulator's flange carries the mobile
camera. The caller keeps what is its own (which object, the trajectory, a frame server, stopping the
devices). :class:`TruthLogger` samples the emulators' motion — the ground truth a live run's record and
``sim serve --truth-log`` keep.
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

if TYPE_CHECKING:  # imported where used: a live run's workers import this module for table_config alone
    from .camera import SimCamera
    from .world import Placement, SimObject

#: the devices of a simulated lab, by role
DEVICES = ("table", "robot", "fixed", "mobile")
CAMERAS = ("fixed", "mobile")

Ports = Literal["inproc", "pty", "tcp"]


@dataclass(frozen=True)
class Scene:
    """What the table carries: ``obj`` at ``placement``, and/or a calibration ``target`` on its pins.

    With a ``target`` the world can switch between the two (:func:`labctl.sim.rigs.target_world`);
    ``calibration`` says which one shows first.
    """

    obj: SimObject | None = None
    placement: Placement | None = None
    target: Any = None  # a labctl.calibration target (PlaneTarget, ...): the sim may not import calibration
    calibration: bool = True

    @classmethod
    def test_block(cls, lab, seed: int = 0) -> Scene:
        """The built-in test block (markers of the lab's radius) at a placement drawn from ``default_rng(seed)``."""
        from .world import builtin_test_object, random_placement

        obj = builtin_test_object(lab.config.marker.radius_mm)
        return cls(obj, random_placement(obj, np.random.default_rng(seed)))


def table_config(lab):
    """The lab's table, or (no table: parts on a conveyor) the default table the simulator moves them on."""
    from ..config import TableConfig

    return lab.table if lab.table is not None else TableConfig()


def _locked(lock, fn):
    def call(*args):
        with lock:
            return fn(*args)

    return call


class SimLab:
    """A simulated lab: emulators, drivers or served ports, world and cameras on one clock (see the module doc).

    Attributes (None or empty where not built): ``grbl``, ``robot_emu`` (the emulators); ``table``,
    ``robot`` (the real drivers on in-process ports, ``ports="inproc"``); ``ptys`` and ``bridges``
    by device role (``"pty"``/``"tcp"``); ``world``; ``cameras`` by role (``fixed``, ``mobile``).
    """

    def __init__(self, lab, clock, seed: int = 0):
        self.lab, self.clock, self.seed = lab, clock, int(seed)
        self.grbl: Any = None  # labctl.sim.emulators.grbl.GrblEmulator
        self.robot_emu: Any = None  # labctl.sim.emulators.robot.RobotEmulator
        self.table: Any = None  # labctl.drivers.grbl.GrblTable
        self.robot: Any = None  # labctl.drivers.robot.SerialRobot
        self.ptys: dict[str, Any] = {}
        self.bridges: dict[str, Any] = {}
        self.world: Any = None  # a SimWorld; with a calibration target, one that can switch scenes (set_scene)
        self.cameras: dict[str, SimCamera] = {}
        self._locks: dict[str, Any] = {"table": threading.RLock(), "robot": threading.RLock()}
        self._stack = contextlib.ExitStack()

    @classmethod
    def build(cls, lab, clock, *, ports: Ports = "inproc", scene: Scene | Callable[[], Scene] | None = None,
              devices: Sequence[str] = DEVICES, seed: int = 0, baud: int | None = None,
              table_start_mm: Sequence[float] | None = None, robot_start: Literal["camera", "controller"] = "camera",
              fps: float | None = None, truth: bool = False,
              on_ports: Callable[[SimLab], None] | None = None) -> SimLab:
        """Assemble the simulated lab of ``lab`` (its driver files' sim fields) on ``clock``.

        ``ports``: the drivers on in-process ports (``inproc``), or the emulators served on ptys
        (``pty``) or TCP ports (``tcp``) for clients in other processes; ``baud`` overrides the driver
        files' rates. ``scene``: what the world shows (None: no world, no cameras). ``devices``: which
        of ``table``, ``robot``, ``fixed``, ``mobile`` to build. ``table_start_mm``: the carriage's
        power-up position (x, y; default the travel's centre, the object under the fixed camera).
        ``robot_start``: ``camera`` puts the mobile camera at ``robot.home_mm`` looking at the table's
        centre (:func:`~labctl.sim.world.home_flange_pose`), ``controller`` leaves the controller at its
        own home. ``fps`` overrides both cameras' rates; ``seed`` is the frames' noise; ``truth`` makes
        the cameras return ground truth with each frame. Nothing is opened or started but the ports.
        ``on_ports(sim)`` is called once the emulators serve their ports, before the world is built (a live run's
        clients connect meanwhile); ``scene`` may then be a function that makes it (the object read from the
        library after the ports are out).
        """
        from .camera import SimCamera
        from .emulators.grbl import GrblEmulator
        from .emulators.robot import RobotEmulator
        from .world import home_flange_pose

        unknown = set(devices) - set(DEVICES)
        if unknown or ports not in ("inproc", "pty", "tcp"):
            raise ValueError(f"unknown device(s) {sorted(unknown)} or ports {ports!r}")
        sim = cls(lab, clock, seed)
        try:
            if "table" in devices:
                t = table_config(lab)
                start = table_start_mm if table_start_mm is not None else (t.travel_mm[0] / 2, t.travel_mm[1] / 2)
                sim.grbl = GrblEmulator(clock.now, travel_mm=t.travel_mm, max_feed_mm_min=t.max_feed_mm_min,
                                        accel_mm_s2=t.accel_mm_s2, start_mm=(start[0], start[1], 0.0))
            if "robot" in devices:
                pose = home_flange_pose(lab) if robot_start == "camera" else None
                sim.robot_emu = RobotEmulator(clock.now, lab.robot, start_pose=pose, arm=arm_servo(lab))
            sim._connect(ports, baud)
            if on_ports is not None:
                on_ports(sim)
            if callable(scene):
                scene = scene()
            if scene is not None:
                sim._make_world(scene)
                for role in CAMERAS:
                    if role in devices:
                        rate = fps or {"fixed": lab.fixed_camera, "mobile": lab.mobile_camera}[role].fps
                        sim.cameras[role] = SimCamera(sim.world, role, clock, fps=rate, seed=seed, truth=truth)
        except BaseException:
            sim._stack.close()
            raise
        return sim

    def _connect(self, ports: Ports, baud: int | None) -> None:
        """The drivers on in-process ports, or the emulators on ptys (and TCP bridges)."""
        emulators = {"table": (self.grbl, table_config(self.lab).baud), "robot": (self.robot_emu, self.lab.robot.baud)}
        emulators = {role: (emu, rate) for role, (emu, rate) in emulators.items() if emu is not None}
        clock = self.clock
        if ports == "inproc":
            from ..drivers.grbl import GrblTable
            from ..drivers.robot import SerialRobot
            from .emulators.link import EmulatorPort

            def port(role):
                emu, rate = emulators[role]
                return EmulatorPort(emu, clock, baud or rate, name=f"sim://{role}")

            if "table" in emulators:
                self.table = GrblTable.from_config(table_config(self.lab), serial_port=port("table"), clock=clock)
            if "robot" in emulators:
                self.robot = SerialRobot.from_config(self.lab.robot, serial_port=port("robot"), clock=clock)
            return
        from .emulators.pty import run_on_pty

        for role, (emu, rate) in emulators.items():
            self.ptys[role] = dev = run_on_pty(emu, baud or rate, clock=clock.now)
            self._stack.callback(dev.stop)
            self._locks[role] = dev.lock
        if ports == "tcp":
            from .tcpserial import TcpSerialBridge

            for role, dev in self.ptys.items():
                self.bridges[role] = bridge = TcpSerialBridge(dev.path)
                self._stack.callback(bridge.stop)

    def _make_world(self, scene: Scene) -> None:
        def read(role, fn):  # a served emulator is read under its pty's lock
            return _locked(self._locks[role], fn) if role in self.ptys else fn

        table_position = flange_pose_at = joints_at = None  # no emulator: the world's own (table and robot at rest)
        if self.grbl is not None:
            table_position = read("table", self.grbl.position_at)
        if self.robot_emu is not None:
            flange_pose_at = read("robot", self.robot_emu.flange_pose_at)
            if self.robot_emu.arm is not None:  # the drawn arm is the controller's
                joints_at = read("robot", self.robot_emu.configuration_at)
        from .world import SimWorld

        if scene.target is None:
            self.world = SimWorld.from_lab(self.lab, obj=scene.obj, placement=scene.placement,
                                           table_position=table_position, flange_pose_at=flange_pose_at,
                                           arm_joints_at=joints_at)
            return
        from .rigs import target_world

        self.world = target_world(self.lab, scene.target, table_position=table_position,
                                  flange_pose_at=flange_pose_at, obj=scene.obj, placement=scene.placement,
                                  arm_joints_at=joints_at)
        self.world.calibration = bool(scene.calibration)

    # --- use ------------------------------------------------------------------------------------
    def emulator(self, role: str):
        """The emulator behind device ``role`` (``table`` or ``robot``)."""
        return {"table": self.grbl, "robot": self.robot_emu}[role]

    def drivers(self) -> dict:
        """The in-process drivers by role (``robot``, ``table``), as the stop path takes them."""
        return {role: dev for role, dev in (("robot", self.robot), ("table", self.table)) if dev is not None}

    def endpoints(self) -> dict[str, str]:
        """Where other processes reach the served devices: a pty path or a ``socket://`` URL, by role."""
        return {role: (self.bridges[role].url if role in self.bridges else dev.path) for role, dev in self.ptys.items()}

    def advance(self, t: float) -> None:
        """Advance the emulators to time ``t`` (s)."""
        for emu in (self.grbl, self.robot_emu):
            if emu is not None:
                emu.advance(t)

    def step_to(self, t: float) -> None:
        """Advance the clock (and the emulators with it) to time ``t`` (s)."""
        self.clock.sleep_until(t)
        self.advance(self.clock.now())

    def open(self) -> None:
        """Open the in-process drivers (table, then robot; virtual time passes: banners, queries) and the cameras."""
        for dev in (self.table, self.robot, *self.cameras.values()):
            if dev is not None:
                dev.open()

    def close(self) -> None:
        """Close the cameras and drivers, stop the served ports."""
        try:
            for dev in (*self.cameras.values(), self.robot, self.table):
                if dev is not None:
                    dev.close()
        finally:
            self._stack.close()

    def __enter__(self) -> SimLab:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def device_state(self) -> dict:
        """Whether the emulated robot and table are moving now, and the table's GRBL state (under the ports' locks)."""
        with self._locks["robot"]:
            robot_moving = bool(self.robot_emu.moving)
        with self._locks["table"]:
            self.grbl.advance(self.clock.now())
            table_moving, table_state = bool(self.grbl.moving), self.grbl.state_word
        return {"t": self.clock.now(), "robot_moving": robot_moving, "table_moving": table_moving,
                "table_state": table_state}

    def robot_stop(self) -> list[float] | None:
        """``[start, end]`` (s, this lab's clock) of the robot controller's latest stop ramp — the braking
        that follows a received ``STOP`` (or the controller's own watchdog): None before any."""
        with self._locks["robot"]:
            stops = [(s.t0, s.t1) for s in self.robot_emu.segments if s.seg_id == -1]
        return list(stops[-1]) if stops else None

    def check_alive(self) -> None:
        """Raise RuntimeError if a served emulator's thread died (it would silently stop answering)."""
        for role, dev in self.ptys.items():
            if not dev._thread.is_alive():
                raise RuntimeError(f"the {role} emulator stopped: {dev.errors[-1] if dev.errors else 'unknown'}")


class TruthLogger:
    """The simulated lab's ground truth of motion, sampled from the emulators themselves — not from any
    driver or labctl process — and handed to ``write`` one line per change.

    A line is ``{"t": s (the lab's clock), "robot_moving": bool, "table_moving": bool, "table_state": GRBL
    state, "robot_stop": [start, end] | None}`` (the latest stop ramp, :meth:`SimLab.robot_stop`). A change
    is one of moving/state and, with ``ramp_is_change``, a new stop ramp; ``first_line`` writes the first
    sample too. :meth:`sample` takes one sample (a caller's own loop: a live run's simulated lab);
    :meth:`start` samples every ``period_s`` in a daemon thread (``sim serve --truth-log``) until
    :meth:`stop`. ``samples``, ``max_gap_s`` and ``gaps_over_20ms`` say how well the period was kept
    (the log's real resolution: the period plus the sample's own time under load).
    """

    def __init__(self, lab: SimLab, write: Callable[[dict], None], *, period_s: float = 0.01,
                 first_line: bool = True, ramp_is_change: bool = True):
        self.lab, self.write, self.period_s = lab, write, float(period_s)
        self.first_line, self.ramp_is_change = first_line, ramp_is_change
        self._last: tuple | None = None
        self._t_last: float | None = None
        self.t_moving = time.monotonic()
        self.still_since: dict[str, float | None] = {"robot": None, "table": None}
        self.samples = 0
        self.max_gap_s = 0.0
        self.gaps_over_20ms = 0
        self._halt = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="truth-log", daemon=True)

    def sample(self) -> dict:
        """One sample: writes a line if it is a change; returns the devices' state with, per device, since
        when it has been still (``robot_still_since``, ``table_still_since``: s, None while moving)."""
        st = self.lab.device_state()
        ramp = self.lab.robot_stop()
        for dev in ("robot", "table"):
            if st[f"{dev}_moving"]:
                self.still_since[dev] = None
                self.t_moving = time.monotonic()
            elif self.still_since[dev] is None:
                self.still_since[dev] = st["t"]
        if self._t_last is not None:
            self.max_gap_s = max(self.max_gap_s, st["t"] - self._t_last)
            self.gaps_over_20ms += st["t"] - self._t_last > 0.02
        self._t_last = st["t"]
        self.samples += 1
        key = (st["robot_moving"], st["table_moving"], st["table_state"]) + ((ramp,) if self.ramp_is_change else ())
        first, changed = self._last is None, key != self._last
        self._last = key
        if changed and (self.first_line or not first):
            self.write({"t": st["t"], "robot_moving": st["robot_moving"], "table_moving": st["table_moving"],
                        "table_state": st["table_state"], "robot_stop": ramp})
        return {**st, "robot_still_since": self.still_since["robot"], "table_still_since": self.still_since["table"]}

    def still_for(self) -> float:
        """Seconds (wall) since a device was last seen moving."""
        return time.monotonic() - self.t_moving

    def start(self) -> TruthLogger:
        """Sample every ``period_s`` in a daemon thread; returns self."""
        self._thread.start()
        return self

    def _loop(self) -> None:
        while not self._halt.is_set():
            self.sample()
            self._halt.wait(self.period_s)

    def stop(self) -> None:
        """Stop the sampling thread."""
        self._halt.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)


class TruthFile:
    """A :class:`TruthLogger`'s lines as JSON lines on CLOCK_MONOTONIC (``sim serve --truth-log FILE``).

    Each line: ``{"mono": s, "t": s, "robot_moving", "table_moving", "table_state", "robot_stop"}``,
    ``mono`` = ``t`` + ``origin`` (the lab clock's origin on CLOCK_MONOTONIC, shared by every process on
    the host, so a run's record converts it with its own origin), the stop ramp on CLOCK_MONOTONIC too.
    Each line is one ``os.write`` on an ``O_APPEND`` descriptor: a reader never sees half a line except
    the one being written. :meth:`close` writes the last line, ``{"mono", "end": true, "samples",
    "max_gap_s", "gaps_over_20ms"}`` (no ``robot_moving``: readers of motion skip it).
    """

    def __init__(self, path, origin: float):
        self.origin = float(origin)
        self._fd = os.open(os.fspath(path), os.O_WRONLY | os.O_CREAT | os.O_APPEND | getattr(os, "O_CLOEXEC", 0),
                           0o666)
        self.lines = 0

    def _put(self, line: dict) -> None:
        import json

        os.write(self._fd, (json.dumps(line) + "\n").encode())
        self.lines += 1

    def write(self, line: dict) -> None:
        """Append one logger line, its times on CLOCK_MONOTONIC (s, 0.1 ms)."""
        o, ramp = self.origin, line["robot_stop"]
        self._put({"mono": round(line["t"] + o, 4), "t": round(line["t"], 4), "robot_moving": line["robot_moving"],
                   "table_moving": line["table_moving"], "table_state": line["table_state"],
                   "robot_stop": None if ramp is None else [round(ramp[0] + o, 4), round(ramp[1] + o, 4)]})

    def close(self, logger: TruthLogger | None = None) -> None:
        """Write the end line (with ``logger``'s sampling statistics) and close the file."""
        try:
            if logger is not None:
                with contextlib.suppress(OSError):
                    self._put({"mono": round(time.monotonic(), 4), "end": True, "samples": logger.samples,
                               "max_gap_s": round(logger.max_gap_s, 4), "gaps_over_20ms": logger.gaps_over_20ms})
        finally:
            os.close(self._fd)


@functools.lru_cache(maxsize=8)
def _arm_servo(arm, robot):
    from ..planning.arm import ArmModel
    from .emulators.arm_servo import ArmPolicy, ArmServo

    return ArmServo(ArmModel.from_config(arm), ArmPolicy.from_config(robot))


def arm_servo(lab):
    """The arm behind the simulated robot controller when the robot's driver file names one (``lab.arm``),
    else None: built once per arm and policy (the sweep of a trials run builds many labs)."""
    return None if lab.arm is None else _arm_servo(lab.arm, lab.robot)
