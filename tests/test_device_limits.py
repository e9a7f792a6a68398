"""The lab's driver files against what the devices say of themselves, before anything moves.

The robot: the host plans every segment from the driver file; a controller whose ``LIMITS`` are lower refuses
those segments mid-run (docs/protocols/robot.md §5-§6). The table: labctl writes programs inside the file's
travel at the file's feeds; GRBL moves by its own ``$$`` (``$110``/``$111``, ``$130``/``$131``). The end-to-end
case is out of process: ``labctl sim serve`` runs the reference controller and the GRBL emulator (the sample
lab's settings) on ptys, and the lab it writes is edited to promise more than they have. The table's check
against the real GRBL 1.1h firmware is in tests/test_grbl_firmware.py.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st
from test_hil import Served, labctl

from labctl.config import load_lab
from labctl.drivers.robot import SerialRobot
from labctl.runtime.devices import robot_limits_problem, table_settings_problem
from labctl.workspace import sample_lab_path

CFG = load_lab(sample_lab_path()).robot
TABLE = load_lab(sample_lab_path()).table
J = 20.0 * CFG.a_max_mm_s2  # the reference controller's jerk limit when the file sets none

#: LIMITS as the reference controller built from CFG sends them (docs/protocols/robot.md §9), written out here
CONTROLLER = {"workspace_min_mm": CFG.workspace_min_mm, "workspace_max_mm": CFG.workspace_max_mm,
              "v_max_mm_s": CFG.v_max_mm_s, "a_max_mm_s2": CFG.a_max_mm_s2, "w_max_deg_s": CFG.w_max_deg_s,
              "watchdog_s": CFG.watchdog_s, "a_stop_mm_s2": round(CFG.a_max_mm_s2 / math.sqrt(3), 6),
              "alpha_stop_deg_s2": 4 * CFG.w_max_deg_s, "j_max_mm_s3": J}

LIMIT_KEYS = ("v_max_mm_s", "a_max_mm_s2", "w_max_deg_s", "j_max_mm_s3")


def test_the_reference_controllers_limits_are_the_files():
    assert robot_limits_problem(CFG, CONTROLLER) is None


@given(scales=st.tuples(*[st.floats(0.05, 1.0)] * 4), shrink=st.floats(0.0, 100.0))
def test_a_file_at_or_below_the_controller_passes(scales, shrink):
    cfg = dataclasses.replace(CFG, **{k: CONTROLLER[k] * s for k, s in zip(LIMIT_KEYS, scales)},
                              workspace_min_mm=tuple(v + shrink for v in CFG.workspace_min_mm),
                              workspace_max_mm=tuple(v - shrink for v in CFG.workspace_max_mm))
    assert robot_limits_problem(cfg, CONTROLLER) is None


@given(key=st.sampled_from(LIMIT_KEYS), excess=st.floats(1e-4, 3.0))
def test_a_limit_above_the_controllers_is_named_with_the_value_to_set(key, excess):
    cfg = dataclasses.replace(CFG, **{key: CONTROLLER[key] * (1 + excess)})
    problem = robot_limits_problem(cfg, CONTROLLER)
    assert problem is not None and problem.startswith(f"{key}: ") and "\n" not in problem
    assert f"at most {CONTROLLER[key]:g}" in problem


@pytest.mark.parametrize("change, key", [
    ({"workspace_max_mm": (1400.0, 1300.0, 1301.0)}, "workspace_max_mm"),
    ({"workspace_min_mm": (-801.0, -900.0, -150.0)}, "workspace_min_mm"),
    ({"heartbeat_s": 0.5, "watchdog_s": 0.8}, "heartbeat_s"),
])
def test_a_box_or_heartbeat_the_controller_does_not_allow_is_named(change, key):
    assert robot_limits_problem(dataclasses.replace(CFG, **change), CONTROLLER).startswith(f"{key}: ")


def test_a_slower_stop_ramp_than_the_host_assumes_is_named():
    """The host assumes the controller brakes at amax/√3 per axis (its stop budget and box checks)."""
    slow = {**CONTROLLER, "a_stop_mm_s2": CONTROLLER["a_stop_mm_s2"] / 2}
    problem = robot_limits_problem(CFG, slow)
    assert problem.startswith("a_max_mm_s2: ") and f"at most {CFG.a_max_mm_s2 / 2:g}" in problem


def test_a_1_0_controller_without_the_later_fields_is_checked_on_what_it_sends():
    first_ten = {k: CONTROLLER[k] for k in ("workspace_min_mm", "workspace_max_mm", "v_max_mm_s", "a_max_mm_s2",
                                            "w_max_deg_s", "watchdog_s")}
    assert robot_limits_problem(CFG, first_ten) is None
    assert robot_limits_problem(dataclasses.replace(CFG, a_max_mm_s2=4000.0), first_ten).startswith("a_max_mm_s2")


#: GRBL's settings as the sample table's emulator reports them ($$), written out here
GRBL = {110: TABLE.max_feed_mm_min, 111: TABLE.max_feed_mm_min, 120: TABLE.accel_mm_s2, 121: TABLE.accel_mm_s2,
        130: TABLE.travel_mm[0], 131: TABLE.travel_mm[1]}


@given(feed=st.floats(0.05, 1.0), travel=st.tuples(st.floats(0.05, 1.0), st.floats(0.05, 1.0)),
       accel=st.floats(0.1, 10.0))
def test_a_table_file_inside_grbls_settings_passes(feed, travel, accel):
    cfg = dataclasses.replace(TABLE, max_feed_mm_min=TABLE.max_feed_mm_min * feed,
                              accel_mm_s2=TABLE.accel_mm_s2 * accel,
                              travel_mm=(TABLE.travel_mm[0] * travel[0], TABLE.travel_mm[1] * travel[1]))
    assert table_settings_problem(cfg, GRBL) is None


@given(axis=st.sampled_from([0, 1]), what=st.sampled_from(["rate", "travel"]), short=st.floats(0.05, 0.999))
def test_grbl_settings_below_the_file_are_named_with_the_value_to_set(axis, what, short):
    number = (110 if what == "rate" else 130) + axis
    settings = {**GRBL, number: GRBL[number] * short}
    problem = table_settings_problem(TABLE, settings)
    key = "max_feed_mm_min" if what == "rate" else "travel_mm"
    assert problem.startswith(f"{key}: ") and f"${number}" in problem and f"at most {settings[number]:g}" in problem


@pytest.mark.skipif(sys.platform != "linux", reason="ptys and the served lab need Linux")
def test_driver_files_above_the_devices_are_named_and_a_run_moves_nothing(tmp_path):
    lab = tmp_path / "served"
    with Served(lab):
        robot_file = lab / "drivers" / "robot.yaml"
        robot_cfg = yaml.safe_load(robot_file.read_text())
        robot_cfg["v_max_mm_s"] = 800.0  # the served controller has 500
        robot_file.write_text(yaml.safe_dump(robot_cfg))
        table_file = lab / "drivers" / "table.yaml"
        table_cfg = yaml.safe_load(table_file.read_text())

        checked = labctl("--json", "devices", lab=lab, timeout=60)
        assert checked.returncode == 3, checked.stderr[-2000:]
        rows = {r["role"]: r for r in json.loads(checked.stdout)["devices"]}
        assert rows["table"]["ok"], rows["table"]
        assert not rows["robot"]["ok"] and "v_max_mm_s: " in rows["robot"]["verdict"], rows["robot"]
        assert "at most 500" in rows["robot"]["verdict"]

        table_file.write_text(yaml.safe_dump({**table_cfg, "max_feed_mm_min": 9000.0}))  # the served GRBL has 6000
        checked = labctl("--json", "devices", lab=lab, timeout=60)
        table_row = next(r for r in json.loads(checked.stdout)["devices"] if r["role"] == "table")
        assert not table_row["ok"] and "max_feed_mm_min: " in table_row["verdict"], table_row
        assert "$110" in table_row["verdict"] and "at most 6000" in table_row["verdict"]
        table_file.write_text(yaml.safe_dump(table_cfg))

        # the served GRBL powers up homing-locked: vouch for it, away from the line's start (150, 200), so that a
        # run which went on would move the table there first
        assert labctl("table", "move", "300", "250", "--unlock", lab=lab, timeout=60).returncode == 0
        run = labctl("run", "--trajectory", "line", lab=lab, timeout=120)
        assert run.returncode == 3, (run.stdout[-1000:], run.stderr[-2000:])
        assert "v_max_mm_s: " in run.stderr and "at most 500" in run.stderr, run.stderr[-2000:]

        # nothing moved: the robot never ran a segment, and the table stands where it was put
        with SerialRobot(robot_cfg["port"], robot_cfg["baud"]) as robot:
            status = robot.status()
            assert not status.moving and status.segment_id == 0
        table = labctl("--json", "table", "status", lab=lab, timeout=60)
        assert table.returncode == 0, table.stderr[-2000:]
        where = json.loads(table.stdout)
        assert where["state"] == "Idle" and (where["position"]["x"], where["position"]["y"]) == (300.0, 250.0), where


def test_every_table_mismatch_is_named_on_one_line():
    """Feed above $110 and $111, travel beyond $130: all three are named, not only the first."""
    settings = {**GRBL, 110: 3000.0, 111: 4000.0, 130: 200.0}
    problem = table_settings_problem(TABLE, settings)
    assert problem is not None and "\n" not in problem and problem.count(" | ") == 2, problem
    for part in ("$110", "at most 3000", "$111", "at most 4000", "$130", "600 mm in X", "at most 200"):
        assert part in problem, (part, problem)
    assert "$131" not in problem


def test_every_robot_mismatch_is_named_on_one_line():
    cfg = dataclasses.replace(CFG, v_max_mm_s=CONTROLLER["v_max_mm_s"] * 2, heartbeat_s=CFG.watchdog_s,
                              workspace_max_mm=tuple(v + 10.0 for v in CFG.workspace_max_mm))
    problem = robot_limits_problem(cfg, CONTROLLER)
    assert problem is not None and "\n" not in problem and problem.count(" | ") == 2, problem
    assert "v_max_mm_s: " in problem and "workspace_max_mm: " in problem and "heartbeat_s: " in problem


def test_the_grbl_emulator_with_several_settings_below_the_file_is_refused_naming_each():
    """The table driver against labctl's GRBL emulator whose $$ differ from the file in two places."""
    from labctl.errors import DeviceError
    from labctl.runtime.devices import check_table_settings, open_device

    lab = load_lab(sample_lab_path())
    table = open_device("table", lab)
    table.emulator.settings.update({110: 3000.0, 130: 200.0})
    with table:
        with pytest.raises(DeviceError) as err:
            check_table_settings(table, lab)
    message = str(err.value)
    assert "\n" not in message and message.count(" | ") == 1, message
    assert "max_feed_mm_min: " in message and "$110" in message and "at most 3000" in message
    assert "travel_mm: 600 mm in X" in message and "$130" in message and "at most 200" in message
