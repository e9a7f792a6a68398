"""Shared cases for the stop-budget tests: random interceptions of a marker on the sample lab's table,
and the robot controller emulator's stop ramp as the oracle (docs/protocols/robot.md §Stopping)."""

from __future__ import annotations

import numpy as np

from labctl.planning import camera_placement_trajectory
from labctl.sim.emulators.robot import StopRamp
from labctl.tracking import PredictedPath


def view_targets(n: int, seed: int = 13):
    """``n`` camera-placement trajectories G(t): a marker on a random straight path across the table
    (up to 20 mm/s each way), seen from 1 m at 63° from a random azimuth."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        path = PredictedPath(0.0, rng.uniform([100, 100], [500, 300]), rng.uniform(-20, 20, 2), np.zeros(2))
        yield camera_placement_trajectory(path, 1000.0, 63.0, azimuth_deg=rng.uniform(-180, 180), marker_z_mm=40.0)


def stop_time(emu, p, v, w) -> float:
    """How long (s) the controller's stop ramp takes from flange velocity ``v`` (mm/s) and angular velocity
    ``w`` (rad/s; None: not turning) at ``p``."""
    w = np.zeros(3) if w is None else w
    return StopRamp(0.0, p, v, np.eye(3), w, emu.a_stop, emu.alpha_stop).t1
