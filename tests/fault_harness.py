"""The fault-injection harness shared by the live simulated lab's and the HIL set-up's fault tables (issue 13).

``inject`` starts ``labctl run`` in its own session, waits for a stage of the run (read from its
record), sends one signal to the supervisor, a worker or the whole process group, and collects
the exit status, stderr, the record and any process of the session left behind. ``check_fault``
asserts what issue 13 promises for every fault, with the ground truth of motion passed in
(``sim_truth`` events: from the record in the live simulated lab, from the serve process's truth
log in the HIL set-up), and returns the numbers for the notes' table.
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

from labctl.records import read_events
from labctl.runtime.stopping import still_after

STAGES = {  # when to strike: the first event of the run that matches
    "wait": lambda e: e["event"] == "table_program",
    "intercept": lambda e: e["event"] == "segment",
    # CRUISE_DELAY_S after the first robot segment was sent: the segments to the first view last about
    # 0.8-1.2 s, so the robot is near its peak speed there and brakes longest
    "cruise": lambda e: e["event"] == "segment",
    "standard": lambda e: e["event"] == "stage" and e.get("stage") == "standard",
}
# (fault, target) -> exit status; -9: the supervisor itself is killed (the shell reports -9)
EXPECTED = {
    ("SIGINT", "group"): 130,
    ("SIGTERM", "group"): 143,  # what timeout, systemd and docker stop send
    ("SIGHUP", "group"): 129,  # the terminal closed
    ("SIGTERM", "supervisor"): 143,
    ("SIGTERM", "predictor"): 1,
    ("SIGTERM", "recognizer"): 1,
    ("SIGKILL", "supervisor"): -9,
    ("SIGKILL", "predictor"): 1,
    ("SIGKILL", "recognizer"): 1,
    ("SIGSTOP", "supervisor"): 1,
    ("SIGSTOP", "predictor"): 1,
    ("SIGSTOP", "recognizer"): 1,
}
CRUISE_DELAY_S = 0.4
FULL = os.environ.get("LABCTL_FAULT_TABLE") == "full"
ALL_CASES = [(f, t, s) for (f, t) in EXPECTED for s in STAGES]


def session_pids(sid: int) -> list[int]:
    """Processes whose session id is ``sid`` (the run was started in a new session)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[3]) == sid and fields[0] != "Z":
            out.append(int(d.name))
    return out


def events_of(run_dir: Path) -> list[dict]:
    return read_events(run_dir) if (run_dir / "events.jsonl").is_file() else []


def _wait_for_stage(lab: Path, before: set, stage: str, p, timeout_s: float) -> tuple[Path, list[dict]]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if p.poll() is not None:  # e.g. the robot's own 0.5 s watchdog tripped on a starved machine
            pytest.skip(f"the run ended by itself before stage {stage}, so no fault was injected: "
                        f"{p.stderr.read().strip()}")
        for run_dir in [d for d in (lab / "runs").glob("*") if d not in before]:
            events = events_of(run_dir)
            if any(STAGES[stage](e) for e in events):
                return run_dir, events
        time.sleep(0.05)
    raise AssertionError(f"the run never reached stage {stage}")


def first_stop_t(events: list[dict]) -> float:
    """The first stop command on the run's clock: the supervisor's stop bytes or a worker's stop."""
    ts = [e["t_stop_sent"] for e in events if e["event"] == "run_aborted"]
    ts += [e["t"] for e in events if e["event"] == "devices_stopped" and e.get("role") == "predictor"]
    assert ts, "no stop was recorded"
    return min(ts)


def inject(lab: Path, fault: str, target: str, stage: str, seed: int = 3) -> dict:
    """Start ``labctl run`` in its own session, strike at ``stage``, and collect what happened.

    Returns ``code``, ``stderr``, ``run_dir``, ``t_fault`` (the run's clock, s), ``origin`` (the
    run clock's origin on CLOCK_MONOTONIC), ``mono_start``/``mono_end`` (CLOCK_MONOTONIC around the
    case) and ``left`` (processes of the run's session still there)."""
    before = set((lab / "runs").glob("*"))
    mono_start = time.monotonic()
    p = subprocess.Popen([sys.executable, "-m", "labctl", "--lab", str(lab), "run", "--trajectory", "line",
                          "--seed", str(seed)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    try:
        run_dir, events = _wait_for_stage(lab, before, stage, p, 150)
        started = {e["role"]: e for e in events if e["event"] == "worker_started"}
        # the run clock's origin on CLOCK_MONOTONIC, as the predictor logged it once the simulated lab had set it
        origin = next(e["origin"] for e in events if e["event"] == "run_clock" and e["role"] == "predictor")
        if stage == "cruise":  # (the segment event's t_end is on the plan's clock, not a reliable end)
            seg = next(e for e in events if STAGES[stage](e))
            time.sleep(max(0.0, origin + seg["t"] + CRUISE_DELAY_S - time.monotonic()))
        pid = p.pid if target in ("supervisor", "group") else started[target]["pid"]
        t_fault = time.monotonic() - origin
        sig = getattr(signal, fault)
        if target == "group":
            os.killpg(p.pid, sig)
        else:
            os.kill(pid, sig)
        if fault == "SIGSTOP" and target == "supervisor":
            time.sleep(5.0)  # the workers give up on it after dead_after_s and stop the devices themselves
            os.kill(pid, signal.SIGCONT)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    deadline = time.monotonic() + 20
    while session_pids(p.pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    return {"code": p.returncode, "stderr": err, "run_dir": run_dir, "t_fault": t_fault, "origin": origin,
            "mono_start": mono_start, "mono_end": time.monotonic(), "left": session_pids(p.pid)}


def check_fault(got: dict, fault: str, target: str, stage: str, truth: list[dict] | None = None,
                setup: str = "live") -> dict | None:
    """Issue 13's promises for one injected fault; ``truth`` (``sim_truth`` events on the run's clock)
    defaults to the record's own. Returns the case's numbers (also appended to ``$LABCTL_FAULT_REPORT``
    as one JSON line), or None when the run finished normally while its supervisor was stopped."""
    assert got["left"] == [], f"processes left behind: {got['left']}"
    if (fault, target) == ("SIGSTOP", "supervisor") and got["code"] == 0:
        # struck near the end: the workers finished the run while the supervisor was stopped
        events = read_events(got["run_dir"], strict=True)
        stops = [e for e in events if e["event"] == "devices_stopped" and e["role"] == "predictor"]
        assert stops and all(o["confirmed"] for o in stops[-1]["outcomes"])
        return None
    assert got["code"] == EXPECTED[(fault, target)], got["stderr"]
    lines = [x for x in got["stderr"].splitlines() if x.strip()]
    if (fault, target) == ("SIGKILL", "supervisor"):
        assert lines == []  # nothing left to print it; the workers stop the devices on their own
    else:
        assert len(lines) == 1 and "Traceback" not in got["stderr"], got["stderr"]
        assert "stopped (confirmed)" in lines[0] and "record kept" in lines[0], lines[0]
    # the record reads back whole (every line one JSON object) and holds the run up to the fault
    events = read_events(got["run_dir"], strict=True)
    assert [e["event"] for e in events[:2]] == ["worker_started", "worker_started"]
    assert any(STAGES[stage](e) for e in events)  # the stage struck at is in the record
    stops = [e for e in events if e["event"] == "devices_stopped" and e["role"] == "predictor"]
    aborted = [e for e in events if e["event"] == "run_aborted"]
    if (fault, target) != ("SIGKILL", "supervisor"):
        assert aborted, "the record must say how the run ended"
        assert set(aborted[-1]["devices_stopped"]) == {"robot", "table"}
        assert all(o["confirmed"] for o in aborted[-1]["stop_outcomes"])
    if target in ("supervisor", "group") and fault != "SIGKILL" or fault == "SIGKILL" and target == "supervisor":
        assert stops, "the predictor records its own stop"
    if stops and fault != "SIGKILL":
        assert all(o["confirmed"] for o in stops[-1]["outcomes"]), stops[-1]
    # the simulator's ground truth: both devices at rest within 0.5 s of the first stop command
    t_stop = first_stop_t(events)
    truth = [e for e in (events if truth is None else truth) if e["event"] == "sim_truth"]
    if stage == "cruise":  # struck while the robot moves, else the case would not test its braking
        assert any(e["robot_moving"] and e["t"] <= got["t_fault"] for e in truth), "the robot was not moving"
    lag = still_after(truth, t_stop)
    row = {"setup": setup, "fault": fault, "target": target, "stage": stage, "code": got["code"],
           "detect_s": round(t_stop - got["t_fault"], 3), **{k: round(v, 3) for k, v in lag.items()}}
    report = os.environ.get("LABCTL_FAULT_REPORT")
    if report:  # one JSON line per case, for the notes' table
        with open(report, "a") as fh:
            fh.write(json.dumps(row) + "\n")
    assert lag["robot"] < 0.5 and lag["table"] < 0.5, row
    assert t_stop >= got["t_fault"] - 0.05  # the stop answers the fault, it did not precede it
    return row


def read_truth_log(path: Path, origin: float, mono_from: float, mono_to: float) -> list[dict]:
    """A served lab's truth log (``labctl sim serve --truth-log``) between two CLOCK_MONOTONIC times, as
    ``sim_truth`` events on a run's clock (``origin``: the run clock's origin on CLOCK_MONOTONIC). The
    state in force at ``mono_from`` comes first, so the window starts with what was moving then."""
    rows = []
    for text in Path(path).read_text().splitlines():
        try:
            row = json.loads(text)
        except ValueError:  # the line being written right now
            continue
        if "robot_moving" in row:  # not the closing summary line
            rows.append(row)
    before = [r for r in rows if r["mono"] < mono_from]
    window = before[-1:] + [r for r in rows if mono_from <= r["mono"] <= mono_to]
    return [{"event": "sim_truth", "t": r["mono"] - origin, "robot_moving": r["robot_moving"],
             "table_moving": r["table_moving"], "table_state": r["table_state"],
             "robot_stop": None if r["robot_stop"] is None else [x - origin for x in r["robot_stop"]]}
            for r in window]
