"""Stops stay inside (issue 19): for random accepted segments, end velocities and STOP times the arm
never leaves the workspace box and can always be brought home (hypothesis, reference controller)."""

from __future__ import annotations

import math

import numpy as np
from fakes import robot_test_limits
from hypothesis import HealthCheck, given, settings, target
from hypothesis import strategies as st

from labctl.drivers.robot_protocol import add_checksum, strip_checksum
from labctl.geometry import make_T, matrix_to_rotvec, rot_x
from labctl.sim.clock import VirtualClock
from labctl.sim.emulators.robot import RobotEmulator

CFG = robot_test_limits()
LO, HI = np.array(CFG.workspace_min_mm), np.array(CFG.workspace_max_mm)

unit = st.floats(0.0, 1.0)
segment = st.fixed_dictionaries({
    "target": st.tuples(unit, unit, unit),
    "pace": st.floats(0.6, 3.0),  # duration / the fastest rest-to-rest time over that distance
    "v": st.tuples(*[st.floats(-1.0, 1.0)] * 3),
    "v_scale": st.sampled_from([0.0, 0.05, 0.3, 1.0]),
    "w": st.tuples(*[st.floats(-1.0, 1.0)] * 3),
    "now": st.booleans(),  # SEGNOW instead of SEG
    "after": st.floats(0.0, 1.5),  # seconds to wait before sending it
})


def send(emu, line: str) -> list[str]:
    emu.receive((add_checksum(line) + "\n").encode())
    return [strip_checksum(x) for x in emu.read_output().decode().split("\n") if x]


def sampled_positions(emu, t_end: float, n: int = 500) -> np.ndarray:
    """Positions over [0, t_end] at n times plus every segment's ends and a ramp's rest time."""
    times = set(np.linspace(0.0, t_end, n).tolist())
    for s in emu.segments:
        times.update([s.t0, s.t1, min(s.t1, t_end)])
    pts = np.array([emu.position_at(t) for t in sorted(times) if t <= t_end])
    np.testing.assert_allclose(pts[-1], emu.state_at(t_end)[0], atol=1e-9)  # the cheap path agrees
    return pts


def within(points: np.ndarray, lo, hi, tol: float = 1e-6) -> bool:
    return bool(np.all(points >= lo - tol) and np.all(points <= hi + tol))


def run_case(start, segs, stop_how, stop_at):
    clk = VirtualClock()
    emu = RobotEmulator(clk, CFG, start_pose=make_T(rot_x(math.pi), start))
    emu.read_output()
    send(emu, "#1 HELLO 1.1")
    lo, hi = np.minimum(LO, start), np.maximum(HI, start)  # an arm outside may only come back
    accepted = 0
    prev = np.asarray(start, float)
    for i, s in enumerate(segs):
        clk.sleep(s["after"])
        send(emu, "#2 HB")
        goal = LO + np.array(s["target"]) * (HI - LO)
        d = float(np.linalg.norm(goal - prev))
        T = s["pace"] * max(1.875 * d / CFG.v_max_mm_s, math.sqrt(5.7735 * d / CFG.a_max_mm_s2), 0.1)
        prev = goal
        v = np.array(s["v"]) * CFG.v_max_mm_s * s["v_scale"]
        w = np.array(s["w"]) * 0.5
        rv = matrix_to_rotvec(rot_x(math.pi))
        args = " ".join(f"{x:.6f}" for x in (*goal, *rv, T, *v, *w))
        out = send(emu, f"#{10 + i} {'SEGNOW' if s['now'] else 'SEG'} {i + 1} {args}")
        accepted += out[0].split()[1] == "ok"
    total = max([emu.now + 0.1, *(x.t1 for x in emu.segments)])
    t_stop = emu.now + stop_at * (total - emu.now)
    while emu.now < t_stop - 1e-9:  # keep the watchdog fed up to the stop
        clk.sleep(min(0.2, t_stop - emu.now))
        send(emu, "#3 HB")
    if stop_how == "stop":
        assert send(emu, "#4 STOP")[0] == "$4 ok"
    elif stop_how == "watchdog":
        clk.sleep(CFG.watchdog_s + 0.01)
        emu.advance(clk.t)
        assert emu.fault == "watchdog" or not emu._commanded_at(emu.now)  # a stop ramp may still run
    for _ in range(200):  # let everything run out (feeding the watchdog if it must not trip)
        if not emu.moving:
            break
        clk.sleep(0.2)
        if stop_how == "none":
            send(emu, "#5 HB")
    assert not emu.moving
    points = sampled_positions(emu, emu.now)
    assert within(points, lo, hi), (points.min(axis=0), points.max(axis=0), lo, hi)
    if within(np.asarray(start)[None], LO, HI):
        assert within(points, LO, HI)
    # and home, always
    send(emu, "#6 CLEAR")
    out = send(emu, "#7 HOME")
    assert out[0].split()[1] == "ok", out
    t1 = float(out[0].split()[3])
    lines = []
    while emu.now < t1 + 0.05:
        clk.sleep(0.2)
        lines += send(emu, "#8 HB")
    assert "@DONE 0" in lines
    np.testing.assert_allclose(emu.state_at(emu.now)[0], CFG.home_mm, atol=1e-6)
    home_path = sampled_positions(emu, emu.now)
    assert within(home_path, lo, hi)
    return accepted


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(start=st.tuples(unit, unit, unit), segs=st.lists(segment, min_size=1, max_size=3),
       stop_how=st.sampled_from(["stop", "watchdog", "none"]), stop_at=st.floats(0.0, 1.0))
def test_random_segments_and_stops_stay_inside_and_home_is_reachable(start, segs, stop_how, stop_at):
    target(float(run_case(LO + np.array(start) * (HI - LO), segs, stop_how, stop_at)), label="accepted segments")


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(start=st.tuples(*[st.floats(-0.15, 1.15)] * 3), segs=st.lists(segment, min_size=1, max_size=2),
       stop_how=st.sampled_from(["stop", "watchdog", "none"]), stop_at=st.floats(0.0, 1.0))
def test_a_stray_arm_never_goes_further_out_and_comes_home(start, segs, stop_how, stop_at):
    run_case(LO + np.array(start) * (HI - LO), segs, stop_how, stop_at)


def test_the_issues_outward_segment_is_refused_and_an_inward_one_from_outside_accepted():
    """Issue 19 item 1: a path inside the box ending at the edge moving outward was accepted and
    braked to x = 1450 with xmax = 1400. Now refused; from outside, a move back in is accepted."""
    clk = VirtualClock()
    emu = RobotEmulator(clk, CFG)
    emu.read_output()
    rv = matrix_to_rotvec(rot_x(math.pi))
    r = " ".join(f"{x:.6f}" for x in rv)
    assert send(emu, f"#1 SEG 1 895 -450 900 {r} 2.5 150 0 0 0 0 0")[0].startswith("$1 E10")
    assert send(emu, f"#2 SEG 2 880 -450 900 {r} 2.5 150 0 0 0 0 0")[0].startswith("$2 ok")  # 13 mm to brake
    outside = RobotEmulator(clk, CFG, start_pose=make_T(rot_x(math.pi), [950.0, -450.0, 900.0]))
    outside.read_output()
    assert send(outside, f"#3 SEG 3 850 -450 900 {r} 2")[0].startswith("$3 ok")
    assert send(outside, f"#4 SEGNOW 4 960 -450 900 {r} 2")[0].startswith("$4 E10")  # further out: no


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(p0=st.tuples(unit, unit, unit), p1=st.tuples(unit, unit, unit), v0=st.tuples(*[st.floats(-1, 1)] * 3),
       v1=st.tuples(*[st.floats(-1, 1)] * 3), a0=st.tuples(*[st.floats(-1, 1)] * 3), scale=st.floats(0.0, 0.6),
       T=st.floats(0.2, 6.0), w0=st.tuples(*[st.floats(-1, 1)] * 3), turn=st.tuples(*[st.floats(-1.5, 1.5)] * 3))
def test_what_the_planner_passes_the_controller_accepts(p0, p1, v0, v1, a0, scale, T, w0, turn):
    """planning.check_segment (the host's last gate) and the controller's check agree one way: a segment
    the planner passes (end acceleration 0, as the dialect's segments end) is never refused."""
    from labctl.geometry import rotvec_to_matrix
    from labctl.planning import Limits, LimitViolation, QuinticSegment, check_segment

    limits = Limits.from_config(CFG)
    p0, p1 = LO + np.array(p0) * (HI - LO), LO + np.array(p1) * (HI - LO)
    v0, v1 = np.array(v0) * CFG.v_max_mm_s * scale, np.array(v1) * CFG.v_max_mm_s * scale
    a0 = np.array(a0) * CFG.a_max_mm_s2 * scale
    R0 = rot_x(math.pi)
    R1 = R0 @ rotvec_to_matrix(turn)
    w_body = np.array(w0) * limits.w_max * scale
    seg = QuinticSegment(0.0, T, p0, v0, a0, p1, v1, np.zeros(3), R0=R0, R1=R1, w0=w_body)
    try:
        check_segment(seg, limits)
    except LimitViolation:
        return
    emu = RobotEmulator(VirtualClock(), CFG, start_pose=make_T(R0, p0))
    ctl = emu._plan(1, p1, R1, T, v1, np.zeros(3), 0.0, (p0, v0, a0, R0, R0 @ w_body))
    assert emu._check(ctl, p0) == 0
