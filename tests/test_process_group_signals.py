"""A signal to the whole process group of ``labctl run``, as ``timeout``, systemd and ``docker stop`` send it.

The run is started in a session of its own, so that ``os.killpg`` reaches what those tools reach:
the supervisor, both workers, the simulated lab and the process server that started them. Each
run must end with its documented exit status (SIGTERM 143, SIGINT 130, SIGHUP 129), one line on
stderr, both devices confirmed stopped by the supervisor, and the simulator's own ground truth
(``sim_truth`` in the record) showing both still within 0.5 s of the stop.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from labctl.records import load_run
from labctl.runtime.stopping import still_after
from labctl.workspace import init_workspace


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> Path:
    return init_workspace(tmp_path_factory.mktemp("pgroup") / "lab")


def _new_run_reaching(proc, lab: Path, before: set, event: str, timeout_s: float) -> Path:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"the run ended (exit {proc.returncode}) before {event!r}: {proc.communicate()}")
        for run_dir in sorted(set((lab / "runs").glob("*")) - before):
            ev = run_dir / "events.jsonl"
            if ev.is_file() and any(json.loads(x)["event"] == event for x in ev.read_text().splitlines() if x.strip()):
                return run_dir
        time.sleep(0.05)
    raise AssertionError(f"the run never reached {event!r}")


@pytest.mark.timeout(240)
@pytest.mark.parametrize(("sig", "stage", "code", "words"), [
    (signal.SIGTERM, "segment", 143, "terminated (SIGTERM)"),     # the robot flying to intercept
    (signal.SIGTERM, "table_program", 143, "terminated (SIGTERM)"),  # tracking begins, the table moving
    (signal.SIGINT, "segment", 130, "interrupted (Ctrl-C)"),
    (signal.SIGHUP, "segment", 129, "hung up (SIGHUP)"),
])
def test_a_signal_to_the_process_group_stops_and_confirms_both_devices(lab, sig, stage, code, words):
    (lab / "runs").mkdir(exist_ok=True)
    before = set((lab / "runs").glob("*"))
    p = subprocess.Popen([sys.executable, "-m", "labctl", "--lab", str(lab), "run", "--trajectory", "line",
                          "--seed", "3"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    try:
        run_dir = _new_run_reaching(p, lab, before, stage, 150)
        os.killpg(p.pid, sig)  # the session's leader is the supervisor: its pid is the group's id
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    lines = [x for x in err.splitlines() if x.strip()]
    assert p.returncode == code, err
    assert len(lines) == 1 and words in lines[0] and "table and robot stopped (confirmed)" in lines[0], err
    run = load_run(run_dir)
    a = run.of("run_aborted")[-1]
    assert a["exit_code"] == code and set(a["devices_stopped"]) == {"robot", "table"}
    assert all(o["confirmed"] for o in a["stop_outcomes"]), a["stop_outcomes"]
    lag = still_after(run.events, a["t_stop_sent"])  # the simulator's ground truth, not a driver's word
    assert lag["table"] < 0.5 and lag["robot"] < 0.5, lag
