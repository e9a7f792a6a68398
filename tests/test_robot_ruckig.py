"""The ruckig segment profile of the robot dialect 1.2 (issue 16 part A).

Oracles: ruckig's own ``Trajectory.at_time`` for the piecewise cubics the controller checks and runs;
brute-force sampling of the executed motion (positions and stop-ramp rest points) for the exact box
check; the real driver over a pty against the reference controller; a 1.1 controller for the fallback.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from fakes import fake_robot, robot_test_limits
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from labctl.drivers.robot import SerialRobot
from labctl.drivers.robot_protocol import add_checksum, strip_checksum
from labctl.geometry import make_T, matrix_to_rotvec, rot_x, rot_z, rotvec_to_matrix
from labctl.planning.limits import Limits
from labctl.planning.ruckig_interception import plan_interception_ruckig
from labctl.planning.ruckig_profile import JerkLimits, _Solver, plan_ruckig
from labctl.sim.clock import VirtualClock
from labctl.sim.emulators.robot import RobotEmulator, RuckigSegment

CFG = replace(robot_test_limits(), watchdog_s=60.0)  # the property test does not heartbeat
LO, HI = np.array(CFG.workspace_min_mm), np.array(CFG.workspace_max_mm)
A_STOP = CFG.a_max_mm_s2 / math.sqrt(3.0)


def send(emu, line: str) -> list[str]:
    emu.receive((add_checksum(line) + "\n").encode())
    return [strip_checksum(x) for x in emu.read_output().decode().split("\n") if x]


def _num(x: float) -> str:
    return f"{float(x):.6f}"


def seg_line(seq: int, cmd: str, sid: int, p, rv, T: float, v=None, extra: str = "") -> str:
    args = [str(sid), *map(_num, p), *map(_num, rv), _num(T)]
    if v is not None:
        args += [*map(_num, v), "0", "0", "0"]
    return f"#{seq} {cmd} {' '.join(args)} profile=ruckig{(' ' + extra) if extra else ''}"


def test_pieces_are_ruckigs_own_trajectory():
    """The exact piecewise cubics (what the controller checks and runs) equal ruckig's ``at_time``."""
    from ruckig import Trajectory

    rng = np.random.default_rng(5)
    lim = JerkLimits(500.0, 1500.0, 15000.0, math.radians(120), 4 * math.radians(120), LO, HI, A_STOP)
    for _ in range(12):
        R0 = rotvec_to_matrix(rng.normal(size=3))
        start = (rng.uniform(0, 600, 3), rng.normal(size=3) * 150, rng.normal(size=3) * 600, R0,
                 rng.normal(size=3) * 0.3)
        R1 = R0 @ rotvec_to_matrix(rng.normal(size=3) * 0.5)
        plan = plan_ruckig(start, rng.uniform(0, 600, 3), R1, np.zeros(3), np.zeros(3), np.zeros(3),
                           float(rng.choice([0.0, 2.5])), lim)
        assert plan.code == 0
        solver = _Solver.get()
        traj = Trajectory(6)
        solver.otg.calculate(solver.inp, traj)  # the same input, ruckig's own evaluation
        assert traj.duration == pytest.approx(plan.duration, abs=1e-12)
        for tau in np.linspace(0.0, plan.duration, 97):
            p, v, a = (np.asarray(x) for x in traj.at_time(tau)[:3])
            q = [np.concatenate([x, y]) for x, y in zip(plan.pos.state(tau), plan.rot.state(tau))]
            np.testing.assert_allclose(q[0], p, atol=1e-7)
            np.testing.assert_allclose(q[1], v, atol=1e-6)
            np.testing.assert_allclose(q[2], a, atol=1e-4)
        p0, v0, a0, R, w = plan.state(0.0)  # the start state is the controller's state, exactly
        for got, want in zip((p0, v0, a0, R, w), start):
            np.testing.assert_allclose(got, want, atol=1e-9)
        np.testing.assert_allclose(plan.state(plan.duration)[3], R1, atol=1e-9)


unit = st.floats(0.0, 1.0)
move = st.fixed_dictionaries({
    "target": st.tuples(unit, unit, unit),
    "T": st.sampled_from([0.0, 0.0, 0.5, 1.5]),
    "v": st.tuples(*[st.floats(-1.0, 1.0)] * 3),
    "v_scale": st.sampled_from([0.0, 0.0, 0.3, 1.0]),
    "turn": st.floats(-1.0, 1.0),
    "after": st.floats(0.05, 0.8),  # seconds into the motion before the splice
})


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(first=move, second=move, stop_at=st.floats(0.0, 1.0))
def test_accepted_ruckig_segments_stay_inside_and_splice_continuously(first, second, stop_at):
    """A ruckig SEG, then a ruckig SEGNOW from the moving state: whatever the controller accepts stays in the
    box with every stop-ramp rest point (sampled, independently of the exact check), and p, v, a and ω are
    continuous at the splice; a STOP at a random later instant comes to rest inside the box."""
    clk = VirtualClock()
    emu = RobotEmulator(clk, CFG, start_pose=make_T(rot_x(math.pi), [300.0, -450.0, 900.0]))
    emu.read_output()
    assert "1.2" in send(emu, "#1 HELLO 1.2")[0]
    seq = 2
    for k, m in enumerate((first, second)):
        p = LO + (0.05 + 0.9 * np.array(m["target"])) * (HI - LO)  # the walls still reachable by overshoot
        v = np.array(m["v"]) * m["v_scale"] * CFG.v_max_mm_s * 0.6
        rv = matrix_to_rotvec(rot_x(math.pi) @ rot_z(m["turn"]))
        before = emu.state_at(clk.now())
        reply = send(emu, seg_line(seq, "SEG" if k == 0 else "SEGNOW", 10 + k, p, rv, m["T"], v))
        seq += 1
        code = reply[0].split()[1]
        assert code in ("ok", "E10", "E12", "E13", "E14", "E17"), reply
        event(f"{'first' if k == 0 else 'splice'} {code}")
        if code == "ok":
            seg = emu.segments[-1]
            assert isinstance(seg, RuckigSegment) and seg.t0 == pytest.approx(clk.now())
            after = seg.state(seg.t0)
            for x, y in zip(before[:3] + before[4:], after[:3] + after[4:]):  # p, v, a, ω at the splice
                np.testing.assert_allclose(x, y, atol=1e-9)
            np.testing.assert_allclose(before[3], after[3], atol=1e-9)
            assert seg.t1 - seg.t0 >= m["T"] - 1e-9
        clk.advance(m["after"])
        emu.read_output()
    t_stop = clk.now() + stop_at * 2.0
    clk.advance(stop_at * 2.0)
    send(emu, f"#{seq} STOP")
    end = max([clk.now(), *(s.t1 for s in emu.segments)]) + 0.5
    times = np.union1d(np.linspace(0.0, end, 400), [s.t0 for s in emu.segments] + [s.t1 for s in emu.segments])
    P = np.array([emu.state_at(t)[0] for t in times])
    V = np.array([emu.state_at(t)[1] for t in times])
    rest = P + V * np.abs(V) / (2 * A_STOP)
    tol = 1e-6
    assert np.all(P >= LO - tol) and np.all(P <= HI + tol)
    assert np.all(rest >= LO - tol) and np.all(rest <= HI + tol)
    clk.advance(end - clk.now() + 0.1)
    assert not emu._moving_at(clk.now())
    assert t_stop <= clk.now()


def test_ruckig_checks_refuse_what_the_limits_forbid():
    """E16 (jmax above LIMITS'), E17 (no trajectory: an end velocity ruckig cannot reach), E10 (an end that
    brakes outside), E15 in a 1.1 session, E02 for ruckig-only arguments on a quintic; none of them moves."""
    clk = VirtualClock()
    emu = RobotEmulator(clk, CFG)
    emu.read_output()
    send(emu, "#1 HELLO 1.2")
    rv = matrix_to_rotvec(rot_x(math.pi))
    p = np.array([400.0, -400.0, 850.0])
    assert send(emu, seg_line(2, "SEG", 1, p, rv, 0, extra="jmax=1e9"))[0].split()[1] == "E16"
    assert send(emu, seg_line(3, "SEG", 1, p, rv, 0, extra="vmax=600"))[0].split()[1] == "E16"
    assert send(emu, seg_line(4, "SEG", 1, p, rv, 0, v=[0, 0, 900.0]))[0].split()[1] == "E17"
    edge = np.array([HI[0] - 5.0, -400.0, 850.0])
    assert send(emu, seg_line(5, "SEG", 1, edge, rv, 0, v=[300.0, 0, 0]))[0].split()[1] == "E10"
    assert send(emu, f"#6 SEG 1 400 -400 850 {' '.join(map(_num, rv))} 1 jmax=100")[0].split()[1] == "E02"
    assert send(emu, f"#7 SEG 1 400 -400 850 {' '.join(map(_num, rv))} 0")[0].split()[1] == "E11"
    assert send(emu, seg_line(8, "SEG", 1, p, rv, -1))[0].split()[1] == "E11"
    assert not emu.segments
    send(emu, "#9 HELLO 1.1")
    assert send(emu, seg_line(10, "SEG", 1, p, rv, 0))[0].split()[1] == "E15"
    assert len(send(emu, "#11 LIMITS")[0].split()) == 2 + 18
    send(emu, "#12 HELLO 1.2")
    assert send(emu, "#13 LIMITS")[0].split()[-1] == "30000"


def test_host_plan_is_what_the_controller_runs():
    """The planner's ruckig interception, sent as the run sends it, is accepted and runs the same duration to
    the same pose (the controller re-plans from its own identical state with the limits the segment carries)."""
    clk = VirtualClock()
    start = make_T(rot_x(math.pi), [300.0, -450.0, 900.0])
    emu = RobotEmulator(clk, CFG, start_pose=start)
    emu.read_output()
    limits = Limits(LO, HI, 0.98 * CFG.v_max_mm_s, 0.98 * CFG.a_max_mm_s2, 0.98 * math.radians(CFG.w_max_deg_s))
    R1 = rot_x(math.pi) @ rot_z(0.8)

    class G:
        rotation = R1

        def __call__(self, t):
            t = np.atleast_1d(t)
            p = np.stack([500 + 8 * t, -200 + 0 * t, 700 + 0 * t], 1)
            return p, np.zeros_like(p), np.zeros_like(p)

    jerk = JerkLimits.from_limits(limits, j_max=0.98 * 30000.0, alpha_max=4 * math.radians(120), a_stop=A_STOP)
    res = plan_interception_ruckig((start[:3, 3], np.zeros(3), np.zeros(3)), 0.0, G(), limits, 10.0,
                                   R0=start[:3, :3], jerk=jerk)
    assert res.reachable
    traj = res.trajectory
    wire = traj.limits.wire()
    extra = " ".join(f"{k}={v:g}" for k, v in wire.items())
    p1 = traj.state(traj.t1)[0]
    reply = send(emu, seg_line(1, "SEGNOW", 1, p1, matrix_to_rotvec(traj.orientation(traj.t1)), traj.t1 - traj.t0,
                               extra=extra))
    assert reply[0].split()[1] == "ok", reply
    t0, t1 = map(float, reply[0].split()[2:4])
    assert t1 - t0 == pytest.approx(traj.t1 - traj.t0, abs=2e-4)
    seg = emu.segments[-1]
    for tau in np.linspace(0.0, seg.t1 - seg.t0, 25):
        np.testing.assert_allclose(seg.state(seg.t0 + tau)[0], traj.state(tau)[0], atol=1e-3)


def test_driver_runs_ruckig_segments_and_falls_back_to_quintic():
    """The real driver over a pty: a 1.2 controller runs a ruckig segment (T = 0: as fast as allowed) to its
    target; against a 1.1 controller ``choose_profile`` falls back to quintic and a ruckig segment is refused
    before it is sent."""
    T1 = make_T(rot_x(math.pi), [420.0, -380.0, 820.0])
    with fake_robot() as dev, SerialRobot(dev.path, 115200, timeout_s=2.0, heartbeat_s=0.1) as robot:
        assert robot.choose_profile("ruckig") == "ruckig"
        assert robot.limits()["j_max_mm_s3"] == pytest.approx(30000.0)
        t0, t1 = robot.segment(T1, 0.0, 5, profile="ruckig", limits={"vmax": 300.0, "jmax": 9000.0})
        assert 0.0 < t1 - t0 < 2.0
        robot.wait_done(5, timeout_s=5)
        np.testing.assert_allclose(robot.status().T_base_flange[:3, 3], T1[:3, 3], atol=1e-3)

    class Controller11(RobotEmulator):
        dialect = "1.1"

    import time

    from fakes import FakeDevice

    dev = FakeDevice(Controller11(time.monotonic, robot_test_limits()), 115200, None)
    try:
        with SerialRobot(dev.path, 115200, timeout_s=2.0, heartbeat_s=0.1) as robot:
            assert robot.dialect == "1.1" and robot.profiles == ("quintic",)
            assert robot.choose_profile("ruckig") == "quintic"
            with pytest.raises(ValueError):
                robot.segment(T1, 0.0, 6, profile="ruckig")
    finally:
        dev.stop()


def test_run_ruckig_legs_brake_within_the_stop_budget():
    """The sample lab's ruckig legs (``ruckig_limits`` with ``run.robot_stop_budget_s``) come to rest within the
    budget by the controller's stop ramp from every instant, as the quintic legs do (test_robot_stop_budget.py)."""
    from interception_cases import stop_time, view_targets

    from labctl.config import load_lab
    from labctl.planning.limits import planning_limits
    from labctl.planning.ruckig_interception import ruckig_limits
    from labctl.planning.ruckig_profile import controller_limits
    from labctl.workspace import sample_lab_path

    lab = load_lab(sample_lab_path())
    budget = lab.config.run.robot_stop_budget_s
    lim = planning_limits(lab.robot, budget)
    jerk, base = ruckig_limits(lab.robot, budget), controller_limits(lab.robot)
    emu = RobotEmulator(lambda: 0.0, lab.robot)
    home = np.asarray(lab.robot.home_mm, float)
    worst, planned = 0.0, 0
    for G in view_targets(15):
        res = plan_interception_ruckig((home, np.zeros(3), np.zeros(3)), 0.0, G, lim, 15.0, R0=rot_x(math.pi),
                                       jerk=jerk, base=base)
        if not res.reachable:
            continue
        planned += 1
        traj = res.trajectory
        for t in np.linspace(traj.t0, traj.t1, 101):
            p, v, _ = traj.state(t)
            worst = max(worst, stop_time(emu, p, v, traj.angular_velocity(t)))
    assert planned >= 10
    assert worst <= budget * (1 + 1e-6), worst
    assert worst > 0.8 * budget


def test_trials_sweep_profiles_on_the_same_seeds(capsys):
    """``labctl trials --profile quintic,ruckig`` plans both profiles on the same seeds; the summary splits them;
    a bad profile is exit 2 with one line."""
    from fakes import run_cli

    from labctl.experiments.trials import plan_specs, summarize

    specs = plan_specs(2, ["line", "zigzag"], [4.0, 8.0], ["a", "b"], 10, ["quintic", "ruckig"])
    assert len(specs) == 16
    by = {p: [(s["trajectory"], s["speed_mm_s"], s["seed"], s["object_name"]) for s in specs if s["profile"] == p]
          for p in ("quintic", "ruckig")}
    assert by["quintic"] == by["ruckig"]
    results = [{"profile": s["profile"], "speed_mm_s": s["speed_mm_s"], "correct": s["seed"] == 10, "views": 1,
                "time_to_identity_s": 5.0 if s["profile"] == "quintic" else 4.0, "stages": {"standard": 1.0},
                "lower_bound_s": 2.0, "lower_bound_quintic_s": 2.5, "index": i, "seed": s["seed"]}
               for i, s in enumerate(specs)]
    out = {row["profile"]: row for row in summarize(results)["by_profile"]}
    assert out["quintic"]["time_to_identity_s_median"] == 5.0 and out["ruckig"]["time_to_identity_s_median"] == 4.0
    assert out["ruckig"]["success_rate"] == 0.5 and out["ruckig"]["stage_medians_s"] == {"standard": 1.0}
    code, _, err = run_cli(capsys, "trials", "--n", "1", "--profile", "trapezoid")
    assert code == 2 and err.count("\n") == 1 and "--profile" in err, err
