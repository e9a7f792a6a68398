"""The arm controller's dialect on a virtual clock: a 1.2 session byte for byte as before the arm, the
1.0 text for a 1.0 host, the order of the arm's checks and what a check costs."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from robot_session_script import SESSION_10, SESSION_12, run_session

from labctl.config import load_lab
from labctl.sim.clock import VirtualClock
from labctl.sim.emulators.arm_servo import ur_branch_ik
from labctl.sim.emulators.robot import RobotEmulator
from labctl.sim.lab import arm_servo
from labctl.sim.world import home_flange_pose
from labctl.workspace import sample_lab_path

DATA = Path(__file__).resolve().parent / "data" / "robot"


def _controller():
    lab = load_lab(sample_lab_path())
    clk = VirtualClock()
    return clk, RobotEmulator(clk.now, lab.robot, start_pose=home_flange_pose(lab), arm=arm_servo(lab))


def test_a_1_2_session_with_the_arm_is_byte_for_byte_the_recorded_one():
    clk, emu = _controller()
    assert emu.dialect == "1.4"
    assert run_session(emu, clk, SESSION_12) == (DATA / "session_1_2.txt").read_text()


def test_a_1_0_session_gets_exactly_the_1_0_text():
    clk, emu = _controller()
    lines = [ln.rpartition("*")[0] for ln in run_session(emu, clk, SESSION_10).splitlines()]
    assert lines[0] == "$1 ok labctl-robot 1.0 queue=8"  # queue= last, no profiles=
    assert len(lines[1].split()) == 2 + 10  # LIMITS: the 1.0 text's ten fields
    assert lines[2].startswith("$3 ok")  # segment id 0 is a 1.0 host's to use
    assert lines[4].split()[-1] == "none" and len(lines[4].split()) == 2 + 11  # STOP did not latch; no joints
    assert lines[5].startswith("$6 ok")


def test_the_branch_closed_form_inverts_the_forward_kinematics_in_every_branch():
    _, emu = _controller()
    m = emu.arm.model
    rng = np.random.default_rng(3)
    qs = rng.uniform(-math.pi, math.pi, size=(300, 6))
    Ts = np.array([m.fk(q) for q in qs])
    worst, solved = 0.0, 0
    for q, T in zip(qs, Ts):
        got, ok = ur_branch_ik(m, T[None], m.configuration(q))
        if ok[0]:
            solved += 1
            worst = max(worst, float(np.abs(m.fk(got[0]) - T).max()))
            assert np.allclose(np.remainder(got[0] - q + math.pi, 2 * math.pi) - math.pi, 0.0, atol=1e-7)
    assert solved >= 295 and worst < 1e-8


def test_the_arm_check_of_a_segment_costs_well_under_a_frame_time():
    """A 1.5-s quintic, sampled every 4 ms (376 poses), checked in a few ms of CPU time."""
    _, emu = _controller()
    T0 = home_flange_pose(load_lab(sample_lab_path()))
    start = (T0[:3, 3], np.zeros(3), np.zeros(3), T0[:3, :3], np.zeros(3))
    seg = emu._plan(1, T0[:3, 3] + [60.0, -40.0, 30.0], T0[:3, :3], 1.5, np.zeros(3), np.zeros(3), 0.0, start)
    costs = []
    for _ in range(15):
        t = time.process_time()
        ts, Ts = seg.sampled(emu.arm.policy.check_dt_s)
        code, qs = emu.arm.check(ts, Ts, emu.joints_at(0.0))
        costs.append(time.process_time() - t)
    assert code == 0 and len(ts) == 376
    assert float(np.median(costs)) < 0.010
