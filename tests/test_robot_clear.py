"""A STOP latched on the robot controller (issue 12/13): a job refuses to start until the operator
clears it with ``labctl robot clear``, which moves nothing. Reference controller on a real pty."""

from __future__ import annotations

import pytest
from fakes import fake_robot, run_cli

from labctl.drivers.robot import RobotFault, SerialRobot


def _latch_stop(path: str) -> None:
    with SerialRobot(path, 115200, timeout_s=2.0) as robot:
        robot.stop()
        robot.status()
        assert robot.latched == "stopped"


def test_a_latched_stop_refuses_the_next_job_until_robot_clear(capsys):
    with fake_robot() as dev:
        _latch_stop(dev.path)
        with SerialRobot(dev.path, 115200, timeout_s=2.0) as robot:
            with pytest.raises(RobotFault, match="labctl robot clear"):
                robot.ensure_ready()  # what `labctl run` does before anything moves
            before = robot.status().T_base_flange
        code, out, err = run_cli(capsys, "robot", "clear", "--port", dev.path, "--baud", "115200")
        assert code == 0 and "cleared: stopped" in out.splitlines(), (out, err)
        with SerialRobot(dev.path, 115200, timeout_s=2.0) as robot:
            st = robot.ensure_ready()
            assert robot.latched is None and not st.moving
            assert (st.T_base_flange == before).all()  # CLEAR moves nothing
        code, out, err = run_cli(capsys, "--json", "robot", "clear", "--port", dev.path, "--baud", "115200")
        assert code == 0 and '"cleared": null' in out


def test_robot_clear_on_a_missing_port_is_one_line_exit_3(capsys, tmp_path):
    code, out, err = run_cli(capsys, "robot", "clear", "--port", str(tmp_path / "no-such-port"))
    assert code == 3 and len(err.strip().splitlines()) == 1 and "Traceback" not in err
