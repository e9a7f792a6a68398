"""The fault-injection table in the HIL set-up (issue 13): every device real, the ground truth from the served world.

``labctl sim serve --lab-out DIR --truth-log FILE`` runs as its own process for the whole module
(it is not part of any run and stays up across the cases): the GRBL and robot controller
emulators on ptys, the cameras as MJPEG streams, and a truth log of the emulators' motion
sampled every 10 ms on CLOCK_MONOTONIC. ``DIR`` is a lab whose drivers are ``grbl``, ``serial``
and ``stream`` only, with the calibration copied from the sample lab (it describes the served
world). Each case first does what an operator does after an emergency stop (the table back at the
start with ``table move --unlock``: a stop in motion leaves GRBL in Alarm, as real GRBL does; the
robot controller's latched STOP cleared), starts ``labctl run`` in its own session, strikes with
one signal at one stage (tests/fault_harness.py, shared with the live simulated lab's table), and
checks issue 13's promises against the served truth, which no labctl process writes.

Default: two cases; ``LABCTL_FAULT_TABLE=full``: every signal × target × stage.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import pytest
from fault_harness import ALL_CASES, FULL, check_fault, inject, read_truth_log
from test_hil import Served, _unlock_at

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="ptys and the served lab need Linux")

# the live table's default set also has SIGKILL of the supervisor; here three cases keep CI short (~15 s each)
DEFAULT_CASES = [("SIGINT", "group", "cruise"), ("SIGTERM", "group", "cruise"), ("SIGSTOP", "predictor", "intercept")]
CASES = ALL_CASES if FULL else DEFAULT_CASES


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    root = tmp_path_factory.mktemp("hil_faults")
    truth = root / "truth.jsonl"
    tcp = ("--tcp",) if os.environ.get("LABCTL_FAULT_HIL_TCP") == "1" else ()  # devices behind a ser2net-style bridge
    with Served(root / "served", "--object", "tee", "--seed", "3", "--truth-log", str(truth), *tcp) as s:
        assert s.info["truth_log"] == str(truth)
        yield s, truth


def _ready_for_a_run(lab: Path) -> None:
    """What the operator does after an emergency stop, before the next run: the table back at the line's
    start (``table move --unlock``: a stop in motion left GRBL in Alarm) and the robot controller's
    latched stop cleared (``CLEAR``, through the real driver; a run never clears it by itself: E41)."""
    from labctl.config import load_lab
    from labctl.drivers.robot import SerialRobot

    _unlock_at(lab, 150, 200)
    robot = SerialRobot.from_config(load_lab(lab).robot)
    robot.open()
    try:
        robot.clear()
    finally:
        robot.close()


def _truth_rows(path: Path) -> list[dict]:
    return [r for r in (json.loads(x) for x in path.read_text().splitlines() if x.endswith("}")) if "robot_moving" in r]


def _settled_truth(path: Path, timeout_s: float = 5.0) -> None:
    """Wait until the truth log's latest line shows both devices still (the serve samples on its own)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        rows = _truth_rows(path)
        if rows and not rows[-1]["robot_moving"] and not rows[-1]["table_moving"]:
            time.sleep(0.1)
            return
        time.sleep(0.05)


def test_truth_log_sees_a_table_move_it_was_not_told_about(served):
    """The log follows the served emulator itself: a `table move` through the real driver shows up as
    the table moving, then still, inside the command's own time window, with GRBL's states."""
    s, truth = served
    before = time.monotonic()
    _unlock_at(s.out, 200, 230)
    after = time.monotonic()
    _settled_truth(truth)
    rows = [r for r in _truth_rows(truth) if before <= r["mono"] <= after + 0.5]
    moving = [r for r in rows if r["table_moving"]]
    assert moving and all(r["table_state"] == "Run" for r in moving), rows
    assert not rows[-1]["table_moving"] and rows[-1]["table_state"] == "Idle", rows
    assert all(b["mono"] >= a["mono"] for a, b in zip(rows, rows[1:], strict=False))


@pytest.mark.timeout(300)
@pytest.mark.parametrize("fault,target,stage", CASES)
def test_hil_fault_stops_everything_within_half_a_second(served, fault, target, stage):
    s, truth_log = served
    _ready_for_a_run(s.out)
    got = inject(s.out, fault, target, stage)
    _settled_truth(truth_log)
    truth = read_truth_log(truth_log, got["origin"], got["mono_start"], time.monotonic())
    check_fault(got, fault, target, stage, truth=truth, setup="hil")


def test_truth_log_in_a_missing_folder_is_bad_input(capsys, tmp_path):
    from fakes import run_cli

    from labctl.workspace import sample_lab_path

    code, out, err = run_cli(capsys, "--lab", str(sample_lab_path()), "sim", "serve", "--truth-log",
                             str(tmp_path / "no-such-folder" / "truth.jsonl"))
    assert code == 2 and out == "", (code, out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "no-such-folder" in lines[0] and "Traceback" not in err
