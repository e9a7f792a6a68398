"""The robot controller emulator: quintic segments, limits, watchdog (docs/protocols/robot.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fakes import robot_test_limits

from labctl.drivers.robot_protocol import add_checksum, strip_checksum
from labctl.geometry import make_T, matrix_to_rotvec, rot_x, rot_z
from labctl.sim.clock import VirtualClock
from labctl.sim.emulators.robot import RobotEmulator, poly_eval, quintic_coeffs


def make():
    clk = VirtualClock()
    emu = RobotEmulator(clk, robot_test_limits())
    emu.read_output()
    return clk, emu


def req(emu, line: str) -> list[str]:
    """Send a request; the reply lines with their (verified) checksums removed."""
    emu.receive((line + "\n").encode())
    lines = [strip_checksum(ln) for ln in emu.read_output().decode().split("\n") if ln]
    assert None not in lines
    return lines


def test_checksums_catch_damaged_requests():
    _, emu = make()
    assert req(emu, add_checksum("#4 HB")) == ["$4 ok"]
    assert req(emu, "#4 HB*00")[0].startswith("$4 E05")


def seg_line(seq, sid, p, R, T, extra=""):
    rv = matrix_to_rotvec(R)
    return f"#{seq} SEG {sid} {p[0]} {p[1]} {p[2]} {rv[0]} {rv[1]} {rv[2]} {T}{extra}"


def test_quintic_meets_boundary_conditions():
    rng = np.random.default_rng(1)
    for _ in range(20):
        p0, v0, a0, p1, v1, a1 = rng.normal(size=(6, 3))
        T = float(rng.uniform(0.2, 3.0))
        c = quintic_coeffs(p0, v0, a0, p1, v1, a1, T)
        for got, want in ((poly_eval(c, 0), p0), (poly_eval(c, 0, 1), v0), (poly_eval(c, 0, 2), a0),
                          (poly_eval(c, T), p1), (poly_eval(c, T, 1), v1), (poly_eval(c, T, 2), a1)):
            assert np.allclose(got, want, atol=1e-9)


def test_segment_reaches_target_at_its_duration():
    clk, emu = make()
    R = rot_x(math.pi) @ rot_z(0.3)
    out = req(emu, seg_line(1, 7, (400.0, -300.0, 700.0), R, 2.0))
    assert out[0].startswith("$1 ok")
    t0, t1 = map(float, out[0].split()[2:4])
    assert t1 - t0 == pytest.approx(2.0)
    mid = emu.flange_pose_at(t0 + 1.0)
    assert emu.moving
    clk.sleep(0.4)
    req(emu, "#2 HB")
    clk.sleep(0.4)
    req(emu, "#3 HB")
    clk.sleep(0.4)
    req(emu, "#4 HB")
    clk.sleep(0.4)
    req(emu, "#5 HB")
    clk.sleep(0.5)
    out = emu.read_output().decode()
    assert "@DONE 7*" in out
    T = emu.flange_pose_at(t1 + 0.1)
    assert np.allclose(T[:3, 3], [400, -300, 700], atol=1e-6)
    assert np.allclose(T[:3, :3], R, atol=1e-6)
    # symmetric rest-to-rest quintic: half way in time is half way in space
    assert np.allclose(mid[:3, 3], (np.array([300, -450, 900]) + [400, -300, 700]) / 2, atol=1e-6)


@pytest.mark.parametrize("line,code", [
    ("#1 SEG 1 400 -300 10 3.1416 0 0 5", "E10"),  # below the workspace box
    ("#1 SEG 1 800 300 700 3.1416 0 0 0.5", "E12"),  # too fast
    ("#1 SEG 1 400 -300 700 3.1416 0 0 0", "E11"),  # zero duration
    ("#1 SEG 1 400 -300 700", "E02"),  # missing values
    ("#1 SEG 1 400 -300 700 3.1416 0 0 nan", "E02"),
    ("#1 FLY", "E01"),
])
def test_limits_and_bad_requests(line, code):
    _, emu = make()
    out = req(emu, line)
    assert out[0].split()[:2] == ["$1", code]
    assert not emu.moving


def test_malformed_request_gets_async_error():
    _, emu = make()
    assert req(emu, "hello") == ["@ERR E03 malformed request"]


def test_watchdog_stops_the_robot_when_heartbeats_stop():
    clk, emu = make()
    req(emu, seg_line(1, 3, (600.0, -100.0, 700.0), rot_x(math.pi), 4.0))
    clk.sleep(1.0)  # no heartbeat for 1 s > watchdog 0.5 s
    out = emu.read_output().decode()
    assert "@WATCHDOG 0.5*" in out and emu.fault == "watchdog"
    clk.sleep(1.0)
    assert not emu.moving
    p_stop = emu.flange_pose_at(clk.t)[:3, 3]
    assert np.linalg.norm(p_stop - [600, -100, 700]) > 50  # it did not finish the segment
    assert req(emu, seg_line(2, 4, (500.0, -100.0, 700.0), rot_x(math.pi), 4.0))[0].startswith("$2 E40")
    assert req(emu, "#3 CLEAR") == ["$3 ok"]


def test_segnow_replans_from_the_current_state_continuously():
    clk, emu = make()
    req(emu, seg_line(1, 1, (500.0, -450.0, 900.0), rot_x(math.pi), 2.0))
    clk.sleep(0.4)
    req(emu, "#5 HB")
    clk.sleep(0.4)
    t_switch = clk.t
    p_before, v_before, *_ = emu.state_at(t_switch)
    out = req(emu, seg_line(2, 2, (450.0, -350.0, 850.0), rot_x(math.pi), 2.0).replace("SEG", "SEGNOW"))
    assert out[0].startswith("$2 ok")
    p_after, v_after, *_ = emu.state_at(t_switch + 1e-9)
    assert np.allclose(p_before, p_after, atol=1e-5) and np.allclose(v_before, v_after, atol=1e-3)


def test_end_velocity_then_automatic_stop():
    clk, emu = make()
    req(emu, seg_line(1, 1, (400.0, -450.0, 900.0), rot_x(math.pi), 1.0, " 50 0 0 0 0 0"))
    _, v, *_ = emu.state_at(1.0 - 1e-9)
    assert v[0] == pytest.approx(50.0, abs=1e-3)
    for _ in range(8):
        clk.sleep(0.25)
        req(emu, "#9 HB")
    assert not emu.moving
    assert emu.flange_pose_at(clk.t)[0, 3] > 400.0  # it coasted to rest past the segment's end


def test_status_and_queue_full():
    clk, emu = make()
    out = req(emu, "#1 STATUS")[0].split()
    assert out[:2] == ["$1", "ok"] and [float(v) for v in out[2:5]] == [300.0, -450.0, 900.0]
    for i in range(9):  # one running + eight waiting
        assert req(emu, seg_line(10 + i, i + 1, (300.0 + 10 * (i + 1), -450.0, 900.0), rot_x(math.pi), 1.0))[0] \
            .startswith(f"${10 + i} ok")
    assert req(emu, seg_line(30, 99, (400.0, -450.0, 900.0), rot_x(math.pi), 1.0))[0].startswith("$30 E20")
    assert req(emu, "#31 STOP") == ["$31 ok"]
    clk.sleep(0.5)
    assert not emu.moving


def test_flange_pose_is_a_rigid_transform_throughout():
    clk, emu = make()
    R1 = rot_x(math.pi) @ rot_z(1.0)
    req(emu, seg_line(1, 1, (450.0, -300.0, 800.0), R1, 3.0))
    for t in np.linspace(0, 3, 31):
        T = emu.flange_pose_at(float(t))
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
        assert T[3].tolist() == [0, 0, 0, 1]
    assert np.allclose(make_T(R1, [450, -300, 800]), emu.flange_pose_at(3.0), atol=1e-6)
