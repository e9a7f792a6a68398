"""The whole simulated lab in one process on a virtual clock (trials and tests).

:func:`build_virtual_lab` wires a :class:`~labctl.sim.clock.VirtualClock`, the GRBL table
emulator (its carriage position drives the world's table), the robot controller emulator (its
flange pose carries the mobile camera), the world with an object placed on the table, and both
simulated cameras. Everything is deterministic for a given seed: the
object's stable pose, yaw and offset are drawn from ``default_rng(seed)``, and every frame's
noise from ``(seed, camera, frame index)``.

The robot starts at the pose that puts the mobile camera at ``robot.home_mm`` looking at the
table's centre (:func:`~labctl.sim.world.home_flange_pose`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .camera import SimCamera
from .clock import VirtualClock
from .world import Placement, SimObject, SimWorld, builtin_test_object, random_placement

if TYPE_CHECKING:
    from .emulators.grbl import GrblEmulator
    from .emulators.robot import RobotEmulator


@dataclass
class VirtualLab:
    """A simulated lab in virtual time: one clock, the world, the GRBL and robot emulators, and the cameras by role."""
    clock: VirtualClock
    world: SimWorld
    table: GrblEmulator
    robot: RobotEmulator
    cameras: dict[str, SimCamera]
    seed: int

    def step_to(self, t: float) -> None:
        """Advance the clock (and both emulators with it) to time ``t``."""
        self.clock.sleep_until(t)
        self.table.advance(self.clock.now())
        self.robot.advance(self.clock.now())


def build_virtual_lab(lab, *, seed: int = 0, obj: SimObject | None = None, placement: Placement | None = None,
                      flange_pose_at: Callable[[float], np.ndarray] | None = None, table_start_mm=None,
                      truth: bool = False, supersample: int = 3, exposure_s: float = 0.0) -> VirtualLab:
    """Assemble the simulated lab of ``lab`` (driver files' sim fields) on a fresh virtual clock at t = 0.

    ``obj`` defaults to the built-in test block; ``placement`` to a random one drawn from the
    seed. ``table_start_mm`` is the carriage's power-up position (default: the travel's centre,
    so the object starts under the fixed camera). ``flange_pose_at`` overrides the robot
    emulator as the source of the flange pose.
    """
    from .emulators.grbl import GrblEmulator
    from .emulators.robot import RobotEmulator
    from .world import home_flange_pose

    clock = VirtualClock(0.0)
    t_cfg = lab.table
    start = table_start_mm if table_start_mm is not None else (t_cfg.travel_mm[0] / 2, t_cfg.travel_mm[1] / 2, 0.0)
    table = GrblEmulator(clock.now, travel_mm=t_cfg.travel_mm, max_feed_mm_min=t_cfg.max_feed_mm_min,
                         accel_mm_s2=t_cfg.accel_mm_s2, start_mm=start)
    robot = RobotEmulator(clock.now, lab.robot, start_pose=home_flange_pose(lab))
    if flange_pose_at is None:
        flange_pose_at = robot.flange_pose_at
    obj = obj if obj is not None else builtin_test_object(lab.config.marker.radius_mm)
    rng = np.random.default_rng(seed)
    placement = placement if placement is not None else random_placement(obj, rng)
    world = SimWorld.from_lab(lab, obj=obj, placement=placement, table_position=table.position_at,
                              flange_pose_at=flange_pose_at, supersample=supersample, exposure_s=exposure_s)
    cameras = {
        "fixed": SimCamera(world, "fixed", clock, fps=lab.fixed_camera.fps, seed=seed, truth=truth),
        "mobile": SimCamera(world, "mobile", clock, fps=lab.mobile_camera.fps, seed=seed, truth=truth),
    }
    return VirtualLab(clock=clock, world=world, table=table, robot=robot, cameras=cameras, seed=seed)
