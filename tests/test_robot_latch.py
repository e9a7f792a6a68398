"""A STOP latched on the robot controller is named where it is made and refused before anything moves.

The driver's E40/E41 says what to run; ``labctl calibrate`` refuses a latched controller before the table moves
(as ``labctl run`` does); the one line of a calibration ended by a refused prompt, and of a run's stop, says the
STOP stays latched and names ``labctl robot clear``. The served lab (``labctl sim serve``: the reference
controller and the GRBL emulator on ptys) outlives each command, as real devices do."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from fakes import fake_robot
from test_hil import Served, labctl

from labctl.drivers.robot import RobotError, SerialRobot
from labctl.runtime.stopping import summary


def _latch(port: str, baud: int = 115200) -> None:
    with SerialRobot(port, baud, timeout_s=2.0) as robot:
        robot.stop()
        robot.status()
        assert robot.latched == "stopped"


def test_e41_names_the_command_that_clears_it():
    with fake_robot() as dev:
        _latch(dev.path)
        with SerialRobot(dev.path, 115200, timeout_s=2.0) as robot:
            with pytest.raises(RobotError) as err:
                robot.home()
    assert err.value.code == 41 and str(err.value).endswith("run `labctl robot clear`"), str(err.value)


def test_the_stop_summary_names_a_latch_left_on_the_controller():
    outcomes = [{"device": "table", "confirmed": True}, {"device": "robot", "confirmed": True, "latched": "stopped"}]
    line = summary(outcomes)
    assert line.startswith("table and robot stopped (confirmed); ") and "'stopped' latched" in line, line
    assert line.endswith("`labctl robot clear`") and "latched" not in summary(outcomes[:1])
    assert "latched" not in summary([{"device": "robot", "confirmed": True, "latched": None}])


def _table_at(lab) -> tuple[float, float]:
    r = labctl("--json", "table", "status", lab=lab, timeout=60)
    assert r.returncode == 0, r.stderr[-2000:]
    where = json.loads(r.stdout)
    return where["position"]["x"], where["position"]["y"]


@pytest.mark.skipif(sys.platform != "linux", reason="ptys and the served lab need Linux")
@pytest.mark.timeout(300)
def test_calibrate_refuses_a_latched_robot_before_the_table_moves_and_a_refused_prompt_latches_none(tmp_path):
    import yaml

    lab = tmp_path / "served"
    with Served(lab, "--scene", "calibration", "--seed", "4"):
        robot_cfg = yaml.safe_load((lab / "drivers" / "robot.yaml").read_text())
        assert labctl("table", "move", "300", "250", "--unlock", lab=lab, timeout=60).returncode == 0
        with SerialRobot(robot_cfg["port"], robot_cfg["baud"], timeout_s=2.0) as robot:
            rest = robot.status().T_base_flange
        _latch(robot_cfg["port"], robot_cfg["baud"])

        r = labctl("calibrate", "--prompt-command", "true", lab=lab, timeout=120)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 3 and len(lines) == 1, r.stderr[-2000:]
        assert "latched 'stopped'" in lines[0] and lines[0].endswith("run `labctl robot clear`"), lines
        assert _table_at(lab) == (300.0, 250.0)  # nothing moved
        with SerialRobot(robot_cfg["port"], robot_cfg["baud"], timeout_s=2.0) as robot:
            st = robot.status()
            assert robot.latched == "stopped" and not st.moving and np.allclose(st.T_base_flange, rest)

        assert labctl("robot", "clear", lab=lab, timeout=60).returncode == 0
        # the operator refuses the first placement: nothing moves at a prompt, so the devices are read back and
        # no STOP is sent (it would latch on this controller until `labctl robot clear`)
        r = labctl("calibrate", "--prompt-command", "false", lab=lab, timeout=120)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1, r.stderr[-2000:]
        assert "--prompt-command" in lines[0] and "no STOP sent" in lines[0], lines
        assert "latched" not in lines[0] and "robot clear" not in lines[0], lines
        assert _table_at(lab) == (300.0, 250.0)
        with SerialRobot(robot_cfg["port"], robot_cfg["baud"], timeout_s=2.0) as robot:
            assert robot.status() is not None and robot.latched is None


@pytest.mark.parametrize("kind", ["serial", "sim"])
def test_the_supervisors_stop_reports_the_latch_a_real_controller_keeps(kind):
    """The run's last line after Ctrl-C/SIGTERM comes from the supervisor's own stop (``confirm_stopped``): on a
    controller that outlives the run it says the STOP stays latched; a built-in simulated one ends with the run."""
    import dataclasses

    from fakes import fake_grbl

    from labctl.config import load_lab
    from labctl.runtime.stopping import confirm_stopped
    from labctl.workspace import sample_lab_path

    sample = load_lab(sample_lab_path())
    with fake_robot() as robot_dev, fake_grbl() as table_dev:
        lab = dataclasses.replace(sample, robot=dataclasses.replace(sample.robot, kind=kind, baud=115200),
                                  table=dataclasses.replace(sample.table, kind="grbl", baud=115200))
        outcomes = confirm_stopped(lab, {"robot": robot_dev.path, "table": table_dev.path})
    line = summary(outcomes)
    assert [o["device"] for o in outcomes if o["confirmed"]] == ["table", "robot"], outcomes
    if kind == "serial":
        assert "'stopped' latched" in line and line.endswith("`labctl robot clear`"), line
    else:
        assert "latched" not in line, line
