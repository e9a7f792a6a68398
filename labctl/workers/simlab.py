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
import time

import numpy as np

from ..config import Lab
from ..drivers.programs import program
from ..errors import UserInputError

#: where the table's carriage starts for each trajectory (mm, machine coordinates) — the object
#: then crosses the fixed camera's field while the run takes place
TRAJECTORY_STARTS = {"line": (150.0, 200.0), "arc": (200.0, 200.0), "circle": (200.0, 200.0),
                     "zigzag": (150.0, 170.0)}


def trajectory_program(name: str, speed_mm_s: float, lab: Lab) -> tuple[tuple[float, float], list[str]]:
    """``(start_xy, gcode_lines)`` of a named trajectory, or of a G-code file (started at the centre)."""
    if name in TRAJECTORY_STARTS:
        start = TRAJECTORY_STARTS[name]
        return start, program(name, speed_mm_s, start=start, travel_mm=lab.table.travel_mm)
    from ..drivers.programs import load_gcode

    try:
        lines = load_gcode(name)
    except OSError as exc:
        raise UserInputError(f"cannot read G-code file {name}: {exc}") from None
    travel = lab.table.travel_mm
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
        from ..sim.world import SimWorld

        return SimWorld.from_lab(self.lab, obj=obj, placement=placement, table_position=self.grbl.position_at,
                                 flange_pose_at=self.robot_emu.flange_pose_at)

    def advance(self, t: float) -> None:
        self.grbl.advance(t)
        self.robot_emu.advance(t)

    def stop(self) -> list[dict]:
        """Stop and confirm both devices; every outcome returned (labctl.workers.stopping)."""
        from .stopping import stop_devices

        return stop_devices({"robot": self.robot, "table": self.table})


def _locked(lock, fn):
    def call(*args):
        with lock:
            return fn(*args)

    return call


class LiveSimLab:
    """The simulated lab in real time: emulators on ptys, cameras behind a frame server."""

    def __init__(self, lab: Lab, spec: dict):
        self.lab, self.spec = lab, spec
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> LiveSimLab:
        from ..sim.camera import FrameServer, SimCamera
        from ..sim.clock import RealClock
        from ..sim.emulators.grbl import GrblEmulator
        from ..sim.emulators.pty import run_on_pty
        from ..sim.emulators.robot import RobotEmulator
        from ..sim.world import SimWorld, home_flange_pose

        lab = self.lab
        rng = np.random.default_rng(self.spec.get("seed", 0))
        self.object_name, obj, placement = _sim_object(lab, self.spec, rng)
        start, _ = trajectory_program(self.spec["trajectory"], self.spec["speed_mm_s"], lab)
        self.origin = time.monotonic()
        clock = RealClock()
        clock._origin = self.origin
        t = lab.table
        self.grbl = GrblEmulator(clock.now, travel_mm=t.travel_mm, max_feed_mm_min=t.max_feed_mm_min,
                                 accel_mm_s2=t.accel_mm_s2, start_mm=(start[0], start[1], 0.0))
        self.robot_emu = RobotEmulator(clock.now, lab.robot, start_pose=home_flange_pose(lab))
        self.table_pty = run_on_pty(self.grbl, t.baud, clock=clock.now)
        self._stack.callback(self.table_pty.stop)
        self.robot_pty = run_on_pty(self.robot_emu, lab.robot.baud, clock=clock.now)
        self._stack.callback(self.robot_pty.stop)
        self.world = SimWorld.from_lab(
            lab, obj=obj, placement=placement,
            table_position=_locked(self.table_pty.lock, self.grbl.position_at),
            flange_pose_at=_locked(self.robot_pty.lock, self.robot_emu.flange_pose_at))
        seed = int(self.spec.get("seed", 0))
        cams = {role: SimCamera(self.world, role, clock, fps=getattr(lab, f"{role}_camera").fps, seed=seed)
                for role in ("fixed", "mobile")}
        for cam in cams.values():
            cam.open()
        self.server = FrameServer(cams).start()
        self._stack.callback(self.server.stop)
        self.clock = clock
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def endpoints(self) -> dict:
        return {"table": self.table_pty.path, "robot": self.robot_pty.path, "origin": self.origin,
                "frame_server": (self.server.address, self.server.authkey)}

    def truth(self) -> dict:
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


def emergency_stop(lab: Lab, endpoints: dict, timeout_s: float = 0.3) -> list[dict]:
    """The supervisor's stop bytes straight to the table's and robot's ports, one outcome per device
    (see :func:`labctl.workers.stopping.send_stop_bytes`; failures are reported, never dropped)."""
    from .stopping import send_stop_bytes

    return send_stop_bytes(lab, endpoints, timeout_s)
