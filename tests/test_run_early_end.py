"""A live run that can never succeed ends early, with its cause on stderr, and both devices stopped.

Two labs built from the sample lab: one whose fixed camera looks for green markers (the simulated
object's are red, so the fixed camera never sees one), and one whose table program ends a second
in (a short G-code file) while the fixed camera again sees nothing. Each must fail well before
``run.timeout_s`` (90 s) with exit 1 (the run's expected failure), one ``labctl: error:`` line naming
the cause, the robot and the table confirmed stopped, and the simulator's ground truth still.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from labctl.records import load_run
from labctl.runtime.early_end import EarlyEnd
from labctl.runtime.stopping import still_after
from labctl.workspace import init_workspace


def _set(path: Path, key: str, value: str) -> None:
    text = path.read_text()
    new, n = re.subn(rf"(?m)^(\s*){key}:.*$", rf"\g<1>{key}: {value}", text)
    if n == 0:  # not in the file: under run:
        new = text.replace("\nrun:\n", f"\nrun:\n  {key}: {value}\n", 1)
    path.write_text(new)


@pytest.fixture(scope="module")
def blind_lab(tmp_path_factory) -> Path:
    lab = init_workspace(tmp_path_factory.mktemp("early") / "lab")
    _set(lab / "drivers" / "fixed_camera.yaml", "marker_hue_deg", "[100.0, 120.0]")  # green: never the red marker
    return lab


def _run(lab: Path, *args: str) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "labctl", "--lab", str(lab), "run", *args, "--seed", "1"],
                       capture_output=True, text=True, timeout=170)
    return p, time.monotonic() - t0


def _check_stopped(lab: Path, reason_words: str) -> None:
    run_dir = max((lab / "runs").glob("*"), key=lambda d: d.stat().st_mtime)
    run = load_run(run_dir)
    fail = run.of("failure")[-1]
    assert reason_words in fail["reason"], fail
    stopped = [e for e in run.of("devices_stopped") if e["role"] == "predictor"][-1]
    assert {o["device"] for o in stopped["outcomes"]} >= {"robot", "table"}, stopped
    assert all(o["confirmed"] for o in stopped["outcomes"]), stopped
    lag = still_after(run.events, fail["t"])  # the simulator's own ground truth
    assert lag["table"] < 1.0 and lag["robot"] < 1.0, lag


def test_unit_the_two_causes_and_their_bounds():
    e = EarlyEnd(no_marker_s=15.0, after_program_s=20.0, t0=2.0)
    assert e.check(16.9, waiting=True) is None
    assert e.check(17.1, waiting=True) == "no marker seen by the fixed camera in 15 s"
    e = EarlyEnd(no_marker_s=15.0, after_program_s=20.0, t0=0.0)
    assert e.check(10.0, waiting=False) is None  # tracking: the wait's clock restarts at the next loss
    assert e.check(20.0, waiting=True) is None
    assert e.check(35.5, waiting=True) is not None
    e = EarlyEnd(no_marker_s=None, after_program_s=20.0, t0=0.0)
    assert e.check(500.0, waiting=True) is None
    e.program_ended(30.0)
    e.program_ended(40.0)  # the first end is kept
    assert e.check(49.9, waiting=False) is None
    assert e.check(50.1, waiting=False) == "the table program ended at t=30.0 s and no identity in the 20 s since"


@pytest.mark.timeout(200)
def test_a_run_whose_fixed_camera_never_sees_a_marker_fails_early_with_the_cause(blind_lab):
    p, took = _run(blind_lab, "--trajectory", "line")
    lines = [x for x in p.stderr.splitlines() if x.strip()]
    assert p.returncode == 1, p.stderr
    assert len(lines) == 1 and lines[0].startswith("labctl: error:"), p.stderr
    assert "no marker seen by the fixed camera in 15 s" in lines[0], p.stderr
    assert took < 60, took  # 15 s of waiting plus start-up and the stop, not the run's 90 s
    _check_stopped(blind_lab, "no marker seen")


@pytest.mark.timeout(200)
def test_a_run_whose_table_program_ended_fails_early_with_the_cause(blind_lab, tmp_path):
    _set(blind_lab / "lab.yaml", "no_marker_s", "null")
    _set(blind_lab / "lab.yaml", "after_program_s", "3.0")
    prog = tmp_path / "short.gcode"
    prog.write_text("G21\nG90\nG1 X310 Y200 F1200\n")  # from the centre, 10 mm: over in about a second
    p, took = _run(blind_lab, "--trajectory", str(prog))
    lines = [x for x in p.stderr.splitlines() if x.strip()]
    assert p.returncode == 1, p.stderr
    assert len(lines) == 1 and re.search(r"the table program ended at t=\d+\.\d s and no identity in the 3 s since",
                                         lines[0]), p.stderr
    assert took < 60, took
    _check_stopped(blind_lab, "the table program ended")
