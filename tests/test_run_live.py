"""The live run: two worker processes and a supervisor, in real time on the simulated lab."""

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
from labctl.records.events import validate
from labctl.runtime.stopping import still_after
from labctl.workspace import init_workspace


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> Path:
    return init_workspace(tmp_path_factory.mktemp("live") / "lab")


def _labctl(*args, **kw):
    return subprocess.Popen([sys.executable, "-m", "labctl", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


@pytest.mark.timeout(180)
def test_live_run_identifies_with_two_worker_processes(lab):
    p = _labctl("--lab", str(lab), "run", "--trajectory", "line", "--seed", "2", "--json")
    out, err = p.communicate(timeout=170)
    assert p.returncode == 0, err
    res = json.loads(out)
    assert res["correct"] is True and res["identity"] == res["true_identity"]
    for key in ("identity", "true_identity", "correct", "time_to_identity_s", "views", "stages"):
        assert key in res
    run = load_run(res["record"])
    for e in run.events:  # all three processes wrote to the record the schema declares
        validate(e)
    started = run.of("worker_started")
    assert {e["role"] for e in started} == {"predictor", "recognizer"}
    pids = {e["pid"] for e in started}
    assert len(pids) == 2 and p.pid not in pids  # two separate processes besides the supervisor
    lines = (Path(res["record"]) / "events.jsonl").read_text().splitlines()
    first_two = [json.loads(line)["event"] for line in lines[:2]]
    assert first_two == ["worker_started", "worker_started"]
    # start-up, phase by phase (s after the command): the workers start beside the simulated lab and
    # open no device before its ports came; the first tracked frame ends it (issue 16)
    # the table's and the robot's ports come before the world is built, and they connect meanwhile; the camera
    # opens, and the table goes to its start, only once the lab is ready and the robot checked
    st = res["startup_s"]
    assert st["workers_forked"] < st["sim_lab_ports"] <= st["endpoints"] <= st["robot_ready"]
    assert st["sim_lab_ports"] < st["sim_lab_ready"] <= st["robot_and_camera_ready"] <= st["table_ready"]
    assert st["endpoints"] <= st["table_connected"] <= st["table_ready"] <= st["first_tracked_frame"]
    assert 0 < st["sim_lab_starting"] < st["workers_forked"]


def _wait_for(path_glob, predicate, timeout_s):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for run_dir in sorted(path_glob()):
            ev = run_dir / "events.jsonl"
            if ev.is_file():
                events = [json.loads(x) for x in ev.read_text().splitlines() if x.strip()]
                if predicate(events):
                    return run_dir, events
        time.sleep(0.05)
    raise AssertionError("the run never reached the awaited point")


@pytest.mark.timeout(180)
@pytest.mark.parametrize("role", ["predictor", "recognizer"])
def test_killed_worker_stops_robot_and_table(lab, role):
    before = set((lab / "runs").glob("*"))
    p = _labctl("--lab", str(lab), "run", "--trajectory", "line", "--seed", "3")
    try:
        run_dir, events = _wait_for(
            lambda: [d for d in (lab / "runs").glob("*") if d not in before],
            lambda evs: any(e["event"] == "segment" for e in evs), 120)
        pid = next(e["pid"] for e in events if e["event"] == "worker_started" and e["role"] == role)
        os.kill(pid, signal.SIGKILL)
        out, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode != 0
    lines = [x for x in err.strip().splitlines() if x.strip()]
    assert len(lines) == 1 and role in lines[0] and "stopped" in lines[0], err
    run = load_run(run_dir)
    for e in run.events:  # the exit paths' events too (devices_stopped, run_aborted, sim_truth)
        validate(e)
    aborted = run.of("run_aborted")
    assert aborted, "the record must say how the run ended"
    a = aborted[-1]
    assert set(a["devices_stopped"]) == {"robot", "table"}
    after = a["devices_after_stop"]
    assert after is not None and not after["robot_moving"] and not after["table_moving"]
    # the simulator's ground truth: table still, robot's controller told to stop, within 0.5 s (the robot
    # then brakes on its own profile, up to 1.5 s: see docs/notes/link_and_records.md)
    lag = still_after(run.events, a["t_stop_sent"])
    assert lag["table"] < 0.5 and lag["robot"] < 0.5, lag
    # the record is complete up to the failure: every line is valid JSON, the run's start is there
    assert [e["event"] for e in run.events[:2]] == ["worker_started", "worker_started"]


@pytest.mark.timeout(180)
def test_live_run_over_a_9600_bps_serial_host_link(tmp_path):
    """The two workers talk over an RS-232 line at 9600 bps (a paced pty null modem), as in 1996."""
    root = init_workspace(tmp_path / "lab")
    cfg = root / "drivers" / "host_link.yaml"
    cfg.write_text(cfg.read_text().replace("transport: local", "transport: serial"))
    p = _labctl("--lab", str(root), "run", "--seed", "2", "--json")
    out, err = p.communicate(timeout=170)
    assert p.returncode == 0, err
    res = json.loads(out)
    assert res["correct"] is True
    link = res["link"]
    assert link["transport"] == "serial" and link["baud"] == 9600 and link["frames_dropped"] == 0
    assert link["utilisation"] < 0.3  # heartbeats and every request and answer, with room to spare


def _ignore_sigint():
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.timeout(180)
@pytest.mark.parametrize("parent_ignored_sigint", [False, True])
def test_ctrl_c_stops_robot_and_table_and_keeps_the_record(lab, parent_ignored_sigint):
    """Also when started ignoring SIGINT, as a non-interactive shell starts a background job (``labctl run &``):
    before, that run went on to its end (exit 0) with the devices moving."""
    before = set((lab / "runs").glob("*"))
    p = _labctl("--lab", str(lab), "run", "--seed", "3", preexec_fn=_ignore_sigint if parent_ignored_sigint else None)
    try:
        run_dir, _ = _wait_for(lambda: [d for d in (lab / "runs").glob("*") if d not in before],
                               lambda evs: any(e["event"] == "segment" for e in evs), 120)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130 and "interrupted" in err and "record kept" in err
    assert len(err.strip().splitlines()) == 1, err
    run = load_run(run_dir)
    a = run.of("run_aborted")[-1]
    assert set(a["devices_stopped"]) == {"robot", "table"}
    assert all(o["confirmed"] for o in a["stop_outcomes"])  # status read back after the stop
    assert not a["devices_after_stop"]["robot_moving"] and not a["devices_after_stop"]["table_moving"]
    assert run.result["identity"] is None and "interrupted" in run.result["failure"]
